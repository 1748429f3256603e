//! `Intersector::refit`: an accelerator built on positions A and refitted to positions B
//! answers as one built on B.
//!
//! The BVH cores (`mbvh8`, `mbvh4`, `bvh2`, every build quality, both precisions) are
//! compared with `brute` built on B, bit for bit, as `bvh_agree` compares fresh builds
//! (with the same exemption: under `precision=fast` a hit on a sliver may be missed, since
//! Möller–Trumbore's t on slivers, or on grazing rays, can put the hit point outside the
//! triangle's box; fresh builds miss those too). `dacrt` and
//! `dacrt-sampled` are compared with a fresh DACRT on B (their refit is their build) and,
//! under the watertight test, with `brute`.
//!
//! Positions B keep A's triangle count and which triangles are degenerate, and are made
//! to stress the refit: small jitter, a common motion, a far translation and a large
//! scaling (the slab test's `scale` must follow), triangles jumping across the scene (very
//! loose boxes), and a whole new soup. Refusals (another count, a triangle becoming
//! degenerate, a degenerate one becoming a triangle) must leave the old answers intact.
//! A real animated scene is refitted from time 0 to later times, and a soup through 20
//! successive refits.

mod common;

use common::{add, bits, unreliable, Rng};
use proptest::prelude::*;
use rayd::accel::bvh::RefitError;
use rayd::accel::triangle::intersect;
use rayd::accel::{build, AccelError, AccelKind, BuildOptions, BuildQuality, Intersector};
use rayd::accel::{Precision, Query};
use rayd::geometry::{Hit, Ray, Triangle};

const QUALITIES: [BuildQuality; 3] = [BuildQuality::Fast, BuildQuality::Sah, BuildQuality::Sbvh];
const TREES: [AccelKind; 3] = [AccelKind::Mbvh8, AccelKind::Mbvh4, AccelKind::Bvh2];
const PRECISIONS: [Precision; 2] = [Precision::Watertight, Precision::Fast];

/// A random soup of about `n` triangles: ordinary, degenerate, tiny, huge, axis-aligned
/// on integer corners, and bursts of exact duplicates (ties across leaves).
fn soup(rng: &mut Rng, n: usize) -> Vec<Triangle> {
    let mut tris: Vec<Triangle> = Vec::with_capacity(n + 32);
    while tris.len() < n {
        match rng.pick(9) {
            0 => {
                let a = rng.vec(5.0);
                let d = rng.vec(1.0);
                let v = if rng.pick(2) == 0 {
                    [a, a, a]
                } else {
                    [a, add(a, d), add(a, add(d, d))]
                };
                tris.push(Triangle { v });
            }
            1 => {
                let c = rng.vec(5.0);
                let s = 10f32.powf(-2.0 - 2.0 * rng.unit());
                tris.push(Triangle {
                    v: [add(c, rng.vec(s)), add(c, rng.vec(s)), add(c, rng.vec(s))],
                });
            }
            2 => tris.push(Triangle {
                v: [rng.vec(50.0), rng.vec(50.0), rng.vec(50.0)],
            }),
            3 if !tris.is_empty() => {
                let t = tris[rng.pick(tris.len())];
                for _ in 0..1 + rng.pick(20) {
                    tris.push(t);
                }
            }
            4 | 5 => {
                let c = rng.vec(5.0).map(|x| x.round());
                let axis = rng.pick(3);
                let (mut b, mut d) = (c, c);
                b[(axis + 1) % 3] += 1.0 + rng.pick(3) as f32;
                d[(axis + 2) % 3] += 1.0 + rng.pick(3) as f32;
                tris.push(Triangle { v: [c, b, d] });
            }
            _ => {
                let c = rng.vec(5.0);
                tris.push(Triangle {
                    v: [
                        add(c, rng.vec(1.0)),
                        add(c, rng.vec(1.0)),
                        add(c, rng.vec(1.0)),
                    ],
                });
            }
        }
    }
    tris
}

/// Whether a tree keeps `t` (see `bvh::is_traceable`).
fn traceable(t: &Triangle) -> bool {
    t.v.iter().flatten().all(|x| x.is_finite()) && !t.is_degenerate()
}

