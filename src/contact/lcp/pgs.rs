//! Projected Gauss–Seidel, row by row.
//!
//! Each contact's normal row takes a projected step on its diagonal, then
//! its two tangential rows solve their 2×2 block; when that solution leaves
//! the disc of radius `μ λ_n`, an isotropic projected step (step
//! `1/λ_max(W_tt)`) is taken instead, so that a sliding contact converges to
//! `λ_t` anti-parallel to `δ_t`. An over-relaxation factor `ω ∈ (0, 2)`
//! scales each update. The normal and tangential rows are solved one after
//! the other, not together, which is what makes it stall on strongly
//! coupled, sliding contacts (see [`super::block`]).

use super::types::{SweepStats, axpy};

/// One forward sweep, keeping `delta = δ₀ + W λ` up to date.
pub(super) fn sweep(
    w: &[f64],
    rows: &[usize],
    mu: &[f64],
    lambda: &mut [f64],
    delta: &mut [f64],
    omega: f64,
) -> SweepStats {
    let m = delta.len();
    let nc = rows.len().saturating_sub(1);
    let row = |r: usize| &w[r * m..(r + 1) * m];
    let mut stats = SweepStats::default();
    for c in 0..nc {
        let r = rows[c];
        let wnn = w[r * m + r];
        if wnn <= 0.0 {
            continue;
        }
        let old_n = lambda[r];
        let mut ln = (old_n - omega * delta[r] / wnn).max(0.0);
        if !ln.is_finite() {
            ln = 0.0;
        }
        if ln != old_n {
            lambda[r] = ln;
            axpy(delta, ln - old_n, row(r));
            stats.max_change = stats.max_change.max((ln - old_n).abs());
            stats.max_disp = stats.max_disp.max((ln - old_n).abs() * wnn);
        }
        stats.max_force = stats.max_force.max(ln);
        if rows[c + 1] - r == 3 {
            let (t1, t2) = (r + 1, r + 2);
            let (old1, old2) = (lambda[t1], lambda[t2]);
            let (d1, d2) = (delta[t1], delta[t2]);
            let (a, b, d) = (w[t1 * m + t1], w[t1 * m + t2], w[t2 * m + t2]);
            let det = a * d - b * b;
            let (mut l1, mut l2) = if det > 1e-300 * (a * d).abs().max(1e-300) {
                (
                    old1 - omega * (d * d1 - b * d2) / det,
                    old2 - omega * (a * d2 - b * d1) / det,
                )
            } else {
                (0.0, 0.0)
            };
            let limit = mu[c] * ln;
            if (l1 * l1 + l2 * l2).sqrt() > limit {
                // Sliding: an isotropic projected step, whose fixed point has δ_t
                // anti-parallel to λ_t (maximal dissipation) whatever W_tt's shape.
                let wmax = 0.5 * (a + d) + (0.25 * (a - d) * (a - d) + b * b).sqrt();
                l1 = old1 - omega * d1 / wmax;
                l2 = old2 - omega * d2 / wmax;
                let norm = (l1 * l1 + l2 * l2).sqrt();
                if norm > limit {
                    let s = if norm > 0.0 { limit / norm } else { 0.0 };
                    l1 *= s;
                    l2 *= s;
                }
            }
            if !(l1.is_finite() && l2.is_finite()) {
                l1 = 0.0;
                l2 = 0.0;
            }
            if l1 != old1 {
                lambda[t1] = l1;
                axpy(delta, l1 - old1, row(t1));
                stats.max_disp = stats.max_disp.max((l1 - old1).abs() * a);
            }
            if l2 != old2 {
                lambda[t2] = l2;
                axpy(delta, l2 - old2, row(t2));
                stats.max_disp = stats.max_disp.max((l2 - old2).abs() * d);
            }
            stats.max_change = stats
                .max_change
                .max((l1 - old1).abs())
                .max((l2 - old2).abs());
            stats.max_force = stats.max_force.max(l1.abs()).max(l2.abs());
        }
    }
    stats
}
