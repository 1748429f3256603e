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
        let aspect = width as f64 / height as f64;
        let c = bounds.center().map(f64::from);
        let radius = (0.5 * bounds.diagonal() as f64).max(1e-3);
        let (camera, description) = match choice {
            CameraChoice::Scene(i) => {
                let cam = scene.cameras.get(*i).ok_or(
                    crate::render::camera::CameraError::NoSuchCamera {
                        index: *i,
                        count: scene.cameras.len(),
                    },
                )?;
                (
                    ViewCamera::from_scene(cam, aspect)?,
                    format!("scene camera {i}"),
                )
            }
            CameraChoice::LookAt {
                eye,
                target,
                up,
                fov,
            } => (
                ViewCamera::look_at(*eye, *target, *up, *fov, aspect)?,
                format!("eye {eye:?} target {target:?} fov {fov}"),
            ),
            CameraChoice::Auto => match scene.cameras.first() {
                Some(cam) => (
                    ViewCamera::from_scene(cam, aspect)?,
                    "scene camera 0".into(),
                ),
                None if kind == ViewKind::Interior => {
                    // Close enough that the model fills most of the frame, inside the room.
                    let d: [f64; 3] = [0.55, 0.35, 1.0];
                    let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                    let dist = 1.6 * radius;
                    let eye = [
                        c[0] + d[0] / l * dist,
                        c[1] + d[1] / l * dist,
                        c[2] + d[2] / l * dist,
                    ];
                    (
                        ViewCamera::look_at(eye, c, [0.0, 1.0, 0.0], 60.0, aspect)?,
                        "default interior view".into(),
                    )
                }
                None => (
                    ViewCamera::framing(&bounds, aspect),
                    "default framing view".into(),
                ),
            },
        };
        let mut triangles = scene.triangles.clone();
        if kind == ViewKind::Interior {
            // A cube around the scene, grown to hold the eye with a margin.
            let h = 2.0 * radius;
            let mut room = Aabb {
                min: [(c[0] - h) as f32, (c[1] - h) as f32, (c[2] - h) as f32],
                max: [(c[0] + h) as f32, (c[1] + h) as f32, (c[2] + h) as f32],
            };
            let eye = camera.eye();
            for (k, e) in eye.iter().enumerate() {
                room.min[k] = room.min[k].min((e - 0.5 * radius) as f32);
                room.max[k] = room.max[k].max((e + 0.5 * radius) as f32);
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
