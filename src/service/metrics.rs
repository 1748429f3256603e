//! The service's Prometheus metrics, served at `/metrics` in the classic text format
//! (version 0.0.4, which `promtool check metrics` reads; the list is in `proto/service.md`).
//!
//! HTTP metrics are labelled with the route *template* (`/v1/jobs/{job}`), never the raw
//! path: ids in paths would make one time series per job. The job engine reports through
//! the typed methods of [`Metrics`] rather than through label strings of its own, so names
//! and buckets stay in one place. The `prometheus` crate is used (not `prometheus-client`)
//! because the latter writes OpenMetrics, whose counters promtool 2.x misreads as untyped
//! series without help text.

use std::sync::{Arc, OnceLock};
use std::time::Instant;

use axum::extract::{MatchedPath, Request, State};
use axum::http::{header, HeaderValue, Method};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use prometheus::{
    Encoder, Gauge, Histogram, HistogramOpts, HistogramVec, IntCounter, IntCounterVec, IntGauge,
    IntGaugeVec, Opts, Registry, TextEncoder,
};

use super::error::ApiError;
use crate::jobs::cache::CacheStats;
use crate::store::JobKind;

/// The media type of the text exposition format.
pub const PROMETHEUS_TEXT: &str = "text/plain; version=0.0.4; charset=utf-8";

/// Every metric of the service, registered in one registry.
#[derive(Clone)]
pub struct Metrics {
    registry: Registry,
    http_requests: IntCounterVec,
    http_duration: HistogramVec,
    http_in_flight: IntGaugeVec,
    connections: IntGauge,
    queue_length: IntGauge,
    jobs_running: IntGauge,
    job_duration: HistogramVec,
    rays_traced: IntCounter,
    trace_mrays: Histogram,
    cache_hits: IntCounter,
    cache_misses: IntCounter,
    cache_bytes: IntGauge,
    texture_hits: IntCounter,
    texture_misses: IntCounter,
    texture_bytes: IntGauge,
    light_hits: IntCounter,
    light_misses: IntCounter,
    light_bytes: IntGauge,
    upload_rate: Gauge,
    body_bytes: IntGauge,
    body_refused: IntCounterVec,
    /// What reads the domain's state into the metrics when they are scraped.
    sampler: Arc<OnceLock<Sampler>>,
}

/// Reads state that changes without a request passing by (the queue, the caches) into
/// the metrics, each time `/metrics` is read.
pub type Sampler = Box<dyn Fn(&Metrics) + Send + Sync>;

impl std::fmt::Debug for Metrics {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Metrics")
    }
}

/// Buckets of request durations, seconds: from a cache hit to a long synchronous trace.
const HTTP_BUCKETS: &[f64] = &[
    0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0,
];
/// Buckets of job durations, seconds: a small trace to a long animation render.
const JOB_BUCKETS: &[f64] = &[
    0.01, 0.05, 0.1, 0.5, 1.0, 5.0, 10.0, 30.0, 60.0, 300.0, 900.0, 3600.0,
];
/// Buckets of trace speed, million rays per second (one core to a large machine).
const MRAYS_BUCKETS: &[f64] = &[
    0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0,
];

/// Finished jobs and the rays of trace jobs, as the domain layer reports them.
impl crate::app::Observer for Metrics {
    fn job_ended(&self, kind: &str, _state: &str, seconds: f64) {
        // A job that never ran (cancelled in the queue) has no duration to record.
        if seconds > 0.0 {
            self.observe_job(kind, seconds);
        }
    }

    fn traced(&self, rays: u64, trace_seconds: f64) {
        self.observe_trace(rays, trace_seconds);
    }
}

