//! The N-wide MBVH layout of Áfra 2013 §3.1: [`WideNode<N>`] multi-nodes and pre-gathered
//! [`MultiTri<N>`] leaves, flattened from the builder's intermediate tree.
//!
//! Nodes are stored depth-first (pre-order) with the root at index 0: a node's subtree
//! occupies one contiguous index range, children come after their parent in lane order,
//! and the multi-triangles of a subtree are contiguous too. Refit relies on that.

use rayon::prelude::*;

use super::build::{self, inner, BNode, CostModel, Kid, Ref};
use crate::accel::BuildQuality;
use crate::geometry::{Aabb, Triangle};

/// Subtrees with at least this many nodes are flattened as separate rayon tasks.
const PAR_EMIT: u32 = 64;

/// One multi-node of an N-wide MBVH (N = 8: 256 bytes; N = 4: 128 bytes), after Áfra 2013
/// §3.1. A node stores its children's boxes, not its own; there is no separate leaf node
/// type: a leaf is a child id that points at multi-triangles.
///
/// Lanes in use come first; the remaining lanes are *empty*: box `min = +inf`,
/// `max = -inf` and id [`Child::EMPTY`]. An empty box is missed by the slab test that
/// takes the near plane by the sign of the ray direction (near = min for a positive
/// component, max for a negative one): its entry distance is +inf and its exit −inf on
/// every axis. Note that the variant which orders each axis pair with `min`/`max` does
/// NOT reject it for negative directions; traversals must use the sign-selected form or
/// mask lanes by id.
#[repr(C, align(64))]
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WideNode<const N: usize> {
    /// Lower corners of the child boxes, `min[axis][lane]` (SoA, one SIMD load per
    /// axis). `+inf` in empty lanes.
    pub min: [[f32; N]; 3],
    /// Upper corners of the child boxes, `max[axis][lane]`. `-inf` in empty lanes.
    pub max: [[f32; N]; 3],
    /// Child ids, one per lane (decode with [`Child::decode`]):
    /// - `id >= 0`: an inner child, the index of its node in [`Mbvh::nodes`];
    /// - sign bit set: a leaf; bits 0..29 are the index of its first multi-triangle in
    ///   [`Mbvh::multi_tris`] and bits 29..31 the number of its multi-triangles minus one
    ///   (the builder makes 1 or 2: at most 2N triangles per leaf);
    /// - [`Child::EMPTY`] (−1) in empty lanes.
    pub child: [i32; N],
    /// Reserved, zero: pads the node to 32·N bytes (a whole number of cache lines).
    pub pad: [u32; N],
}

const _: () = assert!(std::mem::size_of::<WideNode<8>>() == 256);
const _: () = assert!(std::mem::size_of::<WideNode<4>>() == 128);
const _: () = assert!(std::mem::align_of::<WideNode<8>>() == 64);
const _: () = assert!(std::mem::align_of::<WideNode<4>>() == 64);

impl<const N: usize> WideNode<N> {
    /// A node with every lane empty.
    pub const EMPTY: Self = WideNode {
        min: [[f32::INFINITY; N]; 3],
        max: [[f32::NEG_INFINITY; N]; 3],
        child: [Child::EMPTY; N],
        pad: [0; N],
    };

    /// Box of lane `i`.
    pub fn lane_box(&self, i: usize) -> Aabb {
        Aabb {
            min: [self.min[0][i], self.min[1][i], self.min[2][i]],
            max: [self.max[0][i], self.max[1][i], self.max[2][i]],
        }
    }

    /// Sets the box of lane `i`.
    pub fn set_lane_box(&mut self, i: usize, b: &Aabb) {
        for a in 0..3 {
            self.min[a][i] = b.min[a];
            self.max[a][i] = b.max[a];
        }
    }

    /// Number of lanes in use.
    pub fn lanes(&self) -> usize {
        self.child
            .iter()
            .take_while(|&&c| c != Child::EMPTY)
            .count()
    }

