//! Appearance: glTF metallic-roughness materials (with `KHR_materials_specular`,
//! `KHR_materials_emissive_strength` and `KHR_texture_transform`), textures with their
//! samplers, the images' *encoded* bytes, and KHR_lights_punctual lights.
//!
//! Why encoded: decoding is the renderer's job, and only a job that samples a texture pays
//! for it; a ray batch or a `primary`, `normals` or `ao` render never decodes a pixel. The
//! values are the file's, checked by the loader (factors finite and in range, indices in
//! bounds), with glTF's defaults filled in.

use std::sync::Arc;

use glam::{Mat3, Vec2};

/// How a material's alpha is used (glTF 2.0 §3.9.4).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum AlphaMode {
    /// Alpha is ignored: the surface is fully opaque.
    Opaque,
    /// Opaque where alpha ≥ `cutoff`, invisible elsewhere.
    Mask {
        /// `alphaCutoff` (default 0.5).
        cutoff: f32,
    },
    /// Alpha blends the surface with what lies behind it.
    Blend,
}

/// `KHR_texture_transform` of one texture reference: `uv' = T · R · S · uv`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TextureTransform {
    /// UV offset.
    pub offset: [f32; 2],
    /// Rotation in radians, counter-clockwise in UV space.
    pub rotation: f32,
    /// UV scale.
    pub scale: [f32; 2],
}

impl TextureTransform {
    /// The affine 3×3 the extension defines, for `(u, v, 1)` column vectors.
    pub fn matrix(&self) -> Mat3 {
        let (s, c) = self.rotation.sin_cos();
        let t = Mat3::from_translation(Vec2::from(self.offset));
        let r = Mat3::from_cols_array(&[c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0]);
        let sc = Mat3::from_scale(Vec2::from(self.scale));
        t * r * sc
    }

    /// Transforms a texture coordinate.
    pub fn apply(&self, uv: Vec2) -> Vec2 {
        self.matrix().transform_point2(uv)
    }
}

/// A material's use of a texture.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TextureRef {
    /// Index into [`super::Scene::textures`].
    pub texture: usize,
    /// Which `TEXCOORD_n` set (after `KHR_texture_transform`'s override).
    pub tex_coord: u32,
    /// `KHR_texture_transform`, when the reference has one.
    pub transform: Option<TextureTransform>,
}

/// `KHR_materials_specular`; without the extension, glTF's defaults (factor 1, colour 1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Specular {
    /// `specularFactor`: 0 makes the material purely diffuse.
    pub factor: f32,
    /// `specularTexture` (its alpha channel scales `factor`).
    pub texture: Option<TextureRef>,
    /// `specularColorFactor` (linear RGB).
    pub color_factor: [f32; 3],
    /// `specularColorTexture` (RGB, sRGB-encoded).
    pub color_texture: Option<TextureRef>,
}

impl Default for Specular {
    fn default() -> Self {
        Specular {
            factor: 1.0,
            texture: None,
            color_factor: [1.0; 3],
            color_texture: None,
        }
    }
}

/// A glTF metallic-roughness material.
#[derive(Clone, Debug, PartialEq)]
pub struct Material {
    /// Its name (empty when the file gives none).
    pub name: String,
    /// `baseColorFactor`, linear RGBA.
    pub base_color_factor: [f32; 4],
    /// `baseColorTexture` (sRGB RGBA).
    pub base_color_texture: Option<TextureRef>,
    /// `metallicFactor`.
    pub metallic_factor: f32,
    /// `roughnessFactor`.
    pub roughness_factor: f32,
    /// `metallicRoughnessTexture` (roughness in G, metallic in B).
    pub metallic_roughness_texture: Option<TextureRef>,
    /// `normalTexture`.
    pub normal_texture: Option<TextureRef>,
    /// `normalTexture.scale`.
    pub normal_scale: f32,
    /// `occlusionTexture` (R channel).
    pub occlusion_texture: Option<TextureRef>,
    /// `occlusionTexture.strength`.
    pub occlusion_strength: f32,
    /// `emissiveFactor`, linear RGB.
    pub emissive_factor: [f32; 3],
    /// `emissiveTexture` (sRGB RGB).
    pub emissive_texture: Option<TextureRef>,
    /// `KHR_materials_emissive_strength` (1 without the extension).
    pub emissive_strength: f32,
    /// `KHR_materials_specular`.
    pub specular: Specular,
    /// `alphaMode` with `alphaCutoff`.
    pub alpha_mode: AlphaMode,
    /// `doubleSided`: back faces are lit with the flipped normal instead of culled.
    pub double_sided: bool,
}

