//! The scheduler: a bounded queue ordered by priority, and the lease that hands the rayon
//! pool to one step of one job at a time.
//!
//! Every job is admitted with a [`Ticket`] (priority 0–100 for jobs, [`SYNC_PRIORITY`] for
//! synchronous traces, which wait ahead of everything; first come first served within a
//! priority). Past `max_queued` admitted-but-not-started jobs, admission fails and the
//! caller answers `503`. A job's CPU work runs in steps (a trace is one step; a render one
//! step per wave), each under a [`Lease`]: the lease goes to the waiting ticket that ranks
//! first, so a small trace that arrives during a render runs as soon as the render's
//! current wave ends. Each step uses the whole pool; serialising steps keeps caches warm
//! and answers the ranking exactly, where letting rayon interleave two jobs would make
//! both slow.
//!
//! Waves are sized in seconds ([`Scheduler::wave_seconds`]): short while anything waits or
//! an interactive request arrived within the last second (latency), long otherwise (DACRT
//! and throughput like large batches).
//!
//! A job that yields between waves keeps what it has made so far (a render's image and
//! its paths), so preemption has a memory price: left alone, a client sending renders of
//! ever higher priority would have every one of them started at once. At most
//! `max_running` jobs may therefore have started and not finished; a job past that waits
//! for one to end, whatever its priority, while the started ones keep taking turns by
//! theirs. Synchronous traces are not counted: the request-body budget bounds what they
//! hold, and a waiting small request must still win the next wave.
//!
//! Between two of its steps a job holds no lease and is not waiting for one, for the few
//! microseconds it takes to ask again (or a few milliseconds after admission, or after a
//! restart re-admits it, before its thread first asks). A lower-ranked ticket waiting
//! then would take the pool and keep taking turns beside it: a priority-10 render ran
//! beside a priority-50 one (session 31's review). So a ticket that is absent — admitted
//! or between steps, and able to start — keeps the pool from the tickets it outranks for
//! [`ABSENT_GRACE`] after it went absent; a job that stays away longer (it is writing its
//! result, say) leaves the pool to them. Among synchronous traces (one priority) the
//! earlier does not hold the pool back from the later, and after each step a trace goes
//! behind those that wait: their steps take turns, so a small trace behind a large one
//! waits for one of its segments or parts, not for the whole batch. Background work (a thumbnail, small) is not held
//! back: it may still run between another job's steps.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use super::{CancelToken, JobError};

/// The priority of synchronous traces: above every job's 0–100.
pub const SYNC_PRIORITY: u16 = 1000;

/// Seconds a wave should take while other work waits (the latency a waiting small request
/// sees is about one wave).
pub const SHORT_WAVE_SECONDS: f64 = 0.01;
/// Seconds a wave may take when nothing else waits.
pub const LONG_WAVE_SECONDS: f64 = 0.5;

/// How long after an interactive request waves stay short.
const INTERACTIVE_WINDOW: Duration = Duration::from_secs(1);

/// How long an absent ticket (admitted, or between steps) keeps the pool from the tickets
/// it outranks (see the module docs).
pub const ABSENT_GRACE: Duration = Duration::from_millis(5);

/// How often a waiting ticket looks at its cancellation.
const POLL: Duration = Duration::from_millis(20);

/// Rank in the lease queue: higher priority first, then earlier admission.
type Rank = (std::cmp::Reverse<u16>, u64);

#[derive(Default)]
struct State {
    /// Whether a step holds the pool.
    held: bool,
    /// Tickets waiting for the lease, with whether each may take it when it ranks first
    /// (see [`Waiter`]).
    waiting: BTreeMap<Rank, Waiter>,
    /// Tickets neither waiting nor holding the lease (admitted and not yet asking, or
    /// between steps), with when they went absent and how they would wait.
    absent: BTreeMap<Rank, (Instant, Waiter)>,
    /// Admitted tickets that have not held a lease yet.
    queued: usize,
    /// Tickets that have held a lease and are not finished.
    running: usize,
    /// Those of `running` that count against `max_running` (every job but synchronous
    /// traces and background work).
    running_counted: usize,
    /// Those of `queued` that are background work ([`Scheduler::background`]), which takes
    /// no client's place.
    queued_background: usize,
    next_seq: u64,
    shutting_down: bool,
    last_interactive: Option<Instant>,
}

/// What the lease needs to know of a waiting ticket.
#[derive(Clone, Copy)]
struct Waiter {
    /// It has held a lease before (its job is under way).
    started: bool,
    /// It counts against `max_running` once started.
    counted: bool,
}

