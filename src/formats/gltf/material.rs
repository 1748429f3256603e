//! Appearance (renders only): materials, textures, samplers, images and light definitions
//! of a glTF file, checked and turned into the scene's records.
//!
//! Images are kept encoded, with their MIME type: decoding is the renderer's, and only a
//! job that samples a texture pays for it. Every index is checked (a dangling one is
//! [`GltfError::DanglingReference`] naming who refers), and factors must be finite and in
//! the ranges glTF gives them, so the renderer can trust every value.

use std::path::Path;
use std::sync::Arc;

use gltf::json;
use gltf::json::extensions::scene::khr_lights_punctual as lights;
use gltf::json::texture::{MagFilter, MinFilter, WrappingMode};
use gltf::json::validation::Checked;

use super::accessor::Data;
use super::container::{self, UriError};
use super::GltfError;
use crate::scene::{
    AlphaMode, Filter, Image, Light, LightKind, Material, Mipmap, Sampler, Specular, Texture,
    TextureRef, TextureTransform, Wrap,
};

/// What a render needs of a file besides its geometry.
pub(super) struct Appearance {
    pub materials: Vec<Material>,
    pub textures: Vec<Texture>,
    pub images: Vec<Image>,
}

fn bad_material(material: usize, reason: String) -> GltfError {
    GltfError::BadMaterial { material, reason }
}

/// Checks that `v` is finite and within `lo..=hi`.
fn in_range(v: f32, lo: f32, hi: f32) -> bool {
    v.is_finite() && (lo..=hi).contains(&v)
}

/// Reads every material, texture, sampler and image of the file.
pub(super) fn load(
    root: &json::Root,
    data: &Data<'_>,
    base_dir: Option<&Path>,
) -> Result<Appearance, GltfError> {
    let images = root
        .images
        .iter()
        .enumerate()
        .map(|(i, im)| image(root, data, i, im, base_dir))
        .collect::<Result<Vec<_>, _>>()?;
    let samplers = root
        .samplers
        .iter()
        .enumerate()
        .map(|(i, s)| sampler(i, s))
        .collect::<Result<Vec<_>, _>>()?;
    let mut textures = Vec::with_capacity(root.textures.len());
    for (t, tex) in root.textures.iter().enumerate() {
        let image = tex.source.value();
        if image >= images.len() {
            return Err(GltfError::DanglingReference {
                from: format!("texture {t}"),
                kind: "image",
                index: image,
                count: images.len(),
            });
        }
        let sampler = match tex.sampler.map(|s| s.value()) {
            None => Sampler::default(),
            Some(s) => *samplers
                .get(s)
                .ok_or_else(|| GltfError::DanglingReference {
                    from: format!("texture {t}"),
                    kind: "sampler",
                    index: s,
                    count: samplers.len(),
                })?,
        };
        textures.push(Texture { image, sampler });
    }
    let materials = root
        .materials
        .iter()
        .enumerate()
        .map(|(i, m)| material(i, m, textures.len()))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Appearance {
        materials,
        textures,
        images,
    })
}

/// MIME type from the bytes' signature, for images whose file gives none.
fn sniff(bytes: &[u8]) -> &'static str {
    if bytes.starts_with(b"\x89PNG\r\n\x1a\n") {
        "image/png"
    } else if bytes.starts_with(&[0xFF, 0xD8, 0xFF]) {
        "image/jpeg"
    } else if bytes.len() >= 12 && &bytes[..4] == b"RIFF" && &bytes[8..12] == b"WEBP" {
        "image/webp"
    } else if bytes.starts_with(b"\xABKTX 20\xBB") {
        "image/ktx2"
    } else {
        "application/octet-stream"
    }
}

