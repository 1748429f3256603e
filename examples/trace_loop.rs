//! Traces a dumped benchmark ray set again and again with one accelerator, built once, so
//! that a profiler sees the traversal and not the build or the ray generation.
//!
//! ```text
//! rayd bench SCENE --sets diffuse2 --dump DIR ...          # writes DIR/<stem>-interior-diffuse2.ray
//! cargo run --release --example trace_loop -- SCENE DIR/<stem>-interior-diffuse2.ray mbvh8 sbvh 20
//! perf record -e cpu-clock target/release/examples/trace_loop ...
//! ```
//!
//! Arguments: scene, RAY1 files (of the interior view; comma-separated, each traced on the
//! same structures built once), accelerators (comma-separated; the passes alternate between
//! them), build quality, passes,
//! and optionally the thread count (default 1) and the precision (default watertight). Prints the median Mray/s of each.

use rayd::accel::{build, AccelKind, BuildOptions, BuildQuality, Precision, Query};
use rayd::bench::{CameraChoice, View, ViewKind};
use rayd::geometry::Hit;

/// CPU time of all the process's threads so far, in seconds (Linux `schedstat`; 0 where
/// unavailable). On a shared machine it is steadier than wall time: time spent waiting
/// for a core is not counted.
fn cpu_seconds() -> f64 {
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else {
        return 0.0;
    };
    dir.filter_map(|e| std::fs::read_to_string(e.ok()?.path().join("schedstat")).ok())
        .filter_map(|s| s.split_whitespace().next()?.parse::<f64>().ok())
        .sum::<f64>()
        * 1e-9
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 6 {
        eprintln!("usage: trace_loop SCENE RAYS ACCEL BUILD PASSES [THREADS]");
        std::process::exit(2);
    }
    let scene = rayd::formats::load_scene(args[1].as_ref(), &Default::default()).unwrap();
    let view = View::new(&scene, ViewKind::Interior, &CameraChoice::Auto, 1024, 768).unwrap();
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
        dacrt: rayd::accel::dacrt::DacrtTuning::from_env(),
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
    for path in args[2].split(',') {
        let rays = rayd::formats::binary::read_rays(&std::fs::read(path).unwrap()).unwrap();
        if args[2].contains(',') {
            println!("{path}:");
        }
        let mut hits = vec![vec![Hit::MISS; rays.len()]; accels.len()];
        // Passes alternate between the accelerators so that a noisy machine slows all alike.
        let mut times = vec![Vec::new(); accels.len()];
        let mut cpu = vec![Vec::new(); accels.len()];
        for _ in 0..passes {
            for (((a, t), c), h) in accels.iter().zip(&mut times).zip(&mut cpu).zip(&mut hits) {
                let (t0, c0) = (std::time::Instant::now(), cpu_seconds());
                pool.install(|| a.trace(&rays, Query::Closest, h));
                t.push(t0.elapsed().as_secs_f64());
                c.push(cpu_seconds() - c0);
            }
        }
        let mut first = None;
        for (((a, t), c), h) in accels.iter().zip(&mut times).zip(&mut cpu).zip(&hits) {
            t.sort_by(f64::total_cmp);
            c.sort_by(f64::total_cmp);
            let mray = rays.len() as f64 / t[t.len() / 2] / 1e6;
            let mray_cpu = rays.len() as f64 / c[c.len() / 2] / 1e6;
            let (base, base_cpu) = *first.get_or_insert((mray, mray_cpu));
            // The same checksum as scripts/tinybvh/harness.cpp prints, to compare the hits.
            let sum = h.iter().fold(0u64, |s, h| {
                s.wrapping_mul(1_000_003).wrapping_add(if h.is_hit() {
                    u64::from(h.prim) + 1
                } else {
                    0
                })
            });
            println!(
                "{:>8}: median {mray:.3} Mray/s (best {:.3}), {:.3}x the first; per CPU-second {mray_cpu:.3} Mray, {:.3}x; hits {}, checksum {sum:016x}",
                a.name(),
                rays.len() as f64 / t[0] / 1e6,
                mray / base,
                mray_cpu / base_cpu,
                h.iter().filter(|h| h.is_hit()).count()
            );
        }
    }
}
