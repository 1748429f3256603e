//! `dacrt` and `dacrt-sampled` against the brute-force reference: random triangle soups
//! (degenerate, tiny, huge, far away) and random rays (axis-parallel with ±0 components,
//! random intervals including infinite and empty ones), both precisions, both queries and
//! `occluded`, on one thread and on a small pool with every parallel path forced on.
//!
//! DACRT computes each ray/triangle pair with the same arithmetic as the reference, so the
//! closest hit must agree *exactly*: same triangle, same `t` bits, and ties at equal `t`
//! resolved to the lowest id. `any` must agree on hit/miss, and its hit must be a real hit.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};
use std::sync::{Mutex, MutexGuard};

use proptest::prelude::*;
use rayd::accel::dacrt::leaf::{LeafTest, Moller, Watertight};
use rayd::accel::dacrt::{Dacrt, DacrtOptions, ForkSplit};
use rayd::accel::{build, AccelKind, BuildOptions, Intersector, Precision, Query};
use rayd::geometry::{Hit, Ray, Triangle};

/// Counts the heap of the threads that are marked [`COUNTED`] (the memory test's thread and
/// its pool's): bytes in use now and the most in use since the last reset, so that the memory
/// test measures what DACRT itself allocates, whatever other tests do meanwhile.
struct Counting;

static IN_USE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

thread_local! {
    static COUNTED: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

fn counted() -> bool {
    COUNTED.try_with(|c| c.get()).unwrap_or(false)
}

// SAFETY: every call is forwarded to the system allocator unchanged; the counters are
// plain atomics.
#[allow(unsafe_code)]
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        // SAFETY: the caller's contract is passed on to `System`.
        let p = unsafe { System.alloc(l) };
        if !p.is_null() && counted() {
            let now = IN_USE.fetch_add(l.size(), Relaxed) + l.size();
            PEAK.fetch_max(now, Relaxed);
        }
        p
    }

    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        // SAFETY: as above.
        unsafe { System.dealloc(p, l) };
        if counted() {
            IN_USE.fetch_sub(l.size(), Relaxed);
        }
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// Tests of this file run one at a time (they are heavy, and the machine has few cores).
fn exclusive() -> MutexGuard<'static, ()> {
    static LOCK: Mutex<()> = Mutex::new(());
    LOCK.lock().unwrap_or_else(|e| e.into_inner())
}

/// The reference: `brute` of the same precision (every ray against every triangle).
fn reference(tris: &[Triangle], rays: &[Ray], precision: Precision) -> Vec<Hit> {
    let brute = build(
        AccelKind::Brute,
        tris,
        &BuildOptions {
            precision,
            ..BuildOptions::default()
        },
    )
    .expect("brute builds");
    let mut hits = vec![Hit::MISS; rays.len()];
    brute.trace(rays, Query::Closest, &mut hits);
    hits
}

/// Options that send even tiny batches through every parallel path.
fn forced_parallel(mut o: DacrtOptions) -> DacrtOptions {
    o.parallel.data_min_rays = 64;
    o.parallel.fork_min_rays = 8;
    o.parallel.data_min_tris = 16;
    o.parallel.grain = 16;
    o.parallel.fork_budget = 4.0;
    o
}

/// Ray-split forks from the root down to tiny steps, no data-parallel steps (the default
/// scheme, with its thresholds lowered).
fn root_forks(mut o: DacrtOptions) -> DacrtOptions {
    o.parallel.fork_min_rays = 8;
    o
}

/// Ray-split forks from the root, each half partitioning everything it reaches.
fn root_forks_no_top(mut o: DacrtOptions) -> DacrtOptions {
    o.parallel.fork_min_rays = 8;
    o.parallel.top_min_tris = 0;
    o
}

/// Ray-split forks from the root with the top levels partitioned once for all threads
/// down to the smallest nodes (`top.rs`).
fn shared_top(mut o: DacrtOptions) -> DacrtOptions {
    o.parallel.fork_min_rays = 8;
    o.parallel.top_min_tris = 2;
    o
}

fn tris_split(mut o: DacrtOptions) -> DacrtOptions {
    o.parallel.split = ForkSplit::Tris;
    o
}

