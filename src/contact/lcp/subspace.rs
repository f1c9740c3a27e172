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
//! 2. **Newton** on those equations over the free force rows, with a dense
//!    LU with partial pivoting (faer, sequential; the system is unsymmetric),
//!    its `δ = 0` rows damped by a shift of their diagonal ([`NEWTON_SHIFTS`]).
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
//! Cost per iteration: the LU of the free rows (`2/3 |A|³`) and `m` per
//! changed force to keep `δ = δ₀ + W λ` (a Newton update changes the free
//! rows only), against `m` per changed row for a sweep. Within phase 2, an
//! iteration on the same active set as the last LU reuses it (a chord step:
//! only the sliding rows' linearization has moved), a triangular solve
//! instead of a factorization; when the residual then stops halving, the
//! contacts are classified again and the matrix refactored. On the accuracy
//! study's lens through the hole (up to 1 830 rows, 570 free) the two cut
//! the LCP's mean from 12.3 to 8.8 ms per step; on 45 recorded cataract jam
//! problems the median to 10⁻⁶ from 1.37 to 0.93 ms.

use std::mem::MaybeUninit;

use faer::dyn_stack::MemStack;
use faer::linalg::lu::partial_pivoting as lu;
use faer::perm::PermRef;
use faer::{MatMut, Par};

use super::types::{axpy, project_cone, residual};

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
/// of 20 without, the same hours (and about one in 50 to 150 before): see the
/// README.
pub(super) const NEWTON_SHIFTS: [f64; 3] = [1e-10, 1e-3, 1e-2];

/// How a sliding contact's tangential equations are linearized.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Slide {
    /// `P = z_t/‖z_t‖`.
    p: [f64; 2],
    /// `κ = μ λ_n / ‖z_t‖`.
    kappa: f64,
    /// `ρ = 1/W_nn`.
    rho: f64,
    /// Friction coefficient.
    mu: f64,
}

/// A contact's class in the active set (on its normal row).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
enum Kind {
    #[default]
    Open,
    /// Frictionless and pushing.
    Push,
    Stick,
    Slide,
}

/// Scratch of the subspace step.
#[derive(Debug, Clone, Default)]
pub(super) struct SubspaceScratch {
    /// Free force rows (sorted); each has one equation.
    free: Vec<usize>,
    /// The free rows of the previous iteration.
    last: Vec<usize>,
    /// The free rows of the LU factors in `mat` (phase 2; empty when none).
    lu_free: Vec<usize>,
    /// LU factorizations made (the solve reports the difference).
    pub(super) factorizations: usize,
    /// Whether a step may start from the LU the last step left (the caller
    /// solves again with the same `W`: [`super::LcpScratch::reuse_factorization`]).
    pub(super) reuse: bool,
    /// Per normal row of a sliding contact: its linearization.
    slide: Vec<Option<Slide>>,
    /// Per normal row: the contact's class.
    kind: Vec<Kind>,
    /// The classes of each classification of this step, one after another
    /// (`m` each): which contacts flip back and forth.
    history: Vec<Kind>,
    /// Per normal row: a class the classification keeps (the enumeration).
    hold: Vec<Option<Kind>>,
    /// The contacts whose class did not settle (normal rows).
    toggling: Vec<usize>,
    /// Whether a cycling step may enumerate the toggling contacts' classes.
    pub(super) enumerate: bool,
    /// The relative diagonal shift of this step's Newton matrices (one of
    /// [`NEWTON_SHIFTS`], see [`Self::set_shift`]).
    shift: f64,
    /// The Newton matrix (column-major), then its LU factors.
    mat: Vec<f64>,
    /// Right-hand side, then the step.
    rhs: Vec<f64>,
    /// The candidate forces and their `δ`.
    lambda: Vec<f64>,
    /// The candidate's forces before its last change (see [`update_delta`]).
    prev: Vec<f64>,
    delta: Vec<f64>,
    /// The candidate with the lowest residual so far, and its `δ`.
    best: Vec<f64>,
    best_delta: Vec<f64>,
    /// The LU factorization's row permutation and its inverse.
    perm: Vec<usize>,
    perm_inv: Vec<usize>,
    /// faer's workspace.
    mem: Vec<MaybeUninit<u8>>,
}

impl SubspaceScratch {
    /// Drops the LU factors a step could start from.
    pub(super) fn forget(&mut self) {
        self.lu_free.clear();
    }

    /// Sets the next step's shift (one of [`NEWTON_SHIFTS`]); an LU kept for
    /// reuse was made with its own step's shift, so a new one drops it.
    pub(super) fn set_shift(&mut self, shift: f64) {
        if shift != self.shift {
            self.forget();
        }
        self.shift = shift;
    }
}

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
        s.lu_free.clear();
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
    // kept by the changed rows; the solve forms `W λ` afresh at its end).
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
/// symmetric, so row `r` is column `r`): `m` multiply-adds per changed row
/// instead of the `m²` of [`super::types::exact_delta`]. A Newton update changes the free
/// rows only (a third of them on the accuracy study's lens through the hole)
/// and a classification a few, so this was 40 % of a subspace step. The
/// solve recomputes `δ` exactly at its end.
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

