//! The portable SIMD layer: 8- and 4-wide f32, i32 and mask vectors with AVX2+FMA, SSE4.1
//! and scalar-emulation backends, chosen once at run time.
//!
//! The design follows Geimer & Müller's cross-platform framework (§2 of their paper): kernels
//! are written once against abstract vector types and every backend supplies those types with
//! the same semantics, the scalar one being the executable specification. In Rust terms:
//!
//! - [`Simd`] is a zero-sized *token* per backend. Its associated types ([`Simd::F8`],
//!   [`Simd::I8`], [`Simd::M8`] and the 4-wide `F4`, `I4`, `M4`) implement [`FloatV`],
//!   [`IntV`] and [`MaskV`] (methods and operators). Vectors can only be made through a
//!   token (`splat_*`, `load_*`, `mask*`), and a token of a hardware backend can only be made
//!   after run-time detection proved the CPU has its instructions; so holding a vector is
//!   proof that its operations are safe to execute. That is what makes the safe API sound.
//! - Kernels are generic functions `fn k<S: Simd>(s: S, ...)`, packaged as a [`Kernel`] and
//!   entered through [`dispatch`]: one `#[target_feature]` function per backend calls
//!   `Kernel::run`, and everything below it is `#[inline(always)]`, so the whole kernel is
//!   compiled with AVX2/FMA (resp. SSE4.1) enabled and the intrinsics inline into it. Dispatch
//!   happens once per batch, never per operation. **Kernel code must mark `run` and every
//!   helper it calls that touches vectors `#[inline(always)]`**: a helper that is not inlined
//!   is compiled without the target features and every vector operation in it becomes a
//!   function call.
//!
//! Semantics every backend shares (the scalar twin is the reference; `tests/simd_twin.rs`
//! checks the others against it bit for bit):
//!
//! - IEEE add, sub, mul, div, sqrt: correctly rounded, so bit-identical across backends. NaN
//!   payloads are unspecified (only NaN-ness is compared).
//! - `min(a, b) = if a < b { a } else { b }`, `max(a, b) = if a > b { a } else { b }`: the
//!   x86 `minps`/`maxps` rule, so `b` is returned when either is NaN and for `±0` ties. The
//!   slab test relies on it for axis-parallel rays.
//! - `mul_add(a, b, c) = a·b + c` is *fused* (one rounding) for the AVX2 backend's 8-wide
//!   `F8`, and two roundings on SSE and scalar, which are bit-identical to each other. The
//!   4-wide types are SSE's on every x86 backend, so `F4::mul_add` is never fused. Use it only
//!   where that difference is acceptable (box tests), never where two code paths must agree
//!   exactly (the triangle tests do not use it).
//! - `recip_fast` is a hardware approximation refined by one Newton–Raphson step on x86
//!   (relative error below 2^-21) and exact `1/x` on scalar.
//! - Comparisons are ordered (false with a NaN) except `ne`, which is true with a NaN (Rust's
//!   `!=`).
//! - Horizontal `hmin`/`hmax` reduce in a fixed tree (lane i with lane i+N/2, then halves
//!   again), so with NaN lanes the result is still the same on every backend.
//! - `permute` uses the low 3 (8-wide) or 2 (4-wide) bits of each index. `compress` is a
//!   stable partition: the selected lanes first in lane order, then the others in lane order.
//!
//! Checking that the intrinsics inlined: in a release build, disassemble the backend's entry
//! points (`nm -C BIN | grep 'simd::avx2::entry'`, then `objdump -d --start-address=...`):
//! the kernel's body is there and its only `call`s are to cold paths (bounds-check panics,
//! the watertight test's f64 fallback, the scalar recomputation of the winning hit) — no
//! `_mm256_*` wrapper calls. (Verified for `brute` at the time of writing.)
//!
//! Adding NEON (aarch64) would mean a `neon.rs` with 4-wide `float32x4_t` types and pairs
//! for the 8-wide ones, exactly like `sse.rs`, plus a `Backend::Neon` arm in [`dispatch`];
//! nothing in the kernels changes.
#![allow(unsafe_code)]

use std::fmt::Debug;
use std::ops::{Add, BitAnd, BitOr, BitXor, Div, Mul, Neg, Not, Sub};
use std::sync::OnceLock;