/// The queue and the lease (see the module docs).
pub struct Scheduler {
    state: Mutex<State>,
    wake: Condvar,
    max_queued: usize,
    max_running: usize,
}

impl Scheduler {
    /// A scheduler that admits at most `max_queued` jobs waiting to start and lets at most
    /// `max_running` (at least 1) have started and not finished, synchronous traces aside.
    pub fn new(max_queued: usize, max_running: usize) -> Arc<Scheduler> {
        Arc::new(Scheduler {
            state: Mutex::new(State::default()),
            wake: Condvar::new(),
            max_queued,
            max_running: max_running.max(1),
        })
    }

    /// Whether `w` may take the lease now if it ranks first among those that may.
    fn may_start(&self, s: &State, w: Waiter) -> bool {
        w.started || !w.counted || s.running_counted < self.max_running
    }

    /// The waiting ticket that the free pool goes to: the first by rank among those that
    /// may take it.
    fn next(&self, s: &State) -> Option<Rank> {
        s.waiting
            .iter()
            .find(|(_, w)| self.may_start(s, **w))
            .map(|(r, _)| *r)
    }

    /// How much longer a ticket that outranks `rank`, absent for less than
    /// [`ABSENT_GRACE`] and able to start, keeps the pool from `rank` (`None`: none does).
    fn held_back(&self, s: &State, rank: Rank) -> Option<Duration> {
        s.absent
            .range(..rank)
            // Synchronous traces interleave their steps (a 1K trace behind a streamed 4M
            // one waits one segment, not the whole batch); jobs keep first come, first
            // served.
            .filter(|(r, _)| r.0 != rank.0 || rank.0 .0 != SYNC_PRIORITY)
            .filter(|(_, (_, w))| self.may_start(s, *w))
            .filter_map(|(_, (since, _))| ABSENT_GRACE.checked_sub(since.elapsed()))
            .filter(|left| !left.is_zero())
            .min()
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // A panic while holding this lock cannot leave the counters half-updated (every
        // update is a single statement), so a poisoned lock is still consistent.
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Admits a job of `priority` (0–100, or [`SYNC_PRIORITY`]); `interactive` marks a
    /// request a client waits for, which shortens running jobs' waves for a while.
    pub fn admit(self: &Arc<Self>, priority: u16, interactive: bool) -> Result<Ticket, JobError> {
        let mut s = self.lock();
        self.room(&s, priority == SYNC_PRIORITY)?;
        if interactive {
            s.last_interactive = Some(Instant::now());
        }
        let ticket = self.place(&mut s, priority, false);
        ticket.went_absent(&mut s);
        Ok(ticket)
    }

    /// A new ticket's place in the queue, last in its priority's order (neither absent nor
    /// waiting yet).
    fn place(self: &Arc<Self>, s: &mut State, priority: u16, background: bool) -> Ticket {
        s.queued += 1;
        s.queued_background += usize::from(background);
        s.next_seq += 1;
        Ticket {
            sched: Arc::clone(self),
            priority,
            seq: AtomicU64::new(s.next_seq),
            started: AtomicBool::new(false),
            background,
        }
    }

    /// Takes a synchronous trace's place in the queue now for work that starts later (a
    /// frame's trace, whose place is taken before its positions are recorded and held
    /// while its rays arrive): admitted as [`Scheduler::admit`] admits, but not absent and
    /// not interactive until [`Ticket::arrive`]. Absent at once, it held the pool back
    /// from every job it outranks for [`ABSENT_GRACE`] while nothing was about to ask for
    /// it (the frame still writing its version, its rays still arriving: session 36's
    /// review).
    pub fn reserve(self: &Arc<Self>) -> Result<Ticket, JobError> {
        let mut s = self.lock();
        self.room(&s, true)?;
        Ok(self.place(&mut s, SYNC_PRIORITY, false))
    }

    /// Whether [`Scheduler::admit`] would admit a job now, without taking a place: a
    /// request whose place is taken only after its body has arrived is refused at once
    /// when the queue is already full or the service is shutting down.
    pub fn has_room(&self) -> Result<(), JobError> {
        self.room(&self.lock(), false)
    }

    /// Why a job could not be admitted in state `s`, if it could not. A synchronous trace
    /// (`sync`) is admitted while shutting down: it is a request in flight, whose body
    /// began before the signal ([`Scheduler::has_room`] refused it at its head otherwise),
    /// and in-flight requests get the grace period.
    fn room(&self, s: &State, sync: bool) -> Result<(), JobError> {
        if s.shutting_down && !sync {
            return Err(JobError::ShuttingDown);
        }
        let waiting = s.queued - s.queued_background;
        if waiting >= self.max_queued {
            return Err(JobError::QueueFull(waiting));
        }
        Ok(())
    }

    /// Re-admits a job found queued or running when the process started (recovery): it
    /// bypasses the bound, since refusing it would lose acknowledged work, and then waits
    /// and runs as any job.
    pub fn readmit(self: &Arc<Self>, priority: u16) -> Ticket {
        self.ticket(priority, false)
    }

    /// Admits background work of the server's own (a thumbnail): it bypasses the queue's
    /// bound and takes no client's place in it, and does not count against
    /// `max_running` (it is small, and at most one waits at a time).
    pub fn background(self: &Arc<Self>, priority: u16) -> Ticket {
        self.ticket(priority, true)
    }

    fn ticket(self: &Arc<Self>, priority: u16, background: bool) -> Ticket {
        let mut s = self.lock();
        let ticket = self.place(&mut s, priority, background);
        ticket.went_absent(&mut s);
        ticket
    }

    /// Waits until `ticket` ranks first among the waiting tickets that may take the pool
    /// (a job that has not started may not while `max_running` have), and the pool is
    /// free, then holds the pool until the lease is dropped. Fails if `cancel` fires while
    /// waiting.
    pub fn lease<'a>(
        &'a self,
        ticket: &'a Ticket,
        cancel: &CancelToken,
    ) -> Result<Lease<'a>, JobError> {
        let mut s = self.lock();
        let waiter = Waiter {
            started: ticket.started.load(Ordering::Acquire),
            counted: ticket.counted(),
        };
        let rank = ticket.rank();
        s.absent.remove(&rank);
        s.waiting.insert(rank, waiter);
        loop {
            // Once shutting down, no job starts, even on a free pool: a queued one stays
            // queued for the next start, and the grace period is the running ones' alone
            // (and the requests' in flight: a synchronous trace still runs).
            if s.shutting_down
                && !ticket.started.load(Ordering::Acquire)
                && ticket.priority != SYNC_PRIORITY
            {
                s.waiting.remove(&rank);
                self.wake.notify_all();
                return Err(JobError::ShuttingDown);
            }
            // Background work (small) still takes the pool between another job's steps.
            let held_back = if ticket.background {
                None
            } else {
                self.held_back(&s, rank)
            };
            if !s.held && self.next(&s) == Some(rank) && held_back.is_none() {
                s.waiting.remove(&rank);
                s.held = true;
                if !ticket.started.swap(true, Ordering::AcqRel) {
                    s.queued -= 1;
                    s.queued_background -= usize::from(ticket.background);
                    s.running += 1;
                    if ticket.counted() {
                        s.running_counted += 1;
                    }
                }
                return Ok(Lease {
                    sched: self,
                    ticket,
                });
            }
            if cancel.is_cancelled() {
                s.waiting.remove(&rank);
                // Someone else may rank first now.
                self.wake.notify_all();
                return Err(JobError::Cancelled);
            }
            // Cancellation does not notify; poll it while waiting (and look again when an
            // absent ticket's hold ends).
            let wait = held_back.map_or(POLL, |d| d.min(POLL));
            s = self
                .wake
                .wait_timeout(s, wait)
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
    }

