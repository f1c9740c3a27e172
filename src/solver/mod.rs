//! Linear solver of the implicit step: conjugate gradient with a choice of preconditioners.
//!
//! The implicit system `A a = b` (see [`crate::body`]) is solved by
//! [`cg::solve`] with one of the preconditioners of [`PreconditionerKind`]:
//!
//! | kind | what `P` is | refresh |
//! |---|---|---|
//! | `None` | identity | – |
//! | `Jacobi` | `diag(A)` | every step |
//! | `Exact` | `L D Lᵀ` of the current `A` (reference: CG converges in ≤ 2 iterations) | every step |
//! | `Periodic { every }` | `Rᵀ L D Lᵀ R` of an older `A`, warped by the node rotations since | every `every` steps, on the stepping thread |
//! | `Async` | same warp, factor made by a background worker | as soon as the worker is done; never blocks a step (but the very first) |
//!
//! The rotation warp follows the paper (eq. 4): with `R_i` the rotation of node
//! `i` now and `R̂_i` when the factored matrix was handed over, `Q_i = R_i R̂_iᵀ`
//! and `P⁻¹ = Q (L D Lᵀ)⁻¹ Qᵀ`. Node rotations are the polar part of the sum
//! of the rotations of the elements around the node.
//!
//! ## Which warp, if any
//! The warp is exact for a body that turns rigidly since its factor was made.
//! Where it deforms instead (a lens squeezed into a slit), node rotations
//! averaged from sheared, crushed elements swing from step to step and differ
//! between neighbours, and `Q (L D Lᵀ) Qᵀ` can fit the current matrix worse
//! than the unwarped factor of a matrix one or two steps old: in the cataract
//! scene's push the lens needed about twice as many CG iterations with the
//! warp. Where a deforming body also turns as a whole (the lens tumbling out
//! of the slit once it is through), neither fits: the unwarped factor misses
//! the turn, and the nodes' warps scatter about it. For that there is a third
//! choice, [`WarpKind::Body`]: one turn for every node, [`body_turn`] (the
//! polar part of the sum of the node rotations now, against the same of
//! those the factor was made with). A single rotation `Δ` leaves the factor a
//! factor of `Δ Â Δᵀ`, the matrix of the old state turned rigidly (mass and
//! damping are isotropic), so it never sets neighbours against each other.
//!
//! The first solve with each new factor tries the three on its first
//! residual `r` and keeps the one with the smallest `‖r − A P⁻¹ r‖`
//! ([`Preconditioner::apply_first`]; two extra triangular solves and three
//! products with `A`, or one and two when the body has not turned). The
//! choice holds while the factor is in use and is tried again when it is 4,
//! 8, 16, … steps old, as the warp gains on an ageing factor. The contact
//! compliance uses the same choice ([`FactorState::warped`],
//! [`FactorState::warp_kind`]). [`PreconditionerStats::warp_declined`] counts
//! the steps without a warp and [`PreconditionerStats::warp_body`] those with
//! the body's turn. In the cataract scene the lens takes the body's turn in
//! 58–74 % of its steps, and over 29 runs against 19 before it the CG
//! iterations per step fell from a median of 11.6 to 9.3 and the contact
//! phase's consistency refreshes from 57 to 34 a run (see
//! docs/benchmark-log.md, "One turn for the whole body").
//!
//! ## Half and single precision
//! The lagged kinds (`Periodic`, `Async`, `AsyncLagged`) keep two rounded
//! copies of each factor, made with it (by the worker for the async kinds):
//! `L` in `f32` ([`LdltFactor::round_to_single`]) and `L` in IEEE binary16
//! with the diagonal blocks and `D⁻¹` in `f32` ([`LdltFactor::round_to_half`];
//! both at once, the second from the first: [`LdltFactor::round_to_single_and_half`]).
//! A triangular solve reads all of `L`, which for the paper-size lens (66 000
//! 3×3 blocks) is 4.7 MB in `f64`, 2.4 MB in `f32` (still a little more than a
//! core's L2 cache on the development machine) and 1.2 MB in binary16.
//!
//! The CG preconditioner solves with the binary16 copy in `f32` arithmetic
//! ([`LdltFactor::solve_half`]) once the body's previous solve took
//! [`HALF_FROM_ITERATIONS`] iterations or more, with the `f32` copy before
//! ([`PreconditionerStats::half_solves`] counts the former): one solve of the
//! lens 118–121 µs against 204–206 µs with the `f32` copy in `f64`
//! arithmetic (`cargo bench --bench step -- lens_solve`). The rounding (a
//! relative 4.9·10⁻⁴ per entry of `L`) leaves `L̃ D L̃ᵀ` symmetric positive
//! definite and within about 10⁻³ of `L D Lᵀ`;
//! CG still stops on its own residual tolerance, so only the iteration count
//! moves. Each solve of a `lag2` cataract run done both ways: a solve that
//! takes one iteration with the `f32` copy takes two (the lens) or three (the
//! eye) with binary16, one of two 3.6 or 3.2, one of three to eleven about
//! as many, one of twenty and more a tenth more; hence the threshold. Where
//! the CPU lacks F16C, or an entry does not fit binary16, the
//! preconditioner solves with the `f32` copy. The contact correction keeps
//! the `f32` copy for its backward sweep and `f64` for `W`, which must agree
//! with each other; `Exact` keeps `f64` as the reference.
//!
//! ## Rescue
//! The warp follows rotations, not changes of shape. If CG runs out of
//! iterations with an old factor (`Periodic`, `Async`), the body factorizes the
//! current matrix on the stepping thread ([`PreconditionerState::refactor_now`])
//! and continues from the last iterate, so no unconverged step is taken. This
//! blocks that step and is counted in [`PreconditionerStats::rescues`]; a late
//! background factor of an older matrix is then discarded. The contact phase
//! rescues the same way when a correction strays from the matrix
//! ([`crate::contact::ContactSettings::consistency_tolerance`]).
//!
//! An `Async` worker that is already factorizing the very matrix of the
//! rescue's step (handed over at this step's update, so part or all of its
//! work is done while the step ran its free motion and contact detection) is
//! waited for instead, and its factor is taken together with the node columns
//! it precomputed for the contact compliance; counted in
//! [`PreconditionerStats::rescues_from_worker`]. A job of an older matrix is
//! not: its factor would not be of the current matrix, which is what a rescue
//! promises. In the cataract scene a third to a half of the contact phase's
//! rescues find the worker on the same step's matrix.
//!
//! ## Asynchronous refresh
//! [`AsyncFactorizer`] owns a worker thread (crossbeam channels). At the start
//! of a step a finished factor, if any, is swapped in; then, if the worker is
//! idle, the current matrix and node rotations are copied into recycled
//! buffers and handed over. Buffers circulate between the two threads, so the
//! steady state allocates nothing. Dropping the factorizer stops and joins the
//! worker. Across all bodies at most `cores − 1` factorizations run at once, so
//! the stepping thread keeps a core of its own. Bodies that find every slot
//! taken queue for one in order (first come, first served): a body that has
//! just received its factor cannot take the freed slot again ahead of a body
//! still waiting, so with two bodies on two cores they take turns instead of
//! one of them starving with an ever older factor. A body that stops asking
//! (it stopped stepping: paused, failed, or kept but unused) leaves the queue
//! after 250 ms, so it cannot hold up the bodies behind it; it queues again
//! when it asks. `AsyncLagged` bodies do not queue: their factor must be of
//! the matrix handed over exactly `lag` steps before, whatever the other
//! bodies do, so they hand it over at once (and count towards the limit the
//! `Async` bodies see); with more lagged bodies than cores their
//! factorizations share the cores.
//!
//! ## Contact columns made with the factor
//! The contact compliance needs, with every new factor, the node columns
//! `L⁻¹ P E_k` of the nodes in contact and their Gram blocks (see
//! [`crate::contact::compliance`]); on the stepping thread that cost, per
//! refresh, 2.5–5 ms for the paper-size lens with 60–90 contacts and about
//! 20 ms at 260 (`compliance_bench`, "new factor"). The compliance leaves
//! the nodes of its last few builds as a hint ([`columns::HINT_BUILDS`]:
//! contact sets flicker, and a node out of contact for a step or two often
//! comes back); the worker solves their columns
//! and all their Gram blocks right after the factorization, and the factor is
//! handed over with them. The compliance takes them when it first uses that
//! factor, and solves on the stepping thread only nodes that came into
//! contact since. The refresh takes longer by that much, so factors are a
//! little older when contacts are many. Counted in
//! [`PreconditionerStats::precomputed_columns`]. Bodies without contacts
//! leave no hint, and their worker factorizes only.

