//! Texture lookups for `path`: the scene's images decoded with the `image` crate (only those
//! a material uses, and only when a render shades), then sampled as glTF says: texture
//! coordinates through `KHR_texture_transform`, each axis wrapped by its sampler's mode,
//! bilinear filtering unless the sampler asks for nearest, and colour textures (base colour,
//! emissive) decoded from sRGB before filtering while data textures (metallic-roughness,
//! normal) stay linear. Mipmaps are not built: a texel per lookup, without minification filtering.

use std::sync::Arc;

use glam::{Vec2, Vec4};

use crate::scene::{Filter, Scene, TextureRef, Wrap};

/// Most pixels of one texture: 8192 × 8192, 1 GiB once decoded to f32 RGBA.
pub const MAX_TEXTURE_PIXELS: u64 = 1 << 26;

/// Longest side of one texture, pixels.
pub const MAX_TEXTURE_SIDE: u32 = 16384;

/// Errors of preparing textures.
#[derive(Debug, thiserror::Error)]
pub enum TextureError {
    /// An image's bytes do not decode.
    #[error("image {image} ({mime}): cannot decode: {reason}")]
    Decode {
        /// Image index in the file.
        image: usize,
        /// Its MIME type.
        mime: String,
        /// What the decoder said.
        reason: String,
    },
}

/// One decoded image: RGBA texels in [0, 1], row-major from the top row, as stored (not
/// yet linearised).
#[derive(Clone, Debug, PartialEq)]
pub struct Texels {
    width: u32,
    height: u32,
    texels: Store,
}

/// How the texels are held. Images of 8 bits a channel (nearly every glTF texture) keep
/// them as 4 bytes: a quarter of the memory and cache lines of f32 texels, and their sRGB
/// decode is a table lookup ([`SRGB_TO_LINEAR`]) instead of a `powf` per channel of every
/// one of the four texels a bilinear lookup reads. Deeper images keep f32.
#[derive(Clone, Debug, PartialEq)]
enum Store {
    Rgba8(Vec<[u8; 4]>),
    RgbaF32(Vec<[f32; 4]>),
}

/// `to_linear(i / 255)` for every 8-bit code `i`: the same values a lookup would compute.
static SRGB_TO_LINEAR: std::sync::LazyLock<[f32; 256]> =
    std::sync::LazyLock::new(|| std::array::from_fn(|i| to_linear(unit8(i as u8))));

/// An 8-bit code as a value in [0, 1], as the `image` crate converts it.
#[inline]
fn unit8(c: u8) -> f32 {
    c as f32 / 255.0
}

impl Texels {
    /// Decodes `bytes` (any format the `image` crate was built with: PNG, JPEG).
    ///
    /// A few bytes of PNG can declare 100000 × 100000 pixels (a decompression bomb), so
    /// the declared size is checked against [`MAX_TEXTURE_SIDE`] and [`MAX_TEXTURE_PIXELS`]
    /// before a pixel is decoded, and the decoder itself runs under the `image` crate's
    /// allocation limit.
    pub fn decode(bytes: &[u8]) -> Result<Texels, String> {
        use image::ImageDecoder;
        let mut reader = image::ImageReader::new(std::io::Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|e| e.to_string())?;
        let mut limits = image::Limits::default();
        limits.max_alloc = Some(MAX_TEXTURE_PIXELS * 8);
        reader.limits(limits);
        let decoder = reader.into_decoder().map_err(|e| e.to_string())?;
        let (w, h) = decoder.dimensions();
        if w > MAX_TEXTURE_SIDE
            || h > MAX_TEXTURE_SIDE
            || u64::from(w) * u64::from(h) > MAX_TEXTURE_PIXELS
        {
            return Err(format!(
                "the image declares {w} × {h} pixels, over the limit of {MAX_TEXTURE_PIXELS} pixels \
                 and {MAX_TEXTURE_SIDE} on a side"
            ));
        }
        let img = image::DynamicImage::from_decoder(decoder).map_err(|e| e.to_string())?;
        let (width, height) = (img.width(), img.height());
        if width == 0 || height == 0 {
            return Err("the image is empty".into());
        }
        use image::DynamicImage as D;
        let texels = match img {
            D::ImageLuma8(_) | D::ImageLumaA8(_) | D::ImageRgb8(_) | D::ImageRgba8(_) => {
                Store::Rgba8(img.to_rgba8().pixels().map(|p| p.0).collect())
            }
            _ => Store::RgbaF32(img.to_rgba32f().pixels().map(|p| p.0).collect()),
        };
        Ok(Texels {
            width,
            height,
            texels,
        })
    }