    /// Seconds the next wave of a running job should take.
    pub fn wave_seconds(&self) -> f64 {
        let s = self.lock();
        let recent = s
            .last_interactive
            .is_some_and(|t| t.elapsed() < INTERACTIVE_WINDOW);
        if self.next(&s).is_some() || recent {
            SHORT_WAVE_SECONDS
        } else {
            LONG_WAVE_SECONDS
        }
    }

    /// Admitted jobs that have not started.
    pub fn queued(&self) -> usize {
        self.lock().queued
    }

    /// Jobs that have started and not finished.
    pub fn running(&self) -> usize {
        self.lock().running
    }

    /// Wakes every ticket waiting for the pool, so that one whose job was cancelled
    /// (which does not notify by itself) gives up its place at once.
    pub fn nudge(&self) {
        self.wake.notify_all();
    }

    /// Refuses new work from now on ([`JobError::ShuttingDown`]).
    pub fn shut_down(&self) {
        self.lock().shutting_down = true;
        // Waiting jobs that never started give up their places now.
        self.wake.notify_all();
    }
}

/// A job's place in the scheduler; dropping it ends the job.
pub struct Ticket {
    sched: Arc<Scheduler>,
    priority: u16,
    /// Its place among tickets of its priority: its admission's, and for a synchronous
    /// trace renewed after each step (see [`Lease`]'s drop). Changed only under the
    /// scheduler's lock.
    seq: AtomicU64,
    started: AtomicBool,
    /// Background work ([`Scheduler::background`]).
    background: bool,
}

