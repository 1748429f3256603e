//! The engine: the pool, the cache, the scheduler, and how a job gets its structure.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

use super::cache::{LightCache, StructureCache, StructureKey, TextureCache};
use super::sched::Scheduler;
use super::{seconds_since, CancelToken, Control, Geometry, JobError, Limits};
use crate::accel::auto::{self, Geometry as Known};
use crate::accel::dacrt::DacrtTuning;
use crate::accel::{AccelKind, BuildOptions, BuildQuality, Intersector, Precision};

/// Most pool threads a command or the service may ask for (`--threads`): far past any
/// machine this runs on, and short of what makes starting the pool the request's own
/// undoing (10,000 threads took over a minute to start for three rays).
pub const MAX_THREADS: u64 = 1024;

/// How to make an [`Engine`].
#[derive(Clone, Copy, Debug)]
pub struct EngineOptions {
    /// Threads of the pool; 0: all cores.
    pub threads: usize,
    /// Bytes of built structures the cache may hold.
    pub cache_bytes: usize,
    /// Bytes of decoded textures the texture cache may hold.
    pub texture_bytes: usize,
    /// Jobs that may wait to start before new work is refused.
    pub max_queued: usize,
    /// Jobs (synchronous traces aside) that may have started and not finished at once.
    pub max_running: usize,
    /// Bounds every request must fit in.
    pub limits: Limits,
    /// DACRT settings for every build.
    pub tuning: DacrtTuning,
}

impl Default for EngineOptions {
    fn default() -> Self {
        EngineOptions {
            threads: 0,
            cache_bytes: 2 << 30,
            texture_bytes: 1 << 30,
            max_queued: 64,
            max_running: DEFAULT_MAX_RUNNING,
            limits: Limits::default(),
            tuning: DacrtTuning::default(),
        }
    }
}

/// Jobs that may be under way at once by default (`rayd serve --max-running`): enough that
/// a high-priority render can overtake a few long ones, few enough that their images and
/// paths fit in memory together.
pub const DEFAULT_MAX_RUNNING: usize = 4;

/// How a job over moved geometry gets its BVH when a structure over other positions of the
/// same scene is cached: the cost model's choice, always a refit, or always a new build.
/// `rebuild` is what a renderer without refitting does each frame; rayd measures against it.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Update {
    /// Refit when `auto`'s model expects the refit (and its slower trace) to finish first.
    #[default]
    Auto,
    /// Refit whenever a structure to refit is cached.
    Refit,
    /// Build anew; never refit.
    Rebuild,
}

crate::spelled!(Update, [Update::Auto, Update::Refit, Update::Rebuild]);

/// Where a job's structure came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Source {
    /// Built for this job.
    Built,
    /// Found in the cache: no build.
    Cached,
    /// A cached structure over earlier positions, refitted into a copy.
    Refitted,
}

/// A job's structure, ready to trace.
pub struct Prepared {
    /// The accelerator.
    pub accel: Arc<dyn Intersector>,
    /// Seconds spent building or refitting it (0 when cached).
    pub build_seconds: f64,
    /// Where it came from.
    pub source: Source,
}

/// Bytes of light tables kept between render jobs: 16 bytes an emissive triangle, so
/// about four million emitters' worth.
const LIGHT_TABLE_BYTES: usize = 64 << 20;

/// The engine (see the module docs of [`crate::jobs`]).
pub struct Engine {
    pool: Arc<rayon::ThreadPool>,
    cache: StructureCache,
    textures: TextureCache,
    lights: LightCache,
    sched: Arc<Scheduler>,
    options: EngineOptions,
    /// Seconds per byte that large request bodies have taken to arrive (the bits of an f64
    /// running average), for `auto`'s arrival term. Times, not rates, are averaged: one
    /// slow body must move the prediction at once, which an average of rates would bury
    /// under the fast ones.
    upload_cost: AtomicU64,
    /// How many times a scene has been forgotten ([`Engine::forget_scene`]).
    forgets: AtomicU64,
}