    /// Union of the boxes of the lanes in use (the node's own box).
    pub fn bounds(&self) -> Aabb {
        let mut b = Aabb::EMPTY;
        for i in 0..self.lanes() {
            b.union(&self.lane_box(i));
        }
        b
    }
}

/// A decoded child id of a [`WideNode`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Child {
    /// An inner node: its index in [`Mbvh::nodes`].
    Inner(u32),
    /// A leaf: `count` multi-triangles from index `first` of [`Mbvh::multi_tris`].
    Leaf {
        /// First multi-triangle.
        first: u32,
        /// Number of multi-triangles, 1..=4.
        count: u32,
    },
    /// An unused lane.
    Empty,
}

impl Child {
    /// The id of empty lanes. As a leaf it would decode to 4 multi-triangles at index
    /// 2^29 − 1, which no tree reaches, so misuse fails loudly on an index check.
    pub const EMPTY: i32 = -1;
    /// Set on leaf ids.
    pub const LEAF_BIT: u32 = 1 << 31;
    /// Bits of the first multi-triangle index in a leaf id.
    pub const FIRST_BITS: u32 = 29;
    /// Most multi-triangles a leaf id can hold.
    pub const MAX_COUNT: u32 = 4;

    /// Decodes a [`WideNode::child`] entry.
    #[inline]
    pub fn decode(id: i32) -> Child {
        if id >= 0 {
            Child::Inner(id as u32)
        } else if id == Child::EMPTY {
            Child::Empty
        } else {
            let u = id as u32;
            Child::Leaf {
                first: u & ((1 << Child::FIRST_BITS) - 1),
                count: ((u >> Child::FIRST_BITS) & 3) + 1,
            }
        }
    }

    /// Encodes as a [`WideNode::child`] entry.
    #[inline]
    pub fn encode(self) -> i32 {
        match self {
            Child::Inner(i) => {
                debug_assert!(i < 1 << 31);
                i as i32
            }
            Child::Leaf { first, count } => {
                debug_assert!((1..=Child::MAX_COUNT).contains(&count));
                debug_assert!(first < (1 << Child::FIRST_BITS) - 1);
                (Child::LEAF_BIT | ((count - 1) << Child::FIRST_BITS) | first) as i32
            }
            Child::Empty => Child::EMPTY,
        }
    }
}

/// N triangles gathered for one SIMD test (Áfra 2013 §3.1), SoA: `v0[axis][lane]` etc.
/// Lanes in use come first. Padding lanes have id [`MultiTri::PAD_ID`] and all three
/// vertices at the origin: a finite, NaN-free point triangle (e1 = e2 = 0 exactly, so a
/// Möller–Trumbore determinant is exactly 0). A watertight test whose edge functions use
/// FMA can see rounding noise instead of exact zeros on such a triangle, so kernels
/// should also mask lanes by `ids != PAD_ID`.
#[repr(C, align(32))]
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MultiTri<const N: usize> {
    /// First vertices, `v0[axis][lane]`.
    pub v0: [[f32; N]; 3],
    /// Second vertices.
    pub v1: [[f32; N]; 3],
    /// Third vertices.
    pub v2: [[f32; N]; 3],
    /// Triangle ids (contract §1), [`MultiTri::PAD_ID`] in padding lanes.
    pub ids: [u32; N],
}

const _: () = assert!(std::mem::size_of::<MultiTri<8>>() == 320);
const _: () = assert!(std::mem::size_of::<MultiTri<4>>() == 160);

impl<const N: usize> MultiTri<N> {
    /// The id of padding lanes.
    pub const PAD_ID: u32 = u32::MAX;

    /// All lanes padding.
    pub const EMPTY: Self = MultiTri {
        v0: [[0.0; N]; 3],
        v1: [[0.0; N]; 3],
        v2: [[0.0; N]; 3],
        ids: [Self::PAD_ID; N],
    };

