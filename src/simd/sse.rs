//! The SSE4.1 backend: 4-wide vectors are one `__m128`, 8-wide vectors a pair of them.
//!
//! The 4-wide types here are also the AVX2 backend's 4-wide types (AVX2 implies SSE4.1, and
//! inside an AVX2 kernel they compile to VEX-encoded instructions).
//!
//! Soundness: every vector type below has private fields and is only created by a [`Sse`] or
//! [`super::Avx2`] token (or from other vectors), and tokens are only created after
//! `is_x86_feature_detected!` confirmed SSE4.1. Holding a value therefore proves that the
//! intrinsics in its methods may run; that single argument is the `// SAFETY:` of the
//! `x!` macro, which wraps each intrinsic call of this file.
// Older compilers (the crate's rust-version) require `unsafe` around every intrinsic; newer
// ones consider the SSE2 baseline ones safe and would flag those blocks as unused.
#![allow(unused_unsafe)]

use super::{FloatV, IntV, Kernel, MaskV, Select, Simd};
use core::arch::x86_64::*;
use std::ops::{Add, BitAnd, BitOr, BitXor, Div, Mul, Neg, Not, Sub};

/// Runs an intrinsic expression.
macro_rules! x {
    ($e:expr) => {
        // SAFETY: the operands are vectors of this module (or the AVX2 one), which only exist
        // once a token proved the CPU supports SSE4.1 (resp. AVX2+FMA), see the module docs;
        // pointer arguments come from references to arrays of the loaded/stored length.
        unsafe { $e }
    };
}
pub(super) use x;

/// The SSE4.1 backend's token.
#[derive(Clone, Copy, Debug)]
pub struct Sse(());

impl Sse {
    /// The token, if this CPU supports SSE4.1.
    #[inline]
    pub fn new() -> Option<Sse> {
        if is_x86_feature_detected!("sse4.1") {
            Some(Sse(()))
        } else {
            None
        }
    }
}

#[target_feature(enable = "sse4.1")]
unsafe fn entry<K: Kernel>(s: Sse, k: K) -> K::Output {
    k.run(s)
}

/// Runs `k` compiled for SSE4.1.
pub(super) fn enter<K: Kernel>(s: Sse, k: K) -> K::Output {
    // SAFETY: `s` exists, so SSE4.1 was detected on this CPU.
    unsafe { entry(s, k) }
}

/// 4 × f32 in an `__m128`.
#[derive(Clone, Copy)]
pub struct F4(pub(super) __m128);
/// 4 × i32 in an `__m128i`.
#[derive(Clone, Copy)]
pub struct I4(pub(super) __m128i);
/// 4-lane mask: all-ones or all-zeros lanes in an `__m128`.
#[derive(Clone, Copy)]
pub struct M4(pub(super) __m128);
/// 8 × f32 as two halves (lanes 0–3, 4–7).
#[derive(Clone, Copy)]
pub struct F8(F4, F4);
/// 8 × i32 as two halves.
#[derive(Clone, Copy)]
pub struct I8(I4, I4);
/// 8-lane mask as two halves.
#[derive(Clone, Copy)]
pub struct M8(M4, M4);

impl std::fmt::Debug for F4 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.to_array().fmt(f)
    }
}
impl std::fmt::Debug for I4 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        self.to_array().fmt(f)
    }
}
impl std::fmt::Debug for M4 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "M4({:04b})", self.bitmask())
    }
}
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

// Constructors shared with the AVX2 backend (which reuses the 4-wide types).

#[inline(always)]
pub(super) fn f4_splat(x: f32) -> F4 {
    F4(x!(_mm_set1_ps(x)))
}
#[inline(always)]
pub(super) fn f4_load(a: &[f32; 4]) -> F4 {
    F4(x!(_mm_loadu_ps(a.as_ptr())))
}
#[inline(always)]
pub(super) fn i4_splat(x: i32) -> I4 {
    I4(x!(_mm_set1_epi32(x)))
}
#[inline(always)]
pub(super) fn i4_load(a: &[i32; 4]) -> I4 {
    I4(x!(_mm_loadu_si128(a.as_ptr().cast())))
}
#[inline(always)]
pub(super) fn m4_from_bits(bits: u32) -> M4 {
    let lanes = x!(_mm_setr_epi32(1, 2, 4, 8));
    let b = x!(_mm_set1_epi32(bits as i32));
    M4(x!(_mm_castsi128_ps(_mm_cmpeq_epi32(
        _mm_and_si128(b, lanes),
        lanes
    ))))
}
#[inline(always)]
fn ones4() -> __m128i {
    x!(_mm_set1_epi32(-1))
}

