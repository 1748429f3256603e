//! Áfra's multi-node construction (Áfra 2013 §3.2), generic over how one candidate child
//! is split in two ([`Splitter`]: binned SAH, SBVH or Morton).
//!
//! A multi-node is grown from one candidate range of references by *horizontal
//! splitting*: the candidate with the largest surface area whose best binary split pays by
//! eq. 1 is replaced by its two halves, until N candidates exist or none pays. Then each
//! candidate either becomes a leaf or, when eq. 2 says splitting it pays (or it holds more
//! than the leaf limit), a new multi-node built the same way (*vertical splitting*).
//! Every candidate's best split is found once, when the candidate is made, so each range
//! of references is binned exactly once.
//!
//! The output is an intermediate tree ([`BNode`]s in per-task arenas) with subtree sizes,
//! which the layouts ([`super::wide`], [`super::bvh2`]) flatten in parallel into their
//! final depth-first arrays.

use rayon::prelude::*;

use super::binning::{Centroids, SahSplitter};
use super::morton::{self, MortonSplitter};
use super::{is_traceable, DEPTH_LIMIT};
use crate::accel::BuildQuality;
use crate::geometry::{Aabb, Triangle};
use crate::simd::build4;

/// Candidates with at least this many references evaluate their two halves in parallel.
const PAR_EVAL: u32 = 1 << 14;
/// Subtrees with at least this many references are built as their own rayon tasks.
const PAR_TASK: u32 = 1 << 11;

/// A reference to (part of) one triangle: the box the builder sorts and bins. SBVH
/// references may be clipped to less than the triangle's box; the others are the
/// triangle's box. 32 bytes, laid out as a [`B4`] so that the hot loops work on whole
/// 4-lane vectors: lane 3 of `lo` carries the triangle id and lane 3 of `hi` a scratch
/// word, both as raw bits (box arithmetic on lane 3 produces junk that nobody reads).
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(32))]
pub(crate) struct Ref {
    /// Lower corner in lanes 0..3; the id's bits in lane 3.
    pub lo: [f32; 4],
    /// Upper corner in lanes 0..3; the scratch word's bits in lane 3.
    pub hi: [f32; 4],
}

const _: () = assert!(std::mem::size_of::<Ref>() == 32);

impl Default for Ref {
    fn default() -> Self {
        Ref {
            lo: [0.0; 4],
            hi: [0.0; 4],
        }
    }
}

impl Ref {
    /// A reference to triangle `id` with box `b`.
    pub fn new(id: u32, b: &Aabb) -> Ref {
        Ref {
            lo: [b.min[0], b.min[1], b.min[2], f32::from_bits(id)],
            hi: [b.max[0], b.max[1], b.max[2], 0.0],
        }
    }

    /// The triangle id.
    #[inline(always)]
    pub fn id(&self) -> u32 {
        self.lo[3].to_bits()
    }

    /// The scratch word (which side a reference goes to).
    #[inline(always)]
    pub fn aux(&self) -> u32 {
        self.hi[3].to_bits()
    }

    /// Sets the scratch word.
    #[inline(always)]
    pub fn set_aux(&mut self, v: u32) {
        self.hi[3] = f32::from_bits(v);
    }

    /// The box.
    #[inline(always)]
    pub fn aabb(&self) -> Aabb {
        Aabb {
            min: [self.lo[0], self.lo[1], self.lo[2]],
            max: [self.hi[0], self.hi[1], self.hi[2]],
        }
    }

    /// The box as a [`B4`] (lane 3 junk).
    #[inline(always)]
    pub fn b4(&self) -> B4 {
        B4 {
            lo: self.lo,
            hi: self.hi,
        }
    }

    /// Centroid along `axis`, written so that it cannot overflow for finite boxes.
    #[inline(always)]
    pub fn centroid(&self, axis: usize) -> f32 {
        self.lo[axis] * 0.5 + self.hi[axis] * 0.5
    }
}

/// A box in 4-lane form for the hot loops (bins, chopping): lanes 0..3 are x, y, z and
/// lane 3 is junk. Empty is `+inf..-inf` in lanes 0..3.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(32))]
pub(crate) struct B4 {
    /// Lower corner.
    pub lo: [f32; 4],
    /// Upper corner.
    pub hi: [f32; 4],
}

