//! Watertight ray/triangle intersection (Woop, Benthin & Wald, JCGT 2013).
//!
//! The vertices are translated to the ray origin and sheared so that the ray becomes the +z
//! axis; the 2D edge functions U, V, W of the projected triangle then decide the hit. A
//! shared edge gives exactly opposite edge functions in its two triangles (same vertices,
//! same per-ray transform, `a·b - c·d` antisymmetric in IEEE arithmetic), so a ray can never
//! pass between them; an edge function that is exactly 0 is recomputed in f64 (products of
//! f32 are exact there) so that the sign on an edge is consistent too.
//!
//! The edge functions decide *whether* the ray's line crosses the triangle; they are not
//! used for *where*. The paper's t, `(U·z0 + V·z1 + W·z2) / (U + V + W)`, sums sheared
//! vertex depths whose size is the triangle's extent along the ray, not the hit's
//! distance: a 1000-unit triangle hit at t ≈ 0.07 loses about 12 bits to cancellation (a
//! relative error of up to 3e-4 was measured). So the reported t is the plane's distance
//! from the ray origin in f64, `n·(v0 - o) / n·d` ([`plane_t`]), whose error does not grow
//! with the triangle's size. It is computed only where it can matter: a candidate that
//! passes the edge test gets the depth window of its vertices along the ray ([`window8`],
//! three products the paper computes anyway), which always holds the exact t, and only
//! candidates whose window meets `[tmin, tmax]` are refined ([`refined_t`], which also
//! clamps the f64 t into the window, so a window that misses the interval is a miss by
//! construction and a reported t always lies within the triangle's depth range). The
//! interval test and the closest-hit order then use the refined t in
//! every core (the scalar and 8-wide tests here, and the DACRT leaves, all call these
//! functions on the same f32 inputs), so the cores stay bit-identical; the hit/miss
//! decision on the edges is the paper's, unchanged. u and v stay `V / det` and `W / det`:
//! their error is absolute, about that of Möller–Trumbore's (proto/semantics.md gives both
//! bounds).

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

/// The ray parameter where the line `org + t·dir` meets the plane of the triangle `p`,
/// in f64 from the stored f32 values, rounded once to f32.
///
/// The edges and `v0 - org` are differences of f32 values and so exact (or within one f64
/// rounding) in f64, and the cross product's products of f32 differences are nearly
/// exact, so the error is about one f32 rounding of t unless the ray grazes the plane or
/// the triangle is a sliver (proto/semantics.md has the bound). A t that is not finite
/// (the ray is parallel to the plane in f64) comes back as NaN.
#[inline]
pub fn plane_t(org: [f32; 3], dir: [f32; 3], p: &[[f32; 3]; 3]) -> f32 {
    let f = |a: [f32; 3]| [f64::from(a[0]), f64::from(a[1]), f64::from(a[2])];
    plane_t64(f(org), f(dir), p)
}

/// [`plane_t`] with the ray already in f64 (exactly its f32 values).
#[inline(always)]
fn plane_t64(o: [f64; 3], d: [f64; 3], p: &[[f32; 3]; 3]) -> f32 {
    let f = |a: [f32; 3]| [f64::from(a[0]), f64::from(a[1]), f64::from(a[2])];
    let (v0, v1, v2) = (f(p[0]), f(p[1]), f(p[2]));
    let e1 = [v1[0] - v0[0], v1[1] - v0[1], v1[2] - v0[2]];
    let e2 = [v2[0] - v0[0], v2[1] - v0[1], v2[2] - v0[2]];
    let n = [
        e1[1] * e2[2] - e1[2] * e2[1],
        e1[2] * e2[0] - e1[0] * e2[2],
        e1[0] * e2[1] - e1[1] * e2[0],
    ];
    let w = [v0[0] - o[0], v0[1] - o[1], v0[2] - o[2]];
    let num = n[0] * w[0] + n[1] * w[1] + n[2] * w[2];
    let den = n[0] * d[0] + n[1] * d[1] + n[2] * d[2];
    let t = (num / den) as f32;
    if t.is_finite() {
        t
    } else {
        f32::NAN
    }
}

/// The reported watertight t: [`plane_t`] clamped into the depth window `[lo, hi]`
/// ([`window8`]), NaN kept, `-0` made `+0`. The window holds the exact t, so the clamp
/// only ever moves t towards it; it makes "a window outside `[tmin, tmax]` is a miss"
/// true by construction, which is what lets the tests skip refining such candidates
/// without any core answering differently.
///
/// The same function on the same inputs everywhere: every core's closest-hit order and
/// interval test use its result, which keeps them bit-identical.
#[inline]
pub fn refined_t(org: [f32; 3], dir: [f32; 3], p: &[[f32; 3]; 3], lo: f32, hi: f32) -> f32 {
    let f = |a: [f32; 3]| [f64::from(a[0]), f64::from(a[1]), f64::from(a[2])];
    refined_t64(f(org), f(dir), p, lo, hi)
}

