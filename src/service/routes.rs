//! The domain routes of API v1 (contract §5): scenes, geometry versions, traces, renders
//! and jobs. Each handler turns HTTP into a call of [`crate::app::App`] and its answer back
//! into HTTP; none of them knows how rays are traced.

use std::convert::Infallible;
use std::time::Duration;

use axum::body::Body;
use axum::extract::{DefaultBodyLimit, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use serde::Deserialize;
use serde_json::json;

use super::body::{read_body_limited, BodyReader};
use super::error::ApiError;
use super::extract::{ApiJson, ApiPath, ApiQuery};
use super::{AppState, Routes};
use crate::app::{
    App, AppError, JobEvents, RenderSpec, Thumbnail, TraceParams, TracePlace, Tri1Body, UploadKind,
};
use crate::formats::binary::{ray_count, BinaryError, Ray1Sink, HEADER_BYTES};
use crate::jobs::JobError;
use crate::store::StoreError;

/// The media type of RAY1 and HIT1 bodies.
const OCTET: &str = "application/octet-stream";
/// The media type of TRI1 bodies.
const TRI: &str = "application/x-rayd-tri";
/// The media type of a frame: a TRI1 document followed by a RAY1 document.
const FRAME: &str = "application/x-rayd-frame";

/// Every domain route, for [`super::router`].
pub fn routes() -> Routes {
    let unlimited = |r: axum::routing::MethodRouter<AppState>| r.layer(DefaultBodyLimit::disable());
    Routes::new()
        .method_router(
            Method::POST,
            "/v1/scenes",
            unlimited(axum::routing::post(upload)),
        )
        .get("/v1/scenes", list_scenes)
        .get("/v1/scenes/{id}", get_scene)
        .get("/v1/scenes/{id}/thumbnail", thumbnail)
        .delete("/v1/scenes/{id}", delete_scene)
        .method_router(
            Method::PUT,
            "/v1/scenes/{id}/geometry",
            unlimited(axum::routing::put(update_geometry)),
        )
        .get("/v1/scenes/{id}/geometry", get_geometry)
        .method_router(
            Method::POST,
            "/v1/scenes/{id}/trace",
            unlimited(axum::routing::post(trace)),
        )
        .method_router(
            Method::POST,
            "/v1/scenes/{id}/frame",
            unlimited(axum::routing::post(frame)),
        )
        .post("/v1/scenes/{id}/render", render)
        .get("/v1/jobs", list_jobs)
        .get("/v1/jobs/{job}", get_job)
        .delete("/v1/jobs/{job}", delete_job)
        .get("/v1/jobs/{job}/events", job_events)
        .get("/v1/jobs/{job}/result", job_result)
}

/// How a domain error is answered.
impl From<AppError> for ApiError {
    fn from(e: AppError) -> ApiError {
        match e {
            AppError::Store(s) => store_error(s),
            AppError::Job(j) => job_error(j),
            AppError::BadUpload {
                detail,
                byte_offset,
            } => {
                let e = ApiError::bad_request(detail);
                match byte_offset {
                    Some(o) => e.with("byte_offset", o),
                    None => e,
                }
            }
            AppError::BadParameter { field, detail } => {
                ApiError::bad_request(format!("{field}: {detail}")).with_field(field)
            }
            AppError::Unprocessable { field, detail } => {
                ApiError::unprocessable(format!("{field}: {detail}")).with_field(field)
            }
            AppError::NotReady(id) => ApiError::conflict(format!(
                "job {id} has not succeeded (yet): its result is not ready"
            )),
            AppError::Internal(m) => ApiError::internal(m),
            AppError::Busy(m) => ApiError::unavailable(m, 1),
        }
    }
}

fn store_error(e: StoreError) -> ApiError {
    match e {
        // A version the scene does not have names the parameter, as a malformed one does.
        StoreError::NotFound {
            what: "version",
            id,
        } => ApiError::not_found(format!("no version {id}")).with_field("version"),
        StoreError::NotFound { what, id } => ApiError::not_found(format!("no {what} {id}")),
        StoreError::BadPageToken => ApiError::bad_request(e.to_string()).with_field("page_token"),
        StoreError::Invalid { field, reason } => {
            ApiError::bad_request(format!("{field}: {reason}")).with_field(field)
        }
        StoreError::Conflict(m) => ApiError::conflict(m),
        StoreError::Full { .. } => {
            ApiError::insufficient_storage("the server's storage is full; nothing was stored")
        }
        other => ApiError::internal(other),
    }
}

fn job_error(e: JobError) -> ApiError {
    match e {
        JobError::InvalidRays(bad) => ApiError::unprocessable(format!(
            "{bad}; nothing was traced (send invalid=miss to answer them as misses)"
        ))
        .with("ray_index", bad.first_index)
        .with("count", bad.count)
        .with_field("rays"),
        JobError::Limit {
            what: "rays",
            value,
            limit,
        } => {
            ApiError::payload_too_large(format!("{value} rays exceed the limit of {limit}"), limit)
        }
        JobError::Limit { what, .. } => ApiError::unprocessable(e.to_string()).with_field(what),
        JobError::Invalid { field, .. } => ApiError::unprocessable(e.to_string()).with_field(field),
        JobError::Camera(c) => ApiError::unprocessable(c.to_string()).with_field("camera"),
        JobError::QueueFull(_) => {
            ApiError::unavailable(format!("{e}; try again later"), 1).refused("queue_full")
        }
        JobError::ShuttingDown => {
            ApiError::unavailable("the service is shutting down", 5).refused("shutting_down")
        }
        JobError::Cancelled => ApiError::conflict("the job was cancelled"),
        other => ApiError::internal(other),
    }
}

fn binary_error(e: BinaryError) -> ApiError {
    binary_error_at(e, 0)
}

/// [`binary_error`] of a document that starts `start` bytes into the request's body.
fn binary_error_at(e: BinaryError, start: u64) -> ApiError {
    let offset = e.byte_offset().map(|o| o + start);
    let err = match &e {
        BinaryError::TooMany { limit, .. } => ApiError::payload_too_large(e.to_string(), *limit),
        _ => ApiError::bad_request(e.to_string()),
    };
    match offset {
        Some(o) => err.with("byte_offset", o),
        None => err,
    }
}

/// The request's media type, checked against `accepted` (415 otherwise).
fn media_type<'a>(headers: &HeaderMap, accepted: &[&'a str]) -> Result<&'a str, ApiError> {
    let given = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .map(|v| {
            v.split(';')
                .next()
                .unwrap_or("")
                .trim()
                .to_ascii_lowercase()
        });
    accepted
        .iter()
        .find(|a| given.as_deref() == Some(**a))
        .copied()
        .ok_or_else(|| {
            ApiError::unsupported_media_type(
                format!(
                    "Content-Type {} is not accepted here (send one of: {})",
                    given.as_deref().unwrap_or("(none)"),
                    accepted.join(", ")
                ),
                accepted,
            )
        })
}

