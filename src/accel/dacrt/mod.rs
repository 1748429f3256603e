//! Divide-and-conquer ray tracing: no acceleration structure, the triangles are partitioned
//! while the rays are traced (Áfra 2012, "Incoherent ray tracing without acceleration
//! structures"; Nabata et al. 2013, "Efficient divide-and-conquer ray tracing using ray
//! sampling").
//!
//! - `dacrt` is Áfra's method: rays in one array of 32-byte records filtered by reordering
//!   them in place ([`rays`]); triangle boxes precomputed once per frame with the
//!   complementary data that rebuilds each triangle ([`tris`]); middle or 32-bin SAH
//!   partitioning chosen by the ratio of active rays to triangles ([`split`]); naive leaves
//!   ([`leaf`]); ordered traversal by the first active ray ([`traverse`]).
//! - `dacrt-sampled` adds Nabata's ray sampling: 100 sample rays per node with more than
//!   1000 active rays choose the split plane by the sampled cost, the order of the
//!   children, and whether a child needs its rays filtered at all ([`options::Sampling`]).
//!
//! Both share the same code and run on the rayon pool they are called in, with the
//! parallel scheme of [`parallel`] (with the top levels partitioned once for all threads,
//! [`top`]). "Building" one is the per-frame precompute only, so a
//! new frame (new positions for the same or other triangles) is simply a new build.
//!
//! Memory during a trace (T triangles, R rays, P threads): 48·T for the precompute (held
//! between traces), 32·R for the ray records, 4·T·(P + 1) for the id arrays (the batch's
//! and one per group of its index split), plus the fork copies
//! (at most [`options::Parallelism::fork_budget`]·R records at 52 bytes). The hit slots are
//! the caller's output array, used as scratch while tracing.

pub mod lanes;
pub mod leaf;
pub mod options;
pub mod parallel;
pub mod rays;
pub mod sampling;
pub mod split;
pub mod stats;
pub mod top;
pub mod traverse;
pub mod tris;

use std::sync::atomic::{AtomicBool, AtomicIsize, Ordering};
use std::time::Instant;

use rayon::prelude::*;

use super::bvh::RefitError;
use super::tiny_dir;
use super::triangle::TriTest;
use super::{AccelError, Intersector, Precision, Query};
use crate::geometry::{Hit, Ray, Triangle};

pub use options::{DacrtOptions, DacrtTuning, ForkSplit, Parallelism, Sampling};

use leaf::{LeafTest, Moller, Table, Watertight};
use rays::{RayRec, SLOT_MASK};
use split::Node;
use stats::{lap, Stats};
use traverse::{step, Ctx};
use tris::TriData;

/// What every group of a batch's index split shares ([`Dacrt::groups`]).
struct Group<'a> {
    /// The batch's triangle ids, partitioned as `top` says where it is given.
    ids: &'a [u32],
    top: Option<&'a top::Top>,
    /// Rays per group.
    chunk: usize,
}

/// A DACRT accelerator: the frame's triangle precompute and the traversal's settings.
pub struct Dacrt {
    name: &'static str,
    tris: TriData,
    precision: Precision,
    options: DacrtOptions,
}

impl Dacrt {
    /// Áfra's method over `triangles`, with the `RAYD_DACRT_*` overrides of the
    /// environment.
    pub fn new(triangles: &[Triangle], precision: Precision) -> Dacrt {
        Dacrt::with_options(
            "dacrt",
            triangles,
            precision,
            DacrtOptions::afra().with_env(),
        )
    }

    /// Nabata's method over `triangles`, with the environment's overrides.
    pub fn sampled(triangles: &[Triangle], precision: Precision) -> Dacrt {
        Dacrt::with_options(
            "dacrt-sampled",
            triangles,
            precision,
            DacrtOptions::nabata().with_env(),
        )
    }

    /// Either method with explicit settings (`name` is what [`Intersector::name`] reports).
    pub fn with_options(
        name: &'static str,
        triangles: &[Triangle],
        precision: Precision,
        options: DacrtOptions,
    ) -> Dacrt {
        Dacrt {
            name,
            tris: TriData::new(triangles),
            precision,
            options,
        }
    }

    /// The settings in use.
    pub fn options(&self) -> &DacrtOptions {
        &self.options
    }

