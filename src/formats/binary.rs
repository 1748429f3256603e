//! The contract's binary files (§2): RAY1 rays, HIT1 hits and TRI1 triangles.
//!
//! Every file is a 16-byte header `magic: u32, version: u16, format: u16, count: u64`
//! followed by exactly `count` fixed-size records, all little-endian. Readers check the
//! header and the exact body length (without overflow, before allocating) and say which
//! rule failed; `proto/binary-formats.md` is the long form.

use crate::geometry::{Hit, Ray, RaySegment, Triangle};

/// `RAY1` as a little-endian u32.
pub const RAY1_MAGIC: u32 = u32::from_le_bytes(*b"RAY1");
/// `HIT1` as a little-endian u32.
pub const HIT1_MAGIC: u32 = u32::from_le_bytes(*b"HIT1");
/// `TRI1` as a little-endian u32.
pub const TRI1_MAGIC: u32 = u32::from_le_bytes(*b"TRI1");
/// The only version there is.
pub const VERSION: u16 = 1;
/// Size of the common header.
pub const HEADER_BYTES: usize = 16;

const _: () = assert!(RAY1_MAGIC == 0x3159_4152);
const _: () = assert!(HIT1_MAGIC == 0x3154_4948);
const _: () = assert!(TRI1_MAGIC == 0x3149_5254);

/// Which fields a HIT1 record carries.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "snake_case")]
pub enum HitFormat {
    /// `t: f32, prim: u32, u: f32, v: f32` (16 bytes).
    #[default]
    TPrimUv,
    /// `t: f32, prim: u32` (8 bytes).
    TPrim,
    /// `t: f32` (4 bytes).
    T,
    /// `u8`: 1 if the ray hits anything in its interval.
    Occluded,
}

impl HitFormat {
    /// Every format, by code.
    pub const ALL: [HitFormat; 4] = [
        HitFormat::TPrimUv,
        HitFormat::TPrim,
        HitFormat::T,
        HitFormat::Occluded,
    ];

    /// The header's `format` code.
    pub fn code(self) -> u16 {
        match self {
            HitFormat::TPrimUv => 0,
            HitFormat::TPrim => 1,
            HitFormat::T => 2,
            HitFormat::Occluded => 3,
        }
    }

    /// The contract's name.
    pub fn name(self) -> &'static str {
        crate::names::Spelled::name(self)
    }

    /// Parses the contract's name.
    pub fn parse(s: &str) -> Option<HitFormat> {
        crate::names::Spelled::parse_name(s).ok()
    }

    /// Bytes per record.
    pub fn record_bytes(self) -> usize {
        match self {
            HitFormat::TPrimUv => 16,
            HitFormat::TPrim => 8,
            HitFormat::T => 4,
            HitFormat::Occluded => 1,
        }
    }

    fn from_code(code: u16) -> Option<HitFormat> {
        HitFormat::ALL.into_iter().find(|f| f.code() == code)
    }
}

crate::spelled!(HitFormat, HitFormat::ALL);

