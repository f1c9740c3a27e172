//! Headless run of the deformation core on the paper-size lens: N implicit steps
//! while the lens is squeezed and twisted, then the median time of each phase and
//! the CG iterations per preconditioner.
//!
//! ```text
//! cargo run --release --example core_headless -- --steps 300
//! cargo run --release --example core_headless -- --steps 300 --preconditioner async
//! ```
//! Preconditioners: `jacobi`, `exact`, `periodic1`, `periodic4`, `periodic16`, `async`
//! (default: all of them, plus `frozen`, a factor never refreshed after the first
//! step: the cost of a step with no factorization anywhere, to compare `async` with).

use bevy_soft_tissue::core_prelude::*;
use bevy_soft_tissue::mesh::generate::LENS_RADII;

use clap::Parser;

mod common;
use nalgebra::Rotation3;
use std::process::ExitCode;

fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// The deformation core on the paper-size lens, per preconditioner.
#[derive(Parser)]
#[command(long_about = None)]
struct Args {
    /// Steps per preconditioner.
    #[arg(long, default_value_t = 200)]
    steps: usize,
    /// none, jacobi, exact, periodicN, async or lagN (default: a set of them).
    #[arg(long, value_parser = common::args::preconditioner)]
    preconditioner: Option<PreconditionerKind>,
}

fn run(kind: PreconditionerKind, steps: usize) -> Result<()> {
    let mesh = generate::ellipsoid(LENS_RADII, 12)?;
    let material = common::bench::lens_material();
    let settings = BodySettings {
        preconditioner: kind,
        cg: CgSettings {
            tolerance: 1e-6,
            max_iterations: 1000,
            warm_start: true,
        },
        ..Default::default()
    };
    let mut body = DeformableBody::new(mesh.clone(), material, settings)?;
    let top: Vec<usize> = (0..mesh.num_vertices())
        .filter(|&i| mesh.positions()[i].z > 1.6e-3)
        .collect();
    body.fix_where(|p| p.z < -1.6e-3);
    let (mut asm, mut fac, mut pre, mut cg, mut total, mut its, mut ages) =
        (vec![], vec![], vec![], vec![], vec![], vec![], vec![]);
    let mut unconverged = 0;
    let (mut in_flight, mut idle) = (vec![], vec![]);
    for s in 0..steps {
        let t = (s + 1) as f64 * 0.02;
        let a = 0.5 * (1.0 - (t * 2.0).cos());
        let rot = Rotation3::from_axis_angle(&Vec3::z_axis(), a * 0.8);
        for &i in &top {
            let p = mesh.positions()[i];
            body.drive_node(i, rot * v3(p.x, p.y, p.z - a * 1.5e-3))?;
        }
        let busy = body
            .preconditioner()
            .worker()
            .is_some_and(|w| w.in_flight());
        let t0 = std::time::Instant::now();
        let r = body.step(0.02)?;
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        total.push(ms);
        if busy {
            in_flight.push(ms)
        } else {
            idle.push(ms)
        }
        asm.push(r.timings.assemble * 1e3);
        fac.push(r.timings.factorize * 1e3);
        pre.push(r.timings.precond_apply * 1e3);
        cg.push(r.timings.cg_total * 1e3);
        its.push(r.cg.iterations as f64);
        ages.push(r.preconditioner.factor_age as f64);
        unconverged += usize::from(!r.cg.converged);
        if body
            .positions()
            .iter()
            .any(|p| !p.iter().all(|c| c.is_finite()))
        {
            return Err(SoftTissueError::NonFinite("positions"));
        }
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    println!(
        "{:<12} {:>9.3} {:>9.3} {:>9.3} {:>9.3} {:>9.3} {:>8.2} {:>7.2} {:>6}",
        if kind == (PreconditionerKind::Periodic { every: u32::MAX }) {
            "frozen".to_string()
        } else {
            format!("{kind:?}")
                .replace("Periodic { every: ", "every ")
                .replace(" }", "")
        },
        median(&mut total),
        median(&mut asm),
        median(&mut fac),
        median(&mut pre),
        median(&mut cg),
        mean(&its),
        mean(&ages),
        unconverged
    );
    let p = body.preconditioner().stats();
    if p.warp_offered > 0 {
        println!(
            "  warp chosen for {} solves: each node's turn {}, the body's turn {}, none {}",
            p.warp_offered,
            p.warp_offered - p.warp_body - p.warp_declined,
            p.warp_body,
            p.warp_declined
        );
    }
    if kind == PreconditionerKind::Async {
        println!(
            "  async: median step {:.3} ms with a factorization in flight ({} steps), {:.3} ms without ({} steps)",
            median(&mut in_flight.clone()),
            in_flight.len(),
            median(&mut idle.clone()),
            idle.len()
        );
    }
    Ok(())
}

fn main() -> ExitCode {
    let args = Args::parse();
    let steps = args.steps;
    let kinds = match args.preconditioner {
        Some(k) => vec![k],
        None => vec![
            PreconditionerKind::Jacobi,
            PreconditionerKind::Exact,
            PreconditionerKind::Periodic { every: 1 },
            PreconditionerKind::Periodic { every: 4 },
            PreconditionerKind::Periodic { every: 16 },
            PreconditionerKind::Periodic { every: u32::MAX },
            PreconditionerKind::Async,
        ],
    };
    println!(
        "lens 1183 nodes / 5184 tets, nucleus 5x, h = 0.02 s, {steps} steps; times are medians in ms"
    );
    println!(
        "{:<12} {:>9} {:>9} {:>9} {:>9} {:>9} {:>8} {:>7} {:>6}",
        "precond", "step", "assemble", "factor", "P apply", "CG total", "CG its", "age", "unconv"
    );
    for k in kinds {
        if let Err(e) = run(k, steps) {
            eprintln!("{k:?}: {e}");
            return ExitCode::FAILURE;
        }
    }
    ExitCode::SUCCESS
}
