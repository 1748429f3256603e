//! Load generator for `rayd serve`'s speed goals (BENCHMARKS.md §12). It starts
//! `target/release/rayd serve` itself on a free loopback port with a temporary data directory,
//! talks plain HTTP/1.1 over `TcpStream`, and compares with `rayd trace` (same binary, same
//! threads) in the same run, so that the ratios it prints share the machine's load.
//!
//! ```text
//! http_bench trace   SCENE RAYS [--runs N] [--threads T] [--accel A]
//! http_bench latency SCENE [--samples N] [--threads T]
//! http_bench frame   SCENE [RAYS] [--rays N] [--frames N] [--threads T] [--accel A]
//! http_bench rss     SCENE [--rays N] [--threads T]
//! ```
//!
//! - `trace`: a warm trace of RAYS (a RAY1 file, e.g. from `rayd bench --dump`) over HTTP,
//!   split into upload, queueing (time to the first answer byte less Server-Timing's build
//!   and trace), tracing and response, against `rayd trace`'s `trace_seconds`.
//! - `latency`: 1K-ray traces sent one after another while a 1024×768 path-traced render runs;
//!   their latency percentiles, and the same with the server idle.
//! - `frame`: frames of an animated scene, each a new animation time (`time=`) or a new
//!   geometry version (`PUT .../geometry`, or `POST .../frame` with the positions and the
//!   rays in one body) and a trace of N rays (`dacrt` unless `--accel`
//!   names the server's accelerator), against the same frame in process (`rayd trace
//!   --accel dacrt`: preparation plus trace, whatever `--accel` says). With RAYS, the
//!   frame's rays are also written there (for `scripts/http_trace_cpu.py`).
//! - `rss`: the server's peak RSS (VmHWM) around one request of N rays (16M), against the
//!   request + response + structure bytes.
//!
//! Each mode prints Markdown table rows to stdout; progress goes to stderr. Requests use a
//! connection each (`Connection: close`) unless `--keep-alive` has them share one, as a
//! client session does (the Python client's `requests.Session`).

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use rayd::formats::binary::{write_rays, write_tri};
use rayd::render::camera::ViewCamera;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let opts = Opts::parse(&args).unwrap_or_else(|e| {
        eprintln!("http_bench: {e}\n\n{}", USAGE);
        std::process::exit(2);
    });
    let result = match opts.mode.as_str() {
        "trace" => trace_mode(&opts),
        "latency" => latency_mode(&opts),
        "frame" => frame_mode(&opts),
        "rss" => rss_mode(&opts),
        m => Err(format!("unknown mode {m:?}")),
    };
    if let Err(e) = result {
        eprintln!("http_bench: {e}");
        std::process::exit(1);
    }
}

const USAGE: &str = "usage: http_bench trace|latency|frame|rss SCENE [RAYS] [--runs N] \
[--samples N] [--rays N] [--frames N] [--threads T] [--accel A] [--bin PATH] [--keep-alive]";

/// The command line.
struct Opts {
    mode: String,
    scene: PathBuf,
    rays_file: Option<PathBuf>,
    runs: usize,
    samples: usize,
    rays: usize,
    frames: usize,
    threads: usize,
    /// `--accel` as given: the server's accelerator (`trace`: default `mbvh8`; `frame`:
    /// default `dacrt`, the in-process frame's).
    accel: Option<String>,
    bin: PathBuf,
    keep_alive: bool,
}

