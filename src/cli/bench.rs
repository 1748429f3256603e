//! `rayd bench` (placeholder).
use super::CliError;

#[derive(clap::Args, Debug)]
pub(super) struct BenchArgs {}

pub(super) fn run(_a: BenchArgs) -> Result<serde_json::Value, CliError> {
    Ok(serde_json::json!({}))
}
