//! The cataract scene with a simulated haptic device driving the vectis at
//! 1 kHz, against the same scene without haptics.
//!
//! ```text
//! cargo run --release --example haptics -- --seconds 10 [--coarse]
//! ```
//!
//! The device's hand follows the scripted extraction on the scene's clock
//! (so both runs make the same motion), through a mass–spring arm that
//! feels the rendered force; the vectis the tissue sees is the coupled
//! pose. Prints the achieved haptic rate, the tick time (p50, p99, max), the
//! jitter, the LCP sweeps per tick, force continuity (the largest jump
//! between ticks, within a step and across steps) and the scene's steps/s
//! with and without haptics.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Instant;

use bevy_soft_tissue::core_prelude::*;
use bevy_soft_tissue::haptics::{HapticLoop, HapticSettings, SimulatedDevice, SimulatedHand};
use bevy_soft_tissue::scenes::cataract::{self, CataractParams};
use clap::Parser;

#[derive(Parser)]
#[command(about = "Haptic loop at 1 kHz on the cataract scene")]
struct Args {
    /// Scene time to simulate in each run, seconds.
    #[arg(long, default_value_t = 10.0)]
    seconds: f64,
    /// The coarse scene (fewer elements).
    #[arg(long)]
    coarse: bool,
}

const H: f64 = 1.0 / 60.0;

struct Run {
    steps: usize,
    wall: f64,
    max_contacts: usize,
}

fn scene(params: &CataractParams) -> Result<(Scene, cataract::ExtractionPath)> {
    let built = cataract::build(params, BodySettings::default())?;
    let mut scene = Scene::new(built.contact)?;
    scene.add_body(built.lens);
    scene.add_body(built.eye);
    scene.add_tool(built.vectis);
    Ok((scene, built.path))
}

/// Steps the scene for `seconds` of scene time; `before` sets the vectis,
/// `after` sees the stepped scene.
fn run(
    scene: &mut Scene,
    seconds: f64,
    mut before: impl FnMut(&mut Scene, f64) -> Result<()>,
    mut after: impl FnMut(&Scene),
) -> Result<Run> {
    let n = (seconds / H).round() as usize;
    let t0 = Instant::now();
    let mut max_contacts = 0;
    for i in 0..n {
        before(scene, i as f64 * H)?;
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

fn go(args: &Args) -> Result<()> {
    let params = if args.coarse {
        CataractParams::coarse()
    } else {
        CataractParams::default()
    };
    println!(
        "cataract scene, {} s of scene time per run, h = 1/60 s",
        args.seconds
    );

    // Without haptics: the vectis follows the script.
    let (mut plain, path) = scene(&params)?;
    let p2 = path.clone();
    let base = run(
        &mut plain,
        args.seconds,
        |s, t| s.tools[0].set_pose(p2.pose(t + H)),
        |_| {},
    )?;
    let base_rate = base.steps as f64 / base.wall;
    println!(
        "without haptics: {} steps in {:.2} s = {:.1} steps/s (up to {} contacts)",
        base.steps, base.wall, base_rate, base.max_contacts
    );

    // With haptics: the hand follows the script on the scene's clock,
    // interpolated between steps by the wall clock (at most one step).
    let (mut haptic_scene, _) = scene(&params)?;
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
    let settings = HapticSettings::default();
    let haptics = std::cell::RefCell::new(HapticLoop::start(device, settings)?);
    let start = Instant::now();
    let mut max_force: f64 = 0.0;
    let mut max_lag: f64 = 0.0;
    let with = run(
        &mut haptic_scene,
        args.seconds,
        |s, t| {
            clock.store((t + H).to_bits(), Ordering::Release);
            wall_at_step.store(start.elapsed().as_secs_f64().to_bits(), Ordering::Release);
            let state = *haptics.borrow_mut().poll();
            if state.stats.ticks > 0 {
                s.tools[0].set_pose(state.proxy)?;
                max_force = max_force.max(state.force.norm());
                let aim = path.pose(t + H).translation.vector;
                max_lag = max_lag.max((state.proxy.translation.vector - aim).norm());
            } else {
                s.tools[0].set_pose(path.pose(t + H))?;
            }
            Ok(())
        },
        |s| haptics.borrow().publish(s.contact.tool_problem()),
    )?;
    let mut haptics = haptics.into_inner();
    let state = *haptics.poll();
    haptics.stop()?;
    let st = state.stats;
    let rate = with.steps as f64 / with.wall;
    println!(
        "with haptics:    {} steps in {:.2} s = {:.1} steps/s (up to {} contacts)",
        with.steps, with.wall, rate, with.max_contacts
    );
    println!(
        "  scene slowdown: {:.1} % (target ≤ 10 %)",
        100.0 * (1.0 - rate / base_rate)
    );
    println!(
        "  haptic rate: {:.0} Hz over the run ({} ticks in {:.2} s; {:.0} Hz over the last 100 ticks)",
        st.ticks as f64 / st.elapsed.max(1e-9),
        st.ticks,
        st.elapsed,
        st.rate_hz
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
        "  start-time jitter p99: {:.3} ms over the run ({:.3} ms last 1000 ticks); LCP sweeps per tick {:.1} \
         (last 100), {} ticks stopped at the budget",
        st.run_jitter_p99 * 1e3,
        st.jitter_p99 * 1e3,
        st.lcp_iterations,
        st.unconverged
    );
    println!(
        "  force: largest {:.4} N; largest jump between ticks {:.2e} N within a step, {:.2e} N across steps",
        max_force, st.max_jump_between_steps, st.max_jump_at_step
    );
    println!(
        "  problems received {}; proxy's largest distance from the script {:.3} mm",
        st.problems,
        max_lag * 1e3
    );
    Ok(())
}
