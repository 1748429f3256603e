//! Single-ray ordered MBVH traversal (Áfra 2013 §4.1), generic over the node width, the
//! triangle test and the SIMD backend.
//!
//! A ray is tested against all N child boxes of a node at once; the hit children are
//! handled by the number of hits: 1 → continue with it; 2 → push the farther, continue
//! with the nearer; 3 and 4 → push all, sort the top of the stack with a sorting network,
//! pop the nearest; 5–N → push all, insertion sort, pop. Stack entries carry their entry
//! distance, and a popped entry farther than the closest hit so far is skipped.
//!
//! Ties (contract: equal t → lowest id): leaves are tested with `tmax = best t` (closed,
//! so equal-t lanes come back) and a lane wins on `(t, id) < (best t, best id)`; boxes are
//! pruned only when their entry distance is *strictly* beyond the best t (`tn <= tfar` in
//! the slab test, `dist > best` to skip on pop), so an equal-t triangle with a lower id in
//! a later leaf is still found. With the conservative slab test of [`super::ray`] this
//! makes the closest hit bit-identical to `brute`'s.
//!
//! `any` pushes the hit children unsorted and stops at the first triangle hit.
//!
//! Prefetching: when a node pushes children, the node or first leaf pack of the entry that
//! will be popped next (the farther of two hits, else the second nearest after the sort)
//! is prefetched, every line of it, so that its memory latency overlaps the descent into
//! the nearest child. Diffuse rays are memory-latency bound: on MetalRoughSpheres (1M
//! triangles, a 92 MB tree) this took `mbvh8` diffuse2 from 0.73× to 0.86× Embree, and it
//! helped on the 100k-triangle scenes too (lucy 1.09× → 1.20×, saw 1.16× → 1.25×),
//! primary rays unchanged within noise (2-core Zen 3, loaded; same-process alternating
//! passes). Prefetching *every* pushed child was second best (0.85× on MetalRoughSpheres)
//! and had measured 4–12% slower than no prefetching on dragon and the engine in an
//! earlier session; also prefetching the new stack top on every pop added nothing.
//!
//! Rejected: interleaving two or three rays per chunk (advancing each by one node or leaf
//! in turn), to overlap their misses: 10–20% slower, the state juggling costing more than
//! the overlap gained.
//!
//! Rejected (BENCHMARKS.md §20): pushing the hit children in a per-node, per-octant order
//! precomputed from the children's entry corners (Fuetterling et al. 2017; tinybvh's
//! `BVH8_CPU` does it with a permutation; ours was a branch-free scalar loop over the
//! order), instead of sorting by the ray's entry distances:
//! 14% more instructions and 10% more mispredicted branches per ray on nefertiti's primary
//! rays (callgrind; the loop walks all N lanes, and whether the approximate order also
//! visits more nodes was not counted); its Mray/s moved −8% to +8% by scene, within the
//! noise, when done from 2 or from 3 hits.

use super::layout::{leaf_lanes, Pack, TravNode, TravTree};
use super::ray::SlabConsts;
use super::slab::{Lanes, SlabTest};
use super::stack::{self, sort_top, sort_top3, sort_top4, Stack};
use crate::accel::triangle::{PreparedRay, PreparedRay8, TriTest};
use crate::geometry::{Hit, Ray};
use crate::simd::{self, FloatV, MaskV, Simd};

/// Index of the lowest set bit of a non-zero mask, and the mask without it (Áfra's
/// BSF + BTC).
#[inline(always)]
fn next_bit(mask: &mut u32) -> usize {
    let i = mask.trailing_zeros() as usize;
    *mask &= mask.wrapping_sub(1);
    i
}

/// Prefetches what child `id` points at: a node, or a leaf's first pack.
#[inline(always)]
fn prefetch_child<const N: usize, T>(nodes: &[TravNode<N>], packs: &[Pack<T>], id: i32) {
    if id >= 0 {
        let p = nodes.as_ptr().wrapping_add(id as usize);
        simd::prefetch(p.cast(), std::mem::size_of::<TravNode<N>>());
    } else {
        let p = packs.as_ptr().wrapping_add(leaf_lanes(id).0 >> 3);
        simd::prefetch(p.cast(), std::mem::size_of::<Pack<T>>());
    }
}

/// The first pack of leaf `id`, the mask of the leaf's lanes in it, and how many of its
/// triangles are left for the next pack (a leaf of up to 8 triangles lies in one pack; a
/// larger one starts a pack and ends in the next).
#[inline(always)]
fn leaf_head(id: i32) -> (usize, u32, usize) {
    let (start, n) = leaf_lanes(id);
    let lane = start & 7;
    let first = n.min(8 - lane);
    (start >> 3, ((1u32 << first) - 1) << lane, n - first)
}

