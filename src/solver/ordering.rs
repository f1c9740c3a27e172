//! Fill-reducing orderings of the node graph for [`super::ldlt`].
//!
//! Two orderings, and the choice between them:
//! - **AMD** (faer's approximate minimum degree): the best on small meshes.
//! - **Nested dissection** ([`nested_dissection`]): split the graph by a
//!   small vertex separator, order both halves first (recursively) and the
//!   separator last; parts of at most [`ND_LEAF`] nodes are ordered by AMD.
//!   Separators are level sets of a breadth-first search from a
//!   pseudo-peripheral node (George and Liu's automatic nested dissection),
//!   the level with the smallest separator for its balance. On a 3-D mesh the
//!   factor of a nested-dissection ordering grows as `n^{4/3}` and its
//!   factorization as `n²`; minimum degree fills more as the mesh grows.
//! - [`Ordering::Auto`] (the default of [`super::ldlt::LdltSymbolic::new`])
//!   computes both and keeps the one whose factorization costs fewer
//!   operations (`Σ_j c_j²` over the column counts of `L`), counted without
//!   building `L`.
//!
//! Measured (`cargo run --release --example ordering_bench`, 2-core machine;
//! factorization ms, median of 3, and the mean elimination-tree path of a
//! node, which is what a contact column of the compliance costs):
//!
//! | mesh | nodes | AMD | nested dissection |
//! |---|---|---|---|
//! | lens | 1 800 | 35.6 ms, path 343 | 21.8 ms, path 243 |
//! | lens | 4 410 | 316 ms, path 735 | 159 ms, path 457 |
//! | lens | 16 384 | 7 472 ms, path 1 859 | 3 351 ms, path 1 188 |
//! | cataract lens | 1 183 | 11.6 ms, path 229 | 9.3 ms, path 179 |
//! | cataract eye (a thin shell) | 1 192 | 2.6 ms, path 138 | 4.8 ms, path 150 |
//!
//! `Auto` takes nested dissection for every lens and AMD for the eye.

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::SymbolicSparseColMatRef;
use faer::sparse::linalg::amd;

use crate::error::{Result, SoftTissueError};
use crate::fem::assembly::BlockPattern;

/// Parts of at most this many nodes are ordered by AMD instead of being split.
pub const ND_LEAF: usize = 64;

/// Which fill-reducing ordering a symbolic analysis uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Ordering {
    /// Both, keeping the one with the cheaper factorization.
    #[default]
    Auto,
    /// Approximate minimum degree.
    Amd,
    /// Nested dissection with AMD on its small parts.
    NestedDissection,
}

/// A permutation: `perm[new] = old`, `iperm[old] = new`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Permutation {
    /// `perm[new] = old` node.
    pub perm: Vec<usize>,
    /// `iperm[old] = new` node.
    pub iperm: Vec<usize>,
}

impl Permutation {
    fn from_perm(perm: Vec<usize>) -> Self {
        let mut iperm = vec![0; perm.len()];
        for (new, &old) in perm.iter().enumerate() {
            iperm[old] = new;
        }
        Self { perm, iperm }
    }
}

/// The ordering `which` of `pattern` (for `Auto`, the cheaper of the two).
pub fn order(pattern: &BlockPattern, which: Ordering) -> Result<Permutation> {
    match which {
        Ordering::Amd => amd_order(pattern),
        Ordering::NestedDissection => nested_dissection(pattern),
        Ordering::Auto => {
            let a = amd_order(pattern)?;
            let nd = nested_dissection(pattern)?;
            if factor_cost(pattern, &nd).1 < factor_cost(pattern, &a).1 {
                Ok(nd)
            } else {
                Ok(a)
            }
        }
    }
}

/// faer's AMD on the node graph.
fn amd_order(pattern: &BlockPattern) -> Result<Permutation> {
    let n = pattern.n;
    let mut perm = vec![0usize; n];
    let mut iperm = vec![0usize; n];
    if n > 0 {
        amd_into(n, &pattern.row_ptr, &pattern.col_idx, &mut perm, &mut iperm)?;
    }
    Ok(Permutation { perm, iperm })
}

/// AMD of the symmetric graph `(row_ptr, col_idx)` (rows sorted).
fn amd_into(
    n: usize,
    row_ptr: &[usize],
    col_idx: &[usize],
    perm: &mut [usize],
    iperm: &mut [usize],
) -> Result<()> {
    let sym = SymbolicSparseColMatRef::new_checked(n, n, row_ptr, None, col_idx);
    let mut mem = MemBuffer::new(amd::order_scratch::<usize>(n, col_idx.len()));
    amd::order(
        perm,
        iperm,
        sym,
        amd::Control::default(),
        MemStack::new(&mut mem),
    )
    .map_err(|_| SoftTissueError::TooLarge {
        what: "AMD ordering",
        size: n,
        limit: u32::MAX as usize,
    })?;
    Ok(())
}

