//! The contact LCP: Signorini contact with Coulomb friction, three solvers.
//!
//! Unknowns per contact: the normal force `λ_n ≥ 0` and, when `μ > 0`, the
//! tangential force `λ_t ∈ ℝ²`. With `δ = W λ + δ₀`:
//!
//! - normal: `0 ≤ δ_n ⊥ λ_n ≥ 0`;
//! - friction (**circular cone**, not a pyramid): `‖λ_t‖ ≤ μ λ_n`; sticking
//!   (`δ_t = 0`) inside the cone, sliding with `λ_t = −μ λ_n δ_t/‖δ_t‖` on it.
//!
//! ## Solvers ([`LcpSolver`])
//! - [`LcpSolver::ProjectedGaussSeidel`] (`pgs.rs`): row by row, the normal
//!   then the tangential pair, with an isotropic projected step when sliding.
//! - [`LcpSolver::BlockGaussSeidel`] (`block.rs`): contact by contact, the
//!   three forces from an exact local Signorini–Coulomb solve
//!   ([`local_coulomb`]).
//! - [`LcpSolver::Nncg`]: block Gauss–Seidel accelerated by nonsmooth
//!   nonlinear conjugate gradients (Silcowitz, Niebe and Erleben 2010): after
//!   a sweep that changed the forces by `r_k`, the forces move on by
//!   `β p_{k−1}` with `β = ‖r_k‖²/‖r_{k−1}‖²` and `p_k = β p_{k−1} + r_k`,
//!   restarting (`p = 0`) when `β > 1`. The next sweep's local solves put
//!   every contact back into its cone, so the answer is always a sweep's.
//!   `W p` is carried along from the sweeps' own changes of `δ`, so the
//!   acceleration costs `O(m)` per sweep, not a product with `W`.
//! - [`LcpSolver::Subspace`] (the default, `subspace.rs`): after each block
//!   Gauss–Seidel sweep, a semismooth Newton step on the active set (dense
//!   LU of the free rows), kept when it lowers the residual. On the recorded
//!   cataract problems it meets 1e-6 in one to ten sweeps where the
//!   Gauss–Seidel variants stall above 1e-4 after hundreds (`cargo bench
//!   --bench lcp`; the table is in the README).
//!
//! Every solver warm starts from the given forces and stops at the first of:
//! the relative residual ([`residual`]) at or below
//! [`LcpSettings::residual_tolerance`]; the largest force change of a sweep at
//! or below [`LcpSettings::tolerance`] times the largest force; the largest
//! displacement change a contact's own update caused (`|Δλ_r| W_rr`) at or
//! below [`LcpSettings::displacement_tolerance`]; or
//! [`LcpSettings::max_iterations`] sweeps.
//!
//! ## The residual, the same for every solver
//! [`residual`] is the natural-map residual of the cone complementarity form
//! (De Saxcé): with `ũ = (δ_n + μ‖δ_t‖, δ_t)` and a per-contact scale
//! `ρ_c = 1/W_nn`, each contact contributes `λ_c − Π_K(λ_c − ρ_c ũ_c)`, zero
//! exactly when the contact satisfies Signorini and Coulomb. The norm of all
//! contributions is divided by the larger of `‖λ‖` and `‖ρ (−δ₀_n)⁺‖` (the
//! forces that would close each contact alone), so it is dimensionless and
//! comparable across problems. It is what [`ContactProblem`] replays and the
//! `lcp` bench compare.
//!
//! ## Cost
//! `δ = δ₀ + W λ` is kept up to date: a row whose force changes adds its
//! column of `W` to `δ` (`W` is symmetric), and a row whose force stays (an
//! open contact at `λ = 0`, the many alarm-band contacts) costs one read. A
//! sweep therefore costs `m` multiply-adds per *changed* row, not `m²`, and
//! the residuals are recomputed from scratch at the end, so nothing drifts
//! into the report.

mod block;
mod pgs;
mod problem;
mod subspace;
mod warm;

