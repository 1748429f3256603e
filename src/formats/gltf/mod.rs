//! glTF 2.0 loading: `.glb` and `.gltf` (embedded or side-by-side buffers) to a [`Scene`].
//!
//! The `gltf` crate parses the JSON document into typed structs; everything that touches
//! bytes is done here, because the crate's reader slices buffers without checking ranges.
//! Loading runs in layers, each checking what the next relies on:
//!
//! 1. `container`: the GLB header and chunks, the refused required extensions (before
//!    anything else), the JSON text, and every buffer's bytes;
//! 2. `accessor`: every buffer view and accessor range, sparse parts included, against the
//!    bytes actually present — before any element is read;
//! 3. `nodes`: references, the tree shape (one parent per node, no cycles) and transforms;
//! 4. `animation`: every channel checked, kept as the scene's format-free channels;
//! 5. `mesh`: triangulation, morph targets, joint sets and (for renders) shading
//!    attributes, checked; `material`: materials, textures, images and lights (renders).
//!
//! The loader then builds a [`Rig`] (node graph, channels, skins, mesh instances) and asks
//! it for the pose: positions in f64, rounded once to f32 (`crate::scene::rig`). The rig is
//! kept in the scene only when the file animates, so [`Scene::evaluate`] can re-pose it
//! without the file.
//!
//! Triangle ids follow the contract's order (`proto/scenes.md`): the default scene's nodes
//! in pre-order, for each node its mesh's primitives in order, each primitive's triangles
//! in index order.

mod accessor;
mod animation;
mod container;
mod material;
mod mesh;
mod nodes;

use std::path::Path;
use std::sync::Arc;

use glam::{Vec2, Vec4};
use gltf::json;
use gltf::json::validation::Checked;

use super::{LoadOptions, Parts};
use crate::scene::rig::{Compute, Instance, Item, Pose, Rig};
use crate::scene::{Projection, Scene, SceneError, Shading};

pub use accessor::MAX_VIEWLESS_VALUES;
pub use container::REFUSED_EXTENSIONS;

/// Most triangles a scene may have. Instancing lets a small file ask for a huge scene
/// (nodes × triangles per mesh); this bound is checked from the document before the
/// triangles are allocated. 2^28 triangles are 9 GiB of positions.
pub const MAX_TRIANGLES: u64 = 1 << 28;

