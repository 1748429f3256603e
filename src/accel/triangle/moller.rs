//! Möller–Trumbore ray/triangle intersection (1997), without culling.
//!
//! Fewer operations than the watertight test (edges precomputed at build time, no axis
//! permutation), but u, v, t are each divided by a determinant that is rounded separately per
//! triangle, so a ray aimed exactly at a shared edge may miss both triangles or hit both.
//!
//! Its products are of three coordinates, so they leave f32's range long before the
//! coordinates do: a triangle 1e-18 across has a determinant of ~1e-54 (0 in f32), and one
//! 1e-18 behind the origin a t numerator that rounds to ±0, hit at `t = -0`. A lane whose
//! determinant, or (for a lane found inside) whose numerators or t, is not a normal f32 is
//! decided again ([`redecided_lane`]): in f64 ([`f64_lane`]), whose range holds every
//! product of three f32 values, where a step of the f32 test left f32's range.

use super::{PreparedRay, PreparedRay8, Tri8, TriHit, TriTest};
use crate::accel::Precision;
use crate::geometry::Triangle;
use crate::simd::scalar::{max_x86, min_x86};
use crate::simd::{FloatV, MaskV, Simd};

/// The Möller–Trumbore test (`precision=fast`).
#[derive(Clone, Copy, Debug, Default)]
pub struct MollerTrumbore;

/// Whether the test of a lane found inside stayed in f32's normal range: its u, v and t
/// numerators and its t normal numbers (the determinant is checked for every lane, inside
/// or not, since one out of range makes u and v meaningless). A numerator that underflowed
/// rounds to ±0, which `u >= 0` accepts whatever the exact sign (a point beside the
/// triangle taken as on its edge), and a t numerator that did made a plane behind the
/// origin a hit at `t = -0`, which `brute` reported and the trees, whose boxes lay behind
/// the ray, did not. A numerator of exactly 0 (the ray through an edge's line, or from a
/// vertex) is flagged too, and [`redecided_lane`] keeps its f32 answer where nothing
/// underflowed; a determinant of 0 at ordinary scales is not flagged ([`rounded_zero`]).
#[inline(always)]
fn in_range(un: f32, vn: f32, tn: f32, t: f32) -> bool {
    un.is_normal() && vn.is_normal() && tn.is_normal() && t.is_normal()
}

/// The test of one lane (`p` = `v0, e1, e2` as stored, `org` and `dir` the prepared ray's)
/// whose products left f32's normal range, decided again in f64 from the same f32 inputs.
/// Why f64 rather than the watertight test's powers of two: every product of this test is
/// of three coordinates, and f64's range holds every such product of f32 values (their
/// magnitudes lie between 2^-447 and 2^384), so no scaling is needed, and no component is
/// lost for lying far below the largest of its vector. (The watertight test must decide
/// in f32 to keep shared edges closed; this test has no such property to keep.) The
/// operations are the test's, in its order; the origin offset `org - v0` is the exact
/// difference (rounded to f64's 53 bits where the two lie more than 2^29 apart). u, v and
/// t are rounded once to f32; a t that would round to a zero goes to the smallest
/// subnormal of its sign instead, so that a plane just behind the origin is not hit at
/// `tmin = 0`. Edges that overflowed when the tree was built (`v1 - v0` beyond f32's
/// largest) stay a miss. Every core calls this one function for such lanes (cold, out of
/// the kernels), so they stay bit-identical. `None`: a miss (outside, a zero or
/// non-finite determinant, or a t beyond f32's range).
#[cold]
#[inline(never)]
pub(super) fn f64_lane(p: &[[f32; 3]; 3], org: [f32; 3], dir: [f32; 3]) -> Option<TriHit> {
    let f = |a: [f32; 3]| a.map(f64::from);
    let ([v0, e1, e2], o, d) = (p.map(f), f(org), f(dir));
    let s = [o[0] - v0[0], o[1] - v0[1], o[2] - v0[2]];
    let px = d[1] * e2[2] - d[2] * e2[1];
    let py = d[2] * e2[0] - d[0] * e2[2];
    let pz = d[0] * e2[1] - d[1] * e2[0];
    let det = e1[0] * px + e1[1] * py + e1[2] * pz;
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let u = (s[0] * px + s[1] * py + s[2] * pz) / det;
    let qx = s[1] * e1[2] - s[2] * e1[1];
    let qy = s[2] * e1[0] - s[0] * e1[2];
    let qz = s[0] * e1[1] - s[1] * e1[0];
    let v = (d[0] * qx + d[1] * qy + d[2] * qz) / det;
    // (A NaN fails every comparison: a miss.)
    let inside = u >= 0.0 && v >= 0.0 && u + v <= 1.0;
    if !inside {
        return None;
    }
    let q = (e2[0] * qx + e2[1] * qy + e2[2] * qz) / det;
    let t = match q as f32 {
        t if t == 0.0 && q != 0.0 => f32::from_bits(1).copysign(q as f32),
        t => t,
    };
    t.is_finite().then_some(TriHit {
        t,
        u: u as f32,
        v: v as f32,
    })
}

