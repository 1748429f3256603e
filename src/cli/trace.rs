//! `rayd trace SCENE --rays IN --out OUT`: one batch, timed as the contract defines, run
//! by the same engine as the service's trace route.

use std::io::Read;
use std::sync::Arc;

use super::{CliError, CoreArgs, PathArg};
use crate::accel::Query;
use crate::formats::binary::Ray1Sink;
use crate::formats::{FormatError, HitFormat};
use crate::geometry::Ray;
use crate::jobs::{trace, Geometry, GeometryKey, InvalidPolicy, JobError, TraceRequest};

#[derive(clap::Args, Debug)]
pub(super) struct TraceArgs {
    /// Scene file (.glb, .gltf or .tri).
    scene: PathArg,
    /// RAY1 input.
    #[arg(long)]
    rays: PathArg,
    /// HIT1 output.
    #[arg(long)]
    out: PathArg,
    /// Which hit a ray reports.
    #[arg(long, value_enum, default_value_t = Query::Closest)]
    query: Query,
    /// Hit fields to write.
    #[arg(long, value_enum, default_value_t = HitFormat::TPrimUv)]
    hit: HitFormat,
    /// What to do with invalid rays: refuse the batch, or answer them as misses.
    #[arg(long, value_enum, default_value_t = InvalidPolicy::Error)]
    invalid: InvalidPolicy,
    #[command(flatten)]
    core: CoreArgs,
}

/// Reads a RAY1 file straight into ray memory, one chunk at a time (no second copy).
pub(super) fn read_ray_file(path: &std::path::Path) -> Result<Vec<Ray>, CliError> {
    let io = |source| FormatError::Io {
        path: path.display().to_string(),
        source,
    };
    let mut file = std::fs::File::open(path).map_err(io)?;
    let meta = file.metadata().map_err(io)?;
    // A pipe's or a device's length is no body length: read what arrives.
    let len = meta.is_file().then_some(meta.len());
    let mut sink = Ray1Sink::new(usize::MAX, len);
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = file.read(&mut buf).map_err(io)?;
        if n == 0 {
            break;
        }
        sink.push(&buf[..n])
            .map_err(|e| FormatError::from(e).in_file(path))?;
    }
    Ok(sink
        .finish()
        .map_err(|e| FormatError::from(e).in_file(path))?)
}

pub(super) fn run(a: TraceArgs) -> Result<serde_json::Value, CliError> {
    super::refuse_overwriting(&a.out, &[&a.scene, &a.rays])?;
    let scene = crate::formats::load_scene(&a.scene, &a.core.load_options()?)?;
    let mut rays = read_ray_file(&a.rays)?;
    let invalid = trace::validate(&mut rays, a.invalid).map_err(|e| match e {
        JobError::InvalidRays(detail) => CliError::InvalidRays {
            path: a.rays.display().to_string(),
            detail,
        },
        e => e.into(),
    })?;
    let engine = a.core.engine()?;
    let geometry = Geometry {
        key: GeometryKey::new(&a.scene.display().to_string(), 1, a.core.time),
        triangles: Arc::new(scene.triangles),
        forgets: engine.forgets(),
    };
    let request = TraceRequest {
        query: a.query,
        hit: a.hit,
        accel: a.core.accel,
        build: a.core.build,
        precision: a.core.precision,
        invalid: a.invalid,
    };
    let (body, report) = engine.trace(&geometry, &rays, &request, invalid, &engine.detached())?;
    super::write_whole(&a.out, body.as_ref()).map_err(|source| FormatError::Io {
        path: a.out.display().to_string(),
        source,
    })?;
    Ok(serde_json::to_value(report).expect("a report serialises"))
}
