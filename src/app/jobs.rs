//! Jobs: render jobs and asynchronous traces, from submission to a stored result.
//!
//! A job is recorded as `queued` before the client hears `202`, and runs on a thread of its
//! own that waits in the scheduler for the pool; its progress goes to a watch channel (the
//! job's events) at once and to the store at most twice a second. Results are stored as
//! blobs before the record that names them commits, so a crash never shows a half-written
//! result; a job that was queued or running at a crash is queued again by
//! [`App::recover`].

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Instant;

use serde::Serialize;
use tokio::sync::watch;

use super::callbacks::CallbackView;
use super::{App, AppError, RenderSpec, TraceParams};
use crate::geometry::Ray;
use crate::jobs::render::FrameInput;
use crate::jobs::{sched, trace, CancelToken, InvalidPolicy, JobError};
use crate::render::surface::Surfaces;
use crate::render::texture::{DecodedOnce, TextureSet};
use crate::store::{
    BlobId, CallbackState, JobKind, JobOutcome, JobRecord, JobState, NewJob, StoreError,
};

/// A job as the API shows it (contract §5).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct JobView {
    /// Opaque id.
    pub id: String,
    /// `trace` or `render`.
    pub kind: JobKind,
    /// Where it is.
    pub state: JobState,
    /// 0 to 1.
    pub progress: f64,
    /// The scene.
    pub scene: String,
    /// The geometry version.
    pub version: i64,
    /// Submission time, milliseconds since the epoch.
    pub created_at: i64,
    /// Start time.
    pub started_at: Option<i64>,
    /// End time.
    pub finished_at: Option<i64>,
    /// When the finished job and its result will be deleted.
    pub expires_at: Option<i64>,
    /// Timings and counters.
    pub stats: Option<serde_json::Value>,
    /// Why it failed.
    pub error: Option<String>,
    /// Results: 1 for an image or a HIT1 body, one per frame for a sequence.
    pub results: usize,
    /// The request, as resolved at submission.
    pub request: serde_json::Value,
    /// A render's callback and its delivery; absent when the job has none.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub callback: Option<CallbackView>,
}

impl JobView {
    fn from_record(r: &JobRecord) -> JobView {
        let request: serde_json::Value =
            serde_json::from_str(&r.request).unwrap_or(serde_json::Value::Null);
        // Until the store's delivery record is read, a callback shows as owed.
        let callback = match (r.kind, request.get("callback").and_then(|c| c.as_str())) {
            (JobKind::Render, Some(url)) => Some(CallbackView::pending(url)),
            _ => None,
        };
        JobView {
            id: r.id.clone(),
            kind: r.kind,
            state: r.state,
            progress: if r.state == JobState::Succeeded {
                1.0
            } else {
                r.progress
            },
            scene: r.scene_id.clone(),
            version: r.version,
            created_at: r.created_at,
            started_at: r.started_at,
            finished_at: r.finished_at,
            expires_at: r.expires_at,
            stats: r
                .stats
                .as_deref()
                .and_then(|s| serde_json::from_str(s).ok()),
            error: r.error.clone(),
            results: r.result_frames.len().max(usize::from(r.result.is_some())),
            request,
            callback,
        }
    }
}

/// A running or queued job of this process.
pub(super) struct Live {
    cancel: CancelToken,
    events: watch::Sender<JobView>,
}

/// The events of a job: the current state now, then each change until it ends.
pub enum JobEvents {
    /// A live job.
    Live(watch::Receiver<JobView>),
    /// A job that has ended: its final state.
    Ended(Box<JobView>),
}

/// What an async trace job keeps of its request (the rays are in a blob).
#[derive(serde::Serialize, serde::Deserialize)]
struct TraceJobRequest {
    params: TraceParams,
    rays_blob: String,
}

/// What a job runs.
enum Work {
    Render(Box<RenderSpec>),
    Trace(TraceJobRequest),
}

