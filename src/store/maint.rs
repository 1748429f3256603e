//! Upkeep: crash recovery, expiry of finished jobs, blob garbage collection and online
//! backup.

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::SystemTime;

use sqlx::sqlite::SqliteConnectOptions;
use sqlx::{Connection, Row, SqliteConnection};

use super::blob::{create_dir_durable, sync_dir, BlobDir, BlobId};
use super::error::{Result, StoreError};
use super::records::{JobRecord, Millis};
use super::scenes::Doomed;
use super::{blocking, Store, DB_FILE};

/// Every blob a record names: versions, single results and frame results.
const REFERENCED_BLOBS: &str = "SELECT blob FROM scene_versions \
     UNION SELECT result_blob FROM jobs WHERE result_blob IS NOT NULL \
     UNION SELECT input_blob FROM jobs WHERE input_blob IS NOT NULL \
     UNION SELECT blob FROM job_results";

/// What [`Store::gc`] did.
#[derive(Clone, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct GcReport {
    /// Unreferenced blob files deleted.
    pub deleted: u64,
    /// Their bytes.
    pub freed_bytes: u64,
    /// Unreferenced blobs kept because they are younger than `gc_grace` (an upload whose
    /// record may be about to commit).
    pub kept_recent: u64,
    /// Blobs still referenced.
    pub referenced: u64,
}

/// What [`Store::backup`] wrote.
#[derive(Clone, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct BackupReport {
    /// Blobs copied (every one the snapshot's records name).
    pub blobs: u64,
    /// Their bytes.
    pub bytes: u64,
    /// Geometry versions left out of the copy: versions that `keep_versions` deleted in
    /// the running server (with their blobs) after the snapshot was taken, so that the
    /// copy holds what the server held a moment later instead of failing.
    pub dropped_versions: u64,
}

impl Store {
    /// Run once at start, before any worker: jobs a crash left `running` go back to
    /// `queued` (their `started_at` and progress cleared; the work is redone from the
    /// start), in one transaction. Returns every queued job, those included, in scheduling
    /// order, for the engine to queue again: nothing submitted is lost.
    pub async fn recover(&self) -> Result<Vec<JobRecord>> {
        sqlx::query(
            "UPDATE jobs SET state = 'queued', started_at = NULL, progress = 0 \
             WHERE state = 'running'",
        )
        .execute(&self.inner.writer)
        .await?;
        self.queued_jobs().await
    }

    /// Deletes the finished jobs (and their result records) whose `expires_at` is at or
    /// before `now`, in one transaction; returns how many. Their blobs go at the next
    /// [`Store::collect_pruned`] unless another record names the same bytes.
    pub async fn expire(&self, now: Millis) -> Result<u64> {
        const EXPIRED: &str = "expires_at IS NOT NULL AND expires_at <= ?1 \
             AND state IN ('succeeded', 'failed', 'cancelled')";
        let mut tx = self.inner.writer.begin().await?;
        let blobs = super::jobs::job_blobs(&mut tx, EXPIRED, now).await?;
        let n = sqlx::query(sqlx::AssertSqlSafe(format!(
            "DELETE FROM jobs WHERE {EXPIRED}"
        )))
        .bind(now)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        tx.commit().await?;
        self.doom(Doomed::Job, blobs.iter().map(String::as_str));
        Ok(n)
    }

    /// Deletes blob files that no record names and that are older than `gc_grace`.
    ///
    /// Why this cannot race an upload: GC holds the GC gate exclusively from reading the
    /// referenced set (one statement, one snapshot) to its last delete. Storing a blob and
    /// committing a record that names one both hold the gate shared, and storing bytes that
    /// exist renews the file's mtime. So for an upload of the same bytes, either GC ran
    /// first (the file is gone, and the upload writes it again) or the upload ran first
    /// (the file is young, or referenced, and GC keeps it). A record is committed only after
    /// checking, under the gate, that its blobs exist; one that names a blob collected since
    /// its upload (after more than `gc_grace`) fails with `NotFound` instead of dangling.
    ///
    /// A running job's results are stored as it makes them (a sequence's frames, one by
    /// one) and named by its record only when it ends, so blobs written since the oldest
    /// running job started are kept however old they are: a sequence that renders for
    /// longer than `gc_grace` keeps its first frames.
    pub async fn gc(&self) -> Result<GcReport> {
        let _gate = self.inner.gc_gate.write().await;
        let referenced: HashSet<String> = sqlx::query(REFERENCED_BLOBS)
            .fetch_all(&self.inner.reader)
            .await?
            .iter()
            .map(|r| r.try_get::<String, _>(0))
            .collect::<Result<_, _>>()?;
        let running_since = self.running_since().await?;
        let blobs = Arc::clone(&self.inner.blobs);
        let grace = self.inner.options.gc_grace;
        blocking(&self.inner.dir, move || {
            let now = SystemTime::now();
            let mut report = GcReport {
                referenced: referenced.len() as u64,
                ..GcReport::default()
            };
            let mut doomed = Vec::new();
            for (id, modified) in blobs.list()? {
                if referenced.contains(id.as_str()) {
                    continue;
                }
                // A clock step backwards makes the file look young: keep it.
                let age = now.duration_since(modified).unwrap_or_default();
                if age < grace || running_since.is_some_and(|since| modified >= since) {
                    report.kept_recent += 1;
                    continue;
                }
                doomed.push(id);
            }
            delete_blob_files(&blobs, doomed, &mut report)?;
            Ok(report)
        })
        .await
    }

