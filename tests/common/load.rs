//! A load driver for `rayd serve`, shared by the soak test (`tests/soak.rs`) and the load
//! script (`scripts/load.sh`, `examples/load.rs`, which includes this file by path).
//!
//! Worker threads run a weighted mix of request kinds against one server for a bounded
//! time: small and large traces, renders, geometry updates, cancellations and uploads.
//! Every answer is checked against the library's own engine run in this process on the
//! same rays and positions (HIT1 bytes must be identical) or, for renders, against the PNG
//! `rayd render` writes for the same options. A `503` counts as refused only with
//! `Retry-After`, and is retried after a short pause; any other failure is an error. A
//! restarter thread may kill the server (`kill -9`) or stop it (`SIGTERM`) and start it
//! again on the same data directory and port: requests broken by a restart are retried,
//! and everything the server acknowledged before it (scenes, versions, jobs) must be
//! there after it. A sampler records the server's RSS from `/proc`.
#![allow(dead_code)]

use std::collections::HashMap;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};

use rayd::formats::binary::{write_rays, write_tri};
use rayd::geometry::{Ray, Triangle};
use rayd::jobs::{Engine, EngineOptions, Geometry, GeometryKey, InvalidPolicy, TraceRequest};

/// The request kinds of the mix.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Kind {
    /// A 1K-ray trace of the latest or a random version.
    SmallTrace,
    /// A 256K-ray trace of version 1.
    LargeTrace,
    /// A small render job, submitted, polled and fetched.
    Render,
    /// A `PUT …/geometry` of new positions.
    Geometry,
    /// A longer render submitted and cancelled.
    Cancel,
    /// A fresh TRI1 scene uploaded, traced and deleted.
    Upload,
}

impl Kind {
    /// Every kind, in report order.
    pub const ALL: [Kind; 6] = [
        Kind::SmallTrace,
        Kind::LargeTrace,
        Kind::Render,
        Kind::Geometry,
        Kind::Cancel,
        Kind::Upload,
    ];

    /// The name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Kind::SmallTrace => "small trace (1K rays)",
            Kind::LargeTrace => "large trace",
            Kind::Render => "render 48x32 (submit to PNG)",
            Kind::Geometry => "geometry update (PUT)",
            Kind::Cancel => "render cancelled",
            Kind::Upload => "upload + trace + delete",
        }
    }
}

/// How a run goes.
#[derive(Clone, Debug)]
pub struct Plan {
    /// The `rayd` binary.
    pub bin: PathBuf,
    /// The scene every trace, render and geometry update uses.
    pub scene: PathBuf,
    /// Concurrent clients.
    pub workers: usize,
    /// How long the mix runs.
    pub duration: Duration,
    /// Relative weights of the kinds (0: never).
    pub weights: Vec<(Kind, u32)>,
    /// Server threads (`--threads`), and the in-process engine's.
    pub threads: usize,
    /// Kill or stop and restart the server this often (alternately); `None`: never.
    pub restart_every: Option<Duration>,
    /// Rays of a large trace.
    pub large_rays: usize,
    /// Extra `rayd serve` options.
    pub serve_args: Vec<String>,
}

/// One kind's outcome.
#[derive(Clone, Debug, Default)]
pub struct KindStats {
    /// Seconds of each answered request (client clock, connect to last byte).
    pub latencies: Vec<f64>,
    /// Rays traced by answered requests.
    pub rays: u64,
    /// `503` with `Retry-After` (retried).
    pub refused: u64,
    /// Requests broken by a server restart (retried).
    pub interrupted: u64,
}

/// A run's figures.
#[derive(Debug, Default)]
pub struct Report {
    /// Per kind.
    pub kinds: HashMap<Kind, KindStats>,
    /// Every error (a wrong answer, an undocumented status, a lost acknowledgement).
    pub errors: Vec<String>,
    /// Seconds the mix ran.
    pub seconds: f64,
    /// `(seconds since start, server RSS bytes, server incarnation)` every 250 ms.
    pub rss: Vec<(f64, u64, u64)>,
    /// Restarts done: `(kill -9s, clean stops)`.
    pub restarts: (u32, u32),
    /// CPU seconds (user + system) of this process during the mix.
    pub client_cpu: f64,
    /// CPU seconds of the server processes during the mix.
    pub server_cpu: f64,
}

impl Report {
    /// Requests answered, of every kind.
    pub fn requests(&self) -> usize {
        self.kinds.values().map(|k| k.latencies.len()).sum()
    }