    /// Traces one batch of at most `SLOT_MASK + 1` rays; `finish` writes the miss records
    /// (not needed when only occlusion is asked for).
    fn batch<T: LeafTest>(&self, rays: &[Ray], hits: &mut [Hit], any: bool, finish: bool) {
        let stats = self.options.stats.then(Stats::default);
        let t0 = Instant::now();
        // Hit slots hold the best hit so far (t starts at tmax); records carry the slot.
        hits.par_iter_mut().zip(rays.par_iter()).for_each(|(h, r)| {
            *h = Hit {
                t: r.tmax,
                prim: u32::MAX,
                u: 0.0,
                v: 0.0,
            }
        });
        // `tmin` is not in the records; rays whose `tmin` is not 0 find it here.
        let mut tmin: Vec<f32> = if rays.par_iter().any(|r| r.tmin != 0.0) {
            rays.par_iter().map(|r| r.tmin).collect()
        } else {
            Vec::new()
        };
        // Per ray, the exponent of a direction too small for its reciprocal
        // ([`super::tiny_dir`]): such a ray is traced as its scaled twin, as every core
        // tests it (its record, slot and `tmin` in units of `2^-e·t`), and the final pass
        // scales its hit's t back. Empty when no ray of the batch is tiny (nearly always).
        let mut exps: Vec<i32> = Vec::new();
        let live = self.tris.live();
        if live > 0 && !rays.is_empty() {
            let threads = rayon::current_num_threads();
            let p = &self.options.parallel;
            let parallel = p.enabled && threads > 1;
            // With several threads the batch starts split by index into one group of rays
            // per thread (image bands for camera rays), each filtered against the root box
            // and traced at once, so that no thread waits while others filter or partition
            // the whole batch by slot: split in halves, as ray-split forks would, the top
            // levels ran on 2, 4, 8 threads in turn and half of 16 threads' time was idle
            // (BENCHMARKS §11.1, §11.3). Each group counts its slots from 0.
            let groups = if parallel {
                (rays.len() / p.fork_min_rays).clamp(1, threads)
            } else {
                1
            };
            let chunk = rays.len().div_ceil(groups);
            let tiny = AtomicBool::new(false);
            let mut recs: Vec<RayRec> = rays
                .par_iter()
                .enumerate()
                .map(|(i, r)| {
                    let slot = i % chunk;
                    let e = tiny_dir::ray_exponent(r.dir);
                    let mut rec = if e == 0 {
                        RayRec::new(r, slot as u32)
                    } else {
                        tiny.store(true, Ordering::Relaxed);
                        RayRec::new(&tiny_dir::scaled_ray(r, e), slot as u32)
                    };
                    // Empty (or NaN) intervals never hit: such rays start inactive.
                    if !interval_nonempty(r) {
                        rec.set_tmax(f32::NEG_INFINITY);
                    }
                    rec
                })
                .collect();
            if tiny.into_inner() {
                exps = rays
                    .par_iter()
                    .map(|r| tiny_dir::ray_exponent(r.dir))
                    .collect();
                scale_slots(rays, &exps, hits, &mut tmin);
            }
            let budget = (p.fork_budget as f64 * rays.len() as f64) as usize;
            let ctx = Ctx {
                tris: &self.tris,
                opts: &self.options,
                any,
                stats: stats.as_ref(),
                parallel,
                budget: AtomicIsize::new(budget as isize),
                workers: parallel::Workers::new(threads),
                // Triangle-split forks copy rays: keep them small enough that several fit
                // in the budget. Ray-split forks copy none.
                data_min_rays: match p.split {
                    ForkSplit::Tris => p.data_min_rays.min((budget / 4).max(4 * p.fork_min_rays)),
                    ForkSplit::Rays => p.data_min_rays,
                },
            };
            let root = Node {
                bounds: self.tris.bounds,
                cents: self.tris.centroids,
            };
            let mut ids = vec![0u32; live];
            self.tris.fill_ids(&mut ids);
            if groups == 1 {
                self.root::<T>(&ctx, &mut recs, hits, &tmin, &mut ids, None);
            } else {
                // The top levels' partitions, made once for every group (`top.rs`).
                let t0 = ctx.clock();
                let shared = match p.top_min_tris {
                    0 => None,
                    m => {
                        // Sample rays estimate how many rays reach each node (and feed the
                        // sampled cost where it is on), drawn whether or not sampling is on.
                        let mut rng = traverse::Rng(rays.len() as u64);
                        let mut buf: Vec<RayRec> = (0..traverse::MAX_SAMPLES.min(rays.len()))
                            .map(|_| recs[rng.below(recs.len())])
                            .collect();
                        let ns = rays::filter(&mut buf, &rays::FilterBox::new(&root.bounds));
                        top::build(&ctx, &buf[..ns], rays.len(), &mut ids, &root, m)
                    }
                };
                if let Some(s) = &stats {
                    lap(&s.split_ns, t0);
                    Stats::add(
                        &s.top_nodes,
                        shared.as_ref().map_or(0, |t| t.count()) as u64,
                    );
                }
                let group = Group {
                    ids: &ids,
                    top: shared.as_ref(),
                    chunk,
                };
                self.groups::<T>(&ctx, &group, &mut recs, hits, &tmin);
            }
        }
        if finish {
            // Slots that found nothing become the contract's miss record; the others get
            // the reported t of their hit (`TriTest::finish_t`, the one place where DACRT
            // writes a final record), from the triangle rebuilt exactly from the precompute.
            // Möller–Trumbore's is its test's t, but for tiny rays' (scaled back).
            let refines = T::PRECISION == Precision::Watertight || !exps.is_empty();
            hits.par_chunks_mut(FINISH_CHUNK)
                .zip(rays.par_chunks(FINISH_CHUNK))
                .for_each(|(hs, rs)| finish_hits::<T>(&self.tris, hs, rs, refines));
        }
        if let Some(s) = &stats {
            crate::note!(
                "{}",
                s.summary(self.name, rays.len(), t0.elapsed().as_secs_f64())
            );
        }
    }