#[cfg(target_arch = "x86_64")]
pub mod avx2;
pub mod build4;
pub mod scalar;
#[cfg(target_arch = "x86_64")]
pub mod sse;

#[cfg(target_arch = "x86_64")]
pub use avx2::Avx2;
pub use scalar::Scalar;
#[cfg(target_arch = "x86_64")]
pub use sse::Sse;

/// A SIMD backend.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Backend {
    /// AVX2 + FMA, 8 lanes native.
    Avx2,
    /// SSE4.1, 4 lanes native (8-wide vectors are pairs).
    Sse,
    /// Scalar emulation: works everywhere, and is the reference the others are tested against.
    Scalar,
}

impl Backend {
    /// Every backend, fastest first.
    pub const ALL: [Backend; 3] = [Backend::Avx2, Backend::Sse, Backend::Scalar];

    /// The name `rayd info` reports and `RAYD_SIMD` accepts.
    pub fn name(self) -> &'static str {
        match self {
            Backend::Avx2 => "avx2",
            Backend::Sse => "sse",
            Backend::Scalar => "scalar",
        }
    }

    /// Parses a name as [`Backend::name`] writes it (ASCII case ignored).
    pub fn parse(s: &str) -> Option<Backend> {
        Backend::ALL
            .into_iter()
            .find(|b| b.name().eq_ignore_ascii_case(s.trim()))
    }

    /// Whether this CPU (and this build's target) can run the backend.
    pub fn is_supported(self) -> bool {
        match self {
            Backend::Scalar => true,
            #[cfg(target_arch = "x86_64")]
            Backend::Sse => Sse::new().is_some(),
            #[cfg(target_arch = "x86_64")]
            Backend::Avx2 => Avx2::new().is_some(),
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }

    /// The backends this CPU supports, fastest first (tests loop over these).
    pub fn supported() -> Vec<Backend> {
        Backend::ALL
            .into_iter()
            .filter(|b| b.is_supported())
            .collect()
    }
}

impl std::fmt::Display for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Why `RAYD_SIMD` cannot be honoured.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SimdError {
    /// The value names no backend.
    #[error("RAYD_SIMD={0:?} is not a SIMD backend (expected avx2, sse or scalar)")]
    Unknown(String),
    /// The backend exists but this CPU (or build target) cannot run it.
    #[error("RAYD_SIMD={0} asks for a backend this CPU does not support (best available: {1})")]
    Unsupported(Backend, Backend),
}

/// The fastest backend this CPU supports.
pub fn detect() -> Backend {
    Backend::supported()[0]
}

/// The backend asked for by `value` (the content of `RAYD_SIMD`; `None` or blank means "not
/// set", which picks [`detect`]). Split from [`from_env`] so it can be tested without
/// touching the process environment.
pub fn resolve(value: Option<&str>) -> Result<Backend, SimdError> {
    match value.map(str::trim) {
        None | Some("") => Ok(detect()),
        Some(v) => {
            let b = Backend::parse(v).ok_or_else(|| SimdError::Unknown(v.to_string()))?;
            if b.is_supported() {
                Ok(b)
            } else {
                Err(SimdError::Unsupported(b, detect()))
            }
        }
    }
}

/// The backend the environment asks for: `RAYD_SIMD=avx2|sse|scalar` overrides detection.
/// The CLI calls this at startup so that a typo or an unsupported request is a clear error
/// rather than a silent fallback.
pub fn from_env() -> Result<Backend, SimdError> {
    match std::env::var("RAYD_SIMD") {
        Ok(v) => resolve(Some(&v)),
        Err(std::env::VarError::NotPresent) => resolve(None),
        Err(std::env::VarError::NotUnicode(v)) => {
            Err(SimdError::Unknown(v.to_string_lossy().into_owned()))
        }
    }
}

/// The backend in use, decided once per process: [`from_env`], or [`detect`] when the
/// environment's request is invalid (the CLI has refused that case already via `from_env`).
pub fn selected() -> Backend {
    static SELECTED: OnceLock<Backend> = OnceLock::new();
    *SELECTED.get_or_init(|| from_env().unwrap_or_else(|_| detect()))
}

