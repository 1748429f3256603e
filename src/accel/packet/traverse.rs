//! Stackless traversal of a skip-pointer BVH by packets of 4 rays (Geimer & Müller §3.3).
//!
//! The 4 rays of a packet are the lanes of 4-wide vectors. Nodes are visited in array
//! (depth-first) order; a node is entered when its box is hit by any active ray within
//! that ray's `[tmin, best t]`, and otherwise skipped with its skip pointer. At a leaf,
//! each ray that hit the leaf's box is tested against the leaf's 8-wide pack with the same
//! test and tie rule as every other core (`tmax = best t`, `(t, id)` order), so the closest
//! hit is bit-identical to `brute`'s. `any` retires a ray at its first hit and stops when
//! none is left.
//!
//! Rays in a packet may point into different octants, so the slab test orders each axis
//! pair with `min`/`max` per lane rather than by a per-ray near-plane choice. The boxes are
//! grown exactly as in the MBVH cores (see `mbvh::ray`); NaN slab distances (0·∞) are
//! ignored by operand order, which only ever enlarges an interval.

use super::layout::PacketTree;
use crate::accel::mbvh::ray::BoxRay;
use crate::accel::triangle::{PreparedRay, PreparedRay8, TriTest};
use crate::accel::Query;
use crate::geometry::{Hit, Ray};
use crate::simd::{FloatV, MaskV, Simd};

/// Rays per packet.
pub const PACKET: usize = 4;

/// Traces one packet of 1 to 4 rays and writes their hits (or, with `occluded`, 0/1 per
/// ray; then `query` is ignored and treated as `any`).
#[inline(always)]
pub fn packet<S: Simd, T: TriTest>(
    s: S,
    tree: &PacketTree<T>,
    rays: &[Ray],
    query: Query,
    hits: Option<&mut [Hit]>,
    occluded: Option<&mut [u8]>,
) {
    debug_assert!(!rays.is_empty() && rays.len() <= PACKET);
    let ray_at = |i: usize| PreparedRay::new(rays.get(i).unwrap_or(&Ray::EMPTY));
    let pr = [ray_at(0), ray_at(1), ray_at(2), ray_at(3)];
    let br = [
        BoxRay::new(&pr[0], tree.scale),
        BoxRay::new(&pr[1], tree.scale),
        BoxRay::new(&pr[2], tree.scale),
        BoxRay::new(&pr[3], tree.scale),
    ];
    let mut active = 0u32;
    for (i, r) in pr.iter().enumerate() {
        if i < rays.len() && !r.is_empty() {
            active |= 1 << i;
        }
    }
    let first_only = occluded.is_some() || query == Query::Any;
    let mut best_t = [br[0].tmax, br[1].tmax, br[2].tmax, br[3].tmax];
    let mut best_id = [u32::MAX; PACKET];
    let mut best_uv = [(0.0f32, 0.0f32); PACKET];
    // Each winner's pack and lane, for its reported t (`TriTest::finish_t`).
    let mut best_at = [(0usize, 0usize); PACKET];
    if active != 0 {
        // Scalar gathers; the vector loads stay in the kernel's own code.
        let col = |f: fn(&BoxRay) -> f32| [f(&br[0]), f(&br[1]), f(&br[2]), f(&br[3])];
        let inv = [
            s.load_f4(&col(|b| b.inv[0])),
            s.load_f4(&col(|b| b.inv[1])),
            s.load_f4(&col(|b| b.inv[2])),
        ];
        let lo = [
            s.load_f4(&col(|b| b.org_lo[0])),
            s.load_f4(&col(|b| b.org_lo[1])),
            s.load_f4(&col(|b| b.org_lo[2])),
        ];
        let hi = [
            s.load_f4(&col(|b| b.org_hi[0])),
            s.load_f4(&col(|b| b.org_hi[1])),
            s.load_f4(&col(|b| b.org_hi[2])),
        ];
        let tmin = s.load_f4(&col(|b| b.tmin));
        let r8 = [
            PreparedRay8::new(s, &pr[0]),
            PreparedRay8::new(s, &pr[1]),
            PreparedRay8::new(s, &pr[2]),
            PreparedRay8::new(s, &pr[3]),
        ];
        // The bounds boxes are tested against, in the box test's units (`BoxRay::box_t`).
        let box_t = |best_t: &[f32; PACKET]| {
            s.load_f4(&[
                br[0].box_t(best_t[0]),
                br[1].box_t(best_t[1]),
                br[2].box_t(best_t[2]),
                br[3].box_t(best_t[3]),
            ])
        };
        let mut tfar = box_t(&best_t);
        let nodes = &tree.nodes[..];
        let packs = &tree.packs[..];
        let mut i = 0usize;
        while let Some(node) = nodes.get(i) {
            let slab = |k: usize| {
                let a = (s.splat_f4(node.min[k]) - lo[k]) * inv[k];
                let b = (s.splat_f4(node.max[k]) - hi[k]) * inv[k];
                (a.min(b), a.max(b))
            };
            let (nx, fx) = slab(0);
            let (ny, fy) = slab(1);
            let (nz, fz) = slab(2);
            let tn = nx.max(ny.max(nz.max(tmin)));
            let tf = fx.min(fy.min(fz.min(tfar)));
            let mut hit = tn.le(tf).bitmask() & active;
            if hit == 0 {
                i = node.skip as usize;
                continue;
            }
            i += 1;
            if node.pack == 0 {
                continue;
            }
            let pack_index = node.pack as usize - 1;
            let pack = &packs[pack_index];
            let mut changed = false;
            while hit != 0 {
                let lane = hit.trailing_zeros() as usize & 3;
                hit &= hit - 1;
                let (m, t, u, v) = T::intersect8_uv(s, &r8[lane], pack, s.splat_f8(best_t[lane]));
                let mut bits = m.bitmask();
                if bits == 0 {
                    continue;
                }
                let ts = t.to_array();
                let mut win = None;
                if first_only {
                    let j = bits.trailing_zeros() as usize & 7;
                    (best_t[lane], best_id[lane]) = (ts[j], pack.ids[j]);
                    win = Some(j);
                    active &= !(1 << lane);
                    bits = 0;
                }
                while bits != 0 {
                    let j = bits.trailing_zeros() as usize & 7;
                    bits &= bits - 1;
                    let (t, id) = (ts[j], pack.ids[j]);
                    if t < best_t[lane] || (t == best_t[lane] && id < best_id[lane]) {
                        best_t[lane] = t;
                        best_id[lane] = id;
                        win = Some(j);
                        changed = true;
                    }
                }
                if let Some(j) = win {
                    best_uv[lane] = (u.to_array()[j], v.to_array()[j]);
                    best_at[lane] = (pack_index, j);
                }
            }
            if active == 0 {
                break;
            }
            if changed {
                tfar = box_t(&best_t);
            }
        }
    }
    if let Some(out) = occluded {
        for (o, &id) in out.iter_mut().zip(&best_id) {
            *o = u8::from(id != u32::MAX);
        }
    } else if let Some(hits) = hits {
        for (i, h) in hits.iter_mut().enumerate() {
            *h = if best_id[i] == u32::MAX {
                Hit::MISS
            } else {
                let (p, j) = best_at[i];
                Hit {
                    t: T::finish_t(&rays[i], &tree.packs[p].lane(j), best_t[i]),
                    prim: best_id[i],
                    u: best_uv[i].0,
                    v: best_uv[i].1,
                }
            };
        }
    }
}
