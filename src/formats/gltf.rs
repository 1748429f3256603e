//! glTF 2.0 loading (placeholder until the loader lands).
use std::path::Path;

use super::LoadOptions;
use crate::scene::Scene;

/// Errors of glTF loading.
#[derive(Debug, thiserror::Error)]
pub enum GltfError {
    /// Not yet.
    #[error("glTF loading is not implemented yet")]
    NotYet,
}

/// Loads a glTF scene from bytes; `base_dir` resolves side-by-side buffers.
pub fn load(
    _bytes: &[u8],
    _base_dir: Option<&Path>,
    _options: &LoadOptions,
) -> Result<Scene, GltfError> {
    Err(GltfError::NotYet)
}
