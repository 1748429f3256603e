//! The scalar backend: vectors as plain arrays, one lane at a time. It runs everywhere and is
//! the executable specification of every operation (the hardware backends are tested
//! against it), so each method is written as the lane-wise rule the module docs state.

use super::{FloatV, IntV, MaskV, Select, Simd, COMPRESS8};
use std::ops::{Add, BitAnd, BitOr, BitXor, Div, Mul, Neg, Not, Sub};

/// The scalar backend's token (always available).
#[derive(Clone, Copy, Debug, Default)]
pub struct Scalar;

/// N × f32, emulated.
#[derive(Clone, Copy, Debug)]
pub struct SF<const N: usize>([f32; N]);
/// N × i32, emulated.
#[derive(Clone, Copy, Debug)]
pub struct SI<const N: usize>([i32; N]);
/// N-lane mask, emulated.
#[derive(Clone, Copy, Debug)]
pub struct SM<const N: usize>([bool; N]);

/// The x86 `minps` rule.
#[inline(always)]
pub fn min_x86(a: f32, b: f32) -> f32 {
    if a < b {
        a
    } else {
        b
    }
}

/// The x86 `maxps` rule.
#[inline(always)]
pub fn max_x86(a: f32, b: f32) -> f32 {
    if a > b {
        a
    } else {
        b
    }
}

/// The x86 `cvttps2dq` rule: truncation, `i32::MIN` for NaN and out-of-range values.
#[inline(always)]
pub fn trunc_x86(a: f32) -> i32 {
    if (-2147483648.0..2147483648.0).contains(&a) {
        a as i32
    } else {
        i32::MIN
    }
}

/// The lane order of `compress` for an N-lane mask (N = 4 or 8).
#[inline(always)]
fn compress_order<const N: usize>(bits: u32) -> [usize; N] {
    // Lanes >= N count as unselected, so they land after the first N entries.
    let packed = COMPRESS8[(bits & ((1u32 << N) - 1)) as usize];
    std::array::from_fn(|i| ((packed >> (3 * i)) & 7) as usize)
}

#[inline(always)]
fn map<T: Copy, U, const N: usize>(a: [T; N], f: impl Fn(T) -> U) -> [U; N] {
    std::array::from_fn(|i| f(a[i]))
}

#[inline(always)]
fn zip<T: Copy, U, const N: usize>(a: [T; N], b: [T; N], f: impl Fn(T, T) -> U) -> [U; N] {
    std::array::from_fn(|i| f(a[i], b[i]))
}

/// Halving tree reduction shared by every backend's `hmin`/`hmax`.
#[inline(always)]
fn tree<T: Copy, const N: usize>(mut v: [T; N], f: impl Fn(T, T) -> T) -> T {
    let mut n = N;
    while n > 1 {
        n /= 2;
        for i in 0..n {
            v[i] = f(v[i], v[i + n]);
        }
    }
    v[0]
}

impl Simd for Scalar {
    const BACKEND: super::Backend = super::Backend::Scalar;
    type F8 = SF<8>;
    type I8 = SI<8>;
    type M8 = SM<8>;
    type F4 = SF<4>;
    type I4 = SI<4>;
    type M4 = SM<4>;

    #[inline(always)]
    fn splat_f8(self, x: f32) -> SF<8> {
        SF([x; 8])
    }
    #[inline(always)]
    fn load_f8(self, a: &[f32; 8]) -> SF<8> {
        SF(*a)
    }
    #[inline(always)]
    fn splat_i8(self, x: i32) -> SI<8> {
        SI([x; 8])
    }
    #[inline(always)]
    fn load_i8(self, a: &[i32; 8]) -> SI<8> {
        SI(*a)
    }
    #[inline(always)]
    fn mask8(self, bits: u32) -> SM<8> {
        SM(std::array::from_fn(|i| bits >> i & 1 == 1))
    }
    #[inline(always)]
    fn splat_f4(self, x: f32) -> SF<4> {
        SF([x; 4])
    }
    #[inline(always)]
    fn load_f4(self, a: &[f32; 4]) -> SF<4> {
        SF(*a)
    }
    #[inline(always)]
    fn splat_i4(self, x: i32) -> SI<4> {
        SI([x; 4])
    }
    #[inline(always)]
    fn load_i4(self, a: &[i32; 4]) -> SI<4> {
        SI(*a)
    }
    #[inline(always)]
    fn mask4(self, bits: u32) -> SM<4> {
        SM(std::array::from_fn(|i| bits >> i & 1 == 1))
    }
}