impl B4 {
    /// The empty box.
    pub const EMPTY: B4 = B4 {
        lo: [f32::INFINITY; 4],
        hi: [f32::NEG_INFINITY; 4],
    };

    /// A box of one point.
    #[inline(always)]
    pub fn point(p: [f32; 4]) -> B4 {
        B4 { lo: p, hi: p }
    }

    /// Grows the box by `o`.
    #[inline(always)]
    pub fn grow(&mut self, o: &B4) {
        // Lane-wise `fmin`/`fmax` in one instruction each: the compiler's own
        // vectorisation of the per-lane form shuffled lanes around in the partition loop.
        self.lo = build4::min4(&self.lo, &o.lo);
        self.hi = build4::max4(&self.hi, &o.hi);
    }

    /// Grows the box by the centroid of `r`'s box (`lo·0.5 + hi·0.5` per lane, as
    /// [`Ref::centroid`]).
    #[inline(always)]
    pub fn grow_centroid(&mut self, r: &Ref) {
        let m = build4::mid4(&r.lo, &r.hi);
        self.lo = build4::min4(&self.lo, &m);
        self.hi = build4::max4(&self.hi, &m);
    }

    /// The intersection, or `None` when it is empty.
    #[inline(always)]
    pub fn intersect(&self, o: &B4) -> Option<B4> {
        let mut c = B4::EMPTY;
        for k in 0..4 {
            c.lo[k] = fmax(self.lo[k], o.lo[k]);
            c.hi[k] = fmin(self.hi[k], o.hi[k]);
        }
        if c.lo[0] <= c.hi[0] && c.lo[1] <= c.hi[1] && c.lo[2] <= c.hi[2] {
            Some(c)
        } else {
            None
        }
    }

    /// As an [`Aabb`].
    #[inline(always)]
    pub fn aabb(&self) -> Aabb {
        Aabb {
            min: [self.lo[0], self.lo[1], self.lo[2]],
            max: [self.hi[0], self.hi[1], self.hi[2]],
        }
    }
}

