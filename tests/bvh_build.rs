//! Build, refit and statistics of the static BVHs (`mbvh8`, `mbvh4`, `bvh2`) on
//! procedural scenes and random triangle soups. The timing run is `#[ignore]`d:
//!
//! ```text
//! RAYD_SCENES=path/to/scenes cargo test --release --test bvh_build -- --ignored --nocapture
//! ```

use proptest::prelude::*;
use rayd::accel::bvh::{Bvh2, Child, Mbvh, Mbvh4, Mbvh8, RefitError};
use rayd::accel::BuildQuality;
use rayd::geometry::Triangle;

const QUALITIES: [BuildQuality; 3] = [BuildQuality::Fast, BuildQuality::Sah, BuildQuality::Sbvh];

/// Small deterministic generator (SplitMix64) so the scenes need no dependency.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn f(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }
}

fn tri(a: [f32; 3], b: [f32; 3], c: [f32; 3]) -> Triangle {
    Triangle { v: [a, b, c] }
}

/// A UV sphere of `2 · rings · segments` triangles (the poles' slivers are degenerate
/// and get left out).
fn sphere(center: [f32; 3], r: f32, rings: usize, segments: usize) -> Vec<Triangle> {
    let p = |i: usize, j: usize| {
        let th = std::f32::consts::PI * i as f32 / rings as f32;
        let ph = 2.0 * std::f32::consts::PI * j as f32 / segments as f32;
        [
            center[0] + r * th.sin() * ph.cos(),
            center[1] + r * th.cos(),
            center[2] + r * th.sin() * ph.sin(),
        ]
    };
    let mut out = Vec::new();
    for i in 0..rings {
        for j in 0..segments {
            out.push(tri(p(i, j), p(i + 1, j), p(i + 1, j + 1)));
            out.push(tri(p(i, j), p(i + 1, j + 1), p(i, j + 1)));
        }
    }
    out
}

/// A flat grid in z = `z` (a zero-extent axis).
fn grid(n: usize, z: f32) -> Vec<Triangle> {
    let mut out = Vec::new();
    for i in 0..n {
        for j in 0..n {
            let (x, y) = (i as f32, j as f32);
            out.push(tri([x, y, z], [x + 1.0, y, z], [x + 1.0, y + 1.0, z]));
            out.push(tri([x, y, z], [x + 1.0, y + 1.0, z], [x, y + 1.0, z]));
        }
    }
    out
}

/// Random triangles of size about `size` in a cube of side `extent`.
fn soup(n: usize, extent: f32, size: f32, seed: u64) -> Vec<Triangle> {
    let mut rng = Rng(seed);
    (0..n)
        .map(|_| {
            let c = [rng.f() * extent, rng.f() * extent, rng.f() * extent];
            let mut v = || {
                [
                    c[0] + (rng.f() - 0.5) * size,
                    c[1] + (rng.f() - 0.5) * size,
                    c[2] + (rng.f() - 0.5) * size,
                ]
            };
            tri(v(), v(), v())
        })
        .collect()
}

/// Triangles that all share one centroid (binning finds no object split).
fn same_centroid(n: usize) -> Vec<Triangle> {
    (0..n)
        .map(|i| {
            let s = 1.0 + i as f32;
            tri([-s, -s, 0.0], [2.0 * s, 0.0, s], [-s, s, -s])
        })
        .collect()
}

/// Long thin triangles crossing each other (where spatial splits pay).
fn slivers(n: usize) -> Vec<Triangle> {
    (0..n)
        .map(|i| {
            let a = i as f32 * 0.37;
            let (c, s) = (a.cos() * 50.0, a.sin() * 50.0);
            tri(
                [-c, -s, 0.1 * i as f32],
                [c, s, 0.1 * i as f32],
                [c, s + 0.5, 0.1 * i as f32 + 0.2],
            )
        })
        .collect()
}

