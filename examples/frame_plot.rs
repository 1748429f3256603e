//! Draws the per-frame timing plot of an animation render: reads the JSON that
//! `rayd render --frames` prints and writes a PNG of stacked bars, one per frame, split
//! into evaluate, prepare, trace, shade and encode seconds (`proto/cli.md`, `rayd render`).
//!
//! `cargo run --release --example frame_plot -- FRAMES.json OUT.png [TITLE]`
//! (`scripts/pictures.sh` runs it).

use plotters::prelude::*;
use rayd::tradeoff::report::{encode_rgb8, register_font};

/// The parts of a frame, bottom to top, with their JSON keys.
const PARTS: [(&str, &str); 5] = [
    ("evaluate", "evaluate_seconds"),
    ("prepare", "prepare_seconds"),
    ("trace", "trace_seconds"),
    ("shade", "shade_seconds"),
    ("encode", "encode_seconds"),
];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let [_, input, output, rest @ ..] = &args[..] else {
        return Err("usage: frame_plot FRAMES.json OUT.png [TITLE]".into());
    };
    let title = rest
        .first()
        .cloned()
        .unwrap_or_else(|| "seconds per frame".into());
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(input).map_err(|e| format!("{input}: {e}"))?)
            .map_err(|e| format!("{input}: {e}"))?;
    let frames = json["frames"]
        .as_array()
        .ok_or_else(|| format!("{input}: no `frames` array (render with --frames)"))?;
    let parts: Vec<[f64; 5]> = frames
        .iter()
        .enumerate()
        .map(|(k, f)| {
            let mut p = [0.0; 5];
            for (slot, (_, key)) in p.iter_mut().zip(PARTS) {
                *slot = f[key]
                    .as_f64()
                    .ok_or_else(|| format!("{input}: frame {k} has no number `{key}`"))?;
            }
            Ok(p)
        })
        .collect::<Result<_, String>>()?;
    if parts.is_empty() {
        return Err(format!("{input}: no frames").into());
    }
    let top = parts
        .iter()
        .map(|p| p.iter().sum::<f64>())
        .fold(0.0f64, f64::max)
        * 1.25;
    register_font()?;
    let (w, h) = (720u32, 400u32);
    let mut rgb = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut rgb, (w, h)).into_drawing_area();
        root.fill(&WHITE)?;
        let n = parts.len();
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 18))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(60)
            .build_cartesian_2d(-0.5f64..n as f64 - 0.5, 0.0..top.max(1e-6))?;
        chart
            .configure_mesh()
            .disable_x_mesh()
            .x_labels(n.min(20))
            .x_label_formatter(&|x| format!("{}", x.round() as i64))
            .x_desc("frame")
            .y_desc("seconds")
            .label_style(("sans-serif", 13))
            .draw()?;
        for (j, (name, _)) in PARTS.iter().enumerate() {
            let c = Palette99::pick(j).to_rgba();
            let colour = RGBColor(c.0, c.1, c.2);
            chart
                .draw_series(parts.iter().enumerate().map(|(k, p)| {
                    let below: f64 = p[..j].iter().sum();
                    let x = k as f64;
                    Rectangle::new(
                        [(x - 0.35, below), (x + 0.35, below + p[j])],
                        colour.filled(),
                    )
                }))?
                .label(*name)
                .legend(move |(x, y)| {
                    Rectangle::new([(x, y - 5), (x + 10, y + 5)], colour.filled())
                });
        }
        chart
            .configure_series_labels()
            .label_font(("sans-serif", 13))
            .background_style(WHITE.mix(0.9))
            .border_style(BLACK)
            .position(SeriesLabelPosition::UpperRight)
            .draw()?;
        root.present()?;
    }
    std::fs::write(output, encode_rgb8(&rgb, w, h)?).map_err(|e| format!("{output}: {e}"))?;
    Ok(())
}
