//! The divide-and-conquer recursion (Áfra 2012 §2–3.4, Nabata et al. 2013 Algorithm 1).
//!
//! A step receives its active rays (a prefix of the ray array, already filtered against its
//! box), its triangles (a slice of the id array) and their boxes. It either intersects them
//! naively (a leaf) or partitions the triangles, orders the two children, and for each child
//! filters the rays against the child's box in place and recurses on the new prefix. The
//! second child's filtering sees the `tmax` values the first child's hits left in the
//! records, which is what makes front-to-back order pay.

use std::sync::atomic::AtomicIsize;
use std::time::Instant;

use crate::geometry::Aabb;

use super::leaf::{leaf, LeafTest, Table};
use super::options::{DacrtOptions, ForkSplit};
use super::parallel;
use super::rays::{filter, filter2, filter_back, FilterBox, RayRec};
use super::sampling::{sample_pair, sampled_cost, Sampled};
use super::split::{middle, sah, split_axis, Bins, Candidate, Node, Parts, CANDIDATES};
use super::stats::{lap, Stats};
use super::top::Top;
use super::tris::TriData;

/// What every step of one trace shares.
pub struct Ctx<'a> {
    /// The frame's triangles.
    pub tris: &'a TriData,
    /// Tunables.
    pub opts: &'a DacrtOptions,
    /// `any` query: rays leave the active set at their first hit.
    pub any: bool,
    /// Counters, when collected.
    pub stats: Option<&'a Stats>,
    /// Whether more than one thread may work on this trace.
    pub parallel: bool,
    /// Ray records that forks may still copy (see `parallel.rs`).
    pub budget: AtomicIsize,
    /// Which threads are busy (the fork decision).
    pub workers: parallel::Workers,
    /// Steps with at least this many rays work data-parallel; below, they fork. At most the
    /// option's value, and small enough that several forks fit in the copy budget.
    pub data_min_rays: usize,
}

impl Ctx<'_> {
    /// A clock reading when stats are collected.
    #[inline]
    pub fn clock(&self) -> Option<Instant> {
        self.stats.map(|_| Instant::now())
    }

    /// Filters `rays` in place against `b`; returns the number of active rays (now first).
    pub fn filter(&self, rays: &mut [RayRec], b: &Aabb) -> usize {
        let t0 = self.clock();
        let fb = FilterBox::new(b);
        let n = if self.parallel && rays.len() >= self.data_min_rays {
            parallel::filter_par(rays, &fb, self.opts.parallel.grain)
        } else {
            filter(rays, &fb)
        };
        if let Some(s) = self.stats {
            Stats::add(&s.box_tests, rays.len() as u64);
            lap(&s.filter_ns, t0);
        }
        n
    }
}

/// One child to visit: its boxes, its triangles, and whether it takes its parent's rays
/// unfiltered.
pub struct Child<'i> {
    /// Boxes.
    pub node: Node,
    /// Triangle ids.
    pub ids: &'i mut [u32],
    /// Nabata's skip: no filtering for this child.
    pub skip: bool,
    /// The child's partition, when the shared top levels already made it.
    pub top: Option<&'i Top>,
}

