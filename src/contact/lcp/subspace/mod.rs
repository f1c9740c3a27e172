//! Subspace steps: a semismooth Newton method on the active set.
//!
//! Gauss–Seidel moves the forces of a large, strongly coupled contact set
//! slowly: `W` from a soft body has small eigenvalues (the whole lens
//! squeezed), and each sweep reduces their error by little (on the cataract
//! jam's recorded problems, projected Gauss–Seidel stays above a relative
//! residual of 1e-6 after 1 000 sweeps on most of them). A Newton step on
//! the right active set gets the forces in a few linear solves. Each
//! iteration:
//!
//! 1. **Classify** every contact by the natural map `z = λ − ρ ũ`
//!    (`ρ = 1/W_nn`, the primal–dual active set): *open* (`z` in the polar
//!    cone: forces zero), *stick* (`z` in the cone: `δ = 0`), or *slide*
//!    (otherwise: `δ_n = 0` and `λ_t = μ λ_n P(z_t)`, `P(v) = v/‖v‖`).
//! 2. **Newton** on those equations over the free force rows, with dense
//!    factorizations (faer, sequential), its `δ = 0` rows damped by a shift
//!    of their diagonal ([`NEWTON_SHIFTS`]). Phase 1's system is the
//!    symmetric `δ = 0` block plus one column per sliding contact: a Cholesky
//!    factorization of the block and an LU of the sliding contacts' few rows
//!    ([`solve_phase1`](system::solve_phase1)), with an LU of the whole where
//!    more than a quarter of the free rows slide or the Cholesky fails.
//!    Phase 2's is split at the sliding rows ([`Split`](scratch::Split)): a Cholesky
//!    factorization of its symmetric `δ = 0` block (phase 1's last one, where
//!    the rows are the same) and an LU of the Schur complement on the sliding
//!    rows (two per sliding contact), with an LU of the whole where the
//!    Cholesky fails. The system and its solves are in [`system`].
//!    - *Phase 1*, until the free rows stop changing: a sliding contact is
//!      put on the cone's rim in the direction of `z_t` and only its normal
//!      force is free (its column of `W` carries the tangential force
//!      `μ λ_n P`). This finds the active set robustly, but converges only
//!      linearly in the slip directions. It ends as soon as a Newton step's
//!      result classifies into the free rows that step used, before a
//!      second factorization of the same rows (on the cataract jam's
//!      recorded problems this cut the median time to 10⁻⁶ by 16–20 %).
//!    - *Phase 2*: a sliding contact's tangential forces are free too, with
//!      the linearized `λ_t = μ λ_n P(z_t)`:
//!      `(I − κQ) Δλ_t − μ P Δλ_n + κ ρ Q Δδ_t = −(λ_t − μ λ_n P)`,
//!      `Q = I − P Pᵀ`, `κ = μ λ_n / ‖z_t‖` (Alart–Curnier's generalized
//!      Newton), which converges quadratically from there. Started cold it
//!      cycles between active sets, hence phase 1.
//! 3. Stop at the residual target, after [`MAX_ITERATIONS`], or when phase 2
//!    has classified [`PHASE2_CLASSIFICATIONS`] times (it classifies again
//!    each time the residual ([`residual`]) stops halving).
//! 4. **Cycles.** The primal–dual update flips every contact that looks
//!    violated at once. Where two or three coupled contacts decide each
//!    other's class (a sliding contact whose load a frictionless neighbour
//!    takes over when it sticks), the classes can cycle, the right
//!    combination never tried: on two recorded cataract jam problems
//!    (`benches/data/jam_hard_*.lcp`) the solve then took 256 sweeps and
//!    ran to 2 000 (at 3·10⁻⁵). The solve's second step, when it saw a
//!    class vector come back, tries the classes of the contacts that changed
//!    within the cycle (at most [`MAX_TOGGLING`]) in every combination,
//!    fewest changes first, each followed by a few Newton iterations: both
//!    now meet 10⁻⁶ in two sweeps. Once per solve, so a problem it cannot
//!    settle costs at most one enumeration (some cannot: where the right
//!    classes also differ outside the cycle).
//!
//! The iterates are not projected (the active set follows the unprojected
//! forces, as a primal–dual active-set method needs); the best one is put
//! back into each contact's cone and kept only when its residual beats the
//! one the step started from. The block Gauss–Seidel sweep before each step
//! gives it a start near the active set and corrects what a rejected step
//! leaves.
//!
//! Cost per iteration: a factorization of the free rows (`2/3 |F|³` for an
//! LU of the whole, about half that by the Cholesky factors below) and `m` per
//! changed force to keep `δ = δ₀ + W λ` (a Newton update changes the free
//! rows only), against `m` per changed row for a sweep. Within phase 2, an
//! iteration on the same active set as the last factorization reuses it (a
//! chord step: only the sliding rows' linearization has moved), triangular
//! solves instead of a factorization; when the residual then stops halving,
//! the contacts are classified again and the matrix refactored. On the
//! accuracy study's lens through the hole (up to 1 830 rows, 570 free) the
//! two cut the LCP's mean from 12.3 to 8.8 ms per step; on 45 recorded
//! cataract jam problems the median to 10⁻⁶ from 1.37 to 0.93 ms.
//!
//! Phase 2's split costs `|A|³/3` for the Cholesky factor, `2 |A|² |S|` for
//! `X = K⁻¹ W_AS` and `2 |A| |S|²` for the Schur complement, against
//! `2/3 (|A| + |S|)³` for the LU of the whole; and where a classification
//! keeps the free rows and which contacts slide (a fifth of phase 2's
//! factorizations on the lens through the hole), only `C_SA`, `D_SS` and the
//! Schur complement are made again. Matrices are filled a column at a time
//! (a row of `W`, contiguous writes). See docs/benchmark-log.md, "A split
//! Newton matrix", for what these save. Phase 1 by Cholesky, and phase 2's
//! first split taking its factor, cut the LCP's time over the last 50 steps
//! of the lens through the hole (430 contacts on average) from 15.3–16.1 to
//! 13.7–14.4 ms (the deterministic `AsyncLagged { lag: 2 }`, three runs
//! each, alternating), with the same sweeps; on 392 recorded cataract jam
//! problems the total time to 10⁻⁶ went from 351–357 to 338–343 ms.

