//! The service under load, run by hand (`scripts/load.sh`; BENCHMARKS.md §12.6). It starts
//! `target/release/rayd serve` on a free loopback port with a temporary data directory and
//! drives it with the soak test's driver (`tests/common/load.rs`), so that the load test
//! and the soak check answers the same way.
//!
//! ```text
//! load mix  SCENE [--workers N] [--seconds S] [--threads T] [--large-rays N]
//!                 [--restart-every S] [--rss-csv FILE] [--bin PATH]
//! load goal SCENE [--clients N] [--batches B] [--rays N] [--threads T] [--bin PATH]
//! ```
//!
//! - `mix`: N concurrent clients for S seconds, a weighted mix of 1K-ray traces, large
//!   traces, small renders, geometry updates, cancelled renders and uploads; every answer
//!   checked against the engine in this process. Prints the per-kind table (throughput,
//!   p50/p95/p99) and exits 1 on any error other than a `503` with `Retry-After`.
//! - `goal`: the issue's goal, N clients (8) each sending B batches of N rays (256K) at
//!   once; their total rate against one in-process trace of the same batch on the same
//!   threads (`trace_seconds`, median of 3), and the CPU seconds of the clients (this
//!   process) and of the server.

#[path = "../tests/common/load.rs"]
mod load;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use load::{Kind, Plan, ServerProc};

struct Opts {
    mode: String,
    scene: PathBuf,
    workers: usize,
    seconds: u64,
    threads: usize,
    large_rays: usize,
    restart_every: Option<u64>,
    rss_csv: Option<PathBuf>,
    clients: usize,
    batches: usize,
    rays: usize,
    bin: PathBuf,
}

const USAGE: &str = "usage: load mix|goal SCENE [--workers N] [--seconds S] [--threads T] \
[--large-rays N] [--restart-every S] [--rss-csv FILE] [--clients N] [--batches B] [--rays N] \
[--bin PATH]";

impl Opts {
    fn parse(args: &[String]) -> Result<Opts, String> {
        let mut o = Opts {
            mode: String::new(),
            scene: PathBuf::new(),
            workers: 8,
            seconds: 60,
            threads: 2,
            large_rays: 1 << 18,
            restart_every: None,
            rss_csv: None,
            clients: 8,
            batches: 4,
            rays: 1 << 18,
            bin: Path::new(env!("CARGO_MANIFEST_DIR")).join("target/release/rayd"),
        };
        let mut pos = Vec::new();
        let mut it = args.iter();
        while let Some(a) = it.next() {
            let mut value = || {
                it.next()
                    .cloned()
                    .ok_or_else(|| format!("{a} needs a value"))
            };
            let num = |v: String| {
                v.parse::<usize>()
                    .map_err(|_| format!("{a} {v:?} is not a whole number"))
            };
            match a.as_str() {
                "--workers" => o.workers = num(value()?)?,
                "--seconds" => o.seconds = num(value()?)? as u64,
                "--threads" => o.threads = num(value()?)?,
                "--large-rays" => o.large_rays = num(value()?)?,
                "--restart-every" => o.restart_every = Some(num(value()?)? as u64),
                "--rss-csv" => o.rss_csv = Some(value()?.into()),
                "--clients" => o.clients = num(value()?)?,
                "--batches" => o.batches = num(value()?)?,
                "--rays" => o.rays = num(value()?)?,
                "--bin" => o.bin = value()?.into(),
                s if s.starts_with("--") => return Err(format!("unknown option {s}")),
                s => pos.push(s.to_string()),
            }
        }
        let mut pos = pos.into_iter();
        o.mode = pos.next().ok_or("no mode")?;
        o.scene = pos.next().ok_or("no scene")?.into();
        if o.workers == 0 || o.clients == 0 || o.batches == 0 || o.rays == 0 || o.seconds == 0 {
            return Err("counts and --seconds must be at least 1".into());
        }
        Ok(o)
    }
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let o = Opts::parse(&args).unwrap_or_else(|e| {
        eprintln!("load: {e}\n\n{USAGE}");
        std::process::exit(2);
    });
    let result = match o.mode.as_str() {
        "mix" => mix(&o),
        "goal" => goal(&o),
        m => Err(format!("unknown mode {m:?}")),
    };
    match result {
        Ok(true) => {}
        Ok(false) => std::process::exit(1),
        Err(e) => {
            eprintln!("load: {e}");
            std::process::exit(1);
        }
    }
}

