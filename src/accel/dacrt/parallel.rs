//! Several threads on one trace, without giving each thread its own copy of all rays (the
//! papers' "naive" multithreading, which repeats the partitioning per thread).
//!
//! Two mechanisms, chosen by the number of active rays of a step:
//!
//! - **Data-parallel steps** (many rays: the top of the recursion, where there are few
//!   nodes but each is huge). Filtering is an in-place parallel partition: both halves of
//!   the range are filtered recursively in parallel, then the inactive block of the left
//!   half and the active block of the right half trade places (only the shorter of the two
//!   moves). Big triangle ranges are binned and partitioned the same way, and leaves with
//!   many rays test them in parallel chunks whose hits are written back afterwards. No
//!   copies, and front-to-back culling is exactly that of one thread.
//! - **Forks** (fewer rays: the many smaller subtrees below). A fork runs the first child
//!   on a *copy* of its filtered rays with a task-local hit table while the second child
//!   stays stealable. If another thread steals it, the thief builds its own copy from the
//!   parent's rays — which nobody writes during the fork, since the first child works on its
//!   copy — and the two children run at once. If nobody steals it, it runs afterwards on the
//!   parent's array in place, as in one thread, after the first child's hits are merged
//!   back into the parent's records, so its filtering still culls with them. A child's
//!   local table holds, per copied ray, the parent's slot in `v`: merging is one pass over
//!   the copy. Forks are made only when the thread has no stealable work already, and the
//!   records they copy are bounded by a budget, which is what keeps memory near the papers'
//!   formula.
//! - **Ray-split forks** (the default in the fork band): the step's rays are split into
//!   two coherent halves that traverse the same node at once (see [`fork_rays`]); each half
//!   keeps its own front-to-back culling, at the price of partitioning the node's triangles
//!   twice — except in the top levels, which a batch partitions once for all threads
//!   before its first split (`top.rs`). A batch itself starts split into one group of
//!   rays per thread (`Dacrt::groups`), so these forks only rebalance the work later.
//!
//! Forks are made only when a thread is idle ([`Workers`]), so the second half is almost
//! always taken by another thread at once.

use std::sync::atomic::AtomicUsize;
use std::sync::atomic::Ordering::Relaxed;

use rayon::prelude::*;

use crate::geometry::Hit;

use super::leaf::{leaf, merge_slot, LeafTest, Sink, Table};
use super::rays::{filter, filter_copy, FilterBox, RayRec, SLOT_MASK};
use super::split::{middle_plane, partition_acc, Acc, Bins, Node, Parts};
use super::stats::{lap, Stats};
use super::top::Top;
use super::traverse::{step, visit, Child, Ctx};
use super::tris::TriBox;

/// Partitions `v` in place on several threads: `part` partitions one chunk (selected
/// elements first) and returns how many it selected plus a summary; the summaries are
/// combined with `merge`. Returns the total selected and the combined summary.
///
/// Chunks are partitioned in parallel, then the elements on the wrong side of the final
/// boundary — unselected ones before it, selected ones after it, equally many — are paired
/// up and swapped, in one parallel round. Every element moves at most once more than in a
/// sequential partition (a recursive merge of halves would move up to half of them once
/// per level).
pub fn par_partition<T: Send, R: Send>(
    v: &mut [T],
    grain: usize,
    part: impl Fn(&mut [T]) -> (usize, R) + Sync,
    merge: impl Fn(R, R) -> R,
) -> (usize, R) {
    let n = v.len();
    let pieces = 4 * rayon::current_num_threads();
    let chunk = (n.div_ceil(pieces).max(grain).max(8) + 7) & !7;
    if n <= chunk {
        return part(v);
    }
    let results: Vec<(usize, R)> = v.par_chunks_mut(chunk).map(&part).collect();
    let m: usize = results.iter().map(|r| r.0).sum();
    // The misplaced ranges, in position order: unselected tails inside [0, m), selected
    // heads inside [m, n).
    let mut wrong: Vec<(usize, usize, bool)> = Vec::new();
    for (i, (a, _)) in results.iter().enumerate() {
        let (s, e) = (i * chunk, ((i + 1) * chunk).min(n));
        let (tail_lo, tail_hi) = (s + a, e.min(m));
        if tail_lo < tail_hi {
            wrong.push((tail_lo, tail_hi, false));
        }
        let (head_lo, head_hi) = (s.max(m), s + a);
        if head_lo < head_hi {
            wrong.push((head_lo, head_hi, true));
        }
    }
    // Carve the slice into those ranges (disjoint, ascending), then pair them up.
    let mut lows: Vec<&mut [T]> = Vec::new();
    let mut highs: Vec<&mut [T]> = Vec::new();
    let mut rest = v;
    let mut at = 0;
    for &(lo, hi, selected) in &wrong {
        let (_, r) = rest.split_at_mut(lo - at);
        let (mid, r) = r.split_at_mut(hi - lo);
        rest = r;
        at = hi;
        if selected {
            highs.push(mid);
        } else {
            lows.push(mid);
        }
    }
    let mut pairs: Vec<(&mut [T], &mut [T])> = Vec::new();
    let (mut li, mut hi) = (lows.into_iter(), highs.into_iter());
    let (mut l, mut h) = (li.next(), hi.next());
    while let (Some(a), Some(b)) = (l.take(), h.take()) {
        let k = a.len().min(b.len()).min(grain.max(8));
        let (a0, a1) = a.split_at_mut(k);
        let (b0, b1) = b.split_at_mut(k);
        pairs.push((a0, b0));
        l = if a1.is_empty() { li.next() } else { Some(a1) };
        h = if b1.is_empty() { hi.next() } else { Some(b1) };
    }
    pairs
        .into_par_iter()
        .for_each(|(a, b)| a.swap_with_slice(b));
    let summary = results
        .into_iter()
        .map(|r| r.1)
        .reduce(merge)
        .expect("at least one chunk");
    (m, summary)
}

