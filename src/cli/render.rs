//! `rayd render SCENE -o OUT.png|OUT.exr`, run by the same engine as the service's render
//! jobs.

use serde_json::json;

use super::{CameraArgs, CliError, CoreArgs, PathArg};
use crate::formats::{FormatError, Parts};
use crate::jobs::render::{frame_times, FrameInput};
use crate::jobs::{GeometryKey, RenderRequest, Update};
use crate::render::image::ImageFormat;
use crate::render::{Aov, AovSet, Integrator};

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
    /// Largest number of surface scatterings of a `path` (1: direct light only; 0: emitters
    /// and the sky alone).
    #[arg(long, default_value_t = 2)]
    bounces: u32,
    #[command(flatten)]
    camera: CameraArgs,
    /// Seed of the sampling.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Russian roulette of `path`: paths may end at random from this scattering on (1 or
    /// later); off when not given.
    #[arg(long)]
    roulette: Option<u32>,
    /// Radiance R,G,B of the constant environment (`path`).
    #[arg(long, value_parser = super::parse_vec3, default_value = "1,1,1", allow_hyphen_values = true)]
    sky: [f64; 3],
    /// AOV channels to add to an EXR, comma-separated: depth, normal, albedo, prim.
    #[arg(long, value_delimiter = ',')]
    aov: Vec<Aov>,
    /// Animation times START:END:STEP (seconds): one image per time.
    #[arg(long, conflicts_with = "time", allow_hyphen_values = true)]
    frames: Option<String>,
    /// How each frame over moved geometry gets its BVH: auto (the cost model), refit
    /// (whenever a structure of the scene is cached) or rebuild (every frame).
    #[arg(long, value_enum, default_value_t = Update::Auto)]
    update: Update,
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
        // `.png` alone is a hidden file's name with no extension.
        let bare = a.out.file_name().and_then(|n| n.to_str()).is_some_and(|n| {
            let n = n.to_ascii_lowercase();
            n == ".png" || n == ".exr"
        });
        CliError::Usage(if bare {
            format!(
                "{}: the output needs a name before its .png or .exr extension",
                a.out.display()
            )
        } else {
            format!("{}: the output must end in .png or .exr", a.out.display())
        })
    })?;
    if let Some(aov) = Aov::repeated(&a.aov) {
        return Err(CliError::Usage(format!("--aov: '{aov}' is listed twice")));
    }
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
        sky: a.sky.map(|x| x as f32),
        aovs: AovSet::of(&a.aov),
        update: a.update,
        roulette: a.roulette,
    };
    request.check(engine.limits(), times.len())?;
    let path = a.scene.display().to_string();
    // Parsed once; each frame's time re-poses it through the scene's rig (bit-identical to
    // loading the file at that time), so a sequence never reads the file again.
    super::load_options(a.core.time)?;
    let surfaces = request.needs_surfaces();
    let parts = if surfaces {
        Parts::Shading
    } else {
        Parts::Geometry
    };
    let scene = crate::formats::load_scene_with(&a.scene, &Default::default(), parts)?;
    let textures = crate::render::texture::DecodedOnce::default();
    let frame_at = |time: Option<f64>, control: &crate::jobs::Control| {
        let posed = match time {
            None => None,
            Some(t) => Some(
                control
                    .step(|| scene.at(t))?
                    .map_err(|e| crate::jobs::JobError::Geometry(format!("time {t}: {e}")))?,
            ),
        };
        let s = posed.as_ref().unwrap_or(&scene);
        FrameInput::of_scene_with(
            s,
            GeometryKey::new(&path, 1, time),
            surfaces.then_some(&textures),
            &|part| control.step(part),
        )
    };
    let pattern = a.out.display().to_string();
    let sequence = a.frames.is_some();
    // Frame `k`'s file: the pattern's name for it in a sequence, else the pattern.
    let out_of = |k: usize| {
        if sequence {
            frame_name(&pattern, k)
        } else {
            pattern.clone()
        }
    };
    for k in 0..times.len() {
        super::refuse_overwriting(out_of(k).as_ref(), &[&a.scene])?;
        if sequence {
            super::Staged::check(out_of(k).as_ref())?;
        }
    }
    let mut written = Vec::new();
    // A sequence's frames appear together once all are made, or none does, Ctrl-C
    // included: a signal cancels the render, and the staged frames go with `staged`.
    let mut staged = super::Staged::default();
    let cancel = crate::jobs::CancelToken::new();
    let signals = if sequence {
        Some(super::StopOnSignal::install(cancel.clone())?)
    } else {
        None
    };
    let report = engine.render(
        &request,
        &times,
        &frame_at,
        &engine.detached_with(cancel),
        &mut |k, bytes| {
            let out = out_of(k);
            let wrote = if sequence {
                staged.write(out.as_ref(), &bytes)
            } else {
                super::write_whole(out.as_ref(), &bytes)
            };
            wrote.map_err(|source| {
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
    );
    let report = match (report, signals.as_ref().and_then(|s| s.came())) {
        (Err(crate::jobs::JobError::Cancelled), Some((name, number))) => {
            return Err(CliError::Stopped {
                name,
                number,
                detail: "no frame was written",
            })
        }
        (r, _) => r?,
    };
    staged.commit().map_err(|source| FormatError::Io {
        path: pattern.clone(),
        source,
    })?;
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
    if sequence {
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
