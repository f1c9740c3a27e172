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
//!    ([`solve_phase1`]), with an LU of the whole where more than a quarter
//!    of the free rows slide or the Cholesky fails. Phase 2's is split at the
//!    sliding rows ([`Split`]): a Cholesky factorization of its symmetric
//!    `δ = 0` block (phase 1's last one, where the rows are the same) and an
//!    LU of the Schur complement on the sliding rows (two per sliding
//!    contact), with an LU of the whole where the Cholesky fails.
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
/// of 20 without, the same hours (and about one in 50 to 150 before): see
/// docs/benchmark-log.md, "Damped Newton steps".
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

impl Slide {
    /// Tangential row `k` (0 or 1) of the linearized `λ_t − μ λ_n P = 0`:
    /// `(I − κQ) Δλ_t − μ P Δλ_n + κρ Q W_t· Δλ = −(λ_t − μ λ_n P)`,
    /// `Q = I − P Pᵀ`.
    fn row(&self, k: usize) -> SlideRow {
        let p = self.p;
        let q = [
            [1.0 - p[0] * p[0], -p[0] * p[1]],
            [-p[1] * p[0], 1.0 - p[1] * p[1]],
        ];
        let id = |l: usize| if k == l { 1.0 } else { 0.0 };
        SlideRow {
            a: self.kappa * self.rho * q[k][0],
            b: self.kappa * self.rho * q[k][1],
            own: [
                -self.mu * p[k],
                id(0) - self.kappa * q[k][0],
                id(1) - self.kappa * q[k][1],
            ],
        }
    }

    /// The right-hand side of row `k`, `−(λ_t − μ λ_n⁺ P)`, at the forces
    /// `lambda` of the contact whose normal row is `r`.
    fn rhs(&self, lambda: &[f64], r: usize, k: usize) -> f64 {
        -(lambda[r + 1 + k] - self.mu * lambda[r].max(0.0) * self.p[k])
    }
}

/// One tangential row of a sliding contact's Newton equations
/// ([`Slide::row`]): `a W_{r+1,c} + b W_{r+2,c}` in every free column `c`,
/// plus `own` in the contact's own columns (its normal, then its two
/// tangents).
struct SlideRow {
    a: f64,
    b: f64,
    own: [f64; 3],
}

impl SlideRow {
    /// The `W` part in column `c`.
    fn w(&self, w1: &[f64], w2: &[f64], c: usize) -> f64 {
        self.a * w1[c] + self.b * w2[c]
    }
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
    /// Phase 2's Newton system split at its sliding rows ([`solve_split`]).
    split: Split,
}

