//! Contact compliance `W = h² H A⁻¹ Hᵀ` per body, and the matching correction.
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
//! preconditioner itself.
//!
//! ## Other modes
//! - `Exact`: the same with a fresh factorization of the current `A` (Q = I).
//! - `DenseRows`: the paper's CPU method — two full triangular solves per
//!   row of `J`. Same `W` as `Factorized`; kept as the benchmark baseline.
//! - `Diagonal`: uncoupled, `W` from the 3×3 diagonal blocks of `A` only.
//! - `RestPrecomputed`: the dense inverse of the first `A` (at rest),
//!   rotated by the node rotations (the paper's reference \[11\]). Refused above
//!   [`REST_PRECOMPUTED_MAX_NODES`] nodes.

use std::sync::Arc;

use nalgebra::DMatrix;

use crate::body::DeformableBody;
use crate::error::{Result, SoftTissueError};
use crate::math::{Mat3, Vec3};
use crate::solver::columns::ColumnCache;
use crate::solver::ldlt::{LdltFactor, LdltSymbolic};

/// Largest body (in nodes) accepted by [`ComplianceMode::RestPrecomputed`].
pub const REST_PRECOMPUTED_MAX_NODES: usize = 2000;

/// How the contact compliance of a body is computed (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ComplianceMode {
    /// From the body's preconditioner factor, warped (reach-restricted forward solves).
    #[default]
    Factorized,
    /// From a fresh factorization of the current matrix.
    Exact,
    /// Uncoupled: diagonal blocks of the current matrix only.
    Diagonal,
    /// Dense inverse of the matrix at rest, rotated (small meshes only).
    RestPrecomputed,
    /// The paper's CPU method: two full solves per Jacobian row (benchmark baseline).
    DenseRows,
}

/// Builds a body's compliance somewhere else than on the CPU (the GPU path of
/// the `gpu` feature). Called for bodies in [`ComplianceMode::Factorized`] that
/// have a preconditioner factor, with `entries` sorted by node and their `j`
/// (`Qᵀ h`, the factor's frame) filled.
pub trait ComplianceBackend {
    /// Adds `h² J (L D Lᵀ)⁻¹ Jᵀ` of this body to `w` (`m × m`, row-major) and
    /// returns `Ok(true)`, or returns `Ok(false)` to let the CPU do it.
    #[allow(clippy::too_many_arguments)]
    fn accumulate(
        &mut self,
        body_id: u64,
        factor: &LdltFactor,
        factor_version: u64,
        h: f64,
        entries: &[JacEntry],
        w: &mut [f64],
        m: usize,
    ) -> Result<bool>;
}

/// One nonzero 3-vector of the contact Jacobian.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JacEntry {
    /// Node of the body.
    pub node: u32,
    /// Constraint row.
    pub row: u32,
    /// `H` block (world frame): the row's direction times the node's weight and sign.
    pub h: Vec3,
    /// `Qᵀ h`, in the frame of the factor.
    pub j: Vec3,
}

/// Reusable vectors.
#[derive(Debug, Default)]
struct Scratch {
    a: Vec<Vec3>,
    b: Vec<Vec3>,
    c: Vec<Vec3>,
    groups: Vec<(usize, usize)>,
    by_row: Vec<u32>,
    cols: Vec<u32>,
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
    warped: bool,
}

/// Per-body compliance state, kept between steps.
#[derive(Debug, Default)]
pub struct BodyCompliance {
    /// Steps a factor snapshot may serve after a newer factor exists (0: always the newest).
    pub reuse_steps: u64,
    snap: Snapshot,
    cache: ColumnCache,
    own: Option<LdltFactor>,
    own_symbolic: Option<Arc<LdltSymbolic>>,
    own_version: u64,
    rest_inverse: Option<DMatrix<f64>>,
    scratch: Scratch,
}

fn group(entries: &[JacEntry], groups: &mut Vec<(usize, usize)>) {
    groups.clear();
    let mut s = 0;
    for i in 1..=entries.len() {
        if i == entries.len() || entries[i].node != entries[s].node {
            groups.push((s, i));
            s = i;
        }
    }
}

