//! The portable SIMD layer (placeholder until the layer lands).

/// A SIMD backend.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    /// AVX2 + FMA, 8 lanes native.
    Avx2,
    /// SSE4.1, 4 lanes native.
    Sse,
    /// Scalar emulation: works everywhere.
    Scalar,
}

impl Backend {
    /// The name `rayd info` reports.
    pub fn name(self) -> &'static str {
        match self {
            Backend::Avx2 => "avx2",
            Backend::Sse => "sse",
            Backend::Scalar => "scalar",
        }
    }
}

/// The backend in use.
pub fn selected() -> Backend {
    Backend::Scalar
}

/// A SIMD backend request that cannot be met (placeholder).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct SimdError(String);

/// Reads `RAYD_SIMD` (placeholder).
pub fn from_env() -> Result<Backend, SimdError> {
    Ok(selected())
}
