//! The plugin's settings: [`SoftTissueConfig`], the one home of each
//! scene-wide setting, and [`GpuMode`].

use bevy::prelude::*;

use crate::contact::ContactSettings;

/// Where the contact compliance of `Factorized` bodies is built.
///
/// The GPU path needs the `gpu` feature and a render device (`RenderPlugin`);
/// otherwise every mode builds on the CPU.
///
/// On an NVIDIA H200 the GPU build of one body's `W` took 0.72–2.81 ms for
/// 30–260 contacts on the 1 183-node lens, of which 0.53–1.02 ms is spent
/// waiting for the device (the rest is the host's share, which grows with
/// the contact count). A CPU build without cached columns took 1.9–33 ms
/// there, so where `W` is built from scratch each step (`factor_reuse: 0`)
/// the GPU is faster from 30 contacts (`Auto { min_rows: 90 }`). In the
/// cataract scene the CPU path reuses the node columns the worker
/// precomputed, and it stayed faster at every contact count (up to 413; the
/// compliance phase at the median step took 3.9–4.5 ms on the GPU against
/// 1.2–1.9 on the CPU): keep `Off` there. Under the scene's light, steady
/// load (the device busy 12–40 % of the time) the driver lowers the SM clock
/// from 1 980 to 345–600 MHz within 15 seconds, and the forward kernel then
/// took 1.0–1.1 ms a build against 0.24–0.30 ms in `gpu_bench`, which keeps
/// the clock up. docs/benchmark-log.md, "GPU", has the numbers and the
/// commands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Reflect)]
pub enum GpuMode {
    /// Always on the CPU.
    #[default]
    Off,
    /// On the GPU whenever there are contacts.
    On,
    /// On the GPU when a body has at least `min_rows` constraint rows
    /// (contacts × 3 with friction, × 1 without).
    Auto {
        /// Crossover in rows.
        min_rows: usize,
    },
}

impl GpuMode {
    /// The fewest rows a body needs for its `W` to be built on the GPU
    /// (`None`: never).
    pub fn min_rows(self) -> Option<usize> {
        match self {
            GpuMode::Off => None,
            GpuMode::On => Some(0),
            GpuMode::Auto { min_rows } => Some(min_rows),
        }
    }
}

/// Scene-wide settings (a resource; change it at runtime).
///
/// Each setting has one home. Scene-wide ones live here; a body's own
/// (preconditioner, CG, rotation method) live in its
/// [`crate::body::BodySettings`]. The per-body override components write into
/// those homes: `PreconditionerOverride` into the body's settings,
/// `ComplianceOverride` into the contact solver's per-body compliance
/// ([`crate::contact::ContactSolver::set_body_compliance`]), whose default is
/// [`ContactSettings::compliance`] here.
#[derive(Resource, Reflect, Debug, Clone)]
#[reflect(Resource)]
pub struct SoftTissueConfig {
    /// Step size `h`, seconds. The fixed timestep of `Time<Fixed>` is set to it.
    pub timestep: f64,
    /// Gravity, m/s² (`None`: no gravity), for every body.
    pub gravity: Option<bevy::math::DVec3>,
    /// Contact handling on or off.
    pub contacts: bool,
    /// Rayleigh damping on or off, for every body.
    pub damping: bool,
    /// Contact settings: detection, friction on or off, the default compliance
    /// mode, the LCP, the passes.
    #[reflect(ignore)]
    pub contact: ContactSettings,
    /// GPU compliance (feature `gpu`).
    pub gpu: GpuMode,
}

impl Default for SoftTissueConfig {
    fn default() -> Self {
        Self {
            timestep: 1.0 / 60.0,
            gravity: None,
            contacts: true,
            damping: true,
            contact: ContactSettings::default(),
            gpu: GpuMode::Off,
        }
    }
}

impl SoftTissueConfig {
    /// Whether [`Self::timestep`] is a step the solver accepts
    /// ([`crate::error::check_timestep`]: 1 ns to 1e5 s).
    pub fn timestep_ok(&self) -> bool {
        crate::error::check_timestep(self.timestep).is_ok()
    }
}