/// [`filter`] on several threads, in pieces of at least `grain` rays.
pub fn filter_par(rays: &mut [RayRec], b: &FilterBox, grain: usize) -> usize {
    par_partition(rays, grain, |c| (filter(c, b), ()), |_, _| ()).0
}

/// [`partition_acc`] on several threads.
fn partition_par(
    boxes: &[TriBox],
    ids: &mut [u32],
    left: &(impl Fn(&TriBox) -> bool + Sync),
    grain: usize,
) -> (usize, Acc, Acc) {
    let (m, (l, r)) = par_partition(
        ids,
        grain,
        |c| {
            let (m, l, r) = partition_acc(boxes, c, left);
            (m, (l, r))
        },
        |(mut l, mut r), (l2, r2)| {
            l.merge(&l2);
            r.merge(&r2);
            (l, r)
        },
    );
    (m, l, r)
}

fn parts(ids_len: usize, (mid, l, r): (usize, Acc, Acc)) -> Option<Parts> {
    (mid > 0 && mid < ids_len).then(|| Parts {
        mid,
        left: l.node(),
        right: r.node(),
    })
}

/// [`super::split::middle`] on several threads.
pub fn middle_par(boxes: &[TriBox], ids: &mut [u32], node: &Node, grain: usize) -> Option<Parts> {
    let (axis, pivot, le) = middle_plane(node)?;
    let n = ids.len();
    let r = if le {
        partition_par(boxes, ids, &|b: &TriBox| b.centroid(axis) <= pivot, grain)
    } else {
        partition_par(boxes, ids, &|b: &TriBox| b.centroid(axis) < pivot, grain)
    };
    parts(n, r)
}

/// [`Bins::new`] on several threads.
pub fn bins_par(
    boxes: &[TriBox],
    ids: &[u32],
    node: &Node,
    axis: usize,
    big: f32,
    grain: usize,
) -> Option<Bins> {
    let empty = Bins::empty_on(node, axis, big)?;
    let bins = ids
        .par_chunks(grain.max(1))
        .map(|c| {
            let mut b = Bins::empty_on(node, axis, big).expect("same node");
            b.fill(boxes, c);
            b
        })
        .reduce_with(|mut a, b| {
            a.merge(&b);
            a
        });
    Some(bins.unwrap_or(empty))
}

/// [`Bins::partition`] on several threads.
pub fn partition_bins_par(
    bins: &Bins,
    boxes: &[TriBox],
    ids: &mut [u32],
    j: usize,
    grain: usize,
) -> Parts {
    let (mid, l, r) = partition_par(boxes, ids, &|b: &TriBox| bins.goes_left(j, b), grain);
    Parts {
        mid,
        left: l.node(),
        right: r.node(),
    }
}

/// A sink that defers its writes: what parallel chunks of one leaf use.
struct Deferred<'t> {
    tmin: &'t [f32],
    out: Vec<(u32, Hit)>,
}

impl Sink for Deferred<'_> {
    fn tmin(&self, index: usize) -> f32 {
        self.tmin.get(index).copied().unwrap_or(0.0)
    }

    fn offer(&mut self, index: usize, hit: Hit, _old: f32, _any: bool) -> f32 {
        self.out.push((index as u32, hit));
        hit.t
    }
}

