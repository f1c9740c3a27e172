//! The supernodal numeric factorization: faer's `LDLᵀ` of the scalar
//! (`3n × 3n`) matrix in the node ordering of the symbolic analysis (`LdltSymbolic`),
//! gathered into its node-blocked layout.
//!
//! The scalar factor in an ordering that keeps each node's three unknowns
//! in order is the node-blocked factor entry for entry (an `LDLᵀ` factor is
//! unique, and faer's postordering of the elimination tree only relabels
//! it), so the blocked kernel and this one give the same `L` and `D` to
//! round-off (test `supernodal_factor_matches_the_blocked_one`). faer's dense
//! supernode kernels win once supernodes are large: about on par with the
//! blocked kernel at the cataract lens (66 000 blocks of `L`), 2.2× faster at
//! a million blocks (`cargo bench --bench step -- factorize`).
//!
//! Everything the factorization needs is sized here once: the scalar lower
//! triangle's structure and where each entry comes from in `A`, faer's
//! symbolic factor, the index of every entry of the blocked `L` in faer's
//! values, and the scratch size. A factorization then copies `A`'s values,
//! runs faer's numeric factorization and gathers, without allocating.

use std::mem::MaybeUninit;

use faer::dyn_stack::MemStack;
use faer::perm::PermRef;
use faer::sparse::linalg::SupernodalThreshold;
use faer::sparse::linalg::cholesky::{
    CholeskySymbolicParams, SymbolicCholesky, SymbolicCholeskyRaw, SymmetricOrdering,
    factorize_symbolic_cholesky,
};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::{Par, Side};

use crate::error::{Result, SoftTissueError};
use crate::fem::assembly::{BlockCsr, BlockPattern};
use crate::math::{Mat3, Vec3};

/// The analysis of `FactorKernel::Supernodal` (in `super::ldlt`) for one pattern
/// and ordering.
pub(super) struct SupernodalPlan {
    symbolic: SymbolicCholesky<usize>,
    /// Structure of `A`'s scalar lower triangle (original numbering).
    a_col_ptr: Vec<usize>,
    a_row_idx: Vec<usize>,
    /// For every entry of that triangle: `9 slot + 3 c + r`, entry `(r, c)` of
    /// `A`'s block at `slot`.
    a_src: Vec<usize>,
    /// For every block of `L` (in the blocked layout), its nine entries'
    /// indices in faer's values, column-major like [`Mat3`].
    gather_l: Vec<usize>,
    /// Per permuted node: `(1, 0)`, `(2, 0)`, `(2, 1)` of its unit diagonal
    /// block, then its three pivots.
    gather_diag: Vec<usize>,
    values_len: usize,
    scratch_bytes: usize,
}

impl std::fmt::Debug for SupernodalPlan {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SupernodalPlan")
            .field("scalar_unknowns", &(self.a_col_ptr.len() - 1))
            .field("values", &self.values_len)
            .field("scratch_bytes", &self.scratch_bytes)
            .finish()
    }
}

/// A factor's buffers for the supernodal kernel: `A`'s scalar lower triangle,
/// faer's values of `L` and `D`, and the scratch.
#[derive(Clone, Default)]
pub(super) struct SupernodalBuffers {
    a: Vec<f64>,
    l: Vec<f64>,
    stack: Vec<MaybeUninit<u8>>,
}

impl std::fmt::Debug for SupernodalBuffers {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SupernodalBuffers")
            .field("a", &self.a.len())
            .field("l", &self.l.len())
            .field("stack", &self.stack.len())
            .finish()
    }
}

/// The parts of a factor (`super::ldlt::LdltFactor`) the supernodal kernel
/// writes: its blocked `L`, unit diagonal blocks and pivots, and its buffers.
pub(super) struct FactorParts<'a> {
    pub(super) l: &'a mut [Mat3],
    pub(super) ldiag: &'a mut [[f64; 3]],
    pub(super) d: &'a mut [Vec3],
    pub(super) buf: &'a mut SupernodalBuffers,
}