fn location(path: String) -> HeaderValue {
    HeaderValue::from_str(&path).expect("ids are hex")
}

/// The upload route's query string.
#[derive(Debug, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
struct UploadParams {
    /// A name for listings (the status page sends the file's name).
    name: Option<String>,
}

/// `POST /v1/scenes`.
async fn upload(
    State(state): State<AppState>,
    Extension(app): Extension<App>,
    ApiQuery(params): ApiQuery<UploadParams>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    let ct = media_type(&headers, &UploadKind::MEDIA_TYPES)?;
    let kind = UploadKind::from_media_type(ct).expect("accepted");
    let body = read_body_limited(body, state.config.max_body, &state.bodies).await?;
    let (view, created) = app.upload(kind, body.bytes().clone(), params.name).await?;
    drop(body);
    let status = if created {
        StatusCode::CREATED
    } else {
        StatusCode::OK
    };
    let mut resp = (status, Json(&view)).into_response();
    resp.headers_mut().insert(
        header::LOCATION,
        location(format!("/v1/scenes/{}", view.id)),
    );
    Ok(resp)
}

/// Pagination parameters (AIP-158).
#[derive(Debug, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
struct Page {
    limit: Option<u32>,
    page_token: Option<String>,
}

/// `GET /v1/scenes`.
async fn list_scenes(
    Extension(app): Extension<App>,
    ApiQuery(page): ApiQuery<Page>,
) -> Result<Response, ApiError> {
    let (scenes, next) = app
        .scenes(page.limit.unwrap_or(0), page.page_token.as_deref())
        .await?;
    // AIP-158: the last page's token is empty, not absent.
    let next = next.unwrap_or_default();
    Ok(Json(json!({"scenes": scenes, "next_page_token": next})).into_response())
}

