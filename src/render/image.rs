//! Image encoders: 8-bit sRGB PNG for people, OpenEXR for measurements (radiance, coverage
//! and the AOVs a request names), both through kept libraries: `png` (the image-rs
//! project's encoder) and `exr`.
//!
//! Why `png` and not the `image` crate's `PngEncoder`, which wraps the same library: the
//! contract (`proto/rendering.md`, "Output") asks for an `sRGB` chunk, and `image` 0.25
//! cannot write one. `image` decodes the scene's textures instead.
//!
//! Both encoders are deterministic: the same buffers give the same bytes (the EXR is written
//! on one thread, scanline blocks in increasing order), so `rayd render` and the service's
//! render jobs produce identical files.

use exr::prelude::{
    AnyChannel, AnyChannels, Encoding, FlatSamples, Image as ExrImage, Layer, LayerAttributes,
    SmallVec, WritableImage,
};

use super::Image;

/// Errors of encoding an image.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// The PNG encoder failed.
    #[error("PNG encoding failed: {0}")]
    Png(#[from] png::EncodingError),
    /// The OpenEXR encoder failed.
    #[error("OpenEXR encoding failed: {0}")]
    Exr(#[from] exr::error::Error),
    /// The image is larger than the format can describe.
    #[error("image of {width}x{height} is too large for {format}")]
    TooLarge {
        /// Width.
        width: u32,
        /// Height.
        height: u32,
        /// Which format.
        format: &'static str,
    },
    /// A buffer does not hold one value per pixel (a bug of the caller, reported, not a
    /// panic).
    #[error("{what} has {len} values for {pixels} pixels")]
    BadBuffer {
        /// Which buffer.
        what: &'static str,
        /// Its length.
        len: usize,
        /// Pixels of the image.
        pixels: usize,
    },
}

/// Which file format to write.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum ImageFormat {
    /// 8-bit sRGB PNG.
    #[default]
    Png,
    /// Single-part scanline OpenEXR: FLOAT radiance and coverage, plus AOV channels.
    Exr,
}

impl ImageFormat {
    /// The format a file name asks for (by extension: its name), if any.
    pub fn from_path(path: &std::path::Path) -> Option<ImageFormat> {
        let ext = path.extension()?.to_str()?.to_ascii_lowercase();
        crate::names::Spelled::parse_name(&ext).ok()
    }

    /// The MIME type of the encoded image.
    pub fn mime(self) -> &'static str {
        match self {
            ImageFormat::Png => "image/png",
            ImageFormat::Exr => "image/x-exr",
        }
    }
}

crate::spelled!(ImageFormat, [ImageFormat::Png, ImageFormat::Exr]);

/// Linear → sRGB transfer (IEC 61966-2-1's piecewise curve), clamped to [0, 1] with NaN
/// as 0, then 8 bits rounded to nearest.
pub fn srgb8(x: f32) -> u8 {
    let x = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) };
    let s = if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0 + 0.5) as u8
}

fn check(img: &Image) -> Result<usize, ImageError> {
    let n = img.width as usize * img.height as usize;
    let lens = [
        ("pixels", img.pixels.len()),
        ("alpha", img.alpha.len()),
        ("depth", img.aovs.depth.as_ref().map_or(n, Vec::len)),
        ("normal", img.aovs.normal.as_ref().map_or(n, Vec::len)),
        ("albedo", img.aovs.albedo.as_ref().map_or(n, Vec::len)),
        ("prim", img.aovs.prim.as_ref().map_or(n, Vec::len)),
    ];
    for (what, len) in lens {
        if len != n {
            return Err(ImageError::BadBuffer {
                what,
                len,
                pixels: n,
            });
        }
    }
    Ok(n)
}

/// Encodes the radiance as an 8-bit sRGB PNG (RGB, with an `sRGB` chunk). Coverage and
/// AOVs are not written: PNG is for looking at.
pub fn encode_png(img: &Image) -> Result<Vec<u8>, ImageError> {
    check(img)?;
    if img.width == 0 || img.height == 0 {
        return Err(ImageError::TooLarge {
            width: img.width,
            height: img.height,
            format: "PNG",
        });
    }
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, img.width, img.height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
        let mut w = enc.write_header()?;
        let data: Vec<u8> = img.pixels.iter().flat_map(|p| p.map(srgb8)).collect();
        w.write_image_data(&data)?;
        w.finish()?;
    }
    Ok(out)
}

