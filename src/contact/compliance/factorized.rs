//! `Factorized` and `Exact` compliance: `W = h² Yᵀ D⁻¹ Y` from node columns,
//! and the correction with the same factor (see the module docs of
//! [`super`]). `DenseRows` reads its factor through the same
//! [`FactorSource::view`].

use std::sync::Arc;

use super::entries::{ComplianceMode, JacEntry, Scratch};
use crate::body::DeformableBody;
use crate::error::{Result, SoftTissueError};
use crate::math::{Mat3, Vec3};
use crate::solver::columns::{ColumnCache, ColumnPrefetch, FactorKey};
use crate::solver::ldlt::{LdltFactor, LdltSymbolic};

/// The factor, warp and key that `W` and the correction of one step use.
#[derive(Debug, Clone, Copy)]
pub(super) struct FactorView<'a> {
    pub(super) factor: &'a LdltFactor,
    /// `Q_i = R_i R̂_iᵀ` per node, or `None` for the identity.
    pub(super) warp: Option<&'a [Mat3]>,
    pub(super) key: FactorKey,
}

impl FactorView<'_> {
    /// `j = Qᵀ h`: the entries in the frame of the factor.
    pub(super) fn fill_j(&self, entries: &mut [JacEntry]) {
        for e in entries.iter_mut() {
            e.j = match self.warp {
                Some(q) => q[e.node as usize].transpose() * e.h,
                None => e.h,
            };
        }
    }
}

/// A copy of the preconditioner's factor that `W` and the correction keep
/// using for a few steps after the preconditioner moved on, so that the node
/// columns stay cached (see [`crate::contact::ContactSettings::factor_reuse`]).
#[derive(Debug, Default)]
struct Snapshot {
    factor: Option<LdltFactor>,
    rotations: Vec<Mat3>,
    warp: Vec<Mat3>,
    version: u64,
    step: u64,
    /// Take the preconditioner's factor at the next refresh, whatever its age.
    expired: bool,
}

/// Where a body's compliance factor comes from, kept between steps: the
/// preconditioner's (read in place), a snapshot of it, or an own
/// factorization of the current matrix.
#[derive(Debug, Default)]
pub(super) struct FactorSource {
    reuse: u64,
    snap: Snapshot,
    own: Option<LdltFactor>,
    own_symbolic: Option<Arc<LdltSymbolic>>,
    own_count: u64,
}

/// Which of the three a step uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Source {
    Own,
    Snapshot,
    Preconditioner,
}

impl FactorSource {
    fn source(&self, body: &DeformableBody, mode: ComplianceMode) -> Source {
        let has_factor = body.preconditioner().factor_state().is_some();
        if mode == ComplianceMode::Exact || !has_factor {
            Source::Own
        } else if mode == ComplianceMode::Factorized
            && self.reuse > 0
            && body.settings().preconditioner.needs_rotations()
        {
            Source::Snapshot
        } else {
            Source::Preconditioner
        }
    }

    /// Brings the step's factor up to date: factorizes the current matrix
    /// for an own factor, or refreshes the snapshot (and its warp).
    /// `cache` lends its work buffer to a factorization.
    pub(super) fn refresh(
        &mut self,
        body: &DeformableBody,
        mode: ComplianceMode,
        reuse: u64,
        cache: &mut ColumnCache,
    ) -> Result<()> {
        self.reuse = reuse;
        match self.source(body, mode) {
            Source::Own => self.refactor_own(body, cache),
            Source::Snapshot => self.refresh_snapshot(body),
            Source::Preconditioner => Ok(()),
        }
    }

