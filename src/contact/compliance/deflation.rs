//! The rigid-mode completion of a lagging factor (two-level compliance; see
//! [`crate::contact::ContactSettings::rigid_modes`]).
//!
//! With `Z` the body's six rigid modes (translations, and rotations about its
//! centre of mass, zero at constrained nodes), `P` the lagging factor (warped)
//! and `A` the step's matrix, the compliance and the correction use
//!
//! ```text
//! P_D⁻¹ = Q + (I − Q A) P⁻¹ (I − A Q),   Q = Z (Zᵀ A Z)⁻¹ Zᵀ
//! ```
//!
//! instead of `P⁻¹` (the balancing two-level preconditioner of domain
//! decomposition). It is symmetric positive definite, exact on the rigid
//! modes (`P_D⁻¹ A Z = Z`) and leaves the rest to `P`: the part of a force
//! that moves the body as a whole is answered by `A` itself, only the
//! deformation by the factor. With `Y = P⁻¹ A Z`, `G = (Zᵀ A Z)⁻¹`,
//! `S = Zᵀ A Y` and `B = G + G S G`:
//!
//! ```text
//! P_D⁻¹ = P⁻¹ + Z B Zᵀ − Y G Zᵀ − Z G Yᵀ
//! ```
//!
//! so with `U = H Z` and `V = H Y` (six columns each) `W` gains the rank-12
//! term `h² (U B Uᵀ − V G Uᵀ − U G Vᵀ)` and the correction
//! `h² (Z (B a − G b) − Y G a)` with `a = Uᵀ λ`, `b = Vᵀ λ`.
//!
//! `Y` itself is never formed. With the factor `P = Q Pᵀ L D Lᵀ P Qᵀ` (warp
//! `Q`, permutation `P`) and `F = L⁻¹ P Qᵀ A Z`, the forward half of six
//! solves, `Y = Q Pᵀ L⁻ᵀ D⁻¹ F`, so
//! - `S = Fᵀ D⁻¹ F`;
//! - `V`'s row of an entry at node `k` is `jᵀ Z_kᵀ D⁻¹ F` with `Z_k` the
//!   node's column (cached on its elimination-tree path for `W` already);
//! - in the correction, `b = Fᵀ D⁻¹ y` and `Y G a` joins the backward sweep
//!   it already runs: `Q Pᵀ L⁻ᵀ (D⁻¹ y − D⁻¹ F G a)`, `y` its forward part.
//!
//! That is six forward sweeps per step and body in contact instead of six
//! solves; the rest is `O(n + m²)` with a factor six. Where `W` was built
//! without the node columns (a [`super::ComplianceBackend`]), or their
//! paths add up to more than `L` ([`COLUMN_PATH_SHARE`]), the rows of `V`
//! come from one backward sweep of the six instead.

use nalgebra::{Matrix6, Vector6};

use super::entries::{FactorView, JacEntry};
use crate::body::DeformableBody;
use crate::math::{Mat3, Vec3};
use crate::solver::columns::{ColumnCache, FactorKey};

/// Above this share of `L`'s blocks (the diagonal ones included), the node
/// columns' paths of a build, summed, cost more than one backward sweep of
/// the six right-hand sides, and `V` comes from the sweep. Measured in the
/// cataract scene (`--preconditioner lag2`, the lens's 66 000 blocks, jam
/// builds' paths about 44 000): the completion's share of a jam build took
/// 0.76–0.90 ms through the columns and 1.18–1.24 ms through the sweep,
/// other builds 0.18–0.21 against 0.40–0.46 ms (two runs each, with
/// [`path_products`] in AVX2 lanes; in scalar code the columns had cost
/// 1.1 ms a jam build).
const COLUMN_PATH_SHARE: f64 = 1.0;

