//! `rayd render SCENE -o OUT.png|OUT.exr`, run by the same engine as the service's render
//! jobs.

use std::sync::Arc;

use serde_json::json;

use super::{CameraArgs, CliError, CoreArgs, PathArg};
use crate::formats::FormatError;
use crate::jobs::render::{frame_times, FrameInput};
use crate::jobs::{Geometry, GeometryKey, RenderRequest};
use crate::render::image::ImageFormat;
use crate::render::Integrator;

#[derive(clap::Args, Debug)]
pub(super) struct RenderArgs {
    /// Scene file (.glb, .gltf or .tri).
    scene: PathArg,
    /// Output image; the extension (.png or .exr) picks the format. With --frames, a run
    /// of `#` in the name is replaced by the zero-padded frame number.
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
    /// What a pixel shows.
    #[arg(long, value_enum, default_value_t = Integrator::Primary)]
    integrator: Integrator,
    /// Diffuse bounces of the path integrator.
    #[arg(long, default_value_t = 2)]
    bounces: u32,
    #[command(flatten)]
    camera: CameraArgs,
    /// Seed of the sampling.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Animation times START:END:STEP (seconds): one image per time.
    #[arg(long, conflicts_with = "time")]
    frames: Option<String>,
    #[command(flatten)]
    core: CoreArgs,
}

/// `walk-####.png`, frame 7 → `walk-0007.png`; a name without `#` is used as it is.
fn frame_name(pattern: &str, k: usize) -> String {
    let Some(start) = pattern.find('#') else {
        return pattern.to_string();
    };
    let len = pattern[start..].chars().take_while(|&c| c == '#').count();
    format!(
        "{}{:0len$}{}",
        &pattern[..start],
        k,
        &pattern[start + len..],
        len = len
    )
}

fn parse_frames(s: &str, limit: usize) -> Result<Vec<f64>, CliError> {
    let parts: Vec<f64> = s
        .split(':')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| CliError::Usage(format!("--frames {s}: expected START:END:STEP")))?;
    let [start, end, step] = parts[..] else {
        return Err(CliError::Usage(format!(
            "--frames {s}: expected START:END:STEP"
        )));
    };
    Ok(frame_times(start, end, step, limit)?)
}

pub(super) fn run(a: RenderArgs) -> Result<serde_json::Value, CliError> {
    let format = ImageFormat::from_path(&a.out).ok_or_else(|| {
        CliError::Usage(format!(
            "{}: the output must end in .png or .exr",
            a.out.display()
        ))
    })?;
    let engine = a.core.engine()?;
    let times: Vec<Option<f64>> = match &a.frames {
        Some(f) => parse_frames(f, engine.limits().max_frames)?
            .into_iter()
            .map(Some)
            .collect(),
        None => vec![a.core.time],
    };
    let request = RenderRequest {
        width: a.width,
        height: a.height,
        spp: a.spp,
        integrator: a.integrator,
        bounces: a.bounces,
        camera: a.camera.choice(),
        seed: a.seed,
        format,
        accel: a.core.accel,
        build: a.core.build,
        precision: a.core.precision,
    };
    request.check(engine.limits(), times.len())?;
    let path = a.scene.display().to_string();
    // Parsed once; each frame's time re-poses it through the scene's rig (bit-identical to
    // loading the file at that time), so a sequence never reads the file again.
    super::load_options(a.core.time)?;
    let scene = crate::formats::load_scene(&a.scene, &Default::default())?;
    let frame_at = |time: Option<f64>| {
        let (triangles, cameras) = match time {
            None => (scene.triangles.clone(), scene.cameras.clone()),
            Some(t) => {
                let pose = scene
                    .evaluate(t, crate::scene::Compute::Positions)
                    .map_err(|e| crate::jobs::JobError::Geometry(e.to_string()))?;
                (pose.triangles, pose.cameras)
            }
        };
        Ok(FrameInput {
            geometry: Geometry {
                key: GeometryKey::new(&path, 1, time),
                triangles: Arc::new(triangles),
            },
            cameras: Arc::new(cameras),
        })
    };
    let pattern = a.out.display().to_string();
    let mut written = Vec::new();
    let report = engine.render(
        &request,
        &times,
        &frame_at,
        &engine.detached(),
        &mut |k, bytes| {
            let out = if a.frames.is_some() {
                frame_name(&pattern, k)
            } else {
                pattern.clone()
            };
            std::fs::write(&out, bytes).map_err(|source| {
                crate::jobs::JobError::Geometry(
                    FormatError::Io {
                        path: out.clone(),
                        source,
                    }
                    .to_string(),
                )
            })?;
            written.push(out);
            Ok(())
        },
    )?;
    let first = &report.frames[0];
    let mut out = json!({
        "out": written[0],
        "width": a.width,
        "height": a.height,
        "spp": a.spp,
        "integrator": a.integrator,
        "accel": first.accel,
        "threads": report.threads,
        "rays": report.rays,
        "build_seconds": report.build_seconds,
        "trace_seconds": report.trace_seconds,
        "render_seconds": report.render_seconds,
    });
    if a.frames.is_some() {
        out["outputs"] = json!(written);
        out["frames"] = serde_json::to_value(&report.frames).expect("serialises");
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::frame_name;

    #[test]
    fn frame_names_are_zero_padded_like_blender() {
        assert_eq!(frame_name("walk-####.png", 7), "walk-0007.png");
        assert_eq!(frame_name("f#.exr", 12), "f12.exr");
        assert_eq!(frame_name("still.png", 3), "still.png");
    }
}
