//! The two fill-reducing orderings of the `LDLᵀ` factor side by side
//! (`solver::ordering`): on the lens at growing resolutions and on the two
//! bodies of the cataract scene, the factor's size, the operations of a
//! factorization (`Σ c_j²`), one factorization (median of 3), one solve
//! with `L` in double and in single precision (the preconditioner's,
//! `LdltFactor::solve_single`; median of 3 batches of 20), and the mean
//! elimination-tree path of a node (what a contact column of the compliance
//! costs). `Auto` keeps the cheaper.
//!
//! ```text
//! cargo run --release --example ordering_bench
//! ```

use std::sync::Arc;
use std::time::Instant;

use bevy_soft_tissue::core_prelude::*;
use bevy_soft_tissue::mesh::generate::LENS_RADII;
use bevy_soft_tissue::scenes::cataract;
use bevy_soft_tissue::solver::ldlt::{LdltSymbolic, NONE};
use bevy_soft_tissue::solver::ordering::{self, Ordering};

fn median(mut t: Vec<f64>) -> f64 {
    t.sort_by(f64::total_cmp);
    t[t.len() / 2]
}

fn ms(f: &mut dyn FnMut() -> Result<()>) -> Result<f64> {
    let mut t = Vec::new();
    for _ in 0..3 {
        let t0 = Instant::now();
        f()?;
        t.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    Ok(median(t))
}

fn report(name: &str, body: &mut DeformableBody) -> Result<()> {
    // One step assembles the matrix.
    body.step(1.0 / 60.0)?;
    let a = body.system_matrix();
    let auto = ordering::order(&a.pattern, Ordering::Auto)?;
    for which in [Ordering::Amd, Ordering::NestedDissection] {
        let p = ordering::order(&a.pattern, which)?;
        let (nnz, flops) = ordering::factor_cost(&a.pattern, &p);
        let sym = Arc::new(LdltSymbolic::with_ordering(&a.pattern, which)?);
        let mut f = sym.alloc_factor();
        let mut work = Vec::new();
        let factor = ms(&mut || sym.factorize(a, &mut f, &mut work))?;
        let b: Vec<Vec3> = (0..sym.n)
            .map(|i| v3((i as f64).sin(), 1.0, (i as f64 * 0.3).cos()))
            .collect();
        let (mut x, mut tmp) = (vec![Vec3::zeros(); sym.n], vec![Vec3::zeros(); sym.n]);
        let batch = 20;
        let solve = ms(&mut || {
            for _ in 0..batch {
                f.solve(&b, &mut x, &mut tmp);
            }
            Ok(())
        })? / batch as f64;
        f.round_to_single();
        let single = ms(&mut || {
            for _ in 0..batch {
                f.solve_single(&b, &mut x, &mut tmp);
            }
            Ok(())
        })? / batch as f64;
        let mut path = 0usize;
        for k in 0..sym.n {
            let mut j = k;
            while j != NONE {
                path += 1;
                j = sym.parent[j];
            }
        }
        println!(
            "{name:>12} {:>6} {:>18} {:>9} {:>9.2e} {:>10.1} {:>8.2} {:>9.2} {:>6.0}{}",
            sym.n,
            format!("{which:?}"),
            nnz,
            flops,
            factor,
            solve,
            single,
            path as f64 / sym.n as f64,
            if p == auto { "  (Auto)" } else { "" }
        );
    }
    Ok(())
}

fn main() -> Result<()> {
    println!(
        "{:>12} {:>6} {:>18} {:>9} {:>9} {:>10} {:>8} {:>9} {:>6}",
        "mesh",
        "nodes",
        "ordering",
        "L blocks",
        "flops",
        "factor ms",
        "solve ms",
        "f32 solve",
        "path"
    );
    for cells in [10, 14, 20, 26, 31] {
        let mesh = generate::ellipsoid(LENS_RADII, cells)?;
        let material = bevy_soft_tissue::study::cases::lens_material(5.0);
        let mut body = DeformableBody::new(mesh, material, BodySettings::default())?;
        report(&format!("lens {cells}"), &mut body)?;
    }
    let mut scene = cataract::build(
        &cataract::CataractParams::default(),
        BodySettings::default(),
    )?;
    report("cataract lens", &mut scene.lens)?;
    report("cataract eye", &mut scene.eye)?;
    Ok(())
}
