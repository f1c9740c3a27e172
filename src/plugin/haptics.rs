//! [`HapticsPlugin`]: a haptic device drives a tool through the core's
//! haptic loop ([`crate::haptics`]) on its own thread.
//!
//! Mark the tool entity with [`HapticTool`]. Each fixed step, before the
//! pipeline, the tool's `Transform` goes to the coupled (proxy) pose the
//! haptic thread computed last; after the contact phases the tool's contact
//! problem is handed to the thread ([`crate::contact::ContactSolver::capture_tool`]).
//! [`HapticsStatus`] holds the newest state and statistics, mirrored into
//! Bevy's `DiagnosticsStore` under `soft_tissue/haptics/…`. The thread stops
//! when the app exits (or the resource is dropped).

use std::sync::Mutex;

use bevy::app::{AppExit, Last};
use bevy::diagnostic::{Diagnostic, DiagnosticPath, Diagnostics, RegisterDiagnostic};
use bevy::ecs::intern::Interned;
use bevy::ecs::schedule::ScheduleLabel;
use bevy::prelude::*;

use super::components::{SoftTissueContacts, Tool};
use super::schedule::SoftTissueSchedule;
use super::sets::SoftTissueSystems;
use crate::contact::ToolContactProblem;
use crate::haptics::{HapticDevice, HapticLoop, HapticSettings, HapticState};

/// Marks the tool entity the haptic device drives (one per app).
#[derive(Component, Debug, Default, Clone, Copy)]
pub struct HapticTool;

/// The haptic loop's newest state, and whether it runs.
#[derive(Resource, Debug, Default, Clone)]
pub struct HapticsStatus {
    /// The newest state the haptic thread posted (force, proxy, statistics).
    pub state: HapticState,
    /// Whether the haptic thread runs.
    pub running: bool,
    /// Why the loop did not start, if it did not.
    pub error: Option<String>,
}

/// The running loop.
#[derive(Resource)]
struct HapticLink {
    haptics: HapticLoop,
    empty: ToolContactProblem,
    /// Whether the refusal of the real-time priority was reported.
    warned: bool,
}

/// Diagnostic paths of the haptic loop.
pub mod haptic_paths {
    use super::DiagnosticPath;
    /// Ticks per second.
    pub const RATE: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/haptics/rate_hz");
    /// 99th percentile of a tick's work, milliseconds.
    pub const TICK_P99: DiagnosticPath =
        DiagnosticPath::const_new("soft_tissue/haptics/tick_p99_ms");
    /// Mean LCP sweeps per tick.
    pub const LCP_ITERATIONS: DiagnosticPath =
        DiagnosticPath::const_new("soft_tissue/haptics/lcp_iterations");
    /// Norm of the rendered force, newtons.
    pub const FORCE: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/haptics/force_n");
    /// Every path above.
    pub const ALL: [DiagnosticPath; 4] = [RATE, TICK_P99, LCP_ITERATIONS, FORCE];
}

/// Starts a haptic loop with a device and drives the [`HapticTool`] with
/// it (see the module docs). Add it beside `SoftTissuePlugins`.
pub struct HapticsPlugin {
    device: Mutex<Option<Box<dyn HapticDevice>>>,
    settings: HapticSettings,
    schedule: Interned<dyn ScheduleLabel>,
}

impl HapticsPlugin {
    /// The plugin for `device` with `settings`, in [`SoftTissueSchedule`]
    /// (the pipeline's default schedule).
    pub fn new(device: impl HapticDevice, settings: HapticSettings) -> Self {
        Self {
            device: Mutex::new(Some(Box::new(device))),
            settings,
            schedule: SoftTissueSchedule.intern(),
        }
    }

    /// Runs the systems in `schedule` (the one given to `SoftTissuePlugins::new`).
    pub fn in_schedule(mut self, schedule: impl ScheduleLabel) -> Self {
        self.schedule = schedule.intern();
        self
    }
}

