//! What a `path` render knows about surfaces and lights: the scene's shading attributes and
//! glTF materials, resolved at a hit into a [`Bsdf`], an emission and a shading frame, and
//! the KHR_lights_punctual lights in the frame's pose.
//!
//! Built once per frame from a [`Scene`] loaded with shading data (a primitive without a
//! material, and every triangle of a scene without shading data, gets glTF's default
//! material). Surfaces are two-sided for light transport: a hit on a back face is shaded
//! with the normals turned towards the ray, whatever `doubleSided` says, since a path
//! tracer has no rasteriser's culling to emulate.

use glam::{DMat4, DVec3, Vec3};

use super::brdf::Bsdf;
use super::texture::{TextureError, TextureSet};
use crate::geometry::{Hit, Triangle};
use crate::scene::{LightKind, Material, Scene, Shading};

/// A light in world space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PunctualLight {
    /// Light arriving from one direction everywhere.
    Directional {
        /// Unit direction towards the light (the node's +Z).
        to_light: Vec3,
        /// Colour × illuminance (lux).
        irradiance: Vec3,
    },
    /// A point or spot light.
    Point {
        /// Position.
        position: Vec3,
        /// Colour × intensity (candela).
        intensity: Vec3,
        /// Distance where the light ends (glTF's smooth window); infinite when none.
        range: f32,
        /// For spots: the axis the light shines along (node −Z) and the cosines of the
        /// outer and inner cone angles.
        cone: Option<(Vec3, f32, f32)>,
    },
}

/// Light arriving at a point from a punctual light, before visibility.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Incident {
    /// Unit direction towards the light.
    pub wi: Vec3,
    /// Distance to the light (infinite for directional lights).
    pub distance: f32,
    /// Irradiance on a surface facing the light.
    pub irradiance: Vec3,
}

impl PunctualLight {
    /// The light `light` of a scene placed by `to_world`.
    pub fn place(light: &crate::scene::Light, to_world: &DMat4) -> PunctualLight {
        let colour = Vec3::from(light.color) * light.intensity;
        let axis = (-to_world.z_axis.truncate())
            .try_normalize()
            .unwrap_or(DVec3::NEG_Z)
            .as_vec3();
        let position = to_world.w_axis.truncate().as_vec3();
        match light.kind {
            LightKind::Directional => PunctualLight::Directional {
                to_light: -axis,
                irradiance: colour,
            },
            LightKind::Point | LightKind::Spot { .. } => PunctualLight::Point {
                position,
                intensity: colour,
                range: light.range.unwrap_or(f32::INFINITY),
                cone: match light.kind {
                    LightKind::Spot {
                        inner_cone_angle,
                        outer_cone_angle,
                    } => Some((axis, outer_cone_angle.cos(), inner_cone_angle.cos())),
                    _ => None,
                },
            },
        }
    }

    /// What the light sends to point `p`, or `None` where it sends nothing (outside its
    /// range or cone).
    pub fn incident(&self, p: Vec3) -> Option<Incident> {
        match *self {
            PunctualLight::Directional {
                to_light,
                irradiance,
            } => Some(Incident {
                wi: to_light,
                distance: f32::INFINITY,
                irradiance,
            }),
            PunctualLight::Point {
                position,
                intensity,
                range,
                cone,
            } => {
                let d = position - p;
                let r2 = d.length_squared();
                if r2 <= 0.0 || !r2.is_finite() {
                    return None;
                }
                let r = r2.sqrt();
                let wi = d / r;
                // glTF's recommended range window: (1 − (r/range)⁴)², clamped.
                let window = if range.is_finite() {
                    (1.0 - (r / range).powi(4)).clamp(0.0, 1.0).powi(2)
                } else {
                    1.0
                };
                let spot = match cone {
                    None => 1.0,
                    Some((axis, cos_outer, cos_inner)) => {
                        let c = (-wi).dot(axis);
                        let t =
                            ((c - cos_outer) / (cos_inner - cos_outer).max(1e-4)).clamp(0.0, 1.0);
                        t * t
                    }
                };
                let k = window * spot / r2;
                (k > 0.0).then_some(Incident {
                    wi,
                    distance: r,
                    irradiance: intensity * k,
                })
            }
        }
    }
}

