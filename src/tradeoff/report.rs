//! A trade-off run written out three ways: CSV for tools, a Markdown table for
//! BENCHMARKS.md, and a PNG plot of error against time with the Pareto front marked.
//!
//! The plot is drawn by plotters' bitmap backend into our own RGB buffer and encoded by the
//! `png` crate the renderer already uses; its text is set in DejaVu Sans, embedded through
//! the `dejavu` crate, so that drawing needs no system font library.

use std::fmt::Write as _;
use std::sync::OnceLock;

use plotters::prelude::*;

use super::{Axis, Report, TradeoffError};

/// CSV columns, in order.
const COLUMNS: [&str; 17] = [
    "axis",
    "setting",
    "spp",
    "bounces",
    "accel",
    "build",
    "precision",
    "seconds",
    "prepare_seconds",
    "trace_seconds",
    "shade_seconds",
    "rays",
    "rmse",
    "rel_mse",
    "psnr",
    "pareto",
    "threads",
];

/// One CSV field, quoted when it holds a comma, a quote or a line break (RFC 4180).
fn field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// The rows as CSV with a header line; times in seconds, PSNR in dB (`inf` for an image
/// equal to the reference).
pub fn csv(report: &Report) -> String {
    let mut out = COLUMNS.join(",");
    out.push('\n');
    for r in &report.rows {
        let cells = [
            r.axis.to_string(),
            r.setting.clone(),
            r.spp.to_string(),
            r.bounces.to_string(),
            r.accel.to_string(),
            r.build.to_string(),
            r.precision.to_string(),
            format!("{:.6}", r.seconds),
            format!("{:.6}", r.prepare_seconds),
            format!("{:.6}", r.trace_seconds),
            format!("{:.6}", r.shade_seconds),
            r.rays.to_string(),
            format!("{:.6e}", r.errors.rmse),
            format!("{:.6e}", r.errors.rel_mse),
            format!("{:.3}", r.errors.psnr),
            r.pareto.to_string(),
            report.threads.to_string(),
        ];
        let line: Vec<String> = cells.iter().map(|c| field(c)).collect();
        out.push_str(&line.join(","));
        out.push('\n');
    }
    out
}

/// Seconds to four significant digits at least, so that a tiny frame's times are not all
/// `0.000` (three decimals from a second up).
fn secs(x: f64) -> String {
    if !(x.is_finite() && x > 0.0) || x >= 1.0 {
        return format!("{x:.3}");
    }
    let decimals = (3 - x.log10().floor() as i32).clamp(3, 12) as usize;
    format!("{x:.decimals$}")
}

/// The rows as a Markdown table, fastest first, with a line saying what was measured.
pub fn markdown(report: &Report) -> String {
    let mut out = String::new();
    let r = &report.reference;
    let _ = writeln!(
        out,
        "{}, {}×{}, {} thread(s); reference: {} spp, {} bounces, seed {} ({} s, mean radiance {:.4}). \
         Time is the frame's build + trace + shade; ★ marks the Pareto front of time and RMSE.\n",
        report.scene,
        report.width,
        report.height,
        report.threads,
        r.spp,
        r.bounces,
        r.seed,
        secs(r.seconds),
        r.mean
    );
    out.push_str(
        "| axis | setting | spp | bounces | accel | build | precision | seconds | of which trace | RMSE | relMSE | PSNR (dB) | front |\n",
    );
    out.push_str("|---|---|---:|---:|---|---|---|---:|---:|---:|---:|---:|:---:|\n");
    let mut rows: Vec<_> = report.rows.iter().collect();
    rows.sort_by(|a, b| a.seconds.total_cmp(&b.seconds));
    for x in rows {
        let _ = writeln!(
            out,
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {:.4} | {:.4} | {:.2} | {} |",
            x.axis,
            x.setting,
            x.spp,
            x.bounces,
            x.accel,
            x.build,
            x.precision,
            secs(x.seconds),
            secs(x.trace_seconds),
            x.errors.rmse,
            x.errors.rel_mse,
            x.errors.psnr,
            if x.pareto { "★" } else { "" }
        );
    }
    for n in &report.notes {
        let _ = writeln!(out, "\nNot measured: {n}.");
    }
    out
}

/// Plot size in pixels.
const PLOT: (u32, u32) = (960, 640);

