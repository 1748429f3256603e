//! The outer layers of a glTF file: the GLB container, the JSON document, the refused
//! extensions, and the buffers' bytes (GLB BIN chunk, base64 data URIs, side-by-side files).

use std::borrow::Cow;
use std::path::Path;

use gltf::json;

use super::GltfError;

/// `glTF` as a little-endian u32: the GLB magic.
const GLB_MAGIC: &[u8; 4] = b"glTF";
/// Chunk type of the JSON chunk (`JSON`).
const CHUNK_JSON: u32 = 0x4E4F_534A;
/// Chunk type of the binary chunk (`BIN\0`).
const CHUNK_BIN: u32 = 0x004E_4942;

/// Required extensions that change how geometry is stored and that rayd does not decode.
/// Any other required extension (materials, textures, lights…) only affects appearance and
/// is accepted.
pub const REFUSED_EXTENSIONS: &[&str] = &[
    "KHR_draco_mesh_compression",
    "EXT_meshopt_compression",
    "EXT_mesh_gpu_instancing",
];

/// A file split into its JSON text and, for GLB, its BIN chunk.
pub(super) struct Container<'a> {
    pub json: &'a [u8],
    pub bin: Option<&'a [u8]>,
    pub is_glb: bool,
}

fn u32_at(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([bytes[at], bytes[at + 1], bytes[at + 2], bytes[at + 3]])
}

/// Splits a GLB into chunks, or takes the whole input as JSON text.
///
/// Every length is checked against the bytes actually present before it is used.
pub(super) fn split(bytes: &[u8]) -> Result<Container<'_>, GltfError> {
    if !bytes.starts_with(GLB_MAGIC) {
        // A UTF-8 byte-order mark is not allowed by the spec but is harmless; skip it rather
        // than fail on line 1 column 1.
        let json = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
        return Ok(Container {
            json,
            bin: None,
            is_glb: false,
        });
    }
    if bytes.len() < 12 {
        return Err(GltfError::GlbHeader(format!(
            "the file is {} bytes, shorter than the 12-byte GLB header",
            bytes.len()
        )));
    }
    let version = u32_at(bytes, 4);
    if version != 2 {
        return Err(GltfError::GlbHeader(format!(
            "version is {version}, only GLB version 2 is supported"
        )));
    }
    let declared = u32_at(bytes, 8) as usize;
    if declared != bytes.len() {
        return Err(GltfError::GlbLength {
            declared,
            actual: bytes.len(),
        });
    }
    let mut json = None;
    let mut bin = None;
    let mut offset = 12;
    let mut index = 0;
    while offset < bytes.len() {
        if bytes.len() - offset < 8 {
            return Err(GltfError::GlbChunk {
                index,
                offset,
                reason: format!(
                    "only {} bytes remain, too few for an 8-byte chunk header",
                    bytes.len() - offset
                ),
            });
        }
        let length = u32_at(bytes, offset) as usize;
        let kind = u32_at(bytes, offset + 4);
        let start = offset + 8;
        let remaining = bytes.len() - start;
        if length > remaining {
            return Err(GltfError::GlbChunk {
                index,
                offset,
                reason: format!("declares {length} bytes of data but only {remaining} remain"),
            });
        }
        let data = &bytes[start..start + length];
        match (index, kind) {
            // Some exporters pad the JSON chunk with NULs instead of the spaces the spec
            // asks for; the JSON parser would call them trailing garbage.
            (0, CHUNK_JSON) => {
                let end = data.iter().rposition(|&b| b != 0).map_or(0, |i| i + 1);
                json = Some(&data[..end]);
            }
            (0, _) => {
                return Err(GltfError::GlbChunk {
                    index,
                    offset,
                    reason: format!("the first chunk must be JSON, found type 0x{kind:08X}"),
                })
            }
            (_, CHUNK_JSON) => {
                return Err(GltfError::GlbChunk {
                    index,
                    offset,
                    reason: "a second JSON chunk".to_string(),
                })
            }
            // Only the first BIN chunk is addressable (by buffer 0); the spec says readers
            // ignore chunks of unknown types.
            (_, CHUNK_BIN) if bin.is_none() => bin = Some(data),
            _ => {}
        }
        offset = start + length;
        index += 1;
    }
    let Some(json) = json else {
        return Err(GltfError::GlbHeader(
            "the file has no chunks (a JSON chunk is required)".to_string(),
        ));
    };
    Ok(Container {
        json,
        bin,
        is_glb: true,
    })
}