    /// Waits until versions deleted by `keep_versions` have left blobs for
    /// [`Store::collect_pruned`].
    pub async fn pruned_waiting(&self) {
        self.inner.pruned_ready.notified().await;
    }

    /// Deletes the blob files of versions that `keep_versions` deleted, without waiting for
    /// `gc_grace`, unless a record names them (the same positions sent again as a later
    /// version, or uploaded as a scene). Holds the GC gate exclusively, as [`Store::gc`]
    /// does, so no record can commit naming one of them meanwhile. A caller that stored
    /// the same bytes and has not yet committed its record finds the blob gone
    /// (`NotFound { what: "blob" }`) and stores it again: the bytes are never lost.
    ///
    /// With `wait` false it does nothing (and keeps the blobs for the next call) unless it
    /// can take the gate at once: waiting for it would hold up every upload and record
    /// behind a large blob being written.
    pub async fn collect_pruned(&self, wait: bool) -> Result<GcReport> {
        let mut report = GcReport::default();
        if self.pruned().is_empty() {
            return Ok(report);
        }
        let _gate = if wait {
            self.inner.gc_gate.write().await
        } else {
            match self.inner.gc_gate.try_write() {
                Ok(gate) => gate,
                Err(_) => return Ok(report),
            }
        };
        let doomed = std::mem::take(&mut *self.pruned());
        let running_since = self.running_since().await?;
        let mut unreferenced = Vec::new();
        let jobs_from = doomed.versions.len();
        for (k, id) in doomed.versions.into_iter().chain(doomed.jobs).enumerate() {
            let named: bool = sqlx::query_scalar(
                "SELECT EXISTS (SELECT 1 FROM scene_versions WHERE blob = ?1) \
                 OR EXISTS (SELECT 1 FROM jobs WHERE result_blob = ?1 OR input_blob = ?1) \
                 OR EXISTS (SELECT 1 FROM job_results WHERE blob = ?1)",
            )
            .bind(id.as_str())
            .fetch_one(&self.inner.reader)
            .await?;
            if named {
                report.referenced += 1;
            } else {
                unreferenced.push((id, k >= jobs_from));
            }
        }
        let blobs = Arc::clone(&self.inner.blobs);
        let (report, kept) = blocking(&self.inner.dir, move || {
            // A deleted job's bytes that a running job stored again (renewing the file)
            // are that job's results, named only when it ends: kept, as GC keeps them, and
            // tried again next time. (A version's bytes are never a result: positions
            // files and images have different magic numbers.)
            let (kept, gone): (Vec<_>, Vec<_>) =
                unreferenced.into_iter().partition(|(id, of_job)| {
                    *of_job
                        && running_since.is_some_and(|since| {
                            std::fs::metadata(blobs.path(id))
                                .and_then(|m| m.modified())
                                .is_ok_and(|modified| modified >= since)
                        })
                });
            let kept: Vec<BlobId> = kept.into_iter().map(|(id, _)| id).collect();
            let gone = gone.into_iter().map(|(id, _)| id).collect();
            report.kept_recent += kept.len() as u64;
            delete_blob_files(&blobs, gone, &mut report)?;
            Ok((report, kept))
        })
        .await?;
        if !kept.is_empty() {
            self.pruned().jobs.extend(kept);
        }
        Ok(report)
    }