impl Default for Material {
    /// glTF's default material (used by primitives without one).
    fn default() -> Self {
        Material {
            name: String::new(),
            base_color_factor: [1.0; 4],
            base_color_texture: None,
            metallic_factor: 1.0,
            roughness_factor: 1.0,
            metallic_roughness_texture: None,
            normal_texture: None,
            normal_scale: 1.0,
            occlusion_texture: None,
            occlusion_strength: 1.0,
            emissive_factor: [0.0; 3],
            emissive_texture: None,
            emissive_strength: 1.0,
            specular: Specular::default(),
            alpha_mode: AlphaMode::Opaque,
            double_sided: false,
        }
    }
}

/// A magnification or minification filter (mipmap modes keep their base filter).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Filter {
    /// Nearest texel.
    Nearest,
    /// Bilinear.
    Linear,
}

/// How mipmaps are used by minification.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mipmap {
    /// No mipmaps (`NEAREST`/`LINEAR`).
    None,
    /// Nearest mip level.
    Nearest,
    /// Blend of the two nearest levels.
    Linear,
}

/// A wrap mode for one texture axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Wrap {
    /// Clamp to the edge texel.
    ClampToEdge,
    /// Repeat mirrored every other period.
    MirroredRepeat,
    /// Repeat.
    Repeat,
}

/// A texture sampler. glTF leaves filters to the implementation when absent: `None`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Sampler {
    /// `magFilter`.
    pub mag_filter: Option<Filter>,
    /// `minFilter`'s base filter.
    pub min_filter: Option<Filter>,
    /// `minFilter`'s mipmap mode.
    pub mipmap: Mipmap,
    /// `wrapS` (default REPEAT).
    pub wrap_s: Wrap,
    /// `wrapT` (default REPEAT).
    pub wrap_t: Wrap,
}

impl Default for Sampler {
    fn default() -> Self {
        Sampler {
            mag_filter: None,
            min_filter: None,
            mipmap: Mipmap::None,
            wrap_s: Wrap::Repeat,
            wrap_t: Wrap::Repeat,
        }
    }
}

/// A texture: an image and how to sample it.
#[derive(Clone, Debug, PartialEq)]
pub struct Texture {
    /// Index into [`super::Scene::images`].
    pub image: usize,
    /// Its sampler (the default one when the texture names none).
    pub sampler: Sampler,
}

/// An image as stored: encoded bytes and their MIME type. Not decoded.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// `image/png`, `image/jpeg`, … as the file says (or as the bytes' signature says
    /// when the file gives none).
    pub mime_type: String,
    /// The encoded bytes (shared: cloning a scene does not copy them).
    pub bytes: Arc<[u8]>,
}

/// The kind of a KHR_lights_punctual light.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LightKind {
    /// Emits along the node's −Z.
    Directional,
    /// Emits in every direction from the node's origin.
    Point,
    /// A cone around the node's −Z.
    Spot {
        /// Angle (radians) from the axis where falloff starts.
        inner_cone_angle: f32,
        /// Angle (radians) from the axis where it reaches zero.
        outer_cone_angle: f32,
    },
}

/// A light placed by a node of the default scene (a light used by k nodes gives k).
#[derive(Clone, Debug, PartialEq)]
pub struct Light {
    /// The light's name (empty when the file gives none).
    pub name: String,
    /// Index of its definition in the file's `KHR_lights_punctual.lights`.
    pub light: usize,
    /// The node that places it.
    pub node: usize,
    /// Its kind.
    pub kind: LightKind,
    /// Linear RGB colour.
    pub color: [f32; 3],
    /// Candela for point and spot lights, lux for directional ones.
    pub intensity: f32,
    /// Distance where the light's influence ends; `None` is infinite.
    pub range: Option<f32>,
    /// Light-to-world transform of the pose the scene holds.
    pub to_world: glam::DMat4,
}
