//! End to end against a real `rayd serve` on loopback: uploads, traces compared byte for
//! byte with `rayd trace`, render jobs polled to PNG and EXR with their events, cancellation,
//! geometry versions, bad inputs with their status codes, persistence across a restart and
//! a `kill -9` in the middle of a render.

use std::process::Command;
use std::time::{Duration, Instant};

use rayd::formats::binary::{write_rays, write_tri};
use rayd::geometry::{Ray, Triangle};

#[path = "common/server.rs"]
mod server;
use server::{scenes, wait_job, wait_running, Server, BIN};

fn rays_at(bounds_min: [f32; 3], bounds_max: [f32; 3], n: usize) -> Vec<Ray> {
    let c = [0, 1, 2].map(|i| 0.5 * (bounds_min[i] + bounds_max[i]));
    let r = (0..3)
        .map(|i| bounds_max[i] - bounds_min[i])
        .fold(0.0f32, f32::max);
    (0..n)
        .map(|i| {
            let a = i as f32 * 0.61803;
            let b = i as f32 * 0.3137;
            let org = [
                c[0] + 2.0 * r * a.cos(),
                c[1] + 0.3 * r * b.sin(),
                c[2] + 2.0 * r * a.sin(),
            ];
            Ray {
                org,
                tmin: 0.0,
                dir: [
                    c[0] - org[0],
                    c[1] - org[1] + 0.1 * r * b.cos(),
                    c[2] - org[2],
                ],
                tmax: f32::INFINITY,
            }
        })
        .collect()
}

/// `rayd trace SCENE --rays RAYS --out OUT` with `[query, hit, accel]` on the test
/// servers' two threads: what the service's answer must equal byte for byte. Returns its
/// report.
fn cli_trace(
    scene: &std::path::Path,
    rays: &std::path::Path,
    out: &std::path::Path,
    [query, hit, accel]: [&str; 3],
) -> serde_json::Value {
    let cli = Command::new(BIN)
        .arg("trace")
        .arg(scene)
        .arg("--rays")
        .arg(rays)
        .arg("--out")
        .arg(out)
        .args(["--query", query, "--hit", hit, "--accel", accel])
        .args(["--threads", "2"])
        .output()
        .unwrap();
    assert!(
        cli.status.success(),
        "{}",
        String::from_utf8_lossy(&cli.stderr)
    );
    serde_json::from_slice(&cli.stdout).unwrap()
}

/// The unlabelled series of one scrape of `/metrics`.
struct Metrics(String);

impl Metrics {
    fn scrape(s: &Server) -> Metrics {
        let r = s.req("GET", "/metrics", &[], &[]);
        assert_eq!(r.status, 200);
        Metrics(String::from_utf8(r.body).unwrap())
    }

    /// The value of series `name` (which must be there).
    fn get(&self, name: &str) -> f64 {
        self.0
            .lines()
            .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
            .unwrap_or_else(|| panic!("{name} is not in /metrics:\n{}", self.0))
    }
}

