//! The API description: `proto/openapi.yaml`, compiled into the binary and served as JSON
//! at `GET /v1/openapi.json`, plus the check that keeps it and the router equal.
//!
//! The YAML is the one source; the JSON is converted from it once, on first use, so the two
//! can never drift. The router is built from [`Routes`](super::Routes), which records every
//! (method, path template) it registers; [`check_routes`] compares that table with the
//! document's operations, and a test runs it over the full router.

use std::collections::BTreeSet;
use std::sync::OnceLock;

use axum::http::{header, HeaderValue, Method};
use axum::response::{IntoResponse, Response};

use super::error::ApiError;

/// `proto/openapi.yaml`, as compiled in.
pub const OPENAPI_YAML: &str = include_str!("../../proto/openapi.yaml");

/// The HTTP methods an OpenAPI path item may hold operations for.
const OPERATION_KEYS: [&str; 8] = [
    "get", "put", "post", "delete", "options", "head", "patch", "trace",
];

/// The document as JSON (converted once), or why it does not parse.
pub fn openapi_json() -> Result<&'static serde_json::Value, ApiError> {
    static DOC: OnceLock<Result<serde_json::Value, String>> = OnceLock::new();
    DOC.get_or_init(|| {
        serde_yaml_ng::from_str::<serde_json::Value>(OPENAPI_YAML)
            .map_err(|e| format!("proto/openapi.yaml does not parse: {e}"))
    })
    .as_ref()
    .map_err(ApiError::internal)
}

/// Every operation of the document, as (method, path template).
pub fn operations() -> Result<BTreeSet<(Method, String)>, ApiError> {
    let doc = openapi_json()?;
    let paths = doc
        .get("paths")
        .and_then(|p| p.as_object())
        .ok_or_else(|| ApiError::internal("proto/openapi.yaml has no `paths` object"))?;
    let mut ops = BTreeSet::new();
    for (path, item) in paths {
        let Some(item) = item.as_object() else {
            continue;
        };
        for key in OPERATION_KEYS {
            if item.contains_key(key) {
                let m = Method::from_bytes(key.to_ascii_uppercase().as_bytes())
                    .map_err(ApiError::internal)?;
                ops.insert((m, path.clone()));
            }
        }
    }
    Ok(ops)
}

/// Compares a router's route table with the document: `Err` lists the operations only the
/// router has and those only the document has.
pub fn check_routes<'a>(
    routes: impl IntoIterator<Item = &'a (Method, String)>,
) -> Result<(), String> {
    let doc = operations().map_err(|e| e.detail().to_owned())?;
    let router: BTreeSet<(Method, String)> = routes.into_iter().cloned().collect();
    let only_router: Vec<_> = router.difference(&doc).collect();
    let only_doc: Vec<_> = doc.difference(&router).collect();
    if only_router.is_empty() && only_doc.is_empty() {
        Ok(())
    } else {
        Err(format!(
            "router and proto/openapi.yaml differ; only in the router: {only_router:?}; \
             only in the document: {only_doc:?}"
        ))
    }
}

/// `GET /v1/openapi.json`.
pub async fn openapi_handler() -> Response {
    match openapi_json() {
        Ok(doc) => {
            let mut res = axum::Json(doc).into_response();
            res.headers_mut().insert(
                header::CACHE_CONTROL,
                HeaderValue::from_static("public, max-age=300"),
            );
            res
        }
        Err(e) => e.into_response(),
    }
}