/// Index of `L(row, col)` (faer's numbering, `row ≥ col`) in faer's values.
struct Locate<'a> {
    raw: &'a faer::sparse::linalg::cholesky::supernodal::SymbolicSupernodalCholesky<usize>,
    super_of: Vec<usize>,
}

impl Locate<'_> {
    fn at(&self, row: usize, col: usize) -> Option<usize> {
        let s = *self.super_of.get(col)?;
        let (b, e) = (self.raw.supernode_begin()[s], self.raw.supernode_end()[s]);
        let ptr = self.raw.col_ptr_for_row_idx();
        let pattern = &self.raw.row_idx()[ptr[s]..ptr[s + 1]];
        let ncols = e - b;
        let nrows = ncols + pattern.len();
        let pos = if row < e {
            (row >= col).then_some(row - b)?
        } else {
            ncols + pattern.binary_search(&row).ok()?
        };
        Some(self.raw.col_ptr_for_val()[s] + (col - b) * nrows + pos)
    }
}

impl SupernodalPlan {
    /// The plan for `pattern` in the node ordering `perm` (`perm[new] = old`)
    /// with the blocked structure `col_ptr`/`row_idx` of `L`. `None` when faer
    /// cannot analyse it or its structure does not hold the blocked one (then
    /// the blocked kernel is used).
    pub(super) fn new(
        pattern: &BlockPattern,
        perm: &[usize],
        col_ptr: &[usize],
        row_idx: &[usize],
    ) -> Option<Self> {
        let n = pattern.n;
        let dim = 3 * n;
        // The scalar lower triangle of A, column by column.
        let mut a_col_ptr = Vec::with_capacity(dim + 1);
        let mut a_row_idx = Vec::new();
        let mut a_src = Vec::new();
        a_col_ptr.push(0);
        for c in 0..n {
            for cc in 0..3 {
                let col = 3 * c + cc;
                for &r in &pattern.col_idx[pattern.row_ptr[c]..pattern.row_ptr[c + 1]] {
                    let slot = pattern.slot(r, c)?;
                    for rr in 0..3 {
                        if 3 * r + rr >= col {
                            a_row_idx.push(3 * r + rr);
                            a_src.push(9 * slot + 3 * cc + rr);
                        }
                    }
                }
                a_col_ptr.push(a_row_idx.len());
            }
        }
        let fwd: Vec<usize> = (0..dim).map(|k| 3 * perm[k / 3] + k % 3).collect();
        let mut inv = vec![0; dim];
        for (k, &v) in fwd.iter().enumerate() {
            inv[v] = k;
        }
        let symbolic = factorize_symbolic_cholesky(
            SymbolicSparseColMatRef::new_checked(dim, dim, &a_col_ptr, None, &a_row_idx),
            Side::Lower,
            SymmetricOrdering::Custom(PermRef::new_checked(&fwd, &inv, dim)),
            CholeskySymbolicParams {
                supernodal_flop_ratio_threshold: SupernodalThreshold::FORCE_SUPERNODAL,
                ..Default::default()
            },
        )
        .ok()?;
        let SymbolicCholeskyRaw::Supernodal(raw) = symbolic.raw() else {
            return None;
        };
        let (_, finv) = symbolic.perm()?.arrays();
        let mut super_of = vec![0; dim];
        for s in 0..raw.n_supernodes() {
            super_of[raw.supernode_begin()[s]..raw.supernode_end()[s]].fill(s);
        }
        let locate = Locate { raw, super_of };
        // faer's position of unknown `c` of permuted node `k`.
        let at = |k: usize, c: usize| finv[3 * perm[k] + c];
        let mut gather_l = Vec::with_capacity(9 * row_idx.len());
        for i in 0..n {
            for &k in &row_idx[col_ptr[i]..col_ptr[i + 1]] {
                // Block (row node k, column node i), column-major.
                for cc in 0..3 {
                    for rr in 0..3 {
                        let (row, col) = (at(k, rr), at(i, cc));
                        if row <= col {
                            return None;
                        }
                        gather_l.push(locate.at(row, col)?);
                    }
                }
            }
        }
        let mut gather_diag = Vec::with_capacity(6 * n);
        for k in 0..n {
            let p = [at(k, 0), at(k, 1), at(k, 2)];
            if !(p[0] < p[1] && p[1] < p[2]) {
                return None;
            }
            for (r, c) in [(1, 0), (2, 0), (2, 1), (0, 0), (1, 1), (2, 2)] {
                gather_diag.push(locate.at(p[r], p[c])?);
            }
        }
        let values_len = symbolic.len_val();
        let scratch_bytes = symbolic
            .factorize_numeric_ldlt_scratch::<f64>(Par::Seq, Default::default())
            .unaligned_bytes_required();
        Some(Self {
            symbolic,
            a_col_ptr,
            a_row_idx,
            a_src,
            gather_l,
            gather_diag,
            values_len,
            scratch_bytes,
        })
    }

