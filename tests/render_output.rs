//! The renderer's output against its contract (`proto/rendering.md`): EXR files that
//! OpenEXR's own library reads back channel by channel, equal to the renderer's buffers;
//! box-filtered pixels; the same image whatever the thread count; the default view; and
//! the `path` integrator against analytic answers (white furnace, a point light's inverse
//! square law).

use std::path::Path;
use std::process::Command;

use rayd::accel::{build, AccelKind, BuildOptions};
use rayd::geometry::Triangle;
use rayd::render::camera::{CameraChoice, ViewCamera};
use rayd::render::image::encode_exr;
use rayd::render::surface::{PunctualLight, Surfaces};
use rayd::render::{render, AovSet, Image, Integrator, RenderOptions, Waves};

/// Runs every wave at once, on the calling thread's pool.
struct AllAtOnce;

impl Waves for AllAtOnce {
    type Error = std::convert::Infallible;
    fn run_wave(&self, wave: &mut (dyn FnMut() + Send)) -> Result<(), Self::Error> {
        wave();
        Ok(())
    }
    fn wave_seconds(&self) -> f64 {
        f64::INFINITY
    }
    fn progress(&self, _fraction: f64) {}
}

fn tri(a: [f32; 3], b: [f32; 3], c: [f32; 3]) -> Triangle {
    Triangle { v: [a, b, c] }
}

/// A floor quad and a tilted quad standing on it, so that an image has hits, misses and
/// several triangles and normals.
fn two_quads() -> Vec<Triangle> {
    vec![
        tri([-2.0, 0.0, -2.0], [2.0, 0.0, 2.0], [2.0, 0.0, -2.0]),
        tri([-2.0, 0.0, -2.0], [-2.0, 0.0, 2.0], [2.0, 0.0, 2.0]),
        tri([-1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.5, -0.5]),
        tri([-1.0, 0.0, 0.0], [1.0, 1.5, -0.5], [-1.0, 1.5, -0.5]),
    ]
}

fn render_with(tris: &[Triangle], options: &RenderOptions, camera: &CameraChoice) -> Image {
    let accel = build(AccelKind::Mbvh8, tris, &BuildOptions::default()).unwrap();
    let bounds = rayd::scene::bounds_of(tris);
    let aspect = options.width as f64 / options.height as f64;
    let cam = ViewCamera::choose_from(camera, &[], bounds, aspect).unwrap();
    let diag = bounds.map(|b| b.diagonal()).unwrap_or(1.0);
    render(tris, accel.as_ref(), &cam, options, diag, None, &AllAtOnce)
        .unwrap()
        .0
}

fn look() -> CameraChoice {
    CameraChoice::LookAt {
        eye: [0.3, 2.5, 4.0],
        target: [0.0, 0.4, 0.0],
        up: [0.0, 1.0, 0.0],
        fov: 50.0,
    }
}

fn all_aovs() -> AovSet {
    AovSet {
        depth: true,
        normal: true,
        albedo: true,
        prim: true,
    }
}

/// The Python program that reads an EXR with OpenEXR's bindings and writes each channel's
/// pixels, little-endian, to `DIR/NAME.bin`, with `NAME TYPE` lines on stdout.
const READ_EXR: &str = r#"
import sys, OpenEXR, numpy as np
path, out = sys.argv[1], sys.argv[2]
with OpenEXR.File(path, separate_channels=True) as f:
    for name, ch in f.channels().items():
        px = np.ascontiguousarray(ch.pixels)
        kind = {np.dtype('float32'): 'FLOAT', np.dtype('float16'): 'HALF', np.dtype('uint32'): 'UINT'}[px.dtype]
        open(out + '/' + name + '.bin', 'wb').write(px.astype(px.dtype.newbyteorder('<')).tobytes())
        print(name, kind, px.shape[0], px.shape[1])
"#;

fn openexr_available() -> bool {
    Command::new("python3")
        .args(["-c", "import OpenEXR, numpy"])
        .output()
        .is_ok_and(|o| o.status.success())
}

