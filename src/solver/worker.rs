//! The background `LDLᵀ` worker of the `Async` preconditioner (see the
//! module docs of [`super`], "Asynchronous refresh").

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Instant;

use crossbeam::channel::{Receiver, Sender, TryRecvError, bounded};

use super::columns::{ColumnCache, ColumnPrefetch, FactorKey};
use super::ldlt::{LdltFactor, LdltSymbolic};
use crate::error::{Result, SoftTissueError};
use crate::fem::assembly::BlockCsr;
use crate::math::Mat3;
use std::panic::{AssertUnwindSafe, catch_unwind};

pub(super) struct Job {
    pub(super) values: Vec<Mat3>,
    pub(super) rotations: Vec<Mat3>,
    pub(super) factor: LdltFactor,
    pub(super) step: u64,
    /// Nodes whose columns to precompute with the new factor (may be empty).
    pub(super) hint: Vec<u32>,
    pub(super) columns: Option<ColumnCache>,
}

pub(super) struct Done {
    pub(super) values: Vec<Mat3>,
    pub(super) rotations: Vec<Mat3>,
    pub(super) factor: LdltFactor,
    pub(super) step: u64,
    pub(super) result: Result<()>,
    pub(super) seconds: f64,
    pub(super) hint: Vec<u32>,
    /// The precomputed columns (when the job had a hint and the factorization succeeded).
    pub(super) columns: Option<ColumnCache>,
}

/// Locks `m`; a panic elsewhere while it was held leaves the data usable.
fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Factorizations running in background workers, all bodies together.
static IN_FLIGHT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// Factorizers waiting for a background slot, oldest first, with the time
/// each last asked.
static WAITING: std::sync::Mutex<std::collections::VecDeque<(u64, Instant)>> =
    std::sync::Mutex::new(std::collections::VecDeque::new());
/// A waiting factorizer that has not asked for this long is dropped from the
/// queue: its body stopped stepping (paused, failed, kept but unused), and
/// it must not hold up the bodies behind it. It queues again when it asks.
const WAITING_STALE: std::time::Duration = std::time::Duration::from_millis(250);
/// Identity of each [`AsyncFactorizer`] in [`WAITING`].
static NEXT_ID: AtomicU64 = AtomicU64::new(0);

/// How many background factorizations may run at once: one core is left to the
/// stepping thread (at least one worker). Asked of the OS once.
fn max_in_flight() -> usize {
    static LIMIT: std::sync::OnceLock<usize> = std::sync::OnceLock::new();
    *LIMIT.get_or_init(|| {
        std::thread::available_parallelism()
            .map(|n| n.get().saturating_sub(1))
            .unwrap_or(1)
            .max(1)
    })
}

/// Background `LDLᵀ` worker (see the module docs).
pub struct AsyncFactorizer {
    id: u64,
    tx: Option<Sender<Job>>,
    rx: Receiver<Done>,
    handle: Option<JoinHandle<()>>,
    alive: Arc<AtomicBool>,
    /// Test hook: the next job panics.
    fail: Arc<AtomicBool>,
    /// Test hook: the thread exits at its next job.
    stop: Arc<AtomicBool>,
    /// Test hook: microseconds each job waits before it factorizes.
    delay: Arc<AtomicU64>,
    in_flight: bool,
    submitted_step: u64,
    pub(super) spare: Option<(Vec<Mat3>, Vec<Mat3>, LdltFactor)>,
    pub(super) hint: Vec<u32>,
}

impl std::fmt::Debug for AsyncFactorizer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AsyncFactorizer")
            .field("in_flight", &self.in_flight)
            .finish()
    }
}

