//! 4-lane helpers for the BVH builder's hot loops (binning), which work on boxes stored
//! as `[f32; 4]` (x, y, z, junk). SSE2 is part of the x86_64 baseline, so no dispatch is
//! needed; elsewhere the portable form runs.
//!
//! The fourth lane of a builder's box carries an id's or a scratch word's bits, which read
//! as f32 are mostly subnormal. Arithmetic on a subnormal operand takes a microcode assist
//! on Intel cores (about a hundred cycles; AMD's Zen handles it at full speed): with the
//! junk lane multiplied, a `sah` build ran five times slower on a Xeon than on Zen 3. So
//! the arithmetic helpers clear that lane with a bit mask before they compute; min/max
//! take no assist and pass it through.

/// The bins of a box's centroid along x, y and z: per lane
/// `c = lo·0.5 + hi·0.5`, `f = min(max((c − map_lo)·scale − 0.5, 0), last)` with
/// `max(a, b) = if a > b { a } else { b }` and `min(a, b) = if a < b { a } else { b }`
/// (NaN gives `b`), then the integer in the low mantissa bits of `f + 2^23`, masked by
/// `mask`. Written out in SSE2 because the compiler's vectorisation of the portable form
/// mixed vector and scalar code with a branch per lane; both forms do the same IEEE
/// operations in the same order, so their results are identical.
#[inline(always)]
pub fn centroid_bins(
    lo: &[f32; 4],
    hi: &[f32; 4],
    map_lo: &[f32; 4],
    scale: &[f32; 4],
    last: f32,
    mask: u32,
) -> [u32; 3] {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: SSE2 is enabled on every x86_64 target; the loads read whole `[f32; 4]`
    // arrays through references (unaligned loads, so any alignment is fine).
    unsafe {
        use std::arch::x86_64::*;
        let half = _mm_set1_ps(0.5);
        let xyz = xyz_mask();
        let c = _mm_add_ps(
            _mm_mul_ps(_mm_and_ps(_mm_loadu_ps(lo.as_ptr()), xyz), half),
            _mm_mul_ps(_mm_and_ps(_mm_loadu_ps(hi.as_ptr()), xyz), half),
        );
        let f = _mm_mul_ps(
            _mm_sub_ps(c, _mm_loadu_ps(map_lo.as_ptr())),
            _mm_loadu_ps(scale.as_ptr()),
        );
        // MAXPS/MINPS return the second operand unless the first is strictly greater
        // (smaller): exactly the `if` forms above, NaN included.
        let f = _mm_min_ps(
            _mm_max_ps(_mm_sub_ps(f, half), _mm_setzero_ps()),
            _mm_set1_ps(last),
        );
        let k = _mm_and_si128(
            _mm_castps_si128(_mm_add_ps(f, _mm_set1_ps(8_388_608.0))),
            _mm_set1_epi32(mask as i32),
        );
        [
            _mm_cvtsi128_si32(k) as u32,
            _mm_cvtsi128_si32(_mm_srli_si128::<4>(k)) as u32,
            _mm_cvtsi128_si32(_mm_srli_si128::<8>(k)) as u32,
        ]
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        std::array::from_fn(|j| {
            let c = lo[j] * 0.5 + hi[j] * 0.5;
            let f = (c - map_lo[j]) * scale[j] - 0.5;
            let f = if f > 0.0 { f } else { 0.0 };
            let f = if f < last { f } else { last };
            (f + 8_388_608.0).to_bits() & mask
        })
    }
}

/// Lane-wise `if a < b { a } else { b }` (MINPS exactly, NaN gives `b`).
#[inline(always)]
pub fn min4(a: &[f32; 4], b: &[f32; 4]) -> [f32; 4] {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: SSE2 is enabled on every x86_64 target; loads and the store go through
    // references to whole `[f32; 4]` arrays, unaligned.
    unsafe {
        use std::arch::x86_64::*;
        let mut out = [0.0f32; 4];
        _mm_storeu_ps(
            out.as_mut_ptr(),
            _mm_min_ps(_mm_loadu_ps(a.as_ptr()), _mm_loadu_ps(b.as_ptr())),
        );
        out
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        std::array::from_fn(|k| if a[k] < b[k] { a[k] } else { b[k] })
    }
}

/// Lane-wise `if a > b { a } else { b }` (MAXPS exactly, NaN gives `b`).
#[inline(always)]
pub fn max4(a: &[f32; 4], b: &[f32; 4]) -> [f32; 4] {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: as in `min4`.
    unsafe {
        use std::arch::x86_64::*;
        let mut out = [0.0f32; 4];
        _mm_storeu_ps(
            out.as_mut_ptr(),
            _mm_max_ps(_mm_loadu_ps(a.as_ptr()), _mm_loadu_ps(b.as_ptr())),
        );
        out
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        std::array::from_fn(|k| if a[k] > b[k] { a[k] } else { b[k] })
    }
}

/// Lane-wise `lo·0.5 + hi·0.5` (a box's centroid, without overflow for finite boxes).
#[inline(always)]
pub fn mid4(lo: &[f32; 4], hi: &[f32; 4]) -> [f32; 4] {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: as in `min4`.
    unsafe {
        use std::arch::x86_64::*;
        let half = _mm_set1_ps(0.5);
        let xyz = xyz_mask();
        let mut out = [0.0f32; 4];
        _mm_storeu_ps(
            out.as_mut_ptr(),
            _mm_add_ps(
                _mm_mul_ps(_mm_and_ps(_mm_loadu_ps(lo.as_ptr()), xyz), half),
                _mm_mul_ps(_mm_and_ps(_mm_loadu_ps(hi.as_ptr()), xyz), half),
            ),
        );
        out
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let mut m: [f32; 4] = std::array::from_fn(|k| lo[k] * 0.5 + hi[k] * 0.5);
        m[3] = 0.0;
        m
    }
}

