//! Prints the statistics of the three trees over a scene's interior view (with the room),
//! for each build quality.
//!
//! ```text
//! cargo run --release --example tree_stats -- SCENE [fast|sah|sbvh]
//! ```

use rayd::accel::bvh::{Bvh2, Mbvh4, Mbvh8};
use rayd::accel::BuildQuality;
use rayd::bench::{CameraChoice, View, ViewKind};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let scene = rayd::formats::load_scene(args[1].as_ref(), &Default::default()).unwrap();
    let view = View::new(&scene, ViewKind::Interior, &CameraChoice::Auto, 1024, 768).unwrap();
    for q in [BuildQuality::Fast, BuildQuality::Sah, BuildQuality::Sbvh] {
        if args.get(2).is_some_and(|a| a != q.name()) {
            continue;
        }
        let t = &view.triangles;
        println!(
            "mbvh8 leaf sizes 0..=16: {:?}",
            leaf_hist(&Mbvh8::build(t, q))
        );
        for s in [
            Mbvh8::build(t, q).stats(),
            Mbvh4::build(t, q).stats(),
            Bvh2::build(t, q).stats(),
        ] {
            println!("{}", serde_json::to_string(&s).unwrap());
        }
    }
}

/// Histogram of leaf sizes (triangles per leaf) of an MBVH8.
#[allow(dead_code)]
fn leaf_hist(t: &rayd::accel::bvh::Mbvh8) -> Vec<usize> {
    use rayd::accel::bvh::Child;
    let mut h = vec![0usize; 17];
    for n in t.nodes() {
        for &c in &n.child {
            if let Child::Leaf { first, count } = Child::decode(c) {
                let k: usize = t.multi_tris()[first as usize..(first + count) as usize]
                    .iter()
                    .map(|m| m.lanes())
                    .sum();
                h[k] += 1;
            }
        }
    }
    h
}