/// A surface point as shading sees it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    /// Unit geometric normal, on the side the ray came from.
    pub ng: Vec3,
    /// Unit shading normal, on the same side as `ng`.
    pub ns: Vec3,
    /// The material's BRDF there.
    pub bsdf: Bsdf,
    /// Emitted radiance (emissive factor × strength).
    pub emission: Vec3,
}

/// Surfaces and lights of one frame.
#[derive(Clone, Debug, Default)]
pub struct Surfaces {
    shading: Shading,
    materials: Vec<Material>,
    textures: TextureSet,
    /// The frame's lights.
    pub lights: Vec<PunctualLight>,
}

static DEFAULT_MATERIAL: std::sync::LazyLock<Material> =
    std::sync::LazyLock::new(Material::default);

impl Surfaces {
    /// The surfaces of `scene` as posed (its triangles, shading normals and lights are
    /// those of the frame). A scene loaded without shading data gets glTF's default
    /// material and face normals everywhere. Decodes the textures the materials use; an
    /// image that does not decode is an error that names it.
    pub fn of(scene: &Scene) -> Result<Surfaces, TextureError> {
        let shading = scene
            .shading
            .clone()
            .unwrap_or_else(|| Shading::flat(scene.triangles.len()));
        Ok(Surfaces {
            shading,
            materials: scene.materials.clone(),
            textures: TextureSet::of(scene)?,
            lights: scene
                .lights
                .iter()
                .map(|l| PunctualLight::place(l, &l.to_world))
                .collect(),
        })
    }

    /// Surfaces of `triangles` triangles of glTF's default material, lit by `lights`.
    pub fn default_material(triangles: usize, lights: Vec<PunctualLight>) -> Surfaces {
        Surfaces {
            shading: Shading::flat(triangles),
            lights,
            ..Surfaces::default()
        }
    }

    /// Surfaces of one material for every triangle (tests, analytic scenes).
    pub fn uniform(triangles: usize, material: Material, lights: Vec<PunctualLight>) -> Surfaces {
        let mut shading = Shading::flat(triangles);
        shading.materials = vec![0; triangles];
        Surfaces {
            shading,
            materials: vec![material],
            lights,
            ..Surfaces::default()
        }
    }

    fn material(&self, prim: usize) -> &Material {
        self.shading
            .materials
            .get(prim)
            .and_then(|&m| self.materials.get(m as usize))
            .unwrap_or(&DEFAULT_MATERIAL)
    }

    /// The surface at `hit` of triangle `tri` for a ray of direction `dir`.
    pub fn at(&self, tri: &Triangle, hit: &Hit, dir: Vec3) -> SurfacePoint {
        let prim = hit.prim as usize;
        let ng = Vec3::from(tri.normal()).normalize_or_zero();
        let ng = if ng.dot(dir) > 0.0 { -ng } else { ng };
        let b = [1.0 - hit.u - hit.v, hit.u, hit.v];
        let corners = self.shading.corners.get(prim).copied();
        let interp = |attr: &[Vec3]| -> Option<Vec3> {
            let c = corners?;
            let mut sum = Vec3::ZERO;
            for (k, &i) in c.iter().enumerate() {
                sum += *attr.get(i as usize)? * b[k];
            }
            Some(sum)
        };
        let ns = interp(&self.shading.normals)
            .and_then(Vec3::try_normalize)
            .map(|n| if n.dot(ng) < 0.0 { -n } else { n })
            .unwrap_or(ng);
        let mut colour = glam::Vec4::ONE;
        if let Some(c) = corners.filter(|_| !self.shading.colors.is_empty()) {
            colour = glam::Vec4::ZERO;
            for (k, &i) in c.iter().enumerate() {
                colour += self
                    .shading
                    .colors
                    .get(i as usize)
                    .copied()
                    .unwrap_or(glam::Vec4::ONE)
                    * b[k];
            }
        }
        let m = self.material(prim);
        let uv_of = |attr: &[glam::Vec2]| -> glam::Vec2 {
            let Some(c) = corners else {
                return glam::Vec2::ZERO;
            };
            let mut sum = glam::Vec2::ZERO;
            for (k, &i) in c.iter().enumerate() {
                sum += attr.get(i as usize).copied().unwrap_or_default() * b[k];
            }
            sum
        };
        let uv = [uv_of(&self.shading.uv0), uv_of(&self.shading.uv1)];
        let tex = |r: &Option<crate::scene::TextureRef>, srgb: bool| {
            r.as_ref()
                .and_then(|r| self.textures.sample(r, uv, srgb))
                .unwrap_or(glam::Vec4::ONE)
        };
        let base = Vec3::from_slice(&m.base_color_factor[..3])
            * colour.truncate()
            * tex(&m.base_color_texture, true).truncate();
        // glTF: roughness in G, metalness in B.
        let mr = tex(&m.metallic_roughness_texture, false);
        let bsdf = Bsdf::new(
            base,
            m.metallic_factor * mr.z,
            m.roughness_factor * mr.y,
            m.specular.factor,
            Vec3::from(m.specular.color_factor),
        );
        SurfacePoint {
            ng,
            ns,
            bsdf,
            emission: Vec3::from(m.emissive_factor)
                * m.emissive_strength
                * tex(&m.emissive_texture, true).truncate(),
        }
    }
}