/// `GET /v1/scenes/{id}`.
async fn get_scene(
    Extension(app): Extension<App>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(NoQuery {}): ApiQuery<NoQuery>,
) -> Result<Response, ApiError> {
    Ok(Json(app.scene(&id).await?).into_response())
}

/// How long a request for a thumbnail that is still being made waits for it before it is
/// answered 409 (small scenes are done well within it, unless other work holds the pool).
const THUMBNAIL_WAIT: Duration = Duration::from_secs(5);

/// `GET /v1/scenes/{id}/thumbnail`: a small PNG of the scene as uploaded.
async fn thumbnail(
    Extension(app): Extension<App>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(NoQuery {}): ApiQuery<NoQuery>,
) -> Result<Response, ApiError> {
    match app.thumbnail(&id, THUMBNAIL_WAIT).await? {
        Thumbnail::Png(png) => {
            let mut resp = Response::new(Body::from(png));
            let h = resp.headers_mut();
            h.insert(header::CONTENT_TYPE, HeaderValue::from_static("image/png"));
            // A scene id names fixed bytes, so its thumbnail never changes; private, since
            // it came with a token.
            h.insert(
                header::CACHE_CONTROL,
                HeaderValue::from_static("private, max-age=3600"),
            );
            Ok(resp)
        }
        Thumbnail::Pending => Err(ApiError::conflict(format!(
            "the thumbnail of scene {id} is still being rendered (thumbnails wait for other work); ask again after Retry-After seconds"
        ))
        .with_retry_after(1)),
    }
}

/// `DELETE /v1/scenes/{id}`.
async fn delete_scene(
    Extension(app): Extension<App>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(NoQuery {}): ApiQuery<NoQuery>,
) -> Result<Response, ApiError> {
    app.delete_scene(&id).await?;
    Ok(StatusCode::NO_CONTENT.into_response())
}

/// The query of a route that takes no parameters: any is 400, naming it, as on every
/// route.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct NoQuery {}

/// `PUT /v1/scenes/{id}/geometry`.
async fn update_geometry(
    State(state): State<AppState>,
    Extension(app): Extension<App>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(NoQuery {}): ApiQuery<NoQuery>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    media_type(&headers, &[TRI])?;
    app.scene(&id).await?;
    let body = read_body_limited(body, state.config.max_body, &state.bodies).await?;
    let version = app.update_geometry(&id, body.bytes().clone()).await?;
    Ok(Json(json!({"id": id, "version": version})).into_response())
}

/// The query of `GET /v1/scenes/{id}/geometry`: which positions.
#[derive(Debug, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
struct GeometryQuery {
    version: Option<u32>,
    time: Option<f64>,
}

/// `GET /v1/scenes/{id}/geometry`: the triangles a trace of the same `version` and `time`
/// traces, as TRI1, so that clients can compute normals and hit points of their own hits.
async fn get_geometry(
    Extension(app): Extension<App>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(q): ApiQuery<GeometryQuery>,
) -> Result<Response, ApiError> {
    let (body, len) = match app.triangles_tri1(&id, q.version, q.time).await? {
        Tri1Body::Stored { file, len } => (
            Body::from_stream(tokio_util::io::ReaderStream::with_capacity(
                file,
                RESULT_CHUNK,
            )),
            len,
        ),
        Tri1Body::Encoded(bytes) => {
            let len = bytes.len() as u64;
            (Body::from(bytes), len)
        }
    };
    let mut resp = Response::new(body);
    let h = resp.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(TRI));
    h.insert(header::CONTENT_LENGTH, HeaderValue::from(len));
    Ok(resp)
}

