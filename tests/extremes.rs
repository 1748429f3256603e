//! Every core at the numerical extremes: the guarantees of `proto/semantics.md`
//! ("Guarantees at the numerical extremes"), one test per guarantee, each run on every
//! accelerator (`AccelKind::ALL` minus `auto`, which is one of them) in both precisions.
//!
//! Two references: `brute` (every other core must give its closest hits bit for bit) and
//! the float64 oracle (`rayd::accel::triangle::oracle`), whose t on the hit triangle's
//! plane must lie within the written bound ([`t_bound`], plus the oracle's own rounding,
//! [`oracle_t_error`]).
//!
//! `embree` (only with `--features embree`) keeps Embree's own rules, so it is checked
//! loosely: it never crashes, and where the hit is clear-cut (not within its test's
//! rounding of an edge) it hits the same triangle at a t within 1e-4 relative.

mod common;

use common::{bits, Rng};
use rayd::accel::triangle::oracle::{
    oracle_t_error, order_t_bound, t_bound, unresolved_hit_plausible, uv_bound,
};
use rayd::accel::triangle::{intersect_unrefined, oracle_closest_f64, oracle_f64, oracle_line_f64};
use rayd::accel::{build, AccelKind, BuildOptions, BuildQuality, Precision, Query};
use rayd::geometry::{Hit, Ray, Triangle};

const PRECISIONS: [Precision; 2] = [Precision::Fast, Precision::Watertight];

/// The cores this build has, `auto` left out (it runs one of the others), `brute` first.
fn kinds() -> Vec<AccelKind> {
    AccelKind::ALL
        .into_iter()
        .filter(|k| *k != AccelKind::Auto && k.available())
        .collect()
}

/// [`kinds`] without `embree`: the cores that keep our tests' rules bit for bit.
fn exact_cores() -> Vec<AccelKind> {
    kinds()
        .into_iter()
        .filter(|k| *k != AccelKind::Embree)
        .collect()
}

/// Closest (or any) hits of `rays` on `tris` by `kind`, built with `quality`.
fn trace_q(
    kind: AccelKind,
    quality: BuildQuality,
    precision: Precision,
    tris: &[Triangle],
    rays: &[Ray],
    query: Query,
) -> Vec<Hit> {
    let options = BuildOptions {
        quality,
        precision,
        threads: 1,
        ..Default::default()
    };
    let core = build(kind, tris, &options).unwrap_or_else(|e| panic!("{}: {e}", kind.name()));
    let mut hits = vec![Hit::MISS; rays.len()];
    core.trace(rays, query, &mut hits);
    hits
}

fn trace(kind: AccelKind, precision: Precision, tris: &[Triangle], rays: &[Ray]) -> Vec<Hit> {
    trace_q(
        kind,
        BuildQuality::Sah,
        precision,
        tris,
        rays,
        Query::Closest,
    )
}