    /// Texels from values (tests).
    pub fn from_rgba(width: u32, height: u32, rgba: Vec<[f32; 4]>) -> Option<Texels> {
        (width > 0 && height > 0 && rgba.len() == width as usize * height as usize).then_some(
            Texels {
                width,
                height,
                texels: Store::RgbaF32(rgba),
            },
        )
    }

    /// Texel `(x, y)` (in range), linearised from sRGB when `srgb`; alpha stays linear.
    #[inline]
    fn texel(&self, x: i64, y: i64, srgb: bool) -> Vec4 {
        let i = y as usize * self.width as usize + x as usize;
        match &self.texels {
            Store::Rgba8(t) => {
                let p = t[i];
                if srgb {
                    let lut = &*SRGB_TO_LINEAR;
                    Vec4::new(
                        lut[p[0] as usize],
                        lut[p[1] as usize],
                        lut[p[2] as usize],
                        unit8(p[3]),
                    )
                } else {
                    Vec4::new(unit8(p[0]), unit8(p[1]), unit8(p[2]), unit8(p[3]))
                }
            }
            Store::RgbaF32(t) => {
                let v = Vec4::from(t[i]);
                if srgb {
                    Vec4::new(to_linear(v.x), to_linear(v.y), to_linear(v.z), v.w)
                } else {
                    v
                }
            }
        }
    }

    /// The value at texture coordinate `uv` (glTF's: (0, 0) is the image's top-left
    /// corner).
    pub fn sample(&self, uv: Vec2, wrap: [Wrap; 2], filter: Filter, srgb: bool) -> Vec4 {
        let (w, h) = (self.width as i64, self.height as i64);
        let x = uv.x * w as f32 - 0.5;
        let y = uv.y * h as f32 - 0.5;
        if !(x.is_finite() && y.is_finite()) {
            return self.texel(0, 0, srgb);
        }
        match filter {
            Filter::Nearest => {
                let (i, j) = ((x + 0.5).floor() as i64, (y + 0.5).floor() as i64);
                self.texel(wrap_index(i, w, wrap[0]), wrap_index(j, h, wrap[1]), srgb)
            }
            Filter::Linear => {
                let (x0, y0) = (x.floor(), y.floor());
                let (fx, fy) = (x - x0, y - y0);
                let (i, j) = (x0 as i64, y0 as i64);
                let at = |di: i64, dj: i64| {
                    self.texel(
                        wrap_index(i + di, w, wrap[0]),
                        wrap_index(j + dj, h, wrap[1]),
                        srgb,
                    )
                };
                let top = at(0, 0) * (1.0 - fx) + at(1, 0) * fx;
                let bottom = at(0, 1) * (1.0 - fx) + at(1, 1) * fx;
                top * (1.0 - fy) + bottom * fy
            }
        }
    }
}