/// Phase 2's Newton matrix in blocks: `A`, the free rows whose equation is
/// `δ_r = 0` (every free normal row and the tangential rows of sticking
/// contacts), and `S`, the tangential rows of sliding contacts:
///
/// ```text
/// [ K     W_AS ] [Δλ_A]   [b_A]      K = W_AA + ε diag W_AA
/// [ C_SA  D_SS ] [Δλ_S] = [b_S]
/// ```
///
/// `K` is symmetric positive definite (a principal block of `W`, its
/// diagonal shifted, see [`NEWTON_SHIFTS`]) and depends on the active set
/// only; the sliding linearization (`P`, `κ`) is in `C_SA` and `D_SS`
/// alone. The step factors `K` by Cholesky (half the work of an LU of the
/// same size), forms `X = K⁻¹ W_AS` once per active set, and solves the
/// Schur complement `S = D_SS − C_SA X` (`|S|` rows, two per sliding contact)
/// by LU: `Δλ_S = S⁻¹ (b_S − C_SA K⁻¹ b_A)`, `Δλ_A = K⁻¹ b_A − X Δλ_S`.
#[derive(Debug, Clone, Default)]
struct Split {
    /// Whether the factors below are those of the free rows `lu_free`
    /// (false: the whole matrix's LU is in `SubspaceScratch::mat`).
    factored: bool,
    /// Positions (in `free`) of the `A` rows and of the `S` rows.
    pos_a: Vec<usize>,
    pos_s: Vec<usize>,
    /// `pos_s` of the factorization before.
    pos_s_prev: Vec<usize>,
    /// Whether `k` and `x` hold the factors of the free rows `kx_rows` with
    /// the shift `kx_shift` (a reclassification that keeps the free rows and
    /// which contacts slide only changes `C_SA` and `D_SS`).
    kx_valid: bool,
    kx_rows: Vec<usize>,
    kx_shift: f64,
    /// Whether `k` holds the Cholesky factor of `W` over the rows `k_rows`
    /// with the shift `k_shift` (made by phase 1's step, [`solve_phase1`], or
    /// by a split): phase 2's first split on the same `A` rows takes it
    /// instead of factoring `K` again.
    k_valid: bool,
    k_rows: Vec<usize>,
    k_shift: f64,
    /// Phase 1's sliding normal rows ([`phase1_slides`]): each one's
    /// position in `free`, `μ` and `P` (its column carries the tangential
    /// force `μ P` per unit normal force).
    slide_pos: Vec<(usize, f64, [f64; 2])>,
    /// `K`, then its Cholesky factor (column-major, `|A|²`, lower triangle).
    k: Vec<f64>,
    /// `W_AS`, then `X = K⁻¹ W_AS` (column-major, `|A| × |S|`).
    x: Vec<f64>,
    /// `C_SAᵀ` (column-major, `|A| × |S|`: one sliding row per column).
    c: Vec<f64>,
    /// `D_SS`, then the Schur complement, then its LU (column-major).
    s: Vec<f64>,
    perm: Vec<usize>,
    perm_inv: Vec<usize>,
    /// Right-hand sides of the `A` and `S` rows, then their steps.
    ya: Vec<f64>,
    ys: Vec<f64>,
    /// The step by position in `free`, before it is checked.
    step: Vec<f64>,
    /// Solve phase 2 with one LU of the whole matrix instead (a test compares
    /// the two).
    lu_only: bool,
}

/// Capacity for at least `cap` entries in `v`.
fn room<T>(v: &mut Vec<T>, cap: usize) {
    v.reserve(cap.saturating_sub(v.len()));
}

impl Split {
    /// `K = W_RR + shift · diag W_RR` over the rows `R` the caller put in
    /// `k_rows`, Cholesky-factored in place into `k` ([`Self::k_valid`]).
    /// False where `K` is not positive definite in floating point.
    fn factor_k(&mut self, w: &[f64], m: usize, shift: f64, mem: &mut [MaybeUninit<u8>]) -> bool {
        let n = self.k_rows.len();
        // Not zeroed: the lower triangle is filled below, and the Cholesky
        // factorization and its solves read the lower triangle only.
        self.k.resize(n * n, 0.0);
        // A column at a time: column c of W over the rows is row c of W (W
        // is symmetric).
        for (j, &cj) in self.k_rows.iter().enumerate() {
            let wc = &w[cj * m..(cj + 1) * m];
            let col = &mut self.k[j * n + j..(j + 1) * n];
            for (c, &ri) in col.iter_mut().zip(&self.k_rows[j..]) {
                *c = wc[ri];
            }
            // The diagonal shifted: a damped step (see NEWTON_SHIFTS).
            col[0] *= 1.0 + shift;
        }
        let chol = faer::linalg::cholesky::llt::factor::cholesky_in_place(
            MatMut::from_column_major_slice_mut(&mut self.k, n, n),
            Default::default(),
            Par::Seq,
            MemStack::new(mem),
            Default::default(),
        );
        self.k_valid = chol.is_ok();
        self.k_shift = shift;
        self.k_valid
    }

    /// The LU (partial pivoting) of `s`, `ns × ns`, in place: the Schur
    /// complement of a split, or phase 1's `I + Eᵀ Z` ([`solve_phase1`]);
    /// [`back_substitute`] solves with it.
    fn factor_small(&mut self, ns: usize, mem: &mut [MaybeUninit<u8>]) {
        self.perm.clear();
        self.perm.resize(ns, 0);
        self.perm_inv.clear();
        self.perm_inv.resize(ns, 0);
        lu::factor::lu_in_place(
            MatMut::from_column_major_slice_mut(&mut self.s, ns, ns),
            &mut self.perm,
            &mut self.perm_inv,
            Par::Seq,
            MemStack::new(mem),
            Default::default(),
        );
    }

