//! Trace jobs: one batch of rays against one geometry, answered as a HIT1 body.
//!
//! The body is written where the hits land: for `t_prim_uv` the cores write their hit
//! records straight into the response's memory (a HIT1 record of that format is a [`Hit`]
//! on little-endian targets, and the 16-byte header takes the place of one record), so a
//! 16M-ray answer is 256 MiB once, not twice. The narrower formats are packed from the
//! records; `occluded` is written by the cores' occlusion test directly.

use std::time::Instant;

use super::engine::Source;
use super::{seconds_since, Control, Engine, Geometry, InvalidPolicy, JobError};
use crate::accel::{AccelKind, BuildQuality, Precision, Query};
use crate::formats::binary::{hit1_header, Ray1Sink, HEADER_BYTES};
use crate::formats::HitFormat;
use crate::geometry::{Hit, InvalidRays, Ray, RaySegment};

/// What to trace and how (the options of `rayd trace` and of the trace route's query
/// string; the defaults are the contract's).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TraceRequest {
    /// `closest` or `any`.
    pub query: Query,
    /// Which hit fields to return.
    pub hit: HitFormat,
    /// The accelerator (`auto` resolves per job).
    pub accel: AccelKind,
    /// Build quality of the BVH accelerators.
    pub build: BuildQuality,
    /// Ray/triangle test.
    pub precision: Precision,
    /// What to do with invalid rays.
    pub invalid: InvalidPolicy,
}

/// What a trace did, as `rayd trace` prints it and the service reports it.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct TraceReport {
    /// Rays traced.
    pub rays: usize,
    /// The accelerator used (what `auto` chose).
    pub accel: &'static str,
    /// Threads of the pool.
    pub threads: usize,
    /// Preparation the trace needed first (build, refit, DACRT precompute; 0 if cached).
    pub build_seconds: f64,
    /// Validated rays in memory to hit records in memory.
    pub trace_seconds: f64,
    /// `rays / trace_seconds / 1e6`.
    pub mrays_per_s: f64,
    /// The query.
    pub query: Query,
    /// The hit format.
    pub hit: HitFormat,
    /// The precision.
    pub precision: Precision,
    /// The build quality asked for.
    pub build: BuildQuality,
    /// The SIMD backend.
    pub simd: &'static str,
    /// Where the structure came from.
    pub structure: Source,
    /// Rays answered as misses because they were invalid (`invalid=miss`).
    pub invalid_rays: usize,
}

/// A HIT1 body, header included, ready to send or write.
pub enum HitBody {
    /// `t_prim_uv`: the header's bytes in record 0, then one record per ray.
    Records(Vec<Hit>),
    /// Any other format, packed.
    Packed(Vec<u8>),
}

impl AsRef<[u8]> for HitBody {
    fn as_ref(&self) -> &[u8] {
        match self {
            HitBody::Records(r) => bytemuck::cast_slice(r),
            HitBody::Packed(b) => b,
        }
    }
}

impl HitBody {
    /// Bytes of the body.
    pub fn len(&self) -> usize {
        self.as_ref().len()
    }

