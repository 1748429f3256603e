//! Tests of the ray/triangle tests: scalar vs 8-wide (bit-exact on every backend),
//! watertightness on meshes and fans, numerical extremes and the interval rules.

use super::*;
use crate::simd::{dispatch, Backend, FloatV, Kernel, MaskV};

pub(crate) struct Rng(pub u64);
impl Rng {
    pub fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }
    /// Uniform in [-1, 1).
    pub fn sym(&mut self) -> f32 {
        2.0 * self.unit() - 1.0
    }
    pub fn vec(&mut self) -> [f32; 3] {
        [self.sym(), self.sym(), self.sym()]
    }
}

fn add(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
fn scale(a: [f32; 3], s: f32) -> [f32; 3] {
    a.map(|x| x * s)
}
fn lerp3(tri: &Triangle, u: f32, v: f32) -> [f32; 3] {
    let [a, b, c] = tri.v;
    std::array::from_fn(|k| (1.0 - u - v) * a[k] + u * b[k] + v * c[k])
}

/// Runs the 8-wide test of `T` on one backend: `(hit bits, t per lane)`.
struct Eight<'a, T> {
    ray: &'a PreparedRay,
    pack: &'a Tri8<T>,
}
impl<T: TriTest> Kernel for Eight<'_, T> {
    type Output = (u32, [f32; 8]);
    #[inline(always)]
    fn run<S: Simd>(self, s: S) -> (u32, [f32; 8]) {
        let r8 = PreparedRay8::new(s, self.ray);
        let (m, t) = T::intersect8(s, &r8, self.pack, s.splat_f8(self.ray.tmax));
        (m.bitmask(), t.to_array())
    }
}

/// Runs the 8-wide test with barycentrics: `(hit bits, t, u, v per lane)`.
struct EightUv<'a, T> {
    ray: &'a PreparedRay,
    pack: &'a Tri8<T>,
}
impl<T: TriTest> Kernel for EightUv<'_, T> {
    type Output = (u32, [f32; 8], [f32; 8], [f32; 8]);
    #[inline(always)]
    fn run<S: Simd>(self, s: S) -> Self::Output {
        let r8 = PreparedRay8::new(s, self.ray);
        let (m, t, u, v) = T::intersect8_uv(s, &r8, self.pack, s.splat_f8(self.ray.tmax));
        (m.bitmask(), t.to_array(), u.to_array(), v.to_array())
    }
}

/// A random scene-like triangle: size 10^[-4, 3], centre up to `reach` from the origin.
fn random_triangle(rng: &mut Rng, reach: f32) -> Triangle {
    let size = 10f32.powf(rng.unit() * 7.0 - 4.0);
    let c = scale(rng.vec(), reach);
    Triangle {
        v: [
            add(c, scale(rng.vec(), size)),
            add(c, scale(rng.vec(), size)),
            add(c, scale(rng.vec(), size)),
        ],
    }
}

/// A ray aimed at (or near) a point of `tri`: vertices, edges and interiors all get hit
/// often; some directions are axis-parallel with ±0 components.
fn ray_at(rng: &mut Rng, tri: &Triangle, reach: f32) -> Ray {
    let (u, v) = match rng.next() % 5 {
        0 => [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)][(rng.next() % 3) as usize],
        1 => {
            let a = rng.unit();
            [(a, 0.0), (0.0, a), (a, 1.0 - a)][(rng.next() % 3) as usize]
        }
        2 => (rng.sym() * 1.5, rng.sym() * 1.5),
        _ => {
            let (a, b) = (rng.unit(), rng.unit());
            if a + b > 1.0 {
                (1.0 - a, 1.0 - b)
            } else {
                (a, b)
            }
        }
    };
    let target = lerp3(tri, u, v);
    let (org, dir) = if rng.next().is_multiple_of(4) {
        let axis = (rng.next() % 3) as usize;
        let sign = if rng.next().is_multiple_of(2) {
            1.0
        } else {
            -1.0
        };
        let zero = if rng.next().is_multiple_of(2) {
            0.0
        } else {
            -0.0
        };
        let mut dir = [zero; 3];
        dir[axis] = sign;
        let mut org = target;
        org[axis] -= sign * reach.max(1.0) * (0.5 + rng.unit());
        (org, dir)
    } else {
        let org = add(target, scale(rng.vec(), reach.max(1.0)));
        let dir = std::array::from_fn(|k| target[k] - org[k]);
        (org, scale(dir, 10f32.powf(rng.sym() * 3.0)))
    };
    Ray {
        org,
        tmin: if rng.next().is_multiple_of(3) {
            rng.unit()
        } else {
            0.0
        },
        dir,
        tmax: match rng.next() % 3 {
            0 => f32::INFINITY,
            1 => rng.unit() * 3.0,
            _ => 1e30,
        },
    }
}

