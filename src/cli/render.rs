//! `rayd render SCENE -o OUT.png|OUT.exr`.

use std::time::Instant;

use serde_json::json;

use super::{parse_integrator, CameraArgs, CliError, CoreArgs, PathArg};
use crate::accel::auto::{Geometry, Job};
use crate::render::camera::ViewCamera;
use crate::render::image::{encode, ImageFormat};
use crate::render::{Integrator, RenderOptions};

#[derive(clap::Args, Debug)]
pub(super) struct RenderArgs {
    /// Scene file (.glb, .gltf or .tri).
    scene: PathArg,
    /// Output image; the extension (.png or .exr) picks the format.
    #[arg(short = 'o', long = "out")]
    out: PathArg,
    /// Image width in pixels.
    #[arg(long, default_value_t = 640)]
    width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 480)]
    height: u32,
    /// Samples per pixel.
    #[arg(long, default_value_t = 1)]
    spp: u32,
    /// primary, normals, ao or path.
    #[arg(long, default_value = "primary", value_parser = parse_integrator)]
    integrator: Integrator,
    /// Diffuse bounces of the path integrator.
    #[arg(long, default_value_t = 2)]
    bounces: u32,
    #[command(flatten)]
    camera: CameraArgs,
    /// Seed of the sampling.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[command(flatten)]
    core: CoreArgs,
}

/// Largest image side accepted, so that a typo cannot ask for terabytes.
const MAX_SIDE: u32 = 16384;

pub(super) fn run(a: RenderArgs) -> Result<serde_json::Value, CliError> {
    let format = ImageFormat::from_path(&a.out).ok_or_else(|| {
        CliError::Usage(format!(
            "{}: the output must end in .png or .exr",
            a.out.display()
        ))
    })?;
    if a.width == 0 || a.height == 0 || a.width > MAX_SIDE || a.height > MAX_SIDE {
        return Err(CliError::Usage(format!(
            "image size {}x{} is outside 1..={MAX_SIDE} per side",
            a.width, a.height
        )));
    }
    if a.spp == 0 || a.spp > 65536 {
        return Err(CliError::Usage(format!(
            "--spp {} is outside 1..=65536",
            a.spp
        )));
    }
    let scene = crate::formats::load_scene(&a.scene, &a.core.load_options()?)?;
    let aspect = a.width as f64 / a.height as f64;
    let camera = ViewCamera::choose(&a.camera.choice(), &scene, aspect)?;
    let diagonal = scene.bounds().map(|b| b.diagonal()).unwrap_or(1.0);
    let pool = a.core.pool()?;
    let threads = pool.current_num_threads();
    let options = a.core.build_options(threads);
    // One batch per sample for the camera rays, plus one per AO sample or path bounce.
    let per_sample = match a.integrator {
        Integrator::Ao => 2,
        Integrator::Path => 1 + a.bounces as usize,
        _ => 1,
    };
    let batches = a.spp as usize * per_sample;
    let kind = a.core.accel.resolve(&Job {
        rays: a.width as usize * a.height as usize * batches,
        batches,
        triangles: scene.triangles.len(),
        threads,
        quality: options.quality,
        geometry: Geometry::New,
    });
    let opts = RenderOptions {
        width: a.width,
        height: a.height,
        spp: a.spp,
        integrator: a.integrator,
        bounces: a.bounces,
        seed: a.seed,
    };
    let (accel_name, build_seconds, image, stats, render_seconds) = pool.install(|| {
        let t0 = Instant::now();
        let accel = crate::accel::build(kind, &scene.triangles, &options)?;
        let build_seconds = t0.elapsed().as_secs_f64();
        let t1 = Instant::now();
        let (image, stats) =
            crate::render::render(&scene.triangles, accel.as_ref(), &camera, &opts, diagonal);
        Ok::<_, CliError>((
            accel.name(),
            build_seconds,
            image,
            stats,
            t1.elapsed().as_secs_f64(),
        ))
    })?;
    let bytes = encode(&image, format)?;
    std::fs::write(&a.out, bytes).map_err(|source| crate::formats::FormatError::Io {
        path: a.out.display().to_string(),
        source,
    })?;
    Ok(json!({
        "out": a.out.display().to_string(),
        "width": a.width,
        "height": a.height,
        "spp": a.spp,
        "integrator": a.integrator.name(),
        "accel": accel_name,
        "threads": threads,
        "rays": stats.rays,
        "build_seconds": build_seconds,
        "trace_seconds": stats.trace_seconds,
        "render_seconds": render_seconds,
    }))
}
