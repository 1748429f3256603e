//! `rayd serve` (the HTTP service) and `rayd healthcheck` (a probe for container health
//! checks in an image without curl).

use std::io::{ErrorKind, Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde_json::json;

use super::CliError;
use crate::service::{self, AppState, ServeArgs, ServiceError};

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
    let config = state.config.clone();
    // The signals first: one that comes while the store opens starts the shutdown (the
    // server then stops as soon as it has started) instead of killing the process.
    service::health::shutdown_on_signals(state.ready.clone(), state.shutdown.clone())
        .map_err(|source| io("cannot install the SIGTERM handler", source))?;
    #[cfg(unix)]
    service::auth::reload_on_sighup(state.auth.clone(), state.shutdown.clone())
        .map_err(|source| io("cannot install the SIGHUP handler", source))?;
    // The callback options before the store: a bad one stops the start with its message.
    let callbacks = service::callback::CallbackClient::from_options(
        &config.callback_allow,
        config.callback_secret_file.as_deref(),
        config.callback_attempts,
        config.callback_timeout(),
    )
    .map_err(|e| CliError::Service(e.into()))?;
    // The store first: a second server on the same directory stops here.
    let store = crate::store::Store::open(
        &config.data_dir,
        crate::store::StoreOptions {
            result_ttl: (config.result_ttl > 0).then(|| Duration::from_secs(config.result_ttl)),
            max_bytes: config.max_store_bytes,
            keep_versions: (config.keep_versions > 0).then_some(config.keep_versions),
            ..Default::default()
        },
    )
    .await
    .map_err(|e| CliError::Usage(format!("cannot open the store: {e}")))?;
    let engine = Arc::new(crate::jobs::Engine::new(crate::jobs::EngineOptions {
        threads: config.threads,
        cache_bytes: config.cache_bytes as usize,
        texture_bytes: config.texture_bytes as usize,
        max_queued: config.max_queued,
        max_running: config.max_running,
        limits: crate::jobs::Limits {
            max_rays: config.max_rays as usize,
            max_pixels: config.max_pixels,
            max_spp: config.max_spp,
            ..crate::jobs::Limits::default()
        },
        tuning: crate::accel::dacrt::DacrtTuning::from_env(),
    })?);
    let app = crate::app::App::new(
        store.clone(),
        Arc::clone(&engine),
        crate::app::AppOptions {
            observer: Some(Arc::new(state.metrics.clone())),
            callbacks: callbacks.map(|c| Arc::new(c) as Arc<dyn crate::app::CallbackSender>),
            max_triangles: config.max_triangles,
            geometry_bytes: config.geometry_bytes as usize,
        },
    );
    let router = service::router(state.clone(), service::routes::routes())
        .layer(axum::Extension(app.clone()));
    let listener =
        service::bind(addr).map_err(|source| io(&format!("cannot listen on {addr}"), source))?;
    // The signal reaches the engine at once: no job starts from then on, and the ones
    // running get what is left of the grace period once the connections have drained.
    let signalled = {
        let (shutdown, sched) = (state.shutdown.clone(), Arc::clone(engine.scheduler()));
        tokio::spawn(async move {
            shutdown.cancelled().await;
            sched.shut_down();
            std::time::Instant::now()
        })
    };
    // Answering from now on: `/readyz` says 503 (starting), and `/v1` refuses work, until
    // the last run's jobs are queued again and the demo scenes are in.
    let serving = tokio::spawn(service::serve(
        listener,
        router,
        state.server_options(),
        state.ready.clone(),
        state.shutdown.clone(),
        state.metrics.clone(),
    ));
    // Jobs that were queued or running when the last process ended run again.
    let recovered = app
        .recover()
        .await
        .map_err(|e| CliError::Usage(format!("cannot recover the queued jobs: {e}")))?;
    if recovered > 0 {
        tracing::info!(jobs = recovered, "re-queued jobs from the last run");
    }
    if config.demo {
        demo(&app).await;
    }
    state.metrics.sample_with(sampler(Arc::clone(&engine)));
    spawn_housekeeping(state.clone(), app.clone());
    state.ready.set_ready();
    tracing::info!(%addr, data_dir = %config.data_dir.display(), "rayd serve is ready");
    let stopped = serving
        .await
        .map_err(|e| io("serving failed", std::io::Error::other(e)))?
        .map_err(|source| io("serving failed", source))?;
    // No new work (the task refused it when the signal came). Running jobs finish within
    // the grace period, counted from the signal; one still running then stays `running`
    // in the store, and the next start runs it again from the beginning. `serve` returns
    // once the shutdown has started; triggering it again is a no-op that makes sure.
    state.shutdown.trigger();
    let since = signalled
        .await
        .unwrap_or_else(|_| std::time::Instant::now());
    let deadline = since + config.grace();
    while engine.scheduler().running() > 0
        && std::time::Instant::now() < deadline
        && !state.shutdown.is_hurried()
    {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let unfinished = engine.scheduler().running();
    if unfinished > 0 {
        tracing::warn!(
            jobs = unfinished,
            "grace period over; running jobs will run again at the next start"
        );
    }
    store.close().await;
    Ok(json!({
        "addr": addr.to_string(),
        "drained": stopped.drained,
        "abandoned_connections": stopped.abandoned,
        "unfinished_jobs": unfinished,
        "recovered_jobs": recovered,
    }))
}

/// `--demo`: uploads the repository's sample scenes (built into the binary).
async fn demo(app: &crate::app::App) {
    const SCENES: [(&str, &[u8]); 3] = [
        ("Fox.glb", include_bytes!("../../scenes/Fox.glb")),
        ("Box.glb", include_bytes!("../../scenes/Box.glb")),
        (
            "SimpleMeshes.glb",
            include_bytes!("../../scenes/SimpleMeshes.glb"),
        ),
    ];
    for (name, bytes) in SCENES {
        match app
            .upload(
                crate::app::UploadKind::Glb,
                bytes::Bytes::from_static(bytes),
                Some(name.into()),
            )
            .await
        {
            Ok((s, _)) => tracing::info!(scene = %s.id, name, "demo scene"),
            Err(e) => tracing::error!(name, "demo scene refused: {e}"),
        }
    }
}

/// Once a minute: expiry, old versions and blob collection.
fn spawn_housekeeping(state: AppState, app: crate::app::App) {
    tokio::spawn(async move {
        let minute = Duration::from_secs(60);
        let mut tick = tokio::time::interval_at(tokio::time::Instant::now() + minute, minute);
        loop {
            tokio::select! {
                _ = tick.tick() => {}
                _ = app.store().pruned_waiting() => {
                    // Versions just deleted by newer ones: their blobs go within a second,
                    // not after the collection's grace; a second's worth at a time, and
                    // only when no upload holds the gate.
                    tokio::select! {
                        _ = tokio::time::sleep(Duration::from_secs(1)) => {}
                        _ = state.shutdown.cancelled() => break,
                    }
                    if let Err(e) = app.store().collect_pruned(false).await {
                        tracing::warn!("deleting old versions' blobs failed: {e}");
                    }
                    continue;
                }
                _ = state.shutdown.cancelled() => break,
            }
            let store = app.store();
            if let Err(e) = store.expire(crate::store::now_millis()).await {
                tracing::warn!("expiring finished jobs failed: {e}");
            }
            match app.prune_versions().await {
                Ok(0) => {}
                Ok(n) => tracing::info!(versions = n, "old geometry versions deleted"),
                Err(e) => tracing::warn!("deleting old geometry versions failed: {e}"),
            }
            if let Err(e) = store.collect_pruned(true).await {
                tracing::warn!("deleting old versions' blobs failed: {e}");
            }
            if let Err(e) = store.gc().await {
                tracing::warn!("blob collection failed: {e}");
            }
        }
    });
}

/// What `/metrics` reads of the engine at each scrape: the queue, running jobs, both
/// caches and the upload rate `auto` expects. It holds the engine, which holds no
/// metrics, so nothing is kept alive in a cycle.
fn sampler(engine: Arc<crate::jobs::Engine>) -> service::metrics::Sampler {
    Box::new(move |m| {
        let sched = engine.scheduler();
        m.set_queue_length(sched.queued());
        m.set_jobs_running(sched.running());
        m.set_structure_cache(&engine.cache().stats());
        m.set_texture_cache(&engine.textures().stats());
        m.set_light_cache(&engine.lights().stats());
        m.set_upload_rate(engine.upload_rate());
    })
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

/// The longest `--timeout` a probe takes, seconds.
const MAX_PROBE_SECONDS: f64 = 86_400.0;

/// The status code of an HTTP/1.x status line (RFC 9112 §4: `HTTP/1.d SP 3DIGIT SP
/// reason`, the reason possibly empty), or `None` when the line is not one: `HTTP/1.1 2000`
/// or `HTTP/1.1X200` is no 200.
fn status_code(line: &str) -> Option<u16> {
    let b = line.strip_prefix("HTTP/1.")?.as_bytes();
    let well_formed = b.len() >= 5
        && b[0].is_ascii_digit()
        && b[1] == b' '
        && b[2..5].iter().all(u8::is_ascii_digit)
        && (b.len() == 5 || b[5] == b' ');
    well_formed.then(|| b[2..5].iter().fold(0u16, |n, d| 10 * n + (d - b'0') as u16))
}

/// GETs the URL; succeeds (exit 0) only on a 200.
pub(super) fn healthcheck(a: HealthcheckArgs) -> Result<serde_json::Value, CliError> {
    let usage = CliError::Usage;
    // A millisecond at least (the socket timeouts' resolution: less is 0, which the OS
    // refuses) and a day at most (a probe that waits longer is not a health check).
    if !(a.timeout.is_finite() && a.timeout >= 0.001 && a.timeout <= MAX_PROBE_SECONDS) {
        return Err(usage(format!(
            "--timeout {} is not a number of seconds in [0.001, {MAX_PROBE_SECONDS}]",
            a.timeout
        )));
    }
    let timeout = Duration::from_secs_f64(a.timeout);
    // Written into the request line as it is: nothing that could end the line or the
    // head, or split the target.
    if let Some(c) = a.url.chars().find(|c| !c.is_ascii_graphic()) {
        return Err(usage(format!(
            "--url {:?}: {c:?} cannot be sent (percent-encode it)",
            a.url
        )));
    }
    let rest = a
        .url
        .strip_prefix("http://")
        .ok_or_else(|| usage(format!("--url {}: only http:// URLs can be probed", a.url)))?;
    // A fragment is the client's own, never sent.
    let rest = rest.split_once('#').map_or(rest, |(r, _)| r);
    // The authority ends at the path, or at a query with no path (`http://h:8080?x`).
    let (authority, path) = match rest.find(['/', '?']) {
        Some(i) if rest[i..].starts_with('?') => (&rest[..i], format!("/{}", &rest[i..])),
        Some(i) => (&rest[..i], rest[i..].to_owned()),
        None => (rest, "/".to_owned()),
    };
    if authority.contains('@') {
        return Err(usage(format!(
            "--url {}: credentials in the URL are not supported",
            a.url
        )));
    }
    if authority.is_empty() {
        return Err(usage(format!(
            "--url {}: no host[:port] after http://",
            a.url
        )));
    }
    // `host:port` or `[v6]:port`; a colon inside brackets is the address's own.
    let port = match authority.rsplit_once(':') {
        Some((_, p)) if !p.ends_with(']') => Some(p),
        _ => None,
    };
    let target = match port {
        Some(p) if p.parse::<u16>().is_ok_and(|n| n > 0) => authority.to_owned(),
        Some(p) => {
            return Err(usage(format!(
                "--url {}: port {p:?} is not a port number (1 to 65535)",
                a.url
            )))
        }
        None => format!("{authority}:80"),
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
    // The whole answer within the timeout: the head to its blank line, then the body its
    // Content-Length announces (a health answer is small: a head past 64 KiB, or a body
    // past 1 MiB, is no health answer). A server that stalls after its status line, or
    // closes half-way, fails the probe.
    let mut answer = Vec::new();
    let mut buf = [0u8; 4096];
    let mut read_more = |answer: &mut Vec<u8>| -> Result<bool, CliError> {
        stream
            .set_read_timeout(Some(left(start)))
            .map_err(|e| fail(e.to_string()))?;
        match stream.read(&mut buf) {
            Ok(0) => Ok(false),
            Ok(n) => {
                answer.extend_from_slice(&buf[..n]);
                Ok(true)
            }
            // A read past the deadline fails as WouldBlock (Unix) or TimedOut (Windows).
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {
                Err(fail(format!(
                    "{} within {} s",
                    if answer.is_empty() {
                        "no answer"
                    } else {
                        "the answer did not end"
                    },
                    timeout.as_secs_f64()
                )))
            }
            Err(e) if answer.is_empty() => Err(fail(format!("no answer: {e}"))),
            Err(e) => Err(fail(format!("the answer stopped: {e}"))),
        }
    };
    let head_end = loop {
        if let Some(i) = answer.windows(4).position(|w| w == b"\r\n\r\n") {
            break i + 4;
        }
        if answer.len() > MAX_PROBE_HEAD {
            return Err(fail("the answer's head is too long".into()));
        }
        if !read_more(&mut answer)? {
            let text = String::from_utf8_lossy(&answer);
            let line = text.lines().next().unwrap_or("");
            return Err(fail(if status_code(line).is_some() {
                "the connection closed inside the answer's head".into()
            } else {
                format!("not an HTTP answer: {line:?}")
            }));
        }
    };
    let head = String::from_utf8_lossy(&answer[..head_end]).into_owned();
    let line = head.lines().next().unwrap_or("");
    let status = status_code(line).ok_or_else(|| fail(format!("not an HTTP answer: {line:?}")))?;
    let length = head.lines().skip(1).find_map(|l| {
        let (name, value) = l.split_once(':')?;
        name.trim()
            .eq_ignore_ascii_case("content-length")
            .then(|| value.trim().parse::<u64>().ok())?
    });
    if let Some(n) = length {
        if n > MAX_PROBE_BODY {
            return Err(fail(format!("a body of {n} bytes is no health answer")));
        }
        while ((answer.len() - head_end) as u64) < n {
            if !read_more(&mut answer)? {
                return Err(fail(format!(
                    "the body ends after {} of its {n} bytes",
                    answer.len() - head_end
                )));
            }
        }
    }
    if status != 200 {
        return Err(fail(format!("answered {status}, not 200")));
    }
    Ok(json!({ "url": a.url, "status": status }))
}

/// The longest answer head a probe reads.
const MAX_PROBE_HEAD: usize = 64 * 1024;
/// The longest answer body a probe reads.
const MAX_PROBE_BODY: u64 = 1 << 20;

#[cfg(test)]
mod tests {
    use super::status_code;

    #[test]
    fn only_a_well_formed_status_line_has_a_code() {
        assert_eq!(status_code("HTTP/1.1 200 OK"), Some(200));
        assert_eq!(status_code("HTTP/1.0 503 Service Unavailable"), Some(503));
        assert_eq!(status_code("HTTP/1.1 200"), Some(200));
        assert_eq!(status_code("HTTP/1.1 200 "), Some(200));
        for bad in [
            "HTTP/1.1 2000 Weird",
            "HTTP/1.1X200 OK",
            "HTTP/1.1 20 OK",
            "HTTP/1.1 2x0 OK",
            "HTTP/1. 200 OK",
            "HTTP/2 200 OK",
            "",
        ] {
            assert_eq!(status_code(bad), None, "{bad:?}");
        }
    }
}