impl App {
    /// A job's state.
    pub async fn job(&self, id: &str) -> Result<JobView, AppError> {
        let record = self.store().get_job(id).await?;
        let mut view = JobView::from_record(&record);
        // A live job's progress is fresher than the store's.
        if let Some(l) = self.live(id) {
            view.progress = view.progress.max(l.borrow().progress);
        }
        self.with_callback(&mut view).await?;
        Ok(view)
    }

    /// Fills in the delivery state of a job's callback from the store.
    async fn with_callback(&self, view: &mut JobView) -> Result<(), AppError> {
        if view.callback.is_some() {
            if let Some(c) = self.store().get_callback(&view.id).await? {
                view.callback = Some(CallbackView::of(&c));
            }
        }
        Ok(())
    }

    fn live(&self, id: &str) -> Option<watch::Receiver<JobView>> {
        let live = self.inner.live.lock().unwrap_or_else(|e| e.into_inner());
        live.get(id).map(|l| l.events.subscribe())
    }

    /// A page of jobs.
    pub async fn jobs(
        &self,
        limit: u32,
        page_token: Option<&str>,
    ) -> Result<(Vec<JobView>, Option<String>), AppError> {
        let (records, next) = self.store().list_jobs(limit, page_token).await?;
        let mut views: Vec<JobView> = records.iter().map(JobView::from_record).collect();
        for v in &mut views {
            // As in `job`: a live job's progress is fresher than the store's.
            if let Some(l) = self.live(&v.id) {
                v.progress = v.progress.max(l.borrow().progress);
            }
            self.with_callback(v).await?;
        }
        Ok((views, next))
    }

    /// A job's events.
    pub async fn job_events(&self, id: &str) -> Result<JobEvents, AppError> {
        // The live entry first, the record second: a job's end (or cancel) is in the store
        // before its entry goes, so a job found without one has its final state read here.
        // The other order could pair a `running` record with an entry gone meanwhile, and
        // end the stream on a state that was no longer true.
        let rx = self.live(id);
        let view = self.job(id).await?;
        match rx {
            Some(rx) if !view.state.is_finished() => Ok(JobEvents::Live(rx)),
            _ => Ok(JobEvents::Ended(Box::new(view))),
        }
    }

