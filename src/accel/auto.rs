//! `auto`: the accelerator expected to finish a job first, counting its preparation.
//!
//! A job is described by what is known before anything runs: how many rays, in how many
//! batches (trace calls), over how many triangles, on how many threads, at which build
//! quality, and whether the geometry is new (nothing built yet), refittable (a structure
//! built on earlier positions of the same triangles exists) or already built. Each
//! candidate's time is predicted by a cost model of the form the cores' algorithms have:
//!
//! - a BVH core (`mbvh8`): `build·T` (or `refit·T`, or nothing) `+ R·(r₀ + r₁·log₂T)`;
//! - DACRT: `pre·T` (the per-frame AABB precompute) `+ B·top·T + R·(d₀ + d₁·log₂T)`: every
//!   batch partitions the triangles near the root whatever its size (the `top` term),
//!   which is why DACRT needs large batches, and no structure outlives a batch.
//!
//! A batch still arriving (a request body that is uploading) adds one more input: how long
//! until its last ray is in. A BVH core prepares, then traces each piece of rays as it
//! arrives, so it finishes no earlier than the last ray and otherwise as the work allows;
//! DACRT partitions the whole batch at once, so only its precompute can run during the
//! upload and its trace starts after the last ray.
//!
//! Times are per thread and divided by the thread count's measured speed-up. The
//! constants are fitted to `rayd bench --frames` measurements (BENCHMARKS.md, "auto"),
//! which also reports how often this model picks the fastest strategy and what its wrong
//! picks cost.

use super::{AccelKind, BuildQuality};

/// What exists of the job's geometry before it starts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Geometry {
    /// Nothing has been built for these positions (a `rayd trace` or `render` run, a new
    /// scene, a new geometry version with nothing to refit).
    New,
    /// A structure built on earlier positions of the same triangles exists: BVH cores can
    /// refit it instead of rebuilding.
    Refittable,
    /// A structure for exactly these positions exists (a cached scene version): BVH cores
    /// start tracing at once.
    Built,
}

/// What `auto` knows about a job.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Job {
    /// Rays in the whole job.
    pub rays: usize,
    /// Trace calls the rays arrive in (a render traces one batch per sample and bounce).
    pub batches: usize,
    /// Triangles of the scene.
    pub triangles: usize,
    /// Threads of the pool.
    pub threads: usize,
    /// Build quality asked for (BVH cores).
    pub quality: BuildQuality,
    /// What already exists.
    pub geometry: Geometry,
    /// Frames of moving geometry the job traces over these triangles, this one included
    /// (1 for a single batch or frame). A BVH built now is refitted for the frames after
    /// it, so over a sequence its build is paid once and shared by them all, while DACRT
    /// pays its preparation every frame.
    pub frames: usize,
    /// Seconds until the batch's last ray arrives, counted from the job's start (a request
    /// body still uploading; 0 for rays already in memory).
    pub arrival: f64,
    /// The rays stop at their first hit (`any` queries, occlusion): a BVH's traversal
    /// ends there, while DACRT's partitioning, which is most of its work, does not.
    pub first_hit: bool,
}

impl Job {
    /// A single batch of `rays` over `triangles` new triangles on `threads` threads.
    pub fn batch(rays: usize, triangles: usize, threads: usize, quality: BuildQuality) -> Job {
        Job {
            rays,
            batches: 1,
            triangles,
            threads,
            quality,
            geometry: Geometry::New,
            frames: 1,
            arrival: 0.0,
            first_hit: false,
        }
    }
}