/// `scales`: per round one `(k, m)`, by which the scene's positions and the rays'
/// directions are multiplied (`(1, 1)`: as generated); `k` far from 1 drives the tests'
/// products out of f32's range, into their cold paths.
fn check_exact<T: TriTest>(rng: &mut Rng, scales: &[(f32, f32)]) {
    let backends = Backend::supported();
    for round in 0..3000 {
        let reach = [1.0, 1e3, 1e6][round % 3];
        let (k, m) = scales[round / 3 % scales.len()];
        let n = 1 + (rng.next() % 8) as usize;
        let tris: Vec<(u32, Triangle)> = (0..n)
            .map(|i| {
                let t = random_triangle(rng, reach);
                let v = t.v.map(|p| p.map(|x| x * k));
                (i as u32 * 3, Triangle { v })
            })
            .collect();
        let pack = Tri8::<T>::pack(&tris);
        for _ in 0..8 {
            let target = tris[(rng.next() % n as u64) as usize].1;
            let mut ray = ray_at(rng, &target, reach * k);
            if m != 1.0 {
                ray.dir = ray.dir.map(|x| x * m);
                ray.tmin /= m;
                ray.tmax /= m;
            }
            let ray = PreparedRay::new(&ray);
            if ray.is_empty() {
                continue;
            }
            let scalar: Vec<Option<TriHit>> = (0..8)
                .map(|l| T::intersect1(&ray, &pack, l, ray.tmax))
                .collect();
            for &b in &backends {
                let (bits, t) = dispatch(
                    b,
                    Eight {
                        ray: &ray,
                        pack: &pack,
                    },
                );
                for l in 0..8 {
                    match scalar[l] {
                        Some(h) => {
                            assert!(bits >> l & 1 == 1, "{b} lane {l} missed: {ray:?} {pack:?}");
                            assert_eq!(t[l].to_bits(), h.t.to_bits(), "{b} lane {l}: t");
                        }
                        None => assert!(bits >> l & 1 == 0, "{b} lane {l} extra: {ray:?}"),
                    }
                }
                let (bits_uv, t_uv, u, v) = dispatch(
                    b,
                    EightUv {
                        ray: &ray,
                        pack: &pack,
                    },
                );
                assert_eq!(bits_uv, bits, "{b}: intersect8_uv's mask");
                for l in 0..8 {
                    if let Some(h) = scalar[l] {
                        let got = [t_uv[l], u[l], v[l]].map(f32::to_bits);
                        assert_eq!(
                            got,
                            [h.t, h.u, h.v].map(f32::to_bits),
                            "{b} lane {l}: t, u, v"
                        );
                    }
                }
            }
            // The per-triangle entry point is the same test.
            for (l, (_, tri)) in tris.iter().enumerate() {
                if !tri.is_degenerate() {
                    assert_eq!(T::intersect_triangle(&ray, tri), scalar[l]);
                }
            }
        }
    }
}

#[test]
fn scalar_and_8wide_agree_exactly_on_every_backend() {
    check_exact::<Watertight>(&mut Rng(1), &[(1.0, 1.0)]);
    check_exact::<MollerTrumbore>(&mut Rng(2), &[(1.0, 1.0)]);
}

/// The same where the tests' products leave f32's range (scenes 1e-20 and 1e-30 times as
/// large, with directions scaled too, and 1e15 times): the lanes decided again
/// (`watertight`'s `rescaled_lane`, `fast`'s `redecided_lane`) agree on every backend too.
#[test]
fn scalar_and_8wide_agree_exactly_out_of_range() {
    let scales = [(1e-20, 1.0), (1e-30, 1e10), (1e15, 1e-10), (1e12, 1e12)];
    check_exact::<Watertight>(&mut Rng(3), &scales);
    check_exact::<MollerTrumbore>(&mut Rng(4), &scales);
}