    /// Submits a render job. An `Idempotency-Key` already used returns the first job
    /// (`false`).
    pub async fn submit_render(
        &self,
        scene: &str,
        spec: RenderSpec,
        idempotency_key: Option<String>,
    ) -> Result<(JobView, bool), AppError> {
        let (request, times) = spec.resolve(self.engine().limits().max_frames)?;
        request.check(self.engine().limits(), times.len())?;
        if let Some(url) = &spec.callback {
            self.check_callback(url)?;
        }
        // Checks the scene, version and time now, so that a bad one is this request's
        // error and not the job's.
        let asked = spec.version;
        let (geometry, cameras) = self.geometry(scene, asked, spec.time).await?;
        // `frames` are times, which only version 1 has (`time` was checked above).
        let has_frames = spec.frames.is_some();
        let frames_on = move |version| match has_frames {
            true => super::scenes::animated(version, "frames"),
            false => Ok(()),
        };
        frames_on(geometry.key.version)?;
        if let crate::render::camera::CameraChoice::Scene(index) = request.camera {
            use crate::render::camera::CameraError;
            let missing = match cameras.get(index) {
                None => Some(CameraError::NoSuchCamera {
                    index,
                    count: cameras.len(),
                }),
                Some(None) => Some(CameraError::NotPlaced { index }),
                Some(Some(_)) => None,
            };
            if let Some(e) = missing {
                return Err(AppError::Unprocessable {
                    field: "camera",
                    detail: e.to_string(),
                });
            }
        }
        let mut spec = spec;
        // A retry finds its job before it needs a place in the queue (a full queue does not
        // refuse it), and before the latest version is filled in (a version made since the
        // first try does not make it another request). Copies sent at once take turns.
        let _key = match &idempotency_key {
            Some(k) => Some(self.inner.keys.lock(k).await),
            None => None,
        };
        if let Some(job) = self
            .retried(&idempotency_key, JobKind::Render, scene, |version| {
                let mut first = spec.clone();
                first.version = first.version.or(Some(version));
                serde_json::to_string(&first).expect("a spec serialises")
            })
            .await?
        {
            let mut view = JobView::from_record(&job);
            self.with_callback(&mut view).await?;
            return Ok((view, false));
        }
        let priority = spec.priority;
        let ticket = self.engine().scheduler().admit(priority as u16, false)?;
        spec.version = Some(geometry.key.version);
        let new = NewJob {
            kind: JobKind::Render,
            scene_id: scene.to_string(),
            version: i64::from(geometry.key.version),
            request: serde_json::to_string(&spec).expect("a spec serialises"),
            priority,
            idempotency_key: idempotency_key.clone(),
            input_blob: None,
        };
        let (record, created) = if asked.is_none() {
            // The latest version, taken for a request that named none, may be deleted by
            // newer ones before the record is made (`--keep-versions`): it then takes the
            // latest as the store finds it.
            let at = |version: i64| {
                let mut s = spec.clone();
                s.version = u32::try_from(version).ok();
                serde_json::to_string(&s).expect("a spec serialises")
            };
            self.store().create_job_latest(new, &at).await?
        } else {
            self.store().create_job(new).await?
        };
        spec.version = u32::try_from(record.version).ok();
        if created {
            if let Some(url) = &spec.callback {
                // Owed from now on, so that a crash before the job ends still delivers.
                let owed = self
                    .store()
                    .put_callback(&record.id, url, CallbackState::Pending, 0, None)
                    .await;
                if let Err(e) = owed {
                    let _ = self.store().cancel_job(&record.id).await;
                    return Err(e.into());
                }
            }
            self.start(record.clone(), Work::Render(Box::new(spec)), ticket);
        }
        let mut view = JobView::from_record(&record);
        self.with_callback(&mut view).await?;
        Ok((view, created))
    }

    /// Submits an asynchronous trace (`Prefer: respond-async`): the rays are stored and
    /// the job's result is the HIT1 body. With `idempotency_key`, a retry of the same
    /// request finds the first job, as a render's does (the rays are part of the request,
    /// by their hash).
    pub async fn submit_trace(
        &self,
        scene: &str,
        params: TraceParams,
        rays_body: bytes::Bytes,
        idempotency_key: Option<String>,
    ) -> Result<JobView, AppError> {
        let asked = params.version;
        let (geometry, _) = self.geometry(scene, asked, params.time).await?;
        // As for renders: a retry finds its job first (the rays named by their hash).
        let _key = match &idempotency_key {
            Some(k) => Some(self.inner.keys.lock(k).await),
            None => None,
        };
        let rays_id = crate::store::BlobId::of(&rays_body).to_string();
        if let Some(job) = self
            .retried(&idempotency_key, JobKind::Trace, scene, |version| {
                let mut first = params;
                first.version = first.version.or(Some(version));
                serde_json::to_string(&TraceJobRequest {
                    params: first,
                    rays_blob: rays_id.clone(),
                })
                .expect("serialises")
            })
            .await?
        {
            return Ok(JobView::from_record(&job));
        }
        if params.invalid == InvalidPolicy::Error {
            let body = rays_body.clone();
            self.cpu(move || trace::check_body(&body)).await??;
        }
        let ticket = self.engine().scheduler().admit(50, false)?;
        let rays_blob = self.store().put_blob(rays_body).await?;
        let request_at = |version: i64| {
            let mut params = params;
            params.version = u32::try_from(version).ok();
            TraceJobRequest {
                params,
                rays_blob: rays_blob.to_string(),
            }
        };
        let new = NewJob {
            kind: JobKind::Trace,
            scene_id: scene.to_string(),
            version: i64::from(geometry.key.version),
            request: serde_json::to_string(&request_at(i64::from(geometry.key.version)))
                .expect("serialises"),
            priority: 50,
            idempotency_key: idempotency_key.clone(),
            input_blob: Some(rays_blob.clone()),
        };
        // As for renders: the latest version may go before the record is made.
        let (record, created) = if asked.is_none() {
            let at = |v: i64| serde_json::to_string(&request_at(v)).expect("serialises");
            self.store().create_job_latest(new, &at).await?
        } else {
            self.store().create_job(new).await?
        };
        let request = request_at(record.version);
        if created {
            self.start(record.clone(), Work::Trace(request), ticket);
        }
        Ok(JobView::from_record(&record))
    }