/// One body's rigid-mode completion, kept between passes of a step.
#[derive(Debug, Default)]
pub(super) struct Deflation {
    /// The factor and step that `y`, `g`, `b` belong to; `None`: nothing valid.
    key: Option<(FactorKey, u64)>,
    /// Whether `Zᵀ A Z` was positive definite (no completion otherwise).
    pub(super) active: bool,
    /// `Z` and `A Z`, interleaved by node (`z[i][k]`: mode `k` at node `i`).
    z: Vec<[Vec3; 6]>,
    az: Vec<[Vec3; 6]>,
    /// `D⁻¹ F`, in the factor's permuted numbering.
    df: Vec<[Vec3; 6]>,
    g: Matrix6<f64>,
    b: Matrix6<f64>,
    /// The six right-hand sides `Qᵀ A z` (original numbering), and `F`.
    rhs: Vec<[Vec3; 6]>,
    f: Vec<[Vec3; 6]>,
    /// Without node columns only: `L⁻ᵀ D⁻¹ F` (permuted numbering, `Qᵀ Y`
    /// by node); `y_made` says it is this step's.
    y: Vec<[Vec3; 6]>,
    y_made: bool,
    /// With node columns: `Qᵀ Y` at the nodes met so far in this step's
    /// passes (`y_node[k]` valid where `y_stamp[k] == y_gen`), so a later
    /// pass with the same factor reads them instead of the paths again.
    y_node: Vec<[Vec3; 6]>,
    y_stamp: Vec<u32>,
    y_gen: u32,
    /// Tests: rows of `V` read from node columns' paths so far.
    #[cfg(test)]
    pub(super) path_reads: usize,
    /// Tests: builds whose term the in-place mirror added.
    #[cfg(test)]
    pub(super) fused_builds: usize,
    /// Tests: [`COLUMN_PATH_SHARE`] replaced.
    pub(super) path_share: Option<f64>,
    /// Per pass: the rows this body touches, with their `U` and `V` rows.
    rows: Vec<u32>,
    u: Vec<Vector6<f64>>,
    v: Vec<Vector6<f64>>,
    slot: Vec<u32>,
    /// `rows` in ascending order, their `U` and `V` by component
    /// (`soa[c k + j]`, `c < 6` for `U`, then `V`), and one row of sums.
    sorted: Vec<u32>,
    soa: Vec<f64>,
    /// Per row of `sorted`, `(B u − G v) h²` and then `G u h²`.
    coef: Vec<f64>,
    tmp_row: Vec<f64>,
}

/// The rank-12 term of one build, made by [`Deflation::prepare_rows`]: the
/// rows (ascending), their `U` and `V` by component (`soa[c k + j]`, `c < 6`
/// for `U`, then `V`) and each row's twelve coefficients (`coef[12 j..]`).
/// Entry `(i, j)` of the term is `coef_i[..6]·u_j − coef_i[6..]·v_j`.
pub(super) struct Rank12<'a> {
    pub(super) rows: &'a [u32],
    pub(super) soa: &'a [f64],
    pub(super) coef: &'a [f64],
}

impl Deflation {
    /// Makes the completion of `view`'s factor for this step's matrix, unless
    /// it is already made. Returns whether it is active.
    pub(super) fn prepare(&mut self, body: &DeformableBody, view: &FactorView<'_>) -> bool {
        let key = (view.key, body.step_index());
        if self.key == Some(key) {
            return self.active;
        }
        self.key = Some(key);
        self.active = false;
        // Only bodies with every node free come here (see `completes`).
        let n = body.num_nodes();
        // The rows of `V` kept between passes: none valid for a new key.
        self.y_gen = self.y_gen.wrapping_add(1);
        if self.y_gen == 0 || self.y_stamp.len() != n {
            self.y_stamp.clear();
            self.y_stamp.resize(n, 0);
            self.y_node.resize(n, [Vec3::zeros(); 6]);
            self.y_gen = 1;
        }
        let x = body.positions();
        let mass = body.mass();
        let mt: f64 = mass.iter().sum();
        if mt <= 0.0 {
            return false;
        }
        let c = x.iter().zip(mass).map(|(x, m)| x * *m).sum::<Vec3>() / mt;
        let r2 = x
            .iter()
            .zip(mass)
            .map(|(x, m)| m * (x - c).norm_squared())
            .sum::<f64>()
            / mt;
        let len = r2.sqrt();
        if !(len > 0.0 && len.is_finite()) {
            return false;
        }
        // The six modes, interleaved by node: `z[i][k]` is mode `k` at node `i`.
        self.z.clear();
        self.z.extend(x.iter().map(|xi| {
            std::array::from_fn(|k| {
                let mut e = Vec3::zeros();
                e[k % 3] = 1.0;
                if k < 3 { e } else { e.cross(&(xi - c)) / len }
            })
        }));
        // A Z (one pass over A for the six modes), Zᵀ A Z; F = L⁻¹ P Qᵀ A Z;
        // S = Fᵀ D⁻¹ F.
        let a = body.system_matrix();
        let f = view.factor;
        let mut zaz = Matrix6::zeros();
        let mut s = Matrix6::zeros();
        for buf in [&mut self.az, &mut self.rhs, &mut self.f, &mut self.df] {
            buf.resize(n, [Vec3::zeros(); 6]);
        }
        self.y_made = false;
        a.mul_vecs(&self.z, &mut self.az);
        for i in 0..n {
            let (zi, azi) = (&self.z[i], &self.az[i]);
            for k in 0..6 {
                for l in 0..6 {
                    zaz[(l, k)] += zi[l].dot(&azi[k]);
                }
                // In the frame of the factor, as the compliance applies it.
                self.rhs[i][k] = match view.warp {
                    Some(q) => q[i].transpose() * azi[k],
                    None => azi[k],
                };
            }
        }
        f.forward_many(&self.rhs, &mut self.f);
        for ((fk, dfk), d) in self.f.iter().zip(&mut self.df).zip(&f.d) {
            for c in 0..6 {
                dfk[c] = fk[c].component_div(d);
            }
            for k in 0..6 {
                for l in 0..6 {
                    s[(l, k)] += fk[l].dot(&dfk[k]);
                }
            }
        }
        let zaz = (zaz + zaz.transpose()) * 0.5;
        let s = (s + s.transpose()) * 0.5;
        let Some(chol) = zaz.cholesky() else {
            return false;
        };
        let g = chol.inverse();
        if !g.iter().all(|v| v.is_finite()) || !s.iter().all(|v| v.is_finite()) {
            return false;
        }
        self.g = g;
        self.b = g + g * s * g;
        self.active = true;
        true
    }