/// What is wrong with a binary body.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BinaryError {
    /// Fewer than 16 bytes.
    #[error("{kind}: body is {len} bytes, shorter than the 16-byte header")]
    ShortHeader {
        /// Which file kind was expected.
        kind: &'static str,
        /// Body length.
        len: usize,
    },
    /// The magic at byte 0 is not the expected one.
    #[error(
        "{kind}: wrong magic {found:#010x} at byte 0 (expected {expected:#010x}, ASCII \"{kind}\")"
    )]
    WrongMagic {
        /// Which file kind was expected.
        kind: &'static str,
        /// Magic found.
        found: u32,
        /// Magic expected.
        expected: u32,
    },
    /// The version at byte 4 is not 1.
    #[error("{kind}: unknown version {found} at byte 4 (expected 1)")]
    UnknownVersion {
        /// Which file kind was expected.
        kind: &'static str,
        /// Version found.
        found: u16,
    },
    /// The format at byte 6 is not one this kind has.
    #[error("{kind}: unknown format {found} at byte 6 ({allowed})")]
    UnknownFormat {
        /// Which file kind was expected.
        kind: &'static str,
        /// Format found.
        found: u16,
        /// What is allowed.
        allowed: &'static str,
    },
    /// `16 + count × record` overflows.
    #[error("{kind}: count {count} at byte 8 is too large ({record} bytes a record overflows)")]
    CountOverflow {
        /// Which file kind was expected.
        kind: &'static str,
        /// The count in the header.
        count: u64,
        /// Record size.
        record: usize,
    },
    /// The body is not exactly `16 + count × record` bytes.
    #[error("{kind}: body is {}{len} bytes but the header's count {count} needs exactly {expected} (16 + {count} × {record})", if *.at_least { "at least " } else { "" })]
    WrongLength {
        /// Which file kind was expected.
        kind: &'static str,
        /// Body length, or with `at_least` the bytes that had arrived when it ran past
        /// `expected` (a body without a length, read as it streams).
        len: usize,
        /// `len` is a lower bound: the body was refused before its end.
        at_least: bool,
        /// The count in the header.
        count: u64,
        /// Record size.
        record: usize,
        /// Expected body length.
        expected: u128,
    },
    /// The header's count is over the reader's limit.
    #[error("{kind}: count {count} at byte 8 exceeds the limit of {limit} records")]
    TooMany {
        /// Which file kind was expected.
        kind: &'static str,
        /// The count in the header.
        count: u64,
        /// The limit.
        limit: u64,
    },
    /// A TRI1 coordinate is NaN or infinite.
    #[error("TRI1: triangle {index} has a NaN or infinite coordinate (byte offset {offset})")]
    NonFiniteTriangle {
        /// Triangle index.
        index: usize,
        /// Byte offset of the bad coordinate.
        offset: usize,
    },
}

impl BinaryError {
    /// The byte of the body where the error lies, where it has one: what a problem
    /// document's `byte_offset` names.
    pub fn byte_offset(&self) -> Option<u64> {
        match self {
            BinaryError::ShortHeader { len, .. } => Some(*len as u64),
            BinaryError::WrongMagic { .. } => Some(0),
            BinaryError::UnknownVersion { .. } => Some(4),
            BinaryError::UnknownFormat { .. } => Some(6),
            BinaryError::CountOverflow { .. } | BinaryError::TooMany { .. } => Some(8),
            // Where the body and its count part: the end of a short body (the first byte
            // missing), the first byte past the records of a long one.
            BinaryError::WrongLength { len, expected, .. } => {
                Some((*len as u128).min(*expected) as u64)
            }
            BinaryError::NonFiniteTriangle { offset, .. } => Some(*offset as u64),
        }
    }
}

struct Header {
    format: u16,
    count: usize,
}

fn read_u32(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"))
}

fn read_f32(b: &[u8], at: usize) -> f32 {
    f32::from_le_bytes(b[at..at + 4].try_into().expect("4 bytes"))
}

/// Checks the header and the exact body length; `record_for` gives the record size of a
/// format code, or `None` for an unknown one.
fn parse_header(
    bytes: &[u8],
    kind: &'static str,
    magic: u32,
    allowed: &'static str,
    record_for: impl Fn(u16) -> Option<usize>,
) -> Result<Header, BinaryError> {
    let h = parse_header_fields(bytes, kind, magic, allowed, &record_for)?;
    let record = record_for(h.format).expect("checked by parse_header_fields");
    let expected = (h.count as u128) * (record as u128) + HEADER_BYTES as u128;
    if bytes.len() as u128 != expected {
        return Err(BinaryError::WrongLength {
            kind,
            len: bytes.len(),
            at_least: false,
            count: h.count as u64,
            record,
            expected,
        });
    }
    Ok(h)
}

/// Checks the header's fields (not the body's length) from the first 16 bytes.
fn parse_header_fields(
    bytes: &[u8],
    kind: &'static str,
    magic: u32,
    allowed: &'static str,
    record_for: impl Fn(u16) -> Option<usize>,
) -> Result<Header, BinaryError> {
    if bytes.len() < HEADER_BYTES {
        return Err(BinaryError::ShortHeader {
            kind,
            len: bytes.len(),
        });
    }
    let found = read_u32(bytes, 0);
    if found != magic {
        return Err(BinaryError::WrongMagic {
            kind,
            found,
            expected: magic,
        });
    }
    let version = u16::from_le_bytes([bytes[4], bytes[5]]);
    if version != VERSION {
        return Err(BinaryError::UnknownVersion {
            kind,
            found: version,
        });
    }
    let format = u16::from_le_bytes([bytes[6], bytes[7]]);
    let record = record_for(format).ok_or(BinaryError::UnknownFormat {
        kind,
        found: format,
        allowed,
    })?;
    let count = u64::from_le_bytes(bytes[8..16].try_into().expect("8 bytes"));
    let expected = (count as u128) * (record as u128) + HEADER_BYTES as u128;
    if expected > usize::MAX as u128 || expected > isize::MAX as u128 {
        return Err(BinaryError::CountOverflow {
            kind,
            count,
            record,
        });
    }
    Ok(Header {
        format,
        count: count as usize,
    })
}

