//! The Newton system of a subspace step: its matrix over the free rows,
//! solved by blocks ([`Split`]: a Cholesky factor of the
//! `δ = 0` rows and an LU of the sliding rows' Schur complement), by phase
//! 1's Cholesky factor and one column per sliding contact, or by one LU of
//! the whole; the normwise backward error that checks the block solves; and
//! the room each needs, sized up front.

use std::mem::MaybeUninit;

use faer::dyn_stack::MemStack;
use faer::linalg::lu::partial_pivoting as lu;
use faer::perm::PermRef;
use faer::{MatMut, Par};

use super::scratch::{Slide, Split, SubspaceScratch};

/// Capacity for at least `cap` entries in `v`.
fn room<T>(v: &mut Vec<T>, cap: usize) {
    v.reserve(cap.saturating_sub(v.len()));
}

impl Split {
    /// `K = W_RR + shift · diag W_RR` over the rows `R` the caller put in
    /// `k_rows`, Cholesky-factored in place into `k` ([`Self::k_valid`]).
    /// False where `K` is not positive definite in floating point.
    fn factor_k(&mut self, w: &[f64], m: usize, shift: f64, mem: &mut [MaybeUninit<u8>]) -> bool {
        let n = self.k_rows.len();
        // Not zeroed: the lower triangle is filled below, and the Cholesky
        // factorization and its solves read the lower triangle only.
        self.k.resize(n * n, 0.0);
        // A column at a time: column c of W over the rows is row c of W (W
        // is symmetric).
        for (j, &cj) in self.k_rows.iter().enumerate() {
            let wc = &w[cj * m..(cj + 1) * m];
            let col = &mut self.k[j * n + j..(j + 1) * n];
            for (c, &ri) in col.iter_mut().zip(&self.k_rows[j..]) {
                *c = wc[ri];
            }
            // The diagonal shifted: a damped step (see NEWTON_SHIFTS).
            col[0] *= 1.0 + shift;
        }
        let chol = faer::linalg::cholesky::llt::factor::cholesky_in_place(
            MatMut::from_column_major_slice_mut(&mut self.k, n, n),
            Default::default(),
            Par::Seq,
            MemStack::new(mem),
            Default::default(),
        );
        self.k_valid = chol.is_ok();
        self.k_shift = shift;
        self.k_valid
    }

    /// The LU (partial pivoting) of `s`, `ns × ns`, in place: the Schur
    /// complement of a split, or phase 1's `I + Eᵀ Z` ([`solve_phase1`]);
    /// [`back_substitute`] solves with it.
    fn factor_small(&mut self, ns: usize, mem: &mut [MaybeUninit<u8>]) {
        self.perm.clear();
        self.perm.resize(ns, 0);
        self.perm_inv.clear();
        self.perm_inv.resize(ns, 0);
        lu::factor::lu_in_place(
            MatMut::from_column_major_slice_mut(&mut self.s, ns, ns),
            &mut self.perm,
            &mut self.perm_inv,
            Par::Seq,
            MemStack::new(mem),
            Default::default(),
        );
    }

    /// Room for the blocks of any split of `n` free rows (`|A| |S| ≤ n²/4`,
    /// `|S| ≤ 2n/3`).
    fn reserve(&mut self, n: usize) {
        let quarter = n * n / 4 + n;
        room(&mut self.k, n * n);
        room(&mut self.x, quarter);
        room(&mut self.c, quarter);
        room(&mut self.s, 4 * n * n / 9 + n);
        for v in [&mut self.ya, &mut self.ys, &mut self.step] {
            room(v, n);
        }
        room(&mut self.slide_pos, n);
        for v in [
            &mut self.pos_a,
            &mut self.pos_s,
            &mut self.pos_s_prev,
            &mut self.kx_rows,
            &mut self.k_rows,
            &mut self.perm,
            &mut self.perm_inv,
        ] {
            room(v, n);
        }
    }
}