    /// The Markdown table: kind, answered, refused, interrupted, req/s, p50/p95/p99 ms,
    /// Mray/s.
    pub fn table(&self) -> String {
        let mut out = String::from(
            "| kind | answered | 503 | interrupted | req/s | p50 ms | p95 ms | p99 ms | Mray/s |\n\
             |---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
        );
        for kind in Kind::ALL {
            let Some(k) = self.kinds.get(&kind) else {
                continue;
            };
            let mut l = k.latencies.clone();
            l.sort_by(f64::total_cmp);
            let p = |q: f64| {
                if l.is_empty() {
                    f64::NAN
                } else {
                    percentile(&l, q) * 1e3
                }
            };
            out.push_str(&format!(
                "| {} | {} | {} | {} | {:.2} | {:.1} | {:.1} | {:.1} | {} |\n",
                kind.name(),
                l.len(),
                k.refused,
                k.interrupted,
                l.len() as f64 / self.seconds.max(1e-9),
                p(50.0),
                p(95.0),
                p(99.0),
                if k.rays > 0 {
                    format!("{:.2}", k.rays as f64 / self.seconds.max(1e-9) / 1e6)
                } else {
                    "".into()
                }
            ));
        }
        out
    }
}

/// The `p`-th percentile (nearest rank) of sorted values.
pub fn percentile(sorted: &[f64], p: f64) -> f64 {
    let rank = ((p / 100.0) * sorted.len() as f64).ceil() as usize;
    sorted[rank.clamp(1, sorted.len()) - 1]
}

/// The machine's 1-minute load average.
pub fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split(' ').next().map(str::to_string))
        .unwrap_or_else(|| "?".into())
}

/// CPU seconds (user + system) of process `pid` ("self" for this one), from `/proc`.
pub fn cpu_seconds(pid: &str) -> f64 {
    let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
        return 0.0;
    };
    // Fields after the parenthesised command name; utime and stime are the 14th and 15th.
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (ticks(11) + ticks(12)) / 100.0
}

/// The resident set of process `pid`, bytes.
pub fn rss_bytes(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        .map(|kb| kb * 1024)
}

/// One answer.
pub struct Answer {
    /// Status code.
    pub status: u16,
    /// Lowercase names.
    pub headers: Vec<(String, String)>,
    /// The body (chunked bodies joined).
    pub body: Vec<u8>,
}

impl Answer {
    /// A header's value.
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.as_str())
    }

    /// The body as JSON (`Null` if it is not).
    pub fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.body).unwrap_or(serde_json::Value::Null)
    }

    fn describe(&self) -> String {
        let body = String::from_utf8_lossy(&self.body[..self.body.len().min(300)]).to_string();
        format!("{} {body}", self.status)
    }
}

/// One request on a fresh connection (`Connection: close`).
pub fn request(
    addr: &str,
    method: &str,
    path: &str,
    content_type: &str,
    body: &[u8],
) -> std::io::Result<Answer> {
    let mut s = TcpStream::connect(addr)?;
    s.set_nodelay(true)?;
    s.set_read_timeout(Some(Duration::from_secs(120)))?;
    s.set_write_timeout(Some(Duration::from_secs(120)))?;
    let mut head = format!(
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\nContent-Length: {}\r\n",
        body.len()
    );
    if !content_type.is_empty() {
        head.push_str(&format!("Content-Type: {content_type}\r\n"));
    }
    head.push_str("\r\n");
    s.write_all(head.as_bytes())?;
    s.write_all(body)?;
    let mut raw = Vec::new();
    s.read_to_end(&mut raw)?;
    let bad = |what: &str| std::io::Error::new(std::io::ErrorKind::InvalidData, what.to_string());
    let split = raw
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .ok_or_else(|| bad("no answer head"))?;
    let head = String::from_utf8_lossy(&raw[..split]).to_string();
    let mut lines = head.split("\r\n");
    let status = lines
        .next()
        .and_then(|l| l.split(' ').nth(1))
        .and_then(|c| c.parse().ok())
        .ok_or_else(|| bad("bad status line"))?;
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
        .collect();
    let mut body = raw.split_off(split + 4);
    if headers
        .iter()
        .any(|(k, v)| k == "transfer-encoding" && v.contains("chunked"))
    {
        body = dechunk(&body).ok_or_else(|| bad("a broken chunked body"))?;
    }
    // A body shorter than its head announced was cut off (a server killed after sending
    // the head): an error, as any HTTP client reports it, never a short answer.
    let announced = headers
        .iter()
        .find(|(k, _)| k == "content-length")
        .and_then(|(_, v)| v.parse::<usize>().ok());
    if let Some(n) = announced.filter(|&n| n != body.len()) {
        return Err(bad(&format!(
            "the body ended after {} of its {n} bytes",
            body.len()
        )));
    }
    Ok(Answer {
        status,
        headers,
        body,
    })
}

fn dechunk(mut b: &[u8]) -> Option<Vec<u8>> {
    let mut out = Vec::new();
    loop {
        let end = b.windows(2).position(|w| w == b"\r\n")?;
        let size = std::str::from_utf8(&b[..end]).ok()?;
        let n = usize::from_str_radix(size.split(';').next()?.trim(), 16).ok()?;
        b = &b[end + 2..];
        if n == 0 {
            return Some(out);
        }
        out.extend_from_slice(b.get(..n)?);
        b = b.get(n + 2..)?;
    }
}

