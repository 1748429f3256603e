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
use crate::formats::binary::{hit1_header, HEADER_BYTES};
use crate::formats::HitFormat;
use crate::geometry::{Hit, Ray};

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
    let replace = policy == InvalidPolicy::Miss;
    match Ray::validate_batch(rays, replace) {
        None => Ok(0),
        Some(bad) if replace => Ok(bad.count),
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
        let limit = self.limits().max_rays;
        if rays.len() > limit {
            return Err(JobError::Limit {
                what: "rays",
                value: rays.len() as u64,
                limit: limit as u64,
            });
        }
        let kind = self.resolve(
            request.accel,
            geometry,
            request.build,
            request.precision,
            rays.len(),
            1,
        );
        let (body, accel, prepared_seconds, source, trace_seconds) = control.step(|| {
            let prepared = self.structure(
                geometry,
                kind,
                request.build,
                request.precision,
                rays.len(),
                1,
            )?;
            let t0 = Instant::now();
            let body = trace_into_body(prepared.accel.as_ref(), rays, request);
            let trace_seconds = seconds_since(t0);
            Ok::<_, JobError>((
                body,
                prepared.accel.name(),
                prepared.build_seconds,
                prepared.source,
                trace_seconds,
            ))
        })??;
        control.progress(1.0);
        let report = TraceReport {
            rays: rays.len(),
            accel,
            threads: self.threads(),
            build_seconds: prepared_seconds,
            trace_seconds,
            mrays_per_s: if trace_seconds > 0.0 {
                rays.len() as f64 / trace_seconds / 1e6
            } else {
                0.0
            },
            query: request.query,
            hit: request.hit,
            precision: request.precision,
            build: request.build,
            simd: crate::simd::selected().name(),
            structure: source,
            invalid_rays,
        };
        Ok((body, report))
    }
}

/// Runs the trace and lays out the answer (see the module docs).
fn trace_into_body(
    accel: &dyn crate::accel::Intersector,
    rays: &[Ray],
    request: &TraceRequest,
) -> HitBody {
    let n = rays.len();
    let header = hit1_header(request.hit, n);
    match request.hit {
        HitFormat::Occluded => {
            let mut out = vec![0u8; HEADER_BYTES + n];
            out[..HEADER_BYTES].copy_from_slice(&header);
            accel.occluded(rays, &mut out[HEADER_BYTES..]);
            for f in &mut out[HEADER_BYTES..] {
                *f = u8::from(*f != 0);
            }
            HitBody::Packed(out)
        }
        HitFormat::TPrimUv => {
            let mut records: Vec<Hit> = bytemuck::zeroed_vec(n + 1);
            accel.trace(rays, request.query, &mut records[1..]);
            if cfg!(target_endian = "big") {
                for x in bytemuck::cast_slice_mut::<Hit, u32>(&mut records[1..]) {
                    *x = x.to_le();
                }
            }
            bytemuck::cast_slice_mut::<Hit, u8>(&mut records[..1]).copy_from_slice(&header);
            HitBody::Records(records)
        }
        format => {
            let mut hits: Vec<Hit> = bytemuck::zeroed_vec(n);
            accel.trace(rays, request.query, &mut hits);
            let record = format.record_bytes();
            let mut out = Vec::with_capacity(HEADER_BYTES + record * n);
            out.extend_from_slice(&header);
            for h in &hits {
                out.extend_from_slice(&h.t.to_le_bytes());
                if format == HitFormat::TPrim {
                    out.extend_from_slice(&h.prim.to_le_bytes());
                }
            }
            HitBody::Packed(out)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
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