use super::types::{axpy, project_cone, residual};

mod scratch;
mod system;

pub(super) use scratch::SubspaceScratch;
use scratch::{Kind, Slide};
use system::solve_newton;

/// Most Newton iterations in one subspace step.
pub const MAX_ITERATIONS: usize = 16;

/// Most iterations of phase 1 (it can cycle between a few active sets).
const PHASE1_ITERATIONS: usize = 5;

/// Most classifications in phase 2. With three, a recorded cataract jam
/// problem (`benches/data/jam_hard_c206.lcp`) stayed at 3·10⁻⁴ through every
/// step until Gauss–Seidel found its active set after about 500 sweeps; with
/// eight it meets 10⁻⁶ in two sweeps, and of 4 253 recorded problems 4 244
/// instead of 4 240 meet 10⁻⁶ within 100 sweeps, all 4 253 instead of 4 249
/// meet 10⁻⁴ within 100.
const PHASE2_CLASSIFICATIONS: usize = 8;

/// The relative shifts of the diagonal of the Newton matrix's `δ_r = 0` rows,
/// one per subspace step of a solve, in turn (the solve's first step uses the
/// first, a retry the next, and so on). A step with shift `ε` solves
/// `(W_FF + ε diag W_FF) Δλ = −δ_F`: a proximal (Levenberg–Marquardt) damping.
/// A point where the step is zero still has `δ_F = 0`, so an active set's
/// solution is the same; only the way there changes. Along well-conditioned
/// directions of `W_FF` a damped step leaves a fraction of about `ε` of the
/// error; along its near-null directions (several contacts sharing nodes,
/// nearly dependent rows) it no longer moves the forces without bound. Those
/// moves made the classes cycle on the cataract jam's hardest recorded
/// problems: near a relative residual of 10⁻⁵ one contact changing class sent
/// the next iterate to 10⁻², every time (`benches/data/jam_stall_c151.lcp`:
/// 2 000 sweeps, capped at 9.6·10⁻⁵, with every step undamped).
///
/// The first step is undamped (10⁻¹⁰, the shift every step had before), so a
/// solve that its first step finishes, nearly every solve in the scene,
/// gives the answer it gave before; only the retries are damped. Damping the
/// first step as well (10⁻³ or 3·10⁻³) settled a few more recorded problems,
/// but the cataract scene lost the lens in 6 of 120 runs with it against none
/// of 20 without, the same hours (and about one in 50 to 150 before): see
/// docs/benchmark-log.md, "Damped Newton steps".
pub(super) const NEWTON_SHIFTS: [f64; 3] = [1e-10, 1e-3, 1e-2];