/// What a traversal counts: nothing (`()`, compiled away) or [`Counts`].
pub trait Counter {
    /// A multi-node's boxes were tested.
    fn node(&mut self);
    /// A pack of 8 triangle lanes was tested.
    fn pack(&mut self);
}

impl Counter for () {
    #[inline(always)]
    fn node(&mut self) {}
    #[inline(always)]
    fn pack(&mut self) {}
}

/// Traversal steps and triangle tests (Áfra 2013, Table 4), summed over rays.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Counts {
    /// Multi-nodes visited (box tests of N children at once).
    pub nodes: u64,
    /// Packs of 8 triangle lanes tested.
    pub packs: u64,
}

impl Counter for Counts {
    #[inline(always)]
    fn node(&mut self) {
        self.nodes += 1;
    }
    #[inline(always)]
    fn pack(&mut self) {
        self.packs += 1;
    }
}

/// The closest hit of `ray` (contract §2).
#[inline(always)]
pub fn closest<S: Simd, T: TriTest, const N: usize>(
    s: S,
    tree: &TravTree<N, T>,
    ray: &Ray,
    stack: &mut Stack,
) -> Hit
where
    Lanes<N>: SlabTest<N>,
{
    closest_counted(s, tree, ray, stack, &mut ())
}

/// [`closest`], counting its steps into `counts`.
#[inline(always)]
pub fn closest_counted<S: Simd, T: TriTest, const N: usize, C: Counter>(
    s: S,
    tree: &TravTree<N, T>,
    ray: &Ray,
    stack: &mut Stack,
    counts: &mut C,
) -> Hit
where
    Lanes<N>: SlabTest<N>,
{
    let r = PreparedRay::new(ray);
    if r.is_empty() {
        return Hit::MISS;
    }
    let br = SlabConsts::new(s, &r, tree.scale);
    let vr = <Lanes<N> as SlabTest<N>>::ray(s, &br);
    let r8 = PreparedRay8::new(s, &r);
    let nodes = &tree.nodes[..];
    let packs = &tree.packs[..];
    let mut best_t = br.tmax;
    // The bound boxes are tested against, in the box test's units (`SlabConsts::box_t`).
    let mut best_box = br.box_t(best_t);
    let mut best_id = u32::MAX;
    let (mut best_u, mut best_v) = (0.0f32, 0.0f32);
    // The winner's pack and lane, for its reported t (`TriTest::finish_t`).
    let (mut best_p, mut best_lane) = (0usize, 0usize);
    let mut tmax8 = s.splat_f8(best_t);
    let mut sp = 0usize;
    let mut cur: i32 = 0;
    'trav: loop {
        if cur >= 0 {
            let node = &nodes[cur as usize];
            counts.node();
            let (mut mask, dist) = <Lanes<N> as SlabTest<N>>::test(s, &vr, node, best_box);
            if mask != 0 {
                let child = |i: usize| node.child[i & (N - 1)];
                let key = |i: usize| stack::key(dist[i & 7], child(i));
                // 1 hit: continue with it.
                let i0 = next_bit(&mut mask);
                if mask == 0 {
                    cur = child(i0);
                    continue;
                }
                // 2 hits: push the farther one.
                let i1 = next_bit(&mut mask);
                let (k0, k1) = (key(i0), key(i1));
                if mask == 0 {
                    let far = k0.max(k1);
                    prefetch_child(nodes, packs, stack::id(far));
                    stack[sp] = far;
                    sp += 1;
                    cur = stack::id(k0.min(k1));
                    continue;
                }
                // 3 hits: push all three, sort.
                let i2 = next_bit(&mut mask);
                stack[sp] = k0;
                stack[sp + 1] = k1;
                stack[sp + 2] = key(i2);
                sp += 3;
                if mask == 0 {
                    sort_top3(&mut stack[sp - 3..sp]);
                } else {
                    // 4 hits.
                    let i3 = next_bit(&mut mask);
                    stack[sp] = key(i3);
                    sp += 1;
                    if mask == 0 {
                        sort_top4(&mut stack[sp - 4..sp]);
                    } else {
                        // 5–N hits.
                        let base = sp - 4;
                        while mask != 0 {
                            let i = next_bit(&mut mask);
                            stack[sp] = key(i);
                            sp += 1;
                        }
                        sort_top(&mut stack[base..sp]);
                    }
                }
                sp -= 1;
                cur = stack::id(stack[sp]);
                // The next entry to pop (at least two were pushed).
                prefetch_child(nodes, packs, stack::id(stack[sp - 1]));
                continue;
            }
        } else {
            let (mut p, mut lanes, mut rest) = leaf_head(cur);
            loop {
                let Pack(pack) = &packs[p];
                counts.pack();
                let (m, t, u, v) = T::intersect8_uv(s, &r8, pack, tmax8);
                let mut bits = m.bitmask() & lanes;
                if bits == 0 {
                    if rest == 0 {
                        break;
                    }
                    (p, lanes, rest) = (p + 1, (1 << rest) - 1, 0);
                    continue;
                }
                let ts = t.to_array();
                let mut win = None;
                while bits != 0 {
                    let lane = next_bit(&mut bits) & 7;
                    let (t, id) = (ts[lane], pack.ids[lane]);
                    // `t <= best_t` held when the pack was tested, but an earlier lane of
                    // this pack may have lowered best_t since.
                    if t < best_t || (t == best_t && id < best_id) {
                        best_t = t;
                        best_id = id;
                        win = Some(lane);
                    }
                }
                if let Some(lane) = win {
                    (best_u, best_v) = (u.to_array()[lane], v.to_array()[lane]);
                    (best_p, best_lane) = (p, lane);
                }
                tmax8 = s.splat_f8(best_t);
                best_box = br.box_t(best_t);
                if rest == 0 {
                    break;
                }
                (p, lanes, rest) = (p + 1, (1 << rest) - 1, 0);
            }
        }
        // Pop the nearest entry that is not beyond the closest hit.
        let limit = best_box.to_bits();
        loop {
            if sp == 0 {
                break 'trav;
            }
            sp -= 1;
            let k = stack[sp];
            if stack::dist_bits(k) <= limit {
                cur = stack::id(k);
                break;
            }
        }
    }
    if best_id == u32::MAX {
        return Hit::MISS;
    }
    let Pack(pack) = &packs[best_p];
    Hit {
        t: T::finish_t(ray, &pack.lane(best_lane), best_t),
        prim: best_id,
        u: best_u,
        v: best_v,
    }
}

