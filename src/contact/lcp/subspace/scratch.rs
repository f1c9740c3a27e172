//! The subspace step's types: a sliding contact's linearization, a
//! contact's class, the step's scratch and phase 2's split Newton matrix,
//! shared by the step ([`super`]) and its Newton system ([`super::system`]).

use std::mem::MaybeUninit;

/// How a sliding contact's tangential equations are linearized.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(super) struct Slide {
    /// `P = z_t/‖z_t‖`.
    pub(super) p: [f64; 2],
    /// `κ = μ λ_n / ‖z_t‖`.
    pub(super) kappa: f64,
    /// `ρ = 1/W_nn`.
    pub(super) rho: f64,
    /// Friction coefficient.
    pub(super) mu: f64,
}

impl Slide {
    /// Tangential row `k` (0 or 1) of the linearized `λ_t − μ λ_n P = 0`:
    /// `(I − κQ) Δλ_t − μ P Δλ_n + κρ Q W_t· Δλ = −(λ_t − μ λ_n P)`,
    /// `Q = I − P Pᵀ`.
    pub(super) fn row(&self, k: usize) -> SlideRow {
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
    pub(super) fn rhs(&self, lambda: &[f64], r: usize, k: usize) -> f64 {
        -(lambda[r + 1 + k] - self.mu * lambda[r].max(0.0) * self.p[k])
    }
}

/// One tangential row of a sliding contact's Newton equations
/// ([`Slide::row`]): `a W_{r+1,c} + b W_{r+2,c}` in every free column `c`,
/// plus `own` in the contact's own columns (its normal, then its two
/// tangents).
pub(super) struct SlideRow {
    pub(super) a: f64,
    pub(super) b: f64,
    pub(super) own: [f64; 3],
}

impl SlideRow {
    /// The `W` part in column `c`.
    pub(super) fn w(&self, w1: &[f64], w2: &[f64], c: usize) -> f64 {
        self.a * w1[c] + self.b * w2[c]
    }
}

/// A contact's class in the active set (on its normal row).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(super) enum Kind {
    #[default]
    Open,
    /// Frictionless and pushing.
    Push,
    Stick,
    Slide,
}