fn json_error(e: serde_json::Error, is_glb: bool) -> GltfError {
    GltfError::Json {
        line: e.line(),
        column: e.column(),
        detail: if is_glb {
            format!("{e} (in the GLB JSON chunk)")
        } else {
            e.to_string()
        },
    }
}

/// Just the part of the document read before anything else. (Renamed so that a parse
/// error reads "expected struct glTF".)
#[derive(serde::Deserialize)]
#[serde(rename = "glTF")]
struct RequiredOnly {
    #[serde(rename = "extensionsRequired", default)]
    required: Vec<String>,
}

/// Parses the JSON document, refusing the unsupported required extensions first so that a
/// Draco file fails naming Draco, whatever else is odd about it.
pub(super) fn parse(container: &Container<'_>) -> Result<json::Root, GltfError> {
    let required: RequiredOnly =
        serde_json::from_slice(container.json).map_err(|e| json_error(e, container.is_glb))?;
    if let Some(ext) = required
        .required
        .iter()
        .find(|e| REFUSED_EXTENSIONS.contains(&e.as_str()))
    {
        return Err(GltfError::UnsupportedExtension(ext.clone()));
    }
    json::Root::from_slice(container.json).or_else(|e| {
        optional_fields_filled(container.json)
            .map(|v| serde_json::from_value(v).map_err(|e| json_error(e, container.is_glb)))
            .unwrap_or_else(|| Err(json_error(e, container.is_glb)))
    })
}

/// The document with the optional fields that the `gltf` crate's reader requires filled
/// in, if any was missing, or `None`: it was not that. glTF 2.0 makes both optional:
/// - a scene's `nodes`: given `[]`;
/// - an animation channel's `target.node` (`KHR_animation_pointer` channels have none,
///   and glTF says a channel without one is ignored unless an extension defines it): given
///   node 0 and the path `""`, which no loader knows, so that the channel is ignored as
///   every channel of an unknown path is, keeping the other channels' numbers.
fn optional_fields_filled(json: &[u8]) -> Option<serde_json::Value> {
    use serde_json::Value;
    let mut doc: Value = serde_json::from_slice(json).ok()?;
    let mut given = false;
    if let Some(scenes) = doc.get_mut("scenes").and_then(Value::as_array_mut) {
        for scene in scenes.iter_mut().filter_map(Value::as_object_mut) {
            if !scene.contains_key("nodes") {
                scene.insert("nodes".into(), Value::Array(Vec::new()));
                given = true;
            }
        }
    }
    if let Some(animations) = doc.get_mut("animations").and_then(Value::as_array_mut) {
        for animation in animations.iter_mut() {
            let Some(channels) = animation.get_mut("channels").and_then(Value::as_array_mut) else {
                continue;
            };
            for channel in channels.iter_mut() {
                let Some(target) = channel.get_mut("target").and_then(Value::as_object_mut) else {
                    continue;
                };
                if !target.contains_key("node") {
                    target.insert("node".into(), Value::from(0));
                    target.insert("path".into(), Value::from(""));
                    given = true;
                }
            }
        }
    }
    given.then_some(doc)
}

/// Every buffer's bytes, exactly its declared `byteLength`.
///
/// A `data:` URI must decode to exactly `byteLength` bytes; its decoded size is known from
/// the payload's length, so one that cannot match is refused before anything is decoded (a
/// file declaring 36 bytes must not make the loader decode gigabytes). A GLB `BIN` chunk may
/// exceed `byteLength` only by its padding of at most 3 bytes.
pub(super) fn resolve_buffers<'a>(
    root: &json::Root,
    bin: Option<&'a [u8]>,
    base_dir: Option<&Path>,
) -> Result<Vec<Cow<'a, [u8]>>, GltfError> {
    let mut out = Vec::with_capacity(root.buffers.len());
    for (i, buffer) in root.buffers.iter().enumerate() {
        let declared = buffer.byte_length.0;
        let data: Cow<'a, [u8]> = match &buffer.uri {
            // GLB: the first buffer without a uri is the BIN chunk.
            None if i == 0 && bin.is_some() => Cow::Borrowed(bin.unwrap_or_default()),
            None => return Err(GltfError::NoBufferData { buffer: i }),
            Some(uri) => {
                if let Some(rest) = uri.strip_prefix("data:") {
                    let decoded_len = data_uri_decoded_len(rest)
                        .map_err(|reason| GltfError::BadDataUri { buffer: i, reason })?;
                    if decoded_len != declared {
                        return Err(GltfError::DataUriLength {
                            buffer: i,
                            declared,
                            actual: decoded_len,
                        });
                    }
                    Cow::Owned(
                        decode_data_uri(rest)
                            .map_err(|reason| GltfError::BadDataUri { buffer: i, reason })?,
                    )
                } else {
                    Cow::Owned(read_external(i, uri, base_dir, declared)?)
                }
            }
        };
        if (data.len() as u64) < declared {
            return Err(GltfError::BufferTooShort {
                buffer: i,
                declared,
                actual: data.len() as u64,
            });
        }
        if let Cow::Borrowed(b) = &data {
            if b.len() as u64 - declared > 3 {
                return Err(GltfError::BinChunkTooLong {
                    declared,
                    actual: b.len() as u64,
                });
            }
        }
        // `declared <= data.len()` so this fits in usize. The GLB BIN chunk may carry up to
        // three bytes of padding past `byteLength`; views must stay within `byteLength`.
        let data = match data {
            Cow::Borrowed(b) => Cow::Borrowed(&b[..declared as usize]),
            Cow::Owned(mut v) => {
                v.truncate(declared as usize);
                Cow::Owned(v)
            }
        };
        out.push(data);
    }
    Ok(out)
}

