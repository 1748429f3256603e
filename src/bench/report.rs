//! Human-readable and CSV renderings of a [`BenchReport`].

use std::fmt::Write;

use super::{BenchReport, DynamicReport, FrameSeries};

/// A Markdown table per scene and view: one row per accelerator and thread count, Mray/s
/// per ray set, build time, the worst agreement with the reference, and how many
/// disagreeing rays (over all sets) are not edge cases.
pub fn render_table(report: &BenchReport) -> String {
    let mut s = String::new();
    for sc in &report.scenes {
        let _ = writeln!(
            s,
            "\n{} — {} triangles ({} traced), {} view, {}, {}×{}, reference {}, median of {} runs",
            sc.scene,
            sc.triangles,
            sc.traced_triangles,
            sc.view,
            sc.camera,
            report.resolution[0],
            report.resolution[1],
            sc.reference,
            report.runs
        );
        let set_names: Vec<&str> = sc.sets.iter().map(|(n, _)| n.as_str()).collect();
        let _ = write!(s, "\n| accel | threads | build ms |");
        for n in &set_names {
            let _ = write!(s, " {n} Mray/s |");
        }
        let _ = writeln!(s, " agreement | unexplained |");
        let _ = write!(s, "|---|---:|---:|");
        for _ in &set_names {
            let _ = write!(s, "---:|");
        }
        let _ = writeln!(s, "---:|---:|");
        for b in &sc.builds {
            let _ = write!(
                s,
                "| {} | {} | {:.1} |",
                b.accel,
                b.threads,
                b.seconds * 1e3
            );
            let mut worst: f64 = 1.0;
            let mut unexplained = 0;
            for n in &set_names {
                match sc
                    .results
                    .iter()
                    .find(|m| m.accel == b.accel && m.threads == b.threads && m.set == *n)
                {
                    Some(m) => {
                        worst = worst.min(m.agreement);
                        unexplained += m.disagreements - m.edge_disagreements;
                        let _ = write!(s, " {:.3} |", m.mrays_per_s);
                    }
                    None => {
                        let _ = write!(s, " – |");
                    }
                }
            }
            let _ = writeln!(s, " {:.6} | {unexplained} |", worst);
        }
        let mut shown: Vec<&str> = Vec::new();
        for b in &sc.builds {
            let Some(st) = &b.stats else { continue };
            if shown.contains(&b.accel.as_str()) {
                continue;
            }
            if shown.is_empty() {
                let _ = writeln!(s, "\nstructure: multi-nodes, node SIMD utilisation, packs, pack lane utilisation, SAH cost, depth, bytes per triangle\n");
                let _ = writeln!(
                    s,
                    "| accel | nodes | node util | packs | pack util | SAH | depth | B/tri |"
                );
                let _ = writeln!(s, "|---|---:|---:|---:|---:|---:|---:|---:|");
            }
            shown.push(&b.accel);
            let f = |k: &str| st[k].as_f64().unwrap_or(f64::NAN);
            let _ = writeln!(
                s,
                "| {} | {} | {:.3} | {} | {:.3} | {:.1} | {} | {:.1} |",
                b.accel,
                f("nodes"),
                f("node_utilization"),
                f("packs"),
                f("pack_utilization"),
                f("sah_cost"),
                f("max_depth"),
                f("bytes_per_triangle")
            );
        }
        let counted: Vec<&super::Measurement> =
            sc.results.iter().filter(|m| m.steps.is_some()).collect();
        if !counted.is_empty() {
            let _ = writeln!(
                s,
                "\nper ray (first 65,536 rays of each set): multi-nodes visited / 8-lane triangle packs tested\n"
            );
            let _ = write!(s, "| accel |");
            for n in &set_names {
                let _ = write!(s, " {n} |");
            }
            let _ = writeln!(s);
            let _ = write!(s, "|---|");
            for _ in &set_names {
                let _ = write!(s, "---:|");
            }
            let _ = writeln!(s);
            let mut accels: Vec<&str> = Vec::new();
            for m in &counted {
                if !accels.contains(&m.accel.as_str()) {
                    accels.push(&m.accel);
                }
            }
            for a in accels {
                let _ = write!(s, "| {a} |");
                for n in &set_names {
                    match counted.iter().find(|m| m.accel == a && m.set == *n) {
                        Some(m) => {
                            let st = m.steps.as_ref().expect("filtered");
                            let _ = write!(
                                s,
                                " {:.1} / {:.1} |",
                                st["nodes_per_ray"].as_f64().unwrap_or(0.0),
                                st["packs_per_ray"].as_f64().unwrap_or(0.0)
                            );
                        }
                        None => {
                            let _ = write!(s, " – |");
                        }
                    }
                }
                let _ = writeln!(s);
            }
        }
    }
    s
}