    /// Whether the body is empty (never: a body has its header).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Checks the rays (contract §2): with `error`, refuses the batch naming the first bad
/// ray and the count; with `miss`, turns each bad ray into an empty interval and returns how
/// many there were.
pub fn validate(rays: &mut [Ray], policy: InvalidPolicy) -> Result<usize, JobError> {
    settle(
        Ray::validate_batch(rays, policy == InvalidPolicy::Miss),
        policy,
    )
}

/// [`validate`] of rays as their reader handed them on (a segment it vouched for is not
/// read again).
pub fn validate_read(rays: &mut RaySegment, policy: InvalidPolicy) -> Result<usize, JobError> {
    settle(rays.validate(policy == InvalidPolicy::Miss), policy)
}

/// [`validate`]'s verdict under `error` on a whole RAY1 `body`, read through the RAY1
/// reader in segments that are dropped once checked rather than into a second copy of the
/// batch: an asynchronous trace refuses bad rays (422, naming the first and the count)
/// before it is accepted, as a synchronous one does, not as a job that fails later. CPU
/// work: run it on the pool.
pub fn check_body(body: &[u8]) -> Result<(), JobError> {
    const SEGMENT: usize = 4096;
    let malformed = |e: crate::formats::binary::BinaryError| JobError::Invalid {
        field: "rays",
        detail: e.to_string(),
    };
    let mut reader = Ray1Sink::new(usize::MAX, Some(body.len() as u64)).segmented(SEGMENT);
    let (mut bad, mut seen) = (None, 0);
    let mut check = |mut segment: RaySegment| {
        InvalidRays::absorb(&mut bad, segment.validate(false), seen);
        seen += segment.rays.len();
    };
    for piece in body.chunks(SEGMENT * std::mem::size_of::<Ray>()) {
        reader.push(piece).map_err(malformed)?;
        reader.take_ready().for_each(&mut check);
    }
    check(reader.finish_segment().map_err(malformed)?);
    settle(bad, InvalidPolicy::Error).map(|_| ())
}

/// What `policy` makes of the bad rays a check found.
fn settle(bad: Option<InvalidRays>, policy: InvalidPolicy) -> Result<usize, JobError> {
    match bad {
        None => Ok(0),
        Some(bad) if policy == InvalidPolicy::Miss => Ok(bad.count),
        Some(bad) => Err(JobError::InvalidRays(bad)),
    }
}

impl Engine {
    /// Traces validated `rays` against `geometry` as one step of the scheduler (see
    /// [`validate`]); `invalid_rays` is what validation reported, for the report.
    pub fn trace(
        &self,
        geometry: &Geometry,
        rays: &[Ray],
        request: &TraceRequest,
        invalid_rays: usize,
        control: &Control,
    ) -> Result<(HitBody, TraceReport), JobError> {
        let kind = self.batch_accel(geometry, request, rays.len(), 0.0)?;
        // DACRT partitions whatever batch it is given, and the larger the better, so it
        // takes the batch whole where nothing can wait for it (the command line: no
        // scheduler) or where it is under two of its smallest parts. On a large scene a
        // part needs many rays a triangle to trace as fast as the whole batch (BENCHMARKS
        // §40): parts hold at least `DACRT_STEP_RAYS` and `DACRT_PART_RAYS_PER_TRIANGLE`
        // rays a triangle.
        let min_part = DACRT_STEP_RAYS
            .max(DACRT_PART_RAYS_PER_TRIANGLE.saturating_mul(geometry.triangles.len()));
        let whole = if kind.large_batches() {
            !control.wave_seconds().is_finite() || rays.len() < 2 * min_part
        } else {
            rays.len() <= STREAM_SEGMENT_RAYS
        };
        let (body, prepared, trace_seconds) = if whole {
            control.step(|| {
                let prepared = self.batch_structure(geometry, kind, request, rays.len())?;
                let t0 = Instant::now();
                let body = trace_into_body(prepared.accel.as_ref(), rays, request);
                Ok::<_, JobError>((body, prepared, seconds_since(t0)))
            })??
        } else {
            // An accelerator that answers each ray on its own traces a large batch in
            // segments, one step each, as a streamed batch is: work that outranks it (a
            // synchronous trace, for an asynchronous one) runs between them instead of
            // after the whole batch (session 31's review: a 1K trace waited 1.5 s behind
            // an asynchronous 4M one). The answer is the same bytes.
            // DACRT traces a batch of many steps in parts of at least `DACRT_STEP_RAYS`,
            // each sized from the rate so far to last the scheduler's wave: while a
            // request waits that is the smallest part, otherwise parts of about half a
            // second (a 1K trace waited 1,053 ms behind a synchronous 4M-ray DACRT
            // trace taken whole, session 31's review). Closest hits are the same bytes
            // whatever the parts (the contract's order: smallest t, then lowest id).
            let prepared =
                control.step(|| self.batch_structure(geometry, kind, request, rays.len()))??;
            let accel = prepared.accel.as_ref();
            let mut out = BodyWriter::new(request.hit, rays.len());
            let mut trace_seconds = 0.0;
            let mut first = 0;
            let mut rate = None;
            while first < rays.len() {
                let left = rays.len() - first;
                let take = if kind.large_batches() {
                    let want = rate.map_or(min_part, |r: f64| {
                        (r * control.wave_seconds()).min(left as f64) as usize
                    });
                    let want = want.max(min_part);
                    // No part smaller than the smallest is left over for the end.
                    if left - want.min(left) < min_part {
                        left
                    } else {
                        want
                    }
                } else {
                    left.min(STREAM_SEGMENT_RAYS)
                };
                let segment = &rays[first..first + take];
                let seconds = control.step(|| {
                    let t0 = Instant::now();
                    out.trace(accel, segment, request.query, first);
                    seconds_since(t0)
                })?;
                trace_seconds += seconds;
                if seconds > 0.0 {
                    rate = Some(take as f64 / seconds);
                }
                first += take;
                control.progress(first as f64 / rays.len() as f64);
            }
            (out.finish(), prepared, trace_seconds)
        };
        control.progress(1.0);
        let report = self.report(rays.len(), &prepared, trace_seconds, request, invalid_rays);
        Ok((body, report))
    }
}

/// Runs the trace and lays out the answer (see the module docs).
fn trace_into_body(
    accel: &dyn crate::accel::Intersector,
    rays: &[Ray],
    request: &TraceRequest,
) -> HitBody {
    let mut out = BodyWriter::new(request.hit, rays.len());
    out.trace(accel, rays, request.query, 0);
    out.finish()
}

/// A HIT1 body being filled, one range of rays at a time (the whole batch, or the segments
/// of a streamed one).
struct BodyWriter {
    format: HitFormat,
    n: usize,
    body: HitBody,
}

impl BodyWriter {
    /// A body for `n` rays, header written. Its memory is reserved whole but initialised a
    /// range at a time, just before that range is traced, so that a streamed trace clears
    /// each segment's records while they are about to be written (in cache), not the whole
    /// body up front (a cold pass over all of it).
    fn new(format: HitFormat, n: usize) -> BodyWriter {
        let header = hit1_header(format, n);
        let body = match format {
            HitFormat::TPrimUv => {
                let mut records: Vec<Hit> = Vec::with_capacity(n + 1);
                records.push(bytemuck::pod_read_unaligned(&header));
                HitBody::Records(records)
            }
            _ => {
                let mut out = Vec::with_capacity(HEADER_BYTES + format.record_bytes() * n);
                out.extend_from_slice(&header);
                HitBody::Packed(out)
            }
        };
        BodyWriter { format, n, body }
    }