/// A directory removed when dropped.
struct TempDir(PathBuf);

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn temp_dir() -> Result<TempDir, String> {
    let p = std::env::temp_dir().join(format!("rayd-load-{}", std::process::id()));
    std::fs::create_dir_all(&p).map_err(|e| format!("cannot create {}: {e}", p.display()))?;
    Ok(TempDir(p))
}

fn mix(o: &Opts) -> Result<bool, String> {
    let work = temp_dir()?;
    let plan = Plan {
        bin: o.bin.clone(),
        scene: o.scene.clone(),
        workers: o.workers,
        duration: Duration::from_secs(o.seconds),
        weights: vec![
            (Kind::SmallTrace, 40),
            (Kind::LargeTrace, 10),
            (Kind::Render, 15),
            (Kind::Geometry, 10),
            (Kind::Cancel, 10),
            (Kind::Upload, 5),
        ],
        threads: o.threads,
        restart_every: o.restart_every.map(Duration::from_secs),
        large_rays: o.large_rays,
        serve_args: Vec::new(),
    };
    let server = ServerProc::start(&plan.bin, &work.0.join("data"), plan.threads, &[])?;
    eprintln!("load: preparing the expected answers in process");
    let fx = load::Fixture::prepare(&plan, &server, &work.0)?;
    eprintln!(
        "load: {} clients for {} s against {} (load average {})",
        o.workers,
        o.seconds,
        o.scene.display(),
        load::load_average()
    );
    let report = load::run(&plan, &server, &fx);
    print!("{}", report.table());
    let peak = report.rss.iter().map(|r| r.1).max().unwrap_or(0);
    println!(
        "\n{} requests in {:.1} s, {} errors, restarts {:?}, server peak RSS {:.1} MiB, \
         client CPU {:.1} s, server CPU {:.1} s, load average {}",
        report.requests(),
        report.seconds,
        report.errors.len(),
        report.restarts,
        peak as f64 / 1048576.0,
        report.client_cpu,
        report.server_cpu,
        load::load_average()
    );
    if let Some(csv) = &o.rss_csv {
        let mut out = String::from("seconds,rss_bytes,incarnation\n");
        for (t, b, i) in &report.rss {
            out.push_str(&format!("{t:.2},{b},{i}\n"));
        }
        std::fs::write(csv, out).map_err(|e| format!("{}: {e}", csv.display()))?;
    }
    for e in report.errors.iter().take(20) {
        eprintln!("error: {e}");
    }
    Ok(report.errors.is_empty())
}

