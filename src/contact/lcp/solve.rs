//! The solve loop shared by every solver: sweeps, the stopping tests, NNCG's
//! momentum and the subspace steps.

use super::types::{LcpReport, LcpSettings, LcpSolver, exact_delta, friction_residual, residual};
use super::{block, pgs, subspace};

/// Scratch of an LCP solve, sized on first use and kept between solves.
#[derive(Debug, Clone, Default)]
pub struct LcpScratch {
    delta: Vec<f64>,
    subspace: subspace::SubspaceScratch,
    before: Vec<f64>,
    prev: Vec<f64>,
    p: Vec<f64>,
    wp: Vec<f64>,
}

impl LcpScratch {
    /// `δ = W λ + δ₀` of the last solve's answer.
    pub fn delta(&self) -> &[f64] {
        &self.delta
    }

    /// With `on`, the subspace step ([`LcpSolver::Subspace`]) may start from
    /// the factors the last solve left, on the active set they were made
    /// for (a triangular solve instead of a factorization), when that active
    /// set classifies the warm start again: for a caller that solves the
    /// same `W` again and again with a slowly changing `δ₀`, warm-started
    /// (the haptic tick). The caller must then call [`Self::forget_factorization`]
    /// whenever `W` changes. Off by default: each solve starts cold, so that a
    /// solve's result does not depend on the one before.
    pub fn reuse_factorization(&mut self, on: bool) {
        self.subspace.reuse = on;
        self.forget_factorization();
    }

    /// Drops the factors kept for [`Self::reuse_factorization`] (`W`
    /// changed).
    pub fn forget_factorization(&mut self) {
        self.subspace.forget();
    }
}

/// Solves the LCP in place with `settings.solver`. `w` is the dense,
/// symmetric `m × m` matrix (row-major), `rows[c]..rows[c+1]` the rows of
/// contact `c` (1 or 3), `mu[c]` its friction, `lambda` the start (warm or
/// zero) and, on return, the answer; `scratch.delta()` then holds `δ = W λ + δ₀`.
pub fn solve(
    w: &[f64],
    delta0: &[f64],
    rows: &[usize],
    mu: &[f64],
    lambda: &mut [f64],
    settings: &LcpSettings,
    scratch: &mut LcpScratch,
) -> LcpReport {
    solve_until(w, delta0, rows, mu, lambda, settings, scratch, || false)
}

