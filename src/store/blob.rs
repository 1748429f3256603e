//! Content-addressed blob files: `blobs/ab/abcdef…`, named by the blake3 hash of their bytes.
//!
//! A blob is written to a temporary file beside its final place, synced, renamed into place
//! and its directory synced, so a crash leaves either the whole blob or no blob (plus perhaps
//! a temporary file, removed at the next open). Reading re-hashes; a mismatch is
//! [`StoreError::Corrupt`] and the file is moved aside, never served.
//!
//! Everything here is blocking file I/O; [`super::Store`] calls it from
//! `tokio::task::spawn_blocking`.

use std::fmt;
use std::fs::{self, File};
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::SystemTime;

use super::error::{Result, StoreError};

/// Length of a blob id: 32 bytes of blake3, in lowercase hex.
pub const BLOB_ID_LEN: usize = 64;

/// The id of a blob: the lowercase hex blake3 hash of its bytes. Scene ids are blob ids.
///
/// Only 64 lowercase hex digits parse, so an id can never carry a path separator or any
/// other text into a file name.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize)]
#[serde(transparent)]
pub struct BlobId(String);

impl BlobId {
    /// Parses an id; anything but 64 lowercase hex digits is `None`.
    pub fn parse(s: &str) -> Option<BlobId> {
        (s.len() == BLOB_ID_LEN && s.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f')))
            .then(|| BlobId(s.to_string()))
    }

    /// Parses an id or reports `what` (`"scene"`, `"blob"`) as not found, which is what a
    /// malformed id means to a client.
    pub(crate) fn parse_or_not_found(s: &str, what: &'static str) -> Result<BlobId> {
        BlobId::parse(s).ok_or_else(|| StoreError::not_found(what, s))
    }

    /// The id of these bytes.
    pub fn of(bytes: &[u8]) -> BlobId {
        BlobId::from_hash(blake3::hash(bytes))
    }

    fn from_hash(h: blake3::Hash) -> BlobId {
        BlobId(h.to_hex().to_string())
    }

    /// The hex text.
    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl fmt::Display for BlobId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

/// The bytes that blob files may occupy, when `StoreOptions::max_bytes` is set.
///
/// Bytes are reserved before they are written, so concurrent writers cannot overshoot
/// together, and released when a write fails, turns out to be a duplicate, or a blob is
/// collected. The database is not counted (it is small next to the blobs).
#[derive(Debug)]
pub(crate) struct Quota {
    max: Option<u64>,
    used: AtomicU64,
}

impl Quota {
    pub(crate) fn new(max: Option<u64>, used: u64) -> Quota {
        Quota {
            max,
            used: AtomicU64::new(used),
        }
    }

    /// Reserves `n` bytes for a write to `path`, or fails with `Full`.
    pub(crate) fn reserve(&self, n: u64, path: &Path) -> Result<()> {
        let Some(max) = self.max else {
            self.used.fetch_add(n, Ordering::Relaxed);
            return Ok(());
        };
        self.used
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |used| {
                used.checked_add(n).filter(|&total| total <= max)
            })
            .map(|_| ())
            .map_err(|used| StoreError::Full {
                path: path.to_path_buf(),
                detail: format!(
                    "the store's quota of {max} bytes is reached ({used} used, {n} more needed)"
                ),
            })
    }

    pub(crate) fn release(&self, n: u64) {
        // Saturating: a blob deleted by hand must not wrap the count around.
        let _ = self
            .used
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |u| {
                Some(u.saturating_sub(n))
            });
    }

    pub(crate) fn used(&self) -> u64 {
        self.used.load(Ordering::Acquire)
    }
}

/// Where the blob files live, and the quota they share.
#[derive(Debug)]
pub(crate) struct BlobDir {
    /// `DIR/blobs`.
    pub(crate) root: PathBuf,
    pub(crate) quota: Quota,
}

/// The prefix of every temporary file; nothing else in `blobs/` starts with it.
const TMP_PREFIX: &str = ".tmp";

impl BlobDir {
    /// `DIR/blobs/ab/abcdef…`.
    pub(crate) fn path(&self, id: &BlobId) -> PathBuf {
        self.root.join(&id.0[..2]).join(&id.0)
    }