impl SubspaceScratch {
    /// Room for a factorization of `n` free rows, whole or split, in every
    /// buffer either uses: the two share the largest `n` seen, so that
    /// neither allocates once the free rows have stopped growing, whichever
    /// phase meets them first.
    fn reserve(&mut self, n: usize) {
        room(&mut self.mat, n * n);
        room(&mut self.rhs, n);
        room(&mut self.perm, n);
        room(&mut self.perm_inv, n);
        self.split.reserve(n);
        self.mem.resize(
            workspace(n).unaligned_bytes_required(),
            MaybeUninit::uninit(),
        );
    }
}

/// The Newton step's right-hand side over the free rows, into `s.rhs`:
/// `−δ_r` for a row `δ_r = 0` (the normal row of a sliding contact too), and
/// in phase 2 (`full`) the sliding contact's tangential rows, see
/// [`Slide::rhs`].
fn newton_rhs(s: &mut SubspaceScratch, full: bool) {
    s.rhs.clear();
    s.rhs.extend(s.free.iter().map(|&r| -s.delta[r]));
    if !full {
        return;
    }
    for (i, &r) in s.free.iter().enumerate() {
        if let Some(sl) = s.slide.get(r).copied().flatten() {
            for k in 0..2 {
                s.rhs[i + 1 + k] = sl.rhs(&s.lambda, r, k);
            }
        }
    }
}

/// Step 2: builds the Newton matrix over the free rows and solves it into
/// `s.rhs`. Row `i` of the matrix is free row `r_i`'s equation: `δ_{r_i} = 0`,
/// or for the tangential rows of a sliding contact the linearized
/// `λ_t − μ λ_n P = 0` (phase 2, `full`; in phase 1 a sliding contact has
/// only its normal row free).
pub(super) fn solve_newton(
    w: &[f64],
    m: usize,
    s: &mut SubspaceScratch,
    full: bool,
    reuse: bool,
) -> Option<()> {
    let n = s.free.len();
    if !reuse {
        s.reserve(n);
    }
    if full && solve_split(w, m, s, reuse) {
        return s.rhs.iter().all(|v| v.is_finite()).then_some(());
    }
    if !full && !reuse && solve_phase1(w, m, s) {
        return s.rhs.iter().all(|v| v.is_finite()).then_some(());
    }
    newton_rhs(s, full);
    if !reuse {
        s.mat.resize(n * n, 0.0);
        newton_matrix(w, m, s, full);
        s.factorizations += 1;
        s.perm.clear();
        s.perm.resize(n, 0);
        s.perm_inv.clear();
        s.perm_inv.resize(n, 0);
        let a = MatMut::from_column_major_slice_mut(&mut s.mat, n, n);
        lu::factor::lu_in_place(
            a,
            &mut s.perm,
            &mut s.perm_inv,
            Par::Seq,
            MemStack::new(&mut s.mem),
            Default::default(),
        );
    }
    let perm = PermRef::new_checked(&s.perm, &s.perm_inv, n);
    let lu = faer::MatRef::from_column_major_slice(&s.mat, n, n);
    let rhs = MatMut::from_column_major_slice_mut(&mut s.rhs, n, 1);
    lu::solve::solve_in_place(lu, lu, perm, rhs, Par::Seq, MemStack::new(&mut s.mem));
    s.rhs.iter().all(|v| v.is_finite()).then_some(())
}

/// faer's workspace for any factorization and solve of `n` free rows,
/// whole or split: sized by `n` alone, so that it grows only with `n`.
fn workspace(n: usize) -> faer::dyn_stack::StackReq {
    lu::factor::lu_in_place_scratch::<usize, f64>(n, n, Par::Seq, Default::default())
        .or(lu::solve::solve_in_place_scratch::<usize, f64>(
            n,
            1,
            Par::Seq,
        ))
        .or(
            faer::linalg::cholesky::llt::factor::cholesky_in_place_scratch::<f64>(
                n,
                Par::Seq,
                Default::default(),
            ),
        )
}

