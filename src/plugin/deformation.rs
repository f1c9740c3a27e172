//! [`DeformationPlugin`]: assembly, factorization and free motion of every
//! body, through the shared phase functions of [`crate::scene::phases`].

use bevy::ecs::intern::Interned;
use bevy::ecs::schedule::ScheduleLabel;
use bevy::ecs::system::SystemParam;
use bevy::prelude::*;

use super::components::{
    AppliedFixedNodes, FailedPhase, FixedNodes, PreconditionerOverride, SoftBody, SoftBodyError,
    SoftBodyFailed, SoftTissueContacts,
};
use super::config::SoftTissueConfig;
use super::diagnostics::SoftTissueDiagnostics;
use super::sets::SoftTissueSystems;
use crate::error::SoftTissueError;
use crate::math::Vec3 as DVec3;
use crate::scene::phases;

/// Assemble, factorize and free-motion systems.
pub struct DeformationPlugin {
    pub(super) schedule: Interned<dyn ScheduleLabel>,
}

impl Plugin for DeformationPlugin {
    fn build(&self, app: &mut App) {
        app.add_systems(
            self.schedule,
            (
                (begin_step, apply_body_settings, assemble)
                    .chain()
                    .in_set(SoftTissueSystems::Assemble),
                factorize.in_set(SoftTissueSystems::Factorize),
                free_motion.in_set(SoftTissueSystems::FreeMotion),
            ),
        );
    }
}

/// Starts the step's diagnostics (and its wall clock).
fn begin_step(mut diag: ResMut<SoftTissueDiagnostics>) {
    diag.begin_step();
}

/// Writes the config's scene-wide body settings (gravity, damping) and the
/// per-body override components into each body's settings.
#[allow(clippy::type_complexity)]
fn apply_body_settings(
    config: Res<SoftTissueConfig>,
    mut bodies: Query<(
        Entity,
        &mut SoftBody,
        Option<Ref<FixedNodes>>,
        Option<&mut AppliedFixedNodes>,
        Option<&PreconditionerOverride>,
    )>,
    mut removed: RemovedComponents<FixedNodes>,
    mut diag: ResMut<SoftTissueDiagnostics>,
    mut commands: Commands,
) {
    for e in removed.read() {
        if let Ok((_, mut body, None, Some(mut applied), _)) = bodies.get_mut(e) {
            for &n in &applied.0 {
                let _ = body.free_node(n);
            }
            applied.0.clear();
        }
    }
    for (e, mut body, fixed, applied, pre) in &mut bodies {
        let mut s = *body.settings();
        s.gravity = config.gravity.map(|g| DVec3::new(g.x, g.y, g.z));
        s.damping = config.damping;
        if let Some(p) = pre {
            s.preconditioner = p.0;
        }
        if s != *body.settings()
            && let Err(err) = body.set_settings(s)
        {
            diag.errors += 1;
            warn!("soft body settings rejected: {err}");
        }
        let Some(f) = fixed else { continue };
        if !f.is_changed() {
            continue;
        }
        if let Err(err) = body.fix_nodes(&f.0) {
            diag.errors += 1;
            warn!("fixed nodes rejected: {err}");
            continue;
        }
        match applied {
            Some(mut applied) => {
                for &n in &applied.0 {
                    if !f.0.contains(&n) {
                        let _ = body.free_node(n);
                    }
                }
                applied.0.clear();
                applied.0.extend_from_slice(&f.0);
            }
            None => {
                commands.entity(e).insert(AppliedFixedNodes(f.0.clone()));
            }
        }
    }
}

/// What a system needs to mark a body failed.
#[derive(SystemParam)]
struct Failures<'w, 's> {
    commands: Commands<'w, 's>,
    messages: MessageWriter<'w, SoftBodyError>,
    diag: ResMut<'w, SoftTissueDiagnostics>,
}

impl Failures<'_, '_> {
    /// Marks `e` failed in `phase` (see [`SoftBodyFailed`]): reported, left
    /// alone until the user clears it. A phase that fails leaves the body in
    /// its state at the start of the step (see [`crate::body`]).
    fn fail(&mut self, e: Entity, phase: FailedPhase, error: SoftTissueError) {
        self.diag.errors += 1;
        self.diag.failed_bodies += 1;
        warn!(
            "soft body {e}: {phase:?} failed: {error}; it keeps its state at the start of the \
             step and is left alone until `SoftBodyFailed` is removed"
        );
        self.commands.entity(e).insert(SoftBodyFailed {
            phase,
            error: error.clone(),
        });
        self.messages.write(SoftBodyError {
            entity: Some(e),
            phase: Some(phase),
            error,
        });
    }
}

/// The bodies the pipeline steps: not marked failed.
type Live = (Entity, &'static mut SoftBody);

fn assemble(
    config: Res<SoftTissueConfig>,
    contacts: Res<SoftTissueContacts>,
    mut bodies: Query<Live, Without<SoftBodyFailed>>,
    mut f: Failures,
) {
    for (e, mut body) in &mut bodies {
        let body = &mut body.0;
        if let Err(err) = phases::assemble(body, &contacts.solver, contacts.active, config.timestep)
        {
            f.fail(e, FailedPhase::Assemble, err);
            continue;
        }
        let r = *body.report();
        f.diag.assemble_ms += r.timings.assemble * 1e3;
        f.diag.damping_bodies += usize::from(r.damping);
        f.diag.gravity_bodies += usize::from(r.gravity);
    }
}

fn factorize(mut bodies: Query<Live, Without<SoftBodyFailed>>, mut f: Failures) {
    for (e, mut body) in &mut bodies {
        let body = &mut body.0;
        let failures = body.report().preconditioner.failures;
        if let Err(err) = phases::factorize(body) {
            f.fail(e, FailedPhase::Factorize, err);
            continue;
        }
        let r = body.report();
        if r.preconditioner.failures > failures {
            // A background factorization failed: the body goes on with its
            // previous factor; reported, not fatal.
            f.diag.worker_failures += r.preconditioner.failures - failures;
            f.diag.errors += 1;
            if let Some(err) = body.preconditioner().last_error() {
                warn!("soft body {e}: background factorization failed: {err}");
                f.messages.write(SoftBodyError {
                    entity: Some(e),
                    phase: Some(FailedPhase::Factorize),
                    error: err.clone(),
                });
            }
        }
        f.diag.factorize_ms += r.timings.factorize * 1e3;
        f.diag.factor_age = f.diag.factor_age.max(r.preconditioner.factor_age);
        f.diag.refreshes += r.preconditioner.refreshes;
    }
}

fn free_motion(mut bodies: Query<Live, Without<SoftBodyFailed>>, mut f: Failures) {
    for (e, mut body) in &mut bodies {
        let body = &mut body.0;
        match phases::free_motion(body) {
            Ok(cg) => {
                let r = body.report();
                f.diag.free_motion_ms += r.timings.cg_total * 1e3;
                f.diag.cg_iterations += cg.iterations;
                f.diag.cg_unconverged += usize::from(!cg.converged);
            }
            Err(err) => {
                f.fail(e, FailedPhase::FreeMotion, err);
            }
        }
    }
}