fn header(magic: u32, format: u16, count: usize, record: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER_BYTES + count * record);
    out.extend_from_slice(&magic.to_le_bytes());
    out.extend_from_slice(&VERSION.to_le_bytes());
    out.extend_from_slice(&format.to_le_bytes());
    out.extend_from_slice(&(count as u64).to_le_bytes());
    out
}

/// Reads a RAY1 body. Validity of the rays themselves is checked separately
/// ([`Ray::validate_batch`]), since `invalid=miss` answers bad rays instead of refusing them.
pub fn read_rays(bytes: &[u8]) -> Result<Vec<Ray>, BinaryError> {
    let mut sink = Ray1Sink::new(usize::MAX, Some(bytes.len() as u64));
    sink.push(bytes)?;
    sink.finish()
}

/// A RAY1 body arriving in pieces (a file read in chunks, an HTTP body as it uploads),
/// written straight into the rays' memory: on little-endian targets a RAY1 record has the
/// [`Ray`]'s layout, so the bytes are the rays and nothing is decoded or copied twice.
///
/// The header is checked as soon as its 16 bytes are in; with a known body length
/// (`length_hint`, e.g. a file's size or a `Content-Length`) a count that disagrees with it
/// is refused before anything is allocated, and the rays' memory is allocated once. Without
/// one, the memory grows with what actually arrives, so a header that lies about its count
/// cannot make the reader allocate for it.
pub struct Ray1Sink {
    limit: usize,
    hint: Option<u64>,
    header: [u8; HEADER_BYTES],
    header_len: usize,
    count: usize,
    /// The whole rays of the current segment (all of them, unsegmented) received so far.
    rays: Vec<Ray>,
    /// The first bytes of the ray after `rays`, when a piece ended inside it.
    partial: [u8; 32],
    /// How many bytes of `partial` are in.
    partial_len: usize,
    /// Every ray in `rays` passed [`Ray::is_valid`] (checked as it was copied in).
    valid: bool,
    /// Rays per segment (`usize::MAX`: one segment).
    segment: usize,
    /// Rays in the segments completed before `rays`.
    taken: usize,
    /// Completed segments not yet taken.
    ready: Vec<RaySegment>,
}

impl Ray1Sink {
    /// A reader that refuses more than `limit` rays.
    pub fn new(limit: usize, length_hint: Option<u64>) -> Ray1Sink {
        Ray1Sink {
            limit,
            hint: length_hint,
            header: [0; HEADER_BYTES],
            header_len: 0,
            count: 0,
            rays: Vec::new(),
            partial: [0; 32],
            partial_len: 0,
            valid: true,
            segment: usize::MAX,
            taken: 0,
            ready: Vec::new(),
        }
    }

    /// Hands the rays out in segments of `rays` rays as they complete
    /// ([`Ray1Sink::take_ready`]), so a consumer can start on them before the body ends;
    /// the last segment is what [`Ray1Sink::finish`] returns.
    pub fn segmented(mut self, rays: usize) -> Ray1Sink {
        self.segment = rays.max(1);
        self
    }

