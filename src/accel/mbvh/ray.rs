//! Per-ray constants of the slab test, shared by the MBVH and packet cores.
//!
//! # A conservative slab test
//!
//! The closest hit must be bit-identical to `brute`'s, ties to the lowest id included, so
//! every box that holds a triangle the (rounded) triangle test reports at t ∈ [tmin, best]
//! must be entered with an entry distance ≤ t. Rounding breaks this in exact arithmetic's
//! boundary cases: a ray through a box corner, a triangle lying in a box face (its t and
//! the slab's entry distance are two differently rounded values of the same number), a ray
//! that runs inside a face plane with a ±0 direction component (0·∞).
//!
//! The triangle tests' errors are, in space, a few units of 2^-24 · (|vertex| + |origin|)
//! (the translation to the ray origin and the shear), so each box is tested as if grown by
//! `δ = 2^-19 · (scale + max|origin|)` on every side, `scale` being the largest
//! |coordinate| of the scene: 32 times that error bound. Growing costs nothing per node:
//! `(lo - δ - o)·inv = (lo - (o + δ))·inv`, so lower planes are measured from the origin
//! moved by `+δ` and upper planes from the origin moved by `-δ`. It also removes the 0·∞
//! NaN of axis-parallel rays whose origin lies in a box plane (the moved origins never
//! lie in it); the remaining NaN cases (a plane exactly at a moved origin) are ignored by
//! the operand order of the x86 `min`/`max` rule, which only ever enlarges the interval.
//! The grown boxes cost a negligible number of extra visits (δ is ~10⁻⁶ of the scene).
//!
//! # The interval start
//!
//! Growing the boxes makes the entry distance of the box of a reported hit at most its t,
//! but a box test must also not end before that t: a ray grazing a triangle gets a t whose
//! error, along the ray, can exceed δ, so its point may lie past the box's exit. Within
//! `[tmin, best]` that only matters at the start: a hit the triangle test reports at
//! exactly `tmin` (a ray continued from a hit, `tmin` set to that hit's t) was missed when
//! its box's exit, rounded, fell just before `tmin`. Boxes are therefore tested on
//! `[0, best]`, and the triangle test alone applies `tmin`: a ray with `tmin > 0` may
//! visit a few boxes wholly before `tmin`, but never skips one holding a hit.
//!
//! # Finite reciprocals
//!
//! A ±0 direction component would make `1/dir` infinite and every slab distance of that
//! axis NaN in the fused form `plane·inv - org·inv` (∞ - ∞), which the slab test ignores:
//! correct, but an axis-parallel ray would then cull on no axis at all. So components
//! smaller than `TILT = 2^-21` of the largest are raised to that size, keeping their sign:
//! the box test then follows a ray tilted by at most `2^-21·max|dir|` per unit of t. Any
//! box hit lies within the scene, i.e. at `t <= (scale + |org|)/max|dir|`, where the tilt
//! has moved the ray by at most `2^-21·(scale + |org|) = δ/4`: well inside the growth.

//!
//! # Tiny directions
//!
//! The fused slab test computes a plane's distance as `plane·inv − org·inv`, whose products
//! overflow f32 when `|inv|` times the scene's or the origin's scale passes 2^128, long
//! before the distance itself does: a direction of 1e-38 (inv ~1e38) in a scene a few
//! units wide overflowed every box's distances to ±inf or NaN, and the tree missed hits at
//! finite t (2.8e38) that `brute` found. For such directions ([`tiny_dir::exponent`]) the box
//! test runs in units of `2^e·t`: the direction is scaled by `2^e` first (exact: a power of
//! two), so every distance is the unscaled one times `2^-e`, exactly where neither
//! overflows nor is subnormal, and the bound it is compared with, the closest hit's t, is
//! scaled the same way and rounded up ([`SlabConsts::box_t`]). Other rays have `e = 0` and
//! run as before.

use crate::accel::tiny_dir::{self, scaled_dir, scaled_t};
use crate::accel::triangle::PreparedRay;
use crate::simd::{FloatV, IntV, MaskV, Select, Simd};

/// Relative size of the box growth (see the module docs).
pub const SLACK: f32 = 1.0 / (1u32 << 19) as f32;

/// Direction components smaller than this fraction of the largest are raised to it (sign
/// kept) before the reciprocal (see the module docs).
pub const TILT: f32 = 1.0 / (1u32 << 21) as f32;

