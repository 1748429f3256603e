//! `rayd info SCENE`.

use serde_json::json;

use super::{CliError, CoreArgs, PathArg};

#[derive(clap::Args, Debug)]
pub(super) struct InfoArgs {
    /// Scene file (.glb, .gltf or .tri).
    scene: PathArg,
    #[command(flatten)]
    core: CoreArgs,
    /// Also build the accelerator named by --accel and report its memory.
    #[arg(long = "with-accel", default_value_t = false)]
    with_accel: bool,
}

pub(super) fn run(a: InfoArgs) -> Result<serde_json::Value, CliError> {
    let scene = crate::formats::load_scene(&a.scene, &a.core.load_options()?)?;
    let bounds = scene.bounds().map(|b| json!({"min": b.min, "max": b.max}));
    let animations: Vec<_> = scene
        .animations
        .iter()
        .map(|an| json!({"name": an.name, "duration": an.duration}))
        .collect();
    let mut bytes = scene.bytes();
    let mut out = json!({
        "triangles": scene.triangles.len(),
        "bounds": bounds,
        "meshes": scene.meshes,
        "animations": animations,
        "cameras": scene.cameras.len(),
        "simd": crate::simd::selected().name(),
    });
    if a.with_accel {
        let kind = a.core.accel.resolve(0, scene.triangles.len());
        let pool = a.core.pool()?;
        let options = crate::accel::BuildOptions {
            quality: a.core.build,
            precision: a.core.precision,
            threads: a.core.threads,
        };
        let accel = pool.install(|| crate::accel::build(kind, &scene.triangles, &options))?;
        bytes += accel.bytes();
        out["accel"] = json!({"name": accel.name(), "bytes": accel.bytes()});
    }
    out["bytes"] = json!(bytes);
    Ok(out)
}
