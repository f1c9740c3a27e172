//! The cataract scene with a simulated haptic device driving the vectis at
//! 1 kHz, against the same scene without haptics.
//!
//! ```text
//! cargo run --release --example haptics -- --seconds 10 [--coarse] [--repeats N] [--lag N]
//!     [--budget-ms MS] [--lcp pgs|block|nncg|subspace] [--subspace-rows N] [--no-realtime]
//!     [--solvers]
//! ```
//!
//! The device's hand follows the scripted extraction on the scene's clock
//! (so both runs make the same motion), through a mass–spring arm that
//! feels the rendered force; the vectis the tissue sees is the coupled
//! pose. Prints the achieved haptic rate, the tick time (p50, p99, max), the
//! jitter, the LCP sweeps per tick, force continuity (the largest jump
//! between ticks, within a step and across steps) and the scene's steps/s
//! with and without haptics.
//!
//! Each repeat runs three scenes one after the other: without haptics (the
//! vectis on the script), with haptics, and a replay without haptics of the
//! poses the haptic run gave the vectis. The first pair is the comparison
//! the scene's user sees; the second has the same tool motion (so nearly the
//! same contacts) on both sides, and so isolates what the haptic thread costs
//! the stepping threads. With `--repeats N` the summary gives each ratio's
//! range and median over the repeats. With the default `Async`
//! preconditioner the trajectory depends on when background factors arrive,
//! so runs with the same tool motion differ in their contacts and the jam's
//! length, and so in steps/s; `--lag N` (`AsyncLagged`) makes it independent
//! of thread timing, and the replay then repeats the haptic run step for
//! step (the distance between their last states is printed: 0 when they
//! agree to the bit).
//!
//! `--solvers` measures the tick's LCP instead, without threads: the scene
//! steps with the vectis on the script, and after each step 16 ticks with
//! the device along the script's next step run on the calling thread
//! through one renderer per tick solver (`HapticSettings::default()`: the
//! subspace step on at most 128 free rows; block Gauss–Seidel alone; the
//! subspace step with no bound, and on at most 256 and 64 rows), each on
//! the same problems and poses and with no time budget: the work to the
//! tolerance, per solver, free of the scheduler's noise, and how far their
//! forces are apart. `--lcp` and `--subspace-rows` set the haptic loop's
//! tick solver in the three runs. `--no-realtime` runs the haptic thread at
//! normal priority (`HapticSettings::realtime_priority` = 0); the output
//! says which priority the thread got.

mod common;

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use bevy_soft_tissue::core_prelude::*;
use bevy_soft_tissue::haptics::{
    DeviceLimits, HapticLoop, HapticProblem, HapticRenderer, HapticSettings, HapticStats,
    SimulatedDevice, SimulatedHand,
};
use bevy_soft_tissue::scenes::cataract::{self, CataractParams, ExtractionPath};
use clap::Parser;

#[derive(Parser)]
#[command(about = "Haptic loop at 1 kHz on the cataract scene")]
struct Args {
    /// Scene time to simulate in each run, seconds (at least one step).
    #[arg(long, default_value_t = 10.0, value_parser = seconds)]
    seconds: f64,
    /// The coarse scene (fewer elements).
    #[arg(long)]
    coarse: bool,
    /// Repeats of the three runs (without, with haptics, replay), alternating.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..))]
    repeats: u32,
    /// Factor the bodies' matrices in the background but use each factor
    /// exactly N steps after it was asked for (`AsyncLagged`) instead of
    /// when it is ready (`Async`, the default): the scene's trajectory then
    /// no longer depends on thread timing, and the replay repeats the haptic
    /// run step for step.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    lag: Option<u32>,
    /// The haptic LCP's time budget per tick, milliseconds (default: that of
    /// `HapticSettings::default()`).
    #[arg(long)]
    budget_ms: Option<f64>,
    /// The haptic tick's LCP solver: pgs, block, nncg or subspace (default: that of
    /// `HapticSettings::default()`).
    #[arg(long, value_parser = common::args::lcp_solver)]
    lcp: Option<LcpSolver>,
    /// Most free rows the tick's subspace step factorizes (default: that of
    /// `HapticSettings::default()`).
    #[arg(long)]
    subspace_rows: Option<usize>,
    /// Run the haptic thread at normal priority instead of asking for the
    /// real-time priority of `HapticSettings::default()`.
    #[arg(long)]
    no_realtime: bool,
    /// Measure the tick's LCP per solver on the same problems, without
    /// threads (see the module docs), instead of the three runs.
    #[arg(long)]
    solvers: bool,
}