/// Step 2: builds the Newton matrix over the free rows and solves it into
/// `s.rhs`. Row `i` of the matrix is free row `r_i`'s equation: `δ_{r_i} = 0`,
/// or for the tangential rows of a sliding contact the linearized
/// `λ_t − μ λ_n P = 0` (phase 2, `full`; in phase 1 a sliding contact has
/// only its normal row free).
fn solve_newton(
    w: &[f64],
    m: usize,
    s: &mut SubspaceScratch,
    full: bool,
    reuse: bool,
) -> Option<()> {
    let n = s.free.len();
    if !reuse {
        s.mat.clear();
        s.mat.resize(n * n, 0.0);
    }
    s.rhs.clear();
    s.rhs.resize(n, 0.0);
    // Which contact's sliding data a tangential row belongs to: the normal row
    // is the free row just before (r, r+1, r+2 are pushed together).
    let mut i = 0;
    while i < n {
        let r = s.free[i];
        // δ_r = 0, also for the normal row of a sliding contact.
        if reuse {
            s.rhs[i] = -s.delta[r];
        } else {
            delta_row(w, m, r, i, s, full);
        }
        let Some(sl) = s.slide.get(r).copied().flatten().filter(|_| full) else {
            i += 1;
            continue;
        };
        // Tangential rows i+1, i+2 (free rows r+1, r+2):
        // (I − κQ) Δλ_t − μ P Δλ_n + κρ Q W_t· Δλ = −(λ_t − μ λ_n P).
        let Slide {
            p, kappa, rho, mu, ..
        } = sl;
        let q = [
            [1.0 - p[0] * p[0], -p[0] * p[1]],
            [-p[1] * p[0], 1.0 - p[1] * p[1]],
        ];
        let (w1, w2) = (&w[(r + 1) * m..(r + 2) * m], &w[(r + 2) * m..(r + 3) * m]);
        for k in 0..2 {
            let ik = i + 1 + k;
            s.rhs[ik] = -(s.lambda[r + 1 + k] - mu * s.lambda[r].max(0.0) * p[k]);
            if reuse {
                continue;
            }
            let (a, b) = (kappa * rho * q[k][0], kappa * rho * q[k][1]);
            for (j, &cj) in s.free.iter().enumerate() {
                s.mat[j * n + ik] = a * w1[cj] + b * w2[cj];
            }
            // The λ part: columns i (λ_n), i+1, i+2 (λ_t).
            s.mat[i * n + ik] -= mu * p[k];
            for l in 0..2 {
                let id = if k == l { 1.0 } else { 0.0 };
                s.mat[(i + 1 + l) * n + ik] += id - kappa * q[k][l];
            }
        }
        i += 3;
    }
    let req = lu::factor::lu_in_place_scratch::<usize, f64>(n, n, Par::Seq, Default::default()).or(
        lu::solve::solve_in_place_scratch::<usize, f64>(n, 1, Par::Seq),
    );
    s.mem
        .resize(req.unaligned_bytes_required(), MaybeUninit::uninit());
    if !reuse {
        s.factorizations += 1;
        s.perm.clear();
        s.perm.resize(n, 0);
        s.perm_inv.clear();
        s.perm_inv.resize(n, 0);
        let a = MatMut::from_column_major_slice_mut(&mut s.mat, n, n);
        lu::factor::lu_in_place(
            a,
            &mut s.perm,
            &mut s.perm_inv,
            Par::Seq,
            MemStack::new(&mut s.mem),
            Default::default(),
        );
    }
    let perm = PermRef::new_checked(&s.perm, &s.perm_inv, n);
    let lu = faer::MatRef::from_column_major_slice(&s.mat, n, n);
    let rhs = MatMut::from_column_major_slice_mut(&mut s.rhs, n, 1);
    lu::solve::solve_in_place(lu, lu, perm, rhs, Par::Seq, MemStack::new(&mut s.mem));
    s.rhs.iter().all(|v| v.is_finite()).then_some(())
}

/// Equation `i` of the Newton matrix, `δ_r = 0`: row `r` of `W` over the free
/// columns, where in phase 1 (`!full`) the column of a sliding normal also
/// carries its tangential force (`μ P` along the tangential rows).
fn delta_row(w: &[f64], m: usize, r: usize, i: usize, s: &mut SubspaceScratch, full: bool) {
    let n = s.free.len();
    let row = &w[r * m..(r + 1) * m];
    for (j, &cj) in s.free.iter().enumerate() {
        // The diagonal shifted: a damped step (see NEWTON_SHIFTS).
        let mut v = row[cj] * if j == i { 1.0 + s.shift } else { 1.0 };
        if let (false, Some(Slide { p, mu, .. })) = (full, s.slide[cj]) {
            v += mu * (p[0] * row[cj + 1] + p[1] * row[cj + 2]);
        }
        s.mat[j * n + i] = v;
    }
    s.rhs[i] = -s.delta[r];
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