    /// Number of lanes in use.
    pub fn lanes(&self) -> usize {
        self.ids.iter().take_while(|&&i| i != Self::PAD_ID).count()
    }

    /// Writes triangle `t` with id `id` into lane `lane`.
    #[inline]
    pub fn set(&mut self, lane: usize, id: u32, t: &Triangle) {
        for a in 0..3 {
            self.v0[a][lane] = t.v[0][a];
            self.v1[a][lane] = t.v[1][a];
            self.v2[a][lane] = t.v[2][a];
        }
        self.ids[lane] = id;
    }

    /// The triangle in lane `lane`.
    pub fn get(&self, lane: usize) -> Triangle {
        Triangle {
            v: [
                [self.v0[0][lane], self.v0[1][lane], self.v0[2][lane]],
                [self.v1[0][lane], self.v1[1][lane], self.v1[2][lane]],
                [self.v2[0][lane], self.v2[1][lane], self.v2[2][lane]],
            ],
        }
    }
}

/// An N-wide multi-BVH over a triangle scene (Áfra 2013): the structure behind `mbvh8`
/// and `mbvh4`. Built by [`Mbvh::build`], updated in place by [`Mbvh::refit`].
#[derive(Clone, Debug)]
pub struct Mbvh<const N: usize> {
    pub(super) nodes: Vec<WideNode<N>>,
    pub(super) tris: Vec<MultiTri<N>>,
    /// Ids left out of the tree (degenerate or non-finite), ascending.
    pub(super) excluded: Vec<u32>,
    /// Triangles the tree was built over (all ids, excluded ones too).
    pub(super) triangles: usize,
    pub(super) quality: BuildQuality,
    /// Whether leaf boxes may be clipped (SBVH, until a refit).
    pub(super) clipped: bool,
}

/// The 8-wide MBVH of the `mbvh8` accelerator (AVX).
pub type Mbvh8 = Mbvh<8>;
/// The 4-wide MBVH of the `mbvh4` accelerator (SSE).
pub type Mbvh4 = Mbvh<4>;

impl<const N: usize> Mbvh<N> {
    /// The cost model of the N-wide build: K_T = K_I = 1, costs in multi-triangles, at
    /// most 2N triangles per leaf. For `mbvh8 --build sbvh`, K_I = 0.5, 0.7, 1.5 and 2
    /// and leaves of at most N triangles were tried (BENCHMARKS.md §20): none was faster on
    /// every scene and set; all stayed within the ±10% noise or lost.
    pub(super) fn cost() -> CostModel {
        CostModel::new(N as u32, 2 * N as u32, 1.0, 1.0)
    }

    /// Builds the tree over `triangles` (ids are their indices) on the current rayon
    /// pool. Degenerate and non-finite triangles are left out. N must be 4 or 8.
    pub fn build(triangles: &[Triangle], quality: BuildQuality) -> Self {
        let built = WideTree::<N>::build(triangles, quality).built;
        let root = &built.arena[0];
        assert!(
            root.sub.blocks < (1 << Child::FIRST_BITS) - 1,
            "too many multi-triangles for the leaf encoding"
        );
        let mut nodes = vec![WideNode::EMPTY; root.sub.nodes as usize];
        let mut tris = vec![MultiTri::EMPTY; root.sub.blocks as usize];
        emit(
            &built.arena,
            0,
            &mut nodes,
            0,
            &mut tris,
            0,
            &built.refs,
            triangles,
        );
        Mbvh {
            nodes,
            tris,
            excluded: built.excluded,
            triangles: triangles.len(),
            quality,
            clipped: quality == BuildQuality::Sbvh,
        }
    }

    /// The multi-nodes, root first (index 0; a tree over no triangles has one root
    /// with every lane empty).
    pub fn nodes(&self) -> &[WideNode<N>] {
        &self.nodes
    }