/// Elimination tree of a symmetric graph in its elimination order (Liu's
/// algorithm with path compression): `parent[k]`, or `usize::MAX` for a root.
/// `row(k)` lists the neighbours of `k` (permuted numbers; those `≥ k` are
/// skipped).
pub(crate) fn elimination_tree<I: IntoIterator<Item = usize>>(
    n: usize,
    mut row: impl FnMut(usize) -> I,
) -> Vec<usize> {
    let mut parent = vec![usize::MAX; n];
    let mut ancestor = vec![usize::MAX; n];
    for k in 0..n {
        for mut i in row(k) {
            while i < k {
                let next = ancestor[i];
                ancestor[i] = k;
                if next == usize::MAX {
                    parent[i] = k;
                    break;
                }
                i = next;
            }
        }
    }
    parent
}

/// `(nnz, flops)` of the factor of `pattern` under `p`: the number of
/// off-diagonal node blocks of `L` and `Σ_j c_j²` over its column counts,
/// from the elimination tree and the row subtrees, without storing `L`.
pub fn factor_cost(pattern: &BlockPattern, p: &Permutation) -> (usize, f64) {
    let n = pattern.n;
    let row = |k: usize| {
        let old = p.perm[k];
        pattern.col_idx[pattern.row_ptr[old]..pattern.row_ptr[old + 1]]
            .iter()
            .map(|&c| p.iperm[c])
    };
    let parent = elimination_tree(n, row);
    let mut mark = vec![usize::MAX; n];
    let mut count = vec![0usize; n];
    for k in 0..n {
        mark[k] = k;
        for mut i in row(k) {
            while i < k && mark[i] != k {
                mark[i] = k;
                count[i] += 1;
                i = parent[i];
            }
        }
    }
    let nnz = count.iter().sum();
    let flops = count.iter().map(|&c| (c as f64 + 1.0).powi(2)).sum();
    (nnz, flops)
}

/// Nested dissection of the node graph of `pattern` (see the module docs).
pub fn nested_dissection(pattern: &BlockPattern) -> Result<Permutation> {
    let n = pattern.n;
    let mut nd = Dissection {
        pattern,
        perm: vec![usize::MAX; n],
        label: vec![usize::MAX; n],
        level: vec![0; n],
        queue: Vec::with_capacity(n),
        local: vec![usize::MAX; n],
        next_label: 0,
    };
    let mut tasks: Vec<(Vec<usize>, usize)> = vec![((0..n).collect(), 0)];
    while let Some((nodes, lo)) = tasks.pop() {
        nd.split(nodes, lo, &mut tasks)?;
    }
    debug_assert!(nd.perm.iter().all(|&p| p < n));
    Ok(Permutation::from_perm(nd.perm))
}

struct Dissection<'a> {
    pattern: &'a BlockPattern,
    /// `perm[new] = old`, filled part by part.
    perm: Vec<usize>,
    /// Which part a node belongs to now.
    label: Vec<usize>,
    /// Breadth-first level within its part.
    level: Vec<usize>,
    queue: Vec<usize>,
    /// Index of a node within its leaf (AMD).
    local: Vec<usize>,
    next_label: usize,
}