    /// The job a retry with `key` finds: the one the key made, if it was made for the same
    /// kind, scene and request, where `request(version)` is this request as it was stored
    /// with the job's version filled in (a request naming none took the latest); 409 if
    /// the key made another. `None`: no key, or no job yet.
    async fn retried(
        &self,
        key: &Option<String>,
        kind: JobKind,
        scene: &str,
        request: impl FnOnce(u32) -> String,
    ) -> Result<Option<JobRecord>, AppError> {
        let Some(key) = key else {
            return Ok(None);
        };
        let Some(job) = self.store().job_by_idempotency_key(key).await? else {
            return Ok(None);
        };
        let same = job.kind == kind
            && job.scene_id == scene
            && u32::try_from(job.version).is_ok_and(|v| job.request == request(v));
        if !same {
            return Err(StoreError::Conflict(format!(
                "idempotency key {key:?} was used for job {} with a different request",
                job.id
            ))
            .into());
        }
        Ok(Some(job))
    }

    /// Cancels a queued or running job (it stops within one wave and stays as
    /// `cancelled`); deletes an ended one with its results.
    pub async fn cancel_or_delete(&self, id: &str) -> Result<Option<JobView>, AppError> {
        let record = self.store().get_job(id).await?;
        if record.state.is_finished() {
            self.store().delete_job(id).await?;
            return Ok(None);
        }
        // Stopped first, so that its progress no longer moves ([`crate::jobs::Control`]
        // reports none once cancelled) and a job waiting for the pool gives up its place
        // at once; then its progress is read and recorded: the store hears of progress
        // every 500 ms, the live view is fresher, and a cancelled job's progress must not
        // go back.
        let stopped = {
            let live = self.inner.live.lock().unwrap_or_else(|e| e.into_inner());
            live.get(id).map(|l| l.cancel.cancel()).is_some()
        };
        if stopped {
            self.engine().scheduler().nudge();
        }
        let fresher = self.live(id).map(|v| v.borrow().progress);
        if let Some(p) = fresher {
            let _ = self.store().set_progress(id, p).await;
        }
        let cancelled = match self.store().cancel_job(id).await {
            Ok(r) => r,
            // It ended meanwhile: an ended job's DELETE deletes it.
            Err(StoreError::Conflict(_)) if self.store().get_job(id).await?.state.is_finished() => {
                self.store().delete_job(id).await?;
                return Ok(None);
            }
            Err(e) => {
                self.forget_live(id);
                return Err(e.into());
            }
        };
        let live = self.take_live(id);
        let view = JobView::from_record(&cancelled);
        if let Some(l) = live {
            l.cancel.cancel();
            show(&l.events, &view);
        }
        if view.callback.is_some() {
            self.notify(id);
        }
        Ok(Some(view))
    }

    /// The stored result of a finished job: frame `frame` of a sequence, else the one
    /// result. `(blob id, media type)`.
    pub async fn result(
        &self,
        id: &str,
        frame: Option<usize>,
    ) -> Result<(String, String), AppError> {
        let record = self.store().get_job(id).await?;
        if record.state != JobState::Succeeded {
            return Err(AppError::NotReady(id.to_string()));
        }
        let blob = match (frame, &record.result, record.result_frames.as_slice()) {
            (None | Some(0), Some(r), _) => r.clone(),
            (Some(k), None, frames) if k < frames.len() => frames[k].clone(),
            (None, None, [first, ..]) => first.clone(),
            (Some(k), _, frames) => {
                return Err(AppError::BadParameter {
                    field: "frame",
                    detail: format!(
                        "frame {k} does not exist: the job has {} result(s)",
                        frames.len().max(usize::from(record.result.is_some()))
                    ),
                })
            }
            _ => return Err(AppError::NotReady(id.to_string())),
        };
        Ok((blob.blob, blob.content_type))
    }

