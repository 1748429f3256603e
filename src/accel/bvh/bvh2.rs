//! The binary BVH of Geimer & Müller (§3.3) for the `bvh2` accelerator: nodes in one array
//! in depth-first order, each with a *skip pointer* to the node that follows its subtree,
//! so that traversal is a loop without a stack:
//!
//! ```text
//! i = 0
//! while i < nodes.len():
//!     if packet hits nodes[i]: (if leaf: test its triangles); i += 1
//!     else: i = nodes[i].skip
//! ```
//!
//! (For a leaf `skip == i + 1`, so "after a leaf" and "missed" agree.) The children of
//! each node are ordered by surface area, larger first, as the paper does to find a hit
//! early and shorten the rays. The tree comes from the same builder as the MBVHs with
//! N = 2 and per-triangle costs.

use super::build::{self, half_area, inner, BNode, CostModel, Kid, Ref};
use crate::accel::BuildQuality;
use crate::geometry::{Aabb, Triangle};

/// Subtrees with at least this many nodes are flattened as separate rayon tasks.
const PAR_EMIT: u32 = 256;

/// Most triangles in a [`Bvh2`] leaf.
pub const BVH2_MAX_LEAF: u32 = 8;

/// One node of a [`Bvh2`]: its own box, its skip pointer and, for a leaf, its triangles.
/// 32 bytes, aligned to 32 so that no node straddles a cache line (Geimer & Müller §3.3).
#[repr(C, align(32))]
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bvh2Node {
    /// Lower corner of the node's box.
    pub min: [f32; 3],
    /// Index of the first node after this node's subtree in depth-first order: where
    /// traversal continues when the box is missed (and, for a leaf, after it). The last
    /// subtree's nodes skip to `nodes.len()`, which ends the traversal.
    pub skip: u32,
    /// Upper corner of the node's box.
    pub max: [f32; 3],
    /// 0 for an inner node (its first child is the next node, its second child is at the
    /// first child's `skip`). For a leaf: bits 0..4 hold the triangle count (1..=8) and
    /// bits 4..32 the index of its first triangle in [`Bvh2::tris`].
    pub prims: u32,
}

const _: () = assert!(std::mem::size_of::<Bvh2Node>() == 32);

impl Bvh2Node {
    /// Whether the node is a leaf.
    #[inline]
    pub fn is_leaf(&self) -> bool {
        self.prims != 0
    }

    /// A leaf's triangles: (first, count); `(0, 0)` for an inner node.
    #[inline]
    pub fn leaf_range(&self) -> (u32, u32) {
        (self.prims >> 4, self.prims & 15)
    }

    /// The node's box.
    pub fn aabb(&self) -> Aabb {
        Aabb {
            min: self.min,
            max: self.max,
        }
    }

    fn new(b: &Aabb, skip: u32, prims: u32) -> Self {
        Bvh2Node {
            min: b.min,
            skip,
            max: b.max,
            prims,
        }
    }
}

/// One triangle of a [`Bvh2`] leaf, padded to 48 bytes as Geimer & Müller §3.2 do with
/// the id in the padding. We keep the three vertices (not v0 and two edges as the paper
/// does) so that the watertight test sees the exact stored positions; edges are one
/// subtraction away.
#[repr(C, align(16))]
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bvh2Tri {
    /// First vertex.
    pub v0: [f32; 3],
    /// Triangle id (contract §1).
    pub id: u32,
    /// Second vertex.
    pub v1: [f32; 3],
    /// Reserved, zero.
    pub pad1: u32,
    /// Third vertex.
    pub v2: [f32; 3],
    /// Reserved, zero.
    pub pad2: u32,
}

const _: () = assert!(std::mem::size_of::<Bvh2Tri>() == 48);

impl Bvh2Tri {
    const ZERO: Bvh2Tri = Bvh2Tri {
        v0: [0.0; 3],
        id: 0,
        v1: [0.0; 3],
        pad1: 0,
        v2: [0.0; 3],
        pad2: 0,
    };

    /// Triangle `t` with id `id`.
    pub fn new(id: u32, t: &Triangle) -> Self {
        Bvh2Tri {
            v0: t.v[0],
            id,
            v1: t.v[1],
            pad1: 0,
            v2: t.v[2],
            pad2: 0,
        }
    }

    /// The triangle.
    pub fn triangle(&self) -> Triangle {
        Triangle {
            v: [self.v0, self.v1, self.v2],
        }
    }
}

/// A binary BVH with skip pointers over a triangle scene (Geimer & Müller): the
/// structure behind `bvh2`. Built by [`Bvh2::build`], updated by [`Bvh2::refit`].
#[derive(Clone, Debug)]
pub struct Bvh2 {
    pub(super) nodes: Vec<Bvh2Node>,
    pub(super) tris: Vec<Bvh2Tri>,
    pub(super) excluded: Vec<u32>,
    pub(super) triangles: usize,
    pub(super) quality: BuildQuality,
    pub(super) clipped: bool,
    /// Whether children are still ordered by area (true until a refit).
    pub(super) sorted: bool,
}

impl Bvh2 {
    /// The cost model: K_T = K_I = 1 per triangle, at most [`BVH2_MAX_LEAF`] per leaf.
    pub(super) fn cost() -> CostModel {
        CostModel::new(1, BVH2_MAX_LEAF, 1.0, 1.0)
    }

