//! The haptic loop's thread: ticks at a fixed rate, hands problems in and
//! states out through [`Mailbox`]es, and keeps the statistics.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use super::device::HapticDevice;
use super::mailbox::Mailbox;
use super::render::{HapticProblem, HapticRenderer};
use super::types::{HapticSettings, HapticState, HapticStats};
use crate::contact::ToolContactProblem;
use crate::error::{Result, SoftTissueError};
use crate::math::Vec3;

/// Tick times kept for the percentiles.
const WINDOW: usize = 1000;
/// Histogram buckets for the whole run's percentiles: 5 µs wide up to 10 ms.
const BUCKET: f64 = 5e-6;
const BUCKETS: usize = 2000;

/// A fixed histogram of times (the last bucket holds everything longer).
struct Histogram {
    counts: Vec<u64>,
    total: u64,
}

impl Histogram {
    fn new() -> Self {
        Self {
            counts: vec![0; BUCKETS],
            total: 0,
        }
    }

    fn add(&mut self, t: f64) {
        let i = ((t / BUCKET) as usize).min(BUCKETS - 1);
        self.counts[i] += 1;
        self.total += 1;
    }

    /// The upper edge of the bucket holding quantile `q`.
    fn quantile(&self, q: f64) -> f64 {
        let want = (q * self.total as f64).ceil() as u64;
        let mut seen = 0;
        for (i, c) in self.counts.iter().enumerate() {
            seen += c;
            if seen >= want.max(1) {
                return (i + 1) as f64 * BUCKET;
            }
        }
        BUCKETS as f64 * BUCKET
    }
}

/// The haptic loop: a thread that ticks a [`HapticRenderer`] at
/// [`HapticSettings::rate_hz`] with a [`HapticDevice`].
///
/// The simulation thread calls [`Self::publish`] after each step and
/// [`Self::poll`] before the next (to move the tool to the coupled pose);
/// neither ever waits for the haptic thread, nor it for them. Dropping the
/// loop (or [`Self::stop`]) stops the thread after its current tick, with
/// a zero force as the device's last output, and joins it.
#[derive(Debug)]
pub struct HapticLoop {
    settings: HapticSettings,
    inbox: Arc<Mailbox<HapticProblem>>,
    outbox: Arc<Mailbox<HapticState>>,
    stop: Arc<AtomicBool>,
    handle: Option<JoinHandle<()>>,
    latest: HapticState,
}

impl HapticLoop {
    /// Validates `settings` and starts the loop's thread with `device`.
    pub fn start(device: impl HapticDevice, settings: HapticSettings) -> Result<Self> {
        Self::start_boxed(Box::new(device), settings)
    }

    /// [`Self::start`] with a boxed device.
    pub fn start_boxed(device: Box<dyn HapticDevice>, settings: HapticSettings) -> Result<Self> {
        settings.validate()?;
        let inbox = Arc::new(Mailbox::new());
        let outbox = Arc::new(Mailbox::new());
        let stop = Arc::new(AtomicBool::new(false));
        let (i, o, s) = (inbox.clone(), outbox.clone(), stop.clone());
        let handle = std::thread::Builder::new()
            .name("soft-tissue haptics".into())
            .spawn(move || run(device, settings, &i, &o, &s))
            .map_err(|e| SoftTissueError::Io {
                path: "haptic thread".into(),
                reason: e.to_string(),
            })?;
        Ok(Self {
            settings,
            inbox,
            outbox,
            stop,
            handle: Some(handle),
            latest: HapticState::default(),
        })
    }

    /// The settings.
    pub fn settings(&self) -> &HapticSettings {
        &self.settings
    }

    /// Hands the step's tool problem to the haptic thread (it takes the
    /// newest at its next tick). Adds the coupling's compliance here, on the
    /// calling thread.
    pub fn publish(&self, problem: &ToolContactProblem) {
        self.inbox.post(|p| p.set(problem, &self.settings));
    }

    /// The newest state the haptic thread posted (the last one again when
    /// nothing new came).
    pub fn poll(&mut self) -> &HapticState {
        if let Some(b) = self.outbox.take() {
            self.latest = *b;
            self.outbox.recycle(b);
        }
        &self.latest
    }

    /// Whether the thread is running.
    pub fn is_running(&self) -> bool {
        self.handle.as_ref().is_some_and(|h| !h.is_finished())
    }