/// The server process, restartable on the same port and data directory.
pub struct ServerProc {
    bin: PathBuf,
    /// `127.0.0.1:PORT`.
    pub addr: String,
    data: PathBuf,
    args: Vec<String>,
    child: Mutex<Option<Child>>,
    /// Bumped at every stop; a request that saw it change was broken by a restart.
    pub incarnation: AtomicU64,
    /// Set while the server is down for a restart.
    pub down: AtomicBool,
    /// CPU seconds of the incarnations that have exited.
    spent_cpu: Mutex<f64>,
}

impl ServerProc {
    /// Starts `rayd serve` on a free loopback port.
    pub fn start(
        bin: &Path,
        data: &Path,
        threads: usize,
        extra: &[String],
    ) -> Result<ServerProc, String> {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map_err(|e| format!("no free port: {e}"))?
            .port();
        let keep = KEPT_VERSIONS.to_string();
        let mut args: Vec<String> = [
            "--threads",
            &threads.to_string(),
            "--grace",
            "3",
            "--keep-versions",
            &keep,
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        args.extend(extra.iter().cloned());
        let s = ServerProc {
            bin: bin.to_path_buf(),
            addr: format!("127.0.0.1:{port}"),
            data: data.to_path_buf(),
            args,
            child: Mutex::new(None),
            incarnation: AtomicU64::new(0),
            down: AtomicBool::new(true),
            spent_cpu: Mutex::new(0.0),
        };
        s.spawn()?;
        Ok(s)
    }

    fn spawn(&self) -> Result<(), String> {
        let child = Command::new(&self.bin)
            .args(["serve", "--addr", &self.addr, "--data-dir"])
            .arg(&self.data)
            .args(&self.args)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| format!("cannot start {}: {e}", self.bin.display()))?;
        *self.child.lock().unwrap() = Some(child);
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(60) {
            if request(&self.addr, "GET", "/readyz", "", &[]).is_ok_and(|r| r.status == 200) {
                self.down.store(false, Ordering::SeqCst);
                return Ok(());
            }
            std::thread::sleep(Duration::from_millis(25));
        }
        Err("rayd serve did not become ready in 60 s".into())
    }

    /// The running server's process id.
    pub fn pid(&self) -> Option<u32> {
        self.child.lock().unwrap().as_ref().map(Child::id)
    }

    /// CPU seconds of every incarnation so far.
    pub fn cpu(&self) -> f64 {
        let live = self.pid().map_or(0.0, |p| cpu_seconds(&p.to_string()));
        *self.spent_cpu.lock().unwrap() + live
    }

    /// Stops the server (`kill -9`, or SIGTERM and a wait for its exit) and starts it again.
    pub fn restart(&self, kill: bool) -> Result<(), String> {
        self.down.store(true, Ordering::SeqCst);
        self.incarnation.fetch_add(1, Ordering::SeqCst);
        let mut child = self.child.lock().unwrap().take().ok_or("no server")?;
        let cpu = cpu_seconds(&child.id().to_string());
        if kill {
            child.kill().map_err(|e| format!("kill -9: {e}"))?;
            child.wait().map_err(|e| e.to_string())?;
        } else {
            Command::new("kill")
                .args(["-TERM", &child.id().to_string()])
                .status()
                .map_err(|e| format!("kill -TERM: {e}"))?;
            let t0 = Instant::now();
            loop {
                match child.try_wait().map_err(|e| e.to_string())? {
                    Some(st) if st.success() => break,
                    Some(st) => return Err(format!("a clean stop exited with {st}")),
                    None if t0.elapsed() > Duration::from_secs(30) => {
                        let _ = child.kill();
                        return Err("no exit 30 s after SIGTERM".into());
                    }
                    None => std::thread::sleep(Duration::from_millis(20)),
                }
            }
        }
        *self.spent_cpu.lock().unwrap() += cpu;
        self.spawn()
    }
}

