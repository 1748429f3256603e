//! The HTTP service's infrastructure (`proto/service.md`), driven through the router with
//! `oneshot` (no socket), plus one run of the real `rayd serve` on loopback.
//!
//! The domain routes are not here; a few test routes stand in for them to exercise the
//! layers that wrap every `/v1` route (auth, limits, metrics, extractors).

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::process::{Command, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::Body;
use axum::extract::{ConnectInfo, State};
use axum::http::{header, Method, Request};
use axum::response::Response;
use http_body_util::BodyExt;
use rayd::jobs::cache::CacheStats;
use rayd::service::{
    self, openapi, read_body_limited, ApiError, ApiJson, ApiQuery, AppState, Problem, Routes,
    ServeArgs,
};
use tower::ServiceExt;

fn state(args: &[&str]) -> AppState {
    AppState::new(ServeArgs::try_parse_from(args).expect("test arguments parse")).unwrap()
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(dead_code)]
struct RenderLike {
    width: u32,
    height: u32,
}

#[derive(serde::Deserialize)]
#[allow(dead_code)]
struct ListQuery {
    limit: Option<u32>,
}

/// Stand-ins for domain routes: a templated GET, a JSON POST, a bulk body, a query.
fn test_routes() -> Routes {
    Routes::new()
        .get(
            "/v1/things/{id}",
            |axum::extract::Path(id): axum::extract::Path<String>| async move { id },
        )
        .post("/v1/render", |ApiJson(r): ApiJson<RenderLike>| async move {
            format!("{}x{}", r.width, r.height)
        })
        .post(
            "/v1/upload",
            |State(s): State<AppState>, body: Body| async move {
                let b = read_body_limited(body, s.config.max_body, &s.bodies).await?;
                Ok::<_, ApiError>(b.len().to_string())
            },
        )
        .get("/v1/list", |ApiQuery(q): ApiQuery<ListQuery>| async move {
            format!("{:?}", q.limit)
        })
}

fn app(s: &AppState) -> axum::Router {
    s.ready.set_ready();
    service::router(s.clone(), test_routes())
}

async fn send(app: &axum::Router, req: Request<Body>) -> Response {
    app.clone().oneshot(req).await.unwrap()
}

fn get(uri: &str) -> Request<Body> {
    Request::get(uri).body(Body::empty()).unwrap()
}

async fn body_text(res: Response) -> String {
    String::from_utf8(res.into_body().collect().await.unwrap().to_bytes().to_vec()).unwrap()
}

/// Checks the problem+json shape and returns the document.
async fn problem(res: Response, status: u16) -> Problem {
    assert_eq!(res.status().as_u16(), status);
    assert_eq!(
        res.headers()[header::CONTENT_TYPE],
        service::PROBLEM_JSON,
        "errors are problem+json"
    );
    let id = res.headers()[&service::X_REQUEST_ID]
        .to_str()
        .unwrap()
        .to_owned();
    let text = body_text(res).await;
    let p: Problem = serde_json::from_str(&text).unwrap_or_else(|e| panic!("{e}: {text}"));
    assert_eq!(p.status, status);
    assert_eq!(
        p.instance.as_deref(),
        Some(id.as_str()),
        "instance is the request id"
    );
    assert!(
        p.kind.starts_with("/problems/") || p.kind == "about:blank",
        "{}",
        p.kind
    );
    assert!(!p.title.is_empty() && !p.detail.is_empty(), "{text}");
    p
}

#[tokio::test]
async fn request_ids_are_echoed_or_made() {
    let s = state(&[]);
    let app = app(&s);
    let res = send(
        &app,
        Request::get("/healthz")
            .header("x-request-id", "client-42.a")
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    assert_eq!(res.status(), 200);
    assert_eq!(res.headers()["x-request-id"], "client-42.a");

    let res = send(&app, get("/healthz")).await;
    let made = res.headers()["x-request-id"].to_str().unwrap().to_owned();
    assert!(
        uuid::Uuid::parse_str(&made).is_ok(),
        "a fresh id is a UUID: {made}"
    );
    let again = send(&app, get("/healthz")).await;
    assert_ne!(
        again.headers()["x-request-id"],
        made.as_str(),
        "ids are unique"
    );

    // An insane id is replaced, not refused.
    let res = send(
        &app,
        Request::get("/healthz")
            .header("x-request-id", "a b<script>")
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    assert_eq!(res.status(), 200);
    assert_ne!(res.headers()["x-request-id"], "a b<script>");

    // An error's instance is the client's id.
    let res = send(
        &app,
        Request::get("/nowhere")
            .header("x-request-id", "trace-me")
            .body(Body::empty())
            .unwrap(),
    )
    .await;
    assert_eq!(
        problem(res, 404).await.instance.as_deref(),
        Some("trace-me")
    );
}

#[tokio::test]
async fn errors_are_problem_documents() {
    let s = state(&["--max-body", "100", "--max-inflight-bytes", "65536"]);
    let app = app(&s);

    let p = problem(send(&app, get("/no/such/route")).await, 404).await;
    assert!(p.detail.contains("/no/such/route"), "{}", p.detail);

    let res = send(
        &app,
        Request::delete("/healthz").body(Body::empty()).unwrap(),
    )
    .await;
    assert!(
        res.headers().get(header::ALLOW).is_some(),
        "405 lists the allowed methods"
    );
    let p = problem(res, 405).await;
    assert!(p.detail.contains("DELETE"), "{}", p.detail);

    // 413 from the declared length, before reading.
    let res = send(
        &app,
        Request::post("/v1/upload")
            .body(Body::from(vec![0u8; 101]))
            .unwrap(),
    )
    .await;
    let p = problem(res, 413).await;
    assert_eq!(p.extensions["limit"], 100);
    assert!(p.detail.contains("100 bytes"), "{}", p.detail);
    let res = send(
        &app,
        Request::post("/v1/upload")
            .body(Body::from(vec![0u8; 100]))
            .unwrap(),
    )
    .await;
    assert_eq!(body_text(res).await, "100");

    // 413 while streaming a body of no declared length.
    let chunks = futures_stream(vec![vec![1u8; 80], vec![2u8; 80]]);
    let res = send(&app, Request::post("/v1/upload").body(chunks).unwrap()).await;
    assert_eq!(problem(res, 413).await.extensions["byte_offset"], 100);

    // 415: a JSON route without a JSON body.
    let res = send(
        &app,
        Request::post("/v1/render")
            .header("content-type", "text/plain")
            .body(Body::from("{}"))
            .unwrap(),
    )
    .await;
    let p = problem(res, 415).await;
    assert_eq!(p.extensions["field"], "Content-Type");
    let res = send(
        &app,
        Request::post("/v1/render").body(Body::from("{}")).unwrap(),
    )
    .await;
    problem(res, 415).await;

    // 400: bad JSON, a wrong field, an unknown field, a bad query parameter.
    let json = |body: &'static str| {
        Request::post("/v1/render")
            .header("content-type", "application/json")
            .body(Body::from(body))
            .unwrap()
    };
    let p = problem(send(&app, json("{\"width\": 3,")).await, 400).await;
    assert!(p.detail.contains("not valid JSON"), "{}", p.detail);
    let p = problem(send(&app, json(r#"{"width": -3, "height": 2}"#)).await, 400).await;
    assert_eq!(p.extensions["field"], "width");
    let p = problem(
        send(&app, json(r#"{"width": 3, "height": 2, "hieght": 2}"#)).await,
        400,
    )
    .await;
    assert_eq!(p.extensions["field"], "hieght");
    let p = problem(send(&app, json(r#"{"width": 3}"#)).await, 400).await;
    assert_eq!(p.extensions["field"], "height");
    let res = send(&app, json(r#"{"width": 3, "height": 2}"#)).await;
    assert_eq!(body_text(res).await, "3x2");
    let p = problem(send(&app, get("/v1/list?limit=many")).await, 400).await;
    assert_eq!(p.extensions["field"], "limit");
    assert_eq!(
        body_text(send(&app, get("/v1/list?limit=5")).await).await,
        "Some(5)"
    );
}

/// A streaming body without a declared length.
fn futures_stream(chunks: Vec<Vec<u8>>) -> Body {
    Body::new(Chunked(chunks))
}

struct Chunked(Vec<Vec<u8>>);

impl http_body::Body for Chunked {
    type Data = bytes::Bytes;
    type Error = std::convert::Infallible;
    fn poll_frame(
        mut self: std::pin::Pin<&mut Self>,
        _: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Result<http_body::Frame<bytes::Bytes>, Self::Error>>> {
        std::task::Poll::Ready(if self.0.is_empty() {
            None
        } else {
            Some(Ok(http_body::Frame::data(self.0.remove(0).into())))
        })
    }
}

#[tokio::test]
async fn tokens_guard_v1_and_reload() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("tokens");
    std::fs::write(&file, "# the team\nfirst-token\n\nsecond-token\n").unwrap();
    let s = state(&["--token-file", file.to_str().unwrap()]);
    let app = app(&s);
    let with = |tok: &str| {
        Request::get("/v1/things/x")
            .header("authorization", format!("Bearer {tok}"))
            .body(Body::empty())
            .unwrap()
    };

    let res = send(&app, get("/v1/things/x")).await;
    assert_eq!(
        res.headers()[header::WWW_AUTHENTICATE],
        "Bearer realm=\"rayd\""
    );
    problem(res, 401).await;
    let res = send(&app, with("wrong-token")).await;
    assert!(res.headers()[header::WWW_AUTHENTICATE]
        .to_str()
        .unwrap()
        .contains("invalid_token"));
    problem(res, 401).await;
    problem(send(&app, with("first-toke")).await, 401).await;
    problem(send(&app, get("/v1/openapi.json")).await, 401).await;
    assert_eq!(send(&app, with("first-token")).await.status(), 200);
    assert_eq!(send(&app, with("second-token")).await.status(), 200);
    for open in ["/", "/healthz", "/readyz", "/metrics"] {
        assert_eq!(
            send(&app, get(open)).await.status(),
            200,
            "{open} needs no token"
        );
    }

    // Rotation: what SIGHUP does.
    std::fs::write(&file, "third-token\n").unwrap();
    assert_eq!(s.auth.reload().unwrap(), 1);
    problem(send(&app, with("first-token")).await, 401).await;
    assert_eq!(send(&app, with("third-token")).await.status(), 200);
    // A file that no longer reads keeps the tokens in force.
    std::fs::remove_file(&file).unwrap();
    assert!(s.auth.reload().is_err());
    assert_eq!(send(&app, with("third-token")).await.status(), 200);
}

#[tokio::test]
async fn metrics_use_route_templates() {
    let s = state(&[]);
    let app = app(&s);
    // Before anything happened, every documented labelled series reads 0 (a dashboard
    // would see no data otherwise).
    let fresh = body_text(send(&app, get("/metrics")).await).await;
    for line in [
        r#"rayd_job_duration_seconds_count{kind="trace"} 0"#,
        r#"rayd_job_duration_seconds_count{kind="render"} 0"#,
        r#"rayd_requests_refused_total{reason="body_budget"} 0"#,
        r#"rayd_requests_refused_total{reason="client_limit"} 0"#,
        r#"rayd_requests_refused_total{reason="queue_full"} 0"#,
        r#"rayd_requests_refused_total{reason="shutting_down"} 0"#,
        r#"rayd_requests_refused_total{reason="starting"} 0"#,
    ] {
        assert!(fresh.contains(line), "{line}: {fresh}");
    }
    send(&app, get("/v1/things/3f2a9c0d1e")).await;
    send(&app, get("/v1/things/77aa")).await;
    send(&app, get("/no/such/route/123")).await;
    s.metrics.observe_trace(2_000_000, 0.5);
    s.metrics.observe_job("render", 1.5);
    s.metrics.set_structure_cache(&CacheStats {
        hits: 1,
        misses: 2,
        bytes: 3,
        ..CacheStats::default()
    });
    s.metrics.set_texture_cache(&CacheStats {
        hits: 4,
        misses: 5,
        bytes: 6,
        ..CacheStats::default()
    });
    s.metrics.set_light_cache(&CacheStats {
        hits: 7,
        misses: 8,
        bytes: 9,
        ..CacheStats::default()
    });
    s.metrics.set_upload_rate(2.5e8);
    let text = body_text(send(&app, get("/metrics")).await).await;
    assert!(
        text.contains("rayd_trace_upload_bytes_per_second 250000000"),
        "{text}"
    );
    assert!(
        text.contains(
            r#"rayd_http_requests_total{method="GET",route="/v1/things/{id}",status="200"} 2"#
        ),
        "{text}"
    );
    assert!(text.contains(r#"route="unmatched",status="404""#), "{text}");
    assert!(
        !text.contains("3f2a9c0d1e") && !text.contains("/no/such"),
        "raw paths leak: {text}"
    );
    assert!(text.contains("rayd_rays_traced_total 2000000"), "{text}");
    assert!(
        text.contains("rayd_trace_mrays_per_second_bucket{le=\"5\"} 1"),
        "{text}"
    );
    assert!(
        text.contains(r#"rayd_job_duration_seconds_count{kind="render"} 1"#),
        "{text}"
    );
    for line in [
        "rayd_cache_hits_total 1",
        "rayd_cache_misses_total 2",
        "rayd_cache_bytes 3",
        "rayd_texture_cache_hits_total 4",
        "rayd_texture_cache_misses_total 5",
        "rayd_texture_cache_bytes 6",
        "rayd_light_cache_hits_total 7",
        "rayd_light_cache_misses_total 8",
        "rayd_light_cache_bytes 9",
    ] {
        assert!(text.contains(line), "{line}: {text}");
    }
    // Counters only go up: a smaller count from the source leaves them where they are.
    s.metrics.set_structure_cache(&CacheStats::default());
    let text = body_text(send(&app, get("/metrics")).await).await;
    assert!(text.contains("rayd_cache_hits_total 1"), "{text}");
    assert!(text.contains("rayd_cache_bytes 0"), "{text}");
}

#[tokio::test]
async fn metrics_pass_promtool() {
    let s = state(&[]);
    let app = app(&s);
    send(&app, get("/v1/things/a")).await;
    send(&app, get("/missing")).await;
    s.metrics.observe_trace(1000, 0.001);
    s.metrics.observe_job("trace", 0.2);
    s.metrics.refused("client_limit");
    let text = body_text(send(&app, get("/metrics")).await).await;
    let child = Command::new("promtool")
        .args(["check", "metrics"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn();
    let Ok(mut child) = child else {
        eprintln!(
            "SKIP metrics_pass_promtool: promtool is not installed (apt-get install prometheus)"
        );
        return;
    };
    child
        .stdin
        .take()
        .unwrap()
        .write_all(text.as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "promtool check metrics: {}{}\n{text}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

#[tokio::test]
async fn readiness_follows_the_phase() {
    let s = state(&[]);
    let app = service::router(s.clone(), test_routes());
    let res = send(&app, get("/readyz")).await;
    assert!(res.headers().contains_key(header::RETRY_AFTER));
    assert!(problem(res, 503).await.detail.contains("starting"));
    assert_eq!(
        send(&app, get("/healthz")).await.status(),
        200,
        "alive while starting"
    );
    // The API takes no work until the start is over (the last run's jobs re-queued).
    let res = send(&app, get("/v1/things/1")).await;
    assert!(res.headers().contains_key(header::RETRY_AFTER));
    assert!(problem(res, 503).await.detail.contains("starting"));
    s.ready.set_ready();
    assert_eq!(send(&app, get("/readyz")).await.status(), 200);
    assert_eq!(send(&app, get("/v1/things/1")).await.status(), 200);
    s.ready.set_draining();
    s.ready.set_ready();
    let res = send(&app, get("/readyz")).await;
    assert!(problem(res, 503).await.detail.contains("shutting down"));
}

#[tokio::test]
async fn openapi_is_served_and_matches_the_router() {
    let s = state(&[]);
    let app = app(&s);
    let res = send(&app, get("/v1/openapi.json")).await;
    assert_eq!(res.status(), 200);
    let served: serde_json::Value = serde_json::from_str(&body_text(res).await).unwrap();
    let yaml: serde_json::Value = serde_yaml_ng::from_str(openapi::OPENAPI_YAML).unwrap();
    assert_eq!(served, yaml);
    assert!(served["paths"]["/v1/jobs/{job}/result"]["get"].is_object());

    // Every route this module serves is in the document.
    let ops = openapi::operations().unwrap();
    let ours = service::route_table(&Routes::new());
    for op in &ours {
        assert!(ops.contains(op), "{op:?} is served but not documented");
    }
    // The check names what differs, both ways.
    let err = openapi::check_routes(&ours).unwrap_err();
    assert!(err.contains("/v1/scenes"), "{err}");
    let mut extra = ops.iter().cloned().collect::<Vec<_>>();
    assert_eq!(openapi::check_routes(&extra), Ok(()));
    extra.push((Method::PATCH, "/v1/nope".to_owned()));
    assert!(openapi::check_routes(&extra)
        .unwrap_err()
        .contains("/v1/nope"));
}

#[tokio::test]
async fn one_client_cannot_take_every_slot() {
    let s = state(&["--max-client-requests", "1"]);
    s.ready.set_ready();
    let gate = Arc::new(tokio::sync::Notify::new());
    let g = gate.clone();
    let routes = Routes::new().get("/v1/slow", move || {
        let g = g.clone();
        async move {
            g.notified().await;
            "done"
        }
    });
    let app = service::router(s.clone(), routes);
    let from = |ip: [u8; 4]| {
        let mut r = get("/v1/slow");
        r.extensions_mut()
            .insert(ConnectInfo(SocketAddr::from((ip, 5000))));
        r
    };
    let first = tokio::spawn(app.clone().oneshot(from([10, 0, 0, 1])));
    tokio::time::sleep(Duration::from_millis(50)).await;
    let res = send(&app, from([10, 0, 0, 1])).await;
    assert_eq!(res.headers()[header::RETRY_AFTER], "1");
    let p = problem(res, 503).await;
    assert!(p.detail.contains("--max-client-requests"), "{}", p.detail);
    // Another client is not affected; public routes are never bounded.
    let other = tokio::spawn(app.clone().oneshot(from([10, 0, 0, 2])));
    tokio::time::sleep(Duration::from_millis(50)).await;
    assert!(!other.is_finished(), "the other client's request runs");
    let mut h = get("/healthz");
    h.extensions_mut()
        .insert(ConnectInfo(SocketAddr::from(([10, 0, 0, 1], 5001))));
    assert_eq!(send(&app, h).await.status(), 200);
    gate.notify_waiters();
    assert_eq!(first.await.unwrap().unwrap().status(), 200);
    assert_eq!(other.await.unwrap().unwrap().status(), 200);
    // The slot is free again.
    let again = tokio::spawn(app.clone().oneshot(from([10, 0, 0, 1])));
    tokio::time::sleep(Duration::from_millis(50)).await;
    gate.notify_waiters();
    assert_eq!(again.await.unwrap().unwrap().status(), 200);
    // The refusal was counted once, by its reason (the metrics middleware reads the mark
    // the limiter's 503 carries).
    let text = body_text(send(&app, get("/metrics")).await).await;
    assert!(
        text.contains(r#"rayd_requests_refused_total{reason="client_limit"} 1"#),
        "{text}"
    );
}

#[test]
fn serve_help_documents_every_default_and_variable() {
    let out = Command::new(env!("CARGO_BIN_EXE_rayd"))
        .args(["serve", "--help"])
        .output()
        .unwrap();
    assert!(out.status.success());
    let help = String::from_utf8_lossy(&out.stdout);
    for (flag, var, default) in [
        ("--addr", "RAYD_ADDR", "127.0.0.1:8080"),
        ("--data-dir", "RAYD_DATA_DIR", "rayd-data"),
        ("--max-queued", "RAYD_MAX_QUEUED", "64"),
        ("--max-rays", "RAYD_MAX_RAYS", "16777216"),
        ("--grace", "RAYD_GRACE", "5"),
        (
            "--max-inflight-bytes",
            "RAYD_MAX_INFLIGHT_BYTES",
            "2147483648",
        ),
        ("--max-client-requests", "RAYD_MAX_CLIENT_REQUESTS", "8"),
        ("--log-format", "RAYD_LOG_FORMAT", "text"),
    ] {
        assert!(help.contains(flag), "{flag} missing");
        assert!(help.contains(&format!("[env: {var}=")), "{var} missing");
        assert!(
            help.contains(&format!("[default: {default}]")),
            "{flag}: default {default} missing"
        );
    }
    assert!(help.contains("RAYD_TOKEN_FILE") && help.contains("RAYD_DEMO"));
}

/// `proto/service.md`'s table of `rayd serve`'s options and `rayd serve --help` name the
/// same flags, each with the same variable and default: the page cannot fall behind a new
/// flag.
#[test]
fn the_option_table_is_the_help() {
    let out = Command::new(env!("CARGO_BIN_EXE_rayd"))
        .args(["serve", "--help"])
        .output()
        .unwrap();
    let help = String::from_utf8_lossy(&out.stdout);
    let page = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("proto/service.md"),
    )
    .unwrap();
    let cell = |c: &str| c.trim().trim_matches('`').to_string();
    let rows: Vec<[String; 3]> = page
        .lines()
        .filter(|l| l.starts_with("| `--"))
        .map(|l| {
            let c: Vec<&str> = l.split('|').collect();
            // The default's first word: `1073741824` (1 GiB), `0` (all cores), none.
            let default = cell(c[3].split(" (").next().unwrap());
            [cell(c[1]), cell(c[2]), default]
        })
        .collect();
    for [flag, var, default] in &rows {
        let listed = help.lines().any(|l| {
            let l = l.trim_start();
            l == flag || l.starts_with(&format!("{flag} "))
        });
        assert!(listed, "{flag}: not in --help");
        assert!(
            help.contains(&format!("[env: {var}=")),
            "{flag}: {var} not in --help"
        );
        if default.chars().all(|c| c.is_ascii_digit() || c == '.') || default.contains(':') {
            assert!(
                help.contains(&format!("[default: {default}]")),
                "{flag}: default {default} not in --help"
            );
        }
    }
    let documented: Vec<&str> = rows.iter().map(|r| r[0].as_str()).collect();
    for word in help.split_whitespace() {
        let flag = word.trim_end_matches([',', '.']);
        if flag.starts_with("--") && flag.len() > 2 && !["--help", "--version"].contains(&flag) {
            let flag = flag.split(['=', '[', '<']).next().unwrap();
            assert!(
                documented.contains(&flag),
                "{flag} is in --help but not in proto/service.md"
            );
        }
    }
}

/// `RAYD_DEMO=1` (as containers set switches) parses; the server then stops at the next
/// check, a zero `--max-body`, which shows that parsing got past it.
#[test]
fn switches_take_1_and_0_from_the_environment() {
    for v in ["1", "0", "true", "off"] {
        let out = Command::new(env!("CARGO_BIN_EXE_rayd"))
            .args(["serve", "--max-body", "0"])
            .env("RAYD_DEMO", v)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(
            err.contains("--max-body must be at least 1"),
            "RAYD_DEMO={v}: {err}"
        );
    }
}

#[test]
fn flags_win_over_the_environment() {
    let out = Command::new(env!("CARGO_BIN_EXE_rayd"))
        .args(["serve", "--max-body", "10"])
        .env("RAYD_MAX_BODY", "1000")
        .env("RAYD_MAX_INFLIGHT_BYTES", "5")
        .output()
        .unwrap();
    // The environment's budget (5) and the flag's body limit (10) meet in the check.
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("--max-inflight-bytes 5 is smaller than --max-body 10"),
        "{err}"
    );
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// One blocking GET; the status code.
fn http_get(port: u16, path: &str) -> Option<u16> {
    http_get_with(port, path, "")
}

/// One blocking GET with extra header lines (each ending in CRLF); the status code.
fn http_get_with(port: u16, path: &str, headers: &str) -> Option<u16> {
    let mut s = TcpStream::connect(("127.0.0.1", port)).ok()?;
    s.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: x\r\n{headers}Connection: close\r\n\r\n"
    )
    .ok()?;
    let mut out = String::new();
    s.read_to_string(&mut out).ok()?;
    out.get(9..12)?.parse().ok()
}

#[test]
fn real_server_starts_probes_and_stops_within_grace() {
    let dir = tempfile::tempdir().unwrap();
    let port = free_port();
    let addr = format!("127.0.0.1:{port}");
    let tokens = dir.path().join("tokens");
    std::fs::write(&tokens, "old-token\n").unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_rayd"))
        .args([
            "serve",
            "--addr",
            &addr,
            "--grace",
            "2",
            "--header-timeout",
            "1",
        ])
        .arg("--token-file")
        .arg(&tokens)
        .arg("--data-dir")
        .arg(dir.path().join("data"))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let start = Instant::now();
    while http_get(port, "/healthz") != Some(200) {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "no /healthz within 20 s"
        );
        if let Some(st) = child.try_wait().unwrap() {
            let mut err = String::new();
            child
                .stderr
                .take()
                .unwrap()
                .read_to_string(&mut err)
                .unwrap();
            panic!("rayd serve exited {st}: {err}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(http_get(port, "/readyz"), Some(200));

    // Token rotation by SIGHUP.
    let bearer = |t: &str| format!("Authorization: Bearer {t}\r\n");
    assert_eq!(
        http_get_with(port, "/v1/openapi.json", &bearer("old-token")),
        Some(200)
    );
    assert_eq!(http_get(port, "/v1/openapi.json"), Some(401));
    std::fs::write(&tokens, "new-token\n").unwrap();
    let hup = Command::new("kill")
        .args(["-HUP", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(hup.success());
    let t = Instant::now();
    while http_get_with(port, "/v1/openapi.json", &bearer("new-token")) != Some(200) {
        assert!(
            t.elapsed() < Duration::from_secs(5),
            "SIGHUP did not load the new token"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert_eq!(
        http_get_with(port, "/v1/openapi.json", &bearer("old-token")),
        Some(401)
    );

    // The probe the Docker image uses.
    let probe = Command::new(env!("CARGO_BIN_EXE_rayd"))
        .args(["healthcheck", "--url", &format!("http://{addr}/healthz")])
        .output()
        .unwrap();
    assert!(
        probe.status.success(),
        "{}",
        String::from_utf8_lossy(&probe.stderr)
    );
    let probe = Command::new(env!("CARGO_BIN_EXE_rayd"))
        .args(["healthcheck", "--url", &format!("http://{addr}/nothing")])
        .output()
        .unwrap();
    assert!(!probe.status.success(), "a 404 is not healthy");

    // A client that sends half a request head is cut off after --header-timeout.
    let mut slow = TcpStream::connect(("127.0.0.1", port)).unwrap();
    slow.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
        .unwrap();
    slow.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let t = Instant::now();
    let mut buf = Vec::new();
    let _ = slow.read_to_end(&mut buf);
    assert!(
        t.elapsed() < Duration::from_secs(4),
        "slow client kept {:?}",
        t.elapsed()
    );

    // SIGTERM: exits within the grace period, having drained.
    let t = Instant::now();
    let killed = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st;
        }
        assert!(
            t.elapsed() < Duration::from_secs(4),
            "still running 4 s after SIGTERM"
        );
        std::thread::sleep(Duration::from_millis(20));
    };
    assert!(status.success(), "exit status {status}");
    let mut out = String::new();
    child
        .stdout
        .take()
        .unwrap()
        .read_to_string(&mut out)
        .unwrap();
    let v: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
    assert_eq!(v["drained"], true, "{out}");

    // Address reuse: a new server binds the same port at once (logging JSON this time).
    let mut again = Command::new(env!("CARGO_BIN_EXE_rayd"))
        .args(["serve", "--addr", &addr, "--log-format", "json"])
        .arg("--data-dir")
        .arg(dir.path().join("data"))
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let start = Instant::now();
    while http_get(port, "/healthz") != Some(200) {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "restart did not bind"
        );
        assert!(again.try_wait().unwrap().is_none(), "restart exited");
        std::thread::sleep(Duration::from_millis(50));
    }
    let _ = again.kill();
    let _ = again.wait();
    let mut log = String::new();
    again
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut log)
        .unwrap();
    let lines: Vec<serde_json::Value> = log
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("{e}: not JSON: {l}")))
        .collect();
    assert!(lines.iter().any(|l| l["message"] == "listening"), "{log}");
    // The access log line carries the request's span: id, method, route template.
    assert!(
        lines.iter().any(|l| l["span"]["route"] == "/healthz"
            && l["span"]["method"] == "GET"
            && l["span"]["request_id"]
                .as_str()
                .is_some_and(|id| !id.is_empty())),
        "{log}"
    );
}

#[test]
fn the_whole_router_equals_the_document() {
    // The domain routes and the service's own, exactly the operations of proto/openapi.yaml.
    let table = service::route_table(&rayd::service::routes::routes());
    assert_eq!(openapi::check_routes(&table), Ok(()));
}
