//! The records the store keeps (scenes, versions, jobs), their states, and page tokens.
//!
//! Records are plain data with `Serialize`, so the service can answer with them or map them
//! to its wire types. JSON fields (`summary`, `request`, `stats`) are kept as text: the store
//! checks they are JSON but does not interpret them.

use serde::Serialize;
use sqlx::sqlite::SqliteRow;
use sqlx::Row;

use super::blob::BlobId;
use super::error::{Result, StoreError};

/// Milliseconds since the Unix epoch (UTC): the unit of every time the store keeps.
pub type Millis = i64;

/// The current time in [`Millis`].
pub fn now_millis() -> Millis {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as Millis)
        .unwrap_or(0)
}

/// An uploaded scene.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SceneRecord {
    /// The blake3 hash of the uploaded bytes (also the blob of version 1).
    pub id: String,
    /// The upload's MIME type.
    pub content_type: String,
    /// A name given at upload, if any.
    pub name: Option<String>,
    /// JSON text with the fields of `rayd info`, as the caller computed them.
    pub summary: String,
    /// When it was uploaded.
    pub created_at: Millis,
    /// The highest version number (1 until geometry is replaced).
    pub latest_version: i64,
}

/// One version of a scene's geometry.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct VersionRecord {
    /// The scene.
    pub scene_id: String,
    /// 1 is the upload; 2 and later are TRI1 positions.
    pub version: i64,
    /// The blob holding this version's bytes.
    pub blob: String,
    /// When it was added.
    pub created_at: Millis,
}

/// What a job computes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum JobKind {
    /// A ray batch traced asynchronously; the result is a HIT1 body.
    Trace,
    /// An image (or frames of an animation).
    Render,
}

/// Where a job is in its life. `queued → running → succeeded | failed`, and `cancelled`
/// from either of the first two.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    /// Waiting for a worker.
    Queued,
    /// A worker has it.
    Running,
    /// Finished with a result.
    Succeeded,
    /// Finished with an error.
    Failed,
    /// Stopped by a client.
    Cancelled,
}

impl JobKind {
    /// The stored spelling (the same as the serde one).
    pub fn as_str(self) -> &'static str {
        match self {
            JobKind::Trace => "trace",
            JobKind::Render => "render",
        }
    }
    fn parse(s: &str) -> Result<JobKind> {
        match s {
            "trace" => Ok(JobKind::Trace),
            "render" => Ok(JobKind::Render),
            _ => Err(undecodable("kind", s)),
        }
    }
}

impl JobState {
    /// The stored spelling (the same as the serde one).
    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Succeeded => "succeeded",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }
    /// Whether the job has ended (its record only changes by deletion or expiry now).
    pub fn is_finished(self) -> bool {
        matches!(
            self,
            JobState::Succeeded | JobState::Failed | JobState::Cancelled
        )
    }
    fn parse(s: &str) -> Result<JobState> {
        Ok(match s {
            "queued" => JobState::Queued,
            "running" => JobState::Running,
            "succeeded" => JobState::Succeeded,
            "failed" => JobState::Failed,
            "cancelled" => JobState::Cancelled,
            _ => return Err(undecodable("state", s)),
        })
    }
}

/// A stored value this binary cannot read (a damaged database, or one from a newer rayd
/// that slipped past the migration check).
fn undecodable(column: &str, value: &str) -> StoreError {
    StoreError::Db(sqlx::Error::Decode(
        format!("jobs.{column} holds {value:?}, which this rayd does not know").into(),
    ))
}

/// One stored output of a job: a blob and its MIME type.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ResultBlob {
    /// The blob.
    pub blob: String,
    /// Its MIME type (`image/png`, `image/x-exr`, `application/octet-stream`).
    pub content_type: String,
}

