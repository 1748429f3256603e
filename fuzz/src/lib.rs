//! The bodies of rayd's fuzz targets, one function per target.
//!
//! They live in a library rather than in the `fuzz_targets/` files so that the committed
//! seed corpus can also be run through them as an ordinary `cargo test` (`tests/fuzz_corpus.rs`
//! includes this file): CI builds no sanitizer-instrumented copy of rayd, yet every seed, and
//! every crash that became a seed, is replayed through the same code on every run.
//!
//! Each function takes arbitrary bytes and must return without panicking, whatever they are:
//! a parser answers bad input with an error value, the service with a 4xx/5xx answer. The
//! functions also check the few invariants that a successful parse promises (what was read
//! writes back to the same bytes), so a silent misparse fails too, not only a crash.

use std::net::SocketAddr;
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use rayd::formats::{binary, gltf, LoadOptions, Parts};

/// glTF loading of a binary `.glb` (the seeds are GLB files; the bytes are handed to the
/// same loader a `.gltf` goes to, which tells the two apart by the GLB magic).
pub fn gltf_glb(data: &[u8]) {
    load_gltf(data);
}

/// glTF loading of a JSON `.gltf` with embedded (`data:`) buffers and images.
pub fn gltf_json(data: &[u8]) {
    load_gltf(data);
}

/// Most triangles a fuzzed scene may have, as the service's `--max-triangles` bounds an
/// upload: the loader's own bound (2^28, 9 GiB of positions) is for files an operator
/// chose, and would only make libFuzzer report an out-of-memory.
const MAX_TRIANGLES: u64 = 1 << 20;

/// Loads `data` as an uploaded scene would be (no directory: no file may be read), for
/// geometry and for shading, decodes its textures, and poses it at a time when it animates.
fn load_gltf(data: &[u8]) {
    let load = |options: &LoadOptions, parts| {
        gltf::load_limited(data, None, options, parts, MAX_TRIANGLES)
    };
    let static_pose = load(&LoadOptions::default(), Parts::Geometry);
    let Ok(scene) = static_pose else { return };
    if !scene.animations.is_empty() {
        // Animations are validated at every load, so a file that loads at its static pose
        // loads at any time, with one documented exception (proto/scenes.md): a pose whose
        // world positions overflow f32 at that time (a huge morph weight or scale keyframe)
        // is refused at that time, naming the vertex.
        let timed = LoadOptions { time: Some(0.37) };
        match load(&timed, Parts::Geometry) {
            Ok(_)
            | Err(gltf::GltfError::Scene(rayd::scene::SceneError::NonFiniteWorldPosition {
                ..
            })) => {}
            Err(e) => panic!("a file that loads at its static pose must load at any time: {e:?}"),
        }
    }
    if let Ok(shaded) = load(&LoadOptions::default(), Parts::Shading) {
        assert_eq!(
            shaded.triangles.len(),
            scene.triangles.len(),
            "shading loads place the same triangles"
        );
        let _ = rayd::render::texture::TextureSet::of(&shaded);
    }
}

/// The TRI1 reader: what it accepts writes back to the same bytes.
pub fn tri1(data: &[u8]) {
    if let Ok(tris) = binary::read_tri(data) {
        assert_eq!(binary::write_tri(&tris), data, "TRI1 round trip");
        assert_eq!(binary::tri_count(data).ok(), Some(tris.len()));
    }
}