const H: f64 = 1.0 / 60.0;

/// A run's scene time: finite, and at least one step.
fn seconds(v: &str) -> std::result::Result<f64, String> {
    match v.parse::<f64>() {
        Ok(s) if s.is_finite() && s >= H => Ok(s),
        _ => Err(format!(
            "`{v}` is not a time of at least one step ({H:.4} s)"
        )),
    }
}

struct Run {
    steps: usize,
    wall: f64,
    max_contacts: usize,
}

impl Run {
    fn rate(&self) -> f64 {
        self.steps as f64 / self.wall
    }
}

struct HapticRun {
    run: Run,
    stats: HapticStats,
    max_force: f64,
    max_lag: f64,
    /// The vectis pose of each step (the coupled pose), for the replay.
    poses: Vec<Pose>,
    /// Each body's node positions after the last step.
    last_positions: Vec<Vec<Vec3>>,
}

/// The cataract scene and the vectis's scripted path.
struct Setup<'a> {
    params: &'a CataractParams,
    settings: BodySettings,
}

fn scene(setup: &Setup) -> Result<(Scene, ExtractionPath)> {
    let built = cataract::build(setup.params, setup.settings)?;
    let mut scene = Scene::new(built.contact)?;
    scene.add_body(built.lens);
    scene.add_body(built.eye);
    scene.add_tool(built.vectis);
    Ok((scene, built.path))
}

/// Steps the scene for `seconds` of scene time; `before` sets the vectis
/// for step `i` at time `t`, `after` sees the stepped scene.
fn run(
    scene: &mut Scene,
    seconds: f64,
    mut before: impl FnMut(&mut Scene, usize, f64) -> Result<()>,
    mut after: impl FnMut(&Scene),
) -> Result<Run> {
    let n = (seconds / H).round() as usize;
    let t0 = Instant::now();
    let mut max_contacts = 0;
    for i in 0..n {
        before(scene, i, i as f64 * H)?;
        scene.step(H)?;
        max_contacts = max_contacts.max(scene.contact.report().contacts);
        after(scene);
    }
    Ok(Run {
        steps: n,
        wall: t0.elapsed().as_secs_f64(),
        max_contacts,
    })
}

