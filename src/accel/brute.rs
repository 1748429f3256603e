//! Brute force: every ray against every triangle, 8 triangles per SIMD test.
//!
//! The reference accelerator (small scenes only) and the baseline of the benchmarks. The
//! non-degenerate triangles are packed in id order into [`Tri8`] multi-triangles; each ray
//! keeps a per-lane best (t, pack) while it sweeps the packs, so the inner loop has no
//! horizontal operations, and one reduction at the end applies the contract's tie rule
//! (smallest t, then lowest id). Rays are split into chunks that rayon spreads over the pool
//! the caller installed; the SIMD backend is chosen once per chunk.

use super::bvh::RefitError;
use super::triangle::{
    pack_all, MollerTrumbore, PreparedRay, PreparedRay8, Tri8, TriTest, Watertight,
};
use super::{AccelError, Intersector, Precision, Query};
use crate::geometry::{Hit, Ray, Triangle};
use crate::simd::{self, Backend, FloatV, IntV, Kernel, MaskV, Select, Simd};
use rayon::prelude::*;

/// Rays per rayon task: small enough to balance 2–64 threads on a few thousand rays, large
/// enough that dispatch and task overhead vanish next to ≥ 1 pack per ray.
const CHUNK: usize = 64;

enum Packs {
    Fast(Vec<Tri8<MollerTrumbore>>),
    Watertight(Vec<Tri8<Watertight>>),
}

/// Every ray against every triangle.
pub struct Brute {
    packs: Packs,
    backend: Backend,
    /// Triangles given (all ids): what a refit must bring.
    count: usize,
}

impl Brute {
    /// Packs the non-degenerate `triangles` for the test of `precision`, using the process's
    /// SIMD backend ([`simd::selected`]).
    pub fn new(triangles: &[Triangle], precision: Precision) -> Brute {
        Brute::with_backend(triangles, precision, simd::selected())
    }

    /// As [`Brute::new`] on an explicit backend (tests and benchmarks compare backends).
    ///
    /// # Panics
    /// If the CPU does not support `backend`.
    pub fn with_backend(triangles: &[Triangle], precision: Precision, backend: Backend) -> Brute {
        assert!(
            backend.is_supported(),
            "SIMD backend {backend} is not supported on this CPU"
        );
        let packs = match precision {
            Precision::Fast => Packs::Fast(pack_all(triangles)),
            Precision::Watertight => Packs::Watertight(pack_all(triangles)),
        };
        Brute {
            packs,
            backend,
            count: triangles.len(),
        }
    }

    /// The SIMD backend this instance traces with.
    pub fn backend(&self) -> Backend {
        self.backend
    }
}

/// What a chunk of rays should produce.
enum Out<'a> {
    Hits(Query, &'a mut [Hit]),
    Occluded(&'a mut [u8]),
}

struct Chunk<'a, T> {
    packs: &'a [Tri8<T>],
    rays: &'a [Ray],
    out: Out<'a>,
}

impl<T: TriTest> Kernel for Chunk<'_, T> {
    type Output = ();

    #[inline(always)]
    fn run<S: Simd>(self, s: S) {
        let packs = self.packs;
        match self.out {
            Out::Hits(Query::Closest, hits) => {
                for (ray, hit) in self.rays.iter().zip(hits) {
                    *hit = closest(s, packs, ray);
                }
            }
            Out::Hits(Query::Any, hits) => {
                for (ray, hit) in self.rays.iter().zip(hits) {
                    *hit = match first_hit(s, packs, ray) {
                        Some((r, p, lane)) => fields(ray, &r, &packs[p], lane),
                        None => Hit::MISS,
                    };
                }
            }
            Out::Occluded(out) => {
                for (ray, o) in self.rays.iter().zip(out) {
                    *o = u8::from(first_hit(s, packs, ray).is_some());
                }
            }
        }
    }
}

/// The hit record of lane `lane` of `pack`, from the scalar test (bit-identical to the
/// 8-wide one that found it) and the test's [`TriTest::finish_t`]: the one place where
/// `brute` writes a hit.
#[inline]
fn fields<T: TriTest>(ray: &Ray, r: &PreparedRay, pack: &Tri8<T>, lane: usize) -> Hit {
    match T::intersect1(r, pack, lane, r.tmax) {
        Some(h) => Hit {
            t: T::finish_t(ray, &pack.lane(lane), h.t),
            prim: pack.ids[lane],
            u: h.u,
            v: h.v,
        },
        None => {
            debug_assert!(false, "scalar and 8-wide tests disagree");
            Hit::MISS
        }
    }
}