fn check_all(name: &str, tris: &[Triangle]) {
    for q in QUALITIES {
        let m8 = Mbvh8::build(tris, q);
        m8.validate(tris)
            .unwrap_or_else(|e| panic!("{name} mbvh8 {q:?}: {e}"));
        let m4 = Mbvh4::build(tris, q);
        m4.validate(tris)
            .unwrap_or_else(|e| panic!("{name} mbvh4 {q:?}: {e}"));
        let b2 = Bvh2::build(tris, q);
        b2.validate(tris)
            .unwrap_or_else(|e| panic!("{name} bvh2 {q:?}: {e}"));
        let s = m8.stats();
        assert_eq!(s.triangles, tris.len());
        assert_eq!(s.excluded, m8.excluded().len());
        assert!(s.references >= tris.len() - s.excluded, "{name} {q:?}");
        if q != BuildQuality::Sbvh {
            assert_eq!(s.references, tris.len() - s.excluded, "{name} {q:?}");
        }
        assert!(s.node_utilization <= 1.0 && s.multi_triangle_utilization <= 1.0);
        assert!(s.sah_cost.is_finite());
        let s2 = b2.stats();
        assert_eq!(s2.references, b2.tris().len());
    }
}

#[test]
fn empty_scene() {
    let tris: Vec<Triangle> = Vec::new();
    check_all("empty", &tris);
    let m = Mbvh8::build(&tris, BuildQuality::Sah);
    assert_eq!(m.nodes().len(), 1);
    assert_eq!(m.nodes()[0].lanes(), 0);
    assert!(m.multi_tris().is_empty());
    assert!(m.bounds().is_empty());
    assert!(Bvh2::build(&tris, BuildQuality::Sah).nodes().is_empty());
}

#[test]
fn one_and_two_triangles() {
    let one = vec![tri([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])];
    check_all("one", &one);
    let m = Mbvh8::build(&one, BuildQuality::Sah);
    assert_eq!(m.nodes().len(), 1);
    assert_eq!(m.nodes()[0].lanes(), 1);
    assert_eq!(
        Child::decode(m.nodes()[0].child[0]),
        Child::Leaf { first: 0, count: 1 }
    );
    assert_eq!(m.multi_tris()[0].lanes(), 1);
    let b = Bvh2::build(&one, BuildQuality::Sah);
    assert_eq!(b.nodes().len(), 1);
    assert_eq!(b.nodes()[0].skip, 1);
    let mut two = one.clone();
    two.push(tri([5.0, 0.0, 0.0], [6.0, 0.0, 0.0], [5.0, 1.0, 0.0]));
    check_all("two", &two);
}

#[test]
fn degenerate_and_non_finite_triangles_are_left_out() {
    let mut tris = soup(200, 10.0, 1.0, 1);
    tris[3] = tri([1.0; 3], [1.0; 3], [1.0; 3]);
    tris[50] = tri([0.0; 3], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]);
    tris[77] = tri([f32::NAN, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]);
    tris[199] = tri([f32::INFINITY, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]);
    check_all("degenerate", &tris);
    let m = Mbvh8::build(&tris, BuildQuality::Sah);
    assert_eq!(m.excluded(), &[3, 50, 77, 199]);
    // Only degenerate triangles: an empty tree.
    let all_bad = vec![tris[3], tris[50]];
    check_all("all degenerate", &all_bad);
    assert_eq!(
        Mbvh4::build(&all_bad, BuildQuality::Sbvh).nodes()[0].lanes(),
        0
    );
}

#[test]
fn procedural_scenes() {
    check_all("sphere", &sphere([0.0; 3], 1.0, 40, 60));
    check_all("grid", &grid(50, 3.0));
    check_all("soup", &soup(5000, 100.0, 2.0, 7));
    check_all("same centroid", &same_centroid(300));
    check_all("slivers", &slivers(400));
    // Many identical triangles: all centroids equal, nothing to split on at all.
    check_all(
        "duplicates",
        &vec![tri([0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]); 100],
    );
}

#[test]
fn huge_and_tiny_coordinates() {
    let scale = |tris: Vec<Triangle>, s: f32, off: f32| -> Vec<Triangle> {
        tris.into_iter()
            .map(|t| Triangle {
                v: t.v.map(|p| p.map(|x| x * s + off)),
            })
            .collect()
    };
    check_all("huge", &scale(soup(2000, 1.0, 0.05, 3), 1e30, 0.0));
    check_all("tiny", &scale(soup(2000, 1.0, 0.05, 4), 1e-30, 0.0));
    check_all("far off", &scale(soup(2000, 1.0, 0.05, 5), 1.0, 1e7));
    // Mixed: a small cluster near the origin and a few triangles near the f32 limit.
    let mut mixed = soup(1000, 1.0, 0.01, 6);
    mixed.extend(scale(soup(20, 1.0, 0.5, 8), 1e38, -1e38));
    mixed.extend(scale(soup(20, 1.0, 0.5, 9), 1e38, 2e38));
    check_all("mixed", &mixed);
}