    /// Queues again every job the store holds as queued (after [`crate::store::Store::recover`]
    /// sent back the ones running at a crash). Returns how many.
    pub async fn recover(&self) -> Result<usize, AppError> {
        let jobs = self.store().recover().await?;
        let n = jobs.len();
        for record in jobs {
            let work = match record.kind {
                JobKind::Render => {
                    serde_json::from_str(&record.request).map(|s| Work::Render(Box::new(s)))
                }
                JobKind::Trace => serde_json::from_str(&record.request).map(Work::Trace),
            };
            match work {
                Ok(work) => {
                    let ticket = self.engine().scheduler().readmit(record.priority as u16);
                    self.start(record, work, ticket);
                }
                Err(e) => {
                    // Not silently lost: failed with the reason.
                    let _ = self.store().start_job(&record.id).await;
                    let _ = self
                        .store()
                        .finish_job(
                            &record.id,
                            JobOutcome::Failed {
                                error: format!(
                                    "after a restart the stored request did not parse: {e}"
                                ),
                                stats: None,
                            },
                        )
                        .await;
                }
            }
        }
        let resumed = self.resume_callbacks().await?;
        if resumed > 0 {
            tracing::info!(
                callbacks = resumed,
                "resuming callback deliveries of the last run"
            );
        }
        Ok(n)
    }

    /// Starts the job's thread.
    fn start(&self, record: JobRecord, work: Work, ticket: sched::Ticket) {
        let cancel = CancelToken::new();
        // No receiver is kept: [`show`] updates the view whether or not anyone streams it,
        // so a GET and a cancel read the live progress (`send` would drop the value while
        // no stream is open, and a GET would show the store's, up to 500 ms old).
        let (events, _) = watch::channel(JobView::from_record(&record));
        self.inner
            .live
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(
                record.id.clone(),
                Live {
                    cancel: cancel.clone(),
                    events: events.clone(),
                },
            );
        let app = self.clone();
        let spawned = std::thread::Builder::new()
            .name(format!("rayd-job-{}", &record.id[..8.min(record.id.len())]))
            .spawn(move || app.run(record, work, ticket, cancel, events));
        if let Err(e) = spawned {
            tracing::error!("cannot start a job thread: {e}");
        }
    }