    /// `Qᵀ Y` at original node `k` (the factor's frame): from `k`'s node
    /// column, `Z_kᵀ D⁻¹ F` along its path, when `columns` (kept for the
    /// step's later passes); else from `L⁻ᵀ D⁻¹ F`, one backward sweep of
    /// the six made once per step.
    fn y_at(
        &mut self,
        view: &FactorView<'_>,
        columns: Option<&ColumnCache>,
        k: usize,
    ) -> [Vec3; 6] {
        if let Some(cache) = columns {
            if self.y_stamp[k] == self.y_gen {
                return self.y_node[k];
            }
            let cl = cache.cols[cache.col_of_node[k] as usize];
            let range = cl.start..cl.start + cl.len;
            let y = path_products(&cache.blocks[range.clone()], &cache.paths[range], &self.df);
            #[cfg(test)]
            {
                self.path_reads += 1;
            }
            self.y_node[k] = y;
            self.y_stamp[k] = self.y_gen;
            return y;
        }
        if !self.y_made {
            self.y.clear();
            self.y.extend_from_slice(&self.df);
            view.factor.backward_many(&mut self.y);
            self.y_made = true;
        }
        self.y[view.factor.symbolic.iperm[k]]
    }

    /// Whether `rows_of` reads `V` from `cache`'s node columns: they hold
    /// every node of `entries` for this view's factor, and their paths are
    /// shorter than `share` of `L` ([`COLUMN_PATH_SHARE`]; beyond that one
    /// backward sweep of all six costs less).
    fn use_columns<'c>(
        view: &FactorView<'_>,
        cache: Option<&'c ColumnCache>,
        entries: &[JacEntry],
        share: f64,
    ) -> Option<&'c ColumnCache> {
        let cache = cache.filter(|c| c.key == Some(view.key))?;
        let mut path = 0usize;
        let mut last = u32::MAX;
        for e in entries {
            if e.node == last {
                continue;
            }
            last = e.node;
            let i = *cache.col_of_node.get(e.node as usize)?;
            if i == u32::MAX {
                return None;
            }
            path += cache.cols[i as usize].len;
        }
        let blocks = view.factor.symbolic.nnz_blocks() + view.factor.symbolic.n;
        (path as f64 <= share * blocks as f64).then_some(cache)
    }

    /// `U = H Z` and `V = H Y` of the rows `entries` (sorted by node, `j`
    /// filled) touch (`m` rows in all).
    fn rows_of(
        &mut self,
        view: &FactorView<'_>,
        cache: Option<&ColumnCache>,
        entries: &[JacEntry],
        m: usize,
    ) {
        self.slot.clear();
        self.slot.resize(m, u32::MAX);
        self.rows.clear();
        self.u.clear();
        self.v.clear();
        let share = self.path_share.unwrap_or(COLUMN_PATH_SHARE);
        let columns = Self::use_columns(view, cache, entries, share);
        let mut s0 = 0;
        while s0 < entries.len() {
            let k = entries[s0].node as usize;
            let y = self.y_at(view, columns, k);
            let mut e1 = s0;
            while e1 < entries.len() && entries[e1].node as usize == k {
                let e = &entries[e1];
                let r = e.row as usize;
                if self.slot[r] == u32::MAX {
                    self.slot[r] = self.rows.len() as u32;
                    self.rows.push(e.row);
                    self.u.push(Vector6::zeros());
                    self.v.push(Vector6::zeros());
                }
                let s = self.slot[r] as usize;
                for c in 0..6 {
                    self.u[s][c] += e.h.dot(&self.z[k][c]);
                    self.v[s][c] += e.j.dot(&y[c]);
                }
                e1 += 1;
            }
            s0 = e1;
        }
    }

    /// `W += h² (U B Uᵀ − V G Uᵀ − U G Vᵀ)` over the rows of `entries`
    /// ([`Self::prepare_rows`], then [`Self::add_prepared`]).
    /// `cache`: the node columns `W` was built from, if it was.
    pub(super) fn add_to_w(
        &mut self,
        view: &FactorView<'_>,
        cache: Option<&ColumnCache>,
        entries: &[JacEntry],
        h2: f64,
        w: &mut [f64],
        m: usize,
    ) {
        if self.prepare_rows(view, cache, entries, h2, m).is_some() {
            self.add_prepared(w, m);
        }
    }

    /// The rank-12 term over the rows of `entries` (`m` rows in all), ready
    /// to add: row `r` gains `(B u_r − G v_r)·u_s − (G u_r)·v_s` at each
    /// column `s`. The rows' `U` and `V` are laid out by component (in
    /// ascending row order) so a loop over `s` runs in vector lanes, and
    /// each row's two 6-vectors of coefficients are kept by the same order.
    /// `None` when the completion is not active.
    pub(super) fn prepare_rows(
        &mut self,
        view: &FactorView<'_>,
        cache: Option<&ColumnCache>,
        entries: &[JacEntry],
        h2: f64,
        m: usize,
    ) -> Option<Rank12<'_>> {
        if !self.active {
            return None;
        }
        self.rows_of(view, cache, entries, m);
        let k = self.rows.len();
        self.sorted.clear();
        self.sorted.extend_from_slice(&self.rows);
        self.sorted.sort_unstable();
        self.soa.clear();
        self.soa.resize(12 * k, 0.0);
        self.coef.clear();
        self.coef.resize(12 * k, 0.0);
        for (j, &r) in self.sorted.iter().enumerate() {
            let s = self.slot[r as usize] as usize;
            let (u, v) = (&self.u[s], &self.v[s]);
            let a = (self.b * u - self.g * v) * h2;
            let b = self.g * u * h2;
            for c in 0..6 {
                self.soa[c * k + j] = u[c];
                self.soa[(6 + c) * k + j] = v[c];
                self.coef[12 * j + c] = a[c];
                self.coef[12 * j + 6 + c] = b[c];
            }
        }
        Some(Rank12 {
            rows: &self.sorted,
            soa: &self.soa,
            coef: &self.coef,
        })
    }

    /// Adds the term [`Self::prepare_rows`] made to `w` (`m × m`).
    pub(super) fn add_prepared(&mut self, w: &mut [f64], m: usize) {
        let k = self.sorted.len();
        let contiguous = k > 0 && (self.sorted[k - 1] - self.sorted[0]) as usize == k - 1;
        self.tmp_row.clear();
        self.tmp_row.resize(k, 0.0);
        for (j, &r) in self.sorted.iter().enumerate() {
            let a = Vector6::from_column_slice(&self.coef[12 * j..][..6]);
            let b = Vector6::from_column_slice(&self.coef[12 * j + 6..][..6]);
            let wr = &mut w[r as usize * m..][..m];
            if contiguous {
                let r0 = self.sorted[0] as usize;
                rank12_row(&a, &b, &self.soa, &mut wr[r0..r0 + k]);
            } else {
                self.tmp_row.fill(0.0);
                rank12_row(&a, &b, &self.soa, &mut self.tmp_row);
                for (&r, t) in self.sorted.iter().zip(&self.tmp_row) {
                    wr[r as usize] += t;
                }
            }
        }
    }

    /// The correction's share (see the module docs), in three calls around
    /// its sweeps: `a = Uᵀ λ` from `entries` (world `h`).
    pub(super) fn modes_of(&self, entries: &[JacEntry], lambda: &[f64]) -> Vector6<f64> {
        let mut a = Vector6::zeros();
        for e in entries {
            let l = lambda[e.row as usize];
            for c in 0..6 {
                a[c] += l * e.h.dot(&self.z[e.node as usize][c]);
            }
        }
        a
    }

    /// `b = Fᵀ D⁻¹ y` of the correction's forward part `y` (permuted
    /// numbering), then `y ← D⁻¹ y − D⁻¹ F G a`: what its backward sweep
    /// turns into `(P⁻¹ Hᵀ λ − Y G a)`. Returns `b`.
    pub(super) fn divide_and_shift(
        &self,
        d: &[Vec3],
        a: &Vector6<f64>,
        y: &mut [Vec3],
    ) -> Vector6<f64> {
        let mut b = Vector6::zeros();
        let ga = self.g * a;
        for ((yk, dfk), dk) in y.iter_mut().zip(&self.df).zip(d) {
            let mut shift = Vec3::zeros();
            for c in 0..6 {
                b[c] += dfk[c].dot(yk);
                shift += dfk[c] * ga[c];
            }
            *yk = yk.component_div(dk) - shift;
        }
        b
    }

    /// `dx += h² Z (B a − G b)`.
    pub(super) fn add_modes(&self, a: &Vector6<f64>, b: &Vector6<f64>, h2: f64, dx: &mut [Vec3]) {
        let cz = (self.b * a - self.g * b) * h2;
        for (d, z) in dx.iter_mut().zip(&self.z) {
            let mut s = Vec3::zeros();
            for c in 0..6 {
                s += z[c] * cz[c];
            }
            *d += s;
        }
    }
}

