//! Static bounding volume hierarchies: the acceleration structures behind the `mbvh8`,
//! `mbvh4` and `bvh2` accelerators (traversal lives elsewhere; this module only builds,
//! refits, checks and measures the trees).
//!
//! # Layouts
//!
//! - [`Mbvh<N>`] ([`Mbvh8`], [`Mbvh4`]): Áfra 2013 §3.1. One node type, [`WideNode<N>`],
//!   holding N child boxes in SoA form and N 32-bit child ids; leaves are lists of up to
//!   two pre-gathered SoA multi-triangles ([`MultiTri<N>`]) of N triangles each.
//! - [`Bvh2`]: Geimer & Müller §3.3. A binary BVH stored depth-first with skip pointers,
//!   32-byte [`Bvh2Node`]s, the child with the larger surface area first.
//!
//! # Construction (one builder for all three)
//!
//! Áfra §3.2: multi-nodes are built top-down by *horizontal splitting* (repeatedly split
//! the child with the largest surface area while eq. 1 says it pays and fewer than N
//! children exist) and *vertical splitting* (a child becomes a new multi-node when eq. 2,
//! with K_T = K_I = 1, is cheaper than a leaf). Costs count multi-triangles, `⌈T/N⌉`.
//! Leaves hold at most 2N triangles; a node with one triangle is always a leaf. The binary
//! [`Bvh2`] is the same construction with N = 2 and a per-triangle cost (`⌈T/1⌉`).
//!
//! The binary split a candidate child offers depends on [`BuildQuality`]:
//!
//! - `Sah`: binned SAH over triangle centroids, 32 bins on each axis, with the cost of
//!   eq. 1 (counts rounded up to whole multi-triangles). Small ranges are cheaper to split
//!   otherwise: up to 128 references use 16 bins, up to 24 an exact sweep over their
//!   sorted centroids (on the dragon these cut the build's instructions by 7% for a SAH
//!   cost within 0.1%).
//! - `Sbvh`: the same object splits plus spatial splits (Stich, Friedrich & Dietrich
//!   2009): 16 spatial bins per axis with references chopped at the bin planes, tried
//!   when the best object split's children overlap by more than α = 1e-5 of the root's
//!   surface area (and the range has more than 24 references); straddling references are
//!   duplicated unless reference unsplitting is cheaper. References may grow to twice
//!   the triangle count.
//! - `Fast`: a Morton-code build. Centroids are quantised to 10 bits per axis, radix
//!   sorted, and a binary radix tree (split at the highest differing bit, median for equal
//!   codes) is made with bounds bottom-up; the multi-node construction above then collapses
//!   it, still stopping by eq. 1 and eq. 2. No binning at all, so it is several times
//!   quicker than `Sah`, with trees 15–35% worse by SAH cost (see [`BvhStats::sah_cost`]).
//!
//! A candidate's split is only looked for when the construction needs it: to pick what
//! to split horizontally (largest area first) and for the vertical decision, which eq. 2
//! settles without a split for leaves that cost no more than a traversal step (at most N
//! triangles).
//!
//! Triangles that [`Triangle::is_degenerate`] (or that have a non-finite coordinate) are
//! left out of every tree: the contract says they are never hit. Their ids are kept so
//! that [`Mbvh::refit`] can tell when a refit would need them.
//!
//! # Threads
//!
//! Builds and refits run on the rayon pool they are called in: binning is split across
//! threads near the top of the tree and subtrees are built as parallel tasks below. The
//! result does not depend on the number of threads.
//!
//! [`BuildQuality`]: crate::accel::BuildQuality
//! [`Triangle::is_degenerate`]: crate::geometry::Triangle::is_degenerate

mod binning;
mod build;
mod bvh2;
mod morton;
mod refit;
mod sbvh;
mod stats;
mod validate;
mod wide;

pub(crate) use build::half_area;

/// A refitted tree's surface-area cost `now` over its cost as `built` (measured before its
/// first refit, `None` for a tree never refitted): about how much slower it traces than
/// when it was built; 1 where either cost is unknown or 0 (an empty or flat tree).
pub(crate) fn drift(now: f64, built: Option<f64>) -> f64 {
    match built {
        Some(b) if b > 0.0 && now > 0.0 => now / b,
        _ => 1.0,
    }
}
pub(crate) use refit::check as check_refit;

pub use bvh2::{Bvh2, Bvh2Node, Bvh2Tri, BVH2_MAX_LEAF};
pub use stats::BvhStats;
pub use wide::{Child, Mbvh, Mbvh4, Mbvh8, MultiTri, WideNode};
pub(crate) use wide::{WideLane, WideTree};

/// Why [`Mbvh::refit`] or [`Bvh2::refit`] refused new positions. The tree is left
/// unchanged; rebuild it instead.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum RefitError {
    /// The new positions are for a different number of triangles.
    #[error("refit needs {expected} triangles, got {got}")]
    Count {
        /// Triangles the tree was built over.
        expected: usize,
        /// Triangles given.
        got: usize,
    },
    /// A triangle that was left out of the tree (degenerate or non-finite) is now a
    /// proper triangle, or the other way round: the tree's topology no longer covers the
    /// scene.
    #[error(
        "triangle {id} changed between degenerate and non-degenerate; the tree must be rebuilt"
    )]
    Degeneracy {
        /// The first such triangle id found.
        id: u32,
    },
    /// The accelerator has no way to take new positions (only a new build helps).
    #[error("this accelerator cannot refit; it must be rebuilt")]
    Unsupported,
}

/// Deepest multi-node level (or binary level for [`Bvh2`]) built with the split the
/// quality chooses; below it every split is a spatial median split, so the depth of any
/// tree stays below `DEPTH_LIMIT + 32` whatever the input (traversal stacks may rely on
/// it).
pub const DEPTH_LIMIT: u32 = 64;

/// Whether a triangle can go into a tree: not degenerate and with finite coordinates
/// (a NaN or infinite vertex would poison every box above it).
#[inline]
pub(crate) fn is_traceable(t: &crate::geometry::Triangle) -> bool {
    // `x · 0` is ±0 for a finite x and NaN for an infinite or NaN one, and a sum with a
    // NaN term is NaN: one branch instead of nine.
    let s: f32 = t.v.iter().flatten().map(|&x| x * 0.0).sum();
    s == 0.0 && !t.is_degenerate()
}
