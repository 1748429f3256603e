//! What a `path` render knows about surfaces and lights: the scene's shading attributes and
//! glTF materials, resolved at a hit into a [`Bsdf`], an emission and a shading frame, and
//! the KHR_lights_punctual lights in the frame's pose.
//!
//! Built once per frame from a [`Scene`] loaded with shading data (a primitive without a
//! material, and every triangle of a scene without shading data, gets glTF's default
//! material). Surfaces are two-sided for light transport: a hit on a back face is shaded
//! with the normals turned towards the ray, whatever `doubleSided` says, since a path
//! tracer has no rasteriser's culling to emulate.
//!
//! Normal textures tilt the shading normal only, in the tangent frame of the mesh's
//! `TANGENT` attribute or, where a mesh has none, of the triangle's UV gradients; ray
//! offsets keep using the geometric normal, so a tilted normal never moves a ray through
//! the surface. [`Surfaces::presence`] says whether a hit surface is there at all
//! (`alphaMode`): the renderer's waves, not the cores, act on it.

use glam::{DMat4, DVec3, Vec2, Vec3, Vec4};

use super::brdf::Bsdf;
use super::bundle::Bundle;
use super::texture::{slots, specular_slots, Lookup, TextureError, TextureSet, SLOT_IS_COLOUR};
use crate::geometry::{Hit, Triangle};
use crate::scene::{AlphaMode, LightKind, Material, Scene, Shading};

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
                // KHR_lights_punctual's recommended range window, clamp(1 − (r/range)⁴, 0, 1)
                // (not squared, as some engines' variant is).
                let window = if range.is_finite() {
                    (1.0 - (r / range).powi(4)).clamp(0.0, 1.0)
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

/// A hit located on its surface, its textures not yet read ([`Surfaces::locate`]).
#[derive(Clone, Copy)]
pub struct Located {
    prim: usize,
    at: Interp,
    /// The triangle's unit normal as wound.
    face: Vec3,
    /// The same, turned towards the ray.
    ng: Vec3,
    /// Where the material's textures are read; `None` when it has none.
    uv: Option<Lookup>,
    /// Whether its emissive texture is read at level 0 (after a scattering) rather than
    /// through `uv`'s footprint.
    emission_at_point: bool,
}

/// Whether a hit surface stops a ray there (glTF `alphaMode`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Presence {
    /// Always (`OPAQUE`, a `MASK` at or above its cutoff, a `BLEND` of alpha 1).
    Opaque,
    /// Never: a `MASK` below its cutoff, or a `BLEND` of alpha 0.
    Cut,
    /// With probability `alpha` (`BLEND`, 0 < alpha < 1): a ray passes with 1 − alpha.
    Blend(f32),
}

impl Presence {
    /// The probability that the surface stops a ray.
    pub fn coverage(self) -> f32 {
        match self {
            Presence::Opaque => 1.0,
            Presence::Cut => 0.0,
            Presence::Blend(a) => a,
        }
    }
}

/// Surfaces and lights of one frame.
#[derive(Clone, Debug, Default)]
pub struct Surfaces {
    shading: Shading,
    materials: Vec<Material>,
    textures: TextureSet,
    /// Whether a material is not opaque (`MASK` or `BLEND`): only then do the waves test
    /// hits for presence.
    has_alpha: bool,
    /// The frame's lights.
    pub lights: Vec<PunctualLight>,
}

/// Sides of [`SUBDIVISION_CENTROIDS`]' subdivision.
const SUBDIVISION: usize = 2;

/// Barycentric weights (1 − u − v, u, v) of the centroids of the `SUBDIVISION²` triangles
/// that split a triangle `SUBDIVISION` × `SUBDIVISION` (upright and upside down alike, one
/// area each, so their mean is an area mean).
const SUBDIVISION_CENTROIDS: [[f32; 3]; SUBDIVISION * SUBDIVISION] = {
    let mut out = [[0.0; 3]; SUBDIVISION * SUBDIVISION];
    let n = SUBDIVISION as f32;
    let mut k = 0;
    let mut i = 0;
    while i < SUBDIVISION {
        let mut j = 0;
        while i + j < SUBDIVISION {
            // Upright: corners (i, j), (i + 1, j), (i, j + 1) in steps of 1/n of u and v.
            let (u, v) = ((i as f32 + 1.0 / 3.0) / n, (j as f32 + 1.0 / 3.0) / n);
            out[k] = [1.0 - u - v, u, v];
            k += 1;
            if i + j + 1 < SUBDIVISION {
                // Upside down: corners (i + 1, j), (i, j + 1), (i + 1, j + 1).
                let (u, v) = ((i as f32 + 2.0 / 3.0) / n, (j as f32 + 2.0 / 3.0) / n);
                out[k] = [1.0 - u - v, u, v];
                k += 1;
            }
            j += 1;
        }
        i += 1;
    }
    out
};

/// Twice the area of the triangle whose corners are vertices `c` of coordinate set `attr`
/// (a coordinate the set lacks reads as zero).
fn doubled_area(attr: &[Vec2], c: [u32; 3]) -> f32 {
    let corner = |k: usize| attr.get(c[k] as usize).copied().unwrap_or_default();
    let (a, b, d) = (corner(0), corner(1), corner(2));
    (b - a).perp_dot(d - a).abs()
}

/// Material `m`'s emissive factor × strength: its emission before its texture.
fn emissive(m: &Material) -> Vec3 {
    Vec3::from(m.emissive_factor) * m.emissive_strength
}

/// Where a hit lies on its triangle's vertices: barycentric weights (1 − u − v, u, v) of
/// its corners, when the triangle has shading vertices.
#[derive(Clone, Copy)]
struct Interp {
    corners: Option<[u32; 3]>,
    b: [f32; 3],
}

impl Interp {
    fn vec3(&self, attr: &[Vec3]) -> Option<Vec3> {
        let c = self.corners?;
        let mut sum = Vec3::ZERO;
        for (k, &i) in c.iter().enumerate() {
            sum += *attr.get(i as usize)? * self.b[k];
        }
        Some(sum)
    }

