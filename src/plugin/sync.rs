//! [`SyncPlugin`]: the contact components and tool reactions (and, with the
//! `viewer` feature, the render meshes) after each step.

use bevy::ecs::intern::Interned;
use bevy::ecs::schedule::ScheduleLabel;
use bevy::prelude::*;

use super::components::{BodyContacts, SoftTissueContacts, Tool, ToolReaction};
use super::diagnostics::SoftTissueDiagnostics;
use super::sets::SoftTissueSystems;
use crate::math::Vec3 as DVec3;

/// Writes contact components and tool reactions (and render meshes with `viewer`).
pub struct SyncPlugin {
    pub(super) schedule: Interned<dyn ScheduleLabel>,
}

impl Plugin for SyncPlugin {
    fn build(&self, app: &mut App) {
        app.add_systems(
            self.schedule,
            sync_components.in_set(SoftTissueSystems::Sync),
        );
        #[cfg(feature = "viewer")]
        app.add_plugins(super::render::RenderSyncPlugin {
            schedule: self.schedule,
        });
    }
}

fn to_dvec(v: DVec3) -> bevy::math::DVec3 {
    bevy::math::DVec3::new(v.x, v.y, v.z)
}

fn sync_components(
    contacts: Res<SoftTissueContacts>,
    mut bodies: Query<(Entity, &mut BodyContacts)>,
    mut tools: Query<(Entity, &Tool, &mut ToolReaction)>,
    mut diag: ResMut<SoftTissueDiagnostics>,
) {
    let report = *contacts.solver.report();
    let active = contacts.active;
    for (e, mut bc) in &mut bodies {
        let idx = contacts.bodies.iter().position(|b| *b == e);
        let new = match (active, idx) {
            (true, Some(i)) => BodyContacts {
                count: contacts
                    .solver
                    .contacts()
                    .iter()
                    .filter(|c| {
                        c.a.body == i
                            || matches!(c.other, crate::contact::ContactOther::Body(s) if s.body == i)
                    })
                    .count(),
                force: to_dvec(contacts.solver.body_force(i)),
                max_penetration: report.max_penetration,
            },
            _ => BodyContacts::default(),
        };
        if *bc != new {
            *bc = new;
        }
    }
    for (e, tool, mut reaction) in &mut tools {
        let idx = contacts.tools.iter().position(|t| *t == e);
        let (f, tau) = tool.reaction();
        let count = match (active, idx) {
            (true, Some(i)) => contacts
                .solver
                .contacts()
                .iter()
                .filter(|c| c.other == crate::contact::ContactOther::Tool(i))
                .count(),
            _ => 0,
        };
        let new = ToolReaction {
            force: to_dvec(f),
            torque: to_dvec(tau),
            contacts: count,
        };
        if *reaction != new {
            *reaction = new;
        }
    }
    if active {
        diag.contacts = report.contacts;
        diag.friction_rows += report.rows - report.contacts;
        diag.lcp_residual = report.lcp.complementarity.max(report.lcp.friction);
        diag.lcp_iterations = report.lcp.iterations;
        diag.lcp_first_iterations = report.lcp_first.iterations;
        diag.lcp_relative_residual = report.lcp_first.residual;
        diag.lcp_capped += report.lcp_capped as u64;
        diag.consistency_refactors += report.consistency_refactors as u64;
        diag.detect_ms = report.detect * 1e3;
        diag.compliance_ms = report.compliance * 1e3;
        diag.lcp_ms = report.lcp_seconds * 1e3;
        diag.correct_ms = report.correct * 1e3;
        diag.rescue_ms = report.rescue * 1e3;
        diag.contact_passes = report.passes;
        diag.compliance_solves = report.solves;
        diag.gram_blocks = report.gram_blocks;
    }
}