/// Lane-wise `hi − lo` in lanes 0, 1 and 2 (a box's extent along x, y and z) and 0 in lane 3,
/// whatever the junk lanes hold.
#[inline(always)]
pub fn extent_xyz(lo: &[f32; 4], hi: &[f32; 4]) -> [f32; 4] {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: as in `min4`.
    unsafe {
        use std::arch::x86_64::*;
        let xyz = xyz_mask();
        let mut out = [0.0f32; 4];
        _mm_storeu_ps(
            out.as_mut_ptr(),
            _mm_sub_ps(
                _mm_and_ps(_mm_loadu_ps(hi.as_ptr()), xyz),
                _mm_and_ps(_mm_loadu_ps(lo.as_ptr()), xyz),
            ),
        );
        out
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        [hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2], 0.0]
    }
}

/// All bits set in lanes 0, 1 and 2 (x, y, z), none in lane 3: ANDed with a box's corner, it
/// leaves the coordinates and a zero where the junk lane was.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn xyz_mask() -> std::arch::x86_64::__m128 {
    // SAFETY: SSE2 is enabled on every x86_64 target; these only build a register.
    unsafe {
        use std::arch::x86_64::*;
        _mm_castsi128_ps(_mm_set_epi32(0, -1, -1, -1))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The portable form, lane by lane.
    fn reference(lo: &[f32; 4], hi: &[f32; 4], map_lo: &[f32; 4], scale: &[f32; 4]) -> [u32; 3] {
        std::array::from_fn(|j| {
            let c = lo[j] * 0.5 + hi[j] * 0.5;
            let f = (c - map_lo[j]) * scale[j] - 0.5;
            let f = if f > 0.0 { f } else { 0.0 };
            let f = if f < 31.0 { f } else { 31.0 };
            (f + 8_388_608.0).to_bits() & 31
        })
    }

    #[test]
    fn bins_clamp_and_take_nan_to_zero() {
        let z = [0.0f32; 4];
        let scale = [1.0, 3.0, 4.0, 0.0];
        let k = centroid_bins(
            &[3.0, 1.0, 100.0, 0.0],
            &[5.5, 2.0, 100.0, 0.0],
            &z,
            &scale,
            31.0,
            31,
        );
        // Centroids 4.25, 1.5, 100: bins 4, 4 (4.5 − 0.5 = 4 exactly), clamped to 31.
        assert_eq!(k, [4, 4, 31]);
        let k = centroid_bins(
            &[f32::NAN, -5.0, 0.0, 0.0],
            &[f32::NAN, -5.0, 0.0, 0.0],
            &z,
            &scale,
            31.0,
            31,
        );
        assert_eq!(k, [0, 0, 0]);
    }

    #[test]
    fn bins_match_the_portable_form() {
        let map_lo = [-1.0, 0.25, -1e3, 0.0];
        let scale = [31.0 / 2.0, 7.3, 0.0151, 0.0];
        let mut x = 0.123f32;
        for _ in 0..2000 {
            let lo: [f32; 4] = std::array::from_fn(|k| {
                x = (x * 3.7 + 0.31).fract();
                (x - 0.5) * [4.0, 8.0, 3e3, 1.0][k]
            });
            let hi: [f32; 4] = std::array::from_fn(|k| lo[k] + x * 0.1);
            assert_eq!(
                centroid_bins(&lo, &hi, &map_lo, &scale, 31.0, 31),
                reference(&lo, &hi, &map_lo, &scale)
            );
        }
    }

    #[test]
    fn min_max_keep_the_second_operand_on_nan() {
        let a = [1.0, f32::NAN, 3.0, -0.0];
        let b = [2.0, 5.0, f32::NAN, 0.0];
        assert_eq!(min4(&a, &b)[..2], [1.0, 5.0]);
        assert!(min4(&a, &b)[2].is_nan());
        assert_eq!(max4(&a, &b)[..2], [2.0, 5.0]);
        assert!(max4(&a, &b)[2].is_nan());
        assert_eq!(
            mid4(&[1.0, 2.0, -4.0, 0.0], &[3.0, 2.0, 4.0, 0.0]),
            [2.0, 2.0, 0.0, 0.0]
        );
    }

    /// The junk lane (an id's bits: a subnormal f32, or a NaN pattern) changes nothing in
    /// the three coordinates, and the arithmetic helpers leave 0 there.
    #[test]
    fn the_junk_lane_is_ignored() {
        let map_lo = [-1.0, 0.25, -2.0, 0.0];
        let scale = [7.0, 3.0, 5.0, 0.0];
        for junk in [
            f32::from_bits(12345),
            f32::from_bits(0x7fc0_0001),
            -1e30,
            0.0,
        ] {
            let lo = [0.5, 1.0, -1.5, junk];
            let hi = [1.5, 2.0, 0.5, junk];
            let clean = |v: [f32; 4]| [v[0], v[1], v[2], 0.0];
            assert_eq!(
                centroid_bins(&lo, &hi, &map_lo, &scale, 31.0, 31),
                centroid_bins(&clean(lo), &clean(hi), &map_lo, &scale, 31.0, 31)
            );
            assert_eq!(mid4(&lo, &hi), [1.0, 1.5, -0.5, 0.0]);
            assert_eq!(extent_xyz(&lo, &hi), [1.0, 1.0, 2.0, 0.0]);
        }
    }
}