/// The fitted constants, in seconds per triangle or per ray on one thread.
#[derive(Clone, Copy, Debug)]
struct Model {
    /// `mbvh8` build per triangle, by quality (fast, sah, sbvh).
    build: [f64; 3],
    /// `mbvh8` refit per triangle.
    refit: f64,
    /// `mbvh8` trace per ray per log₂ T, on a fresh `fast` tree.
    bvh_ray: f64,
    /// The trace's cost on a tree of each quality relative to a `fast` one.
    trace: [f64; 3],
    /// How much slower a refitted tree traces than a fresh one.
    refit_slowdown: f64,
    /// `dacrt-sampled` precompute per triangle.
    dacrt_pre: f64,
    /// `dacrt-sampled` per batch per triangle (the partitions near the root).
    dacrt_top: f64,
    /// `dacrt-sampled` per ray per log₂ T.
    dacrt_ray: f64,
    /// How the BVH's and DACRT's per-ray costs bend with the scene's size: each is
    /// multiplied by `(log₂ T / 16)^e`, log₂ T held to `[shape_floor, 20]`.
    ray_shape: [f64; 2],
    /// The log₂ T below which the per-ray costs stop bending: under it a ray's fixed
    /// costs, not the scene, decide how DACRT traces against the BVH.
    shape_floor: f64,
    /// Speed-up on 2 threads of the BVH build, the BVH trace and DACRT; more threads
    /// extrapolate it as `threads^log₂(speed-up)`.
    speedup2: [f64; 3],
    /// The BVH's per-ray cost when rays stop at their first hit, relative to closest-hit
    /// rays (DACRT's is taken as unchanged).
    first_hit: f64,
    /// `brute`'s packing of the triangles into 8-wide groups, per triangle.
    brute_pre: f64,
    /// `brute`'s cost per ray and triangle.
    brute_test: f64,
}

/// Fitted to `rayd bench --frames 4 --build fast` on dragon-100k (twist) and BrainStem
/// (animation), 64K–1M rays per frame, primary and diffuse2 rays, 1 and 2 threads
/// (BENCHMARKS.md §8), with the `sah` and `sbvh` builds and their traces from one-thread
/// build runs of both scenes (2-core Zen 3, session 13). `scripts/fit_auto.py` searched a
/// grid of the DACRT, BVH, refit and thread constants over five runs of §8 for the most
/// right picks among points that also predict every strategy's frame times within about
/// 20% (RMS of the log error): ranking alone found constants that picked as well while
/// predicting DACRT's frames at twice their time, which then mispredicted every job
/// unlike the fitted ones. These pick the fastest in 205 of 240 situations (204 with
/// each run held out in turn, §8.1). The BVH and DACRT trace about equally per ray once a
/// batch is large, so DACRT wins where a build would not be repaid.
const MODEL: Model = Model {
    build: [0.09e-6, 0.47e-6, 2.0e-6],
    refit: 0.038e-6,
    bvh_ray: 12.0e-9,
    trace: [1.0, 0.85, 0.9],
    refit_slowdown: 1.1,
    dacrt_pre: 0.055e-6,
    dacrt_top: 0.1e-6,
    dacrt_ray: 12.0e-9,
    speedup2: [1.5, 1.6, 1.5],
    ray_shape: [0.0, 1.5],
    // Session 34 (BENCHMARKS §39): static batches of 64K and 786K rays over 16 scenes of
    // 268 to 1M triangles (`sah` builds; primary, `ao` and diffuse2 rays; 1 and 2
    // threads; two runs) traced with DACRT at 1.0–1.8× the BVH's time below ~20K
    // triangles, where the floor at 12 (4K triangles) predicted 0.76×. At 14.5 (~23K),
    // `scripts/fit_auto.py --floors` scores 313 of those 384 static picks right (was 271;
    // mean pick 1.021× the fastest, was 1.058×) and §8's moving frames as before (464 of
    // 528), their DACRT times closer (RMS log error 0.171, was 0.191). Higher floors
    // lose moving frames of CesiumMan, where DACRT does trace faster.
    shape_floor: 14.5,
    // Session 31's review (Suzanne and DamagedHelmet, 1M primary and diffuse rays, 1 and
    // 2 threads): `mbvh8` over `dacrt-sampled` was 1.22–1.44× faster on closest-hit rays
    // and 1.7–2.3× on `any`, where the model, blind to the query, picked DACRT.
    first_hit: 0.6,
    // The same review: on 1M triangles `brute` spent 80–124 ms packing and about 3.3 ns
    // per ray and triangle (the model said 2 ns and nothing), so it was picked for up to
    // ~75 rays and ran 2–2.9× slower than DACRT.
    brute_pre: 0.1e-6,
    brute_test: 3.3e-9,
};

fn speedup(s2: f64, threads: usize) -> f64 {
    (threads.max(1) as f64).powf(s2.log2())
}

/// log₂ T bent by one of the model's `ray_shape` exponents: DACRT's per-ray cost grows
/// faster with the scene than the BVH's (on 1M triangles it traces at half the BVH's rate,
/// on 100K at about the BVH's). The bend is held between `shape_floor` (~23K triangles)
/// and 1M triangles: below the floor a ray's fixed costs dominate, and DACRT traces
/// no faster relative to the BVH than it does there.
fn shaped(lg: f64, exponent: f64) -> f64 {
    lg * (lg.clamp(MODEL.shape_floor, 20.0) / 16.0).powf(exponent)
}