/// A job and, once it succeeded, its results.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct JobRecord {
    /// Random, 32 lowercase hex digits; opaque to clients.
    pub id: String,
    /// Trace or render.
    pub kind: JobKind,
    /// The scene it works on.
    pub scene_id: String,
    /// The scene version it works on.
    pub version: i64,
    /// JSON text of the request, as the caller resolved it.
    pub request: String,
    /// 0–100, higher first.
    pub priority: u8,
    /// Where the job is.
    pub state: JobState,
    /// 0..=1.
    pub progress: f64,
    /// When it was submitted.
    pub created_at: Millis,
    /// When a worker took it (cleared when a crash sends it back to the queue).
    pub started_at: Option<Millis>,
    /// When it ended.
    pub finished_at: Option<Millis>,
    /// JSON text of the job's statistics.
    pub stats: Option<String>,
    /// Why it failed (or was cancelled / recovered).
    pub error: Option<String>,
    /// The result (a single image or HIT1 body).
    pub result: Option<ResultBlob>,
    /// The results of a multi-frame render, in frame order.
    pub result_frames: Vec<ResultBlob>,
    /// The client's `Idempotency-Key`, if it sent one.
    pub idempotency_key: Option<String>,
    /// When the finished job and its results will be deleted (`None`: kept until deleted).
    pub expires_at: Option<Millis>,
}

/// A job to submit.
#[derive(Clone, Debug, PartialEq)]
pub struct NewJob {
    /// Trace or render.
    pub kind: JobKind,
    /// An existing scene.
    pub scene_id: String,
    /// An existing version of it.
    pub version: i64,
    /// JSON text of the request.
    pub request: String,
    /// 0–100.
    pub priority: u8,
    /// A retried submission with the same key returns the first job.
    pub idempotency_key: Option<String>,
    /// The blob the job reads (an async trace's rays), already stored: kept as long as
    /// the job's record is.
    pub input_blob: Option<BlobId>,
}

/// How a running job ended.
#[derive(Clone, Debug, PartialEq)]
pub enum JobOutcome {
    /// It produced a result (and/or frames); the blobs must already be stored.
    Succeeded {
        /// JSON text of its statistics.
        stats: Option<String>,
        /// The single result, if any.
        result: Option<(BlobId, String)>,
        /// Frame results in frame order, for multi-frame renders.
        frames: Vec<(BlobId, String)>,
    },
    /// It failed.
    Failed {
        /// Why.
        error: String,
        /// JSON text of its statistics so far.
        stats: Option<String>,
    },
}

pub(crate) fn scene_from_row(row: &SqliteRow) -> Result<SceneRecord> {
    Ok(SceneRecord {
        id: row.try_get("id")?,
        content_type: row.try_get("content_type")?,
        name: row.try_get("name")?,
        summary: row.try_get("summary")?,
        created_at: row.try_get("created_at")?,
        latest_version: row.try_get("latest_version")?,
    })
}

pub(crate) fn version_from_row(row: &SqliteRow) -> Result<VersionRecord> {
    Ok(VersionRecord {
        scene_id: row.try_get("scene_id")?,
        version: row.try_get("version")?,
        blob: row.try_get("blob")?,
        created_at: row.try_get("created_at")?,
    })
}

/// A job row without its frames (the caller attaches them).
pub(crate) fn job_from_row(row: &SqliteRow) -> Result<JobRecord> {
    let result_blob: Option<String> = row.try_get("result_blob")?;
    let result_type: Option<String> = row.try_get("result_type")?;
    let priority: i64 = row.try_get("priority")?;
    Ok(JobRecord {
        id: row.try_get("id")?,
        kind: JobKind::parse(row.try_get::<&str, _>("kind")?)?,
        scene_id: row.try_get("scene_id")?,
        version: row.try_get("version")?,
        request: row.try_get("request")?,
        priority: u8::try_from(priority).unwrap_or(u8::MAX),
        state: JobState::parse(row.try_get::<&str, _>("state")?)?,
        progress: row.try_get("progress")?,
        created_at: row.try_get("created_at")?,
        started_at: row.try_get("started_at")?,
        finished_at: row.try_get("finished_at")?,
        stats: row.try_get("stats")?,
        error: row.try_get("error")?,
        result: result_blob.map(|blob| ResultBlob {
            blob,
            content_type: result_type.unwrap_or_default(),
        }),
        result_frames: Vec::new(),
        idempotency_key: row.try_get("idempotency_key")?,
        expires_at: row.try_get("expires_at")?,
    })
}