    /// Traces `rays`, the batch's rays from index `first` on, into their records.
    fn trace(
        &mut self,
        accel: &dyn crate::accel::Intersector,
        rays: &[Ray],
        query: Query,
        first: usize,
    ) {
        debug_assert!(first + rays.len() <= self.n);
        let record = self.format.record_bytes();
        match (&mut self.body, self.format) {
            (HitBody::Records(records), _) => {
                debug_assert_eq!(records.len(), 1 + first, "ranges come in order");
                records.resize(1 + first + rays.len(), bytemuck::Zeroable::zeroed());
                let out = &mut records[1 + first..1 + first + rays.len()];
                accel.trace(rays, query, out);
                if cfg!(target_endian = "big") {
                    for x in bytemuck::cast_slice_mut::<Hit, u32>(out) {
                        *x = x.to_le();
                    }
                }
            }
            (HitBody::Packed(bytes), HitFormat::Occluded) => {
                let start = HEADER_BYTES + first;
                debug_assert_eq!(bytes.len(), start, "ranges come in order");
                bytes.resize(start + rays.len(), 0);
                let out = &mut bytes[start..start + rays.len()];
                accel.occluded(rays, out);
                for f in out {
                    *f = u8::from(*f != 0);
                }
            }
            (HitBody::Packed(bytes), format) => {
                let mut hits: Vec<Hit> = bytemuck::zeroed_vec(rays.len());
                accel.trace(rays, query, &mut hits);
                let start = HEADER_BYTES + record * first;
                debug_assert_eq!(bytes.len(), start, "ranges come in order");
                bytes.resize(start + record * rays.len(), 0);
                let out = &mut bytes[start..start + record * rays.len()];
                for (h, o) in hits.iter().zip(out.chunks_exact_mut(record)) {
                    o[..4].copy_from_slice(&h.t.to_le_bytes());
                    if format == HitFormat::TPrim {
                        o[4..8].copy_from_slice(&h.prim.to_le_bytes());
                    }
                }
            }
        }
    }