/// pshufb controls for `compress` on 4 lanes, indexed by the mask bits.
const COMPRESS4: [[u8; 16]; 16] = {
    let mut lut = [[0u8; 16]; 16];
    let mut m = 0;
    while m < 16 {
        let mut pos = 0;
        let mut pass = 0;
        while pass < 2 {
            let mut i = 0;
            while i < 4 {
                if ((m >> i) & 1 == 1) == (pass == 0) {
                    let mut b = 0;
                    while b < 4 {
                        lut[m][pos * 4 + b] = (i * 4 + b) as u8;
                        b += 1;
                    }
                    pos += 1;
                }
                i += 1;
            }
            pass += 1;
        }
        m += 1;
    }
    lut
};

/// pshufb control that moves lane `idx[i] & 3` to lane i.
#[inline(always)]
fn lane_control4(idx: __m128i) -> __m128i {
    let i = x!(_mm_and_si128(idx, _mm_set1_epi32(3)));
    x!(_mm_add_epi32(
        _mm_mullo_epi32(i, _mm_set1_epi32(0x0404_0404)),
        _mm_set1_epi32(0x0302_0100)
    ))
}

impl Simd for Sse {
    const BACKEND: super::Backend = super::Backend::Sse;
    type F8 = F8;
    type I8 = I8;
    type M8 = M8;
    type F4 = F4;
    type I4 = I4;
    type M4 = M4;

    #[inline(always)]
    fn splat_f8(self, x: f32) -> F8 {
        let h = f4_splat(x);
        F8(h, h)
    }
    #[inline(always)]
    fn load_f8(self, a: &[f32; 8]) -> F8 {
        F8(
            f4_load(a[..4].try_into().unwrap()),
            f4_load(a[4..].try_into().unwrap()),
        )
    }
    #[inline(always)]
    fn splat_i8(self, x: i32) -> I8 {
        let h = i4_splat(x);
        I8(h, h)
    }
    #[inline(always)]
    fn load_i8(self, a: &[i32; 8]) -> I8 {
        I8(
            i4_load(a[..4].try_into().unwrap()),
            i4_load(a[4..].try_into().unwrap()),
        )
    }
    #[inline(always)]
    fn mask8(self, bits: u32) -> M8 {
        M8(m4_from_bits(bits), m4_from_bits(bits >> 4))
    }
    #[inline(always)]
    fn splat_f4(self, x: f32) -> F4 {
        f4_splat(x)
    }
    #[inline(always)]
    fn load_f4(self, a: &[f32; 4]) -> F4 {
        f4_load(a)
    }
    #[inline(always)]
    fn splat_i4(self, x: i32) -> I4 {
        i4_splat(x)
    }
    #[inline(always)]
    fn load_i4(self, a: &[i32; 4]) -> I4 {
        i4_load(a)
    }
    #[inline(always)]
    fn mask4(self, bits: u32) -> M4 {
        m4_from_bits(bits)
    }
}

macro_rules! op4 {
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
op4!(F4, Add, add, _mm_add_ps);
op4!(F4, Sub, sub, _mm_sub_ps);
op4!(F4, Mul, mul, _mm_mul_ps);
op4!(F4, Div, div, _mm_div_ps);
op4!(I4, Add, add, _mm_add_epi32);
op4!(I4, Sub, sub, _mm_sub_epi32);
op4!(I4, Mul, mul, _mm_mullo_epi32);
op4!(I4, BitAnd, bitand, _mm_and_si128);
op4!(I4, BitOr, bitor, _mm_or_si128);
op4!(I4, BitXor, bitxor, _mm_xor_si128);
op4!(M4, BitAnd, bitand, _mm_and_ps);
op4!(M4, BitOr, bitor, _mm_or_ps);
op4!(M4, BitXor, bitxor, _mm_xor_ps);

impl Neg for F4 {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        F4(x!(_mm_xor_ps(self.0, _mm_set1_ps(-0.0))))
    }
}
impl Not for I4 {
    type Output = Self;
    #[inline(always)]
    fn not(self) -> Self {
        I4(x!(_mm_xor_si128(self.0, ones4())))
    }
}
impl Not for M4 {
    type Output = Self;
    #[inline(always)]
    fn not(self) -> Self {
        M4(x!(_mm_xor_ps(self.0, _mm_castsi128_ps(ones4()))))
    }
}