/// Tracks whether the f32 steps of [`redecided_lane`] stayed in f32's range.
struct Steps {
    /// A product of nonzero factors below 2^-126 (rounded, or flushed to ±0), or a step
    /// that overflowed (±inf, or NaN from one).
    lost: bool,
}

impl Steps {
    #[inline(always)]
    fn mul(&mut self, a: f32, b: f32) -> f32 {
        let x = a * b;
        self.lost |= !(x.is_normal() || (x == 0.0 && (a == 0.0 || b == 0.0)));
        x
    }
    #[inline(always)]
    fn add(&mut self, a: f32, b: f32) -> f32 {
        let x = a + b;
        self.lost |= !x.is_finite();
        x
    }
    /// `a·b - c·d`, the test's order.
    #[inline(always)]
    fn cross(&mut self, a: f32, b: f32, c: f32, d: f32) -> f32 {
        let (ab, cd) = (self.mul(a, b), self.mul(c, d));
        self.add(ab, -cd)
    }
    /// `a·b`, the test's order (`a0·b0 + a1·b1 + a2·b2`, left to right).
    #[inline(always)]
    fn dot(&mut self, a: [f32; 3], b: [f32; 3]) -> f32 {
        let (x, y, z) = (
            self.mul(a[0], b[0]),
            self.mul(a[1], b[1]),
            self.mul(a[2], b[2]),
        );
        let xy = self.add(x, y);
        self.add(xy, z)
    }
}

/// A lane that the kernels' range check flagged (`in_range`, `mt_det_ok8`), decided
/// again: its f32 test repeated step by step, and kept where no step left f32's range
/// (a numerator or determinant of exactly 0 from products that cancel: the ray through
/// an edge's line, from a vertex or along the plane, at ordinary scales), else decided by
/// [`f64_lane`]. Why not always f64: on a 2e13 ground quad a ray whose f32 offset lies
/// exactly on the shared diagonal was inside one triangle at `u = -0` in f32; decided in
/// f64 there (outside by 3e-14) and in f32 in its neighbour (outside by 2e-14), it fell
/// through the crack between them. Kept in f32, such lanes decide as they did before the
/// check existed (`rayd trace` hits bit for bit on the dragon's diffuse rays). Cold.
#[cold]
#[inline(never)]
pub(super) fn redecided_lane(p: &[[f32; 3]; 3], org: [f32; 3], dir: [f32; 3]) -> Option<TriHit> {
    let [v0, e1, e2] = *p;
    let d = dir;
    let mut st = Steps { lost: false };
    let px = st.cross(d[1], e2[2], d[2], e2[1]);
    let py = st.cross(d[2], e2[0], d[0], e2[2]);
    let pz = st.cross(d[0], e2[1], d[1], e2[0]);
    let det = st.dot(e1, [px, py, pz]);
    let s = [
        st.add(org[0], -v0[0]),
        st.add(org[1], -v0[1]),
        st.add(org[2], -v0[2]),
    ];
    let un = st.dot(s, [px, py, pz]);
    let qx = st.cross(s[1], e1[2], s[2], e1[1]);
    let qy = st.cross(s[2], e1[0], s[0], e1[2]);
    let qz = st.cross(s[0], e1[1], s[1], e1[0]);
    let vn = st.dot(d, [qx, qy, qz]);
    let tn = st.dot(e2, [qx, qy, qz]);
    if det == 0.0 && !st.lost {
        // Parallel at f32's resolution, exactly as the kernels find it: a miss.
        return None;
    }
    let inv = 1.0 / det;
    st.lost |= !det.is_normal() || !inv.is_normal();
    let (u, v, t) = (st.mul(un, inv), st.mul(vn, inv), st.mul(tn, inv));
    if st.lost {
        return f64_lane(p, org, dir);
    }
    let inside = min_x86(u, v) >= 0.0 && u + v <= 1.0;
    inside.then_some(TriHit { t, u, v })
}

