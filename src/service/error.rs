//! `ApiError`: the service's one error type, answered as `application/problem+json`
//! (RFC 9457; the members and problem types are listed in `proto/service.md`).
//!
//! Every layer below converts its own error into an `ApiError` at this edge, so handlers
//! use `?`. A client mistake says what was wrong and where (`detail`, plus extension members
//! such as `field` or `byte_offset`); an internal failure answers a generic 500 and only the
//! log sees the cause. The request id (`instance`) is not known where an error is made, so
//! the response carries the [`Problem`] as an extension and the request-id middleware
//! writes the final body with `instance` filled in.

use std::borrow::Cow;

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use serde_json::{Map, Value};

/// The media type of every error body.
pub const PROBLEM_JSON: &str = "application/problem+json";

/// An RFC 9457 problem document, as sent on the wire.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Problem {
    /// A URI reference naming the kind of problem (`/problems/<slug>`).
    #[serde(rename = "type")]
    pub kind: String,
    /// A short summary of the kind, the same for every occurrence.
    pub title: String,
    /// The HTTP status code.
    pub status: u16,
    /// The request id of the request that failed (`X-Request-Id`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub instance: Option<String>,
    /// What was wrong with this request, and where.
    pub detail: String,
    /// Extension members that locate the problem (`field`, `ray_index`, `byte_offset`, …).
    #[serde(flatten)]
    pub extensions: Map<String, Value>,
}

impl Problem {
    /// The JSON body of this problem.
    pub fn to_body(&self) -> Vec<u8> {
        // A struct of strings, numbers and a JSON map always serialises.
        serde_json::to_vec(self).unwrap_or_else(|_| b"{}".to_vec())
    }
}

/// What the request-id middleware needs to finish a problem response: the document, and
/// for a 500 the cause that is logged but never sent.
#[derive(Debug, Clone)]
pub(crate) struct ProblemExt {
    pub(crate) problem: Problem,
    pub(crate) internal: Option<String>,
}

/// An error answered to the client as a problem document. Boxed, so that `Result<T,
/// ApiError>` stays one pointer wide on the error side.
#[derive(Debug, Clone, thiserror::Error)]
#[error("{} {}: {}", .0.status, .0.title, .0.detail)]
pub struct ApiError(Box<Inner>);

#[derive(Debug, Clone)]
struct Inner {
    status: StatusCode,
    slug: &'static str,
    title: &'static str,
    detail: Cow<'static, str>,
    extensions: Map<String, Value>,
    retry_after: Option<u64>,
    www_authenticate: Option<&'static str>,
    allow: Option<String>,
    internal: Option<String>,
    refused: Option<&'static str>,
}

/// Every reason [`ApiError::refused`] gives: `rayd_requests_refused_total` shows each at 0
/// from the start, so that a dashboard reads 0 rather than no data.
pub(crate) const REFUSAL_REASONS: [&str; 5] = [
    "body_budget",
    "client_limit",
    "queue_full",
    "shutting_down",
    "starting",
];

/// The reason a `503` refused a request before its work began, for
/// `rayd_requests_refused_total` (the metrics middleware reads it off the response).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Refused(pub &'static str);

impl ApiError {
    fn new(
        status: StatusCode,
        slug: &'static str,
        title: &'static str,
        detail: impl Into<Cow<'static, str>>,
    ) -> Self {
        ApiError(Box::new(Inner {
            status,
            slug,
            title,
            detail: detail.into(),
            extensions: Map::new(),
            retry_after: None,
            www_authenticate: None,
            allow: None,
            internal: None,
            refused: None,
        }))
    }

    /// Marks a `503` as a refusal for `reason` (one of [`REFUSAL_REASONS`]), which `rayd_requests_refused_total` counts: the
    /// metrics middleware reads the mark off the response, so every refusal is counted in
    /// one place, wherever it was made.
    pub fn refused(mut self, reason: &'static str) -> Self {
        debug_assert!(REFUSAL_REASONS.contains(&reason), "{reason}");
        self.0.refused = Some(reason);
        self
    }

    /// 400: a malformed body, parameter or header.
    pub fn bad_request(detail: impl Into<Cow<'static, str>>) -> Self {
        Self::new(
            StatusCode::BAD_REQUEST,
            "bad-request",
            "Bad request",
            detail,
        )
    }

    /// 401: no bearer token, or one the server does not know (`invalid` says which, for
    /// the `WWW-Authenticate` challenge of RFC 6750).
    pub fn unauthorized(detail: impl Into<Cow<'static, str>>, invalid: bool) -> Self {
        let mut e = Self::new(
            StatusCode::UNAUTHORIZED,
            "unauthorized",
            "Unauthorized",
            detail,
        );
        e.0.www_authenticate = Some(if invalid {
            "Bearer realm=\"rayd\", error=\"invalid_token\""
        } else {
            "Bearer realm=\"rayd\""
        });
        e
    }

    /// 404: no route, scene, version or job of that name.
    pub fn not_found(detail: impl Into<Cow<'static, str>>) -> Self {
        Self::new(StatusCode::NOT_FOUND, "not-found", "Not found", detail)
    }

    /// 405: the route exists but not with this method; `allow` lists the methods it has.
    pub fn method_not_allowed(detail: impl Into<Cow<'static, str>>, allow: Option<String>) -> Self {
        let mut e = Self::new(
            StatusCode::METHOD_NOT_ALLOWED,
            "method-not-allowed",
            "Method not allowed",
            detail,
        );
        e.0.allow = allow;
        e
    }