/// One traversal step. `top`, when given, is this node's partition made once for all
/// threads (`top.rs`): `ids` is already partitioned that way and the step only orders and
/// filters.
pub fn step<T: LeafTest>(
    ctx: &Ctx,
    rays: &mut [RayRec],
    table: &mut Table,
    ids: &mut [u32],
    node: &Node,
    depth: u32,
    top: Option<&Top>,
) {
    let o = ctx.opts;
    if rays.len() < o.leaf_rays || ids.len() < o.leaf_tris {
        return leaf_step::<T>(ctx, rays, table, ids);
    }
    if ctx.parallel
        && ctx.opts.parallel.split == ForkSplit::Rays
        && parallel::should_fork(ctx, rays.len())
        && parallel::fork_rays::<T>(ctx, rays, table, ids, node, depth, top)
    {
        return;
    }
    let t0 = ctx.clock();
    let plan = plan(ctx, rays, ids, node, depth, top);
    if let Some(s) = ctx.stats {
        lap(&s.split_ns, t0);
    }
    let Some(plan) = plan else {
        return leaf_step::<T>(ctx, rays, table, ids);
    };
    if let Some(s) = ctx.stats {
        Stats::add(&s.nodes, 1);
    }
    let (ids_l, ids_r) = ids.split_at_mut(plan.parts.mid);
    let kids = top.map_or([None, None], |t| t.kids());
    let left = Child {
        node: plan.parts.left,
        ids: ids_l,
        skip: plan.skip[0],
        top: kids[0],
    };
    let right = Child {
        node: plan.parts.right,
        ids: ids_r,
        skip: plan.skip[1],
        top: kids[1],
    };
    let (first, second) = if plan.first_left {
        (left, right)
    } else {
        (right, left)
    };
    if ctx.parallel
        && ctx.opts.parallel.split == ForkSplit::Tris
        && parallel::should_fork(ctx, rays.len())
    {
        return parallel::fork_tris::<T>(ctx, rays, table, first, second, depth);
    }
    let data_parallel = ctx.parallel && rays.len() >= ctx.data_min_rays;
    if !o.two_box || first.skip || second.skip || data_parallel {
        visit::<T>(ctx, rays, table, first, depth);
        visit::<T>(ctx, rays, table, second, depth);
        return;
    }
    // Both boxes in one pass: [enter the first | enter only the second | neither]. After
    // the first child, only its rays can have changed `tmax`, so only they are filtered
    // again for the second box, towards the back of their range, which makes them
    // adjacent to the rays that enter only the second box.
    let (b1, b2) = (
        FilterBox::new(&first.node.bounds),
        FilterBox::new(&second.node.bounds),
    );
    let t0 = ctx.clock();
    let n = rays.len();
    let (n1, k2) = filter2(rays, &b1, &b2);
    if let Some(s) = ctx.stats {
        Stats::add(&s.box_tests, 2 * n as u64);
        lap(&s.filter_ns, t0);
    }
    if n1 > 0 {
        step::<T>(
            ctx,
            &mut rays[..n1],
            table,
            first.ids,
            &first.node,
            depth + 1,
            first.top,
        );
    }
    let t0 = ctx.clock();
    let m = if n1 > 0 {
        filter_back(&mut rays[..n1], &b2)
    } else {
        0
    };
    if let Some(s) = ctx.stats {
        Stats::add(&s.box_tests, n1 as u64);
        lap(&s.filter_ns, t0);
    }
    let (lo, hi) = (n1 - m, n1 + k2);
    if hi > lo {
        step::<T>(
            ctx,
            &mut rays[lo..hi],
            table,
            second.ids,
            &second.node,
            depth + 1,
            second.top,
        );
    }
}

/// Filters `rays` for `child` (unless it skips) and recurses on the active prefix.
pub fn visit<T: LeafTest>(
    ctx: &Ctx,
    rays: &mut [RayRec],
    table: &mut Table,
    child: Child,
    depth: u32,
) {
    let m = if child.skip {
        if let Some(s) = ctx.stats {
            Stats::add(&s.skips, 1);
        }
        rays.len()
    } else {
        ctx.filter(rays, &child.node.bounds)
    };
    if m > 0 {
        step::<T>(
            ctx,
            &mut rays[..m],
            table,
            child.ids,
            &child.node,
            depth + 1,
            child.top,
        );
    }
}

/// Naive intersection of a leaf.
fn leaf_step<T: LeafTest>(ctx: &Ctx, rays: &mut [RayRec], table: &mut Table, ids: &[u32]) {
    let t0 = ctx.clock();
    if ctx.parallel && rays.len() >= ctx.data_min_rays {
        parallel::leaf_par::<T>(ctx, rays, table, ids);
    } else {
        leaf::<T, _>(ctx.tris, rays, table, ids, ctx.any);
    }
    if let Some(s) = ctx.stats {
        Stats::add(&s.leaves, 1);
        Stats::add(&s.tri_tests, (rays.len() * ids.len()) as u64);
        lap(&s.leaf_ns, t0);
    }
}

