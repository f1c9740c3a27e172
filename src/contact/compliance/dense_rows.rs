//! `DenseRows` compliance, the paper's CPU method: for every row of `J`, two
//! full triangular solves. Same `W` as `Factorized`; the benchmark baseline.

use super::entries::{JacEntry, Scratch};
use crate::math::Vec3;
use crate::solver::columns::ColumnCache;
use crate::solver::ldlt::LdltFactor;

/// `W += h² J (L D Lᵀ)⁻¹ Jᵀ`, one row of `J` at a time; counts the solves in `cache`.
pub(super) fn accumulate(
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