/// The closest hit: per-lane best over all packs, then (t, pack, lane) minimum, which is
/// (t, id) because packs and lanes are in id order.
#[inline(always)]
fn closest<S: Simd, T: TriTest>(s: S, packs: &[Tri8<T>], ray: &Ray) -> Hit {
    let r = PreparedRay::new(ray);
    if r.is_empty() {
        return Hit::MISS;
    }
    let r8 = PreparedRay8::new(s, &r);
    let tmax = s.splat_f8(r.tmax);
    let mut best_t = s.splat_f8(f32::INFINITY);
    let mut best_p = s.splat_i8(0);
    let mut empty = s.mask8(0xff);
    for (i, pack) in packs.iter().enumerate() {
        let (hit, t) = T::intersect8(s, &r8, pack, tmax);
        if hit.none() {
            // The common case; lets the tests' early exits skip the update entirely.
            continue;
        }
        // Strictly smaller t only: an equal t in a later pack has a higher id.
        let better = hit & (t.lt(best_t) | empty);
        if better.any() {
            best_t = better.select(t, best_t);
            best_p = better.select(s.splat_i8(i as i32), best_p);
            empty = empty.andnot(better);
        }
    }
    let found = !empty.bitmask() & 0xff;
    if found == 0 {
        return Hit::MISS;
    }
    let (ts, ps) = (best_t.to_array(), best_p.to_array());
    let mut win = found.trailing_zeros() as usize;
    for lane in 0..8 {
        if found >> lane & 1 == 1 {
            let key = (ts[lane], ps[lane], lane);
            let cur = (ts[win], ps[win], win);
            if key.0 < cur.0 || (key.0 == cur.0 && (key.1, key.2) < (cur.1, cur.2)) {
                win = lane;
            }
        }
    }
    fields(ray, &r, &packs[ps[win] as usize], win)
}

/// The first hit in pack order: `(prepared ray, pack index, lane)`.
#[inline(always)]
fn first_hit<S: Simd, T: TriTest>(
    s: S,
    packs: &[Tri8<T>],
    ray: &Ray,
) -> Option<(PreparedRay, usize, usize)> {
    let r = PreparedRay::new(ray);
    if r.is_empty() {
        return None;
    }
    let r8 = PreparedRay8::new(s, &r);
    let tmax = s.splat_f8(r.tmax);
    for (i, pack) in packs.iter().enumerate() {
        let (hit, _) = T::intersect8(s, &r8, pack, tmax);
        if hit.any() {
            return Some((r, i, hit.bitmask().trailing_zeros() as usize));
        }
    }
    None
}

impl Brute {
    fn run(&self, rays: &[Ray], out: Out<'_>) {
        fn go<T: TriTest>(backend: Backend, packs: &[Tri8<T>], rays: &[Ray], out: Out<'_>) {
            match out {
                Out::Hits(q, hits) => rays
                    .par_chunks(CHUNK)
                    .zip(hits.par_chunks_mut(CHUNK))
                    .for_each(|(rays, hits)| {
                        simd::dispatch(
                            backend,
                            Chunk {
                                packs,
                                rays,
                                out: Out::Hits(q, hits),
                            },
                        )
                    }),
                Out::Occluded(occ) => rays
                    .par_chunks(CHUNK)
                    .zip(occ.par_chunks_mut(CHUNK))
                    .for_each(|(rays, occ)| {
                        simd::dispatch(
                            backend,
                            Chunk {
                                packs,
                                rays,
                                out: Out::Occluded(occ),
                            },
                        )
                    }),
            }
        }
        match &self.packs {
            Packs::Fast(p) => go(self.backend, p, rays, out),
            Packs::Watertight(p) => go(self.backend, p, rays, out),
        }
    }
}

impl Intersector for Brute {
    fn name(&self) -> &'static str {
        "brute"
    }

    fn trace(&self, rays: &[Ray], query: Query, hits: &mut [Hit]) {
        assert_eq!(rays.len(), hits.len(), "one hit record per ray");
        self.run(rays, Out::Hits(query, hits));
    }

    fn occluded(&self, rays: &[Ray], out: &mut [u8]) {
        assert_eq!(rays.len(), out.len(), "one output byte per ray");
        self.run(rays, Out::Occluded(out));
    }

    fn bytes(&self) -> usize {
        let tri8 = std::mem::size_of::<Tri8<Watertight>>();
        match &self.packs {
            Packs::Fast(p) => p.capacity() * tri8,
            Packs::Watertight(p) => p.capacity() * tri8,
        }
    }

    /// Replaces the packs (brute's whole "build"). Only the count is checked: with no
    /// structure to keep, a triangle may change between degenerate and not.
    fn refit(&mut self, triangles: &[Triangle]) -> Result<(), AccelError> {
        if triangles.len() != self.count {
            let reason = RefitError::Count {
                expected: self.count,
                got: triangles.len(),
            };
            return Err(AccelError::refit(self.name(), reason));
        }
        self.packs = match self.packs {
            Packs::Fast(_) => Packs::Fast(pack_all(triangles)),
            Packs::Watertight(_) => Packs::Watertight(pack_all(triangles)),
        };
        Ok(())
    }
}
