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

/// The decision t of a hit whose paper t is `t`, of the prepared ray `r` on the triangle
/// `p`: `t` raised to where the ray enters the triangle's bounding box across the planes of
/// the two minor axes `kx`, `ky` of the ray. Per such axis `k` the near plane's distance
/// is `m_k = min_i (p[i][k] - org[k]) · inv[k]` in f32 ([`inv`](super::inv): 0 where the
/// direction component is ±0, so that such an axis gives the entry ±0, which no hit's t,
/// never negative, is below), the entry `e = max(m_kx, m_ky) + 0`, and the decision t
/// `max(e, t)`, with the x86 `min` and `max` of the SIMD layer (a NaN, which only an
/// overflowing `p - org` can make, is then skipped: `t` stays).
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
/// Why not `kz`: the paper's t is `Σ U·z_i / Σ U` with `U, V, W` of one sign, a convex
/// combination of the vertices' depths along `kz` (`z_i = (p[i][kz] - org[kz]) /
/// dir[kz]`), so along `kz` the hit point never lies before the box by more than the sum's
/// rounding (a few units of 2^-24 of `|p| + |org|`), far inside every tree's margin. The
/// minor axes have no such bound: there a sliver's garbage barycentrics move the point
/// anywhere along the ray.
///
/// The entry is within a few roundings of the exact one (`inv` and the product are each
/// rounded once, the difference nearly always exact), far inside every tree's margins
/// (the slab test's growth `δ`, DACRT's box growth and `T_SLACK`), so a box holding the
/// triangle is entered no later than this t. `min` over the vertices is the near plane's
/// distance whatever the direction's sign (a negative `inv` reverses the order), so no
/// branch is needed. The `+ 0` makes a zero entry `+0`, so `max(e, t)` keeps `t`'s own
/// sign where both are zero.
#[inline]
pub fn lift_t(r: &PreparedRay, p: &[[f32; 3]; 3], t: f32) -> f32 {
    let m = |k: usize| {
        let inv = super::inv(r.dir[k]);
        let d = |i: usize| (p[i][k] - r.org[k]) * inv;
        min_x86(min_x86(d(0), d(1)), d(2))
    };
    let e = max_x86(m(r.k[0]), m(r.k[1])) + 0.0;
    max_x86(e, t)
}

/// The entry `e` of [`lift_t`] on 8 lanes, from `rel[i][j]` = `p[i][k] - org[k]` for the
/// axis `k` that is `j`-th in the lane's ray order `kx, ky, kz` (only `kx`, `ky` are read)
/// and `inv[j]`, the reciprocal direction ([`inv`](super::inv)) of `kx`, `ky`; the
/// decision t is then `e.max(t)`. Shared by the layer's 8-triangle test and DACRT's 8-ray
/// leaf test, so that both decide exactly as the scalar test does. It does not depend on
/// t, so the layer's test computes it as soon as the vertices are loaded: the six
/// differences it reads then die early (kept live across the division they spilled
/// registers, which cost more than the arithmetic).
#[inline(always)]
pub fn entry8<S: Simd>(s: S, rel: &[[S::F8; 3]; 3], inv: [S::F8; 2]) -> S::F8 {
    let m = |j: usize| {
        let (a, b, c) = (rel[0][j] * inv[j], rel[1][j] * inv[j], rel[2][j] * inv[j]);
        a.min(b).min(c)
    };
    m(0).max(m(1)) + s.splat_f8(0.0)
}