/// New positions for `a` (same count, same degeneracy), by one of several motions.
fn moved(rng: &mut Rng, a: &[Triangle]) -> Vec<Triangle> {
    let mode = rng.pick(6);
    let shift = rng.vec(3.0);
    let far = rng.vec(1e5);
    let other = soup(rng, a.len());
    a.iter()
        .enumerate()
        .map(|(i, t)| {
            let b = match mode {
                // Jitter every vertex.
                0 => Triangle {
                    v: t.v.map(|p| add(p, rng.vec(0.05))),
                },
                // A common motion plus jitter.
                1 => Triangle {
                    v: t.v.map(|p| add(add(p, shift), rng.vec(0.01))),
                },
                // Far away: the slab test's scale must grow.
                2 => Triangle {
                    v: t.v.map(|p| add(p, far)),
                },
                // Scaled up a thousand times.
                3 => Triangle {
                    v: t.v.map(|p| p.map(|x| x * 1e3)),
                },
                // Some triangles jump across the scene.
                4 if rng.pick(8) == 0 => {
                    let d = rng.vec(10.0);
                    Triangle {
                        v: t.v.map(|p| add(p, d)),
                    }
                }
                4 => *t,
                // A whole new soup, triangle by triangle.
                _ => other[i],
            };
            if traceable(&b) == traceable(t) {
                b
            } else {
                *t
            }
        })
        .collect()
}

/// Rays aimed at vertices, edges and interiors of `tris`, some axis-parallel with ±0
/// components, some with finite intervals.
fn rays(rng: &mut Rng, tris: &[Triangle], n: usize) -> Vec<Ray> {
    let mut out = Vec::with_capacity(n);
    while out.len() < n {
        let target = if tris.is_empty() || rng.pick(6) == 0 {
            rng.vec(10.0)
        } else {
            let t = tris[rng.pick(tris.len())];
            let (u, v) = match rng.pick(3) {
                0 => [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)][rng.pick(3)],
                1 => {
                    let a = rng.unit();
                    [(a, 0.0), (0.0, a), (a, 1.0 - a)][rng.pick(3)]
                }
                _ => (rng.unit() * 0.5, rng.unit() * 0.5),
            };
            std::array::from_fn(|k| (1.0 - u - v) * t.v[0][k] + u * t.v[1][k] + v * t.v[2][k])
        };
        let span = target.iter().fold(10.0f32, |m, x| m.max(x.abs()));
        let (org, dir) = match rng.pick(7) {
            0 => {
                let axis = rng.pick(3);
                let sign = if rng.pick(2) == 0 { 1.0 } else { -1.0 };
                let mut dir = [if rng.pick(2) == 0 { 0.0 } else { -0.0 }; 3];
                dir[axis] = sign;
                let mut org = target;
                org[axis] -= dir[axis] * span * rng.unit();
                (org, dir)
            }
            1 => (target, rng.vec(1.0)),
            // From near the world origin: with far geometry, only the tree's `scale`
            // (not the origin) makes the slab test's growth large enough.
            2 => {
                let org = rng.vec(1.0);
                (org, std::array::from_fn(|k| target[k] - org[k]))
            }
            _ => {
                let org = add(target, rng.vec(span));
                (org, std::array::from_fn(|k| target[k] - org[k]))
            }
        };
        let tmax = match rng.pick(4) {
            0 => rng.unit() * 2.0,
            _ => f32::INFINITY,
        };
        let r = Ray {
            org,
            tmin: 0.0,
            dir,
            tmax,
        };
        if r.check().is_ok() {
            out.push(r);
        }
    }
    out
}

fn make(
    kind: AccelKind,
    tris: &[Triangle],
    quality: BuildQuality,
    p: Precision,
) -> Box<dyn Intersector> {
    let o = BuildOptions {
        quality,
        precision: p,
        threads: 0,
        ..BuildOptions::default()
    };
    build(kind, tris, &o).expect("builds")
}

/// All answers of `core` on `rays`: closest, any, occluded.
fn answers(core: &dyn Intersector, rays: &[Ray]) -> (Vec<Hit>, Vec<Hit>, Vec<u8>) {
    let mut closest = vec![Hit::MISS; rays.len()];
    let mut any = vec![Hit::MISS; rays.len()];
    let mut occ = vec![0u8; rays.len()];
    core.trace(rays, Query::Closest, &mut closest);
    core.trace(rays, Query::Any, &mut any);
    core.occluded(rays, &mut occ);
    (closest, any, occ)
}

