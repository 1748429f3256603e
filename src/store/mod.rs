//! The embedded store: everything `rayd serve` keeps across restarts, under one data directory.
//!
//! Bytes (uploads, results) are content-addressed blob files; records (scenes, versions, jobs)
//! live in SQLite, reached through sqlx. The store knows nothing of HTTP or ray tracing. The
//! layout, schema and crash guarantees are written down in `proto/store.md`; in short:
//!
//! - a record that names a blob is committed only after the blob is durable, and each state
//!   change is one transaction, so a crash at any moment leaves no half-written record;
//! - a blob without a record is garbage, collected by [`Store::gc`];
//! - [`Store::open`] locks the directory (flock), so one process owns it at a time.
//!
//! The API is async (tokio); file I/O and hashing run on the blocking pool.

mod blob;
mod callbacks;
mod error;
mod jobs;
mod maint;
mod records;
mod scenes;
#[cfg(test)]
mod tests;

use std::fs::File;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use sqlx::migrate::{Migration, MigrationType, Migrator};
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use sqlx::{SqlStr, SqlitePool};
use tokio::sync::RwLock;

pub use blob::BlobId;
pub use callbacks::{CallbackRecord, CallbackState};
pub use error::{Result, StoreError};
pub use maint::{BackupReport, GcReport};
pub use records::{
    now_millis, JobKind, JobOutcome, JobRecord, JobState, Millis, NewJob, ResultBlob, SceneRecord,
    VersionRecord, DEFAULT_PAGE_SIZE, MAX_PAGE_SIZE,
};
pub use scenes::NewScene;

use blob::{BlobDir, SyncBlobWriter};

/// The database file inside the data directory (with its `-wal` and `-shm` companions).
pub const DB_FILE: &str = "rayd.db";
/// The lock file inside the data directory.
pub const LOCK_FILE: &str = "lock";

/// How the store behaves; `StoreOptions::default()` is what `rayd serve` uses.
#[derive(Clone, Debug, PartialEq)]
pub struct StoreOptions {
    /// How long a finished job (and its results) is kept; `None` keeps it until deleted.
    pub result_ttl: Option<Duration>,
    /// How old an unreferenced blob must be before [`Store::gc`] deletes it. This is the
    /// time a caller has between storing a blob and committing the record that names it.
    pub gc_grace: Duration,
    /// The most bytes blob files may take; writes beyond it fail with
    /// [`StoreError::Full`], as a full disk would. `None`: only the disk limits.
    pub max_bytes: Option<u64>,
    /// The most bytes the database may grow to (SQLite's `max_page_count`); beyond it,
    /// statements fail with [`StoreError::Full`]. `None`: only the disk limits.
    pub max_db_bytes: Option<u64>,
    /// How long a statement waits for a lock inside SQLite before failing.
    pub busy_timeout: Duration,
    /// How many of a scene's newest versions (the latest included) are kept besides
    /// version 1 and the versions a job names; older ones are deleted as newer ones
    /// arrive, and their blobs go at the next [`Store::collect_pruned`]. A client that sends new
    /// positions every frame would otherwise fill the disk. `None` keeps every version.
    pub keep_versions: Option<u32>,
}

impl Default for StoreOptions {
    fn default() -> Self {
        StoreOptions {
            result_ttl: Some(Duration::from_secs(7 * 24 * 3600)),
            gc_grace: Duration::from_secs(15 * 60),
            max_bytes: None,
            max_db_bytes: None,
            busy_timeout: Duration::from_secs(5),
            keep_versions: None,
        }
    }
}

/// The schema's migrations, embedded in the binary. Applied in order at open and recorded
/// (with a checksum) in `_sqlx_migrations`; a database that records a migration this binary
/// does not know is refused, and an edited migration is refused by its checksum.
fn migrator() -> Migrator {
    Migrator::with_migrations(vec![
        Migration::new(
            1,
            "initial schema".into(),
            MigrationType::Simple,
            SqlStr::from_static(include_str!("migrations/0001_initial.sql")),
            false,
        ),
        Migration::new(
            2,
            "callback deliveries".into(),
            MigrationType::Simple,
            SqlStr::from_static(include_str!("migrations/0002_callbacks.sql")),
            false,
        ),
        Migration::new(
            3,
            "job input blobs".into(),
            MigrationType::Simple,
            SqlStr::from_static(include_str!("migrations/0003_job_inputs.sql")),
            false,
        ),
    ])
}