#[test]
fn depth_stays_bounded_on_adversarial_input() {
    // Triangles in a geometric progression: every SAH split peels off a few far ones,
    // which would make a tree as deep as the scene is long without the depth guard.
    let mut tris: Vec<Triangle> = (0..4000)
        .map(|i| {
            let x = 1.01f32.powi(i);
            tri([x, 0.0, 0.0], [x * 1.001, 0.0, 0.0], [x, x * 0.001, 0.0])
        })
        .collect();
    // Doubling distances across the whole exponent range.
    tris.extend((-120..120).map(|i| {
        let x = 2f32.powi(i);
        tri(
            [x, 5.0, 0.0],
            [x * 1.001, 5.0, 0.0],
            [x, 5.0 + x * 0.25, 0.0],
        )
    }));
    for q in QUALITIES {
        let limit = rayd::accel::bvh::DEPTH_LIMIT as usize + 32;
        let m = Mbvh8::build(&tris, q);
        m.validate(&tris).unwrap();
        assert!(
            m.stats().max_depth <= limit,
            "{q:?}: {}",
            m.stats().max_depth
        );
        let b = Bvh2::build(&tris, q);
        b.validate(&tris).unwrap();
        assert!(
            b.stats().max_depth <= limit,
            "{q:?}: {}",
            b.stats().max_depth
        );
    }
}

#[test]
fn leaves_respect_the_size_limit_and_sah_stops_early() {
    // A dense cluster of 1000 tiny triangles: every leaf has at most 2N of them.
    let tris = soup(1000, 1.0, 0.001, 11);
    for q in QUALITIES {
        let m = Mbvh8::build(&tris, q);
        let s = m.stats();
        assert!(s.avg_leaf_triangles <= 16.0);
        assert!(s.max_depth >= 2);
        let m4 = Mbvh4::build(&tris, q);
        assert!(m4.stats().avg_leaf_triangles <= 8.0);
    }
}

#[test]
fn sbvh_splits_long_triangles_and_stays_covered() {
    let tris = slivers(2000);
    let sah = Mbvh8::build(&tris, BuildQuality::Sah).stats();
    let sbvh = Mbvh8::build(&tris, BuildQuality::Sbvh).stats();
    assert!(
        sbvh.references > tris.len(),
        "no spatial split on crossing slivers"
    );
    assert!(sbvh.references <= 2 * tris.len());
    assert!(
        sbvh.sah_cost < sah.sah_cost,
        "sbvh {} vs sah {}",
        sbvh.sah_cost,
        sah.sah_cost
    );
}

#[test]
fn build_is_independent_of_thread_count() {
    let mut tris = sphere([0.0; 3], 1.0, 100, 150);
    tris.extend(soup(30_000, 4.0, 0.1, 12));
    for q in QUALITIES {
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let two = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let a = one.install(|| Mbvh8::build(&tris, q));
        let b = two.install(|| Mbvh8::build(&tris, q));
        assert_eq!(a.nodes(), b.nodes(), "{q:?}");
        assert_eq!(a.multi_tris(), b.multi_tris(), "{q:?}");
        b.validate(&tris).unwrap();
        let a = one.install(|| Bvh2::build(&tris, q));
        let b = two.install(|| Bvh2::build(&tris, q));
        assert_eq!(a.nodes(), b.nodes(), "{q:?}");
        assert_eq!(a.tris(), b.tris(), "{q:?}");
    }
}

/// Moves every vertex by a smooth deformation.
fn deform(tris: &[Triangle], t: f32) -> Vec<Triangle> {
    tris.iter()
        .map(|tr| Triangle {
            v: tr.v.map(|p| {
                [
                    p[0] + t * (p[1] * 3.0).sin(),
                    p[1] * (1.0 + 0.5 * t),
                    p[2] - t * p[0] * 0.3,
                ]
            }),
        })
        .collect()
}