/// The body's length as `Content-Length` announces it, if it does.
fn content_length(headers: &HeaderMap) -> Option<u64> {
    headers
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok())
}

/// Whether the client asked for an asynchronous answer (RFC 7240 `Prefer: respond-async`).
/// A preference is its token, before any `=` value or `;` parameters: `respond-async;x=1`
/// still asks for it.
fn prefers_async(headers: &HeaderMap) -> bool {
    headers.get_all("prefer").iter().any(|v| {
        v.to_str().is_ok_and(|s| {
            s.split(',').any(|p| {
                let token = p.split([';', '=']).next().unwrap_or("");
                token.trim().eq_ignore_ascii_case("respond-async")
            })
        })
    })
}

/// `POST /v1/scenes/{id}/trace`.
async fn trace(
    State(state): State<AppState>,
    Extension(app): Extension<App>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(params): ApiQuery<TraceParams>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    media_type(&headers, &[OCTET])?;
    app.scene(&id).await?;
    if prefers_async(&headers) {
        let key = idempotency_key(&headers)?;
        let body = read_body_limited(body, state.config.max_body, &state.bodies).await?;
        // The checks a synchronous trace makes as its body arrives, before anything is
        // stored or queued: a batch over --max-rays is 413 here too, not a failed job.
        ray_count(body.bytes(), state.config.max_rays as usize).map_err(binary_error)?;
        let view = app
            .submit_trace(&id, params, body.bytes().clone(), key)
            .await?;
        let mut resp = (StatusCode::ACCEPTED, Json(&view)).into_response();
        resp.headers_mut()
            .insert(header::LOCATION, location(format!("/v1/jobs/{}", view.id)));
        return Ok(resp);
    }
    // A full queue answers at once, before the body is read; the trace takes its place
    // in the queue only when it can start (`App::begin_trace`).
    app.trace_has_room()?;
    let declared = content_length(&headers);
    let mut reader = BodyReader::new(body, state.config.max_body, &state.bodies).await?;
    let (hits, report) = traced_body(
        &app,
        &state,
        &id,
        &params,
        &mut reader,
        declared,
        bytes::Bytes::new(),
        0,
        None,
    )
    .await?;
    drop(reader);
    Ok(hits_response(&state, hits, &report))
}

/// Reads a RAY1 body (`declared` bytes long, if said), of which `first` has arrived, and
/// traces it: the rays land in their final memory as the body arrives, and go to the
/// trace in pieces if it can start before the body ends. Byte offsets in errors are
/// shifted by `offset` (where the RAY1 document starts in the request's body). `place`:
/// the trace's place in the queue, if taken before ([`App::reserve_trace`]).
#[allow(clippy::too_many_arguments)]
async fn traced_body(
    app: &App,
    state: &AppState,
    id: &str,
    params: &TraceParams,
    reader: &mut BodyReader,
    declared: Option<u64>,
    first: bytes::Bytes,
    offset: u64,
    place: Option<TracePlace>,
) -> Result<(crate::jobs::HitBody, crate::jobs::TraceReport), ApiError> {
    let ray_error = |e| binary_error_at(e, offset);
    let announced = declared
        .and_then(|len| len.checked_sub(16))
        .filter(|records| records % 32 == 0)
        .map(|records| (records / 32) as usize);
    let mut intake = app.begin_trace(id, params, announced, place).await?;
    let mut sink = Ray1Sink::new(state.config.max_rays as usize, declared);
    if let Some(n) = intake.segment_rays() {
        sink = sink.segmented(n);
    }
    sink.push(&first).map_err(ray_error)?;
    // The body's arrival is timed from its first piece to its last (the bytes after the
    // first), so that `auto` learns how fast bodies come.
    let mut arrival: Option<(std::time::Instant, u64)> = None;
    while let Some(chunk) = reader.next_chunk().await? {
        match &mut arrival {
            None => arrival = Some((std::time::Instant::now(), 0)),
            Some((_, bytes)) => *bytes += chunk.len() as u64,
        }
        sink.push(&chunk).map_err(ray_error)?;
        for rays in sink.take_ready() {
            intake.send(rays);
        }
    }
    if let Some((first, bytes)) = arrival {
        app.note_upload(bytes, first.elapsed().as_secs_f64());
    }
    let rays = sink.finish_segment().map_err(ray_error)?;
    Ok(intake.finish(rays).await?)
}

