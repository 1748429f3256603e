//! Benchmarks (placeholder).

/// Errors of a benchmark.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct BenchError(String);