    /// `DIR/blobs/tmp`, where streamed writes whose hash is not yet known are staged (on
    /// the same file system as their final place, so the rename is atomic).
    fn staging(&self) -> PathBuf {
        self.root.join("tmp")
    }

    /// Creates the directories, removes temporary files left by a crashed writer (safe: the
    /// caller holds the data directory's lock, so no writer is alive) and returns the bytes
    /// the blob files occupy (only counted when a quota needs it).
    pub(crate) fn prepare(root: PathBuf, max_bytes: Option<u64>) -> Result<BlobDir> {
        create_dir_durable(&root)?;
        let staging = root.join("tmp");
        create_dir_durable(&staging)?;
        let mut used = 0;
        for entry in read_dir(&root)? {
            let path = entry.path();
            let name = entry.file_name();
            let name = name.to_string_lossy();
            if name == "tmp" {
                // Only files are ours; anything else put there by hand is left alone.
                for tmp in read_dir(&path)? {
                    if tmp.file_type().is_ok_and(|t| !t.is_dir()) {
                        remove_file(&tmp.path())?;
                    }
                }
                continue;
            }
            if !is_shard_name(&name) || !path.is_dir() {
                continue;
            }
            for file in read_dir(&path)? {
                let fname = file.file_name();
                let fname = fname.to_string_lossy();
                if fname.starts_with(TMP_PREFIX) {
                    remove_file(&file.path())?;
                } else if max_bytes.is_some() && BlobId::parse(&fname).is_some() {
                    used += file
                        .metadata()
                        .map_err(|e| StoreError::io(&file.path(), e))?
                        .len();
                }
            }
        }
        Ok(BlobDir {
            root,
            quota: Quota::new(max_bytes, used),
        })
    }

    /// Whether any blob file is stored (a file named by a blob id in a shard directory).
    pub(crate) fn holds_any(&self) -> Result<bool> {
        for entry in read_dir(&self.root)? {
            let name = entry.file_name();
            if !is_shard_name(&name.to_string_lossy()) || !entry.path().is_dir() {
                continue;
            }
            for file in read_dir(&entry.path())? {
                if BlobId::parse(&file.file_name().to_string_lossy()).is_some() {
                    return Ok(true);
                }
            }
        }
        Ok(false)
    }

    /// Stores `bytes` (whose id the caller computed) durably. If the blob is already there
    /// with the right size, only its modification time is renewed: that is what protects a
    /// fresh upload from a concurrent GC (see [`super::Store::gc`]).
    pub(crate) fn put_bytes(&self, id: &BlobId, bytes: &[u8]) -> Result<()> {
        let dest = self.path(id);
        let existing = self.renew_existing(&dest, bytes.len() as u64)?;
        if existing == Existing::Renewed {
            return Ok(());
        }
        let shard = dest.parent().expect("a blob path has a shard directory");
        create_dir_durable(shard)?;
        let len = bytes.len() as u64;
        self.quota.reserve(len, &dest)?;
        let written = (|| {
            let mut tmp = tempfile::Builder::new()
                .prefix(TMP_PREFIX)
                .tempfile_in(shard)
                .map_err(|e| StoreError::io(shard, e))?;
            tmp.write_all(bytes)
                .and_then(|()| tmp.as_file().sync_all())
                .map_err(|e| StoreError::io(tmp.path(), e))?;
            self.install(tmp, &dest, existing)
        })();
        match written {
            Ok(true) => Ok(()),
            // A concurrent put of the same bytes got there first: its file is as good.
            Ok(false) => {
                self.quota.release(len);
                Ok(())
            }
            Err(e) => {
                self.quota.release(len);
                Err(e)
            }
        }
    }

    /// If `dest` exists with `len` bytes, renews its mtime. A file of another size is a
    /// damaged copy, to be replaced by the caller's write.
    fn renew_existing(&self, dest: &Path, len: u64) -> Result<Existing> {
        match fs::metadata(dest) {
            Ok(meta) if meta.len() == len => {
                let f = File::options()
                    .write(true)
                    .open(dest)
                    .map_err(|e| StoreError::io(dest, e))?;
                f.set_modified(SystemTime::now())
                    .map_err(|e| StoreError::io(dest, e))?;
                Ok(Existing::Renewed)
            }
            Ok(meta) => Ok(Existing::Damaged(meta.len())),
            Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(Existing::Absent),
            Err(e) => Err(StoreError::io(dest, e)),
        }
    }