    /// The factor, warp and key of this step (after [`Self::refresh`]).
    pub(super) fn view<'a>(
        &'a self,
        body: &'a DeformableBody,
        mode: ComplianceMode,
    ) -> Result<FactorView<'a>> {
        let missing = SoftTissueError::NonFinite("factor");
        Ok(match self.source(body, mode) {
            Source::Own => FactorView {
                factor: self.own.as_ref().ok_or(missing)?,
                warp: None,
                key: FactorKey::Own(self.own_count),
            },
            Source::Snapshot => FactorView {
                factor: self.snap.factor.as_ref().ok_or(missing)?,
                warp: Some(&self.snap.warp),
                key: FactorKey::Snapshot(self.snap.version),
            },
            Source::Preconditioner => {
                let st = body.preconditioner().factor_state().ok_or(missing)?;
                FactorView {
                    factor: &st.factor,
                    warp: st.warped.then_some(&st.warp[..]),
                    key: FactorKey::Preconditioner(st.version),
                }
            }
        })
    }

    fn refactor_own(&mut self, body: &DeformableBody, cache: &mut ColumnCache) -> Result<()> {
        let sym = match (&self.own_symbolic, body.preconditioner().symbolic()) {
            (Some(s), _) => Arc::clone(s),
            (None, Some(s)) => Arc::clone(s),
            (None, None) => Arc::new(LdltSymbolic::new(&body.system_matrix().pattern)?),
        };
        self.own_symbolic = Some(Arc::clone(&sym));
        let mut f = match self.own.take() {
            Some(f) if Arc::ptr_eq(&f.symbolic, &sym) => f,
            _ => sym.alloc_factor(),
        };
        let mut work = std::mem::take(&mut cache.work);
        let res = sym.factorize(body.system_matrix(), &mut f, &mut work);
        work.clear();
        work.resize(sym.n, Mat3::zeros());
        cache.work = work;
        res?;
        self.own_count = self.own_count.wrapping_add(1);
        self.own = Some(f);
        Ok(())
    }

    /// The next refresh takes the preconditioner's factor (see
    /// [`super::BodyCompliance::drop_snapshot`]).
    pub(super) fn drop_snapshot(&mut self) {
        self.snap.expired = true;
    }

    /// Updates the snapshot from the body's preconditioner factor when it is
    /// older than `reuse` steps (or absent), and recomputes its rotation warp.
    fn refresh_snapshot(&mut self, body: &DeformableBody) -> Result<()> {
        let snap = &mut self.snap;
        let st = body
            .preconditioner()
            .factor_state()
            .ok_or(SoftTissueError::NonFinite("factor"))?;
        let stale = match &snap.factor {
            None => true,
            Some(f) => {
                !Arc::ptr_eq(&f.symbolic, &st.factor.symbolic)
                    || (snap.version != st.version
                        && (snap.expired || body.step_index() >= snap.step + self.reuse))
            }
        };
        snap.expired = false;
        if stale {
            match &mut snap.factor {
                Some(f) if Arc::ptr_eq(&f.symbolic, &st.factor.symbolic) => {
                    f.copy_values_from(&st.factor);
                }
                _ => snap.factor = Some(st.factor.clone()),
            }
            snap.rotations.clear();
            snap.rotations.extend_from_slice(&st.rotations);
            snap.version = st.version;
            snap.step = body.step_index();
        }
        let now = body.node_rotations();
        snap.warp.resize(now.len(), Mat3::identity());
        for i in 0..now.len() {
            snap.warp[i] = now[i] * snap.rotations[i].transpose();
        }
        Ok(())
    }
}

/// How many node pairs ahead `accumulate` prefetches a Gram block.
const PREFETCH_AHEAD: usize = 8;

