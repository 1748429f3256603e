//! The float64 reference every accelerator is tested against.
//!
//! The same watertight formulation as [`super::Watertight`], evaluated in f64 from the
//! stored f32 coordinates: products of f32 values are exact in f64, so the edge functions'
//! signs are right except for rays within ~1e-16 (relative) of an edge, far below the f32
//! tests' own rounding. An edge function that is exactly 0 is on the edge and counts as
//! inside (closed triangle). Degenerate triangles never hit.

use super::PreparedRay;
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
