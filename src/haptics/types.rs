//! The haptic loop's settings, the state it posts and its statistics.

use crate::contact::lcp::{LcpSettings, LcpSolver};
use crate::contact::tool::Pose;
use crate::error::{Result, check_range};
use crate::math::Vec3;

/// The virtual coupling between the device and the simulated tool: a
/// spring–damper in translation and one in rotation. An infinite stiffness
/// is a rigid coupling (the tool is the device).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Coupling {
    /// Translational stiffness (N/m); `f64::INFINITY`: rigid.
    pub stiffness: f64,
    /// Translational damping (N·s/m).
    pub damping: f64,
    /// Rotational stiffness (N·m/rad); `f64::INFINITY`: rigid.
    pub angular_stiffness: f64,
    /// Rotational damping (N·m·s/rad).
    pub angular_damping: f64,
}

impl Default for Coupling {
    /// 1 000 N/m with 1 N·s/m, and 0.5 N·m/rad with 10⁻³ N·m·s/rad: within
    /// what desktop devices render stably.
    fn default() -> Self {
        Self {
            stiffness: 1000.0,
            damping: 1.0,
            angular_stiffness: 0.5,
            angular_damping: 1e-3,
        }
    }
}

impl Coupling {
    /// A rigid coupling: the simulated tool is the device.
    pub fn rigid() -> Self {
        Self {
            stiffness: f64::INFINITY,
            damping: 0.0,
            angular_stiffness: f64::INFINITY,
            angular_damping: 0.0,
        }
    }
}

/// Settings of the haptic loop (the one home of each).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HapticSettings {
    /// Ticks per second (default 1 000).
    pub rate_hz: f64,
    /// Time the LCP may take per tick, seconds (default 0.4 ms); the solve
    /// stops at its tolerance, this budget or `lcp.max_iterations`, whichever
    /// comes first.
    pub budget: f64,
    /// The LCP of a tick: the subspace step ([`LcpSolver::Subspace`]) on at
    /// most 128 free rows (`LcpSettings::subspace_max_rows`: its LU cannot
    /// be interrupted, so its size is bounded; a larger active set is left to
    /// the block Gauss–Seidel sweeps), residual tolerance 10⁻⁶, at most 200
    /// sweeps. On the cataract delivery's tool problems (mean 104 rows, up to
    /// 507) it met the tolerance in every tick at 0.065–0.078 ms a tick on
    /// average, against 0.158–0.187 ms for block Gauss–Seidel alone, which
    /// missed it in 38 of 16 016 (`haptics --solvers`, README). The renderer
    /// lets each tick's step start from the last tick's LU
    /// (`LcpScratch::reuse_factorization`), which took another fifth off
    /// the mean.
    pub lcp: LcpSettings,
    /// The virtual coupling.
    pub coupling: Coupling,
    /// Scale from the contact force to the device's force (default 1).
    pub force_scale: f64,
    /// The real-time priority the haptic thread asks the operating system
    /// for, 1–99, or 0 for none (default 10). On Unix it is the `SCHED_FIFO`
    /// priority of the thread (granted to root, to a process with
    /// `CAP_SYS_NICE`, or under an `rtprio` limit, e.g. in
    /// `/etc/security/limits.conf`); where it is refused, or on other systems,
    /// the thread runs at normal priority and [`HapticStats::realtime`] says
    /// so. With it the loop wakes on time while the simulation keeps every
    /// core busy: on two cores the ticks' start-time jitter (p99) fell from
    /// 3.4–3.9 ms to 0.09–0.17 ms, and the rate kept 1 000 Hz (README,
    /// Haptics). A real-time thread that never slept would starve the rest
    /// of its core, so the loop then sleeps at least a twentieth of a period
    /// every tick, also when it is behind, and after a tick that worked
    /// longer than a period (a slow device driver, a debug build) at least
    /// as long as it worked: at most half a core, at a lower rate.
    pub realtime_priority: u8,
}

impl Default for HapticSettings {
    fn default() -> Self {
        Self {
            rate_hz: 1000.0,
            budget: 0.4e-3,
            lcp: LcpSettings {
                solver: LcpSolver::Subspace,
                subspace_max_rows: 128,
                max_iterations: 200,
                residual_tolerance: 1e-6,
                ..LcpSettings::default()
            },
            coupling: Coupling::default(),
            force_scale: 1.0,
            realtime_priority: 10,
        }
    }
}