/// The variants checked: (label, options, threads).
fn variants() -> Vec<(&'static str, DacrtOptions, usize)> {
    let mut small_leaves = DacrtOptions::afra();
    small_leaves.leaf_rays = 2;
    small_leaves.leaf_tris = 2;
    let mut sampled_small = DacrtOptions::nabata();
    sampled_small.leaf_rays = 2;
    sampled_small.leaf_tris = 2;
    sampled_small.sampling.min_rays = 4;
    sampled_small.sampling.samples = 7;
    vec![
        ("dacrt", DacrtOptions::afra(), 1),
        ("dacrt-small", small_leaves, 1),
        ("dacrt-sampled-small", sampled_small, 1),
        ("dacrt-par", forced_parallel(small_leaves), 2),
        ("dacrt-sampled-par", forced_parallel(sampled_small), 3),
        ("dacrt-root-forks", root_forks(small_leaves), 2),
        ("dacrt-sampled-root-forks", root_forks(sampled_small), 3),
        ("dacrt-shared-top", shared_top(small_leaves), 2),
        ("dacrt-sampled-shared-top", shared_top(sampled_small), 3),
        ("dacrt-no-top", root_forks_no_top(small_leaves), 2),
        // One group of rays per thread from the start, groups of unequal length (5) and
        // many groups (8), with and without the shared top.
        ("dacrt-groups-8", shared_top(small_leaves), 8),
        (
            "dacrt-sampled-groups-5",
            root_forks_no_top(sampled_small),
            5,
        ),
        ("dacrt-sampled-groups-7", shared_top(sampled_small), 7),
        (
            "dacrt-par-tris",
            tris_split(forced_parallel(small_leaves)),
            2,
        ),
        (
            "dacrt-sampled-par-tris",
            tris_split(forced_parallel(sampled_small)),
            3,
        ),
    ]
}

fn run_query(a: &Dacrt, rays: &[Ray], q: Query, threads: usize) -> Vec<Hit> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let mut hits = vec![Hit::MISS; rays.len()];
    pool.install(|| a.trace(rays, q, &mut hits));
    hits
}

fn run_occluded(a: &Dacrt, rays: &[Ray], threads: usize) -> Vec<u8> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let mut out = vec![7u8; rays.len()];
    pool.install(|| a.occluded(rays, &mut out));
    out
}

/// Checks every variant and query against the reference; returns the first disagreement.
fn check(tris: &[Triangle], rays: &[Ray]) -> Result<(), String> {
    let r = check_inner(tris, rays);
    if r.is_err() {
        if let Ok(path) = std::env::var("DACRT_DUMP_FAIL") {
            let mut out = String::new();
            for t in tris {
                for p in t.v {
                    for c in p {
                        out += &format!("{} ", c.to_bits());
                    }
                }
                out += "\n";
            }
            out += "rays\n";
            for r in rays {
                for c in [
                    r.org[0], r.org[1], r.org[2], r.tmin, r.dir[0], r.dir[1], r.dir[2], r.tmax,
                ] {
                    out += &format!("{} ", c.to_bits());
                }
                out += "\n";
            }
            std::fs::write(path, out).unwrap();
        }
    }
    r
}

fn check_inner(tris: &[Triangle], rays: &[Ray]) -> Result<(), String> {
    let _alone = exclusive();
    for precision in [Precision::Watertight, Precision::Fast] {
        let want = reference(tris, rays, precision);
        for (label, opts, threads) in variants() {
            let a = Dacrt::with_options("dacrt", tris, precision, opts);
            let got = run_query(&a, rays, Query::Closest, threads);
            for (i, (g, w)) in got.iter().zip(&want).enumerate() {
                let same = g.prim == w.prim
                    && g.t.to_bits() == w.t.to_bits()
                    && g.u.to_bits() == w.u.to_bits()
                    && g.v.to_bits() == w.v.to_bits();
                let excused = precision == Precision::Fast && mt_near_edge(tris, &rays[i], g, w);
                if !same && !excused {
                    return Err(format!(
                        "{label} {precision:?} closest ray {i} {:?}: got {g:?}, want {w:?}",
                        rays[i]
                    ));
                }
            }
            let any = run_query(&a, rays, Query::Any, threads);
            for (i, (g, w)) in any.iter().zip(&want).enumerate() {
                let excused = precision == Precision::Fast && mt_near_edge(tris, &rays[i], g, w);
                if g.is_hit() != w.is_hit() && !excused {
                    return Err(format!(
                        "{label} {precision:?} any ray {i} {:?}: got {g:?}, want {w:?}",
                        rays[i]
                    ));
                }
                if g.is_hit() {
                    let r = &rays[i];
                    let tri = tris[g.prim as usize].v;
                    let again = match precision {
                        Precision::Fast => Moller::full(r, tri),
                        Precision::Watertight => Watertight::full(r, tri),
                    };
                    if again != Some((g.t, g.u, g.v)) {
                        return Err(format!("{label} any ray {i}: {g:?} is not a hit"));
                    }
                }
            }
            let occ = run_occluded(&a, rays, threads);
            for (i, (o, w)) in occ.iter().zip(&want).enumerate() {
                let excused =
                    precision == Precision::Fast && mt_near_edge(tris, &rays[i], &any[i], w);
                if ((*o == 1) != w.is_hit() && !excused) || *o > 1 {
                    return Err(format!("{label} {precision:?} occluded ray {i}: got {o}"));
                }
            }
        }
    }
    Ok(())
}

