//! Möller–Trumbore ray/triangle intersection (1997), without culling.
//!
//! Fewer operations than the watertight test (edges precomputed at build time, no axis
//! permutation), but u, v, t are each divided by a determinant that is rounded separately per
//! triangle, so a ray aimed exactly at a shared edge may miss both triangles or hit both.

use super::{PreparedRay, PreparedRay8, Tri8, TriHit, TriTest};
use crate::accel::Precision;
use crate::geometry::Triangle;
use crate::simd::scalar::min_x86;
use crate::simd::{FloatV, MaskV, Simd};

/// The Möller–Trumbore test (`precision=fast`).
#[derive(Clone, Copy, Debug, Default)]
pub struct MollerTrumbore;

impl TriTest for MollerTrumbore {
    const PRECISION: Precision = Precision::Fast;

    #[inline]
    fn lane_data(tri: &Triangle) -> [[f32; 3]; 3] {
        let [v0, v1, v2] = tri.v;
        [
            v0,
            crate::geometry::sub(v1, v0),
            crate::geometry::sub(v2, v0),
        ]
    }

    #[inline]
    fn intersect_lane(r: &PreparedRay, p: &[[f32; 3]; 3], tmax: f32) -> Option<TriHit> {
        let [v0, e1, e2] = *p;
        let d = r.dir;
        let px = d[1] * e2[2] - d[2] * e2[1];
        let py = d[2] * e2[0] - d[0] * e2[2];
        let pz = d[0] * e2[1] - d[1] * e2[0];
        let det = e1[0] * px + e1[1] * py + e1[2] * pz;
        let inv = 1.0 / det;
        let s = [r.org[0] - v0[0], r.org[1] - v0[1], r.org[2] - v0[2]];
        let u = (s[0] * px + s[1] * py + s[2] * pz) * inv;
        let qx = s[1] * e1[2] - s[2] * e1[1];
        let qy = s[2] * e1[0] - s[0] * e1[2];
        let qz = s[0] * e1[1] - s[1] * e1[0];
        let v = (d[0] * qx + d[1] * qy + d[2] * qz) * inv;
        let t = (e2[0] * qx + e2[1] * qy + e2[2] * qz) * inv;
        // No `det != 0` term: with det = ±0, inv = ±inf makes u and v ±inf or NaN, and no
        // such pair passes `min(u, v) >= 0 && u + v <= 1` (a NaN u slips past the x86 min
        // but not past the sum). Same form as the 8-wide test, so the two agree bit for bit.
        let hit = min_x86(u, v) >= 0.0 && u + v <= 1.0 && t >= r.tmin && t <= tmax;
        hit.then_some(TriHit { t, u, v })
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
        let ld = |i: usize, k: usize| s.load_f8(&tri.p[i][k]);
        let [dx, dy, dz] = r.dir;
        let (e2x, e2y, e2z) = (ld(2, 0), ld(2, 1), ld(2, 2));
        let px = dy * e2z - dz * e2y;
        let py = dz * e2x - dx * e2z;
        let pz = dx * e2y - dy * e2x;
        let (e1x, e1y, e1z) = (ld(1, 0), ld(1, 1), ld(1, 2));
        let det = e1x * px + e1y * py + e1z * pz;
        let inv = s.splat_f8(1.0) / det;
        let sx = r.org[0] - ld(0, 0);
        let sy = r.org[1] - ld(0, 1);
        let sz = r.org[2] - ld(0, 2);
        let u = (sx * px + sy * py + sz * pz) * inv;
        let qx = sy * e1z - sz * e1y;
        let qy = sz * e1x - sx * e1z;
        let qz = sx * e1y - sy * e1x;
        let v = (dx * qx + dy * qy + dz * qz) * inv;
        let zero = s.splat_f8(0.0);
        // See the scalar test for why det == 0 needs no term of its own.
        let inside = u.min(v).ge(zero) & (u + v).le(s.splat_f8(1.0));
        if inside.none() {
            return (inside, zero, zero, zero);
        }
        let t = (e2x * qx + e2y * qy + e2z * qz) * inv;
        (inside & t.ge(r.tmin) & t.le(tmax), t, u, v)
    }
}