/// sRGB → linear (IEC 61966-2-1).
fn to_linear(c: f32) -> f32 {
    if c <= 0.040_45 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// A texel index `i` of an axis of `n` texels, wrapped.
fn wrap_index(i: i64, n: i64, wrap: Wrap) -> i64 {
    match wrap {
        Wrap::ClampToEdge => i.clamp(0, n - 1),
        Wrap::Repeat => i.rem_euclid(n),
        Wrap::MirroredRepeat => {
            let k = i.rem_euclid(2 * n);
            if k < n {
                k
            } else {
                2 * n - 1 - k
            }
        }
    }
}

/// A texture ready to sample: its decoded image, the sampler's wraps (S, T) and filter.
type Bound = (Arc<Texels>, [Wrap; 2], Filter);

/// The textures of a scene, decoded.
#[derive(Clone, Debug, Default)]
pub struct TextureSet {
    /// Per scene texture: its decoded image (`None`: no material uses it), sampler wraps and
    /// filter.
    textures: Vec<Option<Bound>>,
}

impl TextureSet {
    /// Decodes every image that a material of `scene` samples through a texture this
    /// renderer uses (base colour, metallic-roughness, normal, emissive), each image once.
    pub fn of(scene: &Scene) -> Result<TextureSet, TextureError> {
        let mut used = vec![false; scene.textures.len()];
        for m in &scene.materials {
            for r in [
                m.base_color_texture,
                m.metallic_roughness_texture,
                m.normal_texture,
                m.emissive_texture,
            ]
            .into_iter()
            .flatten()
            {
                if let Some(u) = used.get_mut(r.texture) {
                    *u = true;
                }
            }
        }
        let mut decoded: Vec<Option<Arc<Texels>>> = vec![None; scene.images.len()];
        let mut textures = Vec::with_capacity(scene.textures.len());
        for (t, used) in scene.textures.iter().zip(used) {
            if !used || t.image >= scene.images.len() {
                textures.push(None);
                continue;
            }
            let texels = match &decoded[t.image] {
                Some(d) => Arc::clone(d),
                None => {
                    let im = &scene.images[t.image];
                    let d = Arc::new(Texels::decode(&im.bytes).map_err(|reason| {
                        TextureError::Decode {
                            image: t.image,
                            mime: im.mime_type.clone(),
                            reason,
                        }
                    })?);
                    decoded[t.image] = Some(Arc::clone(&d));
                    d
                }
            };
            // Magnification's filter when given (no mipmaps: every lookup is treated alike).
            let filter = t
                .sampler
                .mag_filter
                .or(t.sampler.min_filter)
                .unwrap_or(Filter::Linear);
            textures.push(Some((texels, [t.sampler.wrap_s, t.sampler.wrap_t], filter)));
        }
        Ok(TextureSet { textures })
    }

    /// Textures from decoded images, in texture-index order (tests, generated scenes).
    pub fn from_texels(list: Vec<(Texels, [Wrap; 2], Filter)>) -> TextureSet {
        TextureSet {
            textures: list
                .into_iter()
                .map(|(t, wrap, filter)| Some((Arc::new(t), wrap, filter)))
                .collect(),
        }
    }

    /// The value of texture reference `r` at texture coordinates `uv` (`uv[k]` is
    /// `TEXCOORD_k`); `None` when the texture was not decoded.
    pub fn sample(&self, r: &TextureRef, uv: [Vec2; 2], srgb: bool) -> Option<Vec4> {
        let (texels, wrap, filter) = self.textures.get(r.texture)?.as_ref()?;
        let mut st = uv[(r.tex_coord as usize).min(1)];
        if let Some(t) = &r.transform {
            st = t.apply(st);
        }
        Some(texels.sample(st, *wrap, *filter, srgb))
    }
}

/// A scene's textures, decoded by the first frame that needs them and shared by the rest
/// of a sequence: poses and geometry versions move positions, never texels, and decoding
/// four 2048² images takes longer than rendering a small frame of them.
#[derive(Debug, Default)]
pub struct DecodedOnce(std::sync::OnceLock<TextureSet>);

impl DecodedOnce {
    /// The textures of `scene` (decoded now if no frame has yet).
    pub fn get(&self, scene: &Scene) -> Result<&TextureSet, TextureError> {
        if let Some(t) = self.0.get() {
            return Ok(t);
        }
        let decoded = TextureSet::of(scene)?;
        Ok(self.0.get_or_init(|| decoded))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn checker() -> Texels {
        // 2×2: black, white / white, black (linear values).
        Texels::from_rgba(
            2,
            2,
            vec![
                [0.0, 0.0, 0.0, 1.0],
                [1.0, 1.0, 1.0, 1.0],
                [1.0, 1.0, 1.0, 1.0],
                [0.0, 0.0, 0.0, 1.0],
            ],
        )
        .unwrap()
    }

    #[test]
    fn texel_centres_bilinear_midpoints_and_wraps() {
        let t = checker();
        let lin = [Wrap::Repeat; 2];
        let at = |u, v, wrap, f| t.sample(Vec2::new(u, v), wrap, f, false).x;
        assert_eq!(at(0.25, 0.25, lin, Filter::Linear), 0.0);
        assert_eq!(at(0.75, 0.25, lin, Filter::Linear), 1.0);
        assert!((at(0.5, 0.25, lin, Filter::Linear) - 0.5).abs() < 1e-6);
        // Repeat: u = 1.25 is u = 0.25; clamp: u = 1.25 is the last texel.
        assert_eq!(at(1.25, 0.25, lin, Filter::Nearest), 0.0);
        let clamp = [Wrap::ClampToEdge; 2];
        assert_eq!(at(1.25, 0.25, clamp, Filter::Nearest), 1.0);
        // Mirrored: u = 1.25 is u = 0.75.
        let mirror = [Wrap::MirroredRepeat; 2];
        assert_eq!(at(1.25, 0.25, mirror, Filter::Nearest), 1.0);
        assert_eq!(wrap_index(-1, 4, Wrap::MirroredRepeat), 0);
        assert_eq!(wrap_index(-1, 4, Wrap::Repeat), 3);
    }

    #[test]
    fn colour_textures_are_linearised_before_filtering() {
        let t = Texels::from_rgba(1, 1, vec![[0.5, 0.5, 0.5, 0.5]]).unwrap();
        let v = t.sample(Vec2::new(0.5, 0.5), [Wrap::Repeat; 2], Filter::Linear, true);
        assert!((v.x - 0.214_041).abs() < 1e-5, "{v}");
        assert_eq!(v.w, 0.5);
    }

    #[test]
    fn png_bytes_decode() {
        let mut png = Vec::new();
        {
            let mut e = ::png::Encoder::new(&mut png, 1, 1);
            e.set_color(::png::ColorType::Rgba);
            let mut w = e.write_header().unwrap();
            w.write_image_data(&[255, 0, 51, 255]).unwrap();
        }
        let t = Texels::decode(&png).unwrap();
        assert_eq!(t.texels, Store::Rgba8(vec![[255, 0, 51, 255]]));
        let at = |srgb| {
            t.sample(
                Vec2::new(0.5, 0.5),
                [Wrap::Repeat; 2],
                Filter::Nearest,
                srgb,
            )
        };
        assert_eq!(at(false), Vec4::new(1.0, 0.0, 0.2, 1.0));
        assert!(Texels::decode(b"not an image").is_err());
    }

    #[test]
    fn eight_bit_texels_decode_as_f32_texels_would() {
        // Every code through the table is what the f32 path computes for the value the
        // `image` crate converts the same code to.
        let codes: Vec<[u8; 4]> = (0..=255u8).map(|c| [c, c, c, c]).collect();
        let flat: Vec<u8> = codes.iter().flatten().copied().collect();
        let img =
            image::DynamicImage::ImageRgba8(image::RgbaImage::from_raw(256, 1, flat).unwrap());
        let as_f32: Vec<[f32; 4]> = img.to_rgba32f().pixels().map(|p| p.0).collect();
        let a = Texels {
            width: 256,
            height: 1,
            texels: Store::Rgba8(codes),
        };
        let b = Texels::from_rgba(256, 1, as_f32).unwrap();
        for x in 0..256 {
            for srgb in [false, true] {
                assert_eq!(
                    a.texel(x, 0, srgb),
                    b.texel(x, 0, srgb),
                    "code {x}, srgb {srgb}"
                );
            }
        }
    }
}
