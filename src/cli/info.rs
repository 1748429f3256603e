//! `rayd info SCENE`.

use serde_json::json;

use super::{CliError, PathArg};
use crate::accel::{AccelKind, BuildQuality, Precision};

#[derive(clap::Args, Debug)]
pub(super) struct InfoArgs {
    /// Scene file (.glb, .gltf or .tri).
    scene: PathArg,
    /// Also build this accelerator and report its build time, memory and statistics.
    #[arg(long, value_enum)]
    accel: Option<AccelKind>,
    /// Build quality of the accelerator: fast, sah, sbvh.
    #[arg(long, default_value = "sah", value_enum)]
    build: BuildQuality,
    /// Ray/triangle test of the accelerator: fast or watertight.
    #[arg(long, default_value = "watertight", value_enum)]
    precision: Precision,
    /// Threads for the build; 0 or absent: all cores (at most 1024).
    #[arg(long, default_value_t = 0, value_parser = super::threads_arg())]
    threads: usize,
    /// Animation time in seconds (absent: the file's static pose).
    #[arg(long, allow_negative_numbers = true)]
    time: Option<f64>,
}

pub(super) fn run(a: InfoArgs) -> Result<serde_json::Value, CliError> {
    // With shading data, so that `bytes_by_part` tells what a render would hold; `bytes`
    // stays the memory held for tracing.
    let scene = crate::formats::load_scene_with(
        &a.scene,
        &super::load_options(a.time)?,
        crate::formats::Parts::Shading,
    )?;
    let mut bytes = scene.bytes();
    let parts = scene.bytes_by_part();
    let mut by_part = json!({
        "positions": parts.positions,
        "attributes": parts.attributes,
        "textures": parts.textures,
        "animation": parts.animation,
    });
    // The contract's fields, as the service's scene summaries carry them.
    let mut out = crate::app::scene_info(&scene);
    if let Some(kind) = a.accel {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(a.threads)
            .build()?;
        // What `auto` would run for a frame of a million rays.
        let kind = kind.resolve(&crate::accel::auto::Job::batch(
            1 << 20,
            scene.triangles.len(),
            pool.current_num_threads(),
            a.build,
        ));
        let options = crate::accel::BuildOptions {
            quality: a.build,
            precision: a.precision,
            threads: pool.current_num_threads(),
            dacrt: crate::accel::dacrt::DacrtTuning::from_env(),
        };
        let t0 = std::time::Instant::now();
        let accel = pool.install(|| crate::accel::build(kind, &scene.triangles, &options))?;
        let build_seconds = t0.elapsed().as_secs_f64();
        bytes += accel.bytes();
        by_part["structures"] = json!(accel.bytes());
        out["accel"] = json!({
            "name": accel.name(),
            "build": a.build.name(),
            "threads": options.threads,
            "build_seconds": build_seconds,
            "bytes": accel.bytes(),
            "stats": accel.stats(),
        });
    }
    out["bytes"] = json!(bytes);
    out["bytes_by_part"] = by_part;
    Ok(out)
}
