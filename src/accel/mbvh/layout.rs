//! The traversal format of the MBVH accelerators: [`TravNode<N>`] multi-nodes whose leaves
//! point at pre-gathered [`Tri8`] packs, laid out from the builder's tree (STYLE habit 3:
//! build format → traversal format): straight from its intermediate nodes when an
//! accelerator is built (`TravTree::from_wide`, which writes each triangle once), or from
//! a finished [`bvh::Mbvh<N>`] ([`TravTree::from_mbvh`]); the two give identical trees.
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

use rayon::prelude::*;

use crate::accel::bvh::{self, half_area, Child, RefitError};
use crate::accel::triangle::{Tri8, TriTest};
use crate::geometry::{Aabb, Triangle};

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

/// A [`Tri8`] aligned to a cache line: 320 bytes are exactly five lines, where `Tri8`'s
/// own 32-byte alignment would let a pack straddle six.
#[repr(C, align(64))]
#[derive(Clone, Debug)]
pub struct Pack<T>(pub Tri8<T>);

const _: () = assert!(std::mem::size_of::<Pack<crate::accel::triangle::Watertight>>() == 320);

/// Bits of a leaf id holding its first lane.
const START_BITS: u32 = 27;

/// Encodes a leaf: `n` (1..=16) triangles from global lane `start` (pack `start / 8`, lane
/// `start % 8`).
fn leaf_id(start: usize, n: usize) -> i32 {
    assert!(
        start < 1 << START_BITS,
        "too many triangle lanes for the leaf encoding"
    );
    debug_assert!((1..=16).contains(&n));
    (1u32 << 31 | ((n as u32 - 1) << START_BITS) | start as u32) as i32
}

/// The child id of an unused lane: a leaf of one lane in the all-padding pack 0 (real
/// leaves start at lane 8).
const EMPTY_LANE: i32 = (1u32 << 31) as i32;

/// Splits a leaf id into (first global lane, triangle count).
#[inline(always)]
pub fn leaf_lanes(id: i32) -> (usize, usize) {
    let u = id as u32;
    (
        (u & ((1 << START_BITS) - 1)) as usize,
        ((u >> START_BITS) & 15) as usize + 1,
    )
}

/// The whole traversal structure: nodes (root at 0), leaf packs, and what the box test
/// needs to stay conservative.
#[derive(Clone, Debug)]
pub struct TravTree<const N: usize, T> {
    /// Multi-nodes, depth-first, root first.
    pub nodes: Vec<TravNode<N>>,
    /// The leaves' triangles, in leaf order.
    pub packs: Vec<Pack<T>>,
    /// Largest |coordinate| of the tree's bounds (0 for an empty tree): the scale of the
    /// rounding errors of the triangle tests, see `ray::BoxRay`.
    pub scale: f32,
    /// Deepest multi-node level (root = 1): bounds the traversal stack.
    pub depth: usize,
    /// Triangles the tree was built over (all ids): a refit must bring as many.
    pub triangles: usize,
    /// Ids left out of the tree (degenerate or non-finite), ascending: a refit must
    /// leave exactly these out.
    pub excluded: Vec<u32>,
    /// [`TravTree::cost`] as built, measured by the first refit (a build pays nothing for
    /// it) and kept by the later ones, to measure how far they drifted.
    pub built_cost: Option<f64>,
}

impl<const N: usize, T> TravTree<N, T> {
    /// The tree's surface-area cost over its root's area: each child box's half area,
    /// once for an inner child and once a pack for a leaf. A refit over positions that
    /// moved triangles far from where the tree grouped them swells the boxes, and the
    /// cost with them, roughly as its traces slow down. 0 for an empty or flat tree.
    pub fn cost(&self) -> f64 {
        let Some(root) = self.nodes.first() else {
            return 0.0;
        };
        let area = bvh::half_area(&root.bounds());
        if !(area > 0.0 && area.is_finite()) {
            return 0.0;
        }
        let mut sum = 0.0;
        for n in &self.nodes {
            for lane in 0..N {
                let c = n.child[lane];
                if c == EMPTY_LANE {
                    continue;
                }
                let weight = if c >= 0 {
                    1.0
                } else {
                    leaf_lanes(c).1.div_ceil(8) as f64
                };
                sum += bvh::half_area(&n.lane_box(lane)) * weight;
            }
        }
        sum / area
    }

