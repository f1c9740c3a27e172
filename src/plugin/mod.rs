//! The Bevy layer (feature `bevy`): [`SoftTissuePlugins`], components, system
//! sets, diagnostics, mesh assets.
//!
//! The plugin is a thin ECS layer over the numerical core. Bodies and tools
//! are entities:
//!
//! - [`SoftBody`] wraps a [`crate::body::DeformableBody`] (mesh, material,
//!   state, solver); it requires [`BodyContacts`] and a `Transform`. Positions
//!   are simulated in world space, so keep the body's `Transform` at identity.
//!   [`SoftBodyFromAsset`] spawns one from a [`TetMeshAsset`] once it loads.
//! - [`Tool`] wraps a [`crate::contact::RigidTool`]; its pose follows the
//!   entity's `Transform` (`f32` → `f64` at the edge), so moving a tool is
//!   moving its `Transform` in `FixedUpdate`. The `Transform` is read as a
//!   world pose (not the `GlobalTransform`, which is only propagated later in
//!   the frame), so tools are top-level entities. It requires
//!   [`ToolReaction`], where the tissue's reaction force and torque land for
//!   haptic output.
//! - [`FixedNodes`], [`PreconditionerOverride`], [`ComplianceOverride`] adjust
//!   one body; each writes into the one home of its setting.
//!
//! ## Entry and layout
//! [`SoftTissuePlugins`] is a plugin group, one plugin per concern, each in
//! its own file; any of them can be left out with
//! `SoftTissuePlugins::default().build().disable::<ContactPlugin>()`:
//!
//! | plugin | file | systems |
//! |---|---|---|
//! | [`SoftTissueSchedulePlugin`] | `schedule.rs` | the config, the chained sets, the fixed timestep |
//! | [`DeformationPlugin`] | `deformation.rs` | assemble, factorize, free motion |
//! | [`ContactPlugin`] | `contact.rs` | tool poses, detect, compliance, LCP, correct, refine |
//! | [`SyncPlugin`] | `sync.rs` | [`BodyContacts`], [`ToolReaction`], render meshes (`viewer`) |
//! | [`SoftTissueDiagnosticsPlugin`] | `diagnostics.rs` | [`SoftTissueDiagnostics`] → `DiagnosticsStore` |
//! | [`MeshAssetPlugin`] | `assets.rs` | `.msh` / TetGen loader, [`SoftBodyFromAsset`] |
//!
//! [`HapticsPlugin`] (`haptics.rs`) is not in the group: it takes a device. It drives
//! the [`HapticTool`] from the core's haptic loop ([`crate::haptics`]).
//!
//! Settings live in `config.rs` ([`SoftTissueConfig`], one home per setting),
//! components in `components.rs`, the sets in `sets.rs`, and the contact
//! phases see the ECS through `views.rs` (no per-step collections). Files
//! import the file that defines an item, never this one, so the module graph
//! has no cycles (`.ci/check_imports.py` checks the whole crate).
//!
//! ## Pipeline
//! Systems run in the chained sets of [`SoftTissueSystems`], in
//! [`SoftTissueSchedule`] unless another schedule is given
//! ([`SoftTissuePlugins::new`]). That schedule runs once per fixed step
//! from `FixedPostUpdate` (set [`SoftTissueStep`]), single-threaded (see
//! its docs for why), so user systems in `FixedUpdate` move tools before
//! detection. Each set calls the core's phase functions, the same ones
//! [`crate::scene::Scene::step`] calls ([`crate::scene::phases`] and the
//! [`crate::contact::ContactSolver`] phases):
//!
//! ```text
//! Assemble → Factorize → FreeMotion → Detect → Compliance → Lcp → Correct → Refine → Sync
//! ```
//!
//! ## Only the effects a scene calls for
//! Contact phases run only when a tool or a second body exists and
//! [`SoftTissueConfig::contacts`] is on; friction rows only for `μ > 0` and
//! `SoftTissueConfig::contact.friction` on; damping terms only for nonzero
//! Rayleigh coefficients and [`SoftTissueConfig::damping`] on; gravity only
//! when [`SoftTissueConfig::gravity`] is set. [`SoftTissueDiagnostics`] counts
//! the work each effect did, so a test can show an absent effect costs nothing.
//!
//! ## Background factorization
//! The asynchronous `LDLᵀ` worker of a body lives inside its
//! [`crate::body::DeformableBody`]; despawning the entity drops the
//! component, which stops and joins the worker thread.