/// Why a relative URI could not be read.
pub(super) enum UriError {
    /// A scheme, an absolute path or a malformed escape.
    Unsupported,
    /// A path that leaves the file's directory (a `..` component, or one that decodes to an
    /// absolute path or a drive): refused before any file is opened.
    Escapes,
    /// No base directory: only embedded data is allowed.
    NotAllowed,
    /// The file could not be read.
    Io {
        /// The path tried.
        path: String,
        /// The OS error.
        detail: String,
    },
}

/// Reads a file stored beside the `.gltf`. URIs are relative references (RFC 3986); a
/// scheme or an absolute path is refused, and so is any file access when there is no base
/// directory (a scene uploaded over HTTP must not read the server's files). The decoded path
/// must stay inside the directory: `..`, a root or a drive in it (also when spelled with
/// `%2e%2e` or `%2f`) is refused without opening anything, so a file cannot make rayd read
/// `/etc/passwd` or a neighbour's data.
///
/// At most `limit` bytes are read ([`crate::formats::read_up_to`]): a buffer needs no more
/// than its `byteLength` (the rest is never used), and an image no more than
/// [`MAX_IMAGE_FILE_BYTES`]; a file that names a pipe or a device fed forever
/// (`/dev/zero`) is not read until memory runs out.
pub(super) fn read_relative(
    uri: &str,
    base_dir: Option<&Path>,
    limit: u64,
) -> Result<Vec<u8>, UriError> {
    let has_scheme = uri
        .split_once(':')
        .is_some_and(|(scheme, _)| !scheme.is_empty() && !scheme.contains('/'));
    if has_scheme || uri.starts_with('/') || uri.starts_with('\\') {
        return Err(UriError::Unsupported);
    }
    let Some(base) = base_dir else {
        return Err(UriError::NotAllowed);
    };
    // Query and fragment parts are not part of the file name.
    let path_part = uri.split(['?', '#']).next().unwrap_or_default();
    let decoded = percent_decode(path_part).ok_or(UriError::Unsupported)?;
    if !stays_inside(&decoded) {
        return Err(UriError::Escapes);
    }
    let path = base.join(decoded);
    let io = |e: std::io::Error| UriError::Io {
        path: path.display().to_string(),
        detail: e.to_string(),
    };
    let file = std::fs::File::open(&path).map_err(io)?;
    let size = crate::formats::regular_len(&file);
    let mut bytes = Vec::new();
    crate::formats::read_up_to(file, &mut bytes, limit, size).map_err(io)?;
    Ok(bytes)
}

/// The most an image file beside a `.gltf` may hold: the service's default body limit.
pub(super) const MAX_IMAGE_FILE_BYTES: u64 = 1 << 30;

/// Whether the relative path `p` names something inside its base directory: only plain
/// names and `.`, no `..`, root, drive or NUL, with `\\` counted as a separator too (a
/// file written on Windows).
fn stays_inside(p: &str) -> bool {
    if p.is_empty() || p.contains('\0') {
        return false;
    }
    p.split(['/', '\\'])
        .enumerate()
        .all(|(i, part)| part != ".." && !(i == 0 && (part.is_empty() || part.contains(':'))))
}