fn goal(o: &Opts) -> Result<bool, String> {
    let work = temp_dir()?;
    let scene = rayd::formats::load_scene(&o.scene, &Default::default())
        .map_err(|e| format!("{}: {e}", o.scene.display()))?;
    let bounds = scene.bounds().ok_or("the scene has no triangles")?;
    let rays = load::rays_at(&bounds, o.rays, 7);
    let body = rayd::formats::binary::write_rays(&rays);
    let engine = rayd::jobs::Engine::new(rayd::jobs::EngineOptions {
        threads: o.threads,
        ..Default::default()
    })
    .map_err(|e| e.to_string())?;
    let geometry = rayd::jobs::Geometry {
        key: rayd::jobs::GeometryKey::new("goal", 1, None),
        triangles: std::sync::Arc::new(scene.triangles),
        forgets: 0,
    };
    let request = rayd::jobs::TraceRequest {
        accel: rayd::accel::AccelKind::Mbvh8,
        ..Default::default()
    };
    let server = ServerProc::start(&o.bin, &work.0.join("data"), o.threads, &[])?;
    let bytes = std::fs::read(&o.scene).map_err(|e| e.to_string())?;
    let up = load::request(
        &server.addr,
        "POST",
        "/v1/scenes",
        "model/gltf-binary",
        &bytes,
    )
    .map_err(|e| e.to_string())?;
    let id = up.json()["id"].as_str().ok_or("no scene id")?.to_string();
    let path = format!("/v1/scenes/{id}/trace?accel=mbvh8");
    let octet = "application/octet-stream";
    // Warm both: the structure is built and cached by the first trace on each side.
    let (want, _) = engine
        .trace(&geometry, &rays, &request, 0, &engine.detached())
        .map_err(|e| e.to_string())?;
    let want = want.as_ref().to_vec();
    let warm =
        load::request(&server.addr, "POST", &path, octet, &body).map_err(|e| e.to_string())?;
    if warm.status != 200 || warm.body != want {
        return Err(format!(
            "the warm-up trace answered {} or differs",
            warm.status
        ));
    }
    let mut in_process = Vec::new();
    for _ in 0..3 {
        let (_, report) = engine
            .trace(&geometry, &rays, &request, 0, &engine.detached())
            .map_err(|e| e.to_string())?;
        in_process.push(report.trace_seconds);
    }
    in_process.sort_by(f64::total_cmp);
    let one = in_process[1];
    drop(engine);
    let load_before = load::load_average();
    let cpu0 = load::cpu_seconds("self");
    let server_cpu0 = server.cpu();
    let t0 = Instant::now();
    let results: Vec<Result<(u64, Vec<f64>), String>> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..o.clients)
            .map(|_| {
                s.spawn(|| {
                    let mut lat = Vec::new();
                    let mut refused = 0;
                    let mut done = 0;
                    while done < o.batches {
                        let t = Instant::now();
                        let a = load::request(&server.addr, "POST", &path, octet, &body)
                            .map_err(|e| e.to_string())?;
                        if a.status == 503 && a.header("retry-after").is_some() {
                            refused += 1;
                            std::thread::sleep(Duration::from_millis(50));
                            continue;
                        }
                        if a.status != 200 || a.body != want {
                            return Err(format!("a trace answered {} or differs", a.status));
                        }
                        lat.push(t.elapsed().as_secs_f64());
                        done += 1;
                    }
                    Ok((refused, lat))
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let wall = t0.elapsed().as_secs_f64();
    let client_cpu = load::cpu_seconds("self") - cpu0;
    let server_cpu = server.cpu() - server_cpu0;
    let mut lat = Vec::new();
    let mut refused = 0;
    for r in results {
        let (n, l) = r?;
        refused += n;
        lat.extend(l);
    }
    lat.sort_by(f64::total_cmp);
    let total_rays = (o.clients * o.batches * o.rays) as f64;
    let service = total_rays / wall / 1e6;
    let single = o.rays as f64 / one / 1e6;
    println!(
        "| scene | clients | rays/batch | batches | thr | service Mray/s | in-process Mray/s | ratio | p50 s | p99 s | 503s | client CPU s | server CPU s | wall s | load |\n\
         |---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"
    );
    println!(
        "| {} | {} | {} | {} | {} | {:.2} | {:.2} | {:.2} | {:.2} | {:.2} | {} | {:.1} | {:.1} | {:.1} | {}–{} |",
        o.scene.file_name().unwrap_or_default().to_string_lossy(),
        o.clients,
        o.rays,
        o.batches,
        o.threads,
        service,
        single,
        service / single,
        load::percentile(&lat, 50.0),
        load::percentile(&lat, 99.0),
        refused,
        client_cpu,
        server_cpu,
        wall,
        load_before,
        load::load_average()
    );
    Ok(true)
}