    /// Room for the blocks of any split of `n` free rows (`|A| |S| ≤ n²/4`,
    /// `|S| ≤ 2n/3`).
    fn reserve(&mut self, n: usize) {
        let quarter = n * n / 4 + n;
        room(&mut self.k, n * n);
        room(&mut self.x, quarter);
        room(&mut self.c, quarter);
        room(&mut self.s, 4 * n * n / 9 + n);
        for v in [&mut self.ya, &mut self.ys, &mut self.step] {
            room(v, n);
        }
        room(&mut self.slide_pos, n);
        for v in [
            &mut self.pos_a,
            &mut self.pos_s,
            &mut self.pos_s_prev,
            &mut self.kx_rows,
            &mut self.k_rows,
            &mut self.perm,
            &mut self.perm_inv,
        ] {
            room(v, n);
        }
    }
}

impl SubspaceScratch {
    /// Room for a factorization of `n` free rows, whole or split, in every
    /// buffer either uses: the two share the largest `n` seen, so that
    /// neither allocates once the free rows have stopped growing, whichever
    /// phase meets them first.
    fn reserve(&mut self, n: usize) {
        room(&mut self.mat, n * n);
        room(&mut self.rhs, n);
        room(&mut self.perm, n);
        room(&mut self.perm_inv, n);
        self.split.reserve(n);
        self.mem.resize(
            workspace(n).unaligned_bytes_required(),
            MaybeUninit::uninit(),
        );
    }