/// A synchronous trace's answer: the HIT1 body, what ran, and its timings.
fn hits_response(
    state: &AppState,
    hits: crate::jobs::HitBody,
    report: &crate::jobs::TraceReport,
) -> Response {
    state
        .metrics
        .observe_trace(report.rays as u64, report.trace_seconds);
    let mut resp = Response::new(Body::from(bytes::Bytes::from_owner(hits)));
    let h = resp.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(OCTET));
    h.insert("x-rayd-accel", HeaderValue::from_static(report.accel));
    h.insert(
        "server-timing",
        HeaderValue::from_str(&format!(
            "build;dur={:.3}, trace;dur={:.3}",
            report.build_seconds * 1e3,
            report.trace_seconds * 1e3
        ))
        .expect("ascii"),
    );
    resp
}

/// `POST /v1/scenes/{id}/frame`: a geometry update and a trace of it in one request, for a
/// client that sends new positions every frame. The body is the update's TRI1 document
/// followed by the trace's RAY1 document. The positions become the next version as a `PUT`
/// makes it while the rays go on arriving, then the rays are traced against it as a
/// trace's are. The answer is the trace's, plus `X-Rayd-Version`.
async fn frame(
    State(state): State<AppState>,
    Extension(app): Extension<App>,
    ApiPath(id): ApiPath<String>,
    ApiQuery(params): ApiQuery<TraceParams>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    media_type(&headers, &[FRAME])?;
    // The trace's options, but not which geometry: a frame traces the version it makes.
    for (field, given) in [
        ("version", params.version.is_some()),
        ("time", params.time.is_some()),
    ] {
        if given {
            return Err(ApiError::bad_request(format!(
                "{field}: a frame traces the version its positions make"
            ))
            .with_field(field));
        }
    }
    let triangles = app.triangle_count(&id).await?;
    app.trace_has_room()?;
    let declared = content_length(&headers);
    let mut reader = BodyReader::new(body, state.config.max_body, &state.bodies).await?;
    // The positions, whole: the header is checked as soon as it is in, so a body for
    // another scene is refused before the rest is read.
    let tri_len = HEADER_BYTES + 36 * triangles;
    let mut tri = bytes::BytesMut::new();
    let mut rest = bytes::Bytes::new();
    while tri.len() < tri_len {
        let Some(mut chunk) = reader.next_chunk().await? else {
            break;
        };
        let had = tri.len();
        let take = chunk.len().min(tri_len - had);
        tri.extend_from_slice(&chunk.split_to(take));
        rest = chunk;
        if had < HEADER_BYTES && tri.len() >= HEADER_BYTES {
            app.check_positions_header(&id, &tri[..HEADER_BYTES])
                .await?;
            tri.reserve(tri_len - tri.len());
        }
    }
    if tri.len() < HEADER_BYTES {
        return Err(binary_error(BinaryError::ShortHeader {
            kind: "TRI1",
            len: tri.len(),
        }));
    }
    if tri.len() < tri_len {
        return Err(ApiError::bad_request(format!(
            "the frame's body ends in its positions: {} of the {tri_len} bytes of {triangles} triangles",
            tri.len()
        ))
        .with("byte_offset", tri.len() as u64));
    }
    // The trace's place in the queue first, so that a queue that filled while the
    // positions arrived refuses the frame before it makes a version (503, nothing made).
    let place = app.reserve_trace()?;
    // The positions become the next version, as a `PUT` would make it, while the rays go
    // on arriving into the connection's buffers; then the rays are read and traced against
    // it as a trace's are (piece by piece as they come, where the core allows).
    let version = app.update_geometry(&id, tri.freeze()).await?;
    let params = TraceParams {
        version: Some(version as u32),
        ..params
    };
    let traced = traced_body(
        &app,
        &state,
        &id,
        &params,
        &mut reader,
        declared.and_then(|n| n.checked_sub(tri_len as u64)),
        rest,
        tri_len as u64,
        Some(place),
    )
    .await;
    // A frame refused for its rays has made its version all the same: the problem says
    // which.
    let (hits, report) = traced.map_err(|e| e.with("version", version))?;
    drop(reader);
    let mut resp = hits_response(&state, hits, &report);
    resp.headers_mut()
        .insert("x-rayd-version", HeaderValue::from(version));
    Ok(resp)
}