pub mod cg;
pub mod columns;
mod half;
pub mod ldlt;
pub mod ordering;
pub mod supernodal;
mod worker;

use std::sync::Arc;
use std::time::Instant;

use crate::error::{Result, SoftTissueError};
use crate::fem::assembly::BlockCsr;
use crate::math::{Mat3, Vec3, polar_rotation};
use columns::{ColumnPrefetch, FactorKey};
use ldlt::{LdltFactor, LdltSymbolic};
pub use worker::AsyncFactorizer;
use worker::Done;

/// Steps between refreshes on the stepping thread when an `Async`
/// preconditioner has no worker thread (it could not be started or stopped).
pub const WORKER_FALLBACK_PERIOD: u64 = 4;

/// Applies `z = P⁻¹ r`.
pub trait Preconditioner: Send {
    /// Computes `z = P⁻¹ r`.
    fn apply(&mut self, r: &[Vec3], z: &mut [Vec3]);

    /// The first application of a solve, with the matrix `a` and the initial
    /// residual `r` at hand (`q` is free scratch of the same length). A
    /// preconditioner with a choice to make for the whole solve makes it here;
    /// the default is [`Self::apply`].
    fn apply_first(&mut self, a: &BlockCsr, r: &[Vec3], z: &mut [Vec3], q: &mut [Vec3]) {
        let _ = (a, q);
        self.apply(r, z);
    }
}

