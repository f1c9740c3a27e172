//! What accuracy costs in time: the whole accuracy study in one command.
//!
//! ```text
//! cargo run --release --example accuracy_study              # full (tens of minutes on 2 cores)
//! cargo run --release --example accuracy_study -- --quick   # coarse, a few minutes
//! cargo run --release --features gpu --example accuracy_study   # + the GPU in Fig. 4
//! cargo run --release --features gpu --example accuracy_study -- --fig4-only
//! ```
//! Writes `results.csv`, `timeseries.csv`, `compliance.csv`, `growth.csv`,
//! `validation.csv`, the figures (`fig3_error.png`, `pareto.png`,
//! `cataract_error.png`, `cataract_pareto.png`, `fig4_compliance.png`,
//! `growth.png`) and `report.md` into `--out` (default
//! `target/accuracy-study`). The study is library code
//! (`bevy_soft_tissue::study`); this is its command line.

use std::path::PathBuf;
use std::process::ExitCode;

use bevy_soft_tissue::contact::ComplianceBackend;
use bevy_soft_tissue::study::{self, Progress, full};
use clap::Parser;
use indicatif::{ProgressBar, ProgressStyle};

#[derive(Parser, Debug)]
#[command(
    about = "Accuracy against time: variants against an exact reference, Fig. 4, growth, validation"
)]
struct Args {
    /// Coarse meshes and few steps (a few minutes on 2 cores).
    #[arg(long)]
    quick: bool,
    /// Output folder.
    #[arg(long, default_value = "target/accuracy-study")]
    out: PathBuf,
    /// Runs of each timing-dependent `async` variant.
    #[arg(long, default_value_t = 3)]
    async_repeats: usize,
    /// Leave out the cataract push.
    #[arg(long)]
    no_cataract: bool,
    /// A variant run stops once its steps have taken this many times as
    /// long as its scene's reference run (`inf`: never).
    #[arg(long, default_value_t = study::DEFAULT_TIME_FACTOR)]
    time_factor: f64,
    /// Only Fig. 4 (the compliance build against contacts, with the GPU
    /// under `--features gpu`): `compliance.csv`, `fig4_compliance.png` and
    /// `fig4.md`, in seconds rather than minutes.
    #[arg(long)]
    fig4_only: bool,
}

#[cfg(feature = "gpu")]
mod gpu {
    use bevy::prelude::*;
    use bevy::render::renderer::{RenderAdapterInfo, RenderDevice, RenderQueue};
    use bevy_soft_tissue::gpu::GpuCompliance;

    /// The GPU compliance path with the adapter's name, or why there is none
    /// (probed first: Bevy panics without any adapter).
    pub fn backend() -> Result<(String, GpuCompliance), String> {
        let mut app = App::new();
        bevy_soft_tissue::gpu::add_headless_render(&mut app, None).map_err(|e| e.to_string())?;
        app.finish();
        app.cleanup();
        let w = app.world();
        let (Some(d), Some(q)) = (
            w.get_resource::<RenderDevice>(),
            w.get_resource::<RenderQueue>(),
        ) else {
            return Err("no render device".into());
        };
        let name = w
            .get_resource::<RenderAdapterInfo>()
            .map(|i| format!("{} ({:?})", i.name, i.device_type))
            .unwrap_or_else(|| "unknown adapter".into());
        Ok((name, GpuCompliance::new(d.clone(), q.clone(), 0)))
    }
}

fn main() -> ExitCode {
    let args = Args::parse();
    let config = full::Config {
        quick: args.quick,
        async_repeats: args.async_repeats.max(1),
        cataract: !args.no_cataract,
        time_factor: args.time_factor,
    };
    #[cfg(feature = "gpu")]
    let mut gpu = gpu::backend();
    #[cfg(feature = "gpu")]
    let backend = match &mut gpu {
        Ok((name, g)) => Ok((name.clone(), g as &mut dyn ComplianceBackend)),
        Err(why) => Err(why.clone()),
    };
    #[cfg(not(feature = "gpu"))]
    let backend: Result<(String, &mut dyn ComplianceBackend), String> =
        Err("built without the `gpu` feature".into());

    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template("{prefix:>28} [{bar:40}] {pos}/{len} {elapsed}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    let mut progress = |p: Progress| match p {
        Progress::Start {
            label,
            repeat,
            steps,
        } => {
            bar.set_prefix(if repeat > 0 {
                format!("{label} #{}", repeat + 1)
            } else {
                label.to_string()
            });
            bar.set_length(steps as u64);
            bar.set_position(0);
        }
        Progress::Step => bar.inc(1),
    };
    if args.fig4_only {
        let fig4 = match full::fig4(&config, backend, &mut progress).and_then(|f| {
            study::output::write_fig4(&f, &full::Machine::detect(), &args.out).map(|()| f)
        }) {
            Ok(f) => f,
            Err(e) => {
                bar.abandon();
                eprintln!("study failed: {e}");
                return ExitCode::FAILURE;
            }
        };
        bar.finish_and_clear();
        print_fig4(&fig4);
        println!("written to {}", args.out.display());
        return ExitCode::SUCCESS;
    }
    let report = match full::run(&config, backend, &mut progress) {
        Ok(r) => r,
        Err(e) => {
            bar.abandon();
            eprintln!("study failed: {e}");
            return ExitCode::FAILURE;
        }
    };
    bar.finish_and_clear();
    if let Err(e) = study::output::write(&report, &args.out) {
        eprintln!("{e}");
        return ExitCode::FAILURE;
    }
    // The headline numbers.
    for case in std::iter::once(&report.lens).chain(report.cataract.as_ref()) {
        println!("{} ({} nodes):", case.scene, case.nodes);
        println!(
            "  {:<18} {:>10} {:>14} {:>10} {:>12} {:>9}",
            "variant", "ms/step", "mean RMS (m)", "relative", "max pen µm", "refactors"
        );
        for s in case.summaries() {
            println!(
                "  {:<18} {:>10.3} {:>14.3e} {:>10.2e} {:>12.3} {:>9.1}{}",
                s.variant,
                s.ms_per_step,
                s.rms_error_mean,
                s.rms_error_mean / case.length_scale,
                s.max_penetration * 1e6,
                s.consistency_refactors,
                s.failure
                    .as_deref()
                    .map(|f| format!("  FAILED: {f}"))
                    .or_else(|| s.stopped.as_deref().map(|f| format!("  {f}")))
                    .unwrap_or_default()
            );
        }
    }
    if let Some(p) = report.growth_exponent {
        println!("growth: step time ~ nodes^{p:.2}");
    }
    if let Some(c) = report.cantilever.last() {
        println!(
            "cantilever error (finest): {:.2} %",
            100.0 * c.relative_error
        );
    }
    let worst = report
        .hertz
        .points
        .iter()
        .map(|p| p.relative_error)
        .fold(0.0, f64::max);
    println!("Hertz error (worst depth): {:.2} %", 100.0 * worst);
    println!(
        "wrote {} ({:.0} s)",
        args.out.join("report.md").display(),
        report.seconds
    );
    ExitCode::SUCCESS
}

/// Fig. 4's table on stdout.
fn print_fig4(fig4: &full::Fig4) {
    match &fig4.backend {
        Ok(name) => println!("Fig. 4 (ms, median), GPU: {name}"),
        Err(why) => println!("Fig. 4 (ms, median), GPU not measured: {why}"),
    }
    print!("{}", study::output::fig4_table(fig4));
}
