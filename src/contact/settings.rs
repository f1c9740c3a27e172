//! Scene-wide contact settings, the one home of every contact setting; a
//! body's own compliance mode is set on the solver
//! ([`super::ContactSolver::set_body_compliance`]).

use super::compliance::ComplianceMode;
use super::lcp::LcpSettings;
use crate::error::{Result, SoftTissueError, check_positive};

/// Scene-wide contact settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContactSettings {
    /// Compliance mode of every body that has none of its own
    /// ([`super::ContactSolver::set_body_compliance`]).
    pub compliance: ComplianceMode,
    /// Proximity (alarm) distance below which a contact is created, metres.
    pub alarm_distance: f64,
    /// Friction coefficient between deformable bodies.
    pub body_friction: f64,
    /// Friction on or off for the whole scene (off: μ = 0 everywhere, no tangent rows).
    pub friction: bool,
    /// The LCP solver and its tolerances.
    pub lcp: LcpSettings,
    /// Maximum contact passes per step. After the first correction, detection
    /// runs again; while some vertex still penetrates deeper than
    /// `penetration_tolerance` (a vertex the correction pushed into a tool, or the
    /// curvature a linearized contact ignores), another frictionless pass corrects it.
    pub max_passes: usize,
    /// Penetration that triggers another pass, metres.
    pub penetration_tolerance: f64,
    /// Steps that `Factorized` compliance keeps using a factor after the
    /// preconditioner swapped in a newer one (0, the default: always the
    /// newest, the most accurate `W`). Node columns and Gram blocks are cached
    /// per factor, so reusing one for a few steps makes more steps' `W` nearly
    /// free. It trades accuracy for time: the rotation warp follows rotations
    /// but not changes of shape, so `W` and the correction drift from the
    /// current stiffness as the tissue deforms. Applies to bodies whose
    /// preconditioner warps (`Periodic`, `Async`).
    pub factor_reuse: u64,
    /// Detect the first pass where the contacts will be, not at the free
    /// motion: each body's free-motion positions plus its previous step's total
    /// correction. Tissue held against a surface springs back in free motion
    /// (in the cataract scene's slit by up to 0.5 mm a step, half the sclera's
    /// thickness) and the correction pushes it out again; detected at the
    /// free motion, such a vertex is deep inside the other body, where the
    /// closest surface point may lie on its far side. At the predicted positions
    /// held contacts sit near their surface, and the linearized gaps account
    /// for the shift exactly (`δ₀ = gap − H·shift`), so the LCP solves the
    /// same problem at a better-chosen linearization point. On by default.
    pub predict: bool,
    /// How far the correction of a body whose factor lags its matrix
    /// (`Factorized` compliance with a `Periodic`, `Async` or `AsyncLagged`
    /// preconditioner) may stray from the matrix before the factor is
    /// refreshed on the spot. The correction `Δx = h² P⁻¹ Hᵀ λ` stores the
    /// energy `Δxᵀ A Δx / 2` in the tissue, while the LCP, which saw
    /// `W = h² H P⁻¹ Hᵀ`, accounted for `Δxᵀ P Δx / 2 = h² λᵀ H Δx / 2`. Their
    /// ratio is 1 when `P = A`; with an old factor warped by node rotations it
    /// is far from 1 where the rotations vary across the body (the warp then
    /// twists the soft rigid-body modes of a free body into stiff deformation,
    /// which [`Self::rigid_modes`] now answers exactly), and the correction
    /// shoots the tissue off. When the ratio leaves
    /// `[1 / (1 + tol), 1 + tol]` the body's matrix is factorized now (or
    /// the background worker's factor of the same step's matrix is waited for,
    /// see [`crate::solver`], "Rescue") and the
    /// pass's `W`, LCP and correction are redone with it (counted in
    /// [`super::ContactReport::consistency_refactors`]). Default 0.1;
    /// `f64::INFINITY` never refreshes. Checked in the first pass.
    pub consistency_tolerance: f64,
    /// The energy a lagging factor's correction may add per pass, relative
    /// to the body's mechanical (kinetic and elastic) energy. The correction
    /// applies the force `A Δx / h²`, not the contact forces `Hᵀ λ` alone;
    /// the difference does work along the step's displacement that no force
    /// accounts for ([`super::ContactReport::misaccounted_work`]). When that
    /// work exceeds `energy_tolerance` times the body's energy the factor is
    /// refreshed as for `consistency_tolerance`, in every pass. Default
    /// `f64::INFINITY`, never: with 1e-5 the cataract jam refreshed about
    /// 1 000 times a run and fell from about 25 to 15–18 steps/s.
    pub energy_tolerance: f64,
    /// Complete a lagging factor with the body's rigid modes (`Factorized`
    /// compliance with a `Periodic`, `Async` or `AsyncLagged`
    /// preconditioner). The warp turns an old factor's rigid-body modes into
    /// stiff deformation where node rotations vary across the body, so
    /// `P⁻¹` answers a force that moves the whole body (a lens landing, or
    /// held up against gravity every step) wrongly, and the correction
    /// stores energy the LCP did not account for. With this on, `W` and the
    /// correction use the two-level inverse `Q + (I − QA) P⁻¹ (I − AQ)`,
    /// `Q = Z (Zᵀ A Z)⁻¹ Zᵀ` over the six rigid modes `Z`: exact on them,
    /// the factor for the deformation. It costs six forward sweeps with the factor
    /// per body and step in contact, and a rank-12 update of `W`. On by
    /// default.
    pub rigid_modes: bool,
    /// Tool contacts inside the bodies' surface triangles, not only at their
    /// vertices. A tool's edge or corner (a vectis's rim) can press into a
    /// face between its vertices, where no vertex contact sees it: in the
    /// cataract scene the vectis went up to 0.39 mm into the lens's faces,
    /// more than the lens's smallest edges. With this on, each surface
    /// triangle near a tool tests 13 barycentric points
    /// ([`super::detect::FACE_SAMPLES`]); from the deepest that can lie
    /// near a point deep enough (a tool thinner than the samples' spacing
    /// passes between them) a pattern search finds the deepest point, and
    /// where that point is inside the alarm band and deeper than all three
    /// corners by [`Self::penetration_tolerance`] it becomes a frictionless
    /// contact on the triangle's three nodes, weighted by its barycentric
    /// coordinates (friction stays with the vertex contacts); where the
    /// search ends at a corner, a second one starts away from it. A flat
    /// tool face against a face adds no row (the vertices carry it). A first
    /// pass solves with the face rows' diagonal shifted
    /// ([`super::FACE_ROW_SHIFT`]): with their corners' rows they are nearly
    /// dependent. Refinement passes keep the pass before's face contacts,
    /// and the penetration they end within covers these points too. The
    /// stability suite's thin rod drawn across the lens keeps its faces out
    /// to twice the tolerance and the energy bound. Off by default: in the
    /// cataract jam it costs about half of the steps per second (the face
    /// search, more passes, larger LCPs; see docs/benchmark-log.md, "Tool
    /// contacts inside faces" and "Fewer queries in the face search").
    /// Experimental.
    pub tool_faces: bool,
}