#[test]
fn refit_matches_the_moved_geometry() {
    let mut tris = sphere([0.0; 3], 2.0, 30, 40);
    tris.extend(soup(3000, 6.0, 0.3, 13));
    tris.extend(slivers(200));
    let moved = deform(&tris, 0.7);
    for q in QUALITIES {
        let mut m8 = Mbvh8::build(&tris, q);
        let mut m4 = Mbvh4::build(&tris, q);
        let mut b2 = Bvh2::build(&tris, q);
        m8.refit(&moved).unwrap();
        m4.refit(&moved).unwrap();
        b2.refit(&moved).unwrap();
        // Tight boxes of the moved triangles at every level, every triangle inside.
        m8.validate(&moved)
            .unwrap_or_else(|e| panic!("mbvh8 {q:?}: {e}"));
        m4.validate(&moved)
            .unwrap_or_else(|e| panic!("mbvh4 {q:?}: {e}"));
        b2.validate(&moved)
            .unwrap_or_else(|e| panic!("bvh2 {q:?}: {e}"));
        // Refitting back gives the original tree (non-SBVH: boxes were tight already).
        if q != BuildQuality::Sbvh {
            let orig = Mbvh8::build(&tris, q);
            m8.refit(&tris).unwrap();
            assert_eq!(m8.nodes(), orig.nodes(), "{q:?}");
            assert_eq!(m8.multi_tris(), orig.multi_tris(), "{q:?}");
            let orig2 = Bvh2::build(&tris, q);
            b2.refit(&tris).unwrap();
            assert_eq!(b2.nodes(), orig2.nodes(), "{q:?}");
        }
        // Against a rebuild over the moved triangles: same root box.
        let rebuilt = Mbvh8::build(&moved, q);
        let mut m = Mbvh8::build(&tris, q);
        m.refit(&moved).unwrap();
        assert_eq!(m.bounds(), rebuilt.bounds());
    }
}

#[test]
fn refit_in_parallel_equals_serial() {
    let tris = soup(40_000, 10.0, 0.2, 14);
    let moved = deform(&tris, 0.3);
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let two = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let mut a = Mbvh8::build(&tris, BuildQuality::Sah);
    let mut b = a.clone();
    one.install(|| a.refit(&moved)).unwrap();
    two.install(|| b.refit(&moved)).unwrap();
    assert_eq!(a.nodes(), b.nodes());
    let mut c = Bvh2::build(&tris, BuildQuality::Sah);
    let mut d = c.clone();
    one.install(|| c.refit(&moved)).unwrap();
    two.install(|| d.refit(&moved)).unwrap();
    assert_eq!(c.nodes(), d.nodes());
}

#[test]
fn refit_refuses_topology_changes() {
    let mut tris = soup(100, 5.0, 0.5, 15);
    tris[10] = tri([1.0; 3], [1.0; 3], [1.0; 3]);
    let mut m = Mbvh8::build(&tris, BuildQuality::Sah);
    assert_eq!(
        m.refit(&tris[..99]),
        Err(RefitError::Count {
            expected: 100,
            got: 99
        })
    );
    // A left-out triangle becomes a proper one.
    let mut t2 = tris.clone();
    t2[10] = tri([0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]);
    assert_eq!(m.refit(&t2), Err(RefitError::Degeneracy { id: 10 }));
    // A triangle in the tree collapses.
    let mut t3 = tris.clone();
    t3[42] = tri([2.0; 3], [2.0; 3], [2.0; 3]);
    assert_eq!(m.refit(&t3), Err(RefitError::Degeneracy { id: 42 }));
    let mut b = Bvh2::build(&tris, BuildQuality::Fast);
    assert_eq!(b.refit(&t3), Err(RefitError::Degeneracy { id: 42 }));
    // Refused refits left the trees as they were.
    m.validate(&tris).unwrap();
    b.validate(&tris).unwrap();
}