/// Updates `snap` from the body's preconditioner factor when it is older than
/// `reuse` steps (or absent), and recomputes its rotation warp.
fn refresh_snapshot(snap: &mut Snapshot, body: &DeformableBody, reuse: u64) -> Result<()> {
    let st = body
        .preconditioner()
        .factor_state()
        .ok_or(SoftTissueError::NonFinite("factor"))?;
    let stale = match &snap.factor {
        None => true,
        Some(f) => {
            !Arc::ptr_eq(&f.symbolic, &st.factor.symbolic)
                || (snap.version != st.version && body.step_index() >= snap.step + reuse)
        }
    };
    if stale {
        match &mut snap.factor {
            Some(f) if Arc::ptr_eq(&f.symbolic, &st.factor.symbolic) => {
                f.l.copy_from_slice(&st.factor.l);
                f.ldiag.copy_from_slice(&st.factor.ldiag);
                f.d.copy_from_slice(&st.factor.d);
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
    snap.warped = true;
    Ok(())
}

impl BodyCompliance {
    /// Whether `Factorized` W for `body` comes from the snapshot (reuse on and the
    /// preconditioner keeps node rotations for the warp).
    fn uses_snapshot(&self, body: &DeformableBody) -> bool {
        self.reuse_steps > 0
            && body.settings().preconditioner.needs_rotations()
            && body.preconditioner().factor_state().is_some()
    }

    /// Fresh state.
    pub fn new() -> Self {
        Self {
            cache: ColumnCache {
                version: u64::MAX,
                ..Default::default()
            },
            ..Default::default()
        }
    }

    /// Forgets the cached node columns and Gram blocks (keeping their memory), as a
    /// new factor does: the next build solves every column again.
    pub fn forget_columns(&mut self) {
        self.cache.version = u64::MAX;
    }

    /// Forward solves (node columns, or full solves for `DenseRows`) in the last build.
    pub fn solves(&self) -> usize {
        self.cache.solves
    }

    /// Gram blocks computed (not found in the cache) in the last build.
    pub fn gram_blocks(&self) -> usize {
        self.cache.gram_blocks
    }

    fn refactor_own(&mut self, body: &DeformableBody) -> Result<()> {
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
        let mut work = std::mem::take(&mut self.cache.work);
        let res = sym.factorize(body.system_matrix(), &mut f, &mut work);
        work.clear();
        work.resize(sym.n, Mat3::zeros());
        self.cache.work = work;
        res?;
        self.own_version = self.own_version.wrapping_add(1);
        self.own = Some(f);
        Ok(())
    }

    /// Adds this body's contribution to `w` (`m × m`, row-major).
    /// `entries` must be sorted by node; their `j` is filled here. A `backend`
    /// may take over `Factorized` bodies.
    #[allow(clippy::too_many_arguments)]
    pub fn accumulate(
        &mut self,
        body: &DeformableBody,
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
        let snapshot = mode == ComplianceMode::Factorized && self.uses_snapshot(body);
        if snapshot {
            refresh_snapshot(&mut self.snap, body, self.reuse_steps)?;
        }
        if let (ComplianceMode::Factorized, Some(backend), Some(st)) =
            (mode, backend, body.preconditioner().factor_state())
        {
            let (factor, version, warp) = match (&self.snap.factor, snapshot) {
                (Some(f), true) => (f, self.snap.version, Some(&self.snap.warp[..])),
                _ => (&st.factor, st.version, st.warped.then_some(&st.warp[..])),
            };
            for e in entries.iter_mut() {
                e.j = match warp {
                    Some(q) => q[e.node as usize].transpose() * e.h,
                    None => e.h,
                };
            }
            if backend.accumulate(body.id(), factor, version, h, entries, w, m)? {
                return Ok(());
            }
        }
        group(entries, &mut self.scratch.groups);
        let h2 = h * h;
        match mode {
            ComplianceMode::Diagonal => {
                for &(s, e) in &self.scratch.groups {
                    let k = entries[s].node as usize;
                    let inv = body.system_matrix().diag(k).try_inverse().ok_or(
                        SoftTissueError::NotPositiveDefinite {
                            node: k,
                            pivot: 0.0,
                        },
                    )?;
                    for a in s..e {
                        for b in s..e {
                            w[entries[a].row as usize * m + entries[b].row as usize] +=
                                h2 * entries[a].h.dot(&(inv * entries[b].h));
                        }
                    }
                }
            }
            ComplianceMode::RestPrecomputed => {
                let n = body.num_nodes();
                if n > REST_PRECOMPUTED_MAX_NODES {
                    return Err(SoftTissueError::TooLarge {
                        what: "RestPrecomputed compliance (dense 3n×3n inverse)",
                        size: n,
                        limit: REST_PRECOMPUTED_MAX_NODES,
                    });
                }
                if self.rest_inverse.is_none() {
                    self.rest_inverse = Some(self.dense_inverse(body)?);
                }
                let rot = body.node_rotations();
                for e in entries.iter_mut() {
                    e.j = rot[e.node as usize].transpose() * e.h;
                }
                let inv = self
                    .rest_inverse
                    .as_ref()
                    .ok_or(SoftTissueError::NonFinite("rest inverse"))?;
                for a in entries.iter() {
                    for b in entries.iter() {
                        let blk = inv.fixed_view::<3, 3>(3 * a.node as usize, 3 * b.node as usize);
                        w[a.row as usize * m + b.row as usize] += h2 * a.j.dot(&(blk * b.j));
                    }
                }
            }
            ComplianceMode::Factorized | ComplianceMode::Exact | ComplianceMode::DenseRows => {
                let use_own =
                    mode == ComplianceMode::Exact || body.preconditioner().factor_state().is_none();
                if use_own {
                    self.refactor_own(body)?;
                }
                let (factor, version, warp): (&LdltFactor, u64, Option<&[Mat3]>) = if use_own {
                    let f = self
                        .own
                        .as_ref()
                        .ok_or(SoftTissueError::NonFinite("factor"))?;
                    (f, self.own_version | (1 << 63), None)
                } else if snapshot {
                    let f = self
                        .snap
                        .factor
                        .as_ref()
                        .ok_or(SoftTissueError::NonFinite("factor"))?;
                    (f, self.snap.version | (1 << 62), Some(&self.snap.warp[..]))
                } else {
                    let st = body
                        .preconditioner()
                        .factor_state()
                        .ok_or(SoftTissueError::NonFinite("factor"))?;
                    (&st.factor, st.version, st.warped.then_some(&st.warp[..]))
                };
                for e in entries.iter_mut() {
                    e.j = match warp {
                        Some(q) => q[e.node as usize].transpose() * e.h,
                        None => e.h,
                    };
                }
                if mode == ComplianceMode::DenseRows {
                    dense_rows(
                        &mut self.scratch,
                        &mut self.cache,
                        factor,
                        h2,
                        entries,
                        w,
                        m,
                    );
                    return Ok(());
                }
                let cache = &mut self.cache;
                if cache.version != version {
                    // A new factor: its columns may be ready from the background worker.
                    match body.preconditioner().take_columns(version) {
                        Some(pre) => {
                            let old = std::mem::replace(cache, pre);
                            body.preconditioner().give_back_columns(old);
                            cache.solves = 0;
                            cache.gram_blocks = 0;
                        }
                        None => cache.reset(body.num_nodes(), version),
                    }
                }
                let sc = &mut self.scratch;
                sc.cols.clear();
                for &(s, _) in &sc.groups {
                    let c = cache.column(factor, entries[s].node as usize);
                    sc.cols.push(c);
                }
                if !use_own && !snapshot {
                    // The next background factor precomputes these nodes' columns.
                    body.preconditioner()
                        .set_column_hint(sc.groups.iter().map(|&(s, _)| entries[s].node));
                }
                // Both orders of each pair, so that every write runs along a row
                // of `w` (the block of (gj, gi) is the cached one transposed).
                for gi in 0..sc.groups.len() {
                    let (si, ei) = sc.groups[gi];
                    for gj in 0..sc.groups.len() {
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
        }
        Ok(())
    }

    fn dense_inverse(&mut self, body: &DeformableBody) -> Result<DMatrix<f64>> {
        let n = body.num_nodes();
        self.refactor_own(body)?;
        let f = self
            .own
            .as_ref()
            .ok_or(SoftTissueError::NonFinite("factor"))?;
        let mut inv = DMatrix::zeros(3 * n, 3 * n);
        let mut b = vec![Vec3::zeros(); n];
        let mut x = vec![Vec3::zeros(); n];
        let mut t = vec![Vec3::zeros(); n];
        for k in 0..n {
            for c in 0..3 {
                b[k][c] = 1.0;
                f.solve(&b, &mut x, &mut t);
                b[k][c] = 0.0;
                for (i, xi) in x.iter().enumerate() {
                    for r in 0..3 {
                        inv[(3 * i + r, 3 * k + c)] = xi[r];
                    }
                }
            }
        }
        Ok(inv)
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
        let snapshot = mode == ComplianceMode::Factorized && self.uses_snapshot(body);
        let sc = &mut self.scratch;
        match mode {
            ComplianceMode::Diagonal => {
                for e in entries {
                    let k = e.node as usize;
                    let inv = body
                        .system_matrix()
                        .diag(k)
                        .try_inverse()
                        .unwrap_or_else(Mat3::zeros);
                    dx[k] += inv * e.h * (h2 * lambda[e.row as usize]);
                }
            }
            ComplianceMode::RestPrecomputed => {
                let inv = self
                    .rest_inverse
                    .as_ref()
                    .ok_or(SoftTissueError::NonFinite("rest inverse"))?;
                sc.a.clear();
                sc.a.resize(n, Vec3::zeros());
                for e in entries {
                    sc.a[e.node as usize] += e.j * lambda[e.row as usize];
                }
                let rot = body.node_rotations();
                group(entries, &mut sc.groups);
                for i in 0..n {
                    let mut acc = Vec3::zeros();
                    for &(s, _) in &sc.groups {
                        let k = entries[s].node as usize;
                        acc += inv.fixed_view::<3, 3>(3 * i, 3 * k) * sc.a[k];
                    }
                    dx[i] = rot[i] * acc * h2;
                }
            }
            _ => {
                let use_own =
                    mode == ComplianceMode::Exact || body.preconditioner().factor_state().is_none();
                let (f, warp): (&LdltFactor, Option<&[Mat3]>) = if use_own {
                    (
                        self.own
                            .as_ref()
                            .ok_or(SoftTissueError::NonFinite("factor"))?,
                        None,
                    )
                } else if snapshot {
                    (
                        self.snap
                            .factor
                            .as_ref()
                            .ok_or(SoftTissueError::NonFinite("factor"))?,
                        Some(&self.snap.warp[..]),
                    )
                } else {
                    let st = body
                        .preconditioner()
                        .factor_state()
                        .ok_or(SoftTissueError::NonFinite("factor"))?;
                    (&st.factor, st.warped.then_some(&st.warp[..]))
                };
                let sym = &*f.symbolic;
                sc.a.clear();
                sc.a.resize(n, Vec3::zeros());
                let y = &mut sc.a;
                let cache = &self.cache;
                let version = if use_own {
                    self.own_version | (1 << 63)
                } else if snapshot {
                    self.snap.version | (1 << 62)
                } else {
                    body.preconditioner()
                        .factor_state()
                        .map(|st| st.version)
                        .unwrap_or(u64::MAX)
                };
                let cached = mode == ComplianceMode::Factorized
                    && cache.version == version
                    && entries.iter().all(|e| {
                        cache
                            .col_of_node
                            .get(e.node as usize)
                            .is_some_and(|&c| c != u32::MAX)
                    });
                if cached {
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
                f.backward(y);
                for k in 0..n {
                    let old = sym.perm[k];
                    let v = y[k] * h2;
                    dx[old] = match warp {
                        Some(q) => q[old] * v,
                        None => v,
                    };
                }
            }
        }
        Ok(())
    }
}

/// The paper's CPU method: for every row of `J`, two full triangular solves.
fn dense_rows(
    sc: &mut Scratch,
    cache: &mut ColumnCache,
    f: &LdltFactor,
    h2: f64,
    entries: &[JacEntry],
    w: &mut [f64],
    m: usize,
) {
    let n = f.symbolic.n;
    sc.a.resize(n, Vec3::zeros());
    sc.b.resize(n, Vec3::zeros());
    sc.c.resize(n, Vec3::zeros());
    sc.by_row.clear();
    sc.by_row.extend(0..entries.len() as u32);
    sc.by_row.sort_unstable_by_key(|&i| entries[i as usize].row);
    let mut s = 0;
    while s < sc.by_row.len() {
        let row = entries[sc.by_row[s] as usize].row;
        let mut e = s;
        sc.a.fill(Vec3::zeros());
        while e < sc.by_row.len() && entries[sc.by_row[e] as usize].row == row {
            let en = &entries[sc.by_row[e] as usize];
            sc.a[en.node as usize] += en.j;
            e += 1;
        }
        f.solve(&sc.a, &mut sc.b, &mut sc.c);
        for en in entries {
            w[en.row as usize * m + row as usize] += h2 * en.j.dot(&sc.b[en.node as usize]);
        }
        cache.solves += 2;
        s = e;
    }
}