impl Ticket {
    /// Its rank in the lease queue.
    fn rank(&self) -> Rank {
        (
            std::cmp::Reverse(self.priority),
            self.seq.load(Ordering::Relaxed),
        )
    }

    /// Whether it counts against `max_running`: every job but a synchronous trace and
    /// background work.
    fn counted(&self) -> bool {
        self.priority != SYNC_PRIORITY && !self.background
    }

    /// The scheduler that admitted this ticket.
    pub fn scheduler(&self) -> &Arc<Scheduler> {
        &self.sched
    }

    /// Waits for the pool (see [`Scheduler::lease`]).
    pub fn lease(&self, cancel: &CancelToken) -> Result<Lease<'_>, JobError> {
        self.sched.lease(self, cancel)
    }

    /// Records that the ticket holds no lease and is not waiting for one, from now.
    /// A reserved ticket ([`Scheduler::reserve`]) whose work is about to ask for the pool:
    /// it takes a new place in its priority's order (behind the synchronous traces that
    /// arrived while it waited, as if admitted now), marks the service interactive and
    /// is absent from now, as a ticket just admitted is.
    pub fn arrive(&self) {
        let mut s = self.sched.lock();
        s.next_seq += 1;
        self.seq.store(s.next_seq, Ordering::Relaxed);
        s.last_interactive = Some(Instant::now());
        self.went_absent(&mut s);
    }

    fn went_absent(&self, s: &mut State) {
        let waiter = Waiter {
            started: self.started.load(Ordering::Acquire),
            counted: self.counted(),
        };
        s.absent.insert(self.rank(), (Instant::now(), waiter));
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        let mut s = self.sched.lock();
        if s.absent.remove(&self.rank()).is_some() {
            // Tickets it outranked need not wait out its grace.
            self.sched.wake.notify_all();
        }
        if self.started.load(Ordering::Acquire) {
            s.running -= 1;
            if self.counted() {
                s.running_counted -= 1;
                // A job held back by `max_running` may start now.
                self.sched.wake.notify_all();
            }
        } else {
            s.queued -= 1;
            s.queued_background -= usize::from(self.background);
        }
    }
}

/// The pool, held by one step; dropping it hands the pool to the next waiting ticket.
pub struct Lease<'a> {
    sched: &'a Scheduler,
    ticket: &'a Ticket,
}

