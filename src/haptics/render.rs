//! One haptic tick: the tool's contact problem at the device's pose,
//! through the virtual coupling, solved warm-started within a time budget.

use std::time::Instant;

use nalgebra::{Isometry3, Translation3, UnitQuaternion};

use super::device::DeviceLimits;
use super::types::HapticSettings;
use crate::contact::lcp::{self, LcpScratch};
use crate::contact::{Pose, ToolContactProblem};
use crate::math::Vec3;

/// A tool's contact problem as the haptic loop uses it: the step's
/// [`ToolContactProblem`] and `W_TT + J C Jᵀ`, the contact compliance in
/// series with the coupling's (`C`, see [`HapticRenderer`]), made once per
/// simulation step on the publishing thread.
#[derive(Debug, Clone, Default)]
pub struct HapticProblem {
    /// The step's problem.
    pub problem: ToolContactProblem,
    /// `W_TT + J C Jᵀ`, `m × m`.
    pub w_coupled: Vec<f64>,
}

impl HapticProblem {
    /// Copies `problem` in (reusing this one's memory) and adds the
    /// coupling's compliance for `settings`.
    pub fn set(&mut self, problem: &ToolContactProblem, settings: &HapticSettings) {
        self.problem.clone_from(problem);
        let m = problem.m();
        self.w_coupled.clear();
        self.w_coupled.extend_from_slice(&problem.w);
        let c = settings.coupling_compliance();
        if c == [0.0, 0.0] {
            return;
        }
        let jac = &problem.jacobian;
        for i in 0..m {
            for j in i..m {
                let (a, b) = (&jac[i], &jac[j]);
                let lin = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
                let ang = a[3] * b[3] + a[4] * b[4] + a[5] * b[5];
                let add = c[0] * lin + c[1] * ang;
                self.w_coupled[i * m + j] += add;
                if j != i {
                    self.w_coupled[j * m + i] += add;
                }
            }
        }
    }
}

/// What one tick computed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TickOutput {
    /// The force sent to the device (scaled, clamped), newtons.
    pub force: Vec3,
    /// The torque sent to the device (scaled, clamped), newton-metres.
    pub torque: Vec3,
    /// The contact force on the tool at the coupled pose, before scaling.
    pub contact_force: Vec3,
    /// The contact torque on the tool about its origin, before scaling.
    pub contact_torque: Vec3,
    /// The coupled (proxy) pose: the tool the tissue sees.
    pub proxy: Pose,
    /// LCP sweeps this tick.
    pub iterations: usize,
    /// The LCP's relative residual at the end of the tick.
    pub residual: f64,
    /// Whether the LCP met its tolerance within the budget.
    pub converged: bool,
    /// The device's pose was not finite: the tick rendered no force and
    /// kept the last proxy.
    pub bad_pose: bool,
}

impl Default for TickOutput {
    fn default() -> Self {
        Self {
            force: Vec3::zeros(),
            torque: Vec3::zeros(),
            contact_force: Vec3::zeros(),
            contact_torque: Vec3::zeros(),
            proxy: Pose::identity(),
            iterations: 0,
            residual: 0.0,
            converged: true,
            bad_pose: false,
        }
    }
}

/// The tool motion from `base` to `pose`: translation of the origin, then
/// the rotation vector of `R Rᵦᵀ`.
fn relative(pose: &Pose, base: &Pose) -> [f64; 6] {
    let t = pose.translation.vector - base.translation.vector;
    let r = (pose.rotation * base.rotation.inverse()).scaled_axis();
    [t.x, t.y, t.z, r.x, r.y, r.z]
}

fn displaced(base: &Pose, q: &[f64; 6]) -> Pose {
    let t = base.translation.vector + Vec3::new(q[0], q[1], q[2]);
    let r = UnitQuaternion::from_scaled_axis(Vec3::new(q[3], q[4], q[5])) * base.rotation;
    Isometry3::from_parts(Translation3::from(t), r)
}

/// Computes the haptic force, tick by tick, with no thread of its own (the
/// haptic loop runs one; tests and custom loops can drive it directly).
///
/// Per tick, with the device at `q_d` (relative to the pose the problem was
/// solved at) and the coupling's spring `k` and damper `c` (per
/// translation and rotation, `k' = k + c / Δt`, `Δt` the nominal tick
/// period):
///
/// 1. the coupling's rest target `q* = (k q_d + (c/Δt)(q_d − q_d⁻ + q_p⁻)) / k'`
///    (`⁻`: the previous tick);
/// 2. the LCP `(W_TT + J C Jᵀ) λ + δ_T + J q*` with the cone, `C = 1/k'`,
///    warm-started from the previous tick (from the step's forces when a new
///    problem arrives), one solve that sweeps until the residual tolerance
///    or the time budget ([`lcp::solve_until`]);
/// 3. the contact wrench `F = Jᵀ λ` (plus the refinement passes' share), the
///    proxy `q_p = q* + C F`: the coupling and the contact balance;
/// 4. the device's output `F` times [`HapticSettings::force_scale`], scaled
///    down to the device's limits.
///
/// With a rigid coupling (`k = ∞`) the proxy is the device. The rendered
/// stiffness is that of the coupling and the tissue in series, so it never
/// exceeds `k`.
#[derive(Debug, Default)]
pub struct HapticRenderer {
    settings: HapticSettings,
    problem: Option<Box<HapticProblem>>,
    delta: Vec<f64>,
    lambda: Vec<f64>,
    scratch: LcpScratch,
    previous: Option<(Pose, Pose)>,
}