/// Phase 2's Newton step by blocks ([`Split`]) into `s.rhs`: factors `K`,
/// `X` and the Schur complement unless `reuse` (a chord step on the factors
/// of the same free rows). Returns false where it did not solve: `K` not
/// positive definite in floating point, a chord step on factors it did not
/// make, or [`Split::lu_only`]; the caller then solves by one LU.
/// Its buffers and faer's workspace have room already
/// ([`SubspaceScratch::reserve`], before every factorization).
pub(super) fn solve_split(w: &[f64], m: usize, s: &mut SubspaceScratch, reuse: bool) -> bool {
    if s.split.lu_only || reuse && !s.split.factored {
        return false;
    }
    let n = s.free.len();
    let sp = &mut s.split;
    if !reuse {
        sp.factored = false;
        std::mem::swap(&mut sp.pos_s, &mut sp.pos_s_prev);
        sp.pos_a.clear();
        sp.pos_s.clear();
        let mut i = 0;
        while i < n {
            sp.pos_a.push(i);
            if s.slide[s.free[i]].is_some() {
                sp.pos_s.extend([i + 1, i + 2]);
                i += 3;
            } else {
                i += 1;
            }
        }
    }
    let (na, ns) = (sp.pos_a.len(), sp.pos_s.len());
    if !reuse {
        let keep = sp.kx_valid
            && sp.kx_shift == s.shift
            && sp.kx_rows == s.free
            && sp.pos_s == sp.pos_s_prev;
        if !keep {
            sp.kx_valid = false;
            // The Cholesky factor of `K` that phase 1's last step made on
            // these rows (phase 1 ends where its active set repeats, and its
            // free rows are the `A` rows), if it is there.
            let k_ready = sp.k_valid
                && sp.k_shift == s.shift
                && sp.k_rows.len() == na
                && sp
                    .pos_a
                    .iter()
                    .zip(&sp.k_rows)
                    .all(|(&pi, &r)| s.free[pi] == r);
            sp.x.clear();
            sp.x.resize(na * ns, 0.0);
            for (js, &pj) in sp.pos_s.iter().enumerate() {
                let wc = &w[s.free[pj] * m..(s.free[pj] + 1) * m];
                let col = &mut sp.x[js * na..(js + 1) * na];
                for (c, &pi) in col.iter_mut().zip(&sp.pos_a) {
                    *c = wc[s.free[pi]];
                }
            }
            if !k_ready {
                sp.k_rows.clear();
                sp.k_rows.extend(sp.pos_a.iter().map(|&pi| s.free[pi]));
                if !sp.factor_k(w, m, s.shift, &mut s.mem) {
                    return false;
                }
                s.factorizations += 1;
            }
            if ns > 0 {
                faer::linalg::cholesky::llt::solve::solve_in_place(
                    faer::MatRef::from_column_major_slice(&sp.k, na, na),
                    MatMut::from_column_major_slice_mut(&mut sp.x, na, ns),
                    Par::Seq,
                    MemStack::new(&mut s.mem),
                );
            }
            sp.kx_valid = true;
            sp.kx_rows.clone_from(&s.free);
            sp.kx_shift = s.shift;
        }
        // C_SAᵀ and D_SS: the linearized λ_t − μ λ_n P = 0 of each sliding
        // contact (see `solve_newton`), one column of C_SAᵀ per sliding row.
        sp.c.clear();
        sp.c.resize(na * ns, 0.0);
        sp.s.clear();
        sp.s.resize(ns * ns, 0.0);
        let mut is = 0;
        for (ia, &pi) in sp.pos_a.iter().enumerate() {
            let r = s.free[pi];
            let Some(sl) = s.slide[r] else {
                continue;
            };
            let (w1, w2) = (&w[(r + 1) * m..(r + 2) * m], &w[(r + 2) * m..(r + 3) * m]);
            for k in 0..2 {
                let (row, eq) = (is + k, sl.row(k));
                let col = &mut sp.c[row * na..(row + 1) * na];
                for (c, &pj) in col.iter_mut().zip(&sp.pos_a) {
                    *c = eq.w(w1, w2, s.free[pj]);
                }
                col[ia] += eq.own[0];
                for (js, &pj) in sp.pos_s.iter().enumerate() {
                    sp.s[js * ns + row] = eq.w(w1, w2, s.free[pj]);
                }
                for l in 0..2 {
                    sp.s[(is + l) * ns + row] += eq.own[1 + l];
                }
            }
            is += 2;
        }
        if ns > 0 {
            // S = D_SS − C_SA X, then its LU.
            faer::linalg::matmul::matmul(
                MatMut::from_column_major_slice_mut(&mut sp.s, ns, ns),
                faer::Accum::Add,
                faer::MatRef::from_column_major_slice(&sp.c, na, ns).transpose(),
                faer::MatRef::from_column_major_slice(&sp.x, na, ns),
                -1.0,
                Par::Seq,
            );
            sp.factor_small(ns, &mut s.mem);
        }
        sp.factored = true;
    }
    // The right-hand sides as the whole matrix's (`−δ_r`, and
    // `−(λ_t − μ λ_n P)` on the tangential rows of the contacts sliding now:
    // in a chord step across solves a contact can have changed between
    // sticking and sliding), by the blocks of the factorization.
    newton_rhs(s, true);
    let sp = &mut s.split;
    sp.ya.clear();
    sp.ya.extend(sp.pos_a.iter().map(|&i| s.rhs[i]));
    sp.ys.clear();
    sp.ys.extend(sp.pos_s.iter().map(|&i| s.rhs[i]));
    let l = faer::MatRef::from_column_major_slice(&sp.k, na, na);
    let ya = MatMut::from_column_major_slice_mut(&mut sp.ya, na, 1);
    faer::linalg::cholesky::llt::solve::solve_in_place(l, ya, Par::Seq, MemStack::new(&mut s.mem));
    if ns > 0 {
        faer::linalg::matmul::matmul(
            MatMut::from_column_major_slice_mut(&mut sp.ys, ns, 1),
            faer::Accum::Add,
            faer::MatRef::from_column_major_slice(&sp.c, na, ns).transpose(),
            faer::MatRef::from_column_major_slice(&sp.ya, na, 1),
            -1.0,
            Par::Seq,
        );
        back_substitute(sp, na, ns, &mut s.mem);
    }
    // The step by position; `s.rhs` still holds the right-hand side.
    sp.step.clear();
    sp.step.resize(n, 0.0);
    for (&pi, &v) in sp.pos_a.iter().zip(&sp.ya) {
        sp.step[pi] = v;
    }
    for (&pi, &v) in sp.pos_s.iter().zip(&sp.ys) {
        sp.step[pi] = v;
    }
    if !reuse && backward_error(w, m, s, &s.split.step, true) > SPLIT_BACKWARD_ERROR {
        // Not as good as one LU of the whole would be: that instead.
        s.split.factored = false;
        s.split.kx_valid = false;
        s.split.k_valid = false;
        return false;
    }
    std::mem::swap(&mut s.rhs, &mut s.split.step);
    true
}