fn ray(org: [f32; 3], dir: [f32; 3], tmin: f32, tmax: f32) -> Ray {
    Ray {
        org,
        tmin,
        dir,
        tmax,
    }
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn addv(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// Checks one hit of `kind` against the written bounds: a real hit on its triangle's
/// plane with t (and u, v) within [`t_bound`] ([`uv_bound`]) of the f64 values there, and
/// inside the ray's interval; a t clamped to an end of the interval within the larger of
/// [`t_bound`] and [`order_t_bound`]. `embree`, the peer, keeps its own rules: its t is
/// held to 1e-4 of the larger of t and the triangle's reach from the origin.
fn check_hit(kind: AccelKind, precision: Precision, r: &Ray, tris: &[Triangle], h: &Hit) {
    if !h.is_hit() {
        return;
    }
    let what = format!("{} {}: {r:?} -> {h:?}", kind.name(), precision.name());
    assert!(
        h.t >= r.tmin && h.t <= r.tmax,
        "t outside the interval: {what}"
    );
    let tri = &tris[h.prim as usize];
    let Some(line) = oracle_line_f64(r, tri) else {
        // Parallel in f64: the triangle is smaller than f64's resolution at its distance
        // from the origin (1e-35 across, seen from 0.1 away), its vertices one point
        // relative to the origin. Möller–Trumbore, which rounds the offset `org - v0` to
        // f32 and keeps the edges apart, hits such a triangle at a vertex where the ray
        // passes within that rounding of it (`unresolved_hit_plausible`); the watertight
        // test, which rounds every vertex's offset, sees a point and misses.
        assert!(
            precision == Precision::Fast && unresolved_hit_plausible(r, tri, h.t),
            "hit a parallel plane: {what}"
        );
        return;
    };
    let t = f64::from(h.t);
    if kind == AccelKind::Embree {
        // Embree's f32 t is accurate relative to how far the triangle reaches from the
        // origin, not to the hit's distance: on a 1000-unit triangle hit at t ≈ 0.05 it was
        // 6.8e-4 off relative to t. Held to 1e-4 of the larger of the two.
        let norm = |a: [f32; 3]| {
            a.iter()
                .map(|&c| f64::from(c) * f64::from(c))
                .sum::<f64>()
                .sqrt()
        };
        let reach = tri
            .v
            .iter()
            .map(|&p| norm(sub(p, r.org)))
            .fold(0.0, f64::max)
            / norm(r.dir);
        assert!(
            (t - line.t).abs() <= 1e-4 * line.t.abs().max(reach) + 1e-30,
            "{what}: exact {} (relative error {:e})",
            line.t,
            (t - line.t).abs() / line.t.abs()
        );
        return;
    }
    let mut tol = t_bound(precision, r, tri, line.t);
    if h.t == r.tmin || h.t == r.tmax {
        tol = tol.max(order_t_bound(precision, r, tri, line.t));
    }
    let tol = tol + oracle_t_error(r, tri);
    assert!(
        (t - line.t).abs() <= tol,
        "t {t} vs {} (bound {tol:e}): {what}",
        line.t
    );
    let tol_uv = uv_bound(precision, r, tri);
    assert!(
        (f64::from(h.u) - line.u).abs() <= tol_uv && (f64::from(h.v) - line.v).abs() <= tol_uv,
        "u, v ({}, {}) vs ({}, {}) (bound {tol_uv:e}): {what}",
        h.u,
        h.v,
        line.u,
        line.v
    );
}

/// Traces `rays` with every core in `precision`; checks each core against `brute` (bit for
/// bit, except `embree`) and every hit against the bounds. Returns `brute`'s hits.
fn all_cores(precision: Precision, tris: &[Triangle], rays: &[Ray]) -> Vec<Hit> {
    cores(&kinds(), precision, tris, rays)
}

/// [`all_cores`] for the cores `kinds` only.
fn cores(kinds: &[AccelKind], precision: Precision, tris: &[Triangle], rays: &[Ray]) -> Vec<Hit> {
    let reference = trace(AccelKind::Brute, precision, tris, rays);
    for &kind in kinds {
        let hits = if kind == AccelKind::Brute {
            reference.clone()
        } else {
            trace(kind, precision, tris, rays)
        };
        for (i, (h, b)) in hits.iter().zip(&reference).enumerate() {
            check_hit(kind, precision, &rays[i], tris, h);
            if kind != AccelKind::Embree {
                assert_eq!(
                    bits(h),
                    bits(b),
                    "{} {} ray {i} differs from brute: {:?}",
                    kind.name(),
                    precision.name(),
                    rays[i]
                );
            }
        }
    }
    reference
}

// Closed meshes.

/// The closed surface of the cube `[0, side]³`, each face cut into `n × n` squares of two
/// triangles with alternating diagonals. With `side` a multiple of `n` every vertex, edge
/// midpoint and face centre is exact in f32, and neighbours share vertices bit for bit.
fn cube(n: usize, side: f32) -> Vec<Triangle> {
    let step = side / n as f32;
    let mut tris = Vec::new();
    // Each face: a fixed axis at 0 or side, two running axes.
    for axis in 0..3 {
        let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
        for level in [0.0, side] {
            let p = |i: usize, j: usize| {
                let mut q = [0.0f32; 3];
                q[axis] = level;
                q[a] = i as f32 * step;
                q[b] = j as f32 * step;
                q
            };
            for i in 0..n {
                for j in 0..n {
                    let (p00, p10, p11, p01) = (p(i, j), p(i + 1, j), p(i + 1, j + 1), p(i, j + 1));
                    if (i + j) % 2 == 0 {
                        tris.push(Triangle { v: [p00, p10, p11] });
                        tris.push(Triangle { v: [p00, p11, p01] });
                    } else {
                        tris.push(Triangle { v: [p00, p10, p01] });
                        tris.push(Triangle { v: [p10, p11, p01] });
                    }
                }
            }
        }
    }
    tris
}

/// An icosahedron subdivided `levels` times and pushed onto the sphere of `radius` about
/// `centre`: a closed mesh whose shared vertices are bit-identical (each is computed once).
fn icosphere(levels: usize, radius: f64, centre: [f64; 3]) -> Vec<Triangle> {
    let g = (1.0 + 5f64.sqrt()) / 2.0;
    let mut verts: Vec<[f64; 3]> = vec![
        [-1.0, g, 0.0],
        [1.0, g, 0.0],
        [-1.0, -g, 0.0],
        [1.0, -g, 0.0],
        [0.0, -1.0, g],
        [0.0, 1.0, g],
        [0.0, -1.0, -g],
        [0.0, 1.0, -g],
        [g, 0.0, -1.0],
        [g, 0.0, 1.0],
        [-g, 0.0, -1.0],
        [-g, 0.0, 1.0],
    ];
    let mut faces: Vec<[usize; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..levels {
        let mut mid = std::collections::HashMap::new();
        let mut next = Vec::with_capacity(faces.len() * 4);
        for f in &faces {
            let mut m = [0usize; 3];
            for k in 0..3 {
                let (a, b) = (f[k].min(f[(k + 1) % 3]), f[k].max(f[(k + 1) % 3]));
                m[k] = *mid.entry((a, b)).or_insert_with(|| {
                    let (p, q) = (verts[a], verts[b]);
                    verts.push(std::array::from_fn(|i| (p[i] + q[i]) / 2.0));
                    verts.len() - 1
                });
            }
            next.push([f[0], m[0], m[2]]);
            next.push([f[1], m[1], m[0]]);
            next.push([f[2], m[2], m[1]]);
            next.push(m);
        }
        faces = next;
    }
    let placed: Vec<[f32; 3]> = verts
        .iter()
        .map(|p| {
            let len = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
            std::array::from_fn(|i| (centre[i] + radius * p[i] / len) as f32)
        })
        .collect();
    faces
        .iter()
        .map(|f| Triangle {
            v: f.map(|i| placed[i]),
        })
        .collect()
}

/// The vertices of `tris` and points on their edges (exact midpoints where the arithmetic
/// allows, else within an ulp of the edge).
fn edge_and_vertex_targets(tris: &[Triangle]) -> Vec<[f32; 3]> {
    let mut out = Vec::new();
    for t in tris {
        for k in 0..3 {
            let (a, b) = (t.v[k], t.v[(k + 1) % 3]);
            out.push(a);
            out.push(std::array::from_fn(|i| a[i] + 0.5 * (b[i] - a[i])));
            out.push(std::array::from_fn(|i| a[i] + 0.25 * (b[i] - a[i])));
        }
    }
    out.sort_by(|a, b| a.partial_cmp(b).unwrap());
    out.dedup();
    out
}

/// Rays from outside a convex closed mesh through `target` (on its surface) into its
/// interior around `centre`: every one must cross the surface. Some are axis-parallel with
/// ±0 components; the rest come from assorted directions.
fn inward_rays(rng: &mut Rng, targets: &[[f32; 3]], centre: [f32; 3], reach: f32) -> Vec<Ray> {
    let mut rays = Vec::new();
    for &p in targets {
        let out = sub(p, centre);
        // Axis-parallel along the axis that points most inward, with signed zeros.
        let axis = (0..3)
            .max_by(|&a, &b| out[a].abs().partial_cmp(&out[b].abs()).unwrap())
            .unwrap();
        for zero in [0.0f32, -0.0] {
            let mut dir = [zero; 3];
            dir[axis] = -out[axis].signum();
            let mut org = p;
            org[axis] -= reach * dir[axis];
            rays.push(ray(org, dir, 0.0, f32::INFINITY));
        }
        let size = (out[0] * out[0] + out[1] * out[1] + out[2] * out[2]).sqrt();
        for _ in 0..3 {
            // From outside, back along the outward direction plus a jitter small enough
            // (|jitter| < 0.52·|out|) that the ray still points into the solid.
            let jitter = rng.vec(0.3 * size);
            let org = addv(p, addv(out, jitter));
            rays.push(ray(org, sub(p, org), 0.0, f32::INFINITY));
        }
    }
    rays
}

#[test]
fn shared_edges_and_vertices_of_closed_meshes_let_no_watertight_ray_through() {
    let mut rng = Rng(11);
    let meshes: Vec<(Vec<Triangle>, [f32; 3], f32)> = vec![
        (cube(4, 8.0), [4.0; 3], 8.0),
        (cube(3, 0.75), [0.375; 3], 1.0),
        (icosphere(2, 1.0, [0.0; 3]), [0.0; 3], 2.0),
        (
            icosphere(1, 3.0e3, [-2.0e4, 1.0e4, 5.0e3]),
            [-2.0e4, 1.0e4, 5.0e3],
            5.0e3,
        ),
    ];
    for (tris, centre, reach) in &meshes {
        let targets = edge_and_vertex_targets(tris);
        let rays = inward_rays(&mut rng, &targets, *centre, *reach);
        for precision in PRECISIONS {
            let hits = all_cores(precision, tris, &rays);
            let misses = hits.iter().filter(|h| !h.is_hit()).count();
            if precision == Precision::Watertight {
                let mut doubles = 0;
                for (r, h) in rays.iter().zip(&hits) {
                    assert!(h.is_hit(), "watertight ray slipped through: {r:?}");
                    // A double (or multiple) hit at a shared edge or vertex goes to the
                    // smallest decision t, then the lowest id.
                    let all: Vec<(f32, u32)> = tris
                        .iter()
                        .enumerate()
                        .filter_map(|(id, t)| {
                            intersect_unrefined(precision, r, t).map(|x| (x.t, id as u32))
                        })
                        .collect();
                    let best = all
                        .iter()
                        .copied()
                        .min_by(|a, b| a.partial_cmp(b).unwrap())
                        .unwrap();
                    assert_eq!(best.1, h.prim, "{r:?}: not the (t, id) minimum of {all:?}");
                    doubles += usize::from(all.iter().filter(|x| x.0 == best.0).count() > 1);
                }
                eprintln!("watertight: {doubles} rays with tied hits at an edge or vertex");
            } else {
                eprintln!(
                    "fast: {misses} of {} edge/vertex rays slipped through",
                    rays.len()
                );
            }
        }
    }
}

#[test]
fn grid_edges_and_vertices_let_no_watertight_ray_through() {
    // An open height field: rays from above at interior vertices and edges.
    let mut rng = Rng(12);
    let n = 8;
    let h = |i: usize, j: usize| ((i * 7 + j * 3) % 5) as f32 * 0.25;
    let p = |i: usize, j: usize| [i as f32, j as f32, h(i, j)];
    let mut tris = Vec::new();
    for i in 0..n {
        for j in 0..n {
            if (i + j) % 2 == 0 {
                tris.push(Triangle {
                    v: [p(i, j), p(i + 1, j), p(i + 1, j + 1)],
                });
                tris.push(Triangle {
                    v: [p(i, j), p(i + 1, j + 1), p(i, j + 1)],
                });
            } else {
                tris.push(Triangle {
                    v: [p(i, j), p(i + 1, j), p(i, j + 1)],
                });
                tris.push(Triangle {
                    v: [p(i + 1, j), p(i + 1, j + 1), p(i, j + 1)],
                });
            }
        }
    }
    let interior = |q: &[f32; 3]| q[0] > 0.0 && q[0] < n as f32 && q[1] > 0.0 && q[1] < n as f32;
    let targets: Vec<[f32; 3]> = edge_and_vertex_targets(&tris)
        .into_iter()
        .filter(interior)
        .collect();
    let mut rays = Vec::new();
    for &q in &targets {
        for dir in [[0.0, 0.0, -1.0], [-0.0, -0.0, -1.0], [0.0, -0.0, -2.0]] {
            rays.push(ray(addv(q, [0.0, 0.0, 4.0]), dir, 0.0, f32::INFINITY));
        }
        for _ in 0..3 {
            let off = [rng.sym() * 2.0, rng.sym() * 2.0, 4.0];
            rays.push(ray(addv(q, off), sub(q, addv(q, off)), 0.0, f32::INFINITY));
        }
    }
    for precision in PRECISIONS {
        let hits = all_cores(precision, &tris, &rays);
        if precision == Precision::Watertight {
            for (r, h) in rays.iter().zip(&hits) {
                assert!(h.is_hit(), "watertight ray slipped through the grid: {r:?}");
            }
        }
    }
}

// Far from the origin.

#[test]
fn exactly_translated_scenes_give_bit_identical_hits() {
    // Integer vertices and ray origins: every translation below is exact in f32, so the
    // geometry seen from each ray is the same and every core must answer bit for bit the
    // same at every offset.
    let base = cube(4, 64.0);
    let mut rng = Rng(13);
    let targets = edge_and_vertex_targets(&base);
    let base_rays: Vec<Ray> = inward_rays(&mut rng, &targets, [32.0; 3], 128.0)
        .into_iter()
        .map(|r| Ray {
            org: r.org.map(f32::round),
            ..r
        })
        .collect();
    for precision in PRECISIONS {
        let reference = all_cores(precision, &base, &base_rays);
        for offset in [1e3f32, 1e4, 1e5, 1e6, 1e7] {
            for sign in [[1.0f32, 1.0, 1.0], [-1.0, 1.0, -1.0]] {
                let o: [f32; 3] = std::array::from_fn(|k| sign[k] * offset);
                let tris: Vec<Triangle> = base
                    .iter()
                    .map(|t| Triangle {
                        v: t.v.map(|p| addv(p, o)),
                    })
                    .collect();
                let rays: Vec<Ray> = base_rays
                    .iter()
                    .map(|r| Ray {
                        org: addv(r.org, o),
                        ..*r
                    })
                    .collect();
                for kind in kinds() {
                    if kind == AccelKind::Embree {
                        continue;
                    }
                    let hits = trace(kind, precision, &tris, &rays);
                    for (i, (h, b)) in hits.iter().zip(&reference).enumerate() {
                        assert_eq!(
                            bits(h),
                            bits(b),
                            "{} {} offset {o:?}, ray {i}: {:?}",
                            kind.name(),
                            precision.name(),
                            rays[i]
                        );
                    }
                }
                // And from the glTF loader, with the offset in a node's translation.
                let loaded = gltf_translated(&base, o);
                assert_eq!(loaded, tris, "glTF node translation {o:?}");
            }
        }
    }
}

#[test]
fn far_scenes_keep_t_within_the_bound() {
    // A sphere that f32 cannot translate exactly: compare each offset's hits with the f64
    // oracle on the coordinates actually stored, rays starting near the scene and at the
    // origin.
    let mut rng = Rng(14);
    for offset in [0.0, 1e3, 1e4, 1e5, 1e6, 1e7] {
        let c = [offset * 1.37, -offset * 0.61, offset];
        let cf = c.map(|x| x as f32);
        let radius = 10.0f64.max(offset * 1e-5);
        let tris = icosphere(2, radius, c);
        let targets = edge_and_vertex_targets(&tris);
        let mut rays = inward_rays(
            &mut rng,
            &targets[..targets.len().min(400)],
            cf,
            3.0 * radius as f32,
        );
        // From the origin towards the scene.
        for p in targets.iter().step_by(7) {
            rays.push(ray([0.0; 3], *p, 0.0, f32::INFINITY));
        }
        // The same sphere made at the origin and moved by a glTF node translation: the
        // loader rounds the world positions itself; the bounds hold for what it stored.
        let at_origin = icosphere(2, radius, [0.0; 3]);
        let loaded = gltf_translated(&at_origin, cf);
        for precision in PRECISIONS {
            for scene in [&tris, &loaded] {
                let hits = all_cores(precision, scene, &rays);
                if precision == Precision::Watertight && scene == &tris {
                    // The near rays enter the sphere, so they all hit.
                    for (r, h) in rays.iter().zip(&hits) {
                        if r.org != [0.0; 3] {
                            assert!(h.is_hit(), "offset {offset}: slipped through: {r:?}");
                        }
                    }
                }
            }
        }
    }
}

/// `base` as a GLB with one mesh under a node translated by `offset`, loaded back.
fn gltf_translated(base: &[Triangle], offset: [f32; 3]) -> Vec<Triangle> {
    let positions: Vec<f32> = base.iter().flat_map(|t| t.v.concat()).collect();
    let doc = serde_json::json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "translation": offset}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "buffers": [{"byteLength": positions.len() * 4}],
        "bufferViews": [{"buffer": 0, "byteLength": positions.len() * 4}],
        "accessors": [{
            "bufferView": 0, "componentType": 5126, "count": positions.len() / 3,
            "type": "VEC3",
        }],
    });
    let bin: Vec<u8> = positions.iter().flat_map(|v| v.to_le_bytes()).collect();
    rayd::formats::gltf::load(&glb(&doc, &bin), None, &Default::default())
        .expect("glTF loads")
        .triangles
}

