//! Scenes and their versions: records naming uploaded blobs.
//!
//! A scene's id is its upload's blob id, so uploading the same bytes twice finds the same
//! scene. Version 1 is the upload itself; [`Store::add_version`] appends TRI1 position blobs
//! as versions 2, 3, … with the number allocated inside the inserting transaction.

use sqlx::Row;

use super::blob::BlobId;
use super::error::{Result, StoreError};
use super::records::{
    check_json, decode_page_token, encode_page_token, now_millis, page_size, scene_from_row,
    version_from_row, ListKind, SceneRecord, VersionRecord,
};
use super::Store;

/// A scene to record, for an upload already stored as a blob.
#[derive(Clone, Debug, PartialEq)]
pub struct NewScene {
    /// The upload's blob (it becomes the scene id and version 1).
    pub blob: BlobId,
    /// The upload's MIME type.
    pub content_type: String,
    /// A name for listings, if the client gave one.
    pub name: Option<String>,
    /// JSON text: the fields of `rayd info` for this scene.
    pub summary: String,
}

/// Longest accepted `name`, `content_type` or idempotency key: far above real use, low
/// enough that a client cannot fill the database through them.
pub(crate) const MAX_LABEL: usize = 1024;

/// Most blobs of deleted versions (and, apart, of deleted jobs) kept for
/// [`Store::collect_pruned`].
const MAX_DOOMED: usize = 1 << 16;

/// What a doomed blob's deleted record was.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Doomed {
    /// A geometry version (or a scene's upload).
    Version,
    /// A job: its result, a sequence's frame or an async trace's rays. The same bytes may
    /// be a running job's result not yet recorded, which [`Store::collect_pruned`] keeps.
    Job,
}

/// Blobs whose records were deleted, awaiting [`Store::collect_pruned`].
#[derive(Debug, Default)]
pub(super) struct Pruned {
    pub(super) versions: Vec<BlobId>,
    pub(super) jobs: Vec<BlobId>,
}

impl Pruned {
    pub(super) fn is_empty(&self) -> bool {
        self.versions.is_empty() && self.jobs.is_empty()
    }
}

/// The condition, on a `scene_versions` row, that no job names it: a job's record keeps
/// its version (and, by the foreign key's cascade, would go with it).
macro_rules! unused_version {
    () => {
        "NOT EXISTS (SELECT 1 FROM jobs WHERE jobs.scene_id = scene_versions.scene_id \
         AND jobs.version = scene_versions.version)"
    };
}

macro_rules! scene_cols {
    () => {
        "id, content_type, name, summary, created_at, latest_version"
    };
}

pub(crate) fn check_label(field: &'static str, s: &str) -> Result<()> {
    if s.is_empty() || s.len() > MAX_LABEL || s.chars().any(char::is_control) {
        return Err(StoreError::invalid(
            field,
            format!("must be 1 to {MAX_LABEL} bytes without control characters"),
        ));
    }
    Ok(())
}

impl Store {
    /// Records a scene for an uploaded blob, in one transaction with its version 1. If the
    /// scene exists already (the same bytes were uploaded before), returns it unchanged
    /// with `false`; a new scene comes with `true`.
    pub async fn create_scene(&self, new: NewScene) -> Result<(SceneRecord, bool)> {
        check_label("content_type", &new.content_type)?;
        if let Some(name) = &new.name {
            check_label("name", name)?;
        }
        check_json("summary", &new.summary)?;
        let _gate = self.inner.gc_gate.read().await;
        self.require_blobs(vec![new.blob.clone()]).await?;
        let now = now_millis();
        let mut tx = self.inner.writer.begin().await?;
        let inserted = sqlx::query(
            "INSERT INTO scenes (id, content_type, name, summary, created_at, latest_version) \
             VALUES (?, ?, ?, ?, ?, 1) ON CONFLICT (id) DO NOTHING",
        )
        .bind(new.blob.as_str())
        .bind(&new.content_type)
        .bind(&new.name)
        .bind(&new.summary)
        .bind(now)
        .execute(&mut *tx)
        .await?
        .rows_affected()
            == 1;
        if inserted {
            sqlx::query(
                "INSERT INTO scene_versions (scene_id, version, blob, created_at) \
                 VALUES (?, 1, ?, ?)",
            )
            .bind(new.blob.as_str())
            .bind(new.blob.as_str())
            .bind(now)
            .execute(&mut *tx)
            .await?;
        }
        let row = sqlx::query(concat!(
            "SELECT ",
            scene_cols!(),
            " FROM scenes WHERE id = ?"
        ))
        .bind(new.blob.as_str())
        .fetch_one(&mut *tx)
        .await?;
        let scene = scene_from_row(&row)?;
        tx.commit().await?;
        Ok((scene, inserted))
    }

    /// A scene by id.
    pub async fn get_scene(&self, id: &str) -> Result<SceneRecord> {
        let id = BlobId::parse_or_not_found(id, "scene")?;
        let row = sqlx::query(concat!(
            "SELECT ",
            scene_cols!(),
            " FROM scenes WHERE id = ?"
        ))
        .bind(id.as_str())
        .fetch_optional(&self.inner.reader)
        .await?
        .ok_or_else(|| StoreError::not_found("scene", id.as_str()))?;
        scene_from_row(&row)
    }