/// The small system's part of a step by blocks, shared by [`solve_split`]
/// and [`solve_phase1`]: `ys ← S⁻¹ ys` by the LU in `s` (`ns` rows), then
/// `ya ← ya − X ys` (`X` is `rows × ns`, in `x`).
fn back_substitute(sp: &mut Split, rows: usize, ns: usize, mem: &mut [MaybeUninit<u8>]) {
    let perm = PermRef::new_checked(&sp.perm, &sp.perm_inv, ns);
    let lu = faer::MatRef::from_column_major_slice(&sp.s, ns, ns);
    let ys = MatMut::from_column_major_slice_mut(&mut sp.ys, ns, 1);
    lu::solve::solve_in_place(lu, lu, perm, ys, Par::Seq, MemStack::new(mem));
    faer::linalg::matmul::matmul(
        MatMut::from_column_major_slice_mut(&mut sp.ya, rows, 1),
        faer::Accum::Add,
        faer::MatRef::from_column_major_slice(&sp.x, rows, ns),
        faer::MatRef::from_column_major_slice(&sp.ys, ns, 1),
        -1.0,
        Par::Seq,
    );
}

/// Phase 1's Newton step by Cholesky, into `s.rhs`: its matrix is
/// `K + U Eᵀ`, `K = W_FF + ε diag W_FF` over the free rows (symmetric
/// positive definite, as in [`Split`]) and one column `U_j = μ (P₀ W_{F,t₀} +
/// P₁ W_{F,t₁})` per sliding contact, added in its normal row's column `j`
/// (`E` picks those columns): the tangential force that follows the normal
/// force. By the Sherman–Morrison–Woodbury identity, with `Z = K⁻¹ U` and
/// `y = K⁻¹ b`, the step is `y − Z (I + Eᵀ Z)⁻¹ Eᵀ y`: a Cholesky factor
/// (`|F|³/3`), `2 |F|² |S|` for `Z` and an LU of `|S|` rows, against
/// `2/3 |F|³` for the LU of the whole, where `|S| ≤ |F| / 4`. Phase 1 ends
/// where its free rows repeat, and they are then phase 2's `A` rows: the
/// first split takes this `K` (see [`Split::k_valid`]). Returns false where it
/// did not solve (too many sliding contacts, `K` not positive definite in
/// floating point, a backward error above [`SPLIT_BACKWARD_ERROR`], or
/// [`Split::lu_only`]); the caller then solves by one LU. On the accuracy
/// study's lens through the hole phase 1's free rows are 450–530 with 40–80
/// sliding contacts.
pub(super) fn solve_phase1(w: &[f64], m: usize, s: &mut SubspaceScratch) -> bool {
    if s.split.lu_only {
        return false;
    }
    let n = s.free.len();
    phase1_slides(s);
    let sp = &mut s.split;
    let ns = sp.slide_pos.len();
    if 4 * ns > n {
        return false;
    }
    // The split's factors are overwritten below.
    sp.factored = false;
    sp.kx_valid = false;
    sp.x.clear();
    sp.x.resize(n * ns, 0.0);
    for (l, &(j, mu, p)) in sp.slide_pos.iter().enumerate() {
        let cj = s.free[j];
        let (w1, w2) = (
            &w[(cj + 1) * m..(cj + 2) * m],
            &w[(cj + 2) * m..(cj + 3) * m],
        );
        for (c, &ri) in sp.x[l * n..(l + 1) * n].iter_mut().zip(&s.free) {
            *c = mu * (p[0] * w1[ri] + p[1] * w2[ri]);
        }
    }
    sp.k_rows.clone_from(&s.free);
    if !sp.factor_k(w, m, s.shift, &mut s.mem) {
        return false;
    }
    s.factorizations += 1;
    newton_rhs(s, false);
    let sp = &mut s.split;
    let l = faer::MatRef::from_column_major_slice(&sp.k, n, n);
    sp.ya.clone_from(&s.rhs);
    faer::linalg::cholesky::llt::solve::solve_in_place(
        l,
        MatMut::from_column_major_slice_mut(&mut sp.ya, n, 1),
        Par::Seq,
        MemStack::new(&mut s.mem),
    );
    if ns > 0 {
        faer::linalg::cholesky::llt::solve::solve_in_place(
            l,
            MatMut::from_column_major_slice_mut(&mut sp.x, n, ns),
            Par::Seq,
            MemStack::new(&mut s.mem),
        );
        // I + Eᵀ Z, its LU, and (I + Eᵀ Z)⁻¹ Eᵀ y.
        sp.s.clear();
        sp.s.resize(ns * ns, 0.0);
        for c in 0..ns {
            for (r, &(j, ..)) in sp.slide_pos.iter().enumerate() {
                sp.s[c * ns + r] = sp.x[c * n + j];
            }
            sp.s[c * ns + c] += 1.0;
        }
        sp.factor_small(ns, &mut s.mem);
        sp.ys.clear();
        sp.ys.extend(sp.slide_pos.iter().map(|&(j, ..)| sp.ya[j]));
        back_substitute(sp, n, ns, &mut s.mem);
    }
    // A NaN fails the check too.
    let e = backward_error(w, m, s, &s.split.ya, false);
    if e.is_nan() || e > SPLIT_BACKWARD_ERROR {
        return false;
    }
    std::mem::swap(&mut s.rhs, &mut s.split.ya);
    true
}