impl AsyncFactorizer {
    /// Starts a worker for matrices over `pattern` with analysis `symbolic`.
    pub fn new(a: &BlockCsr, symbolic: &Arc<LdltSymbolic>) -> Self {
        let (tx, job_rx) = bounded::<Job>(1);
        let (done_tx, rx) = bounded::<Done>(1);
        let alive = Arc::new(AtomicBool::new(true));
        let pattern = Arc::clone(&a.pattern);
        let sym = Arc::clone(symbolic);
        let alive_w = Arc::clone(&alive);
        let fail = Arc::new(AtomicBool::new(false));
        let fail_w = Arc::clone(&fail);
        let stop = Arc::new(AtomicBool::new(false));
        let stop_w = Arc::clone(&stop);
        let delay = Arc::new(AtomicU64::new(0));
        let delay_w = Arc::clone(&delay);
        let handle = std::thread::Builder::new()
            .name("soft-tissue-ldlt".into())
            .spawn(move || {
                let mut work = Vec::with_capacity(sym.n);
                let mut mat = BlockCsr {
                    pattern,
                    values: Vec::new(),
                };
                while let Ok(mut job) = job_rx.recv() {
                    if stop_w.load(Ordering::SeqCst) {
                        // Exit as a dead thread would, but give the slot back.
                        IN_FLIGHT.fetch_sub(1, Ordering::SeqCst);
                        break;
                    }
                    let t0 = Instant::now();
                    mat.values = std::mem::take(&mut job.values);
                    // A panic in the factorization is caught: the slot is
                    // released below and the job comes back as an error, so the
                    // body keeps its factor and the other bodies keep their turns.
                    let outcome = catch_unwind(AssertUnwindSafe(|| {
                        if fail_w.swap(false, Ordering::SeqCst) {
                            panic!("injected by AsyncFactorizer::inject_panic");
                        }
                        let us = delay_w.load(Ordering::Relaxed);
                        if us > 0 {
                            std::thread::sleep(std::time::Duration::from_micros(us));
                        }
                        let result = sym.factorize(&mat, &mut job.factor, &mut work);
                        if result.is_ok() {
                            // The preconditioner solves with `L` in half
                            // precision, the contact correction in single
                            // (see the module docs of `super`).
                            job.factor.round_to_single_and_half();
                        }
                        // The compliance's node columns of the new factor, here
                        // rather than on the stepping thread.
                        // (A job carries a cache only when it has a hint.)
                        if let (Ok(()), Some(c)) = (&result, job.columns.as_mut()) {
                            c.precompute(&job.factor, FactorKey::Preconditioner(0), &job.hint);
                        }
                        result
                    }));
                    let result = outcome.unwrap_or_else(|p| {
                        let msg = p
                            .downcast_ref::<&str>()
                            .map(|s| s.to_string())
                            .or_else(|| p.downcast_ref::<String>().cloned())
                            .unwrap_or_else(|| "unknown panic".into());
                        work.clear();
                        Err(SoftTissueError::WorkerPanic(msg))
                    });
                    IN_FLIGHT.fetch_sub(1, Ordering::SeqCst);
                    let done = Done {
                        values: std::mem::take(&mut mat.values),
                        rotations: job.rotations,
                        factor: job.factor,
                        step: job.step,
                        result,
                        seconds: t0.elapsed().as_secs_f64(),
                        hint: job.hint,
                        columns: job.columns,
                    };
                    if done_tx.send(done).is_err() {
                        break;
                    }
                }
                alive_w.store(false, Ordering::SeqCst);
            })
            .ok();
        if handle.is_none() {
            // No thread: the preconditioner refreshes on the stepping thread.
            alive.store(false, Ordering::SeqCst);
        }
        let spare = Some((
            a.values.clone(),
            vec![Mat3::identity(); a.n()],
            symbolic.alloc_factor(),
        ));
        Self {
            id: NEXT_ID.fetch_add(1, Ordering::Relaxed),
            tx: Some(tx),
            rx,
            handle,
            alive,
            fail,
            stop,
            delay,
            in_flight: false,
            submitted_step: 0,
            spare,
            hint: Vec::new(),
        }
    }

    /// Whether the worker thread runs (false if it could not be started or
    /// has exited).
    pub fn is_alive(&self) -> bool {
        self.alive.load(Ordering::SeqCst)
    }

    /// Test hook: makes the next background factorization panic, to exercise
    /// the recovery (the slot is released, the error reported, the body keeps
    /// its factor).
    #[doc(hidden)]
    pub fn inject_panic(&self) {
        self.fail.store(true, Ordering::SeqCst);
    }

    /// Test hook: the worker thread exits at its next job, as a thread that
    /// died or could not be started leaves the preconditioner (it then
    /// refreshes on the stepping thread).
    #[doc(hidden)]
    pub fn inject_stop(&self) {
        self.stop.store(true, Ordering::SeqCst);
    }

    /// Test hook: every later job waits `delay` before it factorizes, as a
    /// large matrix's factorization would take that long.
    #[doc(hidden)]
    pub fn inject_delay(&self, delay: std::time::Duration) {
        let us = u64::try_from(delay.as_micros()).unwrap_or(u64::MAX);
        self.delay.store(us, Ordering::Relaxed);
    }

