//! Sparse `LDLᵀ` factorization with 3×3 node supernodes.
//!
//! The factor is organised by mesh node: every node is a supernode of three
//! columns that share one sparsity pattern, so `L` is stored as dense 3×3
//! blocks (one per nonzero node pair) plus, per node, a unit lower-triangular
//! 3×3 diagonal block and three pivots of `D`.
//!
//! - **Symbolic analysis** ([`LdltSymbolic::new`], once per mesh):
//!   fill-reducing ordering of the node graph (the cheaper of faer's
//!   approximate minimum degree and a nested dissection, see
//!   [`super::ordering`]), the elimination tree, the column structure of `L`, and for every row the
//!   topologically ordered reach with the storage slot each entry fills.
//! - **Numeric factorization** ([`LdltSymbolic::factorize`]): up-looking
//!   block `LDLᵀ`, allocation-free into a recycled [`LdltFactor`]. A
//!   non-positive pivot is reported as [`SoftTissueError::NotPositiveDefinite`].
//!   From [`SUPERNODAL_MIN_BLOCKS`] blocks of `L` on, faer's supernodal
//!   factorization of the same matrix in the same ordering makes the factor
//!   instead, gathered into the same layout ([`FactorKernel`]; its dense
//!   supernode kernels win on large meshes: 2.7× at 16 000 nodes).
//! - **Solves**: full forward/diagonal/backward solves for the CG
//!   preconditioner (with AVX2, two columns of one supernode are swept
//!   together where the first one's rows are the second and its rows,
//!   [`LdltSymbolic::joined_columns`], so each shared row of `y` is read and
//!   written once for both), and the reach-restricted forward solve of the three unit
//!   columns of one node ([`LdltFactor::node_forward_solve`]), whose nonzeros
//!   lie only on the node's elimination-tree path to the root, or of up to
//!   eight nodes at once, each block on the union of their paths applied to
//!   all of them in vector lanes (`nodes_forward_solve`, the same columns to
//!   the bit). This is what the contact compliance is built from.

use std::sync::Arc;

use super::half::{HalfCopy, Structure};
use super::ordering::{Ordering, Permutation};
use super::supernodal::{FactorParts, SupernodalBuffers, SupernodalPlan};

use crate::error::{Result, SoftTissueError};
use crate::fem::assembly::{BlockCsr, BlockPattern};
#[cfg(target_arch = "x86_64")]
use crate::math::x86;
use crate::math::{
    Mat3, Vec3, has_avx2_fma, unit_lower_solve, unit_lower_solve_mat, unit_lower_t_solve,
};

/// Marker for "no parent" in the elimination tree.
pub const NONE: usize = usize::MAX;

/// Which kernel makes the numeric factorization ([`LdltSymbolic::factorize`]).
/// Both give the same factor, to round-off, in the same layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FactorKernel {
    /// `Supernodal` from [`SUPERNODAL_MIN_BLOCKS`] blocks of `L` on,
    /// `Blocked` below.
    #[default]
    Auto,
    /// This module's up-looking node-blocked factorization.
    Blocked,
    /// faer's supernodal `LDLᵀ` of the scalar matrix in the same ordering,
    /// gathered into the blocked layout (see [`super::supernodal`]). Falls
    /// back to `Blocked` if faer's analysis does not hold the blocked structure.
    Supernodal,
}

/// Blocks of `L` from which [`FactorKernel::Auto`] factorizes supernodally.
/// `cargo bench --bench step -- factorize`: the blocked kernel is on par at
/// 66 000 blocks (the cataract lens) and faer's 2.2× faster at a million.
pub const SUPERNODAL_MIN_BLOCKS: usize = 200_000;

/// Symbolic analysis of the node-blocked `LDLᵀ` factorization.
#[derive(Debug, Clone)]
pub struct LdltSymbolic {
    /// Number of nodes.
    pub n: usize,
    /// `perm[new] = old` node.
    pub perm: Vec<usize>,
    /// `iperm[old] = new` node.
    pub iperm: Vec<usize>,
    /// Elimination-tree parent of each (permuted) node, [`NONE`] for roots.
    pub parent: Vec<usize>,
    /// Column start offsets of `L` (strictly lower blocks), length `n + 1`.
    pub col_ptr: Vec<usize>,
    /// Row (permuted node) of every block of `L`, ascending within a column.
    pub row_idx: Vec<usize>,
    /// For row `k`: `reach_ptr[k]..reach_ptr[k+1]` indexes `reach_col` / `reach_dst`.
    reach_ptr: Vec<usize>,
    /// Columns `i < k` with `L_ki ≠ 0`, in topological order.
    reach_col: Vec<usize>,
    /// Storage slot of `L_ki`.
    reach_dst: Vec<usize>,
    /// For row `k`: the lower entries of `A` as `(permuted col i, slot of A(perm i, perm k))`.
    a_ptr: Vec<usize>,
    a_entries: Vec<(usize, usize)>,
    /// Slot of each permuted node's diagonal block in `A`.
    a_diag: Vec<usize>,
    /// The supernodal kernel's analysis, when it factorizes.
    supernodal: Option<Arc<SupernodalPlan>>,
    /// Whether column `j`'s rows are `j + 1` followed by the rows of column
    /// `j + 1` (the two are one supernode): the sweeps then take the two
    /// columns together, reading and writing each shared row once.
    joins_next: Vec<bool>,
}

/// Numeric values of an `LDLᵀ` factorization (see [`LdltSymbolic`]).
#[derive(Debug, Clone)]
pub struct LdltFactor {
    /// The symbolic analysis this factor belongs to.
    pub symbolic: Arc<LdltSymbolic>,
    /// Off-diagonal blocks `L_ri`, laid out like [`LdltSymbolic::row_idx`].
    pub l: Vec<Mat3>,
    /// Sub-diagonal entries `(l10, l20, l21)` of each unit lower diagonal block.
    pub ldiag: Vec<[f64; 3]>,
    /// Pivots of `D` per node.
    pub d: Vec<Vec3>,
    /// `l` rounded to `f32` for [`Self::solve_single`]: nine entries per
    /// block, column-major, then three of padding (the kernels' four-lane
    /// loads read one entry past a block). Made by [`Self::round_to_single`];
    /// allocated by its first call and kept, its entries valid only while
    /// `single` is set.
    l32: Vec<f32>,
    /// Whether `l32` holds the copy of the current `l` (cleared by each
    /// factorization into this factor).
    single: bool,
    /// The preconditioner's half-precision copy ([`Self::round_to_half`]),
    /// invalidated with `single`.
    half: HalfCopy,
    /// The supernodal kernel's buffers (empty for the blocked kernel).
    supernodal: SupernodalBuffers,
}

impl LdltSymbolic {
    /// Analyses `pattern`: fill-reducing ordering ([`Ordering::Auto`]),
    /// elimination tree and structure of `L`.
    pub fn new(pattern: &BlockPattern) -> Result<Self> {
        Self::with_ordering(pattern, Ordering::Auto)
    }

    /// [`Self::new`] with the given ordering.
    pub fn with_ordering(pattern: &BlockPattern, ordering: Ordering) -> Result<Self> {
        Self::with_kernel(pattern, ordering, FactorKernel::Auto)
    }

    /// [`Self::new`] with the given ordering and numeric kernel.
    pub fn with_kernel(
        pattern: &BlockPattern,
        ordering: Ordering,
        kernel: FactorKernel,
    ) -> Result<Self> {
        let n = pattern.n;
        let Permutation { perm, iperm } = super::ordering::order(pattern, ordering)?;
        // Lower entries of A per permuted row.
        let mut a_ptr = vec![0usize; n + 1];
        let mut a_entries = Vec::with_capacity(pattern.nnz() / 2);
        let mut a_diag = vec![0usize; n];
        for k in 0..n {
            let old_k = perm[k];
            for s in pattern.row_ptr[old_k]..pattern.row_ptr[old_k + 1] {
                let old_i = pattern.col_idx[s];
                let i = iperm[old_i];
                if i < k {
                    // Block A(old_i, old_k) lives in row old_i.
                    let slot = pattern.slot(old_i, old_k).unwrap_or(usize::MAX);
                    a_entries.push((i, slot));
                } else if i == k {
                    a_diag[k] = s;
                }
            }
            a_ptr[k + 1] = a_entries.len();
        }
        let parent = super::ordering::elimination_tree(n, |k| {
            a_entries[a_ptr[k]..a_ptr[k + 1]].iter().map(|&(i, _)| i)
        });
        // Row reaches (topological order) and column counts.
        let mut mark = vec![NONE; n];
        let mut reach_ptr = vec![0usize; n + 1];
        let mut reach_col = Vec::new();
        let mut stack = Vec::with_capacity(n);
        let mut path = Vec::with_capacity(n);
        let mut col_count = vec![0usize; n];
        for k in 0..n {
            mark[k] = k;
            stack.clear();
            for &(i0, _) in &a_entries[a_ptr[k]..a_ptr[k + 1]] {
                let mut i = i0;
                path.clear();
                while i != NONE && mark[i] != k {
                    path.push(i);
                    mark[i] = k;
                    i = parent[i];
                }
                // Push the path so that descendants come before ancestors.
                while let Some(p) = path.pop() {
                    stack.push(p);
                }
            }
            // `stack` popped from the end gives a topological order; store reversed.
            for &i in stack.iter().rev() {
                reach_col.push(i);
                col_count[i] += 1;
            }
            reach_ptr[k + 1] = reach_col.len();
        }
        let mut col_ptr = vec![0usize; n + 1];
        for i in 0..n {
            col_ptr[i + 1] = col_ptr[i] + col_count[i];
        }
        let mut fill = col_ptr[..n].to_vec();
        let mut row_idx = vec![0usize; col_ptr[n]];
        let mut reach_dst = vec![0usize; reach_col.len()];
        for k in 0..n {
            for t in reach_ptr[k]..reach_ptr[k + 1] {
                let i = reach_col[t];
                row_idx[fill[i]] = k;
                reach_dst[t] = fill[i];
                fill[i] += 1;
            }
        }
        let supernodal = match kernel {
            FactorKernel::Blocked => false,
            FactorKernel::Supernodal => true,
            FactorKernel::Auto => row_idx.len() >= SUPERNODAL_MIN_BLOCKS,
        };
        let supernodal = supernodal
            .then(|| SupernodalPlan::new(pattern, &perm, &col_ptr, &row_idx))
            .flatten()
            .map(Arc::new);
        let joins_next = (0..n)
            .map(|j| {
                let rows = &row_idx[col_ptr[j]..col_ptr[j + 1]];
                j + 1 < n
                    && rows.first() == Some(&(j + 1))
                    && rows[1..] == row_idx[col_ptr[j + 1]..col_ptr[j + 2]]
            })
            .collect();
        Ok(Self {
            n,
            perm,
            iperm,
            parent,
            col_ptr,
            row_idx,
            reach_ptr,
            reach_col,
            reach_dst,
            a_ptr,
            a_entries,
            a_diag,
            supernodal,
            joins_next,
        })
    }

    /// The kernel [`Self::factorize`] uses: `Blocked` or `Supernodal`.
    pub fn kernel(&self) -> FactorKernel {
        if self.supernodal.is_some() {
            FactorKernel::Supernodal
        } else {
            FactorKernel::Blocked
        }
    }

