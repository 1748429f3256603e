//! Request bodies: a size limit per route, a memory budget shared by every body in flight,
//! and a bound on concurrent requests per client (`proto/service.md`, "Bodies and limits").
//!
//! A batch of 16M rays is 512 MiB, so axum's 2 MiB default cannot stay and no limit alone
//! protects the machine: eight such uploads at once would hold 4 GiB. Every bulk body is
//! therefore read under a [`BodyBudget`], a semaphore of bytes: a request holds its bytes
//! for as long as it keeps the body (until its [`HeldBody`] or [`BodyReader`] is dropped).
//! One that cannot get its share within [`BUDGET_WAIT`] is answered 503 with
//! `Retry-After`, so the server sheds load instead of swapping. The size limit is checked
//! twice: from the declared length before a byte is read, and while streaming, for bodies
//! without a length or that lie about it.
//!
//! The per-client bound answers 503 (not 429): the contract's clients already retry a 503
//! after `Retry-After`, and the bound is about the server's memory, not a rate quota.

use std::collections::HashMap;
use std::future::Future;
use std::net::{IpAddr, SocketAddr};
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::Body;
use axum::extract::{ConnectInfo, Request, State};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use bytes::{Bytes, BytesMut};
use http_body_util::BodyExt;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use super::error::ApiError;
use super::metrics::Metrics;

/// How long a request waits for body budget before it is answered 503.
pub const BUDGET_WAIT: Duration = Duration::from_secs(2);

/// Seconds a client is told to wait after a 503 for budget or the per-client bound.
pub const RETRY_AFTER_S: u64 = 1;

/// Budget is counted in KiB, so that one permit count (a `u32`) covers bodies past 4 GiB.
const UNIT: u64 = 1024;

/// Budget is taken at least this much at a time while streaming, so that small chunks do
/// not each touch the semaphore.
const STEP: u64 = 1 << 20;

/// The memory budget of request bodies in flight, shared by all requests.
#[derive(Clone, Debug)]
pub struct BodyBudget {
    sem: Arc<Semaphore>,
    total: u64,
    metrics: Metrics,
}

impl BodyBudget {
    /// A budget of `bytes` (rounded down to whole KiB).
    pub fn new(bytes: u64, metrics: Metrics) -> Self {
        let units = (bytes / UNIT).min(Semaphore::MAX_PERMITS as u64) as usize;
        BodyBudget {
            sem: Arc::new(Semaphore::new(units)),
            total: units as u64 * UNIT,
            metrics,
        }
    }

    /// The whole budget, bytes.
    pub fn total(&self) -> u64 {
        self.total
    }

    /// Bytes not held by any request now.
    pub fn available(&self) -> u64 {
        self.sem.available_permits() as u64 * UNIT
    }

    /// Takes budget for `bytes` more bytes, waiting at most [`BUDGET_WAIT`].
    async fn acquire(&self, bytes: u64) -> Result<Held, ApiError> {
        let units = bytes.div_ceil(UNIT);
        let refuse = || {
            ApiError::unavailable(
                format!(
                    "the server's memory for request bodies ({} bytes, --max-inflight-bytes) is \
                     held by other requests; retry later",
                    self.total
                ),
                RETRY_AFTER_S,
            )
            .refused("body_budget")
        };
        let Ok(units) = u32::try_from(units) else {
            return Err(refuse());
        };
        if u64::from(units) * UNIT > self.total {
            return Err(refuse());
        }
        match tokio::time::timeout(BUDGET_WAIT, self.sem.clone().acquire_many_owned(units)).await {
            Ok(Ok(permit)) => {
                let bytes = u64::from(units) * UNIT;
                self.metrics.add_body_bytes(bytes as i64);
                Ok(Held {
                    permit: Some(permit),
                    bytes,
                    metrics: self.metrics.clone(),
                })
            }
            _ => Err(refuse()),
        }
    }
}

/// Budget held by one request; given back on drop.
#[derive(Debug)]
struct Held {
    permit: Option<OwnedSemaphorePermit>,
    bytes: u64,
    metrics: Metrics,
}

impl Held {
    fn none(metrics: Metrics) -> Self {
        Held {
            permit: None,
            bytes: 0,
            metrics,
        }
    }