    /// [`TravTree::cost`] now over the cost as built ([`bvh::drift`]).
    pub fn slowdown(&self) -> f64 {
        bvh::drift(self.cost(), self.built_cost)
    }
}

impl<const N: usize, T: TriTest> TravTree<N, T> {
    /// Converts the builder's tree.
    ///
    /// Two passes: the nodes are copied and every leaf gets its place in lane space
    /// (sequential, integers only), then the packs are filled straight from the
    /// builder's multi-triangles, each pack on its own (in parallel on the caller's pool).
    pub fn from_mbvh(tree: &bvh::Mbvh<N>) -> Self {
        let src = tree.nodes();
        let mts = tree.multi_tris();
        let mut nodes = Vec::with_capacity(src.len());
        let mut places = Places::default();
        let mut leaves: Vec<(u32, Place)> = Vec::with_capacity(mts.len());
        for n in src {
            let mut planes = [[0.0f32; N]; 6];
            planes[..3].copy_from_slice(&n.min);
            planes[3..].copy_from_slice(&n.max);
            let mut child = n.child;
            for c in child.iter_mut() {
                if *c == Child::EMPTY {
                    *c = EMPTY_LANE;
                } else if let Child::Leaf { first, count } = Child::decode(*c) {
                    let k: usize = mts[first as usize..(first + count) as usize]
                        .iter()
                        .map(|mt| mt.lanes())
                        .sum();
                    let place = places.next(k);
                    *c = place.id();
                    leaves.push((first, place));
                }
            }
            nodes.push(TravNode {
                planes,
                child,
                pad: [0; N],
            });
        }
        // A leaf's lane j is lane j % N of its (j / N)-th multi-triangle: the builder
        // fills them in order.
        let packs = fill_packs(
            &leaves,
            &places,
            |&(first, _), j| {
                let mt = &mts[first as usize + j / N];
                (mt.ids[j % N], mt.get(j % N))
            },
            |_, _| {},
        );
        Self::assemble(
            nodes,
            packs,
            tree.triangle_count(),
            tree.excluded().to_vec(),
        )
    }

    /// Lays out the builder's tree directly, writing each triangle once, straight from
    /// `triangles` into its pack; the result equals `from_mbvh` of the [`bvh::Mbvh`]
    /// built the same way (a test checks it), without that intermediate copy.
    pub(crate) fn from_wide(tree: &bvh::WideTree<N>, triangles: &[Triangle]) -> Self {
        let mut nodes = Vec::with_capacity(tree.node_count());
        let mut places = Places::default();
        let mut leaves = Vec::with_capacity(triangles.len() / 4 + 1);
        tree.visit(|me, boxes, lanes| {
            debug_assert_eq!(me as usize, nodes.len(), "nodes come in pre-order");
            let mut node = TravNode {
                planes: [[0.0; N]; 6],
                child: [EMPTY_LANE; N],
                pad: [0; N],
            };
            for (lane, (b, kind)) in boxes.iter().zip(lanes).enumerate() {
                node.set_lane_box(lane, b);
                match *kind {
                    bvh::WideLane::Empty => {}
                    bvh::WideLane::Inner(i) => node.child[lane] = i as i32,
                    bvh::WideLane::Leaf(refs) => {
                        let place = places.next(refs.len());
                        node.child[lane] = place.id();
                        leaves.push((refs, place));
                    }
                }
            }
            nodes.push(node);
        });
        let packs = fill_packs(
            &leaves,
            &places,
            |(refs, _), j| {
                let id = refs.id(j);
                (id, triangles[id as usize])
            },
            |(refs, _), j| {
                // Both ends: a 36-byte triangle may straddle two cache lines.
                let t: *const u8 = (&triangles[refs.id(j) as usize] as *const Triangle).cast();
                crate::simd::prefetch(t, 1);
                crate::simd::prefetch(t.wrapping_add(std::mem::size_of::<Triangle>() - 1), 1);
            },
        );
        Self::assemble(
            nodes,
            packs,
            tree.triangle_count(),
            tree.excluded().to_vec(),
        )
    }