/// The largest normwise backward error a split step ([`solve_split`]) may
/// have, `‖M Δλ − b‖∞ / (‖M‖∞ ‖Δλ‖∞ + ‖b‖∞)` for the whole Newton matrix `M`.
/// An LU with partial pivoting leaves about `n ε` (2·10⁻¹³ for a thousand
/// free rows); the Schur complement of a nearly singular `K` can leave more,
/// and then the step is solved by one LU instead.
pub(super) const SPLIT_BACKWARD_ERROR: f64 = 1e-10;

/// The normwise backward error of the step `x` (by position in `s.free`)
/// for the whole Newton matrix of phase 2 (`full`) or phase 1, as
/// `solve_newton` builds it, and the right-hand side in `s.rhs`: one product
/// with the matrix's rows, a small fraction of a factorization. Each row is
/// one pass over `W`'s entries in the free columns ([`free_dot_abs`]); the
/// diagonal's shift, phase 1's sliding columns (as [`phase1_slides`] listed
/// them: their tangential force, by `W`'s symmetry from the same row) and
/// phase 2's sliding rows' own entries are added to it.
pub(super) fn backward_error(
    w: &[f64],
    m: usize,
    s: &SubspaceScratch,
    x: &[f64],
    full: bool,
) -> f64 {
    let b = &s.rhs;
    let n = s.free.len();
    let slides: &[(usize, f64, [f64; 2])] = if full { &[] } else { &s.split.slide_pos };
    let (mut r_max, mut m_max) = (0.0f64, 0.0f64);
    let x_max = x.iter().fold(0.0f64, |a, v| a.max(v.abs()));
    let b_max = b.iter().fold(0.0f64, |a, v| a.max(v.abs()));
    let mut i = 0;
    while i < n {
        let r = s.free[i];
        // δ_r = 0: row r of W over the free columns, its diagonal shifted;
        // in phase 1 a sliding normal's column carries its tangential force.
        let row = &w[r * m..(r + 1) * m];
        let (mut sum, mut abs) = free_dot_abs(1.0, row, 0.0, row, &s.free, x);
        sum += s.shift * row[r] * x[i];
        abs += s.shift * row[r].abs();
        for &(j, mu, p) in slides {
            let cj = s.free[j];
            let plain = row[cj] * if j == i { 1.0 + s.shift } else { 1.0 };
            // As `delta_columns` forms it.
            let t = mu * (p[0] * row[cj + 1] + p[1] * row[cj + 2]);
            sum += t * x[j];
            abs += (plain + t).abs() - plain.abs();
        }
        r_max = r_max.max((sum - b[i]).abs());
        m_max = m_max.max(abs);
        let Some(sl) = s.slide[r].filter(|_| full) else {
            i += 1;
            continue;
        };
        let (w1, w2) = (&w[(r + 1) * m..(r + 2) * m], &w[(r + 2) * m..(r + 3) * m]);
        for k in 0..2 {
            let eq = sl.row(k);
            let (mut sum, mut abs) = free_dot_abs(eq.a, w1, eq.b, w2, &s.free, x);
            // The λ part, on the contact's own three columns.
            for (l, &own) in eq.own.iter().enumerate() {
                let v = eq.w(w1, w2, r + l);
                sum += own * x[i + l];
                abs += (v + own).abs() - v.abs();
            }
            r_max = r_max.max((sum - b[i + 1 + k]).abs());
            m_max = m_max.max(abs);
        }
        i += 3;
    }
    let scale = m_max * x_max + b_max;
    if scale > 0.0 { r_max / scale } else { 0.0 }
}