/// Checks a BVH core against `brute` on `tris` (its current positions).
fn agrees_with_brute(
    name: &str,
    core: &dyn Intersector,
    tris: &[Triangle],
    rays: &[Ray],
    p: Precision,
) -> Result<(), String> {
    let brute = make(AccelKind::Brute, tris, BuildQuality::Sah, p);
    // Each ray that hits is traced again with `tmin`, then `tmax`, exactly at its hit.
    let mut all = rays.to_vec();
    let (first, _, _) = answers(&*brute, rays);
    for (r, h) in rays.iter().zip(&first) {
        if h.is_hit() {
            all.push(Ray { tmin: h.t, ..*r });
            all.push(Ray { tmax: h.t, ..*r });
        }
    }
    let rays = &all[..];
    let (want, _, want_occ) = answers(&*brute, rays);
    let (closest, any, occ) = answers(core, rays);
    // Under `fast`, whether every triangle the ray hits is exempt (then a core may miss).
    let only_exempt = |r: &Ray| {
        p == Precision::Fast
            && tris.iter().all(|t| match intersect(p, r, t) {
                Some(x) => unreliable(t, r, x.t),
                None => true,
            })
    };
    for (i, r) in rays.iter().enumerate() {
        let (h, w) = (&closest[i], &want[i]);
        let exempt = p == Precision::Fast
            && w.is_hit()
            && unreliable(&tris[w.prim as usize], r, w.t)
            && h.t >= w.t;
        if bits(h) != bits(w) && !exempt {
            return Err(format!(
                "{name}: closest of ray {i} {r:?}: got {h:?}, brute {w:?}"
            ));
        }
        let a = &any[i];
        if a.is_hit() != (want_occ[i] != 0) && !only_exempt(r) {
            return Err(format!(
                "{name}: any of ray {i} {r:?}: got {a:?}, brute {w:?}"
            ));
        }
        if a.is_hit() {
            let again = intersect(p, r, &tris[a.prim as usize])
                .map(|x| [x.t.to_bits(), a.prim, x.u.to_bits(), x.v.to_bits()]);
            if again != Some(bits(a)) {
                return Err(format!("{name}: any of ray {i} reports {a:?}, not a hit"));
            }
        }
        if occ[i] != want_occ[i] && !only_exempt(r) {
            return Err(format!("{name}: occluded of ray {i} {r:?}: got {}", occ[i]));
        }
    }
    Ok(())
}

/// Builds every BVH core on `a`, refits it to `b`, and compares it with `brute` on `b`.
fn trees_refit(a: &[Triangle], b: &[Triangle], rays: &[Ray], p: Precision) -> Result<(), String> {
    for kind in TREES {
        for q in QUALITIES {
            let name = format!("{}/{}/{}", kind.name(), q.name(), p.name());
            let mut core = make(kind, a, q, p);
            core.refit(b)
                .map_err(|e| format!("{name}: refit refused: {e}"))?;
            agrees_with_brute(&name, &*core, b, rays, p)?;
        }
    }
    Ok(())
}

/// Builds DACRT on `a`, refits it to `b`, and compares it with a fresh DACRT on `b` (and
/// under the watertight test with `brute`).
fn dacrt_refit(a: &[Triangle], b: &[Triangle], rays: &[Ray], p: Precision) -> Result<(), String> {
    for kind in [AccelKind::Dacrt, AccelKind::DacrtSampled] {
        let mut core = make(kind, a, BuildQuality::Sah, p);
        core.refit(b)
            .map_err(|e| format!("{}: refused: {e}", kind.name()))?;
        let fresh = make(kind, b, BuildQuality::Sah, p);
        let (c, any, occ) = answers(&*core, rays);
        let (wc, wany, wocc) = answers(&*fresh, rays);
        for i in 0..rays.len() {
            if bits(&c[i]) != bits(&wc[i])
                || any[i].is_hit() != wany[i].is_hit()
                || occ[i] != wocc[i]
            {
                return Err(format!(
                    "{}/{}: ray {i} {:?}: refitted {:?}/{}/{}, fresh {:?}/{}/{}",
                    kind.name(),
                    p.name(),
                    rays[i],
                    c[i],
                    any[i].is_hit(),
                    occ[i],
                    wc[i],
                    wany[i].is_hit(),
                    wocc[i]
                ));
            }
        }
        if p == Precision::Watertight {
            let brute = make(AccelKind::Brute, b, BuildQuality::Sah, p);
            let (want, _, _) = answers(&*brute, rays);
            if let Some(i) = (0..rays.len()).find(|&i| bits(&c[i]) != bits(&want[i])) {
                return Err(format!(
                    "{}: ray {i}: {:?} vs brute {:?}",
                    kind.name(),
                    c[i],
                    want[i]
                ));
            }
        }
    }
    Ok(())
}