impl Default for ContactSettings {
    fn default() -> Self {
        Self {
            compliance: ComplianceMode::Factorized,
            alarm_distance: 1e-4,
            body_friction: 0.0,
            friction: true,
            lcp: LcpSettings::default(),
            max_passes: 3,
            penetration_tolerance: 1e-6,
            factor_reuse: 0,
            predict: true,
            consistency_tolerance: 0.1,
            energy_tolerance: f64::INFINITY,
            rigid_modes: true,
            tool_faces: false,
        }
    }
}

impl ContactSettings {
    /// Checks the parameters.
    pub fn validate(&self) -> Result<()> {
        check_positive("alarm_distance", self.alarm_distance)?;
        crate::error::check_range("body_friction", self.body_friction, 0.0, 1e6)?;
        self.lcp.validate()?;
        check_positive("penetration_tolerance", self.penetration_tolerance)?;
        if self.consistency_tolerance.is_nan() || self.consistency_tolerance <= 0.0 {
            return Err(SoftTissueError::InvalidParameter {
                name: "consistency_tolerance",
                value: self.consistency_tolerance,
                reason: "must be positive (f64::INFINITY: never refresh)",
            });
        }
        if self.energy_tolerance.is_nan() || self.energy_tolerance <= 0.0 {
            return Err(SoftTissueError::InvalidParameter {
                name: "energy_tolerance",
                value: self.energy_tolerance,
                reason: "must be positive (f64::INFINITY: never refresh)",
            });
        }
        if self.max_passes == 0 {
            return Err(SoftTissueError::InvalidParameter {
                name: "max_passes",
                value: 0.0,
                reason: "must be ≥ 1",
            });
        }
        Ok(())
    }
}