/// `(Σ_j v_j x_j, Σ_j |v_j|)` over the free columns `c_j`, with
/// `v_j = α u[c_j] + β t[c_j]`: four partial sums each, so that the
/// scattered loads, not one long chain of additions, set the pace.
fn free_dot_abs(
    alpha: f64,
    u: &[f64],
    beta: f64,
    t: &[f64],
    free: &[usize],
    x: &[f64],
) -> (f64, f64) {
    let (mut sum, mut abs) = ([0.0f64; 4], [0.0f64; 4]);
    let (cols, xs) = (free.chunks_exact(4), x[..free.len()].chunks_exact(4));
    let (rest_c, rest_x) = (cols.remainder(), xs.remainder());
    for (c, xc) in cols.zip(xs) {
        for k in 0..4 {
            let v = alpha * u[c[k]] + beta * t[c[k]];
            sum[k] += v * xc[k];
            abs[k] += v.abs();
        }
    }
    let (mut s, mut a) = (
        (sum[0] + sum[1]) + (sum[2] + sum[3]),
        (abs[0] + abs[1]) + (abs[2] + abs[3]),
    );
    for (&c, &xc) in rest_c.iter().zip(rest_x) {
        let v = alpha * u[c] + beta * t[c];
        s += v * xc;
        a += v.abs();
    }
    (s, a)
}