/// [`read_relative`] for buffer `buffer`, with the buffer errors.
fn read_external(
    buffer: usize,
    uri: &str,
    base_dir: Option<&Path>,
    declared: u64,
) -> Result<Vec<u8>, GltfError> {
    // Only the declared bytes are used (the rest is cut off below).
    read_relative(uri, base_dir, declared).map_err(|e| match e {
        UriError::Unsupported => GltfError::UnsupportedUri {
            buffer,
            uri: uri.to_string(),
        },
        UriError::Escapes => GltfError::UriEscapes {
            buffer,
            uri: uri.to_string(),
        },
        UriError::NotAllowed => GltfError::ExternalBufferNotAllowed {
            buffer,
            uri: uri.to_string(),
        },
        UriError::Io { path, detail } => GltfError::MissingBuffer {
            buffer,
            uri: uri.to_string(),
            path,
            detail,
        },
    })
}

/// `%XX` escapes to bytes, then UTF-8; `None` for a malformed escape or non-UTF-8 result.
fn percent_decode(s: &str) -> Option<String> {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        if b[i] == b'%' {
            let hex = b.get(i + 1..i + 3)?;
            let hi = (hex[0] as char).to_digit(16)?;
            let lo = (hex[1] as char).to_digit(16)?;
            out.push((hi * 16 + lo) as u8);
            i += 3;
        } else {
            out.push(b[i]);
            i += 1;
        }
    }
    String::from_utf8(out).ok()
}

/// Decodes the part of a data URI after `data:`; only base64 payloads carry binary buffers.
pub(super) fn decode_data_uri(rest: &str) -> Result<Vec<u8>, String> {
    let Some((header, payload)) = rest.split_once(',') else {
        return Err("the data URI has no ',' before its payload".to_string());
    };
    if !header.split(';').any(|p| p == "base64") {
        return Err(format!(
            "only base64 data URIs are supported (header is {header:?})"
        ));
    }
    base64_decode(payload.as_bytes())
}

/// The number of bytes the part of a data URI after `data:` decodes to, from the payload's
/// length alone (the characters are checked when it is decoded).
pub(super) fn data_uri_decoded_len(rest: &str) -> Result<u64, String> {
    let Some((header, payload)) = rest.split_once(',') else {
        return Err("the data URI has no ',' before its payload".to_string());
    };
    if !header.split(';').any(|p| p == "base64") {
        return Err(format!(
            "only base64 data URIs are supported (header is {header:?})"
        ));
    }
    let b = payload.as_bytes();
    let trimmed = match b {
        [rest @ .., b'=', b'='] => rest,
        [rest @ .., b'='] => rest,
        _ => b,
    };
    // A malformed payload is reported as such, not as a length that disagrees; checking
    // the characters allocates nothing.
    if let Some(k) = trimmed
        .iter()
        .position(|&c| !(c.is_ascii_alphanumeric() || c == b'+' || c == b'/'))
    {
        return Err(format!(
            "invalid base64 character {:?} at payload offset {k}",
            trimmed[k] as char
        ));
    }
    let n = trimmed.len() as u64;
    if n % 4 == 1 {
        return Err(format!(
            "base64 payload has an impossible length ({} characters)",
            b.len()
        ));
    }
    Ok(n / 4 * 3 + (n % 4).saturating_sub(1))
}

