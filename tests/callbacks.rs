//! Render jobs' callbacks end to end on loopback: a real `rayd serve` POSTs finished jobs to
//! a receiver in this test, which checks each signature; a failing receiver is retried up
//! to `--callback-attempts` and given up on; a redirect is not followed; a host not on
//! `--callback-allow` is refused at submission; a delivery a `kill -9` interrupted is
//! finished by the next start (`proto/service.md`, "Callbacks").

#[path = "common/server.rs"]
mod server;

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use hmac::{KeyInit, Mac};
use server::{wait_job, Server};

const SECRET: &str = "callback test secret, 32 bytes.";

/// One POST the receiver got.
#[derive(Clone, Debug)]
struct Got {
    path: String,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Got {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.as_str())
    }
}

/// A loopback HTTP receiver: `/ok` answers 204, `/fail` 500, `/redirect` 302 to `/ok`,
/// `/flaky` 503 until `healthy` is set, then 204.
struct Receiver {
    port: u16,
    got: Arc<Mutex<Vec<Got>>>,
    healthy: Arc<AtomicBool>,
}

impl Receiver {
    fn start() -> Receiver {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = listener.local_addr().unwrap().port();
        let got = Arc::new(Mutex::new(Vec::new()));
        let healthy = Arc::new(AtomicBool::new(false));
        let (g, h) = (Arc::clone(&got), Arc::clone(&healthy));
        std::thread::spawn(move || {
            for conn in listener.incoming().flatten() {
                let (g, h) = (Arc::clone(&g), Arc::clone(&h));
                std::thread::spawn(move || serve_one(conn, &g, &h));
            }
        });
        Receiver { port, got, healthy }
    }

    fn url(&self, path: &str) -> String {
        format!("http://127.0.0.1:{}{path}", self.port)
    }

    fn got(&self) -> Vec<Got> {
        self.got.lock().unwrap().clone()
    }