/// The lanes of `bad` decided again by [`redecided_lane`] from `p` (`v0, e1, e2`), `org`
/// and `dir` per lane: their t (`+inf` for a miss), barycentrics and validity, merged into
/// the others'. Cold: only lanes that left f32's normal range come here (and those with a
/// determinant or numerator of exactly 0: a ray parallel to the triangle, or through an
/// edge's line).
#[cold]
#[inline(never)]
#[allow(clippy::too_many_arguments)]
fn redecided8<S: Simd>(
    s: S,
    bad: u32,
    p: &[[S::F8; 3]; 3],
    org: &[S::F8; 3],
    dir: &[S::F8; 3],
    tuv: [S::F8; 3],
    valid: S::M8,
) -> (S::F8, S::F8, S::F8, S::M8) {
    let p = p.map(|v| v.map(|x| x.to_array()));
    let (org, dir) = (org.map(|x| x.to_array()), dir.map(|x| x.to_array()));
    super::merge_lanes8(s, bad, tuv, valid, |lane| {
        let at = |a: [[f32; 8]; 3]| a.map(|x| x[lane]);
        redecided_lane(&p.map(at), at(org), at(dir))
    })
}

/// The lanes whose determinant is a normal f32 (finite, at least 2^-126 in magnitude): a
/// NaN fails both bounds.
#[inline(always)]
pub fn mt_det_ok8<S: Simd>(s: S, det: S::F8) -> S::M8 {
    let a = det.abs();
    a.ge(s.splat_f8(f32::MIN_POSITIVE)) & a.le(s.splat_f8(f32::MAX))
}

/// Below this, the scale of a determinant ([`rounded_zero`]) leaves room for underflow:
/// 2^-100.
const ROUNDED_ZERO_SCALE: f32 = 7.888_609e-31;

/// Whether a zero or subnormal determinant is f32's rounding of a ray parallel to the
/// triangle's plane rather than an underflow: its scale, `max|e2|·max|d|` and that times
/// `max|e1|` (each `max` over components, the x86 `max`), is at least 2^-100. Then the
/// determinant's rounding error, a few 2^-24 of its scale, exceeds anything an underflow
/// could have lost (2^-149 per product, times at most `max|e1|`), so it is kept: a miss,
/// as it always was. Why: a ray along an axis against walls that contain that axis (a
/// vertical ray beside axis-aligned boxes) has determinants of exactly 0 in every such
/// triangle; deciding each of those again ran `mbvh8` 2.5× and `dacrt` 3.3× as long on
/// 120,000 box triangles (BENCHMARKS §42). A scale below 2^-100 (triangles ~1e-20 across
/// and smaller, or such directions) is decided again.
#[inline(always)]
fn rounded_zero(det: f32, d: [f32; 3], e1: [f32; 3], e2: [f32; 3]) -> bool {
    let m = |v: [f32; 3]| max_x86(max_x86(v[0].abs(), v[1].abs()), v[2].abs());
    let a = m(e2) * m(d);
    let b = a * m(e1);
    det.abs() < f32::MIN_POSITIVE && a >= ROUNDED_ZERO_SCALE && b >= ROUNDED_ZERO_SCALE
}