/// The documented exception, for `fast` only: Möller–Trumbore is not watertight, and with
/// slivers or large triangles its rounding can report a hit a hair outside a triangle — or,
/// for a near-degenerate sliver, at a `t` where the ray is nowhere near it. Such a hit can lie
/// outside the triangle's bounding box, which DACRT's filtering culls; DACRT then reports the
/// next hit (or a miss) where brute reports the spurious one. A disagreement is excused when
/// the reference's hit that DACRT lacks is *spurious* — its point (`org + t·dir`, in f64) is
/// outside the triangle's box, or within 1e-3 of an edge in barycentric terms — and DACRT's
/// own hit, if any, is a real Möller–Trumbore hit no nearer than the reference's.
fn mt_near_edge(tris: &[Triangle], ray: &Ray, got: &Hit, want: &Hit) -> bool {
    let spurious = |h: &Hit| {
        if !h.is_hit() {
            return true;
        }
        let v = tris[h.prim as usize].v.map(|p| p.map(f64::from));
        let o = ray.org.map(f64::from);
        let d = ray.dir.map(f64::from);
        let p = [0, 1, 2].map(|k| o[k] + f64::from(h.t) * d[k]);
        let outside = (0..3).any(|k| {
            let lo = v[0][k].min(v[1][k]).min(v[2][k]);
            let hi = v[0][k].max(v[1][k]).max(v[2][k]);
            let m = 1e-6 * (hi - lo + lo.abs().max(hi.abs()));
            p[k] < lo - m || p[k] > hi + m
        });
        let sub = |a: [f64; 3], b: [f64; 3]| [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
        let cross = |a: [f64; 3], b: [f64; 3]| {
            [
                a[1] * b[2] - a[2] * b[1],
                a[2] * b[0] - a[0] * b[2],
                a[0] * b[1] - a[1] * b[0],
            ]
        };
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let (e1, e2) = (sub(v[1], v[0]), sub(v[2], v[0]));
        let q = cross(d, e2);
        let det = dot(e1, q);
        if outside || det == 0.0 {
            return true;
        }
        let s = sub(o, v[0]);
        let u = dot(s, q) / det;
        let w = dot(d, cross(s, e1)) / det;
        let m = u.min(w).min(1.0 - u - w);
        m > -1e-3 && m < 1e-3
    };
    let real = !got.is_hit()
        || (Moller::full(ray, tris[got.prim as usize].v) == Some((got.t, got.u, got.v))
            && got.t >= want.t);
    real && (got.prim == want.prim || spurious(want))
}

// ---- generators ----

fn coord(scale: f32) -> impl Strategy<Value = f32> {
    prop_oneof![
        4 => -scale..scale,
        1 => Just(0.0f32),
        1 => Just(-0.0f32),
        1 => (-4i32..4).prop_map(|i| i as f32 * 0.25),
    ]
}

fn vec3(scale: f32) -> impl Strategy<Value = [f32; 3]> {
    [coord(scale), coord(scale), coord(scale)]
}

/// A triangle of one of the awkward kinds.
fn triangle() -> impl Strategy<Value = Triangle> {
    let plain = [vec3(1.0), vec3(1.0), vec3(1.0)].prop_map(|v| Triangle { v });
    let tiny = (vec3(1.0), vec3(1e-4), vec3(1e-4)).prop_map(|(p, a, b)| Triangle {
        v: [
            p,
            [p[0] + a[0], p[1] + a[1], p[2] + a[2]],
            [p[0] + b[0], p[1] + b[1], p[2] + b[2]],
        ],
    });
    let huge = [vec3(1e4), vec3(1e4), vec3(1e4)].prop_map(|v| Triangle { v });
    let far = (vec3(1.0), vec3(1.0), vec3(1.0), vec3(1e6)).prop_map(|(a, b, c, o)| Triangle {
        v: [a, b, c].map(|p| [p[0] + o[0], p[1] + o[1], p[2] + o[2]]),
    });
    let degenerate = (vec3(1.0), vec3(1.0), 0u8..3).prop_map(|(a, b, k)| Triangle {
        v: match k {
            0 => [a, a, b],
            1 => [a, b, a],
            _ => [
                a,
                b,
                [2.0 * b[0] - a[0], 2.0 * b[1] - a[1], 2.0 * b[2] - a[2]],
            ],
        },
    });
    // Grid-snapped triangles share exact edges, vertices and planes: ties in t.
    let snapped = [vec3(1.0), vec3(1.0), vec3(1.0)].prop_map(|v| Triangle {
        v: v.map(|p| p.map(|c| (c * 2.0).round() * 0.5)),
    });
    prop_oneof![
        6 => plain,
        2 => tiny,
        1 => huge,
        1 => far,
        1 => degenerate,
        3 => snapped,
    ]
}

fn direction() -> impl Strategy<Value = [f32; 3]> {
    let axis = (0usize..3, prop::bool::ANY, prop::bool::ANY, prop::bool::ANY).prop_map(
        |(k, neg, nz1, nz2)| {
            let mut d = [
                if nz1 { -0.0 } else { 0.0 },
                if nz2 { -0.0 } else { 0.0 },
                0.0,
            ];
            d[2] = d[k];
            d[k] = if neg { -1.0 } else { 1.0 };
            d
        },
    );
    let random = vec3(1.0).prop_filter("non-zero", |d| d.iter().any(|&c| c != 0.0));
    prop_oneof![3 => random, 1 => axis]
}

fn interval() -> impl Strategy<Value = (f32, f32)> {
    let tmin = prop_oneof![4 => Just(0.0f32), 2 => 0.0f32..2.0, 1 => Just(f32::INFINITY)];
    let tmax = prop_oneof![
        4 => Just(f32::INFINITY),
        3 => 0.0f32..4.0,
        1 => Just(0.0f32),
        1 => -1.0f32..0.0,
    ];
    (tmin, tmax)
}

fn ray() -> impl Strategy<Value = Ray> {
    (vec3(2.0), direction(), interval()).prop_map(|(org, dir, (tmin, tmax))| Ray {
        org,
        tmin,
        dir,
        tmax,
    })
}

/// Rays aimed at the vertices, edge midpoints and centroids of the soup: where ties and
/// shared edges are.
fn aimed(tris: &[Triangle], origins: &[[f32; 3]]) -> Vec<Ray> {
    let mut out = Vec::new();
    for (k, t) in tris.iter().enumerate().take(24) {
        let [a, b, c] = t.v;
        let targets = [
            a,
            [
                (a[0] + b[0]) * 0.5,
                (a[1] + b[1]) * 0.5,
                (a[2] + b[2]) * 0.5,
            ],
            [
                (a[0] + b[0] + c[0]) / 3.0,
                (a[1] + b[1] + c[1]) / 3.0,
                (a[2] + b[2] + c[2]) / 3.0,
            ],
        ];
        for (j, p) in targets.iter().enumerate() {
            let o = origins[(k + j) % origins.len()];
            let d = [p[0] - o[0], p[1] - o[1], p[2] - o[2]];
            if d.iter().all(|&x| x == 0.0) || d.iter().any(|x| !x.is_finite()) {
                continue;
            }
            out.push(Ray {
                org: o,
                tmin: 0.0,
                dir: d,
                tmax: f32::INFINITY,
            });
        }
    }
    out
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    #[test]
    fn random_soups_agree_with_reference(
        tris in prop::collection::vec(triangle(), 1..120),
        mut rays in prop::collection::vec(ray(), 1..300),
        origins in prop::collection::vec(vec3(3.0), 1..4),
    ) {
        rays.extend(aimed(&tris, &origins));
        let r = check(&tris, &rays);
        prop_assert!(r.is_ok(), "{}", r.unwrap_err());
    }
}

/// A bigger scene than proptest makes: a tessellated sphere seen from inside and outside,
/// enough rays and triangles for the sampling, SAH and fork paths at their real thresholds.
#[test]
fn sphere_with_many_rays_agrees() {
    let tris = sphere(40, 60, 1.0);
    let mut rays = Vec::new();
    let mut s = 12345u64;
    let mut rnd = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    };
    for i in 0..6000 {
        let org = if i % 2 == 0 {
            [0.1 * rnd(), 0.1 * rnd(), 0.1 * rnd()]
        } else {
            [3.0, 0.2 * rnd(), 0.2 * rnd()]
        };
        let dir = if i % 2 == 0 {
            [rnd(), rnd(), rnd() + 0.001]
        } else {
            [-1.0, 0.4 * rnd(), 0.4 * rnd()]
        };
        rays.push(Ray {
            org,
            tmin: 0.0,
            dir,
            tmax: f32::INFINITY,
        });
    }
    check(&tris, &rays).unwrap();
}

