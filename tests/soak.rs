//! A bounded soak of `rayd serve` (issue 11, item 7): concurrent uploads, small and large
//! traces, renders, geometry updates and cancellations for `RAYD_SOAK_SECS` seconds
//! (default 60, CI's minute), with the server killed (`kill -9`) and stopped cleanly
//! (SIGTERM) in turn every quarter of the run and started again on the same data
//! directory. Every answer is checked against the library's engine in this process (HIT1
//! bytes identical) or `rayd render`'s PNG; everything acknowledged before a restart must
//! answer the same after it; the only failures allowed are `503`s with `Retry-After` and
//! requests broken by a restart, both retried. The server's RSS is sampled every 250 ms
//! and, after the warm-up (the first quarter, at least 10 s), held to 1.5 × the warm-up
//! peak + 64 MiB, with `--cache-bytes` at 64 MiB, `--geometry-bytes` at 32 MiB and small traces choosing among version 1
//! and the 8 latest versions, so that the working set does not grow with the run. `RAYD_SOAK_CSV=FILE` writes the RSS samples for a plot
//! (`scripts/plot_soak.py`); the driver is `tests/common/load.rs`, which the load script
//! shares.

#[path = "common/load.rs"]
mod load;
#[path = "common/server.rs"]
mod server;

use std::time::Duration;

use load::{Kind, Plan, ServerProc};
use server::{scenes, BIN};

#[test]
fn soak() {
    let secs: u64 = std::env::var("RAYD_SOAK_SECS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(60);
    let dir = tempfile::tempdir().unwrap();
    let plan = Plan {
        bin: BIN.into(),
        scene: scenes().join("Fox.glb"),
        workers: 4,
        duration: Duration::from_secs(secs),
        weights: vec![
            (Kind::SmallTrace, 30),
            (Kind::LargeTrace, 5),
            (Kind::Render, 10),
            (Kind::Geometry, 10),
            (Kind::Cancel, 5),
            (Kind::Upload, 10),
        ],
        threads: 2,
        restart_every: Some(Duration::from_secs((secs / 4).max(5))),
        large_rays: 1 << 16,
        serve_args: Vec::new(),
    };
    // Small caches (structures and evaluated geometry), so that their budgets, not the
    // run's length, bound what they hold: every geometry update adds an evaluated version.
    let server = ServerProc::start(
        &plan.bin,
        &dir.path().join("data"),
        plan.threads,
        &[
            "--cache-bytes".to_string(),
            (64u64 << 20).to_string(),
            "--geometry-bytes".to_string(),
            (32u64 << 20).to_string(),
        ],
    )
    .expect("rayd serve starts");
    let fixture = load::Fixture::prepare(&plan, &server, dir.path()).expect("the fixture");
    let report = load::run(&plan, &server, &fixture);

    println!("soak: {secs} s, load average {}", load::load_average());
    print!("{}", report.table());
    let warm = (secs as f64 / 4.0).max(10.0);
    let peak_warm = report
        .rss
        .iter()
        .filter(|(t, _, _)| *t <= warm)
        .map(|(_, b, _)| *b)
        .max()
        .unwrap_or(0);
    let after: Vec<u64> = report
        .rss
        .iter()
        .filter(|(t, _, _)| *t > warm)
        .map(|(_, b, _)| *b)
        .collect();
    let peak_after = after.iter().copied().max().unwrap_or(0);
    let bound = peak_warm + peak_warm / 2 + (64 << 20);
    println!(
        "requests {}, errors {}, restarts {} kill -9 + {} SIGTERM, RSS warm-up peak {:.1} MiB, \
         later peak {:.1} MiB (bound {:.1} MiB), client CPU {:.1} s, server CPU {:.1} s",
        report.requests(),
        report.errors.len(),
        report.restarts.0,
        report.restarts.1,
        peak_warm as f64 / 1048576.0,
        peak_after as f64 / 1048576.0,
        bound as f64 / 1048576.0,
        report.client_cpu,
        report.server_cpu
    );
    if let Ok(csv) = std::env::var("RAYD_SOAK_CSV") {
        let mut out = String::from("seconds,rss_bytes,incarnation\n");
        for (t, b, i) in &report.rss {
            out.push_str(&format!("{t:.2},{b},{i}\n"));
        }
        std::fs::write(&csv, out).unwrap();
    }
    assert!(report.errors.is_empty(), "errors: {:#?}", report.errors);
    for kind in Kind::ALL {
        let answered = report.kinds.get(&kind).map_or(0, |k| k.latencies.len());
        assert!(answered > 0, "no {} was answered in {secs} s", kind.name());
    }
    assert!(
        report.restarts.0 >= 1 && report.restarts.1 >= 1,
        "{:?}",
        report.restarts
    );
    assert!(!after.is_empty(), "no RSS sample after the warm-up");
    assert!(
        peak_after <= bound,
        "RSS grew to {peak_after} bytes after a warm-up peak of {peak_warm}"
    );
}