fn main() -> std::process::ExitCode {
    let args = Args::parse();
    match go(&args) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("haptics: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Without haptics: the vectis follows the script.
fn plain_run(setup: &Setup, seconds: f64) -> Result<Run> {
    let (mut plain, path) = scene(setup)?;
    run(
        &mut plain,
        seconds,
        |s, _, t| s.tools[0].set_pose(path.pose(t + H)),
        |_| {},
    )
}

/// Without haptics, the vectis at the poses a haptic run gave it; also
/// the largest distance of a node from where the haptic run left it.
fn replay_run(setup: &Setup, h: &HapticRun) -> Result<(Run, f64)> {
    let (mut replay, _) = scene(setup)?;
    let run = run(
        &mut replay,
        h.poses.len() as f64 * H,
        |s, i, _| s.tools[0].set_pose(h.poses[i]),
        |_| {},
    )?;
    let apart = replay
        .bodies
        .iter()
        .zip(&h.last_positions)
        .flat_map(|(b, last)| b.positions().iter().zip(last))
        .map(|(a, b)| (a - b).norm())
        .fold(0.0, f64::max);
    Ok((run, apart))
}

/// With haptics: the hand follows the script on the scene's clock,
/// interpolated between steps by the wall clock (at most one step).
fn haptic_run(setup: &Setup, seconds: f64, args: &Args) -> Result<HapticRun> {
    let (mut haptic_scene, path) = scene(setup)?;
    haptic_scene.contact.capture_tool(Some(0));
    let clock = Arc::new(AtomicU64::new(0f64.to_bits()));
    let wall_at_step = Arc::new(AtomicU64::new(0f64.to_bits()));
    let (c, w) = (clock.clone(), wall_at_step.clone());
    let p3 = path.clone();
    let script = move |time: f64| {
        let t = f64::from_bits(c.load(Ordering::Acquire));
        let since = (time - f64::from_bits(w.load(Ordering::Acquire))).clamp(0.0, H);
        p3.pose(t + since)
    };
    let hand = SimulatedHand {
        mass: 0.2,
        stiffness: 2000.0,
        damping: 0.7 * 2.0 * (2000.0f64 * 0.2).sqrt(),
    };
    let device = SimulatedDevice::scripted(script).with_hand(hand)?;
    let mut settings = HapticSettings::default();
    if let Some(ms) = args.budget_ms {
        settings.budget = ms * 1e-3;
    }
    if let Some(solver) = args.lcp {
        settings.lcp.solver = solver;
    }
    if let Some(rows) = args.subspace_rows {
        settings.lcp.subspace_max_rows = rows;
    }
    if args.no_realtime {
        settings.realtime_priority = 0;
    }
    let haptics = std::cell::RefCell::new(HapticLoop::start(device, settings)?);
    let start = Instant::now();
    let mut max_force: f64 = 0.0;
    let mut max_lag: f64 = 0.0;
    let mut poses = Vec::with_capacity((seconds / H).round() as usize);
    let with = run(
        &mut haptic_scene,
        seconds,
        |s, _, t| {
            clock.store((t + H).to_bits(), Ordering::Release);
            wall_at_step.store(start.elapsed().as_secs_f64().to_bits(), Ordering::Release);
            let state = *haptics.borrow_mut().poll();
            let pose = if state.stats.ticks > 0 {
                max_force = max_force.max(state.force.norm());
                let aim = path.pose(t + H).translation.vector;
                max_lag = max_lag.max((state.proxy.translation.vector - aim).norm());
                state.proxy
            } else {
                path.pose(t + H)
            };
            poses.push(pose);
            s.tools[0].set_pose(pose)
        },
        |s| haptics.borrow().publish(s.contact.tool_problem()),
    )?;
    let mut haptics = haptics.into_inner();
    let state = *haptics.poll();
    haptics.stop()?;
    Ok(HapticRun {
        run: with,
        stats: state.stats,
        max_force,
        max_lag,
        poses,
        last_positions: haptic_scene
            .bodies
            .iter()
            .map(|b| b.positions().to_vec())
            .collect(),
    })
}

fn slowdown(with: &Run, without: &Run) -> f64 {
    100.0 * (1.0 - with.rate() / without.rate())
}

fn report(base: &Run, h: &HapticRun, replay: &Run, apart: f64) {
    let st = &h.stats;
    println!(
        "without haptics: {} steps in {:.2} s = {:.1} steps/s (up to {} contacts)",
        base.steps,
        base.wall,
        base.rate(),
        base.max_contacts
    );
    println!(
        "with haptics:    {} steps in {:.2} s = {:.1} steps/s (up to {} contacts)",
        h.run.steps,
        h.run.wall,
        h.run.rate(),
        h.run.max_contacts
    );
    println!(
        "replay:          {} steps in {:.2} s = {:.1} steps/s (up to {} contacts; \
         the haptic run's vectis poses, no haptic thread)",
        replay.steps,
        replay.wall,
        replay.rate(),
        replay.max_contacts
    );
    println!(
        "  the replay ends {:.3e} m from the haptic run's last state (largest node distance)",
        apart
    );
    println!(
        "  scene slowdown: {:.1} % against the scripted run (target ≤ 10 %), \
         {:.1} % against the replay",
        slowdown(&h.run, base),
        slowdown(&h.run, replay)
    );
    println!(
        "  haptic rate: {:.0} Hz over the run ({} ticks in {:.2} s; {:.0} Hz over the last 100 ticks); \
         the loop's work took {:.1} % of a core",
        st.ticks as f64 / st.elapsed.max(1e-9),
        st.ticks,
        st.elapsed,
        st.rate_hz,
        100.0 * st.busy / st.elapsed.max(1e-9)
    );
    println!(
        "  tick work: p99 {:.3} ms over the run (target < 0.8 ms); last 1000 ticks p50 {:.3} ms, \
         p99 {:.3} ms; max {:.3} ms, {} ticks over the period",
        st.run_tick_p99 * 1e3,
        st.tick_p50 * 1e3,
        st.tick_p99 * 1e3,
        st.tick_max * 1e3,
        st.overruns
    );
    println!(
        "  start-time jitter p99: {:.3} ms over the run ({:.3} ms last 1000 ticks, {}); LCP sweeps per tick {:.1} \
         (last 100), {} ticks stopped at the budget",
        st.run_jitter_p99 * 1e3,
        st.jitter_p99 * 1e3,
        common::args::priority(st.realtime),
        st.lcp_iterations,
        st.unconverged
    );
    println!(
        "  force: largest {:.4} N; largest jump between ticks {:.2e} N within a step, {:.2e} N across steps",
        h.max_force, st.max_jump_between_steps, st.max_jump_at_step
    );
    println!(
        "  problems received {}; proxy's largest distance from the script {:.3} mm",
        st.problems,
        h.max_lag * 1e3
    );
}

fn go(args: &Args) -> Result<()> {
    let params = if args.coarse {
        CataractParams::coarse()
    } else {
        CataractParams::default()
    };
    let mut settings = BodySettings::default();
    if let Some(lag) = args.lag {
        settings.preconditioner = PreconditionerKind::AsyncLagged { lag };
    }
    let setup = Setup {
        params: &params,
        settings,
    };
    println!(
        "cataract scene, {} s of scene time per run, h = 1/60 s, {} repeat(s), preconditioner {:?}",
        args.seconds, args.repeats, settings.preconditioner
    );
    if args.solvers {
        return solvers_bench(&setup, args.seconds);
    }
    let (mut vs_script, mut vs_replay, mut rates, mut p99s) = (vec![], vec![], vec![], vec![]);
    let mut jitters = vec![];
    for k in 0..args.repeats {
        if args.repeats > 1 {
            println!("\n--- repeat {} of {}", k + 1, args.repeats);
        }
        let base = plain_run(&setup, args.seconds)?;
        let h = haptic_run(&setup, args.seconds, args)?;
        let (replay, apart) = replay_run(&setup, &h)?;
        report(&base, &h, &replay, apart);
        vs_script.push(slowdown(&h.run, &base));
        vs_replay.push(slowdown(&h.run, &replay));
        rates.push(h.stats.ticks as f64 / h.stats.elapsed.max(1e-9));
        p99s.push(h.stats.run_tick_p99 * 1e3);
        jitters.push(h.stats.run_jitter_p99 * 1e3);
    }
    if args.repeats > 1 {
        println!("\nover {} repeats:", args.repeats);
        println!("  haptic rate {} Hz", common::bench::spread(&mut rates, 2));
        println!("  tick work p99 {} ms", common::bench::spread(&mut p99s, 3));
        println!(
            "  start-time jitter p99 {} ms",
            common::bench::spread(&mut jitters, 3)
        );
        println!(
            "  scene slowdown against the scripted run {} %",
            common::bench::spread(&mut vs_script, 1)
        );
        println!(
            "  scene slowdown against the replay {} %",
            common::bench::spread(&mut vs_replay, 1)
        );
    }
    Ok(())
}

/// `--solvers`: every step's tool problem, 16 ticks along the script's next
/// step, through one renderer per tick solver, timed on this thread.
fn solvers_bench(setup: &Setup, seconds: f64) -> Result<()> {
    const TICKS: usize = 16;
    let base = HapticSettings {
        budget: 1.0,
        ..HapticSettings::default()
    };
    let with = |solver: LcpSolver, rows: usize| {
        let mut s = base;
        s.lcp.solver = solver;
        s.lcp.subspace_max_rows = rows;
        s
    };
    let variants = [
        ("default", base),
        ("block", with(LcpSolver::BlockGaussSeidel, usize::MAX)),
        ("subspace", with(LcpSolver::Subspace, usize::MAX)),
        ("subspace 256", with(LcpSolver::Subspace, 256)),
        ("subspace 64", with(LcpSolver::Subspace, 64)),
    ];
    let mut renderers: Vec<HapticRenderer> = variants
        .iter()
        .map(|(_, s)| HapticRenderer::new(*s))
        .collect();
    // Each renderer hands back the problem it replaces, for the next step.
    let mut spares: Vec<Option<Box<HapticProblem>>> = vec![None; variants.len()];
    let mut work = vec![Vec::new(); variants.len()];
    let mut unconverged = vec![0usize; variants.len()];
    let mut apart: f64 = 0.0;
    let mut largest: f64 = 0.0;
    let (mut max_rows, mut sum_rows, mut ticked) = (0usize, 0usize, 0usize);
    let limits = DeviceLimits::default();
    let (mut scene, path) = scene(setup)?;
    scene.contact.capture_tool(Some(0));
    let n = (seconds / H).round() as usize;
    for i in 0..n {
        let t = i as f64 * H;
        scene.tools[0].set_pose(path.pose(t + H))?;
        scene.step(H)?;
        let problem = scene.contact.tool_problem();
        if problem.m() == 0 {
            continue;
        }
        max_rows = max_rows.max(problem.m());
        for ((r, spare), (_, settings)) in renderers.iter_mut().zip(&mut spares).zip(&variants) {
            let mut p = spare.take().unwrap_or_default();
            p.set(problem, settings);
            *spare = r.set_problem(p);
        }
        for k in 0..TICKS {
            let device = path.pose(t + H + H * k as f64 / TICKS as f64);
            let mut first = None;
            for (v, r) in renderers.iter_mut().enumerate() {
                let t0 = Instant::now();
                let out = r.tick(&device, &limits);
                work[v].push(t0.elapsed().as_secs_f64() * 1e3);
                unconverged[v] += usize::from(!out.converged);
                let f = out.contact_force;
                match first {
                    None => first = Some(f),
                    Some(f0) => apart = apart.max((f - f0).norm()),
                }
                largest = largest.max(f.norm());
            }
            sum_rows += problem.m();
            ticked += 1;
        }
    }
    if ticked == 0 {
        println!("no step had a contact on the vectis: nothing to tick (run longer)");
        return Ok(());
    }
    println!(
        "{ticked} ticks on {} steps' tool problems (rows: mean {:.0}, max {max_rows}), no budget, one thread",
        ticked / TICKS,
        sum_rows as f64 / ticked as f64
    );
    println!("tick work (ms): solver, mean, p50, p90, p99, max, ticks over 0.4 ms, unconverged");
    for (v, (name, _)) in variants.iter().enumerate() {
        let w = &mut work[v];
        w.sort_by(f64::total_cmp);
        let q = |p: f64| w[((w.len() - 1) as f64 * p).round() as usize];
        let mean = w.iter().sum::<f64>() / w.len() as f64;
        let over = w.iter().filter(|&&x| x > 0.4).count();
        println!(
            "  {name:<13} {mean:.4} {:.4} {:.4} {:.4} {:.3} {over} {}",
            q(0.5),
            q(0.9),
            q(0.99),
            q(1.0),
            unconverged[v]
        );
    }
    println!(
        "largest contact force {largest:.4e} N; largest difference between the solvers' forces {apart:.3e} N"
    );
    Ok(())
}
