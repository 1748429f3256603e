//! `rayd bench SCENE... [options]`: the benchmark suite. The JSON report goes to stdout as
//! every command's result does; the table goes to stderr (or to stdout with
//! `--format table`, CSV with `--format csv`).

use super::{CameraArgs, CliError, PathArg};
use crate::accel::{AccelKind, BuildQuality, Precision};
use crate::bench::{BenchConfig, DynamicConfig, Motion, SetKind, ViewKind};

#[derive(clap::Args, Debug)]
pub(super) struct BenchArgs {
    /// Scene files.
    #[arg(required = true)]
    scenes: Vec<PathArg>,
    /// Accelerators to measure, comma-separated.
    #[arg(long, value_delimiter = ',', default_value = "auto", value_enum)]
    accel: Vec<AccelKind>,
    /// Ray sets: primary, ao, diffuse1, diffuse2, diffuse8 (comma-separated).
    #[arg(long, value_delimiter = ',', default_value = "primary,ao,diffuse1,diffuse2,diffuse8", value_parser = parse_set)]
    sets: Vec<SetKind>,
    /// Views: interior (camera inside a closed room, every ray hits), exterior.
    #[arg(long, value_delimiter = ',', default_value = "interior", value_parser = parse_view)]
    view: Vec<ViewKind>,
    /// Image width: rays per set = width × height.
    #[arg(long, default_value_t = 1024)]
    width: u32,
    /// Image height.
    #[arg(long, default_value_t = 768)]
    height: u32,
    #[command(flatten)]
    camera: CameraArgs,
    /// Timed runs per measurement (median reported; default 5). Not with --frames, where
    /// every frame is one run.
    #[arg(long)]
    runs: Option<usize>,
    /// Thread counts to measure, comma-separated; 0 = all cores.
    #[arg(long, value_delimiter = ',', default_value = "1,0", value_parser = super::threads_arg())]
    threads: Vec<usize>,
    /// Seed of the ray sets.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Build quality: fast, sah, sbvh (embree: LOW, MEDIUM, HIGH).
    #[arg(long, default_value = "sah", value_enum)]
    build: BuildQuality,
    /// Ray/triangle test: fast or watertight.
    #[arg(long, default_value = "watertight", value_enum)]
    precision: Precision,
    /// Reference for the agreement check (auto: brute on small scenes, embree on large ones).
    #[arg(long, default_value = "auto", value_enum)]
    reference: AccelKind,
    /// Animation time in seconds.
    #[arg(long, allow_negative_numbers = true)]
    time: Option<f64>,
    /// Write each ray set (RAY1) and the reference hits (HIT1) into this directory.
    #[arg(long)]
    dump: Option<PathArg>,
    /// Dynamic geometry: this many frames of moving triangles, each paying its own
    /// preparation (rebuild, refit or DACRT's precompute) and trace.
    #[arg(long)]
    frames: Option<usize>,
    /// With --frames: how the geometry moves (auto, the default: the scene's animation,
    /// else twist).
    #[arg(long, value_parser = parse_motion)]
    motion: Option<Motion>,
    /// With --frames: rays per frame, comma-separated (each a square image of about that
    /// many pixels).
    #[arg(long, value_delimiter = ',', default_value = "262144,1048576")]
    rays_per_frame: Vec<usize>,
    /// What goes to stdout: json (the report), table (Markdown) or csv.
    #[arg(long, default_value = "json", value_parser = ["json", "table", "csv"])]
    format: String,
}

fn parse_set(s: &str) -> Result<SetKind, String> {
    SetKind::parse(s).ok_or_else(|| {
        format!("unknown ray set '{s}' (primary, ao, diffuse1, diffuse2 or diffuse8)")
    })
}

fn parse_motion(s: &str) -> Result<Motion, String> {
    Motion::parse(s).ok_or_else(|| format!("unknown motion '{s}' (auto, animation or twist)"))
}

fn parse_view(s: &str) -> Result<ViewKind, String> {
    ViewKind::parse(s).ok_or_else(|| format!("unknown view '{s}' (interior or exterior)"))
}

pub(super) fn run(mut a: BenchArgs) -> Result<serde_json::Value, CliError> {
    // A repeated accelerator or thread count would be measured twice under one row.
    unique(&mut a.accel);
    unique(&mut a.threads);
    // Options of one mode that the other would silently ignore.
    let ignored = match a.frames {
        Some(_) => [
            ("--dump", a.dump.is_some()),
            ("--time", a.time.is_some()),
            ("--runs", a.runs.is_some()),
        ],
        None => [("--motion", a.motion.is_some()), ("", false), ("", false)],
    };
    if let Some((flag, _)) = ignored.iter().find(|(_, given)| *given) {
        return Err(CliError::Usage(if a.frames.is_some() {
            format!("{flag} is not available with --frames")
        } else {
            format!("{flag} needs --frames")
        }));
    }
    if let Some(frames) = a.frames {
        return run_dynamic(a, frames);
    }
    let config = BenchConfig {
        scenes: a.scenes,
        accels: a.accel,
        sets: a.sets,
        views: a.view,
        width: a.width,
        height: a.height,
        camera: a.camera.choice(),
        runs: a.runs.unwrap_or(5),
        threads: a.threads,
        seed: a.seed,
        build: a.build,
        precision: a.precision,
        reference: a.reference,
        time: a.time,
        dump: a.dump,
    };
    let report = crate::bench::run(&config)?;
    let table = crate::bench::render_table(&report);
    match a.format.as_str() {
        "table" => {
            print!("{table}");
            Ok(serde_json::Value::Null)
        }
        "csv" => {
            print!("{}", crate::bench::render_csv(&report));
            Ok(serde_json::Value::Null)
        }
        _ => {
            crate::note!("{table}");
            Ok(serde_json::to_value(&report).map_err(|e| CliError::Usage(e.to_string()))?)
        }
    }
}

fn run_dynamic(a: BenchArgs, frames: usize) -> Result<serde_json::Value, CliError> {
    let config = DynamicConfig {
        scenes: a.scenes,
        accels: a.accel,
        sets: a.sets,
        rays_per_frame: a.rays_per_frame,
        frames,
        motion: a.motion.unwrap_or(Motion::Auto),
        threads: a.threads,
        camera: a.camera.choice(),
        build: a.build,
        precision: a.precision,
        seed: a.seed,
    };
    let report = crate::bench::run_dynamic(&config)?;
    let table = crate::bench::render_dynamic_table(&report);
    match a.format.as_str() {
        "table" => {
            print!("{table}");
            Ok(serde_json::Value::Null)
        }
        "csv" => Err(CliError::Usage(
            "--format csv is not available with --frames (use json or table)".into(),
        )),
        _ => {
            crate::note!("{table}");
            Ok(serde_json::to_value(&report).map_err(|e| CliError::Usage(e.to_string()))?)
        }
    }
}

/// Keeps the first of each value, in order.
fn unique<T: PartialEq + Copy>(v: &mut Vec<T>) {
    let mut seen = Vec::with_capacity(v.len());
    v.retain(|x| {
        let new = !seen.contains(x);
        if new {
            seen.push(*x);
        }
        new
    });
}