/// [`refined_t`] with the ray already in f64 (exactly its f32 values): the same result.
#[inline(always)]
pub fn refined_t64(o: [f64; 3], d: [f64; 3], p: &[[f32; 3]; 3], lo: f32, hi: f32) -> f32 {
    let t = plane_t64(o, d, p);
    // Comparisons, not f32::max/min: their choice between +0 and -0 is unspecified.
    let t = if t < lo {
        lo
    } else if t > hi {
        hi
    } else {
        t
    };
    t + 0.0
}

/// The relative widening of the depth window (2^-21): more than the three roundings of
/// each f32 depth `(1/d_kz)·(p_kz - o_kz)` and the one of the widening itself.
const WIDEN: f32 = 1.0 / 2_097_152.0;

/// The depth window `[lo, hi]` of 8 lanes: the smallest and largest of the sheared vertex
/// depths `z = [z0, z1, z2]` (the t at which the ray reaches each vertex's coordinate on
/// its dominant axis), extended by their spread on each side and widened by 2^-21 of
/// themselves. The spread is for hits that the f32 edge test accepts within its rounding
/// of an edge although the exact line passes just outside: their plane crossing lies just
/// outside the depth range (by a fraction of the range that grows as the view grazes; a
/// tenth was seen), and the clamp must not move it. The exact t of a hit lies between
/// the vertices' depths (the hit point's coordinate lies between theirs), so the window
/// always holds it, whatever the triangle's shape or the ray's angle: a candidate whose
/// window misses `[tmin, tmax]` is a miss without computing its t, and clamping the
/// refined t into the window ([`refined_t`]) changes nothing but ill-conditioned cases.
/// Bit-identical to [`window1`] per lane.
#[inline(always)]
pub fn window8<S: Simd>(s: S, z: [S::F8; 3]) -> (S::F8, S::F8) {
    let [z0, z1, z2] = z;
    let (zl, zh) = (z0.min(z1).min(z2), z0.max(z1).max(z2));
    let k = s.splat_f8(WIDEN);
    let width = zh - zl;
    ((zl - width) - zl.abs() * k, (zh + width) + zh.abs() * k)
}

/// [`window8`] for one lane, with the same operations in the same order (x86 min/max).
#[inline(always)]
pub fn window1(z: [f32; 3]) -> (f32, f32) {
    let [z0, z1, z2] = z;
    let zl = min_x86(min_x86(z0, z1), z2);
    let zh = max_x86(max_x86(z0, z1), z2);
    let width = zh - zl;
    (
        (zl - width) - zl.abs() * WIDEN,
        (zh + width) + zh.abs() * WIDEN,
    )
}

/// [`refined_t`] for the lanes of `bits` of an 8-wide pack (NaN in the others); cold
/// enough (a lane or two per ray) to stay out of line, which keeps the kernels small.
#[inline(never)]
fn refined_t8(
    bits: u32,
    ray: &[[f32; 3]; 2],
    p: &[[[f32; 8]; 3]; 3],
    lo: &[f32; 8],
    hi: &[f32; 8],
) -> [f32; 8] {
    let f = |a: [f32; 3]| [f64::from(a[0]), f64::from(a[1]), f64::from(a[2])];
    let ray = (f(ray[0]), f(ray[1]));
    let mut t = [f32::NAN; 8];
    let mut rest = bits & 0xff;
    while rest != 0 {
        let lane = rest.trailing_zeros() as usize & 7;
        rest &= rest - 1;
        let pt = |i: usize| [p[i][0][lane], p[i][1][lane], p[i][2][lane]];
        t[lane] = refined_t64(ray.0, ray.1, &[pt(0), pt(1), pt(2)], lo[lane], hi[lane]);
    }
    t
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
        if det == 0.0 {
            return None;
        }
        let (lo, hi) = window1([sz * a_z, sz * b_z, sz * c_z]);
        if !(hi >= r.tmin && lo <= tmax) {
            return None;
        }
        let t = refined_t(r.org, r.dir, p, lo, hi);
        let rcp = 1.0 / det;
        if t >= r.tmin && t <= tmax {
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
        let (lo, hi) = window8(s, [sz * a_z, sz * b_z, sz * c_z]);
        let cand = inside & det.ne(zero) & hi.ge(r.tmin) & lo.le(tmax);
        let bits = cand.bitmask();
        if bits == 0 {
            return (cand, zero, zero, zero);
        }
        let t = refined_t8(bits, &r.ray1, &tri.p, &lo.to_array(), &hi.to_array());
        let t = s.load_f8(&t);
        let rcp = s.splat_f8(1.0) / det;
        let hit = cand & t.ge(r.tmin) & t.le(tmax);
        // The scalar test's u, v: the edge functions of v1 and v2 over the determinant.
        (hit, t, v * rcp, w * rcp)
    }
}