/// Which preconditioner a body uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PreconditionerKind {
    /// No preconditioning.
    None,
    /// Diagonal (Jacobi).
    Jacobi,
    /// `LDLᵀ` of the current matrix, every step.
    Exact,
    /// `LDLᵀ` refreshed every `every` steps with the rotation warp.
    Periodic {
        /// Refresh period in steps (≥ 1).
        every: u32,
    },
    /// `LDLᵀ` refreshed by a background worker with the rotation warp.
    #[default]
    Async,
    /// `Async` made deterministic, for reproducible comparisons: the factor of
    /// the matrix handed over at step `n` is swapped in at step `n + lag`
    /// exactly (the stepping thread waits for the worker if it is not done,
    /// and keeps a finished factor until then). Results then do not depend on
    /// thread timing, whatever the number of bodies: a lagged body hands its
    /// matrix over without waiting for a turn among the bodies' background
    /// factorizations (`Async` bodies wait, so that at most `cores − 1` run at
    /// once), so with more lagged bodies than cores their factorizations
    /// share the cores.
    AsyncLagged {
        /// Steps between handing a matrix over and using its factor (≥ 1).
        lag: u32,
    },
}

impl PreconditionerKind {
    /// Whether this kind keeps an `LDLᵀ` factor.
    pub fn has_factor(&self) -> bool {
        matches!(
            self,
            Self::Exact | Self::Periodic { .. } | Self::Async | Self::AsyncLagged { .. }
        )
    }

    /// Whether a background worker makes the factor.
    pub fn is_async(&self) -> bool {
        matches!(self, Self::Async | Self::AsyncLagged { .. })
    }

    /// Whether the factor is warped by node rotations.
    pub fn needs_rotations(&self) -> bool {
        matches!(
            self,
            Self::Periodic { .. } | Self::Async | Self::AsyncLagged { .. }
        )
    }
}

/// Counters of the preconditioner.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PreconditionerStats {
    /// Steps since the matrix in use was handed over for factorization.
    pub factor_age: u64,
    /// Factorizations swapped in since creation.
    pub refreshes: u64,
    /// Duration of the last factorization, seconds (on whichever thread made it).
    pub factor_seconds: f64,
    /// Seconds the stepping thread spent factorizing in the last update.
    pub blocking_seconds: f64,
    /// Factorizations that failed (the previous factor was kept).
    pub failures: u64,
    /// Of those, background factorizations that panicked (caught; the
    /// worker's slot was released and the worker goes on).
    pub worker_panics: u64,
    /// Refreshes made on the stepping thread because the background worker
    /// could not be started or has stopped (every [`WORKER_FALLBACK_PERIOD`] steps).
    pub fallback_refreshes: u64,
    /// Blocking refactorizations because CG did not converge with the old
    /// factor, or because the contact correction strayed from the matrix
    /// ([`PreconditionerState::refactor_now`]).
    pub rescues: u64,
    /// Of those, rescues that waited for the background worker's factor of
    /// the same step's matrix (and its precomputed node columns) instead of
    /// factorizing again on the stepping thread.
    pub rescues_from_worker: u64,
    /// Solves that had a rotation warp to apply.
    pub warp_offered: u64,
    /// Of those, solves where the unwarped factor fitted better and the warp was left out.
    pub warp_declined: u64,
    /// Of those, solves that applied the body's one turn ([`WarpKind::Body`])
    /// instead of each node's own.
    pub warp_body: u64,
    /// Node columns the background worker solved with its new factors for the
    /// contact compliance (see [`crate::contact::compliance`]).
    pub precomputed_columns: u64,
    /// CG solves with the factor's half-precision copy (see
    /// [`HALF_FROM_ITERATIONS`]).
    pub half_solves: u64,
}