/// One case of `refitted_trees_agree_with_brute`: `n` triangles from `seed`, moved, and
/// 300 rays at them, under every precision.
fn trees_case(seed: u64, n: usize) -> Result<(), String> {
    let mut rng = Rng(seed);
    let a = soup(&mut rng, n);
    let b = moved(&mut rng, &a);
    let rays = rays(&mut rng, &b, 300);
    PRECISIONS
        .into_iter()
        .try_for_each(|p| trees_refit(&a, &b, &rays, p))
}

/// The case CI's run of stop 15 found (proptest picks new seeds every run, so it is kept
/// here): copies of one sliver, hit at the same t, where a refitted `mbvh4` under
/// `watertight` answered with the higher id.
#[test]
fn refit_case_of_stop_15() {
    assert_eq!(trees_case(11310695319153505695, 208), Ok(()));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Every BVH core refitted to new positions answers as brute on them.
    #[test]
    fn refitted_trees_agree_with_brute(seed in any::<u64>(), n in 0usize..400) {
        prop_assert_eq!(trees_case(seed, n), Ok(()));
    }

    /// DACRT's refit (its precompute) answers as a fresh DACRT and brute.
    #[test]
    fn refitted_dacrt_agrees(seed in any::<u64>(), n in 0usize..300) {
        let mut rng = Rng(seed);
        let a = soup(&mut rng, n);
        let b = moved(&mut rng, &a);
        let rays = rays(&mut rng, &b, 200);
        for p in PRECISIONS {
            prop_assert_eq!(dacrt_refit(&a, &b, &rays, p), Ok(()));
        }
    }
}

/// Every accelerator of this build.
fn all_kinds() -> Vec<AccelKind> {
    AccelKind::ALL
        .into_iter()
        .filter(|k| *k != AccelKind::Auto && k.available())
        .collect()
}

fn refit_reason(e: AccelError) -> RefitError {
    match e {
        AccelError::Refit { reason, .. } => reason,
        other => panic!("not a refit refusal: {other}"),
    }
}

