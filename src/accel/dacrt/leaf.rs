//! Leaf intersection (Áfra 2012 §3.3): the active rays of a leaf against its few triangles,
//! triangles rebuilt once from the precompute and held while the rays stream past them.
//!
//! A leaf's best hits are kept per ray in registers while its triangles are tested, then
//! written once per ray: `tmax` into the record (so the next box tests cull with it) and
//! `(t, prim)` into the ray's hit slot, which decides ties by the lowest id exactly as
//! `brute` does (a triangle at the same `t` as the slot's but with a lower id replaces it).
//!
//! The arithmetic of both tests is the SIMD layer's scalar reference, operation for
//! operation, so `t` is bit-identical to what `brute` computes for the same pair.

use crate::accel::Precision;
use crate::geometry::{Hit, Ray};

use super::rays::{RayRec, TMIN_FLAG};
use super::tris::{decode, TriData};

/// No candidate yet (any real triangle id is lower).
const NONE: u32 = u32::MAX;

/// A ray/triangle test in the form the leaves use.
pub trait LeafTest: Copy + Send + Sync + 'static {
    /// The contract's precision.
    const PRECISION: Precision;
    /// Per-ray constants.
    type Prep: Copy;
    /// What is stored per triangle, from its vertices.
    fn tri_data(v: [[f32; 3]; 3]) -> [[f32; 3]; 3];
    /// Per-ray constants of a record.
    fn prep(org: [f32; 3], dir: [f32; 3]) -> Self::Prep;
    /// `t` of a hit in `[tmin, tmax]`, else `None`.
    fn hit(r: &Self::Prep, p: &[[f32; 3]; 3], tmin: f32, tmax: f32) -> Option<f32>;
    /// The full hit (`t, u, v`) of `ray` on the triangle with vertices `v`, by the same
    /// arithmetic as [`LeafTest::hit`].
    fn full(ray: &Ray, v: [[f32; 3]; 3]) -> Option<(f32, f32, f32)>;
}

/// Per-ray constants of the watertight test. The axis order is `kz` = the largest |dir|
/// component and `kx, ky` its cyclic successors, *without* the sign swap of Woop et al.:
/// swapping `kx` and `ky` negates U, V, W, det and T exactly in IEEE arithmetic, so `t`, `u`
/// and `v` are the same bits either way, and leaving it out keeps the per-lane axis choice to
/// a rotation.
#[derive(Clone, Copy, Debug)]
pub struct WtPrep {
    org: [f32; 3],
    k: [usize; 3],
    shear: [f32; 3],
}

/// U, V, W in f64, rounded to f32: the fallback when one comes out exactly 0 in f32.
#[inline(always)]
fn edges_f64(ax: f32, ay: f32, bx: f32, by: f32, cx: f32, cy: f32) -> (f32, f32, f32) {
    let (ax, ay, bx, by, cx, cy) = (
        f64::from(ax),
        f64::from(ay),
        f64::from(bx),
        f64::from(by),
        f64::from(cx),
        f64::from(cy),
    );
    (
        (cx * by - cy * bx) as f32,
        (ax * cy - ay * cx) as f32,
        (bx * ay - by * ax) as f32,
    )
}

/// Woop, Benthin & Wald 2013 (`precision=watertight`).
#[derive(Clone, Copy, Debug, Default)]
pub struct Watertight;

impl Watertight {
    #[inline(always)]
    fn core(r: &WtPrep, p: &[[f32; 3]; 3], tmin: f32, tmax: f32) -> Option<(f32, f32, f32)> {
        let [kx, ky, kz] = r.k;
        let [sx, sy, sz] = r.shear;
        let rel = |i: usize, k: usize| p[i][k] - r.org[k];
        let (a_z, b_z, c_z) = (rel(0, kz), rel(1, kz), rel(2, kz));
        let ax = rel(0, kx) - sx * a_z;
        let ay = rel(0, ky) - sy * a_z;
        let bx = rel(1, kx) - sx * b_z;
        let by = rel(1, ky) - sy * b_z;
        let cx = rel(2, kx) - sx * c_z;
        let cy = rel(2, ky) - sy * c_z;
        let mut u = cx * by - cy * bx;
        let mut v = ax * cy - ay * cx;
        let mut w = bx * ay - by * ax;
        if u == 0.0 || v == 0.0 || w == 0.0 {
            (u, v, w) = edges_f64(ax, ay, bx, by, cx, cy);
        }
        let inside = (u >= 0.0 && v >= 0.0 && w >= 0.0) || (u <= 0.0 && v <= 0.0 && w <= 0.0);
        if !inside {
            return None;
        }
        let det = u + v + w;
        let tt = u * (sz * a_z) + v * (sz * b_z) + w * (sz * c_z);
        let rcp = 1.0 / det;
        let t = tt * rcp;
        (det != 0.0 && t >= tmin && t <= tmax).then_some((t, v * rcp, w * rcp))
    }
}