/// `min` that compiles to one instruction (our data holds no NaN).
#[inline(always)]
pub(crate) fn fmin(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// `max` that compiles to one instruction (our data holds no NaN).
#[inline(always)]
pub(crate) fn fmax(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// Grows `b` by the box `lo..hi`.
#[inline(always)]
pub(crate) fn grow(b: &mut Aabb, lo: &[f32; 3], hi: &[f32; 3]) {
    for k in 0..3 {
        b.min[k] = fmin(b.min[k], lo[k]);
        b.max[k] = fmax(b.max[k], hi[k]);
    }
}

/// Union of two boxes.
#[inline(always)]
pub(crate) fn union(a: &Aabb, b: &Aabb) -> Aabb {
    let mut c = *a;
    grow(&mut c, &b.min, &b.max);
    c
}

/// Intersection of two boxes; [`Aabb::EMPTY`] when they are disjoint.
#[inline]
pub(crate) fn intersect(a: &Aabb, b: &Aabb) -> Aabb {
    let mut c = Aabb::EMPTY;
    for k in 0..3 {
        c.min[k] = fmax(a.min[k], b.min[k]);
        c.max[k] = fmin(a.max[k], b.max[k]);
        if c.min[k] > c.max[k] || c.min[k].is_nan() || c.max[k].is_nan() {
            return Aabb::EMPTY;
        }
    }
    c
}

/// Half the surface area, in f64 so that neither huge (1e30) nor tiny (1e-30) boxes
/// overflow or flush to zero; 0 for an empty box.
#[inline]
pub(crate) fn half_area(b: &Aabb) -> f64 {
    let e = [
        b.max[0] as f64 - b.min[0] as f64,
        b.max[1] as f64 - b.min[1] as f64,
        b.max[2] as f64 - b.min[2] as f64,
    ];
    if !(e[0] >= 0.0 && e[1] >= 0.0 && e[2] >= 0.0) {
        return 0.0;
    }
    e[0] * e[1] + e[1] * e[2] + e[2] * e[0]
}

/// `1 / half_area(b)`, or 1 for a box without area (so that costs stay finite).
#[inline]
pub(crate) fn inv_half_area(b: &Aabb) -> f64 {
    let a = half_area(b);
    if a > 0.0 {
        1.0 / a
    } else {
        1.0
    }
}

/// The SAH cost model (Áfra eq. 1 and 2): a leaf of T triangles costs
/// `k_i · ⌈T / width⌉` multi-triangle tests; splitting costs `k_t` (vertical only) plus
/// the area-weighted leaf costs of the halves.
#[derive(Clone, Copy, Debug)]
pub(crate) struct CostModel {
    /// log2 of the triangles per multi-triangle (N for the MBVHs, 1 for
    /// [`super::Bvh2`]); a shift because the sweeps evaluate `⌈T/width⌉` thousands of
    /// times per node and an integer division there cost a third of the build.
    shift: u32,
    /// A candidate with more references is always split.
    pub max_leaf: u32,
    /// Cost of a traversal step (K_T).
    pub k_t: f64,
    /// Cost of one multi-triangle test (K_I).
    pub k_i: f64,
}

impl CostModel {
    /// Costs for multi-triangles of `width` (a power of two) triangles.
    pub fn new(width: u32, max_leaf: u32, k_t: f64, k_i: f64) -> Self {
        assert!(width.is_power_of_two());
        CostModel {
            shift: width.trailing_zeros(),
            max_leaf,
            k_t,
            k_i,
        }
    }

    /// Multi-triangles needed for `n` triangles.
    #[inline(always)]
    pub fn blocks(&self, n: u32) -> f64 {
        ((n + (1 << self.shift) - 1) >> self.shift) as f64
    }

    /// Cost of a leaf of `n` triangles.
    #[inline]
    pub fn leaf(&self, n: u32) -> f64 {
        self.k_i * self.blocks(n)
    }
}

/// A contiguous range of references: `[begin, end)` holds them, `[end, cap)` is free room
/// that SBVH fills with duplicated references.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Range<I> {
    /// First reference.
    pub begin: u32,
    /// One past the last reference.
    pub end: u32,
    /// One past the last slot this range may use.
    pub cap: u32,
    /// Box of the references.
    pub bounds: Aabb,
    /// What the splitter keeps about the range (centroid bounds, Morton node).
    pub info: I,
}

impl<I: Default> Default for Range<I> {
    fn default() -> Self {
        Range {
            begin: 0,
            end: 0,
            cap: 0,
            bounds: Aabb::EMPTY,
            info: I::default(),
        }
    }
}

impl<I> Range<I> {
    /// Number of references.
    #[inline]
    pub fn n(&self) -> u32 {
        self.end - self.begin
    }
}

/// How candidate ranges are split in two.
pub(crate) trait Splitter: Sync {
    /// Per-range data the splitter needs.
    type Info: Copy + Default + Send + Sync;
    /// A chosen split, found by [`Splitter::plan`] and carried out by [`Splitter::apply`].
    type Plan: Copy + Default + Send + Sync;

    /// The best split of the range's references (`refs` is exactly `begin..end`) and its
    /// cost `S = Σ A(child)/A(range) · ⌈T(child)/width⌉`. Must return a split for every
    /// range of two or more references; `median` asks for a plain median split (the depth
    /// guard).
    fn plan(
        &self,
        refs: &[Ref],
        r: &Range<Self::Info>,
        cost: &CostModel,
        median: bool,
    ) -> (Self::Plan, f64);

    /// Carries out `plan` on `refs` (exactly `begin..cap`), returning the two non-empty
    /// halves, which tile `begin..cap`.
    fn apply(
        &self,
        refs: &mut [Ref],
        r: &Range<Self::Info>,
        plan: &Self::Plan,
    ) -> [Range<Self::Info>; 2];
}

/// A range together with its best split, found lazily: only when the construction
/// needs it (see [`Builder::build_multi`]).
#[derive(Clone, Copy)]
struct Cand<I, P> {
    r: Range<I>,
    plan: P,
    /// Split cost S (see [`Splitter::plan`]); +inf when the range cannot be split.
    s: f64,
    /// Half the surface area of the range's box.
    area: f64,
    /// Whether `plan` and `s` have been computed.
    ready: bool,
}

impl<I: Default, P: Default> Default for Cand<I, P> {
    fn default() -> Self {
        Cand {
            r: Range::default(),
            plan: P::default(),
            s: f64::INFINITY,
            area: 0.0,
            ready: false,
        }
    }
}

/// Sizes of a finished subtree, used to place it in the flat arrays.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Sub {
    /// Multi-nodes (this one included).
    pub nodes: u32,
    /// Leaf lanes.
    pub leaves: u32,
    /// Multi-triangles at the node width (`Σ ⌈T/N⌉` over leaves).
    pub blocks: u32,
    /// References in leaves.
    pub refs: u32,
}