/// Errors of glTF loading. Each names what is wrong and where (indices into the glTF
/// arrays, byte offsets), so that a user can find the problem in the file.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GltfError {
    /// The GLB header is short, has another version, or there is no JSON chunk.
    #[error("GLB header: {0}")]
    GlbHeader(String),
    /// The GLB header's total length disagrees with the bytes present (a truncated file).
    #[error(
        "GLB header declares {declared} bytes but the file has {actual} (truncated or padded file)"
    )]
    GlbLength {
        /// Length in the header.
        declared: usize,
        /// Bytes present.
        actual: usize,
    },
    /// A GLB chunk is malformed: its length runs past the end, or it has the wrong type.
    #[error("GLB chunk {index} at byte {offset}: {reason}")]
    GlbChunk {
        /// Chunk number (0 is the JSON chunk).
        index: usize,
        /// Byte offset of the chunk header in the file.
        offset: usize,
        /// What is wrong.
        reason: String,
    },
    /// The JSON text is malformed or does not have glTF's shape.
    #[error("invalid glTF JSON: {detail}")]
    Json {
        /// 1-based line of the error (0 when unknown).
        line: usize,
        /// 1-based column of the error (0 when unknown).
        column: usize,
        /// The parser's message, with its location.
        detail: String,
    },
    /// A required extension changes how geometry is stored and rayd does not decode it.
    #[error(
        "required extension {0} is not supported (rayd cannot decode geometry stored with it)"
    )]
    UnsupportedExtension(String),
    /// The file has no scenes: there is nothing to trace.
    #[error("the file has no scenes: there is nothing to trace")]
    NoScenes,
    /// An index into one of the document's arrays points past its end.
    #[error("{from} refers to {kind} {index}, but the file has {count}")]
    DanglingReference {
        /// Who refers ("node 3", "accessor 2 sparse indices").
        from: String,
        /// The array referred to ("mesh", "accessor"…).
        kind: &'static str,
        /// The index given.
        index: usize,
        /// The array's length.
        count: usize,
    },
    /// A buffer has no uri and is not the GLB BIN chunk.
    #[error("buffer {buffer} has no uri and there is no GLB BIN chunk for it")]
    NoBufferData {
        /// Buffer index.
        buffer: usize,
    },
    /// A buffer's data URI is malformed.
    #[error("buffer {buffer}: bad data URI: {reason}")]
    BadDataUri {
        /// Buffer index.
        buffer: usize,
        /// What is wrong.
        reason: String,
    },
    /// A buffer's URI has a scheme other than `data:` or is an absolute path.
    #[error("buffer {buffer}: URI {uri:?} is not supported (only data: URIs and relative paths)")]
    UnsupportedUri {
        /// Buffer index.
        buffer: usize,
        /// The URI.
        uri: String,
    },
    /// A buffer's URI is a relative path that leaves the file's directory (`..`, or one that
    /// decodes to a root or a drive); nothing was opened.
    #[error("buffer {buffer}: URI {uri:?} leaves the file's directory (`..`, a root or a drive): refused")]
    UriEscapes {
        /// Buffer index.
        buffer: usize,
        /// The URI.
        uri: String,
    },
    /// A buffer's `data:` URI decodes to another number of bytes than its `byteLength`.
    #[error("buffer {buffer}: its data: URI decodes to {actual} bytes but byteLength is {declared} (they must be equal)")]
    DataUriLength {
        /// Buffer index.
        buffer: usize,
        /// `byteLength`.
        declared: u64,
        /// Bytes the URI decodes to.
        actual: u64,
    },
    /// The GLB `BIN` chunk is longer than buffer 0's `byteLength` plus 3 bytes of padding.
    #[error("GLB BIN chunk has {actual} bytes but buffer 0's byteLength is {declared} (at most 3 bytes of padding may follow)")]
    BinChunkTooLong {
        /// `byteLength`.
        declared: u64,
        /// The chunk's length.
        actual: u64,
    },
    /// A buffer is stored in a separate file, but no directory was given to find it in
    /// (e.g. a `.gltf` uploaded on its own): only embedded buffers are allowed.
    #[error("buffer {buffer} refers to external file {uri:?}, but only embedded buffers are allowed here")]
    ExternalBufferNotAllowed {
        /// Buffer index.
        buffer: usize,
        /// The URI.
        uri: String,
    },
    /// A side-by-side buffer file cannot be read.
    #[error("buffer {buffer}: cannot read {path} (uri {uri:?}): {detail}")]
    MissingBuffer {
        /// Buffer index.
        buffer: usize,
        /// The URI.
        uri: String,
        /// The path tried.
        path: String,
        /// The OS error.
        detail: String,
    },
    /// A buffer has fewer bytes than its `byteLength`.
    #[error(
        "buffer {buffer}: byteLength is {declared} but only {actual} bytes of data are present"
    )]
    BufferTooShort {
        /// Buffer index.
        buffer: usize,
        /// `byteLength`.
        declared: u64,
        /// Bytes present.
        actual: u64,
    },
    /// A buffer view's byte range lies outside its buffer.
    #[error("bufferView {view}: bytes {offset}..{end} lie outside buffer {buffer} of {buffer_length} bytes")]
    BufferViewOutOfRange {
        /// View index.
        view: usize,
        /// Buffer index.
        buffer: usize,
        /// `byteOffset`.
        offset: u64,
        /// `byteOffset + byteLength` (saturated).
        end: u64,
        /// The buffer's length.
        buffer_length: u64,
    },
    /// A buffer view is malformed (bad stride).
    #[error("bufferView {view}: {reason}")]
    BadBufferView {
        /// View index.
        view: usize,
        /// What is wrong.
        reason: String,
    },
    /// An accessor's elements run past the end of its buffer view.
    #[error("accessor {accessor}: its elements (from byte {offset}) end at byte {end} of bufferView {view}, which has {view_length} bytes")]
    AccessorOutOfRange {
        /// Accessor index.
        accessor: usize,
        /// View index.
        view: usize,
        /// The accessor's `byteOffset`.
        offset: u64,
        /// End of its last element (saturated).
        end: u64,
        /// The view's length.
        view_length: u64,
    },
    /// A sparse accessor's indices or values run past the end of their buffer view.
    #[error("accessor {accessor}: sparse {part} (from byte {offset}) end at byte {end} of bufferView {view}, which has {view_length} bytes")]
    SparseOutOfRange {
        /// Accessor index.
        accessor: usize,
        /// `"indices"` or `"values"`.
        part: &'static str,
        /// View index.
        view: usize,
        /// `byteOffset`.
        offset: u64,
        /// End of the part (saturated).
        end: u64,
        /// The view's length.
        view_length: u64,
    },
    /// A sparse index points past the accessor's elements.
    #[error("accessor {accessor}: sparse entry {entry} substitutes element {index}, but the accessor has {count}")]
    SparseIndexOutOfRange {
        /// Accessor index.
        accessor: usize,
        /// Sparse entry number.
        entry: usize,
        /// The index it gives.
        index: usize,
        /// The accessor's count.
        count: usize,
    },
    /// An accessor is malformed or of the wrong type for its use.
    #[error("accessor {accessor}: {reason}")]
    BadAccessor {
        /// Accessor index.
        accessor: usize,
        /// What is wrong.
        reason: String,
    },
    /// Accessors without a buffer view (zeros plus sparse values) ask for more memory than
    /// allowed: they cost no file bytes, so their total is bounded.
    #[error("accessor {accessor}: accessors without a bufferView would hold {values} values, more than the limit of {limit}")]
    TooLarge {
        /// Accessor index.
        accessor: usize,
        /// Values (elements × components) asked for, this accessor and earlier ones.
        values: u64,
        /// [`MAX_VIEWLESS_VALUES`].
        limit: u64,
    },
    /// A vertex index points past the primitive's vertices.
    #[error("mesh {mesh} primitive {primitive}: index {index} at position {slot} of accessor {accessor} is out of range ({vertices} vertices)")]
    IndexOutOfRange {
        /// Mesh index.
        mesh: usize,
        /// Primitive index.
        primitive: usize,
        /// The indices accessor.
        accessor: usize,
        /// Position within the indices.
        slot: usize,
        /// The index value.
        index: u64,
        /// The POSITION count.
        vertices: usize,
    },
    /// A stored position (or morph target position delta) is NaN or infinite.
    #[error("accessor {accessor}: position {element} is not finite")]
    NonFinitePosition {
        /// Accessor index.
        accessor: usize,
        /// Element index.
        element: usize,
    },
    /// The scene cannot be posed: a node's transform, an animation, the time, a skin's
    /// joint or a world position that evaluation refuses. One type for these whether they
    /// show up while loading or while evaluating a loaded scene at a new time.
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// The node graph has a cycle; `nodes` lists it, parent before child, first = last.
    #[error("node cycle: {}", .nodes.iter().map(|n| n.to_string()).collect::<Vec<_>>().join(" -> "))]
    NodeCycle {
        /// The cycle, e.g. `[0, 1, 0]`.
        nodes: Vec<usize>,
    },
    /// A node is a child twice (of one parent or of two); glTF nodes have one parent.
    #[error("node {node} is listed as a child of node {first} and of node {second}; a node may have only one parent")]
    NodeMultipleParents {
        /// The child.
        node: usize,
        /// Its first parent.
        first: usize,
        /// The second listing (may equal `first`).
        second: usize,
    },
    /// A scene lists a node that is not a root, or lists it twice.
    #[error("scene {scene} lists node {node} as a root, but {reason}")]
    BadSceneRoot {
        /// Scene index.
        scene: usize,
        /// Node index.
        node: usize,
        /// Why.
        reason: String,
    },
    /// A mesh primitive is malformed.
    #[error("mesh {mesh} primitive {primitive}: {reason}")]
    BadPrimitive {
        /// Mesh index.
        mesh: usize,
        /// Primitive index.
        primitive: usize,
        /// What is wrong.
        reason: String,
    },
    /// A mesh is malformed as a whole (its primitives disagree, or its `weights`).
    #[error("mesh {mesh}: {reason}")]
    BadMesh {
        /// Mesh index.
        mesh: usize,
        /// What is wrong.
        reason: String,
    },
    /// A skin is malformed.
    #[error("skin {skin}: {reason}")]
    BadSkin {
        /// Skin index.
        skin: usize,
        /// What is wrong.
        reason: String,
    },
    /// A camera is malformed.
    #[error("camera {camera}: {reason}")]
    BadCamera {
        /// Camera index.
        camera: usize,
        /// What is wrong.
        reason: String,
    },
    /// A material is malformed (a factor out of range, a bad alpha mode).
    #[error("material {material}: {reason}")]
    BadMaterial {
        /// Material index.
        material: usize,
        /// What is wrong.
        reason: String,
    },
    /// A sampler has an invalid filter or wrap mode.
    #[error("sampler {sampler}: {reason}")]
    BadSampler {
        /// Sampler index.
        sampler: usize,
        /// What is wrong.
        reason: String,
    },
    /// An image's bytes cannot be found.
    #[error("image {image}: {reason}")]
    BadImage {
        /// Image index.
        image: usize,
        /// What is wrong.
        reason: String,
    },
    /// A KHR_lights_punctual light is malformed.
    #[error("light {light}: {reason}")]
    BadLight {
        /// Index in `KHR_lights_punctual.lights`.
        light: usize,
        /// What is wrong.
        reason: String,
    },
    /// The shading data would have more vertices than a u32 can number.
    #[error("the scene's primitives would have {count} shading vertices, more than the limit of {limit}")]
    TooManyVertices {
        /// Vertices asked for (instancing included).
        count: u64,
        /// `u32::MAX`.
        limit: u64,
    },
    /// The scene would have more triangles than allowed ([`MAX_TRIANGLES`], or the
    /// service's `--max-triangles`).
    #[error("the scene would have {count} triangles, more than the limit of {limit}")]
    TooManyTriangles {
        /// Triangles the document asks for.
        count: u64,
        /// The limit.
        limit: u64,
    },
}