    fn merge(&mut self, mut other: Held) {
        if let Some(o) = other.permit.take() {
            if let Some(p) = self.permit.as_mut() {
                p.merge(o);
            } else {
                self.permit = Some(o);
            }
        }
        self.bytes += std::mem::take(&mut other.bytes);
    }
}

impl Drop for Held {
    fn drop(&mut self) {
        self.metrics.add_body_bytes(-(self.bytes as i64));
    }
}

/// A whole body read into memory, holding its share of the budget until dropped.
#[derive(Debug)]
pub struct HeldBody {
    bytes: Bytes,
    _held: Held,
}

impl HeldBody {
    /// The body's bytes.
    pub fn bytes(&self) -> &Bytes {
        &self.bytes
    }
}

impl std::ops::Deref for HeldBody {
    type Target = [u8];
    fn deref(&self) -> &[u8] {
        &self.bytes
    }
}

/// Reads a body chunk by chunk under a size limit and the budget: for routes that work
/// while the upload goes on. The budget taken for the bytes yielded is kept until the
/// reader is dropped, since the caller usually keeps what it read.
#[derive(Debug)]
pub struct BodyReader {
    body: Body,
    limit: u64,
    budget: BodyBudget,
    held: Held,
    read: u64,
}

impl BodyReader {
    /// A reader of `body` allowing at most `limit` bytes. Refuses at once (413) a body whose
    /// declared length is over the limit; with a declared length, takes the budget for all
    /// of it before the first byte (so a request either gets all its memory or none).
    pub async fn new(body: Body, limit: u64, budget: &BodyBudget) -> Result<Self, ApiError> {
        use http_body::Body as _;
        let hint = body.size_hint();
        if hint.lower() > limit {
            return Err(too_large(limit, hint.lower(), true));
        }
        let mut reader = BodyReader {
            body,
            limit,
            budget: budget.clone(),
            held: Held::none(budget.metrics.clone()),
            read: 0,
        };
        if let Some(exact) = hint.exact() {
            if exact > 0 {
                let held = budget.acquire(exact).await?;
                reader.held.merge(held);
            }
        }
        Ok(reader)
    }

    /// Bytes read so far.
    pub fn bytes_read(&self) -> u64 {
        self.read
    }

    /// The next chunk of data, or `None` at the end. 413 when the body grows past the
    /// limit, 400 when it cannot be read (the client went away, or sent fewer bytes than
    /// it declared), 503 when the budget runs out.
    pub async fn next_chunk(&mut self) -> Result<Option<Bytes>, ApiError> {
        loop {
            let Some(frame) = self.body.frame().await else {
                return Ok(None);
            };
            let frame = frame.map_err(|e| {
                let e: &(dyn std::error::Error + 'static) = &e;
                match timeout_cause(e) {
                    Some(why) => ApiError::request_timeout(format!(
                        "the request body was cut off after {} bytes: {why}",
                        self.read
                    )),
                    None => ApiError::bad_request(format!(
                        "the request body could not be read after {} bytes: {e}",
                        self.read
                    )),
                }
                .with("byte_offset", self.read)
            })?;
            let Ok(data) = frame.into_data() else {
                continue; // trailers
            };
            let end = self.read + data.len() as u64;
            if end > self.limit {
                return Err(too_large(self.limit, end, false).with("byte_offset", self.limit));
            }
            if end > self.held.bytes {
                let need = end - self.held.bytes;
                let want = need.max(STEP.min(self.limit.saturating_sub(self.held.bytes)));
                let held = self.budget.acquire(want).await?;
                self.held.merge(held);
            }
            self.read = end;
            if !data.is_empty() {
                return Ok(Some(data));
            }
        }
    }
}

/// Why a request body was cut off for being too slow: each is answered 408.
#[derive(Debug, thiserror::Error)]
pub enum BodyTimeout {
    /// No byte arrived for the idle timeout.
    #[error("no byte arrived for {} s (--body-timeout)", .0.as_secs_f64())]
    Idle(Duration),
    /// The body came slower than the minimum rate, on average, beyond the idle timeout's
    /// allowance.
    #[error(
        "{received} bytes arrived in {:.1} s of waiting for them, slower than {min_rate} \
         bytes a second after the first {} s (--min-body-rate, --body-timeout)",
        .waited.as_secs_f64(), .allowance.as_secs_f64()
    )]
    Slow {
        /// Bytes received.
        received: u64,
        /// Time spent waiting for them.
        waited: Duration,
        /// `--min-body-rate`.
        min_rate: u64,
        /// `--body-timeout`: the waiting any body gets before the rate counts.
        allowance: Duration,
    },
}