impl Dissection<'_> {
    fn neighbours(&self, v: usize) -> &[usize] {
        &self.pattern.col_idx[self.pattern.row_ptr[v]..self.pattern.row_ptr[v + 1]]
    }

    /// Breadth-first search from `root` within the part `label`; fills
    /// `queue` in visiting order and `level`. Returns the number of levels.
    fn bfs(&mut self, root: usize, label: usize) -> usize {
        let visit = label + 1;
        self.queue.clear();
        self.queue.push(root);
        self.label[root] = visit;
        self.level[root] = 0;
        let mut head = 0;
        let mut depth = 1;
        while head < self.queue.len() {
            let v = self.queue[head];
            head += 1;
            let lv = self.level[v];
            for i in self.pattern.row_ptr[v]..self.pattern.row_ptr[v + 1] {
                let u = self.pattern.col_idx[i];
                if self.label[u] == label {
                    self.label[u] = visit;
                    self.level[u] = lv + 1;
                    depth = depth.max(lv + 2);
                    self.queue.push(u);
                }
            }
        }
        // Give the visited nodes their part back.
        for &v in &self.queue {
            self.label[v] = label;
        }
        depth
    }

    /// Orders `nodes` into `perm[lo..lo + nodes.len()]`, pushing the parts
    /// still to order onto `tasks`.
    fn split(
        &mut self,
        nodes: Vec<usize>,
        lo: usize,
        tasks: &mut Vec<(Vec<usize>, usize)>,
    ) -> Result<()> {
        let size = nodes.len();
        if size <= ND_LEAF {
            return self.leaf(&nodes, lo);
        }
        // A fresh pair of labels per part: `label` marks membership,
        // `label + 1` "visited" during a search.
        let label = self.next_label;
        self.next_label += 2;
        for &v in &nodes {
            self.label[v] = label;
        }
        // Pseudo-peripheral root: restart from the farthest node of least
        // degree while the depth grows.
        let mut root = *nodes
            .iter()
            .min_by_key(|&&v| self.neighbours(v).len())
            .unwrap_or(&nodes[0]);
        let mut depth = self.bfs(root, label);
        for _ in 0..8 {
            if self.queue.len() < size {
                break;
            }
            let last = self.level[*self.queue.last().unwrap_or(&root)];
            let cand = *self
                .queue
                .iter()
                .rev()
                .take_while(|&&v| self.level[v] == last)
                .min_by_key(|&&v| self.neighbours(v).len())
                .unwrap_or(&root);
            let d = self.bfs(cand, label);
            if d <= depth {
                // Keep the levels of the deepest search.
                self.bfs(root, label);
                break;
            }
            root = cand;
            depth = d;
        }
        let reached = self.queue.len();
        if reached < size {
            // Not connected: the component found first, then the rest.
            let comp: Vec<usize> = self.queue.clone();
            for &v in &comp {
                self.label[v] = usize::MAX;
            }
            let rest: Vec<usize> = nodes
                .into_iter()
                .filter(|&v| self.label[v] == label)
                .collect();
            for &v in &rest {
                self.label[v] = usize::MAX;
            }
            tasks.push((comp, lo));
            tasks.push((rest, lo + reached));
            return Ok(());
        }
        // Level sizes and, per level `m`, how many of its nodes touch level
        // `m + 1` (a separator taken from below) and how many of level `m + 1`
        // touch level `m` (one taken from above).
        let mut count = vec![0usize; depth];
        let mut below = vec![0usize; depth];
        let mut above = vec![0usize; depth];
        for &v in &self.queue {
            let lv = self.level[v];
            count[lv] += 1;
            let (mut up, mut down) = (false, false);
            for &u in self.neighbours(v) {
                if self.label[u] == label {
                    up |= self.level[u] == lv + 1;
                    down |= lv > 0 && self.level[u] == lv - 1;
                }
            }
            below[lv] += usize::from(up);
            if lv > 0 {
                above[lv - 1] += usize::from(down);
            }
        }
        // The separator with the best ratio |S| / (|A| |B|) among those that
        // leave each side at least a fifth of the part.
        let mut best: Option<(f64, usize, bool)> = None;
        let mut before = 0usize;
        for m in 0..depth.saturating_sub(1) {
            for from_above in [false, true] {
                let s = if from_above { above[m] } else { below[m] };
                // Side A: levels ≤ m (less S when taken from below), B the rest.
                let a = if from_above {
                    before + count[m]
                } else {
                    before + count[m] - s
                };
                let b = size - a - s;
                if s == 0 || 5 * a < size || 5 * b < size {
                    continue;
                }
                let score = s as f64 / (a as f64 * b as f64);
                if best.is_none_or(|(bs, _, _)| score < bs) {
                    best = Some((score, m, from_above));
                }
            }
            before += count[m];
        }
        let Some((_, m, from_above)) = best else {
            // No balanced level cut (a very compact graph): AMD on the whole part.
            for &v in &nodes {
                self.label[v] = usize::MAX;
            }
            return self.leaf(&nodes, lo);
        };
        let (mut a, mut b, mut s) = (Vec::new(), Vec::new(), Vec::new());
        for &v in &self.queue {
            let lv = self.level[v];
            let touches = |lu: usize| {
                self.neighbours(v)
                    .iter()
                    .any(|&u| self.label[u] == label && self.level[u] == lu)
            };
            let in_sep = if from_above {
                lv == m + 1 && touches(m)
            } else {
                lv == m && touches(m + 1)
            };
            if in_sep {
                s.push(v);
            } else if lv <= m {
                a.push(v);
            } else {
                b.push(v);
            }
        }
        for &v in &nodes {
            self.label[v] = usize::MAX;
        }
        // The separator last, in its search order.
        let hi = lo + size;
        for (t, &v) in s.iter().enumerate() {
            self.perm[hi - s.len() + t] = v;
        }
        let (na, nb) = (a.len(), b.len());
        tasks.push((a, lo));
        tasks.push((b, lo + na));
        debug_assert_eq!(na + nb + s.len(), size);
        Ok(())
    }

    /// AMD on the subgraph of `nodes`, into `perm[lo..]`.
    fn leaf(&mut self, nodes: &[usize], lo: usize) -> Result<()> {
        let k = nodes.len();
        for (i, &v) in nodes.iter().enumerate() {
            self.local[v] = i;
        }
        let mut row_ptr = Vec::with_capacity(k + 1);
        let mut col_idx = Vec::new();
        row_ptr.push(0);
        for &v in nodes {
            let start = col_idx.len();
            for &u in self.neighbours(v) {
                let l = self.local[u];
                if l != usize::MAX {
                    col_idx.push(l);
                }
            }
            col_idx[start..].sort_unstable();
            row_ptr.push(col_idx.len());
        }
        for &v in nodes {
            self.local[v] = usize::MAX;
        }
        let mut perm = vec![0usize; k];
        let mut iperm = vec![0usize; k];
        if k > 0 {
            amd_into(k, &row_ptr, &col_idx, &mut perm, &mut iperm)?;
        }
        for (t, &p) in perm.iter().enumerate() {
            self.perm[lo + t] = nodes[p];
        }
        Ok(())
    }
}