/// Registers the embedded font under plotters' `sans-serif` name, once per process: call
/// before drawing text with plotters.
pub fn register_font() -> Result<(), TradeoffError> {
    static LOADED: OnceLock<bool> = OnceLock::new();
    let loaded = *LOADED.get_or_init(|| {
        plotters::style::register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular())
            .is_ok()
    });
    if loaded {
        Ok(())
    } else {
        Err(TradeoffError::Plot(
            "the embedded font does not load".into(),
        ))
    }
}

/// A colour per axis, from plotters' palette.
fn colour(axis: Axis) -> RGBColor {
    let i = <Axis as crate::names::Spelled>::ALL
        .iter()
        .position(|&a| a == axis)
        .unwrap_or(0);
    let c = Palette99::pick(i).to_rgba();
    RGBColor(c.0, c.1, c.2)
}

/// The bounds of a log axis around `values` (all positive), padded by a fifth of a decade.
fn log_bounds(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    let (lo, hi) = values.fold((f64::INFINITY, 0.0f64), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    (lo.is_finite() && hi > 0.0).then(|| (lo / 10f64.powf(0.2), hi * 10f64.powf(0.2)))
}

/// A tick label: the value to six significant digits, without binary noise
/// (`0.30000000000000004` → `0.3`).
fn tick(v: f64) -> String {
    if !(v.is_finite() && v != 0.0) {
        return format!("{v}");
    }
    let scale = 10f64.powi(5 - v.abs().log10().floor() as i32);
    format!("{}", (v * scale).round() / scale)
}

/// RMSE against seconds per frame, both on log scales: one colour per axis, the Pareto
/// front as a staircase with its rungs circled and named. A PNG.
pub fn plot(report: &Report) -> Result<Vec<u8>, TradeoffError> {
    register_font()?;
    let e = |x: &dyn std::fmt::Display| TradeoffError::Plot(x.to_string());
    let usable: Vec<_> = report
        .rows
        .iter()
        .filter(|r| r.seconds > 0.0 && r.errors.rmse > 0.0 && r.seconds.is_finite())
        .collect();
    // Rungs with no error (an image equal to the reference: a black one, say) or no time
    // have no place on log axes: they are left out, and the caption says how many.
    let left_out = report.rows.len() - usable.len();
    let (w, h) = PLOT;
    let mut rgb = vec![0u8; w as usize * h as usize * 3];
    let mut caption = format!(
        "{}: error against time ({}×{}, {} thread(s), reference {} spp)",
        report.scene, report.width, report.height, report.threads, report.reference.spp
    );
    if left_out > 0 {
        caption += &format!("; {left_out} rung(s) of zero error not shown");
    }
    let bounds = log_bounds(usable.iter().map(|r| r.seconds))
        .zip(log_bounds(usable.iter().map(|r| r.errors.rmse)));
    let Some(((x0, x1), (y0, y1))) = bounds else {
        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|x| e(&x))?;
        root.titled(&caption, ("sans-serif", 20))
            .map_err(|x| e(&x))?
            .draw(&Text::new(
                "no rung has both a time and an error above 0 (see the CSV)",
                (40, h as i32 / 2),
                ("sans-serif", 18),
            ))
            .map_err(|x| e(&x))?;
        root.present().map_err(|x| e(&x))?;
        drop(root);
        return encode_rgb8(&rgb, w, h);
    };
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        root.fill(&WHITE).map_err(|x| e(&x))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(caption, ("sans-serif", 20))
            .margin(14)
            .x_label_area_size(44)
            .y_label_area_size(70)
            .build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())
            .map_err(|x| e(&x))?;
        chart
            .configure_mesh()
            .x_desc("seconds per frame (build + trace + shade)")
            .y_desc("RMSE against the reference")
            .x_label_formatter(&|v| tick(*v))
            .y_label_formatter(&|v| tick(*v))
            .label_style(("sans-serif", 14))
            .axis_desc_style(("sans-serif", 15))
            .draw()
            .map_err(|x| e(&x))?;
        for &axis in <Axis as crate::names::Spelled>::ALL {
            let pts: Vec<(f64, f64)> = usable
                .iter()
                .filter(|r| r.axis == axis)
                .map(|r| (r.seconds, r.errors.rmse))
                .collect();
            if pts.is_empty() {
                continue;
            }
            let c = colour(axis);
            chart
                .draw_series(pts.iter().map(|&p| Circle::new(p, 4, c.filled())))
                .map_err(|x| e(&x))?
                .label(axis.to_string())
                .legend(move |(x, y)| Circle::new((x, y), 4, c.filled()));
        }
        let mut front: Vec<_> = usable.iter().filter(|r| r.pareto).collect();
        front.sort_by(|a, b| a.seconds.total_cmp(&b.seconds));
        let mut stairs = Vec::new();
        for (i, r) in front.iter().enumerate() {
            if i > 0 {
                stairs.push((r.seconds, front[i - 1].errors.rmse));
            }
            stairs.push((r.seconds, r.errors.rmse));
        }
        chart
            .draw_series(LineSeries::new(stairs, BLACK.stroke_width(2)))
            .map_err(|x| e(&x))?
            .label("Pareto front")
            .legend(|(x, y)| PathElement::new(vec![(x - 8, y), (x + 8, y)], BLACK.stroke_width(2)));
        chart
            .draw_series(front.iter().map(|r| {
                EmptyElement::at((r.seconds, r.errors.rmse))
                    + Circle::new((0, 0), 8, BLACK.stroke_width(2))
            }))
            .map_err(|x| e(&x))?;
        // The front's labels, each placed beside its point where it covers no other label
        // and no other point of the front (rungs crowd where a setting barely changes the
        // time: bounces=4 and spp=8 fell on one another).
        let font = TextStyle::from(("sans-serif", 13).into_font());
        let points: Vec<(i32, i32)> = front
            .iter()
            .map(|r| chart.backend_coord(&(r.seconds, r.errors.rmse)))
            .collect();
        // The estimate's height (10 pixels at size 13) starts at the anchor, but the glyphs
        // rise about 3 pixels above it: each box is padded to hold the ink, and the text
        // drawn 3 pixels below the box's top.
        let sizes = front
            .iter()
            .map(|r| {
                root.estimate_text_size(&r.setting, &font)
                    .map(|(w, h)| (w, h + LABEL_RISE + 1))
            })
            .collect::<Result<Vec<_>, _>>()
            .map_err(|x| e(&x))?;
        let (xr, yr) = chart.plotting_area().get_pixel_range();
        let area = Rect {
            x: xr.start,
            y: yr.start,
            w: xr.end - xr.start,
            h: yr.end - yr.start,
        };
        for (r, at) in front.iter().zip(place_labels(&points, &sizes, area)) {
            root.draw(&Text::new(
                r.setting.clone(),
                (at.x, at.y + LABEL_RISE as i32),
                font.clone(),
            ))
            .map_err(|x| e(&x))?;
        }
        chart
            .configure_series_labels()
            .label_font(("sans-serif", 14))
            .background_style(WHITE.mix(0.9))
            .border_style(BLACK)
            .position(SeriesLabelPosition::UpperRight)
            .draw()
            .map_err(|x| e(&x))?;
        root.present().map_err(|x| e(&x))?;
    }
    encode_rgb8(&rgb, w, h)
}

