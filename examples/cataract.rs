//! The cataract (MSICS) nucleus-extraction scene.
//!
//! ```text
//! cargo run --release --features viewer --example cataract            # window (headless without a display)
//! cargo run --release --example cataract -- --headless --steps 600     # per-phase timings
//! ```
//!
//! Options (`--help` lists them): `--headless`, `--steps N` (headless, default: the scripted path and
//! one second more, 1080, or 540 with `--push-only`), `--push-only` (the vectis
//! stops with the lens pressed into the slit instead of delivering it out of
//! the eye, `CataractParams::push_only`), `--coarse`
//! (light meshes), `--preconditioner none|jacobi|exact|periodicN|async|lagN`
//! (`lagN`: `AsyncLagged`, the factor arrives exactly N steps later),
//! `--eye-preconditioner KIND` (headless: the eye's, where it differs from the
//! lens's), `--trace FILE` (headless: one CSV line per step),
//! `--compliance factorized|exact|diagonal|rest|dense`, `--reuse N` (steps a
//! factor serves the compliance, `ContactSettings::factor_reuse`), `--passes N`
//! (contact passes per step), `--no-predict` (detect at the free motion, not
//! at the predicted positions, `ContactSettings::predict`),
//! `--no-rigid-modes` (`ContactSettings::rigid_modes` off),
//! `--tool-faces` (`ContactSettings::tool_faces`: the vectis's contacts
//! inside the lens's and the eye's faces as well as at their vertices),
//! `--consistency-tolerance X` (`ContactSettings::consistency_tolerance`),
//! `--energy-tolerance X` (`ContactSettings::energy_tolerance`),
//! `--cg-tolerance X` (`CgSettings::tolerance` of both bodies) — accuracy
//! against time; `--lcp pgs|block|nncg|subspace` (the contact solver, `LcpSolver`);
//! `--record-lcp DIR` writes each step's first-pass contact problem with at
//! least `--record-min-contacts N` (default 91) contacts to `DIR`, for the
//! `lcp` bench (`ContactProblem`); `--gpu off|on|autoN` (`SoftTissueConfig::gpu`:
//! `W` on the CPU, on the GPU, or on the GPU from N constraint rows; needs the
//! `gpu` feature and a GPU adapter; headless it then prints the GPU builds,
//! their time and the time spent waiting for the device);
//! `--repeats N` (headless: N runs, then the ranges and medians of their
//! steps/s, deliveries and penetrations); `--in-fixed-post-update` (headless: the pipeline's sets straight in
//! `FixedPostUpdate` under Bevy's multi-threaded executor, as before
//! `SoftTissueSchedule`).
//!
//! Headless, it prints the median time per phase (and the wall clock of the
//! whole step, from which it reports the steps per second), the
//! contact counts and CG iterations, where the lens ended (inside the eye, in
//! the incision, or out of it), and exits nonzero on NaN, on a pipeline
//! error or on a penetration beyond 1 % of the lens's smallest edge (into
//! the vectis or between lens and sclera, checked at the end of every step).
//!
//! In the window: the lens is coloured by stiffness (red nucleus), the eye is
//! translucent; the panel switches effects, preconditioner, refresh policy,
//! compliance, tool contacts inside faces and where `W` is built (CPU or
//! GPU), and charts FPS, CG
//! iterations, contacts and time per phase.
//! Keys: `Space` toggles the scripted path; `W/S` move the vectis toward/away
//! from the incision, `A/D` sideways, `Q/E` across the slit; drag with the right
//! mouse button to orbit the camera, wheel to zoom.
//!
//! `--haptics` (window only): a simulated haptic device drives the vectis at
//! 1 kHz through `HapticsPlugin`. The device's hand follows the scripted
//! path on the scene's clock (`Space` pauses it) through a mass–spring arm,
//! and `W/S/A/D/Q/E` push the hand off the path; the vectis the tissue sees
//! is the coupled pose. An arrow at the blade shows the force the device
//! renders (1 mm per 2 mN), and the panel charts the haptic rate and force
//! with the tick time, jitter and LCP sweeps. The headless benchmark of the
//! same loop is `cargo run --release --example haptics`.

use std::process::ExitCode;

use bevy_soft_tissue::body::BodySettings;
use bevy_soft_tissue::contact::{ComplianceMode, LcpSolver};
use bevy_soft_tissue::mesh::generate::LENS_RADII;
use bevy_soft_tissue::plugin::{GpuMode, SoftTissueConfig};
use bevy_soft_tissue::scenes::cataract::CataractParams;

mod common;
use bevy_soft_tissue::solver::PreconditionerKind;
use clap::Parser;
use common::headless::{HeadlessOptions, HeadlessSummary, Recording, run_headless_with};