/// The edge functions `U, V, W` of 8 lanes from `rel` (vertex `i` minus the origin, in the
/// lane's ray order `kx, ky, kz`) and the shear `sx, sy`, with the paper's f64 fallback
/// where one is exactly 0: the same operations as the scalar test, shared by the layer's
/// 8-triangle test and DACRT's 8-ray leaf test.
#[inline(always)]
pub fn edges8<S: Simd>(s: S, rel: &[[S::F8; 3]; 3], sx: S::F8, sy: S::F8) -> [S::F8; 3] {
    let (a_z, b_z, c_z) = (rel[0][2], rel[1][2], rel[2][2]);
    let ax = rel[0][0] - sx * a_z;
    let ay = rel[0][1] - sy * a_z;
    let bx = rel[1][0] - sx * b_z;
    let by = rel[1][1] - sy * b_z;
    let cx = rel[2][0] - sx * c_z;
    let cy = rel[2][1] - sy * c_z;
    let u = cx * by - cy * bx;
    let v = ax * cy - ay * cx;
    let w = bx * ay - by * ax;
    let zero = s.splat_f8(0.0);
    let z = u.eq(zero) | v.eq(zero) | w.eq(zero);
    if z.none() {
        return [u, v, w];
    }
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
    [s.load_f8(&uvw[0]), s.load_f8(&uvw[1]), s.load_f8(&uvw[2])]
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

/// Whether the paper's test of a lane stayed in f32's range: its t, t numerator `tt` and
/// determinant `det` normal numbers (finite, and not below 2^-126 in magnitude). Where they
/// were not, the lane is decided again by [`rescaled_lane`]: an edge function times a depth
/// past f32's largest; a determinant that overflowed (`t = tt · 0 = -0` for a plane behind
/// the origin, a hit at `tmin = 0`), or so small that its edge functions kept a few bits;
/// a numerator or a t that underflowed (a grid 1e-18 across, 1e-18 behind the origin, was
/// hit at `t = -0`, and the trees' boxes then culled what `brute` found). A numerator of
/// 0 is decided again too: an underflow, or the origin in the triangle's plane, which keeps
/// its t (nothing underflowed, so the scaled operations give the same bits).
#[inline(always)]
fn in_range(t: f32, tt: f32, det: f32) -> bool {
    t.is_normal() && tt.is_normal() && det.is_normal()
}

/// The edge functions `U, V, W` of one lane from its sheared coordinates across the ray
/// (`[x, y]` of each vertex), with the paper's f64 fallback where one is exactly 0, if the
/// ray is inside: all >= 0 or all <= 0 (zeros count both ways), as min/max with the x86
/// rules, the form the 8-wide test uses (4 fewer vector operations than six compares).
/// Shared by the scalar test and its rescaled decision, so both decide alike.
#[inline(always)]
fn edges_inside([[ax, ay], [bx, by], [cx, cy]]: [[f32; 2]; 3]) -> Option<(f32, f32, f32)> {
    let mut u = cx * by - cy * bx;
    let mut v = ax * cy - ay * cx;
    let mut w = bx * ay - by * ax;
    if u == 0.0 || v == 0.0 || w == 0.0 {
        (u, v, w) = edges_f64(ax, ay, bx, by, cx, cy);
    }
    let inside = min_x86(min_x86(u, v), w) >= 0.0 || max_x86(max_x86(u, v), w) <= 0.0;
    inside.then_some((u, v, w))
}

/// The paper's test on one triangle whose f32 products left f32's normal range
/// (`in_range`), from its vertices
/// relative to the ray origin (`rel[i]` in the ray's order `kx, ky, kz`): the sheared
/// coordinates are computed as the test computes them, then the six across the ray are
/// scaled by the power of two that brings their largest into [1, 2), the three depths by
/// another and the shear's `sz` by a third. Scaling by a power of two is exact, and every
/// later step is the same f32 operation on values scaled by powers of two (the edge
/// functions and the determinant by the square of the first, the t numerator by that times
/// the second and third), so the decision and (u, v) are those of f32 arithmetic without a
/// limit on the exponent (unless a value is more than 2^126 below the largest of its kind,
/// or `sz` is itself subnormal: those were rounded before the scaling), and t is scaled
/// back exactly unless it is below 2^-126 (then rounded, and away from zero to the
/// smallest subnormal rather than to a zero): a 2e13-unit ground quad, a cube of half-side
/// 1e13 seen from inside, a triangle of area 1e-40 and a grid 1e-18 across at the origin
/// are hit as unit ones are. Shared edges stay watertight: rounding is monotone, so an edge
/// function, scaled or not, has the exact product's sign or is 0 (recomputed in f64), and
/// its neighbour, tested unscaled, finds the same sign. Every core calls this one function for such lanes (cold, out of the
/// kernels), so they stay bit-identical. `None`: a miss (outside, a zero determinant, or
/// a t beyond f32's range).
#[cold]
#[inline(never)]
pub(super) fn rescaled_lane(rel: [[f32; 3]; 3], shear: [f32; 3]) -> Option<TriHit> {
    let [sx, sy, sz] = shear;
    let across = rel.map(|p| [p[0] - sx * p[2], p[1] - sy * p[2]]);
    // The exponent that brings the largest of `xs` into [1, 2) (0 for none: all zero, or
    // not finite, which no scaling mends).
    let exponent = |xs: &mut dyn Iterator<Item = f32>| {
        let m = xs.fold(0.0f32, |m, x| m.max(x.abs()));
        (m > 0.0 && m <= f32::MAX).then(|| f64::from(m).log2().floor() as i32)
    };
    let e_xy = exponent(&mut across.iter().flatten().copied())?;
    let e_z = exponent(&mut rel.iter().map(|p| p[2])).unwrap_or(0);
    // `sz` (1 / the direction's largest component) too, so that `sz · a_z` stays normal
    // for a small `sz` (a direction of 1e30) times a depth far below the largest; beyond
    // 8.5e37 `sz` is itself subnormal, and the bits it lost stay lost.
    let e_s = exponent(&mut std::iter::once(sz)).unwrap_or(0);
    // x · 2^k, exact in f64 and then in f32 unless it falls below f32's normal range.
    let scale = |x: f32, k: i32| (f64::from(x) * 2f64.powi(k)) as f32;
    let sz = scale(sz, -e_s);
    let [[ax, ay], [bx, by], [cx, cy]] = across.map(|p| p.map(|x| scale(x, -e_xy)));
    let (a_z, b_z, c_z) = (
        scale(rel[0][2], -e_z),
        scale(rel[1][2], -e_z),
        scale(rel[2][2], -e_z),
    );
    let (u, v, w) = edges_inside([[ax, ay], [bx, by], [cx, cy]])?;
    let det = u + v + w;
    if det == 0.0 {
        return None;
    }
    let tt = u * (sz * a_z) + v * (sz * b_z) + w * (sz * c_z);
    let rcp = 1.0 / det;
    // t scales as the depths do; one that would round to a zero is rounded away from it,
    // to the smallest subnormal of its sign, so that a plane just behind the origin is not
    // hit at `tmin = 0` (f32 without a limit on the exponent has no zero there either).
    // This is the decision t: the reported one (`refined_t`) is rounded to nearest, +0.
    let q = tt * rcp;
    let t = match scale(q, e_z + e_s) {
        t if t == 0.0 && q != 0.0 => f32::from_bits(1).copysign(q),
        t => t,
    };
    t.is_finite().then_some(TriHit {
        t,
        u: v * rcp,
        v: w * rcp,
    })
}

/// The lanes of `bad` decided again by [`rescaled_lane`]: their paper t (`+inf` for a
/// miss), barycentrics and validity, merged into the others'. Cold: only lanes that left
/// f32's normal range come here (and those of rays that start in a triangle's plane).
#[cold]
#[inline(never)]
#[allow(clippy::too_many_arguments)]
fn rescaled8<S: Simd>(
    s: S,
    bad: u32,
    rel: &[[S::F8; 3]; 3],
    shear: [S::F8; 3],
    t: S::F8,
    bu: S::F8,
    bv: S::F8,
    valid: S::M8,
) -> (S::F8, S::F8, S::F8, S::M8) {
    let rel = rel.map(|p| p.map(|x| x.to_array()));
    let shear = shear.map(|x| x.to_array());
    super::merge_lanes8(s, bad, [t, bu, bv], valid, |lane| {
        rescaled_lane(rel.map(|p| p.map(|x| x[lane])), shear.map(|x| x[lane]))
    })
}

/// The paper's t, barycentrics and validity of 8 lanes, with the lanes of `inside` that
/// left f32's range (`in_range`: t, its numerator `tt` or the determinant `det` not a
/// normal number) decided again by [`rescaled_lane`] (the scalar test's rule, lane for
/// lane); shared by the layer's 8-triangle test and DACRT's 8-ray leaf test. `rel` gives
/// the vertices relative to the origin, asked for only then (a closure rather than a
/// reference: with a reference, `mbvh8` and `dacrt` ran 3% more instructions by
/// callgrind; with the closure, within 0.3% of the kernels without this check).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub fn in_range8<S: Simd>(
    s: S,
    rel: impl FnOnce() -> [[S::F8; 3]; 3],
    shear: [S::F8; 3],
    inside: S::M8,
    [tt, det]: [S::F8; 2],
    t: S::F8,
    bu: S::F8,
    bv: S::F8,
    valid: S::M8,
) -> (S::F8, S::F8, S::F8, S::M8) {
    // `in_range` on 8 lanes. With the x86 rules `a.min(b)` and `a.max(b)` are `b` where
    // either is NaN, so t, which is NaN wherever tt or det is, comes second in both: a NaN
    // fails both bounds. (An infinite det makes t ±0 or NaN, which fail too.)
    let (t_abs, det_abs) = (t.abs(), det.abs());
    let least = tt.abs().min(det_abs).min(t_abs);
    let most = det_abs.max(t_abs);
    let normal = least.ge(s.splat_f8(f32::MIN_POSITIVE)) & most.le(s.splat_f8(f32::MAX));
    let bad = inside.andnot(normal);
    if bad.none() {
        return (t, bu, bv, valid);
    }
    rescaled8(s, bad.bitmask(), &rel(), shear, t, bu, bv, valid)
}

