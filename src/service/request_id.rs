//! Request ids: every response carries `X-Request-Id`, every log line of a request carries
//! it in its span, and every problem document names it as `instance`.
//!
//! A client's id is kept when it is sane (1–128 characters of `A–Z a–z 0–9 - _ . : + / =`),
//! so ids can be followed through a proxy; anything else is replaced by a fresh UUID rather
//! than refused, because a bad id is no reason to fail a request. This middleware is also
//! the last word on error bodies: it fills in `instance`, logs the causes of 500s, and turns
//! any error response that is not a problem document (axum's or a layer's plain text) into
//! one, so no route can answer an error in another format.

use axum::body::Body;
use axum::extract::{MatchedPath, Request};
use axum::http::{header, HeaderName, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::Response;
use http_body_util::BodyExt;

use super::error::{ProblemExt, PROBLEM_JSON};

/// The header that carries the request id, both ways.
pub static X_REQUEST_ID: HeaderName = HeaderName::from_static("x-request-id");

/// Longest client id kept.
const MAX_ID_LEN: usize = 128;

/// Bytes of a non-problem error body read to quote it in the problem that replaces it.
const MAX_QUOTED_BODY: usize = 4096;

/// The request id of the request being answered (a request extension).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RequestId(pub String);

impl std::fmt::Display for RequestId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

/// Whether a client-sent id is kept.
pub fn is_sane_id(id: &[u8]) -> bool {
    !id.is_empty()
        && id.len() <= MAX_ID_LEN
        && id
            .iter()
            .all(|&b| b.is_ascii_alphanumeric() || b"-_.:+/=".contains(&b))
}

/// The id for a request: the client's when sane, else a new UUID.
fn choose_id(req: &Request) -> String {
    match req.headers().get(&X_REQUEST_ID) {
        Some(v) if is_sane_id(v.as_bytes()) => String::from_utf8_lossy(v.as_bytes()).into_owned(),
        _ => uuid::Uuid::new_v4().to_string(),
    }
}

/// Middleware: picks the id, stores it in the request (extension and header, so layers
/// inside see it), and finishes the response: `X-Request-Id`, and problem bodies with
/// `instance`.
pub async fn request_id_layer(mut req: Request, next: Next) -> Response {
    let id = choose_id(&req);
    if let Ok(v) = HeaderValue::from_str(&id) {
        req.headers_mut().insert(X_REQUEST_ID.clone(), v);
    }
    req.extensions_mut().insert(RequestId(id.clone()));
    let method = req.method().clone();
    let path = req.uri().path().to_owned();
    let res = next.run(req).await;
    let mut res = finish_problem(res, &id, &method, &path).await;
    if let Ok(v) = HeaderValue::from_str(&id) {
        res.headers_mut().insert(X_REQUEST_ID.clone(), v);
    }
    res
}

/// Fills in `instance` of a problem response, or turns a non-problem error response into
/// a problem.
async fn finish_problem(
    mut res: Response,
    id: &str,
    method: &axum::http::Method,
    path: &str,
) -> Response {
    if let Some(ext) = res.extensions_mut().remove::<ProblemExt>() {
        let mut problem = ext.problem;
        if let Some(cause) = ext.internal {
            tracing::error!(request_id = id, %method, path, cause, "internal error");
        }
        problem.instance = Some(id.to_owned());
        let (parts, _) = res.into_parts();
        return Response::from_parts(parts, Body::from(problem.to_body()));
    }
    let status = res.status();
    let is_problem = res
        .headers()
        .get(header::CONTENT_TYPE)
        .is_some_and(|ct| ct.as_bytes().starts_with(PROBLEM_JSON.as_bytes()));
    if !(status.is_client_error() || status.is_server_error()) || is_problem {
        return res;
    }
    // An error answered by axum or a layer in its own format: quote its text as the detail.
    let (parts, body) = res.into_parts();
    let text = match http_body_util::Limited::new(body, MAX_QUOTED_BODY)
        .collect()
        .await
    {
        Ok(b) => String::from_utf8_lossy(&b.to_bytes()).trim().to_owned(),
        Err(_) => String::new(),
    };
    let detail = if text.is_empty() || status == StatusCode::INTERNAL_SERVER_ERROR {
        format!(
            "{method} {path}: {}",
            status.canonical_reason().unwrap_or("error")
        )
    } else {
        format!("{method} {path}: {text}")
    };
    if status.is_server_error() {
        tracing::error!(request_id = id, %method, path, status = status.as_u16(), body = text, "error response");
    }
    let problem = super::error::Problem {
        kind: "about:blank".to_owned(),
        title: status.canonical_reason().unwrap_or("Error").to_owned(),
        status: status.as_u16(),
        instance: Some(id.to_owned()),
        detail,
        extensions: Default::default(),
    };
    let mut res = Response::from_parts(parts, Body::from(problem.to_body()));
    res.headers_mut()
        .insert(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON));
    res.headers_mut().remove(header::CONTENT_LENGTH);
    res
}

/// The span of one request: its id, method and route template (never the raw path, which
/// may carry ids; `unmatched` when no route matched). For tower-http's `TraceLayer`.
pub fn make_span(req: &Request) -> tracing::Span {
    let id = req
        .extensions()
        .get::<RequestId>()
        .map(|r| r.0.as_str())
        .unwrap_or("");
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map(|m| m.as_str())
        .unwrap_or("unmatched");
    // At ERROR level so that it is enabled whatever `RAYD_LOG` lets through: a warning or
    // error of the request carries its id even where info lines are filtered out.
    tracing::error_span!("request", request_id = id, method = %req.method(), route)
}

#[cfg(test)]
mod tests {
    use super::is_sane_id;

    #[test]
    fn sane_ids() {
        assert!(is_sane_id(b"abc-123_x.y:z"));
        assert!(is_sane_id(b"3f2a6e1c-8f0b-4c1e-9b8f-1f0d3c5a9e77"));
        assert!(!is_sane_id(b""));
        assert!(!is_sane_id(b"has space"));
        assert!(!is_sane_id(b"new\nline"));
        assert!(!is_sane_id("é".as_bytes()));
        assert!(!is_sane_id(&[b'a'; 129]));
        assert!(is_sane_id(&[b'a'; 128]));
    }
}
