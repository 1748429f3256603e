//! Scene thumbnails: a small `normals` render of each scene as uploaded, for listings (the
//! status page shows one per scene).
//!
//! A thumbnail is asked for when a scene is uploaded (the demo scenes too) and again,
//! lazily, on the first request after a restart or an eviction: it is derived data, kept
//! in memory only, and always re-made from the stored scene. The work never runs on the
//! async runtime and never delays the upload's answer: one background thread takes the
//! scenes in order and renders each through the scheduler at [`THUMBNAIL_PRIORITY`], below
//! every job, so a thumbnail only gets the pool when nothing else wants it; being one
//! thread, at most one thumbnail waits in the queue at a time, so thumbnails can never fill
//! the queue that `--max-queued` bounds. Each is the static pose of version 1 (the scene as
//! uploaded, which never changes), so a finished thumbnail never goes stale.

use std::collections::{HashMap, VecDeque};
use std::sync::{mpsc, Mutex, Weak};
use std::time::Duration;

use tokio::sync::watch;

use super::{App, AppError, Inner};
use crate::jobs::render::FrameInput;
use crate::jobs::{CancelToken, JobError, RenderRequest};
use crate::render::Integrator;

/// Width of every thumbnail, pixels.
pub const THUMBNAIL_WIDTH: u32 = 160;
/// Height of every thumbnail, pixels.
pub const THUMBNAIL_HEIGHT: u32 = 120;
/// The scheduler priority of thumbnail renders: below every job's 0–100 default of 50,
/// and equal to the lowest a client can ask for, which it then shares first come first
/// served.
pub const THUMBNAIL_PRIORITY: u16 = 0;
/// Bytes of finished thumbnails kept in memory; past it the oldest are dropped (and made
/// again when asked for).
const KEEP_BYTES: usize = 64 << 20;

/// Where one scene's thumbnail is.
#[derive(Clone, Debug)]
enum Entry {
    /// Queued or rendering.
    Pending,
    /// The PNG.
    Ready(bytes::Bytes),
    /// It cannot be made (the reason); not tried again until the scene is uploaded again.
    Failed(String),
}

/// What a request for a thumbnail gets.
#[derive(Debug)]
pub enum Thumbnail {
    /// The PNG bytes.
    Png(bytes::Bytes),
    /// Still queued or rendering: ask again later.
    Pending,
}

/// The thumbnails of this process and the queue of the thread that makes them.
pub(super) struct Thumbnails {
    state: Mutex<State>,
    /// Bumped each time a thumbnail is finished (or fails): waiters watch it.
    done: watch::Sender<u64>,
    /// Scene ids for the worker thread.
    queue: Mutex<mpsc::Sender<String>>,
}

#[derive(Default)]
struct State {
    entries: HashMap<String, Entry>,
    /// Finished thumbnails, oldest first, for eviction.
    order: VecDeque<String>,
    bytes: usize,
}

impl Thumbnails {
    /// The thumbnails of the app whose inner state `app` will be, with their worker thread
    /// (which ends when the app is dropped).
    pub(super) fn new(app: Weak<Inner>) -> Thumbnails {
        let (tx, rx) = mpsc::channel::<String>();
        let spawned = std::thread::Builder::new()
            .name("rayd-thumbnails".into())
            .spawn(move || worker(app, rx));
        if let Err(e) = spawned {
            tracing::error!("cannot start the thumbnail thread: {e}");
        }
        Thumbnails::with_queue(tx)
    }