impl GltfError {
    /// The byte of the file where the error lies, where the error names one (the GLB
    /// container's): what a problem document's `byte_offset` names.
    pub fn byte_offset(&self) -> Option<u64> {
        match self {
            GltfError::GlbChunk { offset, .. } => Some(*offset as u64),
            GltfError::GlbLength { .. } => Some(8),
            _ => None,
        }
    }
}

/// Loads a glTF scene from the bytes of a `.glb` or `.gltf` file: geometry only (see
/// [`load_with`]).
///
/// `base_dir` is the directory of a `.gltf` whose buffers are side-by-side files; with
/// `None`, only embedded buffers (GLB BIN chunk, base64 data URIs) are allowed and an
/// external URI is [`GltfError::ExternalBufferNotAllowed`]. `options.time` evaluates every
/// animation at that time; `None` is the static pose (`proto/scenes.md`).
///
/// The node graph must be a forest, as glTF requires: a node listed as a child twice, a
/// cycle, or a scene root that has a parent or is listed twice is an error (never a loop,
/// never a duplicated instance). Non-FLOAT positions are accepted only when the file uses
/// `KHR_mesh_quantization`. A skinned node's primitives without `JOINTS_n`/`WEIGHTS_n` are
/// placed by the node's world transform. Output is bounded by [`MAX_TRIANGLES`], and memory
/// for accessors without a buffer view by [`MAX_VIEWLESS_VALUES`]; everything else is
/// bounded by the size of the file.
pub fn load(
    bytes: &[u8],
    base_dir: Option<&Path>,
    options: &LoadOptions,
) -> Result<Scene, GltfError> {
    load_with(bytes, base_dir, options, Parts::Geometry)
}

