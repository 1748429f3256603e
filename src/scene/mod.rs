//! The domain scene: a flat, validated triangle soup in world space (what every core
//! traces), plus what rendering and animation need: shading attributes and materials,
//! textures (still encoded), lights, cameras, and the [`Rig`] that re-poses the triangles
//! at any time. Format-free: `formats` builds it, and the accelerators never see glTF.
//!
//! Only what a job needs is held: a geometry-only load (ray batches) has no shading data,
//! materials or textures; a scene whose file does not animate has no rig. See
//! `proto/scenes.md` for what each part holds and how [`Scene::evaluate`] works.

pub mod material;
pub mod rig;

use std::sync::Arc;

use glam::{Vec2, Vec3, Vec4};

use crate::geometry::{Aabb, Triangle};

pub use material::{
    AlphaMode, Filter, Image, Light, LightKind, Material, Mipmap, Sampler, Specular, Texture,
    TextureRef, TextureTransform, Wrap,
};
pub use rig::{Compute, Pose, Rig};

/// Errors of evaluating a scene at a time. The loader reports the same problems in a file
/// as these (`GltfError::Scene`), so that a file's problem reads the same whether it shows
/// up while loading or while evaluating.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum SceneError {
    /// The requested animation time is NaN or infinite.
    #[error("animation time {0} is not a finite number")]
    BadTime(f64),
    /// An animation cannot be sampled at the time (a rotation that is zero there).
    #[error("animation {animation}: {reason}")]
    BadAnimation {
        /// Animation index.
        animation: usize,
        /// What is wrong (names the channel).
        reason: String,
    },
    /// A node's transform is not usable at the time.
    #[error("node {node}: {reason}")]
    BadNode {
        /// Node index.
        node: usize,
        /// What is wrong.
        reason: String,
    },
    /// A vertex's world position is not finite in f32 (overflow through transforms).
    #[error("node {node} mesh {mesh} primitive {primitive}: vertex {vertex} is not finite in world space")]
    NonFiniteWorldPosition {
        /// Node index.
        node: usize,
        /// Mesh index.
        mesh: usize,
        /// Primitive index.
        primitive: usize,
        /// Vertex index.
        vertex: usize,
    },
    /// A vertex is weighted to a joint the skin does not have.
    #[error("mesh {mesh} primitive {primitive}: vertex {vertex} uses joint {joint}, but skin {skin} has {joints} joints")]
    JointOutOfRange {
        /// Mesh index.
        mesh: usize,
        /// Primitive index.
        primitive: usize,
        /// Vertex index.
        vertex: usize,
        /// The joint number.
        joint: usize,
        /// Skin index.
        skin: usize,
        /// Number of joints of the skin.
        joints: usize,
    },
}

/// Per-vertex shading attributes and per-triangle materials, in triangle-id order.
///
/// Vertices are those of each (mesh instance, primitive) in id order, so a vertex belongs
/// to one placed primitive and its normal can be in world space. A triangle's vertices are
/// `corners[id]`. An attribute array is empty when no primitive of the scene has it, and
/// otherwise has one entry per vertex, with a neutral value where a primitive lacks it:
/// a zero normal (use the face normal, as glTF says), a zero tangent, UV (0, 0), colour
/// white. Stored as `Vec3`/`Vec4` (12/16 bytes), not `Vec3A`: a quarter less memory for
/// normals; widen to `Vec3A` when computing.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Shading {
    /// Per triangle, its three vertices.
    pub corners: Vec<[u32; 3]>,
    /// Per triangle, its material: an index into [`Scene::materials`], or
    /// [`Shading::DEFAULT_MATERIAL`] for glTF's default material.
    pub materials: Vec<u32>,
    /// Unit world-space normals of the pose [`Scene::triangles`] is in.
    pub normals: Vec<Vec3>,
    /// World-space tangents of that pose, `w` the bitangent sign.
    pub tangents: Vec<Vec4>,
    /// TEXCOORD_0.
    pub uv0: Vec<Vec2>,
    /// TEXCOORD_1.
    pub uv1: Vec<Vec2>,
    /// COLOR_0, linear RGBA (RGB files get alpha 1).
    pub colors: Vec<Vec4>,
    /// One bit per triangle id of the pose: set where the triangle has no `NORMAL` and is
    /// placed by a mirroring transform (negative determinant), whose front face glTF winds
    /// clockwise. Empty when no triangle is (most scenes).
    pub mirrored: Vec<u64>,
}