impl Select<F4> for M4 {
    #[inline(always)]
    fn select(self, a: F4, b: F4) -> F4 {
        F4(x!(_mm_blendv_ps(b.0, a.0, self.0)))
    }
}
impl Select<I4> for M4 {
    #[inline(always)]
    fn select(self, a: I4, b: I4) -> I4 {
        I4(x!(_mm_castps_si128(_mm_blendv_ps(
            _mm_castsi128_ps(b.0),
            _mm_castsi128_ps(a.0),
            self.0
        ))))
    }
}

impl MaskV for M4 {
    const LANES: usize = 4;
    #[inline(always)]
    fn andnot(self, o: Self) -> Self {
        M4(x!(_mm_andnot_ps(o.0, self.0)))
    }
    #[inline(always)]
    fn any(self) -> bool {
        self.bitmask() != 0
    }
    #[inline(always)]
    fn all(self) -> bool {
        self.bitmask() == 0xf
    }
    #[inline(always)]
    fn none(self) -> bool {
        self.bitmask() == 0
    }
    #[inline(always)]
    fn bitmask(self) -> u32 {
        x!(_mm_movemask_ps(self.0)) as u32
    }
}

impl FloatV for F4 {
    type Mask = M4;
    type Int = I4;
    type Array = [f32; 4];
    const LANES: usize = 4;

    #[inline(always)]
    fn to_array(self) -> [f32; 4] {
        let mut a = [0.0; 4];
        x!(_mm_storeu_ps(a.as_mut_ptr(), self.0));
        a
    }
    #[inline(always)]
    fn mul_add(self, b: Self, c: Self) -> Self {
        self * b + c
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        F4(x!(_mm_min_ps(self.0, o.0)))
    }
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        F4(x!(_mm_max_ps(self.0, o.0)))
    }
    #[inline(always)]
    fn abs(self) -> Self {
        F4(x!(_mm_andnot_ps(_mm_set1_ps(-0.0), self.0)))
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        F4(x!(_mm_sqrt_ps(self.0)))
    }
    #[inline(always)]
    fn recip(self) -> Self {
        f4_splat(1.0) / self
    }
    #[inline(always)]
    fn recip_fast(self) -> Self {
        let r = F4(x!(_mm_rcp_ps(self.0)));
        r * (f4_splat(2.0) - self * r)
    }
    #[inline(always)]
    fn lt(self, o: Self) -> M4 {
        M4(x!(_mm_cmplt_ps(self.0, o.0)))
    }
    #[inline(always)]
    fn le(self, o: Self) -> M4 {
        M4(x!(_mm_cmple_ps(self.0, o.0)))
    }
    #[inline(always)]
    fn gt(self, o: Self) -> M4 {
        M4(x!(_mm_cmpgt_ps(self.0, o.0)))
    }
    #[inline(always)]
    fn ge(self, o: Self) -> M4 {
        M4(x!(_mm_cmpge_ps(self.0, o.0)))
    }
    #[inline(always)]
    fn eq(self, o: Self) -> M4 {
        M4(x!(_mm_cmpeq_ps(self.0, o.0)))
    }
    #[inline(always)]
    fn ne(self, o: Self) -> M4 {
        M4(x!(_mm_cmpneq_ps(self.0, o.0)))
    }
    #[inline(always)]
    fn hmin(self) -> f32 {
        let m = x!(_mm_min_ps(self.0, _mm_movehl_ps(self.0, self.0)));
        x!(_mm_cvtss_f32(_mm_min_ss(m, _mm_shuffle_ps::<1>(m, m))))
    }
    #[inline(always)]
    fn hmax(self) -> f32 {
        let m = x!(_mm_max_ps(self.0, _mm_movehl_ps(self.0, self.0)));
        x!(_mm_cvtss_f32(_mm_max_ss(m, _mm_shuffle_ps::<1>(m, m))))
    }
    #[inline(always)]
    fn to_bits(self) -> I4 {
        I4(x!(_mm_castps_si128(self.0)))
    }
    #[inline(always)]
    fn to_int_trunc(self) -> I4 {
        I4(x!(_mm_cvttps_epi32(self.0)))
    }
    #[inline(always)]
    fn permute(self, idx: I4) -> Self {
        self.to_bits().permute(idx).to_float_bits()
    }
    #[inline(always)]
    fn compress(self, m: M4) -> Self {
        self.to_bits().compress(m).to_float_bits()
    }
}