/// Which rotation warp a lagging factor is applied with (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum WarpKind {
    /// Each node's own turn `Q_i = R_i R̂_iᵀ` (the paper's eq. 4).
    #[default]
    Nodes,
    /// One turn for the whole body ([`body_turn`]): exact for a body that
    /// turns rigidly, and the same for neighbouring nodes where it deforms.
    Body,
}

/// The turn of a body from the node rotations `then` to `now`: the polar part
/// of `Σ now_i` times the transpose of the polar part of `Σ then_i`. For a
/// body turned rigidly by `Δ` (every `now_i = Δ then_i`) it is `Δ`.
pub fn body_turn(now: &[Mat3], then: &[Mat3]) -> Mat3 {
    let sum = |r: &[Mat3]| r.iter().fold(Mat3::zeros(), |acc, r| acc + r);
    polar_rotation(&sum(now)) * polar_rotation(&sum(then)).transpose()
}

/// Fills `out` with the warp of `kind` from the node rotations `then` to
/// `now`: each node's `now_i thenᵢᵀ`, or [`body_turn`] for every node.
pub fn fill_warp(kind: WarpKind, now: &[Mat3], then: &[Mat3], out: &mut [Mat3]) {
    match kind {
        WarpKind::Nodes => {
            for ((o, n), t) in out.iter_mut().zip(now).zip(then) {
                *o = n * t.transpose();
            }
        }
        WarpKind::Body => out.fill(body_turn(now, then)),
    }
}

/// `LDLᵀ` factor in use plus the rotations it was made with.
#[derive(Debug)]
pub struct FactorState {
    /// The factor.
    pub factor: LdltFactor,
    /// Node rotations when the factored matrix was taken.
    pub rotations: Vec<Mat3>,
    /// The warp applied when [`Self::warped`]: [`Self::node_warp`] or, every
    /// node alike, [`Self::body_warp`], as [`Self::warp_kind`] says.
    pub warp: Vec<Mat3>,
    /// Each node's turn `Q_i = R_i R̂_iᵀ` from those rotations to the current ones.
    pub node_warp: Vec<Mat3>,
    /// The body's turn since then, one rotation for every node (see
    /// [`body_turn`] and the module docs, "Which warp, if any").
    pub body_warp: Mat3,
    /// Which of the two [`Self::warp`] holds.
    pub warp_kind: WarpKind,
    /// Whether `warp` differs from the identity (the factor is older than the matrix).
    pub rotated: bool,
    /// Whether `warp` is applied this step: `rotated`, unless the unwarped factor
    /// fitted the first residual of this step's solve better (see the module docs).
    pub warped: bool,
    /// Step at which the factored matrix was taken.
    pub step: u64,
    /// Bumped each time a new factor is swapped in.
    pub version: u64,
}

/// A body's preconditioner: one of [`PreconditionerKind`] with its buffers.
#[derive(Debug)]
pub struct PreconditionerState {
    kind: PreconditionerKind,
    jacobi: Vec<Vec3>,
    symbolic: Option<Arc<LdltSymbolic>>,
    state: Option<FactorState>,
    worker: Option<AsyncFactorizer>,
    work: Vec<Mat3>,
    tmp: Vec<Vec3>,
    tmp2: Vec<Vec3>,
    /// Scratch of the half-precision solve.
    tmp32: Vec<[f32; 4]>,
    alt: Vec<Vec3>,
    prefetch: ColumnPrefetch,
    /// The last error of a background factorization (see [`Self::last_error`]).
    last_error: Option<SoftTissueError>,
    /// Factor version the warp was last chosen for, and the choice (`None`:
    /// the unwarped factor).
    warp_choice: Option<(u64, Option<WarpKind>)>,
    /// Whether this CG solve uses the factor's half-precision copy (see
    /// [`HALF_FROM_ITERATIONS`]).
    half_now: bool,
    /// Solves with the factor in the current CG solve, one an iteration.
    applies: usize,
    stats: PreconditionerStats,
}

