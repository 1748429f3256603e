//! Golden images: small committed scenes rendered by `path` at low spp and compared with
//! the committed PNGs under `tests/golden/`, within a tolerance (`proto/rendering.md`,
//! "Golden images"). A render that strays writes itself and a diff image next to the
//! test's temporary directory and names them in the failure. `RAYD_BLESS=1 cargo test
//! --release --test golden` rewrites the goldens from the current renderer.
//!
//! Why a tolerance rather than bit equality: the image is deterministic on one machine,
//! but another CPU or libm may round a transcendental function differently, and a path
//! that then takes another random branch moves a pixel by a lot. So the test bounds the
//! mean difference over the image and the difference of 4 × 4 block means, which noise
//! of that kind leaves small while a real change of shading (a light, a texture, a
//! cut-out gone or moved) does not.

use std::path::{Path, PathBuf};

use rayd::accel::{build, AccelKind, BuildOptions};
use rayd::formats::{load_scene_with, Parts};
use rayd::render::camera::{CameraChoice, ViewCamera};
use rayd::render::image::{encode, ImageFormat};
use rayd::render::surface::Surfaces;
use rayd::render::{render, Integrator, RenderOptions};

mod common;
use common::ALL_AT_ONCE;

/// Largest mean absolute difference over all channels, in 8-bit steps.
const MEAN_TOLERANCE: f64 = 1.5;
/// Largest difference of a 4 × 4 block's mean in any channel, in 8-bit steps.
const BLOCK_TOLERANCE: f64 = 24.0;

/// One golden: scene file, camera, and the render's options.
struct Case {
    name: &'static str,
    scene: &'static str,
    camera: CameraChoice,
    options: RenderOptions,
}

fn cases() -> Vec<Case> {
    let base = RenderOptions {
        width: 64,
        height: 48,
        spp: 16,
        integrator: Integrator::Path,
        bounces: 3,
        seed: 1,
        sky: [0.05, 0.05, 0.08],
        ..RenderOptions::default()
    };
    vec![
        // Area and point lights, MIS, a normal-mapped floor, MASK and BLEND quads.
        Case {
            name: "golden-lights",
            scene: "golden-lights.gltf",
            camera: CameraChoice::Scene(0),
            options: base,
        },
        // The same with Russian roulette from the second scattering.
        Case {
            name: "golden-lights-roulette",
            scene: "golden-lights.gltf",
            camera: CameraChoice::Scene(0),
            options: RenderOptions {
                roulette: Some(2),
                bounces: 5,
                ..base
            },
        },
        // A base colour texture under the sky alone.
        Case {
            name: "fox-sky",
            scene: "Fox.glb",
            camera: CameraChoice::Auto,
            options: RenderOptions {
                sky: [1.0, 1.0, 1.0],
                bounces: 2,
                ..base
            },
        },
    ]
}

fn render_case(case: &Case) -> Vec<u8> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(case.scene);
    let scene = load_scene_with(&path, &Default::default(), Parts::Shading).unwrap();
    let surfaces = Surfaces::of(&scene).unwrap();
    let accel = build(AccelKind::Mbvh8, &scene.triangles, &BuildOptions::default()).unwrap();
    let o = &case.options;
    let camera =
        ViewCamera::choose(&case.camera, &scene, o.width as f64 / o.height as f64).unwrap();
    let bounds = scene.bounds();
    let (img, _) = render(
        &scene.triangles,
        accel.as_ref(),
        &camera,
        o,
        bounds.as_ref(),
        Some(&surfaces),
        None,
        &ALL_AT_ONCE,
    )
    .unwrap();
    encode(&img, ImageFormat::Png).unwrap()
}

fn rgb(png: &[u8]) -> image::RgbImage {
    image::load_from_memory(png).unwrap().to_rgb8()
}

