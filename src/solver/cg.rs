//! Preconditioned conjugate gradient on 3-vector blocks.

use crate::fem::assembly::BlockCsr;
use crate::math::{Vec3, dot};
use crate::solver::Preconditioner;

/// Stopping rule of the conjugate gradient.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CgSettings {
    /// Relative residual tolerance `‖b − A x‖ ≤ tol · ‖b‖`.
    pub tolerance: f64,
    /// Maximum number of iterations.
    pub max_iterations: usize,
    /// Start from the previous step's solution.
    pub warm_start: bool,
}

impl Default for CgSettings {
    fn default() -> Self {
        Self {
            tolerance: 1e-6,
            max_iterations: 200,
            warm_start: true,
        }
    }
}

/// What one conjugate-gradient solve did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct CgReport {
    /// Iterations run.
    pub iterations: usize,
    /// Final relative residual `‖b − A x‖ / ‖b‖`.
    pub residual: f64,
    /// Whether the tolerance was reached.
    pub converged: bool,
    /// Seconds spent applying the preconditioner.
    pub precond_seconds: f64,
}

/// Scratch vectors of the conjugate gradient (allocated once per body).
#[derive(Debug, Clone, Default)]
pub struct CgScratch {
    r: Vec<Vec3>,
    z: Vec<Vec3>,
    p: Vec<Vec3>,
    q: Vec<Vec3>,
}

impl CgScratch {
    /// Scratch for `n` nodes.
    pub fn new(n: usize) -> Self {
        let z = vec![Vec3::zeros(); n];
        Self {
            r: z.clone(),
            z: z.clone(),
            p: z.clone(),
            q: z,
        }
    }
}

/// Solves `A x = b` by preconditioned CG starting from `x`.
///
/// The iterate stays finite: if a non-finite or non-positive curvature appears
/// the solve stops, keeps the last finite iterate and reports `converged = false`.
pub fn solve(
    a: &BlockCsr,
    b: &[Vec3],
    x: &mut [Vec3],
    precond: &mut dyn Preconditioner,
    settings: &CgSettings,
    scratch: &mut CgScratch,
) -> CgReport {
    let CgScratch { r, z, p, q } = scratch;
    let bnorm = dot(b, b).sqrt();
    let mut report = CgReport::default();
    if bnorm == 0.0 {
        x.fill(Vec3::zeros());
        report.converged = true;
        return report;
    }
    a.mul_vec(x, q);
    for i in 0..b.len() {
        r[i] = b[i] - q[i];
    }
    let mut rnorm = dot(r, r).sqrt();
    if !rnorm.is_finite() {
        x.fill(Vec3::zeros());
        r.copy_from_slice(b);
        rnorm = bnorm;
    }
    let tol = settings.tolerance * bnorm;
    let t0 = std::time::Instant::now();
    precond.apply_first(a, r, z, q);
    report.precond_seconds += t0.elapsed().as_secs_f64();
    p.copy_from_slice(z);
    let mut rz = dot(r, z);
    while rnorm > tol && report.iterations < settings.max_iterations {
        a.mul_vec(p, q);
        let pq = dot(p, q);
        if !(pq > 0.0 && pq.is_finite() && rz.is_finite()) {
            break;
        }
        let alpha = rz / pq;
        if !alpha.is_finite() {
            break;
        }
        for i in 0..x.len() {
            x[i] += alpha * p[i];
            r[i] -= alpha * q[i];
        }
        report.iterations += 1;
        rnorm = dot(r, r).sqrt();
        if rnorm <= tol {
            break;
        }
        let t0 = std::time::Instant::now();
        precond.apply(r, z);
        report.precond_seconds += t0.elapsed().as_secs_f64();
        let rz_new = dot(r, z);
        let beta = rz_new / rz;
        if !beta.is_finite() {
            break;
        }
        rz = rz_new;
        for i in 0..p.len() {
            p[i] = z[i] + beta * p[i];
        }
    }
    report.residual = rnorm / bnorm;
    report.converged = rnorm <= tol;
    report
}
