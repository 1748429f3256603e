//! Writes the triangles a benchmark view traces (the scene's, then the interior room's 12)
//! as a TRI1 file, so that an outside tracer (`scripts/tinybvh/`) can be measured on exactly
//! the geometry and triangle ids `rayd bench` uses: its prim ids then compare directly with
//! the reference hits `rayd bench --dump` writes.
//!
//! ```text
//! cargo run --release --example export_view -- SCENE OUT.tri [interior|exterior]
//! ```

use rayd::bench::{CameraChoice, View, ViewKind};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 3 {
        eprintln!("usage: export_view SCENE OUT.tri [interior|exterior]");
        std::process::exit(2);
    }
    let kind = match args.get(3).map(String::as_str) {
        None | Some("interior") => ViewKind::Interior,
        Some("exterior") => ViewKind::Exterior,
        Some(other) => {
            eprintln!("export_view: unknown view {other:?} (interior, exterior)");
            std::process::exit(2);
        }
    };
    let scene = match rayd::formats::load_scene(args[1].as_ref(), &Default::default()) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("export_view: {}: {e}", args[1]);
            std::process::exit(1);
        }
    };
    // The size does not change the triangles; it is the bench default.
    let view = match View::new(&scene, kind, &CameraChoice::Auto, 1024, 768) {
        Ok(v) => v,
        Err(e) => {
            eprintln!("export_view: {}: {e}", args[1]);
            std::process::exit(1);
        }
    };
    let bytes = rayd::formats::binary::write_tri(&view.triangles);
    if let Err(e) = std::fs::write(&args[2], bytes) {
        eprintln!("export_view: {}: {e}", args[2]);
        std::process::exit(1);
    }
    println!("{}: {} triangles", args[2], view.triangles.len());
}
