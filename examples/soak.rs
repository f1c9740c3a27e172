//! Soak run of the cataract scene: the vectis goes into the incision and back
//! out again and again (16 s a cycle), with the default solver, through the
//! core `Scene`.
//!
//! ```text
//! cargo run --release --example soak -- --steps 10000 [--coarse]
//! ```
//!
//! Prints the deepest penetration at a step's end, the largest per-step
//! energy rise beyond the contact forces' work, the steps with a NaN, the CG
//! rescues, the worst CG, and whether anything failed; exits nonzero on a
//! failure (an error, a NaN, an unconverged CG, or a penetration beyond 1 %
//! of the lens's smallest edge). `tests/stability.rs` runs a short one.

use std::process::ExitCode;
use std::time::Instant;

use bevy_soft_tissue::scenes::cataract::CataractParams;

use clap::Parser;

mod common;

/// Soak: the cataract scene for many steps, the vectis going in and out.
#[derive(Parser)]
#[command(long_about = None)]
struct Args {
    /// Steps to run.
    #[arg(long, default_value_t = 10_000)]
    steps: usize,
    /// Light meshes.
    #[arg(long)]
    coarse: bool,
}

fn main() -> ExitCode {
    let args = Args::parse();
    let steps = args.steps;
    let params = if args.coarse {
        CataractParams::coarse()
    } else {
        CataractParams::default()
    };
    let t0 = Instant::now();
    let s = match common::soak::run_soak(&params, steps, |i| {
        if (i + 1) % 1000 == 0 {
            println!("  {} steps, {:.0} s", i + 1, t0.elapsed().as_secs_f64());
        }
    }) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("soak: could not build or step the scene: {e}");
            return ExitCode::FAILURE;
        }
    };
    println!(
        "soak: {} steps in {:.0} s",
        s.steps,
        t0.elapsed().as_secs_f64()
    );
    println!(
        "  max penetration at a step's end: {:.3e} m (tolerance {:.3e} m)",
        s.max_penetration, s.tolerance
    );
    println!(
        "  largest per-step energy rise beyond the contact forces' work: {:.3e} J (elastic energy then {:.3e} J)",
        s.max_energy_rise.0, s.max_energy_rise.1
    );
    println!("  steps with NaN: {}", s.nan_steps);
    println!(
        "  elements flat or inverted at a step's end: at most {}, {} at the last",
        s.inverted.0, s.inverted.1
    );
    println!(
        "  CG rescues: {}, worst CG: {} iterations, unconverged: {}",
        s.rescues, s.worst_cg, s.unconverged
    );
    if let Some(e) = &s.error {
        println!("  error: {e}");
    }
    if s.failed() {
        println!("  FAILED");
        ExitCode::FAILURE
    } else {
        println!("  no failure");
        ExitCode::SUCCESS
    }
}