/// A backend token: proof that the CPU supports the backend, and the factory of its vectors.
///
/// All methods are `#[inline(always)]` in every implementation.
pub trait Simd: Copy + Send + Sync + Debug + 'static {
    /// Which backend this is.
    const BACKEND: Backend;
    /// 8 × f32.
    type F8: FloatV<Mask = Self::M8, Int = Self::I8, Array = [f32; 8]>;
    /// 8 × i32.
    type I8: IntV<Mask = Self::M8, Float = Self::F8, Array = [i32; 8]>;
    /// 8-lane mask.
    type M8: MaskV + Select<Self::F8> + Select<Self::I8>;
    /// 4 × f32.
    type F4: FloatV<Mask = Self::M4, Int = Self::I4, Array = [f32; 4]>;
    /// 4 × i32.
    type I4: IntV<Mask = Self::M4, Float = Self::F4, Array = [i32; 4]>;
    /// 4-lane mask.
    type M4: MaskV + Select<Self::F4> + Select<Self::I4>;

    /// All lanes `x`.
    fn splat_f8(self, x: f32) -> Self::F8;
    /// Loads 8 lanes (no alignment needed).
    fn load_f8(self, a: &[f32; 8]) -> Self::F8;
    /// All lanes `x`.
    fn splat_i8(self, x: i32) -> Self::I8;
    /// Loads 8 lanes (no alignment needed).
    fn load_i8(self, a: &[i32; 8]) -> Self::I8;
    /// Lane i set iff bit i of `bits` is set.
    fn mask8(self, bits: u32) -> Self::M8;
    /// All lanes `x`.
    fn splat_f4(self, x: f32) -> Self::F4;
    /// Loads 4 lanes (no alignment needed).
    fn load_f4(self, a: &[f32; 4]) -> Self::F4;
    /// All lanes `x`.
    fn splat_i4(self, x: i32) -> Self::I4;
    /// Loads 4 lanes (no alignment needed).
    fn load_i4(self, a: &[i32; 4]) -> Self::I4;
    /// Lane i set iff bit i of `bits` is set.
    fn mask4(self, bits: u32) -> Self::M4;
}

/// Lane-wise choice between two vectors: `m.select(a, b)` is `a` where `m` is set, else `b`.
pub trait Select<V> {
    /// `a` where the mask is set, `b` elsewhere.
    fn select(self, a: V, b: V) -> V;
}

/// A mask: one boolean per lane (all-ones/all-zeros lanes in the hardware backends).
pub trait MaskV:
    Copy
    + Debug
    + Send
    + Sync
    + BitAnd<Output = Self>
    + BitOr<Output = Self>
    + BitXor<Output = Self>
    + Not<Output = Self>
{
    /// Number of lanes.
    const LANES: usize;
    /// `self & !other`.
    fn andnot(self, other: Self) -> Self;
    /// Whether any lane is set.
    fn any(self) -> bool;
    /// Whether every lane is set.
    fn all(self) -> bool;
    /// Whether no lane is set.
    fn none(self) -> bool;
    /// Bit i set iff lane i is set (`movemask`).
    fn bitmask(self) -> u32;
}

/// A float vector. Arithmetic through the operators; everything else through methods.
pub trait FloatV:
    Copy
    + Debug
    + Send
    + Sync
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    /// Its mask type.
    type Mask: MaskV + Select<Self>;
    /// Its integer vector of the same width.
    type Int: IntV<Mask = Self::Mask, Float = Self>;
    /// `[f32; LANES]`.
    type Array: Copy + Debug + AsRef<[f32]> + AsMut<[f32]>;
    /// Number of lanes.
    const LANES: usize;

    /// The lanes as an array.
    fn to_array(self) -> Self::Array;
    /// `self·b + c`: fused on AVX2, two roundings elsewhere (see the module docs).
    fn mul_add(self, b: Self, c: Self) -> Self;
    /// `if self < o { self } else { o }` (x86 `minps`).
    fn min(self, o: Self) -> Self;
    /// `if self > o { self } else { o }` (x86 `maxps`).
    fn max(self, o: Self) -> Self;
    /// Clears the sign bit.
    fn abs(self) -> Self;
    /// Correctly rounded square root.
    fn sqrt(self) -> Self;
    /// Exact `1 / self` (a division).
    fn recip(self) -> Self;
    /// Approximate `1 / self`, relative error below 2^-21 (exact on scalar).
    fn recip_fast(self) -> Self;
    /// `self < o` (false with NaN).
    fn lt(self, o: Self) -> Self::Mask;
    /// `self <= o` (false with NaN).
    fn le(self, o: Self) -> Self::Mask;
    /// `self > o` (false with NaN).
    fn gt(self, o: Self) -> Self::Mask;
    /// `self >= o` (false with NaN).
    fn ge(self, o: Self) -> Self::Mask;
    /// `self == o` (false with NaN).
    fn eq(self, o: Self) -> Self::Mask;
    /// `self != o` (true with NaN).
    fn ne(self, o: Self) -> Self::Mask;
    /// Minimum over lanes, fixed tree order.
    fn hmin(self) -> f32;
    /// Maximum over lanes, fixed tree order.
    fn hmax(self) -> f32;
    /// Reinterprets the bits as integers.
    fn to_bits(self) -> Self::Int;
    /// Converts to i32 with truncation; NaN and out-of-range give `i32::MIN` (x86 rule).
    fn to_int_trunc(self) -> Self::Int;
    /// Lane i of the result is lane `idx[i] & (LANES-1)` of `self`.
    fn permute(self, idx: Self::Int) -> Self;
    /// Stable partition: lanes selected by `m` first, then the others, each in lane order.
    fn compress(self, m: Self::Mask) -> Self;
}

