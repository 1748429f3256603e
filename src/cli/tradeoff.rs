//! `rayd tradeoff SCENE --out DIR`: the speed/accuracy ladder of `crate::tradeoff`, written
//! as `DIR/tradeoff.csv`, `DIR/tradeoff.png` and `DIR/tradeoff.md`.

use serde_json::json;

use super::{CameraArgs, CliError, PathArg};
use crate::accel::dacrt::DacrtTuning;
use crate::accel::{AccelKind, BuildQuality, Precision};
use crate::formats::{FormatError, Parts};
use crate::jobs::render::FrameInput;
use crate::jobs::{GeometryKey, RenderRequest};
use crate::render::Integrator;
use crate::tradeoff::{report, Axis, Setup};

#[derive(clap::Args, Debug)]
pub(super) struct TradeoffArgs {
    /// Scene file (.glb, .gltf or .tri).
    scene: PathArg,
    /// Directory for tradeoff.csv, tradeoff.png and tradeoff.md (made if missing).
    #[arg(short = 'o', long = "out")]
    out: PathArg,
    /// Image width in pixels.
    #[arg(long, default_value_t = 160)]
    width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 120)]
    height: u32,
    /// Samples per pixel of the base (every rung but those of `spp`).
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..))]
    spp: u32,
    /// Bounces of the base.
    #[arg(long, default_value_t = 3)]
    bounces: u32,
    /// The rungs of the `spp` axis (each at least 1: refused before anything renders).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "1,2,4,8,16,32,64",
        value_parser = clap::value_parser!(u32).range(1..)
    )]
    spp_ladder: Vec<u32>,
    /// The rungs of the `bounces` axis.
    #[arg(long, value_delimiter = ',', default_value = "0,1,2,3,4,6,8")]
    bounces_ladder: Vec<u32>,
    /// The rungs of the `accel` axis (those this build lacks are skipped, with a note).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "mbvh8,mbvh4,bvh2,dacrt,dacrt-sampled,embree"
    )]
    accels: Vec<AccelKind>,
    /// Axes to walk: spp, bounces, roulette, precision, build, accel, dacrt.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "spp,bounces,roulette,precision,build,accel,dacrt"
    )]
    axes: Vec<Axis>,
    /// Samples per pixel of the reference.
    #[arg(long, default_value_t = 1024, value_parser = clap::value_parser!(u32).range(1..))]
    reference_spp: u32,
    /// Bounces of the reference (default: the most of any rung).
    #[arg(long)]
    reference_bounces: Option<u32>,
    #[command(flatten)]
    camera: CameraArgs,
    /// Seed of the rungs; the reference uses another.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Radiance R,G,B of the constant environment.
    #[arg(long, value_parser = super::parse_vec3, default_value = "1,1,1", allow_hyphen_values = true)]
    sky: [f64; 3],
    /// Accelerator of the base (a named one: `auto` would change its pick along the ladder).
    #[arg(long, value_enum, default_value_t = AccelKind::Mbvh8)]
    accel: AccelKind,
    /// Build quality of the base.
    #[arg(long, value_enum, default_value_t = BuildQuality::Sah)]
    build: BuildQuality,
    /// Ray/triangle test of the base.
    #[arg(long, value_enum, default_value_t = Precision::Watertight)]
    precision: Precision,
    /// Threads of every render; 0: all cores (at most 1024).
    #[arg(long, default_value_t = 0, value_parser = super::threads_arg())]
    threads: usize,
    /// Animation time in seconds (absent: the file's static pose).
    #[arg(long, allow_negative_numbers = true)]
    time: Option<f64>,
}

/// The files a run writes into its directory.
const OUTPUTS: [&str; 3] = ["tradeoff.csv", "tradeoff.md", "tradeoff.png"];

