//! Traces a dumped benchmark ray set again and again with one accelerator, built once, so
//! that a profiler sees the traversal and not the build or the ray generation.
//!
//! ```text
//! rayd bench SCENE --sets diffuse2 --dump DIR ...          # writes DIR/<stem>-interior-diffuse2.ray
//! cargo run --release --example trace_loop -- SCENE DIR/<stem>-interior-diffuse2.ray mbvh8 sbvh 20
//! perf record -e cpu-clock target/release/examples/trace_loop ...
//! ```
//!
//! Arguments: scene, RAY1 file (of the interior view), accelerators (comma-separated; the
//! passes alternate between them), build quality, passes,
//! and optionally the thread count (default 1) and the precision (default watertight). Prints the median Mray/s of each.

use rayd::accel::{build, AccelKind, BuildOptions, BuildQuality, Precision, Query};
use rayd::bench::{CameraChoice, View, ViewKind};
use rayd::geometry::Hit;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 6 {
        eprintln!("usage: trace_loop SCENE RAYS ACCEL BUILD PASSES [THREADS]");
        std::process::exit(2);
    }
    let scene = rayd::formats::load_scene(args[1].as_ref(), &Default::default()).unwrap();
    let view = View::new(&scene, ViewKind::Interior, &CameraChoice::Auto, 1024, 768).unwrap();
    let rays = rayd::formats::binary::read_rays(&std::fs::read(&args[2]).unwrap()).unwrap();
    let quality = match args[4].as_str() {
        "fast" => BuildQuality::Fast,
        "sah" => BuildQuality::Sah,
        _ => BuildQuality::Sbvh,
    };
    let passes: usize = args[5].parse().unwrap();
    let threads: usize = args.get(6).map_or(1, |s| s.parse().unwrap());
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let options = BuildOptions {
        quality,
        precision: match args.get(7).map(String::as_str) {
            Some("fast") => Precision::Fast,
            _ => Precision::Watertight,
        },
        threads,
    };
    let kinds: Vec<AccelKind> = args[3]
        .split(',')
        .map(|a| AccelKind::parse(a).expect("accelerator"))
        .collect();
    let accels: Vec<_> = kinds
        .iter()
        .map(|&k| {
            pool.install(|| build(k, &view.triangles, &options))
                .unwrap()
        })
        .collect();
    let mut hits = vec![Hit::MISS; rays.len()];
    // Passes alternate between the accelerators so that a noisy machine slows all alike.
    let mut times = vec![Vec::new(); accels.len()];
    for _ in 0..passes {
        for (a, t) in accels.iter().zip(&mut times) {
            let t0 = std::time::Instant::now();
            pool.install(|| a.trace(&rays, Query::Closest, &mut hits));
            t.push(t0.elapsed().as_secs_f64());
        }
    }
    let mut first = None;
    for (a, t) in accels.iter().zip(&mut times) {
        t.sort_by(f64::total_cmp);
        let mray = rays.len() as f64 / t[t.len() / 2] / 1e6;
        let base = *first.get_or_insert(mray);
        println!(
            "{:>8}: median {mray:.3} Mray/s (best {:.3}), {:.3}x the first",
            a.name(),
            rays.len() as f64 / t[0] / 1e6,
            mray / base
        );
    }
}