/// A height-field grid of `n × n` quads, two triangles each, jittered in z, transformed by
/// `scale` and `offset`; plus the interior vertices and interior edge points to aim at.
fn grid(rng: &mut Rng, n: usize, scale_: f32, offset: [f32; 3]) -> (Vec<Triangle>, Vec<[f32; 3]>) {
    let p = |rng: &mut Rng, i: usize, j: usize| -> [f32; 3] {
        let _ = rng;
        [i as f32, j as f32, 0.0]
    };
    let mut h = vec![0.0f32; (n + 1) * (n + 1)];
    for z in h.iter_mut() {
        *z = rng.sym() * 0.3;
    }
    let vert = |i: usize, j: usize, rng: &mut Rng| {
        let mut v = p(rng, i, j);
        v[2] = h[i * (n + 1) + j];
        add(scale(v, scale_), offset)
    };
    let mut tris = Vec::new();
    let mut targets = Vec::new();
    for i in 0..n {
        for j in 0..n {
            let a = vert(i, j, rng);
            let b = vert(i + 1, j, rng);
            let c = vert(i + 1, j + 1, rng);
            let d = vert(i, j + 1, rng);
            // Alternate the diagonal so vertices have different valences.
            if (i + j) % 2 == 0 {
                tris.push(Triangle { v: [a, b, c] });
                tris.push(Triangle { v: [a, c, d] });
            } else {
                tris.push(Triangle { v: [a, b, d] });
                tris.push(Triangle { v: [b, c, d] });
            }
            if i > 0 && j > 0 {
                targets.push(a);
            }
        }
    }
    // Points on interior edges (rounded to f32: within an ulp of the edge).
    let edges: Vec<([f32; 3], [f32; 3])> = tris
        .iter()
        .flat_map(|t| [(t.v[0], t.v[1]), (t.v[1], t.v[2]), (t.v[2], t.v[0])])
        .collect();
    for (a, b) in edges {
        let interior = |p: [f32; 3]| {
            let q = |k: usize| (p[k] - offset[k]) / scale_;
            q(0) > 0.5 && q(0) < n as f32 - 0.5 && q(1) > 0.5 && q(1) < n as f32 - 0.5
        };
        for s in [0.5f32, 0.25, 1.0 / 3.0, 0.9] {
            let m = std::array::from_fn(|k| a[k] + s * (b[k] - a[k]));
            if interior(a) || interior(b) || interior(m) {
                let q = |k: usize| (m[k] - offset[k]) / scale_;
                if q(0) > 0.0 && q(0) < n as f32 && q(1) > 0.0 && q(1) < n as f32 {
                    targets.push(m);
                }
            }
        }
    }
    (tris, targets)
}

/// A fan of `k` triangles around `centre` in the plane z = `centre.z`, as an axis-aligned
/// or tilted polygon.
fn fan(k: usize, centre: [f32; 3], r: f32, tilt: f32) -> Vec<Triangle> {
    let rim = |i: usize| {
        let a = i as f32 * std::f32::consts::TAU / k as f32;
        let (x, y) = (r * a.cos(), r * a.sin());
        [centre[0] + x, centre[1] + y, centre[2] + tilt * x]
    };
    (0..k)
        .map(|i| Triangle {
            v: [centre, rim(i), rim(i + 1)],
        })
        .collect()
}

fn hits_any<T: TriTest>(ray: &Ray, tris: &[Triangle]) -> bool {
    let r = PreparedRay::new(ray);
    tris.iter().any(|t| T::intersect_triangle(&r, t).is_some())
}

