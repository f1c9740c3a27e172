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
use common::bench::{lens_body, pole_contacts};
use std::time::Instant;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<()> {
    // The paper-size lens; its factor is never refreshed, so every build uses the same one.
    let mut body = lens_body(PreconditionerKind::Periodic { every: 1_000_000 }, 12)?;
    body.fix_where(|p| p.z < -2.0e-3);
    body.step(0.02)?;
    println!(
        "lens {} nodes; compliance build time (ms, median of 7), friction on (3 rows/contact)",
        body.num_nodes()
    );
    println!(
        "{:>8} {:>6} {:>12} {:>16} {:>15} {:>9}",
        "contacts", "rows", "DenseRows", "Factorized cold", "Factorized warm", "speed-up"
    );
    for n in [30, 60, 90, 130, 260] {
        let cs = pole_contacts(&body, n, v3(0.0, 0.0, -1.0), 0.3);
        let mut dense = Vec::new();
        let mut cold = Vec::new();
        let mut warm = Vec::new();
        // One solver per mode, reused as in a running scene (scratch memory kept);
        // `forget_columns` drops the cached columns as a new factor does.
        // Reuse 0: W from the body's current factor (no snapshot copy).
        let solver = |mode| {
            ContactSolver::new(ContactSettings {
                compliance: mode,
                factor_reuse: 0,
                ..Default::default()
            })
        };
        let mut dense_solver = solver(ComplianceMode::DenseRows)?;
        let mut fact_solver = solver(ComplianceMode::Factorized)?;
        for _ in 0..7 {
            dense_solver.set_contacts(&cs, &[&body], 0.02)?;
            let t0 = Instant::now();
            dense_solver.build_compliance(&mut [&mut body], PassKind::First, None)?;
            dense.push(t0.elapsed().as_secs_f64() * 1e3);
            // New factor: every node column is solved.
            fact_solver.set_contacts(&cs, &[&body], 0.02)?;
            fact_solver.forget_columns();
            let t0 = Instant::now();
            fact_solver.build_compliance(&mut [&mut body], PassKind::First, None)?;
            cold.push(t0.elapsed().as_secs_f64() * 1e3);
            // Same factor, same nodes: columns and Gram blocks come from the cache.
            fact_solver.set_contacts(&cs, &[&body], 0.02)?;
            let t0 = Instant::now();
            fact_solver.build_compliance(&mut [&mut body], PassKind::First, None)?;
            warm.push(t0.elapsed().as_secs_f64() * 1e3);
        }
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
        let (d, c, w) = (median(dense), median(cold), median(warm));
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