    /// Segments completed since the last call, in order.
    pub fn take_ready(&mut self) -> std::vec::Drain<'_, RaySegment> {
        self.ready.drain(..)
    }

    /// Rays of the current segment.
    fn segment_rays(&self) -> usize {
        self.segment.min(self.count - self.taken)
    }

    /// The header's count, once the header is in.
    pub fn count(&self) -> Option<usize> {
        (self.header_len == HEADER_BYTES).then_some(self.count)
    }

    /// Whole rays received so far.
    pub fn rays_received(&self) -> usize {
        self.taken + self.rays.len()
    }

    /// Record bytes received into the current segment.
    fn filled(&self) -> usize {
        32 * self.rays.len() + self.partial_len
    }

    fn wrong_length(&self, len: u128, at_least: bool) -> BinaryError {
        BinaryError::WrongLength {
            kind: "RAY1",
            len: len.min(usize::MAX as u128) as usize,
            at_least,
            count: self.count as u64,
            record: 32,
            expected: HEADER_BYTES as u128 + 32 * self.count as u128,
        }
    }

    /// Takes the next bytes of the body.
    pub fn push(&mut self, mut chunk: &[u8]) -> Result<(), BinaryError> {
        if self.header_len < HEADER_BYTES {
            let take = chunk.len().min(HEADER_BYTES - self.header_len);
            self.header[self.header_len..self.header_len + take].copy_from_slice(&chunk[..take]);
            self.header_len += take;
            chunk = &chunk[take..];
            if self.header_len < HEADER_BYTES {
                return Ok(());
            }
            self.start()?;
        }
        let total = 32 * self.taken + self.filled() + chunk.len();
        if total > 32 * self.count {
            return Err(self.wrong_length(HEADER_BYTES as u128 + total as u128, true));
        }
        while !chunk.is_empty() {
            let seg = self.segment_rays();
            if self.partial_len > 0 {
                // Complete the ray the last piece broke off inside.
                let take = chunk.len().min(32 - self.partial_len);
                self.partial[self.partial_len..self.partial_len + take]
                    .copy_from_slice(&chunk[..take]);
                self.partial_len += take;
                chunk = &chunk[take..];
                if self.partial_len < 32 {
                    break;
                }
                self.partial_len = 0;
                let mut ray: Ray = bytemuck::pod_read_unaligned(&self.partial);
                if cfg!(target_endian = "little") {
                    ray.bound_tmax();
                }
                self.valid &= ray.is_valid();
                self.rays.push(ray);
            } else {
                // Whole rays straight from the piece into the segment's memory: each record
                // is read as a ray (the bytes' alignment is the network's), never zeroed first.
                let whole = (chunk.len() / 32).min(seg - self.rays.len());
                let (records, rest) = chunk.split_at(32 * whole);
                if self.rays.capacity() < self.rays.len() + whole {
                    // Growing mode (no length hint): at least double, at most the segment.
                    let want = (self.rays.len() + whole).max(2 * self.rays.len()).min(seg);
                    self.rays.reserve_exact(want - self.rays.len());
                }
                let from = self.rays.len();
                self.rays.extend(
                    records
                        .chunks_exact(32)
                        .map(bytemuck::pod_read_unaligned::<Ray>),
                );
                // Checked while the piece is still in cache (little-endian: the bytes are the
                // rays; big-endian swaps later, so it leaves the check to the consumer).
                // Each +inf tmax is bounded here too ([`Ray::bound_tmax`]).
                self.valid &= cfg!(target_endian = "little")
                    && self.rays[from..].iter_mut().fold(true, |all, r| {
                        r.bound_tmax();
                        all & r.is_valid()
                    });
                chunk = rest;
                if whole == 0 && !chunk.is_empty() && self.rays.len() < seg {
                    let take = chunk.len().min(32);
                    self.partial[..take].copy_from_slice(&chunk[..take]);
                    self.partial_len = take;
                    chunk = &chunk[take..];
                }
            }
            if self.rays.len() == seg && self.taken + seg < self.count {
                // A segment is complete and more follow: hand it out, start the next.
                let mut done = std::mem::take(&mut self.rays);
                to_native(&mut done);
                self.ready.push(RaySegment {
                    rays: done,
                    all_valid: std::mem::replace(&mut self.valid, true),
                });
                self.taken += seg;
                if self.hint.is_some() {
                    self.rays = Vec::with_capacity(self.segment_rays());
                }
            }
        }
        Ok(())
    }

    /// The header is complete: check it and allocate.
    fn start(&mut self) -> Result<(), BinaryError> {
        let h = parse_header_fields(
            &self.header,
            "RAY1",
            RAY1_MAGIC,
            "RAY1 has only format 0",
            |f| (f == 0).then_some(32),
        )?;
        if h.count as u128 > self.limit as u128 {
            return Err(BinaryError::TooMany {
                kind: "RAY1",
                count: h.count as u64,
                limit: self.limit as u64,
            });
        }
        self.count = h.count;
        if let Some(len) = self.hint {
            if len as u128 != HEADER_BYTES as u128 + 32 * self.count as u128 {
                return Err(self.wrong_length(len as u128, false));
            }
            self.rays = Vec::with_capacity(self.segment_rays());
        }
        Ok(())
    }

    /// The rays, once the body is complete: all of them, or, segmented, the last segment.
    pub fn finish(self) -> Result<Vec<Ray>, BinaryError> {
        Ok(self.finish_segment()?.rays)
    }

    /// [`Ray1Sink::finish`], with what reading learned of the rays' validity.
    pub fn finish_segment(mut self) -> Result<RaySegment, BinaryError> {
        if self.header_len < HEADER_BYTES {
            return Err(BinaryError::ShortHeader {
                kind: "RAY1",
                len: self.header_len,
            });
        }
        if self.taken + self.rays.len() != self.count || self.partial_len != 0 {
            return Err(self.wrong_length(
                HEADER_BYTES as u128 + 32 * self.taken as u128 + self.filled() as u128,
                false,
            ));
        }
        to_native(&mut self.rays);
        Ok(RaySegment {
            rays: self.rays,
            all_valid: self.valid,
        })
    }
}

