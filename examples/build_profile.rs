//! Builds one accelerator over a scene's interior view, for profiling the build alone
//! (`valgrind --tool=callgrind --toggle-collect='*profiled_build*'`).
//!
//! ```text
//! cargo run --release --features embree --example build_profile -- SCENE ACCEL QUALITY [THREADS]
//! ```

use rayd::accel::{build, AccelKind, BuildOptions, BuildQuality, Intersector};
use rayd::bench::{CameraChoice, View, ViewKind};
use rayd::geometry::Triangle;

#[inline(never)]
fn profiled_build(
    kind: AccelKind,
    tris: &[Triangle],
    options: &BuildOptions,
) -> Box<dyn Intersector> {
    build(kind, tris, options).unwrap()
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let scene = rayd::formats::load_scene(args[1].as_ref(), &Default::default()).unwrap();
    let view = View::new(&scene, ViewKind::Interior, &CameraChoice::Auto, 1024, 768).unwrap();
    let kind = AccelKind::parse(&args[2]).unwrap();
    let quality = [BuildQuality::Fast, BuildQuality::Sah, BuildQuality::Sbvh]
        .into_iter()
        .find(|q| q.name() == args[3])
        .unwrap();
    let threads: usize = args.get(4).map_or(1, |t| t.parse().unwrap());
    let options = BuildOptions {
        quality,
        threads,
        dacrt: rayd::accel::dacrt::DacrtTuning::from_env(),
        ..BuildOptions::default()
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let t0 = std::time::Instant::now();
    let accel = pool.install(|| profiled_build(kind, &view.triangles, &options));
    eprintln!(
        "{} {}: {} triangles, built in {:.1} ms, {} bytes",
        args[2],
        args[3],
        view.triangles.len(),
        t0.elapsed().as_secs_f64() * 1e3,
        accel.bytes()
    );
}