pub mod assets;
mod components;
mod config;
mod contact;
mod deformation;
mod diagnostics;
mod haptics;
#[cfg(feature = "viewer")]
pub mod render;
mod schedule;
mod sets;
mod sync;
mod views;

use bevy::app::{PluginGroup, PluginGroupBuilder};
use bevy::ecs::intern::Interned;
use bevy::ecs::schedule::ScheduleLabel;

pub use assets::{MeshAssetPlugin, SoftBodyFromAsset, TetMeshAsset, TetMeshLoader};
pub use components::{
    BodyContacts, ComplianceOverride, FailedPhase, FixedNodes, PreconditionerOverride, SoftBody,
    SoftBodyError, SoftBodyFailed, SoftTissueContacts, Tool, ToolReaction,
};
pub use config::{GpuMode, SoftTissueConfig};
pub use contact::ContactPlugin;
#[cfg(feature = "gpu")]
pub use contact::GpuBackend;
pub use deformation::DeformationPlugin;
pub use diagnostics::{
    SoftTissueDiagnostics, SoftTissueDiagnosticsPlugin, paths as diagnostics_paths,
};
pub use haptics::{HapticTool, HapticsPlugin, HapticsStatus, haptic_paths};
pub use schedule::{SoftTissueSchedule, SoftTissueSchedulePlugin};
pub use sets::{SoftTissueStep, SoftTissueSystems};
pub use sync::SyncPlugin;

/// The soft-tissue plugins, one per concern (see the module docs): the entry
/// of the plugin layer.
///
/// ```no_run
/// use bevy::prelude::*;
/// use bevy_soft_tissue::prelude::*;
/// use bevy_soft_tissue::plugin::ContactPlugin;
///
/// App::new()
///     .add_plugins((MinimalPlugins, SoftTissuePlugins::default()))
///     .run();
/// // Bodies that never collide: leave the contact plugin out.
/// App::new()
///     .add_plugins((MinimalPlugins, SoftTissuePlugins::default().build().disable::<ContactPlugin>()))
///     .run();
/// ```
pub struct SoftTissuePlugins {
    schedule: Interned<dyn ScheduleLabel>,
    config: SoftTissueConfig,
}

impl Default for SoftTissuePlugins {
    fn default() -> Self {
        Self::new(SoftTissueSchedule)
    }
}

impl SoftTissuePlugins {
    /// Runs the pipeline's sets in `schedule`: by default [`SoftTissueSchedule`],
    /// the pipeline's own single-threaded schedule, which `FixedPostUpdate`
    /// runs once per fixed step; any other schedule gets the sets directly.
    pub fn new(schedule: impl ScheduleLabel) -> Self {
        Self {
            schedule: schedule.intern(),
            config: SoftTissueConfig::default(),
        }
    }

    /// Starts with `config` (the [`SoftTissueConfig`] resource).
    pub fn with_config(mut self, config: SoftTissueConfig) -> Self {
        self.config = config;
        self
    }
}

impl PluginGroup for SoftTissuePlugins {
    fn build(self) -> PluginGroupBuilder {
        let s = self.schedule;
        PluginGroupBuilder::start::<Self>()
            .add(SoftTissueSchedulePlugin {
                schedule: s,
                config: self.config,
            })
            .add(DeformationPlugin { schedule: s })
            .add(ContactPlugin { schedule: s })
            .add(SyncPlugin { schedule: s })
            .add(SoftTissueDiagnosticsPlugin { schedule: s })
            .add(MeshAssetPlugin)
    }
}