/// The cataract (MSICS) nucleus-extraction scene: in a window with the
/// `viewer` feature and a display, otherwise headless with per-phase timings.
#[derive(Parser)]
#[command(long_about = None)]
struct Args {
    /// Run without a window and print per-phase timings.
    #[arg(long)]
    headless: bool,
    /// Steps to run headless (default: the scripted path and one second
    /// more, 1080, or 540 with `--push-only`).
    #[arg(long, default_value_t = 0)]
    steps: usize,
    /// Light meshes.
    #[arg(long)]
    coarse: bool,
    /// The vectis stops with the lens pressed into the slit instead of
    /// delivering it out of the eye.
    #[arg(long)]
    push_only: bool,
    /// none, jacobi, exact, periodicN, async, or lagN (the factor arrives
    /// exactly N steps after it was requested).
    #[arg(long, default_value = "async", value_parser = common::args::preconditioner)]
    preconditioner: PreconditionerKind,
    /// The eye's preconditioner, where it should differ from the lens's
    /// (`--preconditioner`): the same words (headless only). Two `lagN`
    /// with different lags give a deterministic trajectory in which the
    /// bodies' factors arrive at different ages, as with `async`.
    #[arg(long, value_parser = common::args::preconditioner)]
    eye_preconditioner: Option<PreconditionerKind>,
    /// Headless: write one CSV line per step to this file (contacts, passes,
    /// factor ages, the lens's centre and velocity, the vectis's position,
    /// the lens's inverted elements; with `--repeats`, the last run's).
    #[arg(long)]
    trace: Option<std::path::PathBuf>,
    /// factorized, exact, diagonal, rest or dense.
    #[arg(long, default_value = "factorized", value_parser = compliance)]
    compliance: ComplianceMode,
    /// Steps a factor serves the compliance (`ContactSettings::factor_reuse`).
    #[arg(long)]
    reuse: Option<u64>,
    /// Contact passes per step.
    #[arg(long)]
    passes: Option<usize>,
    /// Detect at the free motion, not at the predicted positions.
    #[arg(long = "no-predict", action = clap::ArgAction::SetFalse)]
    predict: bool,
    /// Switch off the rigid-mode completion of a lagging factor.
    #[arg(long = "no-rigid-modes", action = clap::ArgAction::SetFalse)]
    rigid_modes: bool,
    /// Tool contacts inside surface triangles as well as at their vertices
    /// (`ContactSettings::tool_faces`).
    #[arg(long)]
    tool_faces: bool,
    /// `ContactSettings::consistency_tolerance` (`inf`: never refresh).
    #[arg(long)]
    consistency_tolerance: Option<f64>,
    /// `ContactSettings::energy_tolerance` (default: off).
    #[arg(long)]
    energy_tolerance: Option<f64>,
    /// `CgSettings::tolerance` of both bodies, the relative residual at which
    /// the free motion's conjugate gradient stops (default 1e-6).
    #[arg(long)]
    cg_tolerance: Option<f64>,
    /// The contact solver: pgs, block, nncg or subspace.
    #[arg(long, default_value = "subspace", value_parser = common::args::lcp_solver)]
    lcp: LcpSolver,
    /// Write each step's first-pass contact problem to this folder (for the
    /// `lcp` bench).
    #[arg(long = "record-lcp")]
    record: Option<std::path::PathBuf>,
    /// Record only problems with at least this many contacts.
    #[arg(long = "record-min-contacts", default_value_t = 91)]
    record_min: usize,
    /// A simulated haptic device drives the vectis (window only).
    #[arg(long)]
    haptics: bool,
    /// Where `W` is built: off (CPU), on (GPU whenever there are contacts)
    /// or autoN (GPU from N constraint rows on). Needs the `gpu` feature and
    /// a GPU adapter.
    #[arg(long, default_value = "off", value_parser = gpu_mode)]
    gpu: GpuMode,
    /// Headless: the pipeline's sets straight in `FixedPostUpdate` (Bevy's
    /// multi-threaded executor) instead of their own single-threaded
    /// schedule (`SoftTissuePlugins::new(FixedPostUpdate)`).
    #[arg(long)]
    in_fixed_post_update: bool,
    /// Headless: run the scene this many times and end with the ranges and
    /// medians of the steps/s, deliveries and penetrations over the runs.
    #[arg(long, default_value_t = 1)]
    repeats: usize,
}

fn gpu_mode(v: &str) -> Result<GpuMode, String> {
    match v {
        "off" => Ok(GpuMode::Off),
        "on" => Ok(GpuMode::On),
        _ => v
            .strip_prefix("auto")
            .and_then(|n| n.parse().ok())
            .map(|min_rows| GpuMode::Auto { min_rows })
            .ok_or_else(|| format!("unknown GPU mode `{v}` (off, on or autoN)")),
    }
}

fn compliance(v: &str) -> Result<ComplianceMode, String> {
    Ok(match v {
        "factorized" => ComplianceMode::Factorized,
        "exact" => ComplianceMode::Exact,
        "diagonal" => ComplianceMode::Diagonal,
        "rest" => ComplianceMode::RestPrecomputed,
        "dense" => ComplianceMode::DenseRows,
        _ => return Err(format!("unknown compliance `{v}`")),
    })
}

/// Both bodies' settings from the arguments.
fn body_settings(args: &Args) -> BodySettings {
    let mut body = BodySettings {
        preconditioner: args.preconditioner,
        ..Default::default()
    };
    if let Some(t) = args.cg_tolerance {
        body.cg.tolerance = t;
    }
    body
}

fn headless(args: &Args, params: &CataractParams, config: SoftTissueConfig) -> ExitCode {
    println!(
        "cataract scene, headless: {} steps of {:.4} s, preconditioner {:?}{}, compliance {:?}, GPU {:?}",
        args.steps,
        config.timestep,
        args.preconditioner,
        args.eye_preconditioner
            .map(|k| format!(" (the eye's {k:?})"))
            .unwrap_or_default(),
        args.compliance,
        config.gpu
    );
    let body = body_settings(args);
    let options = HeadlessOptions {
        recording: args.record.as_ref().map(|dir| Recording {
            dir: dir.clone(),
            min_contacts: args.record_min,
        }),
        in_fixed_post_update: args.in_fixed_post_update,
        eye_preconditioner: args.eye_preconditioner,
        trace: args.trace.clone(),
    };
    let runs = args.repeats.max(1);
    let mut done = Vec::new();
    let mut failed = false;
    for run in 0..runs {
        if runs > 1 {
            println!("run {} of {runs}", run + 1);
        }
        match run_headless_with(params, config.clone(), body, args.steps, &options) {
            Ok(s) => {
                print_summary(&s, params, options.recording.as_ref());
                if s.max_penetration > s.tolerance {
                    eprintln!("penetration beyond tolerance");
                    failed = true;
                }
                done.push(s);
            }
            Err(e) => {
                eprintln!("cataract scene failed: {e}");
                failed = true;
            }
        }
    }
    if runs > 1 {
        print_ranges(&done, params, runs);
    }
    if failed {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    }
}