/// A GLB container around `doc` and `bin`.
fn glb(doc: &serde_json::Value, bin: &[u8]) -> Vec<u8> {
    let mut json = serde_json::to_vec(doc).unwrap();
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    let mut bin = bin.to_vec();
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&(total as u32).to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(b"BIN\0");
    out.extend_from_slice(&bin);
    out
}

// Sizes.

#[test]
fn large_triangle_hit_near_the_origin_has_an_accurate_t() {
    // The case that found the inaccurate watertight t: 1000-unit triangles, tilted against
    // the ray, hit at t ≈ 0.07. The sheared vertices are ~1000 while t is 0.07, so the f32
    // watertight t was off by up to 3e-4 (relative); it now comes from the plane in f64.
    let mut rng = Rng(15);
    let mut worst = [0.0f64; 2];
    for _ in 0..400 {
        let dir = [rng.sym() * 0.5, rng.sym() * 0.5, 1.0];
        let org = rng.vec(1.0);
        let t_hit = 0.05 + 0.04 * rng.unit() as f64;
        let p: [f64; 3] = std::array::from_fn(|k| f64::from(org[k]) + t_hit * f64::from(dir[k]));
        // Two in-plane directions of a plane tilted 30–80° from the ray.
        let a = [1.0, 0.0, -(0.3 + 2.0 * rng.unit() as f64)];
        let b = [0.0, 1.0, rng.sym() as f64 * 2.0];
        let v = |s: f64, q: f64| -> [f32; 3] {
            std::array::from_fn(|k| (p[k] + 500.0 * (s * a[k] + q * b[k])) as f32)
        };
        let tri = Triangle {
            v: [v(-1.0, -0.7), v(1.1, -0.4), v(-0.2, 1.0)],
        };
        let r = ray(org, dir, 0.0, f32::INFINITY);
        let n = tri.normal();
        let cos = (n[0] * dir[0] + n[1] * dir[1] + n[2] * dir[2]).abs()
            / ((n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt()
                * (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]).sqrt());
        if cos < 0.2 {
            continue; // grazing: t is ill-conditioned whatever the test
        }
        let exact = oracle_f64(&r, &tri).expect("the oracle hits");
        for (i, precision) in PRECISIONS.into_iter().enumerate() {
            let hits = all_cores(precision, &[tri], &[r]);
            let err = (f64::from(hits[0].t) - exact.t).abs() / exact.t;
            worst[i] = worst[i].max(err);
            if precision == Precision::Watertight {
                // One f32 rounding of an f64 value accurate to ~1e-13 here.
                assert!(
                    err <= 6.0e-8,
                    "watertight t {} vs {}: {err:e}",
                    hits[0].t,
                    exact.t
                );
            }
        }
    }
    eprintln!(
        "worst relative t error: fast {:e}, watertight {:e}",
        worst[0], worst[1]
    );
}

