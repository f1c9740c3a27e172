//! Node columns of an `LDLᵀ` factor and their Gram blocks.
//!
//! For a node `k`, `Z_k = L⁻¹ P E_k` are the three unit columns of the node
//! after one forward solve; their nonzeros lie on the elimination-tree path of
//! `k` to the root ([`LdltFactor::node_forward_solve`]). The Gram block of two
//! nodes is `G_kl = Z_kᵀ D⁻¹ Z_l`, a sum over the common suffix of their paths.
//! Both depend only on the factor. The contact compliance
//! ([`crate::contact::ComplianceMode::Factorized`]) is built from them, and the
//! background factorization ([`super::AsyncFactorizer`]) computes them for the
//! nodes recently in contact ([`HINT_BUILDS`]) before it hands a new factor
//! over, so that the stepping thread finds them ready. Columns not cached yet
//! are solved eight at a time where the CPU has AVX2/FMA
//! (`ColumnCache::columns`), and a cache filled for one build or by the
//! worker forms its Gram blocks in tiles of columns
//! (`ColumnCache::all_pairs`).

use super::ldlt::{BATCH, BatchRows, LdltFactor};
use crate::math::Mat3;

/// Which factor a set of node columns (or a compliance build) belongs to.
///
/// Versions count separately per source, so a key names its source too:
/// columns of the compliance's own factorization number 3 are never taken for
/// the preconditioner's factor number 3.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum FactorKey {
    /// The preconditioner's factor in use, by its version
    /// ([`super::FactorState::version`]).
    Preconditioner(u64),
    /// A copy of the preconditioner's factor that the contact compliance keeps
    /// using for a few steps (`ContactSettings::factor_reuse`), by the version
    /// it was copied from.
    Snapshot(u64),
    /// The contact compliance's own factorization of the current matrix
    /// (`ComplianceMode::Exact`, or a body without a factor), by its count.
    Own(u64),
}

/// The hand-over of node columns between a body's contact compliance (on the
/// stepping thread) and its background factorizer: the nodes last in
/// contact (the hint), the columns of the newest factor, and memory to reuse.
///
/// The body owns it ([`crate::body::DeformableBody::column_prefetch_mut`]).
/// The contact compliance takes it out of the body for its build and puts it
/// back; the preconditioner reads the hint and fills the columns when it swaps
/// a factor in. No lock: both sides run on the stepping thread, and the
/// worker only sees the caches it is handed with a job.
#[derive(Debug, Default)]
pub struct ColumnPrefetch {
    /// Nodes whose columns the next background factorization precomputes:
    /// those of the last [`HINT_BUILDS`] compliance builds.
    pub(crate) hint: Vec<u32>,
    /// Per node: the number of the last build it was in (0: not in the hint).
    stamp: Vec<u32>,
    /// Builds so far.
    builds: u32,
    /// Columns of a factor swapped in (keyed), not yet taken.
    pub(crate) ready: Option<ColumnCache>,
    /// A cache whose memory the next precomputation reuses.
    pub(crate) spare: Option<ColumnCache>,
}

/// How many compliance builds a node stays in the hint after it was last in
/// contact. Contact sets flicker: in the cataract scene's jam, of the node
/// columns the stepping thread had to solve (nodes not in the worker's hint,
/// which held the last build only), 67 % were in contact within the last 3
/// builds, 88 % within 6 and 94 % within 15 (about 2.4 builds a step there).
/// Most of the columns the stepping thread still solves follow a consistency
/// refactor, a factor made on the stepping thread with no precomputed
/// columns (docs/benchmark-log.md, "Where the stepping thread's new columns
/// come from").
pub const HINT_BUILDS: u32 = 6;

