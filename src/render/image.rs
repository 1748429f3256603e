//! Image encoders: 8-bit sRGB PNG for people, 32-bit float OpenEXR for measurements.

use super::Image;

/// Errors of encoding an image.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    /// The PNG encoder failed.
    #[error("PNG encoding failed: {0}")]
    Png(#[from] png::EncodingError),
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
    /// Uncompressed 32-bit float RGB OpenEXR.
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

/// Linear → sRGB transfer, then 8 bits.
fn srgb8(x: f32) -> u8 {
    let x = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) };
    let s = if x <= 0.003_130_8 {
        12.92 * x
    } else {
        1.055 * x.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0 + 0.5) as u8
}

/// Encodes as an 8-bit sRGB PNG.
pub fn encode_png(img: &Image) -> Result<Vec<u8>, ImageError> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, img.width, img.height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
        let mut w = enc.write_header()?;
        let data: Vec<u8> = img.pixels.iter().flat_map(|p| p.map(srgb8)).collect();
        w.write_image_data(&data)?;
    }
    Ok(out)
}

fn attr(out: &mut Vec<u8>, name: &str, ty: &str, value: &[u8]) {
    out.extend_from_slice(name.as_bytes());
    out.push(0);
    out.extend_from_slice(ty.as_bytes());
    out.push(0);
    out.extend_from_slice(&(value.len() as i32).to_le_bytes());
    out.extend_from_slice(value);
}

/// Encodes as a single-part, scanline, uncompressed OpenEXR with FLOAT channels B, G, R
/// (the format's required alphabetical order), one scanline per block.
pub fn encode_exr(img: &Image) -> Result<Vec<u8>, ImageError> {
    let (w, h) = (img.width as usize, img.height as usize);
    if w == 0
        || h == 0
        || w > i32::MAX as usize
        || h > i32::MAX as usize
        || w * 12 > i32::MAX as usize
    {
        return Err(ImageError::TooLarge {
            width: img.width,
            height: img.height,
            format: "OpenEXR",
        });
    }
    let mut out = Vec::new();
    out.extend_from_slice(&20000630u32.to_le_bytes()); // magic 0x762f3101
    out.extend_from_slice(&2u32.to_le_bytes()); // version 2, single-part scanline
    let mut ch = Vec::new();
    for name in ["B", "G", "R"] {
        ch.extend_from_slice(name.as_bytes());
        ch.push(0);
        ch.extend_from_slice(&2i32.to_le_bytes()); // FLOAT
        ch.extend_from_slice(&[0, 0, 0, 0]); // pLinear + reserved
        ch.extend_from_slice(&1i32.to_le_bytes());
        ch.extend_from_slice(&1i32.to_le_bytes());
    }
    ch.push(0);
    attr(&mut out, "channels", "chlist", &ch);
    attr(&mut out, "compression", "compression", &[0]);
    let mut window = Vec::new();
    for v in [0i32, 0, w as i32 - 1, h as i32 - 1] {
        window.extend_from_slice(&v.to_le_bytes());
    }
    attr(&mut out, "dataWindow", "box2i", &window);
    attr(&mut out, "displayWindow", "box2i", &window);
    attr(&mut out, "lineOrder", "lineOrder", &[0]);
    attr(&mut out, "pixelAspectRatio", "float", &1f32.to_le_bytes());
    let mut centre = Vec::new();
    centre.extend_from_slice(&0f32.to_le_bytes());
    centre.extend_from_slice(&0f32.to_le_bytes());
    attr(&mut out, "screenWindowCenter", "v2f", &centre);
    attr(&mut out, "screenWindowWidth", "float", &1f32.to_le_bytes());
    out.push(0); // end of header
    let row_bytes = w * 12;
    let table_start = out.len();
    let first_block = table_start + 8 * h;
    for y in 0..h {
        let offset = (first_block + y * (8 + row_bytes)) as u64;
        out.extend_from_slice(&offset.to_le_bytes());
    }
    for y in 0..h {
        out.extend_from_slice(&(y as i32).to_le_bytes());
        out.extend_from_slice(&(row_bytes as i32).to_le_bytes());
        let row = &img.pixels[y * w..(y + 1) * w];
        for c in [2, 1, 0] {
            for p in row {
                out.extend_from_slice(&p[c].to_le_bytes());
            }
        }
    }
    Ok(out)
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

    fn img() -> Image {
        Image {
            width: 3,
            height: 2,
            pixels: (0..6).map(|i| [i as f32 / 5.0, 0.5, 1.0]).collect(),
        }
    }

    #[test]
    fn png_decodes_back() {
        let bytes = encode_png(&img()).unwrap();
        let dec = png::Decoder::new(std::io::Cursor::new(bytes));
        let mut r = dec.read_info().unwrap();
        let mut buf = vec![0; r.output_buffer_size()];
        let info = r.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (3, 2));
        assert_eq!(&buf[0..3], &[0, srgb8(0.5), 255]);
    }

    #[test]
    fn exr_layout_is_consistent() {
        let im = img();
        let bytes = encode_exr(&im).unwrap();
        assert_eq!(&bytes[0..4], &[0x76, 0x2f, 0x31, 0x01]);
        // The offset table points at blocks whose y and size fields are right, and the
        // last block ends the file.
        let header_end = bytes.len() - 2 * 8 - 2 * (8 + 36);
        for y in 0..2usize {
            let at = header_end + 8 * y;
            let off = u64::from_le_bytes(bytes[at..at + 8].try_into().unwrap()) as usize;
            assert_eq!(
                i32::from_le_bytes(bytes[off..off + 4].try_into().unwrap()),
                y as i32
            );
            assert_eq!(
                i32::from_le_bytes(bytes[off + 4..off + 8].try_into().unwrap()),
                36
            );
            // First value of the block is B of the row's first pixel.
            let b = f32::from_le_bytes(bytes[off + 8..off + 12].try_into().unwrap());
            assert_eq!(b, im.pixels[y * 3][2]);
            // R channel comes last.
            let r0 = f32::from_le_bytes(bytes[off + 8 + 24..off + 8 + 28].try_into().unwrap());
            assert_eq!(r0, im.pixels[y * 3][0]);
        }
    }
}