#[test]
fn tiny_and_huge_triangles_in_one_scene() {
    let mut rng = Rng(16);
    let mut tris = Vec::new();
    let mut rays = Vec::new();
    // Huge triangles around the scene, tilted; tiny ones (1e-6) scattered in between.
    for k in 0..6 {
        let z = 3.0 + k as f32;
        tris.push(Triangle {
            v: [
                [-1e3, -1e3, z - 40.0],
                [1e3, -1e3, z + 30.0],
                [0.0, 1e3, z + 5.0],
            ],
        });
    }
    for _ in 0..200 {
        let c = rng.vec(1.0);
        let s = 1e-6;
        let tri = Triangle {
            v: [
                addv(c, rng.vec(s)),
                addv(c, rng.vec(s)),
                addv(c, rng.vec(s)),
            ],
        };
        if tri.is_degenerate() {
            continue;
        }
        // Aim at the centroid from a little way off.
        let g: [f32; 3] = std::array::from_fn(|k| (tri.v[0][k] + tri.v[1][k] + tri.v[2][k]) / 3.0);
        let org = addv(g, rng.vec(2.0));
        rays.push(ray(org, sub(g, org), 0.0, f32::INFINITY));
        tris.push(tri);
    }
    for precision in PRECISIONS {
        let hits = all_cores(precision, &tris, &rays);
        // The oracle's closest triangle is found, except where the bounds excuse it: a hit
        // within its u, v bound of an edge (of the oracle's triangle or the core's), or
        // two triangles within the t bound of each other.
        let margin = |r: &Ray, id: u32| {
            let tri = &tris[id as usize];
            let l = oracle_line_f64(r, tri).expect("a hit has a plane");
            let m = l.u.min(l.v).min(1.0 - l.u - l.v).abs();
            (l.t, m <= uv_bound(precision, r, tri))
        };
        let mut excused = 0;
        for (r, h) in rays.iter().zip(&hits) {
            let Some((id, o)) = oracle_closest_f64(r, &tris) else {
                assert!(!h.is_hit() || margin(r, h.prim).1, "{r:?} {h:?}");
                continue;
            };
            if h.prim == id {
                continue;
            }
            let (_, oracle_near_edge) = margin(r, id);
            let core_near_edge = h.is_hit() && margin(r, h.prim).1;
            // Ordered by the test's t, whose error is `order_t_bound`.
            let tie = h.is_hit()
                && (f64::from(h.t) - o.t).abs()
                    <= order_t_bound(precision, r, &tris[id as usize], o.t)
                        + order_t_bound(precision, r, &tris[h.prim as usize], o.t)
                        + t_bound(precision, r, &tris[h.prim as usize], o.t);
            assert!(
                oracle_near_edge || core_near_edge || tie,
                "{}: {r:?} hit {h:?}, the oracle {id} at {o:?}",
                precision.name()
            );
            excused += 1;
        }
        eprintln!(
            "{}: {excused} of {} rays excused (near an edge within the u, v bound)",
            precision.name(),
            rays.len()
        );
    }
}

#[test]
fn sliver_triangles_keep_the_guarantees() {
    // A tilted unit square cut into a fan of 2·n slivers from one corner (aspect up to
    // ~n), vertices shared bit for bit: rays aimed at the shared edges never slip through
    // in `watertight`, and every hit of every core keeps the t and u, v bounds, which
    // grow with the sliver factor S.
    let n = 400;
    let z = |x: f32, y: f32| 0.25 * x + 0.125 * y + 1.0;
    let p = |x: f32, y: f32| [x, y, z(x, y)];
    let mut rim = Vec::new();
    for i in 0..=n {
        rim.push(p(i as f32 / n as f32, 1.0));
    }
    for j in (0..n).rev() {
        rim.push(p(1.0, j as f32 / n as f32));
    }
    let corner = p(0.0, 0.0);
    let tris: Vec<Triangle> = rim
        .windows(2)
        .map(|w| Triangle {
            v: [corner, w[0], w[1]],
        })
        .collect();
    let mut rng = Rng(21);
    let mut rays = Vec::new();
    for (k, q) in rim.iter().enumerate().skip(1).take(2 * n - 1) {
        // Points on the shared edge corner–q, away from the square's boundary.
        for f in [0.5f32, 0.125, 0.875, 0.999] {
            let target: [f32; 3] = std::array::from_fn(|i| corner[i] + f * (q[i] - corner[i]));
            let org = addv(target, [rng.sym() * 0.5, rng.sym() * 0.5, 3.0]);
            rays.push(ray(org, sub(target, org), 0.0, f32::INFINITY));
            if k % 16 == 0 {
                rays.push(ray(
                    addv(target, [0.0, 0.0, 2.0]),
                    [0.0, -0.0, -1.0],
                    0.0,
                    f32::INFINITY,
                ));
            }
        }
    }
    for precision in PRECISIONS {
        let hits = all_cores(precision, &tris, &rays);
        let misses = hits.iter().filter(|h| !h.is_hit()).count();
        if precision == Precision::Watertight {
            assert_eq!(misses, 0, "watertight rays slipped between slivers");
        } else {
            eprintln!("fast: {misses} of {} sliver-edge rays missed", rays.len());
        }
    }
}

// Degenerate and invalid.

#[test]
fn degenerate_triangles_are_never_hit_by_any_core() {
    let mut rng = Rng(17);
    let mut tris = Vec::new();
    for _ in 0..100 {
        // Quarter units keep every sum below exact, so these stay degenerate in f32.
        let a = rng.vec(3.0).map(|x| (x * 4.0).round() / 4.0);
        let d = rng.vec(1.0);
        tris.push(Triangle { v: [a, a, a] });
        tris.push(Triangle {
            v: [a, a, addv(a, d)],
        });
        // Exactly collinear.
        tris.push(Triangle {
            v: [a, addv(a, [1.0, 2.0, 4.0]), addv(a, [2.0, 4.0, 8.0])],
        });
    }
    assert!(tris.iter().all(Triangle::is_degenerate));
    let good = Triangle {
        v: [[-9.0, -9.0, 9.0], [9.0, -9.0, 9.0], [0.0, 9.0, 9.0]],
    };
    tris.push(good);
    let good_id = (tris.len() - 1) as u32;
    let mut rays = Vec::new();
    for t in &tris {
        for p in t.v {
            let org = addv(p, rng.vec(1.0));
            rays.push(ray(org, sub(p, org), 0.0, f32::INFINITY));
            rays.push(ray(org, [0.0, 0.0, 1.0], 0.0, f32::INFINITY));
        }
    }
    for precision in PRECISIONS {
        let hits = all_cores(precision, &tris, &rays);
        for h in hits.iter().filter(|h| h.is_hit()) {
            assert!(
                !tris[h.prim as usize].is_degenerate(),
                "hit degenerate triangle {}",
                h.prim
            );
            assert_eq!(h.prim, good_id);
        }
    }
}

#[test]
fn axis_parallel_rays_with_signed_zeros_and_rays_in_a_plane() {
    let tris = cube(2, 2.0);
    let mut rays = Vec::new();
    let zeros = [0.0f32, -0.0];
    for &z0 in &zeros {
        for &z1 in &zeros {
            for axis in 0..3 {
                for sign in [1.0f32, -1.0] {
                    let mut dir = [z0, z1, z0];
                    dir[(axis + 1) % 3] = z1;
                    dir[axis] = sign;
                    for (a, b) in [(0.5, 0.5), (1.0, 1.0), (0.0, 1.0), (2.0, 2.0), (1.5, 0.0)] {
                        let mut org = [0.0f32; 3];
                        org[axis] = if sign > 0.0 { -3.0 } else { 5.0 };
                        org[(axis + 1) % 3] = a;
                        org[(axis + 2) % 3] = b;
                        rays.push(ray(org, dir, 0.0, f32::INFINITY));
                    }
                }
            }
        }
    }
    // In the plane of a face (z = 2): along it, through its interior and along its edges.
    for y in [0.0f32, 0.5, 1.0, 2.0] {
        rays.push(ray([-1.0, y, 2.0], [1.0, 0.0, 0.0], 0.0, f32::INFINITY));
        rays.push(ray([-1.0, y, 2.0], [1.0, -0.0, 0.0], 0.0, f32::INFINITY));
    }
    // Each ray again with the sign of every zero component flipped.
    let flipped: Vec<Ray> = rays
        .iter()
        .map(|r| Ray {
            dir: r.dir.map(|d| if d == 0.0 { -d } else { d }),
            ..*r
        })
        .collect();
    for precision in PRECISIONS {
        let hits = all_cores(precision, &tris, &rays);
        let other = all_cores(precision, &tris, &flipped);
        for ((r, h), g) in rays.iter().zip(&hits).zip(&other) {
            // The same answer (a zero u or v may change sign: compared as numbers).
            assert_eq!(
                (h.prim, h.t, h.u, h.v),
                (g.prim, g.t, g.u, g.v),
                "{r:?}: ±0 changed the answer"
            );
        }
        for (r, h) in rays.iter().zip(&hits) {
            if !h.is_hit() {
                continue;
            }
            // Never the face the ray lies in.
            let tri = &tris[h.prim as usize];
            let n = tri.normal();
            let along = n[0] * r.dir[0] + n[1] * r.dir[1] + n[2] * r.dir[2];
            assert!(
                along != 0.0,
                "hit a triangle parallel to the ray: {r:?} {h:?}"
            );
        }
        // Axis-parallel rays at the cube's boundary or inside it all hit, at exact t.
        for (r, h) in rays.iter().zip(&hits) {
            let lateral: Vec<f32> = (0..3)
                .filter(|&k| r.dir[k] == 0.0)
                .map(|k| r.org[k])
                .collect();
            if lateral.len() == 2 && lateral.iter().all(|x| (0.0..=2.0).contains(x)) {
                if precision == Precision::Watertight {
                    assert!(h.is_hit(), "{r:?}");
                }
                if h.is_hit() {
                    let axis = (0..3).find(|&k| r.dir[k] != 0.0).unwrap();
                    let face = if r.dir[axis] > 0.0 { 0.0 } else { 2.0 };
                    assert_eq!(r.org[axis] + h.t * r.dir[axis], face, "{r:?} {h:?}");
                }
            }
        }
    }
}

