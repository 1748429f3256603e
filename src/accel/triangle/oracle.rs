//! The float64 reference every accelerator is tested against.
//!
//! The same watertight formulation as [`super::Watertight`], evaluated in f64 from the
//! stored f32 coordinates: products of f32 values are exact in f64, so the edge functions'
//! signs are right except for rays within ~1e-16 (relative) of an edge, far below the f32
//! tests' own rounding. An edge function that is exactly 0 is on the edge and counts as
//! inside (closed triangle). Degenerate triangles never hit.

use super::PreparedRay;
use crate::accel::Precision;
use crate::geometry::{Ray, Triangle};

/// A reference hit: `(1-u-v)·v0 + u·v1 + v·v2 = org + t·dir`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OracleHit {
    /// Ray parameter.
    pub t: f64,
    /// Barycentric weight of `v1`.
    pub u: f64,
    /// Barycentric weight of `v2`.
    pub v: f64,
}

/// Edge functions and the t numerator in f64: `(U, V, W, T)`; `det = U + V + W`.
fn edge_functions(ray: &Ray, tri: &Triangle) -> (f64, f64, f64, f64) {
    let r = PreparedRay::new(ray);
    let [kx, ky, kz] = r.k;
    let d = ray.dir.map(f64::from);
    let (sx, sy, sz) = (d[kx] / d[kz], d[ky] / d[kz], 1.0 / d[kz]);
    let p: Vec<[f64; 3]> = tri
        .v
        .iter()
        .map(|q| {
            let rel = |k: usize| f64::from(q[k]) - f64::from(ray.org[k]);
            [rel(kx) - sx * rel(kz), rel(ky) - sy * rel(kz), sz * rel(kz)]
        })
        .collect();
    let (a, b, c) = (p[0], p[1], p[2]);
    let u = c[0] * b[1] - c[1] * b[0];
    let v = a[0] * c[1] - a[1] * c[0];
    let w = b[0] * a[1] - b[1] * a[0];
    (u, v, w, u * a[2] + v * b[2] + w * c[2])
}

/// Where the ray's line meets the triangle's plane, in f64, with barycentrics that may lie
/// outside `[0, 1]` and t outside the ray's interval: the raw material for tolerant
/// comparisons (how far from an edge, how far from the interval ends). `None` when the ray
/// is parallel to the plane (or the triangle is degenerate).
pub fn oracle_line_f64(ray: &Ray, tri: &Triangle) -> Option<OracleHit> {
    if tri.is_degenerate() {
        return None;
    }
    let (u, v, w, tt) = edge_functions(ray, tri);
    let det = u + v + w;
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    Some(OracleHit {
        t: tt / det,
        u: v / det,
        v: w / det,
    })
}

/// The reference test: does `ray` hit `tri` at a t in the closed `[tmin, tmax]`?
pub fn oracle_f64(ray: &Ray, tri: &Triangle) -> Option<OracleHit> {
    if tri.is_degenerate() || PreparedRay::new(ray).is_empty() {
        return None;
    }
    let (u, v, w, tt) = edge_functions(ray, tri);
    let inside = (u >= 0.0 && v >= 0.0 && w >= 0.0) || (u <= 0.0 && v <= 0.0 && w <= 0.0);
    let det = u + v + w;
    if !inside || det == 0.0 {
        return None;
    }
    let t = tt / det;
    (t >= f64::from(ray.tmin) && t <= f64::from(ray.tmax)).then_some(OracleHit {
        t,
        u: v / det,
        v: w / det,
    })
}

/// The reference closest hit over a triangle soup: smallest t, ties to the lowest id.
pub fn oracle_closest_f64(ray: &Ray, tris: &[Triangle]) -> Option<(u32, OracleHit)> {
    let mut best: Option<(u32, OracleHit)> = None;
    for (i, tri) in tris.iter().enumerate() {
        if let Some(h) = oracle_f64(ray, tri) {
            if best.is_none_or(|(_, b)| h.t < b.t) {
                best = Some((i as u32, h));
            }
        }
    }
    best
}