pub use block::local_coulomb;
pub use problem::ContactProblem;
pub use warm::{ContactKey, OtherKey, WarmStart};

/// Which algorithm solves the contact LCP.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LcpSolver {
    /// Projected Gauss–Seidel, row by row (normal, then the tangential pair).
    ProjectedGaussSeidel,
    /// Block Gauss–Seidel with an exact local Signorini–Coulomb solve per contact.
    BlockGaussSeidel,
    /// Block Gauss–Seidel accelerated by nonsmooth nonlinear conjugate gradients.
    Nncg,
    /// Block Gauss–Seidel with a Newton step on the active set every few
    /// sweeps (subspace minimization, `subspace.rs`).
    #[default]
    Subspace,
}

/// Settings of the LCP solve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LcpSettings {
    /// The algorithm.
    pub solver: LcpSolver,
    /// Maximum sweeps.
    pub max_iterations: usize,
    /// Relative residual ([`residual`]) at or below which the sweeps stop;
    /// `0` switches the test off.
    pub residual_tolerance: f64,
    /// Relative force change of a sweep that ends the solve; `0` (the
    /// default) switches the test off. Small changes per sweep do not mean
    /// small errors on a strongly coupled contact set, so the residual is the
    /// better test; this one is kept for projected Gauss–Seidel setups.
    pub tolerance: f64,
    /// Displacement change (metres) below which a sweep ends the solve: the
    /// largest `|Δλ_r| W_rr` of the sweep. `0` (the default) switches it off.
    /// A positive value trades accuracy for time: on a large, strongly coupled
    /// contact set Gauss–Seidel moves slowly, so small changes per sweep do not
    /// mean small errors. In the cataract scene with projected Gauss–Seidel,
    /// 1e-9 m cut the sweeps by half but left the vectis's friction forces
    /// unconverged, and the squeezed lens was shot out of the eye in about one
    /// run of six.
    pub displacement_tolerance: f64,
    /// Over-relaxation factor ω in (0, 2); 1 is plain Gauss–Seidel.
    pub over_relaxation: f64,
    /// Start from the previous step's forces of persisting contacts.
    pub warm_start: bool,
}

impl Default for LcpSettings {
    fn default() -> Self {
        Self {
            solver: LcpSolver::default(),
            max_iterations: 500,
            residual_tolerance: 1e-6,
            tolerance: 0.0,
            displacement_tolerance: 0.0,
            over_relaxation: 1.0,
            warm_start: true,
        }
    }
}

/// Outcome of an LCP solve.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LcpReport {
    /// Sweeps run.
    pub iterations: usize,
    /// Subspace steps kept ([`LcpSolver::Subspace`]).
    pub subspace_steps: usize,
    /// Whether the solve stopped at [`LcpSettings::max_iterations`] without
    /// meeting any of its tolerances.
    pub capped: bool,
    /// Relative natural-map residual of the answer ([`residual`]), dimensionless.
    pub residual: f64,
    /// Largest normal complementarity residual `|min(δ_n, W_nn λ_n)|` (metres).
    pub complementarity: f64,
    /// Largest friction residual (metres): `‖δ_t‖` when sticking, the part of
    /// `δ_t` not opposed to `λ_t` when sliding, plus any cone violation scaled by `W_tt`.
    pub friction: f64,
    /// Largest predicted penetration `max(−δ_n, 0)` (metres).
    pub penetration: f64,
}

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
}

/// What one sweep changed.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct SweepStats {
    max_change: f64,
    max_force: f64,
    max_disp: f64,
}

/// `d += a · x`, vectorizable.
pub(super) fn axpy(d: &mut [f64], a: f64, x: &[f64]) {
    for (di, xi) in d.iter_mut().zip(x) {
        *di += a * xi;
    }
}