#[test]
fn the_service_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let s = Server::start(&data, &[]);

    // Uploads: GLB twice (201 then 200, same id), TRI1.
    let fox = scenes().join("Fox.glb");
    let bytes = std::fs::read(&fox).unwrap();
    let r = s.req(
        "POST",
        "/v1/scenes",
        &[("Content-Type", "model/gltf-binary")],
        &bytes,
    );
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let scene = r.json();
    let id = scene["id"].as_str().unwrap().to_string();
    assert_eq!(
        r.header("location"),
        Some(format!("/v1/scenes/{id}").as_str())
    );
    assert_eq!(scene["version"], 1);
    assert!(r.header("x-request-id").is_some());
    let again = s.req(
        "POST",
        "/v1/scenes",
        &[("Content-Type", "model/gltf-binary")],
        &bytes,
    );
    assert_eq!(again.status, 200);
    assert_eq!(again.json()["id"], scene["id"]);
    let tris: Vec<Triangle> = (0..10)
        .map(|i| Triangle {
            v: [
                [i as f32, 0.0, 0.0],
                [i as f32 + 1.0, 0.0, 0.0],
                [i as f32, 1.0, 0.0],
            ],
        })
        .collect();
    assert_eq!(s.upload_tri(&tris)["triangles"], 10);
    let list = s.req("GET", "/v1/scenes?limit=1", &[], &[]).json();
    assert_eq!(list["scenes"].as_array().unwrap().len(), 1);
    assert!(list["next_page_token"].is_string());
    // An empty token is the first page (AIP-158), as a client loop sends it.
    let again = s.req("GET", "/v1/scenes?limit=1&page_token=", &[], &[]);
    assert_eq!(
        again.status,
        200,
        "{}",
        String::from_utf8_lossy(&again.body)
    );
    assert_eq!(again.json()["scenes"], list["scenes"]);

    // Traces: every query and hit format equals `rayd trace` on the same file.
    let min: Vec<f32> = serde_json::from_value(scene["bounds"]["min"].clone()).unwrap();
    let max: Vec<f32> = serde_json::from_value(scene["bounds"]["max"].clone()).unwrap();
    let rays = rays_at([min[0], min[1], min[2]], [max[0], max[1], max[2]], 3000);
    let ray_file = dir.path().join("rays.ray");
    std::fs::write(&ray_file, write_rays(&rays)).unwrap();
    let body = write_rays(&rays);
    for (query, hit) in [
        ("closest", "t_prim_uv"),
        ("closest", "t_prim"),
        ("closest", "t"),
        ("any", "occluded"),
    ] {
        let out = dir.path().join(format!("{query}-{hit}.hit"));
        cli_trace(&fox, &ray_file, &out, [query, hit, "mbvh8"]);
        let r = s.req(
            "POST",
            &format!("/v1/scenes/{id}/trace?query={query}&hit={hit}&accel=mbvh8"),
            &[("Content-Type", "application/octet-stream")],
            &body,
        );
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        assert_eq!(r.body, std::fs::read(&out).unwrap(), "{query} {hit}");
        assert_eq!(r.header("x-rayd-accel"), Some("mbvh8"));
        assert!(r.header("server-timing").unwrap().contains("trace;dur="));
    }

    // A batch of several segments is traced as it arrives: the same bytes as `rayd trace`,
    // and a bad ray deep in it is still named, with the count of bad ones.
    let big = rays_at([min[0], min[1], min[2]], [max[0], max[1], max[2]], 200_000);
    let big_file = dir.path().join("big.ray");
    std::fs::write(&big_file, write_rays(&big)).unwrap();
    let big_body = write_rays(&big);
    for (query, hit, accel) in [
        ("closest", "t_prim_uv", "mbvh8"),
        ("any", "occluded", "bvh2"),
        ("closest", "t", "dacrt"),
    ] {
        let out = dir.path().join(format!("big-{query}-{hit}.hit"));
        cli_trace(&fox, &big_file, &out, [query, hit, accel]);
        let r = s.req(
            "POST",
            &format!("/v1/scenes/{id}/trace?query={query}&hit={hit}&accel={accel}"),
            &[("Content-Type", "application/octet-stream")],
            &big_body,
        );
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        assert!(
            r.body == std::fs::read(&out).unwrap(),
            "big {query} {hit} {accel}"
        );
    }
    let mut bad_big = big.clone();
    bad_big[150_001].org[2] = f32::NAN;
    bad_big[199_999].dir = [0.0; 3];
    let r = s.req(
        "POST",
        &format!("/v1/scenes/{id}/trace?accel=mbvh8"),
        &[("Content-Type", "application/octet-stream")],
        &write_rays(&bad_big),
    );
    assert_eq!(r.status, 422, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["ray_index"], 150_001);
    assert_eq!(r.json()["count"], 2);

    // Bad inputs, each with its status and the place.
    let trace_path = format!("/v1/scenes/{id}/trace");
    let octet = [("Content-Type", "application/octet-stream")];
    let r = s.req(
        "POST",
        &trace_path,
        &[("Content-Type", "text/plain")],
        &body,
    );
    assert_eq!(r.status, 415);
    assert_eq!(r.header("content-type"), Some("application/problem+json"));
    assert_eq!(r.json()["field"], "Content-Type");
    // Every route's 415 names the header, uploads and geometry updates too.
    for (method, path) in [
        ("POST", "/v1/scenes".to_string()),
        ("PUT", format!("/v1/scenes/{id}/geometry")),
    ] {
        let r = s.req(method, &path, &[("Content-Type", "text/plain")], b"x");
        assert_eq!(
            (r.status, r.json()["field"].as_str()),
            (415, Some("Content-Type")),
            "{path}"
        );
    }
    // A body that is not what its Content-Type says is refused at byte 0.
    let glb_bytes = std::fs::read(scenes().join("Box.glb")).unwrap();
    let r = s.req(
        "POST",
        "/v1/scenes",
        &[("Content-Type", "model/gltf+json")],
        &glb_bytes,
    );
    assert_eq!((r.status, r.json()["byte_offset"].as_u64()), (400, Some(0)));
    // Stored bytes declared as another type are refused as they would be unstored.
    let stored = s.req(
        "POST",
        "/v1/scenes",
        &[("Content-Type", "model/gltf-binary")],
        &glb_bytes,
    );
    assert!(matches!(stored.status, 200 | 201), "{}", stored.status);
    let r = s.req(
        "POST",
        "/v1/scenes",
        &[("Content-Type", "application/x-rayd-tri")],
        &glb_bytes,
    );
    assert_eq!(r.status, 400, "{}", String::from_utf8_lossy(&r.body));
    // A geometry update takes no query parameters.
    let r = s.req(
        "PUT",
        &format!("/v1/scenes/{id}/geometry?time=1"),
        &[("Content-Type", "application/x-rayd-tri")],
        b"",
    );
    assert_eq!((r.status, r.json()["field"].as_str()), (400, Some("time")));
    // A GLB whose JSON chunk runs past the end names the chunk's byte.
    let mut glb = std::fs::read(scenes().join("Box.glb")).unwrap();
    glb[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
    let r = s.req(
        "POST",
        "/v1/scenes",
        &[("Content-Type", "model/gltf-binary")],
        &glb,
    );
    assert_eq!(
        (r.status, r.json()["byte_offset"].as_u64()),
        (400, Some(12)),
        "{}",
        String::from_utf8_lossy(&r.body)
    );
    // A geometry update with a non-finite position names its byte.
    let mut tri = s
        .req("GET", &format!("/v1/scenes/{id}/geometry"), &[], &[])
        .body;
    tri[16 + 4..16 + 8].copy_from_slice(&f32::NAN.to_le_bytes());
    let r = s.req(
        "PUT",
        &format!("/v1/scenes/{id}/geometry"),
        &[("Content-Type", "application/x-rayd-tri")],
        &tri,
    );
    assert_eq!(r.status, 400, "{}", String::from_utf8_lossy(&r.body));
    assert!(
        r.json()["byte_offset"].as_u64().is_some(),
        "{}",
        String::from_utf8_lossy(&r.body)
    );
    // A short body names where it ends: the first byte missing.
    let r = s.req("POST", &trace_path, &octet, &body[..body.len() - 5]);
    assert_eq!(r.status, 400, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["byte_offset"], body.len() - 5);
    let mut bad = rays.clone();
    bad[17].dir = [f32::NAN, 0.0, 0.0];
    bad[40].dir = [0.0; 3];
    let r = s.req("POST", &trace_path, &octet, &write_rays(&bad));
    assert_eq!(r.status, 422);
    let p = r.json();
    assert_eq!(
        (p["ray_index"].as_u64(), p["count"].as_u64()),
        (Some(17), Some(2))
    );
    assert_eq!(p["instance"].as_str(), r.header("x-request-id"));
    let r = s.req(
        "POST",
        &format!("{trace_path}?invalid=miss"),
        &octet,
        &write_rays(&bad),
    );
    assert_eq!(r.status, 200);
    let r = s.req("POST", &format!("{trace_path}?accel=octree"), &octet, &body);
    assert_eq!(r.status, 400);
    assert_eq!(r.json()["field"], "accel");
    let r = s.req("POST", "/v1/scenes/00ff/trace", &octet, &body);
    assert_eq!(r.status, 404);
    let r = s.req("GET", "/v1/scenes/..%2F..%2Fetc", &[], &[]);
    assert_eq!(r.status, 404);
    // A query parameter a route does not take is 400 naming it, on every route.
    for path in [
        format!("/v1/scenes/{id}?versoin=2"),
        format!("/v1/scenes/{id}/thumbnail?versoin=2"),
    ] {
        let r = s.req("GET", &path, &[], &[]);
        assert_eq!(
            r.status,
            400,
            "{path}: {}",
            String::from_utf8_lossy(&r.body)
        );
        assert_eq!(r.json()["field"], "versoin", "{path}");
    }
    let r = s.req(
        "POST",
        "/v1/scenes",
        &[("Content-Type", "model/gltf-binary")],
        b"glTF not really",
    );
    assert_eq!(r.status, 400);
    let r = s.req("GET", &format!("{trace_path}?version=7"), &[], &[]);
    assert_eq!(r.status, 405);
    let r = s.req("POST", &format!("{trace_path}?version=7"), &octet, &body);
    assert_eq!(r.status, 404);

    // Geometry versions: a new version answers differently, the old one still answers.
    let n = scene["triangles"].as_u64().unwrap() as usize;
    let wrong = s.req(
        "PUT",
        &format!("/v1/scenes/{id}/geometry"),
        &[("Content-Type", "application/x-rayd-tri")],
        &write_tri(&tris),
    );
    assert_eq!(
        wrong.status,
        422,
        "{}",
        String::from_utf8_lossy(&wrong.body)
    );
    let moved: Vec<Triangle> = vec![
        Triangle {
            v: [
                [1e6, 1e6, 1e6],
                [1e6 + 1.0, 1e6, 1e6],
                [1e6, 1e6 + 1.0, 1e6]
            ],
        };
        n
    ];
    let v2 = s.req(
        "PUT",
        &format!("/v1/scenes/{id}/geometry"),
        &[("Content-Type", "application/x-rayd-tri")],
        &write_tri(&moved),
    );
    assert_eq!(v2.status, 200, "{}", String::from_utf8_lossy(&v2.body));
    assert_eq!(v2.json()["version"], 2);
    let now = s.req("POST", &format!("{trace_path}?hit=occluded"), &octet, &body);
    assert!(
        now.body[16..].iter().all(|&b| b == 0),
        "version 2 is far away"
    );
    let old = s.req(
        "POST",
        &format!("{trace_path}?version=1&hit=occluded"),
        &octet,
        &body,
    );
    assert!(old.body[16..].contains(&1));
    let r = s.req(
        "POST",
        &format!("{trace_path}?version=2&time=0.5"),
        &octet,
        &body,
    );
    assert_eq!(r.status, 400);

    // A render job polled to PNG, with its events; an EXR; a sequence of frames.
    let render = |spec: &str| {
        let r = s.req(
            "POST",
            &format!("/v1/scenes/{id}/render"),
            &[("Content-Type", "application/json")],
            spec.as_bytes(),
        );
        assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
        assert!(r.header("location").unwrap().starts_with("/v1/jobs/"));
        r.json()["id"].as_str().unwrap().to_string()
    };
    let job = render(r#"{"width": 64, "height": 48, "version": 1}"#);
    let j = wait_job(&s, &job, 60);
    assert_eq!(j["state"], "succeeded", "{j}");
    assert_eq!(j["progress"], 1.0);
    let png = s.req("GET", &format!("/v1/jobs/{job}/result"), &[], &[]);
    assert_eq!(png.status, 200);
    assert_eq!(png.header("content-type"), Some("image/png"));
    assert_eq!(&png.body[1..4], b"PNG");
    let etag = png.header("etag").unwrap().to_string();
    let cached = s.req(
        "GET",
        &format!("/v1/jobs/{job}/result"),
        &[("If-None-Match", &etag)],
        &[],
    );
    assert_eq!(cached.status, 304);
    // If-None-Match compares weakly (RFC 9110): a weak validator of the same tag matches.
    let weak = format!("W/{etag}");
    let cached = s.req(
        "GET",
        &format!("/v1/jobs/{job}/result"),
        &[("If-None-Match", &weak)],
        &[],
    );
    assert_eq!(cached.status, 304);
    let ev = s.req("GET", &format!("/v1/jobs/{job}/events"), &[], &[]);
    assert!(String::from_utf8_lossy(&ev.body).contains("\"succeeded\""));
    let job =
        render(r#"{"width": 32, "height": 32, "format": "exr", "version": 1, "integrator": "ao"}"#);
    assert_eq!(wait_job(&s, &job, 60)["state"], "succeeded");
    let exr = s.req("GET", &format!("/v1/jobs/{job}/result"), &[], &[]);
    assert_eq!(exr.header("content-type"), Some("image/x-exr"));
    assert_eq!(&exr.body[..4], &[0x76, 0x2f, 0x31, 0x01]);
    // A shaded render with a sky and AOVs is the same file as `rayd render` makes.
    let job = render(
        r#"{"width": 24, "height": 16, "spp": 2, "format": "exr", "version": 1, "integrator": "path", "sky": [0.5, 0.7, 1.2], "aov": ["albedo", "prim"], "accel": "mbvh8", "seed": 4}"#,
    );
    assert_eq!(wait_job(&s, &job, 60)["state"], "succeeded");
    let served = s.req("GET", &format!("/v1/jobs/{job}/result"), &[], &[]);
    let out = dir.path().join("fox.exr");
    let cli = Command::new(BIN)
        .args(["render", fox.to_str().unwrap(), "-o", out.to_str().unwrap()])
        .args([
            "--width",
            "24",
            "--height",
            "16",
            "--spp",
            "2",
            "--integrator",
            "path",
        ])
        .args([
            "--sky",
            "0.5,0.7,1.2",
            "--aov",
            "albedo,prim",
            "--accel",
            "mbvh8",
        ])
        .args(["--seed", "4"])
        .output()
        .unwrap();
    assert!(
        cli.status.success(),
        "{}",
        String::from_utf8_lossy(&cli.stderr)
    );
    assert!(
        served.body == std::fs::read(&out).unwrap(),
        "service and CLI differ"
    );
    // The same render again takes the scene's decoded textures from the cache (one hit,
    // no miss) and gives the same file; repeated traces found their structures too.
    let before = Metrics::scrape(&s);
    let job = render(
        r#"{"width": 24, "height": 16, "spp": 2, "format": "exr", "version": 1, "integrator": "path", "sky": [0.5, 0.7, 1.2], "aov": ["albedo", "prim"], "accel": "mbvh8", "seed": 4}"#,
    );
    let j = wait_job(&s, &job, 60);
    assert_eq!(j["state"], "succeeded");
    let render_rays = j["stats"]["rays"].as_f64().unwrap();
    let again = s.req("GET", &format!("/v1/jobs/{job}/result"), &[], &[]);
    assert!(
        again.body == served.body,
        "a render from cached textures differs"
    );
    let after = Metrics::scrape(&s);
    let hits = "rayd_texture_cache_hits_total";
    let misses = "rayd_texture_cache_misses_total";
    assert_eq!(after.get(hits), before.get(hits) + 1.0);
    assert_eq!(after.get(misses), before.get(misses));
    // And its light table (the same positions, sky and sampling).
    let (lh, lm) = (
        "rayd_light_cache_hits_total",
        "rayd_light_cache_misses_total",
    );
    assert_eq!(after.get(lh), before.get(lh) + 1.0);
    assert_eq!(after.get(lm), before.get(lm));
    assert!(after.get("rayd_light_cache_bytes") > 0.0);
    // A render's rays count among the rays traced.
    let traced = "rayd_rays_traced_total";
    assert!(render_rays > 0.0 && after.get(traced) == before.get(traced) + render_rays);
    assert!(after.get(misses) >= 1.0 && after.get("rayd_texture_cache_bytes") > 0.0);
    assert!(after.get("rayd_cache_hits_total") >= 1.0);
    assert!(after.get("rayd_cache_misses_total") >= 1.0);
    assert!(after.get("rayd_cache_bytes") > 0.0);
    // A body that parses but asks what the job cannot do is 422, naming the field, whether
    // a schema's bound, another field, the scene or a configured limit says no; a body
    // that is not a render request at all (a type, an unknown field, an array) is 400.
    for (body, status, field) in [
        (&br#"{"aov": ["depth"]}"#[..], 422, "aov"),
        (br#"{"camera": 4294967296}"#, 422, "camera"),
        (br#"{"eye": [0, 0, 1], "target": [0, 0, 1]}"#, 422, "target"),
        (br#"{"fov": 30}"#, 422, "fov"),
        (br#"{"priority": 101}"#, 422, "priority"),
        (br#"{"width": 0}"#, 422, "width"),
        (br#"{"bounces": 1000000}"#, 422, "bounces"),
        (br#"{"width": -1}"#, 400, "width"),
        (br#"{"widht": 16}"#, 400, "widht"),
    ] {
        let r = s.post_render(&id, body);
        assert_eq!(
            (r.status, r.json()["field"].as_str()),
            (status, Some(field)),
            "{}",
            String::from_utf8_lossy(&r.body)
        );
    }
    let r = s.post_render(&id, b"[16, 16]");
    assert_eq!(r.status, 400, "{}", String::from_utf8_lossy(&r.body));
    let job = render(
        r#"{"width": 16, "height": 16, "version": 1, "frames": {"start": 0, "end": 1, "step": 0.5}}"#,
    );
    let j = wait_job(&s, &job, 60);
    assert_eq!(j["results"], 3, "{j}");
    let f2 = s.req("GET", &format!("/v1/jobs/{job}/result?frame=2"), &[], &[]);
    assert_eq!(f2.status, 200);
    assert_eq!(
        s.req("GET", &format!("/v1/jobs/{job}/result?frame=3"), &[], &[])
            .status,
        400
    );

    // Idempotency-Key: the retry finds the first job.
    let k = [
        ("Content-Type", "application/json"),
        ("Idempotency-Key", "k-1"),
    ];
    let a = s.req(
        "POST",
        &format!("/v1/scenes/{id}/render"),
        &k,
        br#"{"width": 8, "height": 8}"#,
    );
    let b = s.req(
        "POST",
        &format!("/v1/scenes/{id}/render"),
        &k,
        br#"{"width": 8, "height": 8}"#,
    );
    assert_eq!(a.json()["id"], b.json()["id"]);
    // A retry after a geometry update finds the same job (the first took the latest
    // version then); another body with the key is 409.
    let tri = s
        .req(
            "GET",
            &format!("/v1/scenes/{id}/geometry?version=1"),
            &[],
            &[],
        )
        .body;
    let put = s.req(
        "PUT",
        &format!("/v1/scenes/{id}/geometry"),
        &[("Content-Type", "application/x-rayd-tri")],
        &tri,
    );
    assert_eq!(put.status, 200, "{}", String::from_utf8_lossy(&put.body));
    // Frames are times, which versions from 2 on (here the latest) do not have, as `time`.
    for body in [
        &br#"{"width": 8, "height": 8, "frames": {"start": 0, "end": 1, "step": 0.5}}"#[..],
        br#"{"width": 8, "height": 8, "version": 2, "frames": {"start": 0, "end": 1, "step": 0.5}}"#,
    ] {
        let r = s.post_render(&id, body);
        assert_eq!((r.status, r.json()["field"].as_str()), (400, Some("frames")));
    }
    let c = s.req(
        "POST",
        &format!("/v1/scenes/{id}/render"),
        &k,
        br#"{"width": 8, "height": 8}"#,
    );
    assert_eq!((c.status, &c.json()["id"]), (202, &a.json()["id"]));
    let d = s.req(
        "POST",
        &format!("/v1/scenes/{id}/render"),
        &k,
        br#"{"width": 9, "height": 8}"#,
    );
    assert_eq!(d.status, 409, "{}", String::from_utf8_lossy(&d.body));

    // Cancelling a running render: it stops within a wave and stays as cancelled.
    let long = render(
        r#"{"width": 512, "height": 512, "spp": 256, "integrator": "path", "version": 1, "priority": 10}"#,
    );
    let t0 = Instant::now();
    wait_running(&s, &long, 30);
    // A small trace while the render runs is answered.
    let small = s.req(
        "POST",
        &format!("{trace_path}?version=1"),
        &octet,
        &write_rays(&rays[..100]),
    );
    assert_eq!(small.status, 200);
    // Progress seen before the cancel is never taken back by it: the store hears of
    // progress every 500 ms, a GET shows the live job's, and the cancel records that first.
    let progress = || {
        s.req("GET", &format!("/v1/jobs/{long}"), &[], &[]).json()["progress"]
            .as_f64()
            .unwrap()
    };
    // Cancelled just after a step, which the store has most likely not heard of yet.
    let first = progress();
    let seen = loop {
        let p = progress();
        if p > first {
            break p;
        }
        assert!(t0.elapsed() < Duration::from_secs(60));
        std::thread::sleep(Duration::from_millis(2));
    };
    let c = s.req("DELETE", &format!("/v1/jobs/{long}"), &[], &[]);
    assert_eq!(c.status, 200);
    assert_eq!(c.json()["state"], "cancelled");
    let kept = c.json()["progress"].as_f64().unwrap();
    assert!(kept >= seen && kept < 1.0, "seen {seen}, kept {kept}");
    let r = s.req("GET", &format!("/v1/jobs/{long}/result"), &[], &[]);
    assert_eq!(r.status, 409);
    for path in [
        format!("/v1/jobs/{long}?x=1"),
        format!("/v1/jobs/{long}/events?x=1"),
    ] {
        let r = s.req("GET", &path, &[], &[]);
        assert_eq!(
            (r.status, r.json()["field"].as_str()),
            (400, Some("x")),
            "{path}"
        );
    }

    // Persistence across a restart: scenes, versions and results.
    s.stop();
    let s = Server::start(&data, &[]);
    assert_eq!(
        s.req("GET", &format!("/v1/scenes/{id}"), &[], &[]).json()["version"],
        3,
        "versions 2 (moved) and 3 (version 1's positions again, for the idempotency retry)"
    );
    let png2 = s.req("GET", &format!("/v1/jobs/{job}/result?frame=0"), &[], &[]);
    assert_eq!(png2.status, 200);
    let old = s.req(
        "POST",
        &format!("{trace_path}?version=1&hit=occluded"),
        &octet,
        &body,
    );
    assert!(old.body[16..].contains(&1));
    assert_eq!(
        s.req("GET", &format!("/v1/jobs/{long}"), &[], &[]).json()["state"],
        "cancelled"
    );

    // A kill -9 during a render: after the restart the job runs again and finishes. The
    // render lasts seconds (at spp 64 it had finished before the kill by session 17).
    let r = s.req(
        "POST",
        &format!("/v1/scenes/{id}/render"),
        &[("Content-Type", "application/json")],
        br#"{"width": 256, "height": 256, "spp": 512, "integrator": "path", "version": 1}"#,
    );
    let crashed = r.json()["id"].as_str().unwrap().to_string();
    std::thread::sleep(Duration::from_millis(300));
    let before = s
        .req("GET", &format!("/v1/jobs/{crashed}"), &[], &[])
        .json();
    assert!(
        before["state"] == "running" || before["state"] == "queued",
        "the job must be unfinished at the kill: {before}"
    );
    s.kill9();
    let s = Server::start(&data, &[]);
    let j = wait_job(&s, &crashed, 120);
    assert_eq!(j["state"], "succeeded", "{j}");
    // The recovered render's run time reached the job-duration histogram.
    let metrics = String::from_utf8(s.req("GET", "/metrics", &[], &[]).body).unwrap();
    let renders = metrics
        .lines()
        .find_map(|l| l.strip_prefix("rayd_job_duration_seconds_count{kind=\"render\"} "))
        .unwrap_or_else(|| panic!("no render durations in /metrics:\n{metrics}"));
    assert!(renders.parse::<u64>().unwrap() >= 1, "{renders}");
    // A second server on the same directory refuses to start.
    let second = Command::new(BIN)
        .args(["serve", "--addr", "127.0.0.1:0", "--data-dir"])
        .arg(&data)
        .output()
        .unwrap();
    assert!(!second.status.success());
    s.stop();
}

/// `auto` hears how fast trace bodies arrive: after one slow upload, a new scene's batch
/// goes to `mbvh8`, which traces while the rays arrive, where the same batch in memory
/// (`rayd trace --accel auto`) goes to DACRT, which must wait for the last ray. The answer
/// is still `rayd trace`'s, byte for byte.
#[test]
fn auto_weighs_how_long_the_rays_take_to_arrive() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(&dir.path().join("data"), &[]);
    // Two different 61,440-triangle bumpy grids, each a new scene.
    let grid = |lift: f32| -> Vec<Triangle> {
        let (nx, ny) = (192, 160);
        let z =
            |i: usize, j: usize| lift + 0.05 * ((i as f32 * 0.37).sin() + (j as f32 * 0.23).cos());
        let p = |i: usize, j: usize| [i as f32 * 0.01, j as f32 * 0.01, z(i, j)];
        let mut t = Vec::with_capacity(2 * nx * ny);
        for j in 0..ny {
            for i in 0..nx {
                t.push(Triangle {
                    v: [p(i, j), p(i + 1, j), p(i, j + 1)],
                });
                t.push(Triangle {
                    v: [p(i + 1, j), p(i + 1, j + 1), p(i, j + 1)],
                });
            }
        }
        t
    };
    let upload = |tris: &[Triangle]| -> String {
        let r = s.req(
            "POST",
            "/v1/scenes",
            &[("Content-Type", "application/x-rayd-tri")],
            &write_tri(tris),
        );
        assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
        r.json()["id"].as_str().unwrap().to_string()
    };
    let rays = rays_at([0.0, 0.0, -0.2], [1.92, 1.6, 0.2], 1 << 18);
    let body = write_rays(&rays);
    let octet = [("Content-Type", "application/octet-stream")];

    // The same batch over scene B in memory: DACRT.
    let b_tris = grid(0.5);
    let b_file = dir.path().join("b.tri");
    std::fs::write(&b_file, write_tri(&b_tris)).unwrap();
    let ray_file = dir.path().join("rays.ray");
    std::fs::write(&ray_file, &body).unwrap();
    let out = dir.path().join("b.hit");
    let report = cli_trace(&b_file, &ray_file, &out, ["closest", "t_prim_uv", "auto"]);
    assert_eq!(report["accel"], "dacrt-sampled", "{report}");

    // Scene A's batch arrives at about 8 MB/s (8 MiB in about a second).
    let a = upload(&grid(0.0));
    let mut c = s
        .open("POST", &format!("/v1/scenes/{a}/trace"), &octet, body.len())
        .unwrap();
    let t0 = Instant::now();
    for (k, piece) in body.chunks(1 << 16).enumerate() {
        c.write_all(piece).unwrap();
        let due = Duration::from_secs_f64((k + 1) as f64 * (1 << 16) as f64 / 8e6);
        if let Some(wait) = due.checked_sub(t0.elapsed()) {
            std::thread::sleep(wait);
        }
    }
    let r = server::read_resp(c).unwrap();
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));

    // Scene B's batch, sent at full speed, is resolved before it arrives, as the last did.
    let b = upload(&b_tris);
    let r = s.req("POST", &format!("/v1/scenes/{b}/trace"), &octet, &body);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.header("x-rayd-accel"), Some("mbvh8"));
    assert_eq!(r.body, std::fs::read(&out).unwrap());
}

/// With `--geometry-bytes 1` the server keeps only the scene (or positions) in use in
/// memory: every other is dropped and parsed again from the store when asked for. Answers
/// do not change: traces of version 1, of a `time=` pose and of a stored version 2 give
/// the same bytes after their scene was evicted, and a shaded render the same file.
#[test]
fn scenes_evicted_from_memory_come_back_from_the_store() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(&dir.path().join("data"), &["--geometry-bytes", "1"]);
    let fox = s.upload_sample("Fox.glb");
    let other = s.upload_sample("BoxAnimated.glb");
    let id = fox["id"].as_str().unwrap().to_string();
    let other_id = other["id"].as_str().unwrap().to_string();
    let min: Vec<f32> = serde_json::from_value(fox["bounds"]["min"].clone()).unwrap();
    let max: Vec<f32> = serde_json::from_value(fox["bounds"]["max"].clone()).unwrap();
    let body = write_rays(&rays_at(
        [min[0], min[1], min[2]],
        [max[0], max[1], max[2]],
        2000,
    ));
    let octet = [("Content-Type", "application/octet-stream")];
    let trace = |scene: &str, query: &str| {
        let r = s.req(
            "POST",
            &format!("/v1/scenes/{scene}/trace?accel=bvh2{query}"),
            &octet,
            &body,
        );
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        r.body
    };
    // Version 2: the fox's positions moved up by one unit.
    let geometry = s.req("GET", &format!("/v1/scenes/{id}/geometry"), &[], &[]);
    assert_eq!(geometry.status, 200);
    let mut tris = rayd::formats::binary::read_tri(&geometry.body).unwrap();
    for t in &mut tris {
        for v in &mut t.v {
            v[1] += 1.0;
        }
    }
    let put = s.req(
        "PUT",
        &format!("/v1/scenes/{id}/geometry"),
        &[("Content-Type", "application/x-rayd-tri")],
        &write_tri(&tris),
    );
    assert_eq!(put.status, 200, "{}", String::from_utf8_lossy(&put.body));
    let render = || {
        let job = s.submit_render(
            &id,
            br#"{"width": 16, "height": 12, "spp": 1, "integrator": "path", "version": 1, "time": 0.5}"#,
        );
        assert_eq!(wait_job(&s, &job, 60)["state"], "succeeded");
        s.req("GET", &format!("/v1/jobs/{job}/result"), &[], &[])
            .body
    };
    let first = [
        trace(&id, "&version=1"),
        trace(&id, "&version=1&time=0.5"),
        trace(&id, "&version=2"),
        render(),
    ];
    assert_ne!(first[0], first[2], "version 2 moved the fox");
    // Another scene's work evicts everything of the fox's from memory, each time.
    for (k, want) in first.iter().enumerate() {
        trace(&other_id, "");
        let again = match k {
            0 => trace(&id, "&version=1"),
            1 => trace(&id, "&version=1&time=0.5"),
            2 => trace(&id, "&version=2"),
            _ => render(),
        };
        assert!(
            &again == want,
            "answer {k} changed after its scene was evicted"
        );
    }
}

/// With one pool thread (`--threads 1`, or the default on a one-CPU host), a job whose
/// step needs its scene parsed with materials, or posed at a time, does that work on its
/// own thread: sent to the pool, it would wait behind the job waiting for it, and the
/// server would hang every later upload and trace with it.
#[test]
fn one_pool_thread_renders_and_keeps_serving() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(&dir.path().join("data"), &["--threads", "1"]);
    let fox = s.upload_sample("Fox.glb");
    let id = fox["id"].as_str().unwrap().to_string();
    for body in [
        &br#"{"width": 16, "height": 12, "spp": 1, "integrator": "path"}"#[..],
        br#"{"width": 16, "height": 12, "integrator": "primary", "frames": {"start": 0, "end": 0.2, "step": 0.1}}"#,
    ] {
        let job = s.submit_render(&id, body);
        assert_eq!(wait_job(&s, &job, 60)["state"], "succeeded");
    }
    let box_ = s.upload_sample("Box.glb");
    assert!(box_["id"].is_string(), "{box_}");
}

/// Deleting a scene deletes its jobs, and stops those that run or wait: a long render
/// of it ends within a wave instead of running on unseen, holding the pool.
#[test]
fn deleting_a_scene_stops_its_jobs() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(&dir.path().join("data"), &[]);
    let fox = s.upload_sample("Fox.glb");
    let id = fox["id"].as_str().unwrap().to_string();
    let long = br#"{"width": 512, "height": 512, "spp": 1024, "bounces": 4, "integrator": "path"}"#;
    let running = s.submit_render(&id, long);
    let queued = s.submit_render(&id, long);
    wait_running(&s, &running, 30);
    // Their event streams end on a final state too, saying why (they closed on `running`
    // and `queued`, which a client cannot tell from a dropped connection).
    let last_events = std::thread::scope(|scope| {
        let streams: Vec<_> = [&running, &queued]
            .map(|job| {
                let s = &s;
                scope.spawn(move || {
                    let r = s.req("GET", &format!("/v1/jobs/{job}/events"), &[], &[]);
                    let last = String::from_utf8_lossy(&r.body)
                        .lines()
                        .filter_map(|l| l.strip_prefix("data:"))
                        .next_back()
                        .map(|d| serde_json::from_str::<serde_json::Value>(d.trim()).unwrap());
                    last.expect("at least one event")
                })
            })
            .into_iter()
            .collect();
        std::thread::sleep(Duration::from_millis(300));
        assert_eq!(
            s.req("DELETE", &format!("/v1/scenes/{id}"), &[], &[])
                .status,
            204
        );
        streams
            .into_iter()
            .map(|t| t.join().unwrap())
            .collect::<Vec<_>>()
    });
    for last in last_events {
        assert_eq!(last["state"], "cancelled", "{last}");
        assert_eq!(last["error"], "its scene was deleted", "{last}");
    }
    for job in [&running, &queued] {
        assert_eq!(
            s.req("GET", &format!("/v1/jobs/{job}"), &[], &[]).status,
            404
        );
    }
    let t1 = std::time::Instant::now();
    loop {
        let m = Metrics::scrape(&s);
        if m.get("rayd_jobs_running") == 0.0 && m.get("rayd_jobs_queued") == 0.0 {
            break;
        }
        assert!(
            t1.elapsed().as_secs() < 10,
            "the deleted scene's jobs still run"
        );
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
}

/// A job's event stream sends each change once and closes after the final state, even
/// when a cancel lands as the render ends: the last wave's progress step used to overwrite
/// the cancel's final view, and a stream opened at that moment could pair a `running`
/// record with a job already gone, so streams ended on `running`, progress 1.
#[test]
fn event_streams_end_on_the_final_state_and_repeat_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(&dir.path().join("data"), &[]);
    let fox = s.upload_sample("Fox.glb");
    let id = fox["id"].as_str().unwrap().to_string();
    let events = |job: &str| -> Vec<serde_json::Value> {
        let r = s.req("GET", &format!("/v1/jobs/{job}/events"), &[], &[]);
        String::from_utf8_lossy(&r.body)
            .lines()
            .filter_map(|l| l.strip_prefix("data:"))
            .map(|d| serde_json::from_str(d.trim()).unwrap())
            .collect()
    };
    for round in 0..12 {
        let body = format!(
            r#"{{"width": 96, "height": 96, "spp": 16, "integrator": "path", "seed": {round}}}"#
        );
        let job = s.submit_render(&id, body.as_bytes());
        let streams = std::thread::scope(|scope| {
            let streams: Vec<_> = (0..3).map(|_| scope.spawn(|| events(&job))).collect();
            // Cancel near the end (or after it: then the job has succeeded).
            loop {
                let j = s.req("GET", &format!("/v1/jobs/{job}"), &[], &[]).json();
                if j["progress"].as_f64().unwrap() >= 0.95
                    || j["state"] != "running" && j["state"] != "queued"
                {
                    break;
                }
                std::thread::sleep(Duration::from_millis(1));
            }
            let cancel = s.req("DELETE", &format!("/v1/jobs/{job}"), &[], &[]);
            // 200 with the cancelled job, or 204: it had ended, and is deleted.
            let end = match cancel.status {
                200 => cancel.json()["state"].clone(),
                204 => serde_json::json!("succeeded"),
                other => panic!("{round}: DELETE answered {other}"),
            };
            let streams: Vec<_> = streams.into_iter().map(|t| t.join().unwrap()).collect();
            (end, streams)
        });
        let (end, streams) = streams;
        for ev in streams {
            assert_eq!(
                ev.last().map(|e| &e["state"]),
                Some(&end),
                "{round}: {ev:?}"
            );
            assert!(
                ev.windows(2).all(|w| w[0] != w[1]),
                "{round}: an event repeated: {ev:?}"
            );
        }
    }
}

/// `--max-running` bounds the jobs under way: a started render that yields between waves
/// keeps its image, so a render of higher priority may not start beside it past the bound
/// (it waits, queued, for the first to end), while the started one keeps running.
#[test]
fn started_jobs_are_bounded_whatever_their_priority() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(&dir.path().join("data"), &["--max-running", "1"]);
    let fox = s.upload_sample("Fox.glb");
    let id = fox["id"].as_str().unwrap().to_string();
    let state = |job: &str| {
        s.req("GET", &format!("/v1/jobs/{job}"), &[], &[]).json()["state"]
            .as_str()
            .unwrap()
            .to_string()
    };
    let long = s.submit_render(
        &id,
        br#"{"width": 512, "height": 512, "spp": 1024, "bounces": 4, "integrator": "path", "priority": 10}"#,
    );
    wait_running(&s, &long, 30);
    let urgent = s.submit_render(&id, br#"{"width": 8, "height": 8, "priority": 90}"#);
    // Longer than a wave (at most 0.5 s), after which it would have started unbounded.
    std::thread::sleep(std::time::Duration::from_millis(1500));
    assert_eq!(state(&urgent), "queued");
    assert_eq!(state(&long), "running");
    let m = Metrics::scrape(&s);
    assert_eq!(
        (m.get("rayd_jobs_running"), m.get("rayd_jobs_queued")),
        (1.0, 1.0)
    );
    assert_eq!(
        s.req("DELETE", &format!("/v1/jobs/{long}"), &[], &[])
            .status,
        200
    );
    assert_eq!(wait_job(&s, &urgent, 30)["state"], "succeeded");
}

/// A synchronous trace takes its place in the queue when it can start, not while its
/// body is still on the way: two uploads that stall after their first bytes leave a queue
/// of two free for a render.
#[test]
fn stalled_trace_bodies_hold_no_place_in_the_queue() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(&dir.path().join("data"), &["--max-queued", "2"]);
    let fox = s.upload_sample("Fox.glb");
    let id = fox["id"].as_str().unwrap().to_string();
    // 100 rays announced, only the 16-byte header sent.
    let mut head = write_rays(&[]);
    head[8..16].copy_from_slice(&100u64.to_le_bytes());
    let stalled: Vec<std::net::TcpStream> = (0..2)
        .map(|_| {
            let mut c = std::net::TcpStream::connect(&s.addr).unwrap();
            write!(
                c,
                "POST /v1/scenes/{id}/trace HTTP/1.1\r\nHost: x\r\nContent-Type: application/octet-stream\r\nContent-Length: {}\r\n\r\n",
                16 + 100 * 32
            )
            .unwrap();
            c.write_all(&head).unwrap();
            c
        })
        .collect();
    std::thread::sleep(std::time::Duration::from_millis(300));
    let job = s.submit_render(&id, br#"{"width": 8, "height": 8}"#);
    assert_eq!(wait_job(&s, &job, 30)["state"], "succeeded");
    drop(stalled);
}

/// 40,000 small triangles in a unit square; `brute` tests every ray against all of them,
/// so 40,000 rays hold the pool for about a second on two cores.
fn slow_grid() -> Vec<Triangle> {
    (0..40_000)
        .map(|i| {
            let (x, y) = ((i % 200) as f32 / 200.0, (i / 200) as f32 / 200.0);
            Triangle {
                v: [[x, y, 0.0], [x + 0.005, y, 0.0], [x, y + 0.005, 0.0]],
            }
        })
        .collect()
}

/// A synchronous trace whose client hangs up before the answer gives up its place in the
/// queue (session 31's review: four clients that sent 1K rays and closed the connection
/// while a long trace held the pool filled `--max-queued 4`, renders got 503, and the
/// server traced the abandoned batches afterwards).
#[test]
fn abandoned_traces_give_up_their_places() {
    use std::io::Write;
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(&dir.path().join("data"), &["--max-queued", "2"]);
    let tris = slow_grid();
    let id = s.upload_tri(&tris)["id"].as_str().unwrap().to_string();
    let rays = |n| write_rays(&rays_at([0.0, 0.0, -1.0], [1.0, 1.0, 1.0], n));
    let long = rays(40_000);
    let octet = ("Content-Type", "application/octet-stream");
    // An asynchronous trace is one step: it holds the pool until it is done.
    let holder = s.req(
        "POST",
        &format!("/v1/scenes/{id}/trace?accel=brute"),
        &[octet, ("Prefer", "respond-async")],
        &long,
    );
    assert_eq!(
        holder.status,
        202,
        "{}",
        String::from_utf8_lossy(&holder.body)
    );
    let holder = holder.json()["id"].as_str().unwrap().to_string();
    {
        // Until the long trace has the pool.
        let start = std::time::Instant::now();
        while Metrics::scrape(&s).get("rayd_jobs_running") < 1.0 {
            assert!(
                start.elapsed().as_secs() < 30,
                "the long trace never started"
            );
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        // Two whole 1K-ray requests whose clients hang up at once: each would wait for the
        // pool behind the long trace, holding one of the queue's two places.
        let small = rays(1000);
        for _ in 0..2 {
            let mut c = std::net::TcpStream::connect(&s.addr).unwrap();
            write!(
                c,
                "POST /v1/scenes/{id}/trace HTTP/1.1\r\nHost: x\r\nContent-Type: application/octet-stream\r\nContent-Length: {}\r\n\r\n",
                small.len()
            )
            .unwrap();
            c.write_all(&small).unwrap();
            // Long enough for the server to read the body and queue the trace.
            std::thread::sleep(std::time::Duration::from_millis(50));
            drop(c);
        }
        std::thread::sleep(std::time::Duration::from_millis(200));
        let r = s.req(
            "POST",
            &format!("/v1/scenes/{id}/render"),
            &[("Content-Type", "application/json")],
            br#"{"width": 8, "height": 8}"#,
        );
        let still_running = Metrics::scrape(&s).get("rayd_jobs_running") >= 1.0;
        assert!(
            still_running,
            "the long trace ended too soon to test anything"
        );
        assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
        assert_eq!(wait_job(&s, &holder, 60)["state"], "succeeded");
        let job = r.json()["id"].as_str().unwrap().to_string();
        assert_eq!(wait_job(&s, &job, 30)["state"], "succeeded");
    }
}

/// `Prefer: respond-async` on a trace: `202` and a job whose result is the HIT1 body a
/// synchronous trace answers; a body that the synchronous trace would refuse (over
/// `--max-rays`, truncated) is refused the same way before any job is made.
#[test]
fn async_traces_answer_as_sync_ones_and_refuse_bad_bodies_up_front() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(&dir.path().join("data"), &["--max-rays", "1000"]);
    let fox = s.upload_sample("Fox.glb");
    let id = fox["id"].as_str().unwrap().to_string();
    let min: Vec<f32> = serde_json::from_value(fox["bounds"]["min"].clone()).unwrap();
    let max: Vec<f32> = serde_json::from_value(fox["bounds"]["max"].clone()).unwrap();
    let rays = |n| {
        write_rays(&rays_at(
            [min[0], min[1], min[2]],
            [max[0], max[1], max[2]],
            n,
        ))
    };
    let path = format!("/v1/scenes/{id}/trace?accel=bvh2&hit=t_prim_uv");
    let octet = ("Content-Type", "application/octet-stream");
    let prefer = ("Prefer", "respond-async");
    let body = rays(1000);
    let sync = s.req("POST", &path, &[octet], &body);
    assert_eq!(sync.status, 200, "{}", String::from_utf8_lossy(&sync.body));
    let r = s.req("POST", &path, &[octet, prefer], &body);
    assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
    let job = r.json()["id"].as_str().unwrap().to_string();
    assert_eq!(wait_job(&s, &job, 60)["state"], "succeeded");
    let result = s.req("GET", &format!("/v1/jobs/{job}/result"), &[], &[]);
    assert_eq!(result.status, 200);
    assert_eq!(
        result.header("content-length"),
        Some(result.body.len().to_string().as_str())
    );
    assert!(
        result.body == sync.body,
        "the job's hits differ from the sync trace's"
    );
    // Idempotency-Key: a retry finds the first job; the same key with other rays is 409.
    let key = ("Idempotency-Key", "trace-once");
    let first = s.req("POST", &path, &[octet, prefer, key], &body);
    assert_eq!(
        first.status,
        202,
        "{}",
        String::from_utf8_lossy(&first.body)
    );
    let retry = s.req("POST", &path, &[octet, prefer, key], &body);
    assert_eq!(retry.status, 202);
    assert_eq!(retry.json()["id"], first.json()["id"]);
    let other = s.req("POST", &path, &[octet, prefer, key], &rays(999));
    assert_eq!(
        other.status,
        409,
        "{}",
        String::from_utf8_lossy(&other.body)
    );
    let job = first.json()["id"].as_str().unwrap().to_string();
    assert_eq!(wait_job(&s, &job, 60)["state"], "succeeded");

    let jobs_before = s.req("GET", "/v1/jobs", &[], &[]).json()["jobs"]
        .as_array()
        .unwrap()
        .len();
    // Rays 700 (a NaN origin) and 900 (no direction) are invalid.
    let mut invalid = rays_at([min[0], min[1], min[2]], [max[0], max[1], max[2]], 1000);
    invalid[700].org[0] = f32::NAN;
    invalid[900].dir = [0.0; 3];
    let invalid = write_rays(&invalid);
    for (what, bad, status) in [
        ("over --max-rays", rays(1001), 413),
        ("truncated", body[..body.len() - 5].to_vec(), 400),
        ("invalid rays", invalid.clone(), 422),
    ] {
        let sync = s.req("POST", &path, &[octet], &bad);
        assert_eq!(sync.status, status, "sync, {what}");
        let r = s.req("POST", &path, &[octet, prefer], &bad);
        assert_eq!(
            r.status,
            status,
            "async, {what}: {}",
            String::from_utf8_lossy(&r.body)
        );
        assert_eq!(r.header("content-type"), Some("application/problem+json"));
        if status == 422 {
            assert_eq!(
                (r.json()["ray_index"].as_u64(), r.json()["count"].as_u64()),
                (Some(700), Some(2))
            );
        }
    }
    // Under invalid=miss the same rays are answered, by a job.
    let r = s.req(
        "POST",
        &format!("{path}&invalid=miss"),
        &[octet, prefer],
        &invalid,
    );
    assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
    let job = r.json()["id"].as_str().unwrap().to_string();
    assert_eq!(wait_job(&s, &job, 60)["state"], "succeeded");
    let jobs_after = s.req("GET", "/v1/jobs", &[], &[]).json()["jobs"]
        .as_array()
        .unwrap()
        .len();
    assert_eq!(jobs_before + 1, jobs_after, "a refused body made a job");
}

/// Stops a test's background loops when dropped, also while an assertion unwinds: a scoped
/// thread looping on is joined before the panic goes on, and would hang the test.
struct StopOnDrop<'a>(&'a std::sync::atomic::AtomicBool);

impl Drop for StopOnDrop<'_> {
    fn drop(&mut self) {
        self.0.store(true, std::sync::atomic::Ordering::Relaxed);
    }
}

/// Copies of one keyed render sent at once, while geometry updates arrive and the queue
/// has one place left, all get the one job the first made: each copy used to look for the
/// key's job before any had made it, then take a queue place of its own (503) or fill in
/// a version made meanwhile (409, "a different request").
#[test]
fn copies_of_a_keyed_request_sent_at_once_get_one_job() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(
        &dir.path().join("data"),
        &[
            "--max-running",
            "1",
            "--max-queued",
            "2",
            "--keep-versions",
            "1",
            "--max-client-requests",
            "64",
        ],
    );
    let fox = s.upload_sample("Fox.glb");
    let id = fox["id"].as_str().unwrap().to_string();
    let long = br#"{"width": 512, "height": 512, "spp": 1024, "bounces": 4, "integrator": "path"}"#;
    let running = s.submit_render(&id, long);
    wait_running(&s, &running, 30);
    s.submit_render(&id, long);
    let positions = s
        .req("GET", &format!("/v1/scenes/{id}/geometry"), &[], &[])
        .body;
    let stop = std::sync::atomic::AtomicBool::new(false);
    std::thread::scope(|scope| {
        let _stop = StopOnDrop(&stop);
        let updates = scope.spawn(|| {
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                let r = s.req(
                    "PUT",
                    &format!("/v1/scenes/{id}/geometry"),
                    &[("Content-Type", "application/x-rayd-tri")],
                    &positions,
                );
                assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
            }
        });
        for round in 0..4 {
            let key = format!("at-once-{round}");
            let body = format!(r#"{{"width": 8, "height": 8, "seed": {round}}}"#);
            let answers: Vec<(u16, String)> = std::thread::scope(|inner| {
                (0..12)
                    .map(|_| {
                        let (s, key, body, id) = (&s, &key, &body, &id);
                        inner.spawn(move || {
                            let r = s.req(
                                "POST",
                                &format!("/v1/scenes/{id}/render"),
                                &[
                                    ("Content-Type", "application/json"),
                                    ("Idempotency-Key", key),
                                ],
                                body.as_bytes(),
                            );
                            (r.status, String::from_utf8_lossy(&r.body).into_owned())
                        })
                    })
                    .collect::<Vec<_>>()
                    .into_iter()
                    .map(|t| t.join().unwrap())
                    .collect()
            });
            let ids: std::collections::HashSet<String> = answers
                .iter()
                .map(|(status, body)| {
                    assert_eq!(*status, 202, "round {round}: {body}");
                    let job: serde_json::Value = serde_json::from_str(body).unwrap();
                    job["id"].as_str().unwrap().to_string()
                })
                .collect();
            assert_eq!(ids.len(), 1, "round {round}: {ids:?}");
            // The job took the queue's last place: cancelled, it frees it again.
            let job = ids.into_iter().next().unwrap();
            assert_eq!(
                s.req("DELETE", &format!("/v1/jobs/{job}"), &[], &[]).status,
                200
            );
            let t1 = Instant::now();
            while Metrics::scrape(&s).get("rayd_jobs_queued") > 1.0 {
                assert!(
                    t1.elapsed().as_secs() < 10,
                    "the cancelled job kept its place"
                );
                std::thread::sleep(Duration::from_millis(20));
            }
        }
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        updates.join().unwrap();
    });
}

/// A request that names no version takes whatever is latest, even while newer versions
/// delete it as it is read (`--keep-versions 1`, versions sent without pause): a reviewer's
/// renders of the latest answered 404 for a version they never named, half of them.
#[test]
fn requests_for_the_latest_version_never_miss_it_while_versions_arrive() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(&dir.path().join("data"), &["--keep-versions", "1"]);
    let fox = s.upload_sample("Fox.glb");
    let id = fox["id"].as_str().unwrap().to_string();
    let base = rayd::formats::binary::read_tri(
        &s.req("GET", &format!("/v1/scenes/{id}/geometry"), &[], &[])
            .body,
    )
    .unwrap();
    let rays = write_rays(&rays_at([-50.0, 0.0, -50.0], [50.0, 100.0, 50.0], 100));
    let stop = std::sync::atomic::AtomicBool::new(false);
    let put = |k: usize| {
        let mut n = 0u32;
        while !stop.load(std::sync::atomic::Ordering::Relaxed) {
            n += 1;
            let mut tris = base.clone();
            for t in &mut tris {
                for v in &mut t.v {
                    v[1] += (k * 100_000 + n as usize) as f32 * 1e-3;
                }
            }
            let r = s.req(
                "PUT",
                &format!("/v1/scenes/{id}/geometry"),
                &[("Content-Type", "application/x-rayd-tri")],
                &write_tri(&tris),
            );
            assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        }
    };
    std::thread::scope(|scope| {
        let _stop = StopOnDrop(&stop);
        let updates: Vec<_> = (0..2).map(|k| scope.spawn(move || put(k))).collect();
        let t0 = std::time::Instant::now();
        let (mut renders, mut traces) = (0, 0);
        while t0.elapsed() < Duration::from_secs(4) {
            let r = s.post_render(&id, br#"{"width": 4, "height": 4}"#);
            assert!(
                matches!(r.status, 202 | 503),
                "render: {} {}",
                r.status,
                String::from_utf8_lossy(&r.body)
            );
            renders += 1;
            let r = s.req(
                "POST",
                &format!("/v1/scenes/{id}/trace"),
                &[("Content-Type", "application/octet-stream")],
                &rays,
            );
            assert!(
                matches!(r.status, 200 | 503),
                "trace: {} {}",
                r.status,
                String::from_utf8_lossy(&r.body)
            );
            traces += 1;
        }
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        for u in updates {
            u.join().unwrap();
        }
        assert!(
            renders > 10 && traces > 10,
            "{renders} renders, {traces} traces"
        );
    });
}

/// With `--keep-versions 2` a scene keeps version 1, its two newest versions and the
/// versions a job names: an older version answers 404 to traces and to `GET …/geometry`,
/// in memory as on disk, and a version a finished job names outlives newer ones until
/// the job is deleted.
#[test]
fn old_geometry_versions_are_deleted_unless_a_job_names_them() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let s = Server::start(&data, &["--keep-versions", "2"]);
    let fox = s.upload_sample("Fox.glb");
    let id = fox["id"].as_str().unwrap().to_string();
    let geometry = s.req("GET", &format!("/v1/scenes/{id}/geometry"), &[], &[]);
    assert_eq!(geometry.status, 200);
    let base = rayd::formats::binary::read_tri(&geometry.body).unwrap();
    let body_of = |dy: f32| {
        let mut tris = base.clone();
        for t in &mut tris {
            for v in &mut t.v {
                v[1] += dy;
            }
        }
        write_tri(&tris)
    };
    // Where the store keeps a blob (`proto/store.md`: `blobs/ab/abcdef…`).
    let blob_file = |bytes: &[u8]| {
        let hex = blake3::hash(bytes).to_hex().to_string();
        data.join("blobs").join(&hex[..2]).join(hex)
    };
    let put = |dy: f32| {
        let r = s.req(
            "PUT",
            &format!("/v1/scenes/{id}/geometry"),
            &[("Content-Type", "application/x-rayd-tri")],
            &body_of(dy),
        );
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        r.json()["version"].as_i64().unwrap()
    };
    let body = write_rays(&rays_at([-50.0, 0.0, -50.0], [50.0, 100.0, 50.0], 200));
    let octet = [("Content-Type", "application/octet-stream")];
    let trace = |version: i64| {
        s.req(
            "POST",
            &format!("/v1/scenes/{id}/trace?version={version}"),
            &octet,
            &body,
        )
    };
    let status = |version: i64| trace(version).status;
    let geometry = |version: i64| {
        s.req(
            "GET",
            &format!("/v1/scenes/{id}/geometry?version={version}"),
            &[],
            &[],
        )
        .status
    };
    assert_eq!((put(1.0), put(2.0)), (2, 3));
    assert_eq!(status(2), 200, "version 2 is traced (and held in memory)");
    assert_eq!(put(3.0), 4);
    let gone = trace(2);
    assert_eq!(gone.status, 404, "{}", String::from_utf8_lossy(&gone.body));
    // The problem names the parameter, as a malformed version's does.
    assert_eq!(gone.json()["field"], "version");
    for never in [0, 99] {
        let r = trace(never);
        assert_eq!(
            (r.status, r.json()["field"].clone()),
            (404, "version".into())
        );
    }
    assert_eq!(geometry(2), 404);
    // Its blob goes at once, not after the collection's 15-minute grace.
    let t0 = Instant::now();
    while blob_file(&body_of(1.0)).exists() && t0.elapsed() < Duration::from_secs(10) {
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(
        !blob_file(&body_of(1.0)).exists(),
        "version 2's blob is still stored"
    );
    assert!(
        blob_file(&body_of(2.0)).exists(),
        "version 3's blob is kept"
    );
    // A stored version is answered with the bytes its PUT sent.
    let g3 = s.req(
        "GET",
        &format!("/v1/scenes/{id}/geometry?version=3"),
        &[],
        &[],
    );
    assert!(
        g3.body == body_of(2.0),
        "version 3's geometry is not what was PUT"
    );
    assert_eq!(g3.header("content-type"), Some("application/x-rayd-tri"));
    for v in [1, 3, 4] {
        assert_eq!((status(v), geometry(v)), (200, 200), "version {v}");
    }
    // A render job on version 3 keeps it past versions 5 and 6.
    let job = s.submit_render(
        &id,
        br#"{"width": 8, "height": 8, "integrator": "primary", "version": 3}"#,
    );
    assert_eq!(wait_job(&s, &job, 60)["state"], "succeeded");
    assert_eq!((put(4.0), put(5.0)), (5, 6));
    assert_eq!(status(3), 200, "version 3 is named by a job");
    assert_eq!(status(4), 404);
    let del = s.req("DELETE", &format!("/v1/jobs/{job}"), &[], &[]);
    assert_eq!(del.status, 204, "{}", String::from_utf8_lossy(&del.body));
    assert_eq!(put(6.0), 7);
    assert_eq!(
        status(3),
        404,
        "version 3 went with its job at the next version"
    );
    for v in [1, 6, 7] {
        assert_eq!(status(v), 200, "version {v}");
    }
}

/// SIGTERM while a render runs: the server refuses new work, lets the render finish within
/// `--grace` (the test servers' 2 s; the render takes a few tenths), records its end, and
/// only then exits; after a restart the job is `succeeded` with its result, not queued
/// again.
#[test]
fn sigterm_lets_a_running_render_finish_within_the_grace_period() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let s = Server::start(&data, &[]);
    let id = s.upload_sample("Fox.glb")["id"]
        .as_str()
        .unwrap()
        .to_string();
    let r = s.req(
        "POST",
        &format!("/v1/scenes/{id}/render"),
        &[("Content-Type", "application/json")],
        br#"{"width": 256, "height": 256, "spp": 48, "integrator": "path"}"#,
    );
    assert_eq!(r.status, 202);
    let job = r.json()["id"].as_str().unwrap().to_string();
    wait_running(&s, &job, 30);
    // `stop` sends SIGTERM and waits for the exit.
    s.stop();
    let s = Server::start(&data, &[]);
    let j = s.req("GET", &format!("/v1/jobs/{job}"), &[], &[]).json();
    assert_eq!(j["state"], "succeeded", "{j}");
    let png = s.req("GET", &format!("/v1/jobs/{job}/result"), &[], &[]);
    assert_eq!((png.status, &png.body[1..4]), (200, &b"PNG"[..]));
}