    /// Whether column `j`'s rows are `j + 1` followed by column `j + 1`'s
    /// rows (the two are one supernode, `j + 1` the parent of `j`).
    pub fn joins_next(&self, j: usize) -> bool {
        self.joins_next[j]
    }

    /// How many columns the sweeps take together with the next one (see
    /// [`LdltFactor::forward`]): those whose rows are the next column and its
    /// rows.
    pub fn joined_columns(&self) -> usize {
        self.joins_next.iter().filter(|&&b| b).count()
    }

    /// Number of 3×3 blocks in the strictly lower part of `L`.
    pub fn nnz_blocks(&self) -> usize {
        self.row_idx.len()
    }

    /// An empty factor with storage for this structure.
    pub fn alloc_factor(self: &Arc<Self>) -> LdltFactor {
        LdltFactor {
            symbolic: Arc::clone(self),
            l: vec![Mat3::zeros(); self.nnz_blocks()],
            ldiag: vec![[0.0; 3]; self.n],
            d: vec![Vec3::zeros(); self.n],
            l32: Vec::new(),
            single: false,
            half: HalfCopy::default(),
            supernodal: self
                .supernodal
                .as_ref()
                .map(|p| p.alloc())
                .unwrap_or_default(),
        }
    }

    /// Factorizes `a` into `out` (which must come from [`Self::alloc_factor`]), using
    /// `work` (length `n`) as scratch. Allocation-free.
    pub fn factorize(
        &self,
        a: &BlockCsr,
        out: &mut LdltFactor,
        work: &mut Vec<Mat3>,
    ) -> Result<()> {
        let n = self.n;
        out.single = false;
        out.half.invalidate();
        if let Some(plan) = &self.supernodal {
            let parts = FactorParts {
                l: &mut out.l,
                ldiag: &mut out.ldiag,
                d: &mut out.d,
                buf: &mut out.supernodal,
            };
            return plan.factorize(a, &self.perm, &self.a_diag, parts);
        }
        work.clear();
        work.resize(n, Mat3::zeros());
        let y = work;
        for k in 0..n {
            for &(i, slot) in &self.a_entries[self.a_ptr[k]..self.a_ptr[k + 1]] {
                y[i] = a.values[slot];
            }
            let mut dkk = a.values[self.a_diag[k]];
            for t in self.reach_ptr[k]..self.reach_ptr[k + 1] {
                let i = self.reach_col[t];
                let dst = self.reach_dst[t];
                let w = unit_lower_solve_mat(&out.ldiag[i], &y[i]);
                y[i] = Mat3::zeros();
                let range = self.col_ptr[i]..dst;
                sub_products_any(&out.l[range.clone()], &self.row_idx[range], &w, y);
                let di = out.d[i];
                let mut lki = w.transpose();
                for c in 0..3 {
                    let inv = 1.0 / di[c];
                    for r in 0..3 {
                        lki[(r, c)] *= inv;
                    }
                }
                dkk -= lki * w;
                out.l[dst] = lki;
            }
            // Dense LDLᵀ of the 3×3 diagonal block (lower triangle).
            let d0 = dkk[(0, 0)];
            let l10 = dkk[(1, 0)] / d0;
            let l20 = dkk[(2, 0)] / d0;
            let d1 = dkk[(1, 1)] - l10 * l10 * d0;
            let l21 = (dkk[(2, 1)] - l20 * l10 * d0) / d1;
            let d2 = dkk[(2, 2)] - l20 * l20 * d0 - l21 * l21 * d1;
            let scale = dkk[(0, 0)]
                .abs()
                .max(dkk[(1, 1)].abs())
                .max(dkk[(2, 2)].abs());
            for piv in [d0, d1, d2] {
                if !piv.is_finite() || piv <= 1e-14 * scale || scale == 0.0 {
                    return Err(SoftTissueError::NotPositiveDefinite {
                        node: self.perm[k],
                        pivot: piv,
                    });
                }
            }
            out.ldiag[k] = [l10, l20, l21];
            out.d[k] = Vec3::new(d0, d1, d2);
        }
        Ok(())
    }
}

impl LdltFactor {
    /// Forward solve `L y = y` in permuted numbering, in place.
    pub fn forward(&self, y: &mut [Vec3]) {
        self.forward_with::<false>(y);
    }

    /// Backward solve `Lᵀ y = y` in permuted numbering, in place.
    pub fn backward(&self, y: &mut [Vec3]) {
        self.backward_with::<false>(y);
    }

    /// [`Self::backward`] with the single-precision copy of `L` when there is
    /// one ([`Self::round_to_single`]; otherwise this is [`Self::backward`]):
    /// half the memory read, `f32` round-off in the blocks of `L` only.
    pub fn backward_single(&self, y: &mut [Vec3]) {
        if self.has_single() {
            self.backward_with::<true>(y);
        } else {
            self.backward_with::<false>(y);
        }
    }

    /// [`Self::forward`] with the single-precision copy of `L` when there is
    /// one (see [`Self::backward_single`]).
    pub fn forward_single(&self, y: &mut [Vec3]) {
        if self.has_single() {
            self.forward_with::<true>(y);
        } else {
            self.forward_with::<false>(y);
        }
    }

    /// [`Self::forward`] with `L` in double (`SINGLE = false`) or single
    /// precision (`l32`, which must hold the copy).
    fn forward_with<const SINGLE: bool>(&self, y: &mut [Vec3]) {
        #[cfg(target_arch = "x86_64")]
        if has_avx2_fma() {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { self.forward_avx2::<SINGLE>(y) };
        }
        self.forward_portable::<SINGLE>(y);
    }

    /// [`Self::backward`] with `L` in double or single precision (see
    /// [`Self::forward_with`]).
    fn backward_with<const SINGLE: bool>(&self, y: &mut [Vec3]) {
        #[cfg(target_arch = "x86_64")]
        if has_avx2_fma() {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { self.backward_avx2::<SINGLE>(y) };
        }
        self.backward_portable::<SINGLE>(y);
    }

    /// Block `p` of `L`, from `l` or from its single-precision copy.
    #[inline(always)]
    fn block<const SINGLE: bool>(&self, p: usize) -> Mat3 {
        if SINGLE {
            Mat3::from_fn(|r, c| f64::from(self.l32[9 * p + 3 * c + r]))
        } else {
            self.l[p]
        }
    }

    /// The three columns of block `p` of `L` in lanes 0–2, from `l` (lane 3
    /// zero) or from its single-precision copy (lane 3 the next entry of
    /// `l32`: the kernels never let lane 3 reach a result).
    ///
    /// # Safety
    /// With `SINGLE`, `l32` must hold `9 (p + 1) + 3` entries or more
    /// ([`Self::check_single`]).
    #[cfg(target_arch = "x86_64")]
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn block_columns<const SINGLE: bool>(
        &self,
        p: usize,
    ) -> [std::arch::x86_64::__m256d; 3] {
        use std::arch::x86_64::*;
        if SINGLE {
            // SAFETY: the caller guarantees the entries the three four-lane
            // loads read, 9p..9p + 10 (the last one is the next block's, or
            // padding).
            unsafe {
                let q = self.l32.as_ptr().add(9 * p);
                [
                    _mm256_cvtps_pd(_mm_loadu_ps(q)),
                    _mm256_cvtps_pd(_mm_loadu_ps(q.add(3))),
                    _mm256_cvtps_pd(_mm_loadu_ps(q.add(6))),
                ]
            }
        } else {
            x86::columns(&self.l[p])
        }
    }

    /// With `SINGLE`, checks that `l32` covers every block of `L` with its
    /// padding, what [`Self::block_columns`] needs for any block.
    #[inline]
    fn check_single<const SINGLE: bool>(&self) {
        if SINGLE {
            assert!(
                self.single && self.l32.len() >= 9 * self.l.len() + 3,
                "no single-precision copy of L"
            );
        }
    }

    fn forward_portable<const SINGLE: bool>(&self, y: &mut [Vec3]) {
        let s = &*self.symbolic;
        for j in 0..s.n {
            let yj = unit_lower_solve(&self.ldiag[j], &y[j]);
            y[j] = yj;
            for p in s.col_ptr[j]..s.col_ptr[j + 1] {
                y[s.row_idx[p]] -= self.block::<SINGLE>(p) * yj;
            }
        }
    }