    /// The tree of laid-out `nodes` (root first) and `packs`, with the scale and depth
    /// they imply.
    fn assemble(
        nodes: Vec<TravNode<N>>,
        packs: Vec<Pack<T>>,
        triangles: usize,
        excluded: Vec<u32>,
    ) -> Self {
        TravTree {
            scale: nodes.first().map_or(0.0, |n| n.bounds().max_abs()),
            depth: depth(&nodes),
            nodes,
            packs,
            triangles,
            excluded,
            built_cost: None,
        }
    }

    /// Takes new positions for the same triangles (same count, same ids) in place,
    /// without the builder's tree: every pack re-gathers its lanes by id (parallel over
    /// packs), then every box is recomputed bottom-up from the triangles of its leaf's
    /// lanes or the union of its child node's lanes, disjoint subtrees (contiguous in the
    /// depth-first order) being separate rayon tasks. `scale` follows the new bounds, so
    /// the grown slab test (`ray::BoxRay`) stays conservative. Boxes are the tight boxes
    /// of whole triangles (SBVH leaves lose their clipping). Refused, tree unchanged, as
    /// `bvh::Mbvh::refit` refuses.
    pub fn refit(&mut self, triangles: &[Triangle]) -> Result<(), RefitError> {
        bvh::check_refit(&self.excluded, self.triangles, triangles)?;
        if self.built_cost.is_none() {
            self.built_cost = Some(self.cost());
        }
        self.packs
            .par_iter_mut()
            .with_min_len(64)
            .for_each(|p| p.0.regather(triangles));
        let bounds = if self.nodes.is_empty() {
            Aabb::EMPTY
        } else {
            refit_nodes(&mut self.nodes, 0, &self.packs, triangles)
        };
        self.scale = bounds.max_abs();
        Ok(())
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.nodes.capacity() * std::mem::size_of::<TravNode<N>>()
            + self.packs.capacity() * std::mem::size_of::<Pack<T>>()
            + self.excluded.capacity() * std::mem::size_of::<u32>()
    }
}

/// Subtrees with at least this many nodes are refitted as separate rayon tasks.
const PAR_REFIT: usize = 128;

/// Box of the triangles of the leaf `id` (their vertices as given, read by the lanes' ids).
fn leaf_box<T>(id: i32, packs: &[Pack<T>], triangles: &[Triangle]) -> Aabb {
    let (start, n) = leaf_lanes(id);
    let mut b = Aabb::EMPTY;
    // A leaf's lanes are consecutive global lanes (a leaf of more than 8 starts a pack).
    for l in start..start + n {
        let tid = packs[l / 8].0.ids[l % 8];
        for &v in &triangles[tid as usize].v {
            b.grow(v);
        }
    }
    b
}