#[test]
fn watertight_meshes_have_no_cracks() {
    let mut rng = Rng(3);
    let mut mt_misses = 0;
    let mut total = 0;
    for (scale_, offset) in [
        (1.0, [0.0; 3]),
        (0.37, [1e6, -2e6, 5e5]),
        (1e-3, [3.0, 4.0, -5.0]),
        (250.0, [-1e5, 1e5, 0.0]),
    ] {
        let (tris, targets) = grid(&mut rng, 6, scale_, offset);
        for &p in &targets {
            for _ in 0..20 {
                // From above, downwards, at assorted slopes; sometimes exactly vertical with
                // ±0 components.
                let dir = match rng.next() % 4 {
                    0 => [0.0, -0.0, -1.0],
                    1 => [-0.0, 0.0, -1.0],
                    _ => [rng.sym() * 0.8, rng.sym() * 0.8, -1.0],
                };
                let dist = scale_ * (1.0 + 10.0 * rng.unit());
                let org: [f32; 3] = std::array::from_fn(|k| p[k] - dist * dir[k]);
                let ray = Ray {
                    org,
                    tmin: 0.0,
                    dir: std::array::from_fn(|k| p[k] - org[k]),
                    tmax: f32::INFINITY,
                };
                total += 1;
                assert!(
                    hits_any::<Watertight>(&ray, &tris),
                    "watertight ray slipped through at {p:?}: {ray:?}"
                );
                mt_misses += usize::from(!hits_any::<MollerTrumbore>(&ray, &tris));
            }
        }
    }
    eprintln!("Möller–Trumbore missed {mt_misses} of {total} edge/vertex rays");
}

#[test]
fn watertight_fans_hit_at_the_shared_vertex() {
    let mut rng = Rng(4);
    for k in [3, 5, 7, 12, 31] {
        for (centre, r, tilt) in [
            ([0.0, 0.0, 0.0], 1.0, 0.0),
            ([1e6, 1e6, 1e6], 3.0, 0.5),
            ([0.1, -0.2, 0.3], 1e-3, -2.0),
            ([-7e4, 2e3, 1.0], 1e2, 0.1),
        ] {
            let tris = fan(k, centre, r, tilt);
            for _ in 0..200 {
                let dir = match rng.next() % 3 {
                    0 => [0.0, 0.0, -1.0],
                    1 => [-0.0, -0.0, 1.0],
                    _ => [
                        rng.sym(),
                        rng.sym(),
                        if rng.unit() < 0.5 { -1.0 } else { 1.0 },
                    ],
                };
                let org: [f32; 3] = std::array::from_fn(|q| centre[q] - 5.0 * r * dir[q]);
                let ray = Ray {
                    org,
                    tmin: 0.0,
                    dir: std::array::from_fn(|q| centre[q] - org[q]),
                    tmax: f32::INFINITY,
                };
                assert!(
                    hits_any::<Watertight>(&ray, &tris),
                    "fan of {k} around {centre:?}: {ray:?}"
                );
            }
        }
    }
}

fn tri(v: [[f32; 3]; 3]) -> Triangle {
    Triangle { v }
}

fn ray(org: [f32; 3], dir: [f32; 3], tmin: f32, tmax: f32) -> Ray {
    Ray {
        org,
        tmin,
        dir,
        tmax,
    }
}

fn both(r: &Ray, t: &Triangle) -> [Option<TriHit>; 2] {
    [
        intersect(Precision::Fast, r, t),
        intersect(Precision::Watertight, r, t),
    ]
}

#[test]
fn closed_interval_and_empty_intervals() {
    let t = tri([[-1.0, -1.0, 2.0], [3.0, -1.0, 2.0], [-1.0, 3.0, 2.0]]);
    let d = [0.0, 0.0, 1.0];
    for h in both(&ray([0.0; 3], d, 0.0, f32::INFINITY), &t) {
        let h = h.unwrap();
        assert_eq!(h.t, 2.0);
        assert_eq!((h.u, h.v), (0.25, 0.25));
    }
    for (tmin, tmax, hit) in [
        (2.0, 2.0, true),
        (0.0, 2.0, true),
        (2.0, 5.0, true),
        (0.0, 1.9999999, false),
        (2.0000002, 9.0, false),
        (3.0, 1.0, false),
        (f32::INFINITY, f32::INFINITY, false),
        (f32::INFINITY, 1.0, false),
    ] {
        for h in both(&ray([0.0; 3], d, tmin, tmax), &t) {
            assert_eq!(h.is_some(), hit, "[{tmin}, {tmax}]");
        }
    }
    // Origin on the triangle: t = 0 is inside [0, tmax].
    for h in both(&ray([0.0, 0.0, 2.0], [0.3, 0.1, 1.0], 0.0, 1.0), &t) {
        assert_eq!(h.unwrap().t, 0.0);
    }
    // No culling: from behind too.
    for h in both(&ray([0.0, 0.0, 4.0], [0.0, 0.0, -1.0], 0.0, 9.0), &t) {
        assert_eq!(h.unwrap().t, 2.0);
    }
}