/// `Σ_t B_tᵀ df[paths[t]][c]` for the six `c`: one node column's blocks
/// `B_t` along its path against `D⁻¹ F`. In AVX2 lanes where the CPU has
/// them.
fn path_products(blocks: &[Mat3], paths: &[usize], df: &[[Vec3; 6]]) -> [Vec3; 6] {
    #[cfg(target_arch = "x86_64")]
    if crate::math::has_avx2_fma() {
        // SAFETY: the CPU supports the features the function is compiled for.
        return unsafe { path_products_avx2(blocks, paths, df) };
    }
    path_products_portable(blocks, paths, df)
}

fn path_products_portable(blocks: &[Mat3], paths: &[usize], df: &[[Vec3; 6]]) -> [Vec3; 6] {
    let mut out = [Vec3::zeros(); 6];
    for (b, &p) in blocks.iter().zip(paths) {
        let bt = b.transpose();
        for c in 0..6 {
            out[c] += bt * df[p][c];
        }
    }
    out
}

/// [`path_products`] with AVX2 and FMA: entry `i` of output `c` is the dot
/// product of `B_t`'s column `i` with `df[p][c]`, kept lane-wise over the
/// path and summed across lanes once at the end; three outputs at a time
/// (nine accumulators), so the path is read twice.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn path_products_avx2(blocks: &[Mat3], paths: &[usize], df: &[[Vec3; 6]]) -> [Vec3; 6] {
    use crate::math::x86;
    use std::arch::x86_64::*;
    let mut out = [Vec3::zeros(); 6];
    for half in 0..2 {
        let mut acc = [[_mm256_setzero_pd(); 3]; 3];
        for (b, &p) in blocks.iter().zip(paths) {
            let cols = x86::columns(b);
            let d = &df[p];
            for (c, acc_c) in acc.iter_mut().enumerate() {
                let v = x86::load3(&d[3 * half + c]);
                for i in 0..3 {
                    acc_c[i] = _mm256_fmadd_pd(cols[i], v, acc_c[i]);
                }
            }
        }
        for (c, acc_c) in acc.iter().enumerate() {
            for i in 0..3 {
                out[3 * half + c][i] = x86::sum(acc_c[i]);
            }
        }
    }
    out
}