/// [`lens_end`]'s word for a lens out of the eye.
const DELIVERED: &str = "out of the eye: delivered";

/// How far out of the eye the lens ended: delivered, in the incision, or inside.
fn lens_end(s: &HeadlessSummary, params: &CataractParams) -> (f64, &'static str) {
    // The eye is centred at the origin.
    let (end, radius) = (s.lens_center.1.norm(), params.eye.radius);
    let place = if end > radius + LENS_RADII[2] {
        DELIVERED
    } else if end > radius - LENS_RADII[2] {
        "in the incision"
    } else {
        "inside the eye"
    };
    (end, place)
}

/// The ranges and medians over the runs of `--repeats`.
fn print_ranges(done: &[HeadlessSummary], params: &CataractParams, runs: usize) {
    let range = |mut v: Vec<f64>| common::bench::spread(&mut v, 1);
    let per_s = |ms: f64| 1e3 / ms;
    println!(
        "over {} of {runs} runs (steps/s from the wall clock of the pipeline):",
        done.len()
    );
    println!(
        "  jam (steps/s): {} ({} from the phases' timers)",
        range(
            done.iter()
                .filter_map(|s| s.jam.1.map(|j| per_s(j.0)))
                .collect()
        ),
        range(
            done.iter()
                .filter_map(|s| s.jam.1.map(|j| per_s(j.1)))
                .collect()
        )
    );
    println!(
        "  steps with 50-90 contacts (steps/s): {} ({} from the phases' timers)",
        range(
            done.iter()
                .filter_map(|s| s.median_ms_50_90.map(|b| per_s(b.0)))
                .collect()
        ),
        range(
            done.iter()
                .filter_map(|s| s.median_ms_50_90.map(|b| per_s(b.1)))
                .collect()
        )
    );
    println!(
        "  median step (steps/s): {}",
        range(done.iter().map(|s| s.steps_per_second).collect())
    );
    let delivered = done
        .iter()
        .filter(|s| lens_end(s, params).1 == DELIVERED)
        .count();
    let deepest = done.iter().map(|s| s.max_penetration).fold(0.0, f64::max);
    let in_faces = done.iter().map(|s| s.vectis_in_faces.0).fold(0.0, f64::max);
    println!(
        "  delivered in {delivered} of {runs} runs; deepest penetration at a step's end {deepest:.2e} m \
         (vertices; the vectis inside a lens face {in_faces:.2e} m)"
    );
    println!(
        "  solves at the sweep limit per run: {:?}; consistency refreshes per run: {:?}",
        done.iter().map(|s| s.lcp_capped).collect::<Vec<_>>(),
        done.iter()
            .map(|s| s.consistency_refactors)
            .collect::<Vec<_>>()
    );
}

