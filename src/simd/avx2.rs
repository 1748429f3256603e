//! The AVX2+FMA backend: 8-wide vectors are one `__m256`/`__m256i`; the 4-wide ones are the
//! SSE backend's (compiled VEX-encoded inside AVX2 kernels).
//!
//! Soundness: as in `sse.rs`, vectors have private fields and only an [`Avx2`] token (made
//! after detecting AVX2 *and* FMA) creates them, so their methods may run AVX2/FMA
//! instructions; the `x!` macro carries that `// SAFETY:` argument.
#![allow(unused_unsafe)]

use super::sse::{self, x, F4, I4, M4};
use super::{FloatV, IntV, Kernel, MaskV, Select, Simd};
use core::arch::x86_64::*;
use std::ops::{Add, BitAnd, BitOr, BitXor, Div, Mul, Neg, Not, Sub};

/// The AVX2+FMA backend's token.
#[derive(Clone, Copy, Debug)]
pub struct Avx2(());

impl Avx2 {
    /// The token, if this CPU supports AVX2 and FMA (and the OS saves the AVX state, which
    /// the detection macro checks).
    #[inline]
    pub fn new() -> Option<Avx2> {
        if is_x86_feature_detected!("avx2")
            && is_x86_feature_detected!("fma")
            && is_x86_feature_detected!("sse4.1")
        {
            Some(Avx2(()))
        } else {
            None
        }
    }
}

#[target_feature(enable = "avx2,fma")]
unsafe fn entry<K: Kernel>(s: Avx2, k: K) -> K::Output {
    k.run(s)
}

/// Runs `k` compiled for AVX2+FMA.
pub(super) fn enter<K: Kernel>(s: Avx2, k: K) -> K::Output {
    // SAFETY: `s` exists, so AVX2 and FMA were detected on this CPU.
    unsafe { entry(s, k) }
}

/// 8 × f32 in an `__m256`.
#[derive(Clone, Copy)]
pub struct F8(__m256);
/// 8 × i32 in an `__m256i`.
#[derive(Clone, Copy)]
pub struct I8(__m256i);
/// 8-lane mask: all-ones or all-zeros lanes in an `__m256`.
#[derive(Clone, Copy)]
pub struct M8(__m256);

impl std::fmt::Debug for F8 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.to_array().fmt(f)
    }
}
impl std::fmt::Debug for I8 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.to_array().fmt(f)
    }
}
impl std::fmt::Debug for M8 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "M8({:08b})", self.bitmask())
    }
}

#[inline(always)]
fn ones() -> __m256i {
    x!(_mm256_set1_epi32(-1))
}

#[inline(always)]
fn f8_splat(v: f32) -> F8 {
    F8(x!(_mm256_set1_ps(v)))
}

impl Simd for Avx2 {
    const BACKEND: super::Backend = super::Backend::Avx2;
    type F8 = F8;
    type I8 = I8;
    type M8 = M8;
    type F4 = F4;
    type I4 = I4;
    type M4 = M4;

    #[inline(always)]
    fn splat_f8(self, v: f32) -> F8 {
        f8_splat(v)
    }
    #[inline(always)]
    fn load_f8(self, a: &[f32; 8]) -> F8 {
        F8(x!(_mm256_loadu_ps(a.as_ptr())))
    }
    #[inline(always)]
    fn splat_i8(self, v: i32) -> I8 {
        I8(x!(_mm256_set1_epi32(v)))
    }
    #[inline(always)]
    fn load_i8(self, a: &[i32; 8]) -> I8 {
        I8(x!(_mm256_loadu_si256(a.as_ptr().cast())))
    }
    #[inline(always)]
    fn mask8(self, bits: u32) -> M8 {
        let lanes = x!(_mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128));
        let b = x!(_mm256_set1_epi32(bits as i32));
        M8(x!(_mm256_castsi256_ps(_mm256_cmpeq_epi32(
            _mm256_and_si256(b, lanes),
            lanes
        ))))
    }
    #[inline(always)]
    fn splat_f4(self, v: f32) -> F4 {
        sse::f4_splat(v)
    }
    #[inline(always)]
    fn load_f4(self, a: &[f32; 4]) -> F4 {
        sse::f4_load(a)
    }
    #[inline(always)]
    fn splat_i4(self, v: i32) -> I4 {
        sse::i4_splat(v)
    }
    #[inline(always)]
    fn load_i4(self, a: &[i32; 4]) -> I4 {
        sse::i4_load(a)
    }
    #[inline(always)]
    fn mask4(self, bits: u32) -> M4 {
        sse::m4_from_bits(bits)
    }
}