#[test]
fn degenerate_triangles_never_hit() {
    let collinear = tri([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [2.0, 2.0, 0.0]]);
    let point = tri([[1.0, 2.0, 3.0]; 3]);
    let doubled = tri([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]);
    let good = tri([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]);
    // Accelerators drop them at build time (ids of the rest are kept).
    let packs = pack_all::<Watertight>(&[collinear, good, point, doubled, good]);
    assert_eq!(packs.len(), 1);
    assert_eq!(
        packs[0].ids,
        [1, 4, PAD_ID, PAD_ID, PAD_ID, PAD_ID, PAD_ID, PAD_ID]
    );
    let mut rng = Rng(5);
    for d in [collinear, point, doubled] {
        assert!(d.is_degenerate());
        for _ in 0..2000 {
            let r = ray_at(&mut rng, &d, 1.0);
            assert_eq!(both(&r, &d), [None, None]);
        }
    }
    // The raw tests (no is_degenerate filter) never report a zero-determinant hit: a
    // triangle whose vertices coincide after the shear has U = V = W = 0 exactly. (A
    // collinear triangle may round to a sliver with det != 0 in the raw test; that is why
    // the accelerators filter with `Triangle::is_degenerate`.)
    for d in [point, doubled] {
        let p8w = Tri8::<Watertight>::pack(&[(0, d), (1, d)]);
        let p8m = Tri8::<MollerTrumbore>::pack(&[(0, d), (1, d)]);
        for _ in 0..2000 {
            let pr = PreparedRay::new(&ray_at(&mut rng, &d, 1.0));
            for l in 0..8 {
                assert_eq!(MollerTrumbore::intersect1(&pr, &p8m, l, pr.tmax), None);
                if d == point {
                    assert_eq!(Watertight::intersect1(&pr, &p8w, l, pr.tmax), None);
                }
            }
            for b in Backend::supported() {
                assert_eq!(
                    dispatch(
                        b,
                        Eight {
                            ray: &pr,
                            pack: &p8m
                        }
                    )
                    .0,
                    0
                );
                if d == point {
                    assert_eq!(
                        dispatch(
                            b,
                            Eight {
                                ray: &pr,
                                pack: &p8w
                            }
                        )
                        .0,
                        0
                    );
                }
            }
        }
    }
}

/// Relative agreement of a test's hit with the f64 oracle on clear-cut cases.
fn agrees(r: &Ray, t: &Triangle, tol: f64) {
    let o = oracle_f64(r, t).expect("oracle hit");
    for h in both(r, t) {
        let h = h.unwrap_or_else(|| panic!("missed {r:?} {t:?}"));
        let rel = (h.t as f64 - o.t).abs() / o.t.abs().max(1e-30);
        assert!(rel < tol, "t {} vs {} ({rel:e})", h.t, o.t);
        assert!((h.u as f64 - o.u).abs() < 1e-3 && (h.v as f64 - o.v).abs() < 1e-3);
    }
}