    /// Stops the thread and waits for it. Returns an error if it panicked.
    pub fn stop(&mut self) -> Result<()> {
        self.stop.store(true, Ordering::Release);
        match self.handle.take() {
            Some(h) => h
                .join()
                .map_err(|_| SoftTissueError::WorkerPanic("haptic thread".into())),
            None => Ok(()),
        }
    }
}

impl Drop for HapticLoop {
    fn drop(&mut self) {
        let _ = self.stop();
    }
}

/// Running statistics of the loop (all allocation done up front).
struct Stats {
    start: Instant,
    durations: Vec<f64>,
    jitter: Vec<f64>,
    sorted: Vec<f64>,
    next: usize,
    filled: usize,
    window_start: Instant,
    window_ticks: u64,
    window_iterations: usize,
    run_durations: Histogram,
    run_jitter: Histogram,
    out: HapticStats,
}

impl Stats {
    fn new() -> Self {
        let now = Instant::now();
        Self {
            start: now,
            durations: vec![0.0; WINDOW],
            jitter: vec![0.0; WINDOW],
            sorted: vec![0.0; WINDOW],
            next: 0,
            filled: 0,
            window_start: now,
            window_ticks: 0,
            window_iterations: 0,
            run_durations: Histogram::new(),
            run_jitter: Histogram::new(),
            out: HapticStats::default(),
        }
    }

    fn percentile(sorted: &mut [f64], src: &[f64], q: f64) -> f64 {
        sorted.copy_from_slice(src);
        sorted.sort_unstable_by(f64::total_cmp);
        let i = ((sorted.len() as f64 - 1.0) * q).round() as usize;
        sorted.get(i).copied().unwrap_or(0.0)
    }

    fn refresh(&mut self) {
        let n = self.filled;
        let (d, j) = (&self.durations[..n], &self.jitter[..n]);
        let s = &mut self.sorted[..n];
        self.out.tick_p50 = Self::percentile(s, d, 0.5);
        self.out.tick_p99 = Self::percentile(s, d, 0.99);
        self.out.jitter_p99 = Self::percentile(s, j, 0.99);
        self.out.run_tick_p99 = self.run_durations.quantile(0.99);
        self.out.run_jitter_p99 = self.run_jitter.quantile(0.99);
        let span = self.window_start.elapsed().as_secs_f64();
        if span > 0.0 {
            self.out.rate_hz = self.window_ticks as f64 / span;
        }
        if self.window_ticks > 0 {
            self.out.lcp_iterations = self.window_iterations as f64 / self.window_ticks as f64;
        }
        self.window_start = Instant::now();
        self.window_ticks = 0;
        self.window_iterations = 0;
    }
}

fn run(
    mut device: Box<dyn HapticDevice>,
    settings: HapticSettings,
    inbox: &Mailbox<HapticProblem>,
    outbox: &Mailbox<HapticState>,
    stop: &AtomicBool,
) {
    let realtime = raise_priority(settings.realtime_priority);
    let mut renderer = HapticRenderer::new(settings);
    let period = settings.period();
    let limits = device.limits();
    let mut stats = Stats::new();
    stats.out.realtime = realtime;
    let mut last_tick: Option<Instant> = None;
    let mut last_force: Option<Vec3> = None;
    let (mut epoch, mut since_epoch) = (stats.start, 0u64);
    while !stop.load(Ordering::Acquire) {
        let t0 = Instant::now();
        let mut new_problem = false;
        if let Some(p) = inbox.take() {
            if let Some(old) = renderer.set_problem(p) {
                inbox.recycle(old);
            }
            new_problem = true;
            stats.out.problems += 1;
        }
        let time = t0.duration_since(stats.start).as_secs_f64();
        let pose = device.pose(time);
        let dt = last_tick.map_or(period, |t| t0.duration_since(t).as_secs_f64());
        let out = renderer.tick(&pose, &limits);
        device.set_output(out.force, out.torque);
        let work = t0.elapsed().as_secs_f64();

        // Statistics.
        let s = &mut stats;
        s.durations[s.next] = work;
        s.jitter[s.next] = if last_tick.is_some() {
            (dt - period).abs()
        } else {
            0.0
        };
        s.run_durations.add(work);
        s.run_jitter.add(s.jitter[s.next]);
        s.next = (s.next + 1) % WINDOW;
        s.filled = (s.filled + 1).min(WINDOW);
        s.window_ticks += 1;
        s.window_iterations += out.iterations;
        s.out.ticks += 1;
        s.out.tick_max = s.out.tick_max.max(work);
        s.out.busy += work;
        s.out.overruns += u64::from(work > period);
        s.out.unconverged += u64::from(!out.converged);
        s.out.bad_poses += u64::from(out.bad_pose);
        if let Some(f) = last_force {
            let jump = (out.force - f).norm();
            if new_problem {
                s.out.max_jump_at_step = s.out.max_jump_at_step.max(jump);
            } else {
                s.out.max_jump_between_steps = s.out.max_jump_between_steps.max(jump);
            }
        }
        last_force = Some(out.force);
        if s.out.ticks.is_multiple_of(100) {
            s.refresh();
        }
        s.out.elapsed = time;
        let state = HapticState {
            time,
            device: pose,
            proxy: out.proxy,
            force: out.force,
            torque: out.torque,
            contact_force: out.contact_force,
            step: renderer.problem().map_or(0, |p| p.problem.step),
            contacts: renderer.problem().map_or(0, |p| p.problem.num_contacts()),
            iterations: out.iterations,
            residual: out.residual,
            stats: s.out,
        };
        outbox.post(|x| *x = state);
        last_tick = Some(t0);
        since_epoch += 1;

        // Sleep to the next deadline, counted from an epoch so that a late
        // tick does not shift the ones after it.
        let next = epoch + Duration::from_secs_f64(period * since_epoch as f64);
        let now = Instant::now();
        let until_next = (next > now).then(|| next - now);
        if until_next.is_none() && now - next > Duration::from_secs_f64(10.0 * period) {
            // Far behind (the thread was descheduled): no burst of catch-up ticks.
            (epoch, since_epoch) = (now, 0);
        }
        let sleep = rest(realtime, period, work, until_next);
        if !sleep.is_zero() {
            std::thread::sleep(sleep);
        }
    }
    device.set_output(Vec3::zeros(), Vec3::zeros());
}