#[test]
fn rays_starting_on_a_surface_and_the_interval_ends() {
    let tris = cube(2, 2.0);
    let mut rng = Rng(18);
    let mut rays = Vec::new();
    // Starting on a face, at a vertex and on an edge, going in and out.
    for org in [
        [1.0, 1.0, 2.0],
        [0.5, 1.5, 0.0],
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 2.0],
        [2.0, 1.0, 1.0],
    ] {
        for _ in 0..20 {
            rays.push(ray(org, rng.vec(1.0), 0.0, f32::INFINITY));
        }
    }
    for precision in PRECISIONS {
        // Every hit is checked against the bound and the interval by all_cores: t >= 0,
        // and the face the ray starts on, if hit, is hit at t = 0 exactly here (the
        // origin lies exactly in its axis-aligned plane).
        let hits = all_cores(precision, &tris, &rays);
        for (r, h) in rays.iter().zip(&hits) {
            let tri = &tris[h.prim.min(tris.len() as u32 - 1) as usize];
            let axis = (0..3).find(|&k| tri.v.iter().all(|p| p[k] == tri.v[0][k]));
            if h.is_hit() && axis.is_some_and(|k| r.org[k] == tri.v[0][k]) {
                assert_eq!(h.t, 0.0, "{r:?} {h:?}");
            }
        }
        // The interval is tested on the test's own t (t0): [t0, t0] and [0, t0] find the
        // same triangle again, and its reported t is the first one clamped into them.
        let mut again = Vec::new();
        let mut want = Vec::new();
        for (r, h) in rays.iter().zip(&hits).filter(|(_, h)| h.is_hit()) {
            let t0 = intersect_unrefined(precision, r, &tris[h.prim as usize])
                .expect("the reported triangle is hit")
                .t;
            for (tmin, tmax) in [(t0, t0), (0.0, t0)] {
                again.push(Ray { tmin, tmax, ..*r });
                want.push((h.prim, h.t.clamp(tmin, tmax)));
            }
        }
        let second = all_cores(precision, &tris, &again);
        for ((h, w), r) in second.iter().zip(&want).zip(&again) {
            assert!(h.is_hit(), "[t0, t0] or [0, t0] lost the hit: {r:?} {w:?}");
            assert_eq!((h.prim, h.t.to_bits()), (w.0, w.1.to_bits()), "{r:?}");
        }
        // tmin = tmax = 0 from on a surface: the surface at t = 0.
        let zero: Vec<Ray> = [[1.0, 1.0, 2.0], [0.5, 0.0, 1.5]]
            .into_iter()
            .map(|o| ray(o, [0.3, 0.2, 1.0], 0.0, 0.0))
            .collect();
        let z = all_cores(precision, &tris, &zero);
        for h in &z {
            // Möller–Trumbore may miss the second, which starts on a diagonal edge.
            if precision == Precision::Watertight {
                assert!(h.is_hit(), "{h:?}");
            }
            assert!(!h.is_hit() || h.t == 0.0, "{h:?}");
        }
    }
}

#[test]
fn coplanar_overlapping_triangles_go_to_the_lowest_id() {
    // Overlapping triangles in the planes z = 1 and x + y + z = 6 (tilted: the test's t of
    // different triangles of one plane may differ in the last bits), with exact
    // duplicates, listed in a shuffled order.
    let mut rng = Rng(19);
    let mut tris = Vec::new();
    for k in 0..24 {
        let s = 2.0 + (k % 5) as f32;
        let c = [rng.sym(), rng.sym()];
        tris.push(Triangle {
            v: [
                [c[0] - s, c[1] - s, 1.0],
                [c[0] + s, c[1] - s, 1.0],
                [c[0], c[1] + s, 1.0],
            ],
        });
        if k % 3 == 0 {
            tris.push(*tris.last().unwrap());
        }
        let q = |x: f32, y: f32| [x, y, 6.0 - x - y];
        tris.push(Triangle {
            v: [q(-s, -s), q(2.0 * s, -s), q(-s, 2.0 * s)],
        });
    }
    let mut rays = Vec::new();
    for _ in 0..300 {
        let o = [rng.sym() * 0.5, rng.sym() * 0.5, -3.0];
        rays.push(ray(
            o,
            [rng.sym() * 0.05, rng.sym() * 0.05, 1.0],
            0.0,
            f32::INFINITY,
        ));
        let o2 = [rng.sym() * 0.5, rng.sym() * 0.5, 10.0];
        rays.push(ray(
            o2,
            [rng.sym() * 0.05, rng.sym() * 0.05, -1.0],
            0.0,
            f32::INFINITY,
        ));
    }
    for precision in PRECISIONS {
        let hits = all_cores(precision, &tris, &rays);
        for (r, h) in rays.iter().zip(&hits) {
            assert!(h.is_hit(), "{r:?}");
            // By the test's t (what the cores order by): no triangle is nearer, and no
            // lower id is as near.
            let t0 = intersect_unrefined(precision, r, &tris[h.prim as usize])
                .unwrap()
                .t;
            for (id, tri) in tris.iter().enumerate() {
                if let Some(o) = intersect_unrefined(precision, r, tri) {
                    assert!(o.t >= t0, "{r:?}: id {id} is nearer than {}", h.prim);
                    assert!(
                        id as u32 >= h.prim || o.t != t0,
                        "{r:?}: id {id} ties with {} at {t0}",
                        h.prim
                    );
                }
            }
            // Exact duplicates tie exactly, so the lower id of a pair wins.
            if let Some(twin) = tris.iter().position(|t| *t == tris[h.prim as usize]) {
                assert_eq!(twin as u32, h.prim, "{r:?}: the duplicate's lower id");
            }
        }
        // The any query finds a real hit with every core too.
        for kind in kinds() {
            let any = trace_q(kind, BuildQuality::Sah, precision, &tris, &rays, Query::Any);
            for (r, h) in rays.iter().zip(&any) {
                assert!(h.is_hit(), "{} any: {r:?}", kind.name());
                check_hit(kind, precision, r, &tris, h);
            }
        }
    }
}