/// A child of an intermediate node.
pub(crate) enum Kid<const N: usize> {
    /// No child (lane unused).
    Empty,
    /// A leaf over references `begin .. begin + n`.
    Leaf {
        /// First reference.
        begin: u32,
        /// Number of references.
        n: u32,
    },
    /// A node in the same arena.
    Local(u32),
    /// A subtree built by another task: its arena, rooted at index 0.
    Remote(Vec<BNode<N>>),
}

/// An intermediate multi-node: up to N children with their boxes.
pub(crate) struct BNode<const N: usize> {
    /// Children in use (the first `count` lanes).
    pub count: usize,
    /// Child boxes.
    pub boxes: [Aabb; N],
    /// Children.
    pub kids: [Kid<N>; N],
    /// Sizes of this subtree.
    pub sub: Sub,
}

impl<const N: usize> BNode<N> {
    fn empty() -> Self {
        BNode {
            count: 0,
            boxes: [Aabb::EMPTY; N],
            kids: std::array::from_fn(|_| Kid::Empty),
            sub: Sub {
                nodes: 1,
                ..Sub::default()
            },
        }
    }
}

/// Resolves an inner child to its arena and index.
pub(crate) fn inner<'a, const N: usize>(
    arena: &'a [BNode<N>],
    kid: &'a Kid<N>,
) -> Option<(&'a [BNode<N>], usize)> {
    match kid {
        Kid::Local(i) => Some((arena, *i as usize)),
        Kid::Remote(a) => Some((a.as_slice(), 0)),
        _ => None,
    }
}

/// The multi-node builder.
struct Builder<'a, S: Splitter, const N: usize> {
    splitter: &'a S,
    cost: CostModel,
    parallel: bool,
}

type CandOf<S> = Cand<<S as Splitter>::Info, <S as Splitter>::Plan>;

