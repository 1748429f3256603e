//! Jobs: submission (with idempotency keys), state changes, results and listings.
//!
//! Every state change is one transaction whose `UPDATE … WHERE state = …` checks the state
//! it leaves, so two workers cannot both start a job and a cancelled job cannot succeed.
//! A result's blobs are stored before `finish_job` commits the record naming them.

use sqlx::sqlite::SqliteRow;
use sqlx::{Row, SqliteConnection};

use super::blob::BlobId;
use super::error::{Result, StoreError};
use super::records::{
    check_job_id, check_json, decode_page_token, encode_page_token, job_from_row, new_job_id,
    now_millis, page_size, JobOutcome, JobRecord, JobState, ListKind, Millis, NewJob, ResultBlob,
};
use super::scenes::check_label;
use super::scenes::Doomed;
use super::Store;

macro_rules! job_cols {
    () => {
        "id, kind, scene_id, version, request, priority, state, progress, created_at, \
         started_at, finished_at, stats, error, result_blob, result_type, idempotency_key, \
         expires_at"
    };
}

/// The job `key` made, with its frames, on `conn` (a transaction's or a reader's).
async fn job_by_key(conn: &mut SqliteConnection, key: &str) -> Result<Option<JobRecord>> {
    let row = sqlx::query(concat!(
        "SELECT ",
        job_cols!(),
        " FROM jobs WHERE idempotency_key = ?"
    ))
    .bind(key)
    .fetch_optional(&mut *conn)
    .await?;
    match row {
        Some(row) => Ok(Some(with_frames(conn, &row).await?)),
        None => Ok(None),
    }
}

/// Attaches a job's frame results (only succeeded jobs have any).
async fn with_frames(conn: &mut SqliteConnection, row: &SqliteRow) -> Result<JobRecord> {
    let mut job = job_from_row(row)?;
    if job.state == JobState::Succeeded {
        job.result_frames = sqlx::query(
            "SELECT blob, content_type FROM job_results WHERE job_id = ? ORDER BY frame",
        )
        .bind(&job.id)
        .fetch_all(&mut *conn)
        .await?
        .iter()
        .map(|r| {
            Ok(ResultBlob {
                blob: r.try_get("blob")?,
                content_type: r.try_get("content_type")?,
            })
        })
        .collect::<Result<_>>()?;
    }
    Ok(job)
}

impl Store {
    /// Submits a job as `queued`. With an idempotency key that a job already has, returns
    /// that job with `false` (a retried POST finds the first job), or
    /// [`StoreError::Conflict`] if the retry asks for something else; a new job comes with
    /// `true`.
    pub async fn create_job(&self, new: NewJob) -> Result<(JobRecord, bool)> {
        self.create(new, None).await
    }

    /// [`Store::create_job`] for a job that asked for the latest version: if `new.version`,
    /// the latest when the caller looked, was deleted by newer versions (`keep_versions`)
    /// before this transaction, the job takes the scene's latest version as the
    /// transaction reads it, with `request_at(latest)` as its request. (Read apart from the
    /// insert, the latest could be deleted again before the insert every time: each new
    /// version's transaction is queued for the one writer ahead of the job's.) Version 1 is
    /// never deleted, so a request that only version 1 answers (a time, frames) keeps it.
    pub async fn create_job_latest(
        &self,
        new: NewJob,
        request_at: &(dyn Fn(i64) -> String + Send + Sync),
    ) -> Result<(JobRecord, bool)> {
        self.create(new, Some(request_at)).await
    }