/// What the slab test needs of one ray.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoxRay {
    /// `1 / dir`, each component first raised in magnitude to at least
    /// [`TILT`]`·max|dir|` with its sign (bit) kept: finite for every valid ray whose
    /// direction is not denormal-small.
    pub inv: [f32; 3],
    /// Origin for the lower planes: `org + δ`.
    pub org_lo: [f32; 3],
    /// Origin for the upper planes: `org - δ`.
    pub org_hi: [f32; 3],
    /// Per axis, whether the direction's sign bit is set (then the upper plane is the near
    /// one).
    pub neg: [bool; 3],
    /// Start of the interval boxes are tested on: always `+0`, not the ray's `tmin` (see
    /// "The interval start" in the module docs); the triangle test applies `tmin`.
    pub tmin: f32,
    /// Interval end, `+0` for `-0`, in the ray's own t.
    pub tmax: f32,
    /// The `e` of "Tiny directions" (module docs): `inv` is that of the direction times
    /// `2^e`, so box distances measure `2^-e·t` ([`BoxRay::box_t`]).
    pub exp: i32,
}

impl BoxRay {
    /// `t` in the units the box test measures, rounded up, so that a box is never pruned
    /// against a bound smaller than the hit's.
    #[inline(always)]
    pub fn box_t(&self, t: f32) -> f32 {
        scaled_t(t, self.exp)
    }

    /// The constants of `r` in a scene whose coordinates are at most `scale` in magnitude.
    #[inline(always)]
    pub fn new(r: &PreparedRay, scale: f32) -> BoxRay {
        let o = r.org;
        let exp = tiny_dir::exponent(
            r.dir.iter().fold(0.0f32, |m, x| m.max(x.abs())),
            scale,
            o.iter().fold(0.0f32, |m, x| m.max(x.abs())),
        );
        let d = if exp == 0 {
            r.dir
        } else {
            scaled_dir(r.dir, exp)
        };
        let big = o.iter().fold(scale, |m, x| m.max(x.abs()));
        let delta = SLACK * (scale + big);
        let floor = TILT * d.iter().fold(0.0f32, |m, x| m.max(x.abs()));
        let safe = |x: f32| {
            let a = x.abs().max(floor);
            1.0 / if x.is_sign_negative() { -a } else { a }
        };
        BoxRay {
            inv: [safe(d[0]), safe(d[1]), safe(d[2])],
            org_lo: [o[0] + delta, o[1] + delta, o[2] + delta],
            org_hi: [o[0] - delta, o[1] - delta, o[2] - delta],
            neg: [
                r.dir[0].is_sign_negative(),
                r.dir[1].is_sign_negative(),
                r.dir[2].is_sign_negative(),
            ],
            // x + 0.0 turns -0 into +0 and leaves everything else as it is.
            tmin: 0.0,
            tmax: r.tmax + 0.0,
            exp,
        }
    }

    /// Row of the near plane of `axis` in a `[lower x, y, z, upper x, y, z]` plane array.
    #[inline(always)]
    pub fn near_row(&self, axis: usize) -> usize {
        axis + 3 * usize::from(self.neg[axis])
    }

    /// Row of the far plane of `axis`.
    #[inline(always)]
    pub fn far_row(&self, axis: usize) -> usize {
        axis + 3 * usize::from(!self.neg[axis])
    }

    /// The origin to measure the near plane of `axis` from.
    #[inline(always)]
    pub fn near_org(&self, axis: usize) -> f32 {
        if self.neg[axis] {
            self.org_hi[axis]
        } else {
            self.org_lo[axis]
        }
    }

    /// The origin to measure the far plane of `axis` from.
    #[inline(always)]
    pub fn far_org(&self, axis: usize) -> f32 {
        if self.neg[axis] {
            self.org_lo[axis]
        } else {
            self.org_hi[axis]
        }
    }
}

/// [`BoxRay`]'s constants in the form the fused slab test uses, per axis (lane 3 unused):
/// `1/dir`, `-(near origin · inv)`, `-(far origin · inv)`, and the direction's sign bits.
/// Bit-identical to deriving them from [`BoxRay`] (same operations in the same order).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SlabConsts {
    /// `1/dir` (tilted, see [`BoxRay::inv`]).
    pub inv: [f32; 4],
    /// `-(near origin · inv)`.
    pub near_oi: [f32; 4],
    /// `-(far origin · inv)`.
    pub far_oi: [f32; 4],
    /// Bit k set when `dir[k]`'s sign bit is.
    pub neg: u32,
    /// Start of the interval boxes are tested on: `+0` (see [`BoxRay::tmin`]).
    pub tmin: f32,
    /// Interval end (`-0` made `+0`), in the ray's own t.
    pub tmax: f32,
    /// The `e` of "Tiny directions" (module docs): the constants above measure `2^-e·t`.
    pub exp: i32,
}

impl SlabConsts {
    /// `t` in the units the box test measures (`2^-e·t`), rounded up, so that a box is
    /// never pruned against a bound smaller than the hit's.
    #[inline(always)]
    pub fn box_t(&self, t: f32) -> f32 {
        scaled_t(t, self.exp)
    }