impl LeafTest for Watertight {
    const PRECISION: Precision = Precision::Watertight;
    type Prep = WtPrep;

    #[inline(always)]
    fn tri_data(v: [[f32; 3]; 3]) -> [[f32; 3]; 3] {
        v
    }

    #[inline(always)]
    fn prep(org: [f32; 3], d: [f32; 3]) -> WtPrep {
        let a = d.map(f32::abs);
        let kz = if a[0] >= a[1] && a[0] >= a[2] {
            0
        } else if a[1] >= a[2] {
            1
        } else {
            2
        };
        let kx = (kz + 1) % 3;
        let ky = (kx + 1) % 3;
        WtPrep {
            org,
            k: [kx, ky, kz],
            shear: [d[kx] / d[kz], d[ky] / d[kz], 1.0 / d[kz]],
        }
    }

    #[inline(always)]
    fn hit(r: &WtPrep, p: &[[f32; 3]; 3], tmin: f32, tmax: f32) -> Option<f32> {
        Self::core(r, p, tmin, tmax).map(|h| h.0)
    }

    fn full(ray: &Ray, v: [[f32; 3]; 3]) -> Option<(f32, f32, f32)> {
        Self::core(&Self::prep(ray.org, ray.dir), &v, ray.tmin, ray.tmax)
    }
}

/// Möller–Trumbore without culling (`precision=fast`); edges rounded to f32 once per
/// triangle, as the layer's packed triangles store them.
#[derive(Clone, Copy, Debug, Default)]
pub struct Moller;

impl Moller {
    #[inline(always)]
    fn core(
        org: [f32; 3],
        d: [f32; 3],
        p: &[[f32; 3]; 3],
        tmin: f32,
        tmax: f32,
    ) -> Option<(f32, f32, f32)> {
        let [v0, e1, e2] = *p;
        let px = d[1] * e2[2] - d[2] * e2[1];
        let py = d[2] * e2[0] - d[0] * e2[2];
        let pz = d[0] * e2[1] - d[1] * e2[0];
        let det = e1[0] * px + e1[1] * py + e1[2] * pz;
        let inv = 1.0 / det;
        let s = [org[0] - v0[0], org[1] - v0[1], org[2] - v0[2]];
        let u = (s[0] * px + s[1] * py + s[2] * pz) * inv;
        let qx = s[1] * e1[2] - s[2] * e1[1];
        let qy = s[2] * e1[0] - s[0] * e1[2];
        let qz = s[0] * e1[1] - s[1] * e1[0];
        let v = (d[0] * qx + d[1] * qy + d[2] * qz) * inv;
        let t = (e2[0] * qx + e2[1] * qy + e2[2] * qz) * inv;
        let hit = det != 0.0 && u >= 0.0 && v >= 0.0 && u + v <= 1.0 && t >= tmin && t <= tmax;
        hit.then_some((t, u, v))
    }
}

impl LeafTest for Moller {
    const PRECISION: Precision = Precision::Fast;
    type Prep = ([f32; 3], [f32; 3]);

    #[inline(always)]
    fn tri_data(v: [[f32; 3]; 3]) -> [[f32; 3]; 3] {
        let [v0, v1, v2] = v;
        [
            v0,
            crate::geometry::sub(v1, v0),
            crate::geometry::sub(v2, v0),
        ]
    }

    #[inline(always)]
    fn prep(org: [f32; 3], dir: [f32; 3]) -> Self::Prep {
        (org, dir)
    }

    #[inline(always)]
    fn hit(r: &Self::Prep, p: &[[f32; 3]; 3], tmin: f32, tmax: f32) -> Option<f32> {
        Self::core(r.0, r.1, p, tmin, tmax).map(|h| h.0)
    }