    fn finish(self) -> HitBody {
        debug_assert_eq!(
            self.body.len(),
            HEADER_BYTES + self.format.record_bytes() * self.n
        );
        self.body
    }
}

/// What the reader of a streamed batch hands the trace: the next rays in order, or the end
/// of a body that arrived whole.
pub enum Arrival {
    /// The next rays of the batch (checked or not as they were read).
    Rays(RaySegment),
    /// Every ray has arrived and the body was well formed.
    End,
}

/// How many rays a streamed batch is traced in at a time: large enough that the pool's
/// threads each get thousands, small enough that the last segment's trace, which cannot
/// overlap the upload, is short.
pub const STREAM_SEGMENT_RAYS: usize = 1 << 16;

/// The fewest rays a DACRT trace of a large batch takes in one scheduler step: DACRT's
/// partitioning near the root costs each part the same whatever its size, and sampling
/// pays only on large parts (BENCHMARKS §22.3), so parts stay large even while work waits
/// (larger still on large scenes: [`DACRT_PART_RAYS_PER_TRIANGLE`]).
pub const DACRT_STEP_RAYS: usize = 1 << 20;

/// The fewest rays a triangle a part of a DACRT batch holds. Over MetalRoughSpheres (1.04M
/// triangles) a 4M-ray batch in parts of 2²⁰ took 30% longer than whole, a 16M one in
/// parts of 3.1M 24% longer; over the saw (198K) and DamagedHelmet (15K), parts of 2²⁰
/// took no longer than the whole 16M batch (BENCHMARKS §40). At 16 rays a triangle a 16M
/// batch over 1M triangles stays whole and the saw's parts hold 3.2M rays.
pub const DACRT_PART_RAYS_PER_TRIANGLE: usize = 16;

impl Engine {
    /// Whether a trace with `request` of `rays` rays over `geometry`, arriving over
    /// `arrival` seconds ([`Engine::arrival`]), can start before the whole batch has
    /// arrived: when the accelerator it resolves to answers each ray on its own (every core
    /// but DACRT's, which partitions the whole batch at once and likes it large), and the
    /// batch is large enough to span several segments. `auto` weighs the arrival: a BVH
    /// traces while the rays upload, DACRT after.
    pub fn streams(
        &self,
        geometry: &Geometry,
        request: &TraceRequest,
        rays: usize,
        arrival: f64,
    ) -> bool {
        let kind = self.batch_kind(geometry, request, rays, arrival);
        rays > STREAM_SEGMENT_RAYS && !kind.large_batches()
    }

    /// Traces a batch of `count` rays that arrives in pieces on `arrivals`, expected over
    /// `arrival` seconds (see [`Engine::streams`], told the same): the structure is
    /// prepared while the first rays upload, and each piece is validated and traced as it
    /// comes, one scheduler step each. The answer is the same, byte for byte, as
    /// [`Engine::trace`] of the whole batch after [`validate`].
    /// With `invalid=error` a bad ray stops the tracing but not the counting, so the error
    /// names the first bad ray and how many there were. If the sender goes away before
    /// [`Arrival::End`] (a broken body) the trace stops with [`JobError::Cancelled`].
    #[allow(clippy::too_many_arguments)]
    pub fn trace_stream(
        &self,
        geometry: &Geometry,
        request: &TraceRequest,
        count: usize,
        arrival: f64,
        arrivals: std::sync::mpsc::Receiver<Arrival>,
        control: &Control,
    ) -> Result<(HitBody, TraceReport), JobError> {
        let kind = self.batch_accel(geometry, request, count, arrival)?;
        let prepared = control.step(|| self.batch_structure(geometry, kind, request, count))??;
        let accel = prepared.accel.as_ref();
        let mut out = BodyWriter::new(request.hit, count);
        let replace = request.invalid == InvalidPolicy::Miss;
        let mut bad: Option<InvalidRays> = None;
        let mut invalid_rays = 0;
        let mut received = 0usize;
        let mut trace_seconds = 0.0;
        loop {
            let mut segment = match arrivals.recv() {
                Ok(Arrival::Rays(segment)) => segment,
                Ok(Arrival::End) => break,
                Err(_) => return Err(JobError::Cancelled),
            };
            if received + segment.rays.len() > count {
                return Err(JobError::Invalid {
                    field: "rays",
                    detail: format!("more than the {count} rays announced"),
                });
            }
            let bad_here = segment.validate(replace);
            let rays = segment.rays;
            invalid_rays += bad_here.map_or(0, |b| b.count);
            InvalidRays::absorb(&mut bad, bad_here, received);
            if replace || bad.is_none() {
                let first = received;
                trace_seconds += control.step(|| {
                    let t0 = Instant::now();
                    out.trace(accel, &rays, request.query, first);
                    seconds_since(t0)
                })?;
                control.progress((first + rays.len()) as f64 / count.max(1) as f64);
            }
            received += rays.len();
        }
        if let (Some(bad), false) = (bad, replace) {
            return Err(JobError::InvalidRays(bad));
        }
        if received != count {
            return Err(JobError::Invalid {
                field: "rays",
                detail: format!("{received} rays arrived of the {count} announced"),
            });
        }
        control.progress(1.0);
        let report = self.report(count, &prepared, trace_seconds, request, invalid_rays);
        Ok((out.finish(), report))
    }