/// Tries one subspace step from `lambda` (with `delta = δ₀ + W λ` and its
/// residual `current`) toward residual `target`. Returns the new residual
/// when the step was kept (then `lambda` and `delta` hold the new forces),
/// `None` otherwise. The step ends early, with the best iterate so far, when
/// an active set has more than `max_rows` free rows (before its LU) or when
/// `stop()` says so (checked before each Newton iteration after the first).
#[allow(clippy::too_many_arguments)]
pub(super) fn step(
    w: &[f64],
    delta0: &[f64],
    rows: &[usize],
    mu: &[f64],
    lambda: &mut [f64],
    delta: &mut [f64],
    current: f64,
    target: f64,
    max_rows: usize,
    s: &mut SubspaceScratch,
    stop: &mut dyn FnMut() -> bool,
) -> Option<f64> {
    let m = delta0.len();
    s.lambda.clear();
    s.lambda.extend_from_slice(lambda);
    s.delta.clear();
    s.delta.extend_from_slice(delta);
    s.slide.clear();
    s.slide.resize(m, None);
    s.kind.clear();
    s.kind.resize(m, Kind::Open);
    s.history.clear();
    // One class vector per iteration at most: sized up front, so that a
    // solve needing more iterations than any before does not grow it.
    s.history.reserve(m * MAX_ITERATIONS);
    s.hold.clear();
    s.hold.resize(m, None);
    s.best.clear();
    s.last.clear();
    // With the LU of the last step's active set at hand (same `W`, see
    // `reuse`), start in phase 2 and try it first: a warm-started re-solve
    // (a haptic tick) usually keeps its active set. Not in a step that may
    // enumerate (one after a miss): it starts cold, where phase 1 sees the
    // cycle.
    let warm = s.reuse && !s.enumerate && !s.lu_free.is_empty();
    if !warm {
        // `W` may have changed since the last step: no factor is kept.
        s.forget();
    }
    let mut best = f64::INFINITY;
    let mut last_r = f64::INFINITY;
    let mut full = warm;
    let mut phase1 = 0;
    let mut reclassify = true;
    let mut reclassified = 0;
    let mut cycle = None;
    for it in 0..MAX_ITERATIONS {
        if it > 0 && stop() {
            break;
        }
        // Phase 2 classifies, then runs Newton on that active set until the
        // residual stops falling fast, then classifies again.
        s.prev.clone_from(&s.lambda);
        let frozen = full && !reclassify;
        classify(w, rows, mu, s, full, frozen);
        if !full && !s.last.is_empty() && s.free == s.last {
            // The last Newton step's active set classifies its own result
            // again: phase 1 has found it. On to phase 2 from the best
            // iterate, without a second factorization of the same rows.
            full = true;
            resume_from_best(s);
            s.prev.clone_from(&s.lambda);
            classify(w, rows, mu, s, full, false);
        }
        // Each new class vector once; a repeat of an older one is a cycle.
        let k = s.history.len() / m.max(1);
        if k == 0 || s.history[(k - 1) * m..] != s.kind[..] {
            if cycle.is_none() {
                cycle = (0..k)
                    .find(|&j| s.history[j * m..(j + 1) * m] == s.kind[..])
                    .map(|j| j..k);
            }
            s.history.extend_from_slice(&s.kind);
        }
        if full && reclassify {
            reclassify = false;
            reclassified += 1;
        }
        if s.free.is_empty() || s.free.len() > max_rows {
            break;
        }
        // On an unchanged active set, the last LU (a chord step: the
        // sliding rows' linearization moves a little, the rest not at all).
        let chord = (frozen || warm && it == 0) && s.free == s.lu_free;
        if !chord {
            // The factors in `mat` are overwritten below.
            s.lu_free.clear();
        }
        let Some(r) = newton(w, delta0, rows, mu, s, full, chord) else {
            return not_kept(s);
        };
        if full && !chord {
            s.lu_free.clone_from(&s.free);
        }
        if !r.is_finite() {
            return not_kept(s);
        }
        if r < best {
            best = r;
            s.best.clone_from(&s.lambda);
            s.best_delta.clone_from(&s.delta);
        }
        if r <= target {
            break;
        }
        if !full {
            phase1 += 1;
            if phase1 == PHASE1_ITERATIONS {
                // Cycling between active sets (a settled one is caught at the
                // next classification): on to phase 2 from the best iterate.
                full = true;
                resume_from_best(s);
            }
            std::mem::swap(&mut s.free, &mut s.last);
        } else if r > 0.5 * last_r {
            // Newton on this active set has done what it can.
            if reclassified == PHASE2_CLASSIFICATIONS {
                break;
            }
            reclassify = true;
        }
        last_r = r;
    }
    if let Some(window) = cycle.filter(|_| s.enumerate && best > target && !s.best.is_empty()) {
        enumerate(
            w, delta0, rows, mu, target, max_rows, window, s, &mut best, stop,
        );
    }
    if s.best.is_empty() {
        return not_kept(s);
    }
    // The best iterate, back in the cone, if it beats the start (its `δ`
    // kept by the changed rows).
    std::mem::swap(&mut s.lambda, &mut s.best);
    std::mem::swap(&mut s.delta, &mut s.best_delta);
    s.prev.clone_from(&s.lambda);
    project(rows, mu, s);
    update_delta(w, &s.prev, &s.lambda, &mut s.delta);
    let new = residual(w, delta0, rows, mu, &s.lambda, &s.delta);
    if new < current {
        lambda.copy_from_slice(&s.lambda);
        delta.copy_from_slice(&s.delta);
        Some(new)
    } else {
        not_kept(s)
    }
}

