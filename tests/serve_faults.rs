//! Faults against a real `rayd serve`: a `kill -9` in the middle of an upload (a slow client
//! half-way through a big body) and of geometry updates, and a data directory that fills up
//! (`--max-store-bytes`, which fails as a full disk does). After each, what the service
//! acknowledged is intact, nothing half-written is visible, and the same bytes can be sent
//! again (`proto/store.md`, `proto/service.md`).

use std::io::Write;
use std::path::Path;
use std::time::Duration;

use rayd::formats::binary::{write_rays, write_tri};
use rayd::geometry::{Ray, Triangle};

#[path = "common/server.rs"]
mod server;
use server::{read_resp, Resp, Server};

const TRI: [(&str, &str); 1] = [("Content-Type", "application/x-rayd-tri")];
const OCTET: [(&str, &str); 1] = [("Content-Type", "application/octet-stream")];

/// A `cells × cells` grid of right triangles (two a cell) over the unit square, at height
/// `z`, stretched by `sx` along x: every version of a scene is told apart by `z` and `sx`.
fn grid(cells: usize, z: f32, sx: f32) -> Vec<Triangle> {
    let h = 1.0 / cells as f32;
    let mut out = Vec::with_capacity(2 * cells * cells);
    for i in 0..cells {
        for j in 0..cells {
            let (x, y) = (i as f32 * h * sx, j as f32 * h);
            let (x1, y1) = (x + h * sx, y + h);
            out.push(Triangle {
                v: [[x, y, z], [x1, y, z], [x, y1, z]],
            });
            out.push(Triangle {
                v: [[x1, y, z], [x1, y1, z], [x, y1, z]],
            });
        }
    }
    out
}

/// Rays straight up (+z) from below the unit square, spread over it.
fn rays_up(n: usize) -> Vec<u8> {
    let rays: Vec<Ray> = (0..n)
        .map(|i| {
            let u = (i as f32 * 0.618_034).fract();
            let v = (i as f32 * 0.414_213_5 + 0.5 / n as f32).fract();
            Ray {
                org: [u, v, -5.0],
                tmin: 0.0,
                dir: [0.0, 0.0, 1.0],
                tmax: f32::INFINITY,
            }
        })
        .collect();
    write_rays(&rays)
}

fn trace(s: &Server, id: &str, version: i64, rays: &[u8]) -> Vec<u8> {
    let r = s.req(
        "POST",
        &format!("/v1/scenes/{id}/trace?version={version}&hit=t_prim"),
        &OCTET,
        rays,
    );
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    r.body
}

/// The ids of every listed scene (the first page is all of them here).
fn listed(s: &Server) -> Vec<String> {
    let r = s.req("GET", "/v1/scenes?limit=100", &[], &[]);
    assert_eq!(r.status, 200);
    let mut ids: Vec<String> = r.json()["scenes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["id"].as_str().unwrap().to_string())
        .collect();
    ids.sort();
    ids
}

fn upload(s: &Server, body: &[u8]) -> Resp {
    s.req("POST", "/v1/scenes", &TRI, body)
}

/// Every file under `blobs/` is a finished blob: no staged or temporary file is left.
fn no_partial_blobs(data: &Path) {
    let root = data.join("blobs");
    for shard in std::fs::read_dir(&root).unwrap() {
        let shard = shard.unwrap();
        for f in std::fs::read_dir(shard.path()).unwrap() {
            let name = f.unwrap().file_name().to_string_lossy().to_string();
            assert!(
                name.len() >= 32 && name.bytes().all(|b| b.is_ascii_hexdigit()),
                "a half-written file is left in {}: {name}",
                shard.path().display()
            );
        }
    }
}

#[test]
fn kill_9_during_an_upload_and_during_geometry_updates() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let rays = rays_up(4096);
    let s = Server::start(&data, &[]);

    // An acknowledged scene, and its answer.
    let small = write_tri(&grid(20, 0.0, 1.0));
    let r = upload(&s, &small);
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let small_id = r.json()["id"].as_str().unwrap().to_string();
    let small_hits = trace(&s, &small_id, 1, &rays);

    // A slow client: half of a 10 MB body, a pause, then the server dies under it.
    let big = write_tri(&grid(380, 0.0, 1.0));
    let mut c = s
        .open("POST", "/v1/scenes", &TRI, big.len())
        .expect("connect");
    for chunk in big[..big.len() / 2].chunks(64 << 10) {
        c.write_all(chunk).unwrap();
        std::thread::sleep(Duration::from_millis(2));
    }
    std::thread::sleep(Duration::from_millis(200));
    s.kill9();
    assert!(
        c.write_all(&big[big.len() / 2..])
            .and_then(|()| read_resp(c).map(|_| ()))
            .is_err(),
        "a dead server cannot have answered"
    );

    let s = Server::start(&data, &[]);
    assert_eq!(
        listed(&s),
        vec![small_id.clone()],
        "only the complete scene"
    );
    assert_eq!(trace(&s, &small_id, 1, &rays), small_hits);
    no_partial_blobs(&data);
    // The same bytes again: a new scene (201: nothing of the first try was kept), then 200.
    let r = upload(&s, &big);
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let big_id = r.json()["id"].as_str().unwrap().to_string();
    assert_eq!(upload(&s, &big).status, 200);

    // One acknowledged geometry update; then updates with a kill -9 right behind them, at
    // several moments of their handling (before, during or after their commit).
    let n = 2 * 380 * 380;
    let v2 = write_tri(&grid(380, 1.0, 1.0));
    let r = s.req("PUT", &format!("/v1/scenes/{big_id}/geometry"), &TRI, &v2);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["version"], 2);
    let acknowledged = [
        (1, trace(&s, &big_id, 1, &rays)),
        (2, trace(&s, &big_id, 2, &rays)),
    ];
    assert_ne!(acknowledged[0].1, acknowledged[1].1);
    let mut s = s;
    let mut version = 2;
    for (k, delay_ms) in [0u64, 40, 150, 400].into_iter().enumerate() {
        let tris = grid(380, 2.0 + k as f32, 0.5 + 0.1 * k as f32);
        assert_eq!(tris.len(), n);
        let body = write_tri(&tris);
        let mut c = s
            .open(
                "PUT",
                &format!("/v1/scenes/{big_id}/geometry"),
                &TRI,
                body.len(),
            )
            .unwrap();
        c.write_all(&body).unwrap();
        std::thread::sleep(Duration::from_millis(delay_ms));
        s.kill9();
        drop(c);

        s = Server::start(&data, &[]);
        no_partial_blobs(&data);
        assert_eq!(listed(&s).len(), 2, "the two complete scenes");
        let now = s
            .req("GET", &format!("/v1/scenes/{big_id}"), &[], &[])
            .json();
        let after = now["version"].as_i64().unwrap();
        assert!(
            after == version || after == version + 1,
            "version {after} after the kill, {version} before"
        );
        for (v, hits) in &acknowledged {
            assert_eq!(&trace(&s, &big_id, *v, &rays), hits, "version {v}");
        }
        if after > version {
            // The update was committed: all of it, the same answers as the same triangles
            // uploaded as a scene of their own.
            let r = upload(&s, &body);
            assert_eq!(r.status, 201);
            let fresh = r.json()["id"].as_str().unwrap().to_string();
            assert_eq!(
                trace(&s, &big_id, after, &rays),
                trace(&s, &fresh, 1, &rays),
                "version {after} is whole"
            );
            let d = s.req("DELETE", &format!("/v1/scenes/{fresh}"), &[], &[]);
            assert_eq!(d.status, 204);
        } else {
            let r = s.req(
                "POST",
                &format!("/v1/scenes/{big_id}/trace?version={}", version + 1),
                &OCTET,
                &rays,
            );
            assert_eq!(r.status, 404, "an uncommitted version is not visible");
        }
        version = after;
    }
    // Updates still work after all that, numbered on from the last committed one.
    let r = s.req("PUT", &format!("/v1/scenes/{big_id}/geometry"), &TRI, &v2);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["version"], version + 1);
    assert_eq!(trace(&s, &big_id, version + 1, &rays), acknowledged[1].1);
    s.stop();
}