impl<S: Splitter, const N: usize> Builder<'_, S, N> {
    /// A candidate for range `r`, its split not yet computed.
    fn cand(&self, r: Range<S::Info>) -> CandOf<S> {
        Cand {
            area: half_area(&r.bounds),
            r,
            plan: S::Plan::default(),
            s: f64::INFINITY,
            ready: false,
        }
    }

    /// Finds the best split of candidate `c` (`refs` = its references).
    fn eval(&self, refs: &[Ref], c: &mut CandOf<S>, depth: u32) {
        if !c.ready && c.r.n() >= 2 {
            let (plan, s) = self
                .splitter
                .plan(refs, &c.r, &self.cost, depth >= DEPTH_LIMIT);
            c.plan = plan;
            c.s = s;
        }
        c.ready = true;
    }

    /// Finds the split of candidate `c`, whose references lie somewhere in `refs` (whose
    /// first slot is `base`).
    fn eval_in(&self, refs: &[Ref], base: u32, c: &mut CandOf<S>, depth: u32) {
        let slice = &refs[(c.r.begin - base) as usize..(c.r.end - base) as usize];
        self.eval(slice, c, depth);
    }

    /// Whether the vertical decision for `n` references depends on the split at all: a
    /// leaf that costs no more than one traversal step is never worth splitting
    /// vertically (eq. 2: `K_T + K_I·S > K_I·⌈T/N⌉` when `⌈T/N⌉·K_I <= K_T`).
    fn may_split_v(&self, n: u32) -> bool {
        n > self.cost.max_leaf || (n >= 2 && self.cost.leaf(n) > self.cost.k_t)
    }

    /// Eq. 1: splitting inside the current multi-node pays (or is forced).
    fn pays_h(&self, c: &CandOf<S>) -> bool {
        let n = c.r.n();
        n >= 2 && (n > self.cost.max_leaf || self.cost.k_i * c.s < self.cost.leaf(n))
    }

    /// Eq. 2: making a new multi-node pays (or is forced).
    fn pays_v(&self, c: &CandOf<S>) -> bool {
        let n = c.r.n();
        self.may_split_v(n)
            && (n > self.cost.max_leaf || self.cost.k_t + self.cost.k_i * c.s < self.cost.leaf(n))
    }

    /// Splits candidate `c` (which lies in `refs`, whose first slot is `base`). Halves
    /// that must be split anyway (more than the leaf limit) get their split found at once,
    /// in parallel when large; the others when needed.
    fn split(
        &self,
        refs: &mut [Ref],
        base: u32,
        c: &CandOf<S>,
        depth: u32,
    ) -> (CandOf<S>, CandOf<S>) {
        let lo = (c.r.begin - base) as usize;
        let hi = (c.r.cap - base) as usize;
        let [l, r] = self.splitter.apply(&mut refs[lo..hi], &c.r, &c.plan);
        debug_assert!(l.n() > 0 && r.n() > 0);
        let (mut l, mut r) = (self.cand(l), self.cand(r));
        let refs: &[Ref] = refs;
        let max = self.cost.max_leaf;
        if self.parallel && c.r.n() >= PAR_EVAL && l.r.n() > max && r.r.n() > max {
            rayon::join(
                || self.eval_in(refs, base, &mut l, depth),
                || self.eval_in(refs, base, &mut r, depth),
            );
        } else {
            for x in [&mut l, &mut r] {
                if x.r.n() > max {
                    self.eval_in(refs, base, x, depth);
                }
            }
        }
        (l, r)
    }

    /// Builds the multi-node grown from `first` (whose references are `refs`, starting at
    /// slot `base`) into `arena`, returning its index there.
    fn build_multi(
        &self,
        arena: &mut Vec<BNode<N>>,
        refs: &mut [Ref],
        base: u32,
        first: CandOf<S>,
        depth: u32,
    ) -> u32 {
        // Horizontal splitting: the candidate with the largest area whose split pays.
        // Splits are found in that order, as they are needed.
        let mut kids = [CandOf::<S>::default(); N];
        kids[0] = first;
        let mut k = 1;
        while k < N {
            let mut pick = None;
            loop {
                let mut next = None;
                let mut best = -1.0;
                for (i, c) in kids[..k].iter().enumerate() {
                    if c.r.n() >= 2 && (!c.ready || self.pays_h(c)) && c.area > best {
                        best = c.area;
                        next = Some(i);
                    }
                }
                let Some(i) = next else { break };
                self.eval_in(refs, base, &mut kids[i], depth);
                if self.pays_h(&kids[i]) {
                    pick = Some(i);
                    break;
                }
            }
            let Some(i) = pick else { break };
            let (l, r) = self.split(refs, base, &kids[i], depth);
            kids.copy_within(i + 1..k, i + 2);
            kids[i] = l;
            kids[i + 1] = r;
            k += 1;
        }
        for c in kids[..k].iter_mut() {
            if !c.ready && self.may_split_v(c.r.n()) {
                self.eval_in(refs, base, c, depth);
            }
        }

        // Vertical splitting. The node goes in first so that arenas are in pre-order.
        let me = arena.len();
        arena.push(BNode::empty());
        let mut node = BNode::<N>::empty();
        node.count = k;
        let total: u32 = kids[..k].iter().map(|c| c.r.n()).sum();
        let mut rest: &mut [Ref] = refs;
        if !(self.parallel && total >= 2 * PAR_TASK) {
            for (i, c) in kids[..k].iter().enumerate() {
                let (mine, tail) =
                    std::mem::take(&mut rest).split_at_mut((c.r.cap - c.r.begin) as usize);
                rest = tail;
                node.boxes[i] = c.r.bounds;
                node.kids[i] = if self.pays_v(c) {
                    Kid::Local(self.build_multi(arena, mine, c.r.begin, *c, depth + 1))
                } else {
                    Kid::Leaf {
                        begin: c.r.begin,
                        n: c.r.n(),
                    }
                };
            }
        } else {
            let mut par_jobs = Vec::new();
            let mut ser_jobs = Vec::new();
            for (i, c) in kids[..k].iter().enumerate() {
                let (mine, tail) =
                    std::mem::take(&mut rest).split_at_mut((c.r.cap - c.r.begin) as usize);
                rest = tail;
                node.boxes[i] = c.r.bounds;
                if !self.pays_v(c) {
                    node.kids[i] = Kid::Leaf {
                        begin: c.r.begin,
                        n: c.r.n(),
                    };
                } else if c.r.n() >= PAR_TASK {
                    par_jobs.push((i, mine, *c));
                } else {
                    ser_jobs.push((i, mine, *c));
                }
            }
            let (remote, local) = rayon::join(
                || {
                    par_jobs
                        .into_par_iter()
                        .map(|(i, mine, c)| {
                            let mut a = Vec::with_capacity(arena_estimate::<N>(c.r.n()));
                            self.build_multi(&mut a, mine, c.r.begin, c, depth + 1);
                            (i, a)
                        })
                        .collect::<Vec<_>>()
                },
                || {
                    ser_jobs
                        .into_iter()
                        .map(|(i, mine, c)| {
                            (i, self.build_multi(arena, mine, c.r.begin, c, depth + 1))
                        })
                        .collect::<Vec<_>>()
                },
            );
            for (i, a) in remote {
                node.kids[i] = Kid::Remote(a);
            }
            for (i, idx) in local {
                node.kids[i] = Kid::Local(idx);
            }
        }

        // Subtree sizes.
        let mut sub = Sub {
            nodes: 1,
            ..Sub::default()
        };
        for kid in &node.kids[..k] {
            if let Kid::Leaf { n, .. } = kid {
                sub.leaves += 1;
                sub.blocks += n.div_ceil(N as u32);
                sub.refs += n;
            } else if let Some((a, j)) = inner(arena, kid) {
                let s = a[j].sub;
                sub.nodes += s.nodes;
                sub.leaves += s.leaves;
                sub.blocks += s.blocks;
                sub.refs += s.refs;
            }
        }
        node.sub = sub;
        arena[me] = node;
        me as u32
    }
}