/// [`load`], holding the parts asked for: [`Parts::Geometry`] keeps positions (and the
/// rig when the file animates); [`Parts::Shading`] adds per-vertex shading attributes,
/// per-triangle materials, materials, textures with their encoded images, and lights.
pub fn load_with(
    bytes: &[u8],
    base_dir: Option<&Path>,
    options: &LoadOptions,
    parts: Parts,
) -> Result<Scene, GltfError> {
    load_limited(bytes, base_dir, options, parts, MAX_TRIANGLES)
}

/// [`load_with`] refusing scenes of more than `max_triangles` triangles (at most
/// [`MAX_TRIANGLES`]), counted from the document before any is placed: the service's
/// `--max-triangles`, so that a small upload whose nodes instance one mesh many times cannot
/// make the server allocate gigabytes.
pub fn load_limited(
    bytes: &[u8],
    base_dir: Option<&Path>,
    options: &LoadOptions,
    parts: Parts,
    max_triangles: u64,
) -> Result<Scene, GltfError> {
    let max_triangles = max_triangles.min(MAX_TRIANGLES);
    if let Some(t) = options.time.filter(|t| !t.is_finite()) {
        return Err(SceneError::BadTime(t).into());
    }
    let container = container::split(bytes)?;
    let root = container::parse(&container)?;
    if root.scenes.is_empty() {
        return Err(GltfError::NoScenes);
    }
    let scene_index = root.scene.map_or(0, |s| s.value());
    if scene_index >= root.scenes.len() {
        return Err(GltfError::DanglingReference {
            from: "the document's default scene".to_string(),
            kind: "scene",
            index: scene_index,
            count: root.scenes.len(),
        });
    }
    let buffers = container::resolve_buffers(&root, container.bin, base_dir)?;
    let mut data = accessor::Data::new(&root, buffers)?;
    let quantized = root
        .extensions_used
        .iter()
        .any(|e| e == "KHR_mesh_quantization");
    let shading = parts == Parts::Shading;
    // Appearance read (and checked) even where it is not kept.
    let appearance_read = shading || parts == Parts::CheckedGeometry;

    let parents = nodes::check(&root)?;
    let order = nodes::scene_order(&root, scene_index, &parents)?;
    let morph_targets = mesh::morph_target_counts(&root)?;
    let animations = animation::load(&mut data, quantized, &morph_targets)?;
    let mut rig = Rig {
        nodes: nodes::rig_nodes(&root),
        roots: (0..root.nodes.len())
            .filter(|&i| parents[i].is_none())
            .collect(),
        channels: animations.channels,
        skins: vec![None; root.skins.len()],
        camera_count: root.cameras.len(),
        ..Rig::default()
    };
    // The transforms of the pose asked for are checked before any mesh is decoded.
    rig.check_transforms(options.time)?;

    // Bound the output from the document alone, before decoding anything.
    let mut meshes = mesh::Meshes::new(quantized, shading);
    let mut per_mesh: Vec<Option<u64>> = vec![None; root.meshes.len()];
    let mut total = 0u64;
    for &n in &order {
        if let Some(m) = root.nodes[n].mesh.map(|m| m.value()) {
            let count = match per_mesh[m] {
                Some(c) => c,
                None => {
                    let c = meshes.triangle_count(&data, m)?;
                    per_mesh[m] = Some(c);
                    c
                }
            };
            total = total.saturating_add(count);
        }
    }
    if total > max_triangles {
        return Err(GltfError::TooManyTriangles {
            count: total,
            limit: max_triangles,
        });
    }

    let appearance = if appearance_read {
        Some(material::load(&root, &data, base_dir)?).filter(|_| shading)
    } else {
        None
    };
    let mut lights = Vec::new();
    // Per placed primitive, its shading attributes (renders only), in id order.
    let mut placed: Vec<Arc<mesh::PrimShading>> = Vec::new();
    for &n in &order {
        let node = &root.nodes[n];
        if let Some(m) = node.mesh.map(|m| m.value()) {
            let skin = node.skin.map(|s| s.value());
            if let Some(s) = skin {
                if rig.skins[s].is_none() {
                    rig.skins[s] = Some(mesh::load_skin(&mut data, s, root.nodes.len())?);
                }
            }
            let joints = skin.and_then(|s| rig.skins[s].as_ref().map(|k| (s, k.joints.len())));
            let mut primitives = Vec::new();
            for pi in 0..root.meshes[m].primitives.len() {
                let Some(d) = meshes.prim(&mut data, m, pi)? else {
                    continue;
                };
                if let Some((s, count)) = joints.filter(|_| !d.prim.skin_sets.is_empty()) {
                    mesh::Meshes::check_joints(&d.prim, m, pi, s, count)?;
                }
                if shading {
                    placed.push(d.shading.clone());
                }
                primitives.push((pi, d.prim));
            }
            rig.items.push(Item::Mesh(Instance {
                node: n,
                mesh: m,
                skin,
                weights: static_weights(&root, n, m),
                primitives,
            }));
        }
        if let Some(c) = node.camera.map(|c| c.value()) {
            let (projection, clip) = projection(&root, c)?;
            rig.items.push(Item::Camera {
                node: n,
                index: c,
                projection,
                clip,
            });
        }
        if appearance_read {
            if let Some(light) = material::light(&root, n)?.filter(|_| shading) {
                lights.push(light);
                rig.items.push(Item::Light { node: n });
            }
        }
    }
    let prims = || {
        rig.items.iter().flat_map(|i| match i {
            Item::Mesh(inst) => inst.primitives.as_slice(),
            _ => &[],
        })
    };
    if shading {
        let vertices: u64 = prims().map(|(_, p)| p.vertices() as u64).sum();
        if vertices > u64::from(u32::MAX) {
            return Err(GltfError::TooManyVertices {
                count: vertices,
                limit: u64::from(u32::MAX),
            });
        }
        rig.normals = prims().any(|(_, p)| p.normals.is_some());
        rig.tangents = prims().any(|(_, p)| p.tangents.is_some());
    }
    let compute = if shading {
        Compute::PositionsAndNormals
    } else {
        Compute::Positions
    };
    let mut pose = Pose::default();
    rig.pose(options.time, compute, &mut pose)?;
    for (light, m) in lights.iter_mut().zip(&pose.lights) {
        light.to_world = *m;
    }
    let shading_data = shading.then(|| shading_data(&rig, &placed, &mut pose));
    let animated = !rig.channels.is_empty();
    let appearance = appearance.unwrap_or(material::Appearance {
        materials: Vec::new(),
        textures: Vec::new(),
        images: Vec::new(),
    });
    Ok(Scene {
        triangles: pose.triangles,
        meshes: root.meshes.len(),
        cameras: pose.cameras,
        animations: animations.infos,
        shading: shading_data,
        materials: appearance.materials,
        textures: appearance.textures,
        images: appearance.images,
        lights,
        // A file without animation keeps no rig: its pose never changes.
        rig: animated.then(|| Arc::new(rig)),
    })
}