impl Shading {
    /// The material index of triangles that use glTF's default material.
    pub const DEFAULT_MATERIAL: u32 = u32::MAX;

    /// Shading for `triangles` triangles without attributes (TRI1 input): three vertices
    /// each, glTF's default material, no normals (face normals are used).
    pub fn flat(triangles: usize) -> Shading {
        Shading {
            corners: (0..triangles as u32)
                .map(|t| [3 * t, 3 * t + 1, 3 * t + 2])
                .collect(),
            materials: vec![Shading::DEFAULT_MATERIAL; triangles],
            ..Shading::default()
        }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.corners.len() * 12
            + self.materials.len() * 4
            + self.normals.len() * 12
            + self.tangents.len() * 16
            + (self.uv0.len() + self.uv1.len()) * 8
            + self.colors.len() * 16
            + self.mirrored.len() * 8
    }

    /// Whether triangle `id`'s front face is the reverse of its vertex order's (see
    /// [`Shading::mirrored`](Shading#structfield.mirrored)).
    #[inline]
    pub fn is_mirrored(&self, id: usize) -> bool {
        self.mirrored
            .get(id / 64)
            .is_some_and(|w| w >> (id % 64) & 1 == 1)
    }
}

/// Sets bit `i` of `bits`, growing it as needed.
fn set_bit(bits: &mut Vec<u64>, i: usize) {
    if bits.len() <= i / 64 {
        bits.resize(i / 64 + 1, 0);
    }
    bits[i / 64] |= 1 << (i % 64);
}

/// Bytes a scene holds, by part (`rayd info`'s `bytes_by_part`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct BytesByPart {
    /// World positions (the triangles every core traces).
    pub positions: usize,
    /// Shading attributes and per-triangle materials.
    pub attributes: usize,
    /// Encoded image bytes and texture/material records.
    pub textures: usize,
    /// The rig: nodes, keyframes, skins, morph targets, source vertex data.
    pub animation: usize,
}

/// A camera of the scene, in world space.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    /// Camera-to-world transform (column-major 4×4, f64). The camera looks down its local
    /// −Z with +Y up, as glTF defines.
    pub to_world: [[f64; 4]; 4],
    /// How the camera projects.
    pub projection: Projection,
    /// Its clipping planes' distances along the view axis, glTF's `znear` and `zfar`
    /// (`+inf` for a perspective camera without one): nothing nearer or farther is seen.
    pub clip: [f64; 2],
}

/// A camera projection, as glTF stores it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Projection {
    /// Perspective with vertical field of view `yfov` (radians) and an optional aspect ratio.
    Perspective {
        /// Vertical field of view in radians.
        yfov: f64,
        /// Width / height; `None` means the image's own.
        aspect: Option<f64>,
    },
    /// Orthographic with half-extents `xmag`, `ymag`.
    Orthographic {
        /// Half width of the view volume.
        xmag: f64,
        /// Half height of the view volume.
        ymag: f64,
    },
}

/// An animation of the scene, as `rayd info` reports it.
#[derive(Clone, Debug, PartialEq)]
pub struct AnimationInfo {
    /// The animation's name (empty when the file gives none).
    pub name: String,
    /// Length in seconds: the largest input time of its samplers.
    pub duration: f64,
}

/// A loaded scene.
#[derive(Clone, Debug, Default)]
pub struct Scene {
    /// Triangles in the contract's id order (§1), world space, f32.
    pub triangles: Vec<Triangle>,
    /// Number of glTF meshes in the file (0 for TRI1).
    pub meshes: usize,
    /// The file's cameras, by their index in glTF's `cameras` array, each where the first
    /// node of the default scene (in pre-order) that places it puts it; `None` for a camera
    /// no node of the scene places.
    pub cameras: Vec<Option<Camera>>,
    /// Animations of the file.
    pub animations: Vec<AnimationInfo>,
    /// Per-vertex shading data; `None` for a geometry-only load.
    pub shading: Option<Shading>,
    /// Materials of the file (empty for a geometry-only load).
    pub materials: Vec<Material>,
    /// Textures of the file (empty for a geometry-only load).
    pub textures: Vec<Texture>,
    /// Images of the file, encoded (empty for a geometry-only load).
    pub images: Vec<Image>,
    /// Lights placed by the default scene's nodes, in pre-order (empty for a geometry-only
    /// load).
    pub lights: Vec<Light>,
    /// What re-poses the scene at a time; `None` when the file does not animate.
    pub rig: Option<Arc<Rig>>,
}