/// Refits the subtree whose root is `nodes[0]` (global index `base`; `nodes` is exactly
/// that subtree, depth-first) and returns its box.
fn refit_nodes<const N: usize, T: Send + Sync>(
    nodes: &mut [TravNode<N>],
    base: usize,
    packs: &[Pack<T>],
    triangles: &[Triangle],
) -> Aabb {
    let len = nodes.len();
    let (me, mut rest) = nodes.split_first_mut().expect("a subtree has a root");
    // Inner children, by index: each owns the nodes up to the next one (or the end of
    // this subtree), the first one starting right after this node.
    let mut inner: [(usize, usize); N] = [(usize::MAX, 0); N];
    let mut k = 0;
    for (lane, &c) in me.child.iter().enumerate() {
        if c >= 0 {
            inner[k] = (c as usize, lane);
            k += 1;
        }
    }
    let inner = &mut inner[..k];
    inner.sort_unstable();
    let mut jobs: Vec<(usize, usize, &mut [TravNode<N>])> = Vec::with_capacity(k);
    for j in 0..k {
        let (idx, lane) = inner[j];
        let end = inner.get(j + 1).map_or(base + len, |&(next, _)| next);
        debug_assert_eq!(idx, base + len - rest.len(), "children follow their parent");
        let (mine, tail) = std::mem::take(&mut rest).split_at_mut(end - idx);
        rest = tail;
        jobs.push((lane, idx, mine));
    }
    let mut boxes = [Aabb::EMPTY; N];
    if len >= PAR_REFIT && k > 1 && rayon::current_num_threads() > 1 {
        let found: Vec<(usize, Aabb)> = jobs
            .into_par_iter()
            .map(|(lane, idx, sub)| (lane, refit_nodes(sub, idx, packs, triangles)))
            .collect();
        for (lane, b) in found {
            boxes[lane] = b;
        }
    } else {
        for (lane, idx, sub) in jobs {
            boxes[lane] = refit_nodes(sub, idx, packs, triangles);
        }
    }
    let mut all = Aabb::EMPTY;
    for (lane, b) in boxes.iter_mut().enumerate() {
        let c = me.child[lane];
        if c == EMPTY_LANE {
            // Unused lane: keeps its empty box.
            continue;
        }
        if c < 0 {
            *b = leaf_box(c, packs, triangles);
        }
        me.set_lane_box(lane, b);
        all.union(b);
    }
    all
}

/// Where one leaf's triangles go: `n` triangles to global lanes `start .. start + n`.
#[derive(Clone, Copy, Debug)]
struct Place {
    start: u32,
    n: u32,
}

impl Place {
    /// The leaf's child id.
    fn id(&self) -> i32 {
        leaf_id(self.start as usize, self.n as usize)
    }
}

/// Places leaves densely in "lane space", eight lanes a pack, in the order they come: a
/// leaf of at most 8 triangles never straddles two packs, a larger one starts a pack.
/// Leaves come in node order, so small sibling leaves share packs. Lanes 0..8 (pack 0)
/// are padding, which unused node lanes point at (see [`TravNode::child`]).
struct Places {
    pos: usize,
    /// Leaves placed so far.
    leaves: u32,
    /// Per pack, the first leaf with lanes in it (pack 0: leaf 0, which starts later).
    first: Vec<u32>,
}

impl Default for Places {
    fn default() -> Self {
        Places {
            pos: 8,
            leaves: 0,
            first: vec![0],
        }
    }
}

impl Places {
    /// The place of the next leaf, of `k` triangles.
    fn next(&mut self, k: usize) -> Place {
        assert!((1..=16).contains(&k), "leaf of {k} triangles");
        if self.pos % 8 + k > 8 && !self.pos.is_multiple_of(8) {
            self.pos = self.pos.next_multiple_of(8);
        }
        let place = Place {
            start: self.pos as u32,
            n: k as u32,
        };
        // A leaf of more than 8 starts a pack, so its tail starts the next.
        self.pos += k;
        // No pack is skipped: a leaf that does not fit starts the very next one.
        while self.first.len() < self.pos.div_ceil(8) {
            self.first.push(self.leaves);
        }
        self.leaves += 1;
        place
    }

    /// Packs needed so far.
    fn packs(&self) -> usize {
        self.first.len()
    }
}

/// Packs per parallel task of [`fill_packs`].
const FILL_CHUNK: usize = 256;

/// Packs ahead whose triangles [`fill_packs`] prefetches.
const PREFETCH_PACKS: usize = 4;

/// Makes the packs of `places` (pack 0 all padding) with each leaf's triangles in its
/// lanes: `lane(leaf, j)` gives the id and triangle of the leaf's `j`-th lane, and
/// `prefetch(leaf, j)` asks for that triangle's cache lines a few packs ahead (a Morton
/// build's leaves read the input triangles in random order). `leaves` are in the order
/// they were placed. Every pack is made once, in parallel, in place.
fn fill_packs<T: TriTest, L: Sync>(
    leaves: &[(L, Place)],
    places: &Places,
    lane: impl Fn(&(L, Place), usize) -> (u32, Triangle) + Sync,
    prefetch: impl Fn(&(L, Place), usize) + Sync,
) -> Vec<Pack<T>> {
    (0..places.packs())
        .into_par_iter()
        .with_min_len(FILL_CHUNK)
        .map(|pi| {
            if pi + PREFETCH_PACKS < places.packs() {
                for_lanes(leaves, places, pi + PREFETCH_PACKS, |leaf, j, _| {
                    prefetch(leaf, j)
                });
            }
            let mut p = Tri8::<T>::pack(&[]);
            for_lanes(leaves, places, pi, |leaf, j, g| {
                let (id, tri) = lane(leaf, j);
                p.set(g % 8, id, &tri);
            });
            Pack(p)
        })
        .collect()
}