    /// Buffers for one factor.
    pub(super) fn alloc(&self) -> SupernodalBuffers {
        SupernodalBuffers {
            a: vec![0.0; self.a_src.len()],
            l: vec![0.0; self.values_len],
            stack: vec![MaybeUninit::new(0); self.scratch_bytes],
        }
    }

    /// Factorizes `a` into `out` (its blocked layout, through its buffers),
    /// with the symbolic analysis's node ordering `perm` (`perm[new] = old`)
    /// and `a_diag`, the slot of each permuted node's diagonal block in `A`.
    /// A pivot that is not positive, or below `1e-14` of its diagonal entry
    /// of `A`, is [`SoftTissueError::NotPositiveDefinite`].
    pub(super) fn factorize(
        &self,
        a: &BlockCsr,
        perm: &[usize],
        a_diag: &[usize],
        out: FactorParts<'_>,
    ) -> Result<()> {
        let FactorParts { l, ldiag, d, buf } = out;
        if buf.a.len() != self.a_src.len()
            || buf.l.len() != self.values_len
            || buf.stack.len() != self.scratch_bytes
        {
            *buf = self.alloc();
        }
        for (v, &src) in buf.a.iter_mut().zip(&self.a_src) {
            *v = a.values[src / 9][src % 9];
        }
        let dim = self.a_col_ptr.len() - 1;
        let matrix = SparseColMatRef::new(
            SymbolicSparseColMatRef::new_checked(dim, dim, &self.a_col_ptr, None, &self.a_row_idx),
            &buf.a,
        );
        let zero_pivot = match self.symbolic.factorize_numeric_ldlt(
            &mut buf.l,
            matrix,
            Side::Lower,
            Default::default(),
            Par::Seq,
            MemStack::new(&mut buf.stack),
            Default::default(),
        ) {
            Ok(_) => None,
            Err(faer::linalg::cholesky::ldlt::factor::LdltError::ZeroPivot { index }) => {
                Some(index)
            }
        };
        if let Some(index) = zero_pivot {
            // faer's position `index` names the original unknown `fwd[index]`.
            let node = self
                .symbolic
                .perm()
                .and_then(|p| p.arrays().0.get(index).map(|&o| o / 3))
                .unwrap_or(0);
            return Err(SoftTissueError::NotPositiveDefinite { node, pivot: 0.0 });
        }
        for (block, idx) in l.iter_mut().zip(self.gather_l.chunks_exact(9)) {
            for (e, &i) in block.as_mut_slice().iter_mut().zip(idx) {
                *e = buf.l[i];
            }
        }
        for (k, idx) in self.gather_diag.chunks_exact(6).enumerate() {
            ldiag[k] = [buf.l[idx[0]], buf.l[idx[1]], buf.l[idx[2]]];
            let piv = [buf.l[idx[3]], buf.l[idx[4]], buf.l[idx[5]]];
            let akk = a.values[a_diag[k]];
            let scale = akk[(0, 0)]
                .abs()
                .max(akk[(1, 1)].abs())
                .max(akk[(2, 2)].abs());
            for p in piv {
                if !p.is_finite() || p <= 1e-14 * scale || scale == 0.0 {
                    return Err(SoftTissueError::NotPositiveDefinite {
                        node: perm[k],
                        pivot: p,
                    });
                }
            }
            d[k] = Vec3::new(piv[0], piv[1], piv[2]);
        }
        Ok(())
    }
}