    /// [`Self::forward`] with AVX2 and FMA: `y_r -= L_p y_j` as three fused
    /// multiply-adds of `L_p`'s columns with broadcast entries of `y_j`.
    /// Two columns of one supernode (`joins_next`) go together: each shared
    /// row is read and written once for both. Lane 3 of every product is
    /// never stored, so the single-precision columns are used as loaded
    /// (their lane 3 is the next entry of `l32`). `y_r` is read as it is
    /// written, sixteen bytes and eight: one four-lane load over two such
    /// stores cannot take its data from the store buffer, and was slower
    /// (`cargo bench --bench step -- lens_forward_single`: 120–123 against
    /// 108–114 µs).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn forward_avx2<const SINGLE: bool>(&self, y: &mut [Vec3]) {
        use std::arch::x86_64::*;
        let s = &*self.symbolic;
        self.check_single::<SINGLE>();
        let n = s.n;
        assert!(y.len() >= n, "forward: one entry per node");
        let yp = y.as_mut_ptr().cast::<f64>();
        let splat = |v: Vec3| {
            [
                _mm256_set1_pd(v.x),
                _mm256_set1_pd(v.y),
                _mm256_set1_pd(v.z),
            ]
        };
        // SAFETY (callers): `r < n`, the length checked above.
        let load = |r: usize| unsafe { x86::load3_ptr(yp.add(3 * r)) };
        let mut j = 0;
        while j < n {
            // SAFETY: `j < n`.
            let yj = unsafe { &mut *yp.add(3 * j).cast::<Vec3>() };
            *yj = unit_lower_solve(&self.ldiag[j], yj);
            let b = splat(*yj);
            let (start, end) = (s.col_ptr[j], s.col_ptr[j + 1]);
            if s.joins_next[j] {
                // Column `j`'s first block is row `j + 1`; its other rows are
                // column `j + 1`'s.
                let (start1, end1) = (s.col_ptr[j + 1], s.col_ptr[j + 2]);
                // SAFETY: blocks of `L` (checked before the loop); rows are
                // nodes.
                unsafe {
                    let lc = self.block_columns::<SINGLE>(start);
                    let mut acc = load(j + 1);
                    for k in 0..3 {
                        acc = _mm256_fnmadd_pd(lc[k], b[k], acc);
                    }
                    x86::store3_ptr(yp.add(3 * (j + 1)), acc);
                    let y1 = &mut *yp.add(3 * (j + 1)).cast::<Vec3>();
                    *y1 = unit_lower_solve(&self.ldiag[j + 1], y1);
                    let b1 = splat(*y1);
                    for (t, &r) in s.row_idx[start1..end1].iter().enumerate() {
                        let la = self.block_columns::<SINGLE>(start + 1 + t);
                        let lb = self.block_columns::<SINGLE>(start1 + t);
                        let mut acc = load(r);
                        for k in 0..3 {
                            acc = _mm256_fnmadd_pd(la[k], b[k], acc);
                        }
                        for k in 0..3 {
                            acc = _mm256_fnmadd_pd(lb[k], b1[k], acc);
                        }
                        x86::store3_ptr(yp.add(3 * r), acc);
                    }
                }
                j += 2;
                continue;
            }
            for (p, &r) in (start..end).zip(&s.row_idx[start..end]) {
                // SAFETY: checked before the loop (`p` is a block of `L`);
                // `r` is a node.
                unsafe {
                    let lc = self.block_columns::<SINGLE>(p);
                    let mut acc = load(r);
                    for k in 0..3 {
                        acc = _mm256_fnmadd_pd(lc[k], b[k], acc);
                    }
                    x86::store3_ptr(yp.add(3 * r), acc);
                }
            }
            j += 1;
        }
    }

    fn backward_portable<const SINGLE: bool>(&self, y: &mut [Vec3]) {
        let s = &*self.symbolic;
        for j in (0..s.n).rev() {
            let mut acc = y[j];
            for p in s.col_ptr[j]..s.col_ptr[j + 1] {
                acc -= self.block::<SINGLE>(p).transpose() * y[s.row_idx[p]];
            }
            y[j] = unit_lower_t_solve(&self.ldiag[j], &acc);
        }
    }

    /// [`Self::backward`] with AVX2 and FMA: `L_pᵀ y_r` is three dot products;
    /// each column of `L_p` accumulates `L_p[:, k] ⊙ y_r` in its own vector over
    /// the whole column of `L`, and the three are summed once per node. Three
    /// or two columns of one supernode (`joins_next`) go together, each shared
    /// row read once for all (three: 102–107 against 102–114 µs for two on the
    /// benchmark lens, three runs each, alternating); a lone column splits its blocks over two sets of
    /// vectors, so consecutive fused multiply-adds do not wait on each
    /// other's latency. The blocks are taken from the last row up: the nodes
    /// just solved come last, so a column's sums start before the node above
    /// it is done. `y_r` is read with lane 3 zero (and as it is written, see
    /// [`Self::forward_avx2`]), so the blocks are used as loaded; lane 3 of
    /// the sums is set to zero once per node all the same.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn backward_avx2<const SINGLE: bool>(&self, y: &mut [Vec3]) {
        use std::arch::x86_64::*;
        let s = &*self.symbolic;
        self.check_single::<SINGLE>();
        let n = s.n;
        assert!(y.len() >= n, "backward: one entry per node");
        let yp = y.as_mut_ptr().cast::<f64>();
        let zero = _mm256_setzero_pd();
        // `y_j − Σ` with the sums' lane 3 dropped, solved with the diagonal
        // block, into `y_j`.
        // SAFETY (callers): `j < n`.
        let finish = |j: usize, acc: [__m256d; 3]| unsafe {
            let acc = acc.map(|a| _mm256_blend_pd(a, zero, 0b1000));
            let yj = &mut *yp.add(3 * j).cast::<Vec3>();
            let rhs = *yj - x86::sums3(acc);
            *yj = unit_lower_t_solve(&self.ldiag[j], &rhs);
        };
        let mut j = n;
        while j > 0 {
            j -= 1;
            if j > 1 && s.joins_next[j - 1] && s.joins_next[j - 2] {
                // Columns `j − 2`, `j − 1` and `j` (see below for two).
                let (h, i) = (j - 2, j - 1);
                let (start, end) = (s.col_ptr[j], s.col_ptr[j + 1]);
                let (start_i, start_h) = (s.col_ptr[i] + 1, s.col_ptr[h] + 2);
                let mut acc_h = [zero; 3];
                let mut acc_i = [zero; 3];
                let mut acc_j = [zero; 3];
                // SAFETY: blocks of `L` (checked before the loop); rows are
                // nodes.
                unsafe {
                    for t in (0..end - start).rev() {
                        let v = x86::load3_ptr(yp.add(3 * s.row_idx[start + t]));
                        let la = self.block_columns::<SINGLE>(start_h + t);
                        let lb = self.block_columns::<SINGLE>(start_i + t);
                        let lc = self.block_columns::<SINGLE>(start + t);
                        for k in 0..3 {
                            acc_h[k] = _mm256_fmadd_pd(la[k], v, acc_h[k]);
                            acc_i[k] = _mm256_fmadd_pd(lb[k], v, acc_i[k]);
                            acc_j[k] = _mm256_fmadd_pd(lc[k], v, acc_j[k]);
                        }
                    }
                    finish(j, acc_j);
                    let v = x86::load3_ptr(yp.add(3 * j));
                    let la = self.block_columns::<SINGLE>(start_h - 1);
                    let lb = self.block_columns::<SINGLE>(start_i - 1);
                    for k in 0..3 {
                        acc_h[k] = _mm256_fmadd_pd(la[k], v, acc_h[k]);
                        acc_i[k] = _mm256_fmadd_pd(lb[k], v, acc_i[k]);
                    }
                    finish(i, acc_i);
                    let v = x86::load3_ptr(yp.add(3 * i));
                    let la = self.block_columns::<SINGLE>(start_h - 2);
                    for k in 0..3 {
                        acc_h[k] = _mm256_fmadd_pd(la[k], v, acc_h[k]);
                    }
                    finish(h, acc_h);
                }
                j = h;
                continue;
            }
            if j > 0 && s.joins_next[j - 1] {
                // Columns `j − 1` and `j`: the first block of `j − 1` is row
                // `j`, its other rows are column `j`'s.
                let i = j - 1;
                let (start, end) = (s.col_ptr[j], s.col_ptr[j + 1]);
                let start0 = s.col_ptr[i] + 1;
                let mut acc0 = [zero; 3];
                let mut acc1 = [zero; 3];
                // SAFETY: blocks of `L` (checked before the loop); rows are
                // nodes.
                unsafe {
                    for t in (0..end - start).rev() {
                        let v = x86::load3_ptr(yp.add(3 * s.row_idx[start + t]));
                        let la = self.block_columns::<SINGLE>(start0 + t);
                        let lb = self.block_columns::<SINGLE>(start + t);
                        for k in 0..3 {
                            acc0[k] = _mm256_fmadd_pd(la[k], v, acc0[k]);
                            acc1[k] = _mm256_fmadd_pd(lb[k], v, acc1[k]);
                        }
                    }
                    finish(j, acc1);
                    let v = x86::load3_ptr(yp.add(3 * j));
                    let la = self.block_columns::<SINGLE>(start0 - 1);
                    for k in 0..3 {
                        acc0[k] = _mm256_fmadd_pd(la[k], v, acc0[k]);
                    }
                    finish(i, acc0);
                }
                j = i;
                continue;
            }
            let mut acc = [zero; 3];
            let mut acc2 = [zero; 3];
            let (start, end) = (s.col_ptr[j], s.col_ptr[j + 1]);
            let len = end - start;
            // SAFETY: as above.
            unsafe {
                let rows = &s.row_idx[start..end];
                let mut t = len;
                while t >= 2 {
                    t -= 2;
                    let la = self.block_columns::<SINGLE>(start + t + 1);
                    let lb = self.block_columns::<SINGLE>(start + t);
                    let va = x86::load3_ptr(yp.add(3 * rows[t + 1]));
                    let vb = x86::load3_ptr(yp.add(3 * rows[t]));
                    for k in 0..3 {
                        acc[k] = _mm256_fmadd_pd(la[k], va, acc[k]);
                        acc2[k] = _mm256_fmadd_pd(lb[k], vb, acc2[k]);
                    }
                }
                if t == 1 {
                    let lc = self.block_columns::<SINGLE>(start);
                    let v = x86::load3_ptr(yp.add(3 * rows[0]));
                    for k in 0..3 {
                        acc[k] = _mm256_fmadd_pd(lc[k], v, acc[k]);
                    }
                }
                for k in 0..3 {
                    acc[k] = _mm256_add_pd(acc[k], acc2[k]);
                }
                finish(j, acc);
            }
        }
    }

    /// Rounds `L` to single precision for [`Self::solve_single`]; the copy
    /// holds until the next factorization into this factor, and must be made
    /// again after `l` is changed by hand. Entries below `f32`'s smallest
    /// normal number become zero. Returns whether the copy was made: an entry
    /// too large for `f32` leaves the factor without one (and
    /// [`Self::solve_single`] solves in double precision). Allocates on the
    /// first call only.
    pub fn round_to_single(&mut self) -> bool {
        let len = 9 * self.l.len() + 3;
        if self.l32.len() != len {
            self.l32.clear();
            self.l32.resize(len, 0.0);
        }
        // One branch-free pass (the range check is folded into `ok`), which
        // the compiler vectorizes; the padding stays zero.
        let mut ok = true;
        for (b, out) in self.l.iter().zip(self.l32.chunks_exact_mut(9)) {
            for (o, &v) in out.iter_mut().zip(b.as_slice()) {
                let a = v.abs();
                // False for NaN and ±∞ too.
                ok &= a <= f64::from(f32::MAX);
                *o = if a < f64::from(f32::MIN_POSITIVE) {
                    0.0
                } else {
                    v as f32
                };
            }
        }
        self.single = ok;
        ok
    }

    /// Whether a single-precision copy of `L` is in place (see
    /// [`Self::round_to_single`]).
    pub fn has_single(&self) -> bool {
        self.single
    }

    /// The single-precision copy of `L` (nine entries per block, column-major,
    /// laid out like [`Self::l`]), when there is one ([`Self::round_to_single`]).
    pub fn l_single(&self) -> Option<&[f32]> {
        self.has_single().then(|| &self.l32[..9 * self.l.len()])
    }

    /// Copies the values of `other` (a factor of the same structure) into
    /// this one, without a single-precision copy.
    pub fn copy_values_from(&mut self, other: &LdltFactor) {
        self.l.copy_from_slice(&other.l);
        self.ldiag.copy_from_slice(&other.ldiag);
        self.d.copy_from_slice(&other.d);
        self.single = false;
        self.half.invalidate();
    }

    /// Solves `(L̃ D L̃ᵀ) x = b` like [`Self::solve`], with `L̃` the
    /// single-precision copy of `L` when there is one ([`Self::round_to_single`];
    /// otherwise this is [`Self::solve`]). `L̃ D L̃ᵀ` is symmetric positive
    /// definite like `L D Lᵀ` and within `f32` round-off of it: a
    /// preconditioner reads half the memory per solve. Arithmetic, `D` and the
    /// diagonal blocks stay in double precision.
    pub fn solve_single(&self, b: &[Vec3], x: &mut [Vec3], tmp: &mut [Vec3]) {
        if self.has_single() {
            self.solve_with::<true>(b, x, tmp);
        } else {
            self.solve_with::<false>(b, x, tmp);
        }
    }

    /// Makes the preconditioner's half-precision copy of the factor for
    /// [`Self::solve_half`] (`L` in IEEE binary16, the diagonal blocks and
    /// `D⁻¹` in `f32`; see the module docs of [`crate::solver`], "Half and
    /// single precision"). The copy holds until the next
    /// factorization into this factor, and must be made again after the
    /// values are changed by hand. Returns whether it was made: not where the
    /// CPU lacks AVX2, FMA or F16C, nor where an entry of `L` is beyond
    /// binary16's 65 504 or the pivots do not fit `f32` (then
    /// [`Self::solve_half`] solves like [`Self::solve_single`]). Allocates on
    /// the first call only.
    pub fn round_to_half(&mut self) -> bool {
        self.half.make(&self.l, None, &self.ldiag, &self.d)
    }

    /// [`Self::round_to_single`], then [`Self::round_to_half`] from the
    /// single-precision copy where it was made: the same halves (binary16 of
    /// the `f32` value either way) from half the bytes, in eight lanes. What
    /// the lagged preconditioners make of each new factor. Returns whether
    /// each copy was made.
    pub fn round_to_single_and_half(&mut self) -> (bool, bool) {
        let single = self.round_to_single();
        let l32 = single.then(|| &self.l32[..9 * self.l.len()]);
        let half = self.half.make(&self.l, l32, &self.ldiag, &self.d);
        (single, half)
    }

    /// Whether a half-precision copy is in place (see [`Self::round_to_half`]).
    pub fn has_half(&self) -> bool {
        self.half.is_valid()
    }

    /// Solves `(L̃ D L̃ᵀ) x = b` like [`Self::solve`], with `L̃` the
    /// half-precision copy of `L` and `f32` arithmetic when there is a copy
    /// ([`Self::round_to_half`], scratch `tmp32`), otherwise as
    /// [`Self::solve_single`] (scratch `tmp`). For a preconditioner: `L̃ D L̃ᵀ`
    /// is symmetric positive definite and within about 10⁻³ of `L D Lᵀ`, and
    /// a solve reads a quarter of the memory of one in `f64`. Both scratch
    /// slices hold `n` entries.
    pub fn solve_half(&self, b: &[Vec3], x: &mut [Vec3], tmp: &mut [Vec3], tmp32: &mut [[f32; 4]]) {
        if self.has_half() {
            let s = &*self.symbolic;
            let structure = Structure {
                perm: &s.perm,
                col_ptr: &s.col_ptr,
                row_idx: &s.row_idx,
                joins_next: &s.joins_next,
            };
            self.half.solve(structure, b, x, tmp32);
        } else {
            self.solve_single(b, x, tmp);
        }
    }

    /// Solves `(L D Lᵀ) x = b` in original numbering; `tmp` is scratch of length `n`.
    pub fn solve(&self, b: &[Vec3], x: &mut [Vec3], tmp: &mut [Vec3]) {
        self.solve_with::<false>(b, x, tmp);
    }

    fn solve_with<const SINGLE: bool>(&self, b: &[Vec3], x: &mut [Vec3], tmp: &mut [Vec3]) {
        let s = &*self.symbolic;
        for k in 0..s.n {
            tmp[k] = b[s.perm[k]];
        }
        self.forward_with::<SINGLE>(tmp);
        for k in 0..s.n {
            tmp[k] = tmp[k].component_div(&self.d[k]);
        }
        self.backward_with::<SINGLE>(tmp);
        for k in 0..s.n {
            x[s.perm[k]] = tmp[k];
        }
    }

    /// Solves `(L D Lᵀ) x_c = b_c` for `K` right-hand sides at once, in original
    /// numbering (`b[i][c]` is node `i` of right-hand side `c`); `tmp` is
    /// scratch of length `n`. Reads `L` once for all `K`, where `K` calls of
    /// [`Self::solve`] read it `K` times.
    pub fn solve_many<const K: usize>(
        &self,
        b: &[[Vec3; K]],
        x: &mut [[Vec3; K]],
        tmp: &mut [[Vec3; K]],
    ) {
        let s = &*self.symbolic;
        for k in 0..s.n {
            tmp[k] = b[s.perm[k]];
        }
        self.sweeps_many_with::<K, true, true>(tmp);
        for k in 0..s.n {
            x[s.perm[k]] = tmp[k];
        }
    }

    /// The forward half of [`Self::solve_many`]: `y_c = L⁻¹ P b_c` for `K`
    /// right-hand sides at once (`b` in original numbering, `y` in permuted
    /// numbering, neither `D` nor the backward sweep applied).
    ///
    /// # Panics
    /// If `b` or `y` does not have one entry per node.
    pub fn forward_many<const K: usize>(&self, b: &[[Vec3; K]], y: &mut [[Vec3; K]]) {
        let s = &*self.symbolic;
        assert!(
            b.len() == s.n && y.len() == s.n,
            "forward_many: {} and {} entries for {} nodes",
            b.len(),
            y.len(),
            s.n
        );
        for k in 0..s.n {
            y[k] = b[s.perm[k]];
        }
        self.sweeps_many_with::<K, true, false>(y);
    }

    /// The other half: `y_c ← L⁻ᵀ y_c` for `K` right-hand sides in permuted
    /// numbering, in place (`D` not applied).
    ///
    /// # Panics
    /// If `y` does not have one entry per node.
    pub fn backward_many<const K: usize>(&self, y: &mut [[Vec3; K]]) {
        assert_eq!(
            y.len(),
            self.symbolic.n,
            "backward_many: one entry per node"
        );
        self.sweeps_many_with::<K, false, true>(y);
    }

    /// Sweeps of `K` right-hand sides in permuted numbering, in place: with
    /// `FWD` the forward one, with `BWD` the backward one, with both `D`
    /// between them.
    fn sweeps_many_with<const K: usize, const FWD: bool, const BWD: bool>(
        &self,
        y: &mut [[Vec3; K]],
    ) {
        #[cfg(target_arch = "x86_64")]
        if has_avx2_fma() {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { self.sweeps_many_avx2::<K, FWD, BWD>(y) };
        }
        self.sweeps_many::<K, FWD, BWD>(y);
    }

    /// [`Self::sweeps_many`] with AVX2 and FMA. Forward: `y_r[c] -= L_p y_j[c]`
    /// as three fused multiply-adds of `L_p`'s columns with broadcast entries
    /// of `y_j[c]` (broadcast once per column of `L`). Backward:
    /// `acc[c] -= L_pᵀ y_r[c]` as three fused multiply-adds of `L_p`'s rows
    /// (gathered once per block) with broadcast entries of `y_r[c]`; the `K`
    /// accumulators stay in registers over the column.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn sweeps_many_avx2<const K: usize, const FWD: bool, const BWD: bool>(
        &self,
        y: &mut [[Vec3; K]],
    ) {
        use std::arch::x86_64::*;
        let s = &*self.symbolic;
        let mut b = [[_mm256_setzero_pd(); 3]; K];
        let mut b1 = [[_mm256_setzero_pd(); 3]; K];
        let solve_node = |y: &mut [[Vec3; K]], j: usize, b: &mut [[__m256d; 3]; K]| {
            let mut yj = y[j];
            for v in &mut yj {
                *v = unit_lower_solve(&self.ldiag[j], v);
            }
            y[j] = yj;
            for c in 0..K {
                for k in 0..3 {
                    b[c][k] = _mm256_set1_pd(yj[c][k]);
                }
            }
        };
        let mut j = 0;
        while j < if FWD { s.n } else { 0 } {
            solve_node(y, j, &mut b);
            let range = s.col_ptr[j]..s.col_ptr[j + 1];
            if s.joins_next[j] {
                // Two columns of a supernode (see `forward_avx2`): each
                // shared row read and written once for both.
                let lc = x86::columns(&self.l[range.start]);
                let yr = &mut y[j + 1];
                for c in 0..K {
                    let mut acc = x86::load3(&yr[c]);
                    for k in 0..3 {
                        acc = _mm256_fnmadd_pd(lc[k], b[c][k], acc);
                    }
                    x86::store3(&mut yr[c], acc);
                }
                solve_node(y, j + 1, &mut b1);
                let range1 = s.col_ptr[j + 1]..s.col_ptr[j + 2];
                let pairs = self.l[range.start + 1..range.end]
                    .iter()
                    .zip(&self.l[range1.clone()]);
                for ((la, lb), &r) in pairs.zip(&s.row_idx[range1]) {
                    let (la, lb) = (x86::columns(la), x86::columns(lb));
                    let yr = &mut y[r];
                    for c in 0..K {
                        let mut acc = x86::load3(&yr[c]);
                        for k in 0..3 {
                            acc = _mm256_fnmadd_pd(la[k], b[c][k], acc);
                        }
                        for k in 0..3 {
                            acc = _mm256_fnmadd_pd(lb[k], b1[c][k], acc);
                        }
                        x86::store3(&mut yr[c], acc);
                    }
                }
                j += 2;
                continue;
            }
            for (lp, &r) in self.l[range.clone()].iter().zip(&s.row_idx[range]) {
                let lc = x86::columns(lp);
                let yr = &mut y[r];
                for c in 0..K {
                    let mut acc = x86::load3(&yr[c]);
                    for k in 0..3 {
                        acc = _mm256_fnmadd_pd(lc[k], b[c][k], acc);
                    }
                    x86::store3(&mut yr[c], acc);
                }
            }
            j += 1;
        }
        if FWD && BWD {
            for (yk, d) in y.iter_mut().zip(&self.d) {
                for v in yk.iter_mut() {
                    *v = v.component_div(d);
                }
            }
        }
        if !BWD {
            return;
        }
        for j in (0..s.n).rev() {
            let mut acc = [_mm256_setzero_pd(); K];
            for c in 0..K {
                acc[c] = x86::load3(&y[j][c]);
            }
            let range = s.col_ptr[j]..s.col_ptr[j + 1];
            for (lp, &r) in self.l[range.clone()].iter().zip(&s.row_idx[range]) {
                let rows = [
                    _mm256_set_pd(0.0, lp[(0, 2)], lp[(0, 1)], lp[(0, 0)]),
                    _mm256_set_pd(0.0, lp[(1, 2)], lp[(1, 1)], lp[(1, 0)]),
                    _mm256_set_pd(0.0, lp[(2, 2)], lp[(2, 1)], lp[(2, 0)]),
                ];
                let yr = &y[r];
                for c in 0..K {
                    for k in 0..3 {
                        acc[c] = _mm256_fnmadd_pd(rows[k], _mm256_set1_pd(yr[c][k]), acc[c]);
                    }
                }
            }
            let mut out = [Vec3::zeros(); K];
            for c in 0..K {
                x86::store3(&mut out[c], acc[c]);
                out[c] = unit_lower_t_solve(&self.ldiag[j], &out[c]);
            }
            y[j] = out;
        }
    }

    /// The portable kernel of [`Self::sweeps_many_with`].
    #[inline(always)]
    fn sweeps_many<const K: usize, const FWD: bool, const BWD: bool>(&self, y: &mut [[Vec3; K]]) {
        let s = &*self.symbolic;
        for j in 0..if FWD { s.n } else { 0 } {
            let mut yj = y[j];
            for v in &mut yj {
                *v = unit_lower_solve(&self.ldiag[j], v);
            }
            y[j] = yj;
            for p in s.col_ptr[j]..s.col_ptr[j + 1] {
                let l = &self.l[p];
                let yr = &mut y[s.row_idx[p]];
                for c in 0..K {
                    yr[c] -= l * yj[c];
                }
            }
        }
        if FWD && BWD {
            for (yk, d) in y.iter_mut().zip(&self.d) {
                for v in yk.iter_mut() {
                    *v = v.component_div(d);
                }
            }
        }
        if !BWD {
            return;
        }
        for j in (0..s.n).rev() {
            let mut acc = y[j];
            for p in s.col_ptr[j]..s.col_ptr[j + 1] {
                let lt = self.l[p].transpose();
                let yr = &y[s.row_idx[p]];
                for c in 0..K {
                    acc[c] -= lt * yr[c];
                }
            }
            for v in &mut acc {
                *v = unit_lower_t_solve(&self.ldiag[j], v);
            }
            y[j] = acc;
        }
    }

    /// Reach-restricted forward solve of the three unit columns of (original) node
    /// `node`: `Z = L⁻¹ E_node`. Nonzero rows lie on the elimination-tree path of
    /// `iperm[node]` to its root; they are appended to `path` (permuted node ids,
    /// ascending) and `blocks` (3×3, column `c` is the solution for unit vector `c`).
    /// `work` is dense scratch of length `n`, zero on entry and on exit.
    pub fn node_forward_solve(
        &self,
        node: usize,
        work: &mut [Mat3],
        path: &mut Vec<usize>,
        blocks: &mut Vec<Mat3>,
    ) {
        let s = &*self.symbolic;
        let mut j = s.iperm[node];
        work[j] = Mat3::identity();
        while j != NONE {
            let zj = unit_lower_solve_mat(&self.ldiag[j], &work[j]);
            work[j] = Mat3::zeros();
            let (cols, rows) = (
                &self.l[s.col_ptr[j]..s.col_ptr[j + 1]],
                &s.row_idx[s.col_ptr[j]..s.col_ptr[j + 1]],
            );
            sub_products_any(cols, rows, &zj, work);
            path.push(j);
            blocks.push(zj);
            j = s.parent[j];
        }
    }
}