/// Dot product with four partial sums.
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let (ca, cb) = (a.chunks_exact(4), b.chunks_exact(4));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for k in 0..4 {
            acc[k] += x[k] * y[k];
        }
    }
    let mut s = (acc[0] + acc[1]) + (acc[2] + acc[3]);
    for (x, y) in ra.iter().zip(rb) {
        s += x * y;
    }
    s
}

/// `delta = δ₀ + W λ` from scratch.
fn exact_delta(w: &[f64], delta0: &[f64], lambda: &[f64], delta: &mut [f64]) {
    let m = delta0.len();
    for (r, d) in delta.iter_mut().enumerate() {
        *d = delta0[r] + dot(&w[r * m..(r + 1) * m], lambda);
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
    let (mut next_subspace, mut subspace_gap) = (0, 1);
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
            let kept = subspace::step(
                w,
                delta0,
                rows,
                mu,
                lambda,
                &mut s.delta,
                res,
                settings.residual_tolerance,
                &mut s.subspace,
            );
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
        if it + 1 == settings.max_iterations {
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
    exact_delta(w, delta0, lambda, &mut s.delta);
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
            let l = [lambda[r + 1], lambda[r + 2]];
            let dnorm = (d[0] * d[0] + d[1] * d[1]).sqrt();
            let lnorm = (l[0] * l[0] + l[1] * l[1]).sqrt();
            let limit = mu[c] * lambda[r];
            let wtt = w[(r + 1) * m + r + 1].max(w[(r + 2) * m + r + 2]);
            let res = if lnorm < limit * (1.0 - 1e-9) || limit == 0.0 {
                if limit == 0.0 { 0.0 } else { dnorm }
            } else {
                // Sliding: δ_t must be anti-parallel to λ_t.
                let along = -(d[0] * l[0] + d[1] * l[1]) / lnorm;
                (dnorm * dnorm - along * along).max(0.0).sqrt() + (-along).max(0.0)
            };
            let cone = (lnorm - limit).max(0.0) * wtt;
            report.friction = report.friction.max(res + cone);
        }
    }
    report
}

/// The relative natural-map residual of forces `lambda` with `delta = W λ + δ₀`
/// (see the module docs): 0 exactly at a solution, dimensionless. Contacts
/// whose `W_nn` is not positive are left out, as the solvers leave them.
pub fn residual(
    w: &[f64],
    delta0: &[f64],
    rows: &[usize],
    mu: &[f64],
    lambda: &[f64],
    delta: &[f64],
) -> f64 {
    let m = delta0.len();
    let (mut res2, mut force2, mut scale2) = (0.0, 0.0, 0.0);
    for c in 0..rows.len().saturating_sub(1) {
        let r = rows[c];
        let k = rows[c + 1] - r;
        let wnn = w[r * m + r];
        if wnn.is_nan() || wnn <= 0.0 {
            continue;
        }
        let rho = 1.0 / wnn;
        scale2 += (rho * (-delta0[r]).max(0.0)).powi(2);
        let l = [
            lambda[r],
            if k == 3 { lambda[r + 1] } else { 0.0 },
            if k == 3 { lambda[r + 2] } else { 0.0 },
        ];
        force2 += l[0] * l[0] + l[1] * l[1] + l[2] * l[2];
        let contact_mu = if k == 3 { mu[c] } else { 0.0 };
        let e = if contact_mu > 0.0 {
            let (d1, d2) = (delta[r + 1], delta[r + 2]);
            let un = delta[r] + contact_mu * d1.hypot(d2);
            let z = [l[0] - rho * un, l[1] - rho * d1, l[2] - rho * d2];
            let p = block::project_cone(z, contact_mu);
            [l[0] - p[0], l[1] - p[1], l[2] - p[2]]
        } else {
            // Frictionless: the normal's natural map; any tangential force is wrong.
            [l[0] - (l[0] - rho * delta[r]).max(0.0), l[1], l[2]]
        };
        res2 += e[0] * e[0] + e[1] * e[1] + e[2] * e[2];
    }
    res2.sqrt() / force2.max(scale2).sqrt().max(1e-300)
}
