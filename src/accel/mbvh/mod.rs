//! The `mbvh8` and `mbvh4` accelerators: single-ray ordered traversal of an 8- or 4-wide
//! multi-BVH (Áfra 2013), built by [`crate::accel::bvh`] and converted to a traversal
//! format whose leaves are the 8-wide [`Tri8`] packs of the chosen triangle test.
//!
//! - [`layout`]: the traversal format ([`TravNode`], [`TravTree`]), written straight from
//!   the builder's tree when an accelerator is built, or converted from a built
//!   [`bvh::Mbvh`] ([`TravTree::from_mbvh`]).
//! - [`ray`]: per-ray slab constants and why the slab test is conservative.
//! - [`slab`]: the N-wide slab test.
//! - [`stack`]: the (distance, node) stack and its sorting networks.
//! - [`traverse`]: the ordered closest-hit and the first-hit traversals.
//!
//! All threads share one tree; rays are split into chunks that rayon spreads over the
//! pool the caller installed, and the SIMD backend is entered once per chunk.

pub mod layout;
pub mod ray;
pub mod slab;
pub mod stack;
pub mod traverse;

pub use layout::{TravNode, TravTree};

use super::triangle::{MollerTrumbore, TriTest, Watertight};
use super::{bvh, AccelError, BuildOptions, Intersector, Precision, Query};
use crate::geometry::{Hit, Ray, Triangle};
use crate::simd::{self, Backend, Kernel, Simd};
use rayon::prelude::*;
use slab::{Lanes, SlabTest};
use stack::STACK;

/// Rays per rayon task: a few hundred single-ray traversals amortise the dispatch, the
/// stack allocation and the task, and still leave thousands of tasks for load balance.
const CHUNK: usize = 256;

#[derive(Clone)]
enum Trees<const N: usize> {
    Fast(TravTree<N, MollerTrumbore>),
    Watertight(TravTree<N, Watertight>),
}

/// An N-wide MBVH accelerator (`mbvh8` for N = 8, `mbvh4` for N = 4).
#[derive(Clone)]
pub struct MbvhCore<const N: usize> {
    trees: Trees<N>,
    backend: Backend,
}

/// The `mbvh8` accelerator.
pub type Mbvh8Core = MbvhCore<8>;
/// The `mbvh4` accelerator.
pub type Mbvh4Core = MbvhCore<4>;

impl<const N: usize> MbvhCore<N>
where
    Lanes<N>: SlabTest<N>,
{
    /// Builds the tree over `triangles` with `options`' quality and precision on the
    /// current rayon pool, tracing with the process's SIMD backend.
    pub fn build(triangles: &[Triangle], options: &BuildOptions) -> Self {
        let tree = bvh::WideTree::<N>::build(triangles, options.quality);
        let trees = match options.precision {
            Precision::Fast => Trees::Fast(checked(TravTree::from_wide(&tree, triangles))),
            Precision::Watertight => {
                Trees::Watertight(checked(TravTree::from_wide(&tree, triangles)))
            }
        };
        MbvhCore {
            trees,
            backend: simd::selected(),
        }
    }

    /// Converts a built tree for the test of `precision`, tracing on `backend` (tests and
    /// benchmarks compare backends).
    ///
    /// # Panics
    /// If the CPU does not support `backend`, or the tree is too deep for the stack
    /// (the builder's depth limit makes that impossible).
    pub fn from_mbvh(tree: &bvh::Mbvh<N>, precision: Precision, backend: Backend) -> Self {
        assert!(
            backend.is_supported(),
            "SIMD backend {backend} is not supported on this CPU"
        );
        let trees = match precision {
            Precision::Fast => Trees::Fast(checked(TravTree::from_mbvh(tree))),
            Precision::Watertight => Trees::Watertight(checked(TravTree::from_mbvh(tree))),
        };
        MbvhCore { trees, backend }
    }

    /// The SIMD backend this instance traces with.
    pub fn backend(&self) -> Backend {
        self.backend
    }

    fn run(&self, rays: &[Ray], out: Out<'_>) {
        match &self.trees {
            Trees::Fast(t) => run_tree(self.backend, t, rays, out),
            Trees::Watertight(t) => run_tree(self.backend, t, rays, out),
        }
    }
}

/// Checks that the traversal stack covers the tree.
fn checked<const N: usize, T>(t: TravTree<N, T>) -> TravTree<N, T> {
    assert!(
        t.depth * (N - 1) < STACK,
        "tree depth {} exceeds the traversal stack",
        t.depth
    );
    t
}

/// Counts the steps of `closest` over some rays, on one thread.
struct Counted<'a, const N: usize, T> {
    tree: &'a TravTree<N, T>,
    rays: &'a [Ray],
}