/// A second SIGTERM or SIGINT ends the grace period at once: with `--grace 60` and a render
/// that would take longer, the server exits within seconds of the second signal, and the
/// render, left `running` in the store, is queued again at the next start (not lost).
#[test]
fn a_second_signal_ends_the_grace_period() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let s = Server::start(&data, &["--grace", "60"]);
    let id = s.upload_sample("Fox.glb")["id"]
        .as_str()
        .unwrap()
        .to_string();
    let job = s.submit_render(
        &id,
        br#"{"width": 512, "height": 512, "spp": 4096, "integrator": "path"}"#,
    );
    wait_running(&s, &job, 30);
    s.signal("TERM");
    std::thread::sleep(Duration::from_millis(500));
    assert!(
        s.try_request("GET", "/healthz", &[], &[]).is_err(),
        "no longer accepting after the first signal"
    );
    let mut s = s;
    assert!(
        s.child.try_wait().unwrap().is_none(),
        "the first signal waits for the render"
    );
    let t0 = Instant::now();
    s.signal("INT");
    s.wait_exit();
    assert!(
        t0.elapsed() < Duration::from_secs(10),
        "exited {:?} after the second signal",
        t0.elapsed()
    );
    let s = Server::start(&data, &[]);
    let j = s.req("GET", &format!("/v1/jobs/{job}"), &[], &[]).json();
    assert!(
        j["state"] == "queued" || j["state"] == "running",
        "queued again: {j}"
    );
    let r = s.req("DELETE", &format!("/v1/jobs/{job}"), &[], &[]);
    assert_eq!(r.status, 200);
}

