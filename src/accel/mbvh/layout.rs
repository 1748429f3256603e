//! The traversal format of the MBVH accelerators: [`TravNode<N>`] multi-nodes whose leaves
//! point at pre-gathered [`Tri8`] packs, converted from the builder's [`bvh::Mbvh<N>`]
//! (STYLE habit 3: build format → traversal format).
//!
//! The builder's tree already has Áfra's node layout (§3.1); what changes here:
//!
//! - the box planes are one `[[f32; N]; 6]` array (lower corners in rows 0–2, upper
//!   corners in rows 3–5), so that a ray picks its near and far plane of each axis by a
//!   row index computed once per ray from the sign of its direction (Áfra's "near/far by
//!   octant") instead of a per-node select;
//! - leaves hold [`Tri8<T>`] packs in the layout of the chosen triangle test (Möller–
//!   Trumbore stores edges, the watertight test vertices), so that the leaf test is the
//!   same 8-wide test `brute` uses and gives bit-identical t. An MBVH8 leaf (≤ 16
//!   triangles) becomes one or two packs, an MBVH4 leaf (≤ 8 triangles, two 4-wide
//!   multi-triangles in the builder) exactly one.
//!
//! Nodes keep the builder's depth-first order and child-id encoding (sign bit = leaf,
//! bits 0..29 first pack, bits 29..31 pack count − 1), except that empty lanes point at
//! an all-padding pack 0 instead of −1.

use crate::accel::bvh::{self, Child};
use crate::accel::triangle::{Tri8, TriTest};
use crate::geometry::Triangle;

/// One multi-node: N child boxes and N child ids, 32·N bytes (N = 8: four cache lines,
/// N = 4: two), aligned to a cache line.
#[repr(C, align(64))]
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TravNode<const N: usize> {
    /// Box planes `planes[row][lane]`: rows 0, 1, 2 are the lower x, y, z bounds of the
    /// children, rows 3, 4, 5 the upper ones. Empty lanes hold `+inf` lower and `-inf`
    /// upper bounds, which the near/far-by-sign slab test never hits.
    pub planes: [[f32; N]; 6],
    /// Child ids per lane: `>= 0` an inner node's index; sign bit set a leaf (bits 0..29
    /// the first [`Tri8`] pack, bits 29..31 the pack count − 1). Unused lanes are a leaf
    /// of pack 0, which holds only padding: the slab test misses their empty boxes for
    /// every ray with a normal-sized direction, and should NaNs (from a denormal-small
    /// direction) let one through, visiting it is harmless.
    pub child: [i32; N],
    /// Zero; pads the node to whole cache lines.
    pad: [i32; N],
}

const _: () = assert!(std::mem::size_of::<TravNode<8>>() == 256);
const _: () = assert!(std::mem::size_of::<TravNode<4>>() == 128);

/// Splits a leaf id into (first pack, pack count).
#[inline(always)]
pub fn leaf_range(id: i32) -> (usize, usize) {
    let u = id as u32;
    (
        (u & ((1 << Child::FIRST_BITS) - 1)) as usize,
        ((u >> Child::FIRST_BITS) & 3) as usize + 1,
    )
}

/// The whole traversal structure: nodes (root at 0), leaf packs, and what the box test
/// needs to stay conservative.
#[derive(Clone, Debug)]
pub struct TravTree<const N: usize, T> {
    /// Multi-nodes, depth-first, root first.
    pub nodes: Vec<TravNode<N>>,
    /// The leaves' triangles, in leaf order.
    pub packs: Vec<Tri8<T>>,
    /// Largest |coordinate| of the tree's bounds (0 for an empty tree): the scale of the
    /// rounding errors of the triangle tests, see `ray::BoxRay`.
    pub scale: f32,
    /// Deepest multi-node level (root = 1): bounds the traversal stack.
    pub depth: usize,
}

impl<const N: usize, T: TriTest> TravTree<N, T> {
    /// Converts the builder's tree.
    pub fn from_mbvh(tree: &bvh::Mbvh<N>) -> Self {
        let src = tree.nodes();
        let mts = tree.multi_tris();
        let mut nodes = Vec::with_capacity(src.len());
        let mut packs: Vec<Tri8<T>> = Vec::with_capacity(mts.len() * N / 8 + 2);
        // Pack 0 is all padding: empty lanes point at it (see `TravNode::child`).
        packs.push(Tri8::pack(&[]));
        let empty = Child::Leaf { first: 0, count: 1 }.encode();
        let mut lane_buf: Vec<(u32, Triangle)> = Vec::with_capacity(2 * N);
        for n in src {
            let mut planes = [[0.0f32; N]; 6];
            planes[..3].copy_from_slice(&n.min);
            planes[3..].copy_from_slice(&n.max);
            let mut child = n.child;
            for c in child.iter_mut() {
                if *c == Child::EMPTY {
                    *c = empty;
                } else if let Child::Leaf { first, count } = Child::decode(*c) {
                    lane_buf.clear();
                    for mt in &mts[first as usize..(first + count) as usize] {
                        for lane in 0..mt.lanes() {
                            lane_buf.push((mt.ids[lane], mt.get(lane)));
                        }
                    }
                    let start = packs.len() as u32;
                    packs.extend(lane_buf.chunks(8).map(Tri8::pack));
                    let k = packs.len() as u32 - start;
                    assert!((1..=Child::MAX_COUNT).contains(&k), "leaf of {k} packs");
                    *c = Child::Leaf {
                        first: start,
                        count: k,
                    }
                    .encode();
                }
            }
            nodes.push(TravNode {
                planes,
                child,
                pad: [0; N],
            });
        }
        let b = tree.bounds();
        let scale = if b.is_empty() {
            0.0
        } else {
            b.min
                .iter()
                .chain(&b.max)
                .fold(0.0f32, |m, x| m.max(x.abs()))
        };
        TravTree {
            nodes,
            packs,
            scale,
            depth: depth(src),
        }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.nodes.capacity() * std::mem::size_of::<TravNode<N>>()
            + self.packs.capacity() * std::mem::size_of::<Tri8<T>>()
    }
}

/// Deepest level of the builder's tree (root = 1).
fn depth<const N: usize>(nodes: &[bvh::WideNode<N>]) -> usize {
    let mut deepest = 0;
    let mut stack = vec![(0usize, 1usize)];
    while let Some((i, d)) = stack.pop() {
        deepest = deepest.max(d);
        for &c in &nodes[i].child {
            if let Child::Inner(j) = Child::decode(c) {
                stack.push((j as usize, d + 1));
            }
        }
    }
    deepest
}