#[test]
fn openexr_reads_every_channel_as_rendered() {
    if !openexr_available() {
        eprintln!("skipped: python3 with the OpenEXR module is missing (pip install OpenEXR)");
        return;
    }
    let options = RenderOptions {
        width: 37,
        height: 23,
        spp: 3,
        integrator: Integrator::Path,
        bounces: 2,
        seed: 5,
        sky: [0.9, 1.0, 1.3],
        aovs: all_aovs(),
        roulette: None,
    };
    let img = render_with(&two_quads(), &options, &look());
    let dir = tempfile::tempdir().unwrap();
    let exr = dir.path().join("frame.exr");
    std::fs::write(&exr, encode_exr(&img).unwrap()).unwrap();
    let out = Command::new("python3")
        .args(["-c", READ_EXR])
        .arg(&exr)
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let listing = String::from_utf8(out.stdout).unwrap();
    let mut names = Vec::new();
    for line in listing.lines() {
        let f: Vec<&str> = line.split_whitespace().collect();
        assert_eq!(f[2..], ["23", "37"], "{line}");
        let expect_type = if f[0] == "prim.id" { "UINT" } else { "FLOAT" };
        assert_eq!(f[1], expect_type, "{line}");
        names.push(f[0].to_string());
    }
    names.sort();
    let mut want = [
        "R", "G", "B", "A", "depth.Z", "normal.X", "normal.Y", "normal.Z", "albedo.R", "albedo.G",
        "albedo.B", "prim.id",
    ]
    .map(String::from)
    .to_vec();
    want.sort();
    assert_eq!(names, want);

    let read = |name: &str| -> Vec<u32> {
        std::fs::read(dir.path().join(format!("{name}.bin")))
            .unwrap()
            .chunks_exact(4)
            .map(|b| u32::from_le_bytes(b.try_into().unwrap()))
            .collect()
    };
    let bits = |v: &mut dyn Iterator<Item = f32>| v.map(f32::to_bits).collect::<Vec<u32>>();
    let a = &img.aovs;
    let (normal, albedo) = (a.normal.as_ref().unwrap(), a.albedo.as_ref().unwrap());
    for (c, suffix) in ["R", "G", "B"].iter().enumerate() {
        assert_eq!(
            read(suffix),
            bits(&mut img.pixels.iter().map(|p| p[c])),
            "{suffix}"
        );
        let n = format!("normal.{}", ["X", "Y", "Z"][c]);
        assert_eq!(read(&n), bits(&mut normal.iter().map(|p| p[c])), "{n}");
        let n = format!("albedo.{suffix}");
        assert_eq!(read(&n), bits(&mut albedo.iter().map(|p| p[c])), "{n}");
    }
    assert_eq!(read("A"), bits(&mut img.alpha.iter().copied()));
    assert_eq!(
        read("depth.Z"),
        bits(&mut a.depth.as_ref().unwrap().iter().copied())
    );
    assert_eq!(&read("prim.id"), a.prim.as_ref().unwrap());

    // The image is not trivial: it has hits on several triangles, misses, and partly
    // covered pixels.
    let prim = a.prim.as_ref().unwrap();
    assert!(prim.contains(&u32::MAX));
    assert!((0..4).all(|t| prim.contains(&t)), "{prim:?}");
    assert!(img.alpha.iter().any(|&x| x > 0.0 && x < 1.0));
    for (p, d) in prim.iter().zip(a.depth.as_ref().unwrap()) {
        assert_eq!(*p == u32::MAX, d.is_infinite());
    }
}

