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
//! - [`LcpSolver::Subspace`] (the default, `subspace/`): after each block
//!   Gauss–Seidel sweep, a semismooth Newton step on the active set (dense
//!   factorizations of the free rows: an LU, then in its second phase a
//!   Cholesky factor and a Schur complement), kept when it lowers the
//!   residual. On the recorded
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
//! contributions is divided by `‖ρ δ₀‖` (forces of the size that would undo
//! each contact's free violation alone), so it is dimensionless and
//! comparable across problems. The scale is the problem's, not the
//! answer's: divided by `‖λ‖`, a spurious answer with huge forces along a
//! near-null direction of `W` looked converged (a relative residual of
//! 10⁻¹⁴ with 2 cm of predicted penetration, which threw the lens of the
//! accuracy study out of contact). It is what [`ContactProblem`] replays and the
//! `lcp` bench compare.
//!
//! ## Cost
//! `δ = δ₀ + W λ` is kept up to date: a row whose force changes adds its
//! column of `W` to `δ` (`W` is symmetric), and a row whose force stays (an
//! open contact at `λ = 0`, the many alarm-band contacts) costs one read. A
//! sweep therefore costs `m` multiply-adds per *changed* row, not `m²`; the
//! carried `δ` stays within round-off of `δ₀ + W λ` (NNCG's momentum, which
//! drifts, forms it again now and then and at the end), and the report's
//! residuals are worked out from it.
mod block;
mod pgs;
mod problem;
mod solve;
mod subspace;
mod types;
mod warm;

pub use block::local_coulomb;
pub use problem::ContactProblem;
pub use solve::{LcpScratch, solve, solve_until};
pub use types::{LcpReport, LcpSettings, LcpSolver, friction_residual, residual};
pub use warm::{ContactKey, OtherKey, WarmStart};