/// Prints one run's report.
fn print_summary(s: &HeadlessSummary, params: &CataractParams, recording: Option<&Recording>) {
    println!(
        "time per phase (ms): median over all steps, mean over steps with 50-90 contacts, mean over the jam (> 90);"
    );
    println!(
        "  step: the phases' timers summed; pipeline: the wall clock of the whole step, which the steps/s below use"
    );
    for (((n, v), b), j) in common::headless::PHASES
        .iter()
        .zip(s.median_ms)
        .zip(s.mean_ms_50_90)
        .zip(s.mean_ms_jam)
    {
        println!("  {n:<12} {v:8.3} {b:8.3} {j:8.3}");
    }
    println!("steps/s (median step): {:.1}", s.steps_per_second);
    match s.median_ms_50_90 {
        Some((wall, sum)) => println!(
            "steps/s over steps with 50-90 contacts: {:.1} ({:.1} from the phases' timers)",
            1e3 / wall,
            1e3 / sum
        ),
        None => println!("no step had 50-90 contacts"),
    }
    if let (n, Some((wall, sum))) = s.jam {
        println!(
            "steps with more than 90 contacts (lens jammed in the slit): {n}, {:.1} steps/s ({:.1} from the phases' timers), {:.0} contacts on average",
            1e3 / wall,
            1e3 / sum,
            s.contacts_jam
        );
    }
    println!("contacts: median {}, max {}", s.contacts.0, s.contacts.1);
    println!(
        "CG iterations per step (both bodies): {:.2} (steps with 50-90 contacts: {:.2})",
        s.cg_iterations, s.cg_iterations_50_90
    );
    println!(
        "LCP sweeps, contact passes per step with 50-90 contacts: {:.1}, {:.2}",
        s.lcp_50_90.0, s.lcp_50_90.1
    );
    println!(
        "contact passes: at most {} in a step, more than eight in {} steps, mean {:.2} over the jam",
        s.max_passes.0, s.max_passes.1, s.passes_jam
    );
    println!(
        "LCP sweeps (first pass): at most {}, mean {:.1} over the jam steps; solves at the sweep limit: {}",
        s.lcp_sweeps.0, s.lcp_sweeps.1, s.lcp_capped
    );
    let w = s.slowest;
    println!(
        "slowest steps: the longest {:.1} ms (step {}, {} contacts, {} passes, {} LCP solves at the sweep limit), \
         99th percentile {:.1} ms, {} steps longer than h",
        w.ms, w.step, w.contacts, w.passes, w.capped, w.p99_ms, w.over_h
    );
    let phases: Vec<String> = common::headless::PHASES
        .iter()
        .zip(w.phase_ms)
        .take(8)
        .map(|(n, v)| format!("{n} {v:.1}"))
        .collect();
    println!("  the longest step's phases (ms): {}", phases.join(", "));
    println!(
        "compliance on the stepping thread, mean per jam step: {:.1} node columns, {:.0} Gram blocks",
        s.columns_jam.0, s.columns_jam.1
    );
    println!(
        "factors refreshed by the contact phase's consistency checks: {}; \
         rescues that took the worker's factor of the same step: {} of {}",
        s.consistency_refactors, s.rescues.1, s.rescues.0
    );
    let (offered, body, none) = s.warps;
    println!(
        "warp of the lagging factors (both bodies): of {offered} solves, each node's turn {}, \
         the body's turn {body}, none {none}",
        offered - body - none
    );
    if let Some(g) = s.gpu {
        let per = |t: f64, n: u64| t * 1e3 / n.max(1) as f64;
        println!("GPU compliance dispatches: {}", g.dispatches);
        println!(
            "GPU compliance: {} builds, {:.3} ms each ({:.3} ms waiting for the device); \
             {} factor uploads, {:.3} ms each",
            g.builds,
            per(g.compute_seconds, g.builds),
            per(g.wait_seconds, g.builds),
            g.uploads,
            per(g.upload_seconds, g.uploads)
        );
        if g.timed > 0 {
            let [f, gr, c] = g.kernel_seconds;
            println!(
                "GPU timestamps: {} builds, the device busy {:.3} ms each \
                 (forward {:.3}, Gram {:.3}, contraction {:.3}); longest path \
                 {:.1} nodes per build on average, {} at most; {} builds walked \
                 in workgroup memory, {} by pieces; the forward walk {:.1} steps \
                 per build on average",
                g.timed,
                per(g.span_seconds, g.timed),
                per(f, g.timed),
                per(gr, g.timed),
                per(c, g.timed),
                g.path_sum as f64 / g.builds.max(1) as f64,
                g.longest_path,
                g.shared_forwards,
                g.piece_forwards,
                g.depth_sum as f64 / g.builds.max(1) as f64
            );
        }
    }
    if let Some(r) = recording {
        println!(
            "contact problems with at least {} contacts written to {}: {}",
            r.min_contacts,
            r.dir.display(),
            s.recorded
        );
    }
    let moved = (s.lens_center.1 - s.lens_center.0) * 1e3;
    println!(
        "lens centre moved by ({:.2}, {:.2}, {:.2}) mm, peak speed {:.1} mm/s",
        moved.x,
        moved.y,
        moved.z,
        s.max_lens_speed * 1e3
    );
    let (end, place) = lens_end(s, params);
    println!(
        "lens centre ends {:.2} mm from the eye's centre ({place})",
        end * 1e3
    );
    println!(
        "max penetration at step end {:.2e} m (step {}, {} contact passes), lens-sclera {:.2e} m \
         (tolerance {:.2e} m)",
        s.max_penetration,
        s.deepest_step.0,
        s.deepest_step.1,
        s.max_tissue_penetration,
        s.tolerance
    );
    let (in_faces, at_end, triangles) = s.vectis_in_faces;
    println!(
        "the vectis inside the lens's surface triangles between their vertices (91 points each; \
         the contacts hold faces out only with --tool-faces): at most {in_faces:.2e} m at a step's end; at the end {at_end:.2e} m, {triangles} \
         triangles deeper than the tolerance"
    );
    let [(lens, lens_all), (all, all_all)] = s.inverted_at_end;
    println!(
        "elements flat or inverted at the end: lens {lens} of {lens_all}, the eye {} of {}",
        all - lens,
        all_all - lens_all
    );
}

fn main() -> ExitCode {
    let mut args = Args::parse();
    let mut params = if args.coarse {
        CataractParams::coarse()
    } else {
        CataractParams::default()
    };
    if args.push_only {
        params = params.push_only();
    }
    if args.steps == 0 {
        // The scripted path and one second more.
        args.steps = if args.push_only { 540 } else { 1080 };
    }
    let mut config = SoftTissueConfig {
        timestep: 1.0 / 60.0,
        ..Default::default()
    };
    config.contact.compliance = args.compliance;
    if let Some(r) = args.reuse {
        config.contact.factor_reuse = r;
    }
    config.contact.predict = args.predict;
    config.contact.rigid_modes = args.rigid_modes;
    config.contact.tool_faces |= args.tool_faces;
    if let Some(t) = args.consistency_tolerance {
        config.contact.consistency_tolerance = t;
    }
    if let Some(t) = args.energy_tolerance {
        config.contact.energy_tolerance = t;
    }
    config.contact.lcp.solver = args.lcp;
    config.gpu = args.gpu;
    if let Some(p) = args.passes {
        config.contact.max_passes = p.max(1);
    }
    // Probed before Bevy builds the window: winit panics without a display
    // it can connect to, the renderer without a GPU adapter.
    let no_window = if args.headless { None } else { no_window() };
    if args.headless || no_window.is_some() {
        if let Some(why) = &no_window {
            println!("{why}; running headless");
        }
        if args.haptics {
            println!(
                "--haptics needs the window; running without haptics \
                 (the headless haptic benchmark: cargo run --release --example haptics)"
            );
        }
        return headless(&args, &params, config);
    }
    let headless_only: Vec<&str> = [
        ("--eye-preconditioner", args.eye_preconditioner.is_some()),
        ("--trace", args.trace.is_some()),
    ]
    .into_iter()
    .filter_map(|(name, given)| given.then_some(name))
    .collect();
    if !headless_only.is_empty() {
        let (verb, pronoun) = if headless_only.len() > 1 {
            ("apply", "them")
        } else {
            ("applies", "it")
        };
        println!(
            "{} only {verb} headless (--headless); the window runs without {pronoun}",
            headless_only.join(" and ")
        );
    }
    #[cfg(feature = "viewer")]
    viewer::run(params, config, body_settings(&args), args.haptics);
    ExitCode::SUCCESS
}