    /// When the longest-running job started, less a second's slack for file times coarser
    /// than the clock's: blobs written or renewed since may be a running job's results,
    /// which its record names only when it ends. `None` when no job runs.
    async fn running_since(&self) -> Result<Option<SystemTime>> {
        let oldest_running: Option<Millis> =
            sqlx::query_scalar("SELECT MIN(started_at) FROM jobs WHERE state = 'running'")
                .fetch_one(&self.inner.reader)
                .await?;
        Ok(oldest_running.map(|ms| {
            SystemTime::UNIX_EPOCH + std::time::Duration::from_millis(ms.max(0) as u64)
                - std::time::Duration::from_secs(1)
        }))
    }

    /// Writes a consistent copy of the store to `dest` (a new or empty directory) while the
    /// store stays in use: the database through SQLite's `VACUUM INTO` (one read snapshot),
    /// then every blob that snapshot names, verified while copied. `dest` then opens as a
    /// store. GC waits while a backup runs, so no blob of the snapshot vanishes mid-copy.
    pub async fn backup(&self, dest: impl AsRef<Path>) -> Result<BackupReport> {
        let _gate = self.inner.gc_gate.read().await;
        let mut conn = self.inner.reader.acquire().await?;
        backup_into(
            &mut conn,
            &self.inner.blobs.root,
            &self.inner.dir,
            dest.as_ref(),
        )
        .await
    }

    /// Backs up the store in `dir` from outside it, for `rayd backup`: through
    /// [`Store::open`] and [`Store::backup`] when no process holds the store; else beside
    /// the process that does, through a read-only connection (SQLite lets another process
    /// read a WAL database). In that case that process's GC is not held off: if it
    /// collects a blob the snapshot names during the copy (the blob became unreferenced
    /// after the snapshot and is older than its grace period, or is a result's or an
    /// upload's), the backup fails with
    /// `NotFound` and can simply be run again.
    pub async fn backup_dir(dir: impl AsRef<Path>, dest: impl AsRef<Path>) -> Result<BackupReport> {
        let dir = dir.as_ref();
        if !dir.join(DB_FILE).is_file() {
            return Err(StoreError::not_found(
                "store",
                dir.join(DB_FILE).display().to_string(),
            ));
        }
        match Store::open(dir, super::StoreOptions::default()).await {
            Ok(store) => {
                let report = store.backup(dest).await;
                store.close().await;
                report
            }
            Err(StoreError::Locked { .. }) => {
                let mut conn = SqliteConnection::connect_with(
                    &SqliteConnectOptions::new()
                        .filename(dir.join(DB_FILE))
                        .read_only(true),
                )
                .await?;
                let report = backup_into(&mut conn, &dir.join("blobs"), dir, dest.as_ref()).await;
                conn.close().await?;
                report
            }
            Err(e) => Err(e),
        }
    }
}

/// Times a backup beside a live server starts again from a new snapshot when the server
/// deleted a scene's newest version (with its file) before the copy came to it.
const BACKUP_ATTEMPTS: usize = 3;

