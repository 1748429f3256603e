//! `rayd tradeoff` (`proto/cli.md`): Monte Carlo convergence of the `path` integrator (error
//! against a reference falls as 1/√spp), and the command's files and refusals.

use std::path::{Path, PathBuf};
use std::process::Command;

use rayd::accel::dacrt::DacrtTuning;
use rayd::accel::AccelKind;
use rayd::formats::{load_scene_with, Parts};
use rayd::jobs::render::FrameInput;
use rayd::jobs::{GeometryKey, RenderRequest};
use rayd::render::Integrator;
use rayd::tradeoff::measure::{errors, log_log_slope};
use rayd::tradeoff::render_radiance;

fn scene(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name)
}

/// The fox under the sky, 32×24, two bounces: its concave parts make the lighting noisy,
/// and its edges make the pixel footprint noisy.
#[test]
fn error_falls_as_one_over_root_spp() {
    let path = scene("Fox.glb");
    let s = load_scene_with(&path, &Default::default(), Parts::Shading).unwrap();
    let frame = FrameInput::of_scene(&s, GeometryKey::new("fox", 1, None), true).unwrap();
    let base = RenderRequest {
        width: 32,
        height: 24,
        integrator: Integrator::Path,
        bounces: 2,
        accel: AccelKind::Mbvh8,
        ..RenderRequest::default()
    };
    let tuning = DacrtTuning::default();
    let reference = render_radiance(
        &frame,
        &RenderRequest {
            spp: 2048,
            seed: 12345,
            ..base.clone()
        },
        tuning,
        0,
        None,
    )
    .unwrap()
    .pixels;
    let points: Vec<(f64, f64)> = [1u32, 4, 16, 64]
        .iter()
        .map(|&spp| {
            let img = render_radiance(
                &frame,
                &RenderRequest {
                    spp,
                    ..base.clone()
                },
                tuning,
                0,
                None,
            )
            .unwrap()
            .pixels;
            (spp as f64, errors(&img, &reference).unwrap().rmse)
        })
        .collect();
    let slope = log_log_slope(&points).unwrap();
    // Monte Carlo error falls as spp^-1/2; the pixel samples are stratified (shifted
    // Hammersley), which makes the pixel-area part of the integral converge faster, up to
    // spp^-3/4 at edges (a stratified estimator's variance over a discontinuity falls as
    // N^-3/2), while the bounce directions stay plain Monte Carlo. So the slope lies between
    // -3/4 and -1/2, within a tolerance. The reference's own noise (1/32 of the variance at
    // 64 spp) flattens it by under 0.01; a biased estimator would flatten it far more.
    assert!(
        (-0.85..=-0.4).contains(&slope),
        "log-log slope of RMSE against spp is {slope:.3}, not in [-3/4, -1/2] ± 0.1: {points:?}"
    );
    // And the error does fall at every step.
    assert!(points.windows(2).all(|w| w[1].1 < w[0].1), "{points:?}");
}

fn rayd(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_rayd"))
        .args(args)
        .output()
        .unwrap()
}

#[test]
fn the_command_writes_csv_table_and_plot() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("t");
    let fox = scene("Fox.glb");
    let o = rayd(&[
        "tradeoff",
        fox.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--width",
        "16",
        "--height",
        "12",
        "--spp",
        "2",
        "--axes",
        "spp,roulette,accel",
        "--spp-ladder",
        "1,2,8",
        "--accels",
        "mbvh8,bvh2",
        "--reference-spp",
        "64",
    ]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let rows = j["rows"].as_array().unwrap();
    // base (spp 2, mbvh8, 3 bounces), spp 1 and 8 (2 is the base), roulette from the 1st,
    // 2nd and 3rd scattering, bvh2 (mbvh8 is the base).
    let settings: Vec<&str> = rows
        .iter()
        .map(|r| r["setting"].as_str().unwrap())
        .collect();
    assert_eq!(
        settings,
        [
            "base",
            "spp=1",
            "spp=8",
            "roulette=1",
            "roulette=2",
            "roulette=3",
            "accel=bvh2"
        ]
    );
    assert!(rows.iter().any(|r| r["pareto"] == true));
    assert!(rows.iter().all(|r| r["rmse"].as_f64().unwrap() > 0.0));
    assert_eq!(j["reference"]["spp"], 64);
    let csv = std::fs::read_to_string(out.join("tradeoff.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + rows.len());
    let md = std::fs::read_to_string(out.join("tradeoff.md")).unwrap();
    assert!(md.contains("| axis | setting |") && md.contains('★'));
    let png = std::fs::read(out.join("tradeoff.png")).unwrap();
    assert!(png.starts_with(b"\x89PNG\r\n\x1a\n"));
}

#[test]
fn the_command_refuses_what_it_cannot_measure() {
    let dir = tempfile::tempdir().unwrap();
    let fox = scene("Fox.glb");
    let base = |extra: &[&str]| {
        let mut a = vec![
            "tradeoff",
            fox.to_str().unwrap(),
            "-o",
            dir.path().to_str().unwrap(),
            "--width",
            "8",
            "--height",
            "6",
            "--axes",
            "spp",
            "--spp-ladder",
            "1",
            "--reference-spp",
            "4",
        ];
        a.extend_from_slice(extra);
        rayd(&a)
    };
    // A reference with fewer bounces than a rung cannot judge it.
    let o = base(&["--bounces", "4", "--reference-bounces", "2"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("fewer than a rung's 4"));
    // An unknown axis is the parser's to refuse.
    let o = base(&["--axes", "colour"]);
    assert_eq!(o.status.code(), Some(2));
    // A missing scene names itself.
    let o = rayd(&[
        "tradeoff",
        "no-such.glb",
        "-o",
        dir.path().to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("no-such.glb"));
}
