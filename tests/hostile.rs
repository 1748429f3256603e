//! Hostile input to `rayd serve` (and to `rayd info` where a file is read from disk): the
//! catalogue of `proto/service.md`, "Hostile input". Every case checks its status code, that
//! the problem document names what was wrong, and that the server still serves afterwards
//! and lost nothing (the scene uploaded first is still there, unchanged, and no refused
//! upload left a scene behind).
//!
//! The server runs with short timeouts (`--header-timeout 1 --body-timeout 1`) so that the
//! slow-client cases take seconds, and a small body limit so that "too large" is cheap.

#[path = "common/server.rs"]
mod server;

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use base64::Engine as _;
use serde_json::{json, Value};
use server::{scenes, wait_job, Resp, Server, BIN};

const GLB: &str = "model/gltf-binary";
const GLTF: &str = "model/gltf+json";
const MAX_BODY: usize = 8 << 20;

/// A server with the short timeouts and small limits of these tests, and one good scene.
struct Fixture {
    server: Server,
    good: String,
    _dir: tempfile::TempDir,
}

impl Fixture {
    fn start(extra: &[&str]) -> Fixture {
        let dir = tempfile::tempdir().unwrap();
        let max_body = MAX_BODY.to_string();
        let mut args = vec![
            "--header-timeout",
            "1",
            "--body-timeout",
            "1",
            "--max-body",
            &max_body,
            "--max-inflight-bytes",
            "33554432",
            "--max-client-requests",
            "0",
        ];
        args.extend_from_slice(extra);
        let server = Server::start(&dir.path().join("data"), &args);
        let box_glb = std::fs::read(scenes().join("Box.glb")).unwrap();
        let r = server.req("POST", "/v1/scenes", &[("Content-Type", GLB)], &box_glb);
        assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
        let good = r.json()["id"].as_str().unwrap().to_owned();
        Fixture {
            server,
            good,
            _dir: dir,
        }
    }

    fn upload(&self, content_type: &str, body: &[u8]) -> Resp {
        self.server.req(
            "POST",
            "/v1/scenes",
            &[("Content-Type", content_type)],
            body,
        )
    }

    /// The server answers, and holds exactly the good scene, unchanged.
    fn intact(&self) {
        let t0 = Instant::now();
        let health = loop {
            match self.server.try_request("GET", "/healthz", &[], &[]) {
                Ok(r) => break r,
                Err(e) if t0.elapsed() < Duration::from_secs(10) => {
                    eprintln!("healthz: {e}; again");
                    std::thread::sleep(Duration::from_millis(100));
                }
                Err(e) => panic!("the server no longer answers: {e}"),
            }
        };
        assert_eq!(health.status, 200);
        let list = self.server.req("GET", "/v1/scenes", &[], &[]).json();
        let ids: Vec<&str> = list["scenes"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s["id"].as_str().unwrap())
            .collect();
        assert_eq!(ids, [self.good.as_str()], "scenes after the attacks");
        let scene = self
            .server
            .req("GET", &format!("/v1/scenes/{}", self.good), &[], &[]);
        assert_eq!(scene.status, 200);
        assert_eq!(scene.json()["triangles"], 12);
    }
}

/// `r` is a problem document of `status` whose detail contains every one of `words`.
#[track_caller]
fn problem(r: &Resp, status: u16, words: &[&str]) -> Value {
    let text = String::from_utf8_lossy(&r.body).to_string();
    assert_eq!(r.status, status, "{text}");
    assert_eq!(
        r.header("content-type"),
        Some("application/problem+json"),
        "{text}"
    );
    let p = r.json();
    assert_eq!(p["status"], status);
    let detail = p["detail"].as_str().unwrap_or_default();
    for w in words {
        assert!(detail.contains(w), "detail {detail:?} does not say {w:?}");
    }
    p
}