#[test]
fn a_full_store_answers_507_keeps_nothing_half_written_and_recovers() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    // Room for a small scene and one geometry version of it (36 KB each), not for more.
    let quota = "100000";
    let s = Server::start(&data, &["--max-store-bytes", quota]);
    let rays = rays_up(1024);

    let small = write_tri(&grid(22, 0.0, 1.0));
    assert!(small.len() > 34_000 && small.len() < 36_000);
    let r = upload(&s, &small);
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let id = r.json()["id"].as_str().unwrap().to_string();
    let v1 = trace(&s, &id, 1, &rays);

    // An upload past the quota: 507 as problem+json, and no scene.
    let big = write_tri(&grid(120, 0.0, 1.0));
    let r = upload(&s, &big);
    assert_eq!(r.status, 507, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.header("content-type"), Some("application/problem+json"));
    let p = r.json();
    assert_eq!(p["status"], 507);
    assert!(
        p["type"].as_str().unwrap().contains("insufficient-storage"),
        "{p}"
    );
    assert_eq!(listed(&s), vec![id.clone()]);
    no_partial_blobs(&data);

    // Geometry updates: the first fits, the second does not and leaves the version alone.
    let v2 = write_tri(&grid(22, 1.0, 1.0));
    let r = s.req("PUT", &format!("/v1/scenes/{id}/geometry"), &TRI, &v2);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    let v3 = write_tri(&grid(22, 2.0, 1.0));
    let r = s.req("PUT", &format!("/v1/scenes/{id}/geometry"), &TRI, &v3);
    assert_eq!(r.status, 507, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.header("content-type"), Some("application/problem+json"));
    let now = s.req("GET", &format!("/v1/scenes/{id}"), &[], &[]).json();
    assert_eq!(now["version"], 2);
    no_partial_blobs(&data);
    // A full store still answers what needs no new bytes.
    assert_eq!(trace(&s, &id, 1, &rays), v1);
    assert_eq!(s.req("GET", "/readyz", &[], &[]).status, 200);

    // The same quota after a restart counts what is stored: still full.
    s.stop();
    let s = Server::start(&data, &["--max-store-bytes", quota]);
    assert_eq!(upload(&s, &big).status, 507);
    s.stop();

    // Space freed (a larger quota): the refused bytes go in whole, and so does the update.
    let s = Server::start(&data, &["--max-store-bytes", "100000000"]);
    let r = upload(&s, &big);
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let big_id = r.json()["id"].as_str().unwrap().to_string();
    let mut both = vec![id.clone(), big_id];
    both.sort();
    assert_eq!(listed(&s), both);
    let r = s.req("PUT", &format!("/v1/scenes/{id}/geometry"), &TRI, &v3);
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["version"], 3);
    assert_eq!(trace(&s, &id, 1, &rays), v1);
    s.stop();

    // A quota of 0 is refused at the start, with its name.
    let out = std::process::Command::new(server::BIN)
        .args([
            "serve",
            "--addr",
            "127.0.0.1:0",
            "--max-store-bytes",
            "0",
            "--data-dir",
        ])
        .arg(dir.path().join("other"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("max-store-bytes"));
}