    /// Drops the factors a step could start from.
    pub(super) fn forget(&mut self) {
        self.lu_free.clear();
        self.split.factored = false;
        self.split.kx_valid = false;
        self.split.k_valid = false;
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

/// The Newton step's right-hand side over the free rows, into `s.rhs`:
/// `−δ_r` for a row `δ_r = 0` (the normal row of a sliding contact too), and
/// in phase 2 (`full`) the sliding contact's tangential rows, see
/// [`Slide::rhs`].
fn newton_rhs(s: &mut SubspaceScratch, full: bool) {
    s.rhs.clear();
    s.rhs.extend(s.free.iter().map(|&r| -s.delta[r]));
    if !full {
        return;
    }
    for (i, &r) in s.free.iter().enumerate() {
        if let Some(sl) = s.slide.get(r).copied().flatten() {
            for k in 0..2 {
                s.rhs[i + 1 + k] = sl.rhs(&s.lambda, r, k);
            }
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
        s.reserve(n);
    }
    if full && solve_split(w, m, s, reuse) {
        return s.rhs.iter().all(|v| v.is_finite()).then_some(());
    }
    if !full && !reuse && solve_phase1(w, m, s) {
        return s.rhs.iter().all(|v| v.is_finite()).then_some(());
    }
    newton_rhs(s, full);
    if !reuse {
        s.mat.resize(n * n, 0.0);
        newton_matrix(w, m, s, full);
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

/// faer's workspace for any factorization and solve of `n` free rows,
/// whole or split: sized by `n` alone, so that it grows only with `n`.
fn workspace(n: usize) -> faer::dyn_stack::StackReq {
    lu::factor::lu_in_place_scratch::<usize, f64>(n, n, Par::Seq, Default::default())
        .or(lu::solve::solve_in_place_scratch::<usize, f64>(
            n,
            1,
            Par::Seq,
        ))
        .or(
            faer::linalg::cholesky::llt::factor::cholesky_in_place_scratch::<f64>(
                n,
                Par::Seq,
                Default::default(),
            ),
        )
}

/// Phase 2's Newton step by blocks ([`Split`]) into `s.rhs`: factors `K`,
/// `X` and the Schur complement unless `reuse` (a chord step on the factors
/// of the same free rows). Returns false where it did not solve: `K` not
/// positive definite in floating point, a chord step on factors it did not
/// make, or [`Split::lu_only`]; the caller then solves by one LU.
/// Its buffers and faer's workspace have room already
/// ([`SubspaceScratch::reserve`], before every factorization).
fn solve_split(w: &[f64], m: usize, s: &mut SubspaceScratch, reuse: bool) -> bool {
    if s.split.lu_only || reuse && !s.split.factored {
        return false;
    }
    let n = s.free.len();
    let sp = &mut s.split;
    if !reuse {
        sp.factored = false;
        std::mem::swap(&mut sp.pos_s, &mut sp.pos_s_prev);
        sp.pos_a.clear();
        sp.pos_s.clear();
        let mut i = 0;
        while i < n {
            sp.pos_a.push(i);
            if s.slide[s.free[i]].is_some() {
                sp.pos_s.extend([i + 1, i + 2]);
                i += 3;
            } else {
                i += 1;
            }
        }
    }
    let (na, ns) = (sp.pos_a.len(), sp.pos_s.len());
    if !reuse {
        let keep = sp.kx_valid
            && sp.kx_shift == s.shift
            && sp.kx_rows == s.free
            && sp.pos_s == sp.pos_s_prev;
        if !keep {
            sp.kx_valid = false;
            // The Cholesky factor of `K` that phase 1's last step made on
            // these rows (phase 1 ends where its active set repeats, and its
            // free rows are the `A` rows), if it is there.
            let k_ready = sp.k_valid
                && sp.k_shift == s.shift
                && sp.k_rows.len() == na
                && sp
                    .pos_a
                    .iter()
                    .zip(&sp.k_rows)
                    .all(|(&pi, &r)| s.free[pi] == r);
            sp.x.clear();
            sp.x.resize(na * ns, 0.0);
            for (js, &pj) in sp.pos_s.iter().enumerate() {
                let wc = &w[s.free[pj] * m..(s.free[pj] + 1) * m];
                let col = &mut sp.x[js * na..(js + 1) * na];
                for (c, &pi) in col.iter_mut().zip(&sp.pos_a) {
                    *c = wc[s.free[pi]];
                }
            }
            if !k_ready {
                sp.k_rows.clear();
                sp.k_rows.extend(sp.pos_a.iter().map(|&pi| s.free[pi]));
                if !sp.factor_k(w, m, s.shift, &mut s.mem) {
                    return false;
                }
                s.factorizations += 1;
            }
            if ns > 0 {
                faer::linalg::cholesky::llt::solve::solve_in_place(
                    faer::MatRef::from_column_major_slice(&sp.k, na, na),
                    MatMut::from_column_major_slice_mut(&mut sp.x, na, ns),
                    Par::Seq,
                    MemStack::new(&mut s.mem),
                );
            }
            sp.kx_valid = true;
            sp.kx_rows.clone_from(&s.free);
            sp.kx_shift = s.shift;
        }
        // C_SAᵀ and D_SS: the linearized λ_t − μ λ_n P = 0 of each sliding
        // contact (see `solve_newton`), one column of C_SAᵀ per sliding row.
        sp.c.clear();
        sp.c.resize(na * ns, 0.0);
        sp.s.clear();
        sp.s.resize(ns * ns, 0.0);
        let mut is = 0;
        for (ia, &pi) in sp.pos_a.iter().enumerate() {
            let r = s.free[pi];
            let Some(sl) = s.slide[r] else {
                continue;
            };
            let (w1, w2) = (&w[(r + 1) * m..(r + 2) * m], &w[(r + 2) * m..(r + 3) * m]);
            for k in 0..2 {
                let (row, eq) = (is + k, sl.row(k));
                let col = &mut sp.c[row * na..(row + 1) * na];
                for (c, &pj) in col.iter_mut().zip(&sp.pos_a) {
                    *c = eq.w(w1, w2, s.free[pj]);
                }
                col[ia] += eq.own[0];
                for (js, &pj) in sp.pos_s.iter().enumerate() {
                    sp.s[js * ns + row] = eq.w(w1, w2, s.free[pj]);
                }
                for l in 0..2 {
                    sp.s[(is + l) * ns + row] += eq.own[1 + l];
                }
            }
            is += 2;
        }
        if ns > 0 {
            // S = D_SS − C_SA X, then its LU.
            faer::linalg::matmul::matmul(
                MatMut::from_column_major_slice_mut(&mut sp.s, ns, ns),
                faer::Accum::Add,
                faer::MatRef::from_column_major_slice(&sp.c, na, ns).transpose(),
                faer::MatRef::from_column_major_slice(&sp.x, na, ns),
                -1.0,
                Par::Seq,
            );
            sp.factor_small(ns, &mut s.mem);
        }
        sp.factored = true;
    }
    // The right-hand sides as the whole matrix's (`−δ_r`, and
    // `−(λ_t − μ λ_n P)` on the tangential rows of the contacts sliding now:
    // in a chord step across solves a contact can have changed between
    // sticking and sliding), by the blocks of the factorization.
    newton_rhs(s, true);
    let sp = &mut s.split;
    sp.ya.clear();
    sp.ya.extend(sp.pos_a.iter().map(|&i| s.rhs[i]));
    sp.ys.clear();
    sp.ys.extend(sp.pos_s.iter().map(|&i| s.rhs[i]));
    let l = faer::MatRef::from_column_major_slice(&sp.k, na, na);
    let ya = MatMut::from_column_major_slice_mut(&mut sp.ya, na, 1);
    faer::linalg::cholesky::llt::solve::solve_in_place(l, ya, Par::Seq, MemStack::new(&mut s.mem));
    if ns > 0 {
        faer::linalg::matmul::matmul(
            MatMut::from_column_major_slice_mut(&mut sp.ys, ns, 1),
            faer::Accum::Add,
            faer::MatRef::from_column_major_slice(&sp.c, na, ns).transpose(),
            faer::MatRef::from_column_major_slice(&sp.ya, na, 1),
            -1.0,
            Par::Seq,
        );
        back_substitute(sp, na, ns, &mut s.mem);
    }
    // The step by position; `s.rhs` still holds the right-hand side.
    sp.step.clear();
    sp.step.resize(n, 0.0);
    for (&pi, &v) in sp.pos_a.iter().zip(&sp.ya) {
        sp.step[pi] = v;
    }
    for (&pi, &v) in sp.pos_s.iter().zip(&sp.ys) {
        sp.step[pi] = v;
    }
    if !reuse && backward_error(w, m, s, &s.split.step, true) > SPLIT_BACKWARD_ERROR {
        // Not as good as one LU of the whole would be: that instead.
        s.split.factored = false;
        s.split.kx_valid = false;
        s.split.k_valid = false;
        return false;
    }
    std::mem::swap(&mut s.rhs, &mut s.split.step);
    true
}

/// The small system's part of a step by blocks, shared by [`solve_split`]
/// and [`solve_phase1`]: `ys ← S⁻¹ ys` by the LU in `s` (`ns` rows), then
/// `ya ← ya − X ys` (`X` is `rows × ns`, in `x`).
fn back_substitute(sp: &mut Split, rows: usize, ns: usize, mem: &mut [MaybeUninit<u8>]) {
    let perm = PermRef::new_checked(&sp.perm, &sp.perm_inv, ns);
    let lu = faer::MatRef::from_column_major_slice(&sp.s, ns, ns);
    let ys = MatMut::from_column_major_slice_mut(&mut sp.ys, ns, 1);
    lu::solve::solve_in_place(lu, lu, perm, ys, Par::Seq, MemStack::new(mem));
    faer::linalg::matmul::matmul(
        MatMut::from_column_major_slice_mut(&mut sp.ya, rows, 1),
        faer::Accum::Add,
        faer::MatRef::from_column_major_slice(&sp.x, rows, ns),
        faer::MatRef::from_column_major_slice(&sp.ys, ns, 1),
        -1.0,
        Par::Seq,
    );
}

/// Phase 1's Newton step by Cholesky, into `s.rhs`: its matrix is
/// `K + U Eᵀ`, `K = W_FF + ε diag W_FF` over the free rows (symmetric
/// positive definite, as in [`Split`]) and one column `U_j = μ (P₀ W_{F,t₀} +
/// P₁ W_{F,t₁})` per sliding contact, added in its normal row's column `j`
/// (`E` picks those columns): the tangential force that follows the normal
/// force. By the Sherman–Morrison–Woodbury identity, with `Z = K⁻¹ U` and
/// `y = K⁻¹ b`, the step is `y − Z (I + Eᵀ Z)⁻¹ Eᵀ y`: a Cholesky factor
/// (`|F|³/3`), `2 |F|² |S|` for `Z` and an LU of `|S|` rows, against
/// `2/3 |F|³` for the LU of the whole, where `|S| ≤ |F| / 4`. Phase 1 ends
/// where its free rows repeat, and they are then phase 2's `A` rows: the
/// first split takes this `K` (see [`Split::k_valid`]). Returns false where it
/// did not solve (too many sliding contacts, `K` not positive definite in
/// floating point, a backward error above [`SPLIT_BACKWARD_ERROR`], or
/// [`Split::lu_only`]); the caller then solves by one LU. On the accuracy
/// study's lens through the hole phase 1's free rows are 450–530 with 40–80
/// sliding contacts.
fn solve_phase1(w: &[f64], m: usize, s: &mut SubspaceScratch) -> bool {
    if s.split.lu_only {
        return false;
    }
    let n = s.free.len();
    phase1_slides(s);
    let sp = &mut s.split;
    let ns = sp.slide_pos.len();
    if 4 * ns > n {
        return false;
    }
    // The split's factors are overwritten below.
    sp.factored = false;
    sp.kx_valid = false;
    sp.x.clear();
    sp.x.resize(n * ns, 0.0);
    for (l, &(j, mu, p)) in sp.slide_pos.iter().enumerate() {
        let cj = s.free[j];
        let (w1, w2) = (
            &w[(cj + 1) * m..(cj + 2) * m],
            &w[(cj + 2) * m..(cj + 3) * m],
        );
        for (c, &ri) in sp.x[l * n..(l + 1) * n].iter_mut().zip(&s.free) {
            *c = mu * (p[0] * w1[ri] + p[1] * w2[ri]);
        }
    }
    sp.k_rows.clone_from(&s.free);
    if !sp.factor_k(w, m, s.shift, &mut s.mem) {
        return false;
    }
    s.factorizations += 1;
    newton_rhs(s, false);
    let sp = &mut s.split;
    let l = faer::MatRef::from_column_major_slice(&sp.k, n, n);
    sp.ya.clone_from(&s.rhs);
    faer::linalg::cholesky::llt::solve::solve_in_place(
        l,
        MatMut::from_column_major_slice_mut(&mut sp.ya, n, 1),
        Par::Seq,
        MemStack::new(&mut s.mem),
    );
    if ns > 0 {
        faer::linalg::cholesky::llt::solve::solve_in_place(
            l,
            MatMut::from_column_major_slice_mut(&mut sp.x, n, ns),
            Par::Seq,
            MemStack::new(&mut s.mem),
        );
        // I + Eᵀ Z, its LU, and (I + Eᵀ Z)⁻¹ Eᵀ y.
        sp.s.clear();
        sp.s.resize(ns * ns, 0.0);
        for c in 0..ns {
            for (r, &(j, ..)) in sp.slide_pos.iter().enumerate() {
                sp.s[c * ns + r] = sp.x[c * n + j];
            }
            sp.s[c * ns + c] += 1.0;
        }
        sp.factor_small(ns, &mut s.mem);
        sp.ys.clear();
        sp.ys.extend(sp.slide_pos.iter().map(|&(j, ..)| sp.ya[j]));
        back_substitute(sp, n, ns, &mut s.mem);
    }
    // A NaN fails the check too.
    let e = backward_error(w, m, s, &s.split.ya, false);
    if e.is_nan() || e > SPLIT_BACKWARD_ERROR {
        return false;
    }
    std::mem::swap(&mut s.rhs, &mut s.split.ya);
    true
}

/// The largest normwise backward error a split step ([`solve_split`]) may
/// have, `‖M Δλ − b‖∞ / (‖M‖∞ ‖Δλ‖∞ + ‖b‖∞)` for the whole Newton matrix `M`.
/// An LU with partial pivoting leaves about `n ε` (2·10⁻¹³ for a thousand
/// free rows); the Schur complement of a nearly singular `K` can leave more,
/// and then the step is solved by one LU instead.
const SPLIT_BACKWARD_ERROR: f64 = 1e-10;

/// The normwise backward error of the step `x` (by position in `s.free`)
/// for the whole Newton matrix of phase 2 (`full`) or phase 1, as
/// `solve_newton` builds it, and the right-hand side in `s.rhs`: one product
/// with the matrix's rows, a small fraction of a factorization. Each row is
/// one pass over `W`'s entries in the free columns ([`free_dot_abs`]); the
/// diagonal's shift, phase 1's sliding columns (as [`phase1_slides`] listed
/// them: their tangential force, by `W`'s symmetry from the same row) and
/// phase 2's sliding rows' own entries are added to it.
fn backward_error(w: &[f64], m: usize, s: &SubspaceScratch, x: &[f64], full: bool) -> f64 {
    let b = &s.rhs;
    let n = s.free.len();
    let slides: &[(usize, f64, [f64; 2])] = if full { &[] } else { &s.split.slide_pos };
    let (mut r_max, mut m_max) = (0.0f64, 0.0f64);
    let x_max = x.iter().fold(0.0f64, |a, v| a.max(v.abs()));
    let b_max = b.iter().fold(0.0f64, |a, v| a.max(v.abs()));
    let mut i = 0;
    while i < n {
        let r = s.free[i];
        // δ_r = 0: row r of W over the free columns, its diagonal shifted;
        // in phase 1 a sliding normal's column carries its tangential force.
        let row = &w[r * m..(r + 1) * m];
        let (mut sum, mut abs) = free_dot_abs(1.0, row, 0.0, row, &s.free, x);
        sum += s.shift * row[r] * x[i];
        abs += s.shift * row[r].abs();
        for &(j, mu, p) in slides {
            let cj = s.free[j];
            let plain = row[cj] * if j == i { 1.0 + s.shift } else { 1.0 };
            // As `delta_columns` forms it.
            let t = mu * (p[0] * row[cj + 1] + p[1] * row[cj + 2]);
            sum += t * x[j];
            abs += (plain + t).abs() - plain.abs();
        }
        r_max = r_max.max((sum - b[i]).abs());
        m_max = m_max.max(abs);
        let Some(sl) = s.slide[r].filter(|_| full) else {
            i += 1;
            continue;
        };
        let (w1, w2) = (&w[(r + 1) * m..(r + 2) * m], &w[(r + 2) * m..(r + 3) * m]);
        for k in 0..2 {
            let eq = sl.row(k);
            let (mut sum, mut abs) = free_dot_abs(eq.a, w1, eq.b, w2, &s.free, x);
            // The λ part, on the contact's own three columns.
            for (l, &own) in eq.own.iter().enumerate() {
                let v = eq.w(w1, w2, r + l);
                sum += own * x[i + l];
                abs += (v + own).abs() - v.abs();
            }
            r_max = r_max.max((sum - b[i + 1 + k]).abs());
            m_max = m_max.max(abs);
        }
        i += 3;
    }
    let scale = m_max * x_max + b_max;
    if scale > 0.0 { r_max / scale } else { 0.0 }
}

/// `(Σ_j v_j x_j, Σ_j |v_j|)` over the free columns `c_j`, with
/// `v_j = α u[c_j] + β t[c_j]`: four partial sums each, so that the
/// scattered loads, not one long chain of additions, set the pace.
fn free_dot_abs(
    alpha: f64,
    u: &[f64],
    beta: f64,
    t: &[f64],
    free: &[usize],
    x: &[f64],
) -> (f64, f64) {
    let (mut sum, mut abs) = ([0.0f64; 4], [0.0f64; 4]);
    let (cols, xs) = (free.chunks_exact(4), x[..free.len()].chunks_exact(4));
    let (rest_c, rest_x) = (cols.remainder(), xs.remainder());
    for (c, xc) in cols.zip(xs) {
        for k in 0..4 {
            let v = alpha * u[c[k]] + beta * t[c[k]];
            sum[k] += v * xc[k];
            abs[k] += v.abs();
        }
    }
    let (mut s, mut a) = (
        (sum[0] + sum[1]) + (sum[2] + sum[3]),
        (abs[0] + abs[1]) + (abs[2] + abs[3]),
    );
    for (&c, &xc) in rest_c.iter().zip(rest_x) {
        let v = alpha * u[c] + beta * t[c];
        s += v * xc;
        a += v.abs();
    }
    (s, a)
}

/// Phase 1's sliding normal rows of the free rows into
/// [`Split::slide_pos`], for its step ([`solve_phase1`]) and the step's
/// [`backward_error`].
fn phase1_slides(s: &mut SubspaceScratch) {
    let sp = &mut s.split;
    sp.slide_pos.clear();
    sp.slide_pos
        .extend(s.free.iter().enumerate().filter_map(|(j, &cj)| {
            let Slide { p, mu, .. } = s.slide[cj]?;
            Some((j, mu, p))
        }));
}

/// The whole Newton matrix of phase 2 (`full`) or phase 1 over the free
/// rows into `s.mat` (column-major, `n × n`, every entry written): the
/// equations `δ_r = 0` ([`delta_columns`]), then the tangential rows i+1,
/// i+2 of a sliding contact (free rows r+1, r+2, pushed with its normal row
/// r), see [`Slide::row`].
fn newton_matrix(w: &[f64], m: usize, s: &mut SubspaceScratch, full: bool) {
    let n = s.free.len();
    delta_columns(w, m, s, full);
    let mut i = 0;
    while i < n {
        let r = s.free[i];
        let Some(sl) = s.slide.get(r).copied().flatten().filter(|_| full) else {
            i += 1;
            continue;
        };
        let (w1, w2) = (&w[(r + 1) * m..(r + 2) * m], &w[(r + 2) * m..(r + 3) * m]);
        for k in 0..2 {
            let ik = i + 1 + k;
            let row = sl.row(k);
            for (j, &cj) in s.free.iter().enumerate() {
                s.mat[j * n + ik] = row.w(w1, w2, cj);
            }
            // The λ part: columns i (λ_n), i+1, i+2 (λ_t).
            for (l, v) in row.own.iter().enumerate() {
                s.mat[(i + l) * n + ik] += v;
            }
        }
        i += 3;
    }
}

/// The equations `δ_r = 0` of the Newton matrix: for each free row `r_i`,
/// row `r_i` of `W` over the free columns, where in phase 1 (`!full`) the
/// column of a sliding normal also carries its tangential force (`μ P` along
/// the tangential rows). Filled a column at a time (`W` is symmetric, so
/// column `c_j` over the free rows is row `c_j` of `W`): contiguous writes,
/// where a row at a time wrote one entry per column. Phase 2's tangential
/// rows of sliding contacts are filled too and then overwritten by their own
/// equations.
fn delta_columns(w: &[f64], m: usize, s: &mut SubspaceScratch, full: bool) {
    let n = s.free.len();
    for (j, &cj) in s.free.iter().enumerate() {
        let col = &mut s.mat[j * n..(j + 1) * n];
        let wc = &w[cj * m..(cj + 1) * m];
        match s.slide[cj].filter(|_| !full) {
            Some(Slide { p, mu, .. }) => {
                let (w1, w2) = (
                    &w[(cj + 1) * m..(cj + 2) * m],
                    &w[(cj + 2) * m..(cj + 3) * m],
                );
                for (c, &ri) in col.iter_mut().zip(&s.free) {
                    *c = wc[ri] + mu * (p[0] * w1[ri] + p[1] * w2[ri]);
                }
                // The diagonal shifted: a damped step (see NEWTON_SHIFTS).
                col[j] += wc[cj] * s.shift;
            }
            None => {
                for (c, &ri) in col.iter_mut().zip(&s.free) {
                    *c = wc[ri];
                }
                col[j] *= 1.0 + s.shift;
            }
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