    async fn create(
        &self,
        mut new: NewJob,
        request_at: Option<&(dyn Fn(i64) -> String + Send + Sync)>,
    ) -> Result<(JobRecord, bool)> {
        if new.priority > 100 {
            return Err(StoreError::invalid(
                "priority",
                format!("{} is not in 0..=100", new.priority),
            ));
        }
        check_json("request", &new.request)?;
        if let Some(key) = &new.idempotency_key {
            check_label("idempotency_key", key)?;
        }
        let scene = BlobId::parse_or_not_found(&new.scene_id, "scene")?;
        let id = new_job_id()?;
        let now = now_millis();
        let mut conn = self.inner.writer.acquire().await?;
        let mut tx = sqlx::Connection::begin(&mut *conn).await?;
        if let Some(key) = &new.idempotency_key {
            if let Some(job) = job_by_key(&mut tx, key).await? {
                if job.kind != new.kind
                    || job.scene_id != new.scene_id
                    || job.version != new.version
                    || job.request != new.request
                {
                    return Err(StoreError::Conflict(format!(
                        "idempotency key {key:?} was used for job {} with a different request",
                        job.id
                    )));
                }
                return Ok((job, false));
            }
        }
        let version_exists =
            sqlx::query("SELECT 1 FROM scene_versions WHERE scene_id = ? AND version = ?")
                .bind(scene.as_str())
                .bind(new.version)
                .fetch_optional(&mut *tx)
                .await?
                .is_some();
        if !version_exists {
            let latest: Option<i64> =
                sqlx::query_scalar("SELECT latest_version FROM scenes WHERE id = ?")
                    .bind(scene.as_str())
                    .fetch_optional(&mut *tx)
                    .await?;
            match (latest, request_at) {
                (Some(latest), Some(request_at)) if latest > new.version => {
                    new.version = latest;
                    new.request = request_at(latest);
                    check_json("request", &new.request)?;
                }
                (Some(_), _) => {
                    return Err(StoreError::not_found(
                        "version",
                        format!("{scene}/versions/{}", new.version),
                    ))
                }
                (None, _) => return Err(StoreError::not_found("scene", scene.as_str())),
            }
        }
        let row = sqlx::query(concat!(
            "INSERT INTO jobs (id, kind, scene_id, version, request, priority, state, progress, \
             created_at, idempotency_key, input_blob) \
             VALUES (?, ?, ?, ?, ?, ?, 'queued', 0, ?, ?, ?) RETURNING ",
            job_cols!()
        ))
        .bind(&id)
        .bind(new.kind.as_str())
        .bind(scene.as_str())
        .bind(new.version)
        .bind(&new.request)
        .bind(i64::from(new.priority))
        .bind(now)
        .bind(new.idempotency_key.as_deref())
        .bind(new.input_blob.as_ref().map(|b| b.as_str()))
        .fetch_one(&mut *tx)
        .await?;
        let job = job_from_row(&row)?;
        tx.commit().await?;
        Ok((job, true))
    }

    /// A job by id, with its results.
    pub async fn get_job(&self, id: &str) -> Result<JobRecord> {
        check_job_id(id)?;
        let mut conn = self.inner.reader.acquire().await?;
        let row = sqlx::query(concat!("SELECT ", job_cols!(), " FROM jobs WHERE id = ?"))
            .bind(id)
            .fetch_optional(&mut *conn)
            .await?
            .ok_or_else(|| StoreError::not_found("job", id))?;
        let job = with_frames(&mut conn, &row).await?;
        // Past its `expires_at` a job is gone, whether or not the next cleanup pass has
        // deleted its rows yet (it runs once a minute, and first a minute after a start).
        if expired(&job, now_millis()) {
            return Err(StoreError::not_found("job", id));
        }
        Ok(job)
    }

    /// A page of jobs, oldest first, and the token of the next page (`None` on the last).
    /// `limit` as for [`Store::list_scenes`].
    pub async fn list_jobs(
        &self,
        limit: u32,
        page_token: Option<&str>,
    ) -> Result<(Vec<JobRecord>, Option<String>)> {
        let n = page_size(limit);
        let mut conn = self.inner.reader.acquire().await?;
        // AIP-158: an empty token is the first page, as an absent one.
        let rows = match page_token.filter(|t| !t.is_empty()) {
            None => {
                sqlx::query(concat!(
                    "SELECT ",
                    job_cols!(),
                    " FROM jobs ORDER BY created_at, id LIMIT ?"
                ))
                .bind(n + 1)
                .fetch_all(&mut *conn)
                .await?
            }
            Some(token) => {
                let (t, id) = decode_page_token(ListKind::Jobs, token)?;
                sqlx::query(concat!(
                    "SELECT ",
                    job_cols!(),
                    " FROM jobs WHERE created_at > ? OR (created_at = ? AND id > ?) \
                     ORDER BY created_at, id LIMIT ?"
                ))
                .bind(t)
                .bind(t)
                .bind(id)
                .bind(n + 1)
                .fetch_all(&mut *conn)
                .await?
            }
        };
        let more = rows.len() as i64 > n;
        let mut jobs = Vec::with_capacity(rows.len());
        for row in rows.iter().take(n as usize) {
            jobs.push(with_frames(&mut conn, row).await?);
        }
        // The token follows the last row read, listed or not, so that a page whose jobs
        // expired is shorter but the next one starts where it ended (AIP-158 allows
        // short pages).
        let next = if more {
            jobs.last()
                .map(|j| encode_page_token(ListKind::Jobs, j.created_at, &j.id))
        } else {
            None
        };
        let now = now_millis();
        jobs.retain(|j| !expired(j, now));
        Ok((jobs, next))
    }

