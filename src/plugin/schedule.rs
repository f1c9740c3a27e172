//! The plugin that orders the pipeline's system sets, owns the config and
//! keeps the fixed timestep in step with it; the pipeline's own schedule.

use bevy::app::FixedPostUpdate;
use bevy::ecs::intern::Interned;
use bevy::ecs::schedule::{ScheduleLabel, SingleThreadedExecutor};
use bevy::prelude::*;

use super::components::{
    BodyContacts, FixedNodes, SoftBodyError, SoftTissueContacts, ToolReaction,
};
use super::config::SoftTissueConfig;
use super::diagnostics::SoftTissueDiagnostics;
use super::sets::{SoftTissueStep, SoftTissueSystems};

/// The pipeline's own schedule, where its sets run by default: run once per
/// fixed step by a system in `FixedPostUpdate` (in the set
/// [`SoftTissueStep`]), so user systems in `FixedUpdate` move tools first,
/// and with Bevy's single-threaded executor. The pipeline is a chain of
/// dependent systems that each use every core they need themselves; the
/// multi-threaded executor handed each of them to a task-pool thread and
/// cost 0.8–1.6 ms on the median step and 1.8–2.4 ms over the jam of the
/// cataract scene on two cores (the step's wall clock against its phases'
/// timers), the single-threaded one 0.05–0.12 ms.
/// Systems that hook between the phases go into this schedule:
///
/// ```no_run
/// use bevy::prelude::*;
/// use bevy_soft_tissue::plugin::{SoftTissueSchedule, SoftTissueSystems};
///
/// fn inspect_contacts() {}
/// App::new().add_systems(
///     SoftTissueSchedule,
///     inspect_contacts
///         .after(SoftTissueSystems::Detect)
///         .before(SoftTissueSystems::Compliance),
/// );
/// ```
///
/// `SoftTissuePlugins::new(FixedPostUpdate)` puts the sets straight into
/// `FixedPostUpdate` instead, under that schedule's executor.
#[derive(ScheduleLabel, Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct SoftTissueSchedule;

/// Runs [`SoftTissueSchedule`] (in `FixedPostUpdate`); nothing if an app
/// removed it.
fn run_soft_tissue_schedule(world: &mut World) {
    let _ = world.try_run_schedule(SoftTissueSchedule);
}

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
            schedule: SoftTissueSchedule.intern(),
            config: SoftTissueConfig::default(),
        }
    }
}

impl Plugin for SoftTissueSchedulePlugin {
    fn build(&self, app: &mut App) {
        if self.schedule == SoftTissueSchedule.intern() {
            let mut schedule = Schedule::new(SoftTissueSchedule);
            schedule.set_executor(SingleThreadedExecutor::new());
            app.add_schedule(schedule).add_systems(
                FixedPostUpdate,
                run_soft_tissue_schedule.in_set(SoftTissueStep),
            );
        }
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
        app.add_systems(First, sync_timestep).add_systems(
            self.schedule,
            super::diagnostics::end_step_clock.after(SoftTissueSystems::Sync),
        );
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