/// Encodes as a single-part scanline OpenEXR (ZIP, 16 lines per block), FLOAT channels
/// `R`, `G`, `B` (linear radiance) and `A` (coverage, see [`Image::alpha`]), plus each AOV
/// the image holds: `depth.Z`, `normal.X/Y/Z`, `albedo.R/G/B` (FLOAT) and `prim.id`
/// (UINT). The library stores them in the format's alphabetical order.
pub fn encode_exr(img: &Image) -> Result<Vec<u8>, ImageError> {
    check(img)?;
    let (w, h) = (img.width as usize, img.height as usize);
    // OpenEXR's data window is a box of i32 corners.
    if w == 0 || h == 0 || w > i32::MAX as usize || h > i32::MAX as usize {
        return Err(ImageError::TooLarge {
            width: img.width,
            height: img.height,
            format: "OpenEXR",
        });
    }
    let f32s = |name: &str, v: Vec<f32>| AnyChannel::new(name, FlatSamples::F32(v));
    let component = |v: &[[f32; 3]], c: usize| v.iter().map(|p| p[c]).collect::<Vec<f32>>();
    let mut channels: SmallVec<[AnyChannel<FlatSamples>; 4]> = SmallVec::new();
    for (c, name) in ["R", "G", "B"].into_iter().enumerate() {
        channels.push(f32s(name, component(&img.pixels, c)));
    }
    channels.push(f32s("A", img.alpha.clone()));
    let a = &img.aovs;
    if let Some(d) = &a.depth {
        channels.push(f32s("depth.Z", d.clone()));
    }
    if let Some(n) = &a.normal {
        for (c, name) in ["normal.X", "normal.Y", "normal.Z"].into_iter().enumerate() {
            channels.push(f32s(name, component(n, c)));
        }
    }
    if let Some(al) = &a.albedo {
        for (c, name) in ["albedo.R", "albedo.G", "albedo.B"].into_iter().enumerate() {
            channels.push(f32s(name, component(al, c)));
        }
    }
    if let Some(p) = &a.prim {
        channels.push(AnyChannel::new("prim.id", FlatSamples::U32(p.clone())));
    }
    let layer = Layer::new(
        (w, h),
        LayerAttributes::default(),
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(channels),
    );
    let mut out = std::io::Cursor::new(Vec::new());
    ExrImage::from_layer(layer)
        .write()
        .non_parallel()
        .to_buffered(&mut out)?;
    Ok(out.into_inner())
}

/// Encodes in the given format.
pub fn encode(img: &Image, format: ImageFormat) -> Result<Vec<u8>, ImageError> {
    match format {
        ImageFormat::Png => encode_png(img),
        ImageFormat::Exr => encode_exr(img),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::Aovs;

    fn img() -> Image {
        let n = 6;
        Image {
            width: 3,
            height: 2,
            pixels: (0..n).map(|i| [i as f32 / 5.0, 0.5, 1.0]).collect(),
            alpha: (0..n).map(|i| (i % 2) as f32).collect(),
            aovs: Aovs {
                depth: Some((0..n).map(|i| i as f32 + 0.25).collect()),
                normal: Some((0..n).map(|i| [0.0, 1.0, -(i as f32)]).collect()),
                albedo: None,
                prim: Some((0..n as u32).map(|i| i * 7).collect()),
            },
        }
    }

    #[test]
    fn png_decodes_back_with_an_srgb_chunk() {
        let bytes = encode_png(&img()).unwrap();
        let dec = png::Decoder::new(std::io::Cursor::new(bytes));
        let mut r = dec.read_info().unwrap();
        assert!(r.info().srgb.is_some(), "no sRGB chunk");
        let mut buf = vec![0; r.output_buffer_size().unwrap()];
        let info = r.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (3, 2));
        assert_eq!(&buf[0..3], &[0, srgb8(0.5), 255]);
    }

    #[test]
    fn srgb_curve_clamps_and_maps_nan_to_black() {
        assert_eq!(srgb8(f32::NAN), 0);
        assert_eq!(srgb8(-1.0), 0);
        assert_eq!(srgb8(7.0), 255);
        // 18 % grey is about 118 in sRGB.
        assert_eq!(srgb8(0.18), 118);
    }

    #[test]
    fn exr_reads_back_every_channel() {
        use exr::prelude::{ReadChannels, ReadLayers};
        let im = img();
        let bytes = encode_exr(&im).unwrap();
        assert_eq!(&bytes[0..4], &[0x76, 0x2f, 0x31, 0x01]);
        assert_eq!(bytes, encode_exr(&im).unwrap(), "not deterministic");
        let back = exr::prelude::read()
            .no_deep_data()
            .largest_resolution_level()
            .all_channels()
            .first_valid_layer()
            .all_attributes()
            .from_buffered(std::io::Cursor::new(bytes))
            .unwrap();
        let ch = &back.layer_data.channel_data.list;
        let names: Vec<String> = ch.iter().map(|c| c.name.to_string()).collect();
        assert_eq!(
            names,
            ["A", "B", "G", "R", "depth.Z", "normal.X", "normal.Y", "normal.Z", "prim.id"]
        );
        let get = |name: &str| {
            &ch.iter()
                .find(|c| c.name.to_string() == name)
                .unwrap()
                .sample_data
        };
        match get("R") {
            FlatSamples::F32(v) => {
                assert_eq!(v, &im.pixels.iter().map(|p| p[0]).collect::<Vec<_>>())
            }
            other => panic!("R is {other:?}"),
        }
        match get("prim.id") {
            FlatSamples::U32(v) => assert_eq!(Some(v), im.aovs.prim.as_ref()),
            other => panic!("prim.id is {other:?}"),
        }
        match get("normal.Z") {
            FlatSamples::F32(v) => assert_eq!(v[5], -5.0),
            other => panic!("normal.Z is {other:?}"),
        }
    }

    #[test]
    fn mismatched_buffers_are_errors_not_panics() {
        let mut im = img();
        im.alpha.pop();
        assert!(matches!(
            encode_exr(&im),
            Err(ImageError::BadBuffer { what: "alpha", .. })
        ));
        assert!(matches!(
            encode_png(&im),
            Err(ImageError::BadBuffer { what: "alpha", .. })
        ));
    }
}