/// A metric definition could not be registered (a programming error: names clash).
#[derive(Debug, thiserror::Error)]
#[error("metrics registry: {0}")]
pub struct MetricsError(#[from] prometheus::Error);

impl Metrics {
    /// A fresh registry with every metric at zero (one per server, or per test).
    pub fn new() -> Result<Self, MetricsError> {
        let registry = Registry::new_custom(Some("rayd".to_owned()), None)?;
        fn reg<C: prometheus::core::Collector + Clone + 'static>(
            r: &Registry,
            c: C,
        ) -> Result<C, prometheus::Error> {
            r.register(Box::new(c.clone()))?;
            Ok(c)
        }
        let hist = |name: &str, help: &str, buckets: &[f64]| {
            HistogramOpts::new(name, help).buckets(buckets.to_vec())
        };
        let r = &registry;
        Ok(Metrics {
            http_requests: reg(
                r,
                IntCounterVec::new(
                    Opts::new(
                        "http_requests_total",
                        "HTTP requests answered, by route template, method and status code.",
                    ),
                    &["route", "method", "status"],
                )?,
            )?,
            http_duration: reg(
                r,
                HistogramVec::new(
                    hist(
                        "http_request_duration_seconds",
                        "Time from a request's arrival to its response head, by route template and method.",
                        HTTP_BUCKETS,
                    ),
                    &["route", "method"],
                )?,
            )?,
            http_in_flight: reg(
                r,
                IntGaugeVec::new(
                    Opts::new(
                        "http_requests_in_flight",
                        "Requests being handled now, by route template.",
                    ),
                    &["route"],
                )?,
            )?,
            connections: reg(
                r,
                IntGauge::new("http_connections_open", "Client connections open now.")?,
            )?,
            queue_length: reg(
                r,
                IntGauge::new("jobs_queued", "Jobs waiting to run, every kind together.")?,
            )?,
            jobs_running: reg(r, IntGauge::new("jobs_running", "Jobs running now.")?)?,
            job_duration: reg(
                r,
                HistogramVec::new(
                    hist(
                        "job_duration_seconds",
                        "Run time of finished jobs, by kind (trace, render).",
                        JOB_BUCKETS,
                    ),
                    &["kind"],
                )?,
            )?,
            rays_traced: reg(
                r,
                IntCounter::new("rays_traced_total", "Rays traced, every job and request together.")?,
            )?,
            trace_mrays: reg(
                r,
                Histogram::with_opts(hist(
                    "trace_mrays_per_second",
                    "Speed of each trace, million rays per second (the contract's mrays_per_s).",
                    MRAYS_BUCKETS,
                ))?,
            )?,
            cache_hits: reg(
                r,
                IntCounter::new(
                    "cache_hits_total",
                    "Acceleration structures found in the cache.",
                )?,
            )?,
            cache_misses: reg(
                r,
                IntCounter::new(
                    "cache_misses_total",
                    "Acceleration structures that had to be built.",
                )?,
            )?,
            cache_bytes: reg(
                r,
                IntGauge::new("cache_bytes", "Bytes of acceleration structures held in the cache.")?,
            )?,
            texture_hits: reg(
                r,
                IntCounter::new(
                    "texture_cache_hits_total",
                    "Render jobs that found their scene's decoded textures in the cache.",
                )?,
            )?,
            texture_misses: reg(
                r,
                IntCounter::new(
                    "texture_cache_misses_total",
                    "Render jobs that decoded their scene's textures.",
                )?,
            )?,
            texture_bytes: reg(
                r,
                IntGauge::new(
                    "texture_cache_bytes",
                    "Bytes of decoded textures held in the texture cache.",
                )?,
            )?,
            light_hits: reg(
                r,
                IntCounter::new(
                    "light_cache_hits_total",
                    "Path-traced frames that found their light table in the cache.",
                )?,
            )?,
            light_misses: reg(
                r,
                IntCounter::new(
                    "light_cache_misses_total",
                    "Path-traced frames that built their light table.",
                )?,
            )?,
            light_bytes: reg(
                r,
                IntGauge::new(
                    "light_cache_bytes",
                    "Bytes of light tables held in the light-table cache.",
                )?,
            )?,
            upload_rate: reg(
                r,
                Gauge::new(
                    "trace_upload_bytes_per_second",
                    "The rate at which auto expects trace bodies to arrive (the running average of recent bodies of 1 MiB or more).",
                )?,
            )?,
            body_bytes: reg(
                r,
                IntGauge::new(
                    "request_body_bytes_in_flight",
                    "Bytes of request bodies held in memory now (bounded by --max-inflight-bytes).",
                )?,
            )?,
            body_refused: reg(
                r,
                IntCounterVec::new(
                    Opts::new(
                        "requests_refused_total",
                        "Requests answered 503 before their work began (a frame refused for its rays has made its version), by reason (body_budget, client_limit, queue_full, shutting_down, starting).",
                    ),
                    &["reason"],
                )?,
            )?,
            registry,
            sampler: Arc::new(OnceLock::new()),
        })
        .inspect(|m| {
            // Every label value the documentation lists, at 0 from the first scrape.
            for kind in [JobKind::Trace, JobKind::Render] {
                m.job_duration.with_label_values(&[kind.as_str()]);
            }
            for reason in super::error::REFUSAL_REASONS {
                m.body_refused.with_label_values(&[reason]);
            }
        })
    }

    /// Sets what reads the domain's state into the metrics before each scrape (once per
    /// server; a second call is ignored).
    pub fn sample_with(&self, sampler: Sampler) {
        let _ = self.sampler.set(sampler);
    }

    /// The registry, for metrics defined elsewhere (they get the `rayd_` prefix).
    pub fn registry(&self) -> &Registry {
        &self.registry
    }

    /// Sets the number of queued jobs.
    pub fn set_queue_length(&self, n: usize) {
        self.queue_length.set(n as i64);
    }

    /// Sets the number of running jobs.
    pub fn set_jobs_running(&self, n: usize) {
        self.jobs_running.set(n as i64);
    }

    /// Records a finished job of `kind` (`trace`, `render`) that ran `seconds`.
    pub fn observe_job(&self, kind: &str, seconds: f64) {
        self.job_duration
            .with_label_values(&[kind])
            .observe(seconds);
    }

    /// Records a trace of `rays` rays that took `trace_seconds` (the contract's
    /// `trace_seconds`): counts the rays and records the speed.
    pub fn observe_trace(&self, rays: u64, trace_seconds: f64) {
        self.rays_traced.inc_by(rays);
        if trace_seconds > 0.0 && rays > 0 {
            self.trace_mrays.observe(rays as f64 / trace_seconds / 1e6);
        }
    }

    /// Sets the structure cache's counters and size.
    pub fn set_structure_cache(&self, c: &CacheStats) {
        catch_up(&self.cache_hits, c.hits);
        catch_up(&self.cache_misses, c.misses);
        self.cache_bytes.set(c.bytes.min(i64::MAX as usize) as i64);
    }

    /// Sets the texture cache's counters and size.
    pub fn set_texture_cache(&self, c: &CacheStats) {
        catch_up(&self.texture_hits, c.hits);
        catch_up(&self.texture_misses, c.misses);
        self.texture_bytes
            .set(c.bytes.min(i64::MAX as usize) as i64);
    }

    /// Sets the light-table cache's counters and size.
    pub fn set_light_cache(&self, c: &CacheStats) {
        catch_up(&self.light_hits, c.hits);
        catch_up(&self.light_misses, c.misses);
        self.light_bytes.set(c.bytes.min(i64::MAX as usize) as i64);
    }

    /// Sets the rate at which `auto` expects trace bodies to arrive.
    pub fn set_upload_rate(&self, bytes_per_second: f64) {
        self.upload_rate.set(bytes_per_second);
    }

    /// Counts a request refused with 503 before any work, for `reason`.
    pub fn refused(&self, reason: &str) {
        self.body_refused.with_label_values(&[reason]).inc();
    }

    /// Adds `delta` (may be negative) to the bytes of bodies in flight.
    pub(crate) fn add_body_bytes(&self, delta: i64) {
        self.body_bytes.add(delta);
    }

    /// Adds `delta` to the open connections.
    pub(crate) fn add_connections(&self, delta: i64) {
        self.connections.add(delta);
    }

    /// Every metric in the text exposition format, the sampled ones read now.
    pub fn encode(&self) -> Result<String, MetricsError> {
        if let Some(sample) = self.sampler.get() {
            sample(self);
        }
        let mut buf = Vec::new();
        TextEncoder::new().encode(&self.registry.gather(), &mut buf)?;
        Ok(String::from_utf8_lossy(&buf).into_owned())
    }
}