    /// What `auto` resolves a trace of one batch of `rays` rays with `request` to, the last
    /// arriving `arrival` seconds after the trace starts (0 for rays in memory).
    fn batch_kind(
        &self,
        geometry: &Geometry,
        request: &TraceRequest,
        rays: usize,
        arrival: f64,
    ) -> AccelKind {
        self.resolve(
            request.accel,
            geometry,
            request.build,
            request.precision,
            rays,
            1,
            1,
            arrival,
            request.query == Query::Any || request.hit == HitFormat::Occluded,
        )
    }

    /// [`Engine::batch_kind`], after checking the batch against the ray limit.
    fn batch_accel(
        &self,
        geometry: &Geometry,
        request: &TraceRequest,
        rays: usize,
        arrival: f64,
    ) -> Result<AccelKind, JobError> {
        let limit = self.limits().max_rays;
        if rays > limit {
            return Err(JobError::Limit {
                what: "rays",
                value: rays as u64,
                limit: limit as u64,
            });
        }
        Ok(self.batch_kind(geometry, request, rays, arrival))
    }

    /// The structure of `kind` for one batch of `rays` rays (inside a step).
    fn batch_structure(
        &self,
        geometry: &Geometry,
        kind: AccelKind,
        request: &TraceRequest,
        rays: usize,
    ) -> Result<super::engine::Prepared, JobError> {
        self.structure(
            geometry,
            kind,
            request.build,
            request.precision,
            rays,
            1,
            super::Update::Auto,
        )
    }