/// An i32 vector (wrapping arithmetic).
pub trait IntV:
    Copy
    + Debug
    + Send
    + Sync
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + BitAnd<Output = Self>
    + BitOr<Output = Self>
    + BitXor<Output = Self>
    + Not<Output = Self>
{
    /// Its mask type.
    type Mask: MaskV + Select<Self>;
    /// Its float vector of the same width.
    type Float: FloatV<Mask = Self::Mask, Int = Self>;
    /// `[i32; LANES]`.
    type Array: Copy + Debug + AsRef<[i32]> + AsMut<[i32]>;
    /// Number of lanes.
    const LANES: usize;

    /// The lanes as an array.
    fn to_array(self) -> Self::Array;
    /// `self & !o`.
    fn andnot(self, o: Self) -> Self;
    /// Shift left by `N` (0..32).
    fn shl<const N: i32>(self) -> Self;
    /// Logical shift right by `N` (0..32).
    fn shr<const N: i32>(self) -> Self;
    /// Arithmetic shift right by `N` (0..32).
    fn sar<const N: i32>(self) -> Self;
    /// `self == o`.
    fn eq(self, o: Self) -> Self::Mask;
    /// `self > o` (signed).
    fn gt(self, o: Self) -> Self::Mask;
    /// `self < o` (signed).
    fn lt(self, o: Self) -> Self::Mask;
    /// Signed minimum.
    fn min(self, o: Self) -> Self;
    /// Signed maximum.
    fn max(self, o: Self) -> Self;
    /// Signed minimum over lanes.
    fn hmin(self) -> i32;
    /// Reinterprets the bits as floats.
    fn to_float_bits(self) -> Self::Float;
    /// Converts to f32 (round to nearest even, like `as f32`).
    fn to_float(self) -> Self::Float;
    /// Lane i of the result is lane `idx[i] & (LANES-1)` of `self`.
    fn permute(self, idx: Self) -> Self;
    /// Stable partition: lanes selected by `m` first, then the others, each in lane order.
    fn compress(self, m: Self::Mask) -> Self;
}

/// A computation generic over the backend, entered once through [`dispatch`].
///
/// Implementations must mark `run` `#[inline(always)]` (and everything vector-heavy it
/// calls), so that it is compiled inside the backend's `#[target_feature]` entry point.
pub trait Kernel {
    /// What the kernel returns.
    type Output;
    /// The kernel body for backend `S`.
    fn run<S: Simd>(self, s: S) -> Self::Output;
}

/// Runs `kernel` on `backend`: the one place where the backend is chosen.
///
/// # Panics
/// If the CPU does not support `backend` (check [`Backend::is_supported`]; [`selected`]
/// never returns such a backend).
pub fn dispatch<K: Kernel>(backend: Backend, kernel: K) -> K::Output {
    match backend {
        Backend::Scalar => kernel.run(Scalar),
        #[cfg(target_arch = "x86_64")]
        Backend::Sse => match Sse::new() {
            Some(s) => sse::enter(s, kernel),
            None => unsupported(backend),
        },
        #[cfg(target_arch = "x86_64")]
        Backend::Avx2 => match Avx2::new() {
            Some(s) => avx2::enter(s, kernel),
            None => unsupported(backend),
        },
        #[cfg(not(target_arch = "x86_64"))]
        _ => unsupported(backend),
    }
}