impl IntV for I4 {
    type Mask = M4;
    type Float = F4;
    type Array = [i32; 4];
    const LANES: usize = 4;

    #[inline(always)]
    fn to_array(self) -> [i32; 4] {
        let mut a = [0; 4];
        x!(_mm_storeu_si128(a.as_mut_ptr().cast(), self.0));
        a
    }
    #[inline(always)]
    fn andnot(self, o: Self) -> Self {
        I4(x!(_mm_andnot_si128(o.0, self.0)))
    }
    #[inline(always)]
    fn shl<const N: i32>(self) -> Self {
        I4(x!(_mm_slli_epi32::<N>(self.0)))
    }
    #[inline(always)]
    fn shr<const N: i32>(self) -> Self {
        I4(x!(_mm_srli_epi32::<N>(self.0)))
    }
    #[inline(always)]
    fn sar<const N: i32>(self) -> Self {
        I4(x!(_mm_srai_epi32::<N>(self.0)))
    }
    #[inline(always)]
    fn eq(self, o: Self) -> M4 {
        M4(x!(_mm_castsi128_ps(_mm_cmpeq_epi32(self.0, o.0))))
    }
    #[inline(always)]
    fn gt(self, o: Self) -> M4 {
        M4(x!(_mm_castsi128_ps(_mm_cmpgt_epi32(self.0, o.0))))
    }
    #[inline(always)]
    fn lt(self, o: Self) -> M4 {
        M4(x!(_mm_castsi128_ps(_mm_cmplt_epi32(self.0, o.0))))
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        I4(x!(_mm_min_epi32(self.0, o.0)))
    }
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        I4(x!(_mm_max_epi32(self.0, o.0)))
    }
    #[inline(always)]
    fn hmin(self) -> i32 {
        let m = x!(_mm_min_epi32(
            self.0,
            _mm_shuffle_epi32::<0b01_00_11_10>(self.0)
        ));
        let m = x!(_mm_min_epi32(m, _mm_shuffle_epi32::<0b10_11_00_01>(m)));
        x!(_mm_cvtsi128_si32(m))
    }
    #[inline(always)]
    fn to_float_bits(self) -> F4 {
        F4(x!(_mm_castsi128_ps(self.0)))
    }
    #[inline(always)]
    fn to_float(self) -> F4 {
        F4(x!(_mm_cvtepi32_ps(self.0)))
    }
    #[inline(always)]
    fn permute(self, idx: Self) -> Self {
        I4(x!(_mm_shuffle_epi8(self.0, lane_control4(idx.0))))
    }
    #[inline(always)]
    fn compress(self, m: M4) -> Self {
        let ctl = i4_load_bytes(&COMPRESS4[m.bitmask() as usize]);
        I4(x!(_mm_shuffle_epi8(self.0, ctl)))
    }
}

#[inline(always)]
fn i4_load_bytes(a: &[u8; 16]) -> __m128i {
    x!(_mm_loadu_si128(a.as_ptr().cast()))
}

// 8-wide as pairs of halves.

macro_rules! op8 {
    ($ty:ident, $tr:ident, $f:ident) => {
        impl $tr for $ty {
            type Output = Self;
            #[inline(always)]
            fn $f(self, o: Self) -> Self {
                $ty(self.0.$f(o.0), self.1.$f(o.1))
            }
        }
    };
}
op8!(F8, Add, add);
op8!(F8, Sub, sub);
op8!(F8, Mul, mul);
op8!(F8, Div, div);
op8!(I8, Add, add);
op8!(I8, Sub, sub);
op8!(I8, Mul, mul);
op8!(I8, BitAnd, bitand);
op8!(I8, BitOr, bitor);
op8!(I8, BitXor, bitxor);
op8!(M8, BitAnd, bitand);
op8!(M8, BitOr, bitor);
op8!(M8, BitXor, bitxor);

