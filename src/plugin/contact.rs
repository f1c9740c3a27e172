//! [`ContactPlugin`]: detection, compliance, LCP, correction and refinement
//! passes, each in its own set, calling the [`crate::contact::ContactSolver`]
//! phases that [`crate::scene::Scene::step`] calls too.

use bevy::ecs::intern::Interned;
use bevy::ecs::schedule::ScheduleLabel;
use bevy::prelude::*;

use super::components::{
    ComplianceOverride, SoftBody, SoftBodyError, SoftBodyFailed, SoftTissueContacts, Tool,
};
use super::config::SoftTissueConfig;
use super::diagnostics::SoftTissueDiagnostics;
use super::sets::SoftTissueSystems;
use super::views::{BodyView, BodyViewMut, ToolView, ToolViewMut, all_present};
use crate::contact::PassKind;
use crate::error::SoftTissueError;
use crate::math::Vec3 as DVec3;
use crate::scene::phases;

/// Detection, compliance, LCP, correction and refinement systems. Without it
/// (`SoftTissuePlugins::default().build().disable::<ContactPlugin>()`) bodies move
/// freely through tools and each other.
pub struct ContactPlugin {
    pub(super) schedule: Interned<dyn ScheduleLabel>,
}

impl Plugin for ContactPlugin {
    fn build(&self, app: &mut App) {
        app.add_systems(
            self.schedule,
            (
                (tool_poses, apply_compliance_overrides, detect)
                    .chain()
                    .in_set(SoftTissueSystems::Detect),
                compliance.in_set(SoftTissueSystems::Compliance),
                lcp.in_set(SoftTissueSystems::Lcp),
                correct.in_set(SoftTissueSystems::Correct),
                (refine, end_tool_steps)
                    .chain()
                    .in_set(SoftTissueSystems::Refine),
            ),
        );
        #[cfg(feature = "gpu")]
        app.add_systems(
            self.schedule,
            ensure_gpu.in_set(SoftTissueSystems::Detect).before(detect),
        );
    }
}

/// Tool poses from their `Transform` (`f32` → `f64` at the edge).
fn tool_poses(mut tools: Query<(&mut Tool, &Transform)>, mut diag: ResMut<SoftTissueDiagnostics>) {
    for (mut tool, tf) in &mut tools {
        let (rot, pos) = (tf.rotation, tf.translation);
        let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            rot.w as f64,
            rot.x as f64,
            rot.y as f64,
            rot.z as f64,
        ));
        let t = DVec3::new(pos.x as f64, pos.y as f64, pos.z as f64);
        if let Err(e) = tool.set_position(t, q) {
            diag.errors += 1;
            warn!("tool pose rejected: {e}");
        }
    }
}

/// Writes [`ComplianceOverride`] into the solver's per-body mode.
fn apply_compliance_overrides(
    mut contacts: ResMut<SoftTissueContacts>,
    bodies: Query<(&SoftBody, Option<&ComplianceOverride>)>,
) {
    let solver = &mut contacts.bypass_change_detection().solver;
    let default = solver.settings().compliance;
    for (body, ov) in &bodies {
        let want = ov.map(|c| c.0);
        if solver.body_compliance(body.id()) != want.unwrap_or(default) {
            solver.set_body_compliance(body.id(), want);
        }
    }
}

#[allow(clippy::too_many_arguments)] // a Bevy system: one parameter per resource and query
fn detect(
    config: Res<SoftTissueConfig>,
    mut contacts: ResMut<SoftTissueContacts>,
    bodies: Query<&'static SoftBody>,
    tools: Query<&'static Tool>,
    all_bodies: Query<Entity, (With<SoftBody>, Without<SoftBodyFailed>)>,
    all_tools: Query<Entity, With<Tool>>,
    mut diag: ResMut<SoftTissueDiagnostics>,
    mut messages: MessageWriter<SoftBodyError>,
) {
    let contacts = &mut *contacts;
    contacts.bodies.clear();
    contacts.bodies.extend(all_bodies.iter());
    contacts.bodies.sort_unstable();
    contacts.tools.clear();
    contacts.tools.extend(all_tools.iter());
    contacts.tools.sort_unstable();
    contacts.active = config.contacts
        && config.timestep_ok()
        && phases::can_touch(contacts.bodies.len(), contacts.tools.len());
    if !contacts.active {
        return;
    }
    if *contacts.solver.settings() != config.contact
        && let Err(e) = contacts.solver.set_settings(config.contact)
    {
        diag.errors += 1;
        warn!("contact settings rejected: {e}");
    }
    diag.detect_runs += 1;
    let b = BodyView {
        q: &bodies,
        e: &contacts.bodies,
    };
    let t = ToolView {
        q: &tools,
        e: &contacts.tools,
    };
    if let Err(e) = contacts
        .solver
        .detect(&b, &t, config.timestep, PassKind::First)
    {
        contact_failed(&mut diag, &mut messages, "detection", e);
        contacts.active = false;
        return;
    }
    if contacts.solver.contacts().is_empty() {
        contacts.active = false;
    }
}