/// A CG solve with a lagging factor uses the factor's half-precision copy
/// ([`LdltFactor::solve_half`]) when the body's previous solve took this many
/// iterations or more, and the single-precision copy otherwise: where the
/// factor fits the matrix so well that CG converges in one or two iterations,
/// binary16's rounding is what CG would iterate against (one such solve took
/// 1.9 to 3 iterations with it, in the cataract); from three on, the factor's
/// own misfit dominates and binary16 costs no iterations (see the module
/// docs, "Half and single precision").
pub const HALF_FROM_ITERATIONS: usize = 3;

impl PreconditionerState {
    /// A preconditioner of `kind` for matrices over `a`'s pattern.
    pub fn new(kind: PreconditionerKind, a: &BlockCsr) -> Result<Self> {
        if let PreconditionerKind::Periodic { every: 0 } = kind {
            return Err(SoftTissueError::InvalidParameter {
                name: "Periodic.every",
                value: 0.0,
                reason: "refresh period must be ≥ 1 step",
            });
        }
        if let PreconditionerKind::AsyncLagged { lag: 0 } = kind {
            return Err(SoftTissueError::InvalidParameter {
                name: "AsyncLagged.lag",
                value: 0.0,
                reason: "lag must be ≥ 1 step",
            });
        }
        let n = a.n();
        let symbolic = if kind.has_factor() {
            Some(Arc::new(LdltSymbolic::new(&a.pattern)?))
        } else {
            None
        };
        let worker = match &symbolic {
            Some(s) if kind.is_async() => Some(AsyncFactorizer::new(a, s)),
            _ => None,
        };
        Ok(Self {
            kind,
            jacobi: vec![Vec3::zeros(); n],
            symbolic,
            state: None,
            worker,
            work: Vec::with_capacity(n),
            tmp: vec![Vec3::zeros(); n],
            tmp2: vec![Vec3::zeros(); n],
            tmp32: vec![[0.0; 4]; n],
            alt: vec![Vec3::zeros(); n],
            prefetch: ColumnPrefetch::default(),
            warp_choice: None,
            half_now: false,
            applies: 0,
            last_error: None,
            stats: PreconditionerStats::default(),
        })
    }

    /// The last error a background factorization reported (a failed or
    /// panicked job; counted in [`PreconditionerStats::failures`]), if any.
    pub fn last_error(&self) -> Option<&SoftTissueError> {
        self.last_error.as_ref()
    }

    /// The node-column hand-over with the contact compliance (see
    /// [`ColumnPrefetch`]).
    pub fn column_prefetch_mut(&mut self) -> &mut ColumnPrefetch {
        &mut self.prefetch
    }

    /// The kind.
    pub fn kind(&self) -> PreconditionerKind {
        self.kind
    }

    /// Counters.
    pub fn stats(&self) -> PreconditionerStats {
        self.stats
    }

    /// The symbolic analysis, when the kind keeps a factor.
    pub fn symbolic(&self) -> Option<&Arc<LdltSymbolic>> {
        self.symbolic.as_ref()
    }

    /// The factor in use with its warp, when the kind keeps one.
    pub fn factor_state(&self) -> Option<&FactorState> {
        self.state.as_ref()
    }

    /// The background worker, for the `Async` kind.
    pub fn worker(&self) -> Option<&AsyncFactorizer> {
        self.worker.as_ref()
    }

    /// Factorizes `a` now, on this thread, for the kinds whose factor lags the
    /// matrix (`Periodic`, `Async`, `AsyncLagged`): the rescue when CG fails
    /// to converge with a factor the matrix has moved away from, or when a
    /// contact correction strays from it. When the background worker is
    /// factorizing `a` of this same `step`, waits for that factor instead
    /// (see the module docs, "Rescue"). Returns whether a factor was made
    /// (never for the other kinds, whose factor is already current or absent).
    pub fn refactor_now(&mut self, a: &BlockCsr, rotations: &[Mat3], step: u64) -> Result<bool> {
        if !self.kind.needs_rotations() || self.state.is_none() || self.symbolic.is_none() {
            return Ok(false);
        }
        if !self.take_current_from_worker(step) {
            self.factorize_now(a, rotations, step)?;
        }
        if let Some(st) = &mut self.state {
            st.warped = false;
            st.rotated = false;
            st.warp.fill(Mat3::identity());
            st.node_warp.fill(Mat3::identity());
            st.body_warp = Mat3::identity();
        }
        self.stats.rescues += 1;
        self.stats.factor_age = 0;
        Ok(true)
    }