/// Image `i`'s encoded bytes: from its buffer view, its data URI, or a file beside the
/// `.gltf` (only when there is a base directory, as for buffers).
fn image(
    root: &json::Root,
    data: &Data<'_>,
    i: usize,
    im: &json::Image,
    base_dir: Option<&Path>,
) -> Result<Image, GltfError> {
    let bad = |reason: String| GltfError::BadImage { image: i, reason };
    let mut mime = im.mime_type.as_ref().map(|m| m.0.clone());
    let bytes: Vec<u8> = match (&im.buffer_view, &im.uri) {
        (Some(v), _) => {
            let v = v.value();
            if v >= root.buffer_views.len() {
                return Err(GltfError::DanglingReference {
                    from: format!("image {i}"),
                    kind: "bufferView",
                    index: v,
                    count: root.buffer_views.len(),
                });
            }
            data.view_bytes(v)?.0.to_vec()
        }
        (None, Some(uri)) => {
            if let Some(rest) = uri.strip_prefix("data:") {
                if mime.is_none() {
                    let header = rest.split([';', ',']).next().unwrap_or_default();
                    mime = Some(header.to_string()).filter(|h| h.contains('/'));
                }
                container::decode_data_uri(rest).map_err(bad)?
            } else {
                let max = container::MAX_IMAGE_FILE_BYTES;
                // A byte past the most, to tell a longer file from one of exactly that.
                let read =
                    container::read_relative(uri, base_dir, max + 1).map_err(|e| match e {
                        UriError::Unsupported => bad(format!(
                            "URI {uri:?} is not supported (only data: URIs and relative paths)"
                        )),
                        UriError::Escapes => bad(format!(
                        "URI {uri:?} leaves the file's directory (`..`, a root or a drive): refused"
                    )),
                        UriError::NotAllowed => bad(format!(
                        "refers to external file {uri:?}, but only embedded images are allowed here"
                    )),
                        UriError::Io { path, detail } => {
                            bad(format!("cannot read {path} (uri {uri:?}): {detail}"))
                        }
                    })?;
                if read.len() as u64 > max {
                    return Err(bad(format!(
                        "the file of URI {uri:?} holds more than {max} bytes, the most an image may"
                    )));
                }
                read
            }
        }
        (None, None) => return Err(bad("has neither a bufferView nor a uri".to_string())),
    };
    let mime_type = mime.unwrap_or_else(|| sniff(&bytes).to_string());
    Ok(Image {
        mime_type,
        bytes: Arc::from(bytes),
    })
}

fn sampler(i: usize, s: &json::texture::Sampler) -> Result<Sampler, GltfError> {
    let bad = |what: &str| GltfError::BadSampler {
        sampler: i,
        reason: format!("invalid {what}"),
    };
    let mag_filter = match s.mag_filter {
        None => None,
        Some(Checked::Valid(MagFilter::Nearest)) => Some(Filter::Nearest),
        Some(Checked::Valid(MagFilter::Linear)) => Some(Filter::Linear),
        Some(Checked::Invalid) => return Err(bad("magFilter")),
    };
    let (min_filter, mipmap) = match s.min_filter {
        None => (None, Mipmap::None),
        Some(Checked::Valid(f)) => match f {
            MinFilter::Nearest => (Some(Filter::Nearest), Mipmap::None),
            MinFilter::Linear => (Some(Filter::Linear), Mipmap::None),
            MinFilter::NearestMipmapNearest => (Some(Filter::Nearest), Mipmap::Nearest),
            MinFilter::LinearMipmapNearest => (Some(Filter::Linear), Mipmap::Nearest),
            MinFilter::NearestMipmapLinear => (Some(Filter::Nearest), Mipmap::Linear),
            MinFilter::LinearMipmapLinear => (Some(Filter::Linear), Mipmap::Linear),
        },
        Some(Checked::Invalid) => return Err(bad("minFilter")),
    };
    let wrap = |w: &Checked<WrappingMode>, what: &str| match w {
        Checked::Valid(WrappingMode::ClampToEdge) => Ok(Wrap::ClampToEdge),
        Checked::Valid(WrappingMode::MirroredRepeat) => Ok(Wrap::MirroredRepeat),
        Checked::Valid(WrappingMode::Repeat) => Ok(Wrap::Repeat),
        Checked::Invalid => Err(bad(what)),
    };
    Ok(Sampler {
        mag_filter,
        min_filter,
        mipmap,
        wrap_s: wrap(&s.wrap_s, "wrapS")?,
        wrap_t: wrap(&s.wrap_t, "wrapT")?,
    })
}

/// A checked `KHR_texture_transform`.
fn transform(
    m: usize,
    slot: &str,
    t: &json::extensions::texture::TextureTransform,
) -> Result<TextureTransform, GltfError> {
    let out = TextureTransform {
        offset: t.offset.0,
        rotation: t.rotation.0,
        scale: t.scale.0,
    };
    let values = [
        out.offset[0],
        out.offset[1],
        out.rotation,
        out.scale[0],
        out.scale[1],
    ];
    if values.iter().any(|v| !v.is_finite()) {
        return Err(bad_material(
            m,
            format!("{slot} KHR_texture_transform has a non-finite value"),
        ));
    }
    Ok(out)
}