/// Simulates the skip-pointer traversal with an arbitrary hit/miss predicate: the nodes
/// visited must be exactly those whose proper ancestors were all hit, each once.
fn skip_walk_visits(b: &Bvh2, hit: impl Fn(usize) -> bool) {
    let nodes = b.nodes();
    let n = nodes.len();
    // Parents from the structure.
    let mut parent = vec![usize::MAX; n];
    for i in 0..n {
        if !nodes[i].is_leaf() {
            parent[i + 1] = i;
            parent[nodes[i + 1].skip as usize] = i;
        }
    }
    let expect: Vec<bool> = (0..n)
        .map(|i| {
            let mut p = parent[i];
            while p != usize::MAX {
                if !hit(p) {
                    return false;
                }
                p = parent[p];
            }
            true
        })
        .collect();
    let mut visits = vec![0u32; n];
    let mut i = 0;
    let mut steps = 0;
    while i < n {
        visits[i] += 1;
        steps += 1;
        assert!(steps <= n, "walk does not terminate");
        i = if hit(i) {
            i + 1
        } else {
            nodes[i].skip as usize
        };
    }
    assert_eq!(i, n, "walk ends at the stop node");
    for k in 0..n {
        assert_eq!(visits[k], u32::from(expect[k]), "node {k}");
    }
}

#[test]
fn bvh2_skip_pointers_walk_every_node_once() {
    let tris = soup(3000, 10.0, 0.5, 16);
    for q in QUALITIES {
        let b = Bvh2::build(&tris, q);
        skip_walk_visits(&b, |_| true);
        skip_walk_visits(&b, |i| i % 3 != 1);
        skip_walk_visits(&b, |i| i % 7 == 0);
        let mut r = Rng(q as u64);
        let flips: Vec<bool> = (0..b.nodes().len())
            .map(|_| !r.next().is_multiple_of(4))
            .collect();
        skip_walk_visits(&b, |i| flips[i]);
    }
}

#[test]
fn node_layout_sizes() {
    use rayd::accel::bvh::{Bvh2Node, Bvh2Tri, MultiTri, WideNode};
    assert_eq!(std::mem::size_of::<WideNode<8>>(), 256);
    assert_eq!(std::mem::size_of::<WideNode<4>>(), 128);
    assert_eq!(std::mem::align_of::<WideNode<8>>(), 64);
    assert_eq!(std::mem::size_of::<MultiTri<8>>(), 320);
    assert_eq!(std::mem::size_of::<Bvh2Node>(), 32);
    assert_eq!(std::mem::size_of::<Bvh2Tri>(), 48);
    for c in [
        Child::Inner(0),
        Child::Inner(12345),
        Child::Leaf { first: 0, count: 1 },
        Child::Leaf {
            first: (1 << 29) - 2,
            count: 4,
        },
        Child::Leaf {
            first: 77,
            count: 2,
        },
        Child::Empty,
    ] {
        assert_eq!(Child::decode(c.encode()), c);
    }
    assert!(Child::Leaf { first: 5, count: 2 }.encode() < 0);
}

fn arb_coord() -> impl Strategy<Value = f32> {
    prop_oneof![
        4 => -10.0f32..10.0,
        1 => Just(0.0f32),
        1 => Just(1.0f32),
        1 => -1e6f32..1e6,
    ]
}