/// [`rounded_zero`] on 8 lanes, the same operations.
#[inline(always)]
pub fn mt_rounded_zero8<S: Simd>(
    s: S,
    det: S::F8,
    d: [S::F8; 3],
    e1: [S::F8; 3],
    e2: [S::F8; 3],
) -> S::M8 {
    let m = |v: [S::F8; 3]| v[0].abs().max(v[1].abs()).max(v[2].abs());
    let a = m(e2) * m(d);
    let b = a * m(e1);
    let scale = s.splat_f8(ROUNDED_ZERO_SCALE);
    det.abs().lt(s.splat_f8(f32::MIN_POSITIVE)) & a.ge(scale) & b.ge(scale)
}

/// The t, barycentrics and validity of 8 lanes, with the lanes that left f32's range
/// decided again by [`redecided_lane`]: those whose determinant is not normal and not a
/// rounded zero (`det_ok` clear), and
/// those `inside` whose numerators `un, vn, tn` or t are not normal (`in_range`; the scalar
/// test's rule, lane for lane). Shared by the layer's 8-triangle test and DACRT's 8-ray
/// leaf test; `lanes` gives `(p, org, dir)` per lane, asked for only then. The kernels
/// sort out rounded zeros ([`mt_rounded_zero8`]) before their early return, which costs a
/// compare and a branch in every test with a lane inside (+1% of `dacrt`'s instructions
/// on the dragon); sorted out here instead, after t, a vertical ray beside axis-aligned
/// walls ran 1.4× (`mbvh8`) and 2× (`dacrt`) as long as before the check (BENCHMARKS §42).
/// `det_ok` includes them.
#[inline(always)]
pub fn mt_in_range8<S: Simd>(
    s: S,
    lanes: impl FnOnce() -> ([[S::F8; 3]; 3], [S::F8; 3], [S::F8; 3]),
    det_ok: S::M8,
    inside: S::M8,
    [un, vn, tn]: [S::F8; 3],
    tuv: [S::F8; 3],
) -> (S::F8, S::F8, S::F8, S::M8) {
    let t_abs = tuv[0].abs();
    // Inside a lane's un and vn are finite and not NaN (else u or v is ±inf or NaN, which
    // fails the test), and det is normal, so a non-finite tn makes t ±inf or NaN: with the
    // x86 `min` (the second operand where either is NaN) t last, `least` is NaN where t is.
    let least = un.abs().min(vn.abs()).min(tn.abs()).min(t_abs);
    let normal = least.ge(s.splat_f8(f32::MIN_POSITIVE)) & t_abs.le(s.splat_f8(f32::MAX));
    let bad = inside.andnot(normal) | !det_ok;
    if bad.none() {
        return (tuv[0], tuv[1], tuv[2], inside);
    }
    let (p, org, dir) = lanes();
    redecided8(s, bad.bitmask(), &p, &org, &dir, tuv, inside)
}

impl TriTest for MollerTrumbore {
    const PRECISION: Precision = Precision::Fast;