/// A checked texture reference of material `m` in slot `slot`.
fn texture_ref(
    m: usize,
    slot: &str,
    index: usize,
    tex_coord: u32,
    tt: Option<&json::extensions::texture::TextureTransform>,
    textures: usize,
) -> Result<TextureRef, GltfError> {
    if index >= textures {
        return Err(GltfError::DanglingReference {
            from: format!("material {m} {slot}"),
            kind: "texture",
            index,
            count: textures,
        });
    }
    let transform = tt.map(|t| transform(m, slot, t)).transpose()?;
    // The extension's texCoord overrides the reference's when present.
    let tex_coord = tt.and_then(|t| t.tex_coord).unwrap_or(tex_coord);
    // Only two sets are loaded: a third would read another set's coordinates unsaid.
    if tex_coord > 1 {
        return Err(bad_material(
            m,
            format!(
                "{slot} reads TEXCOORD_{tex_coord}: only TEXCOORD_0 and TEXCOORD_1 are supported"
            ),
        ));
    }
    Ok(TextureRef {
        texture: index,
        tex_coord,
        transform,
    })
}

fn info_ref(
    m: usize,
    slot: &str,
    info: &Option<json::texture::Info>,
    textures: usize,
) -> Result<Option<TextureRef>, GltfError> {
    info.as_ref()
        .map(|i| {
            let tt = i
                .extensions
                .as_ref()
                .and_then(|e| e.texture_transform.as_ref());
            texture_ref(m, slot, i.index.value(), i.tex_coord, tt, textures)
        })
        .transpose()
}

/// `KHR_texture_transform` of a normal or occlusion texture, which the `gltf` crate keeps
/// as raw JSON.
fn raw_transform(
    m: usize,
    slot: &str,
    others: &serde_json::Map<String, serde_json::Value>,
) -> Result<Option<json::extensions::texture::TextureTransform>, GltfError> {
    others
        .get("KHR_texture_transform")
        .map(|v| {
            serde_json::from_value(v.clone()).map_err(|e| {
                bad_material(m, format!("{slot} KHR_texture_transform is malformed: {e}"))
            })
        })
        .transpose()
}

fn material(m: usize, mat: &json::Material, textures: usize) -> Result<Material, GltfError> {
    let pbr = &mat.pbr_metallic_roughness;
    let check = |ok: bool, what: &str| {
        if ok {
            Ok(())
        } else {
            Err(bad_material(m, what.to_string()))
        }
    };
    let base = pbr.base_color_factor.0;
    check(
        base.iter().all(|&v| in_range(v, 0.0, 1.0)),
        "baseColorFactor must be in [0, 1]",
    )?;
    check(
        in_range(pbr.metallic_factor.0, 0.0, 1.0),
        "metallicFactor must be in [0, 1]",
    )?;
    check(
        in_range(pbr.roughness_factor.0, 0.0, 1.0),
        "roughnessFactor must be in [0, 1]",
    )?;
    let emissive = mat.emissive_factor.0;
    check(
        emissive.iter().all(|&v| in_range(v, 0.0, 1.0)),
        "emissiveFactor must be in [0, 1]",
    )?;
    let ext = mat.extensions.as_ref();
    let emissive_strength = ext
        .and_then(|e| e.emissive_strength.as_ref())
        .map_or(1.0, |s| s.emissive_strength.0);
    check(
        in_range(emissive_strength, 0.0, f32::MAX),
        "KHR_materials_emissive_strength emissiveStrength must be finite and non-negative",
    )?;
    let specular = match ext.and_then(|e| e.specular.as_ref()) {
        None => Specular::default(),
        Some(s) => {
            check(
                in_range(s.specular_factor.0, 0.0, 1.0),
                "KHR_materials_specular specularFactor must be in [0, 1]",
            )?;
            check(
                s.specular_color_factor
                    .0
                    .iter()
                    .all(|&v| in_range(v, 0.0, f32::MAX)),
                "KHR_materials_specular specularColorFactor must be finite and non-negative",
            )?;
            Specular {
                factor: s.specular_factor.0,
                texture: info_ref(m, "specularTexture", &s.specular_texture, textures)?,
                color_factor: s.specular_color_factor.0,
                color_texture: info_ref(
                    m,
                    "specularColorTexture",
                    &s.specular_color_texture,
                    textures,
                )?,
            }
        }
    };
    let alpha_mode = match mat.alpha_mode {
        Checked::Valid(json::material::AlphaMode::Opaque) => AlphaMode::Opaque,
        Checked::Valid(json::material::AlphaMode::Blend) => AlphaMode::Blend,
        Checked::Valid(json::material::AlphaMode::Mask) => {
            let cutoff = mat.alpha_cutoff.map_or(0.5, |c| c.0);
            check(
                in_range(cutoff, 0.0, f32::MAX),
                "alphaCutoff must be finite and non-negative",
            )?;
            AlphaMode::Mask { cutoff }
        }
        Checked::Invalid => return Err(bad_material(m, "invalid alphaMode".to_string())),
    };
    let (normal_texture, normal_scale) = match &mat.normal_texture {
        None => (None, 1.0),
        Some(n) => {
            check(n.scale.is_finite(), "normalTexture.scale must be finite")?;
            let tt = match &n.extensions {
                Some(e) => raw_transform(m, "normalTexture", &e.others)?,
                None => None,
            };
            let r = texture_ref(
                m,
                "normalTexture",
                n.index.value(),
                n.tex_coord,
                tt.as_ref(),
                textures,
            )?;
            (Some(r), n.scale)
        }
    };
    let (occlusion_texture, occlusion_strength) = match &mat.occlusion_texture {
        None => (None, 1.0),
        Some(o) => {
            check(
                in_range(o.strength.0, 0.0, 1.0),
                "occlusionTexture.strength must be in [0, 1]",
            )?;
            let tt = match &o.extensions {
                Some(e) => raw_transform(m, "occlusionTexture", &e.others)?,
                None => None,
            };
            let r = texture_ref(
                m,
                "occlusionTexture",
                o.index.value(),
                o.tex_coord,
                tt.as_ref(),
                textures,
            )?;
            (Some(r), o.strength.0)
        }
    };
    Ok(Material {
        name: mat.name.clone().unwrap_or_default(),
        base_color_factor: base,
        base_color_texture: info_ref(m, "baseColorTexture", &pbr.base_color_texture, textures)?,
        metallic_factor: pbr.metallic_factor.0,
        roughness_factor: pbr.roughness_factor.0,
        metallic_roughness_texture: info_ref(
            m,
            "metallicRoughnessTexture",
            &pbr.metallic_roughness_texture,
            textures,
        )?,
        normal_texture,
        normal_scale,
        occlusion_texture,
        occlusion_strength,
        emissive_factor: emissive,
        emissive_texture: info_ref(m, "emissiveTexture", &mat.emissive_texture, textures)?,
        emissive_strength,
        specular,
        alpha_mode,
        double_sided: mat.double_sided,
    })
}