/// The request's `Idempotency-Key`, checked: 1 to 255 visible ASCII characters.
fn idempotency_key(headers: &HeaderMap) -> Result<Option<String>, ApiError> {
    let Some(v) = headers.get("idempotency-key") else {
        return Ok(None);
    };
    v.to_str()
        .ok()
        .filter(|s| !s.is_empty() && s.len() <= 255)
        .map(|s| Some(s.to_string()))
        .ok_or_else(|| {
            ApiError::bad_request("Idempotency-Key must be 1 to 255 visible ASCII characters")
                .with_field("Idempotency-Key")
        })
}

/// `POST /v1/scenes/{id}/render`.
async fn render(
    Extension(app): Extension<App>,
    ApiPath(id): ApiPath<String>,
    headers: HeaderMap,
    ApiJson(spec): ApiJson<RenderSpec>,
) -> Result<Response, ApiError> {
    let key = idempotency_key(&headers)?;
    let (view, _) = app.submit_render(&id, spec, key).await?;
    let mut resp = (StatusCode::ACCEPTED, Json(&view)).into_response();
    resp.headers_mut()
        .insert(header::LOCATION, location(format!("/v1/jobs/{}", view.id)));
    Ok(resp)
}

/// `GET /v1/jobs`.
async fn list_jobs(
    Extension(app): Extension<App>,
    ApiQuery(page): ApiQuery<Page>,
) -> Result<Response, ApiError> {
    let (jobs, next) = app
        .jobs(page.limit.unwrap_or(0), page.page_token.as_deref())
        .await?;
    // AIP-158: the last page's token is empty, not absent.
    let next = next.unwrap_or_default();
    Ok(Json(json!({"jobs": jobs, "next_page_token": next})).into_response())
}

/// `GET /v1/jobs/{job}`.
async fn get_job(
    Extension(app): Extension<App>,
    ApiPath(job): ApiPath<String>,
    ApiQuery(NoQuery {}): ApiQuery<NoQuery>,
) -> Result<Response, ApiError> {
    Ok(Json(app.job(&job).await?).into_response())
}

/// `DELETE /v1/jobs/{job}`: cancels a queued or running job, deletes an ended one.
async fn delete_job(
    Extension(app): Extension<App>,
    ApiPath(job): ApiPath<String>,
    ApiQuery(NoQuery {}): ApiQuery<NoQuery>,
) -> Result<Response, ApiError> {
    Ok(match app.cancel_or_delete(&job).await? {
        Some(view) => Json(view).into_response(),
        None => StatusCode::NO_CONTENT.into_response(),
    })
}

/// `GET /v1/jobs/{job}/events`: the job object as Server-Sent Events each time it
/// changes, until it ends (or the service shuts down).
async fn job_events(
    State(state): State<AppState>,
    Extension(app): Extension<App>,
    ApiPath(job): ApiPath<String>,
    ApiQuery(NoQuery {}): ApiQuery<NoQuery>,
) -> Result<Response, ApiError> {
    let events = app.job_events(&job).await?;
    let shutdown = state.shutdown.clone();
    let stream = async_stream(events, shutdown);
    Ok(Sse::new(stream)
        .keep_alive(KeepAlive::new().interval(Duration::from_secs(15)))
        .into_response())
}

fn event_of(view: &crate::app::JobView) -> Event {
    Event::default()
        .event("job")
        .json_data(view)
        .expect("a job view serialises")
}

