//! The service's domain, between the HTTP handlers and the engine: scenes, their geometry
//! versions and jobs, kept in the [`Store`] and run by the [`Engine`].
//!
//! The handlers (`crate::service`) know HTTP and call this layer; this layer knows neither
//! HTTP nor how rays are traced (that is `crate::jobs` and the cores). Everything a client
//! was told has happened is in the store first: a `201` scene, a `202` job and a finished
//! result survive a crash, and a job that was queued or running when the process died is
//! queued again at the next start ([`App::recover`]).

mod callbacks;
mod jobs;
mod keys;
mod scenes;
mod spec;
mod thumbnails;

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex};

pub use callbacks::{CallbackFailure, CallbackSender, CallbackView, SendFuture};
pub use jobs::{JobEvents, JobView};
pub use scenes::{scene_info, SceneView, TraceIntake, TracePlace, Tri1Body, UploadKind};
pub use spec::{FramesSpec, RenderSpec, TraceParams};
pub use thumbnails::{Thumbnail, THUMBNAIL_HEIGHT, THUMBNAIL_PRIORITY, THUMBNAIL_WIDTH};

use crate::jobs::{Engine, JobError};
use crate::store::{Store, StoreError};

/// Errors of the domain layer, each with what the handlers need to pick a status code.
#[derive(Debug, thiserror::Error)]
pub enum AppError {
    /// The store failed or refused (not found, full, corrupt, …).
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The job engine refused or failed.
    #[error(transparent)]
    Job(#[from] JobError),
    /// An uploaded scene or geometry body does not load.
    #[error("{detail}")]
    BadUpload {
        /// What is wrong, with the place.
        detail: String,
        /// Byte offset of the problem, where known.
        byte_offset: Option<u64>,
    },
    /// A query parameter is malformed or names what is not there (400).
    #[error("{field}: {detail}")]
    BadParameter {
        /// The parameter.
        field: &'static str,
        /// What is wrong.
        detail: String,
    },
    /// A well-formed request that cannot be done (422): the wrong triangle count, a
    /// render option outside its range or against another option or the scene.
    #[error("{field}: {detail}")]
    Unprocessable {
        /// The field.
        field: &'static str,
        /// What is wrong.
        detail: String,
    },
    /// The job has not finished (409).
    #[error("job {0} has no result yet")]
    NotReady(String),
    /// The CPU work was lost (the pool went away).
    #[error("internal: {0}")]
    Internal(String),
    /// Work that lost a race it may win if tried again soon (503 with `Retry-After`).
    #[error("{0}")]
    Busy(String),
}

/// Hears about finished work, for monitoring: the service hands its metrics in here, so
/// the domain layer counts nothing itself and knows no metrics library.
pub trait Observer: Send + Sync {
    /// A job of `kind` (`render`, `trace`) ended in `state` after running `seconds`
    /// (from its first step to its end; 0 if it never ran).
    fn job_ended(&self, kind: &str, state: &str, seconds: f64);
    /// A trace job traced `rays` rays in `trace_seconds`.
    fn traced(&self, rays: u64, trace_seconds: f64);
}

/// How the domain layer behaves.
#[derive(Clone)]
pub struct AppOptions {
    /// Bytes of evaluated geometry (positions per scene, version and time) kept in memory.
    pub geometry_bytes: usize,
    /// Most triangles an uploaded scene (or a geometry update) may have
    /// (`--max-triangles`); the loader's own bound is `formats::gltf::MAX_TRIANGLES`.
    pub max_triangles: u64,
    /// Who hears about finished work.
    pub observer: Option<Arc<dyn Observer>>,
    /// Who POSTs render jobs' callbacks; `None`: a job with a `callback` is refused (422).
    pub callbacks: Option<Arc<dyn CallbackSender>>,
}

impl std::fmt::Debug for AppOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AppOptions")
            .field("geometry_bytes", &self.geometry_bytes)
            .field("max_triangles", &self.max_triangles)
            .field("observer", &self.observer.is_some())
            .field("callbacks", &self.callbacks.is_some())
            .finish()
    }
}

impl Default for AppOptions {
    fn default() -> Self {
        AppOptions {
            geometry_bytes: 1 << 30,
            max_triangles: crate::formats::gltf::MAX_TRIANGLES,
            observer: None,
            callbacks: None,
        }
    }
}

/// The domain layer; cheap to clone.
#[derive(Clone)]
pub struct App {
    inner: Arc<Inner>,
}

struct Inner {
    store: Store,
    engine: Arc<Engine>,
    runtime: tokio::runtime::Handle,
    scenes: scenes::SceneCache,
    live: Mutex<HashMap<String, jobs::Live>>,
    observer: Option<Arc<dyn Observer>>,
    max_triangles: u64,
    thumbnails: thumbnails::Thumbnails,
    callbacks: Option<Arc<dyn CallbackSender>>,
    /// Jobs whose callback a task is delivering now.
    delivering: Mutex<HashSet<String>>,
    /// Submissions carrying an `Idempotency-Key`, one at a time per key.
    keys: keys::KeyLocks,
}

impl App {
    /// The domain over `store`, running work on `engine`; must be made inside a tokio
    /// runtime, whose handle the job threads use to reach the store.
    pub fn new(store: Store, engine: Arc<Engine>, options: AppOptions) -> App {
        App {
            inner: Arc::new_cyclic(|weak| Inner {
                store,
                engine,
                runtime: tokio::runtime::Handle::current(),
                scenes: scenes::SceneCache::new(options.geometry_bytes),
                live: Mutex::new(HashMap::new()),
                observer: options.observer,
                callbacks: options.callbacks,
                delivering: Mutex::new(HashSet::new()),
                keys: keys::KeyLocks::default(),
                max_triangles: options.max_triangles,
                thumbnails: thumbnails::Thumbnails::new(weak.clone()),
            }),
        }
    }

    /// The store.
    pub fn store(&self) -> &Store {
        &self.inner.store
    }

    /// The engine.
    pub fn engine(&self) -> &Arc<Engine> {
        &self.inner.engine
    }

    /// Runs CPU work `f` on the engine's pool and awaits it, so that the async runtime's
    /// threads never compute. Awaited on a pool thread (a job's step waiting for its
    /// scene's parse or pose), `f` runs right there: queued behind the job that waits for
    /// it, it would never start on a pool of one thread.
    pub(crate) async fn cpu<T: Send + 'static>(
        &self,
        f: impl FnOnce() -> T + Send + 'static,
    ) -> Result<T, AppError> {
        if self.inner.engine.on_pool() {
            return Ok(f());
        }
        let (tx, rx) = tokio::sync::oneshot::channel();
        self.inner.engine.spawn(move || {
            let _ = tx.send(f());
        });
        rx.await
            .map_err(|_| AppError::Internal("the worker pool dropped a task".into()))
    }
}
