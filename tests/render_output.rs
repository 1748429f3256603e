//! The renderer's output against its contract (`proto/rendering.md`): EXR files that
//! OpenEXR's own library reads back channel by channel, equal to the renderer's buffers;
//! box-filtered pixels; the same image whatever the thread count; the default view; and
//! the `path` integrator against analytic answers (white furnace, a point light's inverse
//! square law).

use std::path::Path;
use std::process::Command;

use rayd::accel::{build, AccelKind, BuildOptions, Intersector};
use rayd::geometry::Triangle;
use rayd::render::camera::{CameraChoice, ViewCamera};
use rayd::render::image::encode_exr;
use rayd::render::surface::{PunctualLight, Surfaces};
use rayd::render::{render, AovSet, Image, Integrator, RenderOptions, RenderStats};

mod common;
use common::{InPlace, ALL_AT_ONCE};

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
    render_on(accel.as_ref(), &ALL_AT_ONCE, tris, options, camera, None).0
}

/// Renders `tris` with `accel` (built over them) in `waves`, through `camera` framed for
/// `options`' aspect, with `surfaces` or the default material.
fn render_on(
    accel: &dyn Intersector,
    waves: &InPlace,
    tris: &[Triangle],
    options: &RenderOptions,
    camera: &CameraChoice,
    surfaces: Option<&Surfaces>,
) -> (Image, RenderStats) {
    let bounds = rayd::scene::bounds_of(tris);
    let aspect = options.width as f64 / options.height as f64;
    let cam = ViewCamera::choose_from(camera, &[], bounds, aspect).unwrap();
    render(
        tris,
        accel,
        &cam,
        options,
        bounds.as_ref(),
        surfaces,
        None,
        waves,
    )
    .unwrap()
}

fn look() -> CameraChoice {
    CameraChoice::LookAt {
        eye: [0.3, 2.5, 4.0],
        target: [0.0, 0.4, 0.0],
        up: [0.0, 1.0, 0.0],
        fov: 50.0,
    }
}