    /// A NaN `v0` (so u, v and t are NaN: never inside), with edges that span a plane
    /// through no axis: with all-NaN padding the determinant was NaN, which sent every
    /// 8-triangle test with a padding lane to the f64 decision (mbvh8 ran 64% more
    /// instructions). These keep it normal for every direction the cores test (tiny ones
    /// are scaled up, `accel::tiny_dir`; the smallest |det|/|d| over axis and small
    /// integer directions is 1.1e-4) unless it lies almost exactly in their plane (a
    /// cosine below ~2^-24, where f32's determinant is rounding noise), and below f32's
    /// largest for the largest. Never a hit: the NaN `v0` makes u and v NaN.
    const PAD: [[f32; 3]; 3] = [
        [f32::NAN; 3],
        [0.123_456_7, -0.098_765_4, 0.045_678_9],
        [0.031_415_9, 0.127_182_8, -0.057_721_5],
    ];

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
        let un = s[0] * px + s[1] * py + s[2] * pz;
        let u = un * inv;
        let qx = s[1] * e1[2] - s[2] * e1[1];
        let qy = s[2] * e1[0] - s[0] * e1[2];
        let qz = s[0] * e1[1] - s[1] * e1[0];
        let vn = d[0] * qx + d[1] * qy + d[2] * qz;
        let v = vn * inv;
        let tn = e2[0] * qx + e2[1] * qy + e2[2] * qz;
        let t = tn * inv;
        // The x86 `min` (a NaN u slips past it but not past the sum): the form of the
        // 8-wide test, so the two agree bit for bit.
        let inside = min_x86(u, v) >= 0.0 && u + v <= 1.0;
        let det_ok = det.is_normal() || rounded_zero(det, d, e1, e2);
        if !det_ok || (inside && !in_range(un, vn, tn, t)) {
            return redecided_lane(p, r.org, r.dir).filter(|h| h.t >= r.tmin && h.t <= tmax);
        }
        (inside && t >= r.tmin && t <= tmax).then_some(TriHit { t, u, v })
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
        let mut det_ok = mt_det_ok8(s, det);
        let inv = s.splat_f8(1.0) / det;
        let sx = r.org[0] - ld(0, 0);
        let sy = r.org[1] - ld(0, 1);
        let sz = r.org[2] - ld(0, 2);
        let un = sx * px + sy * py + sz * pz;
        let u = un * inv;
        let qx = sy * e1z - sz * e1y;
        let qy = sz * e1x - sx * e1z;
        let qz = sx * e1y - sy * e1x;
        let vn = dx * qx + dy * qy + dz * qz;
        let v = vn * inv;
        let zero = s.splat_f8(0.0);
        let inside = u.min(v).ge(zero) & (u + v).le(s.splat_f8(1.0));
        // Every lane outside with its determinant in range: the common case.
        if det_ok.andnot(inside).all() {
            return (inside, zero, zero, zero);
        }
        if !det_ok.all() {
            // Zero determinants of rays parallel to a triangle at ordinary scales.
            let (e1, e2) = ([e1x, e1y, e1z], [e2x, e2y, e2z]);
            det_ok = det_ok | mt_rounded_zero8(s, det, r.dir, e1, e2);
            if det_ok.andnot(inside).all() {
                return (inside, zero, zero, zero);
            }
        }
        let tn = e2x * qx + e2y * qy + e2z * qz;
        let t = tn * inv;
        let lanes = || ([0, 1, 2].map(|i| [0, 1, 2].map(|k| ld(i, k))), r.org, r.dir);
        let (t, u, v, valid) = mt_in_range8(s, lanes, det_ok, inside, [un, vn, tn], [t, u, v]);
        (valid & t.ge(r.tmin) & t.le(tmax), t, u, v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A vertical ray beside a wall that contains the vertical: both of the wall's
    /// triangles have a determinant of exactly 0, from products with a zero factor, and
    /// are kept as misses without being decided again; the same configuration 1e-25 times
    /// as large has a scale below 2^-100 and is decided again.
    #[test]
    fn zero_determinants_at_ordinary_scales_are_kept() {
        let d = [0.0, -1.0, 0.0];
        for k in [1.0f32, 1e-25] {
            let (sx, sy) = (1.5 * k, 0.75 * k);
            for (e1, e2) in [
                ([sx, 0.0, 0.0], [sx, sy, 0.0]),
                ([sx, sy, 0.0], [0.0, sy, 0.0]),
            ] {
                let p = [
                    d[1] * e2[2] - d[2] * e2[1],
                    d[2] * e2[0] - d[0] * e2[2],
                    d[0] * e2[1] - d[1] * e2[0],
                ];
                let det = e1[0] * p[0] + e1[1] * p[1] + e1[2] * p[2];
                assert_eq!(det, 0.0);
                assert_eq!(rounded_zero(det, d, e1, e2), k == 1.0, "scale {k:e}");
            }
        }
        // A normal determinant is not a rounded zero, whatever its scale.
        assert!(!rounded_zero(1.0, d, [1.0; 3], [1.0; 3]));
    }
}