    /// The job's thread: runs the work, stores the result, ends the record.
    fn run(
        &self,
        record: JobRecord,
        work: Work,
        ticket: sched::Ticket,
        cancel: CancelToken,
        events: watch::Sender<JobView>,
    ) {
        let id = record.id.clone();
        let rt = self.inner.runtime.clone();
        let span = tracing::info_span!("job", job = %id);
        let _enter = span.enter();
        tracing::info!(kind = record.kind.as_str(), "job queued");
        let view = Arc::new(std::sync::Mutex::new(JobView::from_record(&record)));
        let last_store = Arc::new(AtomicU64::new(0));
        let t0 = Instant::now();
        let progress = {
            let (events, view, store, id, rt) = (
                events.clone(),
                Arc::clone(&view),
                self.store().clone(),
                id.clone(),
                rt.clone(),
            );
            let last_store = Arc::clone(&last_store);
            let span = span.clone();
            Arc::new(move |p: f64| {
                let mut v = view.lock().unwrap_or_else(|e| e.into_inner());
                v.progress = p;
                show(&events, &v);
                // The store hears about progress at most every 500 ms.
                let ms = t0.elapsed().as_millis() as u64;
                if ms >= last_store.load(Ordering::Relaxed) + 500 {
                    last_store.store(ms, Ordering::Relaxed);
                    let (store, id) = (store.clone(), id.clone());
                    let write = async move { store.set_progress(&id, p).await };
                    rt.spawn(tracing::Instrument::instrument(write, span.clone()));
                }
            }) as crate::jobs::control::ProgressFn
        };
        let ran_from = Arc::new(std::sync::OnceLock::<Instant>::new());
        let started = {
            let ran_from = Arc::clone(&ran_from);
            let (store, id, rt, events, view) = (
                self.store().clone(),
                id.clone(),
                rt.clone(),
                events.clone(),
                Arc::clone(&view),
            );
            move || {
                let _ = ran_from.set(Instant::now());
                if let Ok(r) = rt.block_on(store.start_job(&id)) {
                    let mut v = view.lock().unwrap_or_else(|e| e.into_inner());
                    *v = JobView::from_record(&r);
                    show(&events, &v);
                }
                tracing::info!("job started");
            }
        };
        let control = self
            .engine()
            .control(cancel.clone(), Some(progress), ticket)
            .on_start(started);
        // A panic in the work (a dependency's, say, on memory it could not get) fails the
        // job with the reason instead of leaving it `running` with nobody to end it.
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| match work {
            Work::Render(spec) => self.run_render(&record, &spec, &control),
            Work::Trace(req) => self.run_trace(&record, &req, &control),
        }))
        .unwrap_or_else(|panic| {
            let reason = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "no message".into());
            tracing::error!(%reason, "the job's work panicked");
            Err(AppError::Internal(format!(
                "the job's work panicked: {reason}"
            )))
        });
        // `control` holds the job's place in the scheduler until the end of this function:
        // the job counts as running until its end is recorded, which a shutdown waits for.
        let ran = ran_from.get().map_or(0.0, |t| t.elapsed().as_secs_f64());
        let observe = |state: JobState| {
            if let Some(o) = &self.inner.observer {
                o.job_ended(record.kind.as_str(), state.as_str(), ran);
            }
        };
        let end = match outcome {
            Ok((stats, results)) => {
                let (result, frames) = if results.len() == 1 {
                    (results.into_iter().next(), Vec::new())
                } else {
                    (None, results)
                };
                JobOutcome::Succeeded {
                    stats: Some(stats.to_string()),
                    result,
                    frames,
                }
            }
            Err(AppError::Job(JobError::Cancelled)) => {
                // Its canceller records the end, and takes the live entry to show it.
                tracing::info!("job cancelled");
                observe(JobState::Cancelled);
                return;
            }
            // Refused its start by a shutdown: its record stays queued, for the next start.
            Err(AppError::Job(JobError::ShuttingDown)) if ran_from.get().is_none() => {
                tracing::info!("job left queued by the shutdown");
                self.forget_live(&id);
                return;
            }
            Err(e) => JobOutcome::Failed {
                error: failure_reason(&e),
                stats: None,
            },
        };
        // A job cancelled after its last wave has nothing to finish.
        if !cancel.is_cancelled() {
            // The job may not have started (it failed in the queue): start it to end it.
            let store = self.store().clone();
            // A failure keeps the progress its job had reached (the store hears of it only
            // every 500 ms; a job that failed sooner went from 1 back to 0).
            let reached = matches!(end, JobOutcome::Failed { .. })
                .then(|| self.live(&id).map(|v| v.borrow().progress))
                .flatten();
            let finished = rt.block_on(async {
                if matches!(
                    store.get_job(&id).await.map(|r| r.state),
                    Ok(JobState::Queued)
                ) {
                    let _ = store.start_job(&id).await;
                }
                if let Some(p) = reached {
                    let _ = store.set_progress(&id, p).await;
                }
                match store.finish_job(&id, end).await {
                    Err(e) => {
                        // Cancelled after the check above: the cancel is the job's end
                        // (the canceller has told its event streams and its callback).
                        if let Ok(r) = store.get_job(&id).await {
                            if r.state == JobState::Cancelled {
                                return Ok(r);
                            }
                        }
                        // Its results could not be recorded (a blob gone, say): the job
                        // ends as failed with the reason, never `running` with nobody to
                        // end it.
                        tracing::error!("cannot record the job's end: {e}; recording a failure");
                        let failed = JobOutcome::Failed {
                            error: format!(
                                "the job's results could not be recorded: {}",
                                failure_reason(&AppError::Store(e))
                            ),
                            stats: None,
                        };
                        store.finish_job(&id, failed).await
                    }
                    ok => ok,
                }
            });
            match finished {
                Ok(r) => {
                    tracing::info!(state = r.state.as_str(), "job ended");
                    observe(r.state);
                    let view = JobView::from_record(&r);
                    let has_callback = view.callback.is_some() && r.state != JobState::Cancelled;
                    show(&events, &view);
                    if has_callback {
                        self.notify(&id);
                    }
                }
                Err(e) => tracing::error!("cannot record the job's end: {e}"),
            }
            self.forget_live(&id);
        } else {
            // Its canceller records the end, and takes the live entry to show it.
            observe(JobState::Cancelled);
        }
    }

    /// Stops jobs `ids`, deleted with their scene: each ends within a wave, as a
    /// cancelled job does, with no record left to write its end to.
    pub(super) fn stop_deleted(&self, ids: &[String]) {
        for l in ids.iter().filter_map(|id| self.take_live(id)) {
            l.cancel.cancel();
            // Its event streams end on a final state, as every stream does, saying why;
            // the record itself is gone with the scene.
            let mut view = l.events.borrow().clone();
            view.state = JobState::Cancelled;
            view.finished_at = Some(crate::store::now_millis());
            view.error = Some("its scene was deleted".to_string());
            show(&l.events, &view);
        }
    }

    /// Job `id`'s live entry, taken out of the table.
    fn take_live(&self, id: &str) -> Option<Live> {
        self.inner
            .live
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(id)
    }

    fn forget_live(&self, id: &str) {
        self.take_live(id);
    }

    fn run_render(
        &self,
        record: &JobRecord,
        spec: &RenderSpec,
        control: &crate::jobs::Control,
    ) -> Result<(serde_json::Value, Vec<(BlobId, String)>), AppError> {
        let rt = &self.inner.runtime;
        let (request, times) = spec.resolve(self.engine().limits().max_frames)?;
        let scene = record.scene_id.clone();
        let version = Some(record.version as u32);
        // Geometry for each time comes through the store and caches (async); the job's
        // thread waits for it.
        // Surfaces (materials, shading normals, lights) come from the file, posed at the
        // frame's time for version 1; later versions move positions only, so they shade
        // with the file's static normals and lights.
        let needs_surfaces = request.needs_surfaces();
        // Found in the engine's cache (or decoded into it) by the first frame that shades.
        let textures = DecodedOnce::default();
        let frame_at = |time: Option<f64>, control: &crate::jobs::Control| {
            let time = time.filter(|_| version == Some(1));
            // The geometry and the parsed scene (posed) in one step; the textures, on the
            // first frame, in steps of their own; the surfaces in a last one.
            let (geometry, cameras, shaded) = control.step(|| -> Result<_, JobError> {
                let (geometry, cameras) = rt
                    .block_on(self.geometry(&scene, version, time))
                    .map_err(|e| JobError::Geometry(e.to_string()))?;
                if !needs_surfaces {
                    return Ok((geometry, cameras, None));
                }
                let shaded = rt
                    .block_on(self.shaded_scene(&scene))
                    .map_err(|e| JobError::Geometry(e.to_string()))?;
                let posed = match time {
                    Some(t) => Some(
                        shaded
                            .at(t)
                            .map_err(|e| JobError::Geometry(format!("time {t}: {e}")))?,
                    ),
                    None => None,
                };
                Ok((geometry, cameras, Some((shaded, posed))))
            })??;
            let surfaces =
                match shaded {
                    Some((shaded, posed)) => {
                        // Cancellation between the steps stays a cancellation.
                        let decoded = textures.get_or(|| {
                            self.engine().textures().get_or_decode(&scene, || {
                                TextureSet::in_steps(&shaded, &|part| control.step(part))?
                                    .map_err(|e| JobError::Geometry(e.to_string()))
                            })
                        })?;
                        let posed = posed.as_ref().unwrap_or(&*shaded);
                        Some(control.step(|| {
                            Arc::new(Surfaces::with_textures(posed, (**decoded).clone()))
                        })?)
                    }
                    None => None,
                };
            Ok(FrameInput {
                geometry,
                cameras,
                surfaces,
            })
        };
        let mut results = Vec::new();
        let mime = request.format.mime();
        let mut emit = |_k: usize, bytes: Vec<u8>| {
            let blob = rt.block_on(self.store().put_blob(bytes)).map_err(|e| {
                JobError::Geometry(format!(
                    "storing the result: {}",
                    failure_reason(&AppError::Store(e))
                ))
            })?;
            results.push((blob, mime.to_string()));
            Ok(())
        };
        let report = self
            .engine()
            .render(&request, &times, &frame_at, control, &mut emit)?;
        // Every ray a render traced counts, as a trace's do.
        if let Some(o) = &self.inner.observer {
            o.traced(report.rays, report.trace_seconds);
        }
        Ok((serde_json::to_value(report).expect("serialises"), results))
    }

    fn run_trace(
        &self,
        record: &JobRecord,
        req: &TraceJobRequest,
        control: &crate::jobs::Control,
    ) -> Result<(serde_json::Value, Vec<(BlobId, String)>), AppError> {
        let rt = &self.inner.runtime;
        let bytes = rt.block_on(self.store().get_blob(&req.rays_blob))?;
        let mut rays: Vec<Ray> =
            crate::formats::binary::read_rays(&bytes).map_err(|e| AppError::BadUpload {
                detail: e.to_string(),
                byte_offset: e.byte_offset(),
            })?;
        drop(bytes);
        let invalid = trace::validate(&mut rays, req.params.invalid)?;
        let (geometry, _) = rt.block_on(self.geometry(
            &record.scene_id,
            Some(record.version as u32),
            req.params.time,
        ))?;
        let (body, report) =
            self.engine()
                .trace(&geometry, &rays, &req.params.request(), invalid, control)?;
        if let Some(o) = &self.inner.observer {
            o.traced(report.rays as u64, report.trace_seconds);
        }
        let blob = rt.block_on(self.store().put_blob(body.as_ref().to_vec()))?;
        Ok((
            serde_json::to_value(report).expect("serialises"),
            vec![(blob, "application/octet-stream".to_string())],
        ))
    }
}

