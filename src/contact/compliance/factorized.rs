//! `Factorized` and `Exact` compliance: `W = h² Yᵀ D⁻¹ Y` from node columns,
//! and the correction with the same factor (see the module docs of
//! [`super`]). `DenseRows` reads its factor through the same
//! [`FactorSource::view`].

use std::sync::Arc;

use super::deflation::{Deflation, Rank12};
use super::entries::{ComplianceMode, FactorView, JacEntry, Scratch, WBlock};
use crate::body::DeformableBody;
use crate::error::{Result, SoftTissueError};
use crate::math::{Mat3, Vec3};
use crate::solver::columns::{ColumnCache, ColumnPrefetch, FactorKey};
use crate::solver::fill_warp;
use crate::solver::ldlt::{LdltFactor, LdltSymbolic};

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
        // The kind of warp the preconditioner chose for its own factor.
        let now = body.node_rotations();
        snap.warp.resize(now.len(), Mat3::identity());
        fill_warp(st.warp_kind, now, &snap.rotations, &mut snap.warp);
        Ok(())
    }
}

/// `W += h² J G Jᵀ` from the cached node columns and Gram blocks of the
/// view's factor (solving the columns not cached yet). `scratch.groups` holds
/// the node runs of `entries`. `fresh`: this body's block of `w` is zero
/// (see [`contract`]).
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
    block: WBlock,
    deflation: Option<&mut Deflation>,
) {
    let mut cold = false;
    if cache.key != Some(view.key) {
        // A new factor: its columns may be ready from the background worker.
        match prefetch.take(view.key) {
            Some(pre) => {
                let old = std::mem::replace(cache, pre);
                prefetch.keep_spare(old);
                cache.solves = 0;
                cache.gram_blocks = 0;
            }
            None => {
                cache.reset(view.factor.symbolic.n, view.key);
                cold = true;
            }
        }
    }
    // The columns not cached yet, solved together (the same ids and columns
    // as one at a time below).
    cache.columns(
        view.factor,
        sc.groups.iter().map(|&(s, _)| entries[s].node as usize),
    );
    if cold {
        // Every column is this build's and `contract` takes every pair of
        // them: formed in tiles first, as the worker does (the same blocks).
        cache.all_pairs();
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
    match deflation {
        // The rigid-mode completion's rank-12 term, from the same columns:
        // added by the mirror where `W` is built in place, else after.
        Some(d) => {
            let rank = d.prepare_rows(view, Some(cache), entries, h2, m);
            let fused = contract(cache, sc, h2, entries, w, m, block, rank.as_ref());
            if fused {
                #[cfg(test)]
                {
                    d.fused_builds += 1;
                }
            } else {
                d.add_prepared(w, m);
            }
        }
        None => {
            contract(cache, sc, h2, entries, w, m, block, None);
        }
    }
}

/// `W += h² J G Jᵀ` of the groups in `sc.groups`, whose columns are
/// `sc.cols` (all in `cache`). With a fresh block ([`WBlock::Zero`]: this
/// body's block of `w` is zero, no other body has written any of its rows;
/// or [`WBlock::Unset`]), the pairs of groups go into that block itself
/// and are mirrored there in place, when the body's rows are contiguous;
/// else through `sc.tri`. [`WBlock::Unset`]: where the body's rows are
/// all of `w`'s and contiguous, each row is set by its first write, and
/// the rows no write reaches set to zero, instead of `w` being zeroed
/// first (the same sums: `0 + x` is `x`); else `w` is zeroed first.
///
/// `rank`: the rigid-mode completion's term over the same rows, added by
/// the mirror in place (entries `(i, j)` and `(j, i)` both get the term's
/// entry `(min, max)`). Returns whether it was added; if not, the caller
/// adds it.
#[allow(clippy::too_many_arguments)]
fn contract(
    cache: &mut ColumnCache,
    sc: &mut Scratch,
    h2: f64,
    entries: &[JacEntry],
    w: &mut [f64],
    m: usize,
    block: WBlock,
    rank: Option<&Rank12<'_>>,
) -> bool {
    // Each pair of groups once, read where the cache keeps it: with the
    // groups in the order of their column ids, group `gj` takes the Gram
    // blocks `G_{gi,gj}` of the groups `gi` before it (one run of the
    // cache's row of `gj`) and sums `t_c[r] = Σ_{a in row r} (G_{gi,gj}ᵀ j_a
    // h²)_c` over the rows this body touches (local numbers); each entry `b`
    // of `gj` adds `Σ_c t_c j_{b,c}` to its row of `tri`, a long loop in
    // vector lanes. `tri` holds each such `W_{ab}` once, so it goes into `w`
    // with its transpose. A group with itself goes into `w` directly.
    //
    // In place (`fresh`, contiguous rows from `r0`): the row of entry `b`
    // is `w`'s row `b.row` over the columns `r0..r0 + k`, the block is
    // mirrored there (`W_B ← W_B + W_Bᵀ`, each entry the same sum as
    // through `tri`), and the groups with themselves are added after the
    // mirror, not before. `tri` is neither cleared, written nor read twice:
    // three streams over `k²` entries a pass instead of six.
    let g = sc.groups.len();
    sc.rows.clear();
    sc.rows.extend(entries.iter().map(|e| e.row));
    sc.rows.sort_unstable();
    sc.rows.dedup();
    let k = sc.rows.len();
    let r0 = sc.rows.first().map_or(0, |&r| r as usize);
    let in_place = block != WBlock::Written && k > 0 && sc.rows[k - 1] as usize - r0 == k - 1;
    // Every entry of `w` is this block's, each row written whole below.
    let whole = block == WBlock::Unset && in_place && k == m;
    if block == WBlock::Unset && !whole {
        w.fill(0.0);
    }
    sc.row_set.clear();
    if whole {
        sc.row_set.resize(k, false);
    }
    sc.slot.clear();
    sc.slot.resize(m, u32::MAX);
    for (i, &r) in sc.rows.iter().enumerate() {
        sc.slot[r as usize] = i as u32;
    }
    sc.local_of.clear();
    sc.local_of
        .extend(entries.iter().map(|e| sc.slot[e.row as usize]));
    sc.order.clear();
    sc.order.extend(0..g as u32);
    let cols = &sc.cols;
    sc.order.sort_unstable_by_key(|&gi| cols[gi as usize]);
    if !in_place {
        sc.tri.clear();
        sc.tri.resize(k * k, 0.0);
    }
    sc.t.clear();
    sc.t.resize(3 * k, 0.0);
    for jj in 0..g {
        let gj = sc.order[jj] as usize;
        let cj = sc.cols[gj];
        let (t0, rest) = sc.t.split_at_mut(k);
        let (t1, t2) = rest.split_at_mut(k);
        for &gi in &sc.order[..jj] {
            let gi = gi as usize;
            let gt = cache.gram(sc.cols[gi], cj).transpose() * h2;
            let (si, ei) = sc.groups[gi];
            for (e, &l) in entries[si..ei].iter().zip(&sc.local_of[si..ei]) {
                let v = gt * e.j;
                let l = l as usize;
                t0[l] += v.x;
                t1[l] += v.y;
                t2[l] += v.z;
            }
        }
        let (sj, ej) = sc.groups[gj];
        if jj > 0 {
            for (e, &l) in entries[sj..ej].iter().zip(&sc.local_of[sj..ej]) {
                let out = if in_place {
                    &mut w[e.row as usize * m + r0..][..k]
                } else {
                    &mut sc.tri[l as usize * k..][..k]
                };
                if whole && !sc.row_set[l as usize] {
                    sc.row_set[l as usize] = true;
                    row_update::<true>(out, [&*t0, &*t1, &*t2], e.j);
                } else {
                    row_update::<false>(out, [&*t0, &*t1, &*t2], e.j);
                }
            }
            // Back to zero for the next group: only the rows touched.
            for &gi in &sc.order[..jj] {
                let (si, ei) = sc.groups[gi as usize];
                for &l in &sc.local_of[si..ei] {
                    let l = l as usize;
                    t0[l] = 0.0;
                    t1[l] = 0.0;
                    t2[l] = 0.0;
                }
            }
        }
        if !in_place {
            self_block(cache, cj, h2, &entries[sj..ej], w, m);
        }
    }
    if whole {
        // The rows of the first group only (and any no write reached).
        for (l, _) in sc.row_set.iter().enumerate().filter(|(_, set)| !**set) {
            w[(r0 + l) * m + r0..][..k].fill(0.0);
        }
    }
    if in_place {
        let rank = rank.filter(|r| r.rows == &sc.rows[..]);
        mirror_in_place(w, m, r0, k, rank);
        for &gj in &sc.order {
            let (sj, ej) = sc.groups[gj as usize];
            self_block(cache, sc.cols[gj as usize], h2, &entries[sj..ej], w, m);
        }
        rank.is_some()
    } else {
        mirror_into(&sc.tri, &sc.rows, w, m);
        false
    }
}

/// `W_ab += h² j_aᵀ G_jj j_b` for every pair of the entries of one group
/// (one node, column `cj`).
#[inline]
fn self_block(
    cache: &mut ColumnCache,
    cj: u32,
    h2: f64,
    group: &[JacEntry],
    w: &mut [f64],
    m: usize,
) {
    let gt = cache.gram(cj, cj).transpose() * h2;
    for a in group {
        let v = gt * a.j;
        let wr = &mut w[a.row as usize * m..][..m];
        for b in group {
            wr[b.row as usize] += v.dot(&b.j);
        }
    }
}

/// `out[l] += t[0][l] j.x + t[1][l] j.y + t[2][l] j.z` (slices of one
/// length), or with `SET` `out[l] =` the same sum, in AVX2 lanes where the
/// CPU has them.
fn row_update<const SET: bool>(out: &mut [f64], t: [&[f64]; 3], j: Vec3) {
    #[cfg(target_arch = "x86_64")]
    if crate::math::has_avx2_fma() {
        // SAFETY: the CPU supports the features the function is compiled for.
        return unsafe { row_update_avx2::<SET>(out, t, j) };
    }
    row_update_portable::<SET>(out, t, j);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn row_update_avx2<const SET: bool>(out: &mut [f64], t: [&[f64]; 3], j: Vec3) {
    row_update_portable::<SET>(out, t, j);
}

#[inline(always)]
fn row_update_portable<const SET: bool>(out: &mut [f64], t: [&[f64]; 3], j: Vec3) {
    let n = out.len();
    let (a, b, c) = (&t[0][..n], &t[1][..n], &t[2][..n]);
    for l in 0..n {
        let v = a[l] * j.x + b[l] * j.y + c[l] * j.z;
        if SET {
            out[l] = v;
        } else {
            out[l] += v;
        }
    }
}

/// `w[rows[i], rows[j]] += t[i, j] + t[j, i]` for the `k × k` row-major
/// `t` (`k = rows.len()`, ascending), in tiles so that the transposed reads
/// stay in cache. In AVX2 lanes where the CPU has them.
fn mirror_into(t: &[f64], rows: &[u32], w: &mut [f64], m: usize) {
    #[cfg(target_arch = "x86_64")]
    if crate::math::has_avx2_fma() {
        // SAFETY: the CPU supports the features the function is compiled for.
        return unsafe { mirror_into_avx2(t, rows, w, m) };
    }
    mirror_into_portable(t, rows, w, m);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn mirror_into_avx2(t: &[f64], rows: &[u32], w: &mut [f64], m: usize) {
    mirror_into_portable(t, rows, w, m);
}

/// The kernel of [`mirror_into`]. Full tiles go through fixed-size
/// arrays, so their copies and sums compile to vector moves and adds
/// rather than calls and loops of unknown length; each entry is the same
/// `t[i, j] + t[j, i]` either way.
#[inline(always)]
fn mirror_into_portable(t: &[f64], rows: &[u32], w: &mut [f64], m: usize) {
    const TILE: usize = 8;
    let k = rows.len();
    if k == 0 {
        return;
    }
    let r0 = rows[0] as usize;
    let contiguous = rows[k - 1] as usize - r0 == k - 1;
    let mut tile = [[0.0; TILE]; TILE];
    for i0 in (0..k).step_by(TILE) {
        let ni = TILE.min(k - i0);
        for j0 in (0..k).step_by(TILE) {
            let nj = TILE.min(k - j0);
            // tile[i][j] = t[i0 + i, j0 + j] + t[j0 + j, i0 + i]
            if ni == TILE && nj == TILE {
                for (i, tr) in tile.iter_mut().enumerate() {
                    *tr = t[(i0 + i) * k + j0..][..TILE].try_into().unwrap();
                }
                for j in 0..TILE {
                    let src: &[f64; TILE] = t[(j0 + j) * k + i0..][..TILE].try_into().unwrap();
                    for (tr, &v) in tile.iter_mut().zip(src) {
                        tr[j] += v;
                    }
                }
            } else {
                for (i, tr) in tile.iter_mut().enumerate().take(ni) {
                    for (o, &v) in tr[..nj].iter_mut().zip(&t[(i0 + i) * k + j0..][..nj]) {
                        *o = v;
                    }
                }
                for j in 0..nj {
                    let src = &t[(j0 + j) * k + i0..][..ni];
                    for (i, &v) in src.iter().enumerate() {
                        tile[i][j] += v;
                    }
                }
            }
            for (i, tr) in tile.iter().enumerate().take(ni) {
                let wr = &mut w[rows[i0 + i] as usize * m..][..m];
                if contiguous {
                    for (o, &v) in wr[r0 + j0..r0 + j0 + nj].iter_mut().zip(&tr[..nj]) {
                        *o += v;
                    }
                } else {
                    for (&r, &v) in rows[j0..j0 + nj].iter().zip(&tr[..nj]) {
                        wr[r as usize] += v;
                    }
                }
            }
        }
    }
}

/// `W_B ← W_B + W_Bᵀ` for the `k × k` block `B` of `w` at rows and columns
/// `r0..r0 + k`, in tiles, each pair of tiles read and written once. Entry
/// `(i, j)` becomes `w[i, j] + w[j, i]`, the sum [`mirror_into`] forms from
/// `tri`; with `rank` (over the same rows), `w[i, j] + w[j, i] + R(i, j)`
/// on both sides, `R(i, j)` the term's entry `(i, j)` for `i ≤ j`, as
/// [`Deflation::add_prepared`] sums it (the term is symmetric; its two
/// sums differ by rounding only, and here both sides get the same one). In
/// AVX2 lanes where the CPU has them.
fn mirror_in_place(w: &mut [f64], m: usize, r0: usize, k: usize, rank: Option<&Rank12<'_>>) {
    #[cfg(target_arch = "x86_64")]
    if crate::math::has_avx2_fma() {
        // SAFETY: the CPU supports the features the function is compiled for.
        return unsafe {
            match rank {
                Some(r) => mirror_in_place_avx2::<true>(w, m, r0, k, r.soa, r.coef),
                None => mirror_in_place_avx2::<false>(w, m, r0, k, &[], &[]),
            }
        };
    }
    match rank {
        Some(r) => mirror_in_place_portable::<true>(w, m, r0, k, r.soa, r.coef),
        None => mirror_in_place_portable::<false>(w, m, r0, k, &[], &[]),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn mirror_in_place_avx2<const RANK: bool>(
    w: &mut [f64],
    m: usize,
    r0: usize,
    k: usize,
    soa: &[f64],
    coef: &[f64],
) {
    mirror_in_place_portable::<RANK>(w, m, r0, k, soa, coef);
}

/// The kernel of [`mirror_in_place`]: full tiles through fixed-size arrays
/// (as in [`mirror_into_portable`]), partial tiles entry by entry. With
/// `RANK`, the term's entries of a tile's rows over its columns, summed as
/// `rank12_row` sums them.
#[inline(always)]
fn mirror_in_place_portable<const RANK: bool>(
    w: &mut [f64],
    m: usize,
    r0: usize,
    k: usize,
    soa: &[f64],
    coef: &[f64],
) {
    const TILE: usize = 8;
    let at = |i: usize, j: usize| (r0 + i) * m + r0 + j;
    // The term's entry (i, j): row i's coefficients on column j.
    let row_coef = |i: usize| -> &[f64; 12] { coef[12 * i..][..12].try_into().unwrap() };
    let term = |i: usize, j: usize| term_entry(row_coef(i), |q| soa[q * k + j]);
    for i0 in (0..k).step_by(TILE) {
        let ni = TILE.min(k - i0);
        // The diagonal tile: each pair `i ≤ j` of it once.
        for i in 0..ni {
            for j in i..ni {
                let mut s = w[at(i0 + i, i0 + j)] + w[at(i0 + j, i0 + i)];
                if RANK {
                    s += term(i0 + i, i0 + j);
                }
                w[at(i0 + i, i0 + j)] = s;
                w[at(i0 + j, i0 + i)] = s;
            }
        }
        for j0 in (i0 + TILE..k).step_by(TILE) {
            let nj = TILE.min(k - j0);
            if ni == TILE && nj == TILE {
                // a = the tile at (i0, j0), b = the one at (j0, i0).
                let mut a = [[0.0; TILE]; TILE];
                let mut b = [[0.0; TILE]; TILE];
                for i in 0..TILE {
                    a[i] = w[at(i0 + i, j0)..][..TILE].try_into().unwrap();
                    b[i] = w[at(j0 + i, i0)..][..TILE].try_into().unwrap();
                }
                for (i, ar) in a.iter_mut().enumerate() {
                    for (j, o) in ar.iter_mut().enumerate() {
                        *o += b[j][i];
                    }
                }
                if RANK {
                    // The tile's columns of `U` and `V`, then row by row.
                    let cols: [&[f64; TILE]; 12] =
                        std::array::from_fn(|q| soa[q * k + j0..][..TILE].try_into().unwrap());
                    for (i, ar) in a.iter_mut().enumerate() {
                        let c = row_coef(i0 + i);
                        for (j, o) in ar.iter_mut().enumerate() {
                            *o += term_entry(c, |q| cols[q][j]);
                        }
                    }
                }
                for i in 0..TILE {
                    w[at(i0 + i, j0)..][..TILE].copy_from_slice(&a[i]);
                    for (j, br) in b.iter_mut().enumerate() {
                        br[i] = a[i][j];
                    }
                }
                for (j, br) in b.iter().enumerate() {
                    w[at(j0 + j, i0)..][..TILE].copy_from_slice(br);
                }
            } else {
                for i in 0..ni {
                    for j in 0..nj {
                        let mut s = w[at(i0 + i, j0 + j)] + w[at(j0 + j, i0 + i)];
                        if RANK {
                            s += term(i0 + i, j0 + j);
                        }
                        w[at(i0 + i, j0 + j)] = s;
                        w[at(j0 + j, i0 + i)] = s;
                    }
                }
            }
        }
    }
}

/// One entry of the rigid-mode completion's term: `c[..6]·u − c[6..]·v`,
/// `u(q)` for `q < 6` the column's `U` and then its `V`, each dot product
/// summed in order as `rank12_row` sums it.
#[inline(always)]
fn term_entry(c: &[f64; 12], u: impl Fn(usize) -> f64) -> f64 {
    let su =
        0.0 + c[0] * u(0) + c[1] * u(1) + c[2] * u(2) + c[3] * u(3) + c[4] * u(4) + c[5] * u(5);
    let sv =
        0.0 + c[6] * u(6) + c[7] * u(7) + c[8] * u(8) + c[9] * u(9) + c[10] * u(10) + c[11] * u(11);
    su - sv
}

/// `dx = h² Q Pᵀ L⁻ᵀ D⁻¹ (Y λ)`: from the cached columns when `cache` holds
/// every node of this view's factor, else with one full forward solve.
/// With `deflation` (active, prepared for this view), the rigid-mode
/// completion's share joins the sweep (see [`super::deflation`]).
#[allow(clippy::too_many_arguments)]
pub(super) fn correction(
    view: &FactorView<'_>,
    cache: Option<&ColumnCache>,
    h2: f64,
    entries: &[JacEntry],
    lambda: &[f64],
    sc: &mut Scratch,
    dx: &mut [Vec3],
    deflation: Option<&Deflation>,
) {
    let modes = deflation.map(|d| (d, d.modes_of(entries, lambda)));
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
    let b = match &modes {
        Some((d, a)) => Some(d.divide_and_shift(&f.d, a, y)),
        None => {
            for k in 0..n {
                y[k] = y[k].component_div(&f.d[k]);
            }
            None
        }
    };
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
    if let (Some((d, a)), Some(b)) = (modes, b) {
        d.add_modes(&a, &b, h2, dx);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::test_value;
    use crate::solver::PreconditionerKind;

    /// `accumulate` visits each pair of node groups once and mirrors it; the
    /// result must be, to round-off, `h² Σ_ab j_aᵀ G_ab j_b` over every
    /// ordered pair of entries, added to what `w` held: for groups of one to
    /// five entries, with the body's rows contiguous in `w` or spread among
    /// rows of other bodies.
    #[test]
    fn each_pair_once_matches_every_ordered_pair() {
        let body = super::super::tests::lens(4, PreconditionerKind::Periodic { every: 1 });
        let st = body.preconditioner().factor_state().unwrap();
        let view = FactorView {
            factor: &st.factor,
            warp: None,
            key: FactorKey::Preconditioner(st.version),
        };
        let n = body.num_nodes();
        for spread in [1usize, 3] {
            let mut entries = Vec::new();
            let mut row = 0usize;
            for c in 0..40usize {
                // Contact `c` on one to five nodes, three rows each.
                let nodes: Vec<u32> = (0..1 + c % 5)
                    .map(|i| ((c * 7 + i * 13) % n) as u32)
                    .collect();
                for _ in 0..3 {
                    for (i, &node) in nodes.iter().enumerate() {
                        let v = |s| test_value(c * 31 + i * 5 + row, s);
                        entries.push(JacEntry {
                            node,
                            row: (spread * row) as u32,
                            h: Vec3::new(v(1), v(2), v(3)),
                            j: Vec3::zeros(),
                        });
                    }
                    row += 1;
                }
            }
            // Repeated (node, row) pairs would be one entry in a build.
            entries.sort_by_key(|e| (e.node, e.row));
            entries.dedup_by_key(|e| (e.node, e.row));
            let m = spread * row + 1;
            view.fill_j(&mut entries);
            let start: Vec<f64> = (0..m * m).map(|i| test_value(i, 9)).collect();
            let mut w = start.clone();
            let mut cache = ColumnCache::default();
            let mut prefetch = ColumnPrefetch::default();
            let mut sc = Scratch::default();
            super::super::group(&entries, &mut sc.groups);
            let h2 = 1e-4;
            accumulate(
                &view,
                &mut cache,
                &mut prefetch,
                &mut sc,
                h2,
                &entries,
                &mut w,
                m,
                WBlock::Written,
                None,
            );
            let mut want = start.clone();
            for a in &entries {
                for b in &entries {
                    let ca = cache.col_of_node[a.node as usize];
                    let cb = cache.col_of_node[b.node as usize];
                    let g = cache.gram(ca, cb);
                    want[a.row as usize * m + b.row as usize] += a.j.dot(&(g * b.j)) * h2;
                }
            }
            let scale = want
                .iter()
                .zip(&start)
                .map(|(x, s)| (x - s).abs())
                .fold(0.0, f64::max);
            assert!(scale > 0.0);
            for (i, (got, want)) in w.iter().zip(&want).enumerate() {
                assert!(
                    (got - want).abs() <= 1e-12 * scale,
                    "spread {spread}, entry ({}, {}): {got:e} against {want:e}",
                    i / m,
                    i % m
                );
            }
        }
    }

    /// The mirror of `W`'s pairs (AVX2 where the CPU has it, and portable)
    /// adds exactly `t[i, j] + t[j, i]` to each entry, for sizes with and
    /// without partial tiles and rows contiguous or spread.
    #[test]
    fn mirror_adds_each_entry_and_its_transpose() {
        for k in [0, 1, 7, 8, 9, 16, 19] {
            for spread in [1, 3] {
                let rows: Vec<u32> = (0..k).map(|i| (spread * i + 1) as u32).collect();
                let m = spread * k + 2;
                let t: Vec<f64> = (0..k * k).map(|i| test_value(i, 1)).collect();
                let start: Vec<f64> = (0..m * m).map(|i| test_value(i, 2)).collect();
                let mut want = start.clone();
                for i in 0..k {
                    for j in 0..k {
                        let (r, c) = (rows[i] as usize, rows[j] as usize);
                        want[r * m + c] += t[i * k + j] + t[j * k + i];
                    }
                }
                let mut fast = start.clone();
                mirror_into(&t, &rows, &mut fast, m);
                let mut portable = start.clone();
                mirror_into_portable(&t, &rows, &mut portable, m);
                for (i, w) in want.iter().enumerate() {
                    assert_eq!(
                        fast[i].to_bits(),
                        w.to_bits(),
                        "k {k}, spread {spread}, {i}"
                    );
                    assert_eq!(
                        portable[i].to_bits(),
                        w.to_bits(),
                        "k {k}, spread {spread}, {i}"
                    );
                }
                if k > 0 {
                    assert!(want != start);
                }
            }
        }
    }

    /// `mirror_in_place` makes the block at `r0..r0 + k` of `w` into
    /// `W_B + W_Bᵀ` (each entry the sum `w[i, j] + w[j, i]`, as
    /// [`mirror_into`] forms it) and leaves the rest of `w` alone; in AVX2
    /// lanes and portably. With a rank-12 term, entries `(i, j)` and
    /// `(j, i)` both gain the term's `(min, max)` entry, summed as
    /// `Deflation::add_prepared` sums it, after the pair.
    #[test]
    fn mirror_in_place_sums_the_block_and_its_transpose() {
        for k in [0, 1, 7, 8, 9, 16, 19, 24] {
            for r0 in [0, 3] {
                for with_rank in [false, true] {
                    let m = k + r0 + 2;
                    let start: Vec<f64> = (0..m * m).map(|i| test_value(i, 4)).collect();
                    let soa: Vec<f64> = (0..12 * k).map(|i| test_value(i, 5)).collect();
                    let coef: Vec<f64> = (0..12 * k).map(|i| test_value(i, 6)).collect();
                    let rows: Vec<u32> = (r0 as u32..(r0 + k) as u32).collect();
                    let term = |i: usize, j: usize| {
                        let (a, b) = (&coef[12 * i..12 * i + 6], &coef[12 * i + 6..12 * i + 12]);
                        let mut su = 0.0;
                        let mut sv = 0.0;
                        for c in 0..6 {
                            su += a[c] * soa[c * k + j];
                            sv += b[c] * soa[(6 + c) * k + j];
                        }
                        su - sv
                    };
                    let mut want = start.clone();
                    for i in 0..k {
                        for j in 0..k {
                            let (r, c) = (r0 + i, r0 + j);
                            want[r * m + c] = start[r * m + c] + start[c * m + r];
                            if with_rank {
                                want[r * m + c] += term(i.min(j), i.max(j));
                            }
                        }
                    }
                    let rank = Rank12 {
                        rows: &rows,
                        soa: &soa,
                        coef: &coef,
                    };
                    let mut fast = start.clone();
                    mirror_in_place(&mut fast, m, r0, k, with_rank.then_some(&rank));
                    let mut portable = start.clone();
                    if with_rank {
                        mirror_in_place_portable::<true>(&mut portable, m, r0, k, &soa, &coef);
                    } else {
                        mirror_in_place_portable::<false>(&mut portable, m, r0, k, &[], &[]);
                    }
                    for (i, w) in want.iter().enumerate() {
                        let at = format!("k {k}, r0 {r0}, rank {with_rank}, {i}");
                        assert_eq!(fast[i].to_bits(), w.to_bits(), "{at}");
                        assert_eq!(portable[i].to_bits(), w.to_bits(), "{at}");
                    }
                    if k > 0 {
                        assert!(want != start);
                    }
                }
            }
        }
    }
}