    /// Every queued job, in the order a scheduler should take them: priority (highest
    /// first), then age.
    pub async fn queued_jobs(&self) -> Result<Vec<JobRecord>> {
        sqlx::query(concat!(
            "SELECT ",
            job_cols!(),
            " FROM jobs WHERE state = 'queued' ORDER BY priority DESC, created_at, id"
        ))
        .fetch_all(&self.inner.reader)
        .await?
        .iter()
        .map(job_from_row)
        .collect()
    }

    /// Marks a queued job running (a worker took it) and returns it.
    pub async fn start_job(&self, id: &str) -> Result<JobRecord> {
        check_job_id(id)?;
        let row = sqlx::query(concat!(
            "UPDATE jobs SET state = 'running', started_at = ?, progress = 0 \
             WHERE id = ? AND state = 'queued' RETURNING ",
            job_cols!()
        ))
        .bind(now_millis())
        .bind(id)
        .fetch_optional(&self.inner.writer)
        .await?;
        match row {
            Some(row) => job_from_row(&row),
            None => Err(self.wrong_state(id, "queued").await),
        }
    }

    /// Records a running job's progress (0..=1).
    pub async fn set_progress(&self, id: &str, progress: f64) -> Result<()> {
        check_job_id(id)?;
        if !(0.0..=1.0).contains(&progress) {
            return Err(StoreError::invalid(
                "progress",
                format!("{progress} is not in 0..=1"),
            ));
        }
        let n = sqlx::query("UPDATE jobs SET progress = ? WHERE id = ? AND state = 'running'")
            .bind(progress)
            .bind(id)
            .execute(&self.inner.writer)
            .await?
            .rows_affected();
        if n == 0 {
            return Err(self.wrong_state(id, "running").await);
        }
        Ok(())
    }

    /// Ends a running job. A success names its result blobs, which must be stored already;
    /// they and the new state commit together. The job then expires after `result_ttl`.
    pub async fn finish_job(&self, id: &str, outcome: JobOutcome) -> Result<JobRecord> {
        check_job_id(id)?;
        let (state, stats, error, result, frames) = match outcome {
            JobOutcome::Succeeded {
                stats,
                result,
                frames,
            } => (JobState::Succeeded, stats, None, result, frames),
            JobOutcome::Failed { error, stats } => {
                (JobState::Failed, stats, Some(error), None, Vec::new())
            }
        };
        if let Some(stats) = &stats {
            check_json("stats", stats)?;
        }
        for (_, content_type) in result.iter().chain(&frames) {
            check_label("result content_type", content_type)?;
        }
        let blobs: Vec<BlobId> = result
            .iter()
            .chain(&frames)
            .map(|(b, _)| b.clone())
            .collect();
        let _gate = self.inner.gc_gate.read().await;
        self.require_blobs(blobs).await?;
        let now = now_millis();
        let expires = self.expiry(now);
        let mut conn = self.inner.writer.acquire().await?;
        let mut tx = sqlx::Connection::begin(&mut *conn).await?;
        let row = sqlx::query(concat!(
            "UPDATE jobs SET state = ?, finished_at = ?, expires_at = ?, stats = ?, error = ?, \
             result_blob = ?, result_type = ?, \
             progress = CASE WHEN ? = 'succeeded' THEN 1 ELSE progress END \
             WHERE id = ? AND state = 'running' RETURNING ",
            job_cols!()
        ))
        .bind(state.as_str())
        .bind(now)
        .bind(expires)
        .bind(stats.as_deref())
        .bind(error.as_deref())
        .bind(result.as_ref().map(|(b, _)| b.as_str()))
        .bind(result.as_ref().map(|(_, t)| t.as_str()))
        .bind(state.as_str())
        .bind(id)
        .fetch_optional(&mut *tx)
        .await?;
        let Some(row) = row else {
            drop(tx);
            drop(conn);
            return Err(self.wrong_state(id, "running").await);
        };
        for (frame, (blob, content_type)) in frames.iter().enumerate() {
            sqlx::query(
                "INSERT INTO job_results (job_id, frame, blob, content_type) VALUES (?, ?, ?, ?)",
            )
            .bind(id)
            .bind(frame as i64)
            .bind(blob.as_str())
            .bind(content_type)
            .execute(&mut *tx)
            .await?;
        }
        let job = with_frames(&mut tx, &row).await?;
        tx.commit().await?;
        Ok(job)
    }