    fn vec2(&self, attr: &[Vec2]) -> Vec2 {
        let Some(c) = self.corners else {
            return Vec2::ZERO;
        };
        let mut sum = Vec2::ZERO;
        for (k, &i) in c.iter().enumerate() {
            sum += attr.get(i as usize).copied().unwrap_or_default() * self.b[k];
        }
        sum
    }

    fn colour(&self, colors: &[Vec4]) -> Vec4 {
        match self.corners.filter(|_| !colors.is_empty()) {
            None => Vec4::ONE,
            Some(c) => {
                // From the first corner by the differences to the others: corners of one
                // colour give exactly that colour (a sum weighted by the three barycentrics
                // gave alpha 1 as 0.99999994, which a MASK cutoff of 1 then cut).
                let [c0, c1, c2] = c.map(|i| colors.get(i as usize).copied().unwrap_or(Vec4::ONE));
                c0 + (c1 - c0) * self.b[1] + (c2 - c0) * self.b[2]
            }
        }
    }
}

static DEFAULT_MATERIAL: std::sync::LazyLock<Material> =
    std::sync::LazyLock::new(Material::default);

impl Surfaces {
    /// The surfaces of `scene` as posed (its triangles, shading normals and lights are
    /// those of the frame). A scene loaded without shading data gets glTF's default
    /// material and face normals everywhere. Decodes the textures the materials use; an
    /// image that does not decode is an error that names it.
    pub fn of(scene: &Scene) -> Result<Surfaces, TextureError> {
        Ok(Surfaces::with_textures(scene, TextureSet::of(scene)?))
    }

    /// [`Surfaces::of`] with the scene's textures already decoded (`TextureSet::of` of
    /// this scene at any pose: animation moves no texel), so that the frames of a
    /// sequence decode them once ([`super::texture::DecodedOnce`]).
    pub fn with_textures(scene: &Scene, textures: TextureSet) -> Surfaces {
        let shading = scene
            .shading
            .clone()
            .unwrap_or_else(|| Shading::flat(scene.triangles.len()));
        Surfaces {
            shading,
            materials: scene.materials.clone(),
            textures,
            lights: scene
                .lights
                .iter()
                .map(|l| PunctualLight::place(l, &l.to_world))
                .collect(),
            has_alpha: false,
        }
        .with_alpha()
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
        .with_alpha()
    }

    /// Surfaces of a scene's triangles from parts (tests, generated scenes): shading
    /// attributes, materials and decoded textures.
    pub fn from_parts(
        shading: Shading,
        materials: Vec<Material>,
        textures: TextureSet,
        lights: Vec<PunctualLight>,
    ) -> Surfaces {
        Surfaces {
            shading,
            materials,
            textures,
            lights,
            has_alpha: false,
        }
        .with_alpha()
    }

    fn material(&self, prim: usize) -> &Material {
        self.shading
            .materials
            .get(prim)
            .and_then(|&m| self.materials.get(m as usize))
            .unwrap_or(&DEFAULT_MATERIAL)
    }

    fn interp(&self, prim: usize, b: [f32; 3]) -> Interp {
        Interp {
            corners: self.shading.corners.get(prim).copied(),
            b,
        }
    }

    fn uvs(&self, at: &Interp) -> [Vec2; 2] {
        [at.vec2(&self.shading.uv0), at.vec2(&self.shading.uv1)]
    }

    /// The lookup at `at` on triangle `tri` for a ray cone `width` wide there, meeting the
    /// surface at cosine `cos`: the cone's footprint across the surface (`width / cos`)
    /// scaled into each texture coordinate set by the triangle's ratio of texture area to
    /// world area.
    fn lookup(&self, tri: &Triangle, at: &Interp, width: f32, cos: f32) -> Lookup {
        let uv = self.uvs(at);
        let (Some(c), true) = (at.corners, width > 0.0) else {
            return Lookup::point(uv);
        };
        let world = Vec3::from(tri.normal()).length();
        if !(world > 0.0 && world.is_finite()) {
            return Lookup::point(uv);
        }
        let log2_across = (width / cos.max(1e-6)).log2();
        // Both areas are doubled; their ratio is not.
        let set = |attr: &[Vec2]| log2_across + 0.5 * (doubled_area(attr, c) / world).log2();
        let log2_width = [
            set(&self.shading.uv0),
            if self.shading.uv1.is_empty() {
                f32::NEG_INFINITY
            } else {
                set(&self.shading.uv1)
            },
        ];
        Lookup { uv, log2_width }
    }

    /// Triangle `prim`'s material's textures interleaved, when they are.
    fn bundle(&self, prim: usize) -> Option<&Bundle> {
        let &m = self.shading.materials.get(prim)?;
        self.textures.bundle(m as usize)
    }

    /// Texture slot `slot` (base colour 0, emissive 3) of material `m` of triangle `prim`
    /// at `at`, at level 0 (white without one): what alpha tests and light sampling read.
    fn point_texel(&self, prim: usize, m: &Material, slot: usize, at: &Interp) -> Vec4 {
        self.texel(prim, m, slot, &Lookup::point(self.uvs(at)))
    }

    /// Texture slot `slot` of material `m` of triangle `prim` for lookup `at` (white
    /// without one).
    fn texel(&self, prim: usize, m: &Material, slot: usize, at: &Lookup) -> Vec4 {
        let value = match self.bundle(prim) {
            Some(b) => {
                let (uv, log2_width) = at.set(b.tex_coord());
                b.sample_slot(slot, uv, log2_width)
            }
            None => slots(m)[slot].and_then(|r| self.textures.sample(&r, at, SLOT_IS_COLOUR[slot])),
        };
        value.unwrap_or(Vec4::ONE)
    }