/// A leaf with many rays: chunks of rays in parallel, hits merged into `table` afterwards.
pub fn leaf_par<T: LeafTest>(ctx: &Ctx, rays: &mut [RayRec], table: &mut Table, ids: &[u32]) {
    let tmin = table.tmin;
    let outs: Vec<Vec<(u32, Hit)>> = rays
        .par_chunks_mut(ctx.opts.parallel.grain)
        .map(|chunk| {
            let mut d = Deferred {
                tmin,
                out: Vec::new(),
            };
            leaf::<T, _>(ctx.tris, chunk, &mut d, ids, ctx.any);
            d.out
        })
        .collect();
    for (index, hit) in outs.into_iter().flatten() {
        merge_slot(&mut table.hits[index as usize], hit, ctx.any);
    }
}

/// Whether a step with `n` active rays should fork: it is in the fork band and some thread
/// is idle (counting the forks whose second half nobody has started), so that the fork is
/// taken at once rather than run later by this thread. The fork itself checks the budget.
pub fn should_fork(ctx: &Ctx, n: usize) -> bool {
    let p = &ctx.opts.parallel;
    n >= p.fork_min_rays && n < ctx.data_min_rays && ctx.workers.idle()
}

/// Takes `n` records from the fork budget, or says there is not enough.
fn reserve(ctx: &Ctx, n: usize) -> bool {
    let n = n as isize;
    if ctx.budget.fetch_sub(n, Relaxed) >= n {
        true
    } else {
        ctx.budget.fetch_add(n, Relaxed);
        false
    }
}

fn release(ctx: &Ctx, n: usize) {
    ctx.budget.fetch_add(n as isize, Relaxed);
}

/// How many pool threads are working on this trace, for the fork decision.
pub struct Workers {
    threads: usize,
    /// Threads running a part of the trace (not waiting in a join).
    busy: AtomicUsize,
    /// Forks whose second half has not started yet: each will occupy a thread.
    pending: AtomicUsize,
}

impl Workers {
    /// One thread busy (the caller) out of `threads`.
    pub fn new(threads: usize) -> Workers {
        Workers {
            threads,
            busy: AtomicUsize::new(1),
            pending: AtomicUsize::new(0),
        }
    }

    /// Whether some thread has nothing to do.
    fn idle(&self) -> bool {
        self.busy.load(Relaxed) + self.pending.load(Relaxed) < self.threads
    }
}

/// `rayon::join_context` with the bookkeeping of [`Workers`]: the first half continues
/// this thread's work, the second is pending until it starts (here or on a thief).
pub(super) fn join_tracked<RA: Send, RB: Send>(
    ctx: &Ctx,
    a: impl FnOnce() -> RA + Send,
    b: impl FnOnce(bool) -> RB + Send,
) -> (RA, RB) {
    let w = &ctx.workers;
    w.pending.fetch_add(1, Relaxed);
    let r = rayon::join_context(
        |_| {
            let r = a();
            w.busy.fetch_sub(1, Relaxed);
            r
        },
        |c| {
            w.pending.fetch_sub(1, Relaxed);
            w.busy.fetch_add(1, Relaxed);
            let r = b(c.migrated());
            w.busy.fetch_sub(1, Relaxed);
            r
        },
    );
    w.busy.fetch_add(1, Relaxed);
    r
}

/// A child's rays copied out of its parent's, with a local hit table and, per copied ray,
/// its position in the parent's array (`link`), through which the results go back.
struct Copy {
    rays: Vec<RayRec>,
    hits: Vec<Hit>,
    link: Vec<u32>,
    tmin: Vec<f32>,
}

impl Copy {
    /// Copies the rays of `parent` that `child` needs (all of them when it skips filtering).
    fn make(ctx: &Ctx, parent: &[RayRec], ptmin: &[f32], child: &Child) -> Copy {
        let t0 = ctx.clock();
        let mut rays = Vec::with_capacity(parent.len());
        let mut link = Vec::with_capacity(parent.len());
        if child.skip {
            for (i, r) in parent.iter().enumerate() {
                let mut r = *r;
                r.set_index(i as u32);
                rays.push(r);
                link.push(i as u32);
            }
        } else {
            filter_copy(
                parent,
                &FilterBox::new(&child.node.bounds),
                &mut rays,
                &mut link,
            );
        }
        let hits = rays.iter().map(|r| open_slot(r.tmax())).collect();
        let tmin = if ptmin.is_empty() {
            Vec::new()
        } else {
            link.iter()
                .map(|&p| ptmin[parent[p as usize].index()])
                .collect()
        };
        if let Some(s) = ctx.stats {
            Stats::add(&s.box_tests, parent.len() as u64);
            lap(&s.filter_ns, t0);
        }
        Copy {
            rays,
            hits,
            link,
            tmin,
        }
    }

