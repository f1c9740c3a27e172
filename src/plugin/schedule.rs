//! The plugin that orders the pipeline's system sets, owns the config and
//! keeps the fixed timestep in step with it.

use bevy::app::FixedPostUpdate;
use bevy::ecs::intern::Interned;
use bevy::ecs::schedule::ScheduleLabel;
use bevy::prelude::*;

use super::components::{
    BodyContacts, FixedNodes, SoftBodyError, SoftTissueContacts, ToolReaction,
};
use super::config::SoftTissueConfig;
use super::diagnostics::SoftTissueDiagnostics;
use super::sets::SoftTissueSystems;

/// Inserts [`SoftTissueConfig`] and the shared resources, chains the
/// [`SoftTissueSystems`] sets in `schedule`, and keeps `Time<Fixed>` at
/// [`SoftTissueConfig::timestep`]. The other plugins of the group add their
/// systems to these sets.
pub struct SoftTissueSchedulePlugin {
    pub(super) schedule: Interned<dyn ScheduleLabel>,
    pub(super) config: SoftTissueConfig,
}

impl Default for SoftTissueSchedulePlugin {
    fn default() -> Self {
        Self {
            schedule: FixedPostUpdate.intern(),
            config: SoftTissueConfig::default(),
        }
    }
}

impl Plugin for SoftTissueSchedulePlugin {
    fn build(&self, app: &mut App) {
        app.insert_resource(self.config.clone())
            .register_type::<SoftTissueConfig>()
            .register_type::<ToolReaction>()
            .register_type::<BodyContacts>()
            .register_type::<FixedNodes>()
            .init_resource::<SoftTissueContacts>()
            .init_resource::<SoftTissueDiagnostics>()
            .add_message::<SoftBodyError>()
            .configure_sets(
                self.schedule,
                (
                    SoftTissueSystems::Assemble,
                    SoftTissueSystems::Factorize,
                    SoftTissueSystems::FreeMotion,
                    SoftTissueSystems::Detect,
                    SoftTissueSystems::Compliance,
                    SoftTissueSystems::Lcp,
                    SoftTissueSystems::Correct,
                    SoftTissueSystems::Refine,
                    SoftTissueSystems::Sync,
                )
                    .chain()
                    // No step at all with an unusable time step (reported by
                    // `sync_timestep`); bodies wait for a usable one.
                    .run_if(|c: Res<SoftTissueConfig>| c.timestep_ok()),
            );
        if self.config.timestep_ok() {
            if let Some(mut time) = app.world_mut().get_resource_mut::<Time<Fixed>>() {
                time.set_timestep_seconds(self.config.timestep);
            }
        } else {
            app.world_mut()
                .resource_mut::<SoftTissueDiagnostics>()
                .errors += 1;
            warn!(
                "SoftTissueConfig::timestep = {} is not a usable step (1 ns to 1e5 s); Time<Fixed> keeps its own",
                self.config.timestep
            );
        }
        app.add_systems(First, sync_timestep);
    }
}

/// Keeps `Time<Fixed>` at [`SoftTissueConfig::timestep`] when the config changes.
fn sync_timestep(
    config: Res<SoftTissueConfig>,
    time: Option<ResMut<Time<Fixed>>>,
    mut diag: ResMut<SoftTissueDiagnostics>,
) {
    if !config.is_changed() {
        return;
    }
    if !config.timestep_ok() {
        diag.errors += 1;
        warn!(
            "SoftTissueConfig::timestep = {} is not a usable step (1 ns to 1e5 s)",
            config.timestep
        );
        return;
    }
    if let Some(mut time) = time
        && (time.timestep().as_secs_f64() - config.timestep).abs() > 1e-12
    {
        time.set_timestep_seconds(config.timestep);
    }
}
