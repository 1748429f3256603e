//! Callback deliveries: for each render job that asked for a callback, where its delivery
//! stands (`pending`, `delivered`, `failed`), how many attempts it took and the last error.
//!
//! The row is written when the job is submitted, before the client hears `202`, so a
//! delivery that a crash interrupted (or never began) is still `pending` at the next start
//! and is resumed from its attempt count. It is deleted with its job (`ON DELETE CASCADE`).

use serde::Serialize;
use sqlx::sqlite::SqliteRow;
use sqlx::Row;

use super::error::{Result, StoreError};
use super::records::{check_job_id, now_millis, Millis};
use super::Store;

/// Where a callback's delivery stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum CallbackState {
    /// Not delivered yet: the job has not ended, or attempts remain.
    Pending,
    /// A POST was answered 2xx.
    Delivered,
    /// Every allowed attempt failed, or the receiver answered in a way that retrying
    /// cannot change (a redirect, a 4xx other than 408 and 429).
    Failed,
}

impl CallbackState {
    /// The stored spelling (the same as the serde one).
    pub fn as_str(self) -> &'static str {
        match self {
            CallbackState::Pending => "pending",
            CallbackState::Delivered => "delivered",
            CallbackState::Failed => "failed",
        }
    }

    fn parse(s: &str) -> Result<CallbackState> {
        Ok(match s {
            "pending" => CallbackState::Pending,
            "delivered" => CallbackState::Delivered,
            "failed" => CallbackState::Failed,
            _ => {
                return Err(StoreError::Db(sqlx::Error::Decode(
                    format!("job_callbacks.state holds {s:?}, which this rayd does not know")
                        .into(),
                )))
            }
        })
    }
}

/// One job's callback delivery.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CallbackRecord {
    /// The job.
    pub job_id: String,
    /// Where the finished job is POSTed.
    pub url: String,
    /// Where the delivery stands.
    pub state: CallbackState,
    /// POSTs tried so far.
    pub attempts: u32,
    /// Why the last attempt failed; `None` after a delivery or before the first attempt.
    pub error: Option<String>,
    /// When the row last changed.
    pub updated_at: Millis,
}

fn from_row(row: &SqliteRow) -> Result<CallbackRecord> {
    let attempts: i64 = row.try_get("attempts")?;
    Ok(CallbackRecord {
        job_id: row.try_get("job_id")?,
        url: row.try_get("url")?,
        state: CallbackState::parse(row.try_get::<&str, _>("state")?)?,
        attempts: u32::try_from(attempts).unwrap_or(u32::MAX),
        error: row.try_get("error")?,
        updated_at: row.try_get("updated_at")?,
    })
}

impl Store {
    /// Writes a job's callback row (inserting or replacing it). The job must exist.
    pub async fn put_callback(
        &self,
        job_id: &str,
        url: &str,
        state: CallbackState,
        attempts: u32,
        error: Option<&str>,
    ) -> Result<CallbackRecord> {
        check_job_id(job_id)?;
        let row = sqlx::query(
            "INSERT INTO job_callbacks (job_id, url, state, attempts, error, updated_at) \
             SELECT ?, ?, ?, ?, ?, ? WHERE EXISTS (SELECT 1 FROM jobs WHERE id = ?) \
             ON CONFLICT (job_id) DO UPDATE SET url = excluded.url, state = excluded.state, \
             attempts = excluded.attempts, error = excluded.error, \
             updated_at = excluded.updated_at \
             RETURNING job_id, url, state, attempts, error, updated_at",
        )
        .bind(job_id)
        .bind(url)
        .bind(state.as_str())
        .bind(i64::from(attempts))
        .bind(error)
        .bind(now_millis())
        .bind(job_id)
        .fetch_optional(&self.inner.writer)
        .await?;
        match row {
            Some(row) => from_row(&row),
            None => Err(StoreError::not_found("job", job_id)),
        }
    }

    /// A job's callback row, if it asked for one.
    pub async fn get_callback(&self, job_id: &str) -> Result<Option<CallbackRecord>> {
        check_job_id(job_id)?;
        sqlx::query(
            "SELECT job_id, url, state, attempts, error, updated_at FROM job_callbacks \
             WHERE job_id = ?",
        )
        .bind(job_id)
        .fetch_optional(&self.inner.reader)
        .await?
        .as_ref()
        .map(from_row)
        .transpose()
    }

    /// The callbacks still owed for jobs that have ended, oldest first: what a start
    /// resumes. (A pending callback of a queued or running job is delivered when the
    /// re-queued job ends.)
    pub async fn pending_callbacks(&self) -> Result<Vec<CallbackRecord>> {
        sqlx::query(
            "SELECT c.job_id, c.url, c.state, c.attempts, c.error, c.updated_at \
             FROM job_callbacks c JOIN jobs j ON j.id = c.job_id \
             WHERE c.state = 'pending' AND j.state IN ('succeeded', 'failed', 'cancelled') \
             ORDER BY c.updated_at, c.job_id",
        )
        .fetch_all(&self.inner.reader)
        .await?
        .iter()
        .map(from_row)
        .collect()
    }
}