/// Moves counter `c` up to `total`, a count the domain layer keeps itself (a counter
/// only goes up: a smaller total, which a monotonic source never reports, changes nothing).
fn catch_up(c: &IntCounter, total: u64) {
    let now = c.get();
    if total > now {
        c.inc_by(total - now);
    }
}

/// `GET /metrics`.
pub async fn metrics_handler(State(m): State<Metrics>) -> Response {
    match m.encode() {
        Ok(text) => {
            let mut res = text.into_response();
            res.headers_mut().insert(
                header::CONTENT_TYPE,
                HeaderValue::from_static(PROMETHEUS_TEXT),
            );
            res
        }
        Err(e) => ApiError::internal(e).into_response(),
    }
}

/// Holds one unit of a gauge, also when a request's future is dropped (client gone).
struct InFlight(IntGauge);

impl InFlight {
    fn new(g: IntGauge) -> Self {
        g.inc();
        InFlight(g)
    }
}

impl Drop for InFlight {
    fn drop(&mut self) {
        self.0.dec();
    }
}

/// Middleware: counts and times every request under its route template.
pub async fn record_request(State(m): State<Metrics>, req: Request, next: Next) -> Response {
    let route = req
        .extensions()
        .get::<MatchedPath>()
        .map(|p| p.as_str().to_owned())
        .unwrap_or_else(|| "unmatched".to_owned());
    // Only the standard methods get their own series: a client cannot mint new ones.
    let method = match *req.method() {
        Method::GET
        | Method::HEAD
        | Method::POST
        | Method::PUT
        | Method::DELETE
        | Method::PATCH
        | Method::OPTIONS => req.method().as_str().to_owned(),
        _ => "other".to_owned(),
    };
    let start = Instant::now();
    let in_flight = InFlight::new(m.http_in_flight.with_label_values(&[&route]));
    let res = next.run(req).await;
    drop(in_flight);
    if let Some(super::error::Refused(reason)) = res.extensions().get() {
        m.refused(reason);
    }
    m.http_requests
        .with_label_values(&[&route, &method, res.status().as_str()])
        .inc();
    m.http_duration
        .with_label_values(&[&route, &method])
        .observe(start.elapsed().as_secs_f64());
    res
}
