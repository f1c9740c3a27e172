//! Phase 2b, contact compliance `W = h² H A⁻¹ Hᵀ` per body, and the matching
//! correction `Δx = h² A⁻¹ Hᵀ λ` (phase 4 applies it).
//!
//! ## `Factorized` (the default)
//! With the body's factor `A ≈ Q Pᵀ L D Lᵀ P Qᵀ` (Q the rotation warp since
//! the factor was made, P the fill-reducing permutation) and `J = H Q`:
//!
//! ```text
//! W = h² J (LDLᵀ)⁻¹ Jᵀ = h² Yᵀ D⁻¹ Y,   Y = L⁻¹ P Jᵀ = Σ_k Z_k (J_k)ᵀ,   Z_k = L⁻¹ P E_k
//! ```
//!
//! `Z_k` are the three unit columns of contact node `k` after one forward
//! solve. Their nonzeros lie on the elimination-tree path of `k` to the root,
//! so the solve touches only that path (3×3 node supernodes). `Z_k` depends
//! only on the factor — not on normals, tangents or rotations — so columns and
//! their Gram blocks `G_kl = Z_kᵀ D⁻¹ Z_l` are cached until the factor changes
//! (the paths of `k` and `l` share their common suffix above the lowest common
//! ancestor, the only place `G_kl` sums over). Per step only new nodes are
//! solved and the small 3×3 blocks are contracted with `J`:
//! `W_rs = h² Σ_kl j_rkᵀ G_kl j_sl`. With the `Async` preconditioner even a
//! new factor rarely costs solves here: its background worker solves the
//! columns and Gram blocks of the nodes of the last build before it hands the
//! factor over (see [`crate::solver`], "Contact columns made with the factor").
//!
//! The correction `Δx = h² Q Pᵀ L⁻ᵀ D⁻¹ (Y λ)` needs one backward solve. Using the
//! same factor for `W` and the correction keeps them consistent: the
//! displacement the LCP predicted is exactly the one applied, so contacts end
//! the step without penetration. Re-solving the correction with CG on the exact
//! `A` would move the nodes slightly differently from what `W` assumed, and
//! reopen penetrations of that size; the factor's error is the small error of the
//! preconditioner itself. (Tried: such a CG "polish" of each correction
//! threw two squeezed blocks through their plates within 20 steps, each
//! pass's `W` predicting less than the body then moved.)
//!
//! ## Rigid modes of a lagging factor
//! A factor of an older matrix, warped by the node rotations since, answers
//! a force that moves a free body as a whole wrongly where the rotations
//! vary across the body: the warp turns the rigid modes into deformation.
//! For a lens landing on a plate or held up against gravity every step, the
//! correction is mostly such a motion, and it stored up to a few per cent
//! more energy than the LCP accounted for. With
//! [`crate::contact::ContactSettings::rigid_modes`] (default on) `W` and the
//! correction of a free body with a lagging factor use the two-level inverse
//! `Q + (I − QA) P⁻¹ (I − AQ)`, `Q = Z (Zᵀ A Z)⁻¹ Zᵀ` over its six rigid
//! modes `Z`: exact on them, the factor for the rest. Both stay consistent
//! (the same operator), it costs six solves with the factor per body and step
//! and a rank-12 update of `W` (`deflation.rs`).
//!
//! ## Other modes
//! - `Exact`: the same with a fresh factorization of the current `A` (Q = I).
//! - `DenseRows`: the paper's CPU method — two full triangular solves per
//!   row of `J`. Same `W` as `Factorized`; kept as the benchmark baseline.
//! - `Diagonal`: uncoupled, `W` from the 3×3 diagonal blocks of `A` only.
//! - `RestPrecomputed`: the dense inverse of the first `A` (at rest),
//!   rotated by the node rotations (the paper's reference \[11\]). Refused above
//!   [`REST_PRECOMPUTED_MAX_NODES`] nodes.

//!
//! ## Files
//! One file per mode: `factorized.rs` (`Factorized` and `Exact`: the factor
//! view, the snapshot for `factor_reuse`, cached node columns; `deflation.rs`
//! the rigid-mode completion of a lagging one), `dense_rows.rs`,
//! `diagonal.rs`, `rest.rs`. This file holds the types and the dispatch: every
//! `match` on [`ComplianceMode`] is exhaustive, so a new mode is a compile
//! error until each phase handles it.
//!
//! ## Which factor
//! [`BodyCompliance::accumulate`] asks `FactorSource::view` (`factorized.rs`) once
//! for the factor, warp and [`FactorKey`] of the step; the correction asks the
//! same view again, so `W` and `Δx` always use the same factor. The key, not a
//! bit pattern, tells the column cache whose columns it holds.

