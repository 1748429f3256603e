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

/// The most a scene read from a stream (a pipe, a device) that declares no length of its
/// own (a JSON `.gltf`) may hold: the service's default body limit, so that a stream that
/// never ends (`/dev/zero`) is refused with memory to spare. A regular file's own size
/// bounds it instead.
pub const MAX_STREAMED_SCENE_BYTES: u64 = 1 << 30;

/// Reads a whole scene file, naming it in the error. The file's header bounds what is
/// read: a TRI1 (16 + 36 × its count) or GLB (its length field) is read to one byte past
/// what it declares, so a file or stream that goes on past that is refused at once rather
/// than read to its end (a pipe fed forever would otherwise take all memory). A JSON glTF
/// declares nothing: a regular file is read whole, a stream to
/// [`MAX_STREAMED_SCENE_BYTES`]. Anything else is refused by its parser from its first bytes.
pub fn read_file(path: &Path) -> Result<Vec<u8>, FormatError> {
    let io = |source: std::io::Error| FormatError::Io {
        path: path.display().to_string(),
        source,
    };
    let mut file = std::fs::File::open(path).map_err(io)?;
    let size = regular_len(&file);
    let mut bytes = Vec::new();
    read_up_to(&mut file, &mut bytes, binary::HEADER_BYTES as u64, size).map_err(io)?;
    let (limit, kind) = match bound_of(&bytes) {
        Bound::Declared(n, kind) => (n, Some(kind)),
        Bound::Json => (size.unwrap_or(MAX_STREAMED_SCENE_BYTES), None),
        // No scene starts so: the parser refuses it from these bytes alone.
        Bound::Refused => return Ok(bytes),
    };
    let too_long = |len: Option<u64>| {
        let bound = match kind {
            Some(kind) => format!("the {limit} bytes its {kind} header declares"),
            None => format!("{MAX_STREAMED_SCENE_BYTES} bytes, the most a streamed scene may be"),
        };
        let msg = match len {
            Some(len) => format!("the file is {len} bytes, longer than {bound}"),
            None => format!("the stream goes on past {bound}"),
        };
        io(std::io::Error::new(std::io::ErrorKind::InvalidData, msg))
    };
    if let Some(len) = size.filter(|&len| len > limit) {
        return Err(too_long(Some(len)));
    }
    read_up_to(&mut file, &mut bytes, limit.saturating_add(1), size).map_err(io)?;
    if bytes.len() as u64 > limit {
        return Err(too_long(size));
    }
    Ok(bytes)
}

/// A regular file's length; `None` for a pipe or a device, whose length is unknown.
pub(crate) fn regular_len(file: &std::fs::File) -> Option<u64> {
    file.metadata()
        .ok()
        .filter(|m| m.is_file())
        .map(|m| m.len())
}

/// Appends to `bytes` what `reader` holds from where it is, until `bytes` holds `limit`
/// bytes: a pipe or a device fed forever (`/dev/zero`) is read no further. Room for what
/// a regular file of `size` bytes holds (up to `limit`) is reserved first.
pub(crate) fn read_up_to(
    reader: impl std::io::Read,
    bytes: &mut Vec<u8>,
    limit: u64,
    size: Option<u64>,
) -> std::io::Result<()> {
    use std::io::Read;
    let have = bytes.len() as u64;
    bytes.reserve(size.unwrap_or(0).min(limit).saturating_sub(have) as usize);
    reader
        .take(limit.saturating_sub(have))
        .read_to_end(bytes)
        .map(|_| ())
}

/// How much of a scene file its first bytes allow to be read.
enum Bound {
    /// The whole length the file declares, and the format that declares it: TRI1's
    /// header count (16 + 36 × count) or GLB's length field.
    Declared(u64, &'static str),
    /// A JSON glTF (it starts with `{`, white space or a byte-order mark): no length of
    /// its own.
    Json,
    /// None of those: the parser refuses it from its first bytes.
    Refused,
}

fn bound_of(head: &[u8]) -> Bound {
    if head.starts_with(b"TRI1") {
        if let Ok(count) = binary::tri_header_count(head) {
            let len = 36u64
                .saturating_mul(count as u64)
                .saturating_add(binary::HEADER_BYTES as u64);
            return Bound::Declared(len, "TRI1");
        }
        return Bound::Refused;
    }
    if head.starts_with(b"glTF") {
        return match head.get(8..12) {
            Some(n) => Bound::Declared(
                u32::from_le_bytes(n.try_into().unwrap_or_default()) as u64,
                "GLB",
            ),
            None => Bound::Refused,
        };
    }
    let json = head.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(head);
    match json.first() {
        None | Some(b'{' | b' ' | b'\t' | b'\n' | b'\r') => Bound::Json,
        Some(_) => Bound::Refused,
    }
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