/// The work of a backup, from a connection to the source database and its blobs. The
/// copy is made in a staging directory beside `dest` and renamed to it only when whole:
/// a backup that fails or is killed leaves no `dest` that opens as a store with files
/// missing, and can be run again into the same `dest` (a leftover staging directory of
/// a killed one is named `.DEST.rayd-backup-PID.tmp`).
async fn backup_into(
    conn: &mut SqliteConnection,
    blobs_root: &Path,
    dir: &Path,
    dest: &Path,
) -> Result<BackupReport> {
    let dest = dest.to_path_buf();
    let dest_exists = match std::fs::read_dir(&dest) {
        Ok(mut entries) => {
            if entries.next().is_some() {
                return Err(StoreError::invalid(
                    "backup destination",
                    format!("{} exists and is not empty", dest.display()),
                ));
            }
            true
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => false,
        Err(e) => return Err(StoreError::io(&dest, e)),
    };
    let name = dest.file_name().ok_or_else(|| {
        StoreError::invalid(
            "backup destination",
            format!("{} names no directory", dest.display()),
        )
    })?;
    let parent = match dest.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    // A copy inside the store would be copied by the next backup, and collected by nothing.
    if let (Ok(store), Ok(place)) = (dir.canonicalize(), parent.canonicalize()) {
        if place.starts_with(&store) {
            return Err(StoreError::invalid(
                "backup destination",
                format!(
                    "{} is inside the data directory {}",
                    dest.display(),
                    dir.display()
                ),
            ));
        }
    }
    let mut staged_name = std::ffi::OsString::from(".");
    staged_name.push(name);
    let prefix = format!("{}.rayd-backup-", staged_name.to_string_lossy());
    staged_name.push(format!(".rayd-backup-{}.tmp", std::process::id()));
    let staging = parent.join(staged_name);
    {
        let parent = parent.clone();
        blocking(dir, move || {
            remove_dead_stagings(&parent, &prefix);
            Ok(())
        })
        .await?;
    }
    let clear = |staging: &Path| {
        let staging = staging.to_path_buf();
        blocking(dir, move || remove_dir_if_any(&staging))
    };
    let mut attempt = 0;
    let report = loop {
        attempt += 1;
        clear(&staging).await?;
        match backup_once(conn, blobs_root, dir, &staging).await {
            Err(StoreError::MissingBlob { .. }) if attempt < BACKUP_ATTEMPTS => {}
            Err(e) => {
                let _ = clear(&staging).await;
                return Err(e);
            }
            Ok(report) => break report,
        }
    };
    let (s, d) = (staging.clone(), dest.clone());
    let placed = blocking(dir, move || {
        if dest_exists {
            std::fs::remove_dir(&d).map_err(|e| StoreError::io(&d, e))?;
        }
        std::fs::rename(&s, &d).map_err(|e| StoreError::io(&d, e))?;
        sync_dir(&parent)
    })
    .await;
    if placed.is_err() {
        let _ = clear(&staging).await;
    }
    placed.map(|()| report)
}

/// Removes the staging directories `PREFIX<pid>.tmp` in `parent` that backups killed
/// before their end left (their process is gone). Linux only: elsewhere they stay, to be
/// removed by hand.
fn remove_dead_stagings(parent: &Path, prefix: &str) {
    if !cfg!(target_os = "linux") {
        return;
    }
    let Ok(entries) = std::fs::read_dir(parent) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name();
        let Some(pid) = name
            .to_str()
            .and_then(|n| n.strip_prefix(prefix))
            .and_then(|n| n.strip_suffix(".tmp"))
            .and_then(|p| p.parse::<u32>().ok())
        else {
            continue;
        };
        let alive = Path::new("/proc").join(pid.to_string()).exists();
        if !alive && e.file_type().is_ok_and(|t| t.is_dir()) {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

/// Removes `dir` and all it holds, if it is there.
fn remove_dir_if_any(dir: &Path) -> Result<()> {
    match std::fs::remove_dir_all(dir) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(StoreError::io(dir, e)),
        _ => Ok(()),
    }
}

/// One attempt of [`backup_into`], into the new directory `dest`.
async fn backup_once(
    conn: &mut SqliteConnection,
    blobs_root: &Path,
    dir: &Path,
    dest: &Path,
) -> Result<BackupReport> {
    let dest = dest.to_path_buf();
    let db = dest.join(DB_FILE);
    let db_text = db.to_str().ok_or_else(|| {
        StoreError::invalid(
            "backup destination",
            format!("{} is not valid UTF-8", dest.display()),
        )
    })?;
    let blobs_dest = dest.join("blobs");
    {
        let b = blobs_dest.clone();
        blocking(dir, move || create_dir_durable(&b)).await?;
    }
    // SQLite-specific (PostgreSQL would use pg_dump or a base backup).
    sqlx::query("VACUUM INTO ?")
        .bind(db_text)
        .execute(&mut *conn)
        .await?;
    {
        let (db, dest) = (db.clone(), dest.clone());
        blocking(dir, move || {
            std::fs::File::open(&db)
                .and_then(|f| f.sync_all())
                .map_err(|e| StoreError::io(&db, e))?;
            sync_dir(&dest)
        })
        .await?;
    }
    let mut snapshot =
        SqliteConnection::connect_with(&SqliteConnectOptions::new().filename(&db).read_only(true))
            .await?;
    let ids: Vec<String> = sqlx::query(REFERENCED_BLOBS)
        .fetch_all(&mut snapshot)
        .await?
        .iter()
        .map(|r| r.try_get::<String, _>(0))
        .collect::<Result<_, _>>()?;
    snapshot.close().await?;
    let root = blobs_root.to_path_buf();
    let (mut report, missing) = blocking(dir, move || {
        // Only reads and copies: no `BlobDir::prepare`, which would remove the temporary
        // files of a live writer in another process.
        let source = BlobDir {
            root,
            quota: super::blob::Quota::new(None, 0),
        };
        let mut report = BackupReport::default();
        let mut missing = Vec::new();
        for id in ids {
            let id = BlobId::parse(&id).ok_or_else(|| StoreError::Corrupt {
                blob: id.clone(),
                detail: "a record names a blob id that is not 64 hex digits".into(),
            })?;
            match source.copy_verified_to(&id, &blobs_dest) {
                Ok(bytes) => {
                    report.bytes += bytes;
                    report.blobs += 1;
                }
                Err(StoreError::NotFound { .. }) => missing.push(id),
                Err(e) => return Err(e),
            }
        }
        Ok((report, missing))
    })
    .await?;
    if !missing.is_empty() {
        report.dropped_versions = drop_pruned_versions(&db, &missing).await?;
        blocking(dir, move || {
            std::fs::File::open(&db)
                .and_then(|f| f.sync_all())
                .map_err(|e| StoreError::io(&db, e))
        })
        .await?;
    }
    Ok(report)
}

/// Deletes the files of `ids` (the caller holds the GC gate exclusively and has checked
/// that no record names them), counts them in `report`, then makes each touched shard
/// directory durable once.
fn delete_blob_files(blobs: &BlobDir, ids: Vec<BlobId>, report: &mut GcReport) -> Result<()> {
    let mut touched = HashSet::new();
    for id in ids {
        let path = blobs.path(&id);
        let freed = blobs.delete(&id)?;
        if freed > 0 {
            report.deleted += 1;
            report.freed_bytes += freed;
            touched.insert(path.parent().map(Path::to_path_buf));
        }
    }
    for dir in touched.into_iter().flatten() {
        sync_dir(&dir)?;
    }
    Ok(())
}

/// In a backup's copied database, deletes the versions whose blobs were gone when the
/// copy came to them (`missing`): allowed only when every record naming such a blob is a
/// version from 2 on, not its scene's newest, that no job names, which is what
/// `keep_versions` deletes in a running server; anything else missing is `MissingBlob`,
/// naming what needs it.
/// Returns how many versions went.
async fn drop_pruned_versions(db: &Path, missing: &[BlobId]) -> Result<u64> {
    let mut conn =
        SqliteConnection::connect_with(&SqliteConnectOptions::new().filename(db)).await?;
    let mut dropped = 0;
    for id in missing {
        // Named by anything but a version `keep_versions` may delete, or by a scene's
        // newest version (the copy would report a version it does not hold, so the backup
        // starts again from a newer snapshot).
        let needed: bool = sqlx::query_scalar(
            "SELECT EXISTS (SELECT 1 FROM scene_versions WHERE blob = ?1 AND (version = 1 \
             OR EXISTS (SELECT 1 FROM jobs WHERE jobs.scene_id = scene_versions.scene_id \
             AND jobs.version = scene_versions.version))) \
             OR EXISTS (SELECT 1 FROM scene_versions v JOIN scenes s \
             ON s.id = v.scene_id AND s.latest_version = v.version WHERE v.blob = ?1) \
             OR EXISTS (SELECT 1 FROM jobs WHERE result_blob = ?1 OR input_blob = ?1) \
             OR EXISTS (SELECT 1 FROM job_results WHERE blob = ?1)",
        )
        .bind(id.as_str())
        .fetch_one(&mut conn)
        .await?;
        if needed {
            // Say what needs it, so that whoever mends the store knows what it would lose.
            let names: Vec<String> = sqlx::query_scalar(
                "SELECT 'version ' || version || ' of scene ' || scene_id FROM scene_versions \
                 WHERE blob = ?1 \
                 UNION ALL SELECT 'job ' || id FROM jobs WHERE result_blob = ?1 OR input_blob = ?1 \
                 UNION ALL SELECT 'frame ' || frame || ' of job ' || job_id FROM job_results \
                 WHERE blob = ?1 LIMIT 4",
            )
            .bind(id.as_str())
            .fetch_all(&mut conn)
            .await?;
            let needed_by = match names.len() {
                0 => "a record".to_string(),
                1..=3 => names.join(", "),
                _ => format!("{} and more", names[..3].join(", ")),
            };
            return Err(StoreError::MissingBlob {
                blob: id.as_str().to_string(),
                needed_by,
            });
        }
        dropped += sqlx::query("DELETE FROM scene_versions WHERE blob = ?")
            .bind(id.as_str())
            .execute(&mut conn)
            .await?
            .rows_affected();
    }
    conn.close().await?;
    Ok(dropped)
}