mod deflation;
mod dense_rows;
mod diagonal;
mod factorized;
mod rest;

use crate::body::{DeformableBody, NodeConstraint};
use crate::error::Result;
use crate::math::Vec3;
use crate::solver::columns::{ColumnCache, ColumnPrefetch};
use crate::solver::ldlt::LdltFactor;

mod entries;

pub use crate::solver::columns::FactorKey;
pub use entries::{ComplianceMode, JacEntry};
use entries::{Scratch, group};
pub use rest::REST_PRECOMPUTED_MAX_NODES;

/// Builds a body's compliance somewhere else than on the CPU (the GPU path of
/// the `gpu` feature). Called for bodies in [`ComplianceMode::Factorized`] that
/// have a preconditioner factor, with `entries` sorted by node and their `j`
/// (`Qᵀ h`, the factor's frame) filled.
pub trait ComplianceBackend {
    /// Adds `h² J (L D Lᵀ)⁻¹ Jᵀ` of this body to `w` (`m × m`, row-major) and
    /// returns `Ok(true)`, or returns `Ok(false)` to let the CPU do it. `key`
    /// names the factor: the same key means the same factor values.
    #[allow(clippy::too_many_arguments)]
    fn accumulate(
        &mut self,
        body_id: u64,
        factor: &LdltFactor,
        key: FactorKey,
        h: f64,
        entries: &[JacEntry],
        w: &mut [f64],
        m: usize,
    ) -> Result<bool>;
}

/// Per-body compliance state, kept between steps.
#[derive(Debug, Default)]
pub struct BodyCompliance {
    /// Steps a factor snapshot may serve after a newer factor exists (0: always the newest).
    pub reuse_steps: u64,
    /// Complete a lagging factor with the body's rigid modes
    /// ([`crate::contact::ContactSettings::rigid_modes`]).
    pub rigid_modes: bool,
    source: factorized::FactorSource,
    deflation: deflation::Deflation,
    cache: ColumnCache,
    rest: rest::RestInverse,
    scratch: Scratch,
}

/// Whether `W` and the correction of this view get the rigid-mode
/// completion: `Factorized` with a factor that lags the matrix, for a body
/// with no constrained node (one held in place has no soft rigid modes).
fn completes(
    on: bool,
    body: &DeformableBody,
    mode: ComplianceMode,
    view: &factorized::FactorView<'_>,
) -> bool {
    on && mode == ComplianceMode::Factorized
        && body.settings().preconditioner.needs_rotations()
        && body
            .constraints()
            .iter()
            .all(|c| *c == NodeConstraint::Free)
        && matches!(
            view.key,
            FactorKey::Preconditioner(_) | FactorKey::Snapshot(_)
        )
}

/// Refreshes the step's factor and returns its view.
fn prepare<'a>(
    source: &'a mut factorized::FactorSource,
    cache: &mut ColumnCache,
    body: &'a DeformableBody,
    mode: ComplianceMode,
    reuse: u64,
) -> Result<factorized::FactorView<'a>> {
    source.refresh(body, mode, reuse, cache)?;
    source.view(body, mode)
}

impl BodyCompliance {
    /// Fresh state.
    pub fn new() -> Self {
        Self::default()
    }

    /// Forgets the cached node columns and Gram blocks (keeping their memory), as a
    /// new factor does: the next build solves every column again.
    pub fn forget_columns(&mut self) {
        self.cache.key = None;
    }

    /// Drops the factor snapshot kept for [`crate::contact::ContactSettings::factor_reuse`],
    /// so that the next build takes the preconditioner's newest factor.
    pub fn drop_snapshot(&mut self) {
        self.source.drop_snapshot();
    }

    /// Forward solves (node columns, or full solves for `DenseRows`) in the last build.
    pub fn solves(&self) -> usize {
        self.cache.solves
    }

    /// Gram blocks computed (not found in the cache) in the last build.
    pub fn gram_blocks(&self) -> usize {
        self.cache.gram_blocks
    }