/// Why the viewer cannot open a window here, if it cannot: no X display
/// that answers, or no GPU adapter for the renderer.
#[cfg(feature = "viewer")]
fn no_window() -> Option<String> {
    common::display::x11_display()
        .and_then(|_| bevy_soft_tissue::gpu::probe_adapter(None).map_err(|e| e.to_string()))
        .err()
}

#[cfg(not(feature = "viewer"))]
fn no_window() -> Option<String> {
    Some("built without the `viewer` feature".into())
}

#[cfg(feature = "viewer")]
mod viewer {
    use std::collections::VecDeque;
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
    use std::time::Instant;

    use bevy::input::mouse::{AccumulatedMouseMotion, AccumulatedMouseScroll};
    use bevy::prelude::*;
    use bevy_egui::{EguiContexts, EguiPlugin, EguiPrimaryContextPass, egui};
    use bevy_soft_tissue::SoftTissuePlugins;
    use bevy_soft_tissue::body::BodySettings;
    use bevy_soft_tissue::contact::ComplianceMode;
    use bevy_soft_tissue::haptics::{HapticSettings, SimulatedDevice, SimulatedHand};
    use bevy_soft_tissue::plugin::render::BodyColoring;
    use bevy_soft_tissue::plugin::{
        GpuMode, HapticTool, HapticsPlugin, HapticsStatus, PreconditionerOverride, SoftBody,
        SoftTissueConfig, SoftTissueDiagnostics,
    };
    use bevy_soft_tissue::scenes::cataract::{CataractParams, ExtractionPath, incision_frame};
    use bevy_soft_tissue::scenes::{CataractScenePlugin, Eye, Lens, Vectis};
    use bevy_soft_tissue::solver::PreconditionerKind;

    #[derive(Resource)]
    struct Ui {
        preconditioner: usize,
        period: u32,
        compliance: usize,
        gravity: bool,
        history: VecDeque<[f32; 10]>,
        /// Haptic rate (Hz) and rendered force (mN), one row per frame.
        haptic_history: VecDeque<[f32; 2]>,
        frame_time: f32,
    }

    /// What the simulated hand follows, shared with the haptic thread: the
    /// scripted path on the scene's clock, plus an offset the keys move.
    struct HandShared {
        /// Scene time of the script, seconds (`f64` bits).
        clock: AtomicU64,
        /// Wall time of the last fixed step since `start`, seconds (`f64` bits).
        wall: AtomicU64,
        /// The hand's offset from the path, metres (`f64` bits).
        offset: [AtomicU64; 3],
        paused: AtomicBool,
        start: Instant,
    }

    #[derive(Resource, Clone)]
    struct Hand(Arc<HandShared>);

    fn load(a: &AtomicU64) -> f64 {
        f64::from_bits(a.load(Ordering::Acquire))
    }

    fn store(a: &AtomicU64, v: f64) {
        a.store(v.to_bits(), Ordering::Release);
    }

    /// The arrow of the rendered force: a shaft and a head.
    #[derive(Component)]
    enum ForceArrow {
        Shaft,
        Head,
    }

    /// Arrow length per newton of rendered force (1 mm per 2 mN).
    const ARROW_M_PER_N: f32 = 0.5;

    #[derive(Component)]
    struct OrbitCamera {
        yaw: f32,
        pitch: f32,
        distance: f32,
        target: Vec3,
    }

    pub fn run(
        params: CataractParams,
        config: SoftTissueConfig,
        body: BodySettings,
        haptics: bool,
    ) {
        let (er, _) = incision_frame(&params);
        let target = Vec3::new(er.x as f32, er.y as f32, er.z as f32) * 0.007;
        let path = ExtractionPath::new(&params);
        let mut app = App::new();
        app.add_plugins(DefaultPlugins.set(WindowPlugin {
            primary_window: Some(Window {
                title: "bevy_soft_tissue — MSICS nucleus extraction".into(),
                resolution: (1280u32, 800u32).into(),
                ..Default::default()
            }),
            ..Default::default()
        }))
        .add_plugins(EguiPlugin::default())
        .add_plugins(SoftTissuePlugins::default().with_config(config))
        .add_plugins(CataractScenePlugin { params, body })
        .insert_resource(ClearColor(Color::srgb(0.06, 0.07, 0.09)))
        .insert_resource(Ui {
            preconditioner: 3,
            period: 4,
            compliance: 0,
            gravity: false,
            history: VecDeque::new(),
            haptic_history: VecDeque::new(),
            frame_time: 0.0,
        })
        .add_systems(Startup, move |mut commands: Commands| {
            setup(&mut commands, target)
        })
        .add_systems(PostStartup, style_bodies)
        .add_systems(Update, (orbit_camera, keyboard_tool, record))
        .add_systems(EguiPrimaryContextPass, panel);
        if haptics {
            add_haptics(&mut app, path);
        }
        app.run();
    }

