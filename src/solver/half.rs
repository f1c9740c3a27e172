//! The preconditioner's half-precision copy of a factor: `L` in IEEE binary16,
//! solved with `f32` arithmetic.
//!
//! A CG iteration of the paper-size lens spends most of its time in the two
//! triangular solves with the lagging factor, and each solve reads every block
//! of `L`: 66 000 blocks, 2.4 MB in `f32`, a little more than a core's 2 MB
//! L2 cache on the development machine, so both sweeps stream `L` from the
//! shared L3. In binary16 it is 1.2 MB and stays in L2 between the sweeps and
//! the iterations. Converting a half to `f32` is one instruction (F16C) per
//! column of a block, as converting `f32` to `f64` was, so the arithmetic is
//! done in `f32` (four lanes, lane 3 held at zero) rather than converted once
//! more.
//!
//! What the rounding costs: binary16 keeps 11 bits (a relative 4.9·10⁻⁴ per
//! entry), so `L̃ D L̃ᵀ` is within about 10⁻³ of `L D Lᵀ`. It is still
//! symmetric and positive definite (the same `D`, the transposed `L̃` in the
//! backward sweep), and CG stops on its own residual, so this moves iteration
//! counts, never the solution; a factor several steps old differs from the
//! current matrix by far more. The right-hand side is scaled by its largest
//! entry and `D⁻¹` by its largest before they meet `f32`, so neither the
//! magnitude of the forces nor the stiffness's units can leave `f32`'s range.
//!
//! The copy is made only where the CPU has AVX2, FMA and F16C and every entry
//! fits (binary16 ends at 65 504; `D⁻¹` and the diagonal blocks must fit
//! `f32`); elsewhere
//! [`LdltFactor::solve_half`](crate::solver::ldlt::LdltFactor::solve_half) solves with the
//! single-precision copy.

use crate::math::{Mat3, Vec3, max_abs};

/// The structure of `L` the sweeps walk (borrowed from the factor's
/// symbolic analysis; see `LdltSymbolic`).
#[derive(Clone, Copy)]
#[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
pub(crate) struct Structure<'a> {
    /// `perm[new] = old` node.
    pub perm: &'a [usize],
    /// Column start offsets of `L`, length `n + 1`.
    pub col_ptr: &'a [usize],
    /// Row of every block of `L`.
    pub row_idx: &'a [usize],
    /// Whether column `j`'s rows are `j + 1` followed by column `j + 1`'s.
    pub joins_next: &'a [bool],
}

/// The largest finite binary16 value.
#[cfg(target_arch = "x86_64")]
const HALF_MAX: f64 = 65504.0;

/// Entries of the scaled right-hand side below this are set to zero: far
/// below `f32`'s precision relative to the largest (which is 1), and kept
/// well away from `f32`'s subnormal range, whose arithmetic is slow.
const FLUSH: f64 = 1e-20;

/// `L` in binary16 with the diagonal blocks and `D⁻¹` in `f32` (see the module
/// docs). Valid only while `valid` is set.
#[derive(Debug, Clone, Default)]
pub(crate) struct HalfCopy {
    /// Nine entries per block, column-major, then four of padding (zero): a
    /// column is read as four halves, the fourth the next column's first.
    l: Vec<u16>,
    /// `(l10, l20, l21, 0)` of each unit lower diagonal block.
    diag: Vec<[f32; 4]>,
    /// `D⁻¹ / dmax` per node, lane 3 zero.
    dinv: Vec<[f32; 4]>,
    /// The largest entry of `D⁻¹`.
    dmax: f64,
    valid: bool,
}

/// Whether the CPU runs the half-precision kernels.
pub(crate) fn supported() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        crate::math::has_avx2_fma() && std::arch::is_x86_feature_detected!("f16c")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

impl HalfCopy {
    /// Whether the copy holds the factor's current values.
    pub(crate) fn is_valid(&self) -> bool {
        self.valid
    }

    /// Marks the copy stale (the factor's values changed).
    pub(crate) fn invalidate(&mut self) {
        self.valid = false;
    }