#[test]
fn cores_do_not_crash_on_rays_the_contract_calls_invalid() {
    // The service refuses these (Ray::validate_batch); a library caller that skips
    // validation still gets an answer, never a panic.
    let tris = cube(2, 2.0);
    let nan = f32::NAN;
    let inf = f32::INFINITY;
    let rays = vec![
        ray([nan, 0.0, 0.0], [0.0, 0.0, 1.0], 0.0, inf),
        ray([1.0, 1.0, -1.0], [nan, 0.0, 1.0], 0.0, inf),
        ray([1.0, 1.0, -1.0], [0.0, 0.0, 1.0], nan, inf),
        ray([1.0, 1.0, -1.0], [0.0, 0.0, 1.0], 0.0, nan),
        ray([inf, 1.0, -1.0], [0.0, 0.0, 1.0], 0.0, inf),
        ray([1.0, 1.0, -1.0], [0.0, -inf, 1.0], 0.0, inf),
        ray([1.0, 1.0, -1.0], [0.0, 0.0, 0.0], 0.0, inf),
        ray([1.0, 1.0, -1.0], [0.0, 0.0, 1.0], -1.0, inf),
        ray([0.5, 0.25, -1.0], [0.0, 0.0, 1.0], 0.0, inf),
    ];
    let mut checked = rays.clone();
    let bad = Ray::validate_batch(&mut checked, false).expect("invalid rays are found");
    assert_eq!((bad.first_index, bad.count), (0, 8));
    for precision in PRECISIONS {
        for kind in kinds() {
            let hits = trace(kind, precision, &tris, &rays);
            assert!(hits[8].is_hit(), "{}: the valid ray", kind.name());
        }
    }
}

#[test]
fn nan_and_infinite_inputs_get_errors_that_say_where() {
    use rayd::formats::binary::{read_tri, write_tri, BinaryError};
    use rayd::formats::gltf::GltfError;
    use rayd::geometry::RayError;
    use rayd::scene::SceneError;
    // Rays: each field, first index, reason and count.
    let good = ray([0.0; 3], [0.0, 0.0, 1.0], 0.0, f32::INFINITY);
    let cases: Vec<(Ray, RayError)> = vec![
        (
            ray([f32::NAN, 0.0, 0.0], good.dir, 0.0, 1.0),
            RayError::NonFiniteOrigin,
        ),
        (
            ray([0.0, f32::NEG_INFINITY, 0.0], good.dir, 0.0, 1.0),
            RayError::NonFiniteOrigin,
        ),
        (
            ray([0.0; 3], [0.0, f32::NAN, 1.0], 0.0, 1.0),
            RayError::NonFiniteDirection,
        ),
        (
            ray([0.0; 3], [f32::INFINITY, 0.0, 1.0], 0.0, 1.0),
            RayError::NonFiniteDirection,
        ),
        (
            ray([0.0; 3], [-0.0, 0.0, -0.0], 0.0, 1.0),
            RayError::ZeroDirection,
        ),
        (ray([0.0; 3], good.dir, f32::NAN, 1.0), RayError::BadTmin),
        (ray([0.0; 3], good.dir, -0.5, 1.0), RayError::BadTmin),
        (ray([0.0; 3], good.dir, 0.0, f32::NAN), RayError::NanTmax),
    ];
    for (bad, reason) in &cases {
        let mut batch = vec![good, good, *bad, good, *bad];
        let found = Ray::validate_batch(&mut batch, false).expect("found");
        assert_eq!(
            (found.first_index, found.first_reason, found.count),
            (2, *reason, 2)
        );
        let text = found.to_string();
        assert!(
            text.contains("ray 2") && text.contains("2 invalid"),
            "{text}"
        );
        let found = Ray::validate_batch(&mut batch, true).expect("found");
        assert_eq!(found.count, 2);
        assert_eq!(batch[2], Ray::EMPTY);
    }
    // Allowed edge cases are valid: tmax = +inf, tmin = tmax, empty intervals, -0 tmin.
    for r in [
        good,
        ray([0.0; 3], good.dir, 2.0, 2.0),
        ray([0.0; 3], good.dir, 3.0, 1.0),
        ray([0.0; 3], good.dir, f32::INFINITY, f32::INFINITY),
        ray([0.0; 3], good.dir, -0.0, 1.0),
    ] {
        assert_eq!(r.check(), Ok(()), "{r:?}");
    }
    // TRI1: the triangle and the byte offset of the coordinate.
    for (bad, name) in [
        (f32::NAN, "NaN"),
        (f32::INFINITY, "inf"),
        (f32::NEG_INFINITY, "-inf"),
    ] {
        let mut tris = cube(1, 1.0);
        tris[5].v[2][1] = bad;
        match read_tri(&write_tri(&tris)) {
            Err(BinaryError::NonFiniteTriangle { index, offset }) => {
                assert_eq!(index, 5, "{name}");
                assert_eq!(offset, 16 + 5 * 36 + (2 * 3 + 1) * 4, "{name}");
            }
            other => panic!("{name}: {other:?}"),
        }
    }
    // glTF: a stored NaN position, and a transform that overflows f32 in world space.
    let positions = [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, f32::NAN]];
    match load_positions(&positions, serde_json::json!({"mesh": 0})) {
        Err(GltfError::NonFinitePosition { accessor, element }) => {
            assert_eq!((accessor, element), (0, 2));
        }
        other => panic!("NaN position: {other:?}"),
    }
    let fine = [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 3e38, 0.0]];
    match load_positions(
        &fine,
        serde_json::json!({"mesh": 0, "scale": [1.0, 10.0, 1.0]}),
    ) {
        Err(GltfError::Scene(SceneError::NonFiniteWorldPosition { vertex, .. })) => {
            assert_eq!(vertex, 2)
        }
        other => panic!("overflow: {other:?}"),
    }
    // A huge but finite translation is a scene like any other.
    let ok = load_positions(
        &[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        serde_json::json!({"mesh": 0, "translation": [1e30, 0.0, 0.0]}),
    );
    assert!(ok.is_ok(), "{ok:?}");
}

/// One triangle list with `positions` under the node `node`, loaded.
fn load_positions(
    positions: &[[f32; 3]],
    node: serde_json::Value,
) -> Result<rayd::scene::Scene, rayd::formats::gltf::GltfError> {
    let flat: Vec<f32> = positions.concat();
    let doc = serde_json::json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [node],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "buffers": [{"byteLength": flat.len() * 4}],
        "bufferViews": [{"buffer": 0, "byteLength": flat.len() * 4}],
        "accessors": [{
            "bufferView": 0, "componentType": 5126, "count": flat.len() / 3, "type": "VEC3",
        }],
    });
    let bin: Vec<u8> = flat.iter().flat_map(|v| v.to_le_bytes()).collect();
    rayd::formats::gltf::load(&glb(&doc, &bin), None, &Default::default())
}