/// Columns per tile of [`ColumnCache::precompute`]'s Gram blocks: two tiles
/// of columns (about 20 kB each along their paths on the paper-size lens)
/// fit a core's cache. 24 to 128 measured alike on the Fig. 3 scene, a
/// fifth less time than column order (docs/benchmark-log.md, "Where the
/// back-to-back `async` factor's age comes from").
pub(crate) const PRECOMPUTE_TILE: u32 = 32;

impl ColumnPrefetch {
    /// Keeps `c` for its memory, unless a spare is already kept.
    pub(crate) fn keep_spare(&mut self, c: ColumnCache) {
        if self.spare.is_none() {
            self.spare = Some(c);
        }
    }

    /// The columns of factor `key`, when the background worker precomputed
    /// them (taken once).
    pub(crate) fn take(&mut self, key: FactorKey) -> Option<ColumnCache> {
        if self.ready.as_ref().is_some_and(|c| c.key == Some(key)) {
            self.ready.take()
        } else {
            None
        }
    }

    /// Records the nodes of a compliance build: the next background
    /// factorization precomputes the columns of every node in one of the
    /// last [`HINT_BUILDS`] builds (only `Async` preconditioners have a
    /// worker to read it).
    pub(crate) fn set_hint(&mut self, nodes: impl Iterator<Item = u32>) {
        self.builds = self.builds.wrapping_add(1).max(1);
        let now = self.builds;
        for k in nodes {
            let i = k as usize;
            if i >= self.stamp.len() {
                self.stamp.resize(i + 1, 0);
            }
            if self.stamp[i] == 0 {
                self.hint.push(k);
            }
            self.stamp[i] = now;
        }
        let stamp = &mut self.stamp;
        self.hint.retain(|&k| {
            let keep = now.wrapping_sub(stamp[k as usize]) < HINT_BUILDS;
            if !keep {
                stamp[k as usize] = 0;
            }
            keep
        });
    }

    /// The nodes of the current hint.
    pub fn hint(&self) -> &[u32] {
        &self.hint
    }
}

/// Where the Gram block of columns `a` and `b` (either order) sits in
/// [`ColumnCache::pairs`]: row `max` of the lower triangle, column `min`.
fn pair_slot(a: u32, b: u32) -> usize {
    let (lo, hi) = (a.min(b) as usize, a.max(b) as usize);
    hi * (hi + 1) / 2 + lo
}

#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct Column {
    pub(crate) start: usize,
    pub(crate) len: usize,
    /// Offset of this column's unit-column-major copies in `soa_z` / `soa_s`.
    soa: usize,
}