    /// Waits until `n` POSTs have arrived (and a moment more, to see that no more do).
    fn wait_for(&self, n: usize, secs: u64) -> Vec<Got> {
        let t0 = Instant::now();
        while self.got().len() < n {
            assert!(
                t0.elapsed() < Duration::from_secs(secs),
                "{} of {n} callbacks arrived: {:?}",
                self.got().len(),
                self.got()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        std::thread::sleep(Duration::from_millis(300));
        self.got()
    }
}

fn serve_one(mut conn: TcpStream, got: &Mutex<Vec<Got>>, healthy: &AtomicBool) {
    conn.set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let mut raw = Vec::new();
    let mut buf = [0u8; 4096];
    let split = loop {
        if let Some(i) = raw.windows(4).position(|w| w == b"\r\n\r\n") {
            break i;
        }
        match conn.read(&mut buf) {
            Ok(0) | Err(_) => return,
            Ok(n) => raw.extend_from_slice(&buf[..n]),
        }
    };
    let head = String::from_utf8_lossy(&raw[..split]).to_string();
    let mut lines = head.split("\r\n");
    let request_line = lines.next().unwrap_or("");
    let path = request_line.split(' ').nth(1).unwrap_or("").to_string();
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
        .collect();
    let len: usize = headers
        .iter()
        .find(|(k, _)| k == "content-length")
        .and_then(|(_, v)| v.parse().ok())
        .unwrap_or(0);
    let mut body = raw[split + 4..].to_vec();
    while body.len() < len {
        match conn.read(&mut buf) {
            Ok(0) | Err(_) => return,
            Ok(n) => body.extend_from_slice(&buf[..n]),
        }
    }
    assert!(request_line.starts_with("POST "), "{request_line}");
    let answer = match path.as_str() {
        "/ok" => "HTTP/1.1 204 No Content\r\n".to_string(),
        "/redirect" => "HTTP/1.1 302 Found\r\nLocation: /ok\r\nContent-Length: 0\r\n".into(),
        "/flaky" if healthy.load(Ordering::SeqCst) => "HTTP/1.1 204 No Content\r\n".into(),
        "/flaky" => "HTTP/1.1 503 Service Unavailable\r\nContent-Length: 0\r\n".into(),
        _ => "HTTP/1.1 500 Internal Server Error\r\nContent-Length: 0\r\n".into(),
    };
    got.lock().unwrap().push(Got {
        path,
        headers,
        body,
    });
    let _ = conn.write_all(format!("{answer}Connection: close\r\n\r\n").as_bytes());
}

/// Checks a POST's signature and timestamp as a receiver would, with the HMAC crates.
fn check_signature(g: &Got) {
    let ts = g.header("rayd-timestamp").expect("a timestamp header");
    let sent: u64 = ts.parse().expect("whole seconds");
    let now = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_secs();
    assert!(now.abs_diff(sent) < 120, "timestamp {sent}, now {now}");
    let mut mac = hmac::Hmac::<sha2::Sha256>::new_from_slice(SECRET.as_bytes()).unwrap();
    mac.update(format!("{ts}.").as_bytes());
    mac.update(&g.body);
    let hex: String = mac
        .finalize()
        .into_bytes()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    assert_eq!(
        g.header("rayd-signature"),
        Some(format!("sha256={hex}").as_str())
    );
    assert_eq!(g.header("content-type"), Some("application/json"));
}

fn start(data: &Path, secret: &Path, receiver: &Receiver, attempts: &str) -> Server {
    let allow = format!("127.0.0.1:{}", receiver.port);
    Server::start(
        data,
        &[
            "--callback-allow",
            &allow,
            "--callback-secret-file",
            secret.to_str().unwrap(),
            "--callback-attempts",
            attempts,
            "--callback-timeout",
            "2",
        ],
    )
}

fn secret_file(dir: &Path) -> std::path::PathBuf {
    let f = dir.join("secret");
    std::fs::write(&f, format!("{SECRET}\n")).unwrap();
    f
}

fn upload(s: &Server) -> String {
    s.upload_sample("Box.glb")["id"]
        .as_str()
        .unwrap()
        .to_string()
}

fn render(s: &Server, scene: &str, spec: serde_json::Value) -> server::Resp {
    s.req(
        "POST",
        &format!("/v1/scenes/{scene}/render"),
        &[("Content-Type", "application/json")],
        spec.to_string().as_bytes(),
    )
}

fn submit(s: &Server, scene: &str, spec: serde_json::Value) -> String {
    let r = render(s, scene, spec);
    assert_eq!(r.status, 202, "{}", String::from_utf8_lossy(&r.body));
    r.json()["id"].as_str().unwrap().to_string()
}

/// Polls the job until its callback is no longer pending.
fn wait_callback(s: &Server, id: &str, secs: u64) -> serde_json::Value {
    let t0 = Instant::now();
    loop {
        let j = s.req("GET", &format!("/v1/jobs/{id}"), &[], &[]).json();
        if j["callback"]["state"] != "pending" {
            return j;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(secs),
            "callback still pending: {j}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn finished_and_cancelled_jobs_are_posted_signed() {
    let dir = tempfile::tempdir().unwrap();
    let rx = Receiver::start();
    let s = start(&dir.path().join("data"), &secret_file(dir.path()), &rx, "3");
    let scene = upload(&s);

    let id = submit(
        &s,
        &scene,
        serde_json::json!({"width": 32, "height": 24, "callback": rx.url("/ok")}),
    );
    let done = wait_job(&s, &id, 60);
    assert_eq!(done["state"], "succeeded");
    let got = rx.wait_for(1, 30);
    assert_eq!(got.len(), 1, "one delivery: {got:?}");
    let g = &got[0];
    assert_eq!(g.path, "/ok");
    assert_eq!(g.header("rayd-job"), Some(id.as_str()));
    check_signature(g);
    // The body is the finished job as GET /v1/jobs/{id} shows it.
    let posted: serde_json::Value = serde_json::from_slice(&g.body).unwrap();
    assert_eq!(posted["id"], id.as_str());
    assert_eq!(posted["state"], "succeeded");
    assert_eq!(posted["results"], 1);
    assert_eq!(posted["request"]["callback"], rx.url("/ok"));
    let view = wait_callback(&s, &id, 10);
    assert_eq!(view["callback"]["state"], "delivered");
    assert_eq!(view["callback"]["attempts"], 1);
    for k in ["id", "state", "finished_at", "stats", "request", "results"] {
        assert_eq!(posted[k], view[k], "{k}");
    }

    // A cancelled job is posted too.
    let long = submit(
        &s,
        &scene,
        serde_json::json!({"width": 512, "height": 512, "spp": 256, "integrator": "path",
                           "callback": rx.url("/ok")}),
    );
    let c = s.req("DELETE", &format!("/v1/jobs/{long}"), &[], &[]);
    assert_eq!(c.status, 200);
    let got = rx.wait_for(2, 30);
    let g = got
        .iter()
        .find(|g| g.header("rayd-job") == Some(long.as_str()))
        .expect("the cancelled job's callback");
    check_signature(g);
    let posted: serde_json::Value = serde_json::from_slice(&g.body).unwrap();
    assert_eq!(posted["state"], "cancelled");
    assert_eq!(
        wait_callback(&s, &long, 10)["callback"]["state"],
        "delivered"
    );
    // A job without a callback shows none, and sends none.
    let plain = submit(&s, &scene, serde_json::json!({"width": 8, "height": 8}));
    let j = wait_job(&s, &plain, 60);
    assert!(j.get("callback").is_none(), "{j}");
    assert_eq!(rx.wait_for(2, 5).len(), 2);
}

#[test]
fn a_failing_receiver_is_retried_then_given_up_and_a_redirect_is_not_followed() {
    let dir = tempfile::tempdir().unwrap();
    let rx = Receiver::start();
    let s = start(&dir.path().join("data"), &secret_file(dir.path()), &rx, "3");
    let scene = upload(&s);

    let failing = submit(
        &s,
        &scene,
        serde_json::json!({"width": 8, "height": 8, "callback": rx.url("/fail")}),
    );
    // Three attempts, 0.5 s and 1 s apart, then no more.
    let view = wait_callback(&s, &failing, 30);
    assert_eq!(view["callback"]["state"], "failed", "{view}");
    assert_eq!(view["callback"]["attempts"], 3);
    let error = view["callback"]["error"].as_str().unwrap();
    assert!(error.contains("500"), "{error}");
    let got = rx.wait_for(3, 5);
    assert_eq!(
        got.iter().filter(|g| g.path == "/fail").count(),
        3,
        "{got:?}"
    );
    for g in &got {
        check_signature(g);
    }

    let redirected = submit(
        &s,
        &scene,
        serde_json::json!({"width": 8, "height": 8, "callback": rx.url("/redirect")}),
    );
    let view = wait_callback(&s, &redirected, 30);
    assert_eq!(view["callback"]["state"], "failed", "{view}");
    assert_eq!(view["callback"]["attempts"], 1, "a redirect is not retried");
    let error = view["callback"]["error"].as_str().unwrap();
    assert!(
        error.contains("302") && error.contains("not followed"),
        "{error}"
    );
    let got = rx.wait_for(4, 5);
    assert_eq!(got.iter().filter(|g| g.path == "/redirect").count(), 1);
    assert!(
        got.iter().all(|g| g.path != "/ok"),
        "the redirect was followed: {got:?}"
    );
}

#[test]
fn callbacks_to_hosts_not_allowed_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let rx = Receiver::start();
    let s = start(&dir.path().join("data"), &secret_file(dir.path()), &rx, "3");
    let scene = upload(&s);
    let other_port = format!("http://127.0.0.1:{}/ok", rx.port.wrapping_add(1).max(1));
    for url in [
        "http://127.0.0.2:9/ok".to_string(),
        "http://localhost/ok".to_string(),
        other_port,
        format!("https://127.0.0.1:{}/ok", rx.port),
        "not a url".to_string(),
    ] {
        let r = render(
            &s,
            &scene,
            serde_json::json!({"width": 8, "height": 8, "callback": url}),
        );
        assert_eq!(r.status, 422, "{url}: {}", String::from_utf8_lossy(&r.body));
        assert_eq!(r.json()["field"], "callback", "{url}");
    }
    // Nothing was contacted, and no job was made.
    std::thread::sleep(Duration::from_millis(300));
    assert!(rx.got().is_empty());
    let jobs = s.req("GET", "/v1/jobs", &[], &[]).json();
    assert_eq!(jobs["jobs"].as_array().map(Vec::len), Some(0), "{jobs}");
    drop(s);

    // Without --callback-allow every callback is refused.
    let plain = Server::start(&dir.path().join("plain"), &[]);
    let scene = upload(&plain);
    let r = render(
        &plain,
        &scene,
        serde_json::json!({"callback": rx.url("/ok")}),
    );
    assert_eq!(r.status, 422);
    assert_eq!(r.json()["field"], "callback");
    assert!(r.json()["detail"]
        .as_str()
        .unwrap()
        .contains("--callback-allow"));
}

#[test]
fn a_pending_callback_survives_a_kill_and_is_delivered_by_the_next_start() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let secret = secret_file(dir.path());
    let rx = Receiver::start();
    let s = start(&data, &secret, &rx, "8");
    let scene = upload(&s);
    let id = submit(
        &s,
        &scene,
        serde_json::json!({"width": 8, "height": 8, "callback": rx.url("/flaky")}),
    );
    // The receiver is down (503): wait for a failed attempt to be recorded, then kill.
    let t0 = Instant::now();
    loop {
        let j = s.req("GET", &format!("/v1/jobs/{id}"), &[], &[]).json();
        if j["callback"]["attempts"].as_u64().unwrap_or(0) >= 1 {
            assert_eq!(j["callback"]["state"], "pending", "{j}");
            break;
        }
        assert!(t0.elapsed() < Duration::from_secs(30), "no attempt: {j}");
        std::thread::sleep(Duration::from_millis(20));
    }
    s.kill9();
    let before = rx.got().len();
    assert!(before >= 1);
    rx.healthy.store(true, Ordering::SeqCst);
    let s = start(&data, &secret, &rx, "8");
    let view = wait_callback(&s, &id, 60);
    assert_eq!(view["callback"]["state"], "delivered", "{view}");
    let attempts = view["callback"]["attempts"].as_u64().unwrap();
    assert!(attempts as usize > before, "resumed from its count: {view}");
    let got = rx.got();
    let last = got.last().unwrap();
    check_signature(last);
    let posted: serde_json::Value = serde_json::from_slice(&last.body).unwrap();
    assert_eq!(posted["id"], id.as_str());
    assert_eq!(posted["state"], "succeeded");
}
