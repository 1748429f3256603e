//! Makes inputs for trying the service by hand: `make_rays SCENE OUT.ray N [MOVED.tri]`
//! writes N rays (RAY1) from a camera that frames the scene, through its bounds, and with
//! a fourth argument the scene's triangles lifted by a tenth of its height (TRI1), a
//! geometry update for `PUT /v1/scenes/{id}/geometry`.

use rayd::formats::binary::{write_rays, write_tri};
use rayd::render::camera::ViewCamera;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 4 {
        eprintln!("usage: make_rays SCENE OUT.ray N [MOVED.tri]");
        std::process::exit(2);
    }
    let scene = rayd::formats::load_scene(args[1].as_ref(), &Default::default())
        .unwrap_or_else(|e| panic!("{}: {e}", args[1]));
    let n: usize = args[3].parse().expect("N is a number");
    let bounds = scene.bounds().expect("the scene has triangles");
    let side = (n as f64).sqrt().ceil() as u32;
    let camera = ViewCamera::framing(&bounds, 1.0);
    let rays: Vec<_> = (0..n as u32)
        .map(|i| camera.ray((i % side) as f64 + 0.5, (i / side) as f64 + 0.5, side, side))
        .collect();
    std::fs::write(&args[2], write_rays(&rays)).expect("writes the rays");
    if let Some(out) = args.get(4) {
        let lift = 0.1 * (bounds.max[1] - bounds.min[1]);
        let mut tris = scene.triangles.clone();
        for t in &mut tris {
            for v in &mut t.v {
                v[1] += lift;
            }
        }
        std::fs::write(out, write_tri(&tris)).expect("writes the triangles");
    }
}