/// The file's light definitions (`KHR_lights_punctual.lights`).
pub(super) fn light_definitions(root: &json::Root) -> &[lights::Light] {
    root.extensions
        .as_ref()
        .and_then(|e| e.khr_lights_punctual.as_ref())
        .map_or(&[], |l| l.lights.as_slice())
}

/// Node `n`'s light, checked; its `to_world` is filled in once the pose is known.
pub(super) fn light(root: &json::Root, n: usize) -> Result<Option<Light>, GltfError> {
    let Some(index) = root.nodes[n]
        .extensions
        .as_ref()
        .and_then(|e| e.khr_lights_punctual.as_ref())
        .map(|l| l.light.value())
    else {
        return Ok(None);
    };
    let defs = light_definitions(root);
    let Some(def) = defs.get(index) else {
        return Err(GltfError::DanglingReference {
            from: format!("node {n} (KHR_lights_punctual)"),
            kind: "light",
            index,
            count: defs.len(),
        });
    };
    let bad = |reason: &str| GltfError::BadLight {
        light: index,
        reason: reason.to_string(),
    };
    if !def.color.iter().all(|&c| in_range(c, 0.0, f32::MAX)) {
        return Err(bad("color must be finite and non-negative"));
    }
    if !in_range(def.intensity, 0.0, f32::MAX) {
        return Err(bad("intensity must be finite and non-negative"));
    }
    if def.range.is_some_and(|r| !(r.is_finite() && r > 0.0)) {
        return Err(bad("range must be a positive finite number"));
    }
    let kind = match def.type_ {
        Checked::Valid(lights::Type::Directional) => LightKind::Directional,
        Checked::Valid(lights::Type::Point) => LightKind::Point,
        Checked::Valid(lights::Type::Spot) => {
            let (inner, outer) = def
                .spot
                .as_ref()
                .map_or((0.0, std::f32::consts::FRAC_PI_4), |s| {
                    (s.inner_cone_angle, s.outer_cone_angle)
                });
            let ok = inner.is_finite()
                && outer.is_finite()
                && inner >= 0.0
                && inner < outer
                && outer <= std::f32::consts::FRAC_PI_2;
            if !ok {
                return Err(bad(
                    "spot cone angles must satisfy 0 <= innerConeAngle < outerConeAngle <= pi/2",
                ));
            }
            LightKind::Spot {
                inner_cone_angle: inner,
                outer_cone_angle: outer,
            }
        }
        Checked::Invalid => return Err(bad("invalid type")),
    };
    Ok(Some(Light {
        name: def.name.clone().unwrap_or_default(),
        light: index,
        node: n,
        kind,
        color: def.color,
        intensity: def.intensity,
        range: def.range,
        to_world: glam::DMat4::IDENTITY,
    }))
}
