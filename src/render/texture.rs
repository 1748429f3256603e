//! Texture lookups for `path`: the scene's images decoded with the `image` crate (only those
//! a material uses, and only when a render shades), then sampled as glTF says: texture
//! coordinates through `KHR_texture_transform`, each axis wrapped by its sampler's mode,
//! the sampler's magnification and minification filters, and colour textures (base colour,
//! emissive) decoded from sRGB before filtering while data textures (metallic-roughness,
//! normal) stay linear. Minification reads a MIP pyramid ([`super::mipmap`]) at the level
//! of the lookup's footprint.

use std::sync::Arc;

use glam::{Vec2, Vec4};

use rayon::prelude::*;

use super::bundle::Bundle;
use super::mipmap::{Filtering, Pyramid};
use crate::scene::{Filter, Scene, TextureRef, Wrap};

/// Most pixels of one texture: 8192 × 8192, 1 GiB once decoded to f32 RGBA (its MIP
/// pyramid a third more, per use: colour and data uses of one image build one each).
pub const MAX_TEXTURE_PIXELS: u64 = 1 << 26;

/// Longest side of one texture, pixels.
pub const MAX_TEXTURE_SIDE: u32 = 16384;

/// Most texels a render may decode over all of a scene's textures, counting an image once
/// per use (colour and data uses each build a pyramid): 2^28, 1 GiB of 8-bit texels, about
/// 2 GiB at the decoders' peak with the pyramids. Sixteen 4096² textures fit, or sixty-four
/// of 2048²; a file of many small PNGs that each declare 8192² (a few KB apiece) does not,
/// and is refused before a pixel is decoded, where it would exhaust memory otherwise.
pub const MAX_SCENE_TEXTURE_PIXELS: u64 = 1 << 28;

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
    /// The scene's textures together declare more texels than a render may decode.
    #[error(
        "the scene's textures declare {pixels} texels in all (image {largest}, the largest, \
         {width} × {height}; an image counts once per use), over the limit of {limit}"
    )]
    TooLarge {
        /// Texels declared, over every use.
        pixels: u64,
        /// The limit ([`MAX_SCENE_TEXTURE_PIXELS`]).
        limit: u64,
        /// The image with the most texels.
        largest: usize,
        /// Its width.
        width: u32,
        /// Its height.
        height: u32,
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
/// decode is a table lookup ([`Decode8`]) instead of a `powf` per channel of every
/// one of the four texels a bilinear lookup reads. Deeper images keep f32.
#[derive(Clone, Debug, PartialEq)]
enum Store {
    Rgba8(Vec<[u8; 4]>),
    RgbaF32(Vec<[f32; 4]>),
}

/// The linear values halfway between consecutive 8-bit sRGB codes: the code nearest (in
/// sRGB) to a linear value is the number of bounds at or below it.
static SRGB_CODE_BOUNDS: std::sync::LazyLock<[f32; 255]> =
    std::sync::LazyLock::new(|| std::array::from_fn(|k| to_linear((k as f32 + 0.5) / 255.0)));

/// Per 1/4096 of linear light, the first code whose bound lies above its start: where
/// [`srgb_code`] begins its search, at most a code or two below the answer.
static SRGB_CODE_START: std::sync::LazyLock<[u8; 4097]> = std::sync::LazyLock::new(|| {
    std::array::from_fn(|k| {
        let v = k as f32 / 4096.0;
        SRGB_CODE_BOUNDS.partition_point(|&b| b <= v) as u8
    })
});

/// The 8-bit sRGB code nearest to linear value `v` (clamped to [0, 1]): the count of
/// [`SRGB_CODE_BOUNDS`] at or below it.
#[inline]
fn srgb_code(v: f32) -> u8 {
    let v = v.clamp(0.0, 1.0);
    let bounds = &*SRGB_CODE_BOUNDS;
    let mut c = SRGB_CODE_START[(v * 4096.0) as usize] as usize;
    while c < bounds.len() && bounds[c] <= v {
        c += 1;
    }
    c as u8
}

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

    /// Width in texels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in texels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Bytes of texels held.
    pub fn bytes(&self) -> usize {
        match &self.texels {
            Store::Rgba8(t) => std::mem::size_of_val(&t[..]),
            Store::RgbaF32(t) => std::mem::size_of_val(&t[..]),
        }
    }

    /// The texels, when 8-bit.
    pub(crate) fn rgba8(&self) -> Option<&[[u8; 4]]> {
        match &self.texels {
            Store::Rgba8(t) => Some(t),
            Store::RgbaF32(_) => None,
        }
    }

    /// The next MIP level: half the size on each axis (rounded down, at least 1), each
    /// texel the mean of the 2 × 2 texels it covers (the last row and column of an odd
    /// side take in the 3 left over, so that every texel counts). Colour images (`srgb`)
    /// are averaged in linear light and encoded back: averaging sRGB codes would darken
    /// every edge between light and dark. `None` for a 1 × 1 image.
    pub fn half(&self, srgb: bool) -> Option<Texels> {
        if self.width == 1 && self.height == 1 {
            return None;
        }
        let (w, h) = ((self.width / 2).max(1), (self.height / 2).max(1));
        let span = |i: u32, n: u32, m: u32| -> std::ops::Range<i64> {
            let lo = (2 * i).min(n - 1);
            let hi = if i + 1 == m { n } else { 2 * i + 2 };
            lo as i64..hi as i64
        };
        let texels = match &self.texels {
            // 8-bit images (nearly all): their own loop, through the sRGB tables, since a
            // 2048² image's levels are 1.4M texels each averaging four.
            Store::Rgba8(src) => {
                let sw = self.width as usize;
                let mut out = vec![[0u8; 4]; w as usize * h as usize];
                // Columns (and rows) whose texel averages exactly two: all but the last of
                // an odd side, none of a side of 1.
                let pairs = |n: u32, m: u32| match n {
                    1 => 0,
                    n if n % 2 == 0 => m as usize,
                    _ => m as usize - 1,
                };
                let (pair_cols, pair_rows) = (pairs(self.width, w), pairs(self.height, h));
                out.par_chunks_mut(w as usize)
                    .enumerate()
                    .for_each(|(j, row)| {
                        let ys = span(j as u32, self.height, h);
                        let mut rest = 0;
                        if j < pair_rows {
                            // The common case, 2 × 2, in a loop of its own.
                            let r0 = &src[2 * j * sw..][..2 * pair_cols];
                            let r1 = &src[(2 * j + 1) * sw..][..2 * pair_cols];
                            let quads = r0.chunks_exact(2).zip(r1.chunks_exact(2));
                            for (t, (a, b)) in row[..pair_cols].iter_mut().zip(quads) {
                                *t = average8([a[0], a[1], b[0], b[1]], 4, srgb);
                            }
                            rest = pair_cols;
                        }
                        for (i, t) in row.iter_mut().enumerate().skip(rest) {
                            let xs = span(i as u32, self.width, w);
                            let n = ((xs.end - xs.start) * (ys.end - ys.start)) as u32;
                            let block = ys.clone().flat_map(|y| {
                                xs.clone().map(move |x| src[y as usize * sw + x as usize])
                            });
                            *t = average8(block, n, srgb);
                        }
                    });
                Store::Rgba8(out)
            }
            Store::RgbaF32(_) => {
                let mean = |i: u32, j: u32| -> Vec4 {
                    let (xs, ys) = (span(i, self.width, w), span(j, self.height, h));
                    let mut sum = Vec4::ZERO;
                    for y in ys.clone() {
                        for x in xs.clone() {
                            sum += self.texel(x, y, srgb);
                        }
                    }
                    sum / ((xs.end - xs.start) * (ys.end - ys.start)) as f32
                };
                let mut out = vec![[0f32; 4]; w as usize * h as usize];
                out.par_chunks_mut(w as usize)
                    .enumerate()
                    .for_each(|(j, row)| {
                        for (i, t) in row.iter_mut().enumerate() {
                            *t = encode_f32(mean(i as u32, j as u32), srgb);
                        }
                    });
                Store::RgbaF32(out)
            }
        };
        Some(Texels {
            width: w,
            height: h,
            texels,
        })
    }

    /// Texel `(x, y)` (in range), linearised from sRGB when `srgb`; alpha stays linear.
    #[inline]
    fn texel(&self, x: i64, y: i64, srgb: bool) -> Vec4 {
        let i = y as usize * self.width as usize + x as usize;
        match &self.texels {
            Store::Rgba8(t) => decode8(t[i], srgb),
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
        filter_level(uv, (self.width, self.height), wrap, filter, |x, y| {
            self.texel(x, y, srgb)
        })
    }
}

/// Linear interpolation `a (1 − t) + b t` of filtered values, in this one order of
/// operations, so that a texture read alone ([`Texels::sample`]) and the same texture read
/// in a bundle ([`super::bundle::Bundle`]) give the same bits. (glam's own `lerp` rounds
/// differently.)
pub(crate) trait Blend: Copy {
    fn blend(self, b: Self, t: f32) -> Self;
}

/// Nothing to blend: what a pass over the levels a lookup reads returns when it only
/// touches them ([`super::bundle::Bundle::prefetch`]).
impl Blend for () {
    #[inline(always)]
    fn blend(self, _: (), _: f32) {}
}

impl Blend for Vec4 {
    #[inline(always)]
    fn blend(self, b: Vec4, t: f32) -> Vec4 {
        self * (1.0 - t) + b * t
    }
}

impl<const N: usize> Blend for [Vec4; N] {
    #[inline(always)]
    fn blend(self, b: [Vec4; N], t: f32) -> [Vec4; N] {
        std::array::from_fn(|s| self[s].blend(b[s], t))
    }
}

/// The value at texture coordinate `uv` (glTF's: (0, 0) is the image's top-left corner) of
/// a level of `size` texels whose texel `(x, y)` (in range) is `texel(x, y)`: the nearest
/// texel or the bilinear blend of four, each axis wrapped by its mode.
#[inline(always)]
pub(crate) fn filter_level<T: Blend>(
    uv: Vec2,
    size: (u32, u32),
    wrap: [Wrap; 2],
    filter: Filter,
    texel: impl Fn(i64, i64) -> T,
) -> T {
    let (w, h) = (size.0 as i64, size.1 as i64);
    let x = uv.x * w as f32 - 0.5;
    let y = uv.y * h as f32 - 0.5;
    if !(x.is_finite() && y.is_finite()) {
        return texel(0, 0);
    }
    match filter {
        Filter::Nearest => {
            let (i, j) = (floor(x + 0.5) as i64, floor(y + 0.5) as i64);
            texel(wrap_index(i, w, wrap[0]), wrap_index(j, h, wrap[1]))
        }
        Filter::Linear => {
            let b = Bilinear::at(x, y, (w, h), wrap);
            let [i0, i1] = b.x;
            let [j0, j1] = b.y;
            let top = texel(i0, j0).blend(texel(i1, j0), b.fx);
            let bottom = texel(i0, j1).blend(texel(i1, j1), b.fx);
            top.blend(bottom, b.fy)
        }
    }
}

/// The four taps of a bilinear lookup: two columns, two rows (each wrapped), and the
/// weights of the second of each. One computation for [`filter_level`] and the bundle's
/// own lookups ([`super::bundle::Bundle`]), which must give the same bits.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Bilinear {
    pub x: [i64; 2],
    pub y: [i64; 2],
    pub fx: f32,
    pub fy: f32,
}