    /// Swaps in a finished background factorization and its precomputed node
    /// columns, unless it failed or a rescue has made a newer factor since.
    /// Returns whether the factor was swapped in. The job's buffers go back
    /// to the worker either way.
    fn adopt(&mut self, mut done: Done) -> bool {
        self.stats.factor_seconds = done.seconds;
        let stale = self.state.as_ref().is_some_and(|st| done.step < st.step);
        let mut columns = done.columns.take();
        let adopted = match done.result {
            // A rescue factorized a newer matrix meanwhile: keep that one.
            Ok(()) if stale => false,
            Ok(()) => {
                if let Some(st) = &mut self.state {
                    std::mem::swap(&mut st.factor, &mut done.factor);
                    std::mem::swap(&mut st.rotations, &mut done.rotations);
                    st.step = done.step;
                    st.version += 1;
                    if let Some(mut c) = columns.take() {
                        c.key = Some(FactorKey::Preconditioner(st.version));
                        self.stats.precomputed_columns += c.cols.len() as u64;
                        columns = self.prefetch.ready.replace(c);
                    }
                }
                self.stats.refreshes += 1;
                true
            }
            Err(e) => {
                self.stats.failures += 1;
                if matches!(e, SoftTissueError::WorkerPanic(_)) {
                    self.stats.worker_panics += 1;
                }
                self.last_error = Some(e);
                false
            }
        };
        if let Some(c) = columns {
            self.prefetch.keep_spare(c);
        }
        if let Some(w) = &mut self.worker {
            w.spare = Some((done.values, done.rotations, done.factor));
            w.hint = done.hint;
        }
        adopted
    }

    /// The rescue's factor from the background worker, when the worker is
    /// factorizing the very matrix of `step`: waits for it (the worker
    /// started it at this step's update, so part or all of the work is
    /// done) and swaps it in with the node columns it precomputed. Returns
    /// whether it did; otherwise the caller factorizes on this thread.
    fn take_current_from_worker(&mut self, step: u64) -> bool {
        let t0 = Instant::now();
        let done = match &mut self.worker {
            Some(w) if w.in_flight() && w.submitted_step() == step => w.try_take(true),
            _ => None,
        };
        let adopted = done.is_some_and(|d| self.adopt(d));
        if adopted {
            self.stats.blocking_seconds += t0.elapsed().as_secs_f64();
            self.stats.rescues_from_worker += 1;
        }
        adopted
    }

    fn factorize_now(&mut self, a: &BlockCsr, rotations: &[Mat3], step: u64) -> Result<()> {
        let Some(sym) = self.symbolic.clone() else {
            return Ok(());
        };
        let t0 = Instant::now();
        let st = self.state.get_or_insert_with(|| FactorState {
            factor: sym.alloc_factor(),
            rotations: rotations.to_vec(),
            warp: vec![Mat3::identity(); rotations.len()],
            node_warp: vec![Mat3::identity(); rotations.len()],
            body_warp: Mat3::identity(),
            warp_kind: WarpKind::Nodes,
            rotated: false,
            warped: false,
            step,
            version: 0,
        });
        let res = sym.factorize(a, &mut st.factor, &mut self.work);
        if res.is_ok() && self.kind.needs_rotations() {
            // The lagged kinds solve with `L` in half precision (see the
            // module docs; the single-precision copy is the contact
            // correction's); `Exact` stays the double-precision reference.
            st.factor.round_to_single_and_half();
        }
        let dt = t0.elapsed().as_secs_f64();
        self.stats.factor_seconds = dt;
        self.stats.blocking_seconds += dt;
        match res {
            Ok(()) => {
                st.rotations.copy_from_slice(rotations);
                st.step = step;
                st.version += 1;
                self.stats.refreshes += 1;
                Ok(())
            }
            Err(e) => {
                self.stats.failures += 1;
                self.state = None;
                Err(e)
            }
        }
    }