    /// Makes the copy of `l`, `ldiag` and `d`; returns whether it was made
    /// (see the module docs for when it is not). Allocates on the first call
    /// only.
    ///
    /// `l32`, the factor's single-precision copy where it has one (nine
    /// entries per block, as `l`), is rounded instead of `l`: the same
    /// halves (binary16 of the `f32` value either way), from half the bytes
    /// and in eight lanes.
    pub(crate) fn make(
        &mut self,
        l: &[Mat3],
        l32: Option<&[f32]>,
        ldiag: &[[f64; 3]],
        d: &[Vec3],
    ) -> bool {
        self.valid = false;
        if !supported() {
            return false;
        }
        let mut dmax = 0.0f64;
        for p in d {
            for &v in p.iter() {
                // Positive pivots only (a factor of an SPD matrix); `1 / v`
                // must be a normal `f32` after scaling by the largest.
                if !(v > 0.0 && v.is_finite()) {
                    return false;
                }
                dmax = dmax.max(1.0 / v);
            }
        }
        if !(dmax.is_finite() && dmax > 0.0) {
            return false;
        }
        let len = 9 * l.len() + 4;
        if self.l.len() != len {
            self.l.clear();
            self.l.resize(len, 0);
        }
        let mut ok = ldiag
            .iter()
            .flatten()
            .all(|&v| v.abs() <= f64::from(f32::MAX));
        self.diag.clear();
        self.diag.extend(
            ldiag
                .iter()
                .map(|a| [a[0] as f32, a[1] as f32, a[2] as f32, 0.0]),
        );
        self.dinv.clear();
        self.dinv.extend(d.iter().map(|p| {
            let s = |v: f64| (1.0 / v / dmax) as f32;
            [s(p.x), s(p.y), s(p.z), 0.0]
        }));
        // Pivots more than `f32`'s range apart would leave the smallest
        // `D⁻¹` subnormal or zero.
        ok &= self
            .dinv
            .iter()
            .all(|v| v[..3].iter().all(|&x| x >= f32::MIN_POSITIVE));
        self.dmax = dmax;
        #[cfg(target_arch = "x86_64")]
        {
            // SAFETY: `supported` checked the features.
            ok &= match l32 {
                Some(src) if src.len() == 9 * l.len() => unsafe {
                    round_singles(src, &mut self.l[..src.len()])
                },
                _ => unsafe { round_blocks(l, &mut self.l) },
            };
        }
        self.valid = ok;
        ok
    }

    /// Solves `(L̃ D L̃ᵀ) x = b` in original numbering (`L̃` this copy); `y` is
    /// scratch of length `n`. Must be valid ([`Self::is_valid`]).
    pub(crate) fn solve(&self, sym: Structure<'_>, b: &[Vec3], x: &mut [Vec3], y: &mut [[f32; 4]]) {
        assert!(self.valid, "no half-precision copy of L");
        let n = sym.perm.len();
        assert!(
            b.len() >= n && x.len() >= n && y.len() >= n,
            "solve: one entry per node"
        );
        let s = max_abs(&b[..n]);
        if s == 0.0 {
            x[..n].fill(Vec3::zeros());
            return;
        }
        if !s.is_finite() {
            // As a solve in `f64` would: CG stops on the non-finite product.
            x[..n].fill(Vec3::repeat(f64::NAN));
            return;
        }
        let inv = 1.0 / s;
        let to32 = |v: f64| {
            let v = v * inv;
            if v.abs() < FLUSH { 0.0 } else { v as f32 }
        };
        for k in 0..n {
            let v = b[sym.perm[k]];
            y[k] = [to32(v.x), to32(v.y), to32(v.z), 0.0];
        }
        #[cfg(target_arch = "x86_64")]
        // SAFETY: a valid copy was made, so the CPU has the features.
        unsafe {
            self.forward(sym, y);
        }
        for (v, di) in y[..n].iter_mut().zip(&self.dinv) {
            for c in 0..3 {
                v[c] *= di[c];
            }
        }
        #[cfg(target_arch = "x86_64")]
        // SAFETY: as above.
        unsafe {
            self.backward(sym, y);
        }
        let out = s * self.dmax;
        for k in 0..n {
            let v = y[k];
            x[sym.perm[k]] = Vec3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2])) * out;
        }
    }
}

