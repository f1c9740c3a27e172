//! Block Gauss–Seidel: each contact's three forces solved together, exactly.
//!
//! With the other contacts' forces fixed, contact `c` sees `δ_c = A λ_c + q`
//! (`A = W_cc`, 3×3, `q = δ_c − A λ_c` from the kept-up-to-date `δ`). Its
//! Signorini–Coulomb problem has one of three solutions, tried in order:
//!
//! 1. **open**: `q_n ≥ 0`, `λ_c = 0`;
//! 2. **stick**: `λ_c = −A⁻¹ q` when it lies in the cone `‖λ_t‖ ≤ μ λ_n`;
//! 3. **slide**: `λ_c = λ_n (1, −μ t̂)` with `δ_n = 0` and `δ_t = α t̂`,
//!    `α ≥ 0`: one equation in the angle of `t̂`, solved by Newton from the
//!    last direction, with a bracketing search when Newton fails.
//!
//! The local answer is exact to round-off whatever the shape of `A`, which is
//! what makes block Gauss–Seidel converge steadily where a per-row step that
//! approximates the cone stalls.

use super::types::{SweepStats, axpy, project_cone};

/// One contact's Signorini–Coulomb problem `δ = A λ + q`, solved exactly.
///
/// `a` is the contact's 3×3 block of `W` (rows normal, tangent 1, tangent
/// 2), `guess` the current forces (their direction seeds the sliding
/// search). Returns `None` only when no solution of the three kinds exists
/// (an indefinite block with a large `μ`); the caller then takes a projected
/// step instead.
pub fn local_coulomb(a: &[[f64; 3]; 3], q: [f64; 3], mu: f64, guess: [f64; 3]) -> Option<[f64; 3]> {
    if q[0] >= 0.0 {
        return Some([0.0; 3]);
    }
    if a[0][0] <= 0.0 {
        return None;
    }
    if mu <= 0.0 {
        return Some([-q[0] / a[0][0], 0.0, 0.0]);
    }
    // Stick.
    let stick = solve3(a, [-q[0], -q[1], -q[2]]);
    if let Some(l) = stick
        && l[0] > 0.0
        && l[1].hypot(l[2]) <= mu * l[0]
    {
        return Some(l);
    }
    // Slide. The direction t̂ of δ_t (λ_t = −μ λ_n t̂): from the current forces
    // when they slide, else from the stick trial's tangential force.
    let dir = |t: [f64; 2]| -> Option<f64> {
        let n = t[0].hypot(t[1]);
        (n > 0.0 && n.is_finite()).then(|| (-t[1]).atan2(-t[0]))
    };
    let theta0 = dir([guess[1], guess[2]])
        .or_else(|| stick.and_then(|l| dir([l[1], l[2]])))
        .unwrap_or(0.0);
    let slide = Slide { a, q, mu };
    let theta = slide
        .newton(theta0)
        .or_else(|| slide.bracket(theta0, 48))
        .or_else(|| slide.bracket(theta0, 2048))?;
    let e = slide.eval(theta)?;
    let (c, s) = (theta.cos(), theta.sin());
    Some([e.ln, -mu * e.ln * c, -mu * e.ln * s])
}