/// One CSV line per measurement.
pub fn render_csv(report: &BenchReport) -> String {
    let mut s = String::from(
        "scene,triangles,view,accel,threads,set,rays,seconds,mrays_per_s,agreement,build_seconds\n",
    );
    for sc in &report.scenes {
        for m in &sc.results {
            let build = sc
                .builds
                .iter()
                .find(|b| b.accel == m.accel && b.threads == m.threads)
                .map_or(f64::NAN, |b| b.seconds);
            let _ = writeln!(
                s,
                "{},{},{},{},{},{},{},{:.6},{:.4},{:.6},{:.6}",
                sc.scene,
                sc.triangles,
                sc.view,
                m.accel,
                m.threads,
                m.set,
                m.rays,
                m.seconds,
                m.mrays_per_s,
                m.agreement,
                build
            );
        }
    }
    s
}

/// The dynamic benchmark as Markdown: per scene, set and thread count, one row per
/// strategy with its median preparation time and, for each rays-per-frame count, the
/// median frame time (preparation + trace) and the trace rate; then, per scene and set,
/// how the refitted structures' tracing compares with a rebuild frame by frame (at the
/// largest rays-per-frame count and the first thread count).
pub fn render_dynamic_table(report: &DynamicReport) -> String {
    let mut s = String::new();
    for sc in &report.scenes {
        let _ = writeln!(
            s,
            "\n{} — {} triangles (+12 room), {}, build {}, {}",
            sc.scene, sc.triangles, sc.motion, report.build, report.precision
        );
        let mut sets: Vec<&str> = Vec::new();
        let mut threads: Vec<usize> = Vec::new();
        let mut rays: Vec<usize> = Vec::new();
        let mut strategies: Vec<(&str, &str)> = Vec::new();
        for f in &sc.series {
            if !sets.contains(&f.set.as_str()) {
                sets.push(&f.set);
            }
            if !threads.contains(&f.threads) {
                threads.push(f.threads);
            }
            if !rays.contains(&f.rays) {
                rays.push(f.rays);
            }
            if !strategies.contains(&(f.accel.as_str(), f.mode.as_str())) {
                strategies.push((&f.accel, &f.mode));
            }
        }
        let find = |a: &str, m: &str, t: usize, set: &str, r: usize| {
            sc.series.iter().find(|f| {
                f.accel == a && f.mode == m && f.threads == t && f.set == set && f.rays == r
            })
        };
        for set in &sets {
            for &t in &threads {
                let _ = writeln!(
                    s,
                    "\n{set} rays, {t} thread(s): frame ms = prep + trace (trace Mray/s)\n"
                );
                let _ = write!(s, "| accel | per frame | prep ms |");
                for r in &rays {
                    let _ = write!(s, " {r} rays |");
                }
                let _ = writeln!(s, " agreement |");
                let _ = write!(s, "|---|---|---:|");
                for _ in &rays {
                    let _ = write!(s, "---:|");
                }
                let _ = writeln!(s, "---:|");
                for &(a, m) in &strategies {
                    let Some(first) = rays.iter().find_map(|&r| find(a, m, t, set, r)) else {
                        continue;
                    };
                    let _ = write!(
                        s,
                        "| {a} | {m} | {:.1} |",
                        first.median_update_seconds * 1e3
                    );
                    let mut worst: f64 = 1.0;
                    for &r in &rays {
                        match find(a, m, t, set, r) {
                            Some(f) => {
                                worst = worst.min(f.agreement);
                                let rate = if f.median_trace_seconds > 0.0 {
                                    f.rays as f64 / f.median_trace_seconds / 1e6
                                } else {
                                    0.0
                                };
                                let _ = write!(
                                    s,
                                    " {:.1} ({:.2}) |",
                                    f.median_frame_seconds * 1e3,
                                    rate
                                );
                            }
                            None => {
                                let _ = write!(s, " – |");
                            }
                        }
                    }
                    let _ = writeln!(s, " {worst:.6} |");
                }
            }
        }
        if !sc.auto.is_empty() {
            let _ = writeln!(
                s,
                "\nauto (picks among our cores by its cost model; frame ms of its pick and of the fastest)\n"
            );
            let _ = writeln!(
                s,
                "| set | threads | rays | geometry | auto picks | ms | fastest | ms | cost |"
            );
            let _ = writeln!(s, "|---|---:|---:|---|---|---:|---|---:|---:|");
            for p in &sc.auto {
                let _ = writeln!(
                    s,
                    "| {} | {} | {} | {} | {} | {:.1} | {} | {:.1} | {:.2}× |",
                    p.set,
                    p.threads,
                    p.rays,
                    p.geometry,
                    p.picked,
                    p.picked_seconds * 1e3,
                    p.fastest,
                    p.fastest_seconds * 1e3,
                    p.picked_seconds / p.fastest_seconds
                );
            }
        }
        // Refit against rebuild, frame by frame.
        let (Some(&t), Some(&r)) = (threads.first(), rays.iter().max()) else {
            continue;
        };
        for set in &sets {
            let pairs: Vec<(&FrameSeries, &FrameSeries)> = strategies
                .iter()
                .filter(|(_, m)| *m == "refit")
                .filter_map(|&(a, _)| {
                    Some((find(a, "rebuild", t, set, r)?, find(a, "refit", t, set, r)?))
                })
                .collect();
            if pairs.is_empty() {
                continue;
            }
            let _ = writeln!(
                s,
                "\nrefit vs rebuild, {set} rays, {r} rays, {t} thread(s): trace ms per frame (refit/rebuild)\n"
            );
            let _ = write!(s, "| frame |");
            for (b, _) in &pairs {
                let _ = write!(s, " {} rebuild | {} refit |", b.accel, b.accel);
            }
            let _ = writeln!(s);
            let _ = write!(s, "|---:|");
            for _ in &pairs {
                let _ = write!(s, "---:|---:|");
            }
            let _ = writeln!(s);
            for f in 0..sc.frames {
                let _ = write!(s, "| {f} |");
                for (b, fit) in &pairs {
                    let (x, y) = (b.trace_seconds[f], fit.trace_seconds[f]);
                    let _ = write!(s, " {:.1} | {:.1} ({:.2}×) |", x * 1e3, y * 1e3, y / x);
                }
                let _ = writeln!(s);
            }
        }
    }
    let picks: Vec<&super::AutoPick> = report.scenes.iter().flat_map(|sc| &sc.auto).collect();
    if !picks.is_empty() {
        let right = picks.iter().filter(|p| p.picked == p.fastest).count();
        let costs: Vec<f64> = picks
            .iter()
            .filter(|p| p.picked != p.fastest)
            .map(|p| p.picked_seconds / p.fastest_seconds)
            .collect();
        let worst = costs.iter().copied().fold(1.0f64, f64::max);
        let mean = if costs.is_empty() {
            1.0
        } else {
            costs.iter().sum::<f64>() / costs.len() as f64
        };
        let _ = writeln!(
            s,
            "\nauto picked the fastest of its candidates in {right} of {} situations; its wrong picks took {mean:.2}× the fastest's frame time on average, {worst:.2}× at worst",
            picks.len()
        );
    }
    let unmeasured: Vec<&String> = report
        .scenes
        .iter()
        .flat_map(|sc| &sc.auto_unmeasured)
        .collect();
    if !unmeasured.is_empty() {
        let _ = writeln!(
            s,
            "\nnot scored ({} situation(s): auto's pick was not measured; name it with --accel): {}",
            unmeasured.len(),
            unmeasured.iter().map(|u| u.as_str()).collect::<Vec<_>>().join("; ")
        );
    }
    s
}