/// A handle on an open store. Cheap to clone: clones share one database pool, one lock and
/// one GC gate.
#[derive(Clone, Debug)]
pub struct Store {
    inner: Arc<Inner>,
}

#[derive(Debug)]
struct Inner {
    dir: PathBuf,
    options: StoreOptions,
    blobs: Arc<BlobDir>,
    /// One connection: SQLite has one writer anyway, and a single connection means write
    /// transactions never fail on a lock upgrade; they queue here instead.
    writer: SqlitePool,
    /// Readers, which WAL lets run beside the writer.
    reader: SqlitePool,
    /// Held shared by every operation that stores a blob or commits a record naming one,
    /// and exclusively by GC while it decides and deletes: so GC never deletes a blob that
    /// a concurrent upload has just renewed or a record has just referenced.
    gc_gate: RwLock<()>,
    /// Blobs of deleted versions and jobs, for [`Store::collect_pruned`] to delete at once
    /// rather than after `gc_grace` (a client sending a version a frame would otherwise
    /// keep 15 minutes of frames on disk, and deleted results would fill
    /// `--max-store-bytes`).
    pruned: std::sync::Mutex<scenes::Pruned>,
    /// Woken when `pruned` gains blobs.
    pruned_ready: tokio::sync::Notify,
    /// The flocks on `DIR/lock` and on `DIR` itself ([`take_lock`]); released when the last
    /// clone drops (or the process dies).
    _lock: (File, Option<File>),
}

impl Store {
    /// Opens (creating if needed) the store in `dir`: takes the lock, removes temporary
    /// files a crash left behind, and brings the schema up to date.
    ///
    /// A second open of the same directory, from this process or another, fails with
    /// [`StoreError::Locked`] until the first store is dropped.
    pub async fn open(dir: impl AsRef<Path>, options: StoreOptions) -> Result<Store> {
        let dir = dir.as_ref().to_path_buf();
        let lock = {
            let dir = dir.clone();
            blocking(&dir.clone(), move || take_lock(&dir)).await?
        };
        let no_database = !dir.join(DB_FILE).exists();
        let blobs = {
            let root = dir.join("blobs");
            let max = options.max_bytes;
            Arc::new(blocking(&dir, move || BlobDir::prepare(root, max)).await?)
        };
        // Stored files without the database that names them (a restore that copied only
        // `blobs/`, a database deleted by hand): opened as an empty store, GC would delete
        // every file once its grace passed. Refused, so that they can still be mended.
        if no_database {
            let b = Arc::clone(&blobs);
            if blocking(&dir, move || b.holds_any()).await? {
                return Err(StoreError::invalid(
                    "data directory",
                    format!(
                        "{} has stored files in blobs/ but no {DB_FILE}, the database that \
                         names them: put back the {DB_FILE} they belong to (a backup's), or \
                         move blobs/ away to start an empty store",
                        dir.display()
                    ),
                ));
            }
        }
        let mut connect = SqliteConnectOptions::new()
            .filename(dir.join(DB_FILE))
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(SqliteSynchronous::Full)
            .foreign_keys(true)
            .busy_timeout(options.busy_timeout);
        if let Some(max) = options.max_db_bytes {
            // The default page size is 4096; the database can never shrink below what it
            // holds, so a limit under its current size only stops growth.
            connect = connect.pragma("max_page_count", (max / 4096).max(1).to_string());
        }
        let writer = SqlitePoolOptions::new()
            .max_connections(1)
            .connect_with(connect.clone())
            .await?;
        migrator().run(&writer).await?;
        let reader = SqlitePoolOptions::new()
            .max_connections(4)
            .connect_with(connect)
            .await?;
        Ok(Store {
            inner: Arc::new(Inner {
                dir,
                options,
                blobs,
                writer,
                reader,
                gc_gate: RwLock::new(()),
                pruned: std::sync::Mutex::new(scenes::Pruned::default()),
                pruned_ready: tokio::sync::Notify::new(),
                _lock: lock,
            }),
        })
    }

    /// Closes the database connections cleanly (checkpointing the WAL). Dropping every clone
    /// also releases the store; this only lets the caller wait for it.
    pub async fn close(self) {
        self.inner.writer.close().await;
        self.inner.reader.close().await;
    }

    /// The data directory.
    pub fn dir(&self) -> &Path {
        &self.inner.dir
    }

    /// The options it was opened with.
    pub fn options(&self) -> &StoreOptions {
        &self.inner.options
    }