/// How far a label's glyphs rise above the point plotters anchors the text at, in pixels.
const LABEL_RISE: u32 = 3;

/// A rectangle of pixels: its top-left corner and its size.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Rect {
    x: i32,
    y: i32,
    w: i32,
    h: i32,
}

impl Rect {
    /// The box a front marker at `(x, y)` covers: a circle of radius 8 with a 2-pixel stroke.
    fn marker((x, y): (i32, i32)) -> Rect {
        Rect {
            x: x - 9,
            y: y - 9,
            w: 19,
            h: 19,
        }
    }

    /// Its area, in square pixels.
    fn area(&self) -> i64 {
        i64::from(self.w) * i64::from(self.h)
    }

    /// The area `self` shares with `o`, in square pixels.
    fn overlap(&self, o: &Rect) -> i64 {
        let w = (self.x + self.w).min(o.x + o.w) - self.x.max(o.x);
        let h = (self.y + self.h).min(o.y + o.h) - self.y.max(o.y);
        i64::from(w.max(0)) * i64::from(h.max(0))
    }
}

/// Where the labels of `points` (pixels; `sizes[i]` is label `i`'s width and height) go:
/// each at the first of eight places around its point (right and above first, as before)
/// that covers no label placed before it, no marker of another point (a circle of radius
/// 8 and a 2-pixel stroke) and nothing outside `area`; where none is free, the place that
/// covers least, by area (a pixel outside the plot weighs 4, over a label 2, over a marker
/// 1). Greedy, in the points' order: a front has a few dozen rungs at most. Other rungs'
/// dots, the front's stairs and the legend are not avoided.
fn place_labels(points: &[(i32, i32)], sizes: &[(u32, u32)], area: Rect) -> Vec<Rect> {
    const GAP: i32 = 10;
    let markers: Vec<Rect> = points.iter().copied().map(Rect::marker).collect();
    let mut placed: Vec<Rect> = Vec::with_capacity(points.len());
    for (i, (&(px, py), &(w, h))) in points.iter().zip(sizes).enumerate() {
        let (w, h) = (w as i32, h as i32);
        let candidates = [
            (px + GAP, py - GAP - h),
            (px + GAP, py + GAP),
            (px - GAP - w, py - GAP - h),
            (px - GAP - w, py + GAP),
            (px - w / 2, py - GAP - h - 4),
            (px - w / 2, py + GAP + 4),
            (px + GAP + 4, py - h / 2),
            (px - GAP - 4 - w, py - h / 2),
        ];
        let cost = |r: &Rect| {
            let outside = r.area() - r.overlap(&area);
            let labels: i64 = placed.iter().map(|p| p.overlap(r)).sum();
            let others: i64 = markers
                .iter()
                .enumerate()
                .filter(|&(j, _)| j != i)
                .map(|(_, m)| m.overlap(r))
                .sum();
            4 * outside + 2 * labels + others
        };
        let best = candidates
            .iter()
            .map(|&(x, y)| Rect { x, y, w, h })
            .min_by_key(cost)
            .expect("eight candidates");
        placed.push(best);
    }
    placed
}