/// Solves the 3×3 system `a x = b` (Cramer's rule; `None` when singular).
fn solve3(a: &[[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let c00 = a[1][1] * a[2][2] - a[1][2] * a[2][1];
    let c01 = a[1][2] * a[2][0] - a[1][0] * a[2][2];
    let c02 = a[1][0] * a[2][1] - a[1][1] * a[2][0];
    let det = a[0][0] * c00 + a[0][1] * c01 + a[0][2] * c02;
    let scale = a[0][0].abs() * a[1][1].abs() * a[2][2].abs();
    if det.is_nan() || det.abs() <= 1e-14 * scale {
        return None;
    }
    let inv = 1.0 / det;
    let x0 = (b[0] * c00
        + b[1] * (a[0][2] * a[2][1] - a[0][1] * a[2][2])
        + b[2] * (a[0][1] * a[1][2] - a[0][2] * a[1][1]))
        * inv;
    let x1 = (b[0] * c01
        + b[1] * (a[0][0] * a[2][2] - a[0][2] * a[2][0])
        + b[2] * (a[0][2] * a[1][0] - a[0][0] * a[1][2]))
        * inv;
    let x2 = (b[0] * c02
        + b[1] * (a[0][1] * a[2][0] - a[0][0] * a[2][1])
        + b[2] * (a[0][0] * a[1][1] - a[0][1] * a[1][0]))
        * inv;
    let x = [x0, x1, x2];
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// The sliding equations of one contact as a function of the slip angle.
struct Slide<'a> {
    a: &'a [[f64; 3]; 3],
    q: [f64; 3],
    mu: f64,
}

/// The sliding state at one angle.
struct SlideEval {
    /// Normal force closing the gap.
    ln: f64,
    /// `δ_t × t̂`: zero when the slip is along `t̂`.
    cross: f64,
    /// `δ_t · t̂`: must not be negative (the force opposes the slip).
    along: f64,
    /// `d cross / dθ`.
    slope: f64,
}

impl Slide<'_> {
    /// The state at angle `theta`, or `None` when no positive normal force
    /// closes the gap with that slip direction.
    fn eval(&self, theta: f64) -> Option<SlideEval> {
        let (a, q, mu) = (self.a, self.q, self.mu);
        let (c, s) = (theta.cos(), theta.sin());
        let den = a[0][0] - mu * (a[0][1] * c + a[0][2] * s);
        if den.is_nan() || den <= 1e-12 * a[0][0] {
            return None;
        }
        let ln = -q[0] / den;
        // δ_t = λ_n (a_tn − μ A_tt t̂) + q_t.
        let g1 = a[1][0] - mu * (a[1][1] * c + a[1][2] * s);
        let g2 = a[2][0] - mu * (a[2][1] * c + a[2][2] * s);
        let (d1, d2) = (ln * g1 + q[1], ln * g2 + q[2]);
        let cross = d1 * s - d2 * c;
        let along = d1 * c + d2 * s;
        // Derivatives along u = dt̂/dθ = (−s, c).
        let dln = ln * mu * (-a[0][1] * s + a[0][2] * c) / den;
        let dg1 = -mu * (-a[1][1] * s + a[1][2] * c);
        let dg2 = -mu * (-a[2][1] * s + a[2][2] * c);
        let (e1, e2) = (dln * g1 + ln * dg1, dln * g2 + ln * dg2);
        let slope = (e1 * s - e2 * c) + along;
        Some(SlideEval {
            ln,
            cross,
            along,
            slope,
        })
    }

    /// The size of `δ_t` terms, for a round-off test on `cross`.
    fn scale(&self, ln: f64) -> f64 {
        let a = self.a;
        let big = a[1][0].abs().max(a[2][0].abs()) + self.mu * a[1][1].abs().max(a[2][2].abs());
        ln * big + self.q[1].abs() + self.q[2].abs()
    }

    fn accept(&self, e: &SlideEval) -> bool {
        e.along >= 0.0 && e.cross.abs() <= 1e-12 * self.scale(e.ln).max(1e-300)
    }

    /// Newton on the angle, steps at most half a radian.
    fn newton(&self, mut theta: f64) -> Option<f64> {
        for _ in 0..30 {
            let e = self.eval(theta)?;
            if self.accept(&e) {
                return Some(theta);
            }
            if e.slope == 0.0 || !e.slope.is_finite() {
                return None;
            }
            theta -= (e.cross / e.slope).clamp(-0.5, 0.5);
        }
        None
    }

    /// A search over the circle (`n` samples) for a sign change of `cross`
    /// where the force opposes the slip, refined by bisection; the root
    /// nearest `theta0` wins. Two roots closer than a sample apart cancel,
    /// hence a finer second search when the first finds none.
    fn bracket(&self, theta0: f64, n: usize) -> Option<f64> {
        let step = std::f64::consts::TAU / n as f64;
        let mut best: Option<(f64, f64)> = None;
        let mut prev: Option<(f64, SlideEval)> = None;
        for i in 0..=n {
            let t = theta0 + i as f64 * step;
            let cur = self.eval(t);
            if let (Some((t0, e0)), Some(e1)) = (&prev, &cur)
                && e0.cross.signum() != e1.cross.signum()
            {
                let (mut lo, mut hi, mut flo) = (*t0, t, e0.cross);
                let mut ok = true;
                for _ in 0..80 {
                    let mid = 0.5 * (lo + hi);
                    let Some(em) = self.eval(mid) else {
                        ok = false;
                        break;
                    };
                    if em.cross.signum() == flo.signum() {
                        lo = mid;
                        flo = em.cross;
                    } else {
                        hi = mid;
                    }
                }
                let root = 0.5 * (lo + hi);
                if ok
                    && let Some(er) = self.eval(root)
                    && er.along >= 0.0
                {
                    let dist = (root - theta0).min(theta0 + std::f64::consts::TAU - root);
                    if best.is_none_or(|(_, d)| dist < d) {
                        best = Some((root, dist));
                    }
                }
            }
            prev = cur.map(|e| (t, e));
        }
        best.map(|(t, _)| t)
    }
}

/// One forward sweep of block Gauss–Seidel over the contacts, keeping
/// `delta = δ₀ + W λ` up to date.
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
    let mut stats = SweepStats::default();
    for c in 0..nc {
        let r = rows[c];
        let k = rows[c + 1] - r;
        let wnn = w[r * m + r];
        if wnn.is_nan() || wnn <= 0.0 {
            continue;
        }
        let old = [
            lambda[r],
            if k == 3 { lambda[r + 1] } else { 0.0 },
            if k == 3 { lambda[r + 2] } else { 0.0 },
        ];
        let mut new = if k == 1 {
            [(old[0] - delta[r] / wnn).max(0.0), 0.0, 0.0]
        } else {
            let mut a = [[0.0; 3]; 3];
            for (i, ai) in a.iter_mut().enumerate() {
                ai.copy_from_slice(&w[(r + i) * m + r..(r + i) * m + r + 3]);
            }
            let mut q = [0.0; 3];
            for (i, qi) in q.iter_mut().enumerate() {
                *qi = delta[r + i] - (a[i][0] * old[0] + a[i][1] * old[1] + a[i][2] * old[2]);
            }
            local_coulomb(&a, q, mu[c], old).unwrap_or_else(|| projected(&a, q, mu[c], old))
        };
        if omega != 1.0 {
            // Relax, then back into the cone.
            for i in 0..3 {
                new[i] = old[i] + omega * (new[i] - old[i]);
            }
            new = project_cone(new, mu[c]);
        }
        if !new.iter().all(|v| v.is_finite()) {
            new = [0.0; 3];
        }
        for i in 0..k {
            let d = new[i] - old[i];
            if d != 0.0 {
                lambda[r + i] = new[i];
                axpy(delta, d, &w[(r + i) * m..(r + i + 1) * m]);
                stats.max_change = stats.max_change.max(d.abs());
                stats.max_disp = stats.max_disp.max(d.abs() * w[(r + i) * m + r + i]);
            }
            stats.max_force = stats.max_force.max(new[i].abs());
        }
    }
    stats
}

/// A projected step on the contact alone (the fallback when no exact local
/// solution exists): step `1/λ_max(A)` then back into the cone.
fn projected(a: &[[f64; 3]; 3], q: [f64; 3], mu: f64, old: [f64; 3]) -> [f64; 3] {
    // Gershgorin bound of the largest eigenvalue.
    let bound = (0..3)
        .map(|i| a[i].iter().map(|v| v.abs()).sum::<f64>())
        .fold(0.0, f64::max);
    if bound.is_nan() || bound <= 0.0 {
        return [0.0; 3];
    }
    let mut l = [0.0; 3];
    for i in 0..3 {
        let d = q[i] + a[i][0] * old[0] + a[i][1] * old[1] + a[i][2] * old[2];
        l[i] = old[i] - d / bound;
    }
    project_cone(l, mu)
}