    /// Renames a synced temporary file to `dest` and syncs the directory, so the new name
    /// survives a crash. Replaces a damaged copy; otherwise never overwrites, so two writers
    /// of the same new blob install one file (the loser gets `false`). On failure the
    /// temporary file is removed (by its drop).
    fn install(
        &self,
        tmp: tempfile::NamedTempFile,
        dest: &Path,
        existing: Existing,
    ) -> Result<bool> {
        let installed = match existing {
            Existing::Damaged(old) => {
                tmp.persist(dest)
                    .map_err(|e| StoreError::io(dest, e.error))?;
                self.quota.release(old);
                true
            }
            _ => match tmp.persist_noclobber(dest) {
                Ok(_) => true,
                Err(e) if e.error.kind() == io::ErrorKind::AlreadyExists => false,
                Err(e) => return Err(StoreError::io(dest, e.error)),
            },
        };
        sync_dir(dest.parent().expect("a blob path has a parent"))?;
        Ok(installed)
    }

    /// Reads and verifies a whole blob.
    pub(crate) fn read_verified(&self, id: &BlobId) -> Result<Vec<u8>> {
        let path = self.path(id);
        let bytes = match fs::read(&path) {
            Ok(b) => b,
            Err(e) if e.kind() == io::ErrorKind::NotFound => {
                return Err(StoreError::not_found("blob", id.as_str()))
            }
            Err(e) => return Err(StoreError::io(&path, e)),
        };
        let found = BlobId::of(&bytes);
        if &found != id {
            return Err(self.corrupt(id, &found, bytes.len() as u64));
        }
        Ok(bytes)
    }

    /// Opens a blob for streaming after hashing it whole: the returned handle is at offset 0
    /// and, blobs being immutable, reads exactly the verified bytes.
    pub(crate) fn open_verified(&self, id: &BlobId) -> Result<File> {
        let path = self.path(id);
        let mut file = match File::open(&path) {
            Ok(f) => f,
            Err(e) if e.kind() == io::ErrorKind::NotFound => {
                return Err(StoreError::not_found("blob", id.as_str()))
            }
            Err(e) => return Err(StoreError::io(&path, e)),
        };
        let mut hasher = blake3::Hasher::new();
        let len = io::copy(&mut file, &mut HashSink(&mut hasher))
            .map_err(|e| StoreError::io(&path, e))?;
        let found = BlobId::from_hash(hasher.finalize());
        if &found != id {
            return Err(self.corrupt(id, &found, len));
        }
        io::Seek::rewind(&mut file).map_err(|e| StoreError::io(&path, e))?;
        Ok(file)
    }

    /// The `Corrupt` error for a blob whose bytes hash to `found`.
    fn corrupt(&self, id: &BlobId, found: &BlobId, len: u64) -> StoreError {
        StoreError::Corrupt {
            blob: id.to_string(),
            detail: format!(
                "its {len} bytes at {} hash to {found}",
                self.path(id).display()
            ),
        }
    }

    /// Moves a blob file that fails its hash to `quarantine/` (beside `blobs/`), so it is
    /// never served and a new upload of the right bytes writes a good copy. It is hashed
    /// again first: a good copy written since the failed read is kept. The caller holds the
    /// GC gate exclusively, since this removes a name as GC does.
    pub(crate) fn quarantine(&self, id: &BlobId) -> Result<()> {
        match self.read_verified(id) {
            Err(StoreError::Corrupt { .. }) => {}
            // Good again, or gone: nothing to move.
            Ok(_) | Err(StoreError::NotFound { .. }) => return Ok(()),
            Err(e) => return Err(e),
        }
        let path = self.path(id);
        let len = fs::metadata(&path).map(|m| m.len()).unwrap_or(0);
        let quarantine = self
            .root
            .parent()
            .map(|d| d.join("quarantine"))
            .unwrap_or_else(|| self.root.join("quarantine"));
        create_dir_durable(&quarantine)?;
        let stamp = SystemTime::now()
            .duration_since(SystemTime::UNIX_EPOCH)
            .map(|d| d.as_millis())
            .unwrap_or(0);
        let dest = quarantine.join(format!("{id}.{stamp}"));
        fs::rename(&path, &dest).map_err(|e| StoreError::io(&path, e))?;
        self.quota.release(len);
        sync_dir(path.parent().expect("a blob path has a parent"))
    }