#[test]
fn scenes_with_non_finite_triangles_do_not_crash_the_cores() {
    // The loaders refuse them; a library caller that builds a core over them anyway gets
    // a core that never reports a hit on them.
    let mut tris = cube(2, 2.0);
    let n = tris.len();
    tris.push(Triangle {
        v: [[f32::NAN, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
    });
    tris.push(Triangle {
        v: [[f32::INFINITY, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]],
    });
    let rays = vec![
        ray([0.25, 0.6, -1.0], [0.0, 0.0, 1.0], 0.0, f32::INFINITY),
        ray([0.5, 0.25, 5.0], [0.0, 0.0, -1.0], 0.0, f32::INFINITY),
    ];
    for precision in PRECISIONS {
        for kind in kinds() {
            let hits = trace(kind, precision, &tris, &rays);
            for h in &hits {
                assert!(
                    h.is_hit() && (h.prim as usize) < n,
                    "{}: {h:?}",
                    kind.name()
                );
            }
        }
    }
}

/// Triangles whose test products leave f32's range though their inputs do not
/// (`proto/semantics.md`, "The range the tests decide in"): a ground quad 2e13 wide seen
/// at shallow angles and a cube of half-side 2^43 seen from its centre (the t numerator,
/// extent² × depth, overflows), and a triangle of area 5e-41 seen head on (its
/// determinant is subnormal, whose reciprocal overflows). Both tests hit them all, on
/// every core alike (they missed, every core and Embree too, until the lanes that leave
/// the range were rescaled by a power of two: `watertight` in session 28, `fast`, whose
/// products are of three coordinates, in session 36).
#[test]
fn triangles_whose_products_leave_f32s_range_are_still_hit() {
    for precision in PRECISIONS {
        products_leave_range(precision);
    }
}

fn products_leave_range(precision: Precision) {
    let same_everywhere = |tris: &[Triangle], rays: &[Ray]| -> Vec<Hit> {
        let reference = trace(AccelKind::Brute, precision, tris, rays);
        for kind in exact_cores() {
            let hits = trace(kind, precision, tris, rays);
            for (i, (h, b)) in hits.iter().zip(&reference).enumerate() {
                assert_eq!(bits(h), bits(b), "{} ray {i}: {:?}", kind.name(), rays[i]);
            }
        }
        reference
    };
    // The ground quad, half-size 1e13, in the plane y = 0.
    let h = 1e13f32;
    let quad = vec![
        Triangle {
            v: [[-h, 0.0, -h], [h, 0.0, -h], [h, 0.0, h]],
        },
        Triangle {
            v: [[-h, 0.0, -h], [h, 0.0, h], [-h, 0.0, h]],
        },
    ];
    let mut rng = Rng(11);
    let mut rays = vec![ray([0.3, 1.0, 0.2], [0.5, -0.2, 1.0], 0.0, f32::MAX)];
    for _ in 0..200 {
        // Downwards at shallow angles, from a metre up.
        let (x, z) = (rng.sym(), rng.sym());
        let dy = -(0.01 + 0.5 * rng.unit());
        rays.push(ray([rng.sym(), 1.0, rng.sym()], [x, dy, z], 0.0, f32::MAX));
    }
    let hits = same_everywhere(&quad, &rays);
    for (r, h) in rays.iter().zip(&hits) {
        let want = -r.org[1] / r.dir[1];
        assert!(h.is_hit(), "{r:?} missed the ground");
        assert!(
            (h.t - want).abs() <= 1e-5 * want,
            "{r:?}: t {} for {want}",
            h.t
        );
    }
    // The cube of half-side 2^43 about the origin (vertices exact in f32), from inside:
    // every ray leaves through a face, none through a crack.
    let side = 2f32.powi(44);
    let half = 2f32.powi(43);
    let cube_tris: Vec<Triangle> = cube(4, side)
        .into_iter()
        .map(|t| Triangle {
            v: t.v.map(|p| p.map(|x| x - half)),
        })
        .collect();
    let rays: Vec<Ray> = (0..500)
        .map(|_| {
            let d = [rng.sym(), rng.sym(), rng.sym()];
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-3);
            ray([0.0; 3], d.map(|x| x / n), 0.0, f32::MAX)
        })
        .collect();
    let hits = same_everywhere(&cube_tris, &rays);
    for (r, h) in rays.iter().zip(&hits) {
        assert!(h.is_hit(), "{r:?} left the cube");
        let largest = r.dir.iter().fold(0.0f32, |m, x| m.max(x.abs()));
        let want = half / largest;
        assert!(
            (h.t - want).abs() <= 1e-4 * want,
            "{r:?}: t {} for {want}",
            h.t
        );
    }
    // A right triangle of legs 1e-20 (area 5e-41), head on from either side.
    let a = 1e-20f32;
    let tiny = vec![Triangle {
        v: [[0.0, 0.0, 1.0], [a, 0.0, 1.0], [0.0, a, 1.0]],
    }];
    let rays = vec![
        ray([a / 4.0, a / 4.0, 0.0], [0.0, 0.0, 1.0], 0.0, f32::MAX),
        ray([a / 4.0, a / 4.0, 2.0], [0.0, 0.0, -1.0], 0.0, f32::MAX),
        ray([a, a, 0.0], [0.0, 0.0, 1.0], 0.0, f32::MAX),
    ];
    let hits = same_everywhere(&tiny, &rays);
    for (r, h) in rays.iter().zip(&hits).take(2) {
        assert!(h.is_hit(), "{r:?} missed the tiny triangle");
        assert!((h.t - 1.0).abs() < 1e-6, "{r:?}: t {}", h.t);
        assert!(
            (h.u - 0.25).abs() < 1e-5 && (h.v - 0.25).abs() < 1e-5,
            "{h:?}"
        );
    }
    assert!(
        !hits[2].is_hit(),
        "outside the tiny triangle: {:?}",
        hits[2]
    );
}

/// Grids of triangles 1e-18 to 1e-36 across at the ray origins, alone and beside a grid of
/// 1e30 triangles that shares a vertex with them. The watertight test's t numerator, the
/// extent across the ray squared times the depth along it, is ~1e-54 there, below f32's
/// range: it underflowed to ±0, so a grid 1e-18 *behind* the origin was hit at t = 0 by
/// `brute` while the trees and DACRT, whose boxes lay behind the ray, missed it (session 30's
/// batch-dependent DACRT `t = 0` hit beside such a grid likely came from it). Such lanes are decided again with their coordinates scaled, as those whose
/// products overflow are. Last, planes 2^-149 (the smallest subnormal) before and behind
/// the origin: the t numerator underflows to ±0 in the paper's test; the one behind is
/// missed, the one before hit at t = +0 (`watertight`, whose reported t is the refined one)
/// or at the smallest subnormal (`fast`, whose t 2^-151 rounds away from zero). `fast`,
/// whose products are of three coordinates, underflowed alike (its determinant too: such
/// grids were missed) until session 36 decided its out-of-range lanes again in f64.
#[test]
fn triangles_whose_products_underflow_are_decided_as_larger_ones() {
    for precision in PRECISIONS {
        products_underflow(precision);
    }
}

fn products_underflow(precision: Precision) {
    let grid = |n: usize, side: f32, z: f32, tilt: f32| {
        let mut tris = Vec::new();
        let at = |i: usize, j: usize| {
            let (x, y) = (i as f32 * side, j as f32 * side);
            [x, y, z * side + tilt * x]
        };
        for i in 0..n {
            for j in 0..n {
                let [a, b, c, d] = [at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)];
                tris.push(Triangle { v: [a, b, c] });
                tris.push(Triangle { v: [a, c, d] });
            }
        }
        tris
    };
    let exact_cores = exact_cores();
    let mut rng = Rng(0x5ca1e);
    let mut small_grid_hits = 0;
    let mut rays_traced = 0;
    for side in [1e-18f32, 1e-22, 1e-30, 1e-36] {
        for case in 0..8 {
            // Moved so that its vertex `at` (the first of cell `at`) is the origin.
            let moved = |tris: Vec<Triangle>, at: usize| {
                let o = tris[2 * at].v[0];
                tris.into_iter()
                    .map(|t| Triangle {
                        v: t.v.map(|p| [p[0] - o[0], p[1] - o[1], p[2] - o[2]]),
                    })
                    .collect::<Vec<_>>()
            };
            let mut tris = grid(4, side, rng.sym(), 0.3 * rng.sym());
            if case % 4 >= 2 {
                // The small grid through the origin too (session 30's case).
                tris = moved(tris, 0);
            }
            if case % 2 == 1 {
                // The 1e30 grid, one of its vertices at the origin.
                tris.extend(moved(grid(3, 1e30, 0.5 * rng.sym(), 0.3), case / 2 % 9));
            }
            let rays: Vec<Ray> = (0..256)
                .map(|k| {
                    let org = match k % 3 {
                        0 => [0.0; 3],
                        1 => [
                            4.0 * side * rng.unit(),
                            4.0 * side * rng.unit(),
                            2.0 * side * rng.sym(),
                        ],
                        _ => rng.vec(10.0 * side),
                    };
                    ray(org, [rng.sym(), rng.sym(), rng.sym()], 0.0, f32::INFINITY)
                })
                .collect();
            // Every core bit for bit `brute`'s, each hit within the f64 oracle's bounds (a
            // hit at t = 0 on a plane 1e-18 behind the origin is not).
            let hits = cores(&exact_cores, precision, &tris, &rays);
            // And no miss: where the oracle's closest hit is on the small grid (its first 32
            // triangles), away from an edge, that is the hit. (Beside the 1e30 grid, whose
            // decision t errs by ~1e22, a hit on it may win by proto/semantics.md's ordering
            // caveat: scaled, a vertex 1e-18 from the origin is 2^-159 of the largest
            // coordinate, flushed to 0.)
            let beside_huge = case % 2 == 1;
            for (r, h) in rays.iter().zip(&hits).filter(|_| !beside_huge) {
                let Some((id, o)) = oracle_closest_f64(r, &tris) else {
                    continue;
                };
                if id < 32 && o.u.min(o.v).min(1.0 - o.u - o.v) > 1e-3 {
                    assert_eq!(
                        h.prim, id,
                        "side {side:e}: {r:?} -> {h:?}, the oracle {o:?}"
                    );
                    small_grid_hits += 1;
                }
            }
            rays_traced += rays.len();
        }
    }
    assert!(
        small_grid_hits > rays_traced / 32,
        "{small_grid_hits} hits on the small grids of {rays_traced} rays"
    );
    let tiny = f32::from_bits(1);
    for (z, hits) in [(-tiny, false), (tiny, true)] {
        let tris = vec![Triangle {
            v: [[-1.0, -1.0, z], [2.0, -1.0, z], [-1.0, 2.0, z]],
        }];
        let rays = [ray([0.0; 3], [0.0, 0.0, 4.0], 0.0, f32::INFINITY)];
        let h = cores(&exact_cores, precision, &tris, &rays)[0];
        assert_eq!(h.is_hit(), hits, "plane at z = {z:e}: {h:?}");
        let t_bits = match precision {
            Precision::Watertight => 0,
            Precision::Fast => 1,
        };
        assert!(!hits || h.t.to_bits() == t_bits, "{h:?}");
    }
}

