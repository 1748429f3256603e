//! A real `rayd serve` on a free loopback port and a tiny HTTP/1.1 client over `TcpStream`,
//! shared by the tests that drive the service end to end (`serve.rs`, `serve_faults.rs`).
#![allow(dead_code)]

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The `rayd` binary that cargo built for this test crate.
pub const BIN: &str = env!("CARGO_BIN_EXE_rayd");

/// The repository's small sample scenes.
pub fn scenes() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes")
}

/// A running `rayd serve`, killed when dropped.
pub struct Server {
    pub child: Child,
    pub addr: String,
}

impl Server {
    pub fn start(data: &Path, extra: &[&str]) -> Server {
        // A free port: bind, read it, release it.
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let addr = format!("127.0.0.1:{port}");
        // Two pool threads unless `extra` names its own count.
        let threads: &[&str] = if extra.contains(&"--threads") {
            &[]
        } else {
            &["--threads", "2"]
        };
        // Two seconds of grace unless `extra` names its own.
        let grace: &[&str] = if extra.contains(&"--grace") {
            &[]
        } else {
            &["--grace", "2"]
        };
        let child = Command::new(BIN)
            .args(["serve", "--addr", &addr, "--data-dir"])
            .arg(data)
            .args(threads)
            .args(grace)
            .args(extra)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let s = Server { child, addr };
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(20) {
            if let Ok(r) = s.try_request("GET", "/readyz", &[], &[]) {
                if r.status == 200 {
                    return s;
                }
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        panic!("rayd serve did not become ready");
    }

    pub fn try_request(
        &self,
        method: &str,
        path: &str,
        headers: &[(&str, &str)],
        body: &[u8],
    ) -> std::io::Result<Resp> {
        let mut s = self.open(method, path, headers, body.len())?;
        s.write_all(body)?;
        read_resp(s)
    }

    pub fn req(&self, method: &str, path: &str, headers: &[(&str, &str)], body: &[u8]) -> Resp {
        self.try_request(method, path, headers, body).unwrap()
    }

    /// Uploads `tris` as a TRI1 scene (`201` asserted): its summary.
    pub fn upload_tri(&self, tris: &[rayd::geometry::Triangle]) -> serde_json::Value {
        let r = self.req(
            "POST",
            "/v1/scenes",
            &[("Content-Type", "application/x-rayd-tri")],
            &rayd::formats::binary::write_tri(tris),
        );
        assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
        r.json()
    }

    /// Uploads the repository's sample scene `name` (a `.glb`) as a new scene: its summary.
    pub fn upload_sample(&self, name: &str) -> serde_json::Value {
        let bytes = std::fs::read(scenes().join(name)).unwrap();
        let r = self.req(
            "POST",
            "/v1/scenes",
            &[("Content-Type", "model/gltf-binary")],
            &bytes,
        );
        assert_eq!(r.status, 201, "{}", String::from_utf8_lossy(&r.body));
        r.json()
    }

    /// POSTs render options `body` (JSON) for scene `scene`: the answer, whatever it is.
    pub fn post_render(&self, scene: &str, body: &[u8]) -> Resp {
        self.req(
            "POST",
            &format!("/v1/scenes/{scene}/render"),
            &[("Content-Type", "application/json")],
            body,
        )
    }

    /// POSTs render options `body` for scene `scene`: the new job's id (202 asserted).
    pub fn submit_render(&self, scene: &str, body: &[u8]) -> String {
        let r = self.post_render(scene, body);
        assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
        r.json()["id"].as_str().unwrap().to_string()
    }

    pub fn kill9(mut self) {
        self.child.kill().unwrap();
        self.child.wait().unwrap();
    }

    pub fn stop(self) {
        self.signal("TERM");
        self.wait_exit();
    }

    /// Sends signal `name` (`TERM`, `INT`, …) to the server.
    pub fn signal(&self, name: &str) {
        let pid = self.child.id().to_string();
        Command::new("kill")
            .args([&format!("-{name}"), &pid])
            .status()
            .unwrap();
    }

    /// Waits at most 15 s for the server to exit (after a signal).
    pub fn wait_exit(mut self) {
        let t0 = Instant::now();
        loop {
            if self.child.try_wait().unwrap().is_some() {
                return;
            }
            assert!(
                t0.elapsed() < Duration::from_secs(15),
                "no exit after SIGTERM"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Opens a connection and sends a request head announcing `len` body bytes, leaving
    /// the body to the caller: for clients that send slowly or stop half-way.
    pub fn open(
        &self,
        method: &str,
        path: &str,
        headers: &[(&str, &str)],
        len: usize,
    ) -> std::io::Result<TcpStream> {
        let mut s = TcpStream::connect(&self.addr)?;
        s.set_read_timeout(Some(Duration::from_secs(60)))?;
        let mut req = format!(
            "{method} {path} HTTP/1.1\r\nHost: {}\r\nConnection: close\r\nContent-Length: {len}\r\n",
            self.addr
        );
        for (k, v) in headers {
            req.push_str(&format!("{k}: {v}\r\n"));
        }
        req.push_str("\r\n");
        s.write_all(req.as_bytes())?;
        Ok(s)
    }

    /// The server's process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }
}

/// Reads an answer to its end (the requests say `Connection: close`).
pub fn read_resp(mut s: TcpStream) -> std::io::Result<Resp> {
    let mut raw = Vec::new();
    s.read_to_end(&mut raw)?;
    if raw.is_empty() {
        return Err(std::io::Error::new(
            std::io::ErrorKind::UnexpectedEof,
            "the connection closed without an answer",
        ));
    }
    Ok(Resp::parse(&raw))
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One parsed answer (a chunked body already joined).
pub struct Resp {
    pub status: u16,
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl Resp {
    pub fn parse(raw: &[u8]) -> Resp {
        let split = raw
            .windows(4)
            .position(|w| w == b"\r\n\r\n")
            .expect("a header block");
        let head = String::from_utf8_lossy(&raw[..split]).to_string();
        let mut lines = head.split("\r\n");
        let status = lines
            .next()
            .unwrap()
            .split(' ')
            .nth(1)
            .unwrap()
            .parse()
            .unwrap();
        let headers: Vec<(String, String)> = lines
            .filter_map(|l| l.split_once(':'))
            .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
            .collect();
        let mut body = raw[split + 4..].to_vec();
        if headers
            .iter()
            .any(|(k, v)| k == "transfer-encoding" && v.contains("chunked"))
        {
            body = dechunk(&body);
        }
        Resp {
            status,
            headers,
            body,
        }
    }

    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.as_str())
    }

    pub fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.body)
            .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&self.body)))
    }
}

fn dechunk(mut b: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    loop {
        let line_end = b.windows(2).position(|w| w == b"\r\n").unwrap();
        let n =
            usize::from_str_radix(std::str::from_utf8(&b[..line_end]).unwrap().trim(), 16).unwrap();
        b = &b[line_end + 2..];
        if n == 0 {
            return out;
        }
        out.extend_from_slice(&b[..n]);
        b = &b[n + 2..];
    }
}

/// Waits (polling every 5 ms, at most `secs`) until job `id` is `running`.
pub fn wait_running(s: &Server, id: &str, secs: u64) {
    let t0 = Instant::now();
    while s.req("GET", &format!("/v1/jobs/{id}"), &[], &[]).json()["state"] != "running" {
        assert!(
            t0.elapsed() < Duration::from_secs(secs),
            "job {id} did not start"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
}

pub fn wait_job(s: &Server, id: &str, secs: u64) -> serde_json::Value {
    let t0 = Instant::now();
    loop {
        let j = s.req("GET", &format!("/v1/jobs/{id}"), &[], &[]).json();
        let st = j["state"].as_str().unwrap().to_string();
        if st != "queued" && st != "running" {
            return j;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(secs),
            "job {id} did not end: {j}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}
