//! 3×3-block sparse storage of the system matrix.
//!
//! [`BlockPattern`] is computed once per mesh: the node adjacency in
//! compressed sparse row form (both triangles, columns sorted), the slot of
//! every diagonal block, and for every element the 16 slots its blocks
//! scatter into. [`BlockCsr`] holds one value per slot and is refilled in
//! place every step, so assembly allocates nothing.

use std::sync::Arc;

#[cfg(target_arch = "x86_64")]
use crate::math::x86;
use crate::math::{Mat3, Vec3};

/// Block sparsity pattern of a mesh's system matrix.
#[derive(Debug, Clone, PartialEq)]
pub struct BlockPattern {
    /// Number of block rows (nodes).
    pub n: usize,
    /// Row start offsets, length `n + 1`.
    pub row_ptr: Vec<usize>,
    /// Column (node) of every slot, sorted within each row.
    pub col_idx: Vec<usize>,
    /// Slot of the diagonal block of every row.
    pub diag: Vec<usize>,
    /// For every element, the slot of block `(a, b)` at index `4a + b`.
    pub element_slots: Vec<[usize; 16]>,
}

impl BlockPattern {
    /// Builds the pattern of `n` nodes connected by tetrahedra `tets`.
    pub fn new(n: usize, tets: &[[usize; 4]]) -> Self {
        let mut adj: Vec<Vec<usize>> = vec![Vec::new(); n];
        for (i, list) in adj.iter_mut().enumerate() {
            list.push(i);
        }
        for t in tets {
            for &a in t {
                for &b in t {
                    adj[a].push(b);
                }
            }
        }
        let mut row_ptr = Vec::with_capacity(n + 1);
        let mut col_idx = Vec::new();
        row_ptr.push(0);
        for list in &mut adj {
            list.sort_unstable();
            list.dedup();
            col_idx.extend_from_slice(list);
            row_ptr.push(col_idx.len());
        }
        let mut p = Self {
            n,
            row_ptr,
            col_idx,
            diag: Vec::new(),
            element_slots: Vec::new(),
        };
        p.diag = (0..n).map(|i| p.slot(i, i).unwrap_or(usize::MAX)).collect();
        p.element_slots = tets
            .iter()
            .map(|t| {
                let mut s = [0usize; 16];
                for a in 0..4 {
                    for b in 0..4 {
                        s[4 * a + b] = p.slot(t[a], t[b]).unwrap_or(usize::MAX);
                    }
                }
                s
            })
            .collect();
        p
    }

    /// Slot of block `(row, col)`, if present.
    pub fn slot(&self, row: usize, col: usize) -> Option<usize> {
        let (s, e) = (self.row_ptr[row], self.row_ptr[row + 1]);
        self.col_idx[s..e].binary_search(&col).ok().map(|k| s + k)
    }

    /// Number of stored blocks.
    pub fn nnz(&self) -> usize {
        self.col_idx.len()
    }
}

/// A symmetric 3×3-block sparse matrix over a shared [`BlockPattern`].
#[derive(Debug, Clone)]
pub struct BlockCsr {
    /// The pattern (shared with factorizations and workers).
    pub pattern: Arc<BlockPattern>,
    /// One block per slot.
    pub values: Vec<Mat3>,
}

impl BlockCsr {
    /// A zero matrix over `pattern`.
    pub fn zeros(pattern: Arc<BlockPattern>) -> Self {
        let values = vec![Mat3::zeros(); pattern.nnz()];
        Self { pattern, values }
    }

    /// Number of block rows.
    pub fn n(&self) -> usize {
        self.pattern.n
    }

    /// Sets every block to zero.
    pub fn clear(&mut self) {
        self.values.fill(Mat3::zeros());
    }

    /// `y = A x` ([`Self::mul_vecs`] with one vector).
    pub fn mul_vec(&self, x: &[Vec3], y: &mut [Vec3]) {
        let (x, _) = x.as_chunks::<1>();
        let (y, _) = y.as_chunks_mut::<1>();
        self.mul_vecs(x, y);
    }

    /// `y_k = A x_k` for `K` vectors at once, interleaved by node
    /// (`x[i][k]`): one pass over the matrix instead of `K`.
    pub fn mul_vecs<const K: usize>(&self, x: &[[Vec3; K]], y: &mut [[Vec3; K]]) {
        #[cfg(target_arch = "x86_64")]
        if crate::math::has_avx2_fma() {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { self.mul_vecs_avx2(x, y) };
        }
        self.mul_vecs_portable(x, y);
    }

    fn mul_vecs_portable<const K: usize>(&self, x: &[[Vec3; K]], y: &mut [[Vec3; K]]) {
        let p = &*self.pattern;
        for (i, yi) in y.iter_mut().enumerate().take(p.n) {
            let mut acc = [Vec3::zeros(); K];
            for s in p.row_ptr[i]..p.row_ptr[i + 1] {
                let a = &self.values[s];
                let xj = &x[p.col_idx[s]];
                for k in 0..K {
                    acc[k] += a * xj[k];
                }
            }
            *yi = acc;
        }
    }