impl Watertight {
    /// The paper's test on one triangle: its hit with the paper's own t, before the
    /// decision lift ([`lift_t`]) that `intersect_lane` applies.
    #[inline]
    pub(super) fn paper_lane(r: &PreparedRay, p: &[[f32; 3]; 3], tmax: f32) -> Option<TriHit> {
        let [kx, ky, kz] = r.k;
        let [sx, sy, sz] = r.shear;
        // Vertex minus origin, `rel[i]` in the order kx, ky, kz.
        let rel = [0, 1, 2].map(|i| [kx, ky, kz].map(|k| p[i][k] - r.org[k]));
        let (a_z, b_z, c_z) = (rel[0][2], rel[1][2], rel[2][2]);
        let across = rel.map(|q| [q[0] - sx * q[2], q[1] - sy * q[2]]);
        let (u, v, w) = edges_inside(across)?;
        let det = u + v + w;
        let tt = u * (sz * a_z) + v * (sz * b_z) + w * (sz * c_z);
        let rcp = 1.0 / det;
        let t = tt * rcp;
        if !in_range(t, tt, det) {
            return rescaled_lane(rel, r.shear).filter(|h| h.t >= r.tmin && h.t <= tmax);
        }
        // (`in_range` holds, so det is not 0.)
        (t >= r.tmin && t <= tmax).then_some(TriHit {
            t,
            u: v * rcp,
            v: w * rcp,
        })
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
        refined_t(ray, p, crate::accel::tiny_dir::unscaled_hit_t(ray, t))
    }