/// The 3×3 block `Gᵢⱼ = Σ_r z[i][r] s[j][r]` of three columns against three,
/// all of one length: one pass over the rows with nine independent
/// accumulators (six loads per nine multiply-adds). On x86-64 with AVX2 and
/// FMA (detected at run time) the loop runs on four rows per vector with
/// fused multiply-adds; elsewhere a portable loop of two rows per step.
pub(crate) fn gram3(z: [&[f64]; 3], s: [&[f64]; 3]) -> Mat3 {
    #[cfg(target_arch = "x86_64")]
    if crate::math::has_avx2_fma() {
        // SAFETY: the CPU supports the features the function is compiled for.
        return unsafe { gram3_avx2(z, s) };
    }
    gram3_portable(z, s)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn gram3_avx2(z: [&[f64]; 3], s: [&[f64]; 3]) -> Mat3 {
    use std::arch::x86_64::*;
    let n = z[0].len();
    let (z0, z1, z2) = (&z[0][..n], &z[1][..n], &z[2][..n]);
    let (s0, s1, s2) = (&s[0][..n], &s[1][..n], &s[2][..n]);
    let full = n - n % 4;
    let mut acc = [_mm256_setzero_pd(); 9];
    let mut o = 0;
    while o < full {
        // SAFETY: `o + 4 <= n` and every slice has length `n`.
        let (za, sb) = unsafe {
            (
                [
                    _mm256_loadu_pd(z0.as_ptr().add(o)),
                    _mm256_loadu_pd(z1.as_ptr().add(o)),
                    _mm256_loadu_pd(z2.as_ptr().add(o)),
                ],
                [
                    _mm256_loadu_pd(s0.as_ptr().add(o)),
                    _mm256_loadu_pd(s1.as_ptr().add(o)),
                    _mm256_loadu_pd(s2.as_ptr().add(o)),
                ],
            )
        };
        for a in 0..3 {
            for b in 0..3 {
                acc[3 * a + b] = _mm256_fmadd_pd(za[a], sb[b], acc[3 * a + b]);
            }
        }
        o += 4;
    }
    let mut g = Mat3::zeros();
    for a in 0..3 {
        for b in 0..3 {
            let mut lanes = [0.0f64; 4];
            // SAFETY: `lanes` holds four f64.
            unsafe { _mm256_storeu_pd(lanes.as_mut_ptr(), acc[3 * a + b]) };
            let mut v = (lanes[0] + lanes[1]) + (lanes[2] + lanes[3]);
            for r in full..n {
                v += z[a][r] * s[b][r];
            }
            g[(a, b)] = v;
        }
    }
    g
}

/// [`gram3`] without SIMD intrinsics: rows in pairs, which the compiler vectorizes.
fn gram3_portable(z: [&[f64]; 3], s: [&[f64]; 3]) -> Mat3 {
    const W: usize = 2;
    let n = z[0].len();
    let (z0, z1, z2) = (&z[0][..n], &z[1][..n], &z[2][..n]);
    let (s0, s1, s2) = (&s[0][..n], &s[1][..n], &s[2][..n]);
    let mut acc = [[[0.0f64; W]; 3]; 3];
    let full = n - n % W;
    let mut o = 0;
    while o < full {
        let za = [&z0[o..o + W], &z1[o..o + W], &z2[o..o + W]];
        let sb = [&s0[o..o + W], &s1[o..o + W], &s2[o..o + W]];
        for a in 0..3 {
            for b in 0..3 {
                for k in 0..W {
                    acc[a][b][k] += za[a][k] * sb[b][k];
                }
            }
        }
        o += W;
    }
    let mut g = Mat3::zeros();
    for a in 0..3 {
        for b in 0..3 {
            let mut v = acc[a][b].iter().sum::<f64>();
            for r in full..n {
                v += z[a][r] * s[b][r];
            }
            g[(a, b)] = v;
        }
    }
    g
}

/// Cached node columns `Z_k` and Gram blocks of one factor.
#[derive(Debug, Default)]
pub struct ColumnCache {
    /// The factor these columns belong to (`None`: none yet, or forgotten).
    pub(crate) key: Option<FactorKey>,
    pub(crate) col_of_node: Vec<u32>,
    pub(crate) cols: Vec<Column>,
    pub(crate) paths: Vec<usize>,
    pub(crate) blocks: Vec<Mat3>,
    /// Per column, for each unit column `i`: the `3·len` entries `Z_t(r, i)` along the
    /// path, contiguous (`soa_z`), and the same for `D⁻¹ Z` (`soa_s`), so a Gram
    /// entry is one contiguous dot product.
    pub(crate) soa_z: Vec<f64>,
    pub(crate) soa_s: Vec<f64>,
    /// Gram blocks by column pair `(a ≤ b)`, at `b(b+1)/2 + a`, row by row as
    /// columns are added; `None` until computed.
    pub(crate) pairs: Vec<Option<Mat3>>,
    pub(crate) work: Vec<Mat3>,
    /// Scratch of the batched solves ([`Self::columns`]): zero between them.
    batch_work: Vec<BatchRows>,
    /// Scratch of [`Self::columns`]: the nodes it solves.
    pending: Vec<usize>,
    pub(crate) solves: usize,
    pub(crate) gram_blocks: usize,
}

impl ColumnCache {
    pub(crate) fn reset(&mut self, n: usize, key: FactorKey) {
        if self.col_of_node.len() != n {
            self.col_of_node = vec![u32::MAX; n];
            self.work = vec![Mat3::zeros(); n];
        } else {
            self.col_of_node.fill(u32::MAX);
        }
        self.cols.clear();
        self.paths.clear();
        self.blocks.clear();
        self.soa_z.clear();
        self.soa_s.clear();
        self.pairs.clear();
        self.key = Some(key);
    }

    pub(crate) fn column(&mut self, f: &LdltFactor, node: usize) -> u32 {
        let c = self.col_of_node[node];
        if c != u32::MAX {
            return c;
        }
        let id = self.new_id(node);
        let start = self.paths.len();
        f.node_forward_solve(node, &mut self.work, &mut self.paths, &mut self.blocks);
        self.finish(f, id, start, self.paths.len() - start);
        self.solves += 1;
        id
    }

    /// The next column id, for `node`'s column (made by the caller).
    fn new_id(&mut self, node: usize) -> u32 {
        let id = self.cols.len() as u32;
        self.cols.push(Column::default());
        self.pairs.resize(self.pairs.len() + id as usize + 1, None);
        self.col_of_node[node] = id;
        id
    }

    /// Column `id`: its path and blocks at `start..start + len` of `paths`
    /// and `blocks`; adds its `soa_z` and `soa_s` entries.
    fn finish(&mut self, f: &LdltFactor, id: u32, start: usize, len: usize) {
        let soa = self.soa_z.len();
        for i in 0..3 {
            for t in start..start + len {
                let d = f.d[self.paths[t]];
                let z = &self.blocks[t];
                for r in 0..3 {
                    self.soa_z.push(z[(r, i)]);
                    self.soa_s.push(z[(r, i)] / d[r]);
                }
            }
        }
        self.cols[id as usize] = Column { start, len, soa };
    }

    /// [`Self::column`] of each of `nodes` (original numbering, any order,
    /// repeats allowed, out of range ones skipped): the same ids, in the
    /// order of `nodes`, and the same columns to the bit. Where the CPU has
    /// AVX2/FMA, the columns not cached yet are solved [`BATCH`] at a time
    /// ([`LdltFactor::nodes_forward_solve`]), in the factor's elimination
    /// order, so that each batch's paths share most of their blocks.
    pub(crate) fn columns(&mut self, f: &LdltFactor, nodes: impl IntoIterator<Item = usize>) {
        let n = f.symbolic.n;
        if !crate::math::has_avx2_fma() {
            for k in nodes {
                if k < n {
                    self.column(f, k);
                }
            }
            return;
        }
        let mut pending = std::mem::take(&mut self.pending);
        pending.clear();
        for k in nodes {
            if k < n && self.col_of_node[k] == u32::MAX {
                self.new_id(k);
                pending.push(k);
            }
        }
        pending.sort_unstable_by_key(|&k| f.symbolic.iperm[k]);
        if !pending.is_empty() && self.batch_work.len() != n {
            self.batch_work.clear();
            self.batch_work.resize(n, [[0.0; 3 * BATCH]; 3]);
        }
        for chunk in pending.chunks(BATCH) {
            let mut start = self.paths.len();
            let lens = f.nodes_forward_solve(
                chunk,
                &mut self.batch_work,
                &mut self.paths,
                &mut self.blocks,
            );
            for (&k, len) in chunk.iter().zip(lens) {
                self.finish(f, self.col_of_node[k], start, len);
                start += len;
            }
        }
        self.solves += pending.len();
        self.pending = pending;
    }

    /// Solves the columns of `nodes` (original numbering, any order, repeats
    /// allowed) and every Gram block among them with factor `f`, as the cache
    /// of factor `key`.
    pub(crate) fn precompute(&mut self, f: &LdltFactor, key: FactorKey, nodes: &[u32]) {
        self.reset(f.symbolic.n, key);
        self.columns(f, nodes.iter().map(|&k| k as usize));
        self.all_pairs();
    }

    /// Every Gram block among the cached columns not cached yet, in tiles of
    /// columns: a tile pair's columns stay in the core's cache while their
    /// blocks are formed (in plain column order each pair read its two
    /// columns from the shared cache or memory). Each block is the same
    /// either way.
    pub(crate) fn all_pairs(&mut self) {
        let m = self.cols.len() as u32;
        for b0 in (0..m).step_by(PRECOMPUTE_TILE as usize) {
            let b1 = (b0 + PRECOMPUTE_TILE).min(m);
            for a0 in (0..b1).step_by(PRECOMPUTE_TILE as usize) {
                for b in b0..b1 {
                    for a in a0..(a0 + PRECOMPUTE_TILE).min(b + 1) {
                        self.gram(a, b);
                    }
                }
            }
        }
    }

    /// The Gram block `G_ab = Z_aᵀ D⁻¹ Z_b` of columns `a` and `b`: from the
    /// cache (inlined: a build reads thousands), or computed now.
    #[inline]
    pub(crate) fn gram(&mut self, a: u32, b: u32) -> Mat3 {
        match self.pairs[pair_slot(a, b)] {
            Some(g) if a <= b => g,
            Some(g) => g.transpose(),
            None => self.gram_new(a, b),
        }
    }

    /// [`Self::gram`] of a pair not cached yet: computes and caches it.
    #[inline(never)]
    fn gram_new(&mut self, a: u32, b: u32) -> Mat3 {
        let key = (a.min(b), a.max(b));
        let slot = pair_slot(a, b);
        let (ca, cb) = (self.cols[key.0 as usize], self.cols[key.1 as usize]);
        let pa = &self.paths[ca.start..ca.start + ca.len];
        let pb = &self.paths[cb.start..cb.start + cb.len];
        // Tree paths to the root share a common suffix (from the lowest common ancestor).
        // Below the ancestor the paths never meet again, so "the last `c` nodes
        // agree" holds exactly for `c ≤ common`: binary search for it.
        let (mut lo, mut hi) = (0, pa.len().min(pb.len()));
        while lo < hi {
            let mid = (lo + hi).div_ceil(2);
            if pa[pa.len() - mid] == pb[pb.len() - mid] {
                lo = mid;
            } else {
                hi = mid - 1;
            }
        }
        let common = lo;
        let (i, j) = (pa.len() - common, pb.len() - common);
        let za = |u: usize| {
            let o = ca.soa + u * 3 * ca.len;
            &self.soa_z[o + 3 * i..o + 3 * ca.len]
        };
        let sb = |u: usize| {
            let o = cb.soa + u * 3 * cb.len;
            &self.soa_s[o + 3 * j..o + 3 * cb.len]
        };
        let g = gram3([za(0), za(1), za(2)], [sb(0), sb(1), sb(2)]);
        self.pairs[slot] = Some(g);
        self.gram_blocks += 1;
        if a <= b { g } else { g.transpose() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The hint holds every node of the last `HINT_BUILDS` builds, once, and
    /// lets a node go after `HINT_BUILDS` builds without it.
    #[test]
    fn the_hint_remembers_the_last_builds() {
        let mut p = ColumnPrefetch::default();
        let sorted = |p: &ColumnPrefetch| {
            let mut h = p.hint().to_vec();
            h.sort_unstable();
            h
        };
        p.set_hint([5, 2, 9].into_iter());
        p.set_hint([2, 7].into_iter());
        assert_eq!(sorted(&p), [2, 5, 7, 9]);
        // Node 5 was last in build 1: it stays through build HINT_BUILDS.
        for _ in 2..HINT_BUILDS {
            p.set_hint([2].into_iter());
        }
        assert_eq!(sorted(&p), [2, 5, 7, 9]);
        p.set_hint([2].into_iter());
        assert_eq!(
            sorted(&p),
            [2, 7],
            "build 1's nodes gone after {HINT_BUILDS} builds"
        );
        p.set_hint([5].into_iter());
        p.set_hint([].into_iter());
        assert_eq!(sorted(&p), [2, 5]);
        for _ in 0..HINT_BUILDS {
            p.set_hint([].into_iter());
        }
        assert!(p.hint().is_empty());
    }

    /// `columns` gives the ids and columns that `column` gives one node at a
    /// time, to the bit: nodes in any order, repeated, already cached, out of
    /// range, more than one batch of them.
    #[test]
    fn columns_in_batches_are_the_single_ones() {
        let (sym, f) = super::super::ldlt::tests::arbitrary_factor([3, 3, 6]);
        let n = sym.n;
        let key = FactorKey::Own(3);
        let first = [4usize, 9];
        let mut nodes: Vec<usize> = (0..2 * BATCH + 3).map(|i| (i * 53 + 11) % n).collect();
        nodes.extend([nodes[2], 9, n, n + 7]);
        let (mut batched, mut single) = (ColumnCache::default(), ColumnCache::default());
        batched.reset(n, key);
        single.reset(n, key);
        for k in first {
            batched.column(&f, k);
            single.column(&f, k);
        }
        batched.columns(&f, nodes.iter().copied());
        for &k in &nodes {
            if k < n {
                single.column(&f, k);
            }
        }
        assert_eq!(batched.col_of_node, single.col_of_node, "ids");
        assert_eq!(batched.solves, single.solves);
        assert_eq!(batched.cols.len(), single.cols.len());
        let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        for (a, b) in batched.cols.iter().zip(&single.cols) {
            assert_eq!(a.len, b.len);
            assert_eq!(
                batched.paths[a.start..a.start + a.len],
                single.paths[b.start..b.start + b.len]
            );
            let (za, zb) = (
                &batched.soa_z[a.soa..a.soa + 9 * a.len],
                &single.soa_z[b.soa..b.soa + 9 * b.len],
            );
            assert_eq!(bits(za), bits(zb));
            let (sa, sb) = (
                &batched.soa_s[a.soa..a.soa + 9 * a.len],
                &single.soa_s[b.soa..b.soa + 9 * b.len],
            );
            assert_eq!(bits(sa), bits(sb));
        }
        let m = batched.cols.len() as u32;
        for a in 0..m {
            for b in 0..m {
                assert_eq!(batched.gram(a, b), single.gram(a, b));
            }
        }
        assert!(
            batched
                .batch_work
                .iter()
                .flatten()
                .flatten()
                .all(|&x| x == 0.0)
        );
    }

    /// The dispatched Gram kernel (AVX2/FMA where the CPU has it) and the
    /// portable one agree with a plain sum, for every remainder length.
    #[test]
    fn gram_kernels_agree_with_plain_sums() {
        for n in 0..23 {
            let col = |seed: usize| -> Vec<f64> {
                (0..n)
                    .map(|r| (((r + 3) * (seed + 7) * 2654435761usize) % 1000) as f64 / 500.0 - 1.0)
                    .collect()
            };
            let (z, s): (Vec<_>, Vec<_>) = (0..3).map(|i| (col(i), col(i + 10))).unzip();
            let zr = [&z[0][..], &z[1][..], &z[2][..]];
            let sr = [&s[0][..], &s[1][..], &s[2][..]];
            let fast = gram3(zr, sr);
            let portable = gram3_portable(zr, sr);
            for a in 0..3 {
                for b in 0..3 {
                    let plain: f64 = (0..n).map(|r| z[a][r] * s[b][r]).sum();
                    assert!(
                        (fast[(a, b)] - plain).abs() <= 1e-12 * (1.0 + plain.abs()),
                        "n {n}"
                    );
                    assert!((portable[(a, b)] - plain).abs() <= 1e-12 * (1.0 + plain.abs()));
                }
            }
        }
    }
}