/// The intermediate tree and the references its leaves point into.
pub(crate) struct Built<const N: usize> {
    /// Arena of the root task; the root is index 0.
    pub arena: Vec<BNode<N>>,
    /// References (leaves index into this).
    pub refs: Vec<Ref>,
    /// Ids of the triangles left out (degenerate or non-finite), ascending.
    pub excluded: Vec<u32>,
}

/// References of the traceable triangles, the ids of the others, and the bounds of the
/// references' boxes and centroids.
fn make_refs(tris: &[Triangle]) -> (Vec<Ref>, Vec<u32>, Aabb, Aabb) {
    // One pass over chunks writes a reference for every triangle into slot `id`, with
    // the bounds on the way; untraceable triangles are marked (scratch word 1) and left
    // out of the bounds. Nearly every scene has none, and then that is all; otherwise
    // the marked references are squeezed out in order.
    const CHUNK: usize = 1 << 12;
    let mut refs = vec![Ref::default(); tris.len()];
    let (bounds, cent, bad) = refs
        .par_chunks_mut(CHUNK)
        .zip(tris.par_chunks(CHUNK))
        .enumerate()
        .map(|(ci, (out, tc))| {
            let mut b = B4::EMPTY;
            let mut c = B4::EMPTY;
            let mut bad = 0usize;
            let base = ci * CHUNK;
            for (i, (r, t)) in out.iter_mut().zip(tc).enumerate() {
                let id = f32::from_bits((base + i) as u32);
                if !is_traceable(t) {
                    r.lo[3] = id;
                    r.set_aux(1);
                    bad += 1;
                    continue;
                }
                let mut tb = B4::point([t.v[0][0], t.v[0][1], t.v[0][2], 0.0]);
                for p in &t.v[1..] {
                    tb.grow(&B4::point([p[0], p[1], p[2], 0.0]));
                }
                *r = Ref {
                    lo: [tb.lo[0], tb.lo[1], tb.lo[2], id],
                    hi: [tb.hi[0], tb.hi[1], tb.hi[2], 0.0],
                };
                b.grow(&tb);
                let m: [f32; 4] = std::array::from_fn(|k| tb.lo[k] * 0.5 + tb.hi[k] * 0.5);
                c.grow(&B4::point(m));
            }
            (b, c, bad)
        })
        .reduce(
            || (B4::EMPTY, B4::EMPTY, 0),
            |mut x, y| {
                x.0.grow(&y.0);
                x.1.grow(&y.1);
                (x.0, x.1, x.2 + y.2)
            },
        );
    let mut excluded = Vec::with_capacity(bad);
    if bad > 0 {
        refs.retain(|r| {
            if r.aux() == 1 {
                excluded.push(r.id());
                false
            } else {
                true
            }
        });
    }
    (refs, excluded, bounds.aabb(), cent.aabb())
}