/// A view from far off, where `two_quads` fills a small rectangle of the image.
fn far() -> CameraChoice {
    CameraChoice::LookAt {
        eye: [1.5, 4.0, 14.0],
        target: [0.0, 0.4, 0.0],
        up: [0.0, 1.0, 0.0],
        fov: 35.0,
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
        light_sampling: true,
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

/// Waves sized in seconds (the service's, 8192 pixels first, then from the rate), the
/// per-ray cores' waves (2^16 pixels: two here) and DACRT's (2^18: one here) all give the
/// same image: a pixel's samples never depend on the wave that holds them.
#[test]
fn the_image_does_not_depend_on_the_wave_size() {
    let options = RenderOptions {
        width: 320,
        height: 240,
        integrator: Integrator::Path,
        bounces: 2,
        seed: 5,
        aovs: all_aovs(),
        ..RenderOptions::default()
    };
    let tris = two_quads();
    let with = |kind: AccelKind, timed: bool| {
        let accel = build(kind, &tris, &BuildOptions::default()).unwrap();
        assert_eq!(accel.large_batches(), kind == AccelKind::Dacrt);
        let waves = if timed {
            InPlace { wave_seconds: 1e-4 }
        } else {
            ALL_AT_ONCE
        };
        let (image, stats) = render_on(accel.as_ref(), &waves, &tris, &options, &look(), None);
        assert!(stats.rays > 0);
        encode_exr(&image).unwrap()
    };
    let bvh = with(AccelKind::Mbvh8, false);
    assert_eq!(bvh, with(AccelKind::Dacrt, false));
    assert_eq!(bvh, with(AccelKind::Mbvh8, true));
}

/// Pixels whose camera rays cannot reach the scene's bounds get no rays: they show what a
/// traced miss shows, bit for bit, for every integrator and AOV, with waves of any size.
#[test]
fn pixels_outside_the_scenes_rectangle_are_the_misses_they_would_trace() {
    let tris = two_quads();
    let bounds = rayd::scene::bounds_of(&tris).unwrap();
    let far = far();
    let accel = build(AccelKind::Mbvh8, &tris, &BuildOptions::default()).unwrap();
    let integrators = [
        Integrator::Primary,
        Integrator::Normals,
        Integrator::Ao,
        Integrator::Path,
    ];
    // Seven samples: the outside pixels' sums are made once, beside runs of four and three.
    for (integrator, spp) in integrators.into_iter().flat_map(|i| [(i, 2), (i, 7)]) {
        let options = RenderOptions {
            width: 96,
            height: 64,
            spp,
            integrator,
            bounces: 2,
            seed: 3,
            sky: [0.7, 0.8, 1.1],
            aovs: all_aovs(),
            ..RenderOptions::default()
        };
        let cam = ViewCamera::choose_from(&far, &[], Some(bounds), 1.5).unwrap();
        let rect = cam.pixel_rect(&bounds, 96, 64);
        assert!(
            (rect.x1 - rect.x0) * (rect.y1 - rect.y0) < 96 * 64 / 2,
            "{rect:?}"
        );
        for waves in [ALL_AT_ONCE, InPlace { wave_seconds: 1e-5 }] {
            let go = |b: Option<&rayd::geometry::Aabb>| {
                render(&tris, accel.as_ref(), &cam, &options, b, None, None, &waves).unwrap()
            };
            let (culled, fewer) = go(Some(&bounds));
            let (traced, all) = go(None);
            assert!(fewer.rays < all.rays, "{integrator:?}");
            assert_eq!(
                encode_exr(&culled).unwrap(),
                encode_exr(&traced).unwrap(),
                "{integrator:?}"
            );
        }
    }
}

/// A pixel is the mean of its samples at any radiance f32 holds: a sky of 3e38 seen by 4
/// samples a pixel (whose f32 sum would be +inf) shows 3e38, traced or filled in as a miss.
#[test]
fn the_brightest_sky_is_its_own_mean() {
    let tris = two_quads();
    let options = RenderOptions {
        width: 24,
        height: 16,
        spp: 4,
        integrator: Integrator::Path,
        sky: [3e38, 1.0, 0.0],
        ..RenderOptions::default()
    };
    let img = render_with(&tris, &options, &look());
    let misses: Vec<_> = img
        .pixels
        .iter()
        .zip(&img.alpha)
        .filter(|(_, &a)| a == 0.0)
        .map(|(p, _)| *p)
        .collect();
    assert!(!misses.is_empty());
    for p in misses {
        assert_eq!(p, [3e38, 1.0, 0.0]);
    }
    assert!(img.pixels.iter().flatten().all(|x| x.is_finite()));
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
    render_on(
        accel.as_ref(),
        &ALL_AT_ONCE,
        tris,
        options,
        camera,
        Some(surfaces),
    )
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

/// The mean of a square image's pixels and the standard error of that mean, from the
/// spread of the pixels (each the mean of its own, independent samples).
fn mean_and_error(img: &Image) -> (f64, f64) {
    let v: Vec<f64> = img.pixels.iter().map(|p| p[0] as f64).collect();
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / (n - 1.0);
    (mean, (var / n).sqrt())
}

/// Irradiance at a point under the centre of a Lambertian emitter of radiance `l`, a
/// square of half-side `a` parallel to the receiver at height `h`: four rectangles with
/// a corner over the point, each of the view factor
/// F = 1/(2π) [X/√(1+X²) atan(Y/√(1+X²)) + Y/√(1+Y²) atan(X/√(1+Y²))], X = Y = a/h.
fn square_irradiance(l: f64, a: f64, h: f64) -> f64 {
    let x = a / h;
    let s = (1.0 + x * x).sqrt();
    let f = (2.0 * x / s * (x / s).atan()) / (2.0 * std::f64::consts::PI);
    std::f64::consts::PI * l * 4.0 * f
}

/// A floor (triangles 0, 1) of material 0 and a square emitter (triangles 2, 3) of
/// material 1 at height `h`, facing down.
fn floor_and_square(a: f32, h: f32) -> Vec<Triangle> {
    vec![
        tri([-50.0, 0.0, -50.0], [50.0, 0.0, 50.0], [50.0, 0.0, -50.0]),
        tri([-50.0, 0.0, -50.0], [-50.0, 0.0, 50.0], [50.0, 0.0, 50.0]),
        tri([-a, h, -a], [a, h, -a], [a, h, a]),
        tri([-a, h, -a], [a, h, a], [-a, h, a]),
    ]
}

fn surfaces_of(
    tris: &[Triangle],
    per_triangle: Vec<u32>,
    materials: Vec<rayd::scene::Material>,
    lights: Vec<PunctualLight>,
) -> Surfaces {
    let mut shading = rayd::scene::Shading::flat(tris.len());
    shading.materials = per_triangle;
    Surfaces::from_parts(shading, materials, Default::default(), lights)
}

/// An emissive square over a Lambertian floor: the floor under its centre shows
/// ρ/π · E with E the analytic irradiance, and next-event estimation with MIS and BRDF
/// sampling alone agree with it (and with each other) within their noise, MIS with less.
#[test]
fn an_emissive_square_lights_a_floor_with_the_analytic_irradiance() {
    let (rho, le, a, h) = (0.5f32, 4.0f32, 0.5f32, 1.0f32);
    let tris = floor_and_square(a, h);
    let emitter = rayd::scene::Material {
        base_color_factor: [0.0, 0.0, 0.0, 1.0],
        emissive_factor: [1.0; 3],
        emissive_strength: le,
        ..lambertian(0.0)
    };
    let surfaces = surfaces_of(
        &tris,
        vec![0, 0, 1, 1],
        vec![lambertian(rho), emitter],
        vec![],
    );
    // From the side, under the emitter: a narrow view of the floor's point (0, 0, 0).
    let camera = CameraChoice::LookAt {
        eye: [3.0, 0.5, 0.0],
        target: [0.0; 3],
        up: [0.0, 1.0, 0.0],
        fov: 0.01,
    };
    let want = rho as f64 / std::f64::consts::PI * square_irradiance(le as f64, a as f64, h as f64);
    let mut errors = Vec::new();
    for light_sampling in [true, false] {
        let options = RenderOptions {
            width: 16,
            height: 16,
            spp: 32,
            integrator: Integrator::Path,
            bounces: 1,
            seed: 21,
            sky: [0.0; 3],
            light_sampling,
            ..RenderOptions::default()
        };
        let img = render_surfaces(&tris, &options, &camera, &surfaces);
        let (mean, err) = mean_and_error(&img);
        assert!(
            (mean - want).abs() < 4.0 * err + 1e-3 * want,
            "light sampling {light_sampling}: {mean} ± {err}, want {want}"
        );
        errors.push((mean, err));
    }
    let ((m1, e1), (m2, e2)) = (errors[0], errors[1]);
    assert!(
        (m1 - m2).abs() < 4.0 * (e1 * e1 + e2 * e2).sqrt(),
        "{errors:?}"
    );
    assert!(
        e1 < e2,
        "MIS is no less noisy than BRDF sampling: {errors:?}"
    );
}

/// The furnace at scale: a white floor alone under a sky of 1 reflects exactly 1, however
/// large the floor and however far the camera. Rays that leave a surface start from a
/// point interpolated on its triangle, offset at the scale of its vertices; with hit points
/// taken as `origin + t·dir` and offset at the scale of the point, a 2 km floor seen from
/// eye height rendered 0.84 (0.88 at 2 bounces), and a 2 m quad seen from 1 km 0.76, as the
/// rays leaving it hit it again.
#[test]
fn a_lone_floor_reflects_the_sky_at_any_scale() {
    let floor = |s: f32| {
        vec![
            tri([-s, 0.0, -s], [s, 0.0, s], [s, 0.0, -s]),
            tri([-s, 0.0, -s], [-s, 0.0, s], [s, 0.0, s]),
        ]
    };
    let views = [
        // Eye height over floors of growing size, looking at the horizon.
        (1000.0, [0.3, 1.7, 0.2], [0.3, 0.0, -40.0]),
        (10000.0, [0.3, 1.7, 0.2], [0.3, 0.0, -40.0]),
        // A small floor from far away, looking down at it.
        (1.0, [0.0, 1000.0, 600.0], [0.0, 0.0, 0.0]),
        (1.0, [0.0, 2000.0, 1200.0], [0.0, 0.0, 0.0]),
    ];
    for (size, eye, target) in views {
        let tris = floor(size);
        let surfaces = Surfaces::uniform(tris.len(), lambertian(1.0), Vec::new());
        let fov = if size < 10.0 { 0.1 } else { 60.0 };
        for bounces in [1, 2] {
            let options = RenderOptions {
                width: 32,
                height: 24,
                spp: 4,
                integrator: Integrator::Path,
                bounces,
                seed: 5,
                sky: [1.0; 3],
                ..RenderOptions::default()
            };
            let camera = CameraChoice::LookAt {
                eye,
                target,
                up: [0.0, 1.0, 0.0],
                fov,
            };
            let img = render_surfaces(&tris, &options, &camera, &surfaces);
            let covered: Vec<_> = img
                .pixels
                .iter()
                .zip(&img.alpha)
                .filter(|(_, a)| **a == 1.0)
                .map(|(p, _)| p)
                .collect();
            assert!(covered.len() > 100, "{size} {eye:?}: {}", covered.len());
            for p in covered {
                for c in p {
                    assert!((c - 1.0).abs() < 1e-3, "{size} {eye:?} {bounces}: {p:?}");
                }
            }
        }
    }
}

/// The furnace under Russian roulette: every path may end after its first scattering, and
/// the survivors' weight keeps the mean at ρL.
#[test]
fn roulette_keeps_the_furnace_mean() {
    let (rho, sky) = (0.6f32, [1.0f32; 3]);
    let tris = cube(1.0);
    let surfaces = Surfaces::uniform(tris.len(), lambertian(rho), Vec::new());
    let camera = CameraChoice::LookAt {
        eye: [0.0, 0.0, 3.0],
        target: [0.0; 3],
        up: [0.0, 1.0, 0.0],
        fov: 20.0,
    };
    let options = RenderOptions {
        width: 16,
        height: 16,
        spp: 16,
        integrator: Integrator::Path,
        bounces: 4,
        seed: 8,
        sky,
        roulette: Some(1),
        ..RenderOptions::default()
    };
    let img = render_surfaces(&tris, &options, &camera, &surfaces);
    assert!(img.alpha.iter().all(|&a| a == 1.0));
    let (mean, err) = mean_and_error(&img);
    assert!(err > 0.0, "roulette made no noise: it never ended a path");
    assert!(
        (mean - rho as f64).abs() < 4.0 * err + 1e-4,
        "{mean} ± {err}"
    );
}

/// Sample positions: every sample uniform in its pixel over pixels, and a pixel's samples
/// one per column stratum.
#[test]
fn pixel_samples_are_stratified_and_uniform() {
    let spp = 16;
    for p in [0usize, 7, 1234] {
        let mut columns = [0u32; 16];
        for s in 0..spp {
            let (x, y) = rayd::render::pixel_sample(3, p, s, spp);
            assert!((0.0..1.0).contains(&x) && (0.0..1.0).contains(&y));
            columns[(x * spp as f64) as usize] += 1;
        }
        assert!(columns.iter().all(|&c| c == 1), "{columns:?}");
    }
    let n = 4000;
    let (mut mx, mut my) = (0.0, 0.0);
    for p in 0..n {
        let (x, y) = rayd::render::pixel_sample(5, p, 0, 1);
        mx += x / n as f64;
        my += y / n as f64;
    }
    assert!(
        (mx - 0.5).abs() < 0.02 && (my - 0.5).abs() < 0.02,
        "{mx} {my}"
    );
}

/// `alphaMode`: a `MASK` surface below its cutoff is not there for camera rays, shadow
/// rays or coverage, one above it is; a `BLEND` surface covers its alpha's share of the
/// samples and lets 1 − alpha of a light through.
#[test]
fn alpha_modes_cut_blend_and_shadow() {
    use rayd::scene::AlphaMode;
    let with_alpha = |alpha: f32, mode: AlphaMode| rayd::scene::Material {
        base_color_factor: [0.5, 0.5, 0.5, alpha],
        alpha_mode: mode,
        ..lambertian(0.5)
    };
    // Coverage of a lone quad seen head-on, filling the view.
    let quad = vec![
        tri([-9.0, -9.0, 0.0], [9.0, -9.0, 0.0], [9.0, 9.0, 0.0]),
        tri([-9.0, -9.0, 0.0], [9.0, 9.0, 0.0], [-9.0, 9.0, 0.0]),
    ];
    let camera = CameraChoice::LookAt {
        eye: [0.0, 0.0, 5.0],
        target: [0.0; 3],
        up: [0.0, 1.0, 0.0],
        fov: 30.0,
    };
    let coverage = |m: rayd::scene::Material, integrator| {
        let s = surfaces_of(&quad, vec![0, 0], vec![m], vec![]);
        let options = RenderOptions {
            width: 16,
            height: 16,
            spp: 8,
            integrator,
            bounces: 1,
            ..RenderOptions::default()
        };
        let img = render_surfaces(&quad, &options, &camera, &s);
        img.alpha.iter().map(|&a| a as f64).sum::<f64>() / img.alpha.len() as f64
    };
    for integrator in [Integrator::Primary, Integrator::Path] {
        let mask = |cutoff| AlphaMode::Mask { cutoff };
        assert_eq!(coverage(with_alpha(0.3, mask(0.5)), integrator), 0.0);
        assert_eq!(coverage(with_alpha(0.3, mask(0.2)), integrator), 1.0);
        assert_eq!(
            coverage(with_alpha(0.3, AlphaMode::Opaque), integrator),
            1.0
        );
        // 2048 samples of Bernoulli(0.25): standard deviation 0.01.
        let c = coverage(with_alpha(0.25, AlphaMode::Blend), integrator);
        assert!((c - 0.25).abs() < 0.04, "{integrator:?}: {c}");
    }

    // A point light over a floor, with a large quad between them at half height.
    let (rho, height, intensity) = (0.5f32, 2.0f32, 30.0f32);
    let mut tris = vec![
        tri([-50.0, 0.0, -50.0], [50.0, 0.0, 50.0], [50.0, 0.0, -50.0]),
        tri([-50.0, 0.0, -50.0], [-50.0, 0.0, 50.0], [50.0, 0.0, 50.0]),
    ];
    tris.push(tri([-5.0, 1.0, -5.0], [5.0, 1.0, -5.0], [5.0, 1.0, 5.0]));
    tris.push(tri([-5.0, 1.0, -5.0], [5.0, 1.0, 5.0], [-5.0, 1.0, 5.0]));
    let light = PunctualLight::Point {
        position: glam::Vec3::new(0.0, height, 0.0),
        intensity: glam::Vec3::splat(intensity),
        range: f32::INFINITY,
        cone: None,
    };
    // From below the occluder's height, looking at the floor's point (0, 0, 0.3).
    let camera = CameraChoice::LookAt {
        eye: [3.0, 0.4, 0.3],
        target: [0.0, 0.0, 0.3],
        up: [0.0, 1.0, 0.0],
        fov: 0.01,
    };
    let lit = |occluder: rayd::scene::Material| {
        let s = surfaces_of(
            &tris,
            vec![0, 0, 1, 1],
            vec![lambertian(rho), occluder],
            vec![light],
        );
        let options = RenderOptions {
            width: 1,
            height: 1,
            integrator: Integrator::Path,
            bounces: 1,
            sky: [0.0; 3],
            ..RenderOptions::default()
        };
        render_surfaces(&tris, &options, &camera, &s).pixels[0][0]
    };
    let r2 = 0.09 + height * height;
    let want = rho / std::f32::consts::PI * intensity * (height / r2.sqrt()) / r2;
    let open = lit(with_alpha(0.3, AlphaMode::Mask { cutoff: 0.5 }));
    assert!((open - want).abs() < 1e-3 * want, "{open} vs {want}");
    assert_eq!(lit(with_alpha(0.3, AlphaMode::Opaque)), 0.0);
    let half = lit(with_alpha(0.25, AlphaMode::Blend));
    assert!(
        (half - 0.75 * want).abs() < 1e-3 * want,
        "{half} vs {}",
        0.75 * want
    );
}

/// A floor tiled 64 times with a 256² checker of black and white texels, seen from above
/// so that a pixel spans hundreds of texels: with glTF's default sampler (trilinear MIP
/// mapping) every pixel's albedo is the checker's mean, half the light; a sampler whose
/// `minFilter` is `NEAREST` (no mipmaps) reads single texels, and the pixels alias to
/// black and white.
#[test]
fn minified_textures_are_filtered_unless_the_sampler_says_not_to() {
    use rayd::render::mipmap::Filtering;
    use rayd::render::texture::{Texels, TextureSet};
    use rayd::scene::{Filter, Mipmap, Sampler, TextureRef};
    let floor = vec![
        tri([-1.0, 0.0, -1.0], [1.0, 0.0, 1.0], [1.0, 0.0, -1.0]),
        tri([-1.0, 0.0, -1.0], [-1.0, 0.0, 1.0], [1.0, 0.0, 1.0]),
    ];
    let n = 256u32;
    let checker: Vec<[f32; 4]> = (0..n * n)
        .map(|i| {
            let v = ((i % n + i / n) % 2) as f32;
            [v, v, v, 1.0]
        })
        .collect();
    let texels = Texels::from_rgba(n, n, checker).unwrap();
    let corner = |x: f32, z: f32| glam::Vec2::new((x + 1.0) * 32.0, (z + 1.0) * 32.0);
    let camera = CameraChoice::LookAt {
        eye: [0.0, 2.0, 0.0],
        target: [0.0; 3],
        up: [0.0, 0.0, -1.0],
        fov: 40.0,
    };
    let albedo = |sampler: Sampler| -> Vec<f32> {
        let mut shading = rayd::scene::Shading::flat(floor.len());
        shading.materials = vec![0, 0];
        shading.uv0 = floor
            .iter()
            .flat_map(|t| t.v.map(|p| corner(p[0], p[2])))
            .collect();
        let material = rayd::scene::Material {
            base_color_texture: Some(TextureRef {
                texture: 0,
                tex_coord: 0,
                transform: None,
            }),
            ..lambertian(1.0)
        };
        let textures = TextureSet::from_texels(vec![(texels.clone(), Filtering::of(&sampler))]);
        let s = Surfaces::from_parts(shading, vec![material], textures, vec![]);
        let options = RenderOptions {
            width: 32,
            height: 32,
            integrator: Integrator::Path,
            bounces: 1,
            aovs: AovSet::of(&[rayd::render::Aov::Albedo]),
            ..RenderOptions::default()
        };
        let img = render_surfaces(&floor, &options, &camera, &s);
        let albedo = img.aovs.albedo.unwrap();
        albedo
            .iter()
            .zip(&img.alpha)
            .filter(|(_, &a)| a == 1.0)
            .map(|(c, _)| c[0])
            .collect()
    };
    let filtered = albedo(Sampler::default());
    assert!(filtered.len() > 500, "{}", filtered.len());
    for a in &filtered {
        assert!((a - 0.5).abs() < 0.02, "{a}");
    }
    let unfiltered = albedo(Sampler {
        min_filter: Some(Filter::Nearest),
        mipmap: Mipmap::None,
        ..Sampler::default()
    });
    assert!(unfiltered.iter().all(|&a| a == 0.0 || a == 1.0));
    let white = unfiltered.iter().filter(|&&a| a == 1.0).count();
    assert!(white > 100 && white + 100 < unfiltered.len(), "{white}");
}

/// A render's progress counts the pixels that trace rays, not every pixel of the image:
/// with the scene in a small rectangle of it, each step reports the share of the frame's
/// camera rays traced so far (counted by the pixel, a frame read a quarter done after its
/// rows of sky), and the waves hold about equal numbers of them.
#[test]
fn progress_counts_the_pixels_that_trace() {
    use rayd::accel::Query;
    use rayd::geometry::{Hit, Ray};
    use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};
    use std::sync::Mutex;

    struct Counting {
        inner: Box<dyn Intersector>,
        rays: AtomicUsize,
    }
    impl Intersector for Counting {
        fn name(&self) -> &'static str {
            self.inner.name()
        }
        fn trace(&self, rays: &[Ray], query: Query, hits: &mut [Hit]) {
            self.rays.fetch_add(rays.len(), Relaxed);
            self.inner.trace(rays, query, hits)
        }
        fn bytes(&self) -> usize {
            self.inner.bytes()
        }
    }
    struct Watch<'a> {
        rays: &'a AtomicUsize,
        seen: Mutex<Vec<(f64, usize)>>,
    }
    impl rayd::render::Waves for Watch<'_> {
        type Error = std::convert::Infallible;
        fn run_wave(&self, wave: &mut (dyn FnMut() + Send)) -> Result<(), Self::Error> {
            wave();
            Ok(())
        }
        fn wave_seconds(&self) -> f64 {
            1e-6
        }
        fn progress(&self, fraction: f64) {
            let rays = self.rays.load(Relaxed);
            self.seen.lock().unwrap().push((fraction, rays));
        }
    }

    let tris = two_quads();
    let bounds = rayd::scene::bounds_of(&tris).unwrap();
    let far = far();
    let (w, h, spp) = (320u32, 240u32, 2u32);
    let options = RenderOptions {
        width: w,
        height: h,
        spp,
        integrator: Integrator::Primary,
        ..RenderOptions::default()
    };
    let cam = ViewCamera::choose_from(&far, &[], Some(bounds), 320.0 / 240.0).unwrap();
    let rect = cam.pixel_rect(&bounds, w, h);
    assert!(
        rect.len() * 4 < (w * h) as usize && rect.y0 > h / 8,
        "{rect:?}"
    );
    let accel = Counting {
        inner: build(AccelKind::Mbvh8, &tris, &BuildOptions::default()).unwrap(),
        rays: AtomicUsize::new(0),
    };
    let watch = Watch {
        rays: &accel.rays,
        seen: Mutex::new(Vec::new()),
    };
    let (_, stats) = render(
        &tris,
        &accel,
        &cam,
        &options,
        Some(&bounds),
        None,
        None,
        &watch,
    )
    .unwrap();
    let total = rect.len() * spp as usize;
    assert_eq!(stats.rays as usize, total);
    let seen = watch.seen.into_inner().unwrap();
    assert!(seen.len() > 4, "{} steps", seen.len());
    let mut last = (0.0, 0);
    for &(fraction, rays) in &seen {
        let share = rays as f64 / total as f64;
        assert!(
            (fraction - share).abs() < 1e-9,
            "{fraction} after {rays} of {total} rays"
        );
        assert!(fraction >= last.0, "{seen:?}");
        // After the first (sized before any rate is known), every step but the last
        // traces the same number of camera rays: the smallest wave's, as these waves are
        // timed to a microsecond.
        if rays < total && last.1 > 0 {
            assert_eq!(rays - last.1, seen[1].1 - seen[0].1, "{seen:?}");
        }
        last = (fraction, rays);
    }
    assert_eq!(last, (1.0, total));
}
