//! Watertight ray/triangle intersection (Woop, Benthin & Wald, JCGT 2013).
//!
//! The vertices are translated to the ray origin and sheared so that the ray becomes the +z
//! axis; the 2D edge functions U, V, W of the projected triangle then decide the hit. A
//! shared edge gives exactly opposite edge functions in its two triangles (same vertices,
//! same per-ray transform, `a·b - c·d` antisymmetric in IEEE arithmetic), so a ray can never
//! pass between them; an edge function that is exactly 0 is recomputed in f64 (products of
//! f32 are exact there) so that the sign on an edge is consistent too.
//!
//! The paper's t, `(U·z0 + V·z1 + W·z2) / (U + V + W)`, sums sheared vertex depths whose
//! size is the triangle's extent along the ray, not the hit's distance: a 1000-unit
//! triangle hit at t ≈ 0.07 loses about 12 bits to cancellation (3e-4 relative was
//! measured). That t stays what every core decides and orders with (the interval test,
//! `(t, id)` order), because it is cheap and the cores agree on it bit for bit; only the
//! *reported* t of the hit a query returns is recomputed, once per ray, by [`refined_t`]
//! (the plane's distance from the ray origin in f64). u and v stay `V / det`, `W / det`:
//! their error is absolute, about Möller–Trumbore's (proto/semantics.md gives the bounds).

use super::{PreparedRay, PreparedRay8, Tri8, TriHit, TriTest};
use crate::accel::Precision;
use crate::geometry::{Ray, Triangle};
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

/// The t a query reports for a watertight hit of `ray` on the triangle `p` (its three
/// vertices as stored) whose test gave `t`: the parameter where the ray's line meets the
/// triangle's plane, `n·(v0 - o) / n·d` with `n = (v1 - v0) × (v2 - v0)`, evaluated in f64
/// from the f32 inputs and rounded once to f32.
///
/// Why this form: the differences of f32 values are exact in f64 and their products
/// nearly so, so the result is within about one f32 rounding of the exact t unless the
/// ray grazes the plane or the triangle is a sliver, however large the triangle is
/// relative to the hit's distance (proto/semantics.md has the bound).
///
/// The hit itself was decided on `t` (in `[tmin, tmax]`, edges watertight), so the
/// refined value is clamped into the ray's `[tmin, tmax]` (a hit is never moved out of
/// its interval; the clamp moves t by at most the error of `t` itself), and `t` is kept
/// where the f64 quotient is not finite (the ray parallel to the plane in f64 although not
/// in f32). `-0` becomes `+0`. Every core calls this one function on the same inputs for
/// the hit it reports, after choosing it by `t`, so the reported records stay bit-identical
/// across cores.
#[inline]
pub fn refined_t(ray: &Ray, p: &[[f32; 3]; 3], t: f32) -> f32 {
    let f = |a: [f32; 3]| [f64::from(a[0]), f64::from(a[1]), f64::from(a[2])];
    let (o, d) = (f(ray.org), f(ray.dir));
    let (v0, v1, v2) = (f(p[0]), f(p[1]), f(p[2]));
    let e1 = [v1[0] - v0[0], v1[1] - v0[1], v1[2] - v0[2]];
    let e2 = [v2[0] - v0[0], v2[1] - v0[1], v2[2] - v0[2]];
    let w = [v0[0] - o[0], v0[1] - o[1], v0[2] - o[2]];
    let n = [
        e1[1] * e2[2] - e1[2] * e2[1],
        e1[2] * e2[0] - e1[0] * e2[2],
        e1[0] * e2[1] - e1[1] * e2[0],
    ];
    let num = n[0] * w[0] + n[1] * w[1] + n[2] * w[2];
    let den = n[0] * d[0] + n[1] * d[1] + n[2] * d[2];
    let x = (num / den) as f32;
    // Comparisons, not f32::max/min (whose choice between +0 and -0 is unspecified).
    let x = if !x.is_finite() {
        t
    } else if x < ray.tmin {
        ray.tmin
    } else if x > ray.tmax {
        ray.tmax
    } else {
        x
    };
    x + 0.0
}

