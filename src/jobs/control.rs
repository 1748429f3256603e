//! What drives a running job from outside: a cancellation token, a progress sink and the
//! scheduler's lease. The renderer calls [`Control::checkpoint`] between waves; that is
//! where a job notices cancellation, reports progress and lets waiting work of higher
//! priority run before its next wave.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use super::sched::Ticket;
use super::JobError;

/// A flag that asks a job to stop; cloned into everyone who may cancel it.
#[derive(Clone, Debug, Default)]
pub struct CancelToken(Arc<AtomicBool>);

impl CancelToken {
    /// A token not yet cancelled.
    pub fn new() -> CancelToken {
        CancelToken::default()
    }

    /// Asks the job to stop at its next checkpoint.
    pub fn cancel(&self) {
        self.0.store(true, Ordering::Release);
    }

    /// Whether cancellation was asked for.
    pub fn is_cancelled(&self) -> bool {
        self.0.load(Ordering::Acquire)
    }
}

/// A progress sink: called with the fraction done, from 0 to 1.
pub type ProgressFn = Arc<dyn Fn(f64) + Send + Sync>;

/// The hooks of one job, and the pool its steps run on.
pub struct Control {
    cancel: CancelToken,
    progress: Option<ProgressFn>,
    /// The job's place in the scheduler, for its leases.
    ticket: Option<Ticket>,
    pool: Arc<rayon::ThreadPool>,
    /// Called once, when the job's first step gets the pool (it leaves the queue).
    on_start: std::sync::Mutex<Option<Box<dyn FnOnce() + Send>>>,
}

impl Control {
    /// A job on `pool` with these hooks, scheduled under `ticket` (none: it runs alone, as
    /// on the command line).
    pub fn new(
        pool: Arc<rayon::ThreadPool>,
        cancel: CancelToken,
        progress: Option<ProgressFn>,
        ticket: Option<Ticket>,
    ) -> Control {
        Control {
            cancel,
            progress,
            ticket,
            pool,
            on_start: std::sync::Mutex::new(None),
        }
    }

    /// Calls `f` once, when the job's first step gets the pool.
    pub fn on_start(self, f: impl FnOnce() + Send + 'static) -> Control {
        *self.on_start.lock().unwrap_or_else(|e| e.into_inner()) = Some(Box::new(f));
        self
    }

    /// The cancellation token.
    pub fn cancel_token(&self) -> &CancelToken {
        &self.cancel
    }

    /// Reports `fraction` done (clamped to 0..1).
    pub fn progress(&self, fraction: f64) {
        // A cancelled job's progress stays where it was when it was cancelled: the waves
        // that end after that are not reported, so the cancelled state, which records the
        // progress read after cancelling, is never behind an event sent before it.
        if self.cancel.is_cancelled() {
            return;
        }
        if let Some(p) = &self.progress {
            p(fraction.clamp(0.0, 1.0));
        }
    }

    /// Fails with [`JobError::Cancelled`] once cancellation was asked for.
    pub fn check(&self) -> Result<(), JobError> {
        if self.cancel.is_cancelled() {
            Err(JobError::Cancelled)
        } else {
            Ok(())
        }
    }

    /// Runs one step of CPU work on the pool under the scheduler's lease: waits until no
    /// waiting work outranks this job, then holds the pool for `step`. Cancellation is
    /// checked before the wait and after it.
    pub fn step<T: Send>(&self, step: impl FnOnce() -> T + Send) -> Result<T, JobError> {
        self.check()?;
        let _lease = match &self.ticket {
            Some(ticket) => Some(ticket.lease(&self.cancel)?),
            None => None,
        };
        self.check()?;
        if let Some(f) = self
            .on_start
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .take()
        {
            f();
        }
        // The caller's span (a service job's `job` span) goes with the step to the pool
        // thread, so that what the step logs names its job.
        let span = tracing::Span::current();
        Ok(self.pool.install(move || span.in_scope(step)))
    }

    /// Seconds the next wave should take: short while other work waits or interactive
    /// requests arrived recently (latency), long otherwise (DACRT and throughput like large
    /// batches).
    pub fn wave_seconds(&self) -> f64 {
        match &self.ticket {
            Some(ticket) => ticket.scheduler().wave_seconds(),
            None => f64::INFINITY,
        }
    }
}

impl crate::render::Waves for Control {
    type Error = JobError;

    fn run_wave(&self, wave: &mut (dyn FnMut() + Send)) -> Result<(), JobError> {
        self.step(wave)
    }

    fn wave_seconds(&self) -> f64 {
        Control::wave_seconds(self)
    }

    fn progress(&self, fraction: f64) {
        Control::progress(self, fraction)
    }
}