    /// [`Self::mul_vecs`] with AVX2 and FMA: each block's three columns times
    /// broadcast entries of `x_j`, summed in registers over the row (even and
    /// odd blocks in separate accumulators, so consecutive fused
    /// multiply-adds do not wait on each other) and stored once per row; each
    /// vector's operations are those of a product of that vector alone.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    fn mul_vecs_avx2<const K: usize>(&self, x: &[[Vec3; K]], y: &mut [[Vec3; K]]) {
        use std::arch::x86_64::*;
        let p = &*self.pattern;
        for (i, yi) in y.iter_mut().enumerate().take(p.n) {
            let range = p.row_ptr[i]..p.row_ptr[i + 1];
            let (vals, cols) = (&self.values[range.clone()], &p.col_idx[range]);
            let mut even = [_mm256_setzero_pd(); K];
            let mut odd = [_mm256_setzero_pd(); K];
            let pairs = vals.len() / 2;
            for t in 0..pairs {
                let (xa, xb) = (&x[cols[2 * t]], &x[cols[2 * t + 1]]);
                for k in 0..K {
                    even[k] = x86::add_product(even[k], &vals[2 * t], &xa[k]);
                    odd[k] = x86::add_product(odd[k], &vals[2 * t + 1], &xb[k]);
                }
            }
            if vals.len() % 2 == 1 {
                let last = vals.len() - 1;
                for k in 0..K {
                    even[k] = x86::add_product(even[k], &vals[last], &x[cols[last]][k]);
                }
            }
            for k in 0..K {
                x86::store3(&mut yi[k], _mm256_add_pd(even[k], odd[k]));
            }
        }
    }

    /// Diagonal block of row `i`.
    pub fn diag(&self, i: usize) -> &Mat3 {
        &self.values[self.pattern.diag[i]]
    }

    /// Dense copy (tests and small references only).
    pub fn to_dense(&self) -> nalgebra::DMatrix<f64> {
        let n = self.n();
        let p = &*self.pattern;
        let mut d = nalgebra::DMatrix::zeros(3 * n, 3 * n);
        for i in 0..n {
            for s in p.row_ptr[i]..p.row_ptr[i + 1] {
                let j = p.col_idx[s];
                d.fixed_view_mut::<3, 3>(3 * i, 3 * j)
                    .copy_from(&self.values[s]);
            }
        }
        d
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::test_value as val;

    /// The product (the AVX2 kernel where the CPU has it) matches the
    /// portable loop and the dense matrix on a box mesh's pattern with
    /// irregular blocks, rows with an even and an odd number of blocks alike.
    #[test]
    fn the_product_matches_the_portable_loop_and_the_dense_matrix() {
        let mesh =
            crate::mesh::generate::box_mesh(Vec3::zeros(), Vec3::new(1.0, 2.0, 1.0), [3, 4, 2])
                .unwrap();
        let pattern = Arc::new(BlockPattern::new(mesh.num_vertices(), mesh.tets()));
        let lengths: Vec<usize> = (0..pattern.n)
            .map(|i| pattern.row_ptr[i + 1] - pattern.row_ptr[i])
            .collect();
        assert!(lengths.iter().any(|l| l % 2 == 0) && lengths.iter().any(|l| l % 2 == 1));
        let mut a = BlockCsr::zeros(pattern.clone());
        for (s, v) in a.values.iter_mut().enumerate() {
            *v = Mat3::from_fn(|r, c| val(9 * s + 3 * c + r, 1));
        }
        let x: Vec<Vec3> = (0..pattern.n)
            .map(|i| Vec3::new(val(3 * i, 2), val(3 * i + 1, 2), val(3 * i + 2, 2)))
            .collect();
        let (mut y, mut z) = (
            vec![Vec3::zeros(); pattern.n],
            vec![Vec3::zeros(); pattern.n],
        );
        a.mul_vec(&x, &mut y);
        a.mul_vecs_portable(x.as_chunks::<1>().0, z.as_chunks_mut::<1>().0);
        let flat =
            nalgebra::DVector::from_iterator(3 * x.len(), x.iter().flat_map(|v| [v.x, v.y, v.z]));
        let dense = a.to_dense() * flat;
        let scale = dense.amax();
        for i in 0..pattern.n {
            for k in 0..3 {
                assert!(
                    (y[i][k] - z[i][k]).abs() <= 1e-13 * scale,
                    "row {i}: {} {}",
                    y[i],
                    z[i]
                );
                assert!((y[i][k] - dense[3 * i + k]).abs() <= 1e-13 * scale);
            }
        }
    }
}