/// Some hit of `ray` in its interval: the first one found, with the test's t, and the
/// lane data of its triangle (for [`TriTest::finish_t`], which the `any` query applies
/// and an occlusion query, which needs no t, does not).
#[inline(always)]
pub fn any<S: Simd, T: TriTest, const N: usize>(
    s: S,
    tree: &TravTree<N, T>,
    ray: &Ray,
    stack: &mut Stack,
) -> Option<(Hit, [[f32; 3]; 3])>
where
    Lanes<N>: SlabTest<N>,
{
    let r = PreparedRay::new(ray);
    if r.is_empty() {
        return None;
    }
    let br = SlabConsts::new(s, &r, tree.scale);
    let vr = <Lanes<N> as SlabTest<N>>::ray(s, &br);
    let r8 = PreparedRay8::new(s, &r);
    let nodes = &tree.nodes[..];
    let packs = &tree.packs[..];
    let tmax = br.tmax;
    let tmax_box = br.box_t(tmax);
    let tmax8 = s.splat_f8(tmax);
    let mut sp = 0usize;
    let mut cur: i32 = 0;
    loop {
        if cur >= 0 {
            let node = &nodes[cur as usize];
            let (mut mask, _) = <Lanes<N> as SlabTest<N>>::test(s, &vr, node, tmax_box);
            if mask != 0 {
                cur = node.child[next_bit(&mut mask) & (N - 1)];
                while mask != 0 {
                    stack[sp] = stack::key(0.0, node.child[next_bit(&mut mask) & (N - 1)]);
                    sp += 1;
                }
                continue;
            }
        } else {
            let (mut p, mut lanes, mut rest) = leaf_head(cur);
            loop {
                let Pack(pack) = &packs[p];
                let (m, t, u, v) = T::intersect8_uv(s, &r8, pack, tmax8);
                let bits = m.bitmask() & lanes;
                if bits != 0 {
                    let lane = bits.trailing_zeros() as usize & 7;
                    let hit = Hit {
                        t: t.to_array()[lane],
                        prim: pack.ids[lane],
                        u: u.to_array()[lane],
                        v: v.to_array()[lane],
                    };
                    return Some((hit, pack.lane(lane)));
                }
                if rest == 0 {
                    break;
                }
                (p, lanes, rest) = (p + 1, (1 << rest) - 1, 0);
            }
        }
        if sp == 0 {
            return None;
        }
        sp -= 1;
        cur = stack::id(stack[sp]);
    }
}