impl Drop for Lease<'_> {
    fn drop(&mut self) {
        let mut s = self.sched.lock();
        s.held = false;
        if self.ticket.priority == SYNC_PRIORITY {
            // Synchronous traces take turns: one that has had a step goes behind those
            // that wait. By admission alone, the earlier trace's thread, asking again at
            // once, took the pool before the woken later one could (a 1K trace waited
            // 3.6 s between a 16M-ray trace's parts, session 34).
            s.next_seq += 1;
            self.ticket.seq.store(s.next_seq, Ordering::Relaxed);
        }
        self.ticket.went_absent(&mut s);
        self.sched.wake.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_queue_is_bounded_and_tickets_free_their_place() {
        let s = Scheduler::new(2, 4);
        assert!(s.has_room().is_ok());
        let a = s.admit(50, false).unwrap();
        let _b = s.admit(50, false).unwrap();
        assert!(matches!(s.admit(50, false), Err(JobError::QueueFull(2))));
        assert!(matches!(s.has_room(), Err(JobError::QueueFull(2))));
        drop(a);
        assert!(s.has_room().is_ok());
        assert!(s.admit(50, false).is_ok());
        s.shut_down();
        assert!(matches!(s.has_room(), Err(JobError::ShuttingDown)));
    }

    /// A reserved synchronous trace (a frame's) holds its place in the queue but keeps no
    /// job from the pool until it arrives (session 36's review: admitted at once, it held
    /// every render back for `ABSENT_GRACE` while its frame was still writing).
    #[test]
    fn a_reserved_trace_holds_a_place_but_not_the_pool() {
        let s = Scheduler::new(2, 4);
        let place = s.reserve().unwrap();
        let job = s.admit(50, false).unwrap();
        assert_eq!(s.queued(), 2);
        assert!(matches!(s.admit(50, false), Err(JobError::QueueFull(2))));
        assert!(s.held_back(&s.lock(), job.rank()).is_none());
        place.arrive();
        assert!(s.held_back(&s.lock(), job.rank()).is_some());
        assert!(s.lock().last_interactive.is_some());
        drop(place);
        assert_eq!(s.queued(), 1);
        assert!(s.held_back(&s.lock(), job.rank()).is_none());
        s.shut_down();
        assert!(s.reserve().is_ok(), "a frame in flight may still trace");
    }

    #[test]
    fn a_started_job_leaves_the_queue() {
        let s = Scheduler::new(1, 4);
        let a = s.admit(50, false).unwrap();
        drop(a.lease(&CancelToken::new()).unwrap());
        assert_eq!((s.queued(), s.running()), (0, 1));
        let _b = s.admit(50, false).unwrap();
        drop(a);
        assert_eq!((s.queued(), s.running()), (1, 0));
    }

    #[test]
    fn leases_go_by_priority_then_admission() {
        let s = Scheduler::new(16, 16);
        let holder = s.admit(10, false).unwrap();
        let lease = holder.lease(&CancelToken::new()).unwrap();
        let order = Arc::new(Mutex::new(Vec::new()));
        let mut threads = Vec::new();
        // Admitted in this order; they must run as 90, 50 (first), 50 (second), 10.
        for (name, p) in [("low", 10), ("mid1", 50), ("high", 90), ("mid2", 50)] {
            let t = s.admit(p, false).unwrap();
            let order = Arc::clone(&order);
            threads.push(std::thread::spawn(move || {
                let _l = t.lease(&CancelToken::new()).unwrap();
                order.lock().unwrap().push(name);
            }));
            // Let each thread reach the wait before the next is admitted.
            std::thread::sleep(Duration::from_millis(30));
        }
        drop(lease);
        for t in threads {
            t.join().unwrap();
        }
        assert_eq!(*order.lock().unwrap(), ["high", "mid1", "mid2", "low"]);
    }

    /// A job between two of its steps keeps the pool from the tickets it outranks (session
    /// 31's review: a priority-10 render took turns beside a priority-50 one).
    #[test]
    fn a_job_between_steps_keeps_the_pool_from_lower_ranks() {
        let s = Scheduler::new(16, 16);
        let high = s.admit(50, false).unwrap();
        let low = s.admit(10, false).unwrap();
        let steps = Arc::new(Mutex::new(Vec::new()));
        let lease = high.lease(&CancelToken::new()).unwrap();
        let log = Arc::clone(&steps);
        let waiter = std::thread::spawn(move || {
            let _l = low.lease(&CancelToken::new()).unwrap();
            log.lock().unwrap().push("low");
        });
        std::thread::sleep(Duration::from_millis(30));
        // Twenty waves of `high`, each asking again right after the last: `low` never
        // gets the pool between them.
        drop(lease);
        for _ in 0..20 {
            let _l = high.lease(&CancelToken::new()).unwrap();
            steps.lock().unwrap().push("high");
        }
        drop(high);
        waiter.join().unwrap();
        let steps = steps.lock().unwrap();
        assert_eq!(steps.last(), Some(&"low"), "{steps:?}");
    }

    /// Synchronous traces take turns whatever their admission: an earlier one that asks
    /// again right after its step goes behind a later one that waits (each of its steps
    /// then alternates with the later one's).
    #[test]
    fn synchronous_traces_take_turns() {
        let s = Scheduler::new(16, 16);
        let big = s.admit(SYNC_PRIORITY, true).unwrap();
        let small = s.admit(SYNC_PRIORITY, true).unwrap();
        let steps = Arc::new(Mutex::new(Vec::new()));
        let lease = big.lease(&CancelToken::new()).unwrap();
        let log = Arc::clone(&steps);
        let waiter = std::thread::spawn(move || {
            for _ in 0..3 {
                let _l = small.lease(&CancelToken::new()).unwrap();
                log.lock().unwrap().push("small");
            }
        });
        while s.lock().waiting.is_empty() {
            std::thread::sleep(Duration::from_millis(1));
        }
        drop(lease);
        for _ in 0..3 {
            let _l = big.lease(&CancelToken::new()).unwrap();
            steps.lock().unwrap().push("big");
            // Holding the pool a moment lets the other trace ask for it meanwhile.
            std::thread::sleep(Duration::from_millis(20));
        }
        waiter.join().unwrap();
        let steps = steps.lock().unwrap();
        assert_eq!(steps[0], "small", "{steps:?}");
        assert_eq!(steps[..4], ["small", "big", "small", "big"], "{steps:?}");
    }

    /// An absent ticket's hold ends: one that outranks a waiter but does not ask for the
    /// pool within the grace leaves it to the waiter.
    #[test]
    fn an_absent_ticket_holds_the_pool_back_only_briefly() {
        let s = Scheduler::new(16, 16);
        let _idle = s.admit(90, false).unwrap();
        let low = s.admit(10, false).unwrap();
        let t0 = Instant::now();
        drop(low.lease(&CancelToken::new()).unwrap());
        assert!(t0.elapsed() < Duration::from_secs(1));
    }

    #[test]
    fn a_cancelled_wait_returns() {
        let s = Scheduler::new(4, 4);
        let a = s.admit(50, false).unwrap();
        let _held = a.lease(&CancelToken::new()).unwrap();
        let b = s.admit(50, false).unwrap();
        let cancel = CancelToken::new();
        let c2 = cancel.clone();
        let waiter = std::thread::spawn(move || b.lease(&c2).map(|_| ()));
        std::thread::sleep(Duration::from_millis(50));
        cancel.cancel();
        assert!(matches!(waiter.join().unwrap(), Err(JobError::Cancelled)));
    }

    #[test]
    fn waves_shorten_while_work_waits() {
        let s = Scheduler::new(4, 4);
        assert_eq!(s.wave_seconds(), LONG_WAVE_SECONDS);
        let _t = s.admit(SYNC_PRIORITY, true).unwrap();
        assert_eq!(s.wave_seconds(), SHORT_WAVE_SECONDS);
    }

    #[test]
    fn started_jobs_are_bounded_whatever_the_priority_but_traces_are_not() {
        let s = Scheduler::new(8, 1);
        let low = s.admit(10, false).unwrap();
        drop(low.lease(&CancelToken::new()).unwrap());
        // `high` outranks `low` but may not start while `low` is under way.
        let high = s.admit(90, false).unwrap();
        let started = Arc::new(AtomicBool::new(false));
        let flag = Arc::clone(&started);
        let waiter = std::thread::spawn(move || {
            let _l = high.lease(&CancelToken::new()).unwrap();
            flag.store(true, Ordering::Release);
        });
        std::thread::sleep(Duration::from_millis(80));
        assert!(!started.load(Ordering::Acquire));
        assert_eq!(
            s.wave_seconds(),
            LONG_WAVE_SECONDS,
            "a held-back job shortens no wave"
        );
        // `low` keeps its turns, and a synchronous trace still takes the pool at once.
        drop(low.lease(&CancelToken::new()).unwrap());
        let sync = s.admit(SYNC_PRIORITY, false).unwrap();
        drop(sync.lease(&CancelToken::new()).unwrap());
        drop(sync);
        assert!(!started.load(Ordering::Acquire));
        assert_eq!((s.queued(), s.running()), (1, 1));
        // When `low` ends, `high` starts.
        drop(low);
        waiter.join().unwrap();
        assert!(started.load(Ordering::Acquire));
        assert_eq!((s.queued(), s.running()), (0, 0));
    }

    #[test]
    fn background_work_takes_no_place_and_no_running_slot() {
        let s = Scheduler::new(1, 1);
        let job = s.admit(50, false).unwrap();
        drop(job.lease(&CancelToken::new()).unwrap());
        let thumb = s.background(0);
        // The queue's one place is still free, and the thumbnail starts beside the job.
        let queued = s.admit(50, false).unwrap();
        drop(queued);
        drop(thumb.lease(&CancelToken::new()).unwrap());
        assert_eq!((s.queued(), s.running()), (0, 2));
        drop(thumb);
        assert!(s.has_room().is_ok());
    }

    #[test]
    fn shutting_down_refuses_work() {
        let s = Scheduler::new(4, 4);
        let queued = s.admit(50, false).unwrap();
        s.shut_down();
        assert!(matches!(s.admit(50, false), Err(JobError::ShuttingDown)));
        assert!(matches!(s.has_room(), Err(JobError::ShuttingDown)));
        assert!(matches!(
            queued.lease(&CancelToken::new()),
            Err(JobError::ShuttingDown)
        ));
        // A synchronous trace whose body was on the way at the signal still runs.
        let sync = s.admit(SYNC_PRIORITY, true).unwrap();
        drop(sync.lease(&CancelToken::new()).unwrap());
    }
}
