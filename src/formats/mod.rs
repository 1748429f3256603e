//! File formats: glTF 2.0 and TRI1 scenes in; RAY1 rays in; HIT1 hits out.
//!
//! The only layer that knows about `gltf`. Everything it returns is validated: a malformed
//! file is an error that says what and where, never a panic.

pub mod binary;
pub mod gltf;

use std::path::Path;

use crate::scene::Scene;

pub use binary::{BinaryError, HitFormat};
pub use gltf::GltfError;

/// Errors of reading or writing files.
#[derive(Debug, thiserror::Error)]
pub enum FormatError {
    /// The file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The OS error.
        source: std::io::Error,
    },
    /// A RAY1, HIT1 or TRI1 body is malformed.
    #[error(transparent)]
    Binary(#[from] BinaryError),
    /// A glTF file is malformed or uses something rayd refuses.
    #[error(transparent)]
    Gltf(#[from] GltfError),
    /// The file's kind is not known from its name.
    #[error("{0}: unknown scene file type (expected .glb, .gltf or .tri)")]
    UnknownSceneType(String),
    /// What was wrong in a named file (a body error says where in the file, not which).
    #[error("{path}: {source}")]
    InFile {
        /// The file.
        path: String,
        /// What was wrong with its contents.
        source: Box<FormatError>,
    },
}

impl FormatError {
    /// This error, said of the file at `path` (an I/O error already names it).
    pub fn in_file(self, path: &Path) -> FormatError {
        match self {
            e @ (FormatError::Io { .. }
            | FormatError::UnknownSceneType(_)
            | FormatError::InFile { .. }) => e,
            e => FormatError::InFile {
                path: path.display().to_string(),
                source: Box::new(e),
            },
        }
    }
}

/// How to load a scene.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LoadOptions {
    /// Evaluate animations at this time (seconds); `None` is the file's static pose.
    pub time: Option<f64>,
}

/// Which parts of a scene a load keeps; only what a job needs is read.
///
/// A separate argument rather than a field of [`LoadOptions`], so that every caller that
/// writes `LoadOptions { time }` keeps compiling and keeps getting geometry.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Parts {
    /// World positions (and, when the file animates, the rig that re-poses them): what a
    /// ray batch needs. No shading attributes, materials, textures or lights.
    #[default]
    Geometry,
    /// Geometry plus per-vertex shading attributes, per-triangle materials, materials,
    /// textures (encoded, never decoded here) and lights: what a render needs.
    Shading,
    /// What [`Parts::Geometry`] keeps, after reading and checking what [`Parts::Shading`]
    /// would add of the document's own (materials, samplers, textures, image references,
    /// punctual lights; no attribute and no image is decoded): what the service keeps of
    /// an upload, which must refuse a file that a later render could not load.
    CheckedGeometry,
}

/// Reads a whole file, naming it in the error.
pub fn read_file(path: &Path) -> Result<Vec<u8>, FormatError> {
    std::fs::read(path).map_err(|source| FormatError::Io {
        path: path.display().to_string(),
        source,
    })
}

/// Loads a `.glb`, `.gltf` (embedded or side-by-side buffers) or `.tri` scene: geometry
/// only ([`Parts::Geometry`]).
pub fn load_scene(path: &Path, options: &LoadOptions) -> Result<Scene, FormatError> {
    load_scene_with(path, options, Parts::Geometry)
}

/// [`load_scene`] keeping `parts`. A `.tri` file has geometry only: with
/// [`Parts::Shading`] it gets empty shading data (every triangle the default material,
/// face normals).
pub fn load_scene_with(
    path: &Path,
    options: &LoadOptions,
    parts: Parts,
) -> Result<Scene, FormatError> {
    load_named(path, options, parts).map_err(|e| e.in_file(path))
}

fn load_named(path: &Path, options: &LoadOptions, parts: Parts) -> Result<Scene, FormatError> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase())
        .unwrap_or_default();
    match ext.as_str() {
        "tri" => {
            let bytes = read_file(path)?;
            let mut scene = Scene::from_triangles(binary::read_tri(&bytes)?);
            if parts == Parts::Shading {
                scene.shading = Some(crate::scene::Shading::flat(scene.triangles.len()));
            }
            Ok(scene)
        }
        "glb" | "gltf" => {
            let bytes = read_file(path)?;
            Ok(gltf::load_with(&bytes, path.parent(), options, parts)?)
        }
        _ => Err(FormatError::UnknownSceneType(path.display().to_string())),
    }
}