impl Drop for ServerProc {
    fn drop(&mut self) {
        if let Some(mut c) = self.child.lock().unwrap().take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

/// SplitMix64, seeded per worker.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n.max(1)
    }
    fn unit(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// What every answer is checked against, computed in process before the run.
pub struct Fixture {
    /// The uploaded scene's id.
    pub scene_id: String,
    small_rays: Vec<u8>,
    large_rays: Vec<u8>,
    /// HIT1 of the small rays per geometry variant (0: the file's positions).
    small_hits: Vec<Vec<u8>>,
    large_hits: Vec<u8>,
    /// TRI1 bodies of the variants 1.. (index 0 unused).
    variants: Vec<Vec<u8>>,
    /// The server's versions and the variant each holds (version 1: variant 0).
    versions: RwLock<Vec<(u32, usize)>>,
    render_png: Vec<u8>,
    engine: Engine,
    /// Scenes uploaded and not yet deleted, with their expected small-trace HIT1.
    uploads: Mutex<HashMap<String, Vec<u8>>>,
}

const RENDER: &str = r#"{"width": 48, "height": 32, "integrator": "normals", "version": 1}"#;
const CANCEL: &str = r#"{"width": 256, "height": 256, "spp": 64, "integrator": "path", "version": 1, "priority": 10}"#;
const TRACE_QUERY: &str = "accel=mbvh8";
const VARIANTS: usize = 4;
/// Small traces pick version 1 or one of this many latest versions.
const RECENT_VERSIONS: usize = 8;
/// After a restart, version 1 and this many latest versions are traced again.
const CHECKED_VERSIONS: usize = 32;
/// The server's `--keep-versions`: the versions traced must outlive the ones sent while
/// they are picked (at most one per client in flight, committed or not), so this leaves a
/// margin over `CHECKED_VERSIONS` as wide again. The run still deletes all the others, as
/// a client sending positions every frame makes the server do.
const KEPT_VERSIONS: usize = 2 * CHECKED_VERSIONS;
const _: () = assert!(RECENT_VERSIONS < CHECKED_VERSIONS && CHECKED_VERSIONS < KEPT_VERSIONS);

fn trace_request() -> TraceRequest {
    TraceRequest {
        accel: rayd::accel::AccelKind::Mbvh8,
        invalid: InvalidPolicy::Error,
        ..TraceRequest::default()
    }
}

/// The engine's HIT1 for `rays` against `triangles`.
pub fn expected_hits(
    engine: &Engine,
    name: &str,
    triangles: Vec<Triangle>,
    rays: &[Ray],
) -> Vec<u8> {
    let geometry = Geometry {
        key: GeometryKey::new(name, 1, None),
        triangles: Arc::new(triangles),
        forgets: engine.forgets(),
    };
    let (body, _) = engine
        .trace(&geometry, rays, &trace_request(), 0, &engine.detached())
        .expect("the in-process trace");
    body.as_ref().to_vec()
}

/// Rays from random points of a sphere around the scene towards random points inside it.
pub fn rays_at(bounds: &rayd::geometry::Aabb, n: usize, seed: u64) -> Vec<Ray> {
    let mut rng = Rng(seed);
    let (lo, hi) = (bounds.min, bounds.max);
    let c = [
        0.5 * (lo[0] + hi[0]),
        0.5 * (lo[1] + hi[1]),
        0.5 * (lo[2] + hi[2]),
    ];
    let r = 0.5
        * ((hi[0] - lo[0]).powi(2) + (hi[1] - lo[1]).powi(2) + (hi[2] - lo[2]).powi(2)).sqrt()
        + 1e-3;
    (0..n)
        .map(|_| {
            let mut o = [0f32; 3];
            loop {
                let v = [
                    2.0 * rng.unit() - 1.0,
                    2.0 * rng.unit() - 1.0,
                    2.0 * rng.unit() - 1.0,
                ];
                let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
                if l > 0.1 && l <= 1.0 {
                    for i in 0..3 {
                        o[i] = c[i] + 1.5 * r * v[i] / l;
                    }
                    break;
                }
            }
            let t = [
                lo[0] + rng.unit() * (hi[0] - lo[0]),
                lo[1] + rng.unit() * (hi[1] - lo[1]),
                lo[2] + rng.unit() * (hi[2] - lo[2]),
            ];
            Ray {
                org: o,
                tmin: 0.0,
                dir: [t[0] - o[0], t[1] - o[1], t[2] - o[2]],
                tmax: f32::INFINITY,
            }
        })
        .collect()
}

/// A soup of `n` random small triangles in the unit cube.
fn soup(n: usize, seed: u64) -> Vec<Triangle> {
    let mut rng = Rng(seed);
    (0..n)
        .map(|_| {
            let c = [rng.unit(), rng.unit(), rng.unit()];
            let mut v = [[0f32; 3]; 3];
            for p in &mut v {
                for i in 0..3 {
                    p[i] = c[i] + 0.1 * (rng.unit() - 0.5);
                }
            }
            Triangle { v }
        })
        .collect()
}

impl Fixture {
    /// Uploads the plan's scene and computes every expected answer in process.
    pub fn prepare(plan: &Plan, server: &ServerProc, work: &Path) -> Result<Fixture, String> {
        let scene = rayd::formats::load_scene(&plan.scene, &Default::default())
            .map_err(|e| format!("{}: {e}", plan.scene.display()))?;
        let bounds = scene.bounds().ok_or("the scene has no triangles")?;
        let engine = Engine::new(EngineOptions {
            threads: plan.threads,
            ..Default::default()
        })
        .map_err(|e| e.to_string())?;
        let small = rays_at(&bounds, 1024, 1);
        let large = rays_at(&bounds, plan.large_rays, 2);
        let base = scene.triangles.clone();
        let mut small_hits = vec![expected_hits(&engine, "v0", base.clone(), &small)];
        let mut variants = vec![Vec::new()];
        let c = bounds.center();
        for k in 1..=VARIANTS {
            // Scaled about the centre by up to ±8%: the rays still meet the scene.
            let s = 1.0 + 0.04 * (k as f32 - 2.5);
            let moved: Vec<Triangle> = base
                .iter()
                .map(|t| Triangle {
                    v: t.v.map(|p| [0, 1, 2].map(|i| c[i] + s * (p[i] - c[i]))),
                })
                .collect();
            small_hits.push(expected_hits(
                &engine,
                &format!("v{k}"),
                moved.clone(),
                &small,
            ));
            variants.push(write_tri(&moved));
        }
        let large_hits = expected_hits(&engine, "v0", base, &large);
        // The render, as `rayd render` writes it.
        let png = work.join("expected.png");
        let spec: serde_json::Value = serde_json::from_str(RENDER).expect("JSON");
        let out = Command::new(&plan.bin)
            .arg("render")
            .arg(&plan.scene)
            .arg("-o")
            .arg(&png)
            .args(["--width", &spec["width"].to_string()])
            .args(["--height", &spec["height"].to_string()])
            .args(["--integrator", spec["integrator"].as_str().unwrap_or("")])
            .args(["--threads", &plan.threads.to_string()])
            .output()
            .map_err(|e| format!("cannot run rayd render: {e}"))?;
        if !out.status.success() {
            return Err(format!(
                "rayd render failed: {}",
                String::from_utf8_lossy(&out.stderr)
            ));
        }
        let render_png = std::fs::read(&png).map_err(|e| e.to_string())?;
        let bytes = std::fs::read(&plan.scene).map_err(|e| e.to_string())?;
        let ct = if plan.scene.extension().is_some_and(|e| e == "tri") {
            "application/x-rayd-tri"
        } else {
            "model/gltf-binary"
        };
        let up = request(&server.addr, "POST", "/v1/scenes", ct, &bytes)
            .map_err(|e| format!("upload: {e}"))?;
        if !(200..300).contains(&up.status) {
            return Err(format!("upload: {}", up.describe()));
        }
        let scene_id = up.json()["id"].as_str().ok_or("no scene id")?.to_string();
        Ok(Fixture {
            scene_id,
            small_rays: write_rays(&small),
            large_rays: write_rays(&large),
            small_hits,
            large_hits,
            variants,
            versions: RwLock::new(vec![(1, 0)]),
            render_png,
            engine,
            uploads: Mutex::new(HashMap::new()),
        })
    }

    /// The in-process HIT1 of version `version`'s small trace.
    fn small_expected(&self, version: u32) -> Option<&[u8]> {
        let v = self.versions.read().unwrap();
        v.iter()
            .find(|(n, _)| *n == version)
            .map(|(_, k)| self.small_hits[*k].as_slice())
    }
}

/// What one attempt at a step came to.
enum Step {
    /// Answered; the value is what the step needs next.
    Done(Answer),
    /// Refused with 503 and Retry-After: try again.
    Again,
    /// Broken by a restart (it may have taken effect before the answer): try again.
    Cut,
}

/// A worker's view of the run.
struct Ctx<'a> {
    server: &'a ServerProc,
    fx: &'a Fixture,
    stats: &'a Mutex<HashMap<Kind, KindStats>>,
    errors: &'a Mutex<Vec<String>>,
    deadline: Instant,
}

impl Ctx<'_> {
    fn error(&self, e: String) {
        self.errors.lock().unwrap().push(e);
    }