    /// The bytes blob files occupy, as counted for `max_bytes`; `None` without a quota
    /// (then nothing is counted, so that open need not visit every blob).
    pub fn blob_bytes(&self) -> Option<u64> {
        self.inner
            .options
            .max_bytes
            .map(|_| self.inner.blobs.quota.used())
    }

    /// Stores bytes as a blob and returns its id. Storing the same bytes twice keeps one
    /// file. The blob is durable when this returns; name it in a record within
    /// `gc_grace`, or GC may collect it. Bytes that are also a version's being deleted by
    /// `keep_versions` may be collected sooner ([`Store::collect_pruned`]): recording them
    /// then fails with `NotFound { what: "blob" }`, and storing them again mends it.
    pub async fn put_blob(&self, bytes: impl AsRef<[u8]> + Send + 'static) -> Result<BlobId> {
        let _gate = self.inner.gc_gate.read().await;
        let blobs = Arc::clone(&self.inner.blobs);
        blocking(&self.inner.dir, move || {
            let bytes = bytes.as_ref();
            let id = BlobId::of(bytes);
            blobs.put_bytes(&id, bytes)?;
            Ok(id)
        })
        .await
    }

    /// Stores a file's bytes as a blob, streaming (the file is copied, not moved, so it may
    /// live anywhere and is left in place).
    pub async fn put_blob_file(&self, path: impl AsRef<Path>) -> Result<BlobId> {
        let path = path.as_ref().to_path_buf();
        let mut writer = self.blob_writer().await?;
        let mut file = tokio::fs::File::open(&path)
            .await
            .map_err(|e| StoreError::io(&path, e))?;
        let mut buf = vec![0u8; 1 << 20];
        loop {
            let n = tokio::io::AsyncReadExt::read(&mut file, &mut buf)
                .await
                .map_err(|e| StoreError::io(&path, e))?;
            if n == 0 {
                break;
            }
            writer.write(&buf[..n]).await?;
        }
        writer.commit().await
    }

    /// Starts a streamed blob write: bytes are hashed while they are written to a temporary
    /// file, and [`BlobWriter::commit`] renames it to its hash. Dropping the writer without
    /// committing removes the temporary file.
    pub async fn blob_writer(&self) -> Result<BlobWriter> {
        let blobs = Arc::clone(&self.inner.blobs);
        let w = blocking(&self.inner.dir, move || blobs.writer()).await?;
        Ok(BlobWriter {
            store: self.clone(),
            inner: Some(w),
        })
    }

    /// A blob's bytes, verified against its id. A mismatch is [`StoreError::Corrupt`].
    pub async fn get_blob(&self, id: &str) -> Result<Vec<u8>> {
        let id = BlobId::parse_or_not_found(id, "blob")?;
        let blobs = Arc::clone(&self.inner.blobs);
        let i = id.clone();
        let r = blocking(&self.inner.dir, move || blobs.read_verified(&i)).await;
        self.quarantine_if_corrupt(&id, r).await
    }

    /// A blob opened for streaming, after verifying all of it (so a corrupt blob is never
    /// served, not even in part). The handle is at offset 0.
    pub async fn open_blob(&self, id: &str) -> Result<tokio::fs::File> {
        let id = BlobId::parse_or_not_found(id, "blob")?;
        let blobs = Arc::clone(&self.inner.blobs);
        let i = id.clone();
        let r = blocking(&self.inner.dir, move || blobs.open_verified(&i)).await;
        self.quarantine_if_corrupt(&id, r)
            .await
            .map(tokio::fs::File::from_std)
    }