/// `POST …/frame`: positions and rays in one request answer what a `PUT` of the positions
/// and a trace of the new version answer, and what `rayd trace` answers on those triangles;
/// a frame refused for its positions records no version, one refused for its rays has
/// made its version and says which.
#[test]
fn a_frame_updates_the_geometry_and_traces_it_in_one_request() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let s = Server::start(&data, &[]);
    let fox = s.upload_sample("Fox.glb");
    let id = fox["id"].as_str().unwrap().to_string();
    let base = rayd::formats::binary::read_tri(
        &s.req("GET", &format!("/v1/scenes/{id}/geometry"), &[], &[])
            .body,
    )
    .unwrap();
    let moved = |dy: f32| {
        let mut tris = base.clone();
        for t in &mut tris {
            for v in &mut t.v {
                v[1] += dy;
            }
        }
        tris
    };
    let rays = rays_at([-50.0, 0.0, -50.0], [50.0, 100.0, 50.0], 3000);
    let ray1 = write_rays(&rays);
    let frame_type = [("Content-Type", "application/x-rayd-frame")];
    let frame = |tri: &[u8], ray: &[u8], query: &str| {
        let body = [tri, ray].concat();
        s.req(
            "POST",
            &format!("/v1/scenes/{id}/frame{query}"),
            &frame_type,
            &body,
        )
    };
    let version = || {
        s.req("GET", &format!("/v1/scenes/{id}"), &[], &[]).json()["version"]
            .as_i64()
            .unwrap()
    };

    // The frame, then the same trace of the version it made, then `rayd trace` on a TRI1
    // file of the same positions: the same bytes.
    let tris = moved(7.0);
    let tri1 = write_tri(&tris);
    let r = frame(&tri1, &ray1, "?accel=dacrt");
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.header("x-rayd-version"), Some("2"));
    assert_eq!(r.header("x-rayd-accel"), Some("dacrt"));
    assert!(r.header("server-timing").is_some());
    assert_eq!(version(), 2);
    let again = s.req(
        "POST",
        &format!("/v1/scenes/{id}/trace?version=2&accel=mbvh8"),
        &[("Content-Type", "application/octet-stream")],
        &ray1,
    );
    assert_eq!(again.status, 200);
    assert_eq!(
        r.body, again.body,
        "the frame answers as a trace of its version"
    );
    let files = dir.path();
    std::fs::write(files.join("v2.tri"), &tri1).unwrap();
    std::fs::write(files.join("rays.ray"), &ray1).unwrap();
    cli_trace(
        &files.join("v2.tri"),
        &files.join("rays.ray"),
        &files.join("v2.hit"),
        ["closest", "t_prim_uv", "mbvh8"],
    );
    assert_eq!(std::fs::read(files.join("v2.hit")).unwrap(), r.body);
    assert!(
        r.body[16..]
            .chunks(16)
            .any(|h| h[..4] != f32::INFINITY.to_le_bytes()),
        "some rays hit"
    );

    // Frames refused for their positions record nothing: positions for another scene,
    // positions with a NaN, cut-off positions, another media type, a trace's query.
    let mut nan_tri = tri1.clone();
    nan_tri[16 + 36 * 5..16 + 36 * 5 + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    let short = write_tri(&tris[..tris.len() - 1]);
    for (tri, ray, query, status, place) in [
        (
            &short[..],
            &ray1[..],
            "",
            422,
            ("field", serde_json::json!("count")),
        ),
        (
            &nan_tri,
            &ray1,
            "",
            400,
            ("byte_offset", serde_json::json!(16 + 36 * 5)),
        ),
        (
            &tri1[..100],
            &[][..],
            "",
            400,
            ("byte_offset", serde_json::json!(100)),
        ),
        (
            &tri1,
            &ray1,
            "?version=1",
            400,
            ("field", serde_json::json!("version")),
        ),
    ] {
        let r = frame(tri, ray, query);
        assert_eq!(r.status, status, "{}", String::from_utf8_lossy(&r.body));
        assert_eq!(
            r.json()[place.0],
            place.1,
            "{}",
            String::from_utf8_lossy(&r.body)
        );
    }
    let r = s.req(
        "POST",
        &format!("/v1/scenes/{id}/frame"),
        &[("Content-Type", "application/octet-stream")],
        &ray1,
    );
    assert_eq!(r.status, 415);
    assert_eq!(
        version(),
        2,
        "a frame refused for its positions recorded a version"
    );
    // Frames refused for their rays have made their versions, as a `PUT` and a refused
    // trace would, and say which; byte offsets count from the body's start.
    let mut bad_rays = rays.clone();
    bad_rays[9].dir = [0.0; 3];
    let cut = &ray1[..ray1.len() - 3];
    let tri_len = tri1.len() as u64;
    for (ray, status, place, made) in [
        (
            &write_rays(&bad_rays)[..],
            422,
            ("ray_index", serde_json::json!(9)),
            3,
        ),
        (
            cut,
            400,
            ("byte_offset", serde_json::json!(tri_len + cut.len() as u64)),
            4,
        ),
    ] {
        let r = frame(&tri1, ray, "");
        assert_eq!(r.status, status, "{}", String::from_utf8_lossy(&r.body));
        assert_eq!(
            r.json()[place.0],
            place.1,
            "{}",
            String::from_utf8_lossy(&r.body)
        );
        assert_eq!(
            r.json()["version"],
            made,
            "{}",
            String::from_utf8_lossy(&r.body)
        );
        assert_eq!(version(), made);
    }

    // `invalid=miss` answers the bad ray as a miss.
    let r = frame(&tri1, &write_rays(&bad_rays), "?invalid=miss");
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.header("x-rayd-version"), Some("5"));

    // Versions made by frames survive a restart, as a `PUT`'s do.
    s.stop();
    let s = Server::start(&data, &[]);
    let v2 = s.req(
        "POST",
        &format!("/v1/scenes/{id}/trace?version=2"),
        &[("Content-Type", "application/octet-stream")],
        &ray1,
    );
    assert_eq!(v2.status, 200);
    assert_eq!(v2.body, std::fs::read(files.join("v2.hit")).unwrap());
}

