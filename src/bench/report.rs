//! Human-readable and CSV renderings of a [`BenchReport`].

use std::fmt::Write;

use super::BenchReport;

/// A Markdown table per scene and view: one row per accelerator and thread count, Mray/s
/// per ray set, build time, and the worst agreement with the reference.
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
        let _ = writeln!(s, " agreement |");
        let _ = write!(s, "|---|---:|---:|");
        for _ in &set_names {
            let _ = write!(s, "---:|");
        }
        let _ = writeln!(s, "---:|");
        for b in &sc.builds {
            let _ = write!(
                s,
                "| {} | {} | {:.1} |",
                b.accel,
                b.threads,
                b.seconds * 1e3
            );
            let mut worst: f64 = 1.0;
            for n in &set_names {
                match sc
                    .results
                    .iter()
                    .find(|m| m.accel == b.accel && m.threads == b.threads && m.set == *n)
                {
                    Some(m) => {
                        worst = worst.min(m.agreement);
                        let _ = write!(s, " {:.3} |", m.mrays_per_s);
                    }
                    None => {
                        let _ = write!(s, " – |");
                    }
                }
            }
            let _ = writeln!(s, " {:.6} |", worst);
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