/// RAY1 records are little-endian: on a big-endian target, swap each word in place.
fn to_native(rays: &mut [Ray]) {
    if cfg!(target_endian = "big") {
        for x in bytemuck::cast_slice_mut::<Ray, u32>(rays) {
            *x = u32::from_le(*x);
        }
    }
}

/// The 16-byte header of a HIT1 body of `count` records of `format`.
pub fn hit1_header(format: HitFormat, count: usize) -> [u8; HEADER_BYTES] {
    let mut h = [0u8; HEADER_BYTES];
    h[0..4].copy_from_slice(&HIT1_MAGIC.to_le_bytes());
    h[4..6].copy_from_slice(&VERSION.to_le_bytes());
    h[6..8].copy_from_slice(&format.code().to_le_bytes());
    h[8..16].copy_from_slice(&(count as u64).to_le_bytes());
    h
}

/// Writes rays as a RAY1 body.
pub fn write_rays(rays: &[Ray]) -> Vec<u8> {
    let mut out = header(RAY1_MAGIC, 0, rays.len(), 32);
    for r in rays {
        for x in [
            r.org[0], r.org[1], r.org[2], r.tmin, r.dir[0], r.dir[1], r.dir[2], r.tmax,
        ] {
            out.extend_from_slice(&x.to_le_bytes());
        }
    }
    out
}

/// The ray count of a whole RAY1 body whose header and length hold and whose count is at
/// most `limit`, reading no record: the checks [`Ray1Sink`] makes before the records, for
/// a body that is kept as it is (an asynchronous trace's rays, stored for its job).
pub fn ray_count(bytes: &[u8], limit: usize) -> Result<usize, BinaryError> {
    let mut sink = Ray1Sink::new(limit, None);
    sink.push(&bytes[..bytes.len().min(HEADER_BYTES)])?;
    let count = sink.count().ok_or(BinaryError::ShortHeader {
        kind: "RAY1",
        len: bytes.len(),
    })?;
    if bytes.len() as u128 != HEADER_BYTES as u128 + 32 * count as u128 {
        return Err(sink.wrong_length(bytes.len() as u128, false));
    }
    Ok(count)
}

/// The triangle count of a TRI1 body whose header and length hold, reading no record: what
/// [`read_tri`] checks before it reads the records.
pub fn tri_count(bytes: &[u8]) -> Result<usize, BinaryError> {
    parse_header(bytes, "TRI1", TRI1_MAGIC, "TRI1 has only format 0", |f| {
        (f == 0).then_some(36)
    })
    .map(|h| h.count)
}

/// The triangle count in a TRI1 header (its first 16 bytes, the body's length unchecked):
/// for a TRI1 document that arrives in pieces, or is followed by another (a frame's rays).
pub fn tri_header_count(header: &[u8]) -> Result<usize, BinaryError> {
    parse_header_fields(header, "TRI1", TRI1_MAGIC, "TRI1 has only format 0", |f| {
        (f == 0).then_some(36)
    })
    .map(|h| h.count)
}

