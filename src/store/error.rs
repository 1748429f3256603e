//! The store's one error type.
//!
//! Every failure the store can report is a [`StoreError`]. The variants are chosen so the
//! layers above can map them without string matching: `NotFound` becomes 404, `Conflict` 409,
//! `Full` 507/503, `Invalid` 400/422, and the rest are internal errors worth logging.

use std::io;
use std::path::{Path, PathBuf};

/// What went wrong in the store.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// An id names nothing (or is malformed: ids that could never exist name nothing too).
    #[error("{what} {id:?} not found")]
    NotFound {
        /// The kind of thing: "scene", "version", "job" or "blob".
        what: &'static str,
        /// The id as given.
        id: String,
    },
    /// Another store (in this process or another) holds the data directory's lock.
    #[error("data directory {dir} is in use: another store holds {dir}/lock")]
    Locked {
        /// The data directory.
        dir: PathBuf,
    },
    /// A blob's bytes no longer hash to its id. The bytes are never served; the bad file is
    /// moved to `quarantine/` so that uploading the same bytes again repairs it.
    #[error("blob {blob} is corrupt: {detail}")]
    Corrupt {
        /// The blob id (the hash its content should have).
        blob: String,
        /// What was found instead.
        detail: String,
    },
    /// A blob that records need is not in the blob directory: a backup found it gone, and
    /// it was not one a running server's pruning may delete.
    #[error("blob {blob} is missing from the store's blobs; {needed_by} needs it")]
    MissingBlob {
        /// The blob id.
        blob: String,
        /// What names it: the scene and version, the job, or the job's frame.
        needed_by: String,
    },
    /// The disk (or the configured quota) is full. Nothing was half-written; the store works
    /// again once space is freed.
    #[error("no space left writing {path}: {detail}")]
    Full {
        /// The file or database being written.
        path: PathBuf,
        /// The underlying reason (ENOSPC, EDQUOT, the quota, SQLITE_FULL).
        detail: String,
    },
    /// A file-system operation failed.
    #[error("I/O error on {path}: {source}")]
    Io {
        /// The path involved.
        path: PathBuf,
        /// The error.
        #[source]
        source: io::Error,
    },
    /// The database refused or failed a statement.
    #[error("database error: {0}")]
    Db(#[source] sqlx::Error),
    /// The schema could not be brought up to date (for example: the database was written by
    /// a newer rayd whose migrations this binary does not know).
    #[error("schema migration failed: {0}")]
    Migrate(#[from] sqlx::migrate::MigrateError),
    /// A page token that this store did not hand out (or one for another list).
    #[error("bad page token: not one this list handed out")]
    BadPageToken,
    /// The request contradicts the record's state (e.g. finishing a job that is not running,
    /// or reusing an idempotency key for a different request).
    #[error("conflict: {0}")]
    Conflict(String),
    /// A caller-supplied value is out of range or malformed.
    #[error("invalid {field}: {reason}")]
    Invalid {
        /// The field.
        field: &'static str,
        /// Why it was refused.
        reason: String,
    },
}

/// The store's result type.
pub type Result<T, E = StoreError> = std::result::Result<T, E>;

impl StoreError {
    /// Wraps an I/O error with its path, turning "disk full" and "quota exceeded" into
    /// [`StoreError::Full`] so callers can tell "try later" from "broken".
    pub(crate) fn io(path: &Path, source: io::Error) -> Self {
        if is_full(&source) {
            StoreError::Full {
                path: path.to_path_buf(),
                detail: source.to_string(),
            }
        } else {
            StoreError::Io {
                path: path.to_path_buf(),
                source,
            }
        }
    }

    pub(crate) fn not_found(what: &'static str, id: impl Into<String>) -> Self {
        StoreError::NotFound {
            what,
            id: id.into(),
        }
    }

    pub(crate) fn invalid(field: &'static str, reason: impl Into<String>) -> Self {
        StoreError::Invalid {
            field,
            reason: reason.into(),
        }
    }
}

/// ENOSPC and EDQUOT, whichever way the OS reports them.
fn is_full(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::StorageFull | io::ErrorKind::QuotaExceeded
    )
}

/// SQLite's primary result code for "database or disk is full".
const SQLITE_FULL: i64 = 13;

impl From<sqlx::Error> for StoreError {
    fn from(e: sqlx::Error) -> Self {
        if let sqlx::Error::Database(db) = &e {
            let code = db.code().and_then(|c| c.parse::<i64>().ok());
            if code.map(|c| c & 0xff) == Some(SQLITE_FULL) {
                return StoreError::Full {
                    path: PathBuf::from("rayd.db"),
                    detail: db.message().to_string(),
                };
            }
        }
        if let sqlx::Error::Io(io) = &e {
            if is_full(io) {
                return StoreError::Full {
                    path: PathBuf::from("rayd.db"),
                    detail: io.to_string(),
                };
            }
        }
        StoreError::Db(e)
    }
}
