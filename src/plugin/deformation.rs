//! [`DeformationPlugin`]: assembly, factorization and free motion of every
//! body, through the shared phase functions of [`crate::scene::phases`].

use bevy::ecs::intern::Interned;
use bevy::ecs::schedule::ScheduleLabel;
use bevy::prelude::*;

use super::components::{FixedNodes, PreconditionerOverride, SoftBody, SoftTissueContacts};
use super::config::SoftTissueConfig;
use super::diagnostics::SoftTissueDiagnostics;
use super::sets::SoftTissueSystems;
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
                (apply_body_settings, assemble)
                    .chain()
                    .in_set(SoftTissueSystems::Assemble),
                factorize.in_set(SoftTissueSystems::Factorize),
                free_motion.in_set(SoftTissueSystems::FreeMotion),
            ),
        );
    }
}

/// Writes the config's scene-wide body settings (gravity, damping) and the
/// per-body override components into each body's settings.
fn apply_body_settings(
    config: Res<SoftTissueConfig>,
    mut bodies: Query<(
        &mut SoftBody,
        Option<Ref<FixedNodes>>,
        Option<&PreconditionerOverride>,
    )>,
    mut diag: ResMut<SoftTissueDiagnostics>,
) {
    for (mut body, fixed, pre) in &mut bodies {
        let mut s = *body.settings();
        s.gravity = config.gravity.map(|g| DVec3::new(g.x, g.y, g.z));
        s.damping = config.damping;
        if let Some(p) = pre {
            s.preconditioner = p.0;
        }
        if s != *body.settings()
            && let Err(e) = body.set_settings(s)
        {
            diag.errors += 1;
            warn!("soft body settings rejected: {e}");
        }
        if let Some(f) = fixed
            && f.is_changed()
            && let Err(e) = body.fix_nodes(&f.0)
        {
            diag.errors += 1;
            warn!("fixed nodes rejected: {e}");
        }
    }
}

fn assemble(
    config: Res<SoftTissueConfig>,
    contacts: Res<SoftTissueContacts>,
    mut bodies: Query<&mut SoftBody>,
    mut diag: ResMut<SoftTissueDiagnostics>,
) {
    diag.begin_step();
    if !config.timestep_ok() {
        diag.errors += 1;
        return;
    }
    for mut body in &mut bodies {
        let body = &mut body.0;
        if let Err(e) = phases::assemble(body, &contacts.solver, contacts.active, config.timestep) {
            diag.errors += 1;
            warn!("assembly failed: {e}");
            continue;
        }
        let r = *body.report();
        diag.assemble_ms += r.timings.assemble * 1e3;
        diag.damping_bodies += usize::from(r.damping);
        diag.gravity_bodies += usize::from(r.gravity);
    }
}

fn factorize(mut bodies: Query<&mut SoftBody>, mut diag: ResMut<SoftTissueDiagnostics>) {
    for mut body in &mut bodies {
        if let Err(e) = phases::factorize(&mut body.0) {
            diag.errors += 1;
            warn!("factorization failed: {e}");
            continue;
        }
        let r = body.report();
        diag.factorize_ms += r.timings.factorize * 1e3;
        diag.factor_age = diag.factor_age.max(r.preconditioner.factor_age);
        diag.refreshes += r.preconditioner.refreshes;
    }
}

fn free_motion(mut bodies: Query<&mut SoftBody>, mut diag: ResMut<SoftTissueDiagnostics>) {
    for mut body in &mut bodies {
        match phases::free_motion(&mut body.0) {
            Ok(cg) => {
                let r = body.report();
                diag.free_motion_ms += r.timings.cg_total * 1e3;
                diag.cg_iterations += cg.iterations;
                diag.cg_unconverged += usize::from(!cg.converged);
            }
            Err(e) => {
                diag.errors += 1;
                warn!("free motion failed: {e}");
            }
        }
    }
}
