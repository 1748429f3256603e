//! The `embree` peer through the public factory: exact small cases, the contract's misses
//! and empty intervals, `occluded`, `any`, every build quality and thread option, and a
//! random soup checked against a brute-force Möller–Trumbore written here in f64.
//!
//! Embree is a peer with its own rules (`tnear < t <= tfar`, an approximate reciprocal in
//! the final division), so hand-computed values are compared to within a few ulps and the
//! soup to 99.9 % agreement, with every disagreement required to sit on a triangle edge or
//! at a near-tie in t.
#![cfg(feature = "embree")]

use rayd::accel::{build, AccelKind, BuildOptions, BuildQuality, Intersector, Query};
use rayd::geometry::{Hit, Ray, Triangle};

fn embree(triangles: &[Triangle], options: BuildOptions) -> Box<dyn Intersector> {
    build(AccelKind::Embree, triangles, &options).expect("embree builds")
}

fn ray(org: [f32; 3], dir: [f32; 3], tmin: f32, tmax: f32) -> Ray {
    Ray {
        org,
        tmin,
        dir,
        tmax,
    }
}

fn trace(accel: &dyn Intersector, rays: &[Ray], query: Query) -> Vec<Hit> {
    let mut hits = vec![Hit::MISS; rays.len()];
    accel.trace(rays, query, &mut hits);
    hits
}

fn occluded(accel: &dyn Intersector, rays: &[Ray]) -> Vec<u8> {
    let mut out = vec![9u8; rays.len()];
    accel.occluded(rays, &mut out);
    out
}

fn ulps(a: f32, b: f32) -> u32 {
    a.to_bits().abs_diff(b.to_bits())
}

fn assert_close(hit: Hit, t: f32, prim: u32, u: f32, v: f32) {
    assert_eq!(hit.prim, prim, "{hit:?}");
    assert!(ulps(hit.t, t) <= 2, "t: {hit:?}, want {t}");
    assert!(
        (hit.u - u).abs() <= 2.0 * f32::EPSILON && (hit.v - v).abs() <= 2.0 * f32::EPSILON,
        "u, v: {hit:?}, want {u}, {v}"
    );
}

#[test]
fn single_triangle_t_prim_and_barycentrics() {
    // A skewed right triangle: u weighs v1 (along x, length 2), v weighs v2 (along y,
    // length 4), so swapped barycentrics would show.
    let t = Triangle {
        v: [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 4.0, 0.0]],
    };
    let e = embree(&[t], BuildOptions::default());
    assert_eq!(e.name(), "embree");
    // Point (1, 1, 0) = 0.25·v0 + 0.5·v1 + 0.25·v2; reached at t = 5 from z = 5 going down,
    // and at t = 2.5 with a direction of length 2 (t is in units of the direction).
    let rays = [
        ray([1.0, 1.0, 5.0], [0.0, 0.0, -1.0], 0.0, f32::INFINITY),
        ray([1.0, 1.0, 5.0], [0.0, 0.0, -2.0], 0.0, f32::INFINITY),
        // From below, hitting the back face: no culling.
        ray([0.5, 2.0, -1.0], [0.0, 0.0, 1.0], 0.0, 100.0),
    ];
    let hits = trace(&*e, &rays, Query::Closest);
    assert_close(hits[0], 5.0, 0, 0.5, 0.25);
    assert_close(hits[1], 2.5, 0, 0.5, 0.25);
    assert_close(hits[2], 1.0, 0, 0.25, 0.5);
    // The contract's hit point (1-u-v)·v0 + u·v1 + v·v2 is the ray's point at t.
    for (r, h) in rays.iter().zip(&hits) {
        let p = r.at(h.t);
        let q: Vec<f32> = (0..3)
            .map(|k| (1.0 - h.u - h.v) * t.v[0][k] + h.u * t.v[1][k] + h.v * t.v[2][k])
            .collect();
        for k in 0..3 {
            assert!((p[k] - q[k]).abs() < 1e-5, "{p:?} vs {q:?}");
        }
    }
    assert_eq!(occluded(&*e, &rays), vec![1, 1, 1]);
}