/// How long the loop sleeps after a tick that worked `work` seconds:
/// until the next deadline (`until_next`; `None` when it has passed). A
/// real-time thread leaves the rest of its core at least a twentieth of a
/// period every tick, and after a tick that worked longer than a period at
/// least as long as it worked, so that it never takes more than half a core
/// (see `HapticSettings::realtime_priority`).
fn rest(realtime: bool, period: f64, work: f64, until_next: Option<Duration>) -> Duration {
    let least = match (realtime, work > period) {
        (false, _) => Duration::ZERO,
        (true, false) => Duration::from_secs_f64(period / 20.0),
        (true, true) => Duration::from_secs_f64(work),
    };
    until_next.unwrap_or(Duration::ZERO).max(least)
}

/// Asks for the `SCHED_FIFO` scheduling class at `priority` for the calling
/// thread (0: does not ask); whether it was granted.
#[cfg(unix)]
fn raise_priority(priority: u8) -> bool {
    if priority == 0 {
        return false;
    }
    let param = libc::sched_param {
        sched_priority: i32::from(priority),
    };
    // SAFETY: `pthread_self` names the calling thread, and `param` is a
    // valid `sched_param` that outlives the call; the call only changes this
    // thread's scheduling class and reports an error code when refused.
    unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &param) == 0 }
}

/// No real-time class outside Unix: the thread runs at normal priority.
#[cfg(not(unix))]
fn raise_priority(_priority: u8) -> bool {
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The sleep after a tick: to the deadline at normal priority; a
    /// real-time loop keeps a twentieth of a period free, also when behind,
    /// and after an overrun sleeps as long as the tick worked.
    #[test]
    fn a_real_time_loop_never_holds_its_core() {
        let ms = |v: f64| Duration::from_secs_f64(v * 1e-3);
        let period = 1e-3;
        // Normal priority: to the deadline, or not at all when behind.
        assert_eq!(rest(false, period, 0.2e-3, Some(ms(0.8))), ms(0.8));
        assert_eq!(rest(false, period, 3e-3, None), Duration::ZERO);
        // Real time, on schedule: to the deadline, at least 0.05 ms.
        assert_eq!(rest(true, period, 0.2e-3, Some(ms(0.8))), ms(0.8));
        assert_eq!(rest(true, period, 0.98e-3, Some(ms(0.02))), ms(0.05));
        // Real time, behind: 0.05 ms after a short tick, the tick's own
        // length after one longer than a period (half the core at most).
        assert_eq!(rest(true, period, 0.3e-3, None), ms(0.05));
        assert_eq!(rest(true, period, 3e-3, None), ms(3.0));
        assert_eq!(rest(true, period, 3e-3, Some(ms(0.5))), ms(3.0));
    }
}