    /// Traces `recs` (whole groups of `group.chunk` rays, the last one maybe shorter) one
    /// group per thread: halves of the groups at a time, through [`parallel::join_tracked`]
    /// so that the forks' bookkeeping sees every thread busy, each group on its own copy of
    /// the (top-partitioned) id array and its own slice of the hit slots.
    fn groups<T: LeafTest>(
        &self,
        ctx: &Ctx,
        group: &Group,
        recs: &mut [RayRec],
        hits: &mut [Hit],
        tmin: &[f32],
    ) {
        if recs.len() <= group.chunk {
            let mut ids = group.ids.to_vec();
            return self.root::<T>(ctx, recs, hits, tmin, &mut ids, group.top);
        }
        let mid = recs.len().div_ceil(group.chunk) / 2 * group.chunk;
        let (r1, r2) = recs.split_at_mut(mid);
        let (h1, h2) = hits.split_at_mut(mid);
        let (t1, t2) = if tmin.is_empty() {
            (tmin, tmin)
        } else {
            tmin.split_at(mid)
        };
        let (_, migrated) = parallel::join_tracked(
            ctx,
            || self.groups::<T>(ctx, group, r1, h1, t1),
            |migrated| {
                self.groups::<T>(ctx, group, r2, h2, t2);
                migrated
            },
        );
        Stats::fork(ctx.stats, migrated);
    }

    /// Filters `recs` against the root box and traces the active ones into `hits` (the
    /// records' slots index `hits` and `tmin`) over the triangles `ids`, already
    /// partitioned as `top` says where it is given.
    fn root<T: LeafTest>(
        &self,
        ctx: &Ctx,
        recs: &mut [RayRec],
        hits: &mut [Hit],
        tmin: &[f32],
        ids: &mut [u32],
        top: Option<&top::Top>,
    ) {
        let root = Node {
            bounds: self.tris.bounds,
            cents: self.tris.centroids,
        };
        let n = ctx.filter(recs, &root.bounds);
        if n > 0 {
            let mut table = Table { hits, tmin };
            step::<T>(ctx, &mut recs[..n], &mut table, ids, &root, 0, top);
        }
    }

    fn trace_all<T: LeafTest>(&self, rays: &[Ray], hits: &mut [Hit], any: bool, finish: bool) {
        assert_eq!(rays.len(), hits.len(), "one hit record per ray");
        let per = SLOT_MASK as usize + 1;
        for (r, h) in rays.chunks(per).zip(hits.chunks_mut(per)) {
            self.batch::<T>(r, h, any, finish);
        }
    }