    /// The multi-triangles the leaves point at.
    pub fn multi_tris(&self) -> &[MultiTri<N>] {
        &self.tris
    }

    /// Box of everything in the tree (empty for no triangles).
    pub fn bounds(&self) -> Aabb {
        self.nodes[0].bounds()
    }

    /// Number of triangles the tree was built over (ids `0..count`).
    pub fn triangle_count(&self) -> usize {
        self.triangles
    }

    /// Ids of the triangles left out of the tree (degenerate or non-finite), ascending.
    pub fn excluded(&self) -> &[u32] {
        &self.excluded
    }

    /// The quality it was built with.
    pub fn quality(&self) -> BuildQuality {
        self.quality
    }

    /// Bytes held by nodes and multi-triangles.
    pub fn bytes(&self) -> usize {
        self.nodes.len() * std::mem::size_of::<WideNode<N>>()
            + self.tris.len() * std::mem::size_of::<MultiTri<N>>()
            + self.excluded.len() * 4
    }
}

/// The builder's N-wide tree before it is flattened into an [`Mbvh`], for a layout that
/// places nodes and leaf triangles itself (the MBVH traversal format): going through an
/// `Mbvh` would write every triangle twice, once into its multi-triangles and once into
/// the layout's packs, and on a million triangles that copy was a third of a `fast`
/// build.
pub(crate) struct WideTree<const N: usize> {
    built: build::Built<N>,
    triangles: usize,
}

/// One lane of a multi-node as [`WideTree::visit`] reports it.
#[derive(Clone, Copy, Debug)]
pub(crate) enum WideLane<'a> {
    /// Unused (the lanes in use come first).
    Empty,
    /// A leaf: its triangles, in the order an [`Mbvh`] gathers them.
    Leaf(LeafRefs<'a>),
    /// An inner node: its index in the pre-order that [`WideTree::visit`] follows (the
    /// order of [`Mbvh::nodes`]).
    Inner(u32),
}

/// The triangles of one leaf.
#[derive(Clone, Copy, Debug)]
pub(crate) struct LeafRefs<'a>(&'a [Ref]);

impl LeafRefs<'_> {
    /// Number of triangles.
    pub fn len(&self) -> usize {
        self.0.len()
    }

    /// The id of the `i`-th triangle.
    #[inline]
    pub fn id(&self, i: usize) -> u32 {
        self.0[i].id()
    }
}

impl<const N: usize> WideTree<N> {
    /// Builds the tree over `triangles` on the current rayon pool: the tree that
    /// [`Mbvh::build`] flattens.
    pub fn build(triangles: &[Triangle], quality: BuildQuality) -> Self {
        const { assert!(N == 4 || N == 8, "MBVH width must be 4 or 8") };
        WideTree {
            built: build::build::<N>(triangles, quality, Mbvh::<N>::cost()),
            triangles: triangles.len(),
        }
    }

    /// Number of multi-nodes.
    pub fn node_count(&self) -> usize {
        self.built.arena[0].sub.nodes as usize
    }

    /// Number of triangles the tree was built over (ids `0..count`).
    pub fn triangle_count(&self) -> usize {
        self.triangles
    }

    /// Ids of the triangles left out of the tree (degenerate or non-finite), ascending.
    pub fn excluded(&self) -> &[u32] {
        &self.built.excluded
    }