    /// Runs the child on the copy.
    fn run<T: LeafTest>(&mut self, ctx: &Ctx, child: Child, depth: u32) {
        if !self.rays.is_empty() {
            let mut table = Table {
                hits: &mut self.hits,
                tmin: &self.tmin,
            };
            step::<T>(
                ctx,
                &mut self.rays,
                &mut table,
                child.ids,
                &child.node,
                depth + 1,
                child.top,
            );
        }
    }

    /// Writes the copy's hits back into the parent's table and records.
    fn merge(&self, ctx: &Ctx, parent: &mut [RayRec], ptable: &mut Table) {
        let t0 = ctx.clock();
        for (h, &p) in self.hits.iter().zip(&self.link) {
            if h.prim == u32::MAX {
                continue;
            }
            let r = &mut parent[p as usize];
            let t = merge_slot(&mut ptable.hits[r.index()], *h, ctx.any);
            r.set_tmax(if ctx.any { f32::NEG_INFINITY } else { t });
        }
        if let Some(s) = ctx.stats {
            lap(&s.merge_ns, t0);
        }
    }

    /// Records held.
    fn len(&self) -> usize {
        self.rays.len()
    }
}

/// A hit slot that has found nothing yet, for a ray whose interval ends at `tmax`.
fn open_slot(tmax: f32) -> Hit {
    Hit {
        t: tmax,
        prim: u32::MAX,
        u: 0.0,
        v: 0.0,
    }
}

/// A triangle-split fork: `first` and `second` at once (see the module docs).
pub fn fork_tris<T: LeafTest>(
    ctx: &Ctx,
    rays: &mut [RayRec],
    table: &mut Table,
    first: Child,
    second: Child,
    depth: u32,
) {
    let n = rays.len();
    if !reserve(ctx, n) {
        visit::<T>(ctx, rays, table, first, depth);
        visit::<T>(ctx, rays, table, second, depth);
        return;
    }
    let (prays, ptmin): (&[RayRec], &[f32]) = (rays, table.tmin);
    // The first child's copy is made inside the fork, so that a thief can copy the second
    // child's rays from the same (read-only) parent array at the same time.
    let (a, b) = join_tracked(
        ctx,
        || {
            let mut a = Copy::make(ctx, prays, ptmin, &first);
            release(ctx, n - a.len());
            a.run::<T>(ctx, first, depth);
            a
        },
        |migrated| {
            if !migrated || !reserve(ctx, n) {
                return Err(second);
            }
            let mut b = Copy::make(ctx, prays, ptmin, &second);
            release(ctx, n - b.len());
            b.run::<T>(ctx, second, depth);
            Ok(b)
        },
    );
    a.merge(ctx, rays, table);
    release(ctx, a.len());
    drop(a);
    match b {
        Ok(b) => {
            if let Some(s) = ctx.stats {
                Stats::add(&s.forks_stolen, 1);
            }
            b.merge(ctx, rays, table);
            release(ctx, b.len());
        }
        Err(second) => {
            if let Some(s) = ctx.stats {
                Stats::add(&s.forks_local, 1);
            }
            visit::<T>(ctx, rays, table, second, depth);
        }
    }
}

/// The median slot index of `rays`, estimated from 63 evenly spaced records.
fn slot_median(rays: &[RayRec]) -> u32 {
    let k = 63.min(rays.len());
    let mut s: Vec<u32> = (0..k)
        .map(|i| rays[i * rays.len() / k].index() as u32)
        .collect();
    let mid = k / 2;
    *s.select_nth_unstable(mid).1
}

/// Adds `delta` (mod 2^31) to the slot index of every record.
fn rebase(rays: &mut [RayRec], delta: u32) {
    for r in rays {
        r.set_index((r.index() as u32).wrapping_add(delta) & SLOT_MASK);
    }
}

