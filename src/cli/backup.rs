//! `rayd backup --data-dir DIR --out DEST`: a consistent copy of a store, live or not.

use std::path::PathBuf;

use super::CliError;

#[derive(clap::Args, Debug)]
pub(super) struct BackupArgs {
    /// The data directory of the store to copy (the one `rayd serve --data-dir` uses).
    #[arg(long, env = "RAYD_DATA_DIR", default_value = "rayd-data")]
    data_dir: PathBuf,
    /// Where to write the copy: a new or empty directory, which then opens as a store.
    #[arg(long)]
    out: PathBuf,
}

pub(super) fn run(a: BackupArgs) -> Result<serde_json::Value, CliError> {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| CliError::Usage(format!("cannot start the async runtime: {e}")))?;
    let report = rt.block_on(crate::store::Store::backup_dir(&a.data_dir, &a.out))?;
    Ok(serde_json::json!({
        "data_dir": a.data_dir,
        "out": a.out,
        "blobs": report.blobs,
        "bytes": report.bytes,
        "dropped_versions": report.dropped_versions,
    }))
}