    /// Starts a streamed write.
    pub(crate) fn writer(self: &Arc<Self>) -> Result<SyncBlobWriter> {
        let staging = self.staging();
        let tmp = tempfile::Builder::new()
            .prefix(TMP_PREFIX)
            .tempfile_in(&staging)
            .map_err(|e| StoreError::io(&staging, e))?;
        Ok(SyncBlobWriter {
            dir: Arc::clone(self),
            tmp,
            hasher: blake3::Hasher::new(),
            len: 0,
        })
    }

    /// Deletes a blob file (GC); returns the bytes freed, 0 if it was already gone.
    pub(crate) fn delete(&self, id: &BlobId) -> Result<u64> {
        let path = self.path(id);
        let len = match fs::metadata(&path) {
            Ok(m) => m.len(),
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(0),
            Err(e) => return Err(StoreError::io(&path, e)),
        };
        match fs::remove_file(&path) {
            Ok(()) => {
                self.quota.release(len);
                Ok(len)
            }
            Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(0),
            Err(e) => Err(StoreError::io(&path, e)),
        }
    }

    /// Every blob file: its id and modification time.
    pub(crate) fn list(&self) -> Result<Vec<(BlobId, SystemTime)>> {
        let mut out = Vec::new();
        for entry in read_dir(&self.root)? {
            let name = entry.file_name();
            if !is_shard_name(&name.to_string_lossy()) {
                continue;
            }
            for file in read_dir(&entry.path())? {
                let Some(id) = BlobId::parse(&file.file_name().to_string_lossy()) else {
                    continue;
                };
                match file.metadata().and_then(|m| m.modified()) {
                    Ok(t) => out.push((id, t)),
                    Err(e) if e.kind() == io::ErrorKind::NotFound => {}
                    Err(e) => return Err(StoreError::io(&file.path(), e)),
                }
            }
        }
        Ok(out)
    }

    /// Copies a blob to `dest_root` (another store's `blobs/`), verifying while copying and
    /// writing atomically, for backups.
    pub(crate) fn copy_verified_to(&self, id: &BlobId, dest_root: &Path) -> Result<u64> {
        let src = self.path(id);
        let mut input = match File::open(&src) {
            Ok(f) => f,
            Err(e) if e.kind() == io::ErrorKind::NotFound => {
                return Err(StoreError::not_found("blob", id.as_str()))
            }
            Err(e) => return Err(StoreError::io(&src, e)),
        };
        let shard = dest_root.join(&id.0[..2]);
        create_dir_durable(&shard)?;
        let dest = shard.join(&id.0);
        let mut tmp = tempfile::Builder::new()
            .prefix(TMP_PREFIX)
            .tempfile_in(&shard)
            .map_err(|e| StoreError::io(&shard, e))?;
        let mut hasher = blake3::Hasher::new();
        let len = copy_hashing(&mut input, tmp.as_file_mut(), &mut hasher)
            .map_err(|e| StoreError::io(&dest, e))?;
        let found = BlobId::from_hash(hasher.finalize());
        if &found != id {
            return Err(self.corrupt(id, &found, len));
        }
        tmp.as_file()
            .sync_all()
            .map_err(|e| StoreError::io(&dest, e))?;
        tmp.persist(&dest)
            .map_err(|e| StoreError::io(&dest, e.error))?;
        sync_dir(&shard)?;
        Ok(len)
    }
}

/// What [`BlobDir::renew_existing`] found at a blob's place.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Existing {
    /// A file of the right size, whose mtime is now renewed.
    Renewed,
    /// A file of this other size: a damaged copy.
    Damaged(u64),
    /// Nothing.
    Absent,
}

