//! Phase 4, the correction: `Δx = h² A⁻¹ Hᵀ λ` per body with the same
//! approximation of `A⁻¹` that built `W` ([`super::compliance`]), `Δv = Δx / h`,
//! and the reaction force and torque of the tissue on each tool.

use super::bodies::{BodiesMut, ToolsMut};
use super::compliance::{BodyCompliance, ComplianceMode, JacEntry};
use super::predict::Prediction;
use super::types::{Contact, ContactOther, PassKind};
use crate::body::{DeformableBody, NodeConstraint};
use crate::error::{Result, SoftTissueError};
use crate::math::Vec3;

/// What the correction of one pass reads and writes, per body index.
pub(super) struct PerBody<'a> {
    pub(super) compliance: &'a mut [BodyCompliance],
    pub(super) modes: &'a [ComplianceMode],
    pub(super) predictions: &'a mut [Prediction],
    pub(super) entries: &'a [Vec<JacEntry>],
}

/// Computes this pass's correction of every body in contact into `dx` (one
/// vector per body) and returns whether each is consistent with its matrix
/// (see [`super::ContactSettings::consistency_tolerance`]); `stale` receives
/// the bodies that are not. Nothing is applied yet.
pub(super) fn compute<B: BodiesMut + ?Sized>(
    bodies: &mut B,
    per: &mut PerBody<'_>,
    h: f64,
    lambda: &[f64],
    tolerance: f64,
    dx: &mut Vec<Vec<Vec3>>,
    stale: &mut Vec<usize>,
) -> Result<()> {
    stale.clear();
    let n = bodies.len().min(per.entries.len());
    dx.resize_with(n, Vec::new);
    for bi in 0..n {
        let entries = &per.entries[bi];
        if entries.is_empty() {
            continue;
        }
        let body = bodies.body(bi);
        per.compliance[bi].correction(body, per.modes[bi], h, entries, lambda, &mut dx[bi])?;
        if !dx[bi].iter().all(|d| d.iter().all(|c| c.is_finite())) {
            return Err(SoftTissueError::NonFinite("contact correction"));
        }
        let lagging = per.modes[bi] == ComplianceMode::Factorized
            && body.preconditioner().kind().needs_rotations();
        if lagging && tolerance.is_finite() {
            let rho = energy_ratio(body, h, entries, lambda, &dx[bi]);
            if !(rho <= 1.0 + tolerance && rho * (1.0 + tolerance) >= 1.0) {
                stale.push(bi);
            }
        }
    }
    Ok(())
}

/// Applies the corrections [`compute`] left in `dx` and records them for the
/// next step's prediction.
pub(super) fn apply<B: BodiesMut + ?Sized>(
    bodies: &mut B,
    per: &mut PerBody<'_>,
    dx: &[Vec<Vec3>],
) {
    for bi in 0..bodies.len().min(per.entries.len()).min(dx.len()) {
        if per.entries[bi].is_empty() {
            continue;
        }
        bodies.body_mut(bi).apply_correction(&dx[bi]);
        per.predictions[bi].record(&dx[bi]);
    }
}

/// `Δxᵀ A Δx / (h² λᵀ H Δx)` over the body's free nodes: the energy the
/// correction stores in the tissue over the energy the LCP accounted for
/// (1 when `Δx = h² A⁻¹ Hᵀ λ` exactly). 1 when the correction is zero.
pub(super) fn energy_ratio(
    body: &DeformableBody,
    h: f64,
    entries: &[JacEntry],
    lambda: &[f64],
    dx: &[Vec3],
) -> f64 {
    let free = |i: usize| body.constraints()[i] == NodeConstraint::Free;
    let a = body.system_matrix();
    let p = &a.pattern;
    let mut stored = 0.0;
    for r in 0..p.n {
        if !free(r) || dx[r] == Vec3::zeros() {
            continue;
        }
        let mut row = Vec3::zeros();
        for s in p.row_ptr[r]..p.row_ptr[r + 1] {
            let c = p.col_idx[s];
            if free(c) {
                row += a.values[s] * dx[c];
            }
        }
        stored += dx[r].dot(&row);
    }
    let mut seen = 0.0;
    for e in entries {
        let k = e.node as usize;
        if free(k) {
            seen += lambda[e.row as usize] * e.h.dot(&dx[k]);
        }
    }
    seen *= h * h;
    if stored == 0.0 && seen == 0.0 {
        1.0
    } else {
        stored / seen
    }
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