    /// The colour of material `m`'s emissive texture (white without one) at texture
    /// coordinates `uv` of triangle `prim`, at level 0: black without reading a texel where
    /// its bundle knows the taps black ([`Bundle::emission_black_at`]; the same bits).
    fn point_emission(&self, prim: usize, m: &Material, uv: [Vec2; 2]) -> Vec3 {
        let at = Lookup::point(uv);
        if let Some(b) = self.bundle(prim) {
            if b.emission_black_at(at.set(b.tex_coord()).0) {
                return Vec3::ZERO;
            }
        }
        self.texel(prim, m, 3, &at).truncate()
    }

    /// Whether any material is not opaque; when none is, every hit stops its ray and the
    /// renderer skips the presence tests.
    pub fn has_alpha(&self) -> bool {
        self.has_alpha
    }

    fn with_alpha(mut self) -> Surfaces {
        self.has_alpha = self
            .materials
            .iter()
            .any(|m| m.alpha_mode != AlphaMode::Opaque);
        self
    }

    /// Whether the surface at `hit` stops a ray: glTF's alpha (base colour factor ×
    /// `COLOR_0` × base colour texture, alpha channels) against the material's `alphaMode`.
    pub fn presence(&self, hit: &Hit) -> Presence {
        let prim = hit.prim as usize;
        let m = self.material(prim);
        let cutoff = match m.alpha_mode {
            AlphaMode::Opaque => return Presence::Opaque,
            AlphaMode::Mask { cutoff } => Some(cutoff),
            AlphaMode::Blend => None,
        };
        let at = self.interp(prim, [1.0 - hit.u - hit.v, hit.u, hit.v]);
        let alpha = m.base_color_factor[3]
            * at.colour(&self.shading.colors).w
            * self.point_texel(prim, m, 0, &at).w;
        match cutoff {
            Some(c) if alpha >= c => Presence::Opaque,
            Some(_) => Presence::Cut,
            None if alpha >= 1.0 => Presence::Opaque,
            None if alpha > 0.0 => Presence::Blend(alpha),
            None => Presence::Cut,
        }
    }

    /// Triangle `prim`'s emitted radiance averaged over its area: the emissive factor ×
    /// strength × the emissive texture's mean, estimated at the centroids of the four
    /// triangles of its 2 × 2 subdivision, each read at the MIP level of its own size in
    /// the texture: each reading is the filtered mean over its quarter, from a level a
    /// quarter of the triangle's size per texel, not scattered texels of the full image
    /// (sixteen point readings of DamagedHelmet's 2048² emissive texture per triangle cost
    /// its path frame 23 ms on one thread). What light sampling weighs triangles by, so
    /// that a material whose emissive texture is black nearly everywhere (DamagedHelmet's
    /// lamps on a dark shell) spends its samples on the triangles that glow. An estimate
    /// that misses a small bright spot only adds noise, never bias: a triangle light
    /// sampling skips is still found by BRDF sampling, which then carries the full MIS
    /// weight ([`super::lights::LightSampler::triangle_pdf`] is 0 for it).
    pub fn mean_emission(&self, prim: usize) -> Vec3 {
        let m = self.material(prim);
        let factor = emissive(m);
        if factor == Vec3::ZERO || m.emissive_texture.is_none() {
            return factor;
        }
        let corners = self.shading.corners.get(prim).copied();
        // The width of a part in each coordinate set: the square root of its area there.
        let part = |attr: &[Vec2]| -> f32 {
            let Some(c) = corners else {
                return f32::NEG_INFINITY;
            };
            let area = 0.5 * doubled_area(attr, c);
            0.5 * (area / SUBDIVISION_CENTROIDS.len() as f32).log2()
        };
        let log2_width = [part(&self.shading.uv0), part(&self.shading.uv1)];
        let sum: Vec3 = SUBDIVISION_CENTROIDS
            .iter()
            .map(|&b| {
                let at = Lookup {
                    uv: self.uvs(&self.interp(prim, b)),
                    log2_width,
                };
                self.texel(prim, m, 3, &at).truncate()
            })
            .sum();
        factor * sum / SUBDIVISION_CENTROIDS.len() as f32
    }

    /// Radiance emitted at barycentric point `b` of triangle `prim` (both sides), times the
    /// probability that the surface is there: what a light sample of that point sees. The
    /// emissive texture is read at level 0, as [`Surfaces::finish`] reads it for a hit
    /// after a scattering: glTF's emission there, not a cone's average of it (a scattered
    /// cone is wide, and its average lit a floor under a textured emitter 2.7× too dark
    /// beside the emitter's bright texel and 14× too bright away from it).
    pub fn emission_at(&self, prim: usize, b: [f32; 3]) -> Vec3 {
        let e = self.emission_after_scattering(prim, b);
        if e == Vec3::ZERO || self.material(prim).alpha_mode == AlphaMode::Opaque {
            return e;
        }
        let hit = Hit {
            t: 0.0,
            u: b[1],
            v: b[2],
            prim: prim as u32,
        };
        e * self.presence(&hit).coverage()
    }

    /// The emission of triangle `prim` at barycentric weights `b` as a ray that scattered
    /// before meeting it sees it: the emissive texture read at level 0, as
    /// [`Surfaces::finish`] reads it for a [`Surfaces::locate`]d hit after a scattering,
    /// but without the other textures.
    pub fn emission_after_scattering(&self, prim: usize, b: [f32; 3]) -> Vec3 {
        let m = self.material(prim);
        let factor = emissive(m);
        if factor == Vec3::ZERO {
            return Vec3::ZERO;
        }
        if m.emissive_texture.is_some() {
            factor * self.point_emission(prim, m, self.uvs(&self.interp(prim, b)))
        } else {
            factor
        }
    }

    /// The surface at `hit` of triangle `tri` for a camera ray of direction `dir` whose
    /// cone is `width` wide there (0: a point); the width chooses the textures' MIP levels
    /// ([`super::mipmap`]). [`Surfaces::locate`] then [`Surfaces::finish`].
    pub fn at(&self, tri: &Triangle, hit: &Hit, dir: Vec3, width: f32) -> SurfacePoint {
        self.finish(tri, &self.locate(tri, hit, dir, width, false))
    }

