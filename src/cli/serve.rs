//! `rayd serve` (the HTTP service) and `rayd healthcheck` (a probe for container health
//! checks in an image without curl).

use std::io::{Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};

use serde_json::json;

use super::CliError;
use crate::service::{self, AppState, Routes, ServeArgs, ServiceError};

/// Runs the service until SIGTERM or SIGINT and the grace period.
pub(super) fn run(args: ServeArgs) -> Result<serde_json::Value, CliError> {
    service::init_logging(args.log_format);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("rayd-http")
        .build()
        .map_err(|source| io("cannot start the async runtime", source))?;
    runtime.block_on(serve(args))
}

async fn serve(args: ServeArgs) -> Result<serde_json::Value, CliError> {
    let addr = args.addr;
    let state = AppState::new(args)?;
    // The domain routes (scenes, trace, render, jobs) are added to this table.
    let app = service::router(state.clone(), Routes::new());
    let listener =
        service::bind(addr).map_err(|source| io(&format!("cannot listen on {addr}"), source))?;
    service::health::shutdown_on_signals(state.ready.clone(), state.shutdown.clone())
        .map_err(|source| io("cannot install the SIGTERM handler", source))?;
    #[cfg(unix)]
    service::auth::reload_on_sighup(state.auth.clone(), state.shutdown.clone())
        .map_err(|source| io("cannot install the SIGHUP handler", source))?;
    // Nothing to load yet: the store, once opened above, decides when this is true.
    state.ready.set_ready();
    let stopped = service::serve(
        listener,
        app,
        state.server_options(),
        state.ready.clone(),
        state.shutdown.clone(),
        state.metrics.clone(),
    )
    .await
    .map_err(|source| io("serving failed", source))?;
    Ok(json!({
        "addr": addr.to_string(),
        "drained": stopped.drained,
        "abandoned_connections": stopped.abandoned,
    }))
}

fn io(what: &str, source: std::io::Error) -> CliError {
    CliError::Service(ServiceError::Io {
        what: what.to_owned(),
        source,
    })
}

/// Options of `rayd healthcheck`.
#[derive(clap::Args, Debug)]
pub(super) struct HealthcheckArgs {
    /// URL to probe (plain http only).
    #[arg(
        long,
        env = "RAYD_HEALTHCHECK_URL",
        default_value = "http://127.0.0.1:8080/healthz"
    )]
    url: String,
    /// Seconds to wait for the whole answer.
    #[arg(long, default_value_t = 3.0)]
    timeout: f64,
}

/// GETs the URL; succeeds (exit 0) only on a 200.
pub(super) fn healthcheck(a: HealthcheckArgs) -> Result<serde_json::Value, CliError> {
    let usage = CliError::Usage;
    if !(a.timeout.is_finite() && a.timeout > 0.0) {
        return Err(usage(format!(
            "--timeout {} is not a positive number of seconds",
            a.timeout
        )));
    }
    let timeout = Duration::from_secs_f64(a.timeout);
    let rest = a
        .url
        .strip_prefix("http://")
        .ok_or_else(|| usage(format!("--url {}: only http:// URLs can be probed", a.url)))?;
    let (authority, path) = match rest.find('/') {
        Some(i) => (&rest[..i], &rest[i..]),
        None => (rest, "/"),
    };
    if authority.is_empty() || authority.contains('@') {
        return Err(usage(format!(
            "--url {}: no host[:port] after http://",
            a.url
        )));
    }
    let target = if authority
        .rsplit_once(':')
        .is_some_and(|(_, p)| p.parse::<u16>().is_ok())
        && !authority.ends_with(']')
    {
        authority.to_owned()
    } else {
        format!("{authority}:80")
    };
    let fail = |what: String| CliError::Usage(format!("healthcheck {}: {what}", a.url));
    let start = Instant::now();
    let addrs: Vec<_> = target
        .to_socket_addrs()
        .map_err(|e| fail(format!("cannot resolve {target}: {e}")))?
        .collect();
    let mut stream = None;
    let mut last = None;
    for addr in addrs {
        match TcpStream::connect_timeout(&addr, timeout) {
            Ok(s) => {
                stream = Some(s);
                break;
            }
            Err(e) => last = Some(e),
        }
    }
    let mut stream = stream.ok_or_else(|| {
        fail(match last {
            Some(e) => format!("cannot connect: {e}"),
            None => format!("{target} resolves to no address"),
        })
    })?;
    let left = |start: Instant| {
        timeout
            .saturating_sub(start.elapsed())
            .max(Duration::from_millis(1))
    };
    stream
        .set_write_timeout(Some(left(start)))
        .and_then(|()| {
            write!(
                stream,
                "GET {path} HTTP/1.1\r\nHost: {authority}\r\nUser-Agent: rayd-healthcheck\r\nConnection: close\r\n\r\n"
            )
        })
        .map_err(|e| fail(format!("cannot send the request: {e}")))?;
    // Only the status line matters; read until it is complete.
    let mut head = Vec::new();
    let mut buf = [0u8; 512];
    while !head.contains(&b'\n') && head.len() < 4096 {
        stream
            .set_read_timeout(Some(left(start)))
            .map_err(|e| fail(e.to_string()))?;
        match stream.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => head.extend_from_slice(&buf[..n]),
            Err(e) => return Err(fail(format!("no answer: {e}"))),
        }
    }
    let line = String::from_utf8_lossy(&head);
    let line = line.lines().next().unwrap_or("");
    let status = line
        .strip_prefix("HTTP/1.")
        .and_then(|r| r.get(2..5))
        .and_then(|c| c.parse::<u16>().ok())
        .ok_or_else(|| fail(format!("not an HTTP answer: {line:?}")))?;
    if status != 200 {
        return Err(fail(format!("answered {status}, not 200")));
    }
    Ok(json!({ "url": a.url, "status": status }))
}