/// Most contacts whose classes [`enumerate`] combines (at most 3⁴ = 81
/// combinations).
const MAX_TOGGLING: usize = 4;

/// Newton iterations per combination in [`enumerate`]: two of phase 1 on the
/// held classes, then phase 2.
const ENUMERATED_ITERATIONS: usize = 5;

/// Where the classification cycled (a class vector came back: `window` are
/// the entries of `s.history` from its first occurrence to the one before
/// it came back), the primal–dual update flips every
/// contact that looks violated at once, and on the cataract's hard jam
/// problems two or three coupled contacts (a sliding or sticking one whose
/// load a frictionless neighbour takes over) flip back and forth forever,
/// the right combination never tried. Each combination of classes of the
/// contacts that changed within the cycle (open, push; or open, stick,
/// slide) is held, the fewest changes from the last classification first,
/// and followed by a few Newton iterations from the best iterate (the other
/// contacts classified freely); the first to reach `target` ends it. The
/// best result is left in `s.best`, `best` its residual. `stop()` is asked
/// before each combination.
#[allow(clippy::too_many_arguments)]
fn enumerate(
    w: &[f64],
    delta0: &[f64],
    rows: &[usize],
    mu: &[f64],
    target: f64,
    max_rows: usize,
    window: std::ops::Range<usize>,
    s: &mut SubspaceScratch,
    best: &mut f64,
    stop: &mut dyn FnMut() -> bool,
) {
    let m = delta0.len();
    let k = s.history.len() / m.max(1);
    s.toggling.clear();
    for c in 0..rows.len().saturating_sub(1) {
        let r = rows[c];
        let first = s.history[window.start * m + r];
        if window.clone().any(|i| s.history[i * m + r] != first) {
            s.toggling.push(r);
        }
    }
    if s.toggling.is_empty() || s.toggling.len() > MAX_TOGGLING {
        return;
    }
    // The classes a contact can take, and the one of the last classification.
    let classes = |r: usize| {
        let c = rows.partition_point(|&x| x < r);
        if rows[c + 1] - r == 3 && mu[c] > 0.0 {
            &[Kind::Open, Kind::Stick, Kind::Slide][..]
        } else {
            &[Kind::Open, Kind::Push][..]
        }
    };
    let last_class = (k - 1) * m;
    let total: usize = s.toggling.iter().map(|&r| classes(r).len()).product();
    'changes: for changes in 0..=s.toggling.len() {
        for code in 0..total {
            let (mut rest, mut changed) = (code, 0);
            for &r in &s.toggling {
                let options = classes(r);
                let kind = options[rest % options.len()];
                rest /= options.len();
                changed += usize::from(kind != s.history[last_class + r]);
                s.hold[r] = Some(kind);
            }
            if changed != changes {
                continue;
            }
            if stop() {
                break 'changes;
            }
            s.lambda.clone_from(&s.best);
            s.delta.clone_from(&s.best_delta);
            let mut last = f64::INFINITY;
            for it in 0..ENUMERATED_ITERATIONS {
                let full = it >= 2;
                s.prev.clone_from(&s.lambda);
                classify(w, rows, mu, s, full, false);
                if s.free.is_empty() || s.free.len() > max_rows {
                    break;
                }
                let Some(r) = newton(w, delta0, rows, mu, s, full, false) else {
                    break;
                };
                if r < *best {
                    *best = r;
                    s.best.clone_from(&s.lambda);
                    s.best_delta.clone_from(&s.delta);
                }
                if r <= target {
                    break 'changes;
                }
                if full && r > 0.5 * last {
                    break;
                }
                last = r;
            }
        }
    }
    for &r in &s.toggling {
        s.hold[r] = None;
    }
    // `mat` holds some combination's LU.
    s.lu_free.clear();
}