/// Shading data in id order: corners renumbered to the placed primitives' vertices,
/// materials per triangle, pose-independent attributes, and the pose's normals.
fn shading_data(rig: &Rig, placed: &[Arc<mesh::PrimShading>], pose: &mut Pose) -> Shading {
    let prims: Vec<_> = rig
        .items
        .iter()
        .flat_map(|i| match i {
            Item::Mesh(inst) => inst.primitives.as_slice(),
            _ => &[],
        })
        .map(|(_, p)| p)
        .collect();
    let triangles: usize = prims.iter().map(|p| p.corners.len() / 3).sum();
    let mut out = Shading {
        corners: Vec::with_capacity(triangles),
        materials: Vec::with_capacity(triangles),
        normals: std::mem::take(&mut pose.normals),
        tangents: std::mem::take(&mut pose.tangents),
        mirrored: std::mem::take(&mut pose.mirrored),
        ..Shading::default()
    };
    let any_uv0 = placed.iter().any(|s| s.uv0.is_some());
    let any_uv1 = placed.iter().any(|s| s.uv1.is_some());
    let any_color = placed.iter().any(|s| s.colors.is_some());
    let mut base = 0u32;
    for (prim, s) in prims.iter().zip(placed) {
        let n = prim.vertices();
        for c in prim.corners.chunks_exact(3) {
            out.corners.push([base + c[0], base + c[1], base + c[2]]);
        }
        let material = s.material.map_or(Shading::DEFAULT_MATERIAL, |m| m as u32);
        out.materials
            .extend(std::iter::repeat_n(material, prim.corners.len() / 3));
        let uv = |dst: &mut Vec<Vec2>, src: &Option<Arc<[f64]>>| match src {
            Some(v) => dst.extend(
                v.chunks_exact(2)
                    .map(|c| Vec2::new(c[0] as f32, c[1] as f32)),
            ),
            None => dst.extend(std::iter::repeat_n(Vec2::ZERO, n)),
        };
        if any_uv0 {
            uv(&mut out.uv0, &s.uv0);
        }
        if any_uv1 {
            uv(&mut out.uv1, &s.uv1);
        }
        if any_color {
            match &s.colors {
                Some((v, w)) => out.colors.extend(v.chunks_exact(*w).map(|c| {
                    let a = if *w == 4 { c[3] as f32 } else { 1.0 };
                    Vec4::new(c[0] as f32, c[1] as f32, c[2] as f32, a)
                })),
                None => out.colors.extend(std::iter::repeat_n(Vec4::ONE, n)),
            }
        }
        // Vertices are counted against u32 before the pose is computed.
        base += n as u32;
    }
    out
}