impl Opts {
    fn parse(args: &[String]) -> Result<Opts, String> {
        let mut pos = Vec::new();
        let mut o = Opts {
            mode: String::new(),
            scene: PathBuf::new(),
            rays_file: None,
            runs: 5,
            samples: 200,
            rays: 0,
            frames: 6,
            threads: 2,
            accel: None,
            bin: Path::new(env!("CARGO_MANIFEST_DIR")).join("target/release/rayd"),
            keep_alive: false,
        };
        let mut it = args.iter();
        while let Some(a) = it.next() {
            let mut value = |name: &str| {
                it.next()
                    .cloned()
                    .ok_or_else(|| format!("{name} needs a value"))
            };
            let num = |name: &str, v: String| {
                v.parse::<usize>()
                    .map_err(|_| format!("{name} {v:?} is not a whole number"))
            };
            match a.as_str() {
                "--runs" => o.runs = num(a, value(a)?)?,
                "--samples" => o.samples = num(a, value(a)?)?,
                "--rays" => o.rays = num(a, value(a)?)?,
                "--frames" => o.frames = num(a, value(a)?)?,
                "--threads" => o.threads = num(a, value(a)?)?,
                "--accel" => o.accel = Some(value(a)?),
                "--bin" => o.bin = value(a)?.into(),
                "--keep-alive" => o.keep_alive = true,
                s if s.starts_with("--") => return Err(format!("unknown option {s}")),
                s => pos.push(s.to_string()),
            }
        }
        let mut pos = pos.into_iter();
        o.mode = pos.next().ok_or("no mode")?;
        o.scene = pos.next().ok_or("no scene")?.into();
        o.rays_file = pos.next().map(PathBuf::from);
        if o.runs == 0 || o.samples == 0 || o.frames == 0 {
            return Err("--runs, --samples and --frames must be at least 1".into());
        }
        Ok(o)
    }

    /// The server's accelerator: `--accel`, else `default`.
    fn accel<'a>(&'a self, default: &'a str) -> &'a str {
        self.accel.as_deref().unwrap_or(default)
    }
}

/// A `rayd serve` child on a free port with a temporary data directory.
struct Server {
    child: Child,
    addr: String,
    _data: TempDir,
    /// With `--keep-alive`, the connection the requests share, as a client session keeps
    /// one (the Python client's `requests.Session` does); otherwise a connection each.
    kept: Option<std::cell::RefCell<Option<TcpStream>>>,
}