    /// The thumbnails, their work going to `queue`.
    fn with_queue(queue: mpsc::Sender<String>) -> Thumbnails {
        Thumbnails {
            state: Mutex::new(State::default()),
            done: watch::channel(0).0,
            queue: Mutex::new(queue),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn get(&self, id: &str) -> Option<Entry> {
        self.lock().entries.get(id).cloned()
    }

    /// Queues scene `id` unless its thumbnail is pending or ready; `retry_failed` queues a
    /// failed one again (a fresh upload of the same bytes).
    fn request(&self, id: &str, retry_failed: bool) {
        {
            let mut s = self.lock();
            match s.entries.get(id) {
                Some(Entry::Pending | Entry::Ready(_)) => return,
                Some(Entry::Failed(_)) if !retry_failed => return,
                _ => {}
            }
            s.entries.insert(id.to_string(), Entry::Pending);
        }
        let sent = self
            .queue
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .send(id.to_string());
        if sent.is_err() {
            self.finish(id, Err("the thumbnail thread is not running".into()));
        }
    }

    /// Records the outcome of a pending thumbnail (a scene deleted meanwhile keeps none).
    fn finish(&self, id: &str, outcome: Result<Vec<u8>, String>) {
        {
            let mut s = self.lock();
            if !matches!(s.entries.get(id), Some(Entry::Pending)) {
                return;
            }
            match outcome {
                Ok(png) => {
                    s.bytes += png.len();
                    s.entries
                        .insert(id.to_string(), Entry::Ready(bytes::Bytes::from(png)));
                    s.order.push_back(id.to_string());
                    while s.bytes > KEEP_BYTES && s.order.len() > 1 {
                        let oldest = s.order.pop_front().expect("not empty");
                        if let Some(Entry::Ready(b)) = s.entries.remove(&oldest) {
                            s.bytes -= b.len();
                        }
                    }
                }
                Err(why) => {
                    s.entries.insert(id.to_string(), Entry::Failed(why));
                }
            }
        }
        self.done.send_modify(|n| *n += 1);
    }

    /// Forgets scene `id`'s thumbnail (the scene was deleted).
    pub(super) fn forget(&self, id: &str) {
        let mut s = self.lock();
        if let Some(Entry::Ready(b)) = s.entries.remove(id) {
            s.bytes -= b.len();
            s.order.retain(|o| o != id);
        }
    }
}

/// The worker thread: renders each queued scene in turn until the app is gone.
fn worker(app: Weak<Inner>, rx: mpsc::Receiver<String>) {
    while let Ok(id) = rx.recv() {
        let Some(inner) = app.upgrade() else { break };
        let app = App { inner };
        let outcome = app.render_thumbnail(&id);
        if let Err(why) = &outcome {
            tracing::warn!(scene = %id, "no thumbnail: {why}");
        }
        app.inner.thumbnails.finish(&id, outcome);
    }
}

impl App {
    /// Asks for scene `id`'s thumbnail to be made in the background (after an upload).
    pub(super) fn queue_thumbnail(&self, id: &str) {
        self.inner.thumbnails.request(id, true);
    }

    /// Scene `id`'s thumbnail: the PNG once made; else it is queued (if it was not) and
    /// this waits up to `wait` for it, answering [`Thumbnail::Pending`] if it is still not
    /// done. A scene that does not exist is an error; so is one that cannot be rendered.
    pub async fn thumbnail(&self, id: &str, wait: Duration) -> Result<Thumbnail, AppError> {
        // Checks the scene exists (a deleted one must not be rendered or answered).
        self.store().get_scene(id).await?;
        let thumbs = &self.inner.thumbnails;
        let mut done = thumbs.done.subscribe();
        thumbs.request(id, false);
        let deadline = tokio::time::Instant::now() + wait;
        loop {
            match thumbs.get(id) {
                Some(Entry::Ready(png)) => return Ok(Thumbnail::Png(png)),
                Some(Entry::Failed(why)) => {
                    return Err(AppError::Unprocessable {
                        field: "id",
                        detail: format!("scene {id} has no thumbnail: {why}"),
                    })
                }
                // Deleted while waiting, or evicted: ask again.
                None => thumbs.request(id, false),
                Some(Entry::Pending) => {}
            }
            match tokio::time::timeout_at(deadline, done.changed()).await {
                Ok(Ok(())) => continue,
                Ok(Err(_)) | Err(_) => return Ok(Thumbnail::Pending),
            }
        }
    }

    /// Renders scene `id`'s thumbnail on the pool, under a scheduler ticket of
    /// [`THUMBNAIL_PRIORITY`]; called on the thumbnail thread, which waits for it.
    fn render_thumbnail(&self, id: &str) -> Result<Vec<u8>, String> {
        let request = RenderRequest {
            width: THUMBNAIL_WIDTH,
            height: THUMBNAIL_HEIGHT,
            integrator: Integrator::Normals,
            ..RenderRequest::default()
        };
        let rt = &self.inner.runtime;
        let frame_at = |_time: Option<f64>, control: &crate::jobs::Control| {
            control
                .step(|| rt.block_on(self.geometry(id, Some(1), None)))?
                .map(|(geometry, cameras)| FrameInput {
                    geometry,
                    cameras,
                    // A normals render reads no material.
                    surfaces: None,
                })
                .map_err(|e| JobError::Geometry(e.to_string()))
        };
        // Background work: a thumbnail never takes a client's place in the bounded queue
        // nor a `--max-running` slot, and is never refused (at most one waits at a time).
        let ticket = self.engine().scheduler().background(THUMBNAIL_PRIORITY);
        let control = self.engine().control(CancelToken::new(), None, ticket);
        let mut png = None;
        self.engine()
            .render(&request, &[None], &frame_at, &control, &mut |_, bytes| {
                png = Some(bytes);
                Ok(())
            })
            .map_err(|e| e.to_string())?;
        png.ok_or_else(|| "the render produced no image".to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Thumbnails whose queue nobody works on (the receiver is kept alive).
    fn thumbs() -> (Thumbnails, mpsc::Receiver<String>) {
        let (tx, rx) = mpsc::channel();
        (Thumbnails::with_queue(tx), rx)
    }

    #[test]
    fn requests_reach_the_queue_once() {
        let (t, rx) = thumbs();
        t.request("a", false);
        t.request("a", false);
        assert_eq!(rx.try_recv().unwrap(), "a");
        assert!(rx.try_recv().is_err(), "a pending thumbnail is queued once");
    }

    #[test]
    fn a_dead_worker_fails_the_thumbnail() {
        let (t, rx) = thumbs();
        drop(rx);
        t.request("a", false);
        assert!(matches!(t.get("a"), Some(Entry::Failed(_))));
    }

    #[test]
    fn pending_then_ready_then_forgotten() {
        let (t, _rx) = thumbs();
        t.request("a", false);
        assert!(matches!(t.get("a"), Some(Entry::Pending)));
        t.finish("a", Ok(vec![1, 2, 3]));
        assert!(matches!(t.get("a"), Some(Entry::Ready(b)) if b.as_ref() == [1, 2, 3]));
        // A second request of a ready thumbnail changes nothing.
        t.request("a", true);
        assert!(matches!(t.get("a"), Some(Entry::Ready(_))));
        t.forget("a");
        assert!(t.get("a").is_none());
        assert_eq!(t.lock().bytes, 0);
    }

    #[test]
    fn a_deleted_scene_keeps_no_late_thumbnail() {
        let (t, _rx) = thumbs();
        t.request("a", false);
        t.forget("a");
        t.finish("a", Ok(vec![1]));
        assert!(t.get("a").is_none());
    }

    #[test]
    fn failures_are_kept_until_a_new_upload() {
        let (t, _rx) = thumbs();
        t.request("a", false);
        t.finish("a", Err("no triangles".into()));
        t.request("a", false);
        assert!(matches!(t.get("a"), Some(Entry::Failed(_))));
        t.request("a", true);
        assert!(matches!(t.get("a"), Some(Entry::Pending)));
    }

    #[test]
    fn the_oldest_are_evicted_past_the_budget() {
        let (t, _rx) = thumbs();
        let big = KEEP_BYTES / 2 + 1;
        for id in ["a", "b", "c"] {
            t.request(id, false);
            t.finish(id, Ok(vec![0; big]));
        }
        assert!(t.get("a").is_none());
        assert!(t.get("b").is_none());
        assert!(matches!(t.get("c"), Some(Entry::Ready(_))));
        assert_eq!(t.lock().bytes, big);
    }
}