#[test]
fn numerical_extremes() {
    // Far from the origin.
    let far = tri([
        [1e6, 1e6, 1e6],
        [1e6 + 4.0, 1e6, 1e6],
        [1e6, 1e6 + 4.0, 1e6 + 1.0],
    ]);
    agrees(
        &ray(
            [1e6 + 1.0, 1e6 + 1.0, 0.0],
            [0.0, 0.0, 1.0],
            0.0,
            f32::INFINITY,
        ),
        &far,
        1e-6,
    );
    agrees(
        &ray(
            [1e6 + 1.0, 1e6 + 1.0, 1e6 + 50.0],
            [0.01, -0.02, -1.0],
            0.0,
            1e9,
        ),
        &far,
        1e-5,
    );
    // A tiny triangle next to a huge one.
    let tiny = tri([[0.0, 0.0, 10.0], [1e-4, 0.0, 10.0], [0.0, 1e-4, 10.0]]);
    let huge = tri([[-1e5, -1e5, 11.0], [1e5, -1e5, 11.0], [0.0, 1e5, 11.0]]);
    let r = ray([2e-5, 3e-5, 0.0], [0.0, 0.0, 1.0], 0.0, f32::INFINITY);
    agrees(&r, &tiny, 1e-6);
    agrees(&r, &huge, 1e-6);
    // Axis-parallel rays with ±0 components on axis-aligned triangles, also exactly
    // through a vertex and along an edge's line.
    let flat = tri([[0.0, 0.0, 5.0], [1.0, 0.0, 5.0], [0.0, 1.0, 5.0]]);
    for org in [
        [0.25, 0.25, 0.0],
        [0.0, 0.0, 0.0],
        [0.5, 0.0, 0.0],
        [0.5, 0.5, 0.0],
    ] {
        for dir in [
            [0.0, 0.0, 1.0],
            [-0.0, 0.0, 1.0],
            [0.0, -0.0, 2.0],
            [-0.0, -0.0, 0.5],
        ] {
            let r = ray(org, dir, 0.0, f32::INFINITY);
            let h = intersect(Precision::Watertight, &r, &flat).expect("watertight hit");
            assert_eq!(h.t * dir[2], 5.0);
            assert!(oracle_f64(&r, &flat).is_some());
        }
    }
    // Just outside the edge: both miss (and the oracle agrees).
    let r = ray(
        [0.5000001, 0.5000001, 0.0],
        [0.0, 0.0, 1.0],
        0.0,
        f32::INFINITY,
    );
    assert_eq!(both(&r, &flat), [None, None]);
    assert!(oracle_f64(&r, &flat).is_none());
    // Grazing: nearly parallel to the plane; no panic, and any hit is within the interval.
    let mut rng = Rng(6);
    for _ in 0..10_000 {
        let eps = 10f32.powf(-rng.unit() * 8.0);
        let r = ray(
            [
                rng.sym() * 0.1 - 2.0,
                rng.sym() * 0.1 + 0.2,
                5.0 - eps * rng.sym(),
            ],
            [1.0, rng.sym() * 0.1, eps * rng.sym()],
            0.0,
            f32::INFINITY,
        );
        for h in both(&r, &flat).into_iter().flatten() {
            assert!(h.t >= 0.0 && h.t.is_finite());
        }
    }
    // Edge-on ray in the plane of the triangle: never a hit (det == 0).
    let r = ray([-1.0, 0.25, 5.0], [1.0, 0.0, 0.0], 0.0, f32::INFINITY);
    assert_eq!(intersect(Precision::Watertight, &r, &flat), None);
}

#[test]
fn oracle_closest_breaks_ties_by_id() {
    let a = tri([[-1.0, -1.0, 2.0], [3.0, -1.0, 2.0], [-1.0, 3.0, 2.0]]);
    let r = ray([0.0; 3], [0.0, 0.0, 1.0], 0.0, f32::INFINITY);
    let b = tri([[-1.0, -1.0, 1.0], [3.0, -1.0, 1.0], [-1.0, 3.0, 1.0]]);
    assert_eq!(oracle_closest_f64(&r, &[a, b, b]).unwrap().0, 1);
    assert_eq!(oracle_closest_f64(&r, &[a, a]).unwrap().0, 0);
    assert!(oracle_closest_f64(&r, &[]).is_none());
    let line = oracle_line_f64(
        &r,
        &tri([[5.0, 5.0, 4.0], [6.0, 5.0, 4.0], [5.0, 6.0, 4.0]]),
    )
    .unwrap();
    assert_eq!(line.t, 4.0);
    assert!(line.u < 0.0 || line.v < 0.0 || line.u + line.v > 1.0);
}

