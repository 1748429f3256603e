//! Liveness, readiness and the shutdown signal.
//!
//! `/healthz` answers 200 whenever the process answers at all: a failing liveness probe
//! means "restart me". `/readyz` answers 200 only while [`Ready`] says the store is loaded
//! and work is accepted, and 503 with `Retry-After` while starting or draining, so a load
//! balancer stops sending work before the server stops taking it. [`Shutdown`] is the one
//! token every long-lived task (the job engine, event streams, the accept loop) watches.

use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::Arc;

use axum::extract::State;
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde_json::json;
use tokio_util::sync::CancellationToken;

use super::error::ApiError;

/// Where the service is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Loading; not accepting work yet.
    Starting,
    /// Accepting work.
    Ready,
    /// Shutting down; finishing what it has.
    Draining,
}

/// The readiness flag behind `/readyz`.
#[derive(Debug, Clone)]
pub struct Ready(Arc<AtomicU8>);

impl Default for Ready {
    fn default() -> Self {
        Ready(Arc::new(AtomicU8::new(Phase::Starting as u8)))
    }
}

impl Ready {
    /// The phase now.
    pub fn phase(&self) -> Phase {
        match self.0.load(Ordering::Acquire) {
            0 => Phase::Starting,
            1 => Phase::Ready,
            _ => Phase::Draining,
        }
    }

    /// Marks the service ready (store loaded, accepting work). Ignored once draining: a
    /// server that is shutting down never becomes ready again.
    pub fn set_ready(&self) {
        let _ = self.0.compare_exchange(
            Phase::Starting as u8,
            Phase::Ready as u8,
            Ordering::AcqRel,
            Ordering::Acquire,
        );
    }

    /// Marks the service as shutting down.
    pub fn set_draining(&self) {
        self.0.store(Phase::Draining as u8, Ordering::Release);
    }

    /// Whether work is accepted now.
    pub fn is_ready(&self) -> bool {
        self.phase() == Phase::Ready
    }
}

/// The shutdown signal: triggered once on SIGTERM/SIGINT (or by a test); everything
/// long-lived selects on [`Shutdown::cancelled`]. A second signal during the grace period
/// ends it at once ([`Shutdown::hurry`]), as an operator who presses Ctrl-C twice means.
#[derive(Debug, Clone, Default)]
pub struct Shutdown {
    started: CancellationToken,
    hurried: CancellationToken,
}

impl Shutdown {
    /// Starts the shutdown (idempotent).
    pub fn trigger(&self) {
        self.started.cancel();
    }

    /// Ends the grace period now: open connections are abandoned and running jobs left to
    /// run again at the next start, as when `--grace` runs out. Starts the shutdown too.
    pub fn hurry(&self) {
        self.started.cancel();
        self.hurried.cancel();
    }

    /// Whether the shutdown has started.
    pub fn is_triggered(&self) -> bool {
        self.started.is_cancelled()
    }

    /// Whether the grace period was cut short.
    pub fn is_hurried(&self) -> bool {
        self.hurried.is_cancelled()
    }

    /// Completes when the shutdown starts.
    pub async fn cancelled(&self) {
        self.started.cancelled().await;
    }

    /// Completes when the grace period is cut short.
    pub async fn hurried(&self) {
        self.hurried.cancelled().await;
    }

    /// The underlying token, for code that composes tokens (child tokens per job).
    pub fn token(&self) -> &CancellationToken {
        &self.started
    }
}

/// `GET /healthz`.
pub async fn healthz() -> Json<serde_json::Value> {
    Json(json!({ "status": "ok" }))
}

/// `GET /readyz`.
pub async fn readyz(State(ready): State<Ready>) -> Response {
    match ready.phase() {
        Phase::Ready => Json(json!({ "status": "ready" })).into_response(),
        Phase::Starting => ApiError::unavailable("the service is starting", 1).into_response(),
        Phase::Draining => ApiError::unavailable("the service is shutting down", 5).into_response(),
    }
}

/// Middleware of the `/v1` routes: 503 with `Retry-After` while the service is starting.
/// The server answers from the moment it listens, so that `/healthz` and `/readyz` can
/// say where it is while it re-queues the last run's jobs and loads its demo scenes; work
/// taken before the re-queueing ended could be queued twice.
pub async fn refuse_while_starting(
    State(ready): State<Ready>,
    req: axum::extract::Request,
    next: axum::middleware::Next,
) -> Response {
    if ready.phase() == Phase::Starting {
        return ApiError::unavailable("the service is starting", 1)
            .refused("starting")
            .into_response();
    }
    next.run(req).await
}

/// Waits for SIGTERM or SIGINT, then marks the service draining and triggers `shutdown`;
/// a second one ends the grace period at once ([`Shutdown::hurry`]). Returns at once
/// (spawning the waiter) so the caller can go on to serve.
pub fn shutdown_on_signals(ready: Ready, shutdown: Shutdown) -> std::io::Result<()> {
    let mut signals = Signals::new()?;
    tokio::spawn(async move {
        tokio::select! {
            (name, _) = signals.next() => tracing::info!(signal = name, "shutting down"),
            () = shutdown.cancelled() => {}
        }
        ready.set_draining();
        shutdown.trigger();
        tokio::select! {
            (name, _) = signals.next() => {
                tracing::warn!(signal = name, "second signal: ending the grace period now");
                shutdown.hurry();
            }
            () = shutdown.hurried() => {}
        }
    });
    Ok(())
}

/// The signals that stop the service, and a command line that cleans up after itself:
/// SIGTERM and SIGINT (Ctrl-C elsewhere).
pub(crate) struct Signals {
    #[cfg(unix)]
    term: tokio::signal::unix::Signal,
    #[cfg(unix)]
    int: tokio::signal::unix::Signal,
}

impl Signals {
    /// Installs the handlers (inside a tokio runtime): from now on these signals no longer
    /// end the process.
    pub(crate) fn new() -> std::io::Result<Signals> {
        #[cfg(unix)]
        {
            use tokio::signal::unix::{signal, SignalKind};
            Ok(Signals {
                term: signal(SignalKind::terminate())?,
                int: signal(SignalKind::interrupt())?,
            })
        }
        #[cfg(not(unix))]
        Ok(Signals {})
    }

    /// The next one to arrive: its name and number.
    pub(crate) async fn next(&mut self) -> (&'static str, u8) {
        #[cfg(unix)]
        {
            tokio::select! {
                _ = self.term.recv() => ("SIGTERM", 15),
                _ = self.int.recv() => ("SIGINT", 2),
            }
        }
        #[cfg(not(unix))]
        {
            let _ = tokio::signal::ctrl_c().await;
            ("SIGINT", 2)
        }
    }
}