/// Whether a `fast` hit at `t` of `ray` on `tri` that [`oracle_line_f64`] cannot place is
/// plausible. The sheared f64 oracle subtracts the ray origin from each vertex, so a
/// triangle smaller than f64's resolution at its distance from the origin (1e-35 across,
/// 0.1 away) becomes one point, its ray "parallel"; Möller–Trumbore keeps the edges apart
/// (`v1 - v0`, `v2 - v0`, rounded once) and hits such a triangle where the ray passes
/// within f32's rounding of `org - v0`, at a vertex (and a ray in a triangle's plane, as
/// f32 rounds it, at its origin). Plausible: the hit's point `o + t·d` (in f64) lies in
/// the triangle's bounding box grown, per axis, by 2^-20 of the reach (the largest of the
/// vertices' and the point's distances from the origin: a few of f32's roundings there)
/// plus `|d|` times [`t_bound`] at `t` (where the plane is not parallel in f64).
pub fn unresolved_hit_plausible(ray: &Ray, tri: &Triangle, t: f32) -> bool {
    let f = |a: [f32; 3]| a.map(f64::from);
    let (o, d, v, t) = (f(ray.org), f(ray.dir), tri.v.map(f), f64::from(t));
    let tb = t_bound(Precision::Fast, ray, tri, t);
    let tb = if tb.is_finite() { tb } else { 0.0 };
    (0..3).all(|k| {
        let x = o[k] + t * d[k];
        let reach = v
            .iter()
            .map(|p| (p[k] - o[k]).abs())
            .fold((t * d[k]).abs(), f64::max);
        let lo = v.iter().map(|p| p[k]).fold(f64::INFINITY, f64::min);
        let hi = v.iter().map(|p| p[k]).fold(f64::NEG_INFINITY, f64::max);
        let grow = reach * 2f64.powi(-20) + d[k].abs() * tb;
        x >= lo - grow && x <= hi + grow
    })
}