#[test]
fn refusals_leave_the_old_answers() {
    let mut rng = Rng(7);
    let a: Vec<Triangle> = soup(&mut rng, 300)
        .into_iter()
        .filter(traceable)
        .chain([Triangle {
            v: [[1.0, 2.0, 3.0]; 3],
        }])
        .collect();
    let degenerate = (a.len() - 1) as u32;
    let live = 5u32;
    let rays = rays(&mut rng, &a, 400);
    let mut longer = a.clone();
    longer.push(a[0]);
    let mut dies = a.clone();
    dies[live as usize] = Triangle {
        v: [[0.5, 0.5, 0.5]; 3],
    };
    let mut wakes = a.clone();
    wakes[degenerate as usize] = Triangle {
        v: [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
    };
    for kind in all_kinds() {
        for q in QUALITIES {
            let mut core = make(kind, &a, q, Precision::Watertight);
            let before = answers(&*core, &rays);
            let name = format!("{}/{}", kind.name(), q.name());
            let count = refit_reason(core.refit(&a[1..]).expect_err(&name));
            assert_eq!(
                count,
                RefitError::Count {
                    expected: a.len(),
                    got: a.len() - 1
                },
                "{name}"
            );
            let count = refit_reason(core.refit(&longer).expect_err(&name));
            assert!(matches!(count, RefitError::Count { .. }), "{name}");
            // Brute, DACRT and Embree have no topology to keep: degeneracy may change.
            if TREES.contains(&kind) {
                let e = refit_reason(core.refit(&dies).expect_err(&name));
                assert_eq!(e, RefitError::Degeneracy { id: live }, "{name}");
                let e = refit_reason(core.refit(&wakes).expect_err(&name));
                assert_eq!(e, RefitError::Degeneracy { id: degenerate }, "{name}");
            }
            let after = answers(&*core, &rays);
            assert_eq!(
                before.2, after.2,
                "{name}: occlusion changed after refusals"
            );
            for (x, y) in before.0.iter().zip(&after.0) {
                assert_eq!(bits(x), bits(y), "{name}: closest changed after refusals");
            }
        }
    }
}

#[test]
fn accepted_degeneracy_changes_where_there_is_no_topology() {
    let mut rng = Rng(11);
    let a: Vec<Triangle> = soup(&mut rng, 200);
    let mut b = moved(&mut rng, &a);
    b[3] = Triangle {
        v: [[0.5, 0.5, 0.5]; 3],
    };
    b[4] = Triangle {
        v: [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
    };
    let rays = rays(&mut rng, &b, 300);
    let brute = make(
        AccelKind::Brute,
        &b,
        BuildQuality::Sah,
        Precision::Watertight,
    );
    let want = answers(&*brute, &rays).0;
    for kind in [AccelKind::Brute, AccelKind::Dacrt, AccelKind::DacrtSampled] {
        let mut core = make(kind, &a, BuildQuality::Sah, Precision::Watertight);
        core.refit(&b).expect("accepted");
        let got = answers(&*core, &rays).0;
        for (i, (g, w)) in got.iter().zip(&want).enumerate() {
            assert_eq!(bits(g), bits(w), "{}: ray {i}", kind.name());
        }
    }
}

#[test]
fn twenty_successive_refits_still_agree() {
    let mut rng = Rng(99);
    let mut pos = soup(&mut rng, 600);
    for p in PRECISIONS {
        let mut cores: Vec<(String, Box<dyn Intersector>)> = Vec::new();
        for kind in TREES {
            for q in QUALITIES {
                cores.push((
                    format!("{}/{}", kind.name(), q.name()),
                    make(kind, &pos, q, p),
                ));
            }
        }
        for kind in [AccelKind::Dacrt, AccelKind::Brute] {
            cores.push((kind.name().into(), make(kind, &pos, BuildQuality::Sah, p)));
        }
        for step in 0..20 {
            // Mostly small steps, with an occasional jump.
            pos = if step % 7 == 6 {
                moved(&mut rng, &pos)
            } else {
                pos.iter()
                    .map(|t| {
                        let b = Triangle {
                            v: t.v.map(|v| add(v, rng.vec(0.2))),
                        };
                        if traceable(&b) == traceable(t) {
                            b
                        } else {
                            *t
                        }
                    })
                    .collect()
            };
            for (name, core) in &mut cores {
                core.refit(&pos)
                    .unwrap_or_else(|e| panic!("{name} step {step}: {e}"));
            }
            if step % 5 == 4 {
                let rays = rays(&mut rng, &pos, 400);
                for (name, core) in &cores {
                    let name = format!("{name}/{} step {step}", p.name());
                    agrees_with_brute(&name, &**core, &pos, &rays, p).unwrap();
                }
            }
        }
    }
}

/// Loads `path` at animation time `t` (None when the file is absent).
fn load_at(path: &std::path::Path, t: f64) -> Option<Vec<Triangle>> {
    if !path.exists() {
        eprintln!("skipping {}: not present", path.display());
        return None;
    }
    let opts = rayd::formats::LoadOptions { time: Some(t) };
    Some(
        rayd::formats::load_scene(path, &opts)
            .expect("loads")
            .triangles,
    )
}

/// Refits every core from time 0 to later times of an animated scene.
fn animated(path: &std::path::Path, times: &[f64]) {
    let Some(first) = load_at(path, 0.0) else {
        return;
    };
    let mut rng = Rng(3);
    for p in PRECISIONS {
        let mut cores: Vec<(String, Box<dyn Intersector>)> = Vec::new();
        for kind in all_kinds() {
            for q in QUALITIES {
                if q != BuildQuality::Sah && !TREES.contains(&kind) {
                    continue;
                }
                let name = format!("{}/{}/{}", kind.name(), q.name(), p.name());
                cores.push((name, make(kind, &first, q, p)));
            }
        }
        for &t in times {
            let tris = load_at(path, t).expect("present");
            assert_eq!(tris.len(), first.len());
            let same_set = tris
                .iter()
                .zip(&first)
                .all(|(x, y)| traceable(x) == traceable(y));
            let rays = rays(&mut rng, &tris, 1500);
            for (name, core) in &mut cores {
                match core.refit(&tris) {
                    Ok(()) => {}
                    Err(AccelError::Refit {
                        reason: RefitError::Degeneracy { .. },
                        ..
                    }) if !same_set => continue,
                    Err(e) => panic!("{name} at t={t}: {e}"),
                }
                if name.starts_with("embree") {
                    // A peer with its own interval and tie rules: compared with a fresh
                    // Embree on the new positions.
                    let fresh = make(AccelKind::Embree, &tris, BuildQuality::Sah, p);
                    let (want, _, want_occ) = answers(&*fresh, &rays);
                    let (got, _, occ) = answers(&**core, &rays);
                    let differ = (0..rays.len())
                        .filter(|&i| occ[i] != want_occ[i] || got[i].prim != want[i].prim)
                        .count();
                    eprintln!("{name} at t={t}: {differ} of {} differ", rays.len());
                    assert!(
                        differ * 200 <= rays.len(),
                        "{name} at t={t}: {differ} differ"
                    );
                } else {
                    agrees_with_brute(&format!("{name} t={t}"), &**core, &tris, &rays, p).unwrap();
                }
            }
        }
    }
}

#[test]
fn animated_fox_refits_agree_with_brute() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    animated(&dir.join("scenes/Fox.glb"), &[0.4, 1.1, 2.5, 3.3]);
}

#[test]
fn animated_shared_cesium_man_refits_agree_with_brute() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    animated(
        &dir.join("../shared/scenes/CesiumMan.glb"),
        &[0.5, 1.2, 1.9],
    );
}