    /// A simulated device drives the vectis through `HapticsPlugin`: its hand
    /// follows the scripted path on the scene's clock (interpolated by the
    /// wall clock within a step), off by the keys' offset.
    fn add_haptics(app: &mut App, path: ExtractionPath) {
        let shared = Arc::new(HandShared {
            clock: AtomicU64::new(0f64.to_bits()),
            wall: AtomicU64::new(0f64.to_bits()),
            offset: Default::default(),
            paused: AtomicBool::new(false),
            start: Instant::now(),
        });
        let h = shared.clone();
        let step = app
            .world()
            .get_resource::<SoftTissueConfig>()
            .map_or(1.0 / 60.0, |c| c.timestep);
        let script = move |_: f64| {
            let since = if h.paused.load(Ordering::Acquire) {
                0.0
            } else {
                (h.start.elapsed().as_secs_f64() - load(&h.wall)).clamp(0.0, step)
            };
            let mut pose = path.pose(load(&h.clock) + since);
            for (k, o) in h.offset.iter().enumerate() {
                pose.translation.vector[k] += load(o);
            }
            pose
        };
        let hand = SimulatedHand {
            mass: 0.2,
            stiffness: 2000.0,
            damping: 0.7 * 2.0 * (2000.0f64 * 0.2).sqrt(),
        };
        let device = match SimulatedDevice::scripted(script).with_hand(hand) {
            Ok(d) => d,
            Err(e) => {
                error!("simulated device: {e}");
                return;
            }
        };
        app.add_plugins(HapticsPlugin::new(device, HapticSettings::default()))
            .insert_resource(Hand(shared))
            .add_systems(Startup, spawn_arrow)
            .add_systems(PostStartup, hand_drives_vectis)
            .add_systems(FixedUpdate, advance_hand)
            .add_systems(Update, force_arrow);
    }

    /// The vectis follows the device (its script no longer drives it).
    fn hand_drives_vectis(mut commands: Commands, mut q: Query<(Entity, &mut Vectis)>) {
        for (e, mut v) in &mut q {
            v.scripted = false;
            commands.entity(e).insert(HapticTool);
        }
    }

    /// The hand's script advances with the scene's fixed steps.
    fn advance_hand(hand: Res<Hand>, config: Res<SoftTissueConfig>) {
        let h = &hand.0;
        if !h.paused.load(Ordering::Acquire) {
            store(&h.clock, load(&h.clock) + config.timestep);
        }
        store(&h.wall, h.start.elapsed().as_secs_f64());
    }

    fn spawn_arrow(
        mut commands: Commands,
        mut meshes: ResMut<Assets<Mesh>>,
        mut materials: ResMut<Assets<StandardMaterial>>,
    ) {
        let material = materials.add(StandardMaterial {
            base_color: Color::srgb(1.0, 0.55, 0.1),
            unlit: true,
            ..Default::default()
        });
        commands.spawn((
            Mesh3d(meshes.add(Cylinder::new(0.2e-3, 1.0))),
            MeshMaterial3d(material.clone()),
            Transform::default(),
            Visibility::Hidden,
            ForceArrow::Shaft,
        ));
        commands.spawn((
            Mesh3d(meshes.add(Cone {
                radius: 0.5e-3,
                height: 1.2e-3,
            })),
            MeshMaterial3d(material),
            Transform::default(),
            Visibility::Hidden,
            ForceArrow::Head,
        ));
    }

    /// The arrow starts at the blade's centre and points along the rendered
    /// force, its length proportional to it.
    fn force_arrow(
        status: Res<HapticsStatus>,
        mut q: Query<(&ForceArrow, &mut Transform, &mut Visibility)>,
    ) {
        let s = &status.state;
        let f = Vec3::new(s.force.x as f32, s.force.y as f32, s.force.z as f32);
        let p = s.proxy.translation.vector;
        let origin = Vec3::new(p.x as f32, p.y as f32, p.z as f32);
        let len = (f.length() * ARROW_M_PER_N).min(0.025);
        let shown = len > 2e-5 && f.is_finite();
        let dir = f.normalize_or(Vec3::Y);
        let rotation = Quat::from_rotation_arc(Vec3::Y, dir);
        for (part, mut t, mut v) in &mut q {
            *v = if shown {
                Visibility::Visible
            } else {
                Visibility::Hidden
            };
            *t = match part {
                ForceArrow::Shaft => Transform::from_translation(origin + dir * 0.5 * len)
                    .with_rotation(rotation)
                    .with_scale(Vec3::new(1.0, len, 1.0)),
                ForceArrow::Head => Transform::from_translation(origin + dir * (len + 0.6e-3))
                    .with_rotation(rotation),
            };
        }
    }

    fn setup(commands: &mut Commands, target: Vec3) {
        commands.spawn((
            Camera3d::default(),
            // Millimetre-scale scene: the default near plane (0.1 m) would clip everything.
            Projection::from(PerspectiveProjection {
                near: 1e-4,
                far: 1.0,
                ..Default::default()
            }),
            Transform::default(),
            OrbitCamera {
                yaw: 0.6,
                pitch: 0.5,
                distance: 0.045,
                target,
            },
        ));
        commands.spawn((
            DirectionalLight {
                illuminance: 9000.0,
                shadow_maps_enabled: false,
                ..Default::default()
            },
            Transform::from_xyz(0.3, -0.2, 1.0).looking_at(Vec3::ZERO, Vec3::Z),
        ));
        commands.insert_resource(GlobalAmbientLight {
            brightness: 400.0,
            ..Default::default()
        });
    }

    fn style_bodies(
        mut commands: Commands,
        eyes: Query<Entity, (With<Eye>, Without<BodyColoring>)>,
    ) {
        for e in &eyes {
            commands
                .entity(e)
                .insert(BodyColoring::Solid(Color::srgba(0.95, 0.9, 0.85, 0.35)));
        }
    }