/// Rounds `l` into `out` (nine halves per block, the padding left zero);
/// returns whether every entry fits binary16.
///
/// # Safety
/// The CPU must have AVX2, FMA and F16C.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn round_blocks(l: &[Mat3], out: &mut [u16]) -> bool {
    use std::arch::x86_64::*;
    let mut ok = true;
    let mut buf = [0.0f32; 9];
    for (b, o) in l.iter().zip(out.chunks_exact_mut(9)) {
        for (f, &v) in buf.iter_mut().zip(b.as_slice()) {
            // False for NaN and ±∞ too.
            ok &= v.abs() <= HALF_MAX;
            *f = v as f32;
        }
        // SAFETY: eight readable and writable entries each side, then one.
        unsafe {
            let h = _mm256_cvtps_ph::<_MM_FROUND_TO_NEAREST_INT>(_mm256_loadu_ps(buf.as_ptr()));
            _mm_storeu_si128(o.as_mut_ptr().cast(), h);
            let h = _mm_cvtps_ph::<_MM_FROUND_TO_NEAREST_INT>(_mm_set_ss(buf[8]));
            o[8] = _mm_extract_epi16::<0>(h) as u16;
        }
    }
    ok
}

/// Rounds `src` (`f32`) into `out`, eight at a time; returns whether every
/// entry fits binary16.
///
/// # Safety
/// The CPU must have AVX2, FMA and F16C; `out` as long as `src`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn round_singles(src: &[f32], out: &mut [u16]) -> bool {
    use std::arch::x86_64::*;
    assert_eq!(src.len(), out.len());
    let limit = _mm256_set1_ps(HALF_MAX as f32);
    let sign = _mm256_set1_ps(-0.0);
    // All ones while every magnitude is at most the limit (false for NaN).
    let mut fits = _mm256_castsi256_ps(_mm256_set1_epi32(-1));
    let (body, tail) = (src.len() / 8 * 8, src.len() % 8);
    // SAFETY: eight readable and writable entries at each `i < body`.
    unsafe {
        for i in (0..body).step_by(8) {
            let v = _mm256_loadu_ps(src.as_ptr().add(i));
            let a = _mm256_andnot_ps(sign, v);
            fits = _mm256_and_ps(fits, _mm256_cmp_ps::<_CMP_LE_OQ>(a, limit));
            let h = _mm256_cvtps_ph::<_MM_FROUND_TO_NEAREST_INT>(v);
            _mm_storeu_si128(out.as_mut_ptr().add(i).cast(), h);
        }
    }
    let mut ok = _mm256_movemask_ps(fits) == 0xff;
    if tail > 0 {
        let mut buf = [0.0f32; 8];
        buf[..tail].copy_from_slice(&src[body..]);
        ok &= buf.iter().all(|v| f64::from(v.abs()) <= HALF_MAX);
        let mut h = [0u16; 8];
        // SAFETY: eight entries each side.
        unsafe {
            let v = _mm256_cvtps_ph::<_MM_FROUND_TO_NEAREST_INT>(_mm256_loadu_ps(buf.as_ptr()));
            _mm_storeu_si128(h.as_mut_ptr().cast(), v);
        }
        out[body..].copy_from_slice(&h[..tail]);
    }
    ok
}

#[cfg(target_arch = "x86_64")]
impl HalfCopy {
    /// Checks that `sym` and `y` fit this copy and each other (what the
    /// sweeps' unchecked accesses rely on, with `sym`'s own structure); returns
    /// the number of nodes.
    fn check(&self, sym: Structure<'_>, y: &[[f32; 4]]) -> usize {
        let n = sym.perm.len();
        assert!(
            y.len() >= n
                && sym.col_ptr.len() == n + 1
                && sym.joins_next.len() >= n
                && self.l.len() >= 9 * sym.row_idx.len() + 4,
            "half-precision sweep: structure, copy and vector do not fit"
        );
        n
    }

    /// Column `k` of block `p` in lanes 0–2; lane 3 is the next entry (the
    /// kernels multiply it by a lane held at zero).
    ///
    /// # Safety
    /// `9 p + 3 k + 4 <= l.len()`, which holds for every block and column.
    #[inline]
    #[target_feature(enable = "avx2,fma,f16c")]
    unsafe fn col(&self, p: usize, k: usize) -> std::arch::x86_64::__m128 {
        use std::arch::x86_64::*;
        // SAFETY: the caller guarantees four readable halves.
        unsafe {
            _mm_cvtph_ps(_mm_loadl_epi64(
                self.l.as_ptr().add(9 * p + 3 * k).cast::<__m128i>(),
            ))
        }
    }