/// The upload rate assumed until a large body has been measured: loopback on the
/// development machines moves an 8 MiB ray batch in 3–5 ms while both cores are busy
/// (BENCHMARKS.md §12.10), about 2 GB/s. A real network is slower; the measured bodies
/// take over after the first.
pub const DEFAULT_UPLOAD_BYTES_PER_SECOND: f64 = 2e9;

/// Bodies smaller than this say more about latency than about rate and are not measured.
pub const MIN_MEASURED_UPLOAD_BYTES: u64 = 1 << 20;

/// Weight of each new measurement in the running average of the upload's seconds per byte.
const UPLOAD_COST_WEIGHT: f64 = 0.25;

impl Engine {
    /// Starts the pool.
    pub fn new(options: EngineOptions) -> Result<Engine, rayon::ThreadPoolBuildError> {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(options.threads)
            .thread_name(|i| format!("rayd-pool-{i}"))
            .build()?;
        Ok(Engine {
            pool: Arc::new(pool),
            cache: StructureCache::new(options.cache_bytes),
            textures: TextureCache::new(options.texture_bytes),
            lights: LightCache::new(LIGHT_TABLE_BYTES),
            sched: Scheduler::new(options.max_queued, options.max_running),
            options,
            upload_cost: AtomicU64::new((1.0 / DEFAULT_UPLOAD_BYTES_PER_SECOND).to_bits()),
            forgets: AtomicU64::new(0),
        })
    }

    /// Drops scene `id`'s structures, textures and light tables (the scene was deleted),
    /// and counts the forgetting first, so that structures and tables still being made
    /// over its positions are not kept when they are done ([`Geometry::forgets`]).
    pub fn forget_scene(&self, id: &str) {
        self.forgets.fetch_add(1, Ordering::SeqCst);
        self.cache.forget_scene(id);
        self.textures.forget_scene(id);
        self.lights.forget_scene(id);
    }

    /// How many times a scene has been forgotten: read it before resolving the positions
    /// a job will trace, into [`Geometry::forgets`].
    pub fn forgets(&self) -> u64 {
        self.forgets.load(Ordering::SeqCst)
    }

    /// Whether nothing has been forgotten since `geometry` was resolved, so that what is
    /// made over it may be kept.
    pub(super) fn keeps(&self, geometry: &Geometry) -> bool {
        self.forgets.load(Ordering::SeqCst) == geometry.forgets
    }

    /// Notes that a request body of `bytes` took `seconds` to arrive (from its first piece
    /// to its last): bodies of at least [`MIN_MEASURED_UPLOAD_BYTES`] move the running
    /// average that [`Engine::arrival`] predicts with.
    pub fn note_upload(&self, bytes: u64, seconds: f64) {
        if bytes < MIN_MEASURED_UPLOAD_BYTES || !(seconds > 0.0 && seconds.is_finite()) {
            return;
        }
        // Between 100 GB/s and 1 MB/s.
        let sample = (seconds / bytes as f64).clamp(1e-11, 1e-6);
        // A lost race between two bodies drops one sample; the average is a hint.
        let old = f64::from_bits(self.upload_cost.load(Ordering::Relaxed));
        let new = old + UPLOAD_COST_WEIGHT * (sample - old);
        self.upload_cost.store(new.to_bits(), Ordering::Relaxed);
    }

    /// Bytes per second at which large bodies have been arriving, as the running average
    /// of [`Engine::note_upload`] has it.
    pub fn upload_rate(&self) -> f64 {
        1.0 / f64::from_bits(self.upload_cost.load(Ordering::Relaxed))
    }

    /// Seconds a RAY1 body of `rays` rays is expected to take to arrive.
    pub fn arrival(&self, rays: usize) -> f64 {
        (rays as f64 * 32.0 + 16.0) * f64::from_bits(self.upload_cost.load(Ordering::Relaxed))
    }

    /// Threads of the pool.
    pub fn threads(&self) -> usize {
        self.pool.current_num_threads()
    }

    /// The limits in force.
    pub fn limits(&self) -> &Limits {
        &self.options.limits
    }

    /// The structure cache.
    pub fn cache(&self) -> &StructureCache {
        &self.cache
    }