/// Shows `view` to job's event streams (and to GETs of the live job), unless the job has
/// already ended there: a cancel's final view must not be overwritten by a progress step
/// of the wave that was running when it came, or a stream would end on `running`.
/// (`send_if_modified`, like `send_replace`, updates the value with no stream open.)
fn show(events: &watch::Sender<JobView>, view: &JobView) {
    events.send_if_modified(|shown| {
        if shown.state.is_finished() || *shown == *view {
            return false;
        }
        *shown = view.clone();
        true
    });
}

/// What a failed job's record tells its client: the error, except where it is the server's
/// own (the store's I/O, its database, an internal fault), whose text names server paths
/// and internals (session 31's review found a blob's absolute path in a job's error): then
/// what happened in general terms, the log having the cause under the job's id.
fn failure_reason(e: &AppError) -> String {
    match e {
        AppError::Store(StoreError::Full { .. }) => {
            tracing::error!("job failed: {e}");
            "the server's storage is full; the result was not stored".into()
        }
        AppError::Store(
            StoreError::Io { .. }
            | StoreError::Db(_)
            | StoreError::Migrate(_)
            | StoreError::Corrupt { .. }
            | StoreError::MissingBlob { .. },
        )
        | AppError::Internal(_) => {
            tracing::error!("job failed: {e}");
            "the server failed to finish this job; its log has the cause under the job's id".into()
        }
        other => other.to_string(),
    }
}
