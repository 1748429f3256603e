//! Directions too small for their reciprocals: the power-of-two scaling that the trees'
//! box tests and DACRT's ray records share.
//!
//! A box test measures a plane's distance as `(plane − org) · (1/dir)`. For a direction of
//! ~1e-38 in a scene a few units wide the hits lie at t ~1e38, still finite, but the
//! reciprocal (and its products with the scene's coordinates) leave f32's range: every
//! slab distance became ±∞ or NaN and hits that `brute` reports were missed. Such a ray is
//! tested in units of `2^-e·t` instead: its direction is multiplied by `2^e` (exact, a
//! power of two), so every distance is the unscaled one times `2^-e`, in a range where
//! neither overflows nor is subnormal, and the bounds it is compared with are scaled the
//! same way ([`scaled_t`] rounds them outwards). Every other ray has `e = 0` and is tested
//! exactly as before; deciding that costs one compare ([`exponent`]).

use crate::geometry::Ray;

/// Directions whose largest |component| is below this are traced as their scaled twin
/// ([`ray_exponent`]).
pub const TINY: f32 = 1.0 / (1u128 << 64) as f32;

/// The `e` by which every core scales a ray whose direction is tiny: 0 unless the largest
/// |component| of `dir` is below [`TINY`] (and not 0), else the power of two that lifts it
/// into `[1, 2)`. Such a ray is tested as [`scaled_ray`] — its direction, shear and
/// interval in units of `2^-e·t` — and its hit's t comes back through [`unscaled_t`]
/// (`TriTest::finish_t`): below `TINY`, `1/dir` and the shear `1/dir[kz]` leave f32's
/// range (at ~2.9e-39 they overflow), and a hit at t ~3e38, still in range, was lost by
/// every core.
#[inline(always)]
pub fn ray_exponent(dir: [f32; 3]) -> i32 {
    // On the magnitudes' bits, which order as the magnitudes do (a NaN above every
    // number): a few integer instructions, paid by every ray and every hit.
    let bits = |x: f32| x.to_bits() & 0x7fff_ffff;
    let max = bits(dir[0]).max(bits(dir[1])).max(bits(dir[2]));
    // 0 < max < TINY in one unsigned compare.
    if max.wrapping_sub(1) < TINY.to_bits() - 1 {
        lift(f32::from_bits(max))
    } else {
        0
    }
}

/// The `e` that puts `max` (positive, below [`TINY`]) into `[1, 2)` (cold).
#[cold]
#[inline(never)]
fn lift(max: f32) -> i32 {
    // f32 subnormals are normal in f64: the exponent field is floor(log2).
    let exp = ((f64::from(max).to_bits() >> 52) & 0x7ff) as i32 - 1023;
    -exp
}

/// The twin of `r` that the cores trace when [`ray_exponent`] is `e` (not 0): the
/// direction times `2^e` (exact), `tmin` scaled rounding down, `tmax` rounding up but no
/// further than a t that comes back below `f32::MAX`, so that every hit found unscales to
/// a finite t (a hit beyond f32's range is no hit, as for every ray).
#[cold]
#[inline(never)]
pub fn scaled_ray(r: &Ray, e: i32) -> Ray {
    // Exact: MAX·2^-e is normal for every e ≤ 253 (e is at most 149 + 1).
    let cap = (f64::from(f32::MAX) * 2f64.powi(-e)) as f32;
    let tmax = scaled_t(r.tmax, e);
    Ray {
        org: r.org,
        tmin: scaled_t_down(r.tmin, e),
        dir: scaled_dir(r.dir, e),
        tmax: if tmax > cap { cap } else { tmax },
    }
}

/// The `e` for a box test of a ray whose largest |direction| component is `dir_max` and whose origin's
/// largest |coordinate| is `org_max`, in a scene of coordinates up to `scale`: 0 unless
/// the direction is smaller than about `2^-100` of the scale, else the least that lifts it
/// to that. Then `1/dir` of the largest component is at most `2^100 / scale`, and the
/// products of a box test (with room for the trees' tilt of `2^21`) stay below 2^127.
#[inline(always)]
pub fn exponent(dir_max: f32, scale: f32, org_max: f32) -> i32 {
    // In f32 on the common path (a compare): `max·2^-99` bounds `(scale + org_max)·2^-100`
    // from above without overflowing.
    const LIMIT: f32 = 1.0 / (1u128 << 99) as f32;
    if dir_max >= scale.max(org_max) * LIMIT || dir_max == 0.0 {
        return 0;
    }
    rare_exponent(dir_max, scale, org_max)
}

/// [`exponent`] where it is not 0 (cold).
#[cold]
#[inline(never)]
fn rare_exponent(dir_max: f32, scale: f32, org_max: f32) -> i32 {
    let need = (f64::from(scale) + f64::from(org_max)) * 2f64.powi(-100);
    let a = f64::from(dir_max);
    if a >= need || !need.is_finite() {
        0
    } else {
        (need / a).log2().ceil() as i32
    }
}