impl Scene {
    /// A scene made only of triangles (TRI1 input, tests).
    pub fn from_triangles(triangles: Vec<Triangle>) -> Scene {
        Scene {
            triangles,
            ..Scene::default()
        }
    }

    /// Bounding box of all triangles; `None` when there are none.
    pub fn bounds(&self) -> Option<Aabb> {
        bounds_of(&self.triangles)
    }

    /// Bytes held for tracing: the positions.
    pub fn bytes(&self) -> usize {
        self.triangles.len() * std::mem::size_of::<Triangle>()
    }

    /// Bytes held, by part.
    pub fn bytes_by_part(&self) -> BytesByPart {
        let records = self.materials.len() * std::mem::size_of::<Material>()
            + self.textures.len() * std::mem::size_of::<Texture>()
            + self.images.len() * std::mem::size_of::<Image>();
        BytesByPart {
            positions: self.bytes(),
            attributes: self.shading.as_ref().map_or(0, Shading::bytes),
            textures: records + self.images.iter().map(|i| i.bytes.len()).sum::<usize>(),
            animation: self.rig.as_ref().map_or(0, |r| r.bytes()),
        }
    }

    /// The pose at animation time `t` (seconds), computed from the rig without the file:
    /// the same triangles, bit for bit, as loading the file at that time. `compute` says
    /// whether shading normals and tangents are wanted too (they are only there when the
    /// scene was loaded with shading data). A scene that does not animate returns its
    /// own pose at every time.
    pub fn evaluate(&self, t: f64, compute: Compute) -> Result<Pose, SceneError> {
        let mut pose = Pose::default();
        self.evaluate_into(t, compute, &mut pose)?;
        Ok(pose)
    }

    /// [`Scene::evaluate`] into `pose`, reusing its buffers (frames of an animation).
    pub fn evaluate_into(
        &self,
        t: f64,
        compute: Compute,
        pose: &mut Pose,
    ) -> Result<(), SceneError> {
        if !t.is_finite() {
            return Err(SceneError::BadTime(t));
        }
        match &self.rig {
            Some(rig) => rig.pose(Some(t), compute, pose),
            None => {
                pose.triangles.clone_from(&self.triangles);
                pose.cameras.clone_from(&self.cameras);
                pose.lights.clear();
                pose.lights.extend(self.lights.iter().map(|l| l.to_world));
                let shading = self.shading.as_ref();
                let wanted = compute == Compute::PositionsAndNormals;
                pose.normals.clear();
                pose.tangents.clear();
                pose.mirrored.clear();
                pose.shaded = wanted;
                if let Some(s) = shading.filter(|_| wanted) {
                    pose.normals.extend_from_slice(&s.normals);
                    pose.tangents.extend_from_slice(&s.tangents);
                    pose.mirrored.extend_from_slice(&s.mirrored);
                }
                Ok(())
            }
        }
    }

    /// Replaces the scene's pose (triangles, cameras, lights, shading normals) with `pose`,
    /// e.g. one from [`Scene::evaluate`] of this scene.
    pub fn set_pose(&mut self, pose: Pose) {
        self.triangles = pose.triangles;
        self.cameras = pose.cameras;
        for (l, m) in self.lights.iter_mut().zip(pose.lights) {
            l.to_world = m;
        }
        if let Some(s) = &mut self.shading {
            if s.normals.len() == pose.normals.len() {
                s.normals = pose.normals;
            }
            if s.tangents.len() == pose.tangents.len() {
                s.tangents = pose.tangents;
            }
            if pose.shaded {
                s.mirrored = pose.mirrored;
            }
        }
    }

    /// The scene posed at time `t`: a copy sharing the rig and the images.
    pub fn at(&self, t: f64) -> Result<Scene, SceneError> {
        let compute = if self.shading.is_some() {
            Compute::PositionsAndNormals
        } else {
            Compute::Positions
        };
        let pose = self.evaluate(t, compute)?;
        let mut out = self.clone();
        out.set_pose(pose);
        Ok(out)
    }
}

/// Bounding box of `triangles`; `None` when there are none.
pub fn bounds_of(triangles: &[Triangle]) -> Option<Aabb> {
    if triangles.is_empty() {
        return None;
    }
    let mut b = Aabb::EMPTY;
    for t in triangles {
        b.union(&t.bounds());
    }
    Some(b)
}