/// With one sample per pixel the sample is uniform in the pixel, not at its centre: over
/// many seeds, a pixel that a triangle edge cuts in two is covered by the edge's share.
#[test]
fn one_sample_per_pixel_is_uniform_in_the_pixel() {
    // Orthographic-like: a far, narrow camera looking down -Z at a triangle whose edge
    // x = y crosses the single pixel's diagonal: half the pixel is covered.
    let tris = vec![tri(
        [-10.0, -10.0, 0.0],
        [10.0, -10.0, 0.0],
        [10.0, 10.0, 0.0],
    )];
    let camera = CameraChoice::LookAt {
        eye: [0.0, 0.0, 100.0],
        target: [0.0; 3],
        up: [0.0, 1.0, 0.0],
        fov: 1.0,
    };
    let mut covered = 0.0;
    let seeds = 400;
    for seed in 0..seeds {
        let options = RenderOptions {
            width: 1,
            height: 1,
            seed,
            ..RenderOptions::default()
        };
        covered += render_with(&tris, &options, &camera).alpha[0] as f64;
    }
    let share = covered / seeds as f64;
    // Binomial(400, 1/2): standard deviation 0.025.
    assert!((share - 0.5).abs() < 0.1, "covered {share}");
}

#[test]
fn the_image_does_not_depend_on_the_thread_count() {
    let options = RenderOptions {
        width: 48,
        height: 32,
        spp: 2,
        integrator: Integrator::Path,
        bounces: 3,
        seed: 11,
        aovs: all_aovs(),
        ..RenderOptions::default()
    };
    let on = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| render_with(&two_quads(), &options, &look()))
    };
    let one = on(1);
    let two = on(2);
    assert!(one.pixels.iter().flatten().any(|&x| x > 0.0));
    assert_eq!(encode_exr(&one).unwrap(), encode_exr(&two).unwrap());
}

/// Without a camera the view frames the bounds, even for a scene that has cameras.
#[test]
fn the_default_view_frames_the_bounds_even_with_scene_cameras() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/Cameras.glb");
    let scene = rayd::formats::load_scene(&path, &Default::default()).unwrap();
    assert!(!scene.cameras.is_empty());
    let bounds = scene.bounds().unwrap();
    let auto = ViewCamera::choose(&CameraChoice::Auto, &scene, 1.5).unwrap();
    assert_eq!(auto, ViewCamera::framing(&bounds, 1.5));
    assert_ne!(
        auto,
        ViewCamera::choose(&CameraChoice::Scene(0), &scene, 1.5).unwrap()
    );
}

/// A Lambertian material of albedo `rho` (no specular layer).
fn lambertian(rho: f32) -> rayd::scene::Material {
    rayd::scene::Material {
        base_color_factor: [rho, rho, rho, 1.0],
        metallic_factor: 0.0,
        roughness_factor: 1.0,
        specular: rayd::scene::Specular {
            factor: 0.0,
            ..Default::default()
        },
        ..Default::default()
    }
}

fn render_surfaces(
    tris: &[Triangle],
    options: &RenderOptions,
    camera: &CameraChoice,
    surfaces: &Surfaces,
) -> Image {
    let accel = build(AccelKind::Mbvh8, tris, &BuildOptions::default()).unwrap();
    let bounds = rayd::scene::bounds_of(tris);
    let aspect = options.width as f64 / options.height as f64;
    let cam = ViewCamera::choose_from(camera, &[], bounds, aspect).unwrap();
    let diag = bounds.map(|b| b.diagonal()).unwrap_or(1.0);
    render(
        tris,
        accel.as_ref(),
        &cam,
        options,
        diag,
        Some(surfaces),
        &AllAtOnce,
    )
    .unwrap()
    .0
}

/// The 12 triangles of the axis-aligned cube of half-size `h` around the origin, wound
/// outwards.
fn cube(h: f32) -> Vec<Triangle> {
    let mut out = Vec::new();
    for axis in 0..3 {
        for sign in [-1.0f32, 1.0] {
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            let corner = |a: f32, b: f32| {
                let mut p = [0.0; 3];
                p[axis] = sign * h;
                p[u] = a * h;
                p[v] = b * h;
                p
            };
            let (p00, p10, p11, p01) = (
                corner(-1.0, -1.0),
                corner(1.0, -1.0),
                corner(1.0, 1.0),
                corner(-1.0, 1.0),
            );
            if sign > 0.0 {
                out.push(tri(p00, p10, p11));
                out.push(tri(p00, p11, p01));
            } else {
                out.push(tri(p00, p11, p10));
                out.push(tri(p00, p01, p11));
            }
        }
    }
    out
}