    /// Calls `f(index, boxes, lanes)` for every multi-node in depth-first pre-order
    /// (root first, children in lane order): the order of [`Mbvh::nodes`]. Empty lanes
    /// have empty boxes.
    pub fn visit<'s>(&'s self, mut f: impl FnMut(u32, &[Aabb; N], &[WideLane<'s>; N])) {
        let mut next = 0;
        visit_node(&self.built.arena, 0, &self.built.refs, &mut next, &mut f);
    }
}

/// [`WideTree::visit`] of the subtree of `arena[idx]`, whose index is `*next`.
fn visit_node<'a, const N: usize>(
    arena: &'a [BNode<N>],
    idx: usize,
    refs: &'a [Ref],
    next: &mut u32,
    f: &mut impl FnMut(u32, &[Aabb; N], &[WideLane<'a>; N]),
) {
    let b = &arena[idx];
    let me = *next;
    *next += 1;
    let mut lanes = [WideLane::Empty; N];
    let mut boxes = [Aabb::EMPTY; N];
    let mut child = me + 1;
    for lane in 0..b.count {
        boxes[lane] = b.boxes[lane];
        let kid = &b.kids[lane];
        if let Kid::Leaf { begin, n } = *kid {
            lanes[lane] = WideLane::Leaf(LeafRefs(&refs[begin as usize..(begin + n) as usize]));
        } else if let Some((a, j)) = inner(arena, kid) {
            lanes[lane] = WideLane::Inner(child);
            child += a[j].sub.nodes;
        }
    }
    f(me, &boxes, &lanes);
    for kid in &b.kids[..b.count] {
        if let Some((a, j)) = inner(arena, kid) {
            visit_node(a, j, refs, next, f);
        }
    }
    debug_assert_eq!(*next, child, "a subtree's size is its node count");
}

/// Writes the subtree of `arena[idx]` into `nodes` (its first slot has global index
/// `nbase`) and its multi-triangles into `mts` (from global index `mbase`).
#[allow(clippy::too_many_arguments)]
fn emit<const N: usize>(
    arena: &[BNode<N>],
    idx: usize,
    nodes: &mut [WideNode<N>],
    nbase: u32,
    mts: &mut [MultiTri<N>],
    mbase: u32,
    refs: &[Ref],
    tris: &[Triangle],
) {
    let b = &arena[idx];
    let (me, mut nrest) = nodes.split_first_mut().expect("a node's slot");
    let mut mrest = mts;
    let (mut nb, mut mb) = (nbase + 1, mbase);
    let par = b.sub.nodes >= PAR_EMIT && rayon::current_num_threads() > 1;
    let mut jobs = Vec::new();
    for lane in 0..b.count {
        me.set_lane_box(lane, &b.boxes[lane]);
        let kid = &b.kids[lane];
        if let Kid::Leaf { begin, n } = *kid {
            let k = n.div_ceil(N as u32);
            let (mine, tail) = std::mem::take(&mut mrest).split_at_mut(k as usize);
            mrest = tail;
            fill_leaf(mine, &refs[begin as usize..(begin + n) as usize], tris);
            me.child[lane] = Child::Leaf {
                first: mb,
                count: k,
            }
            .encode();
            mb += k;
        } else if let Some((a, j)) = inner(arena, kid) {
            let s = a[j].sub;
            let (nmine, ntail) = std::mem::take(&mut nrest).split_at_mut(s.nodes as usize);
            let (mmine, mtail) = std::mem::take(&mut mrest).split_at_mut(s.blocks as usize);
            nrest = ntail;
            mrest = mtail;
            me.child[lane] = Child::Inner(nb).encode();
            if par {
                jobs.push((a, j, nmine, nb, mmine, mb));
            } else {
                emit(a, j, nmine, nb, mmine, mb, refs, tris);
            }
            nb += s.nodes;
            mb += s.blocks;
        }
    }
    if par {
        jobs.into_par_iter()
            .for_each(|(a, j, n, nb, m, mb)| emit(a, j, n, nb, m, mb, refs, tris));
    }
}

/// Gathers the triangles of one leaf into its multi-triangles.
fn fill_leaf<const N: usize>(mts: &mut [MultiTri<N>], refs: &[Ref], tris: &[Triangle]) {
    for (mt, chunk) in mts.iter_mut().zip(refs.chunks(N)) {
        for (lane, r) in chunk.iter().enumerate() {
            mt.set(lane, r.id(), &tris[r.id() as usize]);
        }
    }
}