    fn count(&self, kind: Kind, f: impl FnOnce(&mut KindStats)) {
        f(self.stats.lock().unwrap().entry(kind).or_default());
    }

    /// One request, classified: a documented 503 gives `Again`, a restart `Cut` (each
    /// counted).
    fn send(
        &self,
        kind: Kind,
        method: &str,
        path: &str,
        ct: &str,
        body: &[u8],
    ) -> Result<Step, String> {
        let before = self.server.incarnation.load(Ordering::SeqCst);
        let was_down = self.server.down.load(Ordering::SeqCst);
        match request(&self.server.addr, method, path, ct, body) {
            Ok(a) if a.status == 503 => {
                if a.header("retry-after").is_none() {
                    return Err(format!("{method} {path}: 503 without Retry-After"));
                }
                self.count(kind, |k| k.refused += 1);
                std::thread::sleep(Duration::from_millis(100));
                Ok(Step::Again)
            }
            Ok(a) => Ok(Step::Done(a)),
            Err(e) => {
                let restarted = was_down
                    || self.server.down.load(Ordering::SeqCst)
                    || self.server.incarnation.load(Ordering::SeqCst) != before;
                if !restarted {
                    return Err(format!("{method} {path}: {e}"));
                }
                self.count(kind, |k| k.interrupted += 1);
                while self.server.down.load(Ordering::SeqCst) {
                    std::thread::sleep(Duration::from_millis(20));
                }
                Ok(Step::Cut)
            }
        }
    }