#[test]
fn best_lane_orders_by_t_then_id() {
    let t = tri([[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]);
    let pack = Tri8::<Watertight>::pack(&[(9, t), (4, t), (7, t), (2, t)]);
    let ts = [3.0, 1.0, 1.0, 2.0, 0.0, 0.0, 0.0, 0.0];
    assert_eq!(pack.best_lane(0b1111, &ts), Some(1));
    assert_eq!(pack.best_lane(0b1101, &ts), Some(2));
    assert_eq!(pack.best_lane(0b1001, &ts), Some(3));
    assert_eq!(pack.best_lane(0, &ts), None);
    let eq = [5.0; 8];
    assert_eq!(pack.best_lane(0b1111, &eq), Some(3));
    assert_eq!(pack.best_lane(0b0101, &eq), Some(2));
}

/// Every watertight hit over the random cases of `check_exact` (sizes 1e-4..1e3, up to
/// 1e6 from the origin, aimed at vertices, edges and interiors) lies within the written
/// bound of the exact t; so does every fast hit; and the t each test decides and orders
/// by lies within its own written bound (`order_t_bound`).
#[test]
fn t_is_within_the_written_bound_on_random_cases() {
    let mut rng = Rng(7);
    let mut worst = [0.0f64; 2];
    let mut worst_order = 0.0f64;
    for round in 0..20_000 {
        let reach = [1.0, 1e3, 1e6][round % 3];
        let tri = random_triangle(&mut rng, reach);
        if tri.is_degenerate() {
            continue;
        }
        let r = ray_at(&mut rng, &tri, reach);
        let Some(line) = oracle_line_f64(&r, &tri) else {
            continue;
        };
        for (i, p) in [Precision::Fast, Precision::Watertight]
            .into_iter()
            .enumerate()
        {
            if let Some(h) = intersect_unrefined(p, &r, &tri) {
                let err = (f64::from(h.t) - line.t).abs();
                let tol =
                    oracle::order_t_bound(p, &r, &tri, line.t) + oracle::oracle_t_error(&r, &tri);
                assert!(
                    err <= tol,
                    "{p:?}: the test's t {} vs {} ({err:e} > {tol:e}): {r:?} {tri:?}",
                    h.t,
                    line.t
                );
                if p == Precision::Watertight {
                    worst_order = worst_order.max(err / tol);
                }
            }
            if let Some(h) = intersect(p, &r, &tri) {
                let err = (f64::from(h.t) - line.t).abs();
                let tol = oracle::t_bound(p, &r, &tri, line.t) + oracle::oracle_t_error(&r, &tri);
                assert!(
                    err <= tol,
                    "{p:?}: t {} vs {} ({err:e} > {tol:e}): {r:?} {tri:?}",
                    h.t,
                    line.t
                );
                worst[i] = worst[i].max(err / tol);
                let tol_uv = oracle::uv_bound(p, &r, &tri);
                let du = (f64::from(h.u) - line.u)
                    .abs()
                    .max((f64::from(h.v) - line.v).abs());
                assert!(
                    du <= tol_uv,
                    "{p:?}: u, v off by {du:e} > {tol_uv:e}: {r:?} {tri:?}"
                );
            }
        }
    }
    eprintln!(
        "worst error / bound: fast {:.3e}, watertight {:.3e}, watertight decision t {:.3e}",
        worst[0], worst[1], worst_order
    );
}

/// The reported watertight t is clamped into the ray's interval: the hit was decided on
/// the test's t, which lies in `[tmin, tmax]`, and the refinement must not move it out.
/// A 1000-unit triangle hit near the origin, where the test's and the refined t differ by
/// many ulps, traced with the interval shrunk to the test's t on either side.
#[test]
fn refined_t_is_clamped_into_the_interval() {
    let tri = tri([
        [-500.0, -350.0, 150.0],
        [550.0, -200.0, -400.0],
        [-100.0, 500.0, 60.0],
    ]);
    let mut rng = Rng(9);
    let (mut below, mut above) = (0, 0);
    for _ in 0..2000 {
        // Just above the plane (z = -69.91 at the origin), looking down at it: t ≈ 0.01–0.2.
        let o = scale(rng.vec(), 0.1);
        let r = ray(
            [o[0], o[1], o[2] - 69.8],
            [rng.sym() * 0.3, rng.sym() * 0.3, -1.0],
            0.0,
            f32::INFINITY,
        );
        let Some(raw) = intersect_unrefined(Precision::Watertight, &r, &tri) else {
            continue;
        };
        let fine = intersect(Precision::Watertight, &r, &tri).expect("same decision");
        assert_eq!((fine.u, fine.v), (raw.u, raw.v));
        // [t0, t0], and [0, t0] or [t0, inf) on the side the refined t lies.
        let t0 = raw.t;
        let point = intersect(Precision::Watertight, &ray(r.org, r.dir, t0, t0), &tri);
        assert_eq!(point.map(|h| h.t), Some(t0), "{r:?}");
        let (lo, hi) = if fine.t > t0 {
            above += 1;
            (0.0, t0)
        } else {
            below += 1;
            (t0, f32::INFINITY)
        };
        let h = intersect(Precision::Watertight, &ray(r.org, r.dir, lo, hi), &tri).unwrap();
        assert_eq!(h.t, t0, "{r:?}");
    }
    assert!(below > 100 && above > 100, "{below} {above}");
}

/// Where the line of `ray` enters the bounding box of `p`, in f64 (axes with a zero
/// direction component ignored).
fn box_entry(ray: &Ray, p: &[[f32; 3]; 3]) -> f64 {
    (0..3)
        .filter(|&k| ray.dir[k] != 0.0)
        .map(|k| {
            let lo = p
                .iter()
                .map(|v| f64::from(v[k]))
                .fold(f64::INFINITY, f64::min);
            let hi = p
                .iter()
                .map(|v| f64::from(v[k]))
                .fold(f64::NEG_INFINITY, f64::max);
            let near = if ray.dir[k] > 0.0 { lo } else { hi };
            (near - f64::from(ray.org[k])) / f64::from(ray.dir[k])
        })
        .fold(f64::NEG_INFINITY, f64::max)
}

/// The sliver of `refit`'s stop-15 case: the paper's t lies before the triangle's box, and
/// the decision t is moved up to the box (within the few roundings of `lift_t`'s f32 entry).
#[test]
fn a_slivers_decision_t_is_not_before_its_box() {
    let p = [
        [3202.948, 1314.8987, -1469.6019],
        [4019.5227, 1782.2806, -1467.3832],
        [4836.0977, 2249.6626, -1465.1643],
    ];
    let ray = Ray {
        org: [3739.5298, -1227.3225, -2522.1582],
        tmin: 0.0,
        dir: [-430.35303, 2603.0232, 1052.845],
        tmax: f32::INFINITY,
    };
    let r = PreparedRay::new(&ray);
    let h = Watertight::intersect_lane(&r, &p, ray.tmax).expect("a hit");
    let entry = box_entry(&ray, &p);
    assert!(near_entry(h.t, entry), "t {} entry {entry}", h.t);
    let paper = Watertight::paper_lane(&r, &p, ray.tmax).expect("a hit").t;
    assert!(
        f64::from(paper) < entry * (1.0 - 1e-6),
        "the paper's t {paper} is short"
    );
}

/// Whether `t` is within `2^-21` (relative) of `entry`: `lift_t`'s f32 entry is a few
/// roundings off the exact one, and along `kz`, where it does not lift, the paper's t may
/// lie short of the box by its sum's rounding.
fn near_entry(t: f32, entry: f64) -> bool {
    (f64::from(t) - entry).abs() <= entry.abs() / f64::from(1u32 << 21)
}

/// On random slivers and fat triangles the decision t is never before the triangle's box
/// by more than its rounding, and lifting it again changes nothing.
#[test]
fn decision_t_never_lies_before_the_triangles_box() {
    let mut rng = Rng(0x0051_17e2);
    for i in 0..20_000 {
        let a = scale(rng.vec(), 1e3);
        let d = rng.vec();
        let fat = i % 2 == 0;
        let b = add(a, scale(d, 800.0));
        let c = if fat {
            add(a, scale(rng.vec(), 800.0))
        } else {
            add(a, add(scale(d, 1600.0), scale(rng.vec(), 1e-3)))
        };
        let tri = Triangle { v: [a, b, c] };
        if tri.is_degenerate() {
            continue;
        }
        let target = lerp3(&tri, rng.unit() * 0.5, rng.unit() * 0.5);
        let org = add(target, scale(rng.vec(), 3e3));
        let dir = std::array::from_fn(|k| target[k] - org[k]);
        let ray = Ray {
            org,
            tmin: 0.0,
            dir,
            tmax: f32::INFINITY,
        };
        let r = PreparedRay::new(&ray);
        let p = Watertight::lane_data(&tri);
        let Some(h) = Watertight::intersect_lane(&r, &p, ray.tmax) else {
            continue;
        };
        let entry = box_entry(&ray, &p);
        assert!(
            f64::from(h.t) >= entry || near_entry(h.t, entry),
            "case {i}: t {} before the box at {entry}",
            h.t
        );
        let lifted = lift_t(&r, &p, h.t);
        assert_eq!(lifted.to_bits(), h.t.to_bits(), "lifting is idempotent");
    }
}