/// The decision t of a hit of the ray `(org, dir)` on the triangle `p` whose paper t is
/// `t`: `t` itself, unless the ray's line meets the triangle's bounding box only after `t`
/// (on some axis, `org + t·dir` lies before the box's near plane), and then the parameter
/// where the line enters the box, rounded down to f32.
///
/// Why: the traversals skip a box whose entry distance lies beyond the best decision t so
/// far, which is exact only if no triangle's decision t lies before its own box. For a fat
/// triangle the paper's t errs by far less than the boxes' conservative growth (see
/// `accel::mbvh::ray`), but a sliver's t is cancellation noise of the size of its extent
/// along the ray, and can fall before its box: two exact copies of a sliver then got the
/// same t, one was found first, and the other's box, entered after that t, was skipped, so
/// the higher id won. Raised to the box, such a t can no longer end the search early, and
/// brute force, which decides with the same function, agrees bit for bit.
///
/// The check is exact and cheap (an f32 product is exact in f64, the difference of two f32
/// nearly always is); the division runs only for such slivers, never for a fat triangle.
/// Axes with a zero direction component give no entry. A NaN `t` is returned as it is.
#[inline]
pub fn lift_t(org: [f32; 3], dir: [f32; 3], p: &[[f32; 3]; 3], t: f32) -> f32 {
    let tt = f64::from(t);
    let mut entry = f64::NEG_INFINITY;
    for k in 0..3 {
        let d = f64::from(dir[k]);
        let near = if d > 0.0 {
            min_x86(min_x86(p[0][k], p[1][k]), p[2][k])
        } else if d < 0.0 {
            max_x86(max_x86(p[0][k], p[1][k]), p[2][k])
        } else {
            continue;
        };
        let gap = f64::from(near) - f64::from(org[k]);
        // Short of the near plane: `t·d` has not yet covered the gap, on the ray's side.
        if (d > 0.0 && tt * d < gap) || (d < 0.0 && tt * d > gap) {
            entry = entry.max(gap / d);
        }
    }
    if entry > tt {
        let e = entry as f32;
        if f64::from(e) > entry {
            e.next_down()
        } else {
            e
        }
    } else {
        t
    }
}

/// [`lift_t`] on the lanes of an 8-wide test's `hit` mask, lane `l` being the ray `ray(l)`
/// (origin, direction) on the triangle `p(l)`: the new mask and t. A lifted lane stays a
/// hit only while its t is within `tmax`. Shared by the layer's 8-triangle test and DACRT's
/// 8-ray leaf test, so that both decide exactly as the scalar test does.
#[inline(always)]
pub fn lift_hits<S: Simd>(
    s: S,
    hit: S::M8,
    t: S::F8,
    tmax: S::F8,
    ray: impl Fn(usize) -> ([f32; 3], [f32; 3]),
    p: impl Fn(usize) -> [[f32; 3]; 3],
) -> (S::M8, S::F8) {
    let mut rest = hit.bitmask();
    if rest == 0 {
        return (hit, t);
    }
    let mut ts = t.to_array();
    let mut lifted = false;
    while rest != 0 {
        let l = rest.trailing_zeros() as usize;
        rest &= rest - 1;
        let (org, dir) = ray(l);
        let x = lift_t(org, dir, &p(l), ts[l]);
        if x.to_bits() != ts[l].to_bits() {
            ts[l] = x;
            lifted = true;
        }
    }
    if !lifted {
        return (hit, t);
    }
    let t = s.load_f8(&ts);
    (hit & t.le(tmax), t)
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

    #[inline(always)]
    fn finish_t(ray: &Ray, p: &[[f32; 3]; 3], t: f32) -> f32 {
        refined_t(ray, p, t)
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
            let t = lift_t(r.org, r.dir, p, t);
            if t > tmax {
                return None;
            }
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
        // The decision t of every hit lane (`lift_t`): unchanged but for slivers.
        let (hit, t) = lift_hits(s, hit, t, tmax, |_| (r.ray[0], r.ray[1]), |l| tri.lane(l));
        // The scalar test's u, v: the edge functions of v1 and v2 over the determinant.
        (hit, t, v * rcp, w * rcp)
    }
}