/// Reads a TRI1 body; a NaN or infinite coordinate is refused with its triangle and offset.
pub fn read_tri(bytes: &[u8]) -> Result<Vec<Triangle>, BinaryError> {
    let count = tri_count(bytes)?;
    let body = &bytes[HEADER_BYTES..];
    let mut tris = Vec::with_capacity(count);
    for (index, rec) in body.chunks_exact(36).enumerate() {
        let mut t = Triangle::default();
        for (k, x) in t.v.iter_mut().flatten().enumerate() {
            *x = read_f32(rec, 4 * k);
            if !x.is_finite() {
                return Err(BinaryError::NonFiniteTriangle {
                    index,
                    offset: HEADER_BYTES + 36 * index + 4 * k,
                });
            }
        }
        tris.push(t);
    }
    Ok(tris)
}

/// Writes triangles as a TRI1 body.
pub fn write_tri(tris: &[Triangle]) -> Vec<u8> {
    let mut out = header(TRI1_MAGIC, 0, tris.len(), 36);
    for t in tris {
        for x in t.v.iter().flatten() {
            out.extend_from_slice(&x.to_le_bytes());
        }
    }
    out
}

/// Writes hits as a HIT1 body with only the fields of `format`.
pub fn write_hits(hits: &[Hit], format: HitFormat) -> Vec<u8> {
    let mut out = header(HIT1_MAGIC, format.code(), hits.len(), format.record_bytes());
    for h in hits {
        match format {
            HitFormat::TPrimUv => {
                out.extend_from_slice(&h.t.to_le_bytes());
                out.extend_from_slice(&h.prim.to_le_bytes());
                out.extend_from_slice(&h.u.to_le_bytes());
                out.extend_from_slice(&h.v.to_le_bytes());
            }
            HitFormat::TPrim => {
                out.extend_from_slice(&h.t.to_le_bytes());
                out.extend_from_slice(&h.prim.to_le_bytes());
            }
            HitFormat::T => out.extend_from_slice(&h.t.to_le_bytes()),
            HitFormat::Occluded => out.push(u8::from(h.is_hit())),
        }
    }
    out
}

/// Writes `occluded` flags (one byte a ray, 0 or 1) as a HIT1 body of format 3, for the
/// cores' [`occluded`](crate::accel::Intersector::occluded) answers that carry no fields.
pub fn write_occluded(flags: &[u8]) -> Vec<u8> {
    let mut out = header(HIT1_MAGIC, HitFormat::Occluded.code(), flags.len(), 1);
    out.extend(flags.iter().map(|&f| u8::from(f != 0)));
    out
}