/// Whether the bodies and tools detection listed are all still there; if not,
/// the step's contact response is skipped (counted as an error).
/// Counts, logs and sends a contact phase's error.
fn contact_failed(
    diag: &mut SoftTissueDiagnostics,
    messages: &mut MessageWriter<SoftBodyError>,
    what: &str,
    error: SoftTissueError,
) {
    diag.errors += 1;
    warn!("{what} failed: {error}");
    messages.write(SoftBodyError {
        entity: None,
        phase: None,
        error,
    });
}

/// Whether this step's contact response goes on: it is active, and `present`
/// (every entity the solver listed still exists). A listed entity that has
/// gone ends the response for this step, counted, logged and sent as a
/// [`SoftBodyError`].
fn still_active(
    contacts: &mut SoftTissueContacts,
    present: impl FnOnce(&SoftTissueContacts) -> bool,
    diag: &mut SoftTissueDiagnostics,
    messages: &mut MessageWriter<SoftBodyError>,
) -> bool {
    if !contacts.active {
        return false;
    }
    if !present(contacts) {
        contacts.active = false;
        let error =
            SoftTissueError::Interrupted("a body or tool was removed during the contact phases");
        diag.errors += 1;
        warn!("{error}; the step's contact response is skipped");
        messages.write(SoftBodyError {
            entity: None,
            phase: None,
            error,
        });
    }
    contacts.active
}

/// The GPU compliance builder, created once a render device exists.
#[cfg(feature = "gpu")]
#[derive(Resource, Debug)]
pub struct GpuBackend(pub crate::gpu::GpuCompliance);

#[cfg(feature = "gpu")]
fn ensure_gpu(
    mut commands: Commands,
    config: Res<SoftTissueConfig>,
    existing: Option<Res<GpuBackend>>,
    device: Option<Res<bevy::render::renderer::RenderDevice>>,
    queue: Option<Res<bevy::render::renderer::RenderQueue>>,
) {
    if let Some(min_rows) = config.gpu.min_rows()
        && existing.is_none()
        && let (Some(d), Some(q)) = (device, queue)
    {
        commands.insert_resource(GpuBackend(crate::gpu::GpuCompliance::new(
            d.clone(),
            q.clone(),
            min_rows,
        )));
    }
}

fn compliance(
    config: Res<SoftTissueConfig>,
    mut contacts: ResMut<SoftTissueContacts>,
    mut bodies: Query<&'static mut SoftBody>,
    mut diag: ResMut<SoftTissueDiagnostics>,
    #[cfg(feature = "gpu")] gpu: Option<ResMut<GpuBackend>>,
    mut messages: MessageWriter<SoftBodyError>,
) {
    let contacts = &mut *contacts;
    let present = |c: &SoftTissueContacts| all_present(&bodies, &c.bodies);
    if !still_active(contacts, present, &mut diag, &mut messages) {
        return;
    }
    let mut b = BodyViewMut {
        q: &mut bodies,
        e: &contacts.bodies,
    };
    diag.compliance_builds += 1;
    #[cfg(feature = "gpu")]
    let result = match (gpu, config.gpu.min_rows()) {
        (Some(mut g), Some(min_rows)) => {
            let g = &mut g.0;
            g.min_rows = min_rows;
            let (before, waited) = (g.dispatches, g.wait_seconds);
            let r = contacts
                .solver
                .build_compliance(&mut b, PassKind::First, Some(g));
            diag.gpu_dispatches += g.dispatches - before;
            diag.gpu_wait_ms += (g.wait_seconds - waited) * 1e3;
            r
        }
        _ => contacts
            .solver
            .build_compliance(&mut b, PassKind::First, None),
    };
    #[cfg(not(feature = "gpu"))]
    let result = {
        let _ = &config;
        contacts
            .solver
            .build_compliance(&mut b, PassKind::First, None)
    };
    if let Err(e) = result {
        contact_failed(&mut diag, &mut messages, "compliance", e);
        contacts.active = false;
    }
}