/// One Newton iteration after a classification: `δ` of the classified
/// forces, the step over the free rows (`chord`: on the LU in `s.mat`), the
/// new forces (in phase 1 a sliding contact's tangential force follows its
/// normal force) and their `δ`. Returns the new residual, `None` when the
/// linear solve failed.
fn newton(
    w: &[f64],
    delta0: &[f64],
    rows: &[usize],
    mu: &[f64],
    s: &mut SubspaceScratch,
    full: bool,
    chord: bool,
) -> Option<f64> {
    let m = delta0.len();
    update_delta(w, &s.prev, &s.lambda, &mut s.delta);
    solve_newton(w, m, s, full, chord)?;
    s.prev.clone_from(&s.lambda);
    for (&r, &d) in s.free.iter().zip(&s.rhs) {
        s.lambda[r] += d;
        if let (false, Some(Slide { p, mu, .. })) = (full, s.slide[r]) {
            let k = mu * s.lambda[r];
            s.lambda[r + 1] = k * p[0];
            s.lambda[r + 2] = k * p[1];
        }
    }
    update_delta(w, &s.prev, &s.lambda, &mut s.delta);
    Some(residual(w, delta0, rows, mu, &s.lambda, &s.delta))
}

/// A step that was not kept leaves no LU to start from: the next starts
/// cold, with phase 1.
fn not_kept(s: &mut SubspaceScratch) -> Option<f64> {
    s.forget();
    None
}

/// Phase 2 starts from the best iterate so far (when there is one) and its
/// `δ`.
fn resume_from_best(s: &mut SubspaceScratch) {
    if !s.best.is_empty() {
        s.lambda.clone_from(&s.best);
        s.delta.clone_from(&s.best_delta);
    }
}

/// `δ += W (λ − λ_prev)` over the rows whose force changed (`W` is
/// symmetric, so row `r` is column `r`): `m` multiply-adds per changed row,
/// where forming `δ₀ + W λ` again ([`super::types::exact_delta`]) would take
/// `m` per nonzero force. A Newton update changes the free rows only (a third
/// of them on the accuracy study's lens through the hole) and a
/// classification a few, so this was 40 % of a subspace step.
fn update_delta(w: &[f64], prev: &[f64], lambda: &[f64], delta: &mut [f64]) {
    let m = delta.len();
    for (r, (&a, &b)) in prev.iter().zip(lambda).enumerate() {
        if a != b {
            axpy(delta, b - a, &w[r * m..(r + 1) * m]);
        }
    }
}

/// Step 1: the free rows and the sliding linearizations from the natural
/// map of the candidate; open contacts' forces are zeroed.
fn classify(
    w: &[f64],
    rows: &[usize],
    mu: &[f64],
    s: &mut SubspaceScratch,
    full: bool,
    frozen: bool,
) {
    let m = s.delta.len();
    s.free.clear();
    for c in 0..rows.len().saturating_sub(1) {
        let r = rows[c];
        let old_slide = s.slide[r].take();
        let wnn = w[r * m + r];
        if wnn.is_nan() || wnn <= 0.0 {
            continue;
        }
        let rho = 1.0 / wnn;
        let (l, d) = (&mut s.lambda, &s.delta);
        let friction = rows[c + 1] - r == 3 && mu[c] > 0.0;
        if !friction {
            let push = if let Some(k) = s.hold[r] {
                k == Kind::Push
            } else if frozen {
                s.kind[r] == Kind::Push
            } else {
                l[r] - rho * d[r] > 0.0
            };
            s.kind[r] = if push { Kind::Push } else { Kind::Open };
            if push {
                s.free.push(r);
            } else {
                l[r] = 0.0;
            }
            if rows[c + 1] - r == 3 {
                l[r + 1] = 0.0;
                l[r + 2] = 0.0;
            }
            continue;
        }
        let mu = mu[c];
        let (d1, d2) = (d[r + 1], d[r + 2]);
        let un = d[r] + mu * d1.hypot(d2);
        let z = [l[r] - rho * un, l[r + 1] - rho * d1, l[r + 2] - rho * d2];
        let zt = z[1].hypot(z[2]);
        if let Some(k) = s.hold[r] {
            s.kind[r] = k;
        } else if !frozen {
            s.kind[r] = if zt <= mu * z[0] {
                Kind::Stick
            } else if mu * zt <= -z[0] {
                Kind::Open
            } else {
                Kind::Slide
            };
        }
        match s.kind[r] {
            Kind::Stick => s.free.extend([r, r + 1, r + 2]),
            Kind::Slide => {
                let p = if zt > 0.0 {
                    [z[1] / zt, z[2] / zt]
                } else {
                    old_slide.map_or([1.0, 0.0], |o| o.p)
                };
                s.slide[r] = Some(Slide {
                    p,
                    kappa: if zt > 0.0 {
                        (mu * l[r].max(0.0) / zt).min(1.0)
                    } else {
                        1.0
                    },
                    rho,
                    mu,
                });
                if full {
                    s.free.extend([r, r + 1, r + 2]);
                } else {
                    // On the rim in the direction of z_t, the normal force free.
                    let pz = project_cone(z, mu);
                    l[r..r + 3].copy_from_slice(&pz);
                    s.free.push(r);
                }
            }
            _ => l[r..r + 3].fill(0.0),
        }
    }
}