    fn orbit_camera(
        mut q: Query<(&mut OrbitCamera, &mut Transform)>,
        buttons: Res<ButtonInput<MouseButton>>,
        motion: Res<AccumulatedMouseMotion>,
        scroll: Res<AccumulatedMouseScroll>,
        mut contexts: EguiContexts,
    ) {
        let over_ui = contexts
            .ctx_mut()
            .map(|c| c.is_pointer_over_egui())
            .unwrap_or(false);
        for (mut o, mut t) in &mut q {
            if buttons.pressed(MouseButton::Right) && !over_ui {
                o.yaw -= motion.delta.x * 0.005;
                o.pitch = (o.pitch + motion.delta.y * 0.005).clamp(-1.4, 1.4);
            }
            if !over_ui {
                o.distance = (o.distance * (1.0 - 0.1 * scroll.delta.y)).clamp(0.01, 0.2);
            }
            let dir = Vec3::new(
                o.yaw.cos() * o.pitch.cos(),
                o.yaw.sin() * o.pitch.cos(),
                o.pitch.sin(),
            );
            *t = Transform::from_translation(o.target + dir * o.distance)
                .looking_at(o.target, Vec3::Z);
        }
    }

    /// Moves the vectis (or, with haptics, the hand) with the keys.
    fn keyboard_tool(
        keys: Res<ButtonInput<KeyCode>>,
        time: Res<Time>,
        hand: Option<Res<Hand>>,
        mut q: Query<(&mut Vectis, &mut Transform)>,
    ) {
        for (mut v, mut t) in &mut q {
            if keys.just_pressed(KeyCode::Space) {
                match &hand {
                    Some(h) => {
                        h.0.paused.fetch_xor(true, Ordering::AcqRel);
                    }
                    None => v.scripted = !v.scripted,
                }
            }
            let speed = 2e-3 * time.delta_secs();
            let (fwd, side, up) = (t.local_z(), t.local_x(), t.local_y());
            let mut d = Vec3::ZERO;
            for (k, dir) in [
                (KeyCode::KeyW, *fwd),
                (KeyCode::KeyS, -*fwd),
                (KeyCode::KeyD, *side),
                (KeyCode::KeyA, -*side),
                (KeyCode::KeyE, *up),
                (KeyCode::KeyQ, -*up),
            ] {
                if keys.pressed(k) {
                    d += dir;
                }
            }
            if d != Vec3::ZERO {
                let d = d.normalize() * speed;
                match &hand {
                    Some(h) => {
                        for (k, o) in h.0.offset.iter().enumerate() {
                            store(o, load(o) + f64::from(d[k]));
                        }
                    }
                    None => {
                        v.scripted = false;
                        t.translation += d;
                    }
                }
            }
        }
    }

    fn record(
        mut ui: ResMut<Ui>,
        diag: Res<SoftTissueDiagnostics>,
        time: Res<Time>,
        haptics: Option<Res<HapticsStatus>>,
    ) {
        if let Some(h) = haptics {
            let s = &h.state;
            ui.haptic_history
                .push_back([s.stats.rate_hz as f32, 1e3 * s.force.norm() as f32]);
            if ui.haptic_history.len() > 300 {
                ui.haptic_history.pop_front();
            }
        }
        ui.frame_time = 0.9 * ui.frame_time + 0.1 * time.delta_secs();
        let fps = if ui.frame_time > 0.0 {
            1.0 / ui.frame_time
        } else {
            0.0
        };
        let d = &*diag;
        let row = [
            fps,
            d.cg_iterations as f32,
            d.contacts as f32,
            d.assemble_ms as f32,
            d.factorize_ms as f32,
            d.free_motion_ms as f32,
            d.detect_ms as f32,
            d.compliance_ms as f32,
            (d.lcp_ms + d.correct_ms) as f32,
            d.step_ms() as f32,
        ];
        ui.history.push_back(row);
        if ui.history.len() > 300 {
            ui.history.pop_front();
        }
    }