    /// Where `hit` lies on its surface and where its textures will be read, before any
    /// texel is: the first half of [`Surfaces::at`], so that a caller shading many points
    /// can [`Surfaces::prefetch`] the texels of a point a few ahead of the one it shades.
    /// `scattered`: the ray left a scattering (not the camera), so the emissive texture is
    /// read at level 0 rather than through the cone, as light sampling reads it
    /// ([`Surfaces::emission_at`]): the cone's filtering anti-aliases what the camera
    /// sees, but a scattered cone's average is not the light a surface sends.
    pub fn locate(
        &self,
        tri: &Triangle,
        hit: &Hit,
        dir: Vec3,
        width: f32,
        scattered: bool,
    ) -> Located {
        let prim = hit.prim as usize;
        let face = Vec3::from(tri.normal()).normalize_or_zero();
        // glTF winds a mirrored placement's front faces clockwise.
        let face = if self.shading.is_mirrored(prim) {
            -face
        } else {
            face
        };
        let ng = if face.dot(dir) > 0.0 { -face } else { face };
        let at = self.interp(prim, [1.0 - hit.u - hit.v, hit.u, hit.v]);
        let m = self.material(prim);
        let has_specular = m.specular.texture.is_some() || m.specular.color_texture.is_some();
        // The footprint only where a texture will read it.
        let uv = (slots(m).iter().any(Option::is_some) || has_specular)
            .then(|| self.lookup(tri, &at, width, ng.dot(dir).abs()));
        let emission_at_point =
            scattered && m.emissive_texture.is_some() && emissive(m) != Vec3::ZERO;
        Located {
            prim,
            at,
            face,
            ng,
            uv,
            emission_at_point,
        }
    }

    /// Asks the caches for the texel records that [`Surfaces::finish`] of `l` will read
    /// from its material's bundle: a 2048² bundle is 64 MiB a level, and a lookup's four
    /// taps on two levels miss the caches more often than not (a fifth of DamagedHelmet's
    /// shading waited on them). Only a hint: it changes no value.
    #[inline]
    pub fn prefetch(&self, l: &Located) {
        if let (Some(uv), Some(b)) = (&l.uv, self.bundle(l.prim)) {
            let (uv, log2_width) = uv.set(b.tex_coord());
            b.prefetch(uv, log2_width);
            if l.emission_at_point && !b.emission_black_at(uv) {
                b.prefetch(uv, f32::NEG_INFINITY);
            }
        }
    }

    /// The surface point that [`Surfaces::locate`] found: its textures read and its
    /// material resolved.
    pub fn finish(&self, tri: &Triangle, l: &Located) -> SurfacePoint {
        let Located {
            prim,
            at,
            face,
            ng,
            uv,
            emission_at_point,
        } = *l;
        let m = self.material(prim);
        let Some(uv) = uv else {
            return self.shaded(m, tri, &at, face, ng, [None; 4], [None; 2]);
        };
        // The four lookups: from the material's bundle (one record a tap) when it has one.
        let texels = match self.bundle(prim) {
            Some(b) => {
                let (uv, log2_width) = uv.set(b.tex_coord());
                b.sample(uv, log2_width)
            }
            None => {
                let refs = slots(m);
                std::array::from_fn(|k| {
                    refs[k].and_then(|r| self.textures.sample(&r, &uv, SLOT_IS_COLOUR[k]))
                })
            }
        };
        let specular = if m.specular.texture.is_some() || m.specular.color_texture.is_some() {
            specular_slots(m)
                .map(|(r, colour)| r.and_then(|r| self.textures.sample(&r, &uv, colour)))
        } else {
            [None; 2]
        };
        let mut texels = texels;
        if emission_at_point {
            texels[3] = Some(self.point_emission(prim, m, uv.uv).extend(1.0));
        }
        self.shaded(m, tri, &at, face, ng, texels, specular)
    }