    fn run(&self, rays: &[Ray], hits: &mut [Hit], any: bool, finish: bool) {
        match self.precision {
            Precision::Fast => self.trace_all::<Moller>(rays, hits, any, finish),
            Precision::Watertight => self.trace_all::<Watertight>(rays, hits, any, finish),
        }
    }
}

/// The hit slots (which start at the ray's `tmax`) and `tmin` table entries of the rays
/// whose exponent in `exps` is not 0, in their scaled units (the records already are).
fn scale_slots(rays: &[Ray], exps: &[i32], hits: &mut [Hit], tmin: &mut [f32]) {
    for (i, (r, &e)) in rays.iter().zip(exps).enumerate() {
        if e != 0 {
            let s = tiny_dir::scaled_ray(r, e);
            hits[i].t = s.tmax;
            if let Some(t) = tmin.get_mut(i) {
                *t = s.tmin;
            }
        }
    }
}

/// The final pass over one chunk of a batch (see [`Dacrt::batch`]). The hits' triangles are
/// read in the rays' order, so at random places in the precompute, and for diffuse rays
/// nearly every one misses the caches: each hit's triangle is prefetched
/// [`FINISH_AHEAD`] hits before it is needed, which halved the pass on diffuse rays
/// (dragon, 786K rays: 19–20 ms to 8.3–8.6 on one thread; BENCHMARKS §24).
fn finish_hits<T: LeafTest>(data: &TriData, hits: &mut [Hit], rays: &[Ray], refines: bool) {
    for i in 0..hits.len() {
        if refines {
            if let Some(ahead) = hits.get(i + FINISH_AHEAD) {
                let j = ahead.prim as usize;
                if let (Some(b), Some(e)) = (data.boxes.get(j), data.extra.get(j)) {
                    crate::simd::prefetch((b as *const tris::TriBox).cast(), 1);
                    crate::simd::prefetch((e as *const tris::TriExtra).cast(), 1);
                }
            }
        }
        let h = &mut hits[i];
        if h.prim == u32::MAX {
            *h = Hit::MISS;
        } else if refines {
            let j = h.prim as usize;
            let v = tris::decode(&data.boxes[j], &data.extra[j]);
            let p = T::Scalar::lane_data(&Triangle { v });
            h.t = T::Scalar::finish_t(&rays[i], &p, h.t);
        }
    }
}

/// Hits per parallel task of the final pass.
const FINISH_CHUNK: usize = 4096;
/// How many hits ahead the final pass prefetches a hit's triangle.
const FINISH_AHEAD: usize = 16;

/// Whether `[tmin, tmax]` holds any `t` (false for NaN bounds).
fn interval_nonempty(r: &Ray) -> bool {
    matches!(
        r.tmin.partial_cmp(&r.tmax),
        Some(std::cmp::Ordering::Less | std::cmp::Ordering::Equal)
    )
}

impl Intersector for Dacrt {
    fn name(&self) -> &'static str {
        self.name
    }

    fn trace(&self, rays: &[Ray], query: Query, hits: &mut [Hit]) {
        self.run(rays, hits, query == Query::Any, true);
    }

    fn occluded(&self, rays: &[Ray], out: &mut [u8]) {
        let mut hits = vec![Hit::MISS; rays.len()];
        self.run(rays, &mut hits, true, false);
        for (o, h) in out.iter_mut().zip(&hits) {
            *o = u8::from(h.prim != u32::MAX);
        }
    }

    fn bytes(&self) -> usize {
        self.tris.bytes()
    }

    /// Recomputes the per-frame precompute, which is all a DACRT "build" is (so a refit
    /// costs the same as a build, and the answers are a fresh build's). Only the count is
    /// checked: with no structure to keep, a triangle may change between degenerate and
    /// not.
    fn refit(&mut self, triangles: &[Triangle]) -> Result<(), AccelError> {
        let expected = self.tris.boxes.len();
        if triangles.len() != expected {
            let reason = RefitError::Count {
                expected,
                got: triangles.len(),
            };
            return Err(AccelError::refit(self.name, reason));
        }
        self.tris = TriData::new(triangles);
        Ok(())
    }
}