    fn report(
        &self,
        rays: usize,
        prepared: &super::engine::Prepared,
        trace_seconds: f64,
        request: &TraceRequest,
        invalid_rays: usize,
    ) -> TraceReport {
        TraceReport {
            rays,
            accel: prepared.accel.name(),
            threads: self.threads(),
            build_seconds: prepared.build_seconds,
            trace_seconds,
            mrays_per_s: if trace_seconds > 0.0 {
                rays as f64 / trace_seconds / 1e6
            } else {
                0.0
            },
            query: request.query,
            hit: request.hit,
            precision: request.precision,
            build: request.build,
            simd: crate::simd::selected().name(),
            structure: prepared.source,
            invalid_rays,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_body_check_names_the_first_bad_ray_and_counts_them_all() {
        let mut rays = vec![
            Ray {
                org: [0.0; 3],
                tmin: 0.0,
                dir: [0.0, 0.0, 1.0],
                tmax: f32::INFINITY,
            };
            10_000
        ];
        let body = crate::formats::binary::write_rays(&rays);
        assert!(check_body(&body).is_ok());
        rays[4100].org[1] = f32::NAN;
        rays[9000].dir = [0.0; 3];
        rays[9999].tmin = -1.0;
        let body = crate::formats::binary::write_rays(&rays);
        match check_body(&body) {
            Err(JobError::InvalidRays(bad)) => assert_eq!((bad.first_index, bad.count), (4100, 3)),
            other => panic!("{other:?}"),
        }
        let mut copy = rays.clone();
        match validate(&mut copy, InvalidPolicy::Error) {
            Err(JobError::InvalidRays(bad)) => assert_eq!((bad.first_index, bad.count), (4100, 3)),
            other => panic!("{other:?}"),
        }
    }
    use crate::formats::binary::{read_hits, write_hits};
    use crate::geometry::Triangle;
    use std::sync::Arc;

    fn scene() -> Geometry {
        let tris = vec![
            Triangle {
                v: [[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [0.0, 1.0, 2.0]],
            },
            Triangle {
                v: [[-1.0, -1.0, 3.0], [1.0, -1.0, 3.0], [0.0, 1.0, 3.0]],
            },
        ];
        Geometry {
            key: super::super::GeometryKey::new("t", 1, None),
            triangles: Arc::new(tris),
            forgets: 0,
        }
    }

    fn rays() -> Vec<Ray> {
        (0..50)
            .map(|i| Ray {
                org: [-0.5 + 0.02 * i as f32, -0.2, 0.0],
                tmin: 0.0,
                dir: [0.0, 0.0, 1.0],
                tmax: f32::INFINITY,
            })
            .collect()
    }

    #[test]
    fn every_format_matches_the_reference_encoder() {
        let engine = Engine::new(super::super::EngineOptions {
            threads: 1,
            ..Default::default()
        })
        .unwrap();
        let g = scene();
        let rays = rays();
        let brute =
            crate::accel::build(AccelKind::Brute, &g.triangles, &Default::default()).unwrap();
        for query in [Query::Closest, Query::Any] {
            let mut want = vec![Hit::MISS; rays.len()];
            brute.trace(&rays, query, &mut want);
            for hit in [HitFormat::TPrimUv, HitFormat::TPrim, HitFormat::T] {
                let req = TraceRequest {
                    query,
                    hit,
                    accel: AccelKind::Brute,
                    ..Default::default()
                };
                let (body, report) = engine
                    .trace(&g, &rays, &req, 0, &engine.detached())
                    .unwrap();
                assert_eq!(body.as_ref(), &write_hits(&want, hit)[..], "{hit:?}");
                assert_eq!(report.accel, "brute");
                assert!(read_hits(body.as_ref()).is_ok());
            }
        }
        let req = TraceRequest {
            hit: HitFormat::Occluded,
            accel: AccelKind::Mbvh8,
            ..Default::default()
        };
        let (body, _) = engine
            .trace(&g, &rays, &req, 0, &engine.detached())
            .unwrap();
        let mut want = vec![Hit::MISS; rays.len()];
        brute.trace(&rays, Query::Any, &mut want);
        assert_eq!(body.as_ref(), &write_hits(&want, HitFormat::Occluded)[..]);
    }

    /// `brute`'s closest hits of `rays` over `g`: the reference answer.
    fn brute_closest(g: &Geometry, rays: &[Ray]) -> Vec<Hit> {
        let brute =
            crate::accel::build(AccelKind::Brute, &g.triangles, &Default::default()).unwrap();
        let mut want = vec![Hit::MISS; rays.len()];
        brute.trace(rays, Query::Closest, &mut want);
        want
    }

    /// A control under `engine`'s scheduler (a job of priority 50, so its waves are
    /// finite), with the progress it reports logged.
    fn scheduled(engine: &Engine) -> (Control, Arc<std::sync::Mutex<Vec<f64>>>) {
        let seen = Arc::new(std::sync::Mutex::new(Vec::new()));
        let log = Arc::clone(&seen);
        let ticket = engine.scheduler().admit(50, false).unwrap();
        let control = engine.control(
            Default::default(),
            Some(Arc::new(move |p| log.lock().unwrap().push(p))),
            ticket,
        );
        (control, seen)
    }

    /// A batch larger than a segment, traced by a per-ray core in segments (one step
    /// each): the same bytes as `brute`'s answer, and progress reported along the way.
    #[test]
    fn a_large_batch_traced_in_segments_answers_the_same_bytes() {
        let engine = Engine::new(Default::default()).unwrap();
        let g = scene();
        let n = 2 * STREAM_SEGMENT_RAYS + 123;
        let rays: Vec<Ray> = (0..n)
            .map(|i| Ray {
                org: [-1.2 + 2.4 * (i % 997) as f32 / 997.0, -0.2, 0.0],
                tmin: 0.0,
                dir: [0.0, 0.01 * (i % 7) as f32, 1.0],
                tmax: f32::INFINITY,
            })
            .collect();
        let want = brute_closest(&g, &rays);
        let (control, seen) = scheduled(&engine);
        let req = TraceRequest {
            accel: AccelKind::Mbvh8,
            hit: HitFormat::TPrimUv,
            ..Default::default()
        };
        let (body, _) = engine.trace(&g, &rays, &req, 0, &control).unwrap();
        assert_eq!(body.as_ref(), &write_hits(&want, HitFormat::TPrimUv)[..]);
        let seen = seen.lock().unwrap();
        assert!(
            seen.len() >= 3 && seen.windows(2).all(|w| w[0] <= w[1]),
            "{seen:?}"
        );
    }

    /// A DACRT batch of several steps, traced under a scheduler, in parts: the same bytes
    /// as `brute`'s closest hits, progress along the way; without a scheduler (the
    /// command line) it is one part.
    #[test]
    fn a_large_dacrt_batch_traced_in_parts_answers_the_same_bytes() {
        let engine = Engine::new(Default::default()).unwrap();
        let g = scene();
        let n = 2 * DACRT_STEP_RAYS + 4321;
        let rays = many_rays(n);
        let want = brute_closest(&g, &rays);
        let want = write_hits(&want, HitFormat::TPrimUv);
        let req = TraceRequest {
            accel: AccelKind::DacrtSampled,
            hit: HitFormat::TPrimUv,
            ..Default::default()
        };
        let (control, seen) = scheduled(&engine);
        let (body, _) = engine.trace(&g, &rays, &req, 0, &control).unwrap();
        assert_eq!(body.as_ref(), &want[..]);
        let seen = seen.lock().unwrap().clone();
        assert!(
            seen.len() >= 2 && seen[0] < 1.0 && seen.windows(2).all(|w| w[0] <= w[1]),
            "{seen:?}"
        );
        // The first part is the smallest a DACRT step takes.
        assert!(
            (seen[0] - DACRT_STEP_RAYS as f64 / n as f64).abs() < 1e-12,
            "{seen:?}"
        );
        let (whole, _) = engine
            .trace(&g, &rays, &req, 0, &engine.detached())
            .unwrap();
        assert_eq!(whole.as_ref(), &want[..]);
    }

    #[test]
    fn a_second_trace_finds_the_structure_cached() {
        let engine = Engine::new(Default::default()).unwrap();
        let g = scene();
        let req = TraceRequest {
            accel: AccelKind::Mbvh8,
            ..Default::default()
        };
        let (_, first) = engine
            .trace(&g, &rays(), &req, 0, &engine.detached())
            .unwrap();
        let (_, second) = engine
            .trace(&g, &rays(), &req, 0, &engine.detached())
            .unwrap();
        assert_eq!(first.structure, Source::Built);
        assert_eq!(second.structure, Source::Cached);
        assert_eq!(second.build_seconds, 0.0);
    }

    /// `n` rays over the test scene, some hitting, some missing, in a fan.
    fn many_rays(n: usize) -> Vec<Ray> {
        (0..n)
            .map(|i| {
                let a = i as f32 / n as f32;
                Ray {
                    org: [-1.5 + 3.0 * a, -0.2 + 0.3 * (i % 7) as f32 / 7.0, 0.0],
                    tmin: 0.0,
                    dir: [0.01 * (i % 5) as f32, 0.0, 1.0],
                    tmax: if i % 11 == 0 { 2.5 } else { f32::INFINITY },
                }
            })
            .collect()
    }

    fn streamed(
        engine: &Engine,
        g: &Geometry,
        req: &TraceRequest,
        rays: &[Ray],
        pieces: usize,
        end: bool,
    ) -> Result<(HitBody, TraceReport), JobError> {
        let (tx, rx) = std::sync::mpsc::channel();
        for piece in rays.chunks(pieces) {
            tx.send(Arrival::Rays(RaySegment::unchecked(piece.to_vec())))
                .unwrap();
        }
        if end {
            tx.send(Arrival::End).unwrap();
        }
        drop(tx);
        engine.trace_stream(g, req, rays.len(), 0.0, rx, &engine.detached())
    }

    #[test]
    fn a_streamed_trace_answers_what_the_whole_batch_does() {
        let engine = Engine::new(super::super::EngineOptions {
            threads: 2,
            ..Default::default()
        })
        .unwrap();
        let g = scene();
        let rays = many_rays(1000);
        for accel in [AccelKind::Brute, AccelKind::Mbvh8, AccelKind::Bvh2] {
            for hit in [
                HitFormat::TPrimUv,
                HitFormat::TPrim,
                HitFormat::T,
                HitFormat::Occluded,
            ] {
                for query in [Query::Closest, Query::Any] {
                    let req = TraceRequest {
                        accel,
                        hit,
                        query,
                        ..Default::default()
                    };
                    let (whole, _) = engine
                        .trace(&g, &rays, &req, 0, &engine.detached())
                        .unwrap();
                    for pieces in [1, 37, 256, 1000] {
                        let (body, report) =
                            streamed(&engine, &g, &req, &rays, pieces, true).unwrap();
                        assert_eq!(body.as_ref(), whole.as_ref(), "{accel:?} {hit:?} {pieces}");
                        assert_eq!(report.rays, 1000);
                    }
                }
            }
        }
    }

    #[test]
    fn a_streamed_trace_refuses_bad_rays_and_broken_bodies() {
        let engine = Engine::new(Default::default()).unwrap();
        let g = scene();
        let mut rays = many_rays(300);
        rays[130].dir = [0.0; 3];
        rays[20].org[0] = f32::INFINITY;
        rays[299].tmin = -1.0;
        let req = TraceRequest {
            accel: AccelKind::Mbvh8,
            ..Default::default()
        };
        match streamed(&engine, &g, &req, &rays, 64, true) {
            Err(JobError::InvalidRays(bad)) => assert_eq!((bad.first_index, bad.count), (20, 3)),
            other => panic!("{:?}", other.map(|(_, r)| r)),
        }
        // Under invalid=miss the bad rays are misses, as in a whole-batch trace.
        let miss = TraceRequest {
            invalid: InvalidPolicy::Miss,
            ..req
        };
        let mut fixed = rays.clone();
        let count = validate(&mut fixed, InvalidPolicy::Miss).unwrap();
        let (whole, _) = engine
            .trace(&g, &fixed, &miss, count, &engine.detached())
            .unwrap();
        let (body, report) = streamed(&engine, &g, &miss, &rays, 64, true).unwrap();
        assert_eq!(body.as_ref(), whole.as_ref());
        assert_eq!(report.invalid_rays, 3);
        // A body that broke off (the sender went away before the end) traces nothing more.
        let good = many_rays(300);
        assert!(matches!(
            streamed(&engine, &g, &req, &good, 64, false),
            Err(JobError::Cancelled)
        ));
        // Fewer rays than announced.
        let (tx, rx) = std::sync::mpsc::channel();
        tx.send(Arrival::Rays(RaySegment::unchecked(good[..100].to_vec())))
            .unwrap();
        tx.send(Arrival::End).unwrap();
        assert!(matches!(
            engine.trace_stream(&g, &req, 300, 0.0, rx, &engine.detached()),
            Err(JobError::Invalid { field: "rays", .. })
        ));
    }

    #[test]
    fn invalid_rays_are_refused_or_missed() {
        let mut rays = rays();
        rays[7].dir = [0.0; 3];
        rays[9].org[1] = f32::NAN;
        match validate(&mut rays.clone(), InvalidPolicy::Error) {
            Err(JobError::InvalidRays(bad)) => assert_eq!((bad.first_index, bad.count), (7, 2)),
            other => panic!("{other:?}"),
        }
        assert_eq!(validate(&mut rays, InvalidPolicy::Miss).unwrap(), 2);
    }

    #[test]
    fn the_query_string_names_are_the_cli_names() {
        let r: TraceRequest =
            serde_json::from_str(r#"{"accel":"dacrt-sampled","hit":"t_prim","invalid":"miss"}"#)
                .unwrap();
        assert_eq!(r.accel, AccelKind::DacrtSampled);
        assert_eq!(r.hit, HitFormat::TPrim);
        assert_eq!(r.invalid, InvalidPolicy::Miss);
        assert!(serde_json::from_str::<TraceRequest>(r#"{"acel":"brute"}"#).is_err());
    }
}