fn arb_triangle() -> impl Strategy<Value = Triangle> {
    prop_oneof![
        // Free triangles.
        4 => prop::array::uniform3(prop::array::uniform3(arb_coord())).prop_map(|v| Triangle { v }),
        // Small triangles near a point.
        4 => (prop::array::uniform3(arb_coord()), prop::array::uniform3(prop::array::uniform3(-0.1f32..0.1)))
            .prop_map(|(c, d)| Triangle { v: d.map(|e| [c[0] + e[0], c[1] + e[1], c[2] + e[2]]) }),
        // Axis-aligned (flat) triangles.
        1 => (arb_coord(), prop::array::uniform2(arb_coord()), prop::array::uniform2(arb_coord()), prop::array::uniform2(arb_coord()))
            .prop_map(|(z, a, b, c)| Triangle { v: [[a[0], a[1], z], [b[0], b[1], z], [c[0], c[1], z]] }),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    #[test]
    fn random_soups_keep_every_invariant(tris in prop::collection::vec(arb_triangle(), 0..400)) {
        for q in QUALITIES {
            let m8 = Mbvh8::build(&tris, q);
            prop_assert!(m8.validate(&tris).is_ok(), "mbvh8 {:?}: {:?}", q, m8.validate(&tris));
            let m4 = Mbvh4::build(&tris, q);
            prop_assert!(m4.validate(&tris).is_ok(), "mbvh4 {:?}: {:?}", q, m4.validate(&tris));
            let b2 = Bvh2::build(&tris, q);
            prop_assert!(b2.validate(&tris).is_ok(), "bvh2 {:?}: {:?}", q, b2.validate(&tris));
        }
    }

    #[test]
    fn random_soups_refit(tris in prop::collection::vec(arb_triangle(), 1..200), t in -1.0f32..1.0) {
        let moved = deform(&tris, t);
        // Only when the deformation keeps the same triangles degenerate.
        let same = tris.iter().zip(&moved).all(|(a, b)| a.is_degenerate() == b.is_degenerate());
        prop_assume!(same);
        for q in QUALITIES {
            let mut m = Mbvh8::build(&tris, q);
            m.refit(&moved).unwrap();
            prop_assert!(m.validate(&moved).is_ok(), "{:?}: {:?}", q, m.validate(&moved));
            let mut b = Bvh2::build(&tris, q);
            b.refit(&moved).unwrap();
            prop_assert!(b.validate(&moved).is_ok(), "{:?}: {:?}", q, b.validate(&moved));
        }
    }
}

// ---------------------------------------------------------------------------------------
// Measurements (ignored by default).

/// Throwaway glTF reader for measurements only (the real loader lives in `formats`):
/// default scene, node transforms, indexed and non-indexed TRIANGLES primitives.
fn load_glb(path: &std::path::Path) -> Vec<Triangle> {
    let bytes = std::fs::read(path).unwrap();
    let g = gltf::Gltf::from_slice(&bytes).unwrap();
    let blob = g.blob.clone().unwrap_or_default();
    let doc = &g.document;
    let scene = doc.default_scene().or_else(|| doc.scenes().next()).unwrap();
    let mut out = Vec::new();
    fn mul(a: &[[f64; 4]; 4], b: &[[f64; 4]; 4]) -> [[f64; 4]; 4] {
        let mut c = [[0.0; 4]; 4];
        for (i, ci) in c.iter_mut().enumerate() {
            for (j, cij) in ci.iter_mut().enumerate() {
                *cij = (0..4).map(|k| a[k][j] * b[i][k]).sum();
            }
        }
        c
    }
    fn visit(n: gltf::Node, parent: [[f64; 4]; 4], blob: &[u8], out: &mut Vec<Triangle>) {
        let local = n.transform().matrix().map(|c| c.map(f64::from));
        let m = mul(&parent, &local);
        if let Some(mesh) = n.mesh() {
            for p in mesh.primitives() {
                if p.mode() != gltf::mesh::Mode::Triangles {
                    continue;
                }
                let r = p.reader(|_| Some(blob));
                let Some(pos) = r.read_positions() else {
                    continue;
                };
                let pos: Vec<[f32; 3]> = pos
                    .map(|v| {
                        let v = v.map(f64::from);
                        std::array::from_fn(|k| {
                            (m[0][k] * v[0] + m[1][k] * v[1] + m[2][k] * v[2] + m[3][k]) as f32
                        })
                    })
                    .collect();
                let idx: Vec<u32> = match r.read_indices() {
                    Some(i) => i.into_u32().collect(),
                    None => (0..pos.len() as u32).collect(),
                };
                for t in idx.chunks_exact(3) {
                    out.push(Triangle {
                        v: [pos[t[0] as usize], pos[t[1] as usize], pos[t[2] as usize]],
                    });
                }
            }
        }
        for c in n.children() {
            visit(c, m, blob, out);
        }
    }
    let id = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ];
    for n in scene.nodes() {
        visit(n, id, &blob, &mut out);
    }
    out
}

/// Best wall time over `reps` runs, and the last result.
fn time_best<T>(reps: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut best = f64::INFINITY;
    let mut last = None;
    for _ in 0..reps {
        let t0 = std::time::Instant::now();
        let r = f();
        best = best.min(t0.elapsed().as_secs_f64());
        last = Some(r);
    }
    (best, last.unwrap())
}