/// `W += h² J G Jᵀ` from the cached node columns and Gram blocks of the
/// view's factor (solving the columns not cached yet). `scratch.groups` holds
/// the node runs of `entries`.
#[allow(clippy::too_many_arguments)]
pub(super) fn accumulate(
    view: &FactorView<'_>,
    cache: &mut ColumnCache,
    prefetch: &mut ColumnPrefetch,
    sc: &mut Scratch,
    h2: f64,
    entries: &[JacEntry],
    w: &mut [f64],
    m: usize,
) {
    if cache.key != Some(view.key) {
        // A new factor: its columns may be ready from the background worker.
        match prefetch.take(view.key) {
            Some(pre) => {
                let old = std::mem::replace(cache, pre);
                prefetch.keep_spare(old);
                cache.solves = 0;
                cache.gram_blocks = 0;
            }
            None => cache.reset(view.factor.symbolic.n, view.key),
        }
    }
    sc.cols.clear();
    for &(s, _) in &sc.groups {
        let c = cache.column(view.factor, entries[s].node as usize);
        sc.cols.push(c);
    }
    if let FactorKey::Preconditioner(_) = view.key {
        // The next background factor precomputes these nodes' columns.
        prefetch.set_hint(sc.groups.iter().map(|&(s, _)| entries[s].node));
    }
    // Both orders of each pair, so that every write runs along a row
    // of `w` (the block of (gj, gi) is the cached one transposed).
    for gi in 0..sc.groups.len() {
        let (si, ei) = sc.groups[gi];
        for gj in 0..sc.groups.len() {
            if let Some(&ahead) = sc.cols.get(gj + PREFETCH_AHEAD) {
                cache.prefetch_gram(sc.cols[gi], ahead);
            }
            let g = cache.gram(sc.cols[gi], sc.cols[gj]);
            let (sj, ej) = sc.groups[gj];
            for a in si..ei {
                let ga = g.transpose() * entries[a].j * h2;
                let wr = &mut w[entries[a].row as usize * m..][..m];
                for b in sj..ej {
                    wr[entries[b].row as usize] += ga.dot(&entries[b].j);
                }
            }
        }
    }
}

/// `dx = h² Q Pᵀ L⁻ᵀ D⁻¹ (Y λ)`: from the cached columns when `cache` holds
/// every node of this view's factor, else with one full forward solve.
pub(super) fn correction(
    view: &FactorView<'_>,
    cache: Option<&ColumnCache>,
    h2: f64,
    entries: &[JacEntry],
    lambda: &[f64],
    sc: &mut Scratch,
    dx: &mut [Vec3],
) {
    let f = view.factor;
    let sym = &*f.symbolic;
    let n = sym.n;
    sc.a.clear();
    sc.a.resize(n, Vec3::zeros());
    let y = &mut sc.a;
    let cached = cache.filter(|cache| {
        cache.key == Some(view.key)
            && entries.iter().all(|e| {
                cache
                    .col_of_node
                    .get(e.node as usize)
                    .is_some_and(|&c| c != u32::MAX)
            })
    });
    if let Some(cache) = cached {
        // Y λ from the cached node columns (their paths only).
        let mut s = 0;
        while s < entries.len() {
            let k = entries[s].node as usize;
            let mut c = Vec3::zeros();
            let mut e = s;
            while e < entries.len() && entries[e].node as usize == k {
                c += entries[e].j * lambda[entries[e].row as usize];
                e += 1;
            }
            let cl = cache.cols[cache.col_of_node[k] as usize];
            for t in 0..cl.len {
                y[cache.paths[cl.start + t]] += cache.blocks[cl.start + t] * c;
            }
            s = e;
        }
    } else {
        // No cached columns (W built elsewhere, e.g. on the GPU, or by
        // DenseRows/Exact): one full forward solve of P Jᵀ λ.
        for e in entries {
            y[sym.iperm[e.node as usize]] += e.j * lambda[e.row as usize];
        }
        f.forward(y);
    }
    for k in 0..n {
        y[k] = y[k].component_div(&f.d[k]);
    }
    // The backward sweep reads every block of `L`: with the preconditioner's
    // single-precision copy where it has one (half the memory; `W` and the
    // forward part stay in double precision).
    f.backward_single(y);
    for k in 0..n {
        let old = sym.perm[k];
        let v = y[k] * h2;
        dx[old] = match view.warp {
            Some(q) => q[old] * v,
            None => v,
        };
    }
}