    /// Sends until answered (or the run is well past its end: then `None`).
    fn answer(
        &self,
        kind: Kind,
        method: &str,
        path: &str,
        ct: &str,
        body: &[u8],
    ) -> Result<Option<Answer>, String> {
        Ok(self
            .answer_after(kind, method, path, ct, body)?
            .map(|(a, _)| a))
    }

    /// [`Self::answer`], and whether an earlier try was cut off by a restart (so that it
    /// may have taken effect: a DELETE tried again then answers 404).
    fn answer_after(
        &self,
        kind: Kind,
        method: &str,
        path: &str,
        ct: &str,
        body: &[u8],
    ) -> Result<Option<(Answer, bool)>, String> {
        let mut cut_off = false;
        loop {
            if Instant::now() > self.deadline + Duration::from_secs(60) {
                return Ok(None);
            }
            match self.send(kind, method, path, ct, body)? {
                Step::Done(a) => return Ok(Some((a, cut_off))),
                Step::Cut => cut_off = true,
                Step::Again => {}
            }
        }
    }

    fn trace(
        &self,
        kind: Kind,
        scene: &str,
        version: Option<u32>,
        rays: &[u8],
        want: &[u8],
    ) -> Result<(), String> {
        let path = match version {
            Some(v) => format!("/v1/scenes/{scene}/trace?{TRACE_QUERY}&version={v}"),
            None => format!("/v1/scenes/{scene}/trace?{TRACE_QUERY}"),
        };
        let t0 = Instant::now();
        let Some(a) = self.answer(kind, "POST", &path, "application/octet-stream", rays)? else {
            return Ok(());
        };
        let secs = t0.elapsed().as_secs_f64();
        if a.status != 200 {
            return Err(format!("POST {path}: {}", a.describe()));
        }
        if a.body != want {
            return Err(format!(
                "POST {path}: {} HIT1 bytes differ from the in-process trace's {}",
                a.body.len(),
                want.len()
            ));
        }
        let n = (rays.len().saturating_sub(16) / 32) as u64;
        self.count(kind, |k| {
            k.latencies.push(secs);
            k.rays += n;
        });
        Ok(())
    }

    /// Submits a render job with `body` and returns its id; `None` past the run's end.
    fn submit_render(&self, kind: Kind, scene: &str, body: &str) -> Result<Option<String>, String> {
        let path = format!("/v1/scenes/{scene}/render");
        let Some(a) = self.answer(kind, "POST", &path, "application/json", body.as_bytes())? else {
            return Ok(None);
        };
        if a.status != 202 {
            return Err(format!("POST {path}: {}", a.describe()));
        }
        Ok(Some(a.json()["id"].as_str().unwrap_or("").to_string()))
    }

    /// Polls a job until it ends; `None` past the run's end.
    fn wait_job(&self, kind: Kind, id: &str) -> Result<Option<serde_json::Value>, String> {
        let path = format!("/v1/jobs/{id}");
        loop {
            let Some(a) = self.answer(kind, "GET", &path, "", &[])? else {
                return Ok(None);
            };
            if a.status != 200 {
                return Err(format!("GET {path}: {}", a.describe()));
            }
            let j = a.json();
            match j["state"].as_str() {
                Some("queued" | "running") => std::thread::sleep(Duration::from_millis(30)),
                Some(_) => return Ok(Some(j)),
                None => return Err(format!("GET {path}: no state in {j}")),
            }
        }
    }

