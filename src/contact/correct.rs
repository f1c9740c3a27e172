//! Phase 4, the correction: `Δx = h² A⁻¹ Hᵀ λ` per body with the same
//! approximation of `A⁻¹` that built `W` ([`super::compliance`]), `Δv = Δx / h`,
//! and the reaction force and torque of the tissue on each tool.

use super::bodies::{BodiesMut, ToolsMut};
use super::compliance::{BodyCompliance, ComplianceMode, JacEntry};
use super::predict::Prediction;
use super::types::{Contact, ContactOther, PassKind};
use crate::error::{Result, SoftTissueError};
use crate::math::Vec3;

/// What the correction of one pass reads and writes, per body index.
pub(super) struct PerBody<'a> {
    pub(super) compliance: &'a mut [BodyCompliance],
    pub(super) modes: &'a [ComplianceMode],
    pub(super) predictions: &'a mut [Prediction],
    pub(super) entries: &'a [Vec<JacEntry>],
}

/// Applies this pass's correction to every body in contact and records it for
/// the next step's prediction. `dx` is scratch.
pub(super) fn apply<B: BodiesMut + ?Sized>(
    bodies: &mut B,
    per: PerBody<'_>,
    h: f64,
    lambda: &[f64],
    dx: &mut Vec<Vec3>,
) -> Result<()> {
    for bi in 0..bodies.len().min(per.entries.len()) {
        let entries = &per.entries[bi];
        if entries.is_empty() {
            continue;
        }
        per.compliance[bi].correction(bodies.body(bi), per.modes[bi], h, entries, lambda, dx)?;
        if !dx.iter().all(|d| d.iter().all(|c| c.is_finite())) {
            return Err(SoftTissueError::NonFinite("contact correction"));
        }
        bodies.body_mut(bi).apply_correction(dx);
        per.predictions[bi].record(dx);
    }
    Ok(())
}

/// Sets each tool's reaction from the contact forces: replaced by the first
/// pass, added to by refinement passes.
pub(super) fn tool_reactions<T: ToolsMut + ?Sized>(
    tools: &mut T,
    contacts: &[Contact],
    pass: PassKind,
) {
    for ti in 0..tools.len() {
        let t = tools.tool_mut(ti);
        let (mut force, mut torque) = match pass {
            PassKind::First => (Vec3::zeros(), Vec3::zeros()),
            PassKind::Refine => t.reaction(),
        };
        for c in contacts {
            if c.other == ContactOther::Tool(ti) {
                let f =
                    c.normal * c.force.x + c.tangents[0] * c.force.y + c.tangents[1] * c.force.z;
                let arm = c.point - t.pose().translation.vector;
                force -= f;
                torque -= arm.cross(&f);
            }
        }
        t.set_reaction(force, torque);
    }
}