    /// Adds this body's contribution to `w` (`m × m`, row-major).
    /// `entries` must be sorted by node; their `j` is filled here. A `backend`
    /// may take over `Factorized` bodies. `prefetch` is the body's node-column
    /// hand-over with its background factorizer (taken out of the body by the
    /// caller, see [`DeformableBody::column_prefetch_mut`]).
    #[allow(clippy::too_many_arguments)]
    pub fn accumulate(
        &mut self,
        body: &DeformableBody,
        prefetch: &mut ColumnPrefetch,
        mode: ComplianceMode,
        h: f64,
        entries: &mut [JacEntry],
        w: &mut [f64],
        m: usize,
        backend: Option<&mut dyn ComplianceBackend>,
    ) -> Result<()> {
        self.cache.solves = 0;
        self.cache.gram_blocks = 0;
        if entries.is_empty() {
            return Ok(());
        }
        let h2 = h * h;
        match mode {
            ComplianceMode::Diagonal => {
                group(entries, &mut self.scratch.groups);
                diagonal::accumulate(body, &self.scratch.groups, h2, entries, w, m)
            }
            ComplianceMode::RestPrecomputed => self.rest.accumulate(body, h2, entries, w, m),
            ComplianceMode::Factorized | ComplianceMode::Exact | ComplianceMode::DenseRows => {
                let view = prepare(
                    &mut self.source,
                    &mut self.cache,
                    body,
                    mode,
                    self.reuse_steps,
                )?;
                view.fill_j(entries);
                if mode == ComplianceMode::DenseRows {
                    dense_rows::accumulate(
                        &mut self.scratch,
                        &mut self.cache,
                        view.factor,
                        h2,
                        entries,
                        w,
                        m,
                    );
                    return Ok(());
                }
                let shared = matches!(
                    view.key,
                    FactorKey::Preconditioner(_) | FactorKey::Snapshot(_)
                );
                let on_backend = mode == ComplianceMode::Factorized
                    && shared
                    && match backend {
                        Some(backend) => backend.accumulate(
                            body.id(),
                            view.factor,
                            view.key,
                            h,
                            entries,
                            w,
                            m,
                        )?,
                        None => false,
                    };
                if !on_backend {
                    group(entries, &mut self.scratch.groups);
                    factorized::accumulate(
                        &view,
                        &mut self.cache,
                        prefetch,
                        &mut self.scratch,
                        h2,
                        entries,
                        w,
                        m,
                    );
                }
                if completes(self.rigid_modes, body, mode, &view)
                    && self.deflation.prepare(body, &view)
                {
                    self.deflation.add_to_w(entries, h2, w, m);
                }
                Ok(())
            }
        }
    }

    /// Position correction `dx = h² A⁻¹ Hᵀ λ` of this body, with the same approximation
    /// of `A⁻¹` that [`Self::accumulate`] used this step. `entries` as passed there.
    pub fn correction(
        &mut self,
        body: &DeformableBody,
        mode: ComplianceMode,
        h: f64,
        entries: &[JacEntry],
        lambda: &[f64],
        dx: &mut Vec<Vec3>,
    ) -> Result<()> {
        let n = body.num_nodes();
        dx.clear();
        dx.resize(n, Vec3::zeros());
        if entries.is_empty() {
            return Ok(());
        }
        let h2 = h * h;
        match mode {
            ComplianceMode::Diagonal => {
                diagonal::correction(body, h2, entries, lambda, dx);
                Ok(())
            }
            ComplianceMode::RestPrecomputed => {
                group(entries, &mut self.scratch.groups);
                self.rest
                    .correction(body, h2, entries, lambda, &mut self.scratch, dx)
            }
            ComplianceMode::Factorized | ComplianceMode::Exact | ComplianceMode::DenseRows => {
                let view = self.source.view(body, mode)?;
                // Only `Factorized` builds leave this step's columns in the cache.
                let cache = (mode == ComplianceMode::Factorized).then_some(&self.cache);
                factorized::correction(&view, cache, h2, entries, lambda, &mut self.scratch, dx);
                if completes(self.rigid_modes, body, mode, &view)
                    && self.deflation.prepare(body, &view)
                {
                    self.deflation.add_to_correction(entries, lambda, h2, dx);
                }
                Ok(())
            }
        }
    }
}