/// Build and refit times on a shared scene (the dragon by default), same run, 1 and 2
/// threads; prints a table. Wall-clock figures: compare them only within one run.
///
/// ```text
/// RAYD_REFIT_SCENE=path/to/dragon.glb cargo test --release --features embree \
///     --test refit -- --ignored refit_timings --nocapture
/// ```
#[test]
#[ignore]
fn refit_timings() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let path = std::env::var("RAYD_REFIT_SCENE").map_or_else(
        |_| dir.join("../shared/scenes/dragon-100k.from-ply.glb"),
        std::path::PathBuf::from,
    );
    if !path.exists() {
        eprintln!("skipping: {} not present", path.display());
        return;
    }
    let a = rayd::formats::load_scene(&path, &Default::default())
        .expect("loads")
        .triangles;
    let mut rng = Rng(5);
    let b: Vec<Triangle> = a
        .iter()
        .map(|t| {
            let m = Triangle {
                v: t.v.map(|v| add(v, rng.vec(1e-3))),
            };
            if traceable(&m) == traceable(t) {
                m
            } else {
                *t
            }
        })
        .collect();
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    eprintln!("{} triangles: {}", a.len(), path.display());
    eprintln!("accel       quality threads  build ms  refit ms  ratio");
    for threads in [1, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("pool");
        pool.install(|| {
            for kind in all_kinds() {
                if kind == AccelKind::Brute || kind == AccelKind::DacrtSampled {
                    continue;
                }
                let o = BuildOptions {
                    quality: BuildQuality::Sah,
                    precision: Precision::Watertight,
                    threads,
                    ..BuildOptions::default()
                };
                let mut builds = Vec::new();
                let mut core = None;
                for _ in 0..3 {
                    let t0 = std::time::Instant::now();
                    let c = build(kind, &a, &o).expect("builds");
                    builds.push(t0.elapsed().as_secs_f64() * 1e3);
                    core = Some(c);
                }
                let mut core = core.expect("built");
                let mut refits = Vec::new();
                for i in 0..5 {
                    let t0 = std::time::Instant::now();
                    core.refit(if i % 2 == 0 { &b } else { &a })
                        .expect("refits");
                    refits.push(t0.elapsed().as_secs_f64() * 1e3);
                }
                let (bm, rm) = (median(builds), median(refits));
                eprintln!(
                    "{:<11} {:<7} {threads:>7} {bm:>9.2} {rm:>9.2} {:>6.1}",
                    kind.name(),
                    o.quality.name(),
                    bm / rm
                );
            }
        });
    }
}