macro_rules! binop {
    ($ty:ident, $tr:ident, $f:ident, $e:expr) => {
        impl<const N: usize> $tr for $ty<N> {
            type Output = Self;
            #[inline(always)]
            fn $f(self, o: Self) -> Self {
                $ty(zip(self.0, o.0, $e))
            }
        }
    };
}

binop!(SF, Add, add, |a, b| a + b);
binop!(SF, Sub, sub, |a, b| a - b);
binop!(SF, Mul, mul, |a, b| a * b);
binop!(SF, Div, div, |a, b| a / b);
binop!(SI, Add, add, i32::wrapping_add);
binop!(SI, Sub, sub, i32::wrapping_sub);
binop!(SI, Mul, mul, i32::wrapping_mul);
binop!(SI, BitAnd, bitand, |a, b| a & b);
binop!(SI, BitOr, bitor, |a, b| a | b);
binop!(SI, BitXor, bitxor, |a, b| a ^ b);
binop!(SM, BitAnd, bitand, |a, b| a & b);
binop!(SM, BitOr, bitor, |a, b| a | b);
binop!(SM, BitXor, bitxor, |a, b| a ^ b);

impl<const N: usize> Neg for SF<N> {
    type Output = Self;
    #[inline(always)]
    fn neg(self) -> Self {
        SF(map(self.0, |a| -a))
    }
}
impl<const N: usize> Not for SI<N> {
    type Output = Self;
    #[inline(always)]
    fn not(self) -> Self {
        SI(map(self.0, |a| !a))
    }
}
impl<const N: usize> Not for SM<N> {
    type Output = Self;
    #[inline(always)]
    fn not(self) -> Self {
        SM(map(self.0, |a| !a))
    }
}

impl<const N: usize> Select<SF<N>> for SM<N> {
    #[inline(always)]
    fn select(self, a: SF<N>, b: SF<N>) -> SF<N> {
        SF(std::array::from_fn(
            |i| if self.0[i] { a.0[i] } else { b.0[i] },
        ))
    }
}
impl<const N: usize> Select<SI<N>> for SM<N> {
    #[inline(always)]
    fn select(self, a: SI<N>, b: SI<N>) -> SI<N> {
        SI(std::array::from_fn(
            |i| if self.0[i] { a.0[i] } else { b.0[i] },
        ))
    }
}

impl<const N: usize> MaskV for SM<N> {
    const LANES: usize = N;
    #[inline(always)]
    fn andnot(self, o: Self) -> Self {
        SM(zip(self.0, o.0, |a, b| a & !b))
    }
    #[inline(always)]
    fn any(self) -> bool {
        self.0.iter().any(|&b| b)
    }
    #[inline(always)]
    fn all(self) -> bool {
        self.0.iter().all(|&b| b)
    }
    #[inline(always)]
    fn none(self) -> bool {
        !self.any()
    }
    #[inline(always)]
    fn bitmask(self) -> u32 {
        self.0
            .iter()
            .enumerate()
            .fold(0, |m, (i, &b)| m | (u32::from(b) << i))
    }
}