/// A ray-split fork: the step's rays are split at a slot index into two halves that are
/// coherent (for camera rays, image bands), and the same node is traversed for both at once.
/// Since the halves hold the slots below and above the split, the hit table splits there
/// too, into two disjoint slices: nothing is copied but the node's id array (each half
/// partitions the node's triangles its own way); the second half's records count their
/// slots from the split while it runs. Where the node is in the shared top levels
/// (`top.rs`), the copy is already partitioned and both halves follow the same partitions
/// there. Each half keeps its own front-to-back culling,
/// which a triangle-split fork loses for the far child. Returns false (nothing done) when
/// the rays do not split.
pub fn fork_rays<T: LeafTest>(
    ctx: &Ctx,
    rays: &mut [RayRec],
    table: &mut Table,
    ids: &mut [u32],
    node: &Node,
    depth: u32,
    top: Option<&Top>,
) -> bool {
    let n = rays.len();
    let cost = ids.len() / 13 + 1;
    if !reserve(ctx, cost) {
        return false;
    }
    let t0 = ctx.clock();
    let pivot = slot_median(rays);
    let mut h = 0;
    for i in 0..n {
        if (rays[i].index() as u32) < pivot {
            rays.swap(h, i);
            h += 1;
        }
    }
    if h == 0 || h == n {
        release(ctx, cost);
        return false;
    }
    let (r1, r2) = rays.split_at_mut(h);
    rebase(r2, pivot.wrapping_neg());
    let mut ids2 = ids.to_vec();
    let (hits1, hits2) = table.hits.split_at_mut(pivot as usize);
    let (tmin1, tmin2) = if table.tmin.is_empty() {
        (table.tmin, table.tmin)
    } else {
        table.tmin.split_at(pivot as usize)
    };
    if let Some(s) = ctx.stats {
        lap(&s.merge_ns, t0);
    }
    let (_, migrated) = join_tracked(
        ctx,
        || {
            let mut t = Table {
                hits: hits1,
                tmin: tmin1,
            };
            step::<T>(ctx, r1, &mut t, ids, node, depth, top);
        },
        |migrated| {
            let mut t = Table {
                hits: hits2,
                tmin: tmin2,
            };
            step::<T>(ctx, &mut *r2, &mut t, &mut ids2, node, depth, top);
            migrated
        },
    );
    rebase(r2, pivot);
    Stats::fork(ctx.stats, migrated);
    release(ctx, cost);
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn par_partition_brings_selected_to_front() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap();
        for n in [0usize, 5, 64, 1000, 40_000] {
            for pattern in 0..4 {
                let mut v: Vec<u32> = (0..n as u32).collect();
                let sel = |x: u32| match pattern {
                    0 => x.is_multiple_of(3),
                    1 => x < n as u32 / 2,
                    2 => x >= n as u32 / 3,
                    _ => (x / 100) % 2 == 1,
                };
                let (m, count) = pool.install(|| {
                    par_partition(
                        &mut v,
                        16,
                        |c| {
                            let mut w = 0;
                            for i in 0..c.len() {
                                if sel(c[i]) {
                                    c.swap(w, i);
                                    w += 1;
                                }
                            }
                            (w, w)
                        },
                        |a, b| a + b,
                    )
                });
                assert_eq!(m, count);
                assert_eq!(m, (0..n as u32).filter(|&x| sel(x)).count());
                assert!(v[..m].iter().all(|&x| sel(x)), "{n} {pattern}");
                assert!(v[m..].iter().all(|&x| !sel(x)));
                let mut s = v.clone();
                s.sort();
                assert!(s.iter().enumerate().all(|(i, &x)| i as u32 == x));
            }
        }
    }

    #[test]
    fn parallel_partition_matches_sequential_counts() {
        let boxes: Vec<TriBox> = (0..100_000)
            .map(|i| {
                let x = ((i * 7919) % 1000) as f32;
                TriBox {
                    min: [x, 0.0, 0.0, 0.0],
                    max: [x + 1.0, 1.0, 1.0, 0.0],
                }
            })
            .collect();
        let mut ids: Vec<u32> = (0..boxes.len() as u32).collect();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let (mid, l, r) =
            pool.install(|| partition_par(&boxes, &mut ids, &|b: &TriBox| b.min[0] < 500.0, 1000));
        assert_eq!(mid, 50_000);
        assert!(ids[..mid].iter().all(|&i| boxes[i as usize].min[0] < 500.0));
        assert!(ids[mid..]
            .iter()
            .all(|&i| boxes[i as usize].min[0] >= 500.0));
        assert_eq!(l.node().bounds.max[0], 500.0);
        assert_eq!(r.node().bounds.min[0], 500.0);
        let mut sorted = ids.clone();
        sorted.sort();
        assert!(sorted.iter().enumerate().all(|(i, &x)| i as u32 == x));
    }
}