    fn one(&self, kind: Kind, rng: &mut Rng) -> Result<(), String> {
        let fx = self.fx;
        let scene = fx.scene_id.as_str();
        match kind {
            Kind::SmallTrace => {
                // Version 1 or one of the latest: a working set that does not grow with
                // the run, so that RSS can plateau once the caches hold it.
                let (version, k) = {
                    let v = fx.versions.read().unwrap();
                    let recent = &v[v.len().saturating_sub(RECENT_VERSIONS)..];
                    match rng.below(RECENT_VERSIONS as u64 + 1) as usize {
                        0 => v[0],
                        _ => recent[rng.below(recent.len() as u64) as usize],
                    }
                };
                self.trace(
                    kind,
                    scene,
                    Some(version),
                    &fx.small_rays,
                    &fx.small_hits[k],
                )
            }
            Kind::LargeTrace => self.trace(kind, scene, Some(1), &fx.large_rays, &fx.large_hits),
            Kind::Geometry => {
                let k = 1 + rng.below(VARIANTS as u64) as usize;
                let path = format!("/v1/scenes/{scene}/geometry");
                let t0 = Instant::now();
                let Some(a) = self.answer(
                    kind,
                    "PUT",
                    &path,
                    "application/x-rayd-tri",
                    &fx.variants[k],
                )?
                else {
                    return Ok(());
                };
                let secs = t0.elapsed().as_secs_f64();
                if !(200..300).contains(&a.status) {
                    return Err(format!("PUT {path}: {}", a.describe()));
                }
                let version = a.json()["version"]
                    .as_u64()
                    .ok_or_else(|| format!("PUT {path}: no version in {}", a.describe()))?
                    as u32;
                fx.versions.write().unwrap().push((version, k));
                self.count(kind, |s| s.latencies.push(secs));
                // The new version answers as the same positions do in process.
                let want = fx.small_expected(version).expect("just added").to_vec();
                self.trace(
                    Kind::SmallTrace,
                    scene,
                    Some(version),
                    &fx.small_rays,
                    &want,
                )
            }
            Kind::Render => {
                let t0 = Instant::now();
                let Some(id) = self.submit_render(kind, scene, RENDER)? else {
                    return Ok(());
                };
                let Some(j) = self.wait_job(kind, &id)? else {
                    return Ok(());
                };
                if j["state"] != "succeeded" {
                    return Err(format!("render {id} ended {}: {}", j["state"], j["error"]));
                }
                let rpath = format!("/v1/jobs/{id}/result");
                let Some(r) = self.answer(kind, "GET", &rpath, "", &[])? else {
                    return Ok(());
                };
                if r.status != 200 || r.body != fx.render_png {
                    return Err(format!(
                        "GET {rpath}: {} with {} bytes, not rayd render's {}-byte PNG",
                        r.status,
                        r.body.len(),
                        fx.render_png.len()
                    ));
                }
                let secs = t0.elapsed().as_secs_f64();
                self.count(kind, |s| s.latencies.push(secs));
                // Finished jobs are deleted, so the store does not grow over a soak.
                let _ = self.answer(kind, "DELETE", &format!("/v1/jobs/{id}"), "", &[])?;
                Ok(())
            }
            Kind::Cancel => {
                let t0 = Instant::now();
                let Some(id) = self.submit_render(kind, scene, CANCEL)? else {
                    return Ok(());
                };
                std::thread::sleep(Duration::from_millis(rng.below(200)));
                let jpath = format!("/v1/jobs/{id}");
                let Some(d) = self.answer(kind, "DELETE", &jpath, "", &[])? else {
                    return Ok(());
                };
                match d.status {
                    // Cancelled (or, when it had ended already, deleted).
                    200 if d.json()["state"] == "cancelled" => {}
                    204 => {}
                    _ => return Err(format!("DELETE {jpath}: {}", d.describe())),
                }
                let secs = t0.elapsed().as_secs_f64();
                if d.status == 200 {
                    let Some(g) = self.answer(kind, "GET", &jpath, "", &[])? else {
                        return Ok(());
                    };
                    if g.status != 200 || g.json()["state"] != "cancelled" {
                        return Err(format!("GET {jpath} after a cancel: {}", g.describe()));
                    }
                    let Some(r) = self.answer(kind, "GET", &format!("{jpath}/result"), "", &[])?
                    else {
                        return Ok(());
                    };
                    if r.status != 409 {
                        return Err(format!("a cancelled job's result: {}", r.describe()));
                    }
                    let _ = self.answer(kind, "DELETE", &jpath, "", &[])?;
                }
                self.count(kind, |s| s.latencies.push(secs));
                Ok(())
            }
            Kind::Upload => {
                let seed = rng.next();
                let tris = soup(200, seed);
                let rays = rays_at(
                    &rayd::geometry::Aabb {
                        min: [0.0; 3],
                        max: [1.0; 3],
                    },
                    256,
                    seed ^ 1,
                );
                let want = expected_hits(&fx.engine, &format!("soup{seed}"), tris.clone(), &rays);
                let t0 = Instant::now();
                let Some(a) = self.answer(
                    kind,
                    "POST",
                    "/v1/scenes",
                    "application/x-rayd-tri",
                    &write_tri(&tris),
                )?
                else {
                    return Ok(());
                };
                if a.status != 201 && a.status != 200 {
                    return Err(format!("POST /v1/scenes: {}", a.describe()));
                }
                let id = a.json()["id"].as_str().unwrap_or("").to_string();
                fx.uploads.lock().unwrap().insert(id.clone(), want.clone());
                self.trace(Kind::SmallTrace, &id, None, &write_rays(&rays), &want)?;
                let dpath = format!("/v1/scenes/{id}");
                // Asked to delete, it may be gone from now on (a restart's check may come
                // between the deletion and its answer).
                fx.uploads.lock().unwrap().remove(&id);
                let Some((d, cut_off)) = self.answer_after(kind, "DELETE", &dpath, "", &[])? else {
                    return Ok(());
                };
                // A try cut off by a restart may have deleted it before the answer.
                let deleted = (200..300).contains(&d.status) || (cut_off && d.status == 404);
                if !deleted {
                    return Err(format!("DELETE {dpath}: {}", d.describe()));
                }
                let secs = t0.elapsed().as_secs_f64();
                self.count(kind, |s| s.latencies.push(secs));
                Ok(())
            }
        }
    }
}

