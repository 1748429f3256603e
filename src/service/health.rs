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
/// long-lived selects on [`Shutdown::cancelled`].
#[derive(Debug, Clone, Default)]
pub struct Shutdown(CancellationToken);

impl Shutdown {
    /// Starts the shutdown (idempotent).
    pub fn trigger(&self) {
        self.0.cancel();
    }

    /// Whether the shutdown has started.
    pub fn is_triggered(&self) -> bool {
        self.0.is_cancelled()
    }

    /// Completes when the shutdown starts.
    pub async fn cancelled(&self) {
        self.0.cancelled().await;
    }

    /// The underlying token, for code that composes tokens (child tokens per job).
    pub fn token(&self) -> &CancellationToken {
        &self.0
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

/// Waits for SIGTERM or SIGINT, then marks the service draining and triggers `shutdown`.
/// Returns at once (spawning the waiter) so the caller can go on to serve.
pub fn shutdown_on_signals(ready: Ready, shutdown: Shutdown) -> std::io::Result<()> {
    #[cfg(unix)]
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
    tokio::spawn(async move {
        #[cfg(unix)]
        let terminate = async {
            term.recv().await;
        };
        #[cfg(not(unix))]
        let terminate = std::future::pending::<()>();
        tokio::select! {
            _ = tokio::signal::ctrl_c() => tracing::info!("SIGINT: shutting down"),
            () = terminate => tracing::info!("SIGTERM: shutting down"),
            () = shutdown.cancelled() => {}
        }
        ready.set_draining();
        shutdown.trigger();
    });
    Ok(())
}