    /// A page of scenes, oldest first, and the token of the next page (`None` on the last).
    /// `limit` 0 means [`super::DEFAULT_PAGE_SIZE`]; larger than
    /// [`super::MAX_PAGE_SIZE`] is cut to it.
    pub async fn list_scenes(
        &self,
        limit: u32,
        page_token: Option<&str>,
    ) -> Result<(Vec<SceneRecord>, Option<String>)> {
        let n = page_size(limit);
        // AIP-158: an empty token is the first page, as an absent one.
        let rows = match page_token.filter(|t| !t.is_empty()) {
            None => {
                sqlx::query(concat!(
                    "SELECT ",
                    scene_cols!(),
                    " FROM scenes ORDER BY created_at, id LIMIT ?"
                ))
                .bind(n + 1)
                .fetch_all(&self.inner.reader)
                .await?
            }
            Some(token) => {
                let (t, id) = decode_page_token(ListKind::Scenes, token)?;
                sqlx::query(concat!(
                    "SELECT ",
                    scene_cols!(),
                    " FROM scenes WHERE created_at > ? OR (created_at = ? AND id > ?) \
                     ORDER BY created_at, id LIMIT ?"
                ))
                .bind(t)
                .bind(t)
                .bind(id)
                .bind(n + 1)
                .fetch_all(&self.inner.reader)
                .await?
            }
        };
        let mut scenes = rows
            .iter()
            .map(scene_from_row)
            .collect::<Result<Vec<_>>>()?;
        let next = if scenes.len() as i64 > n {
            scenes.truncate(n as usize);
            scenes
                .last()
                .map(|s| encode_page_token(ListKind::Scenes, s.created_at, &s.id))
        } else {
            None
        };
        Ok((scenes, next))
    }

    /// Adds a version naming `blob` (TRI1 positions, already stored) and returns it, with
    /// the numbers of the older versions this deleted to keep the scene within
    /// [`StoreOptions::keep_versions`](super::StoreOptions::keep_versions). The number is
    /// the scene's latest plus one, allocated in the same transaction, so concurrent adds
    /// get consecutive numbers; the pruning shares that transaction too, so a frame's
    /// update costs one commit.
    pub async fn add_version(
        &self,
        scene_id: &str,
        blob: &BlobId,
    ) -> Result<(VersionRecord, Vec<i64>)> {
        let scene = BlobId::parse_or_not_found(scene_id, "scene")?;
        let _gate = self.inner.gc_gate.read().await;
        self.require_blobs(vec![blob.clone()]).await?;
        let now = now_millis();
        let mut tx = self.inner.writer.begin().await?;
        let version: i64 = sqlx::query(
            "UPDATE scenes SET latest_version = latest_version + 1 WHERE id = ? \
             RETURNING latest_version",
        )
        .bind(scene.as_str())
        .fetch_optional(&mut *tx)
        .await?
        .ok_or_else(|| StoreError::not_found("scene", scene.as_str()))?
        .try_get(0)?;
        sqlx::query(
            "INSERT INTO scene_versions (scene_id, version, blob, created_at) VALUES (?, ?, ?, ?)",
        )
        .bind(scene.as_str())
        .bind(version)
        .bind(blob.as_str())
        .bind(now)
        .execute(&mut *tx)
        .await?;
        let mut pruned = Vec::new();
        if let Some(keep) = self.inner.options.keep_versions {
            pruned = sqlx::query(concat!(
                "DELETE FROM scene_versions WHERE scene_id = ? AND version > 1 AND version <= ? AND ",
                unused_version!(),
                " RETURNING scene_id, version, blob, created_at"
            ))
            .bind(scene.as_str())
            .bind(version - i64::from(keep.max(1)))
            .fetch_all(&mut *tx)
            .await?
            .iter()
            .map(version_from_row)
            .collect::<Result<_>>()?;
        }
        tx.commit().await?;
        let mut numbers: Vec<i64> = pruned.iter().map(|v| v.version).collect();
        numbers.sort_unstable();
        self.doom_blobs(&pruned);
        Ok((
            VersionRecord {
                scene_id: scene.to_string(),
                version,
                blob: blob.to_string(),
                created_at: now,
            },
            numbers,
        ))
    }

    /// Deletes, in every scene, the versions that [`Store::add_version`] would have pruned
    /// but a job still named then (the job has since expired or been deleted). Returns the
    /// `(scene, version)` pairs deleted; their blobs go at the next
    /// [`Store::collect_pruned`]. Does
    /// nothing when every version is kept.
    pub async fn prune_versions(&self) -> Result<Vec<(String, i64)>> {
        let Some(keep) = self.inner.options.keep_versions else {
            return Ok(Vec::new());
        };
        let pruned: Vec<VersionRecord> = sqlx::query(concat!(
            "DELETE FROM scene_versions WHERE version > 1 AND version <= \
             (SELECT latest_version FROM scenes WHERE scenes.id = scene_versions.scene_id) - ? AND ",
            unused_version!(),
            " RETURNING scene_id, version, blob, created_at"
        ))
        .bind(i64::from(keep.max(1)))
        .fetch_all(&self.inner.writer)
        .await?
        .iter()
        .map(version_from_row)
        .collect::<Result<_>>()?;
        self.doom_blobs(&pruned);
        let mut pairs: Vec<(String, i64)> = pruned
            .into_iter()
            .map(|v| (v.scene_id, v.version))
            .collect();
        pairs.sort_unstable();
        Ok(pairs)
    }