/// Node columns solved together by [`LdltFactor::nodes_forward_solve`].
pub(crate) const BATCH: usize = 8;

/// One node's rows in [`LdltFactor::nodes_forward_solve`]: row `i` holds
/// entry `i` of the three unit columns of each of the [`BATCH`] nodes, node
/// `b`'s column `c` at `3 b + c`.
pub(crate) type BatchRows = [[f64; 3 * BATCH]; 3];

impl LdltFactor {
    /// [`Self::node_forward_solve`] of up to [`BATCH`] nodes at once, to
    /// the bit the same: each node's path and blocks are appended in the
    /// order of `nodes`, as that function would one node after the other.
    /// Each block of `L` on the union of the nodes' paths is read once and
    /// applied to all of them, in vector lanes across their columns (where
    /// a node's path does not pass, its lanes are zero and stay zero).
    /// Cheaper than one node at a time when the paths share most of their
    /// blocks (nodes near each other in the elimination tree). `work`
    /// (length `n`) must be zero on entry and is on exit. Returns each
    /// node's path length (its blocks' count). Needs AVX2/FMA (the caller
    /// checks; `is_x86_feature_detected!`); not for other CPUs, whose
    /// one-node path does not fuse its products.
    ///
    /// # Panics
    /// With more than [`BATCH`] nodes, a node out of range, or without
    /// AVX2/FMA.
    pub(crate) fn nodes_forward_solve(
        &self,
        nodes: &[usize],
        work: &mut [BatchRows],
        path: &mut Vec<usize>,
        blocks: &mut Vec<Mat3>,
    ) -> [usize; BATCH] {
        assert!(nodes.len() <= BATCH, "at most {BATCH} nodes");
        assert!(has_avx2_fma(), "the batched node solve needs AVX2/FMA");
        let s = &*self.symbolic;
        assert!(work.len() >= s.n, "work: one entry per node");
        // Each node's path, and a cursor along it (its next block to write).
        let base = path.len();
        let mut cursor = [(0usize, 0usize); BATCH];
        for (b, &node) in nodes.iter().enumerate() {
            let start = path.len();
            let mut j = s.iperm[node];
            work[j][0][3 * b] = 1.0;
            work[j][1][3 * b + 1] = 1.0;
            work[j][2][3 * b + 2] = 1.0;
            while j != NONE {
                path.push(j);
                j = s.parent[j];
            }
            cursor[b] = (start, path.len());
        }
        let first = blocks.len();
        blocks.resize(first + path.len() - base, Mat3::zeros());
        #[cfg(target_arch = "x86_64")]
        {
            let (count, out) = (nodes.len(), &mut blocks[first..]);
            if std::arch::is_x86_feature_detected!("avx512f") {
                // SAFETY: the CPU supports the features the function is compiled for.
                unsafe { self.batch_sweep_avx512(count, &mut cursor, work, path, base, out) };
            } else {
                // SAFETY: as above (checked by the assertion).
                unsafe { self.batch_sweep_avx2(count, &mut cursor, work, path, base, out) };
            }
        }
        let mut lens = [0; BATCH];
        for (b, len) in lens.iter_mut().enumerate().take(nodes.len()) {
            *len = cursor[b].1 - if b == 0 { base } else { cursor[b - 1].1 };
        }
        lens
    }