    /// The surface point of material `m` at `at`, given its four textures' values there
    /// (base colour, metallic-roughness, normal, emissive; `None` where it has none) and
    /// its two `KHR_materials_specular` textures' (strength in alpha, colour). `face` is
    /// the triangle's unit normal as wound, `ng` the same turned towards the ray.
    /// Inlined into both of [`Surfaces::at`]'s paths, so that untextured shading pays no
    /// call for the split.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn shaded(
        &self,
        m: &Material,
        tri: &Triangle,
        at: &Interp,
        face: Vec3,
        ng: Vec3,
        [t_base, t_mr, t_normal, t_emissive]: [Option<Vec4>; 4],
        [t_specular, t_specular_colour]: [Option<Vec4>; 2],
    ) -> SurfacePoint {
        // The interpolated normal as stored (its own side), or the face normal as wound:
        // the normal map perturbs the front side's normal, and a back face then shows the
        // whole perturbed normal reversed, as glTF says of double-sided back faces. (The
        // normal already turned to the ray would build a mirrored tangent frame there.)
        let stored = at.vec3(&self.shading.normals).and_then(Vec3::try_normalize);
        let smooth = stored.unwrap_or(face);
        let mut ns = smooth;
        if let Some(r) = &m.normal_texture {
            if let Some(t) = t_normal {
                // glTF: without normals, "the provided tangents (if present) MUST be
                // ignored".
                let given = stored.is_some();
                if let Some(n) = self
                    .tangent_frame(tri, at, smooth, r.tex_coord, given)
                    .and_then(|(tangent, bitangent)| {
                        let s = m.normal_scale;
                        let local = Vec3::new(
                            (2.0 * t.x - 1.0) * s,
                            (2.0 * t.y - 1.0) * s,
                            2.0 * t.z - 1.0,
                        );
                        (tangent * local.x + bitangent * local.y + smooth * local.z).try_normalize()
                    })
                {
                    ns = n;
                }
            }
        }
        // Turned to the side the ray came from.
        let ns = if ns.dot(ng) < 0.0 { -ns } else { ns };
        let colour = at.colour(&self.shading.colors);
        let base = Vec3::from_slice(&m.base_color_factor[..3])
            * colour.truncate()
            * t_base.unwrap_or(Vec4::ONE).truncate();
        // glTF: roughness in G, metalness in B.
        let mr = t_mr.unwrap_or(Vec4::ONE);
        let bsdf = Bsdf::new(
            base,
            m.metallic_factor * mr.z,
            m.roughness_factor * mr.y,
            m.specular.factor * t_specular.map_or(1.0, |t| t.w),
            Vec3::from(m.specular.color_factor) * t_specular_colour.unwrap_or(Vec4::ONE).truncate(),
        );
        SurfacePoint {
            ng,
            ns,
            bsdf,
            emission: emissive(m) * t_emissive.unwrap_or(Vec4::ONE).truncate(),
        }
    }

    /// The unit tangent and bitangent of normal `n` at `at`: the mesh's `TANGENT`
    /// (bitangent = n × t · w, as glTF defines) when `tangents` allows it, or, where the
    /// mesh has none, the triangle's gradient of `TEXCOORD_set`, with the bitangent along decreasing v (the
    /// texture's +Y is up in the image, and glTF's v grows downwards). `None` where
    /// neither defines a frame (degenerate UVs).
    fn tangent_frame(
        &self,
        tri: &Triangle,
        at: &Interp,
        n: Vec3,
        set: u32,
        tangents: bool,
    ) -> Option<(Vec3, Vec3)> {
        let given = at.corners.filter(|_| tangents).and_then(|c| {
            let t = &self.shading.tangents;
            let mut sum = Vec3::ZERO;
            for (k, &i) in c.iter().enumerate() {
                sum += t.get(i as usize)?.truncate() * at.b[k];
            }
            let w = t.get(c[0] as usize)?.w;
            Some((sum, if w < 0.0 { -1.0 } else { 1.0 }))
        });
        let (tangent, sign) = match given.filter(|(t, _)| t.length_squared() > 0.0) {
            Some(g) => g,
            None => {
                let c = at.corners?;
                let uv = if set == 0 {
                    &self.shading.uv0
                } else {
                    &self.shading.uv1
                };
                let [t0, t1, t2] = c.map(|i| uv.get(i as usize).copied().unwrap_or_default());
                let p = tri.v.map(Vec3::from);
                let (e1, e2) = (p[1] - p[0], p[2] - p[0]);
                let (d1, d2) = (t1 - t0, t2 - t0);
                let det = d1.x * d2.y - d2.x * d1.y;
                if det == 0.0 || !det.is_finite() {
                    return None;
                }
                let dp_du = (e1 * d2.y - e2 * d1.y) / det;
                let dp_dv = (e2 * d1.x - e1 * d2.x) / det;
                let sign = if n.cross(dp_du).dot(-dp_dv) < 0.0 {
                    -1.0
                } else {
                    1.0
                };
                (dp_du, sign)
            }
        };
        // Gram–Schmidt against the shading normal.
        let t = (tangent - n * n.dot(tangent)).try_normalize()?;
        Some((t, n.cross(t) * sign))
    }
}

/// The point of triangle `tri` at barycentrics `u` (of `v1`) and `v` (of `v2`): where a
/// hit is, for the rays that leave it. Interpolated from the vertices rather than taken as
/// `origin + t·dir`, whose rounding grows with the distance the ray travelled: a ray that
/// crossed a kilometre-wide floor found its hit point millimetres off the floor, on either
/// side, and the ray leaving it hit the floor again. The interpolated point is off the
/// triangle's plane by a few ULPs of its vertices' coordinates, wherever the ray came from.
#[inline]
pub fn surface_point(tri: &Triangle, u: f32, v: f32) -> [f32; 3] {
    let w = 1.0 - u - v;
    let [a, b, c] = tri.v;
    std::array::from_fn(|k| w * a[k] + u * b[k] + v * c[k])
}

/// The magnitude that bounds the rounding of a point on `tri` and of the intersection
/// tests against it: its largest vertex coordinate.
#[inline]
fn coordinate_scale(tri: &Triangle) -> f32 {
    tri.v.iter().flatten().fold(0.0f32, |m, x| m.max(x.abs()))
}

/// How far [`offset_ray`] moves a point, relative to its triangle's scale: 2^-15, 256 ULPs
/// of a coordinate at that scale, as Wächter and Binder's integer offset (Ray Tracing Gems,
/// ch. 6) moves a coordinate of the point's own magnitude.
const OFFSET_RELATIVE: f32 = 1.0 / 32768.0;