/// [`solve`] that also stops after any sweep at which `stop()` says so (a
/// time budget, for example); the report is then `capped`. One solve, not a
/// series of short ones: `δ = W λ + δ₀` is formed once, at the start (`m`
/// multiply-adds per nonzero force of the warm start), and carried through
/// the sweeps and subspace steps.
#[allow(clippy::too_many_arguments)]
pub fn solve_until(
    w: &[f64],
    delta0: &[f64],
    rows: &[usize],
    mu: &[f64],
    lambda: &mut [f64],
    settings: &LcpSettings,
    scratch: &mut LcpScratch,
    mut stop: impl FnMut() -> bool,
) -> LcpReport {
    let m = delta0.len();
    let nncg = settings.solver == LcpSolver::Nncg;
    let sweep = match settings.solver {
        LcpSolver::ProjectedGaussSeidel => pgs::sweep,
        LcpSolver::BlockGaussSeidel | LcpSolver::Nncg | LcpSolver::Subspace => block::sweep,
    };
    let subspace = settings.solver == LcpSolver::Subspace;
    let s = scratch;
    s.delta.resize(m, 0.0);
    exact_delta(w, delta0, lambda, &mut s.delta);
    if nncg {
        for v in [&mut s.before, &mut s.prev, &mut s.p, &mut s.wp] {
            v.clear();
            v.resize(m, 0.0);
        }
    }
    let omega = settings.over_relaxation;
    let mut report = LcpReport::default();
    let mut last_norm2 = 0.0;
    let (mut next_subspace, mut subspace_gap) = (0, 1usize);
    for it in 0..settings.max_iterations {
        if nncg {
            s.prev.copy_from_slice(lambda);
            s.before.copy_from_slice(&s.delta);
        }
        let stats = sweep(w, rows, mu, lambda, &mut s.delta, omega);
        report.iterations = it + 1;
        let mut res = if settings.residual_tolerance > 0.0 || subspace {
            residual(w, delta0, rows, mu, lambda, &s.delta)
        } else {
            f64::INFINITY
        };
        let mut converged = stats.max_change <= settings.tolerance * stats.max_force.max(1e-300)
            || stats.max_disp <= settings.displacement_tolerance
            || res <= settings.residual_tolerance;
        if subspace && !converged && it >= next_subspace {
            let before = s.subspace.factorizations;
            // A cycling step may enumerate classes once per solve, in its
            // second step: a first step that misses is often finished by
            // the next one (a trial that enumerated in every step took 161
            // LUs on a recorded 335-contact jam problem that needs 16 without).
            s.subspace.enumerate = subspace_gap == 2;
            // The solve's `k`-th step (the gap doubles after each) damps its
            // Newton steps by the `k`-th shift, in turn.
            let k = subspace_gap.trailing_zeros() as usize;
            let shifts = subspace::NEWTON_SHIFTS;
            s.subspace.set_shift(shifts[k % shifts.len()]);
            let kept = subspace::step(
                w,
                delta0,
                rows,
                mu,
                lambda,
                &mut s.delta,
                res,
                settings.residual_tolerance,
                settings.subspace_max_rows,
                &mut s.subspace,
                &mut stop,
            );
            report.factorizations += s.subspace.factorizations - before;
            if let Some(r) = kept {
                report.subspace_steps += 1;
                res = r;
                converged = res <= settings.residual_tolerance;
            }
            // A step that missed the target is retried after twice as many
            // sweeps as the last, so a problem it cannot finish costs sweeps,
            // not factorizations.
            if !converged {
                next_subspace = it + subspace_gap;
                subspace_gap *= 2;
            }
        }
        if converged {
            break;
        }
        if it + 1 == settings.max_iterations || stop() {
            report.capped = true;
            break;
        }
        if nncg {
            // r = λ − λ_prev (the sweep's step), W r = δ − δ_before.
            let mut norm2 = 0.0;
            for (l, p) in lambda.iter().zip(&s.prev) {
                norm2 += (l - p) * (l - p);
            }
            let beta = if last_norm2 > 0.0 {
                norm2 / last_norm2
            } else {
                0.0
            };
            if beta > 1.0 || !beta.is_finite() {
                s.p.fill(0.0);
                s.wp.fill(0.0);
            } else {
                for i in 0..m {
                    let r = lambda[i] - s.prev[i];
                    let wr = s.delta[i] - s.before[i];
                    lambda[i] += beta * s.p[i];
                    s.delta[i] += beta * s.wp[i];
                    s.p[i] = beta * s.p[i] + r;
                    s.wp[i] = beta * s.wp[i] + wr;
                }
            }
            last_norm2 = norm2;
            // Round-off of the carried W p stays small; start it afresh now and then.
            if (it + 1) % 64 == 0 {
                exact_delta(w, delta0, lambda, &mut s.delta);
            }
        }
    }
    // The sweeps and the subspace steps keep `δ` by rows of `W` (a change of
    // a force adds its row), to round-off; NNCG's momentum carries `W p`,
    // which drifts, so its `δ` is made afresh (as at the start).
    if nncg {
        exact_delta(w, delta0, lambda, &mut s.delta);
    }
    report.residual = residual(w, delta0, rows, mu, lambda, &s.delta);
    let delta = &s.delta;
    for c in 0..rows.len().saturating_sub(1) {
        let r = rows[c];
        let dn = delta[r];
        let wnn = w[r * m + r].max(0.0);
        report.complementarity = report.complementarity.max(dn.min(wnn * lambda[r]).abs());
        report.penetration = report.penetration.max(-dn);
        if rows[c + 1] - r == 3 {
            let d = [delta[r + 1], delta[r + 2]];
            let l = [lambda[r], lambda[r + 1], lambda[r + 2]];
            let wtt = w[(r + 1) * m + r + 1].max(w[(r + 2) * m + r + 2]);
            let res = friction_residual(l, d, mu[c], wtt);
            report.friction = report.friction.max(res);
        }
    }
    report
}