fn b64(bytes: &[u8]) -> String {
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// One triangle, its 36 bytes of positions embedded as a `data:` URI.
fn triangle_doc() -> Value {
    let pos: Vec<u8> = [0f32, 0., 0., 1., 0., 0., 0., 1., 0.]
        .iter()
        .flat_map(|f| f.to_le_bytes())
        .collect();
    json!({
        "asset": {"version": "2.0"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                       "min": [0, 0, 0], "max": [1, 1, 0]}],
        "bufferViews": [{"buffer": 0, "byteLength": 36}],
        "buffers": [{"byteLength": 36,
                     "uri": format!("data:application/octet-stream;base64,{}", b64(&pos))}],
    })
}

fn bytes_of(v: &Value) -> Vec<u8> {
    serde_json::to_vec(v).unwrap()
}

#[test]
fn the_triangle_document_itself_is_accepted() {
    // The documents below are this one with one thing broken: it must load as it is.
    let f = Fixture::start(&[]);
    let r = f.upload(GLTF, &bytes_of(&triangle_doc()));
    assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
    let id = r.json()["id"].as_str().unwrap().to_owned();
    let r = f
        .server
        .req("DELETE", &format!("/v1/scenes/{id}"), &[], &[]);
    assert!(r.status == 204 || r.status == 200, "{}", r.status);
    f.intact();
}

