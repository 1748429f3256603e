//! End-to-end tests of the `rayd` binary: the contract's command line, formats and errors.

use std::path::{Path, PathBuf};
use std::process::Command;

use rayd::formats::binary::{read_hits, write_rays, write_tri, HitFormat};
use rayd::geometry::{Hit, Ray, Triangle};

fn rayd(args: &[&str]) -> (bool, serde_json::Value, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_rayd"))
        .args(args)
        .output()
        .expect("runs");
    let stdout = String::from_utf8_lossy(&out.stdout).to_string();
    let stderr = String::from_utf8_lossy(&out.stderr).to_string();
    let json = serde_json::from_str(stdout.trim()).unwrap_or(serde_json::Value::Null);
    (out.status.success(), json, stderr)
}

fn p(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// A unit quad in the z = 0 plane made of two triangles, plus a degenerate one.
fn quad_scene(dir: &Path) -> PathBuf {
    let tris = vec![
        Triangle {
            v: [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
        },
        Triangle {
            v: [[1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]],
        },
        Triangle {
            v: [[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [2.0, 2.0, 0.0]],
        },
    ];
    let path = dir.join("quad.tri");
    std::fs::write(&path, write_tri(&tris)).unwrap();
    path
}

fn down(x: f32, y: f32) -> Ray {
    Ray {
        org: [x, y, 1.0],
        tmin: 0.0,
        dir: [0.0, 0.0, -1.0],
        tmax: f32::INFINITY,
    }
}

#[test]
fn info_reports_the_contract_fields() {
    let dir = tempfile::tempdir().unwrap();
    let scene = quad_scene(dir.path());
    let (ok, j, err) = rayd(&["info", p(&scene)]);
    assert!(ok, "{err}");
    assert_eq!(j["triangles"], 3);
    assert_eq!(j["bounds"]["min"], serde_json::json!([0.0, 0.0, 0.0]));
    assert_eq!(j["bounds"]["max"], serde_json::json!([2.0, 2.0, 0.0]));
    assert_eq!(j["meshes"], 0);
    assert_eq!(j["cameras"], 0);
    assert_eq!(j["animations"], serde_json::json!([]));
    assert_eq!(j["bytes"], 3 * 36);
    assert!(["avx2", "sse", "scalar"].contains(&j["simd"].as_str().unwrap()));
}

#[test]
fn trace_writes_every_hit_format() {
    let dir = tempfile::tempdir().unwrap();
    let scene = quad_scene(dir.path());
    let rays = vec![
        down(0.25, 0.25),
        down(0.75, 0.75),
        down(3.0, 3.0),
        Ray {
            tmax: 0.5,
            ..down(0.25, 0.25)
        },
        Ray {
            tmin: 2.0,
            tmax: 1.0,
            ..down(0.25, 0.25)
        },
    ];
    let ray_path = dir.path().join("in.ray");
    std::fs::write(&ray_path, write_rays(&rays)).unwrap();
    for format in HitFormat::ALL {
        for query in ["closest", "any"] {
            let out = dir
                .path()
                .join(format!("out-{}-{query}.hit", format.name()));
            let (ok, j, err) = rayd(&[
                "trace",
                p(&scene),
                "--rays",
                p(&ray_path),
                "--out",
                p(&out),
                "--hit",
                format.name(),
                "--query",
                query,
                "--threads",
                "1",
                "--accel",
                "brute",
            ]);
            assert!(ok, "{err}");
            assert_eq!(j["rays"], 5);
            assert_eq!(j["accel"], "brute");
            assert_eq!(j["threads"], 1);
            for key in ["build_seconds", "trace_seconds", "mrays_per_s"] {
                assert!(j[key].as_f64().unwrap() >= 0.0, "{key}");
            }
            let (f, hits) = read_hits(&std::fs::read(&out).unwrap()).unwrap();
            assert_eq!(f, format);
            let hit_mask: Vec<bool> = hits.iter().map(Hit::is_hit).collect();
            assert_eq!(hit_mask, [true, true, false, false, false]);
            if format == HitFormat::TPrimUv {
                assert_eq!(hits[0].prim, 0);
                assert_eq!(hits[1].prim, 1);
                assert_eq!(hits[0].t, 1.0);
                assert!((hits[0].u - 0.25).abs() < 1e-6 && (hits[0].v - 0.25).abs() < 1e-6);
                assert_eq!(hits[2], Hit::MISS);
            }
        }
    }
}

#[test]
fn invalid_rays_refuse_the_batch_or_miss() {
    let dir = tempfile::tempdir().unwrap();
    let scene = quad_scene(dir.path());
    let mut rays = vec![down(0.25, 0.25); 6];
    rays[2].dir = [0.0; 3];
    rays[4].org[0] = f32::NAN;
    let ray_path = dir.path().join("bad.ray");
    std::fs::write(&ray_path, write_rays(&rays)).unwrap();
    let out = dir.path().join("bad.hit");
    let (ok, _, err) = rayd(&["trace", p(&scene), "--rays", p(&ray_path), "--out", p(&out)]);
    assert!(!ok);
    assert!(
        err.contains("2 invalid ray(s)") && err.contains("ray 2"),
        "{err}"
    );
    assert!(!out.exists(), "no output may be written");
    let (ok, _, err) = rayd(&[
        "trace",
        p(&scene),
        "--rays",
        p(&ray_path),
        "--out",
        p(&out),
        "--invalid",
        "miss",
    ]);
    assert!(ok, "{err}");
    let (_, hits) = read_hits(&std::fs::read(&out).unwrap()).unwrap();
    let mask: Vec<bool> = hits.iter().map(Hit::is_hit).collect();
    assert_eq!(mask, [true, true, false, true, false, true]);
}

#[test]
fn malformed_files_get_specific_errors() {
    let dir = tempfile::tempdir().unwrap();
    let scene = quad_scene(dir.path());
    let out = dir.path().join("x.hit");
    let cases: Vec<(Vec<u8>, &str)> = vec![
        (b"RAY1".to_vec(), "shorter than the 16-byte header"),
        (write_tri(&[]), "wrong magic"),
        (
            {
                let mut b = write_rays(&[down(0.0, 0.0)]);
                b.pop();
                b
            },
            "needs exactly",
        ),
        (
            {
                let mut b = write_rays(&[]);
                b[4] = 9;
                b
            },
            "unknown version 9",
        ),
    ];
    for (i, (bytes, needle)) in cases.into_iter().enumerate() {
        let path = dir.path().join(format!("case{i}.ray"));
        std::fs::write(&path, bytes).unwrap();
        let (ok, _, err) = rayd(&["trace", p(&scene), "--rays", p(&path), "--out", p(&out)]);
        assert!(!ok);
        assert!(err.contains(needle), "case {i}: {err}");
        assert!(err.contains(p(&path)), "case {i} names no file: {err}");
    }
    let (ok, _, err) = rayd(&["info", "no-such-file.glb"]);
    assert!(!ok && err.contains("no-such-file.glb"), "{err}");
    let (ok, _, err) = rayd(&["info", "scene.obj"]);
    assert!(!ok && err.contains("unknown scene file type"), "{err}");
    let (ok, _, err) = rayd(&[
        "trace",
        p(&scene),
        "--rays",
        "a",
        "--out",
        "b",
        "--accel",
        "kd",
    ]);
    // clap lists the names the enum's serde attributes give (one spelling everywhere).
    assert!(
        !ok && err.contains("invalid value 'kd' for '--accel") && err.contains("dacrt-sampled"),
        "{err}"
    );
}

/// An output that is one of the inputs is refused before anything is written; rays may
/// come from a pipe; an output is written whole (no temporary file is left beside it).
#[test]
fn outputs_never_overwrite_inputs_and_rays_may_come_from_a_pipe() {
    let dir = tempfile::tempdir().unwrap();
    let scene = quad_scene(dir.path());
    let rays = dir.path().join("rays.ray");
    let body = write_rays(&[down(0.25, 0.25), down(5.0, 5.0)]);
    std::fs::write(&rays, &body).unwrap();
    let scene_bytes = std::fs::read(&scene).unwrap();
    let other_name = dir.path().join("sub").join("..").join("rays.ray");
    std::fs::create_dir(dir.path().join("sub")).unwrap();
    for out in [&rays, &scene, &other_name] {
        let (ok, _, err) = rayd(&["trace", p(&scene), "--rays", p(&rays), "--out", p(out)]);
        assert!(!ok && err.contains("would destroy the input"), "{err}");
    }
    assert_eq!(std::fs::read(&rays).unwrap(), body);
    assert_eq!(std::fs::read(&scene).unwrap(), scene_bytes);

    let out = dir.path().join("hits.hit");
    let mut child = Command::new(env!("CARGO_BIN_EXE_rayd"))
        .args(["trace", p(&scene), "--rays", "/dev/stdin", "--out", p(&out)])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    use std::io::Write;
    child.stdin.take().unwrap().write_all(&body).unwrap();
    let piped = child.wait_with_output().unwrap();
    assert!(
        piped.status.success(),
        "{}",
        String::from_utf8_lossy(&piped.stderr)
    );
    let (ok, _, err) = rayd(&[
        "trace",
        p(&scene),
        "--rays",
        p(&rays),
        "--out",
        p(&dir.path().join("file.hit")),
    ]);
    assert!(ok, "{err}");
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(dir.path().join("file.hit")).unwrap()
    );
    let names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .collect();
    assert!(!names.iter().any(|n| n.ends_with(".tmp")), "{names:?}");
}

/// A ray whose direction is so small that its t overflows never reports a hit at
/// t = +inf (contract §2: +inf is a miss), on either test, closest or any.
#[test]
fn no_hit_is_reported_at_an_infinite_t() {
    let dir = tempfile::tempdir().unwrap();
    let scene = quad_scene(dir.path());
    let rays = dir.path().join("tiny.ray");
    let tiny = |d: f32| Ray {
        org: [0.25, 0.25, 5.0],
        tmin: 0.0,
        dir: [0.0, 0.0, -d],
        tmax: f32::INFINITY,
    };
    std::fs::write(
        &rays,
        write_rays(&[tiny(1e-45), tiny(1e-40), tiny(1e-38), tiny(1.0)]),
    )
    .unwrap();
    for precision in ["watertight", "fast"] {
        for accel in ["brute", "mbvh8", "dacrt"] {
            for (query, hit) in [("closest", "t_prim_uv"), ("any", "occluded")] {
                let out = dir.path().join("tiny.hit");
                let (ok, _, err) = rayd(&[
                    "trace",
                    p(&scene),
                    "--rays",
                    p(&rays),
                    "--out",
                    p(&out),
                    "--query",
                    query,
                    "--hit",
                    hit,
                    "--accel",
                    accel,
                    "--precision",
                    precision,
                ]);
                assert!(ok, "{err}");
                let (_, hits) = read_hits(&std::fs::read(&out).unwrap()).unwrap();
                for (i, h) in hits.iter().enumerate() {
                    // t = 5 / d overflows to +inf for the three tiny directions: misses.
                    assert_eq!(
                        h.is_hit(),
                        i == 3,
                        "{precision} {accel} {query} ray {i}: {h:?}"
                    );
                    if query == "closest" {
                        assert_eq!(h.t.is_finite(), h.is_hit(), "{precision} {accel} ray {i}");
                    }
                }
            }
        }
    }
}

/// Sizes past the limits are refused by name before anything is allocated, options that
/// would be ignored are refused, and negative numbers are values.
#[test]
fn absurd_sizes_and_ignored_options_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let scene = quad_scene(dir.path());
    let s = p(&scene);
    for (args, needle) in [
        (
            vec!["bench", s, "--width", "65536", "--height", "65536"],
            "over the limit",
        ),
        (
            vec!["bench", s, "--frames", "18446744073709551615"],
            "over the limit",
        ),
        (
            vec![
                "bench",
                s,
                "--frames",
                "3",
                "--rays-per-frame",
                "10000000000",
            ],
            "over the limit",
        ),
        (vec!["info", s, "--threads", "5000"], "not in 0..=1024"),
        (vec!["render", s, "-o", "x.png", "--fov", "30"], "--eye"),
        (vec!["render", s, "-o", "x.png", "--up", "0,0,1"], "--eye"),
    ] {
        let (ok, _, err) = rayd(&args);
        assert!(!ok && err.contains(needle), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
    let (ok, _, err) = rayd(&["info", s, "--time", "-0.5"]);
    assert!(ok, "{err}");
}

#[test]
fn render_writes_png_and_exr() {
    let dir = tempfile::tempdir().unwrap();
    let scene = quad_scene(dir.path());
    for (name, magic) in [
        ("a.png", &b"\x89PNG"[..]),
        ("a.exr", &[0x76, 0x2f, 0x31, 0x01][..]),
    ] {
        let out = dir.path().join(name);
        let (ok, j, err) = rayd(&[
            "render",
            p(&scene),
            "-o",
            p(&out),
            "--width",
            "32",
            "--height",
            "24",
            "--eye",
            "0.5,0.5,2",
            "--target",
            "0.5,0.5,0",
        ]);
        assert!(ok, "{err}");
        // Rays traced: one per pixel that can see the quad (the others see the background
        // without one).
        let rays = j["rays"].as_u64().unwrap();
        assert!(rays > 0 && rays < 32 * 24, "{rays}");
        assert!(std::fs::read(&out).unwrap().starts_with(magic));
    }
    let (ok, _, err) = rayd(&["render", p(&scene), "-o", "x.jpg"]);
    assert!(!ok && err.contains(".png or .exr"), "{err}");
    let (ok, _, err) = rayd(&["render", p(&scene), "-o", "x.png", "--aov", "depth"]);
    assert!(!ok && err.contains("aov") && err.contains("exr"), "{err}");
    let (ok, _, err) = rayd(&["render", p(&scene), "-o", "x.exr", "--sky", "1,-1,0"]);
    assert!(!ok && err.contains("sky"), "{err}");
    let out = dir.path().join("path.exr");
    let (ok, _, err) = rayd(&[
        "render",
        p(&scene),
        "-o",
        p(&out),
        "--integrator",
        "path",
        "--aov",
        "depth,normal,albedo,prim",
        "--sky",
        "0.2,0.3,0.4",
    ]);
    assert!(ok, "{err}");
}

#[test]
fn bench_runs_and_agrees_with_its_reference() {
    let dir = tempfile::tempdir().unwrap();
    let scene = quad_scene(dir.path());
    let dump = dir.path().join("dump");
    let (ok, j, err) = rayd(&[
        "bench",
        p(&scene),
        "--accel",
        "brute",
        "--width",
        "16",
        "--height",
        "12",
        "--runs",
        "1",
        "--threads",
        "1",
        "--dump",
        p(&dump),
    ]);
    assert!(ok, "{err}");
    let sc = &j["scenes"][0];
    // Interior view: every ray of every set hits the room or the quad.
    for set in sc["sets"].as_array().unwrap() {
        assert_eq!(set[1], 16 * 12, "{set}");
    }
    for m in sc["results"].as_array().unwrap() {
        assert_eq!(m["agreement"], 1.0, "{m}");
        assert_eq!(m["disagreements"], 0, "{m}");
        assert_eq!(m["edge_disagreements"], 0, "{m}");
    }
    assert!(dump.join("quad-interior-diffuse8.ray").exists());
    assert!(dump.join("quad-interior-primary.hit").exists());
    // The dumped hits name the traced triangles (the quad's, then the room's walls), which
    // the dump holds as TRI1: tracing them again gives the same hits.
    let traced = dump.join("quad-interior.tri");
    let out = dir.path().join("again.hit");
    let (ok, _, err) = rayd(&[
        "trace",
        p(&traced),
        "--rays",
        p(&dump.join("quad-interior-primary.ray")),
        "--out",
        p(&out),
        "--accel",
        "brute",
    ]);
    assert!(ok, "{err}");
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(dump.join("quad-interior-primary.hit")).unwrap()
    );
}

/// `bench --frames N` with the default `--accel auto` measures the strategies auto
/// chooses among and scores its pick (it measured nothing and said nothing).
#[test]
fn bench_frames_with_auto_measures_autos_candidates() {
    let (ok, j, err) = rayd(&[
        "bench",
        &sample("Fox.glb"),
        "--frames",
        "2",
        "--sets",
        "primary",
        "--rays-per-frame",
        "256",
        "--threads",
        "1",
    ]);
    assert!(ok, "{err}");
    let sc = &j["scenes"][0];
    let mut measured: Vec<String> = sc["series"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| {
            format!(
                "{} {}",
                s["accel"].as_str().unwrap(),
                s["mode"].as_str().unwrap()
            )
        })
        .collect();
    measured.sort();
    assert_eq!(
        measured,
        [
            "dacrt update",
            "dacrt-sampled update",
            "mbvh8 rebuild",
            "mbvh8 refit"
        ],
        "{sc}"
    );
    assert_eq!(sc["auto"].as_array().unwrap().len(), 2, "{sc}");
}

/// The manifest's directory holds the committed sample scenes.
fn sample(name: &str) -> String {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name)
        .display()
        .to_string()
}

#[test]
fn bench_frames_measures_every_strategy_on_moving_geometry() {
    // An animated scene (the fox walks) and a static one (twisted): every strategy traces
    // the same rays each frame and agrees with the first one.
    for (scene, motion) in [("Fox.glb", "animation"), ("SimpleMeshes.glb", "twist")] {
        let (ok, j, err) = rayd(&[
            "bench",
            &sample(scene),
            "--frames",
            "3",
            "--motion",
            motion,
            "--accel",
            "brute,dacrt,dacrt-sampled,mbvh8,bvh2",
            "--sets",
            "primary,diffuse1",
            "--rays-per-frame",
            "256,1024",
            "--threads",
            "1,2",
        ]);
        assert!(ok, "{scene}: {err}");
        let sc = &j["scenes"][0];
        assert!(sc["motion"].as_str().unwrap().starts_with(motion), "{sc}");
        let series = sc["series"].as_array().unwrap();
        // 2 sets × 2 ray counts × 2 thread counts for brute, dacrt, dacrt-sampled, and
        // each BVH rebuilt and refitted.
        assert_eq!(series.len(), 7 * 8, "{scene}: {err}");
        for s in series {
            assert_eq!(s["agreement"], 1.0, "{scene}: {s}");
            assert_eq!(s["update_seconds"].as_array().unwrap().len(), 3, "{s}");
            assert_eq!(s["trace_seconds"].as_array().unwrap().len(), 3, "{s}");
        }
        // auto is scored in every situation (2 sets × 2 ray counts × 2 thread counts, new
        // and refittable geometry), its pick among the measured strategies.
        let auto = sc["auto"].as_array().unwrap();
        assert_eq!(auto.len(), 16, "{scene}: {auto:?}");
    }
}

#[test]
fn bench_frames_refuses_what_it_cannot_measure() {
    let (ok, _, err) = rayd(&["bench", &sample("Fox.glb"), "--frames", "1"]);
    assert!(!ok && err.contains("--frames must be at least 2"), "{err}");
    let (ok, _, err) = rayd(&[
        "bench",
        &sample("SimpleMeshes.glb"),
        "--frames",
        "2",
        "--motion",
        "animation",
    ]);
    assert!(
        !ok && err.contains("needs a scene with animations"),
        "{err}"
    );
    let (ok, _, err) = rayd(&[
        "bench",
        &sample("Fox.glb"),
        "--frames",
        "2",
        "--motion",
        "spin",
    ]);
    assert!(!ok && err.contains("unknown motion 'spin'"), "{err}");
}

#[test]
fn mbvh_statistics_are_printed_by_info_and_bench() {
    let (ok, j, err) = rayd(&["info", &sample("Fox.glb"), "--accel", "mbvh8"]);
    assert!(ok, "{err}");
    let st = &j["accel"]["stats"];
    assert_eq!(st["triangles"], 576, "{st}");
    assert_eq!(st["references"], 576, "{st}");
    assert!(st["nodes"].as_u64().unwrap() > 1, "{st}");
    let util = st["pack_utilization"].as_f64().unwrap();
    assert!(util > 0.5 && util <= 1.0, "{st}");
    let (ok, j, err) = rayd(&[
        "bench",
        &sample("Fox.glb"),
        "--accel",
        "mbvh8,dacrt",
        "--sets",
        "primary,ao",
        "--width",
        "32",
        "--height",
        "24",
        "--runs",
        "1",
        "--threads",
        "1",
    ]);
    assert!(ok, "{err}");
    for m in j["scenes"][0]["results"].as_array().unwrap() {
        let counted = m["accel"] == "mbvh8" && m["set"] == "primary";
        assert_eq!(!m["steps"].is_null(), counted, "{m}");
        if counted {
            // Every ray visits the root; some test a leaf pack (every ray hits).
            assert!(m["steps"]["nodes_per_ray"].as_f64().unwrap() >= 1.0, "{m}");
            assert!(m["steps"]["packs_per_ray"].as_f64().unwrap() >= 1.0, "{m}");
        }
    }
}

#[test]
fn a_sequence_frame_is_the_frame_rendered_alone() {
    // The fox's texture is decoded by the sequence's first frame and shared by the rest:
    // a later frame must be byte for byte the frame that `--time` renders on its own.
    let dir = tempfile::tempdir().unwrap();
    let args = |out: &Path| {
        vec![
            "render".to_string(),
            sample("Fox.glb"),
            "--out".into(),
            p(out).into(),
            "--integrator".into(),
            "path".into(),
            "--spp".into(),
            "2".into(),
            "--width".into(),
            "40".into(),
            "--height".into(),
            "30".into(),
            "--threads".into(),
            "1".into(),
        ]
    };
    let mut seq = args(&dir.path().join("f-#.png"));
    seq.extend(["--frames".into(), "0:0.2:0.1".into()]);
    let (ok, j, err) = rayd(&seq.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(ok, "{err}");
    let outputs = j["outputs"].as_array().unwrap();
    assert_eq!(outputs.len(), 3, "{j}");
    let alone = dir.path().join("alone.png");
    let mut one = args(&alone);
    one.extend(["--time".into(), "0.2".into()]);
    let (ok, _, err) = rayd(&one.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(ok, "{err}");
    assert_eq!(
        std::fs::read(outputs[2].as_str().unwrap()).unwrap(),
        std::fs::read(&alone).unwrap(),
        "frame 2 of the sequence differs from the frame at time 0.2 alone"
    );
    // A sequence may start at a negative time, written as a separate argument.
    let mut early = args(&dir.path().join("e-#.png"));
    early.extend(["--frames".into(), "-0.2:0:0.1".into()]);
    let (ok, j, err) = rayd(&early.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(ok, "{err}");
    assert_eq!(j["outputs"].as_array().unwrap().len(), 3, "{j}");
}

#[test]
fn render_frames_update_policy_decides_refit_or_rebuild() {
    // Frame 0 always builds; later frames of the walking fox refit or rebuild as told, and
    // the images do not depend on it beyond what a refit's looser boxes cannot change.
    let dir = tempfile::tempdir().unwrap();
    let mut images = Vec::new();
    for (update, later) in [("rebuild", "built"), ("refit", "refitted")] {
        let out = dir.path().join(format!("{update}-#.png"));
        let (ok, j, err) = rayd(&[
            "render",
            &sample("Fox.glb"),
            "--out",
            p(&out),
            "--width",
            "32",
            "--height",
            "24",
            "--accel",
            "mbvh8",
            "--frames",
            "0:0.2:0.1",
            "--update",
            update,
            "--threads",
            "1",
        ]);
        assert!(ok, "{update}: {err}");
        let frames = j["frames"].as_array().unwrap();
        assert_eq!(frames.len(), 3, "{j}");
        assert_eq!(frames[0]["structure"], "built", "{j}");
        for f in &frames[1..] {
            assert_eq!(f["structure"], later, "{update}: {j}");
        }
        images.push(
            j["outputs"]
                .as_array()
                .unwrap()
                .iter()
                .map(|o| std::fs::read(o.as_str().unwrap()).unwrap())
                .collect::<Vec<_>>(),
        );
    }
    assert_eq!(
        images[0], images[1],
        "a refit must not change what a frame shows"
    );
    let (ok, _, err) = rayd(&[
        "render",
        &sample("Fox.glb"),
        "--out",
        "x.png",
        "--update",
        "never",
    ]);
    assert!(!ok && err.contains("never"), "{err}");
}

/// A scene file is read no further than its header declares: a TRI1 stream that goes on
/// past its count (a pipe fed forever) is refused as soon as it does, not read until
/// memory runs out, and a regular file longer than its header says is refused by size.
#[test]
fn scene_files_are_read_no_further_than_they_declare() {
    let dir = tempfile::tempdir().unwrap();
    let one = write_tri(&[Triangle {
        v: [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
    }]);
    let fifo = dir.path().join("stream.tri");
    let made = Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .expect("mkfifo runs");
    assert!(made.success());
    let writer = {
        let (fifo, one) = (fifo.clone(), one.clone());
        std::thread::spawn(move || {
            use std::io::Write;
            let mut f = std::fs::OpenOptions::new().write(true).open(&fifo).unwrap();
            f.write_all(&one).unwrap();
            let zeros = vec![0u8; 1 << 16];
            // Until the reader goes away (a broken pipe), or 1 GiB as a bound on the test.
            let mut sent = 0usize;
            while sent < 1 << 30 && f.write_all(&zeros).is_ok() {
                sent += zeros.len();
            }
            sent
        })
    };
    let (ok, _, err) = rayd(&["info", p(&fifo)]);
    assert!(
        !ok && err.contains("goes on past the 52 bytes its TRI1 header declares"),
        "{err}"
    );
    let sent = writer.join().unwrap();
    assert!(
        sent < 1 << 30,
        "the reader read {sent} bytes past the header"
    );

    let long = dir.path().join("long.tri");
    let mut bytes = one;
    bytes.extend_from_slice(&[0u8; 100]);
    std::fs::write(&long, &bytes).unwrap();
    let (ok, _, err) = rayd(&["info", p(&long)]);
    assert!(
        !ok && err.contains("the file is 152 bytes, longer than the 52 bytes its TRI1 header"),
        "{err}"
    );
}

/// Outputs appear together or not at all: a sequence one of whose frames cannot be
/// written writes none (checked before any is rendered), and a tradeoff whose options are
/// refused makes no directory.
#[test]
fn refused_commands_leave_no_outputs() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("p-1.png")).unwrap();
    let pattern = dir.path().join("p-#.png");
    let (ok, _, err) = rayd(&[
        "render",
        &sample("Box.glb"),
        "-o",
        p(&pattern),
        "--frames",
        "0:2:1",
        "--width",
        "8",
        "--height",
        "8",
    ]);
    assert!(!ok && err.contains("is not a regular file"), "{err}");
    assert!(!dir.path().join("p-0.png").exists());
    let out = dir.path().join("tradeoff");
    let (ok, _, err) = rayd(&["tradeoff", &sample("Box.glb"), "-o", p(&out), "--spp", "0"]);
    assert!(!ok, "{err}");
    assert!(!out.exists(), "{err}");
    let (ok, _, err) = rayd(&["healthcheck", "--timeout", "1e20"]);
    assert!(!ok && err.contains("--timeout"), "{err}");
}

/// Render options refused with a message that says what is wrong: an AOV listed twice (as
/// the service refuses it), a file named only `.png`, and `--frames` whose parts name
/// themselves, even where their count is past what an integer holds.
#[test]
fn render_refusals_name_what_is_wrong() {
    let dir = tempfile::tempdir().unwrap();
    let box_ = sample("Box.glb");
    let out = |name: &str| dir.path().join(name).display().to_string();
    let small = ["--width", "8", "--height", "6"];
    for (args, needle) in [
        (
            vec![
                "-o".to_string(),
                out("a.exr"),
                "--aov".into(),
                "depth,normal,depth".into(),
            ],
            "--aov: 'depth' is listed twice",
        ),
        (
            vec!["-o".into(), out(".png")],
            "needs a name before its .png or .exr extension",
        ),
        (
            vec![
                "-o".into(),
                out("f-#.png"),
                "--frames".into(),
                "0:1:0".into(),
            ],
            "frames.step: must be positive",
        ),
        (
            vec![
                "-o".into(),
                out("f-#.png"),
                "--frames".into(),
                "1:0:1".into(),
            ],
            "frames.end: must not be before start",
        ),
        (
            vec![
                "-o".into(),
                out("f-#.png"),
                "--frames".into(),
                "0:1e300:1e-300".into(),
            ],
            "frames.step: makes more than 1.8e308 frames, over the limit",
        ),
        (
            vec![
                "-o".into(),
                out("f-#.png"),
                "--frames".into(),
                "0:1e12:1e-12".into(),
            ],
            "frames.step: makes 1.000e24 frames, over the limit",
        ),
    ] {
        let mut all = vec!["render".to_string(), box_.clone()];
        all.extend(args);
        all.extend(small.map(String::from));
        let all: Vec<&str> = all.iter().map(String::as_str).collect();
        let (ok, _, err) = rayd(&all);
        assert!(!ok && err.contains(needle), "{all:?}: {err}");
    }
    assert_eq!(
        std::fs::read_dir(dir.path()).unwrap().count(),
        0,
        "nothing written"
    );
}

/// A name as long as a file name may be (255 bytes) is written, alone or in a sequence:
/// the staging file beside it takes a shorter name where `.NAME…` would not fit.
#[test]
fn outputs_may_have_the_longest_names() {
    let dir = tempfile::tempdir().unwrap();
    let long = format!("{}.png", "x".repeat(251));
    let seq = format!("{}-##.png", "y".repeat(248));
    let scene = sample("Box.glb");
    for (name, frames) in [(&long, None), (&seq, Some("0:1:1"))] {
        let path = dir.path().join(name);
        let mut args = vec!["render", &scene, "-o", p(&path)];
        args.extend(["--width", "8", "--height", "6"]);
        if let Some(f) = frames {
            args.extend(["--frames", f]);
        }
        let (ok, _, err) = rayd(&args);
        assert!(ok, "{}: {err}", name.len());
    }
    let mut names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names.len(), 3, "no staging file left: {names:?}");
    assert!(names.iter().all(|n| n.len() == 255), "{names:?}");
}

/// Ctrl-C during a sequence stops it within a wave, removes the frames it had staged and
/// exits 130 (128 + SIGINT), as shells expect.
#[cfg(unix)]
#[test]
fn an_interrupted_sequence_leaves_no_files() {
    use std::time::{Duration, Instant};
    let dir = tempfile::tempdir().unwrap();
    let pattern = dir.path().join("walk-##.png");
    let mut child = Command::new(env!("CARGO_BIN_EXE_rayd"))
        .args(["render", &sample("Fox.glb"), "-o", p(&pattern)])
        .args(["--width", "320", "--height", "240", "--spp", "256"])
        .args([
            "--integrator",
            "path",
            "--frames",
            "0:2:0.1",
            "--threads",
            "1",
        ])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // Until the first frame is staged.
    let t0 = Instant::now();
    while std::fs::read_dir(dir.path()).unwrap().count() == 0 {
        assert!(t0.elapsed() < Duration::from_secs(120), "no frame staged");
        assert!(
            child.try_wait().unwrap().is_none(),
            "ended before its first frame"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    let pid = child.id().to_string();
    Command::new("kill").args(["-INT", &pid]).status().unwrap();
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(130), "{err}");
    assert!(err.contains("stopped by SIGINT"), "{err}");
    let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert!(left.is_empty(), "{left:?}");
}

/// `healthcheck` passes on a whole 200 answer only: a server that stalls after its status
/// line, or closes inside its head or body, fails the probe; a URL that could not be sent
/// as it is (a line break, a space), names credentials or a port out of range is refused.
#[test]
fn healthcheck_wants_a_whole_answer_and_a_sendable_url() {
    use std::io::{Read, Write};
    use std::net::TcpListener;
    // Answers each connection with the next canned reply, then closes it (or holds it open
    // for 5 s after a reply marked to stall).
    let replies: Vec<(&'static [u8], bool)> = vec![
        (b"HTTP/1.1 200 OK\r\nContent-Length: 2\r\n\r\nok", false),
        (b"HTTP/1.1 200 OK\r\nContent-Length: 2", true),
        (b"HTTP/1.1 200 OK\r\nContent-Le", false),
        (b"HTTP/1.1 200 OK\r\nContent-Length: 10\r\n\r\nok", false),
    ];
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    let server = std::thread::spawn(move || {
        for (reply, stall) in replies {
            let (mut c, _) = listener.accept().unwrap();
            let mut head = Vec::new();
            let mut b = [0u8; 1024];
            while !head.windows(4).any(|w| w == b"\r\n\r\n") {
                let n = c.read(&mut b).unwrap();
                assert!(n > 0);
                head.extend_from_slice(&b[..n]);
            }
            let text = String::from_utf8_lossy(&head).into_owned();
            assert!(text.starts_with("GET /healthz?x=1 HTTP/1.1\r\n"), "{text}");
            c.write_all(reply).unwrap();
            if stall {
                // Held open, unanswered, beside the next connections.
                std::thread::spawn(move || {
                    std::thread::sleep(std::time::Duration::from_secs(5));
                    drop(c);
                });
            }
        }
    });
    let url = format!("http://{addr}/healthz?x=1#frag");
    let probe = |url: &str| rayd(&["healthcheck", "--url", url, "--timeout", "2"]);
    let (ok, j, err) = probe(&url);
    assert!(ok, "{err}");
    assert_eq!(j["status"], 200);
    for needle in [
        "the answer did not end within 2 s",
        "closed inside the answer's head",
        "the body ends after 2 of its 10 bytes",
    ] {
        let (ok, _, err) = probe(&url);
        assert!(!ok && err.contains(needle), "{needle}: {err}");
    }
    server.join().unwrap();
    for (url, needle) in [
        (format!("http://{addr}/a\r\nX-Evil: 1"), "cannot be sent"),
        (format!("http://{addr}/a b"), "cannot be sent"),
        ("http://user:pw@127.0.0.1:1/".to_string(), "credentials"),
        (
            "http://127.0.0.1:99999/healthz".to_string(),
            "not a port number",
        ),
    ] {
        let (ok, _, err) = probe(&url);
        assert!(!ok && err.contains(needle), "{url:?}: {err}");
    }
}

/// `bench` refuses what it would silently ignore or overwrite, and measures a repeated
/// accelerator once; `tradeoff` refuses `auto`, whose pick would change along its ladder.
#[test]
fn bench_and_tradeoff_refuse_what_they_would_ignore() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("a");
    let b = dir.path().join("b");
    std::fs::create_dir_all(&a).unwrap();
    std::fs::create_dir_all(&b).unwrap();
    std::fs::copy(sample("Box.glb"), a.join("S.glb")).unwrap();
    std::fs::copy(sample("Fox.glb"), b.join("S.glb")).unwrap();
    let dump = dir.path().join("dump");
    let small = [
        "--width",
        "16",
        "--height",
        "16",
        "--runs",
        "1",
        "--threads",
        "1",
    ];
    let cases: Vec<(Vec<String>, &str)> = vec![
        (
            vec![
                p(&a.join("S.glb")).into(),
                p(&b.join("S.glb")).into(),
                "--dump".into(),
                p(&dump).into(),
            ],
            "would write the same files",
        ),
        (
            vec![
                sample("Fox.glb"),
                "--frames".into(),
                "2".into(),
                "--dump".into(),
                p(&dump).into(),
            ],
            "--dump is not available with --frames",
        ),
        (
            vec![
                sample("Fox.glb"),
                "--frames".into(),
                "2".into(),
                "--time".into(),
                "1".into(),
            ],
            "--time is not available with --frames",
        ),
        (
            vec![sample("Fox.glb"), "--motion".into(), "twist".into()],
            "--motion needs --frames",
        ),
        (
            // (`small` below adds `--runs 1`.)
            vec![sample("Fox.glb"), "--frames".into(), "2".into()],
            "--runs is not available with --frames",
        ),
    ];
    for (args, needle) in cases {
        let mut all = vec!["bench".to_string()];
        all.extend(args);
        all.extend(small.map(String::from));
        let all: Vec<&str> = all.iter().map(String::as_str).collect();
        let (ok, _, err) = rayd(&all);
        assert!(!ok && err.contains(needle), "{all:?}: {err}");
    }
    assert!(!dump.exists());
    let scene = sample("Box.glb");
    let mut args = vec![
        "bench",
        &scene,
        "--accel",
        "mbvh8,mbvh8",
        "--sets",
        "primary",
    ];
    args.extend(small);
    let (ok, j, err) = rayd(&args);
    assert!(ok, "{err}");
    let results = j["scenes"][0]["results"].as_array().unwrap();
    assert_eq!(results.len(), 1, "{j}");
    for accel in [["--accel", "auto"], ["--accels", "mbvh8,auto"]] {
        let out = dir.path().join("t");
        let (ok, _, err) = rayd(&["tradeoff", &scene, "-o", p(&out), accel[0], accel[1]]);
        assert!(!ok && err.contains("not auto"), "{err}");
        assert!(!out.exists());
    }
}

/// A `.gltf`'s external buffer is read no further than its `byteLength`: a buffer file
/// that is a device fed forever (`/dev/zero`) took all memory.
#[cfg(unix)]
#[test]
fn an_external_buffer_is_read_no_further_than_its_byte_length() {
    let dir = tempfile::tempdir().unwrap();
    std::os::unix::fs::symlink("/dev/zero", dir.path().join("buf.bin")).unwrap();
    let doc = serde_json::json!({
        "asset": {"version": "2.0"},
        "buffers": [{"uri": "buf.bin", "byteLength": 36}],
        "bufferViews": [{"buffer": 0, "byteLength": 36}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                       "min": [0.0, 0.0, 0.0], "max": [0.0, 0.0, 0.0]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
        "scene": 0
    });
    let scene = dir.path().join("zero.gltf");
    std::fs::write(&scene, doc.to_string()).unwrap();
    let (ok, j, err) = rayd(&["info", p(&scene)]);
    assert!(ok, "{err}");
    assert_eq!(j["triangles"], 1, "{j}");
}