/// A point just off the surface at `p` on the side `n` faces, for the next ray: Wächter
/// and Binder's offset (Ray Tracing Gems, ch. 6), which moves each coordinate by a number of
/// ULPs proportional to the normal, so it stays above f32 rounding at any magnitude, and
/// by a small fixed distance near the origin, where ULPs are tiny.
#[inline]
pub fn offset_ray(p: [f32; 3], n: [f32; 3]) -> [f32; 3] {
    const ORIGIN: f32 = 1.0 / 32.0;
    const FLOAT_SCALE: f32 = 1.0 / 65536.0;
    const INT_SCALE: f32 = 256.0;
    let mut out = [0.0; 3];
    for k in 0..3 {
        let of_i = (INT_SCALE * n[k]) as i32;
        let bits = p[k].to_bits() as i32;
        let moved = if p[k] < 0.0 {
            bits.wrapping_sub(of_i)
        } else {
            bits.wrapping_add(of_i)
        };
        out[k] = if p[k].abs() < ORIGIN {
            p[k] + FLOAT_SCALE * n[k]
        } else {
            f32::from_bits(moved as u32)
        };
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offset_moves_to_the_normal_side_at_every_scale() {
        for scale in [1e-3f32, 0.5, 1.0, 1e3, 1e6] {
            let p = [scale, -scale, 0.25 * scale];
            let n = [0.0, 0.0, 1.0];
            let q = offset_ray(p, n);
            assert!(q[2] > p[2], "{scale}: {q:?}");
            assert_eq!([q[0], q[1]], [p[0], p[1]]);
            let q = offset_ray(p, [0.0, 0.0, -1.0]);
            assert!(q[2] < p[2], "{scale}: {q:?}");
        }
    }

    #[test]
    fn point_light_falls_off_with_the_square_and_spots_have_cones() {
        let l = PunctualLight::Point {
            position: Vec3::new(0.0, 2.0, 0.0),
            intensity: Vec3::splat(8.0),
            range: f32::INFINITY,
            cone: None,
        };
        let i = l.incident(Vec3::ZERO).unwrap();
        assert_eq!(i.irradiance, Vec3::splat(2.0));
        assert_eq!(i.wi, Vec3::Y);
        let spot = PunctualLight::Point {
            position: Vec3::new(0.0, 2.0, 0.0),
            intensity: Vec3::splat(8.0),
            range: f32::INFINITY,
            cone: Some((Vec3::NEG_Y, 0.5f32.cos(), 0.3f32.cos())),
        };
        assert_eq!(
            spot.incident(Vec3::ZERO).unwrap().irradiance,
            Vec3::splat(2.0)
        );
        assert!(spot.incident(Vec3::new(5.0, 0.0, 0.0)).is_none());
    }
}
