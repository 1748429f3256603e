//! `rayd serve`: the HTTP edge of rayd (contract §5; `proto/openapi.yaml` describes every
//! route, `proto/service.md` the choices behind them).
//!
//! This module knows HTTP and nothing of ray tracing: configuration, problem documents,
//! request ids, authentication, metrics, health, body limits and the server loop. The
//! domain routes (scenes, trace, render, jobs) are written elsewhere and handed to
//! [`router`] as a [`Routes`] table; everything here wraps them the same way. The layers,
//! outermost first:
//!
//! 1. request id (`X-Request-Id` both ways; finishes every error as problem+json),
//! 2. the request's tracing span (id, method, route template),
//! 3. metrics (count and duration per route template and status),
//! 4. the request body's idle timeout (`--body-timeout`),
//! 5. on `/v1` routes only: the bearer token check, then the per-client bound.
//!
//! Handlers return `Result<_, ApiError>`, take bodies with [`ApiJson`] or
//! [`read_body_limited`]/[`BodyReader`] and query strings with [`ApiQuery`], so every
//! rejection is a problem document too.

pub mod auth;
pub mod body;
pub mod callback;
pub mod config;
pub mod error;
pub mod extract;
pub mod health;
pub mod metrics;
pub mod openapi;
pub mod page;
pub mod request_id;
pub mod routes;
pub mod server;

use std::sync::Arc;

use axum::extract::FromRef;
use axum::handler::Handler;
use axum::http::{Method, Uri};
use axum::middleware::{from_fn, from_fn_with_state};
use axum::routing::MethodRouter;
use axum::Router;
use tower_http::trace::{DefaultOnResponse, TraceLayer};

pub use auth::{Auth, AuthError};
pub use body::{read_body_limited, BodyBudget, BodyReader, ClientLimiter, HeldBody};
pub use config::{ConfigError, LogFormat, ServeArgs};
pub use error::{ApiError, Problem, PROBLEM_JSON};
pub use extract::{ApiJson, ApiPath, ApiQuery};
pub use health::{Phase, Ready, Shutdown};
pub use metrics::Metrics;
pub use request_id::{RequestId, X_REQUEST_ID};
pub use server::{bind, serve, ServerOptions, Stopped};

/// Errors of starting or running the service.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// The options contradict each other.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// The token file is unusable.
    #[error(transparent)]
    Auth(#[from] AuthError),
    /// The metrics registry could not be made.
    #[error(transparent)]
    Metrics(#[from] metrics::MetricsError),
    /// The callback options are unusable.
    #[error(transparent)]
    Callback(#[from] callback::CallbackError),
    /// Binding, serving or signal handling failed.
    #[error("{what}: {source}")]
    Io {
        /// What was being done.
        what: String,
        /// Why it failed.
        source: std::io::Error,
    },
}

/// What every handler can reach: the service's own pieces. The job engine and the store
/// join here as further fields (with a `FromRef` impl each, so handlers extract only what
/// they use).
#[derive(Clone, Debug)]
pub struct AppState {
    /// The options the server was started with.
    pub config: Arc<ServeArgs>,
    /// Accepted bearer tokens.
    pub auth: Auth,
    /// The metrics registry.
    pub metrics: Metrics,
    /// Readiness (`/readyz`).
    pub ready: Ready,
    /// The shutdown signal.
    pub shutdown: Shutdown,
    /// The memory budget of request bodies.
    pub bodies: BodyBudget,
    /// The per-client bound on concurrent requests.
    pub clients: ClientLimiter,
}

impl AppState {
    /// The service's state for `config`: reads the token file, makes the metrics and the
    /// budgets. Readiness starts as [`Phase::Starting`].
    pub fn new(config: ServeArgs) -> Result<Self, ServiceError> {
        config.validate()?;
        let auth = match &config.token_file {
            Some(f) => Auth::from_file(f)?,
            None => Auth::disabled(),
        };
        let metrics = Metrics::new()?;
        Ok(AppState {
            bodies: BodyBudget::new(config.max_inflight_bytes, metrics.clone()),
            clients: ClientLimiter::new(config.max_client_requests),
            config: Arc::new(config),
            auth,
            metrics,
            ready: Ready::default(),
            shutdown: Shutdown::default(),
        })
    }

    /// The server loop's options.
    pub fn server_options(&self) -> ServerOptions {
        ServerOptions {
            header_timeout: self.config.header_timeout(),
            max_connections: self.config.max_connections,
            grace: self.config.grace(),
        }
    }
}

macro_rules! from_ref {
    ($($field:ident: $ty:ty),*) => {$(
        impl FromRef<AppState> for $ty {
            fn from_ref(s: &AppState) -> Self {
                s.$field.clone()
            }
        }
    )*};
}
from_ref!(auth: Auth, metrics: Metrics, ready: Ready, shutdown: Shutdown, bodies: BodyBudget, clients: ClientLimiter);

impl FromRef<AppState> for Arc<ServeArgs> {
    fn from_ref(s: &AppState) -> Self {
        s.config.clone()
    }
}

/// A table of routes being built, which remembers each (method, path template) it
/// registers so the document check ([`openapi::check_routes`]) sees exactly what the
/// router serves. Paths are full (`/v1/scenes/{id}`).
#[derive(Debug, Default)]
pub struct Routes {
    router: Router<AppState>,
    table: Vec<(Method, String)>,
}

impl Routes {
    /// No routes.
    pub fn new() -> Self {
        Routes::default()
    }

    fn add(mut self, method: Method, path: &str, route: MethodRouter<AppState>) -> Self {
        self.router = self.router.route(path, route);
        self.table.push((method, path.to_owned()));
        self
    }

    /// `GET path` (axum answers `HEAD` with it).
    pub fn get<H: Handler<T, AppState>, T: 'static>(self, path: &str, h: H) -> Self {
        self.add(Method::GET, path, axum::routing::get(h))
    }

    /// `POST path`.
    pub fn post<H: Handler<T, AppState>, T: 'static>(self, path: &str, h: H) -> Self {
        self.add(Method::POST, path, axum::routing::post(h))
    }

    /// `PUT path`.
    pub fn put<H: Handler<T, AppState>, T: 'static>(self, path: &str, h: H) -> Self {
        self.add(Method::PUT, path, axum::routing::put(h))
    }

    /// `DELETE path`.
    pub fn delete<H: Handler<T, AppState>, T: 'static>(self, path: &str, h: H) -> Self {
        self.add(Method::DELETE, path, axum::routing::delete(h))
    }

    /// A route whose method router is built by hand (for per-route layers such as
    /// `DefaultBodyLimit::disable()`); `method` is what it is recorded as.
    pub fn method_router(self, method: Method, path: &str, route: MethodRouter<AppState>) -> Self {
        self.add(method, path, route)
    }

    /// The (method, path template) pairs registered so far.
    pub fn table(&self) -> &[(Method, String)] {
        &self.table
    }
}