/// A point just off triangle `tri` at `p` (a point on it) on the side `n` (unit) faces, for
/// the next ray. Wächter and Binder scale the offset with
/// the point's own coordinates, and by a fixed 1/65536 near the origin; but what rounds is
/// the triangle's arithmetic, at the scale of its vertices: a point at the middle of a
/// kilometre-wide floor has coordinates near 0 and errors near 6e-5, which their fixed
/// offset did not clear. So the point moves 2^-15 of the triangle's largest vertex
/// coordinate ([`coordinate_scale`]) along `n`, which stays 256 ULPs above the rounding of
/// the point and of the tests at any scale, and shrinks with tiny scenes instead of leaking
/// light through their walls.
#[inline]
pub fn offset_ray(p: [f32; 3], n: [f32; 3], tri: &Triangle) -> [f32; 3] {
    let d = (coordinate_scale(tri) * OFFSET_RELATIVE).max(f32::MIN_POSITIVE);
    std::array::from_fn(|k| p[k] + d * n[k])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::TextureRef;

    #[test]
    fn offset_moves_to_the_normal_side_at_every_scale() {
        for scale in [1e-6f32, 1e-3, 0.5, 1.0, 1e3, 1e6, 1e19] {
            let p = [scale, -scale, 0.25 * scale];
            // A triangle whose largest coordinate is `scale`, with `p` a vertex.
            let tri = Triangle {
                v: [p, [0.0; 3], [0.0; 3]],
            };
            let n = [0.0, 0.0, 1.0];
            let q = offset_ray(p, n, &tri);
            assert!(q[2] > p[2], "{scale}: {q:?}");
            assert_eq!([q[0], q[1]], [p[0], p[1]]);
            let q = offset_ray(p, [0.0, 0.0, -1.0], &tri);
            assert!(q[2] < p[2], "{scale}: {q:?}");
            // Near the origin of a large triangle the offset is the triangle's, not the
            // point's.
            let q = offset_ray([0.0; 3], n, &tri);
            assert!(q[2] >= scale / 65536.0, "{scale}: {q:?}");
        }
    }

    #[test]
    fn surface_points_lie_on_the_triangle_whatever_the_distance_travelled() {
        // A floor 2 km wide at y = 0 and a ray that crosses it 1,500 m away.
        let tri = Triangle {
            v: [
                [-1000.0, 0.0, -1000.0],
                [1000.0, 0.0, -1000.0],
                [0.0, 0.0, 1000.0],
            ],
        };
        let p = surface_point(&tri, 0.3, 0.4);
        assert_eq!(p[1], 0.0);
        assert_eq!(coordinate_scale(&tri), 1000.0);
        let q = offset_ray(p, [0.0, 1.0, 0.0], &tri);
        assert!(q[1] > 0.03 - 1e-3, "{q:?}");
    }

    /// A triangle in the XY plane facing +Z, with u along +X and v along −Y (glTF's v
    /// grows down the image), and a normal texture of the one texel `rgb`.
    fn normal_mapped(rgb: [f32; 3], scale: f32, tangents: Vec<Vec4>) -> (Surfaces, Triangle) {
        normal_mapped_with(rgb, scale, tangents, Vec::new())
    }

    /// The triangle (0,0,0), (1,0,0), (0,1,0) (its normal +Z) and flat shading for it,
    /// of material 0.
    fn unit_triangle() -> (Triangle, Shading) {
        let mut shading = Shading::flat(1);
        shading.materials = vec![0];
        let tri = Triangle {
            v: [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        };
        (tri, shading)
    }

    /// [`normal_mapped`] with vertex normals.
    fn normal_mapped_with(
        rgb: [f32; 3],
        scale: f32,
        tangents: Vec<Vec4>,
        normals: Vec<Vec3>,
    ) -> (Surfaces, Triangle) {
        use super::super::texture::{Texels, TextureSet};
        use crate::render::mipmap::Filtering;
        use crate::scene::{Filter, Wrap};
        let (tri, mut shading) = unit_triangle();
        shading.uv0 = vec![
            Vec2::new(0.0, 1.0),
            Vec2::new(1.0, 1.0),
            Vec2::new(0.0, 0.0),
        ];
        shading.tangents = tangents;
        shading.normals = normals;
        let material = Material {
            normal_texture: Some(TextureRef {
                texture: 0,
                tex_coord: 0,
                transform: None,
            }),
            normal_scale: scale,
            ..Material::default()
        };
        let texels = Texels::from_rgba(1, 1, vec![[rgb[0], rgb[1], rgb[2], 1.0]]).unwrap();
        let textures = TextureSet::from_texels(vec![(
            texels,
            Filtering::single(Filter::Nearest, [Wrap::Repeat; 2]),
        )]);
        (
            Surfaces::from_parts(shading, vec![material], textures, Vec::new()),
            tri,
        )
    }

    fn shading_normal(s: &Surfaces, tri: &Triangle, dir: Vec3) -> Vec3 {
        let hit = Hit {
            t: 1.0,
            u: 0.25,
            v: 0.25,
            prim: 0,
        };
        s.at(tri, &hit, dir, 0.0).ns
    }

    #[test]
    fn normal_textures_tilt_the_shading_normal_in_the_tangent_frame() {
        let down = Vec3::NEG_Z;
        // Tangent-space (0.6, 0, 0.8): towards +u, which is +X.
        let (s, tri) = normal_mapped([0.8, 0.5, 0.9], 1.0, Vec::new());
        let n = shading_normal(&s, &tri, down);
        assert!((n - Vec3::new(0.6, 0.0, 0.8)).length() < 1e-5, "{n}");
        // Tangent-space (0, 0.6, 0.8): towards the image's up, which is −v, here +Y.
        let (s, tri) = normal_mapped([0.5, 0.8, 0.9], 1.0, Vec::new());
        let n = shading_normal(&s, &tri, down);
        assert!((n - Vec3::new(0.0, 0.6, 0.8)).length() < 1e-5, "{n}");
        // Scale 0 leaves the geometric normal.
        let (s, tri) = normal_mapped([0.8, 0.5, 0.9], 0.0, Vec::new());
        assert!((shading_normal(&s, &tri, down) - Vec3::Z).length() < 1e-6);
        // The mesh's TANGENT wins over the UV gradient: here +Y, so +X of the texture
        // tilts towards +Y.
        let t = vec![Vec4::new(0.0, 1.0, 0.0, 1.0); 3];
        let (s, tri) = normal_mapped_with([0.8, 0.5, 0.9], 1.0, t.clone(), vec![Vec3::Z; 3]);
        let n = shading_normal(&s, &tri, down);
        assert!((n - Vec3::new(0.0, 0.6, 0.8)).length() < 1e-5, "{n}");
        // Unless the mesh has no normals: glTF says its tangents are then ignored.
        let (s, tri) = normal_mapped([0.8, 0.5, 0.9], 1.0, t);
        let n = shading_normal(&s, &tri, down);
        assert!((n - Vec3::new(0.6, 0.0, 0.8)).length() < 1e-5, "{n}");
        // Seen from behind, the whole perturbed normal is reversed (glTF: a double-sided
        // back face's normals are reversed), with vertex normals or without (here none),
        // and with a mesh TANGENT.
        let (s, tri) = normal_mapped([0.8, 0.5, 0.9], 1.0, Vec::new());
        let n = shading_normal(&s, &tri, Vec3::Z);
        assert!((n - Vec3::new(-0.6, 0.0, -0.8)).length() < 1e-5, "{n}");
        let (s, tri) = normal_mapped([0.5, 0.8, 0.9], 1.0, Vec::new());
        let n = shading_normal(&s, &tri, Vec3::Z);
        assert!((n - Vec3::new(0.0, -0.6, -0.8)).length() < 1e-5, "{n}");
        let t = vec![Vec4::new(1.0, 0.0, 0.0, 1.0); 3];
        let (s, tri) = normal_mapped_with([0.5, 0.8, 0.9], 1.0, t, vec![Vec3::Z; 3]);
        let n = shading_normal(&s, &tri, Vec3::Z);
        assert!((n - Vec3::new(0.0, -0.6, -0.8)).length() < 1e-5, "{n}");
    }

    /// A triangle mirrored in X (its front face, clockwise as glTF winds mirrored
    /// placements, facing +Z) tilts its normal map as the mirror image of the unmirrored
    /// triangle's tilt, without vertex normals as with them.
    #[test]
    fn a_mirrored_triangle_tilts_its_normal_map_as_the_mirror_image() {
        let down = Vec3::NEG_Z;
        for normals in [Vec::new(), vec![Vec3::Z; 3]] {
            let with = !normals.is_empty();
            let (mut s, mut tri) = normal_mapped_with([0.8, 0.5, 0.9], 1.0, Vec::new(), normals);
            for v in &mut tri.v {
                v[0] = -v[0];
            }
            // Only a primitive without NORMAL is marked (`Shading::mirrored`).
            if !with {
                s.shading.mirrored = vec![1];
            }
            let n = shading_normal(&s, &tri, down);
            assert!(
                (n - Vec3::new(-0.6, 0.0, 0.8)).length() < 1e-5,
                "{n} {with}"
            );
        }
    }

    /// Corners of one vertex colour give exactly that colour anywhere on the triangle: an
    /// alpha of 1 read as 0.99999994 was cut by a MASK cutoff of 1 (and 0.5 × that by the
    /// default 0.5 under a base colour alpha of 0.5).
    #[test]
    fn equal_vertex_colours_interpolate_exactly() {
        let colour = Vec4::new(0.3, 0.7, 0.1, 1.0);
        let colors = vec![colour; 3];
        let mut rng = crate::render::rng::Pcg32::new(7, 1);
        for _ in 0..10_000 {
            let (u, v) = (rng.next_f32(), rng.next_f32());
            let (u, v) = if u + v > 1.0 {
                (1.0 - u, 1.0 - v)
            } else {
                (u, v)
            };
            let at = Interp {
                corners: Some([0, 1, 2]),
                b: [1.0 - u - v, u, v],
            };
            assert_eq!(at.colour(&colors), colour, "at ({u}, {v})");
        }
    }

    /// After a scattering, a light sample of a point on an emissive-textured triangle and
    /// a BRDF-sampled ray that hits it read the same emission, the texture's at level 0,
    /// however wide their cones (multiple importance sampling weighs two estimates of one
    /// integrand, and the integrand is glTF's); a camera ray reads it through its cone.
    #[test]
    fn scattered_rays_and_light_samples_read_emission_at_level_zero() {
        use super::super::texture::{Texels, TextureSet};
        use crate::render::mipmap::Filtering;
        use crate::scene::Sampler;
        let (tri, mut shading) = unit_triangle();
        shading.uv0 = vec![Vec2::ZERO, Vec2::X, Vec2::Y];
        let colour = Vec3::new(1.0, 0.5, 0.25);
        let material = Material {
            emissive_factor: colour.to_array(),
            emissive_texture: Some(TextureRef {
                texture: 0,
                tex_coord: 0,
                transform: None,
            }),
            ..Material::default()
        };
        let n = 64;
        let checker = (0..n * n)
            .map(|i| {
                let v = ((i % n / 8 + i / n / 8) % 2) as f32;
                [v, v, v, 1.0]
            })
            .collect();
        let texels = Texels::from_rgba(n, n, checker).unwrap();
        let filtering = Filtering::of(&Sampler::default());
        let textures = TextureSet::from_texels(vec![(texels, filtering)]);
        let s = Surfaces::from_parts(shading, vec![material], textures, Vec::new());
        for (u, v) in [(0.2, 0.3), (0.61, 0.07), (0.05, 0.9)] {
            let b = [1.0 - u - v, u, v];
            let by_light = s.emission_at(0, b);
            assert!(by_light == Vec3::ZERO || by_light == colour, "{by_light}");
            for width in [0.0, 1e-3, 0.02, 0.3, 5.0] {
                let hit = Hit {
                    t: 1.0,
                    u,
                    v,
                    prim: 0,
                };
                let l = s.locate(&tri, &hit, Vec3::NEG_Z, width, true);
                assert_eq!(s.finish(&tri, &l).emission, by_light, "({u}, {v}), {width}");
            }
            // A path's last vertex reads it without the rest of the surface.
            assert_eq!(s.emission_after_scattering(0, b), by_light);
        }
        // A camera ray's cone wider than the triangle reads the checker's mean.
        let hit = Hit {
            t: 1.0,
            u: 0.3,
            v: 0.2,
            prim: 0,
        };
        let wide = s.at(&tri, &hit, Vec3::NEG_Z, 5.0).emission;
        assert!((wide - 0.5 * colour).abs().max_element() < 0.05, "{wide}");
    }

    /// A path's last vertex ([`Surfaces::emission_after_scattering`]) sees what the whole
    /// surface point after a scattering shows, for emitters without textures, half
    /// transparent ones (a hit is on the surface: no coverage, which light samples weigh
    /// by) and surfaces that emit nothing.
    #[test]
    fn last_vertex_emission_is_the_surface_points() {
        let (tri, shading) = unit_triangle();
        let glow = [0.5, 2.0, 0.25];
        let materials = [
            Material {
                emissive_factor: glow,
                ..Material::default()
            },
            Material {
                emissive_factor: glow,
                emissive_strength: 3.0,
                base_color_factor: [1.0, 1.0, 1.0, 0.5],
                alpha_mode: AlphaMode::Blend,
                ..Material::default()
            },
            Material::default(),
        ];
        for (k, material) in materials.into_iter().enumerate() {
            let textures = super::super::texture::TextureSet::from_texels(Vec::new());
            let s = Surfaces::from_parts(shading.clone(), vec![material], textures, Vec::new());
            let hit = Hit {
                t: 1.0,
                u: 0.25,
                v: 0.5,
                prim: 0,
            };
            let b = [0.25, 0.25, 0.5];
            let l = s.locate(&tri, &hit, Vec3::NEG_Z, 0.1, true);
            let whole = s.finish(&tri, &l).emission;
            assert_eq!(s.emission_after_scattering(0, b), whole, "material {k}");
            let expected = match k {
                0 => Vec3::from(glow),
                1 => Vec3::from(glow) * 3.0,
                _ => Vec3::ZERO,
            };
            assert_eq!(whole, expected, "material {k}");
            // A light sample of the half-transparent one sees half of it.
            let coverage = if k == 1 { 0.5 } else { 1.0 };
            assert_eq!(s.emission_at(0, b), expected * coverage, "material {k}");
        }
    }

    /// `KHR_materials_specular`'s textures scale its factors: the strength by the alpha of
    /// `specularTexture`, the colour by the RGB of `specularColorTexture` (sRGB-decoded).
    #[test]
    fn specular_textures_scale_the_specular_factors() {
        use super::super::texture::{Texels, TextureSet};
        use crate::render::mipmap::Filtering;
        use crate::scene::{Filter, Specular, Wrap};
        let (tri, mut shading) = unit_triangle();
        shading.uv0 = vec![Vec2::ZERO; 3];
        let r = |texture| {
            Some(TextureRef {
                texture,
                tex_coord: 0,
                transform: None,
            })
        };
        let material = |texture, color_texture| Material {
            base_color_factor: [0.5, 0.5, 0.5, 1.0],
            specular: Specular {
                factor: 0.8,
                texture,
                color_factor: [1.0, 0.5, 0.25],
                color_texture,
            },
            ..Material::default()
        };
        // Texture 0: strength 0.25 in alpha (its RGB must not matter). Texture 1: colour
        // (1, 0.5, 0) as stored, whose sRGB decode the colour lookup must apply. Texture
        // 2: strength 0.
        let one = |rgba: [f32; 4]| {
            (
                Texels::from_rgba(1, 1, vec![rgba]).unwrap(),
                Filtering::single(Filter::Nearest, [Wrap::Repeat; 2]),
            )
        };
        let textures = || {
            TextureSet::from_texels(vec![
                one([0.9, 0.9, 0.9, 0.25]),
                one([1.0, 0.5, 0.0, 1.0]),
                one([1.0, 1.0, 1.0, 0.0]),
            ])
        };
        let hit = Hit {
            t: 1.0,
            u: 0.25,
            v: 0.25,
            prim: 0,
        };
        let bsdf = |m: Material| {
            Surfaces::from_parts(shading.clone(), vec![m], textures(), Vec::new())
                .at(&tri, &hit, Vec3::NEG_Z, 0.01)
                .bsdf
        };
        let plain = bsdf(material(None, None));
        assert_eq!(plain.specular, 0.8);
        assert_eq!(plain.f0_dielectric, 0.04 * Vec3::new(1.0, 0.5, 0.25));
        let strength = bsdf(material(r(0), None));
        assert_eq!(strength.specular, 0.8 * 0.25);
        assert_eq!(strength.f0_dielectric, plain.f0_dielectric);
        let coloured = bsdf(material(None, r(1)));
        assert_eq!(coloured.specular, 0.8);
        // sRGB 0.5 in linear light (IEC 61966-2-1).
        let half = ((0.5f32 + 0.055) / 1.055).powf(2.4);
        let want = 0.04 * Vec3::new(1.0, 0.5, 0.25) * Vec3::new(1.0, half, 0.0);
        assert!(
            (coloured.f0_dielectric - want).abs().max_element() < 1e-3 * want.max_element(),
            "{} against {want}",
            coloured.f0_dielectric
        );
        // A strength texture of alpha 0 makes the material purely diffuse, as factor 0 does.
        let none = bsdf(material(r(2), None));
        let diffuse = bsdf(Material {
            specular: Specular {
                factor: 0.0,
                ..material(None, None).specular
            },
            ..material(None, None)
        });
        assert_eq!(none, diffuse);
    }

    #[test]
    fn presence_follows_alpha_mode() {
        let hit = Hit {
            t: 1.0,
            u: 0.2,
            v: 0.2,
            prim: 0,
        };
        let of = |alpha: f32, mode: AlphaMode| {
            let m = Material {
                base_color_factor: [1.0, 1.0, 1.0, alpha],
                alpha_mode: mode,
                ..Material::default()
            };
            let s = Surfaces::uniform(1, m, Vec::new());
            (s.has_alpha(), s.presence(&hit))
        };
        assert_eq!(of(0.1, AlphaMode::Opaque), (false, Presence::Opaque));
        let mask = AlphaMode::Mask { cutoff: 0.5 };
        assert_eq!(of(0.4, mask), (true, Presence::Cut));
        assert_eq!(of(0.5, mask), (true, Presence::Opaque));
        assert_eq!(of(0.4, AlphaMode::Blend), (true, Presence::Blend(0.4)));
        assert_eq!(of(0.0, AlphaMode::Blend).1, Presence::Cut);
        assert_eq!(of(1.0, AlphaMode::Blend).1, Presence::Opaque);
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
        // With a range of 4 at distance 2: the window 1 − (2/4)⁴ = 0.9375, over r².
        let ranged = PunctualLight::Point {
            position: Vec3::new(0.0, 2.0, 0.0),
            intensity: Vec3::splat(8.0),
            range: 4.0,
            cone: None,
        };
        let i = ranged.incident(Vec3::ZERO).unwrap();
        assert!(
            (i.irradiance - Vec3::splat(8.0 * 0.9375 / 4.0))
                .abs()
                .max_element()
                < 1e-6
        );
        // Nothing at or past the range.
        assert!(ranged.incident(Vec3::new(0.0, -2.0, 0.0)).is_none());
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