/// Puts every contact of the candidate back into its cone.
fn project(rows: &[usize], mu: &[f64], s: &mut SubspaceScratch) {
    for c in 0..rows.len().saturating_sub(1) {
        let r = rows[c];
        let l = &mut s.lambda;
        if rows[c + 1] - r == 3 {
            let v = project_cone([l[r], l[r + 1], l[r + 2]], mu[c]);
            l[r..r + 3].copy_from_slice(&v);
        } else {
            l[r] = l[r].max(0.0);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::system::{SPLIT_BACKWARD_ERROR, backward_error, newton_matrix, phase1_slides};
    use super::*;

    /// A contact problem for a Newton step.
    struct Problem {
        w: Vec<f64>,
        rows: Vec<usize>,
        mu: Vec<f64>,
        lambda: Vec<f64>,
        delta: Vec<f64>,
    }

    /// A random symmetric positive definite `W` (`B Bᵀ + I/10`), forces and
    /// `δ` for `contacts` friction contacts and two frictionless ones.
    fn problem(seed: u64, contacts: usize) -> Problem {
        let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        let mut rows: Vec<usize> = (0..contacts).map(|c| 3 * c).collect();
        rows.extend([3 * contacts, 3 * contacts + 1, 3 * contacts + 2]);
        let m = 3 * contacts + 2;
        let b: Vec<f64> = (0..m * m).map(|_| next()).collect();
        let mut w = vec![0.0; m * m];
        for i in 0..m {
            for j in 0..m {
                let d: f64 = (0..m).map(|k| b[i * m + k] * b[j * m + k]).sum();
                w[i * m + j] = d + if i == j { 0.1 } else { 0.0 };
            }
        }
        let mut mu = vec![0.5; contacts];
        mu.extend([0.0, 0.0]);
        let lambda: Vec<f64> = (0..m)
            .map(|i| {
                if i % 3 == 0 {
                    2.0 + next()
                } else {
                    2.0 * next()
                }
            })
            .collect();
        let delta: Vec<f64> = (0..m).map(|_| next()).collect();
        Problem {
            w,
            rows,
            mu,
            lambda,
            delta,
        }
    }

    /// A subspace step's scratch at the forces `lambda` with their `delta`,
    /// the first shift, no contact classified yet; `lu_only`: every Newton
    /// step by one LU of the whole matrix.
    fn scratch(lambda: &[f64], delta: &[f64], lu_only: bool) -> SubspaceScratch {
        let m = delta.len();
        let mut s = SubspaceScratch::default();
        s.split.lu_only = lu_only;
        s.set_shift(NEWTON_SHIFTS[0]);
        s.lambda.extend_from_slice(lambda);
        s.delta.extend_from_slice(delta);
        s.slide.resize(m, None);
        s.kind.resize(m, Kind::Open);
        s.hold.resize(m, None);
        s
    }

    /// Two Newton steps agree to 10⁻⁹ of the larger entry of `b`.
    fn assert_same_step(a: &[f64], b: &[f64], seed: u64) {
        let scale = b.iter().fold(0.0f64, |x, v| x.max(v.abs()));
        let err = a
            .iter()
            .zip(b)
            .fold(0.0f64, |x, (u, v)| x.max((u - v).abs()));
        assert!(
            err <= 1e-9 * scale,
            "seed {seed}: the steps differ by {err:.3e} (scale {scale:.3e})"
        );
    }

    /// Phase 1's Newton step by Cholesky and the low-rank correction of its
    /// sliding columns ([`solve_phase1`]) and by one LU of the whole matrix,
    /// on random problems with sticking and sliding contacts: the same step.
    /// Phase 2's first split on the same rows then takes phase 1's Cholesky
    /// factor (no new factorization) and gives the step of one LU too.
    #[test]
    fn phase1_newton_step_by_cholesky_equals_the_whole_lu() {
        let mut checked = 0;
        for seed in 1..200 {
            let mut p = problem(seed, 16);
            // Most contacts' tangential forces and slips made small, so that
            // they stick and a few slide (phase 1 takes the LU where more
            // than a quarter of its free rows slide).
            for c in (0..16).filter(|c| !(c + seed as usize).is_multiple_of(5)) {
                for r in [3 * c + 1, 3 * c + 2] {
                    p.lambda[r] *= 0.05;
                    p.delta[r] *= 0.05;
                }
            }
            let (w, rows, mu, m) = (&p.w, &p.rows, &p.mu, p.delta.len());
            let mut runs = Vec::new();
            for lu_only in [false, true] {
                let mut s = scratch(&p.lambda, &p.delta, lu_only);
                classify(w, rows, mu, &mut s, false, false);
                let sliding = s.free.iter().filter(|&&r| s.slide[r].is_some()).count();
                let free1 = s.free.clone();
                solve_newton(w, m, &mut s, false, false).unwrap();
                // By Cholesky: one factorization, no LU after it.
                let by_cholesky = s.split.k_valid && s.factorizations == 1;
                let phase1 = (s.rhs.clone(), by_cholesky, sliding, s.free.len());
                // Phase 2 on the same classes (as where phase 1 ends, its
                // classes repeating): its `A` rows are phase 1's free rows,
                // and it needs no factorization of its own.
                let made = s.factorizations;
                classify(w, rows, mu, &mut s, true, true);
                solve_newton(w, m, &mut s, true, false).unwrap();
                let same_rows = s.split.pos_a.iter().map(|&i| s.free[i]).eq(free1);
                let phase2 = (s.rhs.clone(), s.factorizations == made, same_rows);
                // Classified afresh (in phase 1 a sliding contact's forces
                // were put on its cone): other rows, which take a factor of
                // their own.
                classify(w, rows, mu, &mut s, true, false);
                solve_newton(w, m, &mut s, true, false).unwrap();
                runs.push((phase1, phase2, s.rhs.clone()));
            }
            let (by_parts, whole) = (&runs[0], &runs[1]);
            let ((p1, used, sliding, n), (p2, reused, same_rows), p3) = by_parts;
            assert!(!whole.0.1, "seed {seed}: Cholesky used with lu_only");
            assert!(
                *used || 4 * sliding > *n,
                "seed {seed}: not by Cholesky with {sliding} sliding of {n} free rows"
            );
            if !*used || *sliding == 0 {
                continue;
            }
            checked += 1;
            assert!(
                *same_rows && *reused,
                "seed {seed}: phase 2 factored phase 1's rows again"
            );
            for (a, b) in [(p1, &whole.0.0), (p2, &whole.1.0), (p3, &whole.2)] {
                assert_same_step(a, b, seed);
            }
        }
        assert!(
            checked >= 20,
            "only {checked} problems had a phase-1 step by Cholesky with sliding contacts"
        );
    }

    /// The backward error of a step as [`backward_error`] works it out from
    /// `W`'s rows, against the same figure from the whole Newton matrix as
    /// the LU's path builds it ([`newton_matrix`]), in both phases on
    /// problems with sticking and sliding contacts.
    #[test]
    fn backward_error_from_w_equals_the_whole_matrix() {
        let mut sliding = [0; 2];
        // `W` scaled down too, so that a sliding contact's own entries in its
        // tangential rows weigh in `‖M‖∞`.
        for (seed, scale) in (1..60).flat_map(|seed| [(seed, 1.0), (seed, 1e-3)]) {
            let mut p = problem(seed, 16);
            p.w.iter_mut().for_each(|v| *v *= scale);
            for c in (0..16).filter(|c| !(c + seed as usize).is_multiple_of(4)) {
                for r in [3 * c + 1, 3 * c + 2] {
                    p.lambda[r] *= 0.05;
                    p.delta[r] *= 0.05;
                }
            }
            let (w, rows, mu, m) = (&p.w, &p.rows, &p.mu, p.delta.len());
            for full in [false, true] {
                let mut s = scratch(&p.lambda, &p.delta, false);
                s.shift = NEWTON_SHIFTS[1];
                classify(w, rows, mu, &mut s, full, false);
                let n = s.free.len();
                sliding[full as usize] += s.free.iter().filter(|&&r| s.slide[r].is_some()).count();
                // Any step and right-hand side: another problem's forces.
                let q = problem(seed + 1000, 16);
                let x = q.lambda[..n].to_vec();
                s.rhs = q.delta[..n].to_vec();
                s.mat = vec![f64::NAN; n * n]; // every entry is written
                newton_matrix(w, m, &mut s, full);
                let (mut r_max, mut m_max) = (0.0f64, 0.0f64);
                for i in 0..n {
                    let row = (0..n).map(|j| s.mat[j * n + i]);
                    let ax: f64 = row.clone().zip(&x).map(|(a, x)| a * x).sum();
                    r_max = r_max.max((ax - s.rhs[i]).abs());
                    m_max = m_max.max(row.map(f64::abs).sum());
                }
                let norm = |v: &[f64]| v.iter().fold(0.0f64, |a, v| a.max(v.abs()));
                let want = r_max / (m_max * norm(&x) + norm(&s.rhs));
                phase1_slides(&mut s);
                let got = backward_error(w, m, &s, &x, full);
                assert!(
                    (got - want).abs() <= 1e-12 * want,
                    "seed {seed}, scale {scale}, full {full}: {got:.15e} against {want:.15e}"
                );
            }
        }
        assert!(
            sliding[0] >= 20 && sliding[1] >= 20,
            "sliding contacts {sliding:?}"
        );
    }

    /// Phase 2's Newton step, by blocks ([`solve_split`]) and by one LU of
    /// the whole matrix, on random problems with sticking and sliding
    /// contacts: the same step, also in a chord step on the factors of the
    /// step before.
    #[test]
    fn split_newton_step_equals_the_whole_lu() {
        let mut checked = 0;
        for seed in 1..40 {
            let Problem {
                w,
                rows,
                mu,
                lambda,
                delta,
            } = problem(seed, 12);
            let m = delta.len();
            let mut steps = Vec::new();
            for lu_only in [false, true] {
                let mut s = scratch(&lambda, &delta, lu_only);
                classify(&w, &rows, &mu, &mut s, true, false);
                solve_newton(&w, m, &mut s, true, false).unwrap();
                let first = s.rhs.clone();
                if !lu_only {
                    // The split's check of its own step: at round-off for
                    // the step it solved, far above its bound for one entry
                    // off by a thousandth of the step.
                    std::mem::swap(&mut s.rhs, &mut s.split.step);
                    let e = backward_error(&w, m, &s, &s.split.step, true);
                    assert!(e <= 1e-13, "seed {seed}: backward error {e:.3e}");
                    let big = first.iter().fold(0.0f64, |a, v| a.max(v.abs()));
                    let last = first.len() - 1;
                    s.split.step[last] += 1e-3 * big;
                    let e = backward_error(&w, m, &s, &s.split.step, true);
                    assert!(
                        e > SPLIT_BACKWARD_ERROR,
                        "seed {seed}: backward error {e:.3e} of a wrong step"
                    );
                    s.split.step[last] -= 1e-3 * big;
                    std::mem::swap(&mut s.rhs, &mut s.split.step);
                }
                // A chord step: the same matrix, another right-hand side.
                for d in &mut s.delta {
                    *d *= 0.5;
                }
                solve_newton(&w, m, &mut s, true, true).unwrap();
                let chord = s.rhs.clone();
                let slides = s.free.iter().filter(|&&r| s.slide[r].is_some()).count();
                let sticks = s.free.iter().filter(|&&r| s.kind[r] == Kind::Stick).count();
                // The same classes, another sliding linearization: the split
                // keeps K and X (no new factorization) and redoes the rest.
                for &r in &s.free {
                    s.lambda[r] *= 1.1;
                }
                let made = s.factorizations;
                classify(&w, &rows, &mu, &mut s, true, true);
                solve_newton(&w, m, &mut s, true, false).unwrap();
                let kept = s.factorizations == made;
                steps.push((
                    first,
                    chord,
                    s.rhs.clone(),
                    slides,
                    sticks,
                    s.split.factored,
                    kept,
                ));
            }
            let (split, whole) = (&steps[0], &steps[1]);
            assert!(
                split.5 && !whole.5,
                "seed {seed}: the split was not used, or not only it"
            );
            assert!(
                split.6,
                "seed {seed}: the split refactored K on the same free rows"
            );
            if split.3 == 0 || split.4 == 0 {
                continue;
            }
            checked += 1;
            for (a, b) in [
                (&split.0, &whole.0),
                (&split.1, &whole.1),
                (&split.2, &whole.2),
            ] {
                assert_same_step(a, b, seed);
            }
        }
        assert!(
            checked >= 10,
            "only {checked} problems had sliding and sticking contacts"
        );
    }
}