/// Which list a page token belongs to, so a token of one list is refused by the other.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum ListKind {
    Scenes,
    Jobs,
}

impl ListKind {
    fn tag(self) -> &'static str {
        match self {
            ListKind::Scenes => "s1",
            ListKind::Jobs => "j1",
        }
    }
}

/// Lists are ordered by `(created_at, id)`, a total order that inserts never reorder; a
/// token is the position after the last record of a page, hex-encoded so it is opaque and
/// URL-safe.
pub(crate) fn encode_page_token(kind: ListKind, created_at: Millis, id: &str) -> String {
    let plain = format!("{}:{created_at}:{id}", kind.tag());
    plain.bytes().map(|b| format!("{b:02x}")).collect()
}

/// Decodes a token made by [`encode_page_token`] for the same list.
pub(crate) fn decode_page_token(kind: ListKind, token: &str) -> Result<(Millis, String)> {
    let bad = || StoreError::BadPageToken;
    if !token.len().is_multiple_of(2) || token.len() > 512 {
        return Err(bad());
    }
    let bytes = (0..token.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(token.get(i..i + 2).ok_or_else(bad)?, 16).map_err(|_| bad()))
        .collect::<Result<Vec<u8>>>()?;
    let plain = String::from_utf8(bytes).map_err(|_| bad())?;
    let mut parts = plain.splitn(3, ':');
    let (Some(tag), Some(t), Some(id)) = (parts.next(), parts.next(), parts.next()) else {
        return Err(bad());
    };
    // The id is one of the list's own: a job id, or a scene's content hash.
    let id_ok = match kind {
        ListKind::Jobs => check_job_id(id).is_ok(),
        ListKind::Scenes => super::blob::BlobId::parse(id).is_some(),
    };
    if tag != kind.tag() || !id_ok {
        return Err(bad());
    }
    let t: Millis = t.parse().map_err(|_| bad())?;
    if t < 0 {
        return Err(bad());
    }
    Ok((t, id.to_string()))
}

/// The page size when the caller asks for 0 (AIP-158: "server default").
pub const DEFAULT_PAGE_SIZE: u32 = 50;
/// The largest page; larger requests are cut to it (AIP-158 coerces rather than refuses).
pub const MAX_PAGE_SIZE: u32 = 1000;

pub(crate) fn page_size(limit: u32) -> i64 {
    match limit {
        0 => DEFAULT_PAGE_SIZE as i64,
        n => n.min(MAX_PAGE_SIZE) as i64,
    }
}

/// Checks that a text field holds JSON.
pub(crate) fn check_json(field: &'static str, text: &str) -> Result<()> {
    serde_json::from_str::<serde::de::IgnoredAny>(text)
        .map(|_| ())
        .map_err(|e| StoreError::invalid(field, format!("not JSON: {e}")))
}

/// Job ids: 128 random bits as 32 lowercase hex digits.
pub(crate) const JOB_ID_LEN: usize = 32;

pub(crate) fn new_job_id() -> Result<String> {
    let mut bytes = [0u8; JOB_ID_LEN / 2];
    getrandom::fill(&mut bytes).map_err(|e| StoreError::Io {
        path: "getrandom".into(),
        source: std::io::Error::other(e.to_string()),
    })?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// Checks a job id's form; anything else names no job.
pub(crate) fn check_job_id(id: &str) -> Result<()> {
    if id.len() == JOB_ID_LEN && id.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f')) {
        Ok(())
    } else {
        Err(StoreError::not_found("job", id))
    }
}