/// The events of a job as a stream: the state now, each change, the end.
fn async_stream(
    events: JobEvents,
    shutdown: super::Shutdown,
) -> impl futures_core::Stream<Item = Result<Event, Infallible>> {
    let (tx, rx) = tokio::sync::mpsc::channel::<Event>(16);
    tokio::spawn(async move {
        match events {
            JobEvents::Ended(view) => {
                let _ = tx.send(event_of(&view)).await;
            }
            // The job's live view changes only when it differs (`App`'s `show`), so each
            // change is one event.
            JobEvents::Live(mut rx) => loop {
                let view = rx.borrow_and_update().clone();
                if tx.send(event_of(&view)).await.is_err() || view.state.is_finished() {
                    break;
                }
                tokio::select! {
                    changed = rx.changed() => if changed.is_err() {
                        // The job's thread is done: its last state was sent, or the job
                        // was cancelled (its final view was sent by the canceller).
                        let last = rx.borrow().clone();
                        if last != view {
                            let _ = tx.send(event_of(&last)).await;
                        }
                        break;
                    },
                    _ = shutdown.cancelled() => break,
                }
            },
        }
    });
    tokio_stream_from(rx)
}

/// An mpsc receiver as a stream of `Ok` items.
fn tokio_stream_from(
    mut rx: tokio::sync::mpsc::Receiver<Event>,
) -> impl futures_core::Stream<Item = Result<Event, Infallible>> {
    futures_util::stream::poll_fn(move |cx| rx.poll_recv(cx).map(|o| o.map(Ok)))
}

/// `?frame=N` of the result route.
#[derive(Debug, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
struct FrameParam {
    frame: Option<usize>,
}

/// Bytes read from a stored file (a result, a geometry version) at a time while it is sent.
const RESULT_CHUNK: usize = 256 << 10;

/// `GET /v1/jobs/{job}/result`.
async fn job_result(
    Extension(app): Extension<App>,
    ApiPath(job): ApiPath<String>,
    ApiQuery(q): ApiQuery<FrameParam>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let (blob, content_type) = app.result(&job, q.frame).await?;
    // The blob id is the content's hash: a strong validator.
    let etag = format!("\"{blob}\"");
    if headers
        .get(header::IF_NONE_MATCH)
        .and_then(|v| v.to_str().ok())
        // Weak comparison (RFC 9110 §13.1.2): `W/"x"` matches `"x"`.
        .is_some_and(|v| {
            v.split(',')
                .map(str::trim)
                .any(|t| t == "*" || t.strip_prefix("W/").unwrap_or(t) == etag)
        })
    {
        let mut resp = StatusCode::NOT_MODIFIED.into_response();
        resp.headers_mut()
            .insert(header::ETAG, HeaderValue::from_str(&etag).expect("hex"));
        return Ok(resp);
    }
    // Streamed from the file, not read into memory: a 16M-ray result is 256 MiB, and a
    // request's memory outside the in-flight budget must stay small. The whole file is
    // verified against its id first, so a corrupt blob is never served, not even in part.
    let file = app.store().open_blob(&blob).await.map_err(AppError::from)?;
    let len = file
        .metadata()
        .await
        .map_err(|e| AppError::Internal(format!("result {blob}: {e}")))?
        .len();
    let body = Body::from_stream(tokio_util::io::ReaderStream::with_capacity(
        file,
        RESULT_CHUNK,
    ));
    let mut resp = Response::new(body);
    let h = resp.headers_mut();
    h.insert(header::CONTENT_LENGTH, HeaderValue::from(len));
    h.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_str(&content_type).unwrap_or(HeaderValue::from_static(OCTET)),
    );
    h.insert(header::ETAG, HeaderValue::from_str(&etag).expect("hex"));
    Ok(resp)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn respond_async_is_read_with_its_parameters() {
        let asks = |values: &[&str]| {
            let mut h = HeaderMap::new();
            for v in values {
                h.append("prefer", v.parse().unwrap());
            }
            prefers_async(&h)
        };
        for yes in [
            &["respond-async"][..],
            &["Respond-Async"],
            &["respond-async;foo"],
            &["respond-async ; foo=1"],
            &["wait=5, respond-async"],
            &["return=minimal", "respond-async"],
        ] {
            assert!(asks(yes), "{yes:?}");
        }
        for no in [
            &[][..],
            &["wait=5"],
            &["respond-asynchronously"],
            &["x;respond-async"],
        ] {
            assert!(!asks(no), "{no:?}");
        }
    }
}