/// Reads a HIT1 body. Fields the format does not carry come back as the miss's values,
/// except that `prim` is 0 for a hit of the `t` and `occluded` formats so that
/// [`Hit::is_hit`] tells hits from misses; compare only what was written.
pub fn read_hits(bytes: &[u8]) -> Result<(HitFormat, Vec<Hit>), BinaryError> {
    let h = parse_header(bytes, "HIT1", HIT1_MAGIC, "HIT1 formats are 0 to 3", |f| {
        HitFormat::from_code(f).map(HitFormat::record_bytes)
    })?;
    let format = HitFormat::from_code(h.format).expect("checked by parse_header");
    let body = &bytes[HEADER_BYTES..];
    let mut hits = Vec::with_capacity(h.count);
    for rec in body.chunks_exact(format.record_bytes()) {
        let mut hit = Hit::MISS;
        match format {
            HitFormat::TPrimUv => {
                hit.t = read_f32(rec, 0);
                hit.prim = read_u32(rec, 4);
                hit.u = read_f32(rec, 8);
                hit.v = read_f32(rec, 12);
            }
            HitFormat::TPrim => {
                hit.t = read_f32(rec, 0);
                hit.prim = read_u32(rec, 4);
            }
            HitFormat::T => {
                hit.t = read_f32(rec, 0);
                if hit.t.is_finite() {
                    hit.prim = 0;
                }
            }
            HitFormat::Occluded => {
                if rec[0] != 0 {
                    hit.t = 0.0;
                    hit.prim = 0;
                }
            }
        }
        hits.push(hit);
    }
    Ok((format, hits))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rays() -> Vec<Ray> {
        (0..5)
            .map(|i| Ray {
                org: [i as f32, 1.0, 2.0],
                tmin: 0.0,
                dir: [0.0, 0.0, -1.0],
                tmax: if i % 2 == 0 { f32::INFINITY } else { 10.0 },
            })
            .collect()
    }

    #[test]
    fn rays_round_trip() {
        let r = rays();
        let bytes = write_rays(&r);
        assert_eq!(bytes.len(), 16 + 5 * 32);
        assert_eq!(&bytes[0..4], b"RAY1");
        // Read back the same, but for a +inf tmax, bounded to the largest finite f32
        // (`Ray::bound_tmax`: the same interval, and no hit at t = +inf).
        let bounded: Vec<Ray> = r
            .iter()
            .map(|r| Ray {
                tmax: r.tmax.min(f32::MAX),
                ..*r
            })
            .collect();
        assert_eq!(read_rays(&bytes).unwrap(), bounded);
    }

    #[test]
    fn ray_count_checks_header_length_and_limit_only() {
        let bytes = write_rays(&rays());
        assert_eq!(ray_count(&bytes, 5).unwrap(), 5);
        assert!(matches!(
            ray_count(&bytes, 4),
            Err(BinaryError::TooMany {
                count: 5,
                limit: 4,
                ..
            })
        ));
        assert!(matches!(
            ray_count(&bytes[..bytes.len() - 1], 5),
            Err(BinaryError::WrongLength { .. })
        ));
        // A wrong length's byte offset is where the body and its count part: the first
        // byte missing from a short body, the first extra one of a long body.
        let short = ray_count(&bytes[..bytes.len() - 1], 5).unwrap_err();
        assert_eq!(short.byte_offset(), Some(bytes.len() as u64 - 1));
        let mut long = bytes.clone();
        long.extend([0; 7]);
        let long = ray_count(&long, 5).unwrap_err();
        assert_eq!(long.byte_offset(), Some(bytes.len() as u64));
        assert!(!long.to_string().contains("at least"), "{long}");
        // Streamed without a length, an overrun is refused on the piece that brings it:
        // the message says the body is at least what had arrived.
        let mut sink = Ray1Sink::new(usize::MAX, None);
        sink.push(&bytes).unwrap();
        let over = sink.push(&[0; 40]).unwrap_err();
        assert_eq!(over.byte_offset(), Some(bytes.len() as u64));
        let m = over.to_string();
        assert!(m.contains(&format!("at least {}", bytes.len() + 40)), "{m}");
        assert!(matches!(
            ray_count(&bytes[..10], 5),
            Err(BinaryError::ShortHeader { len: 10, .. })
        ));
        let mut wrong = bytes.clone();
        wrong[0] = b'X';
        assert!(matches!(
            ray_count(&wrong, 5),
            Err(BinaryError::WrongMagic { .. })
        ));
        // A NaN ray is left to the trace's `invalid` policy.
        let mut nan = rays();
        nan[2].dir[1] = f32::NAN;
        assert_eq!(ray_count(&write_rays(&nan), 5).unwrap(), 5);
    }

    #[test]
    fn a_segmented_sink_hands_out_every_ray_once_in_order() {
        let all: Vec<Ray> = (0..103)
            .map(|i| Ray {
                org: [i as f32, 0.5, -1.0],
                tmin: 0.0,
                dir: [0.0, 1.0, 0.0],
                tmax: i as f32,
            })
            .collect();
        let bytes = write_rays(&all);
        for hint in [None, Some(bytes.len() as u64)] {
            for (segment, chunk) in [
                (1, 7),
                (10, 1),
                (10, 33),
                (7, 45),
                (2, 31),
                (64, 100),
                (103, 5),
                (500, 64),
            ] {
                let mut sink = Ray1Sink::new(usize::MAX, hint).segmented(segment);
                let mut got = Vec::new();
                for c in bytes.chunks(chunk) {
                    sink.push(c).unwrap();
                    for seg in sink.take_ready() {
                        assert_eq!(
                            seg.rays.len(),
                            segment,
                            "only whole segments before the end"
                        );
                        assert!(seg.all_valid);
                        got.extend(seg.rays);
                    }
                    assert_eq!(sink.rays_received(), got.len() + sink.rays.len());
                }
                let last = sink.finish().unwrap();
                assert!(!last.is_empty() && last.len() <= segment);
                got.extend(last);
                assert_eq!(got, all, "segment {segment}, chunk {chunk}, hint {hint:?}");
            }
        }
        // A short body is still refused, segmented or not.
        let mut sink = Ray1Sink::new(usize::MAX, None).segmented(10);
        sink.push(&bytes[..bytes.len() - 32]).unwrap();
        assert!(matches!(
            sink.finish(),
            Err(BinaryError::WrongLength { .. })
        ));
        let mut sink = Ray1Sink::new(usize::MAX, None).segmented(10);
        assert!(sink.push(&[&bytes[..], &[0u8; 32][..]].concat()).is_err());
    }

    #[test]
    fn a_sink_flags_the_segments_it_cannot_vouch_for() {
        let mut all: Vec<Ray> = (0..40)
            .map(|i| Ray {
                org: [i as f32, 0.0, 0.0],
                tmin: 0.0,
                dir: [0.0, 0.0, 1.0],
                tmax: 1.0,
            })
            .collect();
        all[13].dir = [0.0; 3];
        all[31].org[2] = f32::NAN;
        let bytes = write_rays(&all);
        for chunk in [1, 31, 32, 33, 1000] {
            let mut sink = Ray1Sink::new(usize::MAX, Some(bytes.len() as u64)).segmented(10);
            let mut flags = Vec::new();
            for c in bytes.chunks(chunk) {
                sink.push(c).unwrap();
                flags.extend(sink.take_ready().map(|s| s.all_valid));
            }
            flags.push(sink.finish_segment().unwrap().all_valid);
            assert_eq!(
                flags,
                [true, false, true, false],
                "segments 1 and 3 hold the bad rays (chunk {chunk})"
            );
        }
    }

    #[test]
    fn triangles_round_trip_and_refuse_nan() {
        let t = vec![
            Triangle {
                v: [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]],
            };
            3
        ];
        let mut bytes = write_tri(&t);
        assert_eq!(read_tri(&bytes).unwrap(), t);
        let off = 16 + 36 + 4 * 4;
        bytes[off..off + 4].copy_from_slice(&f32::NAN.to_le_bytes());
        assert_eq!(
            read_tri(&bytes),
            Err(BinaryError::NonFiniteTriangle {
                index: 1,
                offset: off
            })
        );
    }

    #[test]
    fn hits_round_trip_in_every_format() {
        let hits = [
            Hit {
                t: 1.5,
                prim: 7,
                u: 0.25,
                v: 0.5,
            },
            Hit::MISS,
        ];
        for f in HitFormat::ALL {
            let bytes = write_hits(&hits, f);
            assert_eq!(bytes.len(), 16 + 2 * f.record_bytes());
            let (g, back) = read_hits(&bytes).unwrap();
            assert_eq!(g, f);
            assert_eq!(back[1], Hit::MISS);
            match f {
                HitFormat::TPrimUv => assert_eq!(back[0], hits[0]),
                HitFormat::TPrim => assert_eq!((back[0].t, back[0].prim), (1.5, 7)),
                HitFormat::T => assert_eq!(back[0].t, 1.5),
                HitFormat::Occluded => assert!(back[0].is_hit()),
            }
        }
    }

    #[test]
    fn header_errors_say_which_rule() {
        let good = write_rays(&rays());
        assert!(matches!(
            read_rays(&good[..10]),
            Err(BinaryError::ShortHeader { len: 10, .. })
        ));
        let mut b = good.clone();
        b[0] = b'X';
        assert!(matches!(read_rays(&b), Err(BinaryError::WrongMagic { .. })));
        assert!(matches!(
            read_rays(&write_tri(&[])),
            Err(BinaryError::WrongMagic { .. })
        ));
        let mut b = good.clone();
        b[4] = 2;
        assert!(matches!(
            read_rays(&b),
            Err(BinaryError::UnknownVersion { found: 2, .. })
        ));
        let mut b = good.clone();
        b[6] = 1;
        assert!(matches!(
            read_rays(&b),
            Err(BinaryError::UnknownFormat { found: 1, .. })
        ));
        let mut b = good.clone();
        b.push(0);
        assert!(matches!(
            read_rays(&b),
            Err(BinaryError::WrongLength { .. })
        ));
        assert!(matches!(
            read_rays(&good[..good.len() - 1]),
            Err(BinaryError::WrongLength { .. })
        ));
        let mut b = good.clone();
        b[8..16].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(matches!(
            read_rays(&b),
            Err(BinaryError::CountOverflow { .. })
        ));
        let mut h = write_hits(&[Hit::MISS], HitFormat::T);
        h[6] = 4;
        assert!(matches!(
            read_hits(&h),
            Err(BinaryError::UnknownFormat { found: 4, .. })
        ));
    }
}