/// A directory removed when dropped (std only: no tempfile in an example's path).
struct TempDir(PathBuf);

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn temp_dir(tag: &str) -> Result<TempDir, String> {
    let p = std::env::temp_dir().join(format!("rayd-http-bench-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&p).map_err(|e| format!("cannot create {}: {e}", p.display()))?;
    Ok(TempDir(p))
}

impl Server {
    fn start(o: &Opts) -> Result<Server, String> {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .map_err(|e| format!("no free port: {e}"))?
            .port();
        let addr = format!("127.0.0.1:{port}");
        let data = temp_dir("data")?;
        let child = Command::new(&o.bin)
            .args(["serve", "--addr", &addr, "--data-dir"])
            .arg(&data.0)
            .args(["--threads", &o.threads.to_string()])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| format!("cannot start {}: {e}", o.bin.display()))?;
        let s = Server {
            child,
            addr,
            _data: data,
            kept: o.keep_alive.then(Default::default),
        };
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(30) {
            if s.request("GET", "/readyz", "", &[])
                .is_ok_and(|r| r.status == 200)
            {
                return Ok(s);
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        Err("rayd serve did not become ready in 30 s".into())
    }

    /// One request, timed on the client: on a fresh connection, or with `--keep-alive` on
    /// the kept one (a new one if the server closed it).
    fn request(
        &self,
        method: &str,
        path: &str,
        content_type: &str,
        body: &[u8],
    ) -> Result<Timed, String> {
        let Some(kept) = &self.kept else {
            return self
                .exchange(None, method, path, content_type, body)
                .map(|(t, _)| t);
        };
        let reused = kept.borrow_mut().take();
        let was_reused = reused.is_some();
        let (timed, back) = match self.exchange(reused, method, path, content_type, body) {
            Err(_) if was_reused => self.exchange(None, method, path, content_type, body)?,
            other => other?,
        };
        *kept.borrow_mut() = back;
        Ok(timed)
    }

    /// One request and its answer on `stream` (a new connection if `None`); the stream
    /// comes back if it stays open.
    fn exchange(
        &self,
        stream: Option<TcpStream>,
        method: &str,
        path: &str,
        content_type: &str,
        body: &[u8],
    ) -> Result<(Timed, Option<TcpStream>), String> {
        let fail = |e: std::io::Error| format!("{method} {path}: {e}");
        let t0 = Instant::now();
        let keep = self.kept.is_some();
        let mut s = match stream {
            Some(s) => s,
            None => {
                let s = TcpStream::connect(&self.addr).map_err(fail)?;
                s.set_nodelay(true).map_err(fail)?;
                s
            }
        };
        let mut head = format!(
            "{method} {path} HTTP/1.1\r\nHost: {}\r\nConnection: {}\r\nContent-Length: {}\r\n",
            self.addr,
            if keep { "keep-alive" } else { "close" },
            body.len()
        );
        if !content_type.is_empty() {
            head.push_str(&format!("Content-Type: {content_type}\r\n"));
        }
        head.push_str("\r\n");
        s.write_all(head.as_bytes()).map_err(fail)?;
        s.write_all(body).map_err(fail)?;
        let sent = t0.elapsed().as_secs_f64();
        // The head first, then the body straight into memory of its announced length, as a
        // client that cares about large answers reads it (no growing buffer, no second copy).
        let mut raw = Vec::with_capacity(1 << 14);
        let mut buf = [0u8; 1 << 14];
        let mut first = None;
        let split = loop {
            let n = s.read(&mut buf).map_err(fail)?;
            if n == 0 {
                return Err(format!(
                    "{method} {path}: the connection closed before the head"
                ));
            }
            first.get_or_insert_with(|| t0.elapsed().as_secs_f64());
            raw.extend_from_slice(&buf[..n]);
            if let Some(p) = raw.windows(4).position(|w| w == b"\r\n\r\n") {
                break p;
            }
        };
        let head = String::from_utf8_lossy(&raw[..split]).to_string();
        let status = head
            .split(' ')
            .nth(1)
            .and_then(|c| c.parse().ok())
            .ok_or_else(|| format!("{method} {path}: bad status line"))?;
        let headers: Vec<(String, String)> = head
            .split("\r\n")
            .skip(1)
            .filter_map(|l| l.split_once(':'))
            .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
            .collect();
        let length = headers
            .iter()
            .find(|(k, _)| k == "content-length")
            .and_then(|(_, v)| v.parse::<usize>().ok());
        let mut body = Vec::with_capacity(length.unwrap_or(0));
        body.extend_from_slice(&raw[split + 4..]);
        match length {
            Some(len) => {
                let more = len.saturating_sub(body.len()) as u64;
                (&mut s).take(more).read_to_end(&mut body).map_err(fail)?;
            }
            None => {
                s.read_to_end(&mut body).map_err(fail)?;
            }
        }
        let done = t0.elapsed().as_secs_f64();
        let closes = length.is_none()
            || headers
                .iter()
                .any(|(k, v)| k == "connection" && v.eq_ignore_ascii_case("close"));
        let back = (keep && !closes).then_some(s);
        Ok((
            Timed {
                status,
                headers,
                body,
                sent,
                first: first.unwrap_or(done),
                done,
            },
            back,
        ))
    }

    /// A request that must answer 2xx.
    fn ok(&self, method: &str, path: &str, ct: &str, body: &[u8]) -> Result<Timed, String> {
        let r = self.request(method, path, ct, body)?;
        if !(200..300).contains(&r.status) {
            return Err(format!(
                "{method} {path}: {} {}",
                r.status,
                String::from_utf8_lossy(&r.body)
            ));
        }
        Ok(r)
    }

    /// Uploads a scene file and returns its id.
    fn upload(&self, scene: &Path) -> Result<String, String> {
        let bytes =
            std::fs::read(scene).map_err(|e| format!("cannot read {}: {e}", scene.display()))?;
        let ct = if scene.extension().is_some_and(|e| e == "tri") {
            "application/x-rayd-tri"
        } else {
            "model/gltf-binary"
        };
        let r = self.ok("POST", "/v1/scenes", ct, &bytes)?;
        json_str(&r.body, "id")
    }

    /// The server's peak resident set (VmHWM) and current one (VmRSS), in bytes.
    fn memory(&self) -> Result<(u64, u64), String> {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id()))
            .map_err(|e| format!("cannot read the server's /proc status: {e}"))?;
        let field = |name: &str| {
            status
                .lines()
                .find_map(|l| l.strip_prefix(name))
                .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
                .map(|kb| kb * 1024)
                .ok_or_else(|| format!("no {name} in /proc status"))
        };
        Ok((field("VmHWM:")?, field("VmRSS:")?))
    }

    /// A gauge or counter of `/metrics` whose name ends with `name`.
    fn metric(&self, name: &str) -> Result<f64, String> {
        let r = self.ok("GET", "/metrics", "", &[])?;
        String::from_utf8_lossy(&r.body)
            .lines()
            .filter(|l| !l.starts_with('#'))
            .find_map(|l| {
                let (k, v) = l.split_once(' ')?;
                k.ends_with(name).then(|| v.trim().parse().ok())?
            })
            .ok_or_else(|| format!("no metric {name}"))
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// An answer with the client's clock: seconds from connecting to the last body byte
/// written, to the first answer byte read, and to the last.
struct Timed {
    status: u16,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
    sent: f64,
    first: f64,
    done: f64,
}

impl Timed {
    /// `name;dur=MS` of the Server-Timing header, in seconds.
    fn server_timing(&self, name: &str) -> Option<f64> {
        let (_, v) = self.headers.iter().find(|(k, _)| k == "server-timing")?;
        v.split(',')
            .find_map(|part| {
                let (n, rest) = part.trim().split_once(';')?;
                (n == name).then(|| rest.trim().strip_prefix("dur=")?.parse::<f64>().ok())?
            })
            .map(|ms| ms / 1e3)
    }
}

/// A string field of a JSON object (the few this tool reads are flat).
fn json_str(body: &[u8], field: &str) -> Result<String, String> {
    let v: serde_json::Value =
        serde_json::from_slice(body).map_err(|e| format!("not JSON ({e}): {field}"))?;
    v[field]
        .as_str()
        .map(str::to_string)
        .ok_or_else(|| format!("no {field} in {v}"))
}

/// Runs `rayd trace` on a file and returns its report.
fn cli_trace(
    o: &Opts,
    scene: &Path,
    rays: &Path,
    extra: &[&str],
) -> Result<serde_json::Value, String> {
    let out = temp_dir("cli")?;
    let r = Command::new(&o.bin)
        .arg("trace")
        .arg(scene)
        .arg("--rays")
        .arg(rays)
        .arg("--out")
        .arg(out.0.join("hits.hit"))
        .args(["--threads", &o.threads.to_string()])
        .args(extra)
        .output()
        .map_err(|e| format!("cannot run rayd trace: {e}"))?;
    if !r.status.success() {
        return Err(format!(
            "rayd trace failed: {}",
            String::from_utf8_lossy(&r.stderr)
        ));
    }
    serde_json::from_slice(&r.stdout).map_err(|e| format!("rayd trace printed no report: {e}"))
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// The `p`-th percentile (nearest rank) of sorted values.
fn percentile(sorted: &[f64], p: f64) -> f64 {
    let rank = ((p / 100.0) * sorted.len() as f64).ceil() as usize;
    sorted[rank.clamp(1, sorted.len()) - 1]
}

/// The load average of the last minute: how busy the shared machine was.
fn load() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split(' ').next().map(str::to_string))
        .unwrap_or_else(|| "?".into())
}

/// N camera rays (one per pixel of a square image) that frame the scene: primary rays.
fn camera_rays(scene: &Path, n: usize, time: Option<f64>) -> Result<Vec<u8>, String> {
    let opts = rayd::formats::LoadOptions { time };
    let scene =
        rayd::formats::load_scene(scene, &opts).map_err(|e| format!("{}: {e}", scene.display()))?;
    let bounds = scene.bounds().ok_or("the scene has no triangles")?;
    let side = (n as f64).sqrt().ceil() as u32;
    let camera = ViewCamera::framing(&bounds, 1.0);
    let rays: Vec<_> = (0..n as u32)
        .map(|i| camera.ray((i % side) as f64 + 0.5, (i / side) as f64 + 0.5, side, side))
        .collect();
    Ok(write_rays(&rays))
}

fn trace_mode(o: &Opts) -> Result<(), String> {
    let rays_file = o.rays_file.as_ref().ok_or("trace needs a RAYS file")?;
    let rays = std::fs::read(rays_file).map_err(|e| format!("{}: {e}", rays_file.display()))?;
    let n = rays.len().saturating_sub(16) / 32;
    let s = Server::start(o)?;
    let id = s.upload(&o.scene)?;
    let path = format!("/v1/scenes/{id}/trace?accel={}", o.accel("mbvh8"));
    let octet = "application/octet-stream";
    // Warm: the structure is built and cached by the first trace.
    let warm = s.ok("POST", &path, octet, &rays)?;
    let build = warm.server_timing("build").unwrap_or(f64::NAN);
    let (mut up, mut queue, mut tr, mut resp, mut total, mut cli) =
        (vec![], vec![], vec![], vec![], vec![], vec![]);
    for run in 0..o.runs {
        // Alternate: one in process, one over HTTP, so both see the same load.
        let c = cli_trace(o, &o.scene, rays_file, &["--accel", o.accel("mbvh8")])?;
        cli.push(c["trace_seconds"].as_f64().ok_or("no trace_seconds")?);
        let r = s.ok("POST", &path, octet, &rays)?;
        let t = r.server_timing("trace").ok_or("no Server-Timing trace")?;
        let b = r.server_timing("build").unwrap_or(0.0);
        up.push(r.sent);
        tr.push(t);
        queue.push((r.first - r.sent - t - b).max(0.0));
        resp.push(r.done - r.first);
        total.push(r.done);
        eprintln!(
            "run {run}: http {:.3} s (upload {:.3}, trace {:.3}), rayd trace {:.3} s, load {}",
            r.done,
            r.sent,
            t,
            cli[run],
            load()
        );
    }
    let mut ratios: Vec<f64> = total.iter().zip(&cli).map(|(h, c)| h / c).collect();
    println!(
        "| {} | {n} | {} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {:.2} | {} |",
        o.scene.file_name().unwrap_or_default().to_string_lossy(),
        o.threads,
        build * 1e3,
        median(&mut up) * 1e3,
        median(&mut queue) * 1e3,
        median(&mut tr) * 1e3,
        median(&mut resp) * 1e3,
        median(&mut total) * 1e3,
        median(&mut cli) * 1e3,
        median(&mut ratios),
        load()
    );
    Ok(())
}

fn latency_mode(o: &Opts) -> Result<(), String> {
    let s = Server::start(o)?;
    let id = s.upload(&o.scene)?;
    let rays = camera_rays(&o.scene, 1024, None)?;
    let path = format!("/v1/scenes/{id}/trace?accel={}", o.accel("mbvh8"));
    let octet = "application/octet-stream";
    s.ok("POST", &path, octet, &rays)?;
    let sample = |n: usize| -> Result<Vec<f64>, String> {
        let mut lat = Vec::with_capacity(n);
        for _ in 0..n {
            lat.push(s.ok("POST", &path, octet, &rays)?.done);
            std::thread::sleep(Duration::from_millis(10));
        }
        lat.sort_by(f64::total_cmp);
        Ok(lat)
    };
    let idle = sample(o.samples)?;
    let job = s.ok(
        "POST",
        &format!("/v1/scenes/{id}/render"),
        "application/json",
        br#"{"width": 1024, "height": 768, "spp": 4096, "integrator": "path", "accel": "mbvh8"}"#,
    )?;
    let job = json_str(&job.body, "id")?;
    let t0 = Instant::now();
    while json_str(
        &s.ok("GET", &format!("/v1/jobs/{job}"), "", &[])?.body,
        "state",
    )? != "running"
    {
        if t0.elapsed() > Duration::from_secs(30) {
            return Err("the render did not start".into());
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    let busy = sample(o.samples)?;
    let state = json_str(
        &s.ok("GET", &format!("/v1/jobs/{job}"), "", &[])?.body,
        "state",
    )?;
    s.ok("DELETE", &format!("/v1/jobs/{job}"), "", &[])?;
    if state != "running" {
        return Err(format!("the render was {state} before the last sample"));
    }
    for (what, lat) in [("idle", &idle), ("during a 1024×768 path render", &busy)] {
        println!(
            "| {} | {what} | {} | {:.1} | {:.1} | {:.1} | {:.1} | {} |",
            o.scene.file_name().unwrap_or_default().to_string_lossy(),
            lat.len(),
            percentile(lat, 50.0) * 1e3,
            percentile(lat, 90.0) * 1e3,
            percentile(lat, 99.0) * 1e3,
            lat[lat.len() - 1] * 1e3,
            load()
        );
    }
    Ok(())
}

fn frame_mode(o: &Opts) -> Result<(), String> {
    let n = if o.rays == 0 { 1 << 18 } else { o.rays };
    let s = Server::start(o)?;
    let id = s.upload(&o.scene)?;
    let tmp = temp_dir("frame")?;
    // With RAYS, the frame's rays are written (and read back by `rayd trace`) there.
    let rays_path = o
        .rays_file
        .clone()
        .unwrap_or_else(|| tmp.0.join("rays.ray"));
    let rays = camera_rays(&o.scene, n, Some(0.0))?;
    std::fs::write(&rays_path, &rays).map_err(|e| format!("{}: {e}", rays_path.display()))?;
    let octet = "application/octet-stream";
    let base = rayd::formats::load_scene(&o.scene, &Default::default())
        .map_err(|e| format!("{}: {e}", o.scene.display()))?;
    let height = base
        .bounds()
        .map(|b| b.max[1] - b.min[1])
        .ok_or("no triangles")?;
    // Warm: the first trace loads the scene; its time is not a frame's.
    s.ok(
        "POST",
        &format!("/v1/scenes/{id}/trace?accel=dacrt"),
        octet,
        &rays,
    )?;
    let (mut t_http, mut t_cli, mut g_http, mut g_cli) = (vec![], vec![], vec![], vec![]);
    let mut f_http = vec![];
    for k in 1..=o.frames {
        // `time=`: a new animation time every frame.
        let time = 0.1 * k as f64;
        let r = s.ok(
            "POST",
            &format!(
                "/v1/scenes/{id}/trace?accel={}&version=1&time={time}",
                o.accel("dacrt")
            ),
            octet,
            &rays,
        )?;
        t_http.push(r.done);
        let c = cli_trace(
            o,
            &o.scene,
            &rays_path,
            &["--accel", "dacrt", "--time", &time.to_string()],
        )?;
        t_cli.push(
            c["build_seconds"].as_f64().unwrap_or(0.0) + c["trace_seconds"].as_f64().unwrap_or(0.0),
        );
        // A geometry update: the scene lifted by a little more every frame.
        let mut tris = base.triangles.clone();
        let lift = 0.01 * k as f32 * height;
        for t in &mut tris {
            for v in &mut t.v {
                v[1] += lift;
            }
        }
        let tri = write_tri(&tris);
        let tri_path = tmp.0.join("frame.tri");
        std::fs::write(&tri_path, &tri).map_err(|e| e.to_string())?;
        let put = s.ok(
            "PUT",
            &format!("/v1/scenes/{id}/geometry"),
            "application/x-rayd-tri",
            &tri,
        )?;
        let r = s.ok(
            "POST",
            &format!("/v1/scenes/{id}/trace?accel={}", o.accel("dacrt")),
            octet,
            &rays,
        )?;
        g_http.push(put.done + r.done);
        let c = cli_trace(o, &tri_path, &rays_path, &["--accel", "dacrt"])?;
        g_cli.push(
            c["build_seconds"].as_f64().unwrap_or(0.0) + c["trace_seconds"].as_f64().unwrap_or(0.0),
        );
        // The same positions and rays in one request (`POST .../frame`), after the same
        // in-process run as the `PUT` + trace: against the same reference.
        let r = s.ok(
            "POST",
            &format!("/v1/scenes/{id}/frame?accel={}", o.accel("dacrt")),
            "application/x-rayd-frame",
            &[&tri[..], &rays[..]].concat(),
        )?;
        f_http.push(r.done);
        eprintln!(
            "frame {k}: time= {:.3} s vs {:.3} s; PUT+trace {:.3} s (PUT {:.3}), frame {:.3} s, vs {:.3} s; load {}",
            t_http[k - 1],
            t_cli[k - 1],
            g_http[k - 1],
            put.done,
            f_http[k - 1],
            g_cli[k - 1],
            load()
        );
    }
    let name = o
        .scene
        .file_name()
        .unwrap_or_default()
        .to_string_lossy()
        .to_string();
    let mut f_cli = g_cli.clone();
    for (what, http, cli) in [
        ("time=", &mut t_http, &mut t_cli),
        ("PUT geometry + trace", &mut g_http, &mut g_cli),
        ("POST frame", &mut f_http, &mut f_cli),
    ] {
        let mut ratios: Vec<f64> = http.iter().zip(cli.iter()).map(|(h, c)| h / c).collect();
        println!(
            "| {name} | {what} | {n} | {} | {:.1} | {:.1} | {:.2} | {} |",
            http.len(),
            median(http) * 1e3,
            median(cli) * 1e3,
            median(&mut ratios),
            load()
        );
    }
    Ok(())
}

fn rss_mode(o: &Opts) -> Result<(), String> {
    let n = if o.rays == 0 { 1 << 24 } else { o.rays };
    let s = Server::start(o)?;
    let id = s.upload(&o.scene)?;
    let octet = "application/octet-stream";
    let path = format!("/v1/scenes/{id}/trace?accel={}", o.accel("mbvh8"));
    // The structure is built (and cached) by a small trace first, so the peak of the big
    // request is measured from a server that already holds it.
    s.ok("POST", &path, octet, &camera_rays(&o.scene, 1024, None)?)?;
    let rays = camera_rays(&o.scene, n, None)?;
    let (hwm0, rss0) = s.memory()?;
    let r = s.ok("POST", &path, octet, &rays)?;
    let (hwm1, _) = s.memory()?;
    // The housekeeping tick sets the cache gauge once a second.
    std::thread::sleep(Duration::from_millis(1500));
    let structure = s.metric("cache_bytes")? as u64;
    let request = rays.len() as u64;
    let response = r.body.len() as u64;
    let sum = request + response + structure;
    let mib = |b: u64| b as f64 / (1 << 20) as f64;
    println!(
        "| {} | {n} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.0} | {:.2} | {:.2} | {} |",
        o.scene.file_name().unwrap_or_default().to_string_lossy(),
        mib(request),
        mib(response),
        mib(structure),
        mib(rss0),
        mib(hwm0),
        mib(hwm1),
        mib(hwm1.saturating_sub(rss0)),
        hwm1 as f64 / sum as f64,
        hwm1.saturating_sub(rss0) as f64 / sum as f64,
        load()
    );
    Ok(())
}
