//! Watertight ray/triangle intersection (Woop, Benthin & Wald, JCGT 2013).
//!
//! The vertices are translated to the ray origin and sheared so that the ray becomes the +z
//! axis; the 2D edge functions U, V, W of the projected triangle then decide the hit. A
//! shared edge gives exactly opposite edge functions in its two triangles (same vertices,
//! same per-ray transform, `a·b - c·d` antisymmetric in IEEE arithmetic), so a ray can never
//! pass between them; an edge function that is exactly 0 is recomputed in f64 (products of
//! f32 are exact there) so that the sign on an edge is consistent too.

use super::{PreparedRay, PreparedRay8, Tri8, TriHit, TriTest};
use crate::accel::Precision;
use crate::geometry::Triangle;
use crate::simd::scalar::{max_x86, min_x86};
use crate::simd::{FloatV, MaskV, Simd};

/// The watertight test (`precision=watertight`, the default).
#[derive(Clone, Copy, Debug, Default)]
pub struct Watertight;

/// U, V, W from the projected vertices in f64, rounded back to f32 (the paper's fallback).
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

/// The f64 fallback for the lanes of `zero`, on arrays (cold; kept out of the kernel so the
/// hot path stays small).
#[cold]
#[inline(never)]
fn fallback8(zero: u32, xy: [[f32; 8]; 6], uvw: &mut [[f32; 8]; 3]) {
    for lane in 0..8 {
        if zero >> lane & 1 == 1 {
            let (u, v, w) = edges_f64(
                xy[0][lane],
                xy[1][lane],
                xy[2][lane],
                xy[3][lane],
                xy[4][lane],
                xy[5][lane],
            );
            uvw[0][lane] = u;
            uvw[1][lane] = v;
            uvw[2][lane] = w;
        }
    }
}

impl TriTest for Watertight {
    const PRECISION: Precision = Precision::Watertight;

    #[inline]
    fn lane_data(tri: &Triangle) -> [[f32; 3]; 3] {
        tri.v
    }

    #[inline]
    fn intersect_lane(r: &PreparedRay, p: &[[f32; 3]; 3], tmax: f32) -> Option<TriHit> {
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
        // All >= 0 or all <= 0 (zeros count both ways): as min/max with the x86 rules, the
        // form the 8-wide test uses (4 fewer vector operations than six compares).
        let inside = min_x86(min_x86(u, v), w) >= 0.0 || max_x86(max_x86(u, v), w) <= 0.0;
        if !inside {
            return None;
        }
        let det = u + v + w;
        let tt = u * (sz * a_z) + v * (sz * b_z) + w * (sz * c_z);
        let rcp = 1.0 / det;
        let t = tt * rcp;
        if det != 0.0 && t >= r.tmin && t <= tmax {
            Some(TriHit {
                t,
                u: v * rcp,
                v: w * rcp,
            })
        } else {
            None
        }
    }

    #[inline(always)]
    fn intersect8<S: Simd>(
        s: S,
        r: &PreparedRay8<S>,
        tri: &Tri8<Self>,
        tmax: S::F8,
    ) -> (S::M8, S::F8) {
        let (hit, t, _, _) = Self::intersect8_uv(s, r, tri, tmax);
        (hit, t)
    }

    #[inline(always)]
    fn intersect8_uv<S: Simd>(
        s: S,
        r: &PreparedRay8<S>,
        tri: &Tri8<Self>,
        tmax: S::F8,
    ) -> (S::M8, S::F8, S::F8, S::F8) {
        let [kx, ky, kz] = r.k;
        let [sx, sy, sz] = r.shear;
        let [ox, oy, oz] = r.org_k;
        let ld = |i: usize, k: usize| s.load_f8(&tri.p[i][k]);
        let (a_z, b_z, c_z) = (ld(0, kz) - oz, ld(1, kz) - oz, ld(2, kz) - oz);
        let ax = (ld(0, kx) - ox) - sx * a_z;
        let ay = (ld(0, ky) - oy) - sy * a_z;
        let bx = (ld(1, kx) - ox) - sx * b_z;
        let by = (ld(1, ky) - oy) - sy * b_z;
        let cx = (ld(2, kx) - ox) - sx * c_z;
        let cy = (ld(2, ky) - oy) - sy * c_z;
        let mut u = cx * by - cy * bx;
        let mut v = ax * cy - ay * cx;
        let mut w = bx * ay - by * ax;
        let zero = s.splat_f8(0.0);
        let z = u.eq(zero) | v.eq(zero) | w.eq(zero);
        if z.any() {
            let mut uvw = [u.to_array(), v.to_array(), w.to_array()];
            let xy = [
                ax.to_array(),
                ay.to_array(),
                bx.to_array(),
                by.to_array(),
                cx.to_array(),
                cy.to_array(),
            ];
            fallback8(z.bitmask(), xy, &mut uvw);
            u = s.load_f8(&uvw[0]);
            v = s.load_f8(&uvw[1]);
            w = s.load_f8(&uvw[2]);
        }
        let inside = u.min(v).min(w).ge(zero) | u.max(v).max(w).le(zero);
        if inside.none() {
            return (inside, zero, zero, zero);
        }
        let det = u + v + w;
        let tt = u * (sz * a_z) + v * (sz * b_z) + w * (sz * c_z);
        let rcp = s.splat_f8(1.0) / det;
        let t = tt * rcp;
        let hit = inside & det.ne(zero) & t.ge(r.tmin) & t.le(tmax);
        // The scalar test's u, v: the edge functions of v1 and v2 over the determinant.
        (hit, t, v * rcp, w * rcp)
    }
}