fn quality_index(q: BuildQuality) -> usize {
    match q {
        BuildQuality::Fast => 0,
        BuildQuality::Sah => 1,
        BuildQuality::Sbvh => 2,
    }
}

/// Predicted seconds of `kind` (one of `mbvh8`, `dacrt-sampled`, `brute`) for `job`;
/// `None` for kinds the model does not cover.
pub fn predict(kind: AccelKind, job: &Job) -> Option<f64> {
    let m = &MODEL;
    let t = job.triangles.max(1) as f64;
    let r = job.rays as f64;
    let lg = t.log2().max(1.0);
    match kind {
        AccelKind::Mbvh8 => {
            // Per frame of the job: a new tree's build is shared by the frames that then
            // refit it, each tracing a little slower.
            let f = job.frames.max(1) as f64;
            let (prep, slow) = match job.geometry {
                Geometry::New => (
                    (m.build[quality_index(job.quality)] + (f - 1.0) * m.refit) / f * t,
                    (1.0 + (f - 1.0) * m.refit_slowdown) / f,
                ),
                Geometry::Refittable => (m.refit * t, m.refit_slowdown),
                Geometry::Built => (0.0, 1.0),
            };
            let trace = r
                * m.bvh_ray
                * m.trace[quality_index(job.quality)]
                * shaped(lg, m.ray_shape[0])
                * slow
                * if job.first_hit { m.first_hit } else { 1.0 };
            let work = prep / speedup(m.speedup2[0], job.threads)
                + trace / speedup(m.speedup2[1], job.threads);
            Some(work.max(job.arrival))
        }
        AccelKind::DacrtSampled => {
            let prep = m.dacrt_pre * t;
            let top = job.batches.max(1) as f64 * m.dacrt_top * t;
            let trace = r * m.dacrt_ray * shaped(lg, m.ray_shape[1]);
            let s = speedup(m.speedup2[2], job.threads);
            Some((prep / s).max(job.arrival) + (top + trace) / s)
        }
        // Every ray against every triangle, eight at a time: only for a handful.
        AccelKind::Brute => {
            let work = m.brute_pre * t / speedup(m.speedup2[0], job.threads)
                + r * t * m.brute_test / speedup(m.speedup2[1], job.threads);
            Some(work.max(job.arrival))
        }
        _ => None,
    }
}

