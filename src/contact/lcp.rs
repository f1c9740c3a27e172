//! Projected Gauss–Seidel for the Signorini LCP with Coulomb friction.
//!
//! Unknowns per contact: the normal force `λ_n ≥ 0` and, when `μ > 0`, the
//! tangential force `λ_t ∈ ℝ²`. With `δ = W λ + δ₀`:
//!
//! - normal: `0 ≤ δ_n ⊥ λ_n ≥ 0`;
//! - friction (**circular cone**, not a pyramid): `‖λ_t‖ ≤ μ λ_n`; sticking
//!   (`δ_t = 0`) inside the cone, sliding with `λ_t = −μ λ_n δ_t/‖δ_t‖` on it.
//!
//! Each sweep updates contacts in order: the normal row by a projected
//! step on its diagonal, then the two tangential rows by solving their 2×2
//! block; when that solution leaves the disc of radius `μ λ_n`, an isotropic
//! projected step (step `1/λ_max(W_tt)`) is taken instead, so that a sliding
//! contact converges to `λ_t` anti-parallel to `δ_t`. An
//! over-relaxation factor `ω ∈ (0, 2)` scales each update. The solve warm
//! starts from the previous step's forces and stops when, in one sweep, the
//! largest force change drops below `tolerance` times the largest force, or
//! the largest displacement change a contact's own update caused
//! (`|Δλ_r| W_rr`) drops below `displacement_tolerance`.
//!
//! ## Cost
//! `δ = δ₀ + W λ` is kept up to date: a row whose force changes adds its
//! column of `W` to `δ` (`W` is symmetric), and a row whose force stays (an
//! open contact at `λ = 0`, the many alarm-band contacts) costs one read. A
//! sweep therefore costs `m` multiply-adds per *changed* row, not `m²`, and
//! the residuals are recomputed from scratch at the end, so nothing drifts
//! into the report.

/// Settings of the projected Gauss–Seidel solver.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LcpSettings {
    /// Maximum sweeps.
    pub max_iterations: usize,
    /// Relative force change that ends the sweeps.
    pub tolerance: f64,
    /// Displacement change (metres) below which a sweep ends the solve: the
    /// largest `|Δλ_r| W_rr` of the sweep. `0` (the default) uses the force
    /// criterion alone. A positive value trades accuracy for time: on a large,
    /// strongly coupled contact set Gauss–Seidel moves slowly, so small changes
    /// per sweep do not mean small errors. In the cataract scene, 1e-9 m cut
    /// the sweeps by half but left the vectis's friction forces unconverged,
    /// and the squeezed lens was shot out of the eye in about one run of six.
    pub displacement_tolerance: f64,
    /// Over-relaxation factor ω in (0, 2); 1 is plain Gauss–Seidel.
    pub over_relaxation: f64,
    /// Start from the previous step's forces of persisting contacts.
    pub warm_start: bool,
}

impl Default for LcpSettings {
    fn default() -> Self {
        Self {
            max_iterations: 500,
            tolerance: 1e-8,
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
    /// Largest normal complementarity residual `|min(δ_n, W_nn λ_n)|` (metres).
    pub complementarity: f64,
    /// Largest friction residual (metres): `‖δ_t‖` when sticking, the part of
    /// `δ_t` not opposed to `λ_t` when sliding, plus any cone violation scaled by `W_tt`.
    pub friction: f64,
    /// Largest predicted penetration `max(−δ_n, 0)` (metres).
    pub penetration: f64,
}

/// `d += a · x`, vectorizable.
fn axpy(d: &mut [f64], a: f64, x: &[f64]) {
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

/// Solves the LCP in place. `w` is the dense, symmetric `m × m` matrix
/// (row-major), `rows[c]..rows[c+1]` the rows of contact `c` (1 or 3), `mu[c]`
/// its friction. `delta` is scratch; on return it holds `δ = W λ + δ₀`.
pub fn solve(
    w: &[f64],
    delta0: &[f64],
    rows: &[usize],
    mu: &[f64],
    lambda: &mut [f64],
    settings: &LcpSettings,
    delta: &mut Vec<f64>,
) -> LcpReport {
    let m = delta0.len();
    let nc = rows.len().saturating_sub(1);
    let omega = settings.over_relaxation;
    let row = |r: usize| &w[r * m..(r + 1) * m];
    let exact = |delta: &mut Vec<f64>, lambda: &[f64]| {
        delta.clear();
        delta.extend((0..m).map(|r| delta0[r] + dot(row(r), lambda)));
    };
    exact(delta, lambda);
    let mut report = LcpReport::default();
    for it in 0..settings.max_iterations {
        let mut max_change: f64 = 0.0;
        let mut max_force: f64 = 0.0;
        let mut max_disp: f64 = 0.0;
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
                max_change = max_change.max((ln - old_n).abs());
                max_disp = max_disp.max((ln - old_n).abs() * wnn);
            }
            max_force = max_force.max(ln);
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
                    max_disp = max_disp.max((l1 - old1).abs() * a);
                }
                if l2 != old2 {
                    lambda[t2] = l2;
                    axpy(delta, l2 - old2, row(t2));
                    max_disp = max_disp.max((l2 - old2).abs() * d);
                }
                max_change = max_change.max((l1 - old1).abs()).max((l2 - old2).abs());
                max_force = max_force.max(l1.abs()).max(l2.abs());
            }
        }
        report.iterations = it + 1;
        if max_change <= settings.tolerance * max_force.max(1e-300)
            || max_disp <= settings.displacement_tolerance
        {
            break;
        }
    }
    exact(delta, lambda);
    // Residuals of the final iterate.
    for c in 0..nc {
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

/// Identity of a contact across steps: (body id, vertex, other side), where the
/// other side is a tool index or a body id.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct ContactKey {
    /// Id of the vertex's body ([`crate::body::DeformableBody::id`]).
    pub body: u64,
    /// The vertex.
    pub node: u32,
    /// What the vertex touches.
    pub other: OtherKey,
}

/// The other side of a [`ContactKey`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum OtherKey {
    /// A tool, by index.
    Tool(usize),
    /// A body, by id.
    Body(u64),
}

/// Forces of the last step's first pass by contact, to start the next solve from.
#[derive(Debug, Default)]
pub struct WarmStart {
    previous: std::collections::HashMap<ContactKey, [f64; 3]>,
}

impl WarmStart {
    /// Copies the remembered forces of the contacts `keys` into `lambda`
    /// (`rows[c]..rows[c+1]` are the rows of contact `c`).
    pub fn apply(
        &self,
        keys: impl Iterator<Item = ContactKey>,
        rows: &[usize],
        lambda: &mut [f64],
    ) {
        for (ci, key) in keys.enumerate() {
            if let Some(prev) = self.previous.get(&key) {
                let r = rows[ci];
                let k = rows[ci + 1] - r;
                lambda[r..r + k].copy_from_slice(&prev[..k]);
            }
        }
    }

    /// Forgets every remembered force.
    pub fn clear(&mut self) {
        self.previous.clear();
    }

    /// Remembers the force `f` of contact `key`.
    pub fn remember(&mut self, key: ContactKey, f: [f64; 3]) {
        self.previous.insert(key, f);
    }
}