fn lcp(
    mut contacts: ResMut<SoftTissueContacts>,
    bodies: Query<&'static SoftBody>,
    mut diag: ResMut<SoftTissueDiagnostics>,
    mut messages: MessageWriter<SoftBodyError>,
) {
    let contacts = &mut *contacts;
    let present = |c: &SoftTissueContacts| all_present(&bodies, &c.bodies);
    if !still_active(contacts, present, &mut diag, &mut messages) {
        return;
    }
    let b = BodyView {
        q: &bodies,
        e: &contacts.bodies,
    };
    diag.lcp_solves += 1;
    contacts.solver.solve_lcp(&b, PassKind::First);
}

/// Runs `phase` (a pass that moves bodies and sets tool reactions) when the
/// contact response is active and every listed entity is still there; a
/// failure is counted, logged and sent as a [`SoftBodyError`].
fn run_mutating_phase(
    contacts: &mut SoftTissueContacts,
    bodies: &mut Query<&'static mut SoftBody>,
    tools: &mut Query<&'static mut Tool>,
    diag: &mut SoftTissueDiagnostics,
    messages: &mut MessageWriter<SoftBodyError>,
    what: &str,
    phase: impl FnOnce(
        &mut crate::contact::ContactSolver,
        &mut BodyViewMut,
        &mut ToolViewMut,
    ) -> crate::error::Result<()>,
) {
    let present =
        |c: &SoftTissueContacts| all_present(bodies, &c.bodies) && all_present(tools, &c.tools);
    if !still_active(contacts, present, diag, messages) {
        return;
    }
    let mut b = BodyViewMut {
        q: bodies,
        e: &contacts.bodies,
    };
    let mut t = ToolViewMut {
        q: tools,
        e: &contacts.tools,
    };
    if let Err(e) = phase(&mut contacts.solver, &mut b, &mut t) {
        contact_failed(diag, messages, what, e);
        contacts.active = false;
    }
}

fn correct(
    mut contacts: ResMut<SoftTissueContacts>,
    mut bodies: Query<&'static mut SoftBody>,
    mut tools: Query<&'static mut Tool>,
    mut diag: ResMut<SoftTissueDiagnostics>,
    mut messages: MessageWriter<SoftBodyError>,
) {
    run_mutating_phase(
        &mut contacts,
        &mut bodies,
        &mut tools,
        &mut diag,
        &mut messages,
        "contact correction",
        |s, b, t| s.correct(b, t, PassKind::First),
    );
}

fn refine(
    config: Res<SoftTissueConfig>,
    mut contacts: ResMut<SoftTissueContacts>,
    mut bodies: Query<&'static mut SoftBody>,
    mut tools: Query<&'static mut Tool>,
    mut diag: ResMut<SoftTissueDiagnostics>,
    mut messages: MessageWriter<SoftBodyError>,
) {
    run_mutating_phase(
        &mut contacts,
        &mut bodies,
        &mut tools,
        &mut diag,
        &mut messages,
        "contact refinement",
        |s, b, t| s.refine(b, t, config.timestep),
    );
}

/// Without a contact response this step, forgets warm-start forces and
/// zeroes every tool's reaction; then every tool ends its step.
fn end_tool_steps(mut contacts: ResMut<SoftTissueContacts>, mut tools: Query<&'static mut Tool>) {
    let contacts = &mut *contacts;
    if !contacts.active {
        let none: &mut [&mut crate::contact::RigidTool] = &mut [];
        contacts.solver.clear_forces(none);
        for mut t in &mut tools {
            t.0.set_reaction(DVec3::zeros(), DVec3::zeros());
        }
    }
    for mut t in &mut tools {
        phases::end_step(&mut t.0);
    }
}