/// Calls `f(leaf, j, g)` for every lane of pack `pi`: lane `j` of `leaf` at global lane `g`.
fn for_lanes<L>(
    leaves: &[(L, Place)],
    places: &Places,
    pi: usize,
    mut f: impl FnMut(&(L, Place), usize, usize),
) {
    let (lo, hi) = (pi * 8, pi * 8 + 8);
    for leaf in &leaves[places.first[pi] as usize..] {
        let l = &leaf.1;
        if l.start as usize >= hi {
            break;
        }
        let first = (l.start as usize).max(lo);
        let last = ((l.start + l.n) as usize).min(hi);
        for g in first..last {
            f(leaf, g - l.start as usize, g);
        }
    }
}

/// Deepest multi-node level of `nodes` (root = 1).
fn depth<const N: usize>(nodes: &[TravNode<N>]) -> usize {
    let mut deepest = 0;
    let mut stack = vec![(0usize, 1usize)];
    while let Some((i, d)) = stack.pop() {
        deepest = deepest.max(d);
        for &c in &nodes[i].child {
            if c >= 0 {
                stack.push((c as usize, d + 1));
            }
        }
    }
    deepest
}

impl<const N: usize> TravNode<N> {
    /// The box of lane `lane` (an empty lane's is empty).
    fn lane_box(&self, lane: usize) -> Aabb {
        Aabb {
            min: [0, 1, 2].map(|k| self.planes[k][lane]),
            max: [3, 4, 5].map(|k| self.planes[k][lane]),
        }
    }

    /// Sets the box of lane `lane`.
    fn set_lane_box(&mut self, lane: usize, b: &Aabb) {
        for a in 0..3 {
            self.planes[a][lane] = b.min[a];
            self.planes[a + 3][lane] = b.max[a];
        }
    }

    /// The union of the lanes' boxes: the node's own box.
    fn bounds(&self) -> Aabb {
        let mut b = Aabb::EMPTY;
        for lane in 0..N {
            b.union(&self.lane_box(lane));
        }
        b
    }
}