    /// Refreshes the preconditioner for the matrix `a` of step `step`.
    /// `rotations` are the current node rotations (only read by warped kinds).
    pub fn update(&mut self, a: &BlockCsr, rotations: &[Mat3], step: u64) -> Result<()> {
        self.stats.blocking_seconds = 0.0;
        match self.kind {
            PreconditionerKind::None => {}
            PreconditionerKind::Jacobi => {
                for i in 0..a.n() {
                    let d = a.diag(i);
                    self.jacobi[i] = Vec3::new(1.0 / d[(0, 0)], 1.0 / d[(1, 1)], 1.0 / d[(2, 2)]);
                }
            }
            PreconditionerKind::Exact => self.factorize_now(a, rotations, step)?,
            PreconditionerKind::Periodic { every } => {
                let due = self
                    .state
                    .as_ref()
                    .is_none_or(|s| step >= s.step + every as u64);
                if due {
                    self.factorize_now(a, rotations, step)?;
                }
            }
            PreconditionerKind::Async | PreconditionerKind::AsyncLagged { .. } => {
                // `AsyncLagged`: take the factor at `submitted + lag` exactly,
                // waiting for it if need be; `Async`: whenever it is done.
                let take = |w: &mut AsyncFactorizer| match self.kind {
                    PreconditionerKind::AsyncLagged { lag } => (w.in_flight()
                        && step >= w.submitted_step() + lag as u64)
                        .then(|| w.try_take(true))
                        .flatten(),
                    _ => w.try_take(false),
                };
                if self.state.is_none() {
                    // First step: blocking is allowed.
                    self.factorize_now(a, rotations, step)?;
                } else if let Some(done) = self.worker.as_mut().and_then(take) {
                    self.adopt(done);
                }
                if let Some(w) = &mut self.worker {
                    if w.is_alive() {
                        let queue = !matches!(self.kind, PreconditionerKind::AsyncLagged { .. });
                        w.submit(a, rotations, step, &mut self.prefetch, queue);
                    } else if !w.in_flight()
                        && self
                            .state
                            .as_ref()
                            .is_some_and(|s| step >= s.step + WORKER_FALLBACK_PERIOD)
                    {
                        // No worker thread: refresh here, as `Periodic` would.
                        self.factorize_now(a, rotations, step)?;
                        self.stats.fallback_refreshes += 1;
                    }
                }
            }
        }
        if let Some(st) = &mut self.state {
            self.stats.factor_age = step.saturating_sub(st.step);
            st.rotated = self.kind.needs_rotations() && st.step != step;
            st.warped = st.rotated;
            if st.rotated {
                fill_warp(WarpKind::Nodes, rotations, &st.rotations, &mut st.node_warp);
                st.body_warp = body_turn(rotations, &st.rotations);
                // The kind chosen for this factor holds until it is tried again.
                let kind = match self.warp_choice {
                    Some((v, Some(kind))) if v == st.version => kind,
                    _ => WarpKind::Nodes,
                };
                st.set_warp_kind(kind);
            } else {
                st.warp.fill(Mat3::identity());
                st.node_warp.fill(Mat3::identity());
                st.body_warp = Mat3::identity();
            }
        }
        Ok(())
    }
}

fn residual_norm2(a: &BlockCsr, r: &[Vec3], z: &[Vec3], q: &mut [Vec3]) -> f64 {
    a.mul_vec(z, q);
    r.iter()
        .zip(q.iter())
        .map(|(r, q)| (r - q).norm_squared())
        .sum()
}

impl FactorState {
    /// Fills [`Self::warp`] with the warp of `kind`.
    fn set_warp_kind(&mut self, kind: WarpKind) {
        match kind {
            WarpKind::Nodes => self.warp.copy_from_slice(&self.node_warp),
            WarpKind::Body => self.warp.fill(self.body_warp),
        }
        self.warp_kind = kind;
    }

    /// [`Self::set_warp_kind`] where [`Self::warp`] holds another kind.
    fn switch_warp_kind(&mut self, kind: WarpKind) {
        if self.warp_kind != kind {
            self.set_warp_kind(kind);
        }
    }
}