/// An 8-bit RGB PNG of `rgb` (already display-ready: no colour conversion), as plotters'
/// bitmap backend leaves it.
pub fn encode_rgb8(rgb: &[u8], w: u32, h: u32) -> Result<Vec<u8>, TradeoffError> {
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, w, h);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        enc.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
        let mut writer = enc
            .write_header()
            .map_err(|x| TradeoffError::Plot(x.to_string()))?;
        writer
            .write_image_data(rgb)
            .map_err(|x| TradeoffError::Plot(x.to_string()))?;
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::accel::{BuildQuality, Precision};
    use crate::tradeoff::{Errors, Reference, Row};

    #[test]
    fn crowded_labels_are_placed_apart() {
        // Three rungs within a few pixels of each other (as bounces=4 and spp=8 fell), one
        // in a corner, one alone.
        let points = [(400, 300), (404, 301), (398, 296), (12, 12), (700, 500)];
        let sizes = [(70, 14), (50, 14), (90, 14), (40, 14), (40, 14)];
        let area = Rect {
            x: 0,
            y: 0,
            w: 800,
            h: 600,
        };
        let placed = place_labels(&points, &sizes, area);
        for (i, a) in placed.iter().enumerate() {
            assert_eq!((a.w, a.h), (sizes[i].0 as i32, sizes[i].1 as i32));
            assert_eq!(a.overlap(&area), a.area(), "label {i} leaves the plot");
            for (j, b) in placed.iter().enumerate().skip(i + 1) {
                assert_eq!(a.overlap(b), 0, "labels {i} and {j} overlap: {a:?} {b:?}");
            }
            for (j, &p) in points.iter().enumerate().filter(|&(j, _)| j != i) {
                assert_eq!(
                    a.overlap(&Rect::marker(p)),
                    0,
                    "label {i} covers point {j}: {a:?}"
                );
            }
            // Beside its own point: the gap from the point to the box at most 14 pixels
            // (the farthest of the eight places).
            let (px, py) = points[i];
            let gx = (a.x - px).max(px - (a.x + a.w)).max(0);
            let gy = (a.y - py).max(py - (a.y + a.h)).max(0);
            assert!(gx.max(gy) <= 14, "label {i} far from its point: {a:?}");
        }
        // A lone point keeps the old place: right of it and above.
        assert_eq!((placed[4].x, placed[4].y), (710, 500 - 10 - 14));
        // A marker where the first place would be moves the label: alone, point 0's label
        // goes right of it and above; with point 1 there, elsewhere.
        let alone = place_labels(&[(100, 100)], &[(60, 14)], area);
        assert_eq!((alone[0].x, alone[0].y), (110, 76));
        let beside = place_labels(&[(100, 100), (140, 84)], &[(60, 14), (20, 14)], area);
        assert_ne!((beside[0].x, beside[0].y), (110, 76));
        assert_eq!(beside[0].overlap(&Rect::marker((140, 84))), 0);
    }

    fn report() -> Report {
        let row = |axis, setting: &str, seconds: f64, rmse: f64, pareto| Row {
            axis,
            setting: setting.into(),
            spp: 4,
            bounces: 2,
            accel: "mbvh8",
            build: BuildQuality::Sah,
            precision: Precision::Watertight,
            seconds,
            prepare_seconds: 0.01,
            trace_seconds: seconds / 2.0,
            shade_seconds: seconds / 2.0 - 0.01,
            rays: 1000,
            errors: Errors {
                rmse,
                rel_mse: rmse * rmse,
                psnr: -20.0 * rmse.log10(),
            },
            pareto,
        };
        Report {
            scene: "tiny, \"quoted\"".into(),
            width: 8,
            height: 6,
            threads: 2,
            reference: Reference {
                spp: 256,
                bounces: 4,
                seed: 7,
                seconds: 1.0,
                mean: 0.5,
            },
            rows: vec![
                row(Axis::Base, "base", 0.2, 0.05, true),
                row(Axis::Spp, "spp=1", 0.05, 0.2, true),
                row(Axis::Accel, "accel=bvh2", 0.3, 0.05, false),
            ],
            notes: vec!["roulette: not yet".into()],
        }
    }

    #[test]
    fn csv_has_a_header_and_a_line_per_row() {
        let text = csv(&report());
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 4);
        assert_eq!(lines[0].split(',').count(), COLUMNS.len());
        assert!(lines[2].starts_with("spp,spp=1,4,2,mbvh8,sah,watertight,0.050000,"));
        assert!(lines[3].ends_with(",false,2"));
        assert_eq!(field("a,\"b\""), "\"a,\"\"b\"\"\"");
    }

    #[test]
    fn markdown_sorts_by_time_and_stars_the_front() {
        let text = markdown(&report());
        let rows: Vec<&str> = text.lines().filter(|l| l.starts_with("| ")).collect();
        assert!(rows[1].starts_with("| spp | spp=1 |"), "{rows:?}");
        assert!(rows[1].ends_with("| ★ |"));
        assert!(rows[3].starts_with("| accel | accel=bvh2 |"));
        assert!(rows[3].ends_with("|  |"));
        assert!(text.contains("Not measured: roulette: not yet."));
    }

    #[test]
    fn tiny_times_keep_four_digits() {
        assert_eq!(secs(2.5), "2.500");
        assert_eq!(secs(0.25), "0.2500");
        assert_eq!(secs(0.000_123_4), "0.0001234");
        assert_eq!(secs(0.0), "0.000");
    }

    #[test]
    fn ticks_lose_binary_noise() {
        assert_eq!(tick(0.1 + 0.2), "0.3");
        assert_eq!(tick(0.001), "0.001");
        assert_eq!(tick(40.0), "40");
    }

    #[test]
    fn the_plot_is_a_png_of_its_size() {
        let bytes = plot(&report()).unwrap();
        let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
        let reader = decoder.read_info().unwrap();
        assert_eq!((reader.info().width, reader.info().height), PLOT);
        // Rungs equal to the reference (a black frame) have no place on log axes: the plot
        // says so instead of failing the run, with one or with every rung at zero error.
        let mut some = report();
        some.rows[1].errors.rmse = 0.0;
        let mut empty = report();
        for r in &mut empty.rows {
            r.errors.rmse = 0.0;
        }
        for r in [some, empty] {
            let bytes = plot(&r).unwrap();
            let reader = png::Decoder::new(std::io::Cursor::new(bytes))
                .read_info()
                .unwrap();
            assert_eq!((reader.info().width, reader.info().height), PLOT);
        }
    }
}