    /// Computes the constants 4-wide (a third of the instructions of the scalar route,
    /// which matters once per ray).
    #[inline(always)]
    pub fn new<S: Simd>(s: S, r: &PreparedRay, scale: f32) -> SlabConsts {
        let o = s.load_f4(&[r.org[0], r.org[1], r.org[2], 0.0]);
        let d = s.load_f4(&[r.dir[0], r.dir[1], r.dir[2], 0.0]);
        let big = o.abs().hmax();
        let exp = tiny_dir::exponent(d.abs().hmax(), scale, big);
        let d = if exp == 0 {
            d
        } else {
            let [x, y, z] = scaled_dir(r.dir, exp);
            s.load_f4(&[x, y, z, 0.0])
        };
        let a = d.abs();
        let big = if big > scale { big } else { scale };
        let delta = s.splat_f4(SLACK * (scale + big));
        let neg = d.to_bits().lt(s.splat_i4(0));
        let mag = a.max(s.splat_f4(TILT * a.hmax()));
        let inv = s.splat_f4(1.0) / neg.select(-mag, mag);
        let (lo, hi) = (o + delta, o - delta);
        let near = neg.select(hi, lo);
        let far = neg.select(lo, hi);
        SlabConsts {
            inv: inv.to_array(),
            near_oi: (-(near * inv)).to_array(),
            far_oi: (-(far * inv)).to_array(),
            neg: neg.bitmask() & 7,
            tmin: 0.0,
            tmax: r.tmax + 0.0,
            exp,
        }
    }

    /// The same constants from the scalar [`BoxRay`] (the reference).
    pub fn from_box_ray(b: &BoxRay) -> SlabConsts {
        let oi = |o: f32, k: usize| -(o * b.inv[k]);
        SlabConsts {
            inv: [b.inv[0], b.inv[1], b.inv[2], 0.0],
            near_oi: [
                oi(b.near_org(0), 0),
                oi(b.near_org(1), 1),
                oi(b.near_org(2), 2),
                0.0,
            ],
            far_oi: [
                oi(b.far_org(0), 0),
                oi(b.far_org(1), 1),
                oi(b.far_org(2), 2),
                0.0,
            ],
            neg: (0..3).map(|k| u32::from(b.neg[k]) << k).sum(),
            tmin: b.tmin,
            tmax: b.tmax,
            exp: b.exp,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Ray;
    use crate::simd::{dispatch, Backend, Kernel};

    struct Consts(Vec<(PreparedRay, f32)>);
    impl Kernel for Consts {
        type Output = Vec<SlabConsts>;
        #[inline(always)]
        fn run<S: Simd>(self, s: S) -> Vec<SlabConsts> {
            self.0
                .iter()
                .map(|(r, sc)| SlabConsts::new(s, r, *sc))
                .collect()
        }
    }

    #[test]
    fn simd_constants_equal_the_scalar_reference() {
        let vals = [
            0.0f32, -0.0, 1.0, -1.0, 3.5, -1e-30, 1e-30, 7e5, -2.5e-3, 1e20, 3e-39, -1e-38,
        ];
        let mut cases = Vec::new();
        for (i, &a) in vals.iter().enumerate() {
            for (j, &b) in vals.iter().enumerate() {
                let c = vals[(i * 7 + j * 3) % vals.len()];
                let dir = [a, b, c];
                if dir.iter().all(|&x| x == 0.0) {
                    continue;
                }
                let ray = Ray {
                    org: [b, c, a],
                    tmin: if i % 2 == 0 { 0.0 } else { -0.0 },
                    dir,
                    tmax: if j % 3 == 0 { f32::INFINITY } else { 2.0 },
                };
                cases.push((PreparedRay::new(&ray), [0.0, 1.0, 1e6][(i + j) % 3]));
            }
        }
        let want: Vec<SlabConsts> = cases
            .iter()
            .map(|(r, sc)| SlabConsts::from_box_ray(&BoxRay::new(r, *sc)))
            .collect();
        for b in Backend::supported() {
            let got = dispatch(b, Consts(cases.clone()));
            for ((g, w), c) in got.iter().zip(&want).zip(&cases) {
                let bits = |x: &[f32; 4]| x[..3].iter().map(|v| v.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&g.inv), bits(&w.inv), "{b} {c:?}");
                assert_eq!(bits(&g.near_oi), bits(&w.near_oi), "{b} {c:?}");
                assert_eq!(bits(&g.far_oi), bits(&w.far_oi), "{b} {c:?}");
                assert_eq!(
                    (g.neg, g.tmin.to_bits(), g.tmax.to_bits(), g.exp),
                    (w.neg, w.tmin.to_bits(), w.tmax.to_bits(), w.exp),
                    "{b} {c:?}"
                );
            }
        }
    }
}