    /// Where a blob's file is, if it exists; not verified (use [`Store::open_blob`] to serve
    /// it). The path stays valid while a record names the blob.
    pub async fn blob_path(&self, id: &str) -> Result<PathBuf> {
        let id = BlobId::parse_or_not_found(id, "blob")?;
        let path = self.inner.blobs.path(&id);
        match tokio::fs::metadata(&path).await {
            Ok(_) => Ok(path),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                Err(StoreError::not_found("blob", id.as_str()))
            }
            Err(e) => Err(StoreError::io(&path, e)),
        }
    }

    /// On a hash mismatch, moves the bad file aside (under the GC gate, after hashing it
    /// again, so a good copy written meanwhile is kept) and passes the error on.
    async fn quarantine_if_corrupt<T>(&self, id: &BlobId, r: Result<T>) -> Result<T> {
        if let Err(StoreError::Corrupt { .. }) = &r {
            let _gate = self.inner.gc_gate.write().await;
            let blobs = Arc::clone(&self.inner.blobs);
            let id = id.clone();
            blocking(&self.inner.dir, move || blobs.quarantine(&id)).await?;
        }
        r
    }

    /// Checks, for a record about to name them, that blobs exist. Call with the GC gate
    /// held shared, so none can vanish before the record commits.
    async fn require_blobs(&self, ids: Vec<BlobId>) -> Result<()> {
        let blobs = Arc::clone(&self.inner.blobs);
        blocking(&self.inner.dir, move || {
            for id in &ids {
                let path = blobs.path(id);
                match std::fs::metadata(&path) {
                    Ok(_) => {}
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                        return Err(StoreError::not_found("blob", id.as_str()))
                    }
                    Err(e) => return Err(StoreError::io(&path, e)),
                }
            }
            Ok(())
        })
        .await
    }
}

/// A streamed blob write; see [`Store::blob_writer`].
#[derive(Debug)]
pub struct BlobWriter {
    store: Store,
    inner: Option<SyncBlobWriter>,
}

impl BlobWriter {
    /// Appends bytes. After an error the writer is spent: its temporary file is gone and
    /// further calls fail.
    pub async fn write(&mut self, data: &[u8]) -> Result<()> {
        let mut w = self.inner.take().ok_or_else(spent)?;
        let data = data.to_vec();
        let (w, r) = blocking(&self.store.inner.dir, move || {
            let r = w.write(&data);
            Ok((w, r))
        })
        .await?;
        match r {
            Ok(()) => {
                self.inner = Some(w);
                Ok(())
            }
            Err(e) => {
                w.abort();
                Err(e)
            }
        }
    }

    /// Makes the blob durable under its hash and returns the id.
    pub async fn commit(mut self) -> Result<BlobId> {
        let w = self.inner.take().ok_or_else(spent)?;
        let _gate = self.store.inner.gc_gate.read().await;
        blocking(&self.store.inner.dir, move || w.commit()).await
    }

    /// The bytes written so far.
    pub fn len(&self) -> u64 {
        self.inner.as_ref().map_or(0, |w| w.len())
    }

    /// Whether nothing was written yet.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

impl Drop for BlobWriter {
    fn drop(&mut self) {
        if let Some(w) = self.inner.take() {
            w.abort();
        }
    }
}

fn spent() -> StoreError {
    StoreError::Conflict("this blob writer failed or finished; start a new one".into())
}

/// Runs blocking file work on tokio's blocking pool.
async fn blocking<T, F>(dir: &Path, f: F) -> Result<T>
where
    F: FnOnce() -> Result<T> + Send + 'static,
    T: Send + 'static,
{
    tokio::task::spawn_blocking(f)
        .await
        .map_err(|e| StoreError::Io {
            path: dir.to_path_buf(),
            source: std::io::Error::other(format!("blocking store task failed: {e}")),
        })?
}

/// Creates the data directory if needed and takes the exclusive flocks on `DIR` (where the
/// file system can lock a directory) and on `DIR/lock`.
fn take_lock(dir: &Path) -> Result<(File, Option<File>)> {
    blob::create_dir_durable(dir)?;
    // The directory itself is locked as well: a lock file can be unlinked while held (a
    // hand's `rm DIR/lock`), and a second server would then lock a new one and write the
    // same store; the directory cannot be replaced under a server. Where a file system
    // cannot lock a directory, the lock file alone guards it.
    let held_dir = match File::open(dir) {
        Ok(d) => match fs4::FileExt::try_lock(&d) {
            Ok(()) => Some(d),
            Err(fs4::TryLockError::WouldBlock) => {
                return Err(StoreError::Locked {
                    dir: dir.to_path_buf(),
                })
            }
            Err(fs4::TryLockError::Error(_)) => None,
        },
        Err(_) => None,
    };
    let path = dir.join(LOCK_FILE);
    let file = File::options()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .map_err(|e| StoreError::io(&path, e))?;
    match fs4::FileExt::try_lock(&file) {
        Ok(()) => Ok((file, held_dir)),
        Err(fs4::TryLockError::WouldBlock) => Err(StoreError::Locked {
            dir: dir.to_path_buf(),
        }),
        Err(fs4::TryLockError::Error(e)) => Err(StoreError::io(&path, e)),
    }
}