/// How a node splits.
struct Plan {
    parts: Parts,
    first_left: bool,
    /// Skip filtering for [left, right].
    skip: [bool; 2],
}

/// Most sample rays a node draws.
pub(super) const MAX_SAMPLES: usize = 256;

/// A small deterministic generator for the sample positions (splitmix64).
pub(super) struct Rng(pub(super) u64);

impl Rng {
    pub(super) fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    pub(super) fn below(&mut self, n: usize) -> usize {
        (((self.next() >> 32) * n as u64) >> 32) as usize
    }
}

/// Draws the sample rays of a node with `rays` active into `buf` (none when sampling is
/// off or the node has too few rays); returns how many.
fn draw_samples(
    ctx: &Ctx,
    rays: &[RayRec],
    t: usize,
    depth: u32,
    buf: &mut [RayRec; MAX_SAMPLES],
) -> usize {
    let s = &ctx.opts.sampling;
    let n = rays.len();
    if !(s.enabled() && n > s.min_rays) {
        return 0;
    }
    let ns = s.samples.min(MAX_SAMPLES);
    let mut rng = Rng((n as u64) << 32 ^ (t as u64) << 8 ^ u64::from(depth));
    for b in buf.iter_mut().take(ns) {
        *b = rays[rng.below(n)];
    }
    ns
}

/// Partitions `ids` for a node with `n` active rays (SAH or sampled-cost binning above the
/// ratio of rays to triangles, the middle below), using `samples` for the sampled cost.
/// Returns the parts and, for the sampled cost, what the samples said about the chosen
/// pair; `None` when the node should be a leaf.
pub(super) fn choose(
    ctx: &Ctx,
    samples: &[RayRec],
    n: usize,
    ids: &mut [u32],
    node: &Node,
) -> Option<(Parts, Option<Sampled>)> {
    let o = ctx.opts;
    let s = &o.sampling;
    let boxes = &ctx.tris.boxes;
    let t = ids.len();
    let ns = samples.len();
    let mut info: Option<Sampled> = None;
    let parts = if n as f32 > o.sah_ratio * t as f32 {
        // Áfra bins the widest centroid axis only; `all_axes` bins the three. No iterator
        // chains or vectors of bins here: a binning is 2 KiB, and moving it around cost
        // more than filling it.
        let par = ctx.parallel && t >= o.parallel.data_min_tris;
        let bin = |axis: usize, big: f32| {
            if par {
                parallel::bins_par(boxes, ids, node, axis, big, o.parallel.grain)
            } else {
                Bins::new(boxes, ids, node, axis, big)
            }
        };
        let first = split_axis(&node.cents).0;
        // The size candidate once per node.
        let mut binned: [Option<Bins>; 3] = [bin(first, o.big_fraction), None, None];
        if o.all_axes {
            let others = [(first + 1) % 3, (first + 2) % 3];
            binned[1] = bin(others[0], 0.0);
            binned[2] = bin(others[1], 0.0);
        }
        let binned: Vec<&Bins> = binned.iter().flatten().collect();
        let per = CANDIDATES;
        let mut cands: Vec<Candidate> = Vec::with_capacity(per * binned.len());
        for b in &binned {
            b.candidates_into(&mut cands);
        }
        let j = if ns > 0 && s.cost {
            let (j, si) = sampled_cost(&cands, samples, &node.bounds, s.prior)?;
            info = Some(si);
            j
        } else {
            let (j, cost) = sah(&cands, &node.bounds)?;
            if t <= o.sah_stop_max && o.traversal_cost + cost >= t as f32 {
                return None;
            }
            j
        };
        let (bins, j) = (binned[j / per], j % per);
        if let Some(st) = ctx.stats {
            Stats::add(&st.binned, 1);
        }
        if ctx.parallel && t >= o.parallel.data_min_tris {
            parallel::partition_bins_par(bins, boxes, ids, j, o.parallel.grain)
        } else {
            bins.partition(boxes, ids, j)
        }
    } else if ctx.parallel && t >= o.parallel.data_min_tris {
        parallel::middle_par(boxes, ids, node, o.parallel.grain)?
    } else {
        middle(boxes, ids, node)?
    };
    Some((parts, info))
}