/// The mean absolute difference (8-bit steps) and the largest 4 × 4 block-mean
/// difference of two images of one size.
fn differences(a: &image::RgbImage, b: &image::RgbImage) -> (f64, f64) {
    let (w, h) = a.dimensions();
    let mut sum = 0.0;
    for (p, q) in a.pixels().zip(b.pixels()) {
        for c in 0..3 {
            sum += (p[c] as f64 - q[c] as f64).abs();
        }
    }
    let mean = sum / (w as f64 * h as f64 * 3.0);
    let mut worst = 0.0f64;
    for by in (0..h).step_by(4) {
        for bx in (0..w).step_by(4) {
            let mut d = [0.0f64; 3];
            let mut n = 0.0;
            for y in by..(by + 4).min(h) {
                for x in bx..(bx + 4).min(w) {
                    let (p, q) = (a.get_pixel(x, y), b.get_pixel(x, y));
                    for c in 0..3 {
                        d[c] += p[c] as f64 - q[c] as f64;
                    }
                    n += 1.0;
                }
            }
            worst = d.iter().fold(worst, |m, v| m.max(v.abs() / n));
        }
    }
    (mean, worst)
}

/// |a − b| × 8 per channel: where the images part.
fn diff_image(a: &image::RgbImage, b: &image::RgbImage) -> image::RgbImage {
    image::RgbImage::from_fn(a.width(), a.height(), |x, y| {
        let (p, q) = (a.get_pixel(x, y), b.get_pixel(x, y));
        image::Rgb(std::array::from_fn(|c| {
            ((p[c] as i32 - q[c] as i32).unsigned_abs() * 8).min(255) as u8
        }))
    })
}

#[test]
fn renders_match_the_goldens() {
    let golden_dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden");
    let bless = std::env::var("RAYD_BLESS").is_ok_and(|v| v == "1");
    let out_dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("golden");
    let mut failures = Vec::new();
    for case in cases() {
        let png = render_case(&case);
        let golden = golden_dir.join(format!("{}.png", case.name));
        if bless {
            std::fs::create_dir_all(&golden_dir).unwrap();
            std::fs::write(&golden, &png).unwrap();
            eprintln!("blessed {}", golden.display());
            continue;
        }
        let want = match std::fs::read(&golden) {
            Ok(b) => rgb(&b),
            Err(e) => {
                failures.push(format!(
                    "{}: {e} (RAYD_BLESS=1 writes it)",
                    golden.display()
                ));
                continue;
            }
        };
        let got = rgb(&png);
        assert_eq!(got.dimensions(), want.dimensions(), "{}", case.name);
        let (mean, block) = differences(&got, &want);
        if mean > MEAN_TOLERANCE || block > BLOCK_TOLERANCE {
            std::fs::create_dir_all(&out_dir).unwrap();
            let new = out_dir.join(format!("{}-new.png", case.name));
            let diff = out_dir.join(format!("{}-diff.png", case.name));
            std::fs::write(&new, &png).unwrap();
            diff_image(&got, &want).save(&diff).unwrap();
            failures.push(format!(
                "{}: mean difference {mean:.2} (at most {MEAN_TOLERANCE}), worst 4×4 block \
                 {block:.1} (at most {BLOCK_TOLERANCE}); wrote {} and {}",
                case.name,
                new.display(),
                diff.display()
            ));
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// The comparison itself can fail: a golden with a light missing is caught.
#[test]
fn the_comparison_catches_a_changed_image() {
    let case = &cases()[0];
    let got = rgb(&render_case(case));
    let mut darker = got.clone();
    for p in darker.pixels_mut() {
        for c in 0..3 {
            p[c] = (p[c] as f32 * 0.8) as u8;
        }
    }
    let (mean, block) = differences(&got, &darker);
    assert!(
        mean > MEAN_TOLERANCE || block > BLOCK_TOLERANCE,
        "{mean} {block}"
    );
    assert_eq!(differences(&got, &got), (0.0, 0.0));
}