/// Times the builds (and a refit) on generated and real scenes. Environment:
/// `RAYD_SCENES` (folder with the test scenes), `RAYD_MEASURE` (scene name filter),
/// `RAYD_QUALITY` (fast|sah|sbvh), `RAYD_LAYOUTS` (e.g. `mbvh8,bvh2`), `RAYD_THREADS`
/// (e.g. `1,2`), `RAYD_REPS` (best of), `RAYD_DUMP_DIR` (write each scene's raw positions,
/// 9 × f32 per triangle, to time other builders on the same input).
#[test]
#[ignore]
fn measure_build_times() {
    let mut scenes: Vec<(String, Vec<Triangle>)> = Vec::new();
    if let Ok(dir) = std::env::var("RAYD_SCENES") {
        for f in [
            "dragon-100k.from-ply.glb",
            "lucy-100k.from-drc.glb",
            "2CylinderEngine.glb",
            "ReciprocatingSaw.glb",
            "MetalRoughSpheresNoTextures.glb",
        ] {
            let p = std::path::Path::new(&dir).join(f);
            if p.exists() {
                scenes.push((f.split('.').next().unwrap().to_string(), load_glb(&p)));
            }
        }
    }
    let mut big = sphere([0.0; 3], 1.0, 500, 1000);
    big.extend(soup(100_000, 3.0, 0.05, 21));
    scenes.push(("sphere+soup-1.1M".into(), big));
    let only = std::env::var("RAYD_MEASURE").unwrap_or_default();
    let reps: usize = std::env::var("RAYD_REPS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(3);
    for (name, tris) in &scenes {
        if !only.is_empty() && !name.contains(&only) {
            continue;
        }
        // Raw positions (9 × f32 per triangle) for timing other builders on the same input.
        if let Ok(dir) = std::env::var("RAYD_DUMP_DIR") {
            let bytes: Vec<u8> = tris
                .iter()
                .flat_map(|t| t.v.iter().flatten().flat_map(|x| x.to_le_bytes()))
                .collect();
            std::fs::write(
                std::path::Path::new(&dir).join(format!("{name}.raw")),
                bytes,
            )
            .unwrap();
        }
        let threads_list: Vec<usize> = std::env::var("RAYD_THREADS")
            .unwrap_or_else(|_| "1,2".into())
            .split(',')
            .filter_map(|t| t.parse().ok())
            .collect();
        for &threads in &threads_list {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            for q in QUALITIES {
                let want = std::env::var("RAYD_QUALITY").unwrap_or_default();
                if !want.is_empty() && want != q.name() {
                    continue;
                }
                let layouts =
                    std::env::var("RAYD_LAYOUTS").unwrap_or_else(|_| "mbvh8,mbvh4,bvh2".into());
                let mut line = format!(
                    "{name:>22} {:>8} tris  threads={threads} {:>4}:",
                    tris.len(),
                    q.name()
                );
                let mut stats = Vec::new();
                if layouts.contains("mbvh8") {
                    let (t, m) = pool.install(|| time_best(reps, || Mbvh::<8>::build(tris, q)));
                    let (tr, _) = pool.install(|| {
                        let mut m = m.clone();
                        time_best(reps, move || m.refit(tris).unwrap())
                    });
                    line += &format!("  mbvh8 {:7.1} ms  refit8 {:6.1} ms", t * 1e3, tr * 1e3);
                    stats.push(m.stats());
                }
                if layouts.contains("mbvh4") {
                    let (t, m) = pool.install(|| time_best(reps, || Mbvh::<4>::build(tris, q)));
                    line += &format!("  mbvh4 {:7.1} ms", t * 1e3);
                    stats.push(m.stats());
                }
                if layouts.contains("bvh2") {
                    let (t, b) = pool.install(|| time_best(reps, || Bvh2::build(tris, q)));
                    line += &format!("  bvh2 {:7.1} ms", t * 1e3);
                    stats.push(b.stats());
                }
                println!("{line}");
                if threads == threads_list[0] {
                    for s in stats {
                        println!("    {}", serde_json::to_string(&s).unwrap());
                    }
                }
            }
        }
    }
}