#[test]
fn quad_of_two_triangles() {
    let quad = [
        Triangle {
            v: [[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.0]],
        },
        Triangle {
            v: [[0.0, 0.0, 1.0], [1.0, 1.0, 1.0], [0.0, 1.0, 1.0]],
        },
    ];
    let e = embree(&quad, BuildOptions::default());
    let down = |x: f32, y: f32| ray([x, y, 0.0], [0.0, 0.0, 1.0], 0.0, f32::INFINITY);
    let hits = trace(&*e, &[down(0.75, 0.25), down(0.25, 0.75)], Query::Closest);
    // (0.75, 0.25) in triangle 0: 0.25·v0 + 0.5·v1 + 0.25·v2.
    assert_close(hits[0], 1.0, 0, 0.5, 0.25);
    // (0.25, 0.75) in triangle 1: 0.25·v0 + 0.25·v1 + 0.5·v2.
    assert_close(hits[1], 1.0, 1, 0.25, 0.5);
}

#[test]
fn misses_are_the_contract_miss() {
    let t = Triangle {
        v: [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
    };
    let e = embree(&[t], BuildOptions::default());
    let rays = [
        // Beside the triangle.
        ray([2.0, 2.0, -1.0], [0.0, 0.0, 1.0], 0.0, f32::INFINITY),
        // Pointing away.
        ray([0.2, 0.2, -1.0], [0.0, 0.0, -1.0], 0.0, f32::INFINITY),
        // In the plane, parallel.
        ray([-1.0, 0.2, 0.0], [1.0, 0.0, 0.0], 0.0, f32::INFINITY),
    ];
    assert_eq!(trace(&*e, &rays, Query::Closest), vec![Hit::MISS; 3]);
    assert_eq!(trace(&*e, &rays, Query::Any), vec![Hit::MISS; 3]);
    assert_eq!(occluded(&*e, &rays), vec![0, 0, 0]);
}

#[test]
fn empty_and_short_intervals_miss() {
    let t = Triangle {
        v: [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
    };
    let e = embree(&[t], BuildOptions::default());
    let o = [0.25, 0.25, -2.0];
    let d = [0.0, 0.0, 1.0];
    let rays = [
        ray(o, d, 3.0, 1.0),                     // tmin > tmax
        ray(o, d, f32::INFINITY, f32::INFINITY), // tmin = +inf
        ray(o, d, 0.0, 1.5),                     // ends before the hit
        ray(o, d, 2.5, f32::INFINITY),           // starts after it
        Ray::EMPTY,                              // the invalid=miss stand-in
        ray(o, d, 0.0, f32::INFINITY),           // control: hits
        ray(o, d, 1.5, 2.5),                     // control: hits
    ];
    let hits = trace(&*e, &rays, Query::Closest);
    assert_eq!(hits[..5], [Hit::MISS; 5]);
    assert!(hits[5].is_hit() && hits[6].is_hit());
    assert_eq!(occluded(&*e, &rays), vec![0, 0, 0, 0, 0, 1, 1]);
}

/// The peer's documented difference from the contract's closed interval: Embree accepts a
/// hit when `tnear < t <= tfar` (compared before its final division), so a hit exactly at
/// `tmin` is dropped and a zero-length interval never hits. Here t = 2 exactly.
#[test]
fn embree_keeps_its_own_interval_rule() {
    let t = Triangle {
        v: [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
    };
    let e = embree(&[t], BuildOptions::default());
    let r = ray([0.25, 0.5, -2.0], [0.0, 0.0, 1.0], 0.0, f32::INFINITY);
    let rays = [
        Ray { tmin: 2.0, ..r },
        Ray { tmax: 2.0, ..r },
        Ray {
            tmin: 2.0,
            tmax: 2.0,
            ..r
        },
    ];
    let hits = trace(&*e, &rays, Query::Closest);
    let hit: Vec<bool> = hits.iter().map(Hit::is_hit).collect();
    assert_eq!(hit, [false, true, false]);
    assert_eq!(occluded(&*e, &rays), vec![0, 1, 0]);
}

#[test]
fn degenerate_triangles_keep_ids_and_are_never_hit() {
    let tris = [
        Triangle {
            v: [[0.0, 0.0, 1.0], [1.0, 1.0, 1.0], [2.0, 2.0, 1.0]],
        },
        Triangle { v: [[0.5; 3]; 3] },
        Triangle {
            v: [[-1.0, -1.0, 2.0], [3.0, -1.0, 2.0], [-1.0, 3.0, 2.0]],
        },
    ];
    let e = embree(&tris, BuildOptions::default());
    let hits = trace(
        &*e,
        &[ray([0.5, 0.5, 0.0], [0.0, 0.0, 1.0], 0.0, f32::INFINITY)],
        Query::Closest,
    );
    assert_eq!(hits[0].prim, 2);
}

#[test]
fn empty_scene_misses_everything() {
    let e = embree(&[], BuildOptions::default());
    let rays = [ray([0.0; 3], [1.0, 0.0, 0.0], 0.0, f32::INFINITY)];
    assert_eq!(trace(&*e, &rays, Query::Closest), vec![Hit::MISS]);
    assert_eq!(occluded(&*e, &rays), vec![0]);
}

// ---- the random soup -------------------------------------------------------------------

/// xorshift64*: deterministic, dependency-free.
struct Rng(u64);

impl Rng {
    fn next_f32(&mut self) -> f32 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        let x = self.0.wrapping_mul(0x2545_f491_4f6c_dd1d);
        (x >> 40) as f32 / (1u64 << 24) as f32
    }
    fn point(&mut self, lo: f32, hi: f32) -> [f32; 3] {
        [0; 3].map(|_| lo + (hi - lo) * self.next_f32())
    }
}

fn soup(n: usize, seed: u64) -> Vec<Triangle> {
    let mut rng = Rng(seed);
    (0..n)
        .map(|_| {
            let c = rng.point(0.0, 1.0);
            let v = [0; 3].map(|_| {
                let d = rng.point(-0.06, 0.06);
                [c[0] + d[0], c[1] + d[1], c[2] + d[2]]
            });
            Triangle { v }
        })
        .collect()
}

fn soup_rays(n: usize, seed: u64) -> Vec<Ray> {
    let mut rng = Rng(seed);
    (0..n)
        .map(|i| {
            let o = rng.point(-0.5, 1.5);
            let target = rng.point(0.2, 0.8);
            let dir = [target[0] - o[0], target[1] - o[1], target[2] - o[2]];
            // Every fourth ray has a finite tmax, so intervals matter.
            let tmax = if i % 4 == 0 {
                0.5 + rng.next_f32()
            } else {
                f32::INFINITY
            };
            ray(o, dir, 0.0, tmax)
        })
        .collect()
}

/// Möller–Trumbore in f64 without the range tests: (t, u, v) of the ray's crossing with the
/// triangle's plane, or None when parallel or degenerate.
fn crossing(r: &Ray, tri: &Triangle) -> Option<(f64, f64, f64)> {
    let f = |a: [f32; 3]| a.map(f64::from);
    let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    let cross = |a: [f64; 3], b: [f64; 3]| {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let (v0, v1, v2) = (f(tri.v[0]), f(tri.v[1]), f(tri.v[2]));
    let (o, d) = (f(r.org), f(r.dir));
    let e1 = sub(v1, v0);
    let e2 = sub(v2, v0);
    let p = cross(d, e2);
    let det = dot(e1, p);
    if det == 0.0 {
        return None;
    }
    let s = sub(o, v0);
    let u = dot(s, p) / det;
    let q = cross(s, e1);
    let v = dot(d, q) / det;
    let t = dot(e2, q) / det;
    Some((t, u, v))
}

/// The contract's closest hit, brute force.
fn reference(tris: &[Triangle], r: &Ray) -> Hit {
    let mut best = Hit::MISS;
    let mut best_t = f64::INFINITY;
    for (i, tri) in tris.iter().enumerate() {
        if let Some((t, u, v)) = crossing(r, tri) {
            let inside = u >= 0.0 && v >= 0.0 && u + v <= 1.0;
            if inside && t >= f64::from(r.tmin) && t <= f64::from(r.tmax) && t < best_t {
                best_t = t;
                best = Hit {
                    t: t as f32,
                    prim: i as u32,
                    u: u as f32,
                    v: v as f32,
                };
            }
        }
    }
    best
}

/// How far the ray's crossing with `tri` is from the triangle's boundary, in barycentrics.
fn edge_distance(r: &Ray, tri: &Triangle) -> f64 {
    match crossing(r, tri) {
        Some((_, u, v)) => u.abs().min(v.abs()).min((1.0 - u - v).abs()),
        None => 0.0,
    }
}

fn same(a: &Hit, b: &Hit) -> bool {
    if a.prim != b.prim {
        return false;
    }
    if !a.is_hit() {
        return true;
    }
    (a.t - b.t).abs() <= 1e-4 * b.t.abs().max(1e-3)
        && (a.u - b.u).abs() <= 1e-3
        && (a.v - b.v).abs() <= 1e-3
}

/// Checks `hits` against the reference; returns the agreement fraction and panics on a
/// disagreement that is neither at an edge nor at a near-tie.
fn compare(tris: &[Triangle], rays: &[Ray], hits: &[Hit]) -> f64 {
    let mut agree = 0usize;
    for (r, h) in rays.iter().zip(hits) {
        let want = reference(tris, r);
        if same(h, &want) {
            agree += 1;
            continue;
        }
        let near_edge =
            |prim: u32| prim != u32::MAX && edge_distance(r, &tris[prim as usize]) < 1e-4;
        let near_tie = h.is_hit() && want.is_hit() && (h.t - want.t).abs() <= 1e-4 * want.t;
        let near_end = (want.is_hit() && (want.t - r.tmax).abs() <= 1e-5 * want.t)
            || (h.is_hit() && (h.t - r.tmax).abs() <= 1e-5 * h.t);
        assert!(
            near_edge(h.prim) || near_edge(want.prim) || near_tie || near_end,
            "ray {r:?}: embree {h:?}, reference {want:?}"
        );
    }
    agree as f64 / rays.len() as f64
}

#[test]
fn random_soup_agrees_with_brute_force() {
    let tris = soup(3000, 7);
    let rays = soup_rays(20_000, 11);
    let e = embree(&tris, BuildOptions::default());
    let hits = trace(&*e, &rays, Query::Closest);
    let hit_count = hits.iter().filter(|h| h.is_hit()).count();
    assert!(hit_count > rays.len() / 2, "soup too sparse: {hit_count}");
    let agreement = compare(&tris, &rays, &hits);
    eprintln!(
        "soup: {hit_count} of {} rays hit, agreement {agreement}, {} bytes",
        rays.len(),
        e.bytes()
    );
    assert!(agreement >= 0.999, "agreement {agreement}");

    // occluded says exactly whether trace found a hit: both use Embree's interval rule.
    let occ = occluded(&*e, &rays);
    let mismatched = occ
        .iter()
        .zip(&hits)
        .filter(|(o, h)| (**o == 1) != h.is_hit())
        .count();
    assert_eq!(mismatched, 0);
    assert!(e.bytes() > 48 * tris.len());
}

#[test]
fn any_reports_a_real_hit_in_the_interval() {
    let tris = soup(1500, 3);
    let rays = soup_rays(5000, 5);
    let e = embree(&tris, BuildOptions::default());
    let closest = trace(&*e, &rays, Query::Closest);
    let any = trace(&*e, &rays, Query::Any);
    for ((r, a), c) in rays.iter().zip(&any).zip(&closest) {
        assert_eq!(a.is_hit(), c.is_hit(), "{r:?}");
        if a.is_hit() {
            assert!(a.t >= r.tmin && a.t <= r.tmax, "{r:?} {a:?}");
            let (t, _, _) = crossing(r, &tris[a.prim as usize]).expect("crosses");
            assert!((t as f32 - a.t).abs() <= 1e-4 * a.t, "{r:?} {a:?} {t}");
        }
    }
}

#[test]
fn every_build_quality_agrees() {
    let tris = soup(2000, 17);
    let rays = soup_rays(8000, 19);
    let mut results = Vec::new();
    for quality in [BuildQuality::Fast, BuildQuality::Sah, BuildQuality::Sbvh] {
        let e = embree(
            &tris,
            BuildOptions {
                quality,
                ..Default::default()
            },
        );
        let hits = trace(&*e, &rays, Query::Closest);
        let agreement = compare(&tris, &rays, &hits);
        assert!(agreement >= 0.999, "{quality:?}: agreement {agreement}");
        results.push(hits);
    }
    // Different trees, same answers up to edge cases.
    for other in &results[1..] {
        let differ = results[0]
            .iter()
            .zip(other)
            .filter(|(a, b)| !same(a, b))
            .count();
        assert!(differ * 1000 <= rays.len(), "{differ} differ");
    }
}

#[test]
fn thread_options_give_the_same_answers() {
    let tris = soup(2000, 23);
    let rays = soup_rays(8000, 29);
    let all = trace(
        &*embree(&tris, BuildOptions::default()),
        &rays,
        Query::Closest,
    );
    for threads in [1, 2] {
        let e = embree(
            &tris,
            BuildOptions {
                threads,
                quality: BuildQuality::Sah,
                ..Default::default()
            },
        );
        // Trace on a pool of the same size, as `rayd trace --threads N` does.
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let hits = pool.install(|| trace(&*e, &rays, Query::Closest));
        assert_eq!(hits, all, "threads={threads}");
    }
}