impl Plugin for HapticsPlugin {
    fn build(&self, app: &mut App) {
        let mut status = HapticsStatus::default();
        let device = self.device.lock().ok().and_then(|mut d| d.take());
        match device.map(|d| HapticLoop::start_boxed(d, self.settings)) {
            Some(Ok(haptics)) => {
                status.running = true;
                app.insert_resource(HapticLink {
                    haptics,
                    empty: ToolContactProblem::default(),
                    warned: self.settings.realtime_priority == 0,
                });
            }
            Some(Err(e)) => {
                warn!("haptic loop not started: {e}");
                status.error = Some(e.to_string());
            }
            None => status.error = Some("the plugin was built twice".into()),
        }
        app.insert_resource(status);
        for p in haptic_paths::ALL {
            app.register_diagnostic(Diagnostic::new(p).with_max_history_length(240));
        }
        app.add_systems(
            self.schedule,
            (
                follow_device.in_set(SoftTissueSystems::Assemble),
                capture.in_set(SoftTissueSystems::Compliance),
                publish
                    .after(SoftTissueSystems::Refine)
                    .before(SoftTissueSystems::Sync),
            ),
        )
        .add_systems(Last, stop_on_exit);
    }
}

fn to_transform(pose: &crate::contact::Pose, tf: &mut Transform) {
    let t = pose.translation.vector;
    let q = pose.rotation;
    tf.translation = Vec3::new(t.x as f32, t.y as f32, t.z as f32);
    tf.rotation = Quat::from_xyzw(q.i as f32, q.j as f32, q.k as f32, q.w as f32).normalize();
}

/// The tool goes to the proxy pose; the status and diagnostics take the
/// newest state.
fn follow_device(
    link: Option<ResMut<HapticLink>>,
    mut status: ResMut<HapticsStatus>,
    mut tools: Query<&mut Transform, With<HapticTool>>,
    mut store: Diagnostics,
) {
    let Some(mut link) = link else { return };
    let state = *link.haptics.poll();
    status.state = state;
    status.running = link.haptics.is_running();
    if state.stats.ticks > 0 {
        for mut tf in &mut tools {
            to_transform(&state.proxy, &mut tf);
        }
        if !state.stats.realtime && !link.warned {
            link.warned = true;
            warn!(
                "the haptic thread runs at normal priority: the system refused the real-time \
                 priority of HapticSettings::realtime_priority (it may start ticks late while \
                 the simulation keeps every core busy)"
            );
        }
    }
    let s = &state.stats;
    for (p, v) in [
        (&haptic_paths::RATE, s.rate_hz),
        (&haptic_paths::TICK_P99, s.tick_p99 * 1e3),
        (&haptic_paths::LCP_ITERATIONS, s.lcp_iterations),
        (&haptic_paths::FORCE, state.force.norm()),
    ] {
        store.add_measurement(p, || v);
    }
}

/// Tells the contact solver which tool's problem to keep (its index in the
/// order detection listed the tools).
fn capture(mut contacts: ResMut<SoftTissueContacts>, haptic: Query<Entity, With<HapticTool>>) {
    let contacts = &mut *contacts;
    let index = haptic
        .iter()
        .next()
        .and_then(|e| contacts.tools.iter().position(|&t| t == e));
    contacts.solver.capture_tool(index);
}

/// Hands the step's problem of the haptic tool to the thread (an empty one
/// at the tool's pose when it touched nothing).
fn publish(
    link: Option<ResMut<HapticLink>>,
    contacts: Res<SoftTissueContacts>,
    haptic: Query<&Tool, With<HapticTool>>,
) {
    let Some(mut link) = link else { return };
    let Some(tool) = haptic.iter().next() else {
        return;
    };
    let p = contacts.solver.tool_problem();
    if contacts.active && p.step > 0 && p.pose == *tool.pose() {
        link.haptics.publish(p);
    } else {
        let link = &mut *link;
        link.empty.clear();
        link.empty.pose = *tool.pose();
        link.haptics.publish(&link.empty);
    }
}

/// Stops the thread when the app exits.
fn stop_on_exit(
    mut exit: MessageReader<AppExit>,
    link: Option<ResMut<HapticLink>>,
    mut status: ResMut<HapticsStatus>,
) {
    if exit.read().next().is_some()
        && let Some(mut link) = link
    {
        if let Err(e) = link.haptics.stop() {
            status.error = Some(e.to_string());
        }
        status.running = false;
    }
}