/// Scratch of the subspace step.
#[derive(Debug, Clone, Default)]
pub(in crate::contact::lcp) struct SubspaceScratch {
    /// Free force rows (sorted); each has one equation.
    pub(super) free: Vec<usize>,
    /// The free rows of the previous iteration.
    pub(super) last: Vec<usize>,
    /// The free rows of the LU factors in `mat` (phase 2; empty when none).
    pub(super) lu_free: Vec<usize>,
    /// LU factorizations made (the solve reports the difference).
    pub(in crate::contact::lcp) factorizations: usize,
    /// Whether a step may start from the LU the last step left (the caller
    /// solves again with the same `W`:
    /// [`LcpScratch::reuse_factorization`](super::super::LcpScratch::reuse_factorization)).
    pub(in crate::contact::lcp) reuse: bool,
    /// Per normal row of a sliding contact: its linearization.
    pub(super) slide: Vec<Option<Slide>>,
    /// Per normal row: the contact's class.
    pub(super) kind: Vec<Kind>,
    /// The classes of each classification of this step, one after another
    /// (`m` each): which contacts flip back and forth.
    pub(super) history: Vec<Kind>,
    /// Per normal row: a class the classification keeps (the enumeration).
    pub(super) hold: Vec<Option<Kind>>,
    /// The contacts whose class did not settle (normal rows).
    pub(super) toggling: Vec<usize>,
    /// Whether a cycling step may enumerate the toggling contacts' classes.
    pub(in crate::contact::lcp) enumerate: bool,
    /// The relative diagonal shift of this step's Newton matrices (one of
    /// [`NEWTON_SHIFTS`](super::NEWTON_SHIFTS), see [`Self::set_shift`]).
    pub(super) shift: f64,
    /// The Newton matrix (column-major), then its LU factors.
    pub(super) mat: Vec<f64>,
    /// Right-hand side, then the step.
    pub(super) rhs: Vec<f64>,
    /// The candidate forces and their `δ`.
    pub(super) lambda: Vec<f64>,
    /// The candidate's forces before its last change (see [`update_delta`](super::update_delta)).
    pub(super) prev: Vec<f64>,
    pub(super) delta: Vec<f64>,
    /// The candidate with the lowest residual so far, and its `δ`.
    pub(super) best: Vec<f64>,
    pub(super) best_delta: Vec<f64>,
    /// The LU factorization's row permutation and its inverse.
    pub(super) perm: Vec<usize>,
    pub(super) perm_inv: Vec<usize>,
    /// faer's workspace.
    pub(super) mem: Vec<MaybeUninit<u8>>,
    /// Phase 2's Newton system split at its sliding rows
    /// ([`solve_split`](super::system::solve_split)).
    pub(super) split: Split,
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
/// diagonal shifted, see [`NEWTON_SHIFTS`](super::NEWTON_SHIFTS)) and depends on the active set
/// only; the sliding linearization (`P`, `κ`) is in `C_SA` and `D_SS`
/// alone. The step factors `K` by Cholesky (half the work of an LU of the
/// same size), forms `X = K⁻¹ W_AS` once per active set, and solves the
/// Schur complement `S = D_SS − C_SA X` (`|S|` rows, two per sliding contact)
/// by LU: `Δλ_S = S⁻¹ (b_S − C_SA K⁻¹ b_A)`, `Δλ_A = K⁻¹ b_A − X Δλ_S`.
#[derive(Debug, Clone, Default)]
pub(super) struct Split {
    /// Whether the factors below are those of the free rows `lu_free`
    /// (false: the whole matrix's LU is in `SubspaceScratch::mat`).
    pub(super) factored: bool,
    /// Positions (in `free`) of the `A` rows and of the `S` rows.
    pub(super) pos_a: Vec<usize>,
    pub(super) pos_s: Vec<usize>,
    /// `pos_s` of the factorization before.
    pub(super) pos_s_prev: Vec<usize>,
    /// Whether `k` and `x` hold the factors of the free rows `kx_rows` with
    /// the shift `kx_shift` (a reclassification that keeps the free rows and
    /// which contacts slide only changes `C_SA` and `D_SS`).
    pub(super) kx_valid: bool,
    pub(super) kx_rows: Vec<usize>,
    pub(super) kx_shift: f64,
    /// Whether `k` holds the Cholesky factor of `W` over the rows `k_rows`
    /// with the shift `k_shift` (made by phase 1's step,
    /// [`solve_phase1`](super::system::solve_phase1), or by a split): phase 2's
    /// first split on the same `A` rows takes it
    /// instead of factoring `K` again.
    pub(super) k_valid: bool,
    pub(super) k_rows: Vec<usize>,
    pub(super) k_shift: f64,
    /// Phase 1's sliding normal rows
    /// ([`phase1_slides`](super::system::phase1_slides)): each one's position in
    /// `free`, `μ` and `P` (its column carries the tangential
    /// force `μ P` per unit normal force).
    pub(super) slide_pos: Vec<(usize, f64, [f64; 2])>,
    /// `K`, then its Cholesky factor (column-major, `|A|²`, lower triangle).
    pub(super) k: Vec<f64>,
    /// `W_AS`, then `X = K⁻¹ W_AS` (column-major, `|A| × |S|`).
    pub(super) x: Vec<f64>,
    /// `C_SAᵀ` (column-major, `|A| × |S|`: one sliding row per column).
    pub(super) c: Vec<f64>,
    /// `D_SS`, then the Schur complement, then its LU (column-major).
    pub(super) s: Vec<f64>,
    pub(super) perm: Vec<usize>,
    pub(super) perm_inv: Vec<usize>,
    /// Right-hand sides of the `A` and `S` rows, then their steps.
    pub(super) ya: Vec<f64>,
    pub(super) ys: Vec<f64>,
    /// The step by position in `free`, before it is checked.
    pub(super) step: Vec<f64>,
    /// Solve phase 2 with one LU of the whole matrix instead (a test compares
    /// the two).
    pub(super) lu_only: bool,
}

impl SubspaceScratch {
    /// Drops the factors a step could start from.
    pub(in crate::contact::lcp) fn forget(&mut self) {
        self.lu_free.clear();
        self.split.factored = false;
        self.split.kx_valid = false;
        self.split.k_valid = false;
    }

    /// Sets the next step's shift (one of [`NEWTON_SHIFTS`](super::NEWTON_SHIFTS)); an LU kept for
    /// reuse was made with its own step's shift, so a new one drops it.
    pub(in crate::contact::lcp) fn set_shift(&mut self, shift: f64) {
        if shift != self.shift {
            self.forget();
        }
        self.shift = shift;
    }
}