/// A streamed blob write in progress (blocking half of [`super::BlobWriter`]).
#[derive(Debug)]
pub(crate) struct SyncBlobWriter {
    dir: Arc<BlobDir>,
    tmp: tempfile::NamedTempFile,
    hasher: blake3::Hasher,
    len: u64,
}

impl SyncBlobWriter {
    /// Appends bytes, hashing them on the way, within the quota.
    pub(crate) fn write(&mut self, data: &[u8]) -> Result<()> {
        self.dir.quota.reserve(data.len() as u64, self.tmp.path())?;
        if let Err(e) = self.tmp.write_all(data) {
            self.dir.quota.release(data.len() as u64);
            return Err(StoreError::io(self.tmp.path(), e));
        }
        self.hasher.update(data);
        self.len += data.len() as u64;
        Ok(())
    }

    /// Makes the blob durable under its hash; a duplicate of an existing blob is dropped.
    pub(crate) fn commit(self) -> Result<BlobId> {
        let SyncBlobWriter {
            dir,
            tmp,
            hasher,
            len,
        } = self;
        let id = BlobId::from_hash(hasher.finalize());
        let dest = dir.path(&id);
        let result = (|| {
            let existing = dir.renew_existing(&dest, len)?;
            if existing == Existing::Renewed {
                return Ok(false);
            }
            tmp.as_file()
                .sync_all()
                .map_err(|e| StoreError::io(tmp.path(), e))?;
            let shard = dest.parent().expect("a blob path has a shard directory");
            create_dir_durable(shard)?;
            dir.install(tmp, &dest, existing)
        })();
        match result {
            Ok(true) => Ok(id),
            // A duplicate: the bytes written leave the quota, the existing file stays.
            Ok(false) => {
                dir.quota.release(len);
                Ok(id)
            }
            Err(e) => {
                dir.quota.release(len);
                Err(e)
            }
        }
    }

    pub(crate) fn len(&self) -> u64 {
        self.len
    }

    /// Gives up: the temporary file is removed and its bytes leave the quota.
    pub(crate) fn abort(self) {
        self.dir.quota.release(self.len);
    }
}

/// `io::Write` into a hasher, to hash a reader with `io::copy`.
struct HashSink<'a>(&'a mut blake3::Hasher);

impl Write for HashSink<'_> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.0.update(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

/// Copies `input` to `out`, hashing the bytes; returns the length.
fn copy_hashing(input: &mut File, out: &mut File, hasher: &mut blake3::Hasher) -> io::Result<u64> {
    let mut buf = vec![0u8; 1 << 20];
    let mut len = 0;
    loop {
        let n = input.read(&mut buf)?;
        if n == 0 {
            return Ok(len);
        }
        hasher.update(&buf[..n]);
        out.write_all(&buf[..n])?;
        len += n as u64;
    }
}

fn is_shard_name(name: &str) -> bool {
    name.len() == 2 && name.bytes().all(|b| matches!(b, b'0'..=b'9' | b'a'..=b'f'))
}

fn read_dir(dir: &Path) -> Result<Vec<fs::DirEntry>> {
    fs::read_dir(dir)
        .and_then(|it| it.collect::<io::Result<Vec<_>>>())
        .map_err(|e| StoreError::io(dir, e))
}

fn remove_file(path: &Path) -> Result<()> {
    match fs::remove_file(path) {
        Err(e) if e.kind() != io::ErrorKind::NotFound => Err(StoreError::io(path, e)),
        _ => Ok(()),
    }
}

/// Syncs a directory, so that the names created in it survive a crash.
pub(crate) fn sync_dir(dir: &Path) -> Result<()> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(|e| StoreError::io(dir, e))
}

/// Creates a directory (and its parents) if missing; a new one is made durable by syncing
/// its parent.
pub(crate) fn create_dir_durable(dir: &Path) -> Result<()> {
    if dir.is_dir() {
        return Ok(());
    }
    fs::create_dir_all(dir).map_err(|e| StoreError::io(dir, e))?;
    match dir.parent() {
        Some(parent) if !parent.as_os_str().is_empty() => sync_dir(parent),
        _ => Ok(()),
    }
}
