//! The status page: `GET /` for a browser, a plain HTML page with its script and style
//! sheet compiled into the binary (`proto/service.md`, "Status page").
//!
//! The page holds no data: it is the same bytes for everyone, and everything it shows comes
//! from the `/v1` routes, called by its script with the bearer token the user types in
//! (kept in `sessionStorage`, sent as `Authorization`, never in a URL). That is why `/` and
//! the assets need no token. `/` answers the page to clients that ask for HTML
//! (`Accept: text/html`, what browsers send) and the JSON index to everyone else, so API
//! clients keep their link document.
//!
//! Every page response carries a strict Content-Security-Policy (scripts, styles and
//! connections only from this origin, images also from `blob:` and `data:`, no inline
//! script, no framing) and `X-Content-Type-Options: nosniff`; no response grants
//! cross-origin access (no `Access-Control-Allow-Origin`).

use axum::extract::State;
use axum::http::{header, HeaderMap, HeaderName, HeaderValue};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde_json::json;

use super::Auth;

/// The page.
const INDEX_HTML: &str = include_str!("index.html");
/// Its script (an ES module).
const APP_JS: &str = include_str!("app.js");
/// Its style sheet.
const STYLE_CSS: &str = include_str!("style.css");

/// The path of the script.
pub const APP_JS_PATH: &str = "/page/app.js";
/// The path of the style sheet.
pub const STYLE_CSS_PATH: &str = "/page/style.css";

/// The policy of every page response. `img-src` adds `blob:` (results and thumbnails are
/// fetched with the token and shown through object URLs) and `data:` (the empty icon).
pub const CONTENT_SECURITY_POLICY: &str = "default-src 'self'; script-src 'self'; \
     style-src 'self'; img-src 'self' blob: data:; connect-src 'self'; object-src 'none'; \
     base-uri 'none'; form-action 'self'; frame-ancestors 'none'";

/// Whether the request asks for HTML before JSON: `text/html` is listed with a quality
/// above that of `application/json` (absent types count as quality 0, `*/*` as neither).
pub fn wants_html(headers: &HeaderMap) -> bool {
    let mut html = 0.0f32;
    let mut json = 0.0f32;
    for value in headers.get_all(header::ACCEPT) {
        let Ok(value) = value.to_str() else { continue };
        for item in value.split(',') {
            let mut parts = item.split(';');
            let media = parts.next().unwrap_or("").trim().to_ascii_lowercase();
            let q = parts
                .filter_map(|p| p.trim().strip_prefix("q="))
                .find_map(|q| q.trim().parse::<f32>().ok())
                .unwrap_or(1.0);
            match media.as_str() {
                "text/html" => html = html.max(q),
                "application/json" => json = json.max(q),
                _ => {}
            }
        }
    }
    html > json
}

/// A page response: `body` as `content_type`, with the security headers; the assets are
/// revalidated on every load (`no-cache`), so a new server's page is never mixed with an
/// old script.
fn asset(content_type: &'static str, body: &'static str) -> Response {
    let mut res = body.into_response();
    let h = res.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(CONTENT_SECURITY_POLICY),
    );
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    h.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("no-referrer"),
    );
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    h.insert(
        HeaderName::from_static("cross-origin-opener-policy"),
        HeaderValue::from_static("same-origin"),
    );
    res
}

/// `GET /`: the page for a browser, else what this server is and where its documents are.
/// `auth` tells the page whether to ask for a token before its first call.
pub async fn index(State(auth): State<Auth>, headers: HeaderMap) -> Response {
    let mut res = if wants_html(&headers) {
        asset("text/html; charset=utf-8", INDEX_HTML)
    } else {
        Json(json!({
            "service": "rayd",
            "version": env!("CARGO_PKG_VERSION"),
            "api": "/v1",
            "openapi": "/v1/openapi.json",
            "health": "/healthz",
            "ready": "/readyz",
            "metrics": "/metrics",
            "page": "/",
            "auth": if auth.enabled() { "bearer" } else { "none" },
        }))
        .into_response()
    };
    res.headers_mut()
        .insert(header::VARY, HeaderValue::from_static("Accept"));
    res
}

/// `GET /page/app.js`.
pub async fn app_js() -> Response {
    asset("text/javascript; charset=utf-8", APP_JS)
}

/// `GET /page/style.css`.
pub async fn style_css() -> Response {
    asset("text/css; charset=utf-8", STYLE_CSS)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn accept(v: &str) -> HeaderMap {
        let mut h = HeaderMap::new();
        h.insert(header::ACCEPT, HeaderValue::from_str(v).unwrap());
        h
    }

    #[test]
    fn browsers_get_html_and_clients_json() {
        let chromium = "text/html,application/xhtml+xml,application/xml;q=0.9,image/avif,*/*;q=0.8";
        assert!(wants_html(&accept(chromium)));
        assert!(!wants_html(&HeaderMap::new()));
        assert!(!wants_html(&accept("*/*")));
        assert!(!wants_html(&accept("application/json")));
        assert!(!wants_html(&accept("application/json, text/html;q=0.5")));
        // Equal ranks: JSON (the page is for clients that rank HTML above it).
        assert!(!wants_html(&accept("application/json, text/html")));
        assert!(!wants_html(&accept("text/html, application/json")));
        assert!(wants_html(&accept("application/json;q=0.5, text/html")));
        assert!(!wants_html(&accept("text/html;q=0")));
    }

    #[test]
    fn the_page_loads_only_its_own_assets() {
        // The page names its script and style sheet by the paths served here, and has no
        // inline script or style the policy would block.
        assert!(INDEX_HTML.contains(&format!("src=\"{APP_JS_PATH}\"")));
        assert!(INDEX_HTML.contains(&format!("href=\"{STYLE_CSS_PATH}\"")));
        assert!(!INDEX_HTML.contains("<script>"));
        assert!(!INDEX_HTML.contains("<style"));
        assert!(!INDEX_HTML.contains(" style="));
        // No inline event handlers (` onclick=` and the like).
        let lower = INDEX_HTML.to_ascii_lowercase();
        for (i, _) in lower.match_indices(" on") {
            let name: String = lower[i + 3..]
                .chars()
                .take_while(|c| c.is_ascii_alphabetic())
                .collect();
            let after = lower[i + 3 + name.len()..].trim_start();
            assert!(!after.starts_with('='), "an inline handler on{name}=");
        }
        // Data never goes through innerHTML.
        assert!(!APP_JS.contains("innerHTML"));
        assert!(!APP_JS.contains("insertAdjacentHTML"));
    }
}
