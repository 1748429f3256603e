//! The listener and the connection loop: address reuse, slow-client timeouts, a bound on
//! open connections, and graceful shutdown within `--grace`.
//!
//! axum's own `serve` hides the knobs a public server needs, so connections are served with
//! hyper-util directly: `SO_REUSEADDR` lets a restart right after a crash bind the address
//! still in TIME_WAIT; the header read timeout closes clients that send headers byte by
//! byte (slowloris) and keep-alive connections left idle, and a connection that sends no
//! byte at all is closed after the same time (hyper's timer only starts at a first byte); `max_buf_size` bounds a request's
//! head; a semaphore bounds open connections (past it, new ones wait in the kernel's
//! backlog instead of costing memory). On shutdown the loop stops accepting, every
//! connection is asked to finish its request in flight and close, and after `--grace` the
//! rest are abandoned so `main` can flush the store and exit.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use axum::extract::ConnectInfo;
use axum::Router;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::conn::auto;
use hyper_util::server::graceful::GracefulShutdown;
use hyper_util::service::TowerToHyperService;
use tokio::net::{TcpListener, TcpSocket};
use tokio::sync::Semaphore;
use tower::ServiceExt;

use super::health::{Ready, Shutdown};
use super::metrics::Metrics;

/// Largest request head (request line and headers), bytes; larger ones get 431.
pub const MAX_HEAD_BYTES: usize = 64 * 1024;

/// How the connection loop is tuned (from `ServeArgs`).
#[derive(Debug, Clone)]
pub struct ServerOptions {
    /// Time a client has to send a request head, and to start the next one on an idle
    /// keep-alive connection.
    pub header_timeout: Duration,
    /// Open connections at once.
    pub max_connections: usize,
    /// Time in-flight requests get after shutdown starts.
    pub grace: Duration,
}

/// How the server stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Stopped {
    /// Every connection finished within the grace period.
    pub drained: bool,
    /// Connections still open when the grace period ended.
    pub abandoned: usize,
}

/// Binds `addr` with `SO_REUSEADDR` (and a deep backlog).
pub fn bind(addr: SocketAddr) -> std::io::Result<TcpListener> {
    let socket = if addr.is_ipv4() {
        TcpSocket::new_v4()?
    } else {
        TcpSocket::new_v6()?
    };
    #[cfg(unix)]
    socket.set_reuseaddr(true)?;
    socket.set_nodelay(true)?;
    socket.bind(addr)?;
    socket.listen(1024)
}

/// Serves `app` on `listener` until `shutdown` is triggered, then drains for at most
/// `options.grace`. `ready` is marked draining as soon as the shutdown starts.
pub async fn serve(
    listener: TcpListener,
    app: Router,
    options: ServerOptions,
    ready: Ready,
    shutdown: Shutdown,
    metrics: Metrics,
) -> std::io::Result<Stopped> {
    let mut builder = auto::Builder::new(TokioExecutor::new());
    builder
        .http1()
        .timer(TokioTimer::new())
        .header_read_timeout(options.header_timeout)
        .max_buf_size(MAX_HEAD_BYTES);
    builder
        .http2()
        .timer(TokioTimer::new())
        .max_header_list_size(MAX_HEAD_BYTES as u32)
        .keep_alive_interval(Some(Duration::from_secs(30)))
        .keep_alive_timeout(options.header_timeout);
    let builder = Arc::new(builder);
    let slots = Arc::new(Semaphore::new(options.max_connections.max(1)));
    let graceful = GracefulShutdown::new();
    if let Ok(addr) = listener.local_addr() {
        tracing::info!(%addr, "listening");
    }
    loop {
        let slot = tokio::select! {
            s = slots.clone().acquire_owned() => s,
            () = shutdown.cancelled() => break,
        };
        let Ok(slot) = slot else { break };
        let (stream, peer) = tokio::select! {
            r = listener.accept() => match r {
                Ok(x) => x,
                Err(e) => {
                    // Out of file descriptors and the like: back off instead of spinning.
                    tracing::warn!(error = %e, "accept failed");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
            () = shutdown.cancelled() => break,
        };
        let _ = stream.set_nodelay(true);
        let svc = app
            .clone()
            .map_request(move |mut req: axum::extract::Request<_>| {
                req.extensions_mut().insert(ConnectInfo(peer));
                req
            });
        let metrics = metrics.clone();
        let builder = Arc::clone(&builder);
        let watcher = graceful.watcher();
        let shutdown = shutdown.clone();
        let first_byte = options.header_timeout;
        metrics.add_connections(1);
        tokio::spawn(async move {
            // hyper's header timeout starts at a request's first byte, so a client that
            // connects and sends nothing would hold its slot forever: it gets the same
            // time to send its first byte, then the connection is closed.
            let mut probe = [0u8; 1];
            let arrived = tokio::select! {
                r = tokio::time::timeout(first_byte, stream.peek(&mut probe)) => {
                    matches!(r, Ok(Ok(n)) if n > 0)
                }
                () = shutdown.cancelled() => false,
            };
            if arrived {
                let conn = builder
                    .serve_connection_with_upgrades(
                        TokioIo::new(stream),
                        TowerToHyperService::new(svc),
                    )
                    .into_owned();
                if let Err(e) = watcher.watch(conn).await {
                    tracing::debug!(%peer, error = %e, "connection ended with an error");
                }
            } else {
                tracing::debug!(%peer, "closed a connection that sent nothing");
            }
            metrics.add_connections(-1);
            drop(slot);
        });
    }
    ready.set_draining();
    drop(listener);
    let open = options.max_connections.max(1) - slots.available_permits();
    tracing::info!(
        connections = open,
        grace_s = options.grace.as_secs_f64(),
        "no longer accepting; draining"
    );
    tokio::select! {
        () = graceful.shutdown() => Ok(Stopped { drained: true, abandoned: 0 }),
        () = grace_over(options.grace, &shutdown) => {
            let abandoned = options.max_connections.max(1) - slots.available_permits();
            tracing::warn!(connections = abandoned, "grace period over; abandoning connections");
            Ok(Stopped { drained: false, abandoned })
        }
    }
}

/// Completes when the grace period ends: after `grace`, or at once on a second signal.
async fn grace_over(grace: Duration, shutdown: &Shutdown) {
    tokio::select! {
        () = tokio::time::sleep(grace) => {}
        () = shutdown.hurried() => {}
    }
}