/// `out[j] += a·u_j − b·v_j` for the `k = out.len()` columns laid out in
/// `soa` (see [`Deflation::add_to_w`]); each dot product summed in order,
/// as `Vector6::dot` does.
fn rank12_row(a: &Vector6<f64>, b: &Vector6<f64>, soa: &[f64], out: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    if crate::math::has_avx2_fma() {
        // SAFETY: the CPU supports the features the function is compiled for.
        return unsafe { rank12_row_avx2(a, b, soa, out) };
    }
    rank12_row_portable(a, b, soa, out);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn rank12_row_avx2(a: &Vector6<f64>, b: &Vector6<f64>, soa: &[f64], out: &mut [f64]) {
    rank12_row_portable(a, b, soa, out);
}

#[inline(always)]
fn rank12_row_portable(a: &Vector6<f64>, b: &Vector6<f64>, soa: &[f64], out: &mut [f64]) {
    let k = out.len();
    let col = |c: usize| &soa[c * k..(c + 1) * k];
    let (u0, u1, u2, u3, u4, u5) = (col(0), col(1), col(2), col(3), col(4), col(5));
    let (v0, v1, v2, v3, v4, v5) = (col(6), col(7), col(8), col(9), col(10), col(11));
    for j in 0..k {
        let su = 0.0
            + a[0] * u0[j]
            + a[1] * u1[j]
            + a[2] * u2[j]
            + a[3] * u3[j]
            + a[4] * u4[j]
            + a[5] * u5[j];
        let sv = 0.0
            + b[0] * v0[j]
            + b[1] * v1[j]
            + b[2] * v2[j]
            + b[3] * v3[j]
            + b[4] * v4[j]
            + b[5] * v5[j];
        out[j] += su - sv;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The AVX2 path kernel (where the CPU has it) gives what the portable
    /// one gives, to round-off, for paths of every length up to nine.
    #[test]
    fn path_products_kernels_agree() {
        let val = crate::math::test_value;
        let df: Vec<[Vec3; 6]> = (0..12)
            .map(|p| std::array::from_fn(|c| Vec3::from_fn(|r, _| val(p * 18 + c * 3 + r, 1))))
            .collect();
        for len in 0..10 {
            let blocks: Vec<Mat3> = (0..len)
                .map(|t| Mat3::from_fn(|r, c| val(t * 9 + r * 3 + c, 2)))
                .collect();
            let paths: Vec<usize> = (0..len).map(|t| (t * 5) % 12).collect();
            let fast = path_products(&blocks, &paths, &df);
            let portable = path_products_portable(&blocks, &paths, &df);
            let mut want = [Vec3::zeros(); 6];
            for (b, &p) in blocks.iter().zip(&paths) {
                for c in 0..6 {
                    for i in 0..3 {
                        want[c][i] += (0..3).map(|r| b[(r, i)] * df[p][c][r]).sum::<f64>();
                    }
                }
            }
            for c in 0..6 {
                for (got, name) in [(fast[c], "fast"), (portable[c], "portable")] {
                    let d = (got - want[c]).norm();
                    assert!(
                        d <= 1e-12 * (1.0 + want[c].norm()),
                        "{name}, len {len}, c {c}: {d:e}"
                    );
                }
            }
            if len > 0 {
                assert!(want.iter().any(|v| v.norm() > 1.0));
            }
        }
    }

    /// The row kernel of `add_to_w` (AVX2 where the CPU has it) gives, to the
    /// bit, `a·u_j − b·v_j` with nalgebra's 6-vector dot products, which is
    /// what it replaced, for every remainder length.
    #[test]
    fn rank12_row_matches_the_vector6_dot_products() {
        let val = crate::math::test_value;
        let a = Vector6::from_fn(|c, _| val(c, 1));
        let b = Vector6::from_fn(|c, _| val(c, 2));
        for k in 0..13 {
            let u: Vec<Vector6<f64>> = (0..k)
                .map(|j| Vector6::from_fn(|c, _| val(j * 6 + c, 3)))
                .collect();
            let v: Vec<Vector6<f64>> = (0..k)
                .map(|j| Vector6::from_fn(|c, _| val(j * 6 + c, 4)))
                .collect();
            let mut soa = vec![0.0; 12 * k];
            for j in 0..k {
                for c in 0..6 {
                    soa[c * k + j] = u[j][c];
                    soa[(6 + c) * k + j] = v[j][c];
                }
            }
            let start: Vec<f64> = (0..k).map(|j| val(j, 5)).collect();
            let (mut fast, mut portable) = (start.clone(), start.clone());
            rank12_row(&a, &b, &soa, &mut fast);
            rank12_row_portable(&a, &b, &soa, &mut portable);
            for j in 0..k {
                let want = start[j] + (a.dot(&u[j]) - b.dot(&v[j]));
                assert_eq!(fast[j].to_bits(), want.to_bits(), "k {k}, j {j}");
                assert_eq!(portable[j].to_bits(), want.to_bits(), "k {k}, j {j}");
            }
        }
    }
}