    /// The job an `Idempotency-Key` made, if any.
    pub async fn job_by_idempotency_key(&self, key: &str) -> Result<Option<JobRecord>> {
        check_label("idempotency_key", key)?;
        let mut conn = self.inner.reader.acquire().await?;
        job_by_key(&mut conn, key).await
    }

    /// Cancels a queued or running job; its record stays, as `cancelled`, until it expires
    /// or is deleted. Cancelling an ended job is a [`StoreError::Conflict`].
    pub async fn cancel_job(&self, id: &str) -> Result<JobRecord> {
        check_job_id(id)?;
        let now = now_millis();
        let row = sqlx::query(concat!(
            "UPDATE jobs SET state = 'cancelled', finished_at = ?, expires_at = ? \
             WHERE id = ? AND state IN ('queued', 'running') RETURNING ",
            job_cols!()
        ))
        .bind(now)
        .bind(self.expiry(now))
        .bind(id)
        .fetch_optional(&self.inner.writer)
        .await?;
        match row {
            Some(row) => job_from_row(&row),
            None => Err(self.wrong_state(id, "queued or running").await),
        }
    }

    /// Deletes an ended job and its results (their blobs go at the next
    /// [`Store::collect_pruned`] unless another record names the same bytes). A queued or
    /// running job must be cancelled first ([`StoreError::Conflict`]).
    pub async fn delete_job(&self, id: &str) -> Result<()> {
        check_job_id(id)?;
        let mut tx = self.inner.writer.begin().await?;
        let blobs = job_blobs(&mut tx, "id = ?1", id).await?;
        let n = sqlx::query(
            "DELETE FROM jobs WHERE id = ? AND state IN ('succeeded', 'failed', 'cancelled')",
        )
        .bind(id)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        if n == 0 {
            drop(tx);
            return Err(self.wrong_state(id, "succeeded, failed or cancelled").await);
        }
        tx.commit().await?;
        self.doom(Doomed::Job, blobs.iter().map(String::as_str));
        Ok(())
    }

    /// When a job finished at `now` expires.
    fn expiry(&self, now: Millis) -> Option<Millis> {
        self.inner
            .options
            .result_ttl
            .map(|ttl| now.saturating_add(i64::try_from(ttl.as_millis()).unwrap_or(i64::MAX)))
    }

    /// The error for a state change that found no job in the state it needs: `NotFound` if
    /// there is no such job, else a `Conflict` naming the state it is in.
    async fn wrong_state(&self, id: &str, needed: &str) -> StoreError {
        match sqlx::query("SELECT state FROM jobs WHERE id = ?")
            .bind(id)
            .fetch_optional(&self.inner.reader)
            .await
        {
            Ok(None) => StoreError::not_found("job", id),
            Ok(Some(row)) => match row.try_get::<String, _>(0) {
                Ok(state) => StoreError::Conflict(format!("job {id} is {state}, not {needed}")),
                Err(e) => e.into(),
            },
            Err(e) => e.into(),
        }
    }
}

/// Whether `job` is past its `expires_at` at `now`: gone to every reader.
fn expired(job: &JobRecord, now: Millis) -> bool {
    job.expires_at.is_some_and(|at| at <= now)
}

/// Every blob that the jobs matching `condition` (on `jobs`, with `?1` bound to `value`)
/// name: results, a sequence's frames and an async trace's rays. Read in the transaction
/// that deletes them, so that their files can go at once instead of after GC's grace.
pub(super) async fn job_blobs<'q, T>(
    conn: &mut SqliteConnection,
    condition: &str,
    value: T,
) -> Result<Vec<String>>
where
    T: 'q + sqlx::Encode<'q, sqlx::Sqlite> + sqlx::Type<sqlx::Sqlite> + Send,
{
    let sql = format!(
        "SELECT result_blob FROM jobs WHERE ({condition}) AND result_blob IS NOT NULL \
         UNION SELECT input_blob FROM jobs WHERE ({condition}) AND input_blob IS NOT NULL \
         UNION SELECT blob FROM job_results WHERE job_id IN \
         (SELECT id FROM jobs WHERE {condition})"
    );
    Ok(sqlx::query_scalar(sqlx::AssertSqlSafe(sql))
        .bind(value)
        .fetch_all(conn)
        .await?)
}