impl Neg for F8 {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        F8(-self.0, -self.1)
    }
}
impl Not for I8 {
    type Output = Self;
    #[inline(always)]
    fn not(self) -> Self {
        I8(!self.0, !self.1)
    }
}
impl Not for M8 {
    type Output = Self;
    #[inline(always)]
    fn not(self) -> Self {
        M8(!self.0, !self.1)
    }
}
impl Select<F8> for M8 {
    #[inline(always)]
    fn select(self, a: F8, b: F8) -> F8 {
        F8(self.0.select(a.0, b.0), self.1.select(a.1, b.1))
    }
}
impl Select<I8> for M8 {
    #[inline(always)]
    fn select(self, a: I8, b: I8) -> I8 {
        I8(self.0.select(a.0, b.0), self.1.select(a.1, b.1))
    }
}

impl MaskV for M8 {
    const LANES: usize = 8;
    #[inline(always)]
    fn andnot(self, o: Self) -> Self {
        M8(self.0.andnot(o.0), self.1.andnot(o.1))
    }
    #[inline(always)]
    fn any(self) -> bool {
        (self.0 | self.1).any()
    }
    #[inline(always)]
    fn all(self) -> bool {
        (self.0 & self.1).all()
    }
    #[inline(always)]
    fn none(self) -> bool {
        (self.0 | self.1).none()
    }
    #[inline(always)]
    fn bitmask(self) -> u32 {
        self.0.bitmask() | (self.1.bitmask() << 4)
    }
}

#[inline(always)]
fn split<T: Copy + Default>(a: [T; 8]) -> ([T; 4], [T; 4]) {
    let mut lo = [T::default(); 4];
    let mut hi = [T::default(); 4];
    lo.copy_from_slice(&a[..4]);
    hi.copy_from_slice(&a[4..]);
    (lo, hi)
}

#[inline(always)]
fn join<T: Copy + Default>(lo: [T; 4], hi: [T; 4]) -> [T; 8] {
    let mut a = [T::default(); 8];
    a[..4].copy_from_slice(&lo);
    a[4..].copy_from_slice(&hi);
    a
}

#[inline(always)]
fn f8_from(a: [f32; 8]) -> F8 {
    let (lo, hi) = split(a);
    F8(f4_load(&lo), f4_load(&hi))
}

#[inline(always)]
fn i8_from(a: [i32; 8]) -> I8 {
    let (lo, hi) = split(a);
    I8(i4_load(&lo), i4_load(&hi))
}

/// The compress order of `super::COMPRESS8`, applied to an array.
#[inline(always)]
fn compress_array<T: Copy>(a: [T; 8], bits: u32) -> [T; 8] {
    let packed = super::COMPRESS8[bits as usize & 0xff];
    std::array::from_fn(|i| a[((packed >> (3 * i)) & 7) as usize])
}

impl FloatV for F8 {
    type Mask = M8;
    type Int = I8;
    type Array = [f32; 8];
    const LANES: usize = 8;