macro_rules! float_impl {
    ($n:literal) => {
        impl FloatV for SF<$n> {
            type Mask = SM<$n>;
            type Int = SI<$n>;
            type Array = [f32; $n];
            const LANES: usize = $n;
            #[inline(always)]
            fn to_array(self) -> [f32; $n] {
                self.0
            }
            #[inline(always)]
            fn mul_add(self, b: Self, c: Self) -> Self {
                self * b + c
            }
            #[inline(always)]
            fn min(self, o: Self) -> Self {
                SF(zip(self.0, o.0, min_x86))
            }
            #[inline(always)]
            fn max(self, o: Self) -> Self {
                SF(zip(self.0, o.0, max_x86))
            }
            #[inline(always)]
            fn abs(self) -> Self {
                SF(map(self.0, f32::abs))
            }
            #[inline(always)]
            fn sqrt(self) -> Self {
                SF(map(self.0, f32::sqrt))
            }
            #[inline(always)]
            fn recip(self) -> Self {
                SF(map(self.0, |a| 1.0 / a))
            }
            #[inline(always)]
            fn recip_fast(self) -> Self {
                self.recip()
            }
            #[inline(always)]
            fn lt(self, o: Self) -> SM<$n> {
                SM(zip(self.0, o.0, |a, b| a < b))
            }
            #[inline(always)]
            fn le(self, o: Self) -> SM<$n> {
                SM(zip(self.0, o.0, |a, b| a <= b))
            }
            #[inline(always)]
            fn gt(self, o: Self) -> SM<$n> {
                SM(zip(self.0, o.0, |a, b| a > b))
            }
            #[inline(always)]
            fn ge(self, o: Self) -> SM<$n> {
                SM(zip(self.0, o.0, |a, b| a >= b))
            }
            #[inline(always)]
            fn eq(self, o: Self) -> SM<$n> {
                SM(zip(self.0, o.0, |a, b| a == b))
            }
            #[inline(always)]
            fn ne(self, o: Self) -> SM<$n> {
                SM(zip(self.0, o.0, |a, b| a != b))
            }
            #[inline(always)]
            fn hmin(self) -> f32 {
                tree(self.0, min_x86)
            }
            #[inline(always)]
            fn hmax(self) -> f32 {
                tree(self.0, max_x86)
            }
            #[inline(always)]
            fn to_bits(self) -> SI<$n> {
                SI(map(self.0, |a| a.to_bits() as i32))
            }
            #[inline(always)]
            fn to_int_trunc(self) -> SI<$n> {
                SI(map(self.0, trunc_x86))
            }
            #[inline(always)]
            fn permute(self, idx: SI<$n>) -> Self {
                SF(map(idx.0, |i| self.0[i as usize & ($n - 1)]))
            }
            #[inline(always)]
            fn compress(self, m: SM<$n>) -> Self {
                SF(map(compress_order::<$n>(m.bitmask()), |i| self.0[i]))
            }
        }

        impl IntV for SI<$n> {
            type Mask = SM<$n>;
            type Float = SF<$n>;
            type Array = [i32; $n];
            const LANES: usize = $n;
            #[inline(always)]
            fn to_array(self) -> [i32; $n] {
                self.0
            }
            #[inline(always)]
            fn andnot(self, o: Self) -> Self {
                SI(zip(self.0, o.0, |a, b| a & !b))
            }
            #[inline(always)]
            fn shl<const S: i32>(self) -> Self {
                SI(map(self.0, |a| {
                    if S >= 32 {
                        0
                    } else {
                        ((a as u32) << S) as i32
                    }
                }))
            }
            #[inline(always)]
            fn shr<const S: i32>(self) -> Self {
                SI(map(self.0, |a| {
                    if S >= 32 {
                        0
                    } else {
                        ((a as u32) >> S) as i32
                    }
                }))
            }
            #[inline(always)]
            fn sar<const S: i32>(self) -> Self {
                SI(map(self.0, |a| a >> S.min(31)))
            }
            #[inline(always)]
            fn eq(self, o: Self) -> SM<$n> {
                SM(zip(self.0, o.0, |a, b| a == b))
            }
            #[inline(always)]
            fn gt(self, o: Self) -> SM<$n> {
                SM(zip(self.0, o.0, |a, b| a > b))
            }
            #[inline(always)]
            fn lt(self, o: Self) -> SM<$n> {
                SM(zip(self.0, o.0, |a, b| a < b))
            }
            #[inline(always)]
            fn min(self, o: Self) -> Self {
                SI(zip(self.0, o.0, i32::min))
            }
            #[inline(always)]
            fn max(self, o: Self) -> Self {
                SI(zip(self.0, o.0, i32::max))
            }
            #[inline(always)]
            fn hmin(self) -> i32 {
                tree(self.0, i32::min)
            }
            #[inline(always)]
            fn to_float_bits(self) -> SF<$n> {
                SF(map(self.0, |a| f32::from_bits(a as u32)))
            }
            #[inline(always)]
            fn to_float(self) -> SF<$n> {
                SF(map(self.0, |a| a as f32))
            }
            #[inline(always)]
            fn permute(self, idx: Self) -> Self {
                SI(map(idx.0, |i| self.0[i as usize & ($n - 1)]))
            }
            #[inline(always)]
            fn compress(self, m: SM<$n>) -> Self {
                SI(map(compress_order::<$n>(m.bitmask()), |i| self.0[i]))
            }
        }
    };
}

float_impl!(4);
float_impl!(8);