    /// Hands the blobs of deleted versions to [`Store::collect_pruned`].
    fn doom_blobs(&self, pruned: &[VersionRecord]) {
        self.doom(Doomed::Version, pruned.iter().map(|v| v.blob.as_str()));
    }

    /// Hands blobs whose records were deleted to [`Store::collect_pruned`], which deletes
    /// those that no record names by then.
    pub(super) fn doom<'a>(&self, kind: Doomed, blobs: impl Iterator<Item = &'a str>) {
        let mut pruned = self.pruned();
        let doomed = match kind {
            Doomed::Version => &mut pruned.versions,
            Doomed::Job => &mut pruned.jobs,
        };
        let before = doomed.len();
        doomed.extend(blobs.filter_map(BlobId::parse));
        if doomed.len() == before {
            return;
        }
        // Uncollected (no caller runs `collect_pruned`), the oldest are left to GC's grace.
        if doomed.len() > MAX_DOOMED {
            let over = doomed.len() - MAX_DOOMED;
            doomed.drain(..over);
        }
        drop(pruned);
        self.inner.pruned_ready.notify_one();
    }

    /// The blobs of deleted records awaiting [`Store::collect_pruned`].
    pub(super) fn pruned(&self) -> std::sync::MutexGuard<'_, Pruned> {
        self.inner.pruned.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// One version of a scene.
    pub async fn get_version(&self, scene_id: &str, version: i64) -> Result<VersionRecord> {
        let scene = BlobId::parse_or_not_found(scene_id, "scene")?;
        let row = sqlx::query(
            "SELECT scene_id, version, blob, created_at FROM scene_versions \
             WHERE scene_id = ? AND version = ?",
        )
        .bind(scene.as_str())
        .bind(version)
        .fetch_optional(&self.inner.reader)
        .await?;
        match row {
            Some(row) => version_from_row(&row),
            None => {
                // Say which of the two is missing.
                self.get_scene(scene.as_str()).await?;
                Err(StoreError::not_found(
                    "version",
                    format!("{scene}/versions/{version}"),
                ))
            }
        }
    }

    /// Every version of a scene, oldest first.
    pub async fn list_versions(&self, scene_id: &str) -> Result<Vec<VersionRecord>> {
        let scene = self.get_scene(scene_id).await?;
        sqlx::query(
            "SELECT scene_id, version, blob, created_at FROM scene_versions \
             WHERE scene_id = ? ORDER BY version",
        )
        .bind(&scene.id)
        .fetch_all(&self.inner.reader)
        .await?
        .iter()
        .map(version_from_row)
        .collect()
    }

    /// Deletes a scene with its versions and all its jobs (their results included), in one
    /// transaction. Returns the ids of the deleted jobs that were still queued or running,
    /// so the engine can stop them (their later updates find no job). Their blobs go at the
    /// next [`Store::collect_pruned`] unless another record names the same bytes.
    pub async fn delete_scene(&self, id: &str) -> Result<Vec<String>> {
        let scene = BlobId::parse_or_not_found(id, "scene")?;
        let mut tx = self.inner.writer.begin().await?;
        let unfinished: Vec<String> = sqlx::query_scalar(
            "SELECT id FROM jobs WHERE scene_id = ? AND state IN ('queued', 'running') \
             ORDER BY created_at, id",
        )
        .bind(scene.as_str())
        .fetch_all(&mut *tx)
        .await?;
        // Its versions' files (the upload's among them) go at the next `collect_pruned`,
        // within seconds, unless another record names the same bytes: left to GC's grace,
        // a client that uploads and deletes scenes would fill `--max-store-bytes` with
        // deleted ones for 15 minutes.
        let blobs: Vec<String> =
            sqlx::query_scalar("SELECT blob FROM scene_versions WHERE scene_id = ?")
                .bind(scene.as_str())
                .fetch_all(&mut *tx)
                .await?;
        let job_blobs = super::jobs::job_blobs(&mut tx, "scene_id = ?1", scene.as_str()).await?;
        let deleted = sqlx::query("DELETE FROM scenes WHERE id = ?")
            .bind(scene.as_str())
            .execute(&mut *tx)
            .await?
            .rows_affected();
        if deleted == 0 {
            return Err(StoreError::not_found("scene", scene.as_str()));
        }
        tx.commit().await?;
        self.doom(Doomed::Version, blobs.iter().map(String::as_str));
        self.doom(Doomed::Job, job_blobs.iter().map(String::as_str));
        Ok(unfinished)
    }
}