/// The RAY1 reader, whole and streamed in uneven pieces: both see the same rays, and what
/// they accept writes back to the same bytes, but for a +inf `tmax`, read as the largest
/// finite f32 (`Ray::bound_tmax`).
pub fn ray1(data: &[u8]) {
    let whole = binary::read_rays(data);
    if let Ok(rays) = &whole {
        let mut bounded = data.to_vec();
        for record in bounded[16..].chunks_exact_mut(32) {
            if record[28..32] == f32::INFINITY.to_le_bytes() {
                record[28..32].copy_from_slice(&f32::MAX.to_le_bytes());
            }
        }
        assert_eq!(binary::write_rays(rays), bounded, "RAY1 round trip");
    }
    let mut sink = binary::Ray1Sink::new(usize::MAX, Some(data.len() as u64));
    let mut streamed = Ok(());
    let mut at = 0;
    let mut step = 1;
    while at < data.len() && streamed.is_ok() {
        let end = (at + step).min(data.len());
        streamed = sink.push(&data[at..end]);
        at = end;
        step = step * 3 + 1;
    }
    let streamed = streamed
        .and_then(|()| sink.finish_segment())
        .map(|segment| {
            // A sink that vouches for its rays (the trace then skips its own check) is right.
            if segment.all_valid {
                let mut rays = segment.rays.clone();
                assert_eq!(rayd::geometry::Ray::validate_batch(&mut rays, false), None);
            }
            segment.rays
        });
    assert_eq!(
        whole.is_ok(),
        streamed.is_ok(),
        "whole {:?} vs streamed {:?}",
        whole.as_ref().err(),
        streamed.as_ref().err()
    );
    if let (Ok(a), Ok(b)) = (&whole, &streamed) {
        assert_eq!(binary::write_rays(a), binary::write_rays(b));
    }
}

/// The HIT1 reader (the format clients read, and `rayd` checks in its tests).
pub fn hit1(data: &[u8]) {
    if let Ok((format, hits)) = binary::read_hits(data) {
        let again = binary::write_hits(&hits, format);
        assert_eq!(again.len(), data.len(), "HIT1 round trip length");
    }
}

/// The service, through its whole router (every layer: request id, metrics, token check,
/// per-client bound, bodies): the input is a request as text, a request line, header
/// lines, a blank line and the body. `{scene}` in the request line stands for the id of a
/// scene uploaded when the service started, so that the routes under `/v1/scenes/{id}`
/// are reached with an id that exists.
///
/// ```text
/// POST /v1/scenes/{scene}/trace?format=t
/// content-type: application/x-rayd-rays
///
/// RAY1...
/// ```
pub fn http(data: &[u8]) {
    let service = Service::get();
    let Some(req) = parse_request(data, &service.scene) else {
        return;
    };
    service.runtime.block_on(async {
        use http_body_util::BodyExt;
        use tower::ServiceExt;
        let resp = match service.router.clone().oneshot(req).await {
            Ok(r) => r,
            Err(e) => match e {},
        };
        let status = resp.status();
        assert!(
            !status.is_server_error() || status.as_u16() == 503 || status.as_u16() == 507,
            "a fuzzed request got {status}"
        );
        // Read the answer, but not forever: event streams never end.
        let mut body = resp.into_body();
        let deadline = tokio::time::sleep(Duration::from_millis(50));
        tokio::pin!(deadline);
        loop {
            tokio::select! {
                f = body.frame() => match f {
                    Some(Ok(_)) => {}
                    _ => break,
                },
                () = &mut deadline => break,
            }
        }
    });
}

/// The request written in `data`, or `None` when its first line is not a method and a URI.
fn parse_request(data: &[u8], scene: &str) -> Option<axum::extract::Request> {
    let (head, body) = match find(data, b"\n\n") {
        Some(i) => (&data[..i], &data[i + 2..]),
        None => (data, &[][..]),
    };
    let head = std::str::from_utf8(head).ok()?;
    let mut lines = head.split('\n');
    let (method, uri) = lines.next()?.split_once(' ')?;
    let uri = uri.trim().replace("{scene}", scene);
    let mut builder = axum::http::Request::builder()
        .method(method.trim())
        .uri(uri);
    for line in lines {
        if let Some((k, v)) = line.split_once(':') {
            builder = builder.header(k.trim(), v.trim());
        }
    }
    let mut req = builder.body(axum::body::Body::from(body.to_vec())).ok()?;
    // What the connection loop adds: the peer, for the per-client bound.
    let peer: SocketAddr = ([127, 0, 0, 1], 40000).into();
    req.extensions_mut()
        .insert(axum::extract::ConnectInfo(peer));
    Some(req)
}