impl<const N: usize, T: TriTest> Kernel for Counted<'_, N, T>
where
    Lanes<N>: SlabTest<N>,
{
    type Output = traverse::Counts;

    #[inline(always)]
    fn run<S: Simd>(self, s: S) -> traverse::Counts {
        let mut stack = [0u64; STACK];
        let mut c = traverse::Counts::default();
        for ray in self.rays {
            traverse::closest_counted(s, self.tree, ray, &mut stack, &mut c);
        }
        c
    }
}

/// What a chunk of rays should produce.
enum Out<'a> {
    Hits(Query, &'a mut [Hit]),
    Occluded(&'a mut [u8]),
}

struct Chunk<'a, const N: usize, T> {
    tree: &'a TravTree<N, T>,
    rays: &'a [Ray],
    out: Out<'a>,
}

impl<const N: usize, T: TriTest> Kernel for Chunk<'_, N, T>
where
    Lanes<N>: SlabTest<N>,
{
    type Output = ();

    #[inline(always)]
    fn run<S: Simd>(self, s: S) {
        let tree = self.tree;
        let mut stack = [0u64; STACK];
        match self.out {
            Out::Hits(Query::Closest, hits) => {
                for (ray, hit) in self.rays.iter().zip(hits) {
                    *hit = traverse::closest(s, tree, ray, &mut stack);
                }
            }
            Out::Hits(Query::Any, hits) => {
                for (ray, hit) in self.rays.iter().zip(hits) {
                    *hit = match traverse::any(s, tree, ray, &mut stack) {
                        Some((h, p)) => Hit {
                            t: T::finish_t(ray, &p, h.t),
                            ..h
                        },
                        None => Hit::MISS,
                    };
                }
            }
            Out::Occluded(out) => {
                for (ray, o) in self.rays.iter().zip(out) {
                    *o = u8::from(traverse::any(s, tree, ray, &mut stack).is_some());
                }
            }
        }
    }
}

fn run_tree<const N: usize, T: TriTest>(
    backend: Backend,
    tree: &TravTree<N, T>,
    rays: &[Ray],
    out: Out<'_>,
) where
    Lanes<N>: SlabTest<N>,
{
    let go = |rays, out| simd::dispatch(backend, Chunk { tree, rays, out });
    match out {
        Out::Hits(q, hits) => rays
            .par_chunks(CHUNK)
            .zip(hits.par_chunks_mut(CHUNK))
            .for_each(|(r, h)| go(r, Out::Hits(q, h))),
        Out::Occluded(occ) => rays
            .par_chunks(CHUNK)
            .zip(occ.par_chunks_mut(CHUNK))
            .for_each(|(r, o)| go(r, Out::Occluded(o))),
    }
}

impl<const N: usize> Intersector for MbvhCore<N>
where
    Lanes<N>: SlabTest<N>,
{
    fn name(&self) -> &'static str {
        if N == 8 {
            "mbvh8"
        } else {
            "mbvh4"
        }
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
        match &self.trees {
            Trees::Fast(t) => t.bytes(),
            Trees::Watertight(t) => t.bytes(),
        }
    }

    fn stats(&self) -> Option<serde_json::Value> {
        Some(match &self.trees {
            Trees::Fast(t) => t.stats(),
            Trees::Watertight(t) => t.stats(),
        })
    }

    fn count_steps(&self, rays: &[Ray]) -> Option<serde_json::Value> {
        let c = match &self.trees {
            Trees::Fast(t) => simd::dispatch(self.backend, Counted { tree: t, rays }),
            Trees::Watertight(t) => simd::dispatch(self.backend, Counted { tree: t, rays }),
        };
        let n = rays.len().max(1) as f64;
        Some(serde_json::json!({
            "rays": rays.len(),
            "nodes_per_ray": c.nodes as f64 / n,
            "packs_per_ray": c.packs as f64 / n,
            "triangle_lanes_per_ray": 8.0 * c.packs as f64 / n,
        }))
    }

    /// Refits the traversal tree in place ([`TravTree::refit`]); no builder tree is kept.
    fn refit(&mut self, triangles: &[Triangle]) -> Result<(), AccelError> {
        let done = match &mut self.trees {
            Trees::Fast(t) => t.refit(triangles),
            Trees::Watertight(t) => t.refit(triangles),
        };
        done.map_err(|e| AccelError::refit(self.name(), e))
    }

    fn refit_copy(&self, triangles: &[Triangle]) -> Result<Box<dyn Intersector>, AccelError> {
        let mut copy = self.clone();
        copy.refit(triangles)?;
        Ok(Box::new(copy))
    }

    /// [`TravTree::slowdown`].
    fn refit_slowdown(&self) -> f64 {
        match &self.trees {
            Trees::Fast(t) => t.slowdown(),
            Trees::Watertight(t) => t.slowdown(),
        }
    }
}