impl Bilinear {
    /// The taps around `(x, y)` in texel units (texel centres at `k + 0.5`, already
    /// shifted by a half: the finite `uv · size − 0.5`) of a level of `size` texels.
    #[inline(always)]
    pub(crate) fn at(x: f32, y: f32, (w, h): (i64, i64), wrap: [Wrap; 2]) -> Bilinear {
        let (x0, y0) = (floor(x), floor(y));
        let (i, j) = (x0 as i64, y0 as i64);
        // Each axis wrapped once for both of its taps.
        Bilinear {
            x: [wrap_index(i, w, wrap[0]), wrap_index(i + 1, w, wrap[0])],
            y: [wrap_index(j, h, wrap[1]), wrap_index(j + 1, h, wrap[1])],
            fx: x - x0,
            fy: y - y0,
        }
    }
}

/// `x.floor()` without the libm call that `floor` compiles to on x86-64's baseline (SSE2
/// has no rounding instruction): every texture lookup takes two or three. Infinities and
/// NaN pass through as they are; only `-0.0` differs, giving `+0.0`, which no caller can
/// tell apart (the taps are cast to integers, and a level of detail is floored only when
/// positive).
#[inline(always)]
pub(crate) fn floor(x: f32) -> f32 {
    // At 2^23 and beyond every f32 is an integer.
    if x.abs() < 8_388_608.0 {
        let t = x as i32 as f32;
        if t > x {
            t - 1.0
        } else {
            t
        }
    } else {
        x
    }
}