/// Phase 1's sliding normal rows of the free rows into
/// [`Split::slide_pos`], for its step ([`solve_phase1`]) and the step's
/// [`backward_error`].
pub(super) fn phase1_slides(s: &mut SubspaceScratch) {
    let sp = &mut s.split;
    sp.slide_pos.clear();
    sp.slide_pos
        .extend(s.free.iter().enumerate().filter_map(|(j, &cj)| {
            let Slide { p, mu, .. } = s.slide[cj]?;
            Some((j, mu, p))
        }));
}

/// The whole Newton matrix of phase 2 (`full`) or phase 1 over the free
/// rows into `s.mat` (column-major, `n × n`, every entry written): the
/// equations `δ_r = 0` ([`delta_columns`]), then the tangential rows i+1,
/// i+2 of a sliding contact (free rows r+1, r+2, pushed with its normal row
/// r), see [`Slide::row`].
pub(super) fn newton_matrix(w: &[f64], m: usize, s: &mut SubspaceScratch, full: bool) {
    let n = s.free.len();
    delta_columns(w, m, s, full);
    let mut i = 0;
    while i < n {
        let r = s.free[i];
        let Some(sl) = s.slide.get(r).copied().flatten().filter(|_| full) else {
            i += 1;
            continue;
        };
        let (w1, w2) = (&w[(r + 1) * m..(r + 2) * m], &w[(r + 2) * m..(r + 3) * m]);
        for k in 0..2 {
            let ik = i + 1 + k;
            let row = sl.row(k);
            for (j, &cj) in s.free.iter().enumerate() {
                s.mat[j * n + ik] = row.w(w1, w2, cj);
            }
            // The λ part: columns i (λ_n), i+1, i+2 (λ_t).
            for (l, v) in row.own.iter().enumerate() {
                s.mat[(i + l) * n + ik] += v;
            }
        }
        i += 3;
    }
}

/// The equations `δ_r = 0` of the Newton matrix: for each free row `r_i`,
/// row `r_i` of `W` over the free columns, where in phase 1 (`!full`) the
/// column of a sliding normal also carries its tangential force (`μ P` along
/// the tangential rows). Filled a column at a time (`W` is symmetric, so
/// column `c_j` over the free rows is row `c_j` of `W`): contiguous writes,
/// where a row at a time wrote one entry per column. Phase 2's tangential
/// rows of sliding contacts are filled too and then overwritten by their own
/// equations.
fn delta_columns(w: &[f64], m: usize, s: &mut SubspaceScratch, full: bool) {
    let n = s.free.len();
    for (j, &cj) in s.free.iter().enumerate() {
        let col = &mut s.mat[j * n..(j + 1) * n];
        let wc = &w[cj * m..(cj + 1) * m];
        match s.slide[cj].filter(|_| !full) {
            Some(Slide { p, mu, .. }) => {
                let (w1, w2) = (
                    &w[(cj + 1) * m..(cj + 2) * m],
                    &w[(cj + 2) * m..(cj + 3) * m],
                );
                for (c, &ri) in col.iter_mut().zip(&s.free) {
                    *c = wc[ri] + mu * (p[0] * w1[ri] + p[1] * w2[ri]);
                }
                // The diagonal shifted: a damped step (see NEWTON_SHIFTS).
                col[j] += wc[cj] * s.shift;
            }
            None => {
                for (c, &ri) in col.iter_mut().zip(&s.free) {
                    *c = wc[ri];
                }
                col[j] *= 1.0 + s.shift;
            }
        }
    }
}