    /// Builds the tree over `triangles` (ids are their indices) on the current rayon
    /// pool. Degenerate and non-finite triangles are left out; with none left the tree
    /// has no nodes.
    pub fn build(triangles: &[Triangle], quality: BuildQuality) -> Self {
        let built = build::build::<2>(triangles, quality, Self::cost());
        let root = &built.arena[0];
        let (n_nodes, n_tris) = match root.count {
            0 => (0, 0),
            1 => (1, root.sub.refs),
            _ => (root.sub.nodes + root.sub.leaves, root.sub.refs),
        };
        assert!(
            n_tris < 1 << 28,
            "too many triangle records for the leaf encoding"
        );
        let mut nodes = vec![Bvh2Node::new(&Aabb::EMPTY, 0, 0); n_nodes as usize];
        let mut tris = vec![Bvh2Tri::ZERO; n_tris as usize];
        match root.count {
            0 => {}
            1 => emit(
                &built.arena,
                &root.boxes[0],
                &root.kids[0],
                &mut nodes,
                0,
                &mut tris,
                0,
                &built.refs,
                triangles,
            ),
            _ => emit_inner(
                &built.arena,
                0,
                &build::union(&root.boxes[0], &root.boxes[1]),
                &mut nodes,
                0,
                &mut tris,
                0,
                &built.refs,
                triangles,
            ),
        }
        Bvh2 {
            nodes,
            tris,
            excluded: built.excluded,
            triangles: triangles.len(),
            quality,
            clipped: quality == BuildQuality::Sbvh,
            sorted: true,
        }
    }

    /// The nodes in depth-first order, root first.
    pub fn nodes(&self) -> &[Bvh2Node] {
        &self.nodes
    }

    /// The leaves' triangles.
    pub fn tris(&self) -> &[Bvh2Tri] {
        &self.tris
    }

    /// Box of everything in the tree.
    pub fn bounds(&self) -> Aabb {
        self.nodes.first().map_or(Aabb::EMPTY, |n| n.aabb())
    }

    /// Number of triangles the tree was built over.
    pub fn triangle_count(&self) -> usize {
        self.triangles
    }

    /// Ids of the triangles left out of the tree, ascending.
    pub fn excluded(&self) -> &[u32] {
        &self.excluded
    }

    /// The quality it was built with.
    pub fn quality(&self) -> BuildQuality {
        self.quality
    }

    /// Bytes held by nodes and triangles.
    pub fn bytes(&self) -> usize {
        self.nodes.len() * std::mem::size_of::<Bvh2Node>()
            + self.tris.len() * std::mem::size_of::<Bvh2Tri>()
            + self.excluded.len() * 4
    }
}

/// Nodes and triangle records of a child's subtree.
fn size_of_kid(arena: &[BNode<2>], kid: &Kid<2>) -> (u32, u32) {
    match kid {
        Kid::Leaf { n, .. } => (1, *n),
        _ => {
            let (a, j) = inner(arena, kid).expect("an inner child");
            let s = a[j].sub;
            (s.nodes + s.leaves, s.refs)
        }
    }
}

/// Writes the subtree of child `kid` (box `b`) at `nodes[0]` (global index `base`).
#[allow(clippy::too_many_arguments)]
fn emit(
    arena: &[BNode<2>],
    b: &Aabb,
    kid: &Kid<2>,
    nodes: &mut [Bvh2Node],
    base: u32,
    out: &mut [Bvh2Tri],
    tbase: u32,
    refs: &[Ref],
    tris: &[Triangle],
) {
    if let Kid::Leaf { begin, n } = *kid {
        nodes[0] = Bvh2Node::new(b, base + 1, (tbase << 4) | n);
        for (o, r) in out
            .iter_mut()
            .zip(&refs[begin as usize..(begin + n) as usize])
        {
            *o = Bvh2Tri::new(r.id(), &tris[r.id() as usize]);
        }
    } else {
        let (a, j) = inner(arena, kid).expect("an inner child");
        emit_inner(a, j, b, nodes, base, out, tbase, refs, tris);
    }
}

/// Writes inner node `arena[idx]` (box `b`) and its subtree.
#[allow(clippy::too_many_arguments)]
fn emit_inner(
    arena: &[BNode<2>],
    idx: usize,
    b: &Aabb,
    nodes: &mut [Bvh2Node],
    base: u32,
    out: &mut [Bvh2Tri],
    tbase: u32,
    refs: &[Ref],
    tris: &[Triangle],
) {
    let node = &arena[idx];
    debug_assert_eq!(node.count, 2, "inner binary nodes have two children");
    let (me, rest) = nodes.split_first_mut().expect("a node's slot");
    *me = Bvh2Node::new(b, base + 1 + rest.len() as u32, 0);
    // Larger surface area first (Geimer & Müller §3.3).
    let order = if half_area(&node.boxes[1]) > half_area(&node.boxes[0]) {
        [1, 0]
    } else {
        [0, 1]
    };
    let (n0, t0) = size_of_kid(arena, &node.kids[order[0]]);
    let (first_nodes, second_nodes) = rest.split_at_mut(n0 as usize);
    let (first_tris, second_tris) = out.split_at_mut(t0 as usize);
    let mut go0 = move || {
        emit(
            arena,
            &node.boxes[order[0]],
            &node.kids[order[0]],
            first_nodes,
            base + 1,
            first_tris,
            tbase,
            refs,
            tris,
        )
    };
    let mut go1 = move || {
        emit(
            arena,
            &node.boxes[order[1]],
            &node.kids[order[1]],
            second_nodes,
            base + 1 + n0,
            second_tris,
            tbase + t0,
            refs,
            tris,
        )
    };
    if node.sub.nodes >= PAR_EMIT && rayon::current_num_threads() > 1 {
        rayon::join(go0, go1);
    } else {
        go0();
        go1();
    }
}
