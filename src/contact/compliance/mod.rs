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
//! (the same operator), it costs six forward sweeps with the factor per body and step
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
//! One file per mode: `factorized.rs` (`Factorized` and `Exact`: where the
//! factor comes from, the snapshot for `factor_reuse`, `W` from cached node
//! columns, the correction; `deflation.rs` the rigid-mode completion of a
//! lagging factor), `dense_rows.rs`, `diagonal.rs`, `rest.rs`. `entries.rs`
//! holds the types they share (the mode, the Jacobian entry, the factor
//! view, scratch); this file the dispatch: every `match` on
//! [`ComplianceMode`] is exhaustive, so a new mode is a compile error until
//! each phase handles it.
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
pub(crate) use entries::WBlock;
pub use entries::{ComplianceMode, JacEntry};
use entries::{FactorView, Scratch, group};
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
    /// Set by the contact solver for the next [`Self::accumulate`] only:
    /// what the build may assume of `w` (see [`WBlock`]).
    pub(crate) block: WBlock,
    source: factorized::FactorSource,
    deflation: deflation::Deflation,
    cache: ColumnCache,
    rest: rest::RestInverse,
    scratch: Scratch,
}

/// Whether `W` and the correction of this view get the rigid-mode
/// completion: `Factorized` with a factor that lags the matrix, for a body
/// with no constrained node (one held in place has no soft rigid modes).
fn completes(on: bool, body: &DeformableBody, mode: ComplianceMode, view: &FactorView<'_>) -> bool {
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
) -> Result<FactorView<'a>> {
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
        let mut block = std::mem::take(&mut self.block);
        self.cache.solves = 0;
        self.cache.gram_blocks = 0;
        let in_place_capable = matches!(mode, ComplianceMode::Factorized | ComplianceMode::Exact);
        if block == WBlock::Unset && (entries.is_empty() || !in_place_capable) {
            w.fill(0.0);
            block = WBlock::Zero;
        }
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
                let on_backend_mode = mode == ComplianceMode::Factorized && shared;
                if block == WBlock::Unset && on_backend_mode && backend.is_some() {
                    // The backend adds to `w`.
                    w.fill(0.0);
                    block = WBlock::Zero;
                }
                let on_backend = on_backend_mode
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
                let complete = completes(self.rigid_modes, body, mode, &view)
                    && self.deflation.prepare(body, &view);
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
                        block,
                        complete.then_some(&mut self.deflation),
                    );
                } else if complete {
                    self.deflation.add_to_w(&view, None, entries, h2, w, m);
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
                let deflation = (completes(self.rigid_modes, body, mode, &view)
                    && self.deflation.prepare(body, &view))
                .then_some(&self.deflation);
                factorized::correction(
                    &view,
                    cache,
                    h2,
                    entries,
                    lambda,
                    &mut self.scratch,
                    dx,
                    deflation,
                );
                Ok(())
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::BodySettings;
    use crate::fem::assembly::BlockCsr;
    use crate::material::TissueMaterial;
    use crate::math::{Mat3, test_value};
    use crate::mesh::generate;
    use crate::solver::PreconditionerKind;
    use nalgebra::{DMatrix, DVector, Rotation3};

    /// A small free lens (`cells` across) with preconditioner `kind`, after
    /// one step (it has a factor).
    pub(super) fn lens(cells: usize, kind: PreconditionerKind) -> DeformableBody {
        let mesh = generate::ellipsoid([2e-3, 2e-3, 1.5e-3], cells).unwrap();
        let settings = BodySettings {
            preconditioner: kind,
            ..Default::default()
        };
        let mut body = DeformableBody::new(mesh, TissueMaterial::default(), settings).unwrap();
        body.step(0.01).unwrap();
        body
    }

    /// A free lens whose factor (taken at rest) lags a twisted, turned
    /// state: the warp varies across it, so the completion matters.
    fn twisted_lens() -> DeformableBody {
        let mut body = lens(3, PreconditionerKind::Periodic { every: 1000 });
        let x: Vec<Vec3> = body
            .positions()
            .iter()
            .map(|p| Rotation3::from_axis_angle(&Vec3::z_axis(), 0.4 + 150.0 * p.z) * p)
            .collect();
        let v = vec![Vec3::zeros(); x.len()];
        body.set_state(&x, &v).unwrap();
        body.step(0.01).unwrap();
        body
    }

    /// A later pass of the same step reads the completion's rows of `V` at
    /// the nodes an earlier pass met instead of their paths again, and gets
    /// the `W` of a build that reads every path (to round-off: the Gram
    /// blocks are summed in the order of the cache's columns); a new step
    /// reads them anew.
    #[test]
    fn later_passes_reuse_the_completions_node_rows() {
        let mut body = twisted_lens();
        let n = body.num_nodes();
        let h = 0.01;
        let m = 12;
        // Pass 1 on nodes 0, 7, 14, ...; pass 2 shares half of them.
        let make = |offset: usize| {
            let mut e: Vec<JacEntry> = (0..m)
                .map(|row| JacEntry {
                    node: (((row + offset) * 7) % n) as u32,
                    row: row as u32,
                    h: Vec3::new(test_value(row, 1), test_value(row, 2), test_value(row, 3)),
                    j: Vec3::zeros(),
                })
                .collect();
            e.sort_by_key(|e| (e.node, e.row));
            e
        };
        let build = |comp: &mut BodyCompliance, body: &DeformableBody, e: &mut Vec<JacEntry>| {
            let mut prefetch = ColumnPrefetch::default();
            let mut w = vec![0.0; m * m];
            comp.accumulate(
                body,
                &mut prefetch,
                ComplianceMode::Factorized,
                h,
                e,
                &mut w,
                m,
                None,
            )
            .unwrap();
            w
        };
        let mut comp = BodyCompliance::new();
        comp.rigid_modes = true;
        comp.deflation.path_share = Some(f64::INFINITY);
        let (mut first, mut second) = (make(0), make(m / 2));
        build(&mut comp, &body, &mut first);
        assert!(comp.deflation.active);
        assert_eq!(comp.deflation.path_reads, m, "one path per node");
        let w2 = build(&mut comp, &body, &mut second);
        assert_eq!(
            comp.deflation.path_reads,
            m + m / 2,
            "only the nodes new in the second pass read their paths"
        );
        let mut fresh = BodyCompliance::new();
        fresh.rigid_modes = true;
        fresh.deflation.path_share = Some(f64::INFINITY);
        let w_fresh = build(&mut fresh, &body, &mut make(m / 2));
        assert_eq!(fresh.deflation.path_reads, m);
        let scale = w_fresh.iter().map(|v| v.abs()).fold(0.0, f64::max);
        assert!(scale > 0.0);
        for (a, b) in w2.iter().zip(&w_fresh) {
            assert!((a - b).abs() <= 1e-12 * scale, "{a:e} against {b:e}");
        }
        // A new step (same factor, new matrix): every node is read anew.
        body.step(0.01).unwrap();
        build(&mut comp, &body, &mut make(m / 2));
        assert_eq!(comp.deflation.path_reads, 2 * m + m / 2);
    }

    /// `per_row · k` entries on `k` rows (`row_of(r)`, `r < k`) at nodes
    /// spread over `n`, sorted by node as a build sorts them; a row's
    /// entries lie at different nodes when `per_row > 1`.
    fn spread_entries(
        n: usize,
        k: usize,
        per_row: usize,
        row_of: &dyn Fn(usize) -> u32,
    ) -> Vec<JacEntry> {
        let mut e: Vec<JacEntry> = (0..per_row * k)
            .map(|i| JacEntry {
                node: ((i * 13) % n) as u32,
                row: row_of(i % k),
                h: Vec3::new(test_value(i, 1), test_value(i, 2), test_value(i, 3)),
                j: Vec3::zeros(),
            })
            .collect();
        e.sort_by_key(|e| (e.node, e.row));
        e.dedup_by_key(|e| (e.node, e.row));
        e
    }

    /// `W` (`m × m`) of one `Factorized` build of `body`'s `entries`, with
    /// the completion on or off and the block as `block` says: from zero,
    /// or for [`WBlock::Unset`] from NaN in every entry.
    fn factorized_w(
        body: &DeformableBody,
        rigid: bool,
        block: WBlock,
        mut entries: Vec<JacEntry>,
        m: usize,
    ) -> Vec<f64> {
        let mut comp = BodyCompliance::new();
        comp.rigid_modes = rigid;
        comp.block = block;
        let mut rows: Vec<u32> = entries.iter().map(|e| e.row).collect();
        rows.sort_unstable();
        rows.dedup();
        let contiguous = rows
            .last()
            .is_some_and(|&l| (l - rows[0]) as usize + 1 == rows.len());
        let start = if block == WBlock::Unset {
            f64::NAN
        } else {
            0.0
        };
        let mut w = vec![start; m * m];
        comp.accumulate(
            body,
            &mut ColumnPrefetch::default(),
            ComplianceMode::Factorized,
            0.01,
            &mut entries,
            &mut w,
            m,
            None,
        )
        .unwrap();
        assert_eq!(comp.block, WBlock::Written, "the block serves one build");
        assert_eq!(comp.deflation.active, rigid);
        // The completion's term goes in with the mirror where `W` is built
        // in place.
        let fused = rigid && block != WBlock::Written && contiguous;
        assert_eq!(comp.deflation.fused_builds, usize::from(fused));
        w
    }

    /// A body whose rows of `W` are not contiguous (another body's rows
    /// between them) gets exactly the entries it gets with its rows packed,
    /// and leaves the rows between alone; with the rigid-mode completion and
    /// without.
    #[test]
    fn rows_between_a_bodys_rows_stay_untouched() {
        let body = twisted_lens();
        let n = body.num_nodes();
        let k = 11;
        for rigid in [true, false] {
            let build = |row_of: &dyn Fn(usize) -> u32, m: usize| {
                factorized_w(
                    &body,
                    rigid,
                    WBlock::Written,
                    spread_entries(n, k, 2, row_of),
                    m,
                )
            };
            let packed = build(&|r| r as u32, k);
            let m = 2 * k + 1;
            let spread = build(&|r| (2 * r + 1) as u32, m);
            for r in 0..m {
                for c in 0..m {
                    let want = if r % 2 == 1 && c % 2 == 1 {
                        packed[(r / 2) * k + c / 2]
                    } else {
                        0.0
                    };
                    let got = spread[r * m + c];
                    assert!(
                        got == want,
                        "rigid {rigid}: ({r}, {c}): {got:e} against {want:e}"
                    );
                }
            }
            assert!(packed.iter().all(|v| v.is_finite()) && packed[0] > 0.0);
        }
    }

    /// [`ColumnCache::precompute`] forms every Gram block of its columns
    /// once, in tiles, to the bit as a cache that forms them on demand in
    /// another order, over more columns than two tiles (full and partial
    /// tiles, a node twice).
    #[test]
    fn precompute_forms_every_block_as_on_demand() {
        use crate::solver::columns::PRECOMPUTE_TILE;
        let body = lens(5, PreconditionerKind::Exact);
        let f = &body.preconditioner().factor_state().unwrap().factor;
        let n = f.symbolic.n;
        let count = 2 * PRECOMPUTE_TILE as usize + 7;
        assert!(n > count, "{n} nodes");
        // Spread over the mesh, one node twice.
        let mut nodes: Vec<u32> = (0..count).map(|i| ((i * 7919) % n) as u32).collect();
        nodes.push(nodes[3]);
        let key = FactorKey::Own(1);
        let mut pre = ColumnCache::default();
        pre.precompute(f, key, &nodes);
        let cols = pre.cols.len() as u32;
        assert_eq!(cols as usize, count);
        assert_eq!(pre.gram_blocks, count * (count + 1) / 2, "each pair once");
        assert!(pre.pairs.iter().all(|g| g.is_some()));
        // The same columns, each block formed when first asked for, last
        // pair first.
        let mut lazy = ColumnCache::default();
        lazy.reset(n, key);
        for &k in &nodes {
            lazy.column(f, k as usize);
        }
        assert_eq!(lazy.col_of_node, pre.col_of_node);
        for b in (0..cols).rev() {
            for a in (0..cols).rev() {
                assert_eq!(pre.gram(a, b), lazy.gram(a, b), "columns {a}, {b}");
            }
        }
        assert_eq!(lazy.gram_blocks, pre.gram_blocks);
        assert!(pre.gram(0, 0)[(0, 0)] > 0.0);
    }

    /// A body whose block of `W` is still zero ([`WBlock::Zero`]) gets it
    /// built in place: the same `W` as through `tri`, to the bit where each
    /// row has entries at one node only, and to rounding where a row's
    /// entries span nodes (the self-blocks of the nodes are then summed in
    /// another order, and the completion's term before the self-blocks,
    /// by the mirror). Rows that are not contiguous go through `tri` even
    /// when fresh, and the block serves one build only. A build into a `w`
    /// of NaN ([`WBlock::Unset`]) gives the in-place `W` to the bit, both
    /// where it writes every entry itself (its rows all of `w`'s) and where
    /// it zeroes `w` first.
    #[test]
    fn a_fresh_block_is_built_in_place_to_the_same_w() {
        let body = twisted_lens();
        let n = body.num_nodes();
        // 21 rows: full and partial 8×8 tiles, on and off the diagonal.
        let k = 21;
        for rigid in [true, false] {
            for per_row in [1, 2] {
                for spread in [false, true] {
                    let row_of = |r: usize| if spread { 2 * r as u32 } else { r as u32 };
                    let m = if spread { 2 * k } else { k };
                    let build = |block: WBlock| {
                        factorized_w(
                            &body,
                            rigid,
                            block,
                            spread_entries(n, k, per_row, &row_of),
                            m,
                        )
                    };
                    let (through_tri, in_place) = (build(WBlock::Written), build(WBlock::Zero));
                    let unset = build(WBlock::Unset);
                    for (i, (a, b)) in unset.iter().zip(&in_place).enumerate() {
                        assert!(
                            a == b,
                            "rigid {rigid}, {per_row} per row, spread {spread}: unset \
                             entry {i}: {a:e} against {b:e}"
                        );
                    }
                    let scale = through_tri.iter().fold(0.0f64, |a, v| a.max(v.abs()));
                    assert!(scale > 0.0 && in_place.iter().all(|v| v.is_finite()));
                    // With the completion in place its term is added
                    // before the self-blocks, not after: rounding again.
                    let tol = if (per_row == 1 && !rigid) || spread {
                        0.0
                    } else {
                        1e-14 * scale
                    };
                    for r in 0..m {
                        for c in 0..m {
                            let (got, want) = (in_place[r * m + c], through_tri[r * m + c]);
                            assert!(
                                (got - want).abs() <= tol,
                                "rigid {rigid}, {per_row} per row, spread {spread}: \
                                 ({r}, {c}): {got:e} against {want:e}"
                            );
                        }
                    }
                }
            }
        }
    }

    /// `(L D Lᵀ)⁻¹` of `f` densely, in original numbering (`warp` applied
    /// as `Q (·) Qᵀ` when given).
    fn dense_inverse(f: &LdltFactor, warp: Option<&[Mat3]>) -> DMatrix<f64> {
        let n = f.symbolic.n;
        let mut inv = DMatrix::zeros(3 * n, 3 * n);
        let (mut b, mut x, mut tmp) = (
            vec![Vec3::zeros(); n],
            vec![Vec3::zeros(); n],
            vec![Vec3::zeros(); n],
        );
        for i in 0..n {
            for r in 0..3 {
                b.fill(Vec3::zeros());
                let mut e = Vec3::zeros();
                e[r] = 1.0;
                b[i] = warp.map_or(e, |q| q[i].transpose() * e);
                f.solve(&b, &mut x, &mut tmp);
                for k in 0..n {
                    let xk = warp.map_or(x[k], |q| q[k] * x[k]);
                    for c in 0..3 {
                        inv[(3 * k + c, 3 * i + r)] = xk[c];
                    }
                }
            }
        }
        inv
    }

    /// `Q + (I − Q A) P⁻¹ (I − A Q)`, `Q = Z (Zᵀ A Z)⁻¹ Zᵀ` over the six
    /// rigid modes of `body` (as `deflation.rs` makes them).
    fn two_level(body: &DeformableBody, a: &BlockCsr, pinv: &DMatrix<f64>) -> DMatrix<f64> {
        let x = body.positions();
        let mass = body.mass();
        let n = x.len();
        let mt: f64 = mass.iter().sum();
        let c = x.iter().zip(mass).map(|(x, m)| x * *m).sum::<Vec3>() / mt;
        let len = (x
            .iter()
            .zip(mass)
            .map(|(x, m)| m * (x - c).norm_squared())
            .sum::<f64>()
            / mt)
            .sqrt();
        let z = DMatrix::from_fn(3 * n, 6, |row, k| {
            let (i, r) = (row / 3, row % 3);
            let mut e = Vec3::zeros();
            e[k % 3] = 1.0;
            let v = if k < 3 { e } else { e.cross(&(x[i] - c)) / len };
            v[r]
        });
        let a = a.to_dense();
        let g = (z.transpose() * &a * &z).try_inverse().unwrap();
        let q = &z * g * z.transpose();
        let id = DMatrix::<f64>::identity(3 * n, 3 * n);
        &q + (&id - &q * &a) * pinv * (&id - &a * &q)
    }

    /// Adds `h² J (L D Lᵀ)⁻¹ Jᵀ` from a dense inverse, as a GPU backend
    /// would add it: the completion then has no node columns to read.
    struct Dense(DMatrix<f64>);

    impl ComplianceBackend for Dense {
        fn accumulate(
            &mut self,
            _: u64,
            _: &LdltFactor,
            _: FactorKey,
            h: f64,
            entries: &[JacEntry],
            w: &mut [f64],
            m: usize,
        ) -> Result<bool> {
            for a in entries {
                for b in entries {
                    let (i, k) = (3 * a.node as usize, 3 * b.node as usize);
                    let blk = Mat3::from_fn(|r, c| self.0[(i + r, k + c)]);
                    w[a.row as usize * m + b.row as usize] += h * h * a.j.dot(&(blk * b.j));
                }
            }
            Ok(true)
        }
    }

    /// With a lagging warped factor, `W` and the correction of a free body
    /// are `h² H P_D⁻¹ Hᵀ` and `h² P_D⁻¹ Hᵀ λ` with the two-level inverse
    /// `P_D⁻¹` formed densely, whether `W`'s rows of `V` come from the node
    /// columns or from a backward sweep (chosen by cost, or because a
    /// backend built `W` without the columns); without the
    /// completion they are the factor's alone, which differs.
    #[test]
    fn completion_matches_the_dense_two_level_inverse() {
        let body = twisted_lens();
        let n = body.num_nodes();
        let h = 0.01;
        let mut entries = Vec::new();
        let m = 24;
        for row in 0..m {
            for t in 0..1 + row % 3 {
                let node = ((row * 11 + t * 29) % n) as u32;
                let v = |s| test_value(row * 3 + t, s);
                entries.push(JacEntry {
                    node,
                    row: row as u32,
                    h: Vec3::new(v(1), v(2), v(3)),
                    j: Vec3::zeros(),
                });
            }
        }
        entries.sort_by_key(|e| (e.node, e.row));
        entries.dedup_by_key(|e| (e.node, e.row));
        let hm = DMatrix::from_fn(m, 3 * n, |r, col| {
            entries
                .iter()
                .filter(|e| e.row as usize == r && e.node as usize == col / 3)
                .map(|e| e.h[col % 3])
                .sum()
        });
        let lambda: Vec<f64> = (0..m).map(|r| test_value(r, 8).abs() + 0.5).collect();
        let mut results = Vec::new();
        // (completion, backend, share of `L` under which `V` reads the node
        // columns: all of them, or none, the backward sweep).
        let inf = f64::INFINITY;
        for (rigid, backend, share) in [
            (true, false, inf),
            (true, false, 0.0),
            (true, true, inf),
            (false, false, inf),
        ] {
            let mut comp = BodyCompliance::new();
            comp.rigid_modes = rigid;
            comp.deflation.path_share = Some(share);
            let mut prefetch = ColumnPrefetch::default();
            let mut w = vec![0.0; m * m];
            let mut dense = None;
            if backend {
                comp.source
                    .refresh(&body, ComplianceMode::Factorized, 0, &mut comp.cache)
                    .unwrap();
                let view = comp.source.view(&body, ComplianceMode::Factorized).unwrap();
                dense = Some(Dense(dense_inverse(view.factor, None)));
            }
            comp.accumulate(
                &body,
                &mut prefetch,
                ComplianceMode::Factorized,
                h,
                &mut entries,
                &mut w,
                m,
                dense.as_mut().map(|d| d as &mut dyn ComplianceBackend),
            )
            .unwrap();
            let mut dx = Vec::new();
            comp.correction(
                &body,
                ComplianceMode::Factorized,
                h,
                &entries,
                &lambda,
                &mut dx,
            )
            .unwrap();
            let view = comp.source.view(&body, ComplianceMode::Factorized).unwrap();
            assert!(view.warp.is_some(), "the factor lags with a warp");
            assert_eq!(comp.deflation.active, rigid);
            let mut pinv = dense_inverse(view.factor, view.warp);
            if rigid {
                pinv = two_level(&body, body.system_matrix(), &pinv);
            }
            let w_ref = &hm * &pinv * hm.transpose() * (h * h);
            let dx_ref = &pinv * hm.transpose() * DVector::from_vec(lambda.clone()) * (h * h);
            let scale = w_ref.abs().max();
            for r in 0..m {
                for c in 0..m {
                    let d = (w[r * m + c] - w_ref[(r, c)]).abs();
                    assert!(
                        d <= 1e-9 * scale,
                        "rigid {rigid}, backend {backend}, share {share}: W ({r}, {c}) off by {d:e} of {scale:e}"
                    );
                }
            }
            let dscale = dx_ref.abs().max();
            for i in 0..n {
                for c in 0..3 {
                    // The backward sweep reads `L` in single precision.
                    let d = (dx[i][c] - dx_ref[3 * i + c]).abs();
                    assert!(
                        d <= 1e-5 * dscale,
                        "rigid {rigid}, backend {backend}, share {share}: dx off by {d:e} of {dscale:e}"
                    );
                }
            }
            results.push(w);
        }
        let diff = results[0]
            .iter()
            .zip(&results[3])
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        let scale = results[3].iter().map(|v| v.abs()).fold(0.0, f64::max);
        assert!(
            diff > 1e-3 * scale,
            "the completion changes W ({diff:e} of {scale:e})"
        );
    }
}