/// Checks that everything acknowledged before a restart is there after it: the scene,
/// version 1 and the latest versions (each traces as in process), and the live uploads.
fn check_durable(server: &ServerProc, fx: &Fixture) -> Result<(), String> {
    let versions = {
        let all = fx.versions.read().unwrap();
        let mut some = vec![all[0]];
        some.extend_from_slice(&all[all.len().saturating_sub(CHECKED_VERSIONS).max(1)..]);
        some
    };
    for (v, k) in versions {
        let path = format!("/v1/scenes/{}/trace?{TRACE_QUERY}&version={v}", fx.scene_id);
        let a = request(
            &server.addr,
            "POST",
            &path,
            "application/octet-stream",
            &fx.small_rays,
        )
        .map_err(|e| format!("after a restart, {path}: {e}"))?;
        if a.status == 503 {
            continue;
        }
        if a.status != 200 || a.body != fx.small_hits[k] {
            return Err(format!(
                "after a restart, version {v} does not answer as acknowledged: {}",
                a.status
            ));
        }
    }
    let uploads: Vec<String> = fx.uploads.lock().unwrap().keys().cloned().collect();
    for id in uploads {
        let a = request(&server.addr, "GET", &format!("/v1/scenes/{id}"), "", &[])
            .map_err(|e| e.to_string())?;
        // Deleted meanwhile by its worker is fine; anything else but 200 is not.
        if a.status != 200 && fx.uploads.lock().unwrap().contains_key(&id) {
            return Err(format!(
                "after a restart, uploaded scene {id}: {}",
                a.status
            ));
        }
    }
    Ok(())
}

/// Runs the plan's mix against `server` (already started) and returns its figures.
pub fn run(plan: &Plan, server: &ServerProc, fx: &Fixture) -> Report {
    let stats = Mutex::new(HashMap::new());
    let errors = Mutex::new(Vec::new());
    let rss = Mutex::new(Vec::new());
    let restarts = Mutex::new((0u32, 0u32));
    let stop = AtomicBool::new(false);
    let t0 = Instant::now();
    let deadline = t0 + plan.duration;
    let cpu0 = cpu_seconds("self");
    let server_cpu0 = server.cpu();
    let total: u32 = plan.weights.iter().map(|(_, w)| w).sum();
    std::thread::scope(|s| {
        // RSS every 250 ms.
        s.spawn(|| {
            while !stop.load(Ordering::SeqCst) {
                if let Some(b) = server.pid().and_then(rss_bytes) {
                    let inc = server.incarnation.load(Ordering::SeqCst);
                    rss.lock()
                        .unwrap()
                        .push((t0.elapsed().as_secs_f64(), b, inc));
                }
                std::thread::sleep(Duration::from_millis(250));
            }
        });
        if let Some(every) = plan.restart_every {
            let (errors, restarts) = (&errors, &restarts);
            s.spawn(move || {
                let mut kill = true;
                let mut next = Instant::now() + every;
                while Instant::now() + Duration::from_secs(2) < deadline {
                    if Instant::now() < next {
                        std::thread::sleep(Duration::from_millis(50));
                        continue;
                    }
                    if let Err(e) = server.restart(kill) {
                        errors.lock().unwrap().push(format!("restart: {e}"));
                        return;
                    }
                    {
                        let mut r = restarts.lock().unwrap();
                        if kill {
                            r.0 += 1;
                        } else {
                            r.1 += 1;
                        }
                    }
                    if let Err(e) = check_durable(server, fx) {
                        errors.lock().unwrap().push(e);
                    }
                    kill = !kill;
                    next = Instant::now() + every;
                }
            });
        }
        let workers: Vec<_> = (0..plan.workers)
            .map(|w| {
                let ctx = Ctx {
                    server,
                    fx,
                    stats: &stats,
                    errors: &errors,
                    deadline,
                };
                s.spawn(move || {
                    let mut rng = Rng(0x5eed ^ (w as u64) << 32);
                    while Instant::now() < ctx.deadline {
                        let mut pick = rng.below(u64::from(total.max(1))) as u32;
                        let kind = plan
                            .weights
                            .iter()
                            .find(|(_, wt)| {
                                if pick < *wt {
                                    true
                                } else {
                                    pick -= wt;
                                    false
                                }
                            })
                            .map_or(Kind::SmallTrace, |(k, _)| *k);
                        if let Err(e) = ctx.one(kind, &mut rng) {
                            ctx.error(format!("{}: {e}", kind.name()));
                            if ctx.errors.lock().unwrap().len() > 50 {
                                return;
                            }
                        }
                    }
                })
            })
            .collect();
        for w in workers {
            let _ = w.join();
        }
        stop.store(true, Ordering::SeqCst);
    });
    let seconds = t0.elapsed().as_secs_f64();
    Report {
        kinds: stats.into_inner().unwrap(),
        errors: errors.into_inner().unwrap(),
        seconds,
        rss: rss.into_inner().unwrap(),
        restarts: restarts.into_inner().unwrap(),
        client_cpu: cpu_seconds("self") - cpu0,
        server_cpu: server.cpu() - server_cpu0,
    }
}
