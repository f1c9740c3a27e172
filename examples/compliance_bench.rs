//! Compliance build time against the number of contacts on the paper-size lens
//! (1183 nodes), with friction (3 rows per contact): the paper's CPU method
//! (`DenseRows`, two full solves per row) against `Factorized` (reach-restricted
//! forward solves of node columns), cold (new factor) and warm (columns cached).
//!
//! ```text
//! cargo run --release --example compliance_bench
//! ```

use bevy_soft_tissue::core_prelude::*;
mod common;
use bevy_soft_tissue::study::compliance::lens_with_factor;
use common::bench::pole_contacts;

fn main() -> Result<()> {
    // The paper-size lens; its factor is never refreshed, so every build uses the same one.
    let mut body = lens_with_factor(12)?;
    println!(
        "lens {} nodes; compliance build time (ms, median of 7), friction on (3 rows/contact)",
        body.num_nodes()
    );
    println!(
        "{:>8} {:>6} {:>12} {:>16} {:>15} {:>9}",
        "contacts", "rows", "DenseRows", "Factorized cold", "Factorized warm", "speed-up"
    );
    let counts = [30, 60, 90, 130, 260];
    let rows =
        bevy_soft_tissue::study::compliance::timings(&mut body, &counts, 7, None, &mut |_| {})?;
    for t in rows {
        let n = t.contacts;
        let cs = pole_contacts(&body, n, v3(0.0, 0.0, -1.0), 0.3);
        if std::env::var("PATH_STATS").is_ok() {
            let sym = body.preconditioner().symbolic().expect("factor");
            let mut union = std::collections::HashSet::new();
            let mut total = 0;
            let mut flops = 0usize;
            let mut paths: Vec<Vec<usize>> = Vec::new();
            let mut nodes: Vec<usize> = cs.iter().map(|c| c.a.nodes[0] as usize).collect();
            nodes.sort();
            nodes.dedup();
            for &nd in &nodes {
                let mut j = sym.iperm[nd];
                let mut p = Vec::new();
                while j != usize::MAX {
                    union.insert(j);
                    total += 1;
                    flops += sym.col_ptr[j + 1] - sym.col_ptr[j];
                    p.push(j);
                    j = sym.parent[j];
                }
                paths.push(p);
            }
            let mut pair = 0usize;
            for a in 0..paths.len() {
                for b in a..paths.len() {
                    let s: std::collections::HashSet<_> = paths[a].iter().collect();
                    pair += paths[b].iter().filter(|x| s.contains(x)).count();
                }
            }
            println!(
                "  distinct nodes {}, fwd block-products {} ({} MFMA), pair-suffix nodes {} ({} MFMA)",
                nodes.len(),
                flops,
                flops * 27 / 1000000,
                pair,
                pair * 27 / 1000000
            );
            println!(
                "  mean path {:.1} nodes, union {} nodes, L blocks {}",
                total as f64 / n as f64,
                union.len(),
                sym.nnz_blocks()
            );
        }
        let (d, c, w) = (t.dense_rows, t.factorized_cold, t.factorized_warm);
        println!(
            "{:>8} {:>6} {:>12.3} {:>16.3} {:>15.3} {:>8.1}x",
            n,
            3 * n,
            d,
            c,
            w,
            d / c
        );
    }
    Ok(())
}
