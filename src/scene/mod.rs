//! The domain scene: a flat, validated triangle soup in world space plus the few facts the
//! commands report (meshes, cameras, animations). Format-free: `formats` builds it, and the
//! accelerators never see glTF.

use crate::geometry::{Aabb, Triangle};

/// A camera of the scene, in world space.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    /// Camera-to-world transform (column-major 4×4, f64). The camera looks down its local
    /// −Z with +Y up, as glTF defines.
    pub to_world: [[f64; 4]; 4],
    /// How the camera projects.
    pub projection: Projection,
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
    /// Cameras, in the order the default scene's nodes reach them.
    pub cameras: Vec<Camera>,
    /// Animations of the file.
    pub animations: Vec<AnimationInfo>,
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