/// A UV sphere of `2·stacks·slices` triangles (some degenerate at the poles).
fn sphere(stacks: usize, slices: usize, r: f32) -> Vec<Triangle> {
    let p = |i: usize, j: usize| {
        let th = std::f32::consts::PI * i as f32 / stacks as f32;
        let ph = 2.0 * std::f32::consts::PI * j as f32 / slices as f32;
        [
            r * th.sin() * ph.cos(),
            r * th.cos(),
            r * th.sin() * ph.sin(),
        ]
    };
    let mut out = Vec::new();
    for i in 0..stacks {
        for j in 0..slices {
            out.push(Triangle {
                v: [p(i, j), p(i + 1, j), p(i + 1, j + 1)],
            });
            out.push(Triangle {
                v: [p(i, j), p(i + 1, j + 1), p(i, j + 1)],
            });
        }
    }
    out
}

/// The papers' budget: 32·R + (48 + 4·N)·T bytes for R rays, T triangles and N threads,
/// stack and hits excluded. DACRT's own heap (the precompute held between traces, and what
/// a trace allocates: records, the id array, fork copies) must stay within 1.2 times it;
/// the scene, the input rays and the output hits are not counted.
#[test]
fn memory_stays_within_the_papers_budget() {
    let tris = sphere(250, 400, 1.0); // 200 000 triangles
    let t = tris.len();
    let mut s = 99u64;
    let mut rnd = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    };
    let rays: Vec<Ray> = (0..500_000)
        .map(|i| Ray {
            org: if i % 2 == 0 {
                [0.2 * rnd(), 0.2 * rnd(), 0.2 * rnd()]
            } else {
                [0.0, 0.0, 3.0]
            },
            tmin: 0.0,
            dir: if i % 2 == 0 {
                [rnd(), rnd(), rnd() + 1e-3]
            } else {
                [0.5 * rnd(), 0.5 * rnd(), -1.0]
            },
            tmax: f32::INFINITY,
        })
        .collect();
    let r = rays.len();
    let mut hits = vec![Hit::MISS; r];
    let mut flags = vec![0u8; r];
    for threads in [1usize, 2, 4] {
        for opts in [DacrtOptions::afra(), DacrtOptions::nabata()] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .start_handler(|_| COUNTED.with(|c| c.set(true)))
                .build()
                .unwrap();
            let _alone = exclusive();
            COUNTED.with(|c| c.set(true));
            let base = IN_USE.load(Relaxed);
            let a =
                pool.install(|| Dacrt::with_options("dacrt", &tris, Precision::default(), opts));
            let held = IN_USE.load(Relaxed) - base;
            PEAK.store(IN_USE.load(Relaxed), Relaxed);
            pool.install(|| a.trace(&rays, Query::Closest, &mut hits));
            let trace_peak = PEAK.load(Relaxed) - base;
            PEAK.store(IN_USE.load(Relaxed), Relaxed);
            pool.install(|| a.occluded(&rays, &mut flags));
            let occluded_peak = PEAK.load(Relaxed) - base;
            drop(a);
            COUNTED.with(|c| c.set(false));
            let budget = 32 * r + (48 + 4 * threads) * t;
            eprintln!(
                "memory: {threads} thread(s), sampling {}: held {held} B ({:.1} B/tri), \
                 trace peak {trace_peak} B, occluded peak {occluded_peak} B; papers' budget \
                 {budget} B: trace at {:.3}x",
                opts.sampling.enabled(),
                held as f64 / t as f64,
                trace_peak as f64 / budget as f64
            );
            assert!(held as f64 <= 48.1 * t as f64, "precompute {held} B");
            assert!(
                trace_peak as f64 <= 1.2 * budget as f64,
                "trace peak {trace_peak} B > 1.2 × {budget} B"
            );
            // `occluded` has no output hit records to hold the hit slots in: its own 16 B
            // per ray are the hits that the budget leaves out.
            assert!(
                occluded_peak as f64 <= 1.2 * budget as f64 + 16.0 * r as f64,
                "occluded peak {occluded_peak} B"
            );
        }
    }
}