/// `dir` times `2^e` (exact: a power of two, the result normal).
pub fn scaled_dir(dir: [f32; 3], e: i32) -> [f32; 3] {
    let k = 2f64.powi(e);
    dir.map(|x| (f64::from(x) * k) as f32)
}

/// `t` in units of `2^-e·t`, rounded up (`t` itself for `e = 0`): a bound that a scaled
/// test must never fall short of.
#[inline(always)]
pub fn scaled_t(t: f32, e: i32) -> f32 {
    if e == 0 {
        return t;
    }
    let exact = f64::from(t) * 2f64.powi(-e);
    let x = exact as f32;
    if f64::from(x) < exact {
        x.next_up()
    } else {
        x
    }
}

/// `t` in units of `2^-e·t`, rounded down (`t` itself for `e = 0`): a lower bound that a
/// scaled test must never pass.
pub fn scaled_t_down(t: f32, e: i32) -> f32 {
    if e == 0 {
        return t;
    }
    let exact = f64::from(t) * 2f64.powi(-e);
    let x = exact as f32;
    if f64::from(x) > exact {
        x.next_down()
    } else {
        x
    }
}

/// A `t'` measured in units of `2^-e·t` back in the ray's own `t`: exact where `t'` is
/// normal (below [`scaled_ray`]'s cap it never overflows).
#[inline(always)]
pub fn unscaled_t(t: f32, e: i32) -> f32 {
    if e == 0 {
        return t;
    }
    (f64::from(t) * 2f64.powi(e)) as f32
}

/// The test's `t` of a hit of `ray` in the ray's own t: `t` itself unless the ray was
/// tested as its scaled twin ([`ray_exponent`] not 0), then scaled back and kept within
/// the ray's own `[tmin, tmax]` (the twin's interval was rounded outwards).
#[inline(always)]
pub fn unscaled_hit_t(ray: &Ray, t: f32) -> f32 {
    match ray_exponent(ray.dir) {
        0 => t,
        e => {
            let x = unscaled_t(t, e);
            // Comparisons, not f32::max/min (whose choice between +0 and -0 is unspecified).
            let x = if x < ray.tmin {
                ray.tmin
            } else if x > ray.tmax {
                ray.tmax
            } else {
                x
            };
            x + 0.0
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_directions_far_below_the_scene_are_scaled() {
        assert_eq!(exponent(1.0, 1.0, 0.0), 0);
        assert_eq!(exponent(0.0, 1.0, 0.0), 0);
        assert_eq!(exponent(1e-20, 1.0, 0.0), 0);
        let e = exponent(1e-39, 1.0, 0.0);
        assert!(e > 0);
        let d = scaled_dir([1e-39, -3e-40, 0.0], e);
        assert!(d[0].is_normal() && d[1].is_normal() && d[2] == 0.0);
        assert!(d[0] >= 2f32.powi(-101) && d[0] < 2f32.powi(-99));
        // A larger scene or a farther origin asks for more.
        assert!(exponent(1e-39, 1e10, 0.0) > e);
        assert!(exponent(1e-39, 1.0, 1e10) > e);
    }

    #[test]
    fn tiny_rays_are_lifted_into_one_two_and_come_back_finite() {
        assert_eq!(ray_exponent([1.0, 0.0, 0.0]), 0);
        assert_eq!(ray_exponent([0.0, 0.0, 0.0]), 0);
        assert_eq!(ray_exponent([f32::NAN, 0.0, 0.0]), 0);
        assert_eq!(ray_exponent([1e-19, 0.0, 0.0]), 0);
        for d in [
            [2.6e-39f32, -2.3e-40, 7e-40],
            [1e-45, 0.0, 0.0],
            [0.0, -3e-20, 1e-21],
        ] {
            let e = ray_exponent(d);
            assert!(e > 0, "{d:?}");
            let r = scaled_ray(
                &Ray {
                    org: [0.0; 3],
                    tmin: 1e-30,
                    dir: d,
                    tmax: f32::INFINITY,
                },
                e,
            );
            let max = r.dir.iter().fold(0.0f32, |m, x| m.max(x.abs()));
            assert!((1.0..2.0).contains(&max), "{d:?} → {:?}", r.dir);
            assert_eq!(unscaled_t(r.tmax, e), f32::MAX);
            assert!(unscaled_t(r.tmin, e) <= 1e-30);
        }
    }

    #[test]
    fn scaled_bounds_round_outwards_and_come_back_exactly() {
        let t = 1.0f32 + f32::EPSILON;
        for e in [1, 30, 100, 140] {
            let up = scaled_t(t, e);
            let down = scaled_t_down(t, e);
            assert!(f64::from(up) >= f64::from(t) * 2f64.powi(-e));
            assert!(f64::from(down) <= f64::from(t) * 2f64.powi(-e));
            if up.is_normal() {
                assert_eq!(unscaled_t(up, e), t);
            }
        }
        assert_eq!(scaled_t(f32::INFINITY, 40), f32::INFINITY);
        assert_eq!(unscaled_t(f32::MAX, 3), f32::INFINITY);
    }
}
