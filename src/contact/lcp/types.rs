//! The LCP's settings, report and the pieces every solver shares: the
//! residual, the cone projection and the dense kernels.

use crate::error::{Result, SoftTissueError, check_range};
#[cfg(target_arch = "x86_64")]
use crate::math::has_avx2_fma;

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
    /// sweeps (subspace minimization, `subspace/`).
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
    /// Most free rows a subspace step ([`LcpSolver::Subspace`]) factorizes:
    /// a step whose active set has more stops there and leaves the problem
    /// to the sweeps. A factorization costs up to `2/3 f³` for `f` free rows
    /// (an LU; phase 2's split costs less) and cannot be interrupted, so a
    /// caller with a time budget (the haptic tick) bounds it here. Default
    /// `usize::MAX` (no bound).
    pub subspace_max_rows: usize,
}

impl LcpSettings {
    /// Checks the parameters (names as fields of `ContactSettings::lcp`).
    pub fn validate(&self) -> Result<()> {
        // The stopping tests: each finite and non-negative (0: off).
        for (name, value) in [
            ("lcp.tolerance", self.tolerance),
            ("lcp.residual_tolerance", self.residual_tolerance),
            ("lcp.displacement_tolerance", self.displacement_tolerance),
        ] {
            check_range(name, value, 0.0, f64::MAX)?;
        }
        if !(self.over_relaxation > 0.0 && self.over_relaxation < 2.0) {
            return Err(SoftTissueError::InvalidParameter {
                name: "lcp.over_relaxation",
                value: self.over_relaxation,
                reason: "must lie in (0, 2)",
            });
        }
        if self.max_iterations == 0 {
            return Err(SoftTissueError::InvalidParameter {
                name: "lcp.max_iterations",
                value: 0.0,
                reason: "must be ≥ 1",
            });
        }
        Ok(())
    }
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
            subspace_max_rows: usize::MAX,
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
    /// Factorizations the subspace steps made: LUs of phase 1's Newton
    /// matrices and Cholesky factorizations of phase 2's `δ = 0` block (a
    /// chord step, a step that starts from the last solve's factors, or a
    /// reclassification of phase 2 that keeps the free rows and which
    /// contacts slide makes none; see
    /// [`super::LcpScratch::reuse_factorization`]).
    pub factorizations: usize,
    /// Whether the solve stopped at [`LcpSettings::max_iterations`] (or where
    /// the caller of [`super::solve_until`] stopped it) without meeting any
    /// of its tolerances.
    pub capped: bool,
    /// Relative natural-map residual of the answer ([`residual`]), dimensionless.
    pub residual: f64,
    /// Largest normal complementarity residual `|min(δ_n, W_nn λ_n)|` (metres).
    pub complementarity: f64,
    /// Largest friction residual (metres): per contact the smaller of `‖δ_t‖`
    /// (what sticking leaves) and the part of `δ_t` not opposed to `λ_t` plus
    /// `λ_t`'s distance from the cone's rim scaled by `W_tt` (what sliding
    /// leaves), plus any cone violation scaled by `W_tt`.
    pub friction: f64,
    /// Largest predicted penetration `max(−δ_n, 0)` (metres).
    pub penetration: f64,
}

/// What one sweep changed.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct SweepStats {
    pub(super) max_change: f64,
    pub(super) max_force: f64,
    pub(super) max_disp: f64,
}

/// `d += a · x`, vectorizable. With AVX2 the same loop in 256-bit lanes
/// (no fused multiply-add, so the result is the same to the bit).
pub(super) fn axpy(d: &mut [f64], a: f64, x: &[f64]) {
    #[cfg(target_arch = "x86_64")]
    if has_avx2_fma() {
        // SAFETY: the CPU supports the features the function is compiled for.
        return unsafe { axpy_avx2(d, a, x) };
    }
    axpy_portable(d, a, x);
}