/// Partitions the node's triangles (unless the shared top levels did) and decides order
/// and skips.
fn plan(
    ctx: &Ctx,
    rays: &[RayRec],
    ids: &mut [u32],
    node: &Node,
    depth: u32,
    top: Option<&Top>,
) -> Option<Plan> {
    let o = ctx.opts;
    let s = &o.sampling;
    let t = ids.len();
    let mut buf = [RayRec::default(); MAX_SAMPLES];
    let ns = draw_samples(ctx, rays, t, depth, &mut buf);
    let samples = &buf[..ns];
    let (parts, mut info) = match top {
        Some(top) => (top.parts, None),
        None => choose(ctx, samples, rays.len(), ids, node)?,
    };
    if ns > 0 && info.is_none() && (s.order || s.skip) {
        info = Some(sample_pair(
            samples,
            &parts.left.bounds,
            &parts.right.bounds,
        ));
    }
    if let (Some(st), true) = (ctx.stats, ns > 0) {
        Stats::add(&st.sampled, 1);
        Stats::add(&st.box_tests, (ns * 2) as u64);
    }
    // A child nested in the other's box goes first: the outer one encloses it (a room
    // around an object), every ray enters the outer box at once, and neither rule below
    // sees that the inner one is hit first.
    let first_left = if contains(&parts.right.bounds, &parts.left.bounds) {
        true
    } else if contains(&parts.left.bounds, &parts.right.bounds) {
        false
    } else {
        match info {
            // A tie (typically every sample ray starts inside both boxes, entry 0) says
            // nothing: the first ray's direction does.
            Some(si) if s.order && si.nearer_left != si.nearer_right => {
                si.nearer_left > si.nearer_right
            }
            _ => afra_first_left(&rays[0], &parts),
        }
    };
    let skip = match info {
        Some(si) if s.skip => [
            skip_filtering(o, si.hits_left, ns, parts.mid),
            skip_filtering(o, si.hits_right, ns, t - parts.mid),
        ],
        _ => [false, false],
    };
    Some(Plan {
        parts,
        first_left,
        skip,
    })
}

/// Nabata's criterion (eq. 5): skip a child's filtering when the fraction `α` of sample rays
/// entering it exceeds `1 - C_bv / (n_child · C_child)`. For a child that will be split,
/// `n_child = 2` and `C_child = C_bv`, so `α > 0.5` (eq. 6); for a child that will be a leaf
/// (fewer triangles than `leaf_tris`), `n_child` is its triangle count and `C_child` a
/// ray/triangle test, so unfiltered rays must be rarer still before skipping pays.
fn skip_filtering(o: &DacrtOptions, hits: u32, samples: usize, tris: usize) -> bool {
    let alpha = hits as f32 / samples as f32;
    let limit = if tris < o.leaf_tris {
        1.0 - o.sampling.box_cost / tris.max(1) as f32
    } else {
        0.5
    };
    alpha > limit
}

/// Whether `outer` contains `inner`.
fn contains(outer: &Aabb, inner: &Aabb) -> bool {
    (0..3).all(|k| outer.min[k] <= inner.min[k] && inner.max[k] <= outer.max[k])
}

/// Áfra's order (after Wald et al. 2007): on the axis where the children's centres are
/// farthest apart, the first active ray's direction picks the nearer child.
fn afra_first_left(ray: &RayRec, p: &Parts) -> bool {
    let (cl, cr) = (p.left.bounds.center(), p.right.bounds.center());
    let mut axis = 0;
    let mut best = -1.0f32;
    for k in 0..3 {
        let d = (cl[k] - cr[k]).abs();
        if d > best {
            best = d;
            axis = k;
        }
    }
    let left_lower = cl[axis] <= cr[axis];
    if ray.dir()[axis] >= 0.0 {
        left_lower
    } else {
        !left_lower
    }
}