    /// [`Self::batch_sweep`] in AVX-512 lanes (three registers a row).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx2,fma")]
    fn batch_sweep_avx512(
        &self,
        count: usize,
        cursor: &mut [(usize, usize); BATCH],
        work: &mut [BatchRows],
        path: &[usize],
        base: usize,
        blocks: &mut [Mat3],
    ) {
        self.batch_sweep(count, cursor, work, path, base, blocks);
    }

    /// [`Self::batch_sweep`] in AVX2 lanes.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn batch_sweep_avx2(
        &self,
        count: usize,
        cursor: &mut [(usize, usize); BATCH],
        work: &mut [BatchRows],
        path: &[usize],
        base: usize,
        blocks: &mut [Mat3],
    ) {
        self.batch_sweep(count, cursor, work, path, base, blocks);
    }

    /// The sweep of [`Self::nodes_forward_solve`] over the union of the
    /// paths, in ascending order (each path ascends, so the next node is the
    /// smallest of the cursors'). The arithmetic of each entry is that of
    /// [`unit_lower_solve_mat`] and [`sub_products_avx2`]: unfused in the
    /// diagonal block, one fused multiply-add per product after.
    #[inline(always)]
    fn batch_sweep(
        &self,
        count: usize,
        cursor: &mut [(usize, usize); BATCH],
        work: &mut [BatchRows],
        path: &[usize],
        base: usize,
        blocks: &mut [Mat3],
    ) {
        const W: usize = 3 * BATCH;
        let s = &*self.symbolic;
        loop {
            let mut j = NONE;
            for &(c, end) in &cursor[..count] {
                if c < end {
                    j = j.min(path[c]);
                }
            }
            if j == NONE {
                break;
            }
            let l = &self.ldiag[j];
            let b = std::mem::replace(&mut work[j], [[0.0; W]; 3]);
            let mut z = [[0.0; W]; 3];
            for c in 0..W {
                let x0 = b[0][c];
                let x1 = b[1][c] - l[0] * x0;
                let x2 = b[2][c] - l[1] * x0 - l[2] * x1;
                z[0][c] = x0;
                z[1][c] = x1;
                z[2][c] = x2;
            }
            for (k, (c, end)) in cursor[..count].iter_mut().enumerate() {
                if *c < *end && path[*c] == j {
                    blocks[*c - base] = Mat3::from_fn(|r, q| z[r][3 * k + q]);
                    *c += 1;
                }
            }
            for p in s.col_ptr[j]..s.col_ptr[j + 1] {
                let lp = &self.l[p];
                let w = &mut work[s.row_idx[p]];
                for (i, row) in w.iter_mut().enumerate() {
                    let mut acc = *row;
                    for (k, zk) in z.iter().enumerate() {
                        let a = -lp[(i, k)];
                        for c in 0..W {
                            acc[c] = a.mul_add(zk[c], acc[c]);
                        }
                    }
                    *row = acc;
                }
            }
        }
    }
}

/// `work[rows[i]] -= l[i] · z` for every block of one column of `L` (the inner
/// loop of the factorization and of the node column solves), with the
/// AVX-512 or AVX2/FMA kernel where the CPU has it.
fn sub_products_any(l: &[Mat3], rows: &[usize], z: &Mat3, work: &mut [Mat3]) {
    #[cfg(target_arch = "x86_64")]
    if has_avx2_fma() && std::arch::is_x86_feature_detected!("avx512f") {
        // SAFETY: the CPU supports the features the function is compiled for.
        return unsafe { sub_products_avx512(l, rows, z, work) };
    }
    #[cfg(target_arch = "x86_64")]
    if has_avx2_fma() {
        // SAFETY: the CPU supports the features the function is compiled for.
        return unsafe { sub_products_avx2(l, rows, z, work) };
    }
    sub_products(l, rows, z, work);
}

/// `work[rows[i]] -= l[i] · z` for every block of one column of `L`.
fn sub_products(l: &[Mat3], rows: &[usize], z: &Mat3, work: &mut [Mat3]) {
    for (li, &r) in l.iter().zip(rows) {
        work[r] -= li * z;
    }
}

/// [`sub_products`] with AVX2 and FMA: each column of `l[i] · z` is three fused
/// multiply-adds of `l[i]`'s columns (four lanes, the fourth zeroed) with
/// broadcast entries of `z`, subtracted from the matching column of `work[r]`
/// in place. The first two columns are read and written as four lanes (the
/// fourth is the next column's first entry, which the next store overwrites);
/// the last is read and written as two lanes plus one, never past the block.
/// Masked stores are avoided: they are slow on some CPUs.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn sub_products_avx2(l: &[Mat3], rows: &[usize], z: &Mat3, work: &mut [Mat3]) {
    use std::arch::x86_64::*;
    // zb[k][c] = Z[k, c] in every lane (no closures: they would not inherit
    // the target features).
    let mut zb = [[_mm256_setzero_pd(); 3]; 3];
    for k in 0..3 {
        for c in 0..3 {
            zb[k][c] = _mm256_set1_pd(z[(k, c)]);
        }
    }
    for (li, &r) in l.iter().zip(rows) {
        let lc = x86::columns(li);
        let w = &mut work[r];
        let wp = w.as_mut_slice().as_mut_ptr();
        // SAFETY: every access stays inside the nine entries of `w` (offsets
        // 0..4, 3..7, and 6..9 through `load3`/`store3`).
        unsafe {
            // All loads before any store: a load overlapping a store just made
            // stalls store forwarding.
            let mut acc = [
                _mm256_loadu_pd(wp),
                _mm256_loadu_pd(wp.add(3)),
                x86::load3_ptr(wp.add(6)),
            ];
            for c in 0..3 {
                for k in 0..3 {
                    acc[c] = _mm256_fnmadd_pd(lc[k], zb[k][c], acc[c]);
                }
            }
            // In this order each store's fourth lane (an old value) is
            // overwritten by the next one.
            _mm256_storeu_pd(wp, acc[0]);
            _mm256_storeu_pd(wp.add(3), acc[1]);
            x86::store3_ptr(wp.add(6), acc[2]);
        }
    }
}

