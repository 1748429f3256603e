//! The `bvh2` accelerator: Geimer & Müller's binary BVH with skip pointers, traversed
//! without a stack by packets of 4 consecutive rays of the batch. Made for coherent rays
//! (primary rays of neighbouring pixels), where the 4 rays of a packet mostly visit the
//! same nodes; incoherent rays are better served by `mbvh8`.
//!
//! - [`layout`]: the traversal format ([`PacketTree::from_bvh2`]).
//! - [`traverse`]: the packet traversal.

pub mod layout;
pub mod traverse;

pub use layout::{PacketNode, PacketTree};

use super::triangle::{MollerTrumbore, TriTest, Watertight};
use super::{bvh, AccelError, BuildOptions, Intersector, Precision, Query};
use crate::geometry::{Hit, Ray, Triangle};
use crate::simd::{self, Backend, Kernel, Simd};
use rayon::prelude::*;
use traverse::PACKET;

/// Rays per rayon task (a multiple of the packet size).
const CHUNK: usize = 256;
const _: () = assert!(CHUNK.is_multiple_of(PACKET));

#[derive(Clone)]
enum Trees {
    Fast(PacketTree<MollerTrumbore>),
    Watertight(PacketTree<Watertight>),
}

/// The `bvh2` accelerator.
#[derive(Clone)]
pub struct Bvh2Packet {
    trees: Trees,
    backend: Backend,
}

impl Bvh2Packet {
    /// Builds the tree over `triangles` with `options`' quality and precision on the
    /// current rayon pool, tracing with the process's SIMD backend.
    pub fn build(triangles: &[Triangle], options: &BuildOptions) -> Self {
        let tree = bvh::Bvh2::build(triangles, options.quality);
        Self::from_bvh2(&tree, options.precision, simd::selected())
    }

    /// Converts a built tree for the test of `precision`, tracing on `backend`.
    ///
    /// # Panics
    /// If the CPU does not support `backend`.
    pub fn from_bvh2(tree: &bvh::Bvh2, precision: Precision, backend: Backend) -> Self {
        assert!(
            backend.is_supported(),
            "SIMD backend {backend} is not supported on this CPU"
        );
        let trees = match precision {
            Precision::Fast => Trees::Fast(PacketTree::from_bvh2(tree)),
            Precision::Watertight => Trees::Watertight(PacketTree::from_bvh2(tree)),
        };
        Bvh2Packet { trees, backend }
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

/// What a chunk of rays should produce.
enum Out<'a> {
    Hits(Query, &'a mut [Hit]),
    Occluded(&'a mut [u8]),
}

struct Chunk<'a, T> {
    tree: &'a PacketTree<T>,
    rays: &'a [Ray],
    out: Out<'a>,
}

impl<T: TriTest> Kernel for Chunk<'_, T> {
    type Output = ();

    #[inline(always)]
    fn run<S: Simd>(self, s: S) {
        let packets = self.rays.chunks(PACKET);
        match self.out {
            Out::Hits(q, hits) => {
                for (rays, h) in packets.zip(hits.chunks_mut(PACKET)) {
                    traverse::packet(s, self.tree, rays, q, Some(h), None);
                }
            }
            Out::Occluded(occ) => {
                for (rays, o) in packets.zip(occ.chunks_mut(PACKET)) {
                    traverse::packet(s, self.tree, rays, Query::Any, None, Some(o));
                }
            }
        }
    }
}

fn run_tree<T: TriTest>(backend: Backend, tree: &PacketTree<T>, rays: &[Ray], out: Out<'_>) {
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

impl Intersector for Bvh2Packet {
    fn name(&self) -> &'static str {
        "bvh2"
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

    /// Refits the traversal tree in place ([`PacketTree::refit`]); no builder tree is kept.
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

    /// [`PacketTree::slowdown`].
    fn refit_slowdown(&self) -> f64 {
        match &self.trees {
            Trees::Fast(t) => t.slowdown(),
            Trees::Watertight(t) => t.slowdown(),
        }
    }
}