/// Standard base64 (RFC 4648 §4), padding optional, no whitespace.
fn base64_decode(input: &[u8]) -> Result<Vec<u8>, String> {
    fn value(c: u8) -> Option<u32> {
        Some(match c {
            b'A'..=b'Z' => c - b'A',
            b'a'..=b'z' => c - b'a' + 26,
            b'0'..=b'9' => c - b'0' + 52,
            b'+' => 62,
            b'/' => 63,
            _ => return None,
        } as u32)
    }
    let trimmed = match input {
        [rest @ .., b'=', b'='] => rest,
        [rest @ .., b'='] => rest,
        _ => input,
    };
    if trimmed.len() % 4 == 1 {
        return Err(format!(
            "base64 payload has an impossible length ({} characters)",
            input.len()
        ));
    }
    let mut out = Vec::with_capacity(trimmed.len() / 4 * 3 + 2);
    for (n, group) in trimmed.chunks(4).enumerate() {
        let mut acc = 0u32;
        for (k, &c) in group.iter().enumerate() {
            let v = value(c).ok_or_else(|| {
                format!(
                    "invalid base64 character {:?} at payload offset {}",
                    c as char,
                    n * 4 + k
                )
            })?;
            acc |= v << (18 - 6 * k);
        }
        let bytes = acc.to_be_bytes();
        out.extend_from_slice(&bytes[1..group.len()]);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_that_leave_the_directory_are_refused() {
        for inside in [
            "a.bin",
            "./a.bin",
            "sub/a.bin",
            "sub//a.bin",
            "a..b.bin",
            "..a",
        ] {
            assert!(stays_inside(inside), "{inside}");
        }
        for outside in [
            "../a.bin",
            "sub/../../a.bin",
            "..",
            "/etc/passwd",
            "\\\\server\\share",
            "..\\a.bin",
            "C:/x",
            "C:",
            "a\0b",
            "",
        ] {
            assert!(!stays_inside(outside), "{outside}");
        }
        // Percent-encoded dots and slashes are decoded before the check.
        let dir = std::env::temp_dir();
        for uri in [
            "%2e%2e/a.bin",
            "%2E%2E%2Fa.bin",
            "%2Fetc%2Fpasswd",
            "sub%2F..%2F..%2Fx",
        ] {
            assert!(
                matches!(
                    read_relative(uri, Some(&dir), 1 << 20),
                    Err(UriError::Escapes)
                ),
                "{uri}"
            );
        }
    }

    #[test]
    fn data_uri_length_is_known_before_decoding() {
        for bytes in [&b""[..], b"f", b"fo", b"foo", b"foob", b"fooba", b"foobar"] {
            for padded in [true, false] {
                let mut text = base64_encode(bytes);
                if !padded {
                    text = text.trim_end_matches('=').to_string();
                }
                let uri = format!("application/octet-stream;base64,{text}");
                assert_eq!(
                    data_uri_decoded_len(&uri).unwrap(),
                    decode_data_uri(&uri).unwrap().len() as u64,
                    "{text}"
                );
            }
        }
        assert!(data_uri_decoded_len("text/plain,abc").is_err());
        assert!(data_uri_decoded_len(";base64,A").is_err());
    }

    fn base64_encode(b: &[u8]) -> String {
        const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
        let mut out = String::new();
        for c in b.chunks(3) {
            let n = (u32::from(c[0]) << 16)
                | (u32::from(*c.get(1).unwrap_or(&0)) << 8)
                | u32::from(*c.get(2).unwrap_or(&0));
            for k in 0..4 {
                if k <= c.len() {
                    out.push(A[(n >> (18 - 6 * k) & 63) as usize] as char);
                } else {
                    out.push('=');
                }
            }
        }
        out
    }

    #[test]
    fn base64_round_trips() {
        assert_eq!(base64_decode(b"").unwrap(), b"");
        assert_eq!(base64_decode(b"Zg==").unwrap(), b"f");
        assert_eq!(base64_decode(b"Zm8=").unwrap(), b"fo");
        assert_eq!(base64_decode(b"Zm9v").unwrap(), b"foo");
        assert_eq!(base64_decode(b"Zm9vYg").unwrap(), b"foob");
        assert_eq!(base64_decode(b"AAECAw==").unwrap(), [0, 1, 2, 3]);
        assert!(base64_decode(b"Zm9v!").is_err());
        assert!(base64_decode(b"Z").is_err());
    }

    #[test]
    fn percent_decoding() {
        assert_eq!(percent_decode("a%20b.bin").unwrap(), "a b.bin");
        assert!(percent_decode("a%2").is_none());
        assert!(percent_decode("a%zz").is_none());
    }

    #[test]
    fn glb_lengths_are_checked() {
        assert!(matches!(split(b"glTF"), Err(GltfError::GlbHeader(_))));
        let mut glb = b"glTF".to_vec();
        glb.extend_from_slice(&2u32.to_le_bytes());
        glb.extend_from_slice(&40u32.to_le_bytes());
        assert!(matches!(split(&glb), Err(GltfError::GlbLength { .. })));
        let mut glb = b"glTF".to_vec();
        glb.extend_from_slice(&2u32.to_le_bytes());
        glb.extend_from_slice(&20u32.to_le_bytes());
        glb.extend_from_slice(&100u32.to_le_bytes());
        glb.extend_from_slice(&CHUNK_JSON.to_le_bytes());
        // A chunk that declares more bytes than remain.
        assert!(matches!(
            split(&glb),
            Err(GltfError::GlbChunk { offset: 12, .. })
        ));
        // A chunk header cut short.
        glb.truncate(16);
        glb[8..12].copy_from_slice(&16u32.to_le_bytes());
        assert!(matches!(
            split(&glb),
            Err(GltfError::GlbChunk {
                index: 0,
                offset: 12,
                ..
            })
        ));
        // A header with no chunks at all.
        glb.truncate(12);
        glb[8..12].copy_from_slice(&12u32.to_le_bytes());
        assert!(matches!(split(&glb), Err(GltfError::GlbHeader(_))));
    }
}