/// [`sub_products`] with AVX-512: the first eight entries of a block
/// (column-major, lane `j` row `j % 3` and column `j / 3`) in one register,
/// three fused multiply-adds of `l[i]`'s column `k` spread over the lanes'
/// rows (one two-source permute of the block's nine entries) with `z`'s row
/// `k` spread over their columns; the ninth entry by three scalar fused
/// multiply-adds. Three multiply-adds of eight lanes where
/// [`sub_products_avx2`] takes nine of four lanes, in the same order for
/// every entry: the results are the same to the bit.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2,fma")]
fn sub_products_avx512(l: &[Mat3], rows: &[usize], z: &Mat3, work: &mut [Mat3]) {
    use std::arch::x86_64::*;
    let zv: [__m512d; 3] = std::array::from_fn(|k| {
        let (a, b, c) = (z[(k, 0)], z[(k, 1)], z[(k, 2)]);
        _mm512_setr_pd(a, a, a, b, b, b, c, c)
    });
    // Entry `3k + j % 3` of the block; 8 is the second source, the ninth.
    let idx = [
        _mm512_setr_epi64(0, 1, 2, 0, 1, 2, 0, 1),
        _mm512_setr_epi64(3, 4, 5, 3, 4, 5, 3, 4),
        _mm512_setr_epi64(6, 7, 8, 6, 7, 8, 6, 7),
    ];
    let z2 = [z[(0, 2)], z[(1, 2)], z[(2, 2)]];
    for (li, &r) in l.iter().zip(rows) {
        let lp = li.as_slice().as_ptr();
        let wp = work[r].as_mut_slice().as_mut_ptr();
        // SAFETY: eight of the nine entries of `l[i]` and of `work[r]` as
        // one register, the ninth alone.
        unsafe {
            let a = _mm512_loadu_pd(lp);
            let b = _mm512_set1_pd(*lp.add(8));
            let mut acc = _mm512_loadu_pd(wp);
            for k in 0..3 {
                acc = _mm512_fnmadd_pd(_mm512_permutex2var_pd(a, idx[k], b), zv[k], acc);
            }
            _mm512_storeu_pd(wp, acc);
            let mut w8 = *wp.add(8);
            for (k, zk) in z2.iter().enumerate() {
                w8 = (-*lp.add(3 * k + 2)).mul_add(*zk, w8);
            }
            *wp.add(8) = w8;
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::math::{dot, max_abs};

    /// Arbitrary but reproducible values.
    fn val(i: usize) -> f64 {
        ((i as f64) * 0.618).sin() * 0.3
    }

    /// A symmetric positive definite matrix on a box mesh's pattern:
    /// arbitrary off-diagonal blocks, diagonal blocks that dominate them.
    fn spd_matrix(cells: [usize; 3]) -> (BlockPattern, crate::fem::assembly::BlockCsr) {
        let mesh = crate::mesh::generate::box_mesh(Vec3::zeros(), Vec3::new(1.0, 1.0, 2.0), cells)
            .unwrap();
        let pattern = BlockPattern::new(mesh.num_vertices(), mesh.tets());
        let mut a = crate::fem::assembly::BlockCsr::zeros(Arc::new(pattern.clone()));
        for r in 0..pattern.n {
            for s in pattern.row_ptr[r]..pattern.row_ptr[r + 1] {
                let c = pattern.col_idx[s];
                if c < r {
                    let b = Mat3::from_fn(|i, j| val(9 * (r * 31 + c) + 3 * j + i));
                    a.values[s] = b;
                    a.values[pattern.slot(c, r).unwrap()] = b.transpose();
                }
            }
        }
        for r in 0..pattern.n {
            let off: f64 = (pattern.row_ptr[r]..pattern.row_ptr[r + 1])
                .filter(|&s| pattern.col_idx[s] != r)
                .map(|s| a.values[s].abs().sum())
                .sum();
            let m = Mat3::from_fn(|i, j| val(r * 13 + i + j));
            a.values[pattern.diag[r]] = (m + m.transpose()) * 0.1 + Mat3::identity() * (off + 1.0);
        }
        (pattern, a)
    }

    /// The supernodal kernel (faer's factorization, gathered) gives the blocked
    /// kernel's factor in its layout, and reports a matrix that is not
    /// positive definite as the blocked one does.
    #[test]
    fn supernodal_factor_matches_the_blocked_one() {
        let (pattern, mut a) = spd_matrix([3, 4, 6]);
        let blocked = Arc::new(
            LdltSymbolic::with_kernel(&pattern, Ordering::Auto, FactorKernel::Blocked).unwrap(),
        );
        let supernodal = Arc::new(
            LdltSymbolic::with_kernel(&pattern, Ordering::Auto, FactorKernel::Supernodal).unwrap(),
        );
        assert_eq!(blocked.kernel(), FactorKernel::Blocked);
        assert_eq!(supernodal.kernel(), FactorKernel::Supernodal);
        let (mut fb, mut fs) = (blocked.alloc_factor(), supernodal.alloc_factor());
        let mut work = Vec::new();
        for round in 0..2 {
            blocked.factorize(&a, &mut fb, &mut work).unwrap();
            supernodal.factorize(&a, &mut fs, &mut work).unwrap();
            let scale = fb.l.iter().map(|b| b.abs().max()).fold(1.0, f64::max);
            for (p, (x, y)) in fb.l.iter().zip(&fs.l).enumerate() {
                assert!(
                    (x - y).abs().max() <= 1e-12 * scale,
                    "round {round}, block {p}: {x} vs {y}"
                );
            }
            for (x, y) in fb.ldiag.iter().zip(&fs.ldiag) {
                for (u, v) in x.iter().zip(y) {
                    assert!((u - v).abs() <= 1e-12 * (1.0 + u.abs()), "{x:?} vs {y:?}");
                }
            }
            for (x, y) in fb.d.iter().zip(&fs.d) {
                assert!((x - y).norm() <= 1e-12 * x.norm(), "{x} vs {y}");
            }
            // The factor solves A: the comparison is not of two wrong ones.
            let b: Vec<Vec3> = (0..a.n()).map(|i| Vec3::new(1.0, val(i), -0.5)).collect();
            let (mut x, mut tmp, mut ax) = (b.clone(), b.clone(), b.clone());
            fs.solve(&b, &mut x, &mut tmp);
            a.mul_vec(&x, &mut ax);
            let r: f64 = ax.iter().zip(&b).map(|(p, q)| (p - q).norm_squared()).sum();
            let n2: f64 = b.iter().map(|q| q.norm_squared()).sum();
            assert!((r / n2).sqrt() < 1e-12, "residual {:e}", (r / n2).sqrt());
            // New values into the same factors.
            for v in a.values.iter_mut() {
                *v *= 1.5;
            }
        }
        // Not positive definite: both kernels say so, at a node of the mesh.
        let r = pattern.n / 2;
        a.values[pattern.diag[r]] = -a.values[pattern.diag[r]];
        for sym in [&blocked, &supernodal] {
            let mut f = sym.alloc_factor();
            match sym.factorize(&a, &mut f, &mut work) {
                Err(SoftTissueError::NotPositiveDefinite { node, .. }) => assert!(node < pattern.n),
                other => panic!("{:?}: {other:?}", sym.kernel()),
            }
        }
    }

    /// `FactorKernel::Auto` factorizes supernodally from
    /// `SUPERNODAL_MIN_BLOCKS` blocks of `L` on, and with the blocked kernel
    /// below.
    #[test]
    fn auto_kernel_follows_the_size_of_l() {
        for cells in [[3, 3, 3], [12, 12, 16]] {
            let mesh =
                crate::mesh::generate::box_mesh(Vec3::zeros(), Vec3::new(1.0, 1.0, 1.0), cells)
                    .unwrap();
            let pattern = BlockPattern::new(mesh.num_vertices(), mesh.tets());
            let sym = LdltSymbolic::new(&pattern).unwrap();
            let large = sym.nnz_blocks() >= SUPERNODAL_MIN_BLOCKS;
            assert_eq!(large, cells[0] > 3, "{} blocks", sym.nnz_blocks());
            let want = if large {
                FactorKernel::Supernodal
            } else {
                FactorKernel::Blocked
            };
            assert_eq!(sym.kernel(), want, "{} blocks", sym.nnz_blocks());
        }
    }

    /// A factor of a box mesh's pattern with arbitrary blocks and pivots.
    pub(crate) fn arbitrary_factor(cells: [usize; 3]) -> (Arc<LdltSymbolic>, LdltFactor) {
        let mesh = crate::mesh::generate::box_mesh(Vec3::zeros(), Vec3::new(1.0, 1.0, 2.0), cells)
            .unwrap();
        let pattern = BlockPattern::new(mesh.num_vertices(), mesh.tets());
        let sym = Arc::new(LdltSymbolic::new(&pattern).unwrap());
        let mut f = sym.alloc_factor();
        for (p, b) in f.l.iter_mut().enumerate() {
            *b = Mat3::from_fn(|r, c| val(9 * p + 3 * c + r));
        }
        for (k, d) in f.ldiag.iter_mut().enumerate() {
            *d = [val(7 * k), val(7 * k + 1), val(7 * k + 2)];
        }
        for (k, d) in f.d.iter_mut().enumerate() {
            *d = Vec3::new(1.0 + val(5 * k).abs(), 2.0, 0.5 + val(5 * k + 1).abs());
        }
        (sym, f)
    }

    /// The batched node columns are those of one node at a time to the bit
    /// (where the CPU has AVX2/FMA: elsewhere the batch is not used): up to
    /// [`BATCH`] nodes, near each other in the tree or not, in any order, each
    /// path and its blocks appended in the order of the nodes; `work` is zero
    /// again after.
    #[test]
    fn batched_node_columns_are_the_single_ones() {
        if !has_avx2_fma() {
            eprintln!("SKIPPED: no AVX2/FMA, the batched node solve is not used");
            return;
        }
        let (sym, f) = arbitrary_factor([3, 3, 6]);
        let n = sym.n;
        let mut single = vec![Mat3::zeros(); n];
        let mut work = vec![[[0.0; 3 * BATCH]; 3]; n];
        let spread: Vec<usize> = (0..BATCH).map(|i| (i * 37 + 5) % n).collect();
        let near: Vec<usize> = (0..BATCH).map(|i| sym.perm[i]).collect();
        let sets: [&[usize]; 5] = [&spread, &near, &near[..3], &[n - 1], &[]];
        for nodes in sets {
            let (mut path, mut blocks) = (vec![7], vec![Mat3::identity()]);
            let lens = f.nodes_forward_solve(nodes, &mut work, &mut path, &mut blocks);
            let (mut p1, mut b1) = (vec![7], vec![Mat3::identity()]);
            for &k in nodes {
                f.node_forward_solve(k, &mut single, &mut p1, &mut b1);
            }
            assert_eq!(path, p1, "paths of {nodes:?}");
            assert_eq!(blocks.len(), b1.len());
            for (t, (a, b)) in blocks.iter().zip(&b1).enumerate() {
                assert!(
                    a.iter()
                        .zip(b.iter())
                        .all(|(x, y)| x.to_bits() == y.to_bits()),
                    "block {t} of {nodes:?}: {a} against {b}"
                );
            }
            let mut total = 1;
            for (b, &k) in nodes.iter().enumerate() {
                let mut len = 0;
                let mut j = sym.iperm[k];
                while j != NONE {
                    len += 1;
                    j = sym.parent[j];
                }
                assert_eq!(lens[b], len, "path length of node {k}");
                total += len;
            }
            assert_eq!(total, path.len());
            assert!(lens[nodes.len()..].iter().all(|&l| l == 0));
            assert!(
                work.iter().flatten().flatten().all(|&x| x == 0.0),
                "work left dirty"
            );
        }
        let nine: Vec<usize> = (0..=BATCH).collect();
        let caught = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            f.nodes_forward_solve(&nine, &mut work, &mut Vec::new(), &mut Vec::new())
        }));
        assert!(caught.is_err(), "more than BATCH nodes must be refused");
    }

    /// The AVX2/FMA forward and backward solves (where the CPU has them) match
    /// the portable ones on a factor with arbitrary blocks.
    #[test]
    fn solve_kernels_agree() {
        let (sym, f) = arbitrary_factor([2, 2, 4]);
        // Both kinds of column are swept: those taken with the next one
        // (a supernode's) and those taken alone.
        let joined = sym.joined_columns();
        assert!(joined > 0 && 2 * joined < sym.n, "{joined} of {}", sym.n);
        // ... the root's column among them (the pair whose second column
        // has no rows), and three in a row (the backward sweep's triples).
        assert!(sym.joins_next[sym.n - 2]);
        assert!(sym.joins_next.windows(2).any(|w| w[0] && w[1]));
        let y0: Vec<Vec3> = (0..sym.n)
            .map(|i| Vec3::new(val(3 * i + 1000), val(3 * i + 1001), val(3 * i + 1002)))
            .collect();
        let (mut fp, mut bp) = (y0.clone(), y0.clone());
        f.forward_portable::<false>(&mut fp);
        f.backward_portable::<false>(&mut bp);
        let (mut ff, mut bf) = (y0.clone(), y0.clone());
        f.forward(&mut ff);
        f.backward(&mut bf);
        for (a, b) in fp.iter().zip(&ff).chain(bp.iter().zip(&bf)) {
            assert!((a - b).norm() <= 1e-12 * (1.0 + b.norm()), "{a} vs {b}");
        }
        // The solves did something.
        assert!(fp.iter().zip(&y0).any(|(a, b)| (a - b).norm() > 1e-3));
    }

    /// The single-precision solves: the AVX2/FMA kernels (where the CPU has
    /// them) match the portable ones on the same rounded blocks; the solve
    /// differs from the double-precision one by `f32` round-off only; a new
    /// factorization or a value too large for `f32` drops the copy, and the
    /// solve is then the double-precision one.
    #[test]
    fn single_precision_solves() {
        let (sym, mut f) = arbitrary_factor([2, 2, 4]);
        let n = sym.n;
        let y0: Vec<Vec3> = (0..n)
            .map(|i| Vec3::new(val(3 * i + 1000), val(3 * i + 1001), val(3 * i + 1002)))
            .collect();
        assert!(!f.has_single() && f.l_single().is_none());
        assert!(f.round_to_single());
        assert!(f.has_single());
        let l32 = f.l_single().unwrap();
        assert_eq!(l32.len(), 9 * f.l.len());
        for (p, b) in f.l.iter().enumerate() {
            for (i, &v) in b.as_slice().iter().enumerate() {
                assert_eq!(l32[9 * p + i], v as f32);
            }
        }
        for forward in [true, false] {
            let (mut portable, mut fast, mut double) = (y0.clone(), y0.clone(), y0.clone());
            if forward {
                f.forward_portable::<true>(&mut portable);
                f.forward_with::<true>(&mut fast);
                f.forward(&mut double);
            } else {
                f.backward_portable::<true>(&mut portable);
                f.backward_with::<true>(&mut fast);
                f.backward(&mut double);
            }
            let scale = double.iter().map(|v| v.norm()).fold(1.0, f64::max);
            for (a, b) in portable.iter().zip(&fast) {
                assert!((a - b).norm() <= 1e-12 * (1.0 + b.norm()), "{a} vs {b}");
            }
            // f32 keeps 24 bits: each block is within 2⁻²⁴ of its f64 value,
            // and the sweeps add up at most `n` such terms per entry.
            let worst = fast
                .iter()
                .zip(&double)
                .map(|(a, b)| (a - b).norm())
                .fold(0.0, f64::max);
            assert!(worst <= n as f64 * 2f64.powi(-24) * scale, "{worst:e}");
            // ... and rounding did happen: the kernels read the f32 copy.
            assert!(worst > 0.0);
        }
        let (mut b32, mut b64) = (y0.clone(), y0.clone());
        f.backward_single(&mut b32);
        f.backward_with::<true>(&mut b64);
        assert_eq!(b32, b64);
        let (mut x, mut xs, mut tmp) = (y0.clone(), y0.clone(), y0.clone());
        f.solve(&y0, &mut x, &mut tmp);
        f.solve_single(&y0, &mut xs, &mut tmp);
        assert!(x != xs);
        // Too large for f32: no copy, and the double-precision solve.
        f.l[3][(1, 2)] = 1e39;
        assert!(!f.round_to_single());
        assert!(!f.has_single());
        f.solve(&y0, &mut x, &mut tmp);
        f.solve_single(&y0, &mut xs, &mut tmp);
        assert_eq!(x, xs);
        let (mut b32, mut b64) = (y0.clone(), y0.clone());
        f.backward_single(&mut b32);
        f.backward(&mut b64);
        assert_eq!(b32, b64);
        // Not a number, or infinite: no copy either.
        for bad in [f64::NAN, f64::INFINITY, f64::NEG_INFINITY, -1e39] {
            f.l[3][(1, 2)] = 0.25;
            assert!(f.round_to_single());
            f.l[3][(1, 2)] = bad;
            assert!(!f.round_to_single() && !f.has_single(), "{bad}");
        }
        // Below f32's smallest normal number: zero. Largest: kept.
        f.l[3][(1, 2)] = 1e-39;
        f.l[4][(0, 0)] = -f64::from(f32::MAX);
        assert!(f.round_to_single());
        let l32 = f.l_single().unwrap();
        assert_eq!(l32[9 * 3 + 3 * 2 + 1], 0.0);
        assert_eq!(l32[9 * 4], -f32::MAX);
        // Copying values drops the copy too.
        f.l[3][(1, 2)] = 0.25;
        assert!(f.round_to_single());
        let other = f.clone();
        f.copy_values_from(&other);
        assert!(!f.has_single());
    }

    /// Whether the half-precision copy can be made here; says so when not.
    fn half_supported() -> bool {
        let ok = super::super::half::supported();
        if !ok {
            eprintln!("SKIPPED: no AVX2/FMA/F16C, the half-precision copy is not made");
        }
        ok
    }

    /// `max_i (|L| |D| |Lᵀ| 1)_i`, the ∞-norm of `|L| |D| |Lᵀ|` (unit
    /// diagonal blocks included), which bounds what rounding `L` moves
    /// `L D Lᵀ` by.
    fn abs_product_norm(f: &LdltFactor) -> f64 {
        let s = &*f.symbolic;
        let unit = |l: &[f64; 3]| {
            Mat3::new(
                1.0,
                0.0,
                0.0,
                l[0].abs(),
                1.0,
                0.0,
                l[1].abs(),
                l[2].abs(),
                1.0,
            )
        };
        let ones = Vec3::repeat(1.0);
        let mut w: Vec<Vec3> = (0..s.n)
            .map(|j| unit(&f.ldiag[j]).transpose() * ones)
            .collect();
        for j in 0..s.n {
            for p in s.col_ptr[j]..s.col_ptr[j + 1] {
                w[j] += f.l[p].abs().transpose() * ones;
            }
        }
        let v: Vec<Vec3> = w
            .iter()
            .zip(&f.d)
            .map(|(w, d)| w.component_mul(&d.abs()))
            .collect();
        let mut u: Vec<Vec3> = (0..s.n).map(|j| unit(&f.ldiag[j]) * v[j]).collect();
        for j in 0..s.n {
            for p in s.col_ptr[j]..s.col_ptr[j + 1] {
                u[s.row_idx[p]] += f.l[p].abs() * v[j];
            }
        }
        u.iter().map(|x| x.max()).fold(0.0, f64::max)
    }

    /// The half-precision solve of a real factor (an SPD matrix's, several
    /// supernode shapes): its residual against the matrix is within what
    /// rounding `L` to binary16 and the arithmetic to `f32` can leave (the
    /// first-order bound `(2·2⁻¹¹ + 4n·2⁻²⁴) ‖|L||D||Lᵀ|‖ ‖x‖`), it is not
    /// the single-precision solve (the copy is binary16), it is symmetric and
    /// positive as a preconditioner must be, and it scales exactly with the
    /// right-hand side (powers of two, far outside `f32`'s range).
    #[test]
    fn half_precision_solve() {
        if !half_supported() {
            return;
        }
        let (pattern, a) = spd_matrix([3, 3, 5]);
        let sym = Arc::new(LdltSymbolic::new(&pattern).unwrap());
        let n = sym.n;
        assert!(sym.joined_columns() > 0);
        let mut f = sym.alloc_factor();
        sym.factorize(&a, &mut f, &mut Vec::new()).unwrap();
        assert!(!f.has_half());
        assert!(f.round_to_single());
        assert!(f.round_to_half());
        assert!(f.has_half());
        let b: Vec<Vec3> = (0..n)
            .map(|i| Vec3::new(val(3 * i + 7), val(3 * i + 8) - 0.5, val(3 * i + 9) + 0.2))
            .collect();
        let (mut xh, mut xs, mut tmp) = (b.clone(), b.clone(), b.clone());
        let mut t32 = vec![[0.0f32; 4]; n];
        f.solve_half(&b, &mut xh, &mut tmp, &mut t32);
        f.solve_single(&b, &mut xs, &mut tmp);
        // `max |A x − b|`.
        let residual_of = |x: &[Vec3]| {
            let mut ax = vec![Vec3::zeros(); n];
            a.mul_vec(x, &mut ax);
            ax.iter()
                .zip(&b)
                .map(|(p, q)| (p - q).amax())
                .fold(0.0, f64::max)
        };
        let residual = residual_of(&xh);
        let bound = (2.0 * 2f64.powi(-11) + 4.0 * n as f64 * 2f64.powi(-24))
            * abs_product_norm(&f)
            * max_abs(&xh);
        assert!(residual <= bound, "residual {residual:e} above {bound:e}");
        // Binary16, not f32: the single-precision solve is 2¹³ times closer.
        let residual_single = residual_of(&xs);
        assert!(
            residual > 8.0 * residual_single,
            "{residual:e} vs {residual_single:e}"
        );
        // Rounded from the single-precision copy: the same halves.
        let mut g = f.clone();
        assert_eq!(g.round_to_single_and_half(), (true, true));
        let mut xg = b.clone();
        g.solve_half(&b, &mut xg, &mut tmp, &mut t32);
        assert_eq!(xg, xh);
        // Symmetric (the backward sweep reads the same rounded blocks as the
        // forward one) and positive.
        let u: Vec<Vec3> = (0..n)
            .map(|i| Vec3::new(val(5 * i + 1), -val(5 * i + 2), 0.3 - val(5 * i + 3)))
            .collect();
        let mut xu = b.clone();
        f.solve_half(&u, &mut xu, &mut tmp, &mut t32);
        let (ub, bu) = (dot(&u, &xh), dot(&b, &xu));
        let norm = |p: &[Vec3]| dot(p, p).sqrt();
        assert!(
            (ub - bu).abs() <= 8.0 * n as f64 * 2f64.powi(-24) * norm(&u) * norm(&xh),
            "{ub} vs {bu}"
        );
        assert!(dot(&b, &xh) > 0.0 && dot(&u, &xu) > 0.0);
        // The right-hand side is scaled before it meets f32: exact for powers
        // of two, whatever their size.
        for e in [-1000, -100, 100, 1000] {
            let s = 2f64.powi(e);
            let bs: Vec<Vec3> = b.iter().map(|v| v * s).collect();
            let mut x = b.clone();
            f.solve_half(&bs, &mut x, &mut tmp, &mut t32);
            for (p, q) in x.iter().zip(&xh) {
                assert_eq!(*p, q * s, "2^{e}");
            }
        }
        // A zero right-hand side gives zero; a non-finite one, not a number
        // (CG then stops, as with a solve in f64).
        let zero = vec![Vec3::zeros(); n];
        let mut x = b.clone();
        f.solve_half(&zero, &mut x, &mut tmp, &mut t32);
        assert!(x.iter().all(|v| *v == Vec3::zeros()));
        let mut bad = b.clone();
        bad[3].y = f64::INFINITY;
        f.solve_half(&bad, &mut x, &mut tmp, &mut t32);
        assert!(x.iter().all(|v| v.iter().all(|c| c.is_nan())));
    }

    /// The half-precision kernels against the double-precision solve on a
    /// factor whose values binary16 and `f32` hold exactly (multiples of
    /// 2⁻¹⁰ below 2, pivots powers of two): only the `f32` arithmetic
    /// differs, so the two agree to `f32` round-off, over pairs and triples
    /// of joined columns and lone ones.
    #[test]
    fn half_precision_kernels_match_the_double_solve() {
        if !half_supported() {
            return;
        }
        let (sym, mut f) = arbitrary_factor([2, 2, 4]);
        let n = sym.n;
        assert!(sym.joins_next.windows(2).any(|w| w[0] && w[1]));
        let exact = |v: f64| (v * 1024.0).round() / 1024.0;
        for b in &mut f.l {
            *b = b.map(|v| exact(v * 0.5));
        }
        for d in &mut f.ldiag {
            *d = d.map(exact);
        }
        for (k, d) in f.d.iter_mut().enumerate() {
            *d = Vec3::new(1.0, 2f64.powi((k % 5) as i32), 0.5);
        }
        assert!(f.round_to_half());
        let b: Vec<Vec3> = (0..n)
            .map(|i| Vec3::new(val(3 * i + 1000), val(3 * i + 1001), val(3 * i + 1002)))
            .collect();
        let (mut x, mut xh, mut tmp) = (b.clone(), b.clone(), b.clone());
        let mut t32 = vec![[0.0f32; 4]; n];
        f.solve(&b, &mut x, &mut tmp);
        f.solve_half(&b, &mut xh, &mut tmp, &mut t32);
        let scale = max_abs(&x).max(max_abs(&b));
        let worst = x
            .iter()
            .zip(&xh)
            .map(|(p, q)| (p - q).amax())
            .fold(0.0, f64::max);
        // The three sweeps add up at most `n` terms per entry, each rounded
        // to f32 (2⁻²⁴), from a right-hand side rounded to f32.
        assert!(
            worst <= 4.0 * n as f64 * 2f64.powi(-24) * scale,
            "{worst:e}"
        );
        assert!(worst > 0.0, "the solve ran in f32");
    }

    /// No half-precision copy where an entry does not fit (beyond binary16's
    /// 65 504 in `L`, a pivot that is not positive and finite, a diagonal
    /// block beyond `f32`): the solve is then the single-precision one. A new
    /// factorization or copied values drop the copy.
    #[test]
    fn half_precision_copy_refused_and_dropped() {
        if !half_supported() {
            return;
        }
        let (sym, mut f) = arbitrary_factor([2, 2, 3]);
        let n = sym.n;
        assert!(f.round_to_single());
        let b: Vec<Vec3> = (0..n)
            .map(|i| Vec3::new(val(i), 1.0, -val(2 * i)))
            .collect();
        let (mut xh, mut xs, mut tmp) = (b.clone(), b.clone(), b.clone());
        let mut t32 = vec![[0.0f32; 4]; n];
        f.l[2][(2, 1)] = 65504.0;
        assert!(f.round_to_half());
        type Edit = fn(&mut LdltFactor);
        let edits: [(&str, Edit); 7] = [
            ("L beyond binary16", |f| f.l[2][(2, 1)] = 65520.0),
            ("L not a number", |f| f.l[2][(2, 1)] = f64::NAN),
            ("L infinite", |f| f.l[2][(0, 0)] = f64::NEG_INFINITY),
            ("zero pivot", |f| f.d[1].y = 0.0),
            ("negative pivot", |f| f.d[4].z = -1.0),
            ("pivots beyond f32's range apart", |f| f.d[0].x = 1e-40),
            ("diagonal block beyond f32", |f| f.ldiag[3][1] = 1e39),
        ];
        for (what, edit) in edits {
            let mut g = f.clone();
            assert!(g.round_to_half(), "{what}: before");
            edit(&mut g);
            assert!(!g.round_to_half() && !g.has_half(), "{what}");
            assert!(!g.round_to_single_and_half().1 && !g.has_half(), "{what}");
            if g.round_to_single() {
                g.solve_half(&b, &mut xh, &mut tmp, &mut t32);
                g.solve_single(&b, &mut xs, &mut tmp);
                assert_eq!(xh, xs, "{what}");
            }
        }
        assert!(f.round_to_half());
        let other = f.clone();
        f.copy_values_from(&other);
        assert!(!f.has_half());
    }

    /// Factorizing drops the single- and half-precision copies of the
    /// previous values.
    #[test]
    fn factorizing_drops_the_single_copy() {
        let mesh =
            crate::mesh::generate::box_mesh(Vec3::zeros(), Vec3::new(1.0, 1.0, 1.0), [2, 2, 2])
                .unwrap();
        let pattern = BlockPattern::new(mesh.num_vertices(), mesh.tets());
        let sym = Arc::new(LdltSymbolic::new(&pattern).unwrap());
        let pattern = Arc::new(pattern);
        let mut a = crate::fem::assembly::BlockCsr::zeros(Arc::clone(&pattern));
        for i in 0..a.n() {
            a.values[pattern.diag[i]] = Mat3::identity() * 4.0;
        }
        let mut f = sym.alloc_factor();
        sym.factorize(&a, &mut f, &mut Vec::new()).unwrap();
        assert!(f.round_to_single());
        assert!(f.round_to_half() || !super::super::half::supported());
        sym.factorize(&a, &mut f, &mut Vec::new()).unwrap();
        assert!(!f.has_single());
        assert!(!f.has_half());
    }

    /// Solving several right-hand sides at once gives what solving each gives,
    /// and its forward and backward halves what the sweeps of each give.
    #[test]
    fn solve_many_matches_solve() {
        let (sym, f) = arbitrary_factor([2, 3, 4]);
        let n = sym.n;
        let b: Vec<[Vec3; 3]> = (0..n)
            .map(|i| {
                std::array::from_fn(|c| {
                    let o = 1000 + 9 * i + 3 * c;
                    Vec3::new(val(o), val(o + 1), val(o + 2))
                })
            })
            .collect();
        let mut x = vec![[Vec3::zeros(); 3]; n];
        let mut tmp = x.clone();
        f.solve_many(&b, &mut x, &mut tmp);
        // The portable sweeps (whichever kernel `solve_many` took).
        let mut portable = vec![[Vec3::zeros(); 3]; n];
        for k in 0..n {
            tmp[k] = b[sym.perm[k]];
        }
        f.sweeps_many::<3, true, true>(&mut tmp);
        for k in 0..n {
            portable[sym.perm[k]] = tmp[k];
        }
        // The forward half alone, both kernels.
        let mut fwd = vec![[Vec3::zeros(); 3]; n];
        f.forward_many(&b, &mut fwd);
        let mut fwd_portable = vec![[Vec3::zeros(); 3]; n];
        for k in 0..n {
            fwd_portable[k] = b[sym.perm[k]];
        }
        f.sweeps_many::<3, true, false>(&mut fwd_portable);
        let (mut one, mut scratch) = (vec![Vec3::zeros(); n], vec![Vec3::zeros(); n]);
        for c in 0..3 {
            let bc: Vec<Vec3> = b.iter().map(|r| r[c]).collect();
            f.solve(&bc, &mut one, &mut scratch);
            for i in 0..n {
                assert!((x[i][c] - one[i]).norm() <= 1e-12 * (1.0 + one[i].norm()));
                assert!((portable[i][c] - one[i]).norm() <= 1e-12 * (1.0 + one[i].norm()));
            }
            assert!(one.iter().zip(&bc).any(|(a, b)| (a - b).norm() > 1e-3));
            let mut y: Vec<Vec3> = (0..n).map(|k| bc[sym.perm[k]]).collect();
            f.forward(&mut y);
            for k in 0..n {
                assert!((fwd[k][c] - y[k]).norm() <= 1e-12 * (1.0 + y[k].norm()));
                assert!((fwd_portable[k][c] - y[k]).norm() <= 1e-12 * (1.0 + y[k].norm()));
            }
            assert!(y.iter().zip(&one).any(|(a, b)| (a - b).norm() > 1e-3));
            // The backward half alone (no `D`), both kernels, on the forward result.
            let mut bwd = fwd.clone();
            f.backward_many(&mut bwd);
            let mut bwd_portable = fwd.clone();
            f.sweeps_many::<3, false, true>(&mut bwd_portable);
            let mut yb = y.clone();
            f.backward(&mut yb);
            for k in 0..n {
                assert!((bwd[k][c] - yb[k]).norm() <= 1e-12 * (1.0 + yb[k].norm()));
                assert!((bwd_portable[k][c] - yb[k]).norm() <= 1e-12 * (1.0 + yb[k].norm()));
            }
            assert!(yb.iter().zip(&y).any(|(a, b)| (a - b).norm() > 1e-3));
        }
    }

    /// The AVX2/FMA block update (where the CPU has it) matches the portable one,
    /// and touches nothing but the rows it updates; the AVX-512 one (where the
    /// CPU has it) is the AVX2 one to the bit.
    #[test]
    fn block_update_kernels_agree() {
        let m = |seed: f64| Mat3::from_fn(|r, c| ((r * 3 + c) as f64 * 0.37 + seed).sin());
        let l: Vec<Mat3> = (0..5).map(|i| m(i as f64)).collect();
        let rows = [0usize, 2, 3, 5, 6];
        let z = m(9.0);
        let start: Vec<Mat3> = (0..7).map(|i| m(20.0 + i as f64)).collect();
        let mut portable = start.clone();
        sub_products(&l, &rows, &z, &mut portable);
        for (i, w) in portable.iter().enumerate() {
            let expect = match rows.iter().position(|&r| r == i) {
                Some(k) => start[i] - l[k] * z,
                None => start[i],
            };
            assert!((w - expect).abs().max() < 1e-14);
        }
        #[cfg(target_arch = "x86_64")]
        if has_avx2_fma() {
            let mut fast = start.clone();
            // SAFETY: the features were detected.
            unsafe { sub_products_avx2(&l, &rows, &z, &mut fast) };
            for (a, b) in fast.iter().zip(&portable) {
                assert!((a - b).abs().max() < 1e-14);
            }
            if std::arch::is_x86_feature_detected!("avx512f") {
                // The same operations per entry: the same bits.
                let mut wide = start.clone();
                // SAFETY: the features were detected.
                unsafe { sub_products_avx512(&l, &rows, &z, &mut wide) };
                assert_eq!(wide, fast);
            } else {
                eprintln!("SKIPPED: no AVX-512, its block update is not used");
            }
        }
    }
}
