//! Callbacks: when a render job that names a `callback` URL ends (succeeded, failed or
//! cancelled), the finished job's JSON, the object `GET /v1/jobs/{job}` answers, is POSTed
//! to it (`proto/service.md`, "Callbacks").
//!
//! This layer decides *when* and *how often*; how a POST is made, signed and which hosts
//! may be contacted belongs to a [`CallbackSender`] the service hands in, so the domain layer
//! knows no HTTP. Delivery is I/O and runs as a task on the async runtime, never on the
//! engine's pool. Each attempt and its outcome is written to the store, and the row exists
//! from submission on, so a delivery that a crash or a stop interrupted is resumed at the
//! next start from the attempts it has left: delivery is at least once, and a receiver that
//! must act once deduplicates on the job id.

use std::future::Future;
use std::pin::Pin;
use std::time::Duration;

use serde::Serialize;

use super::{App, AppError};
use crate::store::{CallbackRecord, CallbackState};

/// Why one POST did not deliver.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CallbackFailure {
    /// Whether another attempt could succeed (a refused connection, a timeout, a 5xx, 408
    /// or 429), or not (a redirect, another 4xx).
    pub retry: bool,
    /// What happened, for the job's `callback.error`.
    pub detail: String,
}

/// One attempt's future.
pub type SendFuture = Pin<Box<dyn Future<Output = Result<(), CallbackFailure>> + Send>>;

/// Makes the POSTs: the service's HTTP client with its allow-list and signing key.
pub trait CallbackSender: Send + Sync {
    /// Whether `url` may be called back; `Err` says why not (the submission's 422).
    fn check(&self, url: &str) -> Result<(), String>;
    /// Attempts a delivery gets in all, the first included (at least 1).
    fn attempts(&self) -> u32;
    /// The wait before attempt `n + 1` after `n` failed ones.
    fn backoff(&self, failed: u32) -> Duration {
        // 0.5 s, 1 s, 2 s, … up to a minute.
        Duration::from_millis(500u64.saturating_mul(1 << failed.saturating_sub(1).min(7)))
            .min(Duration::from_secs(60))
    }
    /// One POST of `body` for job `job` to `url` (already checked), within its own
    /// time limit.
    fn send(&self, url: &str, job: &str, body: Vec<u8>) -> SendFuture;
}

/// A job's callback as the API shows it (the job's `callback` field).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CallbackView {
    /// The URL.
    pub url: String,
    /// `pending`, `delivered` or `failed`.
    pub state: CallbackState,
    /// POSTs tried so far.
    pub attempts: u32,
    /// Why the last attempt failed.
    pub error: Option<String>,
}

impl CallbackView {
    /// A callback that nothing has been tried for yet.
    pub(super) fn pending(url: &str) -> CallbackView {
        CallbackView {
            url: url.to_string(),
            state: CallbackState::Pending,
            attempts: 0,
            error: None,
        }
    }

    pub(super) fn of(r: &CallbackRecord) -> CallbackView {
        CallbackView {
            url: r.url.clone(),
            state: r.state,
            attempts: r.attempts,
            error: r.error.clone(),
        }
    }
}

impl App {
    /// Checks a submission's callback URL: refused (422, field `callback`) when this server
    /// sends no callbacks or the URL's host is not allowed.
    pub(super) fn check_callback(&self, url: &str) -> Result<(), AppError> {
        let refuse = |detail: String| AppError::Unprocessable {
            field: "callback",
            detail,
        };
        match &self.inner.callbacks {
            None => Err(refuse(
                "callbacks are not enabled on this server (no --callback-allow)".into(),
            )),
            Some(sender) => sender.check(url).map_err(refuse),
        }
    }

    /// Starts delivering job `id`'s callback, if it has one and it is still owed: a task on
    /// the runtime, so the caller (a job's thread or a handler) does not wait for it.
    pub(super) fn notify(&self, id: &str) {
        if self.inner.callbacks.is_none() {
            return;
        }
        let (app, id) = (self.clone(), id.to_string());
        self.inner.runtime.spawn(async move {
            if let Err(e) = app.deliver(&id).await {
                tracing::warn!(job = %id, "callback delivery stopped: {e}");
            }
        });
    }

    /// Resumes the deliveries still owed for ended jobs (after a restart). Returns how many.
    pub(super) async fn resume_callbacks(&self) -> Result<usize, AppError> {
        if self.inner.callbacks.is_none() {
            return Ok(0);
        }
        let owed = self.store().pending_callbacks().await?;
        for c in &owed {
            self.notify(&c.job_id);
        }
        Ok(owed.len())
    }

    /// Delivers job `id`'s callback: POSTs the job as `GET /v1/jobs/{id}` shows it until
    /// an attempt succeeds, one fails for good, or the attempts are spent, recording each.
    async fn deliver(&self, id: &str) -> Result<(), AppError> {
        let Some(sender) = self.inner.callbacks.clone() else {
            return Ok(());
        };
        let Some(mut rec) = self.store().get_callback(id).await? else {
            return Ok(());
        };
        // Two deliveries of one job never run at once: the second finds the first's claim.
        if rec.state != CallbackState::Pending || !self.claim_delivery(id) {
            return Ok(());
        }
        let _claim = DeliveryClaim {
            app: self.clone(),
            id: id.to_string(),
        };
        let body = serde_json::to_vec(&self.job(id).await?).expect("a job view serialises");
        let limit = sender.attempts().max(1);
        while rec.attempts < limit {
            if rec.attempts > 0 {
                tokio::time::sleep(sender.backoff(rec.attempts)).await;
            }
            let outcome = sender.send(&rec.url, id, body.clone()).await;
            let attempts = rec.attempts + 1;
            let (state, error) = match &outcome {
                Ok(()) => (CallbackState::Delivered, None),
                Err(f) if !f.retry || attempts >= limit => {
                    (CallbackState::Failed, Some(f.detail.as_str()))
                }
                Err(f) => (CallbackState::Pending, Some(f.detail.as_str())),
            };
            match &outcome {
                Ok(()) => tracing::info!(job = %id, attempts, "callback delivered"),
                Err(f) => {
                    tracing::warn!(job = %id, attempts, "callback attempt failed: {}", f.detail)
                }
            }
            rec = self
                .store()
                .put_callback(id, &rec.url, state, attempts, error)
                .await?;
            if state != CallbackState::Pending {
                return Ok(());
            }
        }
        // Attempts spent in an earlier run (a stop after the last attempt's record).
        self.store()
            .put_callback(
                id,
                &rec.url,
                CallbackState::Failed,
                rec.attempts,
                rec.error.as_deref(),
            )
            .await?;
        Ok(())
    }

    fn claim_delivery(&self, id: &str) -> bool {
        self.inner
            .delivering
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(id.to_string())
    }
}

/// Releases a delivery's claim when the delivery ends, however it ends.
struct DeliveryClaim {
    app: App,
    id: String,
}

impl Drop for DeliveryClaim {
    fn drop(&mut self) {
        self.app
            .inner
            .delivering
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(&self.id);
    }
}