/// The conditioning of a hit, in f64: `(S, G, L)` with `S = |e1|·|e2| / |n|` (1 for a
/// right isosceles triangle, huge for a sliver), `G = |n|·|d| / |n·d|` (1 head-on, huge
/// when grazing) and `L = (|v0 - o| + |e1| + |e2|) / |d|` (how far, in units of t, the
/// triangle's corner and extent are from the origin). `None` for a degenerate triangle or
/// a ray parallel to its plane.
fn conditioning(ray: &Ray, tri: &Triangle) -> Option<(f64, f64, f64)> {
    let f = |a: [f32; 3]| a.map(f64::from);
    let (o, d) = (f(ray.org), f(ray.dir));
    let v = tri.v.map(f);
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let len = |a: [f64; 3]| (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    let (e1, e2, w) = (sub(v[1], v[0]), sub(v[2], v[0]), sub(v[0], o));
    let n = [
        e1[1] * e2[2] - e1[2] * e2[1],
        e1[2] * e2[0] - e1[0] * e2[2],
        e1[0] * e2[1] - e1[1] * e2[0],
    ];
    let nd = (n[0] * d[0] + n[1] * d[1] + n[2] * d[2]).abs();
    let (ln, ld) = (len(n), len(d));
    if ln == 0.0 || nd == 0.0 {
        return None;
    }
    let s = len(e1) * len(e2) / ln;
    let g = ln * ld / nd;
    let l = (len(w) + len(e1) + len(e2)) / ld;
    Some((s, g, l))
}

/// The written bound (proto/semantics.md, "Error bounds") on `|t - t*|` for a hit of
/// `ray` on `tri` reported by the test of `precision`, where `t*` is the exact parameter
/// of the line's crossing with the triangle's plane (`t_exact`, from [`oracle_line_f64`]
/// up to [`oracle_t_error`]):
///
/// - `watertight`: `2^-24·|t*| + 2^-49·S·G·(L + |t*|)`: one f32 rounding of an f64 value
///   ([`super::refined_t`]);
/// - `fast`: `2^-24·|t*| + 2^-19·S·G·(L + |t*|)`: Möller–Trumbore in f32, whose error
///   grows with the distance of the triangle's corner from the origin and its size;
///
/// each plus 2^-149, f32's spacing below 2^-126, where a rounding's error is no longer
/// relative (a t of 1e-60 is reported as 0).
///
/// `S`, `G`, `L` are the sliver, grazing and distance factors of [`conditioning`]. `+inf`
/// for a ray parallel to the plane (no bound).
pub fn t_bound(precision: Precision, ray: &Ray, tri: &Triangle, t_exact: f64) -> f64 {
    let Some((s, g, l)) = conditioning(ray, tri) else {
        return f64::INFINITY;
    };
    let t = t_exact.abs();
    let k = match precision {
        Precision::Watertight => 2f64.powi(-49),
        Precision::Fast => 2f64.powi(-19),
    };
    2f64.powi(-24) * t + k * s * g * (l + t) + SUBNORMAL_SPACING
}

/// f32's spacing below 2^-126 (its smallest subnormal), where a rounding's error is
/// absolute: both t bounds add it.
const SUBNORMAL_SPACING: f64 = f32::from_bits(1) as f64;

/// The written bound on `|u - u*|` and `|v - v*|` (absolute; u, v are barycentrics) for
/// either precision: `2^-19·G·S·L·|d| / min(|e1|, |e2|)`, which for a fat triangle seen
/// head-on from a distance comparable to its size is a few f32 ulps of 1. Both tests
/// divide f32 edge functions (or their Möller–Trumbore equivalents) by an f32
/// determinant, so both lose accuracy as the origin recedes relative to the triangle's
/// size (`L`), as the view grazes (`G`) and for slivers (`S`).
pub fn uv_bound(precision: Precision, ray: &Ray, tri: &Triangle) -> f64 {
    let _ = precision;
    let Some((s, g, l)) = conditioning(ray, tri) else {
        return f64::INFINITY;
    };
    let f = |a: [f32; 3]| a.map(f64::from);
    let v = tri.v.map(f);
    let len = |a: [f64; 3], b: [f64; 3]| {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
    };
    let size = len(v[1], v[0]).min(len(v[2], v[0]));
    let ld = f(ray.dir).map(|x| x * x).iter().sum::<f64>().sqrt();
    2f64.powi(-19) * g * s * l * ld / size
}

/// A first-order bound on the rounding error of the oracle's own t (the sheared f64
/// computation of [`oracle_line_f64`], following pbrt-v3's analysis of the same test):
/// what a comparison with the oracle must add to [`t_bound`]. Far below it except for
/// slivers and grazing rays.
pub fn oracle_t_error(ray: &Ray, tri: &Triangle) -> f64 {
    sheared_t_error(ray, tri, f64::EPSILON / 2.0, 1.0)
}

/// The written bound on `|t - t*|` for the t a core *decides and orders by* (the test's
/// own t, before [`super::TriTest::finish_t`]): for `watertight`, the paper's sheared f32
/// t, whose error grows with the vertices' depths along the ray (pbrt-v3's analysis of
/// the test, carried out for f32 and with a factor 2 to spare); for `fast`, [`t_bound`]
/// (its reported t is the one it orders by). Two hits whose exact t differ by less than
/// the sum of their bounds may be ordered either way (proto/semantics.md, "Error bounds").
pub fn order_t_bound(precision: Precision, ray: &Ray, tri: &Triangle, t_exact: f64) -> f64 {
    match precision {
        Precision::Fast => t_bound(precision, ray, tri, t_exact),
        // Plus f32's spacing below 2^-126: a decision t that would round to 0 is rounded
        // away from it (`watertight::rescaled_lane`).
        Precision::Watertight => sheared_t_error(ray, tri, 2f64.powi(-24), 2.0) + SUBNORMAL_SPACING,
    }
}

/// The pbrt-v3 style error bound of the sheared watertight t computed with unit roundoff
/// `u`, with its terms evaluated in f64 from the stored f32 values; `q` roundings in the
/// final quotient (1 for a division, 2 for the f32 test's reciprocal and product).
fn sheared_t_error(ray: &Ray, tri: &Triangle, u: f64, q: f64) -> f64 {
    let r = PreparedRay::new(ray);
    let [kx, ky, kz] = r.k;
    let d = ray.dir.map(f64::from);
    let (sx, sy, sz) = (d[kx] / d[kz], d[ky] / d[kz], 1.0 / d[kz]);
    let gamma = |n: f64| n * u / (1.0 - n * u);
    let (mut xm, mut ym, mut zm, mut rz) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    let mut p = [[0.0f64; 3]; 3];
    for (i, q) in tri.v.iter().enumerate() {
        let rel = |k: usize| f64::from(q[k]) - f64::from(ray.org[k]);
        p[i] = [rel(kx) - sx * rel(kz), rel(ky) - sy * rel(kz), sz * rel(kz)];
        xm = xm.max(p[i][0].abs());
        ym = ym.max(p[i][1].abs());
        zm = zm.max(p[i][2].abs());
        rz = rz.max(rel(kz).abs());
    }
    let (a, b, c) = (p[0], p[1], p[2]);
    let e = [
        c[0] * b[1] - c[1] * b[0],
        a[0] * c[1] - a[1] * c[0],
        b[0] * a[1] - b[1] * a[0],
    ];
    let em = e.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let det = (e[0] + e[1] + e[2]).abs();
    if det == 0.0 {
        return f64::INFINITY;
    }
    let tt = e[0] * a[2] + e[1] * b[2] + e[2] * c[2];
    let dz = gamma(3.0) * zm;
    let dx = gamma(5.0) * (xm + rz);
    let dy = gamma(5.0) * (ym + rz);
    let de = 2.0 * (gamma(2.0) * xm * ym + dy * xm + dx * ym);
    let dt = 3.0 * (gamma(3.0) * em * zm + de * zm + dz * em);
    let ddet = 3.0 * de + gamma(2.0) * 3.0 * em;
    2.0 * ((dt + (tt / det).abs() * ddet) / det + q * u * (tt / det).abs())
}