    fn chart(ui: &mut egui::Ui, title: &str, series: &[(&str, Vec<f32>, egui::Color32)]) {
        let max = series
            .iter()
            .flat_map(|s| s.1.iter())
            .fold(1e-6f32, |a, &b| a.max(b));
        let last: Vec<String> = series
            .iter()
            .map(|s| format!("{} {:.2}", s.0, s.1.last().copied().unwrap_or(0.0)))
            .collect();
        ui.label(format!("{title}: {}", last.join(", ")));
        let (rect, _) = ui.allocate_exact_size(egui::vec2(300.0, 60.0), egui::Sense::hover());
        let painter = ui.painter_at(rect);
        painter.rect_filled(rect, 2.0, egui::Color32::from_gray(25));
        for (_, v, color) in series {
            let n = v.len().max(2) as f32;
            let pts: Vec<egui::Pos2> = v
                .iter()
                .enumerate()
                .map(|(i, y)| {
                    egui::pos2(
                        rect.left() + rect.width() * i as f32 / (n - 1.0),
                        rect.bottom() - rect.height() * y / max,
                    )
                })
                .collect();
            painter.add(egui::Shape::line(pts, egui::Stroke::new(1.5, *color)));
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn panel(
        mut contexts: EguiContexts,
        mut ui_state: ResMut<Ui>,
        mut config: ResMut<SoftTissueConfig>,
        diag: Res<SoftTissueDiagnostics>,
        mut commands: Commands,
        bodies: Query<Entity, With<SoftBody>>,
        mut vectis: Query<&mut Vectis>,
        lens: Query<&SoftBody, With<Lens>>,
        haptics: Option<Res<HapticsStatus>>,
        hand: Option<Res<Hand>>,
    ) -> Result {
        let ctx = contexts.ctx_mut()?;
        let s = &mut *ui_state;
        egui::Window::new("Soft tissue")
            .default_width(320.0)
            .default_height(740.0)
            .vscroll(true)
            .show(ctx, |ui| {
                ui.heading("Effects");
                ui.checkbox(&mut config.contacts, "contacts");
                ui.checkbox(&mut config.contact.friction, "friction");
                ui.checkbox(&mut config.damping, "damping");
                if ui.checkbox(&mut s.gravity, "gravity").changed() {
                    config.gravity = s.gravity.then_some(bevy::math::DVec3::new(0.0, 0.0, -9.81));
                }
                if let Some(hand) = &hand {
                    let mut paused = hand.0.paused.load(Ordering::Acquire);
                    if ui.checkbox(&mut paused, "hand paused (Space)").changed() {
                        hand.0.paused.store(paused, Ordering::Release);
                    }
                } else {
                    for mut v in &mut vectis {
                        ui.checkbox(&mut v.scripted, "scripted vectis path (Space)");
                    }
                }
                ui.separator();
                ui.heading("Preconditioner and refresh policy");
                let names = [
                    "Jacobi",
                    "Exact LDLT every step",
                    "Periodic LDLT",
                    "Async LDLT",
                ];
                let mut changed = false;
                for (i, n) in names.iter().enumerate() {
                    changed |= ui.radio_value(&mut s.preconditioner, i, *n).changed();
                }
                changed |= ui
                    .add_enabled(
                        s.preconditioner == 2,
                        egui::Slider::new(&mut s.period, 1..=32).text("refresh every N steps"),
                    )
                    .changed();
                if changed {
                    let kind = match s.preconditioner {
                        0 => PreconditionerKind::Jacobi,
                        1 => PreconditionerKind::Exact,
                        2 => PreconditionerKind::Periodic { every: s.period },
                        _ => PreconditionerKind::Async,
                    };
                    for e in &bodies {
                        commands.entity(e).insert(PreconditionerOverride(kind));
                    }
                }
                ui.separator();
                ui.heading("Contact compliance");
                let modes = [
                    ("Factorized (node columns)", ComplianceMode::Factorized),
                    ("Exact (fresh LDLT)", ComplianceMode::Exact),
                    ("Diagonal (uncoupled)", ComplianceMode::Diagonal),
                    ("Rest-precomputed dense", ComplianceMode::RestPrecomputed),
                    ("Dense rows (paper CPU)", ComplianceMode::DenseRows),
                ];
                for (i, (n, m)) in modes.iter().enumerate() {
                    if ui.radio_value(&mut s.compliance, i, *n).changed() {
                        config.contact.compliance = *m;
                    }
                }
                ui.checkbox(
                    &mut config.contact.predict,
                    "detect at predicted positions (fewer passes)",
                );
                ui.checkbox(
                    &mut config.contact.tool_faces,
                    "tool contacts inside faces (slower)",
                );
                // `Factorized` bodies' W in the compute shader (`GpuMode::On`).
                let mut on_gpu = config.gpu != GpuMode::Off;
                if ui
                    .checkbox(&mut on_gpu, "build W on the GPU (Factorized)")
                    .changed()
                {
                    config.gpu = if on_gpu { GpuMode::On } else { GpuMode::Off };
                }
                ui.separator();
                let col = |k: usize| s.history.iter().map(|r| r[k]).collect::<Vec<f32>>();
                chart(ui, "FPS", &[("fps", col(0), egui::Color32::LIGHT_GREEN)]);
                chart(
                    ui,
                    "CG iterations",
                    &[("its", col(1), egui::Color32::LIGHT_BLUE)],
                );
                chart(ui, "contacts", &[("n", col(2), egui::Color32::YELLOW)]);
                chart(
                    ui,
                    "time per phase (ms)",
                    &[
                        ("step", col(9), egui::Color32::WHITE),
                        ("asm", col(3), egui::Color32::LIGHT_RED),
                        ("fact", col(4), egui::Color32::from_rgb(255, 160, 60)),
                        ("cg", col(5), egui::Color32::LIGHT_BLUE),
                        ("det", col(6), egui::Color32::GRAY),
                        ("W", col(7), egui::Color32::YELLOW),
                        ("lcp+corr", col(8), egui::Color32::LIGHT_GREEN),
                    ],
                );
                ui.label(format!(
                    "factor age {} steps, LCP residual {:.1e} m, errors {}",
                    diag.factor_age, diag.lcp_residual, diag.errors
                ));
                if config.gpu != GpuMode::Off {
                    ui.label(format!(
                        "W on the GPU: waited {:.2} ms for the device this step",
                        diag.gpu_wait_ms
                    ));
                }
                if let Some(l) = lens.iter().next() {
                    ui.label(format!(
                        "lens: {} nodes, {} tets",
                        l.num_nodes(),
                        l.mesh().num_tets()
                    ));
                }
            });
        if let Some(h) = &haptics {
            let s = &*ui_state;
            egui::Window::new("Haptics (simulated device)")
                .anchor(egui::Align2::RIGHT_TOP, egui::vec2(-10.0, 10.0))
                .default_width(320.0)
                .show(ctx, |ui| {
                    let hc = |k: usize| s.haptic_history.iter().map(|r| r[k]).collect::<Vec<f32>>();
                    chart(
                        ui,
                        "haptic rate (Hz)",
                        &[("rate", hc(0), egui::Color32::LIGHT_GREEN)],
                    );
                    chart(
                        ui,
                        "rendered force (mN)",
                        &[("|F|", hc(1), egui::Color32::from_rgb(255, 140, 30))],
                    );
                    let st = &h.state.stats;
                    ui.label(format!(
                        "tick p50 {:.3} ms, p99 {:.3} ms; jitter p99 {:.2} ms ({}); \
                         {:.1} LCP sweeps per tick; {} tool contacts",
                        st.tick_p50 * 1e3,
                        st.tick_p99 * 1e3,
                        st.jitter_p99 * 1e3,
                        crate::common::args::priority(st.realtime),
                        st.lcp_iterations,
                        h.state.contacts
                    ));
                    ui.label("arrow: the force on the hand, 1 mm per 2 mN");
                    if let Some(e) = &h.error {
                        ui.label(format!("haptic loop: {e}"));
                    }
                });
        }
        Ok(())
    }
}