#[test]
fn ties_go_to_the_lowest_id() {
    // Four copies of one quad, in shuffled id order, plus a farther one: every ray ties
    // between copies and must report the lowest id.
    let q = [
        [-1.0, -1.0, 0.0],
        [1.0, -1.0, 0.0],
        [1.0, 1.0, 0.0],
        [-1.0, 1.0, 0.0],
    ];
    let far = q.map(|p| [p[0], p[1], 1.0]);
    let mut tris = Vec::new();
    for k in 0..12 {
        let src = if k % 5 == 0 { far } else { q };
        tris.push(Triangle {
            v: [src[0], src[1], src[2]],
        });
        tris.push(Triangle {
            v: [src[0], src[2], src[3]],
        });
    }
    let rays: Vec<Ray> = (0..400)
        .map(|i| {
            let x = (i % 20) as f32 / 10.0 - 0.95;
            let y = (i / 20) as f32 / 10.0 - 0.95;
            Ray {
                org: [x, y, if i % 3 == 0 { 5.0 } else { -5.0 }],
                tmin: 0.0,
                dir: [0.0, 0.0, if i % 3 == 0 { -1.0 } else { 1.0 }],
                tmax: f32::INFINITY,
            }
        })
        .collect();
    check(&tris, &rays).unwrap();
}