impl PreconditionerState {
    /// [`Preconditioner::apply`] with the warp of `kind`, or none (a factor is in use).
    fn apply_warped(&mut self, kind: Option<WarpKind>, r: &[Vec3], z: &mut [Vec3]) {
        if let Some(st) = &mut self.state {
            st.warped = kind.is_some();
            if let Some(kind) = kind {
                st.switch_warp_kind(kind);
            }
        }
        self.solve_with_factor(r, z);
    }

    /// Starts a CG solve: chooses the copy of the factor it solves with (see
    /// [`HALF_FROM_ITERATIONS`]) and counts the first residual's solve.
    fn start_solve(&mut self) {
        self.half_now = self.applies >= HALF_FROM_ITERATIONS;
        self.applies = 1;
        if self.half_now && self.state.as_ref().is_some_and(|st| st.factor.has_half()) {
            self.stats.half_solves += 1;
        }
    }

    /// `z = P⁻¹ r`, uncounted.
    fn solve_with_factor(&mut self, r: &[Vec3], z: &mut [Vec3]) {
        match (&self.kind, &self.state) {
            (PreconditionerKind::None, _) => z.copy_from_slice(r),
            (PreconditionerKind::Jacobi, _) => {
                for i in 0..r.len() {
                    z[i] = r[i].component_mul(&self.jacobi[i]);
                }
            }
            (_, Some(st)) => {
                let rhs = if st.warped {
                    for i in 0..r.len() {
                        self.tmp2[i] = st.warp[i].transpose() * r[i];
                    }
                    &self.tmp2
                } else {
                    r
                };
                if self.half_now {
                    st.factor.solve_half(rhs, z, &mut self.tmp, &mut self.tmp32);
                } else {
                    st.factor.solve_single(rhs, z, &mut self.tmp);
                }
                if st.warped {
                    for zi in z.iter_mut().zip(&st.warp) {
                        *zi.0 = zi.1 * *zi.0;
                    }
                }
            }
            (_, None) => z.copy_from_slice(r),
        }
    }
}

impl Preconditioner for PreconditionerState {
    /// With a warp to apply, tries the factor with each node's turn, with the
    /// body's one turn (where the body turned at all) and without a warp on
    /// the first residual, and keeps the one that leaves the smallest residual
    /// `‖r − A P⁻¹ r‖` (the best fit of `A` where the solve starts). The
    /// choice holds for the factor's later steps and is tried again when the
    /// factor is 4, 8, 16, … steps old.
    fn apply_first(&mut self, a: &BlockCsr, r: &[Vec3], z: &mut [Vec3], q: &mut [Vec3]) {
        self.start_solve();
        let Some((version, turned)) = self
            .state
            .as_ref()
            .filter(|st| st.rotated)
            .map(|st| (st.version, st.body_warp != Mat3::identity()))
        else {
            return self.solve_with_factor(r, z);
        };
        self.stats.warp_offered += 1;
        // Decided once per factor, and again as it ages (4, 8, 16, … steps).
        let age = self.stats.factor_age;
        let choice = match self.warp_choice {
            Some((v, choice)) if v == version && !(age >= 4 && age.is_power_of_two()) => {
                self.apply_warped(choice, r, z);
                choice
            }
            _ => {
                let mut alt = std::mem::take(&mut self.alt);
                let mut best = (Some(WarpKind::Nodes), 0.0);
                self.apply_warped(best.0, r, z);
                best.1 = residual_norm2(a, r, z, q);
                let candidates: &[Option<WarpKind>] = if turned {
                    &[Some(WarpKind::Body), None]
                } else {
                    &[None]
                };
                for &c in candidates {
                    self.apply_warped(c, r, &mut alt);
                    let fit = residual_norm2(a, r, &alt, q);
                    if fit < best.1 {
                        best = (c, fit);
                        z.copy_from_slice(&alt);
                    }
                }
                self.alt = alt;
                if let (Some(st), Some(kind)) = (&mut self.state, best.0) {
                    st.switch_warp_kind(kind);
                }
                self.warp_choice = Some((version, best.0));
                best.0
            }
        };
        if let Some(st) = &mut self.state {
            st.warped = choice.is_some();
        }
        match choice {
            None => self.stats.warp_declined += 1,
            Some(WarpKind::Body) => self.stats.warp_body += 1,
            Some(WarpKind::Nodes) => {}
        }
    }

    fn apply(&mut self, r: &[Vec3], z: &mut [Vec3]) {
        self.applies += 1;
        self.solve_with_factor(r, z);
    }
}