impl HapticSettings {
    /// Checks every setting.
    pub fn validate(&self) -> Result<()> {
        check_range("HapticSettings::rate_hz", self.rate_hz, 1.0, 1e5)?;
        check_range("HapticSettings::budget", self.budget, 0.0, 1.0)?;
        check_range("HapticSettings::force_scale", self.force_scale, 0.0, 1e6)?;
        check_range(
            "HapticSettings::realtime_priority",
            f64::from(self.realtime_priority),
            0.0,
            99.0,
        )?;
        self.lcp.validate()?;
        let c = &self.coupling;
        for (name, k) in [
            ("Coupling::stiffness", c.stiffness),
            ("Coupling::angular_stiffness", c.angular_stiffness),
        ] {
            if k != f64::INFINITY {
                check_range(name, k, f64::MIN_POSITIVE, 1e12)?;
            }
        }
        check_range("Coupling::damping", c.damping, 0.0, 1e9)?;
        check_range("Coupling::angular_damping", c.angular_damping, 0.0, 1e9)?;
        Ok(())
    }

    /// Seconds per tick.
    pub fn period(&self) -> f64 {
        1.0 / self.rate_hz
    }

    /// The coupling's compliance per translation and rotation,
    /// `1 / (k + c / Δt)` at the tick period (0 when rigid).
    pub fn coupling_compliance(&self) -> [f64; 2] {
        let dt = self.period();
        let c = &self.coupling;
        let one = |k: f64, d: f64| {
            if k.is_finite() {
                1.0 / (k + d / dt)
            } else {
                0.0
            }
        };
        [
            one(c.stiffness, c.damping),
            one(c.angular_stiffness, c.angular_damping),
        ]
    }
}

/// Statistics of the haptic loop (the percentiles and the rate over the
/// last window of ticks, the rest since the start).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct HapticStats {
    /// Ticks since the start.
    pub ticks: u64,
    /// Seconds since the start.
    pub elapsed: f64,
    /// Ticks per second over the last 100 ticks.
    pub rate_hz: f64,
    /// Median time of a tick's work (problem, device, LCP, output), seconds.
    pub tick_p50: f64,
    /// 99th percentile of the tick's work, seconds.
    pub tick_p99: f64,
    /// 99th percentile of the tick's work since the start (to 5 µs), seconds.
    pub run_tick_p99: f64,
    /// 99th percentile of the interval jitter since the start (to 5 µs), seconds.
    pub run_jitter_p99: f64,
    /// Longest tick since the start, seconds.
    pub tick_max: f64,
    /// Seconds of tick work since the start: over [`HapticStats::elapsed`],
    /// the share of a core the loop takes from the simulation.
    pub busy: f64,
    /// 99th percentile of `|interval − period|` between tick starts, seconds.
    pub jitter_p99: f64,
    /// Mean LCP sweeps per tick over the last 100 ticks.
    pub lcp_iterations: f64,
    /// Ticks whose LCP stopped at the budget before its tolerance.
    pub unconverged: u64,
    /// Ticks whose work took longer than the period.
    pub overruns: u64,
    /// Ticks whose device pose was not finite (no force rendered).
    pub bad_poses: u64,
    /// Problems received from the simulation.
    pub problems: u64,
    /// Largest change of the output force from one tick to the next, in ticks
    /// that kept the same problem (newtons).
    pub max_jump_between_steps: f64,
    /// Largest change of the output force in ticks that took a new problem:
    /// the jump across simulation steps (newtons).
    pub max_jump_at_step: f64,
    /// Whether the thread runs at the real-time priority it asked for
    /// ([`HapticSettings::realtime_priority`]).
    pub realtime: bool,
}

/// What the haptic thread posts after each tick.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HapticState {
    /// Seconds since the loop started.
    pub time: f64,
    /// The device's pose.
    pub device: Pose,
    /// The coupled pose: where the simulated tool goes.
    pub proxy: Pose,
    /// Force sent to the device (newtons).
    pub force: Vec3,
    /// Torque sent to the device (newton-metres).
    pub torque: Vec3,
    /// Contact force on the tool before scaling and clamping.
    pub contact_force: Vec3,
    /// The simulation step whose problem the tick used (0: none yet).
    pub step: u64,
    /// Contacts on the tool in that problem.
    pub contacts: usize,
    /// LCP sweeps of the tick.
    pub iterations: usize,
    /// LCP relative residual at the end of the tick.
    pub residual: f64,
    /// The loop's statistics.
    pub stats: HapticStats,
}

impl Default for HapticState {
    fn default() -> Self {
        Self {
            time: 0.0,
            device: Pose::identity(),
            proxy: Pose::identity(),
            force: Vec3::zeros(),
            torque: Vec3::zeros(),
            contact_force: Vec3::zeros(),
            step: 0,
            contacts: 0,
            iterations: 0,
            residual: 0.0,
            stats: HapticStats::default(),
        }
    }
}
