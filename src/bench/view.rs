//! Benchmark views: a camera, and for interior views a closed room around the scene so
//! that every ray hits something and every bounce keeps the full batch.

use super::{BenchError, CameraChoice};
use crate::geometry::{Aabb, Triangle};
use crate::render::camera::ViewCamera;
use crate::scene::Scene;

/// Whether the camera looks at the scene from inside a closed room.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ViewKind {
    /// Scene plus a closed box around it and the camera: every ray hits. This is where ray
    /// tracers are compared.
    Interior,
    /// The scene alone: rays that miss leave the batch.
    Exterior,
}

impl ViewKind {
    /// The command line's name.
    pub fn name(self) -> &'static str {
        match self {
            ViewKind::Interior => "interior",
            ViewKind::Exterior => "exterior",
        }
    }

    /// Parses the command line's name.
    pub fn parse(s: &str) -> Option<ViewKind> {
        [ViewKind::Interior, ViewKind::Exterior]
            .into_iter()
            .find(|v| v.name() == s)
    }
}

/// A view ready to make rays.
pub struct View {
    /// The traced triangles: the scene's, then (interior views) the room's 12.
    pub triangles: Vec<Triangle>,
    /// The camera.
    pub camera: ViewCamera,
    /// Image size.
    pub width: u32,
    /// Image size.
    pub height: u32,
    /// Length of the scene's bounding-box diagonal (sets the AO distance).
    pub diagonal: f32,
    /// The camera, in words, for the report.
    pub camera_description: String,
}

/// The 12 triangles of a box, in a fixed order.
pub fn box_triangles(b: &Aabb) -> Vec<Triangle> {
    let c = |i: usize| {
        [
            if i & 1 == 0 { b.min[0] } else { b.max[0] },
            if i & 2 == 0 { b.min[1] } else { b.max[1] },
            if i & 4 == 0 { b.min[2] } else { b.max[2] },
        ]
    };
    // Each face as a quad of corner indices.
    const FACES: [[usize; 4]; 6] = [
        [0, 2, 6, 4], // -x
        [1, 5, 7, 3], // +x
        [0, 4, 5, 1], // -y
        [2, 3, 7, 6], // +y
        [0, 1, 3, 2], // -z
        [4, 6, 7, 5], // +z
    ];
    FACES
        .iter()
        .flat_map(|f| {
            [
                Triangle {
                    v: [c(f[0]), c(f[1]), c(f[2])],
                },
                Triangle {
                    v: [c(f[0]), c(f[2]), c(f[3])],
                },
            ]
        })
        .collect()
}

/// Where the default interior camera stands, in units of the room's half extents from the
/// centre.
const INTERIOR_EYE: [f64; 3] = [0.45, 0.3, 0.9];

/// The room of an interior view: the scene's box grown by a quarter of its extent on every
/// side (flat axes by a quarter of the largest extent), so that bounces go back and forth
/// between the model and walls close to it, as in an architectural interior.
pub fn room_around(bounds: &Aabb) -> Aabb {
    let e = bounds.extent();
    let largest = e[0].max(e[1]).max(e[2]).max(1e-3);
    let mut room = *bounds;
    for k in 0..3 {
        let grow = 0.25 * e[k].max(0.25 * largest);
        room.min[k] -= grow;
        room.max[k] += grow;
    }
    room
}

impl View {
    /// Makes the view of `scene`.
    pub fn new(
        scene: &Scene,
        kind: ViewKind,
        choice: &CameraChoice,
        width: u32,
        height: u32,
    ) -> Result<View, BenchError> {
        let bounds = scene
            .bounds()
            .ok_or_else(|| BenchError::Config("the scene has no triangles to benchmark".into()))?;
        View::around(scene, bounds, kind, choice, width, height)
    }

    /// Makes the view of `scene` as if its triangles filled `bounds`: a moving scene's
    /// room and default camera are set from the box of all its frames, so that every frame
    /// stays inside the room.
    pub fn around(
        scene: &Scene,
        bounds: Aabb,
        kind: ViewKind,
        choice: &CameraChoice,
        width: u32,
        height: u32,
    ) -> Result<View, BenchError> {
        let aspect = width as f64 / height as f64;
        let c = bounds.center().map(f64::from);
        let room = room_around(&bounds);
        let half_room = [0, 1, 2].map(|k| 0.5 * (room.max[k] as f64 - room.min[k] as f64));
        // The bench's default is the scene's camera 0 when a node places it; a camera the
        // file lists but places nowhere is not one the scene has (the default view then).
        let no_camera = !matches!(scene.cameras.first(), Some(Some(_)));
        let (camera, description) = match choice {
            CameraChoice::Auto if no_camera && kind == ViewKind::Interior => {
                // Inside the room, outside the model's box (0.9 of the room's half depth is
                // past the model's face), looking at the model's centre: the model fills
                // most of the frame and the walls the rest.
                let eye = [0, 1, 2].map(|k| c[k] + INTERIOR_EYE[k] * half_room[k]);
                (
                    ViewCamera::look_at(eye, c, [0.0, 1.0, 0.0], 60.0, aspect)?,
                    "default interior view".to_string(),
                )
            }
            _ => {
                let description = match choice {
                    CameraChoice::Scene(i) => format!("scene camera {i}"),
                    CameraChoice::LookAt {
                        eye, target, fov, ..
                    } => {
                        format!("eye {eye:?} target {target:?} fov {fov}")
                    }
                    CameraChoice::Auto if no_camera => "default framing view".into(),
                    CameraChoice::Auto => "scene camera 0".into(),
                };
                // The bench keeps its own default of the scene's camera 0 (a render's
                // default view frames the bounds even when the scene has cameras).
                let choice = match choice {
                    CameraChoice::Auto if !no_camera => &CameraChoice::Scene(0),
                    other => other,
                };
                (ViewCamera::choose(choice, scene, aspect)?, description)
            }
        };
        let mut triangles = scene.triangles.clone();
        if kind == ViewKind::Interior {
            // A scene camera may stand outside the room: grow the room to hold it.
            let mut room = room;
            let eye = camera.eye();
            let margin = 0.05 * bounds.diagonal() as f64;
            for (k, e) in eye.iter().enumerate() {
                room.min[k] = room.min[k].min((e - margin) as f32);
                room.max[k] = room.max[k].max((e + margin) as f32);
            }
            triangles.extend(box_triangles(&room));
        }
        Ok(View {
            triangles,
            camera,
            width,
            height,
            diagonal: bounds.diagonal(),
            camera_description: description,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_is_closed_and_not_degenerate() {
        let b = Aabb {
            min: [-1.0, -2.0, -3.0],
            max: [1.0, 2.0, 3.0],
        };
        let t = box_triangles(&b);
        assert_eq!(t.len(), 12);
        assert!(t.iter().all(|t| !t.is_degenerate()));
        // Every edge is shared by exactly two triangles: the box is closed.
        let mut edges = std::collections::HashMap::new();
        for tri in &t {
            for k in 0..3 {
                let (a, b) = (tri.v[k], tri.v[(k + 1) % 3]);
                let key = if a < b { (a, b) } else { (b, a) };
                let key = (key.0.map(f32::to_bits), key.1.map(f32::to_bits));
                *edges.entry(key).or_insert(0) += 1;
            }
        }
        assert!(edges.values().all(|&n| n == 2));
    }
}
