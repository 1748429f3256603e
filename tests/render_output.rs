//! The renderer's output against its contract (`proto/rendering.md`): EXR files that
//! OpenEXR's own library reads back channel by channel, equal to the renderer's buffers;
//! box-filtered pixels; the same image whatever the thread count; the default view.

use std::path::Path;
use std::process::Command;

use rayd::accel::{build, AccelKind, BuildOptions};
use rayd::geometry::Triangle;
use rayd::render::camera::{CameraChoice, ViewCamera};
use rayd::render::image::encode_exr;
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
    render(tris, accel.as_ref(), &cam, options, diag, &AllAtOnce)
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