/// Clusters of triangles from 1e-35 to 1e35 across, centred at the origin or up to 1e35
/// from it, side by side, and rays from in and around them with directions of 1e-30 to
/// 1e30 (a third aimed at a triangle). Every core gives `brute`'s closest hits bit for bit,
/// each within the f64 oracle's bounds, and `any` agrees on hit and miss. Before session
/// 35 a determinant that overflowed (1e19 triangles, directions of 1e18) made the paper's
/// t `tt · 0 = -0`: `brute` hit a plane 0.28 behind the origin at t = 0 while the trees
/// missed it; lanes whose t, numerator or determinant is not a normal number are now
/// decided again scaled. `fast` (session 36) likewise, its lanes decided again in f64; a
/// triangle below f64's resolution at its distance from the origin, which only `fast`
/// hits, is checked to lie within rounding of the hit (`check_hit`).
#[test]
fn clusters_at_every_scale_keep_every_core_exact() {
    for precision in PRECISIONS {
        clusters_at_every_scale(precision);
    }
}

fn clusters_at_every_scale(precision: Precision) {
    let exact_cores = exact_cores();
    let mut rng = Rng(0x5ca1e5);
    let pow10 =
        |rng: &mut Rng, lo: f32, hi: f32| 10f64.powf(f64::from(lo + (hi - lo) * rng.unit()));
    let (mut traced, mut hit) = (0, 0);
    for _case in 0..48 {
        let mut tris = Vec::new();
        let mut clusters = Vec::new();
        for _ in 0..1 + rng.next() % 4 {
            let c = if rng.next().is_multiple_of(3) {
                [0.0; 3]
            } else {
                let m = pow10(&mut rng, -35.0, 35.0);
                [0; 3].map(|_| m * f64::from(rng.sym()))
            };
            let size = pow10(&mut rng, -35.0, 35.0);
            for _ in 0..1 + rng.next() % 30 {
                let v =
                    [0; 3].map(|_| [0, 1, 2].map(|k| (c[k] + size * f64::from(rng.sym())) as f32));
                let t = Triangle { v };
                if !t.is_degenerate() && v.iter().flatten().all(|x| x.is_finite()) {
                    tris.push(t);
                }
            }
            clusters.push((c, size));
        }
        if tris.is_empty() {
            continue;
        }
        let mut rays = Vec::new();
        for _ in 0..128 {
            let (c, size) = clusters[rng.next() as usize % clusters.len()];
            let off = size * pow10(&mut rng, -3.0, 3.0);
            let org = match rng.next() % 4 {
                0 => [0.0; 3],
                _ => [0, 1, 2].map(|k| (c[k] + off * f64::from(rng.sym())) as f32),
            };
            let dir = if rng.next().is_multiple_of(3) {
                let t = &tris[rng.next() as usize % tris.len()];
                let w = [rng.unit(), rng.unit(), rng.unit()].map(f64::from);
                let total = w[0] + w[1] + w[2];
                [0, 1, 2].map(|k| {
                    let p = (0..3).map(|i| f64::from(t.v[i][k]) * w[i]).sum::<f64>() / total;
                    (p - f64::from(org[k])) as f32
                })
            } else {
                let m = if rng.next().is_multiple_of(4) {
                    pow10(&mut rng, -30.0, 30.0)
                } else {
                    1.0
                };
                [0; 3].map(|_| (m * f64::from(rng.sym())) as f32)
            };
            if dir.iter().any(|&d| d != 0.0) && dir.iter().all(|d| d.is_finite()) {
                rays.push(ray(org, dir, 0.0, f32::INFINITY));
            }
        }
        let closest = cores(&exact_cores, precision, &tris, &rays);
        for &kind in &exact_cores {
            let any = trace_q(kind, BuildQuality::Sah, precision, &tris, &rays, Query::Any);
            for (i, (a, c)) in any.iter().zip(&closest).enumerate() {
                assert_eq!(
                    a.is_hit(),
                    c.is_hit(),
                    "{} any, ray {i}: {:?}",
                    kind.name(),
                    rays[i]
                );
            }
        }
        traced += rays.len();
        hit += closest.iter().filter(|h| h.is_hit()).count();
    }
    assert!(hit > traced / 4, "{hit} hits of {traced} rays");
}

/// Directions of 1e-39–1e-35 (hits at t up to ~1e39, some beyond f32's range) and a scene
/// at 2^120. The trees' fused slab test (`plane·inv − org·inv`) overflowed its products
/// long before the distances did, and `mbvh4`/`mbvh8` missed hits every other core found;
/// `bvh2`'s and DACRT's reciprocals of subnormal components were infinite; and every core,
/// `brute` included, lost hits at t ~3.3e38 (the decision t's entry and the shear
/// overflowed). Every core now tests a direction below 2^-64 as its scaled twin
/// (`accel::tiny_dir`), under both precisions.
#[test]
fn tiny_directions_and_huge_scenes_keep_every_core_exact() {
    let mut rng = Rng(0x7153);
    let sphere = icosphere(3, 1.0, [0.2, -0.1, 0.3]);
    let targets = edge_and_vertex_targets(&sphere);
    let mut rays = Vec::new();
    for scale in [3e-39f32, 1e-38, 1.2e-38, 1e-36, 4e-35] {
        for r in inward_rays(&mut rng, &targets[..200], [0.2, -0.1, 0.3], 4.0) {
            let dir = r.dir.map(|d| d * scale);
            if dir.iter().any(|&d| d != 0.0) {
                rays.push(ray(r.org, dir, 0.0, f32::INFINITY));
            }
        }
    }
    let hits = all_cores(Precision::Watertight, &sphere, &rays);
    assert!(hits.iter().filter(|h| h.t.is_finite()).count() > rays.len() / 4);
    // Hits just inside f32's range: every core lost these (at t ~3.3e38) while it took
    // `1/dir` and the shear of directions of ~3e-39 as they were.
    let near_max = hits
        .iter()
        .filter(|h| h.t > 3e38 && h.t.is_finite())
        .count();
    assert!(near_max > 100, "{near_max}");
    let fast = all_cores(Precision::Fast, &sphere, &rays);
    assert!(
        fast.iter()
            .filter(|h| h.t > 3e38 && h.t.is_finite())
            .count()
            > 100
    );
    // A sphere of radius 2^90 about a centre 2^100 away, rays of |dir| ~2^-34 from 3
    // radii out: hits at t ~2^125, but |origin| · |1/dir| is ~2^134.
    let big = 2f64.powi(100);
    let centre = [0.5 * big, -0.75 * big, big];
    let sphere = icosphere(2, 2f64.powi(90), centre);
    let c = centre.map(|x| x as f32);
    let mut rays = Vec::new();
    for p in edge_and_vertex_targets(&sphere).into_iter().take(600) {
        let org: [f32; 3] = std::array::from_fn(|k| c[k] + 3.0 * (p[k] - c[k]));
        let dir = std::array::from_fn(|k| (p[k] - org[k]) * 2f32.powi(-125));
        rays.push(ray(org, dir, 0.0, f32::INFINITY));
    }
    let hits = all_cores(Precision::Watertight, &sphere, &rays);
    let hit = hits.iter().filter(|h| h.t.is_finite()).count();
    assert!(hit > rays.len() / 2, "{hit} of {}", rays.len());
}
