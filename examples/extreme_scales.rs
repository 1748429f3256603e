//! A random search for disagreements between the cores at the numerical extremes
//! (BENCHMARKS §41, proto/semantics.md "The range the tests decide in"): clusters of
//! triangles 1e-35 to 1e35 across, centred at the origin or up to 1e35 from it, and rays
//! from in and around them with directions of 1e-30 to 1e30 (a third aimed at a
//! triangle). Per scene it counts, against `brute`: each core's closest hits that differ
//! in any bit, `any` answers that differ on hit or miss, and `brute`'s hits outside the
//! f64 oracle's t bound (t above 1e-37) or, where the ray runs along the triangle's plane
//! in f64, off its triangle (those on it are counted apart: `fast` hits a triangle below
//! f64's resolution at its distance at a vertex).
//! `tests/extremes.rs`'s `clusters_at_every_scale_keep_every_core_exact` is its fixed-seed,
//! smaller twin.
//!
//! ```sh
//! cargo run --release --features embree --example extreme_scales -- SEED SCENES PRECISION
//! ```

use rayd::accel::triangle::oracle::{
    oracle_t_error, order_t_bound, t_bound, unresolved_hit_plausible,
};
use rayd::accel::triangle::oracle_line_f64;
use rayd::accel::{build, AccelKind, BuildOptions, BuildQuality, Precision, Query};
use rayd::geometry::{Hit, Ray, Triangle};
use std::collections::BTreeMap;

/// SplitMix64, f64 draws.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
    fn sym(&mut self) -> f64 {
        2.0 * self.unit() - 1.0
    }
    fn pow10(&mut self, lo: f64, hi: f64) -> f64 {
        10f64.powf(lo + (hi - lo) * self.unit())
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
}

fn trace(kind: AccelKind, p: Precision, q: Query, tris: &[Triangle], rays: &[Ray]) -> Vec<Hit> {
    let options = BuildOptions {
        quality: BuildQuality::Sah,
        precision: p,
        threads: 1,
        ..Default::default()
    };
    let core = build(kind, tris, &options).expect("a core of this build");
    let mut hits = vec![Hit::MISS; rays.len()];
    core.trace(rays, q, &mut hits);
    hits
}

/// One scene: its triangles and rays.
fn scene(rng: &mut Rng) -> (Vec<Triangle>, Vec<Ray>) {
    let mut tris = Vec::new();
    let mut clusters = Vec::new();
    for _ in 0..1 + rng.below(4) {
        let c = if rng.next().is_multiple_of(3) {
            [0.0; 3]
        } else {
            let m = rng.pow10(-35.0, 35.0);
            [m * rng.sym(), m * rng.sym(), m * rng.sym()]
        };
        let size = rng.pow10(-35.0, 35.0);
        for _ in 0..1 + rng.below(40) {
            let v: [[f32; 3]; 3] =
                std::array::from_fn(|_| std::array::from_fn(|k| (c[k] + size * rng.sym()) as f32));
            let t = Triangle { v };
            if !t.is_degenerate() && v.iter().flatten().all(|x| x.is_finite()) {
                tris.push(t);
            }
        }
        clusters.push((c, size));
    }
    let mut rays = Vec::new();
    if tris.is_empty() {
        return (tris, rays);
    }
    for _ in 0..256 {
        let (c, size) = clusters[rng.below(clusters.len())];
        let off = size * rng.pow10(-3.0, 3.0);
        let org: [f32; 3] = match rng.next() % 4 {
            0 => [0.0; 3],
            _ => std::array::from_fn(|k| (c[k] + off * rng.sym()) as f32),
        };
        let scale = if rng.next().is_multiple_of(4) {
            rng.pow10(-30.0, 30.0)
        } else {
            1.0
        };
        let dir: [f32; 3] = if rng.next().is_multiple_of(3) {
            // At a point of a triangle.
            let t = &tris[rng.below(tris.len())];
            let w = [rng.unit(), rng.unit(), rng.unit()];
            let sum = w[0] + w[1] + w[2];
            std::array::from_fn(|k| {
                let p = (0..3).map(|i| f64::from(t.v[i][k]) * w[i]).sum::<f64>() / sum;
                (p - f64::from(org[k])) as f32
            })
        } else {
            std::array::from_fn(|_| (scale * rng.sym()) as f32)
        };
        if dir.iter().any(|&d| d != 0.0) && dir.iter().all(|d| d.is_finite()) {
            rays.push(Ray {
                org,
                tmin: 0.0,
                dir,
                tmax: f32::INFINITY,
            });
        }
    }
    (tris, rays)
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let arg = |i: usize, default: &str| args.get(i).cloned().unwrap_or_else(|| default.into());
    let seed: u64 = arg(1, "1").parse().expect("SEED: an integer");
    let scenes: usize = arg(2, "200").parse().expect("SCENES: an integer");
    let p = match arg(3, "watertight").as_str() {
        "watertight" => Precision::Watertight,
        "fast" => Precision::Fast,
        other => panic!("PRECISION: watertight or fast, not {other}"),
    };
    let mut rng = Rng(seed);
    let mut bad: BTreeMap<String, usize> = BTreeMap::new();
    let (mut rays_traced, mut hits, mut unresolved) = (0, 0, 0);
    for _ in 0..scenes {
        let (tris, rays) = scene(&mut rng);
        if rays.is_empty() {
            continue;
        }
        let reference = trace(AccelKind::Brute, p, Query::Closest, &tris, &rays);
        rays_traced += rays.len();
        for (r, h) in rays.iter().zip(&reference).filter(|(_, h)| h.is_hit()) {
            hits += 1;
            let tri = &tris[h.prim as usize];
            let Some(line) = oracle_line_f64(r, tri) else {
                // The triangle is below f64's resolution at its distance from the origin
                // (1e-35 across, 0.1 away): `fast` hits it at a vertex where the ray passes
                // within rounding of it (`oracle::unresolved_hit_plausible`).
                if unresolved_hit_plausible(r, tri, h.t) {
                    unresolved += 1;
                } else {
                    *bad.entry("brute off a plane parallel in f64".into())
                        .or_default() += 1;
                }
                continue;
            };
            let mut tol = t_bound(p, r, tri, line.t);
            if h.t == r.tmin || h.t == r.tmax {
                tol = tol.max(order_t_bound(p, r, tri, line.t));
            }
            let tol = tol + oracle_t_error(r, tri);
            // (A NaN distance counts as outside.)
            let within = (f64::from(h.t) - line.t).abs() <= tol;
            if !within && line.t.abs() > 1e-37 {
                *bad.entry("brute outside the t bound".into()).or_default() += 1;
            }
        }
        let bits = |h: &Hit| (h.t.to_bits(), h.prim, h.u.to_bits(), h.v.to_bits());
        for kind in [
            AccelKind::Mbvh8,
            AccelKind::Mbvh4,
            AccelKind::Bvh2,
            AccelKind::Dacrt,
            AccelKind::DacrtSampled,
        ] {
            let closest = trace(kind, p, Query::Closest, &tris, &rays);
            let any = trace(kind, p, Query::Any, &tris, &rays);
            for ((c, a), b) in closest.iter().zip(&any).zip(&reference) {
                if bits(c) != bits(b) {
                    *bad.entry(kind.name().into()).or_default() += 1;
                }
                if a.is_hit() != b.is_hit() {
                    *bad.entry("any".into()).or_default() += 1;
                }
            }
        }
    }
    println!(
        "{} seed {seed}: rays {rays_traced} hits {hits} (below f64's resolution {unresolved}) \
         disagreements {bad:?}",
        p.name()
    );
}