    /// 408: the client stopped sending its request body (no byte for `--body-timeout`).
    pub fn request_timeout(detail: impl Into<Cow<'static, str>>) -> Self {
        Self::new(
            StatusCode::REQUEST_TIMEOUT,
            "request-timeout",
            "Request timeout",
            detail,
        )
    }

    /// 409: the resource is not in a state that allows this (a result not ready yet).
    pub fn conflict(detail: impl Into<Cow<'static, str>>) -> Self {
        Self::new(StatusCode::CONFLICT, "conflict", "Conflict", detail)
    }

    /// 413: the body is larger than `limit` bytes.
    pub fn payload_too_large(detail: impl Into<Cow<'static, str>>, limit: u64) -> Self {
        Self::new(
            StatusCode::PAYLOAD_TOO_LARGE,
            "payload-too-large",
            "Request body too large",
            detail,
        )
        .with("limit", limit)
    }

    /// 415: the body's `Content-Type` is not one this route takes (`accepted` lists them).
    /// The place is always the `Content-Type` header, so every 415 names it.
    pub fn unsupported_media_type(detail: impl Into<Cow<'static, str>>, accepted: &[&str]) -> Self {
        Self::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported-media-type",
            "Unsupported media type",
            detail,
        )
        .with("accepted", accepted)
        .with_field("Content-Type")
    }

    /// 422: well-formed but invalid (NaN rays, a wrong triangle count, a limit exceeded).
    pub fn unprocessable(detail: impl Into<Cow<'static, str>>) -> Self {
        Self::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            "unprocessable",
            "Unprocessable request",
            detail,
        )
    }

    /// 503 with `Retry-After: retry_after_s`: the queue is full, a budget is spent, or the
    /// service is starting or shutting down.
    pub fn unavailable(detail: impl Into<Cow<'static, str>>, retry_after_s: u64) -> Self {
        let mut e = Self::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "unavailable",
            "Service unavailable",
            detail,
        );
        e.0.retry_after = Some(retry_after_s);
        e
    }

    /// 507: the data directory has no room for what was uploaded or produced.
    pub fn insufficient_storage(detail: impl Into<Cow<'static, str>>) -> Self {
        Self::new(
            StatusCode::INSUFFICIENT_STORAGE,
            "insufficient-storage",
            "Insufficient storage",
            detail,
        )
    }

    /// 500: an internal failure. The client gets a generic body; `cause` is only logged,
    /// with the request id.
    pub fn internal(cause: impl std::fmt::Display) -> Self {
        let mut e = Self::new(
            StatusCode::INTERNAL_SERVER_ERROR,
            "internal",
            "Internal server error",
            "the server failed to answer this request; the log has the cause under this request id",
        );
        e.0.internal = Some(cause.to_string());
        e
    }

    /// Adds an extension member that locates the problem (`field`, `ray_index`, `count`,
    /// `byte_offset`, …). Members of the base document (`type`, `title`, …) are refused
    /// silently, so an extension can never overwrite them.
    pub fn with(mut self, key: &str, value: impl Serialize) -> Self {
        if !matches!(key, "type" | "title" | "status" | "instance" | "detail") {
            let v = serde_json::to_value(value).unwrap_or(Value::Null);
            self.0.extensions.insert(key.to_owned(), v);
        }
        self
    }

    /// Names the request field (a JSON path, a query parameter or a header) that is wrong.
    pub fn with_field(self, field: impl Into<String>) -> Self {
        self.with("field", field.into())
    }

    /// Sets `Retry-After` on an error of any status.
    pub fn with_retry_after(mut self, seconds: u64) -> Self {
        self.0.retry_after = Some(seconds);
        self
    }

    /// The status code.
    pub fn status(&self) -> StatusCode {
        self.0.status
    }

    /// The detail message.
    pub fn detail(&self) -> &str {
        &self.0.detail
    }

    /// The extension members.
    pub fn extensions(&self) -> &Map<String, Value> {
        &self.0.extensions
    }

    /// The problem document (without `instance`, which the middleware adds).
    pub fn problem(&self) -> Problem {
        Problem {
            kind: format!("/problems/{}", self.0.slug),
            title: self.0.title.to_owned(),
            status: self.0.status.as_u16(),
            instance: None,
            detail: self.0.detail.to_string(),
            extensions: self.0.extensions.clone(),
        }
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let problem = self.problem();
        let inner = *self.0;
        let mut res = (inner.status, problem.to_body()).into_response();
        let h = res.headers_mut();
        h.insert(header::CONTENT_TYPE, HeaderValue::from_static(PROBLEM_JSON));
        if let Some(s) = inner.retry_after {
            h.insert(header::RETRY_AFTER, HeaderValue::from(s));
        }
        if let Some(w) = inner.www_authenticate {
            h.insert(header::WWW_AUTHENTICATE, HeaderValue::from_static(w));
        }
        if let Some(allow) = inner.allow.and_then(|a| HeaderValue::from_str(&a).ok()) {
            h.insert(header::ALLOW, allow);
        }
        if let Some(reason) = inner.refused {
            res.extensions_mut().insert(Refused(reason));
        }
        res.extensions_mut().insert(ProblemExt {
            problem,
            internal: inner.internal,
        });
        res
    }
}