    fn full(ray: &Ray, v: [[f32; 3]; 3]) -> Option<(f32, f32, f32)> {
        Self::core(ray.org, ray.dir, &Self::tri_data(v), ray.tmin, ray.tmax)
    }
}

/// Where a leaf's best hits go.
pub trait Sink {
    /// The `tmin` of the ray with hit slot `index` (stored in the slot's `u` while tracing).
    fn tmin(&self, index: usize) -> f32;
    /// Offers a ray's best hit of this leaf; returns the ray's new `tmax` (closest query).
    fn offer(&mut self, index: usize, t: f32, prim: u32, any: bool) -> f32;
}

/// Merges a candidate `(t, prim)` into a hit slot: the contract's order (smaller `t`, then
/// lower id); with `any`, the first hit stays. Returns the slot's `t` afterwards.
#[inline(always)]
pub fn merge_slot(slot: &mut Hit, t: f32, prim: u32, any: bool) -> f32 {
    let take = if any {
        slot.prim == NONE
    } else {
        t < slot.t || (t == slot.t && prim < slot.prim)
    };
    if take {
        slot.t = t;
        slot.prim = prim;
    }
    slot.t
}

impl Sink for [Hit] {
    #[inline(always)]
    fn tmin(&self, index: usize) -> f32 {
        self[index].u
    }

    #[inline(always)]
    fn offer(&mut self, index: usize, t: f32, prim: u32, any: bool) -> f32 {
        merge_slot(&mut self[index], t, prim, any)
    }
}

/// Triangles rebuilt per block of a leaf.
const BLOCK: usize = 32;

/// Intersects `rays` with the triangles `ids`, updating the records and offering each ray's
/// best hit to `sink`. With `any`, a ray that hits is finished: its `tmax` becomes `-inf`,
/// which no box and no triangle test accepts.
pub fn leaf<T: LeafTest, S: Sink + ?Sized>(
    tris: &TriData,
    rays: &mut [RayRec],
    sink: &mut S,
    ids: &[u32],
    any: bool,
) {
    let mut block = [([[0.0f32; 3]; 3], 0u32); BLOCK];
    for chunk in ids.chunks(BLOCK) {
        for (slot, &id) in block.iter_mut().zip(chunk) {
            let i = id as usize;
            *slot = (T::tri_data(decode(&tris.boxes[i], &tris.extra[i])), id);
        }
        let block = &block[..chunk.len()];
        for group in rays.chunks_mut(8) {
            group8::<T, S>(group, sink, block, any);
        }
    }
}

/// One group of up to 8 rays against a block of triangles.
#[inline(always)]
fn group8<T: LeafTest, S: Sink + ?Sized>(
    group: &mut [RayRec],
    sink: &mut S,
    block: &[([[f32; 3]; 3], u32)],
    any: bool,
) {
    for r in group.iter_mut() {
        if r.tmax == f32::NEG_INFINITY {
            continue;
        }
        let prep = T::prep(r.org, r.dir);
        let tmin = if r.slot & TMIN_FLAG != 0 {
            sink.tmin(r.index())
        } else {
            0.0
        };
        let mut best_t = r.tmax;
        let mut best = NONE;
        for (p, id) in block {
            if let Some(t) = T::hit(&prep, p, tmin, best_t) {
                if t < best_t || *id < best {
                    best_t = t;
                    best = *id;
                    if any {
                        break;
                    }
                }
            }
        }
        if best != NONE {
            let t = sink.offer(r.index(), best_t, best, any);
            r.tmax = if any { f32::NEG_INFINITY } else { t };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sign_swap_free_watertight_matches_its_definition() {
        // A ray along -z (where Woop swaps kx and ky) and one along +z hit the same triangle
        // at the same point with mirrored t; u, v must be those of the hit point.
        let v = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let down = Ray {
            org: [0.25, 0.5, 2.0],
            tmin: 0.0,
            dir: [0.0, 0.0, -1.0],
            tmax: f32::INFINITY,
        };
        let (t, u, w) = Watertight::full(&down, v).unwrap();
        assert_eq!((t, u, w), (2.0, 0.25, 0.5));
        let up = Ray {
            org: [0.25, 0.5, -2.0],
            dir: [0.0, 0.0, 1.0],
            ..down
        };
        assert_eq!(Watertight::full(&up, v), Some((2.0, 0.25, 0.5)));
        assert_eq!(Moller::full(&up, v), Some((2.0, 0.25, 0.5)));
    }
}