/// The accelerator `auto` runs for `job`: the candidate with the smallest predicted time.
pub fn choose(job: &Job) -> AccelKind {
    let mut best = (AccelKind::Mbvh8, f64::INFINITY);
    for k in [AccelKind::Brute, AccelKind::DacrtSampled, AccelKind::Mbvh8] {
        if let Some(s) = predict(k, job) {
            if s < best.1 {
                best = (k, s);
            }
        }
    }
    best.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_hit_rays_favour_the_bvh_and_brute_pays_its_packing() {
        // A million rays over Suzanne's ~1K triangles: `any` goes to the tree (the review
        // measured `mbvh8` 2.3× faster there than the DACRT that was picked).
        let closest = Job::batch(1 << 20, 968, 1, BuildQuality::Sah);
        let any = Job {
            first_hit: true,
            ..closest
        };
        assert!(
            predict(AccelKind::Mbvh8, &any).unwrap() < predict(AccelKind::Mbvh8, &closest).unwrap()
        );
        assert_eq!(choose(&any), AccelKind::Mbvh8);
        // 64 rays over a million triangles: not `brute` (2–2.9× slower than DACRT there).
        assert_ne!(
            choose(&Job::batch(64, 1_040_000, 1, BuildQuality::Sah)),
            AccelKind::Brute
        );
    }

    #[test]
    fn below_the_floor_dacrt_gains_nothing_on_the_bvh() {
        // Session 34's static batches: on Suzanne (3,948 triangles with the bench's room)
        // DACRT traced a 786K-ray batch in 1.0–1.8× the `sah` tree's time; the model
        // predicted 0.76× before the floor rose. Now it sees them about even (1.00 by
        // these constants: which way the pick goes rests on the small terms).
        let job = Job::batch(786_432, 3948, 1, BuildQuality::Sah);
        let ratio = predict(AccelKind::DacrtSampled, &job).unwrap()
            / predict(AccelKind::Mbvh8, &job).unwrap();
        assert!((0.97..1.1).contains(&ratio), "{ratio}");
        // Below the floor the ratio no longer falls with the scene.
        let tiny = Job::batch(786_432, 268, 1, BuildQuality::Sah);
        let tiny_ratio = predict(AccelKind::DacrtSampled, &tiny).unwrap()
            / predict(AccelKind::Mbvh8, &tiny).unwrap();
        assert!(tiny_ratio >= ratio * 0.99, "{tiny_ratio} {ratio}");
        // A moving frame of CesiumMan (4,684 triangles), a `fast` tree to refit: DACRT
        // traced those in 0.89–0.97× the refitted tree's time (§8), and still gets them.
        let mut frame = Job::batch(1 << 20, 4684, 1, BuildQuality::Fast);
        frame.geometry = Geometry::Refittable;
        assert_eq!(choose(&frame), AccelKind::DacrtSampled);
    }

    #[test]
    fn a_tiny_scene_goes_to_brute_and_a_cached_structure_to_the_bvh() {
        assert_eq!(
            choose(&Job::batch(1000, 4, 1, BuildQuality::Sah)),
            AccelKind::Brute
        );
        let mut job = Job::batch(1 << 20, 100_000, 2, BuildQuality::Sah);
        job.geometry = Geometry::Built;
        assert_eq!(choose(&job), AccelKind::Mbvh8);
    }

    #[test]
    fn predictions_grow_with_the_work() {
        for k in [AccelKind::Mbvh8, AccelKind::DacrtSampled] {
            let small = predict(k, &Job::batch(1000, 1000, 1, BuildQuality::Sah)).unwrap();
            let more_rays = predict(k, &Job::batch(100_000, 1000, 1, BuildQuality::Sah)).unwrap();
            let more_tris = predict(k, &Job::batch(1000, 100_000, 1, BuildQuality::Sah)).unwrap();
            let threads = predict(k, &Job::batch(1000, 1000, 2, BuildQuality::Sah)).unwrap();
            assert!(
                more_rays > small && more_tris > small && threads < small,
                "{k:?}"
            );
        }
    }

    #[test]
    fn a_sequence_of_frames_shares_one_build() {
        // One 256K-ray frame of a 60K-triangle scene on 2 threads: DACRT beats a `sah`
        // build that only this frame uses, not one that 8 frames share by refitting.
        let mut job = Job::batch(1 << 18, 60_000, 2, BuildQuality::Sah);
        assert_eq!(choose(&job), AccelKind::DacrtSampled);
        job.frames = 8;
        assert_eq!(choose(&job), AccelKind::Mbvh8);
        let per_frame = |frames| {
            let mut j = job;
            j.frames = frames;
            predict(AccelKind::Mbvh8, &j).unwrap()
        };
        assert!(per_frame(2) < per_frame(1) && per_frame(8) < per_frame(2));
    }

    #[test]
    fn a_slow_upload_goes_to_the_bvh_that_traces_while_it_arrives() {
        // The frame of `a_sequence_of_frames_shares_one_build`, whose rays are in memory,
        // goes to DACRT. Arriving over 100 ms (16 MiB at 160 MB/s), the BVH's build and
        // trace fit inside the upload, while DACRT's trace must follow it.
        let mut job = Job::batch(1 << 18, 60_000, 2, BuildQuality::Sah);
        assert_eq!(choose(&job), AccelKind::DacrtSampled);
        job.arrival = 0.1;
        assert_eq!(choose(&job), AccelKind::Mbvh8);
        let bvh = predict(AccelKind::Mbvh8, &job).unwrap();
        let dacrt = predict(AccelKind::DacrtSampled, &job).unwrap();
        assert_eq!(bvh, 0.1, "the BVH finishes with the last ray");
        assert!(dacrt > 0.1);
        // A quick upload changes nothing.
        job.arrival = 1e-4;
        assert_eq!(choose(&job), AccelKind::DacrtSampled);
    }

    #[test]
    fn many_batches_turn_dacrt_down() {
        let mut job = Job::batch(1 << 20, 100_000, 1, BuildQuality::Sah);
        let one = predict(AccelKind::DacrtSampled, &job).unwrap();
        job.batches = 64;
        assert!(predict(AccelKind::DacrtSampled, &job).unwrap() > one);
    }
}