/// Writes the three outputs into `dir` all or none ([`super::Staged`]), making `dir`
/// only now, after every option was checked and every render made: a run that fails
/// leaves no directory and no file behind.
fn write_all(dir: &std::path::Path, files: [(&str, &[u8]); 3]) -> Result<[String; 3], CliError> {
    let io = |path: &std::path::Path| {
        let path = path.display().to_string();
        move |source| FormatError::Io { path, source }
    };
    let made = !dir.exists();
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let written = (|| {
        let mut staged = super::Staged::default();
        let mut written = Vec::new();
        for (name, bytes) in files {
            let path = dir.join(name);
            staged.write(&path, bytes).map_err(io(&path))?;
            written.push(path.display().to_string());
        }
        staged.commit().map_err(io(dir))?;
        Ok::<_, FormatError>(written.try_into().expect("three files"))
    })();
    // The staged files are gone (committed or removed): a directory made here and left
    // empty goes too.
    if written.is_err() && made {
        let _ = std::fs::remove_dir(dir);
    }
    Ok(written?)
}

pub(super) fn run(a: TradeoffArgs) -> Result<serde_json::Value, CliError> {
    super::load_options(a.time)?;
    // `auto` picks per frame: as the base, its pick would change along the ladder (and the
    // build axis would walk a core with no build); as a rung, it repeats a named one.
    if a.accel == AccelKind::Auto || a.accels.contains(&AccelKind::Auto) {
        return Err(CliError::Usage(
            "--accel/--accels: the trade-off compares named accelerators, not auto \
             (its pick would change along the ladder)"
                .into(),
        ));
    }
    let mut setup = Setup::new(RenderRequest {
        width: a.width,
        height: a.height,
        spp: a.spp,
        integrator: Integrator::Path,
        bounces: a.bounces,
        camera: a.camera.choice(),
        seed: a.seed,
        accel: a.accel,
        build: a.build,
        precision: a.precision,
        sky: a.sky.map(|x| x as f32),
        ..RenderRequest::default()
    });
    setup.tuning = DacrtTuning::from_env();
    setup.threads = a.threads;
    setup.time = a.time;
    setup.reference_spp = a.reference_spp;
    setup.spp = a.spp_ladder;
    setup.bounces = a.bounces_ladder;
    setup.accels = a.accels;
    setup.axes = a.axes;
    let walks_bounces = setup.axes.contains(&Axis::Bounces);
    let most = setup
        .bounces
        .iter()
        .copied()
        .filter(|_| walks_bounces)
        .chain([a.bounces])
        .max()
        .unwrap_or(a.bounces);
    setup.reference_bounces = a.reference_bounces.unwrap_or(most);
    if a.out.exists() && !a.out.is_dir() {
        return Err(CliError::Usage(format!(
            "{}: the output directory exists and is not a directory",
            a.out.display()
        )));
    }
    for name in OUTPUTS {
        super::Staged::check(&a.out.join(name))?;
    }
    let path = a.scene.display().to_string();
    let scene = crate::formats::load_scene_with(&a.scene, &Default::default(), Parts::Shading)?;
    let posed = match a.time {
        None => None,
        Some(t) => Some(
            scene
                .at(t)
                .map_err(|e| CliError::Usage(format!("{path}: time {t}: {e}")))?,
        ),
    };
    let frame = FrameInput::of_scene(
        posed.as_ref().unwrap_or(&scene),
        GeometryKey::new(&path, 1, a.time),
        true,
    )?;
    let name = a
        .scene
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| path.clone());
    crate::note!(
        "rayd tradeoff: rendering the reference ({} spp, {} bounces)",
        setup.reference_spp,
        setup.reference_bounces
    );
    let result = crate::tradeoff::run(&name, &frame, &setup, &mut |k, n, row| {
        crate::note!(
            "rayd tradeoff: {}/{} {:<8} {:<22} {:>8.3} s  RMSE {:.5}",
            k + 1,
            n,
            row.axis,
            row.setting,
            row.seconds,
            row.errors.rmse
        );
    })?;
    let (csv, table, plot) = (
        report::csv(&result),
        report::markdown(&result),
        report::plot(&result)?,
    );
    let [csv, table, plot] = write_all(
        &a.out,
        [
            (OUTPUTS[0], csv.as_bytes()),
            (OUTPUTS[1], table.as_bytes()),
            (OUTPUTS[2], &plot),
        ],
    )?;
    Ok(json!({
        "scene": path,
        "width": result.width,
        "height": result.height,
        "threads": result.threads,
        "csv": csv,
        "table": table,
        "plot": plot,
        "reference": result.reference,
        "rows": result.rows,
        "notes": result.notes,
    }))
}