    #[inline(always)]
    fn to_array(self) -> [f32; 8] {
        join(self.0.to_array(), self.1.to_array())
    }
    #[inline(always)]
    fn mul_add(self, b: Self, c: Self) -> Self {
        F8(self.0.mul_add(b.0, c.0), self.1.mul_add(b.1, c.1))
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        F8(self.0.min(o.0), self.1.min(o.1))
    }
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        F8(self.0.max(o.0), self.1.max(o.1))
    }
    #[inline(always)]
    fn abs(self) -> Self {
        F8(self.0.abs(), self.1.abs())
    }
    #[inline(always)]
    fn sqrt(self) -> Self {
        F8(self.0.sqrt(), self.1.sqrt())
    }
    #[inline(always)]
    fn recip(self) -> Self {
        F8(self.0.recip(), self.1.recip())
    }
    #[inline(always)]
    fn recip_fast(self) -> Self {
        F8(self.0.recip_fast(), self.1.recip_fast())
    }
    #[inline(always)]
    fn lt(self, o: Self) -> M8 {
        M8(self.0.lt(o.0), self.1.lt(o.1))
    }
    #[inline(always)]
    fn le(self, o: Self) -> M8 {
        M8(self.0.le(o.0), self.1.le(o.1))
    }
    #[inline(always)]
    fn gt(self, o: Self) -> M8 {
        M8(self.0.gt(o.0), self.1.gt(o.1))
    }
    #[inline(always)]
    fn ge(self, o: Self) -> M8 {
        M8(self.0.ge(o.0), self.1.ge(o.1))
    }
    #[inline(always)]
    fn eq(self, o: Self) -> M8 {
        M8(FloatV::eq(self.0, o.0), FloatV::eq(self.1, o.1))
    }
    #[inline(always)]
    fn ne(self, o: Self) -> M8 {
        M8(FloatV::ne(self.0, o.0), FloatV::ne(self.1, o.1))
    }
    #[inline(always)]
    fn hmin(self) -> f32 {
        self.0.min(self.1).hmin()
    }
    #[inline(always)]
    fn hmax(self) -> f32 {
        self.0.max(self.1).hmax()
    }
    #[inline(always)]
    fn to_bits(self) -> I8 {
        I8(self.0.to_bits(), self.1.to_bits())
    }
    #[inline(always)]
    fn to_int_trunc(self) -> I8 {
        I8(self.0.to_int_trunc(), self.1.to_int_trunc())
    }
    #[inline(always)]
    fn permute(self, idx: I8) -> Self {
        let a = self.to_array();
        f8_from(idx.to_array().map(|i| a[i as usize & 7]))
    }
    #[inline(always)]
    fn compress(self, m: M8) -> Self {
        f8_from(compress_array(self.to_array(), m.bitmask()))
    }
}

impl IntV for I8 {
    type Mask = M8;
    type Float = F8;
    type Array = [i32; 8];
    const LANES: usize = 8;

    #[inline(always)]
    fn to_array(self) -> [i32; 8] {
        join(self.0.to_array(), self.1.to_array())
    }
    #[inline(always)]
    fn andnot(self, o: Self) -> Self {
        I8(self.0.andnot(o.0), self.1.andnot(o.1))
    }
    #[inline(always)]
    fn shl<const N: i32>(self) -> Self {
        I8(self.0.shl::<N>(), self.1.shl::<N>())
    }
    #[inline(always)]
    fn shr<const N: i32>(self) -> Self {
        I8(self.0.shr::<N>(), self.1.shr::<N>())
    }
    #[inline(always)]
    fn sar<const N: i32>(self) -> Self {
        I8(self.0.sar::<N>(), self.1.sar::<N>())
    }
    #[inline(always)]
    fn eq(self, o: Self) -> M8 {
        M8(IntV::eq(self.0, o.0), IntV::eq(self.1, o.1))
    }
    #[inline(always)]
    fn gt(self, o: Self) -> M8 {
        M8(self.0.gt(o.0), self.1.gt(o.1))
    }
    #[inline(always)]
    fn lt(self, o: Self) -> M8 {
        M8(self.0.lt(o.0), self.1.lt(o.1))
    }
    #[inline(always)]
    fn min(self, o: Self) -> Self {
        I8(self.0.min(o.0), self.1.min(o.1))
    }
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        I8(self.0.max(o.0), self.1.max(o.1))
    }
    #[inline(always)]
    fn hmin(self) -> i32 {
        self.0.min(self.1).hmin()
    }
    #[inline(always)]
    fn to_float_bits(self) -> F8 {
        F8(self.0.to_float_bits(), self.1.to_float_bits())
    }
    #[inline(always)]
    fn to_float(self) -> F8 {
        F8(self.0.to_float(), self.1.to_float())
    }
    #[inline(always)]
    fn permute(self, idx: Self) -> Self {
        let a = self.to_array();
        i8_from(idx.to_array().map(|i| a[i as usize & 7]))
    }
    #[inline(always)]
    fn compress(self, m: M8) -> Self {
        i8_from(compress_array(self.to_array(), m.bitmask()))
    }
}