    /// A flag that turns false once the worker thread has exited.
    pub fn alive_flag(&self) -> Arc<AtomicBool> {
        Arc::clone(&self.alive)
    }

    /// Whether a factorization is running.
    pub fn in_flight(&self) -> bool {
        self.in_flight
    }

    /// Step of the matrix the running (or last) factorization was handed.
    pub fn submitted_step(&self) -> u64 {
        self.submitted_step
    }

    pub(super) fn try_take(&mut self, block: bool) -> Option<Done> {
        if !self.in_flight {
            return None;
        }
        // A closed channel (the thread has exited) ends the job as surely as
        // a result does: otherwise the factorizer would wait on it forever
        // and never hand over, nor let the fallback refresh.
        let (got, over) = if block {
            match self.rx.recv() {
                Ok(d) => (Some(d), true),
                Err(_) => (None, true),
            }
        } else {
            match self.rx.try_recv() {
                Ok(d) => (Some(d), true),
                Err(TryRecvError::Empty) => (None, false),
                Err(TryRecvError::Disconnected) => (None, true),
            }
        };
        if over {
            self.in_flight = false;
        }
        got
    }

    pub(super) fn submit(
        &mut self,
        a: &BlockCsr,
        rotations: &[Mat3],
        step: u64,
        prefetch: &mut ColumnPrefetch,
        queue: bool,
    ) {
        if self.in_flight {
            return;
        }
        // Share the machine: with several bodies, at most `cores − 1` factorizations run
        // at once; the others queue and hand over their matrix when their turn comes.
        // Without `queue` (`AsyncLagged`, whose factor must be of the step it
        // was asked at, whatever the other bodies do) the job goes out now and
        // only counts towards the others' limit.
        // (A factorizer never changes kind: a body that switches gets a new
        // one, and the old one leaves the queue when dropped.)
        if !queue {
            IN_FLIGHT.fetch_add(1, Ordering::SeqCst);
        } else {
            let limit = max_in_flight();
            let mut waiting = lock(&WAITING);
            let now = Instant::now();
            let id = self.id;
            waiting.retain(|&(w, t)| w == id || now.duration_since(t) < WAITING_STALE);
            if let Some(e) = waiting.iter_mut().find(|e| e.0 == id) {
                e.1 = now;
            }
            let first = waiting.front().is_none_or(|&(w, _)| w == id);
            let got = first
                && IN_FLIGHT
                    .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| {
                        (n < limit).then_some(n + 1)
                    })
                    .is_ok();
            if !got {
                if !waiting.iter().any(|e| e.0 == id) {
                    waiting.push_back((id, now));
                }
                return;
            }
            if waiting.front().map(|e| e.0) == Some(id) {
                waiting.pop_front();
            }
        }
        let (Some(tx), Some((mut values, mut rots, factor))) = (&self.tx, self.spare.take()) else {
            // Nothing to send with: give the slot back.
            IN_FLIGHT.fetch_sub(1, Ordering::SeqCst);
            return;
        };
        values.copy_from_slice(&a.values);
        rots.copy_from_slice(rotations);
        let mut hint = std::mem::take(&mut self.hint);
        hint.clear();
        hint.extend_from_slice(&prefetch.hint);
        let columns = if hint.is_empty() {
            None
        } else {
            Some(prefetch.spare.take().unwrap_or_default())
        };
        let job = Job {
            values,
            rotations: rots,
            factor,
            step,
            hint,
            columns,
        };
        if tx.send(job).is_ok() {
            self.in_flight = true;
            self.submitted_step = step;
        } else {
            IN_FLIGHT.fetch_sub(1, Ordering::SeqCst);
        }
    }
}

impl Drop for AsyncFactorizer {
    fn drop(&mut self) {
        lock(&WAITING).retain(|&(w, _)| w != self.id);
        self.tx = None;
        // Drain a finished job so the worker is not stuck on a full channel.
        while self.rx.try_recv().is_ok() {}
        if let Some(h) = self.handle.take() {
            // The worker finishes its current factorization, fails to send or sees the
            // closed job channel, and exits.
            let rx = self.rx.clone();
            let drain = std::thread::spawn(move || while rx.recv().is_ok() {});
            let _ = h.join();
            let _ = drain.join();
        }
    }
}
