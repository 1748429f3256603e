//! `rayd trace SCENE --rays IN --out OUT`: one batch, timed as the contract defines.

use std::time::Instant;

use serde_json::json;

use super::{parse_hit, parse_query, CliError, CoreArgs, PathArg};
use crate::accel::auto::Job;
use crate::accel::Query;
use crate::formats::{binary, HitFormat};
use crate::geometry::{Hit, Ray};

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
    /// closest or any.
    #[arg(long, default_value = "closest", value_parser = parse_query)]
    query: Query,
    /// Hit fields to write: t_prim_uv, t_prim, t or occluded.
    #[arg(long, default_value = "t_prim_uv", value_parser = parse_hit)]
    hit: HitFormat,
    /// What to do with invalid rays: error (refuse the batch) or miss.
    #[arg(long, default_value = "error", value_parser = ["error", "miss"])]
    invalid: String,
    #[command(flatten)]
    core: CoreArgs,
}

pub(super) fn run(a: TraceArgs) -> Result<serde_json::Value, CliError> {
    let scene = crate::formats::load_scene(&a.scene, &a.core.load_options()?)?;
    let mut rays = binary::read_rays(&crate::formats::read_file(&a.rays)?)?;
    let replace = a.invalid == "miss";
    if let Some(bad) = Ray::validate_batch(&mut rays, replace) {
        if !replace {
            return Err(CliError::InvalidRays {
                path: a.rays.display().to_string(),
                detail: bad,
            });
        }
    }
    let pool = a.core.pool()?;
    let threads = pool.current_num_threads();
    let options = a.core.build_options(threads);
    let kind = a.core.accel.resolve(&Job::batch(
        rays.len(),
        scene.triangles.len(),
        threads,
        options.quality,
    ));
    let (accel, build_seconds, body, trace_seconds) = pool.install(|| {
        let t0 = Instant::now();
        let accel = crate::accel::build(kind, &scene.triangles, &options)?;
        let build_seconds = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        // Only the fields asked for are computed: `occluded` needs no hit records at all.
        let body = if a.hit == HitFormat::Occluded {
            let mut flags = vec![0u8; rays.len()];
            accel.occluded(&rays, &mut flags);
            let trace_seconds = t1.elapsed().as_secs_f64();
            (binary::write_occluded(&flags), trace_seconds)
        } else {
            let mut hits = vec![Hit::MISS; rays.len()];
            accel.trace(&rays, a.query, &mut hits);
            let trace_seconds = t1.elapsed().as_secs_f64();
            (binary::write_hits(&hits, a.hit), trace_seconds)
        };
        Ok::<_, CliError>((accel, build_seconds, body.0, body.1))
    })?;
    std::fs::write(&a.out, body).map_err(|source| crate::formats::FormatError::Io {
        path: a.out.display().to_string(),
        source,
    })?;
    let mrays = if trace_seconds > 0.0 {
        rays.len() as f64 / trace_seconds / 1e6
    } else {
        0.0
    };
    Ok(json!({
        "rays": rays.len(),
        "accel": accel.name(),
        "threads": threads,
        "build_seconds": build_seconds,
        "trace_seconds": trace_seconds,
        "mrays_per_s": mrays,
        "query": a.query.name(),
        "hit": a.hit.name(),
        "precision": a.core.precision.name(),
        "build": a.core.build.name(),
        "simd": crate::simd::selected().name(),
    }))
}