macro_rules! op {
    ($ty:ident, $tr:ident, $f:ident, $intr:ident) => {
        impl $tr for $ty {
            type Output = Self;
            #[inline(always)]
            fn $f(self, o: Self) -> Self {
                $ty(x!($intr(self.0, o.0)))
            }
        }
    };
}
op!(F8, Add, add, _mm256_add_ps);
op!(F8, Sub, sub, _mm256_sub_ps);
op!(F8, Mul, mul, _mm256_mul_ps);
op!(F8, Div, div, _mm256_div_ps);
op!(I8, Add, add, _mm256_add_epi32);
op!(I8, Sub, sub, _mm256_sub_epi32);
op!(I8, Mul, mul, _mm256_mullo_epi32);
op!(I8, BitAnd, bitand, _mm256_and_si256);
op!(I8, BitOr, bitor, _mm256_or_si256);
op!(I8, BitXor, bitxor, _mm256_xor_si256);
op!(M8, BitAnd, bitand, _mm256_and_ps);
op!(M8, BitOr, bitor, _mm256_or_ps);
op!(M8, BitXor, bitxor, _mm256_xor_ps);

impl Neg for F8 {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        F8(x!(_mm256_xor_ps(self.0, _mm256_set1_ps(-0.0))))
    }
}
impl Not for I8 {
    type Output = Self;
    #[inline(always)]
    fn not(self) -> Self {
        I8(x!(_mm256_xor_si256(self.0, ones())))
    }
}
impl Not for M8 {
    type Output = Self;
    #[inline(always)]
    fn not(self) -> Self {
        M8(x!(_mm256_xor_ps(self.0, _mm256_castsi256_ps(ones()))))
    }
}

impl Select<F8> for M8 {
    #[inline(always)]
    fn select(self, a: F8, b: F8) -> F8 {
        F8(x!(_mm256_blendv_ps(b.0, a.0, self.0)))
    }
}
impl Select<I8> for M8 {
    #[inline(always)]
    fn select(self, a: I8, b: I8) -> I8 {
        I8(x!(_mm256_castps_si256(_mm256_blendv_ps(
            _mm256_castsi256_ps(b.0),
            _mm256_castsi256_ps(a.0),
            self.0
        ))))
    }
}

impl MaskV for M8 {
    const LANES: usize = 8;
    #[inline(always)]
    fn andnot(self, o: Self) -> Self {
        M8(x!(_mm256_andnot_ps(o.0, self.0)))
    }
    #[inline(always)]
    fn any(self) -> bool {
        x!(_mm256_testz_ps(self.0, self.0)) == 0
    }
    #[inline(always)]
    fn all(self) -> bool {
        self.bitmask() == 0xff
    }
    #[inline(always)]
    fn none(self) -> bool {
        x!(_mm256_testz_ps(self.0, self.0)) != 0
    }
    #[inline(always)]
    fn bitmask(self) -> u32 {
        x!(_mm256_movemask_ps(self.0)) as u32
    }
}

#[inline(always)]
fn halves(v: __m256) -> (F4, F4) {
    (
        F4(x!(_mm256_castps256_ps128(v))),
        F4(x!(_mm256_extractf128_ps::<1>(v))),
    )
}

#[inline(always)]
fn halves_i(v: __m256i) -> (I4, I4) {
    (
        I4(x!(_mm256_castsi256_si128(v))),
        I4(x!(_mm256_extracti128_si256::<1>(v))),
    )
}

/// Permutation indices for `compress` (low 3 bits of each lane are used).
#[inline(always)]
fn compress_idx(m: M8) -> __m256i {
    let packed = super::COMPRESS8[m.bitmask() as usize];
    x!(_mm256_srlv_epi32(
        _mm256_set1_epi32(packed as i32),
        _mm256_setr_epi32(0, 3, 6, 9, 12, 15, 18, 21)
    ))
}

impl FloatV for F8 {
    type Mask = M8;
    type Int = I8;
    type Array = [f32; 8];
    const LANES: usize = 8;