impl<const N: usize, T: TriTest> TravTree<N, T> {
    /// Áfra 2013's Table 2 and 4 statistics of the tree as it is now (after refits, of
    /// the refitted boxes), computed from the traversal layout so that building never
    /// pays for them: multi-nodes, leaves, node and pack SIMD utilisation, SAH cost
    /// (`Σ A(node)/A(root) + Σ_leaves packs·A(leaf)/A(root)`, K_T = K_I = 1, where a
    /// node's area is its children's union), depth and bytes per triangle.
    pub fn stats(&self) -> serde_json::Value {
        let empty = leaf_id(0, 1);
        let (mut lanes_used, mut leaves, mut leaf_tris, mut leaf_packs) =
            (0usize, 0usize, 0usize, 0usize);
        let mut sah = 0.0f64;
        let root = self.nodes.first().map_or(0.0, |n| half_area(&n.bounds()));
        let inv = if root > 0.0 { 1.0 / root } else { 0.0 };
        for n in &self.nodes {
            sah += half_area(&n.bounds()) * inv;
            for lane in 0..N {
                let c = n.child[lane];
                if c == empty {
                    continue;
                }
                lanes_used += 1;
                if c < 0 {
                    let (start, count) = leaf_lanes(c);
                    let packs = (start % 8 + count).div_ceil(8);
                    leaves += 1;
                    leaf_tris += count;
                    leaf_packs += packs;
                    sah += packs as f64 * half_area(&n.lane_box(lane)) * inv;
                }
            }
        }
        let real_packs = self.packs.len().saturating_sub(1);
        let live = self.triangles - self.excluded.len();
        let ratio = |a: f64, b: f64| if b > 0.0 { a / b } else { 0.0 };
        serde_json::json!({
            "width": N,
            "triangles": self.triangles,
            "excluded": self.excluded.len(),
            "references": leaf_tris,
            "nodes": self.nodes.len(),
            "leaves": leaves,
            "node_utilization": ratio(lanes_used as f64, (self.nodes.len() * N) as f64),
            "packs": real_packs,
            "pack_utilization": ratio(leaf_tris as f64, (real_packs * 8) as f64),
            "packs_per_leaf": ratio(leaf_packs as f64, leaves as f64),
            "avg_leaf_triangles": ratio(leaf_tris as f64, leaves as f64),
            "sah_cost": sah,
            "max_depth": self.depth,
            "bytes": self.bytes(),
            "bytes_per_triangle": ratio(self.bytes() as f64, live as f64),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::accel::triangle::tests::Rng;
    use crate::accel::triangle::{MollerTrumbore, Watertight};
    use crate::accel::BuildQuality;

    /// Small triangles scattered in clusters, some degenerate or non-finite (left out).
    fn soup(n: usize, seed: u64) -> Vec<Triangle> {
        let mut rng = Rng(seed);
        (0..n)
            .map(|i| {
                let c = rng.vec().map(|x| x * 10.0 * (1 + i % 3) as f32);
                let mut t = Triangle {
                    v: std::array::from_fn(|_| {
                        let d = rng.vec();
                        std::array::from_fn(|k| c[k] + 0.3 * d[k])
                    }),
                };
                match i % 97 {
                    5 => t.v[2] = t.v[1],
                    11 => t.v[0][1] = f32::NAN,
                    _ => {}
                }
                t
            })
            .collect()
    }

    fn assert_same<const N: usize, T: TriTest>(a: &TravTree<N, T>, b: &TravTree<N, T>) {
        assert_eq!(a.nodes, b.nodes);
        assert_eq!(a.packs.len(), b.packs.len());
        for (i, (x, y)) in a.packs.iter().zip(&b.packs).enumerate() {
            assert_eq!(x.0.ids, y.0.ids, "pack {i}");
            let bits = |p: &Pack<T>| p.0.p.map(|q| q.map(|r| r.map(f32::to_bits)));
            assert_eq!(bits(x), bits(y), "pack {i}");
        }
        assert_eq!(a.scale.to_bits(), b.scale.to_bits());
        assert_eq!(a.depth, b.depth);
        assert_eq!(a.triangles, b.triangles);
        assert_eq!(a.excluded, b.excluded);
    }

    fn check<const N: usize>(tris: &[Triangle], q: BuildQuality) {
        let wide = bvh::WideTree::<N>::build(tris, q);
        let mbvh = bvh::Mbvh::<N>::build(tris, q);
        assert_same(
            &TravTree::<N, Watertight>::from_wide(&wide, tris),
            &TravTree::<N, Watertight>::from_mbvh(&mbvh),
        );
        assert_same(
            &TravTree::<N, MollerTrumbore>::from_wide(&wide, tris),
            &TravTree::<N, MollerTrumbore>::from_mbvh(&mbvh),
        );
    }

    /// The direct layout is exactly the layout of the built [`bvh::Mbvh`], for every
    /// width and quality, on one thread and on several (the builder's parallel tasks
    /// make sub-arenas that the pre-order walk must cross).
    #[test]
    fn the_direct_layout_equals_the_one_through_an_mbvh() {
        for (n, seed) in [(0, 1), (1, 2), (7, 3), (300, 4), (20_000, 5)] {
            let tris = soup(n, seed);
            for threads in [1, 3] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                pool.install(|| {
                    for q in [BuildQuality::Fast, BuildQuality::Sah, BuildQuality::Sbvh] {
                        check::<8>(&tris, q);
                        check::<4>(&tris, q);
                    }
                });
            }
        }
    }
}
