//! A body's solver settings, node constraints and step report.

use crate::error::{Result, SoftTissueError, check_positive, check_vector};
use crate::fem::RotationMethod;
use crate::math::Vec3;
use crate::solver::cg::{CgReport, CgSettings};
use crate::solver::{PreconditionerKind, PreconditionerStats};

/// Per-body solver settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BodySettings {
    /// Preconditioner of the conjugate gradient.
    pub preconditioner: PreconditionerKind,
    /// Element rotation extraction.
    pub rotation: RotationMethod,
    /// Conjugate-gradient stopping rule.
    pub cg: CgSettings,
    /// Gravity acceleration, if any.
    pub gravity: Option<Vec3>,
    /// Apply the material's Rayleigh damping (no damping term is assembled when
    /// false or when both coefficients are zero).
    pub damping: bool,
}

impl Default for BodySettings {
    fn default() -> Self {
        Self {
            preconditioner: PreconditionerKind::Async,
            rotation: RotationMethod::Polar,
            cg: CgSettings::default(),
            gravity: None,
            damping: true,
        }
    }
}

/// Boundary condition of a node.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum NodeConstraint {
    /// Moves freely.
    #[default]
    Free,
    /// Held in place.
    Fixed,
    /// Moved to a target position each step.
    Driven,
}

/// Wall-clock seconds spent in each phase of the last step.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct StepTimings {
    /// Rotations, forces and matrix assembly.
    pub assemble: f64,
    /// Preconditioner update on the stepping thread (factorization when blocking).
    pub factorize: f64,
    /// Preconditioner application inside CG.
    pub precond_apply: f64,
    /// Whole conjugate gradient, application included.
    pub cg_total: f64,
}

/// What the last step did.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct StepReport {
    /// Conjugate-gradient outcome.
    pub cg: CgReport,
    /// Preconditioner counters (factor age, refresh count).
    pub preconditioner: PreconditionerStats,
    /// Phase timings.
    pub timings: StepTimings,
    /// Whether damping terms were assembled.
    pub damping: bool,
    /// Whether gravity was applied.
    pub gravity: bool,
}

pub(super) fn validate_settings(s: &BodySettings) -> Result<()> {
    check_positive("cg.tolerance", s.cg.tolerance)?;
    if s.cg.max_iterations == 0 {
        return Err(SoftTissueError::InvalidParameter {
            name: "cg.max_iterations",
            value: 0.0,
            reason: "must be ≥ 1",
        });
    }
    if let Some(g) = s.gravity {
        check_vector("gravity", &g)?;
        if g.norm() > 1e6 {
            return Err(SoftTissueError::InvalidParameter {
                name: "gravity",
                value: g.norm(),
                reason: "above 1e6 m/s²",
            });
        }
    }
    Ok(())
}