/// Asks the CPU to bring the `bytes` bytes from `p` (rounded out to cache lines) into all
/// cache levels, so that a load issued later (when a traversal pops a pushed node) finds
/// them there instead of waiting for memory.
///
/// Only a hint: it never faults, whatever `p` is, and changes no value; a no-op on targets
/// without a prefetch instruction. On x86-64 it is SSE's `prefetcht0`, part of the
/// baseline, so it needs no backend token.
#[inline(always)]
pub fn prefetch(p: *const u8, bytes: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        let mut off = 0;
        while off < bytes {
            // SAFETY: `prefetcht0` is in the x86-64 baseline and only hints the cache: it
            // never faults and reads nothing observable, even for an invalid address (the
            // pointer is formed with `wrapping_add` and never dereferenced).
            unsafe {
                std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(
                    p.wrapping_add(off).cast::<i8>(),
                )
            };
            off += 64;
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (p, bytes);
}

#[cold]
fn unsupported(backend: Backend) -> ! {
    panic!("SIMD backend {backend} is not supported on this CPU")
}

/// The compress permutation for an 8-lane mask: lane indices, 3 bits each, selected lanes
/// first (stable), then the others. Shared by the AVX2 backend and the scalar reference.
pub(crate) const COMPRESS8: [u32; 256] = {
    let mut lut = [0u32; 256];
    let mut m = 0;
    while m < 256 {
        let mut packed = 0u32;
        let mut pos = 0;
        let mut pass = 0;
        while pass < 2 {
            let mut i = 0;
            while i < 8 {
                let sel = (m >> i) & 1 == 1;
                if sel == (pass == 0) {
                    packed |= (i as u32) << (3 * pos);
                    pos += 1;
                }
                i += 1;
            }
            pass += 1;
        }
        lut[m] = packed;
        m += 1;
    }
    lut
};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip() {
        for b in Backend::ALL {
            assert_eq!(Backend::parse(b.name()), Some(b));
            assert_eq!(Backend::parse(&b.name().to_uppercase()), Some(b));
        }
        assert_eq!(Backend::parse("avx512"), None);
    }

    #[test]
    fn resolve_reports_bad_values() {
        assert_eq!(resolve(None), Ok(detect()));
        assert_eq!(resolve(Some("  ")), Ok(detect()));
        assert_eq!(resolve(Some("scalar")), Ok(Backend::Scalar));
        let e = resolve(Some("neon")).unwrap_err();
        assert_eq!(e, SimdError::Unknown("neon".into()));
        assert!(e.to_string().contains("expected avx2, sse or scalar"));
        for b in Backend::ALL {
            if b.is_supported() {
                assert_eq!(resolve(Some(b.name())), Ok(b));
            } else {
                assert!(matches!(
                    resolve(Some(b.name())),
                    Err(SimdError::Unsupported(..))
                ));
            }
        }
        assert!(Backend::Scalar.is_supported());
        assert_eq!(detect(), Backend::supported()[0]);
    }

    #[test]
    fn compress_lut_is_a_stable_partition() {
        for m in 0..256u32 {
            let idx: Vec<u32> = (0..8)
                .map(|i| (COMPRESS8[m as usize] >> (3 * i)) & 7)
                .collect();
            let want: Vec<u32> = (0..8)
                .filter(|i| m >> i & 1 == 1)
                .chain((0..8).filter(|i| m >> i & 1 == 0))
                .collect();
            assert_eq!(idx, want, "mask {m:08b}");
        }
    }

    struct Sum(Vec<f32>);
    impl Kernel for Sum {
        type Output = f32;
        #[inline(always)]
        fn run<S: Simd>(self, s: S) -> f32 {
            let mut acc = s.splat_f8(0.0);
            for c in self.0.chunks_exact(8) {
                acc = acc + s.load_f8(c.try_into().unwrap());
            }
            acc.to_array().iter().sum()
        }
    }

    #[test]
    fn dispatch_runs_every_supported_backend() {
        let v: Vec<f32> = (0..64).map(|i| i as f32).collect();
        for b in Backend::supported() {
            assert_eq!(dispatch(b, Sum(v.clone())), 2016.0, "{b}");
        }
        assert!(Backend::supported().contains(&selected()));
    }
}