    /// The cache of scenes' decoded textures, which render jobs of the service share.
    pub fn textures(&self) -> &TextureCache {
        &self.textures
    }

    /// The cache of path-traced frames' light tables.
    pub fn lights(&self) -> &LightCache {
        &self.lights
    }

    /// The scheduler.
    pub fn scheduler(&self) -> &Arc<Scheduler> {
        &self.sched
    }

    /// Runs `f` on the pool without waiting for the scheduler's lease: small CPU work a
    /// request needs before it can be queued, such as parsing an upload.
    pub fn spawn(&self, f: impl FnOnce() + Send + 'static) {
        self.pool.spawn(f);
    }

    /// Whether the calling thread is one of the pool's: a job's step that waits for work
    /// it would [`Engine::spawn`] must do that work itself instead, or, with every pool
    /// thread waiting so (one with `--threads 1`), nothing would ever run it.
    pub fn on_pool(&self) -> bool {
        self.pool.current_thread_index().is_some()
    }

    /// Hooks for a job that runs alone, nobody cancelling it (the command line).
    pub fn detached(&self) -> Control {
        self.detached_with(CancelToken::new())
    }

    /// Hooks for a job that runs alone and stops when `cancel` is cancelled (a command
    /// interrupted by a signal).
    pub fn detached_with(&self, cancel: CancelToken) -> Control {
        Control::new(Arc::clone(&self.pool), cancel, None, None)
    }

    /// Hooks for a scheduled job.
    pub fn control(
        &self,
        cancel: CancelToken,
        progress: Option<super::control::ProgressFn>,
        ticket: super::sched::Ticket,
    ) -> Control {
        Control::new(Arc::clone(&self.pool), cancel, progress, Some(ticket))
    }

    /// Build options for `quality` and `precision` on this engine.
    pub fn build_options(&self, quality: BuildQuality, precision: Precision) -> BuildOptions {
        BuildOptions {
            quality,
            precision,
            threads: self.threads(),
            dacrt: self.options.tuning,
        }
    }

    fn key(
        &self,
        geometry: &Geometry,
        accel: AccelKind,
        quality: BuildQuality,
        precision: Precision,
    ) -> StructureKey {
        let bvh = matches!(
            accel,
            AccelKind::Mbvh8 | AccelKind::Mbvh4 | AccelKind::Bvh2 | AccelKind::Embree
        );
        let tuning = match accel {
            AccelKind::Dacrt | AccelKind::DacrtSampled => self.options.tuning.fingerprint(),
            _ => 0,
        };
        StructureKey {
            geometry: geometry.key.clone(),
            accel,
            // Cores without a build quality share one entry whatever was asked.
            quality: if bvh {
                quality
            } else {
                BuildQuality::default()
            },
            precision,
            simd: crate::simd::selected().name(),
            tuning,
        }
    }

    /// What exists for `kind` over `geometry`, as `auto`'s model sees it.
    fn known(&self, key: &StructureKey) -> Known {
        if self.cache.contains(key) {
            Known::Built
        } else if self.cache.refittable(key).is_some() {
            Known::Refittable
        } else {
            Known::New
        }
    }

    /// Resolves `accel` for a job of `rays` rays in `batches` trace calls over `geometry`,
    /// the first of `frames` frames over moving positions of its triangles (1: a single
    /// one), whose last ray arrives `arrival` seconds after the job starts (a request body
    /// still uploading; 0 for rays in memory), which stop at their first hit when
    /// `first_hit` (`any`, occlusion): `auto` asks the cost model, told what the cache
    /// holds.
    #[allow(clippy::too_many_arguments)]
    pub fn resolve(
        &self,
        accel: AccelKind,
        geometry: &Geometry,
        quality: BuildQuality,
        precision: Precision,
        rays: usize,
        batches: usize,
        frames: usize,
        arrival: f64,
        first_hit: bool,
    ) -> AccelKind {
        let mbvh = self.key(geometry, AccelKind::Mbvh8, quality, precision);
        accel.resolve(&auto::Job {
            rays,
            batches,
            triangles: geometry.triangles.len(),
            threads: self.threads(),
            quality,
            geometry: self.known(&mbvh),
            frames,
            arrival,
            first_hit,
        })
    }