/// The [`BodyTimeout`] in `e` or its sources, if the body was cut off for being slow.
pub fn timeout_cause<'a>(e: &'a (dyn std::error::Error + 'static)) -> Option<&'a BodyTimeout> {
    let mut cur = Some(e);
    while let Some(err) = cur {
        if let Some(t) = err.downcast_ref::<BodyTimeout>() {
            return Some(t);
        }
        cur = err.source();
    }
    None
}

/// How long the server waits for a request body: `idle` for each next byte, and in all
/// `idle` plus a second for each `min_rate` bytes received (Apache's `RequestReadTimeout`
/// `body=…,MinRate=…` rule), so that a client trickling a byte now and then cannot hold
/// its connection, memory budget, per-client slot and queue place for ever.
#[derive(Debug, Clone, Copy)]
pub struct BodyPace {
    /// `--body-timeout`.
    pub idle: Duration,
    /// `--min-body-rate`, bytes a second; 0: no rate.
    pub min_rate: u64,
}

/// A request body that fails with [`BodyTimeout`] when the server has waited `idle` for
/// its next byte, or longer in all than the rate allows. Only time spent waiting counts:
/// a handler that pauses between reads (a trace feeding the engine) is not charged for
/// its own pauses.
struct PacedBody {
    inner: Body,
    pace: BodyPace,
    sleep: Pin<Box<tokio::time::Sleep>>,
    /// When the current wait began, while waiting.
    waiting_since: Option<tokio::time::Instant>,
    /// Time spent waiting in earlier waits.
    waited: Duration,
    received: u64,
}

impl PacedBody {
    /// The waiting left before the rate is broken (`None`: no rate).
    fn rate_allowance(&self) -> Option<Duration> {
        (self.pace.min_rate > 0).then(|| {
            let earned = Duration::from_secs_f64(self.received as f64 / self.pace.min_rate as f64);
            (self.pace.idle + earned).saturating_sub(self.waited)
        })
    }
}

impl http_body::Body for PacedBody {
    type Data = Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, axum::Error>>> {
        let this = &mut *self;
        let now = tokio::time::Instant::now();
        let since = match this.waiting_since {
            Some(since) => since,
            None => {
                let wait = this
                    .rate_allowance()
                    .map_or(this.pace.idle, |left| left.min(this.pace.idle));
                this.sleep.as_mut().reset(now + wait);
                this.waiting_since = Some(now);
                now
            }
        };
        match Pin::new(&mut this.inner).poll_frame(cx) {
            Poll::Ready(frame) => {
                this.waited += now.saturating_duration_since(since);
                this.waiting_since = None;
                if let Some(Ok(f)) = &frame {
                    if let Some(data) = f.data_ref() {
                        this.received += data.len() as u64;
                    }
                }
                Poll::Ready(frame)
            }
            Poll::Pending => match this.sleep.as_mut().poll(cx) {
                Poll::Ready(()) => {
                    let waited_now = tokio::time::Instant::now().saturating_duration_since(since);
                    let e = if waited_now >= this.pace.idle {
                        BodyTimeout::Idle(this.pace.idle)
                    } else {
                        BodyTimeout::Slow {
                            received: this.received,
                            waited: this.waited + waited_now,
                            min_rate: this.pace.min_rate,
                            allowance: this.pace.idle,
                        }
                    };
                    Poll::Ready(Some(Err(axum::Error::new(e))))
                }
                Poll::Pending => Poll::Pending,
            },
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

/// Middleware: every request body gets `pace` (`--body-timeout`, `--min-body-rate`), so a
/// client that declares more bytes than it sends, a chunked body that never ends, or a
/// body trickled a byte at a time holds its connection, its memory budget and its
/// per-client slot for a bounded time.
pub async fn paced(State(pace): State<BodyPace>, req: Request, next: Next) -> Response {
    let (parts, body) = req.into_parts();
    let body = Body::new(PacedBody {
        inner: body,
        pace,
        sleep: Box::pin(tokio::time::sleep(pace.idle)),
        waiting_since: None,
        waited: Duration::ZERO,
        received: 0,
    });
    next.run(Request::from_parts(parts, body)).await
}

/// The 413 for a body over `limit`.
fn too_large(limit: u64, seen: u64, declared: bool) -> ApiError {
    let how = if declared {
        format!("its declared length is {seen} bytes")
    } else {
        format!("it grew past {limit} bytes while being read")
    };
    ApiError::payload_too_large(
        format!("the request body is larger than this route's limit of {limit} bytes (--max-body): {how}"),
        limit,
    )
}

/// Reads a whole body into memory under `limit` and the budget; the budget stays held
/// until the returned body is dropped.
pub async fn read_body_limited(
    body: Body,
    limit: u64,
    budget: &BodyBudget,
) -> Result<HeldBody, ApiError> {
    use http_body::Body as _;
    let capacity = body.size_hint().exact().unwrap_or(0).min(limit) as usize;
    let mut reader = BodyReader::new(body, limit, budget).await?;
    let mut first: Option<Bytes> = None;
    let mut buf = BytesMut::new();
    while let Some(chunk) = reader.next_chunk().await? {
        // One chunk is kept as it is; only a body of several is copied together.
        match first.take() {
            None if buf.is_empty() => first = Some(chunk),
            prev => {
                if buf.is_empty() {
                    buf.reserve(capacity.max(chunk.len()));
                }
                if let Some(p) = prev {
                    buf.extend_from_slice(&p);
                }
                buf.extend_from_slice(&chunk);
            }
        }
    }
    let bytes = first.unwrap_or_else(|| buf.freeze());
    Ok(HeldBody {
        bytes,
        _held: std::mem::replace(&mut reader.held, Held::none(budget.metrics.clone())),
    })
}

/// The per-client bound on concurrent requests.
#[derive(Clone, Debug)]
pub struct ClientLimiter {
    max: usize,
    counts: Arc<Mutex<HashMap<IpAddr, usize>>>,
}

impl ClientLimiter {
    /// At most `max` concurrent requests per IP address; 0: no bound.
    pub fn new(max: usize) -> Self {
        ClientLimiter {
            max,
            counts: Arc::default(),
        }
    }

    /// Takes one slot for `ip`, or `None` when it has `max` requests running.
    pub fn try_acquire(&self, ip: IpAddr) -> Option<ClientSlot> {
        let mut counts = self.counts.lock().unwrap_or_else(|p| p.into_inner());
        let n = counts.entry(ip).or_insert(0);
        if self.max != 0 && *n >= self.max {
            return None;
        }
        *n += 1;
        Some(ClientSlot {
            ip,
            counts: self.counts.clone(),
        })
    }
}

/// One running request of a client; frees its slot on drop.
#[derive(Debug)]
pub struct ClientSlot {
    ip: IpAddr,
    counts: Arc<Mutex<HashMap<IpAddr, usize>>>,
}

impl Drop for ClientSlot {
    fn drop(&mut self) {
        let mut counts = self.counts.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(n) = counts.get_mut(&self.ip) {
            *n -= 1;
            if *n == 0 {
                counts.remove(&self.ip);
            }
        }
    }
}

/// Middleware of the `/v1` routes: 503 when the client (by peer IP address) already has
/// `--max-client-requests` requests running. A slot is held until the handler returns its
/// response, so an upload holds one, but a long event stream that follows does not.
/// Requests without a peer address (in-process tests) are not bounded.
pub async fn limit_per_client(
    State(limiter): State<ClientLimiter>,
    req: Request,
    next: Next,
) -> Response {
    let Some(ConnectInfo(peer)) = req.extensions().get::<ConnectInfo<SocketAddr>>().copied() else {
        return next.run(req).await;
    };
    match limiter.try_acquire(peer.ip()) {
        Some(slot) => {
            let res = next.run(req).await;
            drop(slot);
            res
        }
        None => ApiError::unavailable(
            format!(
                "{} already has {} requests running (--max-client-requests); retry when one ends",
                peer.ip(),
                limiter.max
            ),
            RETRY_AFTER_S,
        )
        .refused("client_limit")
        .into_response(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::pin::Pin;
    use std::task::{Context, Poll};

    fn budget(bytes: u64) -> BodyBudget {
        BodyBudget::new(bytes, Metrics::new().unwrap())
    }

    /// A body of `chunks` that declares no length.
    struct Chunked(Vec<Bytes>);
    impl http_body::Body for Chunked {
        type Data = Bytes;
        type Error = std::convert::Infallible;
        fn poll_frame(
            mut self: Pin<&mut Self>,
            _: &mut Context<'_>,
        ) -> Poll<Option<Result<http_body::Frame<Bytes>, Self::Error>>> {
            if self.0.is_empty() {
                Poll::Ready(None)
            } else {
                Poll::Ready(Some(Ok(http_body::Frame::data(self.0.remove(0)))))
            }
        }
    }

    #[tokio::test]
    async fn limits_budget_and_release() {
        let b = budget(64 << 10);
        let body = read_body_limited(Body::from(vec![7u8; 5000]), 10_000, &b)
            .await
            .unwrap();
        assert_eq!(body.len(), 5000);
        assert_eq!(b.available(), (64 << 10) - 5 * 1024);
        drop(body);
        assert_eq!(b.available(), 64 << 10);

        // Declared length over the limit: refused before reading.
        let e = read_body_limited(Body::from(vec![0u8; 101]), 100, &b)
            .await
            .unwrap_err();
        assert_eq!(e.status(), 413);
        assert_eq!(e.extensions()["limit"], 100);

        // No declared length: refused while streaming, at the limit's offset.
        let chunks = vec![Bytes::from(vec![1u8; 60]), Bytes::from(vec![2u8; 60])];
        let e = read_body_limited(Body::new(Chunked(chunks)), 100, &b)
            .await
            .unwrap_err();
        assert_eq!(e.status(), 413);
        assert_eq!(e.extensions()["byte_offset"], 100);

        // Several chunks are joined in order.
        let chunks = vec![
            Bytes::from_static(b"ab"),
            Bytes::from_static(b"cd"),
            Bytes::from_static(b"e"),
        ];
        let body = read_body_limited(Body::new(Chunked(chunks)), 100, &b)
            .await
            .unwrap();
        assert_eq!(&body[..], b"abcde");
        drop(body);
        assert_eq!(b.available(), 64 << 10);
    }

    #[tokio::test]
    async fn spent_budget_is_503_with_retry_after() {
        let b = budget(8 << 10);
        let first = read_body_limited(Body::from(vec![0u8; 6 << 10]), 1 << 20, &b)
            .await
            .unwrap();
        let e = read_body_limited(Body::from(vec![0u8; 4 << 10]), 1 << 20, &b)
            .await
            .unwrap_err();
        assert_eq!(e.status(), 503);
        drop(first);
        // Once the first body is gone the second fits.
        assert!(
            read_body_limited(Body::from(vec![0u8; 4 << 10]), 1 << 20, &b)
                .await
                .is_ok()
        );
        // A body larger than the whole budget can never fit: refused without waiting.
        let e = read_body_limited(Body::from(vec![0u8; 9 << 10]), 1 << 20, &b)
            .await
            .unwrap_err();
        assert_eq!(e.status(), 503);
    }

    #[test]
    fn client_slots() {
        let l = ClientLimiter::new(2);
        let ip: IpAddr = "127.0.0.1".parse().unwrap();
        let other: IpAddr = "::1".parse().unwrap();
        let a = l.try_acquire(ip).unwrap();
        let _b = l.try_acquire(ip).unwrap();
        assert!(l.try_acquire(ip).is_none());
        assert!(l.try_acquire(other).is_some());
        drop(a);
        assert!(l.try_acquire(ip).is_some());
        let unbounded = ClientLimiter::new(0);
        let _slots: Vec<_> = (0..100)
            .map(|_| unbounded.try_acquire(ip).unwrap())
            .collect();
    }
}