    #[inline]
    fn intersect_lane(r: &PreparedRay, p: &[[f32; 3]; 3], tmax: f32) -> Option<TriHit> {
        let h = Self::paper_lane(r, p, tmax)?;
        let t = lift_t(r, p, h.t);
        (t <= tmax).then_some(TriHit { t, ..h })
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
        // Vertex minus origin, `rel[i]` in the order kx, ky, kz.
        let rel = |i: usize| [ld(i, kx) - ox, ld(i, ky) - oy, ld(i, kz) - oz];
        let rel = [rel(0), rel(1), rel(2)];
        // The decision t's entry (`lift_t`), from the minor axes' differences.
        let inv = [s.splat_f8(r.inv_k[0]), s.splat_f8(r.inv_k[1])];
        let entry = entry8(s, &rel, inv);
        let [u, v, w] = edges8(s, &rel, sx, sy);
        let (a_z, b_z, c_z) = (rel[0][2], rel[1][2], rel[2][2]);
        let zero = s.splat_f8(0.0);
        let inside = u.min(v).min(w).ge(zero) | u.max(v).max(w).le(zero);
        if inside.none() {
            return (inside, zero, zero, zero);
        }
        let det = u + v + w;
        let tt = u * (sz * a_z) + v * (sz * b_z) + w * (sz * c_z);
        let rcp = s.splat_f8(1.0) / det;
        let t = tt * rcp;
        // The scalar test's u, v: the edge functions of v1 and v2 over the determinant.
        let (t, bu, bv, valid) = in_range8(
            s,
            || rel,
            [sx, sy, sz],
            inside,
            [tt, det],
            t,
            v * rcp,
            w * rcp,
            // Lanes that `in_range` passes have a normal det; the others are decided again.
            inside,
        );
        // The decision t (`lift_t`): unchanged but for slivers and hits on a box's plane.
        let hit = valid & t.ge(r.tmin) & t.le(tmax);
        let t = entry.max(t);
        let hit = hit & t.le(tmax);
        (hit, t, bu, bv)
    }
}