    /// Forward sweep `L̃ y = y` in place (permuted numbering), with the
    /// structure of `LdltFactor::forward`'s AVX2 kernel: two
    /// columns of one supernode share each row's load and store.
    ///
    /// # Safety
    /// The CPU must have AVX2, FMA and F16C; the copy must be valid for
    /// `sym`'s factor and `y` hold `sym.n` entries.
    #[target_feature(enable = "avx2,fma,f16c")]
    unsafe fn forward(&self, sym: Structure<'_>, y: &mut [[f32; 4]]) {
        use std::arch::x86_64::*;
        let n = self.check(sym, y);
        let yp = y.as_mut_ptr().cast::<f32>();
        // Broadcasts of a solved node's entries, lane 3 zero.
        let splat = |v: [f32; 4]| {
            [
                _mm_set_ps(0.0, v[0], v[0], v[0]),
                _mm_set_ps(0.0, v[1], v[1], v[1]),
                _mm_set_ps(0.0, v[2], v[2], v[2]),
            ]
        };
        let solve = |v: &mut [f32; 4], l: &[f32; 4]| {
            v[1] -= l[0] * v[0];
            v[2] -= l[1] * v[0] + l[2] * v[1];
        };
        let mut j = 0;
        while j < n {
            // SAFETY: `j < n`; blocks of `L` and rows below `n` throughout
            // (the structure of `sym`).
            unsafe {
                let yj = &mut *yp.add(4 * j).cast::<[f32; 4]>();
                solve(yj, &self.diag[j]);
                let b = splat(*yj);
                let (start, end) = (sym.col_ptr[j], sym.col_ptr[j + 1]);
                if sym.joins_next[j] {
                    // Column `j`'s first block is row `j + 1`; its other rows
                    // are column `j + 1`'s.
                    let (start1, end1) = (sym.col_ptr[j + 1], sym.col_ptr[j + 2]);
                    let p1 = yp.add(4 * (j + 1));
                    let mut acc = _mm_loadu_ps(p1);
                    for k in 0..3 {
                        acc = _mm_fnmadd_ps(self.col(start, k), b[k], acc);
                    }
                    _mm_storeu_ps(p1, acc);
                    let y1 = &mut *p1.cast::<[f32; 4]>();
                    solve(y1, &self.diag[j + 1]);
                    let b1 = splat(*y1);
                    for (t, &r) in sym.row_idx[start1..end1].iter().enumerate() {
                        let pr = yp.add(4 * r);
                        let mut acc = _mm_loadu_ps(pr);
                        for k in 0..3 {
                            acc = _mm_fnmadd_ps(self.col(start + 1 + t, k), b[k], acc);
                        }
                        for k in 0..3 {
                            acc = _mm_fnmadd_ps(self.col(start1 + t, k), b1[k], acc);
                        }
                        _mm_storeu_ps(pr, acc);
                    }
                    j += 2;
                    continue;
                }
                for (p, &r) in (start..end).zip(&sym.row_idx[start..end]) {
                    let pr = yp.add(4 * r);
                    let mut acc = _mm_loadu_ps(pr);
                    for k in 0..3 {
                        acc = _mm_fnmadd_ps(self.col(p, k), b[k], acc);
                    }
                    _mm_storeu_ps(pr, acc);
                }
            }
            j += 1;
        }
    }