#[test]
fn empty_scene_and_all_degenerate_scene_miss() {
    let rays = vec![Ray {
        org: [0.0; 3],
        tmin: 0.0,
        dir: [1.0, 0.0, 0.0],
        tmax: f32::INFINITY,
    }];
    check(&[], &rays).unwrap();
    let d = Triangle {
        v: [[1.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 2.0, 2.0]],
    };
    check(&[d, d], &rays).unwrap();
    check(&[d], &[]).unwrap();
}

/// Traces a ray set dumped by `rayd bench --dump` on the bench's interior view of a scene,
/// once, inside [`profiled_trace`], for instruction and cache counts that do not depend on
/// the machine's load (`valgrind --tool=cachegrind --toggle-collect='*profiled_trace*'`).
/// Skipped unless `DACRT_PROFILE_SCENE` and `DACRT_PROFILE_RAYS` are set; `DACRT_PROFILE_ACCEL`
/// picks the accelerator (default `dacrt`), `DACRT_PROFILE_THREADS` the pool (default 1).
#[test]
#[ignore]
fn profile_one_trace() {
    let (Ok(scene), Ok(rays)) = (
        std::env::var("DACRT_PROFILE_SCENE"),
        std::env::var("DACRT_PROFILE_RAYS"),
    ) else {
        return;
    };
    let scene = rayd::formats::load_scene(
        std::path::Path::new(&scene),
        &rayd::formats::LoadOptions::default(),
    )
    .unwrap();
    let view = rayd::bench::View::new(
        &scene,
        rayd::bench::ViewKind::Interior,
        &rayd::bench::CameraChoice::Auto,
        1024,
        768,
    )
    .unwrap();
    let rays = rayd::formats::binary::read_rays(&std::fs::read(rays).unwrap()).unwrap();
    let kind = std::env::var("DACRT_PROFILE_ACCEL").unwrap_or_else(|_| "dacrt".into());
    let accel = build(
        AccelKind::parse(&kind).unwrap(),
        &view.triangles,
        &BuildOptions::default(),
    )
    .unwrap();
    let threads = std::env::var("DACRT_PROFILE_THREADS")
        .ok()
        .and_then(|t| t.parse().ok())
        .unwrap_or(1);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let mut hits = vec![Hit::MISS; rays.len()];
    let t0 = std::time::Instant::now();
    pool.install(|| profiled_trace(accel.as_ref(), &rays, &mut hits));
    eprintln!(
        "{kind}: {} rays in {:.1} ms, {} hit",
        rays.len(),
        t0.elapsed().as_secs_f64() * 1e3,
        hits.iter().filter(|h| h.is_hit()).count()
    );
}

#[inline(never)]
fn profiled_trace(accel: &dyn Intersector, rays: &[Ray], hits: &mut [Hit]) {
    accel.trace(rays, Query::Closest, hits);
}