    #[inline(always)]
    fn to_array(self) -> [f32; 8] {
        let mut a = [0.0; 8];
        x!(_mm256_storeu_ps(a.as_mut_ptr(), self.0));
        a
    }
    #[inline(always)]
    fn mul_add(self, b: Self, c: Self) -> Self {
        F8(x!(_mm256_fmadd_ps(self.0, b.0, c.0)))
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        F8(x!(_mm256_min_ps(self.0, o.0)))
    }
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        F8(x!(_mm256_max_ps(self.0, o.0)))
    }
    #[inline(always)]
    fn abs(self) -> Self {
        F8(x!(_mm256_andnot_ps(_mm256_set1_ps(-0.0), self.0)))
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        F8(x!(_mm256_sqrt_ps(self.0)))
    }
    #[inline(always)]
    fn recip(self) -> Self {
        f8_splat(1.0) / self
    }
    #[inline(always)]
    fn recip_fast(self) -> Self {
        let r = x!(_mm256_rcp_ps(self.0));
        let e = x!(_mm256_fnmadd_ps(self.0, r, _mm256_set1_ps(1.0)));
        F8(x!(_mm256_fmadd_ps(r, e, r)))
    }
    #[inline(always)]
    fn lt(self, o: Self) -> M8 {
        M8(x!(_mm256_cmp_ps::<_CMP_LT_OQ>(self.0, o.0)))
    }
    #[inline(always)]
    fn le(self, o: Self) -> M8 {
        M8(x!(_mm256_cmp_ps::<_CMP_LE_OQ>(self.0, o.0)))
    }
    #[inline(always)]
    fn gt(self, o: Self) -> M8 {
        M8(x!(_mm256_cmp_ps::<_CMP_GT_OQ>(self.0, o.0)))
    }
    #[inline(always)]
    fn ge(self, o: Self) -> M8 {
        M8(x!(_mm256_cmp_ps::<_CMP_GE_OQ>(self.0, o.0)))
    }
    #[inline(always)]
    fn eq(self, o: Self) -> M8 {
        M8(x!(_mm256_cmp_ps::<_CMP_EQ_OQ>(self.0, o.0)))
    }
    #[inline(always)]
    fn ne(self, o: Self) -> M8 {
        M8(x!(_mm256_cmp_ps::<_CMP_NEQ_UQ>(self.0, o.0)))
    }
    #[inline(always)]
    fn hmin(self) -> f32 {
        let (lo, hi) = halves(self.0);
        lo.min(hi).hmin()
    }
    #[inline(always)]
    fn hmax(self) -> f32 {
        let (lo, hi) = halves(self.0);
        lo.max(hi).hmax()
    }
    #[inline(always)]
    fn to_bits(self) -> I8 {
        I8(x!(_mm256_castps_si256(self.0)))
    }
    #[inline(always)]
    fn to_int_trunc(self) -> I8 {
        I8(x!(_mm256_cvttps_epi32(self.0)))
    }
    #[inline(always)]
    fn permute(self, idx: I8) -> Self {
        F8(x!(_mm256_permutevar8x32_ps(self.0, idx.0)))
    }
    #[inline(always)]
    fn compress(self, m: M8) -> Self {
        F8(x!(_mm256_permutevar8x32_ps(self.0, compress_idx(m))))
    }
}

impl IntV for I8 {
    type Mask = M8;
    type Float = F8;
    type Array = [i32; 8];
    const LANES: usize = 8;

    #[inline(always)]
    fn to_array(self) -> [i32; 8] {
        let mut a = [0; 8];
        x!(_mm256_storeu_si256(a.as_mut_ptr().cast(), self.0));
        a
    }
    #[inline(always)]
    fn andnot(self, o: Self) -> Self {
        I8(x!(_mm256_andnot_si256(o.0, self.0)))
    }
    #[inline(always)]
    fn shl<const N: i32>(self) -> Self {
        I8(x!(_mm256_slli_epi32::<N>(self.0)))
    }
    #[inline(always)]
    fn shr<const N: i32>(self) -> Self {
        I8(x!(_mm256_srli_epi32::<N>(self.0)))
    }
    #[inline(always)]
    fn sar<const N: i32>(self) -> Self {
        I8(x!(_mm256_srai_epi32::<N>(self.0)))
    }
    #[inline(always)]
    fn eq(self, o: Self) -> M8 {
        M8(x!(_mm256_castsi256_ps(_mm256_cmpeq_epi32(self.0, o.0))))
    }
    #[inline(always)]
    fn gt(self, o: Self) -> M8 {
        M8(x!(_mm256_castsi256_ps(_mm256_cmpgt_epi32(self.0, o.0))))
    }
    #[inline(always)]
    fn lt(self, o: Self) -> M8 {
        M8(x!(_mm256_castsi256_ps(_mm256_cmpgt_epi32(o.0, self.0))))
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        I8(x!(_mm256_min_epi32(self.0, o.0)))
    }
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        I8(x!(_mm256_max_epi32(self.0, o.0)))
    }
    #[inline(always)]
    fn hmin(self) -> i32 {
        let (lo, hi) = halves_i(self.0);
        lo.min(hi).hmin()
    }
    #[inline(always)]
    fn to_float_bits(self) -> F8 {
        F8(x!(_mm256_castsi256_ps(self.0)))
    }
    #[inline(always)]
    fn to_float(self) -> F8 {
        F8(x!(_mm256_cvtepi32_ps(self.0)))
    }
    #[inline(always)]
    fn permute(self, idx: Self) -> Self {
        I8(x!(_mm256_permutevar8x32_epi32(self.0, idx.0)))
    }
    #[inline(always)]
    fn compress(self, m: M8) -> Self {
        I8(x!(_mm256_permutevar8x32_epi32(self.0, compress_idx(m))))
    }
}