    /// Backward sweep `L̃ᵀ y = y` in place (permuted numbering): each column
    /// of a block accumulates its products with `y_r` over the whole column
    /// of `L̃` and is summed once per node; two or three columns of one
    /// supernode share each row's load (see
    /// `LdltFactor::backward`'s AVX2 kernel).
    ///
    /// # Safety
    /// As [`Self::forward`].
    #[target_feature(enable = "avx2,fma,f16c")]
    unsafe fn backward(&self, sym: Structure<'_>, y: &mut [[f32; 4]]) {
        use std::arch::x86_64::*;
        let n = self.check(sym, y);
        let yp = y.as_mut_ptr().cast::<f32>();
        let zero = _mm_setzero_ps();
        // `y_j − Σ`, solved with the diagonal block, into `y_j`. Lane 3 of
        // every product is zero (`y`'s lane 3 is), so the sums take all four.
        // SAFETY (callers): `j < n`.
        let finish = |j: usize, acc: [__m128; 3]| unsafe {
            let s = _mm_hadd_ps(_mm_hadd_ps(acc[0], acc[1]), _mm_hadd_ps(acc[2], zero));
            let pj = yp.add(4 * j);
            let r = _mm_sub_ps(_mm_loadu_ps(pj), s);
            let mut v = [0.0f32; 4];
            _mm_storeu_ps(v.as_mut_ptr(), r);
            let l = &self.diag[j];
            let x2 = v[2];
            let x1 = v[1] - l[2] * x2;
            let x0 = v[0] - l[0] * x1 - l[1] * x2;
            *pj.cast::<[f32; 4]>() = [x0, x1, x2, 0.0];
        };
        let mut j = n;
        while j > 0 {
            j -= 1;
            // SAFETY (the three cases): blocks of `L` and rows below `n`
            // (the structure of `sym`).
            if j > 1 && sym.joins_next[j - 1] && sym.joins_next[j - 2] {
                unsafe { self.backward_group::<3>(sym, yp, j, &finish) };
                j -= 2;
                continue;
            }
            if j > 0 && sym.joins_next[j - 1] {
                unsafe { self.backward_group::<2>(sym, yp, j, &finish) };
                j -= 1;
                continue;
            }
            // A lone column: its blocks over two sets of sums, so consecutive
            // multiply-adds do not wait on each other.
            let (start, end) = (sym.col_ptr[j], sym.col_ptr[j + 1]);
            let mut acc = [zero; 3];
            let mut acc2 = [zero; 3];
            unsafe {
                let rows = &sym.row_idx[start..end];
                let mut t = end - start;
                while t >= 2 {
                    t -= 2;
                    let va = _mm_loadu_ps(yp.add(4 * rows[t + 1]));
                    let vb = _mm_loadu_ps(yp.add(4 * rows[t]));
                    for k in 0..3 {
                        acc[k] = _mm_fmadd_ps(self.col(start + t + 1, k), va, acc[k]);
                        acc2[k] = _mm_fmadd_ps(self.col(start + t, k), vb, acc2[k]);
                    }
                }
                if t == 1 {
                    let v = _mm_loadu_ps(yp.add(4 * rows[0]));
                    for k in 0..3 {
                        acc[k] = _mm_fmadd_ps(self.col(start, k), v, acc[k]);
                    }
                }
                for k in 0..3 {
                    acc[k] = _mm_add_ps(acc[k], acc2[k]);
                }
                finish(j, acc);
            }
        }
    }

    /// Columns `j − G + 1` to `j` of one supernode in the backward sweep
    /// (column `j − g`'s rows are `j − g + 1` to `j`, then column `j`'s):
    /// each row of column `j` is read once for all `G`, and each column is
    /// finished as soon as the nodes after it are.
    ///
    /// # Safety
    /// As [`Self::backward`], with `yp` its `y` and `j − G + 1` to `j` joined.
    #[inline]
    #[target_feature(enable = "avx2,fma,f16c")]
    unsafe fn backward_group<const G: usize>(
        &self,
        sym: Structure<'_>,
        yp: *mut f32,
        j: usize,
        finish: &impl Fn(usize, [std::arch::x86_64::__m128; 3]),
    ) {
        use std::arch::x86_64::*;
        let (start, end) = (sym.col_ptr[j], sym.col_ptr[j + 1]);
        // Column `j − g`'s block in the row of column `j`'s block `t` is
        // `starts[g] + t`.
        let starts: [usize; G] = std::array::from_fn(|g| sym.col_ptr[j - g] + g);
        let mut acc = [[_mm_setzero_ps(); 3]; G];
        // SAFETY: the caller's guarantees.
        unsafe {
            for t in (0..end - start).rev() {
                let v = _mm_loadu_ps(yp.add(4 * sym.row_idx[start + t]));
                for (a, &s) in acc.iter_mut().zip(&starts) {
                    for k in 0..3 {
                        a[k] = _mm_fmadd_ps(self.col(s + t, k), v, a[k]);
                    }
                }
            }
            finish(j, acc[0]);
            for done in 1..G {
                let v = _mm_loadu_ps(yp.add(4 * (j + 1 - done)));
                for g in done..G {
                    for k in 0..3 {
                        acc[g][k] = _mm_fmadd_ps(self.col(starts[g] - done, k), v, acc[g][k]);
                    }
                }
                finish(j - done, acc[done]);
            }
        }
    }
}