#[inline(always)]
fn axpy_portable(d: &mut [f64], a: f64, x: &[f64]) {
    for (di, xi) in d.iter_mut().zip(x) {
        *di += a * xi;
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn axpy_avx2(d: &mut [f64], a: f64, x: &[f64]) {
    axpy_portable(d, a, x);
}

/// `delta = δ₀ + W λ` from scratch, as the sweeps keep it: the row of `W`
/// of each nonzero force times that force (`W` is symmetric, so its row is
/// its column), so only those rows are read. A solve's warm start has most
/// forces zero (about two thirds of them, weighted by `m`, on the accuracy
/// study's lens through the hole), where a product by rows would read all of
/// `W` (27 MB at 1 830 rows); that took the LCP's last 50 steps there from
/// 15.1–15.7 to 14.2–14.5 ms.
pub(super) fn exact_delta(w: &[f64], delta0: &[f64], lambda: &[f64], delta: &mut [f64]) {
    let m = delta0.len();
    delta.copy_from_slice(delta0);
    for (j, &l) in lambda.iter().enumerate() {
        if l != 0.0 {
            axpy(delta, l, &w[j * m..(j + 1) * m]);
        }
    }
}

/// Euclidean projection onto the cone `‖λ_t‖ ≤ μ λ_n`.
pub(super) fn project_cone(l: [f64; 3], mu: f64) -> [f64; 3] {
    let t = l[1].hypot(l[2]);
    if t <= mu * l[0] {
        return l;
    }
    if mu * t <= -l[0] {
        return [0.0; 3];
    }
    let n = (l[0] + mu * t) / (1.0 + mu * mu);
    let s = if t > 0.0 { mu * n / t } else { 0.0 };
    [n, l[1] * s, l[2] * s]
}

/// One contact's friction residual in metres, as [`LcpReport::friction`]
/// measures it: with forces `l = (λ_n, λ_t)`, tangential displacement `d`
/// (`δ_t`), friction coefficient `mu` and the larger tangential diagonal
/// `wtt` of `W`, the smaller of what sticking leaves (`‖δ_t‖`) and what
/// sliding leaves (the part of `δ_t` not opposed to `λ_t`, plus `λ_t`'s
/// distance inside the rim times `wtt`), plus any part of `λ_t` outside the
/// cone times `wtt` (all there is when `μ λ_n = 0`). The sliding branch is continuous at the rim: a `λ_t` a
/// rounding error inside it with `δ_t` opposed is not read as a sticking
/// contact that slides.
pub fn friction_residual(l: [f64; 3], d: [f64; 2], mu: f64, wtt: f64) -> f64 {
    let limit = mu * l[0];
    let lnorm = l[1].hypot(l[2]);
    let cone = (lnorm - limit).max(0.0) * wtt;
    if limit == 0.0 {
        return cone;
    }
    let dnorm = d[0].hypot(d[1]);
    let slide = if lnorm > 0.0 {
        let along = -(d[0] * l[1] + d[1] * l[2]) / lnorm;
        (dnorm * dnorm - along * along).max(0.0).sqrt()
            + (-along).max(0.0)
            + (limit - lnorm).max(0.0) * wtt
    } else {
        f64::INFINITY
    };
    dnorm.min(slide) + cone
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
    let (mut res2, mut scale2) = (0.0, 0.0);
    for c in 0..rows.len().saturating_sub(1) {
        let r = rows[c];
        let k = rows[c + 1] - r;
        let wnn = w[r * m + r];
        if wnn.is_nan() || wnn <= 0.0 {
            continue;
        }
        let rho = 1.0 / wnn;
        for &d0 in &delta0[r..r + k] {
            scale2 += (rho * d0).powi(2);
        }
        let l = [
            lambda[r],
            if k == 3 { lambda[r + 1] } else { 0.0 },
            if k == 3 { lambda[r + 2] } else { 0.0 },
        ];
        let contact_mu = if k == 3 { mu[c] } else { 0.0 };
        let e = if contact_mu > 0.0 {
            let (d1, d2) = (delta[r + 1], delta[r + 2]);
            let un = delta[r] + contact_mu * d1.hypot(d2);
            let z = [l[0] - rho * un, l[1] - rho * d1, l[2] - rho * d2];
            let p = project_cone(z, contact_mu);
            [l[0] - p[0], l[1] - p[1], l[2] - p[2]]
        } else {
            // Frictionless: the normal's natural map; any tangential force is wrong.
            [l[0] - (l[0] - rho * delta[r]).max(0.0), l[1], l[2]]
        };
        res2 += e[0] * e[0] + e[1] * e[1] + e[2] * e[2];
    }
    res2.sqrt() / scale2.sqrt().max(1e-300)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The dispatched `axpy` (AVX2 where the CPU has it) gives the portable
    /// loop's results to the bit, for every remainder length.
    #[test]
    fn dense_kernels_agree_to_the_bit_with_the_portable_loops() {
        let val = crate::math::test_value;
        for n in 0..23 {
            let x: Vec<f64> = (0..n).map(|i| val(i, 1)).collect();
            let y: Vec<f64> = (0..n).map(|i| val(i, 2)).collect();
            let (mut d1, mut d2) = (y.clone(), y.clone());
            axpy(&mut d1, 0.37, &x);
            axpy_portable(&mut d2, 0.37, &x);
            for i in 0..n {
                assert_eq!(d1[i].to_bits(), d2[i].to_bits(), "n {n}, i {i}");
                assert_eq!(d2[i].to_bits(), (y[i] + 0.37 * x[i]).to_bits());
            }
        }
    }

    /// `exact_delta` is `δ₀ + W λ` for a symmetric `W`, and reads no row of a
    /// zero force: those rows are NaN here, and the answer is finite.
    #[test]
    fn exact_delta_reads_the_rows_of_the_nonzero_forces_only() {
        let val = crate::math::test_value;
        let m = 11;
        let mut w = vec![0.0; m * m];
        for i in 0..m {
            for j in 0..=i {
                let v = val(i * m + j, 3);
                w[i * m + j] = v;
                w[j * m + i] = v;
            }
        }
        let lambda: Vec<f64> = (0..m)
            .map(|i| if i % 3 == 1 { 0.0 } else { val(i, 4) })
            .collect();
        let delta0: Vec<f64> = (0..m).map(|i| val(i, 5)).collect();
        let want: Vec<f64> = (0..m)
            .map(|r| delta0[r] + (0..m).map(|j| w[r * m + j] * lambda[j]).sum::<f64>())
            .collect();
        for (r, &l) in lambda.iter().enumerate() {
            if l == 0.0 {
                w[r * m..(r + 1) * m].fill(f64::NAN);
            }
        }
        let mut delta = vec![f64::NAN; m];
        exact_delta(&w, &delta0, &lambda, &mut delta);
        for r in 0..m {
            // Round-off of a sum of `m + 1` terms, a few ε of their magnitudes.
            let scale = delta0[r].abs()
                + (0..m)
                    .map(|j| (w[j * m + r] * lambda[j]).abs())
                    .filter(|v| !v.is_nan())
                    .sum::<f64>();
            assert!(
                (delta[r] - want[r]).abs() <= 1e-14 * scale,
                "row {r}: {} against {}",
                delta[r],
                want[r]
            );
        }
    }
}