/// The 8-bit texel of a MIP level over the `n` texels of `block`: the nearest code to
/// their mean, of the light for colour channels (`srgb`), of the codes for data and alpha.
#[inline(always)]
fn average8(block: impl IntoIterator<Item = [u8; 4]>, n: u32, srgb: bool) -> [u8; 4] {
    let lut = &decode_tables().srgb;
    let (mut light, mut code) = ([0f32; 3], [0u32; 4]);
    for p in block {
        for c in 0..4 {
            code[c] += u32::from(p[c]);
        }
        if srgb {
            for c in 0..3 {
                light[c] += lut[p[c] as usize];
            }
        }
    }
    let mut t = code.map(|k| ((k + n / 2) / n) as u8);
    if srgb {
        for c in 0..3 {
            t[c] = srgb_code(light[c] / n as f32);
        }
    }
    t
}

/// A linear value as the f32 texel a level stores (sRGB-encoded colour when `srgb`).
fn encode_f32(v: Vec4, srgb: bool) -> [f32; 4] {
    if srgb {
        [to_srgb(v.x), to_srgb(v.y), to_srgb(v.z), v.w]
    } else {
        v.to_array()
    }
}

/// An 8-bit texel as linear values: colour channels through the sRGB table when `srgb`,
/// alpha (and data) as `code / 255`.
#[inline]
pub(crate) fn decode8(p: [u8; 4], srgb: bool) -> Vec4 {
    DECODE8.decode(p, srgb)
}

/// Every 8-bit code's value, linear (`c / 255`) and sRGB-decoded: a decode is four loads,
/// no division. A filtered lookup of a material's four textures decodes 128 codes, so
/// callers in a loop take the tables once ([`decode_tables`]) rather than through the
/// lazy static each time.
pub(crate) struct Decode8 {
    /// `c / 255`.
    linear: [f32; 256],
    /// `to_linear(c / 255)`: the same values a lookup would compute.
    srgb: [f32; 256],
}

static DECODE8: std::sync::LazyLock<Decode8> = std::sync::LazyLock::new(|| Decode8 {
    linear: std::array::from_fn(|i| unit8(i as u8)),
    srgb: std::array::from_fn(|i| to_linear(unit8(i as u8))),
});

/// The decode tables, initialised.
#[inline]
pub(crate) fn decode_tables() -> &'static Decode8 {
    &DECODE8
}

impl Decode8 {
    /// An 8-bit RGBA texel as linear values: colour channels through the sRGB curve when
    /// `srgb`, alpha (and data) as `c / 255`, as the `image` crate converts them.
    #[inline(always)]
    pub(crate) fn decode(&self, p: [u8; 4], srgb: bool) -> Vec4 {
        let rgb = if srgb { &self.srgb } else { &self.linear };
        Vec4::new(
            rgb[p[0] as usize],
            rgb[p[1] as usize],
            rgb[p[2] as usize],
            self.linear[p[3] as usize],
        )
    }
}