/// The routes that need no token: `/` (the status page or the JSON index) and the page's
/// assets, `/healthz`, `/readyz`, `/metrics`.
fn public_routes() -> Routes {
    Routes::new()
        .get("/", page::index)
        .get(page::APP_JS_PATH, page::app_js)
        .get(page::STYLE_CSS_PATH, page::style_css)
        .get("/healthz", health::healthz)
        .get("/readyz", health::readyz)
        .get("/metrics", metrics::metrics_handler)
}

/// The `/v1` routes this module serves itself, added to the domain's.
fn own_v1_routes(v1: Routes) -> Routes {
    v1.get("/v1/openapi.json", openapi::openapi_handler)
}

/// Every (method, path template) that [`router`]`(state, v1)` serves: the table to compare
/// with `proto/openapi.yaml`.
pub fn route_table(v1: &Routes) -> Vec<(Method, String)> {
    let mut t = public_routes().table;
    t.extend(v1.table.iter().cloned());
    t.push((Method::GET, "/v1/openapi.json".to_owned()));
    t
}

/// The whole service: the public routes, `/v1/openapi.json`, the domain's `/v1` routes
/// (`v1`, full paths), the fallbacks and every layer.
pub fn router(state: AppState, v1: Routes) -> Router {
    let v1 = own_v1_routes(v1)
        .router
        .route_layer(from_fn_with_state(
            state.clients.clone(),
            body::limit_per_client,
        ))
        .route_layer(from_fn_with_state(state.auth.clone(), auth::require_token))
        .route_layer(from_fn_with_state(
            state.ready.clone(),
            health::refuse_while_starting,
        ));
    public_routes()
        .router
        .merge(v1)
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(from_fn_with_state(state.config.body_pace(), body::paced))
        .layer(from_fn_with_state(
            state.metrics.clone(),
            metrics::record_request,
        ))
        .layer(
            TraceLayer::new_for_http()
                .make_span_with(request_id::make_span)
                .on_response(DefaultOnResponse::new().level(tracing::Level::INFO))
                .on_failure(log_failure),
        )
        .layer(from_fn(request_id::request_id_layer))
        .with_state(state)
}

/// Logs a response that failed: a 503 (a full queue, a busy client, a shutdown: refusals
/// the API documents, which clients retry) as a warning, anything else (a 500, an error of
/// the connection) as an error.
fn log_failure(
    class: tower_http::classify::ServerErrorsFailureClass,
    latency: std::time::Duration,
    _span: &tracing::Span,
) {
    use tower_http::classify::ServerErrorsFailureClass as C;
    let ms = latency.as_secs_f64() * 1e3;
    match class {
        C::StatusCode(s) if s == http::StatusCode::SERVICE_UNAVAILABLE => {
            tracing::warn!(status = s.as_u16(), latency_ms = ms, "refused")
        }
        C::StatusCode(s) => tracing::error!(status = s.as_u16(), latency_ms = ms, "failed"),
        C::Error(e) => tracing::error!(error = %e, latency_ms = ms, "failed"),
    }
}

/// The fallback of unknown paths.
async fn not_found(uri: Uri) -> ApiError {
    ApiError::not_found(format!("no route at {}", uri.path()))
}

/// The fallback of known paths with a method they do not have.
async fn method_not_allowed(method: Method, uri: Uri) -> ApiError {
    ApiError::method_not_allowed(format!("{} does not answer {method}", uri.path()), None)
}

/// Installs the log subscriber on stderr: `RAYD_LOG` (an `EnvFilter`, default `info`)
/// selects what is logged, `format` how. A second call is a no-op.
pub fn init_logging(format: LogFormat) {
    use tracing_subscriber::EnvFilter;
    let filter = EnvFilter::try_from_env("RAYD_LOG").unwrap_or_else(|_| EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_writer(std::io::stderr)
        // A log line that cannot be written (stderr's reader gone) is dropped. Reported,
        // it would go through `eprintln!`, which panics on that same stderr: in a request's
        // task, or in the signal handler before it starts the shutdown.
        .log_internal_errors(false);
    let _ = match format {
        LogFormat::Text => builder.try_init(),
        LogFormat::Json => builder
            .json()
            .flatten_event(true)
            .with_current_span(true)
            .try_init(),
    };
}
