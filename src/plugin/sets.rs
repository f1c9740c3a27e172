//! The pipeline's system sets.

use bevy::prelude::*;

/// The pipeline's system sets, chained in this order.
#[derive(SystemSet, Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SoftTissueSystems {
    /// Element rotations, forces and the implicit system.
    Assemble,
    /// Preconditioner refresh: factor swap, hand-off to the worker, rotation warp.
    Factorize,
    /// Conjugate gradient and integration to free-motion positions.
    FreeMotion,
    /// Tool poses from transforms; collision detection (first pass).
    Detect,
    /// Contact Jacobian and compliance `W` (first pass).
    Compliance,
    /// Friction LCP (first pass).
    Lcp,
    /// Position/velocity correction and tool reactions (first pass).
    Correct,
    /// Further frictionless passes while a vertex still penetrates.
    Refine,
    /// Components, diagnostics and render meshes.
    Sync,
}

/// The system in `FixedPostUpdate` that runs the pipeline's own schedule,
/// [`SoftTissueSchedule`](super::SoftTissueSchedule) (the default): order
/// `FixedPostUpdate` systems before or after the whole step with it.
#[derive(SystemSet, Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct SoftTissueStep;