#[test]
fn documents_that_ask_for_too_much() {
    let f = Fixture::start(&[]);

    // JSON nested a million deep, as a scene (at the top, and in a member that glTF does
    // not know, which the parser skips without recursing: the document is then refused for
    // what it lacks) and as a render's options.
    let deep = format!("{}{}", "[".repeat(1_000_000), "]".repeat(1_000_000));
    problem(
        &f.upload(GLTF, deep.as_bytes()),
        400,
        &["invalid glTF JSON"],
    );
    let skipped = format!(r#"{{"scenes": [{{"nodes": []}}], "unknown": {deep}}}"#);
    problem(
        &f.upload(GLTF, skipped.as_bytes()),
        400,
        &["invalid glTF JSON", "asset"],
    );
    let deep_obj = format!("{}1{}", "{\"a\":".repeat(300_000), "}".repeat(300_000));
    let r = f.server.req(
        "POST",
        &format!("/v1/scenes/{}/render", f.good),
        &[("Content-Type", "application/json")],
        deep_obj.as_bytes(),
    );
    problem(&r, 400, &["JSON"]);

    // Counts in the billions: accessor elements, sparse entries, accessors without a view,
    // node references.
    let mut d = triangle_doc();
    d["accessors"][0]["count"] = json!(3_000_000_000u64);
    problem(
        &f.upload(GLTF, &bytes_of(&d)),
        400,
        &["accessor 0", "bufferView 0"],
    );
    let mut d = triangle_doc();
    d["accessors"][0]["sparse"] = json!({
        "count": 2_999_999_999u64,
        "indices": {"bufferView": 0, "componentType": 5125},
        "values": {"bufferView": 0},
    });
    problem(
        &f.upload(GLTF, &bytes_of(&d)),
        400,
        &["accessor 0", "sparse"],
    );
    let mut d = triangle_doc();
    d["accessors"][0] = json!({"componentType": 5126, "count": 3_000_000_000u64, "type": "VEC3"});
    problem(
        &f.upload(GLTF, &bytes_of(&d)),
        400,
        &["accessor 0", "limit"],
    );
    let mut d = triangle_doc();
    d["scenes"][0]["nodes"] = json!([4_000_000_000u64]);
    problem(
        &f.upload(GLTF, &bytes_of(&d)),
        400,
        &["node 4000000000", "the file has 1"],
    );
    let mut d = triangle_doc();
    d["nodes"][0]["children"] = json!([3_000_000_000u64]);
    problem(&f.upload(GLTF, &bytes_of(&d)), 400, &["node", "3000000000"]);

    // An instancing explosion: 30000 nodes place one mesh of 10000 triangles (its positions
    // an accessor without a view, which costs no file bytes): 3 * 10^8 triangles from a
    // 400 KB file, more than the loader's limit, refused before anything is allocated. And
    // 7000 nodes, 7 * 10^7 triangles (2.5 GiB of positions): under the loader's 2^28 but over
    // the service's --max-triangles (2^26).
    let mut d = triangle_doc();
    d["accessors"][0] = json!({"componentType": 5126, "count": 30000, "type": "VEC3"});
    let nodes: Vec<Value> = (0..30000).map(|_| json!({"mesh": 0})).collect();
    d["scenes"][0]["nodes"] = json!((0..30000).collect::<Vec<u32>>());
    d["nodes"] = json!(nodes);
    let t0 = Instant::now();
    problem(
        &f.upload(GLTF, &bytes_of(&d)),
        400,
        &["300000000 triangles", "limit of 67108864"],
    );
    d["scenes"][0]["nodes"] = json!((0..7000).collect::<Vec<u32>>());
    problem(
        &f.upload(GLTF, &bytes_of(&d)),
        400,
        &["70000000 triangles", "limit of 67108864"],
    );
    assert!(t0.elapsed() < Duration::from_secs(5), "{:?}", t0.elapsed());
    // Instances that multiply through the node graph cannot exist: it must be a forest, so
    // a node reached twice (a diamond, here 20 levels of it: 2^20 paths) is refused.
    let mut d = triangle_doc();
    let mut nodes = vec![json!({"mesh": 0})];
    for _ in 0..20 {
        let below = nodes.len() - 1;
        nodes.push(json!({"children": [below]}));
        nodes.push(json!({"children": [below]}));
    }
    let n = nodes.len();
    d["nodes"] = json!(nodes);
    d["scenes"][0]["nodes"] = json!([n - 1, n - 2]);
    problem(&f.upload(GLTF, &bytes_of(&d)), 400, &["node"]);

    f.intact();
}

#[test]
fn data_uris_that_lie() {
    let f = Fixture::start(&[]);
    // A buffer declaring 36 bytes whose data: URI holds 4 MiB: refused, not cut to 36.
    let mut d = triangle_doc();
    let big = vec![0u8; 4 << 20];
    d["buffers"][0]["uri"] = json!(format!(
        "data:application/octet-stream;base64,{}",
        b64(&big)
    ));
    problem(
        &f.upload(GLTF, &bytes_of(&d)),
        400,
        &["buffer 0", "4194304 bytes", "byteLength is 36"],
    );
    // A buffer declaring gigabytes with 36 bytes of data.
    let mut d = triangle_doc();
    d["buffers"][0]["byteLength"] = json!(4_000_000_000u64);
    problem(
        &f.upload(GLTF, &bytes_of(&d)),
        400,
        &["buffer 0", "36 bytes", "4000000000"],
    );
    // A body declared larger than --max-body: 413 before a byte of it is read.
    let c = raw(
        &f.server,
        &format!(
            "POST /v1/scenes HTTP/1.1\r\nHost: x\r\nContent-Type: {GLTF}\r\nContent-Length: {}\r\n\r\n",
            MAX_BODY + 1
        ),
    );
    problem(&answer(c).0.expect("an answer"), 413, &["limit"]);
    f.intact();

    // `rayd info` reads files from disk and says the same.
    let dir = tempfile::tempdir().unwrap();
    let mut d = triangle_doc();
    let big = vec![7u8; 48 << 10];
    d["buffers"][0]["uri"] = json!(format!(
        "data:application/octet-stream;base64,{}",
        b64(&big)
    ));
    let file = dir.path().join("liar.gltf");
    std::fs::write(&file, bytes_of(&d)).unwrap();
    let (ok, out) = info(&file);
    assert!(
        !ok,
        "rayd info accepted a data: URI longer than byteLength: {out}"
    );
    assert!(
        out.contains("49152 bytes") && out.contains("byteLength is 36"),
        "{out}"
    );
}

/// Runs `rayd info FILE` (killed after 20 s: a file it blocks on is a failure too).
fn info(file: &Path) -> (bool, String) {
    let mut child = Command::new(BIN)
        .arg("info")
        .arg(file)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if t0.elapsed() > Duration::from_secs(20) {
            child.kill().unwrap();
            panic!(
                "rayd info {} did not finish (it opened a FIFO?)",
                file.display()
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let out = child.wait_with_output().unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

#[test]
fn uris_that_name_server_files() {
    let f = Fixture::start(&[]);
    for uri in [
        "/etc/passwd",
        "../../../../../../etc/passwd",
        "file:///etc/passwd",
        "%2Fetc%2Fpasswd",
        "..%2F..%2Fetc%2Fpasswd",
        "buffer.bin",
    ] {
        let mut d = triangle_doc();
        d["buffers"][0]["uri"] = json!(uri);
        problem(&f.upload(GLTF, &bytes_of(&d)), 400, &["buffer 0", uri]);
        // The same as an image of a textured document.
        let mut d = triangle_doc();
        d["images"] = json!([{"uri": uri}]);
        d["textures"] = json!([{"source": 0}]);
        d["materials"] = json!([{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]);
        d["meshes"][0]["primitives"][0]["material"] = json!(0);
        // Refused at upload: the service keeps no scene that a render could not load.
        problem(&f.upload(GLTF, &bytes_of(&d)), 400, &["image 0", uri]);
    }
    // So is every other flaw of the appearance a render reads and a trace does not.
    let textured = |material: serde_json::Value| {
        let mut d = triangle_doc();
        d["materials"] = json!([material]);
        d["meshes"][0]["primitives"][0]["material"] = json!(0);
        d
    };
    let mut lit = triangle_doc();
    lit["extensionsUsed"] = json!(["KHR_lights_punctual"]);
    lit["nodes"][0]["extensions"] = json!({"KHR_lights_punctual": {"light": 3}});
    let mut spot = triangle_doc();
    spot["extensionsUsed"] = json!(["KHR_lights_punctual"]);
    spot["extensions"] = json!({"KHR_lights_punctual": {"lights": [
        {"type": "spot", "spot": {"innerConeAngle": 0.6, "outerConeAngle": 0.5}}]}});
    spot["nodes"][0]["extensions"] = json!({"KHR_lights_punctual": {"light": 0}});
    for (d, words) in [
        (
            textured(json!({"pbrMetallicRoughness": {"roughnessFactor": 2.0}})),
            &["material 0", "roughness"][..],
        ),
        (
            textured(json!({"pbrMetallicRoughness": {"baseColorTexture": {"index": 5}}})),
            &["texture 5"][..],
        ),
        (lit, &["light 3"][..]),
        (spot, &["light 0", "cone"][..]),
    ] {
        problem(&f.upload(GLTF, &bytes_of(&d)), 400, words);
    }
    f.intact();

    // From disk, relative paths are allowed only inside the file's directory. The paths
    // outside are FIFOs: opening one would block `rayd info` (and fail the test), so a
    // refusal proves that nothing was opened.
    let dir = tempfile::tempdir().unwrap();
    let inner = dir.path().join("scene");
    std::fs::create_dir(&inner).unwrap();
    let fifo = dir.path().join("outside.bin");
    assert!(Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .unwrap()
        .success());
    for uri in [
        "../outside.bin",
        "%2e%2e/outside.bin",
        "sub/../../outside.bin",
    ] {
        for image in [false, true] {
            let mut d = triangle_doc();
            if image {
                d["images"] = json!([{"uri": uri}]);
            } else {
                d["buffers"][0]["uri"] = json!(uri);
            }
            let file = inner.join("escape.gltf");
            std::fs::write(&file, bytes_of(&d)).unwrap();
            let (ok, out) = info(&file);
            assert!(!ok, "{uri}: {out}");
            assert!(out.contains("leaves the file's directory"), "{uri}: {out}");
        }
    }
    let pos: Vec<u8> = [0f32, 0., 0., 1., 0., 0., 0., 1., 0.]
        .iter()
        .flat_map(|f| f.to_le_bytes())
        .collect();
    std::fs::write(inner.join("inside.bin"), &pos).unwrap();
    let mut d = triangle_doc();
    d["buffers"][0]["uri"] = json!("./inside.bin");
    let file = inner.join("fine.gltf");
    std::fs::write(&file, bytes_of(&d)).unwrap();
    let (ok, out) = info(&file);
    assert!(ok, "a buffer beside the file: {out}");
}

/// A PNG that declares `w` × `h` pixels of RGBA8, with a few rows of real data.
fn png_declaring(w: u32, h: u32) -> Vec<u8> {
    fn chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
        out.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let mut c = kind.to_vec();
        c.extend_from_slice(data);
        out.extend_from_slice(&c);
        out.extend_from_slice(&crc32(&c).to_be_bytes());
    }
    fn crc32(b: &[u8]) -> u32 {
        let mut c = !0u32;
        for &x in b {
            c ^= u32::from(x);
            for _ in 0..8 {
                c = if c & 1 != 0 {
                    0xEDB8_8320 ^ (c >> 1)
                } else {
                    c >> 1
                };
            }
        }
        !c
    }
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 6, 0, 0, 0]);
    // A stored (uncompressed) zlib stream of one short row.
    let row = [0u8; 17];
    let mut z = vec![0x78, 0x01, 0x01];
    z.extend_from_slice(&(row.len() as u16).to_le_bytes());
    z.extend_from_slice(&(!(row.len() as u16)).to_le_bytes());
    z.extend_from_slice(&row);
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    chunk(&mut png, b"IHDR", &ihdr);
    chunk(&mut png, b"IDAT", &z);
    chunk(&mut png, b"IEND", &[]);
    png
}

#[test]
fn textures_that_declare_too_many_pixels() {
    let f = Fixture::start(&[]);
    for (w, h) in [(100_000u32, 100_000u32), (20_000, 4)] {
        let mut d = triangle_doc();
        d["images"] = json!([{
            "uri": format!("data:image/png;base64,{}", b64(&png_declaring(w, h)))
        }]);
        d["textures"] = json!([{"source": 0}]);
        d["materials"] = json!([{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]);
        d["meshes"][0]["primitives"][0]["material"] = json!(0);
        let r = f.upload(GLTF, &bytes_of(&d));
        assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
        let id = r.json()["id"].as_str().unwrap().to_owned();
        let t0 = Instant::now();
        let r = f.server.req(
            "POST",
            &format!("/v1/scenes/{id}/render"),
            &[("Content-Type", "application/json")],
            br#"{"width": 8, "height": 8, "integrator": "path", "spp": 1}"#,
        );
        assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
        let job = r.json()["id"].as_str().unwrap().to_owned();
        let j = wait_job(&f.server, &job, 30);
        assert_eq!(j["state"], "failed", "{j}");
        let err = j["error"].as_str().unwrap();
        assert!(
            err.contains("image 0") && err.contains(&format!("{w} × {h} pixels")),
            "{err}"
        );
        assert!(t0.elapsed() < Duration::from_secs(10), "{:?}", t0.elapsed());
        let r = f
            .server
            .req("DELETE", &format!("/v1/scenes/{id}"), &[], &[]);
        assert!(r.status < 300, "{}", r.status);
    }
    f.intact();
}

/// A connection on which a request head has been sent.
fn raw(s: &Server, head: &str) -> TcpStream {
    let mut c = TcpStream::connect(&s.addr).unwrap();
    c.set_read_timeout(Some(Duration::from_secs(20))).unwrap();
    c.write_all(head.as_bytes()).unwrap();
    c
}

/// Reads what the server sends until it closes; the answer (if any) and how long it took.
fn answer(mut c: TcpStream) -> (Option<Resp>, Duration) {
    let t0 = Instant::now();
    let mut buf = Vec::new();
    let _ = c.read_to_end(&mut buf);
    let took = t0.elapsed();
    ((!buf.is_empty()).then(|| Resp::parse(&buf)), took)
}

#[test]
fn bodies_that_lie_or_never_end() {
    let f = Fixture::start(&[]);
    let s = &f.server;
    let tri = rayd::formats::binary::write_tri(&[rayd::geometry::Triangle {
        v: [[0., 0., 0.], [1., 0., 0.], [0., 1., 0.]],
    }]);

    // Content-Length promises more than is sent, then the client goes quiet: 408 after
    // --body-timeout, and the budget it held is free again.
    let mut c = raw(
        s,
        &format!(
            "POST /v1/scenes HTTP/1.1\r\nHost: x\r\nContent-Type: {GLB}\r\nContent-Length: 4000000\r\n\r\n"
        ),
    );
    c.write_all(&[0u8; 1000]).unwrap();
    let (r, took) = answer(c);
    let r = r.expect("an answer");
    problem(&r, 408, &["body", "1000 bytes", "--body-timeout"]);
    assert!(took < Duration::from_secs(5), "{took:?}");

    // A chunked body that never ends: the same.
    let mut c = raw(
        s,
        &format!(
            "POST /v1/scenes/{}/trace HTTP/1.1\r\nHost: x\r\nContent-Type: application/octet-stream\r\nTransfer-Encoding: chunked\r\n\r\n",
            f.good
        ),
    );
    c.write_all(b"10\r\nRAY1\x01\x00\x00\x00\x05\x00\x00\x00\x00\x00\x00\x00\r\n")
        .unwrap();
    let (r, took) = answer(c);
    problem(&r.expect("an answer"), 408, &["body", "--body-timeout"]);
    assert!(took < Duration::from_secs(5), "{took:?}");

    // A body trickled a few bytes at a time, never idle for --body-timeout: cut off once
    // the waiting passes --body-timeout plus a second per --min-body-rate bytes (4096).
    let c = raw(
        s,
        &format!(
            "POST /v1/scenes HTTP/1.1\r\nHost: x\r\nContent-Type: {GLB}\r\nContent-Length: 4000000\r\n\r\n"
        ),
    );
    let mut w = c.try_clone().unwrap();
    let trickle = std::thread::spawn(move || {
        for _ in 0..100 {
            if w.write_all(&[0u8; 64]).is_err() {
                return;
            }
            std::thread::sleep(Duration::from_millis(300));
        }
    });
    let (r, took) = answer(c);
    problem(&r.expect("an answer"), 408, &["body", "--min-body-rate"]);
    assert!(took < Duration::from_secs(5), "{took:?}");
    trickle.join().unwrap();

    // A JSON body (render options) that stops half-way.
    let mut c = raw(
        s,
        &format!(
            "POST /v1/scenes/{}/render HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 100\r\n\r\n",
            f.good
        ),
    );
    c.write_all(b"{\"width\": ").unwrap();
    let (r, _) = answer(c);
    problem(&r.expect("an answer"), 408, &["body"]);

    // A chunked body that goes on past --max-body: 413 once it passes the limit.
    let mut c = raw(
        s,
        &format!(
            "POST /v1/scenes HTTP/1.1\r\nHost: x\r\nContent-Type: {GLB}\r\nTransfer-Encoding: chunked\r\n\r\n"
        ),
    );
    let chunk = vec![b'x'; 1 << 20];
    let mut refused = false;
    for _ in 0..(MAX_BODY >> 20) + 4 {
        let mut piece = format!("{:x}\r\n", chunk.len()).into_bytes();
        piece.extend_from_slice(&chunk);
        piece.extend_from_slice(b"\r\n");
        if c.write_all(&piece).is_err() {
            refused = true;
            break;
        }
    }
    let (r, _) = answer(c);
    if let Some(r) = r {
        problem(&r, 413, &["limit"]);
    } else {
        assert!(refused, "no answer and the body was taken whole");
    }

    // Content-Length larger than the limit: 413 before a byte of the body is read.
    let c = raw(
        s,
        &format!(
            "POST /v1/scenes HTTP/1.1\r\nHost: x\r\nContent-Type: {GLB}\r\nContent-Length: 99999999999\r\n\r\n"
        ),
    );
    problem(&answer(c).0.expect("an answer"), 413, &["declared length"]);

    // Content-Length smaller than what follows: the body is its declared bytes (a short
    // TRI1, refused), and the rest is not a request.
    let mut c = raw(
        s,
        "POST /v1/scenes HTTP/1.1\r\nHost: x\r\nConnection: close\r\nContent-Type: application/x-rayd-tri\r\nContent-Length: 20\r\n\r\n",
    );
    c.write_all(&tri).unwrap();
    let (r, _) = answer(c);
    problem(&r.expect("an answer"), 400, &["TRI1"]);

    // Two Content-Lengths that disagree: refused by the HTTP layer (400), never guessed at.
    let (r, _) = answer(raw(
        s,
        "POST /v1/scenes HTTP/1.1\r\nHost: x\r\nContent-Length: 5\r\nContent-Length: 6\r\n\r\nhello!",
    ));
    assert_eq!(r.expect("an answer").status, 400);
    // A Content-Length beside chunked: chunked decides (RFC 9112 §6.3), so the body is the
    // empty chunked one, answered as such (here 415: it has no Content-Type), and the bytes
    // that Content-Length would have counted are not smuggled into a body.
    let (r, _) = answer(raw(
        s,
        "POST /v1/scenes HTTP/1.1\r\nHost: x\r\nConnection: close\r\nContent-Length: 5\r\nTransfer-Encoding: chunked\r\n\r\n0\r\n\r\nhello",
    ));
    problem(&r.expect("an answer"), 415, &["Content-Type"]);
    f.intact();
}

#[test]
fn heads_that_are_huge_or_slow() {
    let f = Fixture::start(&[]);
    let s = &f.server;

    // A header of 100 KiB: 431.
    let big = "a".repeat(100 << 10);
    let (r, _) = answer(raw(
        s,
        &format!("GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: {big}\r\n\r\n"),
    ));
    assert_eq!(r.expect("an answer").status, 431);
    // Thousands of small headers: refused too (hyper allows 100).
    let many: String = (0..5000).map(|i| format!("X-H{i}: v\r\n")).collect();
    let (r, _) = answer(raw(
        s,
        &format!("GET /healthz HTTP/1.1\r\nHost: x\r\n{many}\r\n"),
    ));
    let status = r.expect("an answer").status;
    assert!(status == 431 || status == 400, "{status}");

    // Slowloris: a head sent a byte every 200 ms never completes; the connection is closed
    // once --header-timeout (1 s) has passed since it opened.
    let mut c = TcpStream::connect(&s.addr).unwrap();
    c.set_read_timeout(Some(Duration::from_millis(50))).unwrap();
    let t0 = Instant::now();
    let head = b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Slow: ".to_vec();
    let mut closed = None;
    let mut i = 0;
    while t0.elapsed() < Duration::from_secs(8) {
        let byte = head.get(i).copied().unwrap_or(b'a');
        i += 1;
        if c.write_all(&[byte]).is_err() {
            closed = Some(t0.elapsed());
            break;
        }
        let mut buf = [0u8; 512];
        match c.read(&mut buf) {
            Ok(0) => {
                closed = Some(t0.elapsed());
                break;
            }
            Ok(_) => {
                // An answer (408) before closing is fine.
                closed = Some(t0.elapsed());
                break;
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
            Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
            Err(_) => {
                closed = Some(t0.elapsed());
                break;
            }
        }
        std::thread::sleep(Duration::from_millis(150));
    }
    let closed = closed.expect("a slowloris connection was kept open for 8 s");
    assert!(closed < Duration::from_secs(4), "{closed:?}");
    f.intact();
}

#[test]
fn thousands_of_idle_connections() {
    // 2000 connections that send nothing, against a server that holds at most 500 at once:
    // the server keeps answering (idle ones are closed after --header-timeout, and those
    // past the bound wait in the backlog, costing it nothing).
    let f = Fixture::start(&["--max-connections", "500"]);
    let mut idle = Vec::new();
    for _ in 0..2000 {
        match TcpStream::connect(&f.server.addr) {
            Ok(c) => idle.push(c),
            Err(e) => panic!("connect {}: {e}", idle.len()),
        }
    }
    let t0 = Instant::now();
    let r = f.server.req("GET", "/healthz", &[], &[]);
    assert_eq!(r.status, 200);
    let waited = t0.elapsed();
    assert!(waited < Duration::from_secs(15), "{waited:?}");
    // The server closed the idle connections it accepted.
    let mut closed = 0;
    for c in idle.iter_mut().take(200) {
        c.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let mut b = [0u8; 64];
        if c.read(&mut b).is_ok() {
            closed += 1;
        }
    }
    assert!(
        closed > 100,
        "only {closed} of 200 idle connections were closed"
    );
    drop(idle);
    f.intact();
}

#[test]
fn ids_with_path_separators() {
    let f = Fixture::start(&[]);
    let s = &f.server;
    for path in [
        "/v1/scenes/..%2F..%2Fetc%2Fpasswd",
        "/v1/scenes/%2e%2e",
        "/v1/scenes/..%5C..%5Cwindows",
        "/v1/scenes/a%00b",
        "/v1/jobs/..%2Fscenes",
        "/v1/jobs/%2Fetc%2Fpasswd/result",
    ] {
        for method in ["GET", "DELETE"] {
            if method == "DELETE" && path.ends_with("/result") {
                continue;
            }
            let r = s.req(method, path, &[], &[]);
            assert!(
                r.status == 404 || r.status == 400,
                "{method} {path}: {}",
                r.status
            );
            problem(&r, r.status, &[]);
        }
    }
    let r = s.req(
        "PUT",
        "/v1/scenes/..%2F..%2Fx/geometry",
        &[("Content-Type", "application/x-rayd-tri")],
        b"TRI1",
    );
    assert!(r.status == 404 || r.status == 400, "{}", r.status);
    // Unnormalised paths reach no route.
    let r = s.req("GET", &format!("/v1/scenes/../scenes/{}", f.good), &[], &[]);
    assert!(r.status == 404 || r.status == 400, "{}", r.status);
    f.intact();
}

#[test]
fn requests_without_a_token_or_with_a_wrong_one() {
    let dir = tempfile::tempdir().unwrap();
    let tokens = dir.path().join("tokens");
    std::fs::write(&tokens, "# the test's token\nsecret-token-1\n").unwrap();
    let server = Server::start(
        &dir.path().join("data"),
        &["--token-file", tokens.to_str().unwrap()],
    );
    let long = format!("Bearer {}", "x".repeat(10_000));
    for (auth, invalid) in [
        (None, false),
        (Some("Bearer wrong"), true),
        (Some("Bearer secret-token-"), true),
        (Some("Bearer secret-token-12"), true),
        (Some("Bearer "), false),
        (Some("Basic c2VjcmV0LXRva2VuLTE6"), false),
        (Some("secret-token-1"), false),
        (Some(long.as_str()), true),
    ] {
        let headers: Vec<(&str, &str)> = auth.iter().map(|a| ("Authorization", *a)).collect();
        let r = server.req("GET", "/v1/scenes", &headers, &[]);
        let p = problem(&r, 401, &[]);
        assert!(
            p["detail"]
                .as_str()
                .unwrap()
                .to_lowercase()
                .contains("token"),
            "{p}"
        );
        let challenge = r.header("www-authenticate").unwrap();
        assert!(challenge.starts_with("Bearer"), "{challenge}");
        if invalid {
            assert!(challenge.contains("invalid_token"), "{auth:?}: {challenge}");
        }
        // An upload without the right token stores nothing.
        let mut h = headers.clone();
        h.push(("Content-Type", GLB));
        let r = server.req("POST", "/v1/scenes", &h, b"glTF");
        assert_eq!(r.status, 401);
    }
    let ok = server.req(
        "GET",
        "/v1/scenes",
        &[("Authorization", "Bearer secret-token-1")],
        &[],
    );
    assert_eq!(ok.status, 200);
    assert_eq!(ok.json()["scenes"], json!([]));
    assert_eq!(server.req("GET", "/healthz", &[], &[]).status, 200);
}