fn find(hay: &[u8], needle: &[u8]) -> Option<usize> {
    hay.windows(needle.len()).position(|w| w == needle)
}

/// One service for the whole run: a store in a temporary directory, small limits so that a
/// fuzzed render or trace stays cheap, and the router `rayd serve` serves.
struct Service {
    runtime: tokio::runtime::Runtime,
    router: axum::Router,
    /// The id of the scene uploaded at start (`Triangle.glb`).
    scene: String,
    _dir: tempfile::TempDir,
}

impl Service {
    fn get() -> &'static Service {
        static SERVICE: OnceLock<Service> = OnceLock::new();
        SERVICE.get_or_init(Service::start)
    }

    fn start() -> Service {
        let dir = tempfile::tempdir().expect("a temporary data directory");
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .expect("a tokio runtime");
        let data_dir = dir.path().to_str().expect("a UTF-8 temporary path");
        let args = rayd::service::ServeArgs::try_parse_from([
            "--data-dir",
            data_dir,
            "--max-body",
            "1048576",
            "--max-inflight-bytes",
            "8388608",
            "--max-rays",
            "4096",
            "--max-pixels",
            "4096",
            "--max-spp",
            "4",
            "--max-store-bytes",
            "67108864",
            "--max-client-requests",
            "0",
        ])
        .expect("fuzz service options");
        let (router, scene) = runtime.block_on(async {
            let state = rayd::service::AppState::new(args).expect("service state");
            let store = rayd::store::Store::open(
                &state.config.data_dir,
                rayd::store::StoreOptions {
                    max_bytes: state.config.max_store_bytes,
                    ..Default::default()
                },
            )
            .await
            .expect("the store");
            let engine = Arc::new(
                rayd::jobs::Engine::new(rayd::jobs::EngineOptions {
                    threads: 1,
                    cache_bytes: 64 << 20,
                    texture_bytes: 64 << 20,
                    max_queued: 8,
                    max_running: 2,
                    limits: rayd::jobs::Limits {
                        max_rays: 4096,
                        max_pixels: 4096,
                        max_spp: 4,
                        max_bounces: 4,
                        max_frames: 4,
                        ..Default::default()
                    },
                    tuning: Default::default(),
                })
                .expect("the engine"),
            );
            let app = rayd::app::App::new(
                store,
                engine,
                rayd::app::AppOptions {
                    max_triangles: MAX_TRIANGLES,
                    // Parsed scenes share this budget. The default (1 GiB) is a server's;
                    // a small one keeps a long run's memory flat and exercises eviction.
                    geometry_bytes: 16 << 20,
                    ..Default::default()
                },
            );
            state.ready.set_ready();
            let router = rayd::service::router(state, rayd::service::routes::routes())
                .layer(axum::Extension(app));
            let scene = upload(&router, TRIANGLE).await;
            (router, scene)
        });
        Service {
            runtime,
            router,
            scene,
            _dir: dir,
        }
    }
}

/// The scene every run starts with.
const TRIANGLE: &[u8] = include_bytes!("../../scenes/Triangle.glb");

/// Uploads a GLB through `router` and returns its id.
async fn upload(router: &axum::Router, glb: &'static [u8]) -> String {
    use http_body_util::BodyExt;
    use tower::ServiceExt;
    let mut req = axum::http::Request::post("/v1/scenes")
        .header("content-type", "model/gltf-binary")
        .body(axum::body::Body::from(glb))
        .expect("an upload request");
    let peer: SocketAddr = ([127, 0, 0, 1], 40000).into();
    req.extensions_mut()
        .insert(axum::extract::ConnectInfo(peer));
    let resp = match router.clone().oneshot(req).await {
        Ok(r) => r,
        Err(e) => match e {},
    };
    assert!(resp.status().is_success(), "seed upload: {}", resp.status());
    let body = resp
        .into_body()
        .collect()
        .await
        .expect("the upload's answer")
        .to_bytes();
    let v: serde_json::Value = serde_json::from_slice(&body).expect("JSON");
    v["id"].as_str().expect("an id").to_owned()
}