/// Box and centroid box of `refs` (in parallel for long slices).
pub(crate) fn bounds_of(refs: &[Ref]) -> (Aabb, Aabb) {
    fn scan(refs: &[Ref]) -> (Aabb, Aabb) {
        let mut b = B4::EMPTY;
        let mut c = B4::EMPTY;
        for r in refs {
            b.grow(&r.b4());
            c.grow_centroid(r);
        }
        (b.aabb(), c.aabb())
    }
    if refs.len() < 1 << 15 {
        return scan(refs);
    }
    refs.par_chunks(1 << 13).map(scan).reduce(
        || (Aabb::EMPTY, Aabb::EMPTY),
        |a, b| (union(&a.0, &b.0), union(&a.1, &b.1)),
    )
}

/// Builds the intermediate N-wide tree over `tris` with the given quality and costs.
pub(crate) fn build<const N: usize>(
    tris: &[Triangle],
    quality: BuildQuality,
    cost: CostModel,
) -> Built<N> {
    assert!(
        tris.len() < (1 << 28),
        "a BVH holds fewer than 2^28 triangles (got {})",
        tris.len()
    );
    let (mut refs, excluded, bounds, cent) = make_refs(tris);
    let n = refs.len() as u32;
    let parallel = rayon::current_num_threads() > 1;
    let arena = match quality {
        BuildQuality::Sah | BuildQuality::Sbvh => {
            let spatial = quality == BuildQuality::Sbvh;
            if spatial {
                // Room for spatial splits to duplicate every reference once.
                refs.resize(2 * refs.len(), Ref::default());
            }
            let root = Range {
                begin: 0,
                end: n,
                cap: refs.len() as u32,
                bounds,
                info: Centroids(cent),
            };
            let splitter = SahSplitter::new(tris, spatial, &bounds);
            let b = Builder::<_, N> {
                splitter: &splitter,
                cost,
                parallel,
            };
            build_root(&b, &mut refs, root)
        }
        BuildQuality::Fast => {
            let (nodes, root_info) = morton::sort_and_link(&mut refs, &cent, parallel);
            let splitter = MortonSplitter { nodes: &nodes };
            let root = Range {
                begin: 0,
                end: n,
                cap: n,
                bounds,
                info: root_info,
            };
            let b = Builder::<_, N> {
                splitter: &splitter,
                cost,
                parallel,
            };
            build_root(&b, &mut refs, root)
        }
    };
    Built {
        arena,
        refs,
        excluded,
    }
}

/// Room for the multi-nodes of a subtree over `n` references, so that its arena is
/// seldom moved while it grows: leaves average about N/2 triangles and multi-nodes about
/// 0.7·N lanes, so there are about n / (0.35·N²) nodes; a third more for slack.
fn arena_estimate<const N: usize>(n: u32) -> usize {
    (n as usize * 4).div_ceil(N * N) + 1
}

fn build_root<S: Splitter, const N: usize>(
    b: &Builder<'_, S, N>,
    refs: &mut [Ref],
    root: Range<S::Info>,
) -> Vec<BNode<N>> {
    let mut arena = Vec::with_capacity(arena_estimate::<N>(root.n()));
    if root.n() == 0 {
        arena.push(BNode::empty());
        return arena;
    }
    let mut c = b.cand(root);
    b.eval(&refs[..root.n() as usize], &mut c, 0);
    b.build_multi(&mut arena, refs, 0, c, 0);
    arena
}