/// Static morph weights of node `n` instancing mesh `m`: the node's, else the mesh's, else
/// none (all zero).
fn static_weights(root: &json::Root, n: usize, m: usize) -> Vec<f64> {
    root.nodes[n]
        .weights
        .as_ref()
        .or(root.meshes[m].weights.as_ref())
        .map(|w| w.iter().map(|&x| f64::from(x)).collect())
        .unwrap_or_default()
}

/// Camera `c`'s projection, checked.
/// Camera `c`'s projection and its clipping planes (`Camera::clip`). A clipping plane
/// glTF would not allow (a negative or non-finite `znear`, a `zfar` not beyond it) clips
/// nothing on its side, as a viewer that ignored clipping would show it.
fn projection(root: &json::Root, c: usize) -> Result<(Projection, [f64; 2]), GltfError> {
    use json::camera::Type;
    let cam = &root.cameras[c];
    let bad = |reason: &str| GltfError::BadCamera {
        camera: c,
        reason: reason.to_string(),
    };
    let finite_pos = |v: f32| v.is_finite() && v > 0.0;
    match cam.type_ {
        Checked::Valid(Type::Perspective) => {
            let p = cam
                .perspective
                .as_ref()
                .ok_or_else(|| bad("type is perspective but there is no perspective object"))?;
            if !finite_pos(p.yfov) {
                return Err(bad("yfov must be a positive finite number"));
            }
            if p.aspect_ratio.is_some_and(|a| !finite_pos(a)) {
                return Err(bad("aspectRatio must be a positive finite number"));
            }
            Ok((
                Projection::Perspective {
                    yfov: f64::from(p.yfov),
                    aspect: p.aspect_ratio.map(f64::from),
                },
                clip(p.znear, p.zfar),
            ))
        }
        Checked::Valid(Type::Orthographic) => {
            let o = cam
                .orthographic
                .as_ref()
                .ok_or_else(|| bad("type is orthographic but there is no orthographic object"))?;
            if !o.xmag.is_finite() || !o.ymag.is_finite() || o.xmag == 0.0 || o.ymag == 0.0 {
                return Err(bad("xmag and ymag must be finite and non-zero"));
            }
            Ok((
                Projection::Orthographic {
                    xmag: f64::from(o.xmag),
                    ymag: f64::from(o.ymag),
                },
                clip(o.znear, Some(o.zfar)),
            ))
        }
        Checked::Invalid => Err(bad("invalid type")),
    }
}

/// glTF's `znear` and `zfar` as `Camera::clip`.
fn clip(znear: f32, zfar: Option<f32>) -> [f64; 2] {
    let near = f64::from(znear);
    let near = if near.is_finite() && near > 0.0 {
        near
    } else {
        0.0
    };
    let far = zfar.map(f64::from).filter(|f| f.is_finite() && *f > near);
    [near, far.unwrap_or(f64::INFINITY)]
}