/// linear → sRGB (IEC 61966-2-1), the inverse of [`to_linear`].
fn to_srgb(c: f32) -> f32 {
    if c <= 0.003_130_8 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
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
#[inline]
fn wrap_index(i: i64, n: i64, wrap: Wrap) -> i64 {
    // Nearly every tap lies inside: no division for it.
    if (0..n).contains(&i) {
        return i;
    }
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

/// A texture ready to sample: its image's MIP pyramid and its sampler.
type Bound = (Arc<Pyramid>, Filtering);

/// The textures of a scene, decoded, each with the pyramid of its use: colour textures
/// (sampled as sRGB) are filtered down in linear light, data textures as stored, so one
/// texture used both ways (rare) has a pyramid of each.
#[derive(Clone, Debug, Default)]
pub struct TextureSet {
    /// Per scene texture, per use (`[data, colour]`): its pyramid (`None`: no material
    /// uses it so) and sampler.
    textures: Vec<[Option<Bound>; 2]>,
    /// Per material, its textures interleaved where they allow it ([`Bundle`]).
    bundles: Vec<Option<Arc<Bundle>>>,
}

/// Where a shading point's lookups read: the texture coordinates of each set and the
/// footprint of the ray cone there, as log2 of its width in each set's units (`-∞`: a
/// point, so the finest level).
#[derive(Clone, Copy, Debug)]
pub struct Lookup {
    /// `TEXCOORD_0` and `TEXCOORD_1`.
    pub uv: [Vec2; 2],
    /// log2 of the footprint's width in each set's units.
    pub log2_width: [f32; 2],
}

impl Lookup {
    /// The coordinates and footprint in coordinate set `tex_coord` (a set past the last is
    /// the last).
    pub fn set(&self, tex_coord: u32) -> (Vec2, f32) {
        let k = (tex_coord as usize).min(1);
        (self.uv[k], self.log2_width[k])
    }

    /// A lookup of one point (no footprint): level 0, as light sampling and alpha tests
    /// read.
    pub fn point(uv: [Vec2; 2]) -> Lookup {
        Lookup {
            uv,
            log2_width: [f32::NEG_INFINITY; 2],
        }
    }
}

/// Refuses a scene whose used images together declare more than
/// [`MAX_SCENE_TEXTURE_PIXELS`], reading only their headers: the images are decoded at
/// once, so one image's limit does not bound them all. An image whose header does not
/// read is left to the decoder, which names it.
fn check_declared_size(scene: &Scene, uses: &[[bool; 2]]) -> Result<(), TextureError> {
    let mut pixels = 0u64;
    let mut largest = (0u64, 0usize, 0u32, 0u32);
    for (image, u) in uses.iter().enumerate() {
        let n = u64::from(u[0]) + u64::from(u[1]);
        if n == 0 {
            continue;
        }
        let dims = image::ImageReader::new(std::io::Cursor::new(&scene.images[image].bytes))
            .with_guessed_format()
            .ok()
            .and_then(|r| r.into_dimensions().ok());
        // An image over one image's limits is the decoder's to refuse, by name.
        let dims = dims.filter(|&(w, h)| {
            w <= MAX_TEXTURE_SIDE
                && h <= MAX_TEXTURE_SIDE
                && u64::from(w) * u64::from(h) <= MAX_TEXTURE_PIXELS
        });
        if let Some((w, h)) = dims {
            let p = u64::from(w) * u64::from(h);
            pixels = pixels.saturating_add(p.saturating_mul(n));
            if p > largest.0 {
                largest = (p, image, w, h);
            }
        }
    }
    if pixels > MAX_SCENE_TEXTURE_PIXELS {
        return Err(TextureError::TooLarge {
            pixels,
            limit: MAX_SCENE_TEXTURE_PIXELS,
            largest: largest.1,
            width: largest.2,
            height: largest.3,
        });
    }
    Ok(())
}

/// Runs a part of some CPU work (a service job's step on the pool, or the part at once),
/// or refuses to with `E` (the job was cancelled).
pub type Steps<'a, E> = dyn Fn(&mut (dyn FnMut() + Send)) -> Result<(), E> + 'a;

/// [`Steps`] that run each part at once, on the caller's thread: work done outside any
/// job.
pub fn at_once<E>(part: &mut (dyn FnMut() + Send)) -> Result<(), E> {
    part();
    Ok(())
}

/// Image `image` of `scene` decoded, with its pyramid for each of `uses` (`[data,
/// colour]`).
fn pyramids_of(
    scene: &Scene,
    image: usize,
    uses: [bool; 2],
) -> Result<[Option<Arc<Pyramid>>; 2], TextureError> {
    let im = &scene.images[image];
    let base = Texels::decode(&im.bytes).map_err(|reason| TextureError::Decode {
        image,
        mime: im.mime_type.clone(),
        reason,
    })?;
    Ok(match uses {
        [true, true] => [
            Some(Arc::new(Pyramid::new(base.clone(), false))),
            Some(Arc::new(Pyramid::new(base, true))),
        ],
        [data, _] => {
            let p = Some(Arc::new(Pyramid::new(base, !data)));
            if data {
                [p, None]
            } else {
                [None, p]
            }
        }
    })
}

impl TextureSet {
    /// Decodes every image that a material of `scene` samples through a texture this
    /// renderer uses (base colour, metallic-roughness, normal, emissive, and
    /// `KHR_materials_specular`'s two), each image once,
    /// and builds its pyramid for each use.
    pub fn of(scene: &Scene) -> Result<TextureSet, TextureError> {
        match TextureSet::in_steps(scene, &at_once::<std::convert::Infallible>) {
            Ok(decoded) => decoded,
            Err(never) => match never {},
        }
    }

    /// [`TextureSet::of`] in parts, each run through `step` (a service job's step on the
    /// pool, which a waiting request may go before): as many images at once as the pool
    /// has threads, then the bundles. Decoding DamagedHelmet's four 2048² JPEGs held the
    /// pool for up to 0.9 s as one step. The outer error is `step`'s (the job was
    /// cancelled), the inner one the scene's.
    pub fn in_steps<E>(
        scene: &Scene,
        step: &Steps<'_, E>,
    ) -> Result<Result<TextureSet, TextureError>, E> {
        let mut used = vec![[false; 2]; scene.textures.len()];
        for m in &scene.materials {
            for (r, colour) in read_apart(m, false) {
                if let Some(u) = r.and_then(|r| used.get_mut(r.texture)) {
                    u[colour as usize] = true;
                }
            }
        }
        // Each image decoded once, with a pyramid per use its textures make of it.
        let mut uses = vec![[false; 2]; scene.images.len()];
        for (t, used) in scene.textures.iter().zip(&used) {
            if let Some(u) = uses.get_mut(t.image) {
                u[0] |= used[0];
                u[1] |= used[1];
            }
        }
        if let Err(e) = check_declared_size(scene, &uses) {
            return Ok(Err(e));
        }
        // On the pool, an image per task: decoding is serial within an image, and four
        // 2048² JPEGs one after another were most of a textured frame's preparation.
        let wanted: Vec<usize> = (0..uses.len())
            .filter(|&i| uses[i][0] || uses[i][1])
            .collect();
        let mut pyramids: Vec<[Option<Arc<Pyramid>>; 2]> = vec![[None, None]; uses.len()];
        let mut next = 0;
        while next < wanted.len() {
            let mut failed = None;
            step(&mut || {
                let group = &wanted[next..(next + rayon::current_num_threads()).min(wanted.len())];
                let made: Vec<_> = group
                    .par_iter()
                    .map(|&image| pyramids_of(scene, image, uses[image]))
                    .collect();
                next += group.len();
                for (&image, made) in group.iter().zip(made) {
                    match made {
                        Ok(p) => pyramids[image] = p,
                        // The first failure in image order, whichever task met its own
                        // first.
                        Err(e) => {
                            failed = Some(e);
                            break;
                        }
                    }
                }
            })?;
            if let Some(e) = failed {
                return Ok(Err(e));
            }
        }
        let mut set = None;
        step(&mut || set = Some(TextureSet::assemble(scene, used.clone(), &pyramids)))?;
        Ok(Ok(set.expect("the step ran")))
    }

    /// The set of `scene`'s textures from its images' pyramids (`used`: each texture's
    /// uses, `[data, colour]`): every texture bound to its sampler, and the materials'
    /// bundles.
    fn assemble(
        scene: &Scene,
        used: Vec<[bool; 2]>,
        pyramids: &[[Option<Arc<Pyramid>>; 2]],
    ) -> TextureSet {
        let mut textures: Vec<[Option<Bound>; 2]> = scene
            .textures
            .iter()
            .zip(used)
            .map(|(t, used)| {
                [0, 1].map(|k| {
                    let p = pyramids.get(t.image)?[k].as_ref().filter(|_| used[k])?;
                    Some((Arc::clone(p), Filtering::of(&t.sampler)))
                })
            })
            .collect();
        // Materials that read the same textures the same way share one bundle, and a
        // texture goes into one bundle at most (a second material that mixes it with
        // others reads its textures apart instead of copying it).
        let mut made: Vec<([Option<TextureRef>; SLOTS], Arc<Bundle>)> = Vec::new();
        let bundles = scene
            .materials
            .iter()
            .map(|m| {
                let refs = slots(m);
                if let Some((_, b)) = made.iter().find(|(k, _)| *k == refs) {
                    return Some(Arc::clone(b));
                }
                let taken = |t: usize| {
                    made.iter()
                        .any(|(k, _)| k.iter().flatten().any(|r| r.texture == t))
                };
                if refs.iter().flatten().any(|r| taken(r.texture)) {
                    return None;
                }
                let b = Arc::new(bundle_of(&textures, refs)?);
                made.push((refs, Arc::clone(&b)));
                Some(b)
            })
            .collect::<Vec<_>>();
        // A pyramid that only bundled materials read lives on in their bundles alone.
        let mut needed = vec![[false; 2]; textures.len()];
        for (m, b) in scene.materials.iter().zip(&bundles) {
            for (r, colour) in read_apart(m, b.is_some()) {
                if let Some(n) = r.and_then(|r| needed.get_mut(r.texture)) {
                    n[colour as usize] = true;
                }
            }
        }
        for (t, n) in textures.iter_mut().zip(needed) {
            for k in 0..2 {
                if !n[k] {
                    t[k] = None;
                }
            }
        }
        TextureSet { textures, bundles }
    }

    /// Textures from decoded images, in texture-index order, each usable both ways (tests,
    /// generated scenes).
    pub fn from_texels(list: Vec<(Texels, Filtering)>) -> TextureSet {
        TextureSet {
            bundles: Vec::new(),
            textures: list
                .into_iter()
                .map(|(t, filtering)| {
                    [false, true]
                        .map(|srgb| Some((Arc::new(Pyramid::new(t.clone(), srgb)), filtering)))
                })
                .collect(),
        }
    }

    /// Bytes of texels held: every pyramid and bundle once, however many textures and
    /// materials share it (what a cache of decoded textures accounts for).
    pub fn bytes(&self) -> usize {
        let mut seen: Vec<*const ()> = Vec::new();
        let mut once = |p: *const ()| {
            let new = !seen.contains(&p);
            if new {
                seen.push(p);
            }
            new
        };
        let pyramids: usize = self
            .textures
            .iter()
            .flatten()
            .flatten()
            .filter(|(p, _)| once(Arc::as_ptr(p).cast()))
            .map(|(p, _)| p.bytes())
            .sum();
        let bundles: usize = self
            .bundles
            .iter()
            .flatten()
            .filter(|b| once(Arc::as_ptr(b).cast()))
            .map(|b| b.bytes())
            .sum();
        pyramids + bundles
    }

    /// Material `material`'s textures interleaved, when they could be.
    pub fn bundle(&self, material: usize) -> Option<&Bundle> {
        self.bundles.get(material)?.as_deref()
    }

    /// The value of texture reference `r` for lookup `at`; `None` when the texture was not
    /// decoded for this use.
    pub fn sample(&self, r: &TextureRef, at: &Lookup, srgb: bool) -> Option<Vec4> {
        let (pyramid, filtering) = self.textures.get(r.texture)?[srgb as usize].as_ref()?;
        let (mut st, mut log2_width) = at.set(r.tex_coord);
        if let Some(t) = &r.transform {
            st = t.apply(st);
            // The transform's scale stretches the footprint with the coordinates.
            log2_width += 0.5 * (t.scale[0] * t.scale[1]).abs().log2();
        }
        Some(pyramid.sample(st, log2_width, filtering, srgb))
    }
}

/// The texture slots of a material this renderer reads.
pub const SLOTS: usize = 4;

/// Which slots hold colour (sRGB) textures: base colour and emissive.
pub const SLOT_IS_COLOUR: [bool; SLOTS] = [true, false, false, true];

/// Material `m`'s texture references in slot order: base colour, metallic-roughness,
/// normal, emissive.
pub fn slots(m: &crate::scene::Material) -> [Option<TextureRef>; SLOTS] {
    [
        m.base_color_texture,
        m.metallic_roughness_texture,
        m.normal_texture,
        m.emissive_texture,
    ]
}

/// Material `m`'s `KHR_materials_specular` textures, each with whether it holds colour:
/// `specularTexture` (data: its alpha channel scales `specularFactor`) and
/// `specularColorTexture` (sRGB colour scaling `specularColorFactor`). Rare enough (no
/// scene of the test set has them) that they are read apart, never bundled.
pub fn specular_slots(m: &crate::scene::Material) -> [(Option<TextureRef>, bool); 2] {
    [
        (m.specular.texture, false),
        (m.specular.color_texture, true),
    ]
}

/// The texture references material `m` reads from pyramids of their own, each with
/// whether it holds colour: its four slots unless it is `bundled`, and its specular
/// textures always (they are never bundled).
fn read_apart(
    m: &crate::scene::Material,
    bundled: bool,
) -> impl Iterator<Item = (Option<TextureRef>, bool)> {
    let four = if bundled { [None; SLOTS] } else { slots(m) };
    four.into_iter()
        .zip(SLOT_IS_COLOUR)
        .chain(specular_slots(m))
}

/// The bundle of texture references `refs` (slot order) from `textures`: only where every
/// one reads the same coordinate set, untransformed, through the same sampler, from
/// pyramids of the same sizes ([`Bundle::of`] checks those).
fn bundle_of(textures: &[[Option<Bound>; 2]], refs: [Option<TextureRef>; SLOTS]) -> Option<Bundle> {
    let mut slots: [Option<&Pyramid>; SLOTS] = [None; SLOTS];
    let mut shared: Option<(u32, Filtering)> = None;
    for (s, r) in refs.iter().enumerate() {
        let Some(r) = r else { continue };
        if r.transform.is_some() {
            return None;
        }
        let (p, f) = textures.get(r.texture)?[SLOT_IS_COLOUR[s] as usize].as_ref()?;
        match shared {
            None => shared = Some((r.tex_coord, *f)),
            Some(k) if k == (r.tex_coord, *f) => {}
            Some(_) => return None,
        }
        slots[s] = Some(p);
    }
    let (tex_coord, filtering) = shared?;
    Bundle::of(slots, filtering, tex_coord)
}

/// A scene's textures, decoded (or found) by the first frame that needs them and shared by
/// the rest of a sequence: poses and geometry versions move positions, never texels, and
/// decoding four 2048² images takes longer than rendering a small frame of them.
#[derive(Debug, Default)]
pub struct DecodedOnce(std::sync::OnceLock<Arc<TextureSet>>);

impl DecodedOnce {
    /// The textures of `scene` (decoded now if no frame has yet).
    pub fn get(&self, scene: &Scene) -> Result<&TextureSet, TextureError> {
        Ok(self.get_or(|| TextureSet::of(scene).map(Arc::new))?)
    }

    /// [`DecodedOnce::get`] in `step`'s steps ([`TextureSet::in_steps`]).
    pub fn get_in_steps<E>(
        &self,
        scene: &Scene,
        step: &Steps<'_, E>,
    ) -> Result<Result<&TextureSet, TextureError>, E> {
        if let Some(t) = self.0.get() {
            return Ok(Ok(t));
        }
        Ok(match TextureSet::in_steps(scene, step)? {
            Ok(t) => Ok(self.0.get_or_init(|| Arc::new(t))),
            Err(e) => Err(e),
        })
    }

    /// The textures an earlier frame got, or what `find` gives now (the service's cache of
    /// decoded textures, which decodes them on a miss), kept for the later frames whatever
    /// that cache evicts meanwhile.
    pub fn get_or<E>(
        &self,
        find: impl FnOnce() -> Result<Arc<TextureSet>, E>,
    ) -> Result<&Arc<TextureSet>, E> {
        if let Some(t) = self.0.get() {
            return Ok(t);
        }
        let found = find()?;
        Ok(self.0.get_or_init(|| found))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_texture_set_counts_each_pyramid_once() {
        // f32 texels (16 bytes): levels of 2 × 2 and 1 × 1, a pyramid per use.
        let one = 16 * (4 + 1);
        let f = Filtering::of(&crate::scene::Sampler::default());
        let set = TextureSet::from_texels(vec![(checker(), f)]);
        assert_eq!(set.bytes(), 2 * one);
        // A copy shares its pyramids: what a job's surfaces clone from the cache's entry.
        let mut doubled = set.clone();
        doubled.textures.extend(set.textures.iter().cloned());
        assert_eq!(doubled.bytes(), 2 * one);
        assert_eq!(TextureSet::default().bytes(), 0);
    }

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

    /// A 4 × 4 PNG of assorted codes.
    fn png(seed: u8) -> Vec<u8> {
        let mut png = Vec::new();
        {
            let mut e = ::png::Encoder::new(&mut png, 4, 4);
            e.set_color(::png::ColorType::Rgba);
            let mut w = e.write_header().unwrap();
            let data: Vec<u8> = (0..64u8)
                .map(|i| i.wrapping_mul(37).wrapping_add(seed))
                .collect();
            w.write_image_data(&data).unwrap();
        }
        png
    }

    /// A scene of `n` textures, texture `i` the PNG `png(i * 50)` with the default
    /// sampler, and `materials`.
    fn textured_scene(n: u8, materials: Vec<crate::scene::Material>) -> Scene {
        use crate::scene::{Image, Texture};
        Scene {
            images: (0..n)
                .map(|i| Image {
                    mime_type: "image/png".into(),
                    bytes: png(i * 50).into(),
                })
                .collect(),
            textures: (0..n as usize)
                .map(|image| Texture {
                    image,
                    sampler: Default::default(),
                })
                .collect(),
            materials,
            ..Scene::default()
        }
    }

    /// A black `side` × `side` grey PNG: tens of KB that decode to `side`² bytes and
    /// more, as a decompression bomb's do.
    fn declared_png(side: u32) -> Vec<u8> {
        let mut png = Vec::new();
        {
            let mut e = ::png::Encoder::new(&mut png, side, side);
            e.set_color(::png::ColorType::Grayscale);
            e.set_compression(::png::Compression::Fast);
            let mut w = e.write_header().unwrap();
            w.write_image_data(&vec![0u8; (side * side) as usize])
                .unwrap();
        }
        png
    }

    /// A scene of `images`, each the base colour texture of a material of its own.
    fn scene_of(images: Vec<crate::scene::Image>) -> Scene {
        use crate::scene::{Material, Texture};
        Scene {
            textures: (0..images.len())
                .map(|image| Texture {
                    image,
                    sampler: Default::default(),
                })
                .collect(),
            materials: (0..images.len())
                .map(|t| Material {
                    base_color_texture: Some(TextureRef {
                        texture: t,
                        tex_coord: 0,
                        transform: None,
                    }),
                    ..Material::default()
                })
                .collect(),
            images,
            ..Scene::default()
        }
    }

    /// A scene of `images` 4 × 4 PNG base colour textures, one material each, image
    /// `bad` (if any) not an image at all.
    fn scene_of_images(images: usize, bad: Option<usize>) -> Scene {
        use crate::scene::Image;
        let png = |k: usize| {
            let mut png = Vec::new();
            {
                let mut e = ::png::Encoder::new(&mut png, 4, 4);
                e.set_color(::png::ColorType::Rgba);
                let mut w = e.write_header().unwrap();
                let data: Vec<u8> = (0..64).map(|i| (i * 7 + k * 31) as u8).collect();
                w.write_image_data(&data).unwrap();
            }
            png
        };
        scene_of(
            (0..images)
                .map(|k| Image {
                    mime_type: "image/png".into(),
                    bytes: if Some(k) == bad {
                        b"not a png".to_vec().into()
                    } else {
                        png(k).into()
                    },
                })
                .collect(),
        )
    }

    /// Decoding in steps gives the textures of one decode, in as many steps as the pool
    /// takes images at once, plus one; a refused step (a cancelled job) stops it, and a
    /// bad image ends it after its own step with the error that names it.
    #[test]
    fn textures_decode_in_steps_of_as_many_images_as_threads() {
        let scene = scene_of_images(5, None);
        let steps = std::cell::Cell::new(0);
        let counted = |part: &mut (dyn FnMut() + Send)| -> Result<(), &str> {
            steps.set(steps.get() + 1);
            part();
            Ok(())
        };
        let stepped = TextureSet::in_steps(&scene, &counted).unwrap().unwrap();
        let whole = TextureSet::of(&scene).unwrap();
        assert_eq!(
            steps.get(),
            5usize.div_ceil(rayon::current_num_threads()) + 1
        );
        assert_eq!(stepped.bytes(), whole.bytes());
        for t in 0..5 {
            let r = TextureRef {
                texture: t,
                tex_coord: 0,
                transform: None,
            };
            for uv in [Vec2::new(0.1, 0.2), Vec2::new(0.7, 0.45)] {
                let at = Lookup::point([uv, uv]);
                assert_eq!(stepped.sample(&r, &at, true), whole.sample(&r, &at, true));
                assert!(stepped.sample(&r, &at, true).is_some());
            }
        }
        // Cancelled before its second step.
        steps.set(0);
        let refusing = |part: &mut (dyn FnMut() + Send)| -> Result<(), &str> {
            steps.set(steps.get() + 1);
            if steps.get() > 1 {
                return Err("cancelled");
            }
            part();
            Ok(())
        };
        assert_eq!(
            TextureSet::in_steps(&scene, &refusing).map(|_| ()),
            Err("cancelled")
        );
        // Image 0 does not decode: the first step says so and nothing more runs.
        steps.set(0);
        match TextureSet::in_steps(&scene_of_images(5, Some(0)), &counted) {
            Ok(Err(TextureError::Decode { image: 0, .. })) => {}
            other => panic!("{:?}", other.map(|r| r.map(|_| ()))),
        }
        assert_eq!(steps.get(), 1);
    }

    #[test]
    fn textures_that_together_declare_too_many_texels_are_refused_before_decoding() {
        use crate::scene::Image;
        let side = 8192u32;
        let n = (MAX_SCENE_TEXTURE_PIXELS / (u64::from(side) * u64::from(side))) as usize;
        let bytes: std::sync::Arc<[u8]> = declared_png(side).into();
        let scene = |images: usize| {
            scene_of(
                (0..images)
                    .map(|_| Image {
                        mime_type: "image/png".into(),
                        bytes: bytes.clone(),
                    })
                    .collect(),
            )
        };
        match TextureSet::of(&scene(n + 1)) {
            Err(e @ TextureError::TooLarge { .. }) => {
                let text = e.to_string();
                assert!(
                    text.contains("8192 × 8192") && text.contains("268435456"),
                    "{text}"
                );
            }
            other => panic!("{:?}", other.map(|_| ())),
        }
        // One image fewer is within the limit (not decoded here: 1 GiB of texels).
        assert!(check_declared_size(&scene(n), &vec![[false, true]; n]).is_ok());
    }

    #[test]
    fn materials_share_a_bundle_only_when_they_read_alike() {
        use crate::scene::{Material, TextureTransform};
        let r = |texture, tex_coord, transform| {
            Some(TextureRef {
                texture,
                tex_coord,
                transform,
            })
        };
        let material = |tex_coord, transform: Option<TextureTransform>| Material {
            base_color_texture: r(0, tex_coord, transform),
            metallic_roughness_texture: r(1, tex_coord, transform),
            normal_texture: r(2, tex_coord, transform),
            ..Material::default()
        };
        let tiled = TextureTransform {
            offset: [0.0; 2],
            rotation: 0.0,
            scale: [4.0, 4.0],
        };
        let scene = textured_scene(
            3,
            vec![
                material(0, None),
                material(1, None),
                material(0, Some(tiled)),
            ],
        );
        let set = TextureSet::of(&scene).unwrap();
        assert!(set.bundle(0).is_some());
        // The same textures through another coordinate set, or transformed: read apart,
        // from pyramids that stay.
        assert!(set.bundle(1).is_none() && set.bundle(2).is_none());
        let at = Lookup {
            uv: [Vec2::new(0.3, 0.6), Vec2::new(0.8, 0.1)],
            log2_width: [-4.0, -1.5],
        };
        for (k, srgb) in [(0, true), (1, false), (2, false)] {
            let direct = set.sample(&r(k, 0, None).unwrap(), &at, srgb).unwrap();
            let via = set.bundle(0).unwrap().sample(at.uv[0], at.log2_width[0])[k].unwrap();
            assert_eq!(direct, via);
            assert!(set.sample(&r(k, 1, None).unwrap(), &at, srgb).is_some());
        }
    }

    /// A bundled material's `KHR_materials_specular` textures are read apart: the
    /// pyramids they need stay even where the bundle holds the same image (here its
    /// metallic-roughness texture as the specular strength), decoded for their own use
    /// (the colour texture as sRGB).
    #[test]
    fn specular_textures_are_decoded_beside_bundles() {
        use crate::scene::{Material, Specular};
        let r = |texture| {
            Some(TextureRef {
                texture,
                tex_coord: 0,
                transform: None,
            })
        };
        let scene = textured_scene(
            4,
            vec![Material {
                base_color_texture: r(0),
                metallic_roughness_texture: r(1),
                normal_texture: r(2),
                specular: Specular {
                    texture: r(1),
                    color_texture: r(3),
                    ..Specular::default()
                },
                ..Material::default()
            }],
        );
        let set = TextureSet::of(&scene).unwrap();
        assert!(set.bundle(0).is_some());
        let at = Lookup {
            uv: [Vec2::new(0.3, 0.6); 2],
            log2_width: [-4.0; 2],
        };
        let strength = set.sample(&r(1).unwrap(), &at, false).unwrap();
        let bundled = set.bundle(0).unwrap().sample(at.uv[0], at.log2_width[0])[1].unwrap();
        assert_eq!(strength, bundled);
        let colour = set.sample(&r(3).unwrap(), &at, true).unwrap();
        let texels = Texels::decode(&png(150)).unwrap();
        let want = Pyramid::new(texels, true).sample(
            at.uv[0],
            -4.0,
            &Filtering::of(&Default::default()),
            true,
        );
        assert_eq!(colour, want);
        // Not decoded for a use nothing makes of it.
        assert!(set.sample(&r(3).unwrap(), &at, false).is_none());
    }

    #[test]
    fn srgb_codes_survive_the_round_trip_through_light() {
        for c in 0..=255u8 {
            let v = decode_tables().srgb[c as usize];
            assert_eq!(SRGB_CODE_BOUNDS.partition_point(|&b| b <= v), c as usize);
            assert_eq!(srgb_code(v), c);
            for d in [-1e-7f32, 1e-7] {
                let near = SRGB_CODE_BOUNDS[(c as usize).min(254)] + d;
                assert_eq!(
                    srgb_code(near) as usize,
                    SRGB_CODE_BOUNDS.partition_point(|&b| b <= near)
                );
            }
            assert_eq!((to_srgb(v) * 255.0).round() as u8, c);
        }
    }

    #[test]
    fn eight_bit_levels_are_the_f32_levels_rounded() {
        // A 6 × 5 image of assorted codes, halved both ways: each 8-bit texel is the f32
        // path's mean encoded to the nearest code.
        let codes: Vec<[u8; 4]> = (0..30u32)
            .map(|i| {
                [
                    (i * 37 % 256) as u8,
                    (i * 91 % 256) as u8,
                    (i * 13) as u8,
                    200,
                ]
            })
            .collect();
        let as_f32: Vec<[f32; 4]> = codes.iter().map(|p| p.map(unit8)).collect();
        let a = Texels {
            width: 6,
            height: 5,
            texels: Store::Rgba8(codes),
        };
        let b = Texels::from_rgba(6, 5, as_f32).unwrap();
        for srgb in [false, true] {
            let (ha, hb) = (a.half(srgb).unwrap(), b.half(srgb).unwrap());
            assert_eq!((ha.width, ha.height), (3, 2));
            for y in 0..2 {
                for x in 0..3 {
                    // Compared as codes: the 8-bit level is the exact mean rounded to
                    // the nearest code, however dark.
                    let code = |v: Vec4| Vec4::from(encode_f32(v, srgb)) * 255.0;
                    let (va, vb) = (code(ha.texel(x, y, srgb)), code(hb.texel(x, y, srgb)));
                    assert!(
                        (va - vb).abs().max_element() <= 0.5 + 1e-3,
                        "{x},{y} {srgb}: {va} {vb}"
                    );
                }
            }
        }
    }

    #[test]
    fn floor_is_f32_floor_for_every_finite_value() {
        let mut values = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            0.999_999_94,
            -0.999_999_94,
            8_388_607.5,
            -8_388_607.5,
            8_388_608.0,
            -8_388_608.0,
            1e20,
            -1e20,
            f32::MAX,
            f32::MIN,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
            2047.5,
            -2048.25,
        ];
        let mut x = 0x1234_5678u32;
        for _ in 0..100_000 {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            let v = f32::from_bits(x);
            if v.is_finite() {
                values.push(v);
            }
            values.push((x % 100_000) as f32 / 37.0 - 1350.0);
        }
        for v in values {
            assert_eq!(floor(v), v.floor(), "{v:e}");
        }
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