    /// The structure of `kind` (resolved) over `geometry`: from the cache, refitted from a
    /// cached structure over other positions of the same scene when `update` says so (under
    /// [`Update::Auto`], when the cost model expects that to finish first; `rays` and
    /// `batches` describe the job), or built, and kept in the cache. Call inside the pool (a
    /// [`Control::step`]).
    #[allow(clippy::too_many_arguments)]
    pub fn structure(
        &self,
        geometry: &Geometry,
        kind: AccelKind,
        quality: BuildQuality,
        precision: Precision,
        rays: usize,
        batches: usize,
        update: Update,
    ) -> Result<Prepared, JobError> {
        let key = self.key(geometry, kind, quality, precision);
        if let Some(accel) = self.cache.get(&key) {
            return Ok(Prepared {
                accel,
                build_seconds: 0.0,
                source: Source::Cached,
            });
        }
        let t0 = Instant::now();
        let options = self.build_options(quality, precision);
        let geometry_triangles = geometry.triangles.len();
        // Whether a refit whose traces are `slowdown` times slower than a fresh tree's
        // (beyond the model's usual drift) finishes first.
        let refit_pays = |slowdown: f64| {
            if update != Update::Auto {
                return update == Update::Refit;
            }
            let job = |geometry| auto::Job {
                rays,
                batches,
                triangles: geometry_triangles,
                threads: self.threads(),
                quality,
                geometry,
                frames: 1,
                arrival: 0.0,
                first_hit: false,
            };
            let refit = auto::predict(AccelKind::Mbvh8, &job(Known::Refittable));
            let trace = auto::predict(AccelKind::Mbvh8, &job(Known::Built));
            let build = auto::predict(AccelKind::Mbvh8, &job(Known::New));
            matches!((refit, trace, build), (Some(r), Some(t), Some(b))
                if r + t * (slowdown - 1.0).max(0.0) < b)
        };
        let mut made: Option<(Box<dyn Intersector>, Source)> = None;
        if let Some(old) = self.cache.refittable(&key) {
            if refit_pays(1.0) {
                // A refused refit (a triangle turned degenerate, say) falls back to a build,
                // and so does one whose boxes swelled so far (triangles moved far from
                // where the tree grouped them) that a build now finishes first: its
                // traces could be a hundred times slower, and every later version would
                // be refitted from it.
                if let Ok(copy) = old.refit_copy(&geometry.triangles) {
                    if refit_pays(copy.refit_slowdown()) {
                        made = Some((copy, Source::Refitted));
                    }
                }
            }
        }
        let (accel, source) = match made {
            Some(m) => m,
            None => (
                crate::accel::build(kind, &geometry.triangles, &options)?,
                Source::Built,
            ),
        };
        let build_seconds = seconds_since(t0);
        let accel: Arc<dyn Intersector> = Arc::from(accel);
        self.cache
            .insert_if(key, Arc::clone(&accel), || self.keeps(geometry));
        Ok(Prepared {
            accel,
            build_seconds,
            source,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Triangle;
    use crate::jobs::GeometryKey;

    fn one_thread() -> Engine {
        Engine::new(EngineOptions {
            threads: 1,
            ..Default::default()
        })
        .unwrap()
    }

    #[test]
    fn measured_bodies_move_the_expected_arrival() {
        let e = one_thread();
        let rays = 1 << 18; // 8 MiB
        let first = e.arrival(rays);
        assert!((first - 8.0 * 1048576.0 / DEFAULT_UPLOAD_BYTES_PER_SECOND).abs() < 1e-4);
        // Small, instant or broken measurements are ignored.
        e.note_upload(1000, 1.0);
        e.note_upload(8 << 20, 0.0);
        e.note_upload(8 << 20, f64::NAN);
        assert_eq!(e.arrival(rays), first);
        // One body at 20 MB/s moves the estimate at once (a quarter of its 0.42 s for
        // 8 MiB); more pull it there.
        e.note_upload(20_000_000, 1.0);
        assert!(e.arrival(rays) > 0.1);
        for _ in 0..40 {
            e.note_upload(20_000_000, 1.0);
        }
        assert!((e.upload_rate() / 20e6 - 1.0).abs() < 0.01);
        assert!((e.arrival(rays) - 0.419).abs() < 0.01);
    }

    /// A grid of `n`² unit squares (two triangles each) in the z = 0 plane, at `version`.
    fn grid(n: usize, version: u32, forgets: u64) -> Geometry {
        let mut tris = Vec::new();
        for i in 0..n {
            for j in 0..n {
                let (x, y) = (i as f32, j as f32);
                let [a, b, c, d] = [[x, y], [x + 1.0, y], [x, y + 1.0], [x + 1.0, y + 1.0]]
                    .map(|[x, y]| [x, y, 0.0]);
                tris.push(Triangle { v: [a, b, c] });
                tris.push(Triangle { v: [b, d, c] });
            }
        }
        Geometry {
            key: GeometryKey::new("grid", version, None),
            triangles: Arc::new(tris),
            forgets,
        }
    }

    fn prepare(e: &Engine, g: &Geometry, rays: usize) -> Prepared {
        e.pool
            .install(|| {
                e.structure(
                    g,
                    AccelKind::Mbvh8,
                    BuildQuality::Sah,
                    Precision::Watertight,
                    rays,
                    1,
                    Update::Auto,
                )
            })
            .unwrap()
    }

    /// A structure finished after its scene was forgotten (deleted) is not kept: the same
    /// id uploaded again could have other positions under the same version number.
    #[test]
    fn a_structure_made_over_a_forgotten_scene_is_not_kept() {
        let e = one_thread();
        let before = grid(8, 2, e.forgets());
        e.forget_scene("grid");
        assert_eq!(prepare(&e, &before, 1000).source, Source::Built);
        assert_eq!(e.cache().stats().entries, 0);
        // Positions resolved after the forgetting are kept, and found again.
        let after = grid(8, 2, e.forgets());
        assert_eq!(prepare(&e, &after, 1000).source, Source::Built);
        assert_eq!(prepare(&e, &after, 1000).source, Source::Cached);
    }

    /// A new version that moves the triangles a little is refitted; one that moves them
    /// far from where the tree grouped them (here: every triangle's positions handed to
    /// another, far away) is built anew, and later versions refit the new tree.
    #[test]
    fn a_refit_that_swells_the_tree_is_built_instead() {
        let e = one_thread();
        let rays = 1 << 16;
        let v1 = grid(64, 1, 0);
        assert_eq!(prepare(&e, &v1, rays).source, Source::Built);
        let nudge = |g: &Geometry, version: u32| {
            let mut tris = (*g.triangles).clone();
            for t in &mut tris {
                for v in &mut t.v {
                    v[2] += 0.01 * v[0];
                }
            }
            Geometry {
                key: GeometryKey::new("grid", version, None),
                triangles: Arc::new(tris),
                forgets: 0,
            }
        };
        let v2 = nudge(&v1, 2);
        let p2 = prepare(&e, &v2, rays);
        assert_eq!(p2.source, Source::Refitted);
        assert!(
            p2.accel.refit_slowdown() < 1.1,
            "{}",
            p2.accel.refit_slowdown()
        );
        // Neighbouring ids get positions 7919 triangles apart (7919 is prime, the count
        // a power of two).
        let n = v2.triangles.len();
        let shuffled: Vec<Triangle> = (0..n).map(|i| v2.triangles[i * 7919 % n]).collect();
        let v3 = Geometry {
            key: GeometryKey::new("grid", 3, None),
            triangles: Arc::new(shuffled),
            forgets: 0,
        };
        let p3 = prepare(&e, &v3, rays);
        assert_eq!(p3.source, Source::Built);
        assert_eq!(p3.accel.refit_slowdown(), 1.0);
        let v4 = nudge(&v3, 4);
        assert_eq!(prepare(&e, &v4, rays).source, Source::Refitted);
    }
}