/// White furnace: a convex object of albedo ρ under a constant sky L reflects exactly ρL
/// once it may scatter (every scattered ray leaves it and sees the sky).
#[test]
fn white_furnace_gives_albedo_times_sky() {
    let (rho, sky) = (0.6f32, [0.8f32, 0.5, 1.5]);
    let tris = cube(1.0);
    let surfaces = Surfaces::uniform(tris.len(), lambertian(rho), Vec::new());
    for bounces in [1, 2, 5] {
        let options = RenderOptions {
            width: 24,
            height: 24,
            spp: 4,
            integrator: Integrator::Path,
            bounces,
            seed: 3,
            sky,
            ..RenderOptions::default()
        };
        let camera = CameraChoice::LookAt {
            eye: [2.0, 2.5, 3.0],
            target: [0.0; 3],
            up: [0.0, 1.0, 0.0],
            fov: 40.0,
        };
        let img = render_surfaces(&tris, &options, &camera, &surfaces);
        let mut covered = 0;
        for (p, a) in img.pixels.iter().zip(&img.alpha) {
            if *a == 1.0 {
                covered += 1;
                for c in 0..3 {
                    let want = rho * sky[c];
                    assert!((p[c] - want).abs() < 0.02 * want, "{bounces}: {p:?}");
                }
            } else if *a == 0.0 {
                assert_eq!(*p, sky);
            }
        }
        assert!(covered > 100, "{covered}");
    }
    // No scattering: surfaces are black, the sky shows.
    let options = RenderOptions {
        width: 8,
        height: 8,
        integrator: Integrator::Path,
        bounces: 0,
        sky,
        ..RenderOptions::default()
    };
    let img = render_surfaces(&tris, &options, &look(), &surfaces);
    for (p, a) in img.pixels.iter().zip(&img.alpha) {
        if *a == 1.0 {
            assert_eq!(*p, [0.0; 3]);
        }
    }
}

/// A point light of intensity I over a Lambertian plane of albedo ρ: the radiance seen at
/// a point is ρ/π · I cos θ / r².
#[test]
fn point_light_over_a_lambertian_plane_follows_the_inverse_square_law() {
    let rho = 0.5f32;
    let (height, intensity) = (2.0f32, 30.0f32);
    let tris = vec![
        tri([-50.0, 0.0, -50.0], [50.0, 0.0, 50.0], [50.0, 0.0, -50.0]),
        tri([-50.0, 0.0, -50.0], [-50.0, 0.0, 50.0], [50.0, 0.0, 50.0]),
    ];
    let light = PunctualLight::Point {
        position: glam::Vec3::new(0.0, height, 0.0),
        intensity: glam::Vec3::splat(intensity),
        range: f32::INFINITY,
        cone: None,
    };
    let surfaces = Surfaces::uniform(tris.len(), lambertian(rho), vec![light]);
    for x in [0.0f32, 0.7, 1.5, 3.0, 6.0] {
        let target = [x as f64, 0.0, 0.3];
        let camera = CameraChoice::LookAt {
            eye: [x as f64 + 0.5, 5.0, 1.0],
            target,
            up: [0.0, 1.0, 0.0],
            fov: 0.01,
        };
        let options = RenderOptions {
            width: 1,
            height: 1,
            integrator: Integrator::Path,
            bounces: 1,
            sky: [0.0; 3],
            ..RenderOptions::default()
        };
        let img = render_surfaces(&tris, &options, &camera, &surfaces);
        let r2 = x * x + 0.09 + height * height;
        let cos = height / r2.sqrt();
        let want = rho / std::f32::consts::PI * intensity * cos / r2;
        let got = img.pixels[0][0];
        assert!((got - want).abs() < 1e-3 * want, "x = {x}: {got} vs {want}");
    }
}