/// A frame whose queue filled while its positions arrived is refused before it makes a
/// version: 503 with `Retry-After`, no version recorded, no `version` in the problem. Its
/// trace takes its place in the queue before the positions become a version (until
/// session 36 the version was made and then the trace refused, so that a client that
/// sent the frame again made another).
#[test]
fn a_frame_that_finds_the_queue_full_makes_no_version() {
    use std::io::{Read, Write};
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(&dir.path().join("data"), &["--max-queued", "1"]);
    let tris = slow_grid();
    let id = s.upload_tri(&tris)["id"].as_str().unwrap().to_string();
    let version = || {
        s.req("GET", &format!("/v1/scenes/{id}"), &[], &[]).json()["version"]
            .as_i64()
            .unwrap()
    };
    let rays = |n| write_rays(&rays_at([0.0, 0.0, -1.0], [1.0, 1.0, 1.0], n));
    let holder = s.req(
        "POST",
        &format!("/v1/scenes/{id}/trace?accel=brute"),
        &[
            ("Content-Type", "application/octet-stream"),
            ("Prefer", "respond-async"),
        ],
        &rays(40_000),
    );
    assert_eq!(holder.status, 202);
    let holder = holder.json()["id"].as_str().unwrap().to_string();
    wait_running(&s, &holder, 30);
    // The frame's head and half its positions: the queue has room then.
    let tri1 = write_tri(&tris);
    let body = [tri1.clone(), rays(100)].concat();
    let mut c = std::net::TcpStream::connect(&s.addr).unwrap();
    write!(
        c,
        "POST /v1/scenes/{id}/frame HTTP/1.1\r\nHost: x\r\nContent-Type: application/x-rayd-frame\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    )
    .unwrap();
    c.write_all(&body[..tri1.len() / 2]).unwrap();
    // Until the server reads the body (its head checked, the queue then with room).
    let start = Instant::now();
    while Metrics::scrape(&s).get("rayd_request_body_bytes_in_flight") <= 0.0 {
        assert!(
            start.elapsed().as_secs() < 30,
            "the frame's body was never read"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    // A render takes the queue's one place behind the long trace.
    let r = s.req(
        "POST",
        &format!("/v1/scenes/{id}/render"),
        &[("Content-Type", "application/json")],
        br#"{"width": 8, "height": 8}"#,
    );
    assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
    let render = r.json()["id"].as_str().unwrap().to_string();
    c.write_all(&body[tri1.len() / 2..]).unwrap();
    let mut answer = Vec::new();
    c.read_to_end(&mut answer).unwrap();
    let answer = String::from_utf8_lossy(&answer).to_string();
    let still_running =
        s.req("GET", &format!("/v1/jobs/{holder}"), &[], &[]).json()["state"] == "running";
    assert!(
        still_running,
        "the long trace ended too soon to test anything"
    );
    assert!(answer.starts_with("HTTP/1.1 503"), "{answer}");
    assert!(
        answer.to_ascii_lowercase().contains("retry-after:"),
        "{answer}"
    );
    let problem: serde_json::Value =
        serde_json::from_str(answer.split("\r\n\r\n").nth(1).unwrap()).unwrap();
    assert!(problem.get("version").is_none(), "{problem}");
    assert_eq!(
        version(),
        1,
        "a frame refused for a full queue made a version"
    );
    assert_eq!(wait_job(&s, &holder, 60)["state"], "succeeded");
    assert_eq!(wait_job(&s, &render, 30)["state"], "succeeded");
    // With room again, the same frame makes version 2.
    let r = s.req(
        "POST",
        &format!("/v1/scenes/{id}/frame"),
        &[("Content-Type", "application/x-rayd-frame")],
        &body,
    );
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.header("x-rayd-version"), Some("2"));
}

/// A scene whose stored file was damaged in place (same size, one byte flipped) is
/// mended by uploading its bytes again, before or after a read has found the damage:
/// the re-upload hashes the stored copy rather than trusting its size.
#[test]
fn uploading_the_same_bytes_again_mends_a_damaged_scene() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let bytes = std::fs::read(scenes().join("Box.glb")).unwrap();
    let upload = |s: &Server| {
        s.req(
            "POST",
            "/v1/scenes",
            &[("Content-Type", "model/gltf-binary")],
            &bytes,
        )
    };
    let s = Server::start(&data, &[]);
    let id = s.upload_sample("Box.glb")["id"]
        .as_str()
        .unwrap()
        .to_owned();
    s.stop();
    let file = data.join("blobs").join(&id[..2]).join(&id);
    let mut damaged = std::fs::read(&file).unwrap();
    let mid = damaged.len() / 2;
    damaged[mid] ^= 0xff;
    std::fs::write(&file, &damaged).unwrap();
    let s = Server::start(&data, &[]);
    assert_eq!(upload(&s).status, 200);
    assert_eq!(
        std::fs::read(&file).unwrap(),
        bytes,
        "the copy was not written again"
    );
    let r = s.req("GET", &format!("/v1/scenes/{id}/geometry"), &[], &[]);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
}

/// A scene without animation has one pose: traces at any `time=` share its structure
/// (each time made one of its own, never found again, crowding the cache).
#[test]
fn times_of_a_static_scene_share_one_structure() {
    let dir = tempfile::tempdir().unwrap();
    let s = Server::start(&dir.path().join("data"), &[]);
    let scene = s.upload_sample("Box.glb");
    let id = scene["id"].as_str().unwrap().to_string();
    let min: Vec<f32> = serde_json::from_value(scene["bounds"]["min"].clone()).unwrap();
    let max: Vec<f32> = serde_json::from_value(scene["bounds"]["max"].clone()).unwrap();
    let body = write_rays(&rays_at(
        [min[0], min[1], min[2]],
        [max[0], max[1], max[2]],
        1000,
    ));
    let misses = || {
        let metrics = String::from_utf8(s.req("GET", "/metrics", &[], &[]).body).unwrap();
        let line = metrics
            .lines()
            .find(|l| l.starts_with("rayd_cache_misses_total "))
            .map(str::to_string);
        line.unwrap()
    };
    let mut answers = Vec::new();
    let mut after_first = String::new();
    for (k, time) in ["", "&time=0.1", "&time=7", "&time=1e9"].iter().enumerate() {
        let r = s.req(
            "POST",
            &format!("/v1/scenes/{id}/trace?accel=mbvh8{time}"),
            &[("Content-Type", "application/octet-stream")],
            &body,
        );
        assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
        let timing = r.header("server-timing").unwrap().to_string();
        if k > 0 {
            assert!(timing.contains("build;dur=0.000"), "{time}: {timing}");
        }
        answers.push(r.body);
        if k == 0 {
            after_first = misses();
        }
    }
    assert!(answers.iter().all(|a| *a == answers[0]));
    assert_eq!(misses(), after_first);
}