impl HapticRenderer {
    /// A renderer with `settings` (validate them first:
    /// [`HapticSettings::validate`]).
    pub fn new(settings: HapticSettings) -> Self {
        Self {
            settings,
            ..Default::default()
        }
    }

    /// The settings.
    pub fn settings(&self) -> &HapticSettings {
        &self.settings
    }

    /// The problem in use, if any.
    pub fn problem(&self) -> Option<&HapticProblem> {
        self.problem.as_deref()
    }

    /// Takes a new problem (from the newest simulation step) and returns the
    /// one it replaces, for reuse. The warm start becomes the step's forces.
    pub fn set_problem(&mut self, problem: Box<HapticProblem>) -> Option<Box<HapticProblem>> {
        // Ticks re-solve this problem's `W` with a slowly moving `δ`: the
        // subspace step may start from the last tick's LU where the active
        // set holds; none is kept from the problem before.
        self.scratch.reuse_factorization(true);
        self.lambda.clear();
        self.lambda.extend_from_slice(&problem.problem.lambda);
        self.problem.replace(problem)
    }

    /// One tick with the device at `device`.
    ///
    /// The coupling's damper is discretized at the nominal period
    /// ([`HapticSettings::period`]) whenever the tick really comes: the
    /// coupled matrix holds `C = 1/(k + c/Δt)` at that period, and step 1 must
    /// use the same `Δt`, or a held device would see the damper pull like a
    /// spring (a tick after a late one, `Δt` a tenth of the period, would rest
    /// the proxy at several times `F/k` from the device). A late tick is
    /// damped as if on time, which stays passive (the damper still only takes
    /// energy out).
    pub fn tick(&mut self, device: &Pose, limits: &DeviceLimits) -> TickOutput {
        let start = Instant::now();
        let finite = device.translation.vector.iter().all(|c| c.is_finite())
            && device.rotation.coords.iter().all(|c| c.is_finite());
        if !finite {
            let fallback = self
                .problem
                .as_ref()
                .map_or(Pose::identity(), |p| p.problem.pose);
            return TickOutput {
                proxy: self.previous.map_or(fallback, |(_, proxy)| proxy),
                bad_pose: true,
                ..Default::default()
            };
        }
        let (prev_device, prev_proxy) = self.previous.unwrap_or((*device, *device));
        let Some(hp) = self.problem.as_deref() else {
            // No step yet: the tool follows the device and nothing is felt.
            self.previous = Some((*device, *device));
            return TickOutput {
                proxy: *device,
                ..Default::default()
            };
        };
        let p = &hp.problem;
        let qd = relative(device, &p.pose);
        let qd0 = relative(&prev_device, &p.pose);
        let qp0 = relative(&prev_proxy, &p.pose);
        let k = [
            self.settings.coupling.stiffness,
            self.settings.coupling.angular_stiffness,
        ];
        let c = [
            self.settings.coupling.damping,
            self.settings.coupling.angular_damping,
        ];
        let dt = self.settings.period();
        let mut target = qd;
        for i in 0..6 {
            let g = i / 3;
            if k[g].is_finite() {
                let cd = c[g] / dt;
                target[i] = (k[g] * qd[i] + cd * (qd[i] - qd0[i] + qp0[i])) / (k[g] + cd);
            }
        }
        let m = p.m();
        self.delta.clear();
        for r in 0..m {
            let j = &p.jacobian[r];
            let mut d = p.delta[r];
            for i in 0..6 {
                d += j[i] * target[i];
            }
            self.delta.push(d);
        }
        self.lambda.resize(m, 0.0);
        let mut out = TickOutput::default();
        if m > 0 {
            // The clock is read after every sweep (tens of nanoseconds; a
            // sweep of the jam's tool rows takes microseconds).
            let budget = self.settings.budget;
            let report = lcp::solve_until(
                &hp.w_coupled,
                &self.delta,
                &p.rows,
                &p.mu,
                &mut self.lambda,
                &self.settings.lcp,
                &mut self.scratch,
                || start.elapsed().as_secs_f64() >= budget,
            );
            out.iterations = report.iterations;
            out.residual = report.residual;
            out.converged = !report.capped;
        }
        let (mut f, mut t) = p.wrench(&self.lambda);
        f += p.extra_force;
        t += p.extra_torque;
        let cc = self.settings.coupling_compliance();
        let mut q = target;
        for i in 0..3 {
            q[i] += cc[0] * f[i];
            q[i + 3] += cc[1] * t[i];
        }
        let proxy = displaced(&p.pose, &q);
        out.contact_force = f;
        out.contact_torque = t;
        out.proxy = proxy;
        let s = self.settings.force_scale;
        out.force = clamp_norm(f * s, limits.max_force);
        out.torque = clamp_norm(t * s, limits.max_torque);
        self.previous = Some((*device, proxy));
        out
    }
}

fn clamp_norm(v: Vec3, max: f64) -> Vec3 {
    let n = v.norm();
    if n > max && n > 0.0 { v * (max / n) } else { v }
}
