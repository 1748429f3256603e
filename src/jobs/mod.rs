//! The engine under both faces: typed trace and render jobs, their limits and reports, the
//! structure cache and the scheduler. `rayd trace`/`rayd render` and the HTTP handlers both
//! call this layer; it knows no HTTP and no files, and the cores below it know neither.
//!
//! - [`Engine`] owns the rayon pool (sized by `--threads`), the [`cache::StructureCache`] of
//!   built accelerators, the [`cache::TextureCache`] of decoded textures and the
//!   [`sched::Scheduler`] that orders CPU work by priority.
//! - [`TraceRequest`] / [`trace::TraceReport`]: one batch of rays against a [`Geometry`].
//! - [`RenderRequest`] / [`render::RenderReport`]: an image (or one per frame time).
//! - [`Control`]: the hooks a running job is driven by: cancellation, progress, and the
//!   checkpoints between waves at which a long job yields to waiting work.

pub mod cache;
pub mod control;
mod engine;
pub(crate) mod lru;
pub mod render;
pub mod sched;
pub mod trace;

use std::sync::Arc;

pub use control::{CancelToken, Control};
pub use engine::{Engine, EngineOptions, Update, DEFAULT_MAX_RUNNING, MAX_THREADS};
pub use render::{FrameTimes, RenderReport, RenderRequest};
pub use trace::{HitBody, TraceReport, TraceRequest};

use crate::geometry::{InvalidRays, Triangle};

/// What to do with invalid rays (contract §2).
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum InvalidPolicy {
    /// Refuse the whole batch, naming the first bad ray and the count.
    #[default]
    Error,
    /// Answer each invalid ray as a miss.
    Miss,
}

crate::spelled!(InvalidPolicy, [InvalidPolicy::Error, InvalidPolicy::Miss]);

/// Bounds a job must fit in before any work starts (contract §4: `--max-rays`,
/// `--max-pixels`, `--max-spp`), so that a typo or a hostile request cannot ask for
/// terabytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub struct Limits {
    /// Rays in one batch.
    pub max_rays: usize,
    /// Width × height of one image.
    pub max_pixels: u64,
    /// Largest image side.
    pub max_side: u32,
    /// Samples per pixel.
    pub max_spp: u32,
    /// Path bounces.
    pub max_bounces: u32,
    /// Frames of one animation render.
    pub max_frames: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            max_rays: 1 << 24,
            max_pixels: 16384 * 16384,
            max_side: 16384,
            max_spp: 65536,
            max_bounces: 64,
            max_frames: 10_000,
        }
    }
}

/// Which positions a structure was built over: a scene, one of its geometry versions, and
/// the animation time version 1 was evaluated at (`None`: the static pose). Two jobs with
/// equal keys trace identical triangles.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct GeometryKey {
    /// The scene's id (the service's content hash; the CLI's file path).
    pub scene: Arc<str>,
    /// Geometry version (1: the uploaded file).
    pub version: u32,
    /// Bits of the animation time (`f64::to_bits`), `None` for the static pose.
    pub time_bits: Option<u64>,
}

impl GeometryKey {
    /// The key of `scene` at `version` and `time`.
    pub fn new(scene: &str, version: u32, time: Option<f64>) -> GeometryKey {
        GeometryKey {
            scene: scene.into(),
            version,
            // +0 and -0 are the same time.
            time_bits: time.map(|t| if t == 0.0 { 0 } else { t.to_bits() }),
        }
    }
}

/// World-space triangles in id order, shared between the jobs that trace them.
#[derive(Clone, Debug)]
pub struct Geometry {
    /// What these positions are.
    pub key: GeometryKey,
    /// The triangles.
    pub triangles: Arc<Vec<Triangle>>,
    /// [`engine::Engine::forgets`] read before these positions were resolved: a
    /// structure or light table made over them is kept only if no scene has been
    /// forgotten since. A scene deleted while a job built over it, then uploaded again
    /// (the same id: ids are content hashes) with other positions under the same version
    /// number, would otherwise find the deleted scene's structure under its key. 0 where
    /// nothing is ever forgotten (the command line).
    pub forgets: u64,
}

/// Errors of jobs: everything a caller may need to tell its user, with the place.
#[derive(Debug, thiserror::Error)]
pub enum JobError {
    /// The batch has invalid rays and `invalid=error` is in force.
    #[error("{0}")]
    InvalidRays(InvalidRays),
    /// A request exceeds a limit.
    #[error("{what} {value} exceeds the limit of {limit}")]
    Limit {
        /// What is counted (`rays`, `pixels`, `spp`, …), also the request field it came from.
        what: &'static str,
        /// The requested amount.
        value: u64,
        /// The limit.
        limit: u64,
    },
    /// A request field is unusable.
    #[error("{field}: {detail}")]
    Invalid {
        /// The field.
        field: &'static str,
        /// What is wrong.
        detail: String,
    },
    /// An accelerator could not be built.
    #[error(transparent)]
    Accel(#[from] crate::accel::AccelError),
    /// The camera cannot be made.
    #[error(transparent)]
    Camera(#[from] crate::render::camera::CameraError),
    /// The image cannot be encoded.
    #[error(transparent)]
    Image(#[from] crate::render::image::ImageError),
    /// The job was cancelled.
    #[error("cancelled")]
    Cancelled,
    /// The scheduler's queue is full; try again later.
    #[error("the queue is full ({0} jobs waiting)")]
    QueueFull(usize),
    /// The engine is shutting down.
    #[error("shutting down")]
    ShuttingDown,
    /// Geometry for a job could not be had (the caller's loader failed).
    #[error("{0}")]
    Geometry(String),
}

/// Seconds of `t0.elapsed()`.
pub(crate) fn seconds_since(t0: std::time::Instant) -> f64 {
    t0.elapsed().as_secs_f64()
}
