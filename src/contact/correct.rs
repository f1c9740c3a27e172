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
    /// Scratch: one body's nodal contact forces `Hᵀ λ` of the pass.
    pub(super) forces: &'a mut Vec<Vec3>,
}

/// How far a pass's corrections may stray from the matrix before the factor
/// is refreshed (see [`super::ContactSettings::consistency_tolerance`] and
/// [`super::ContactSettings::energy_tolerance`]).
#[derive(Debug, Clone, Copy)]
pub(super) struct Tolerances {
    /// Band of the energy ratio (`∞`: not checked).
    pub(super) ratio: f64,
    /// Misaccounted work over the body's mechanical energy (`∞`: not checked).
    pub(super) energy: f64,
}

/// Computes this pass's correction of every body in contact into `dx` (one
/// vector per body) and checks that each is consistent with its matrix
/// (see [`super::ContactSettings::consistency_tolerance`] and
/// [`super::ContactSettings::energy_tolerance`]); `stale` receives the bodies
/// that are not. Returns the misaccounted work of the consistent ones (J).
/// Nothing is applied yet.
pub(super) fn compute<B: BodiesMut + ?Sized>(
    bodies: &mut B,
    per: &mut PerBody<'_>,
    h: f64,
    lambda: &[f64],
    tolerance: Tolerances,
    dx: &mut Vec<Vec<Vec3>>,
    stale: &mut Vec<usize>,
) -> Result<f64> {
    stale.clear();
    let mut misaccounted = 0.0;
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
        if lagging {
            nodal_forces(body, entries, lambda, per.forces);
            let c = consistency(body, h, per.forces, &dx[bi]);
            let rho = c.ratio();
            let t = tolerance.ratio;
            let strays = !(rho <= 1.0 + t && rho * (1.0 + t) >= 1.0) && t.is_finite();
            // The body's mechanical energy only when the work could exceed
            // its share (the elastic energy costs a pass over the elements).
            let e = tolerance.energy;
            let kinetic = body.kinetic_energy();
            let gains = c.misaccounted > e * kinetic
                && c.misaccounted > e * (kinetic + body.elastic_energy());
            if strays || gains {
                stale.push(bi);
            } else {
                misaccounted += c.misaccounted;
            }
        }
    }
    Ok(misaccounted)
}

/// `Hᵀ λ` of one body at its free nodes into `out` (zero elsewhere).
fn nodal_forces(body: &DeformableBody, entries: &[JacEntry], lambda: &[f64], out: &mut Vec<Vec3>) {
    out.clear();
    out.resize(body.num_nodes(), Vec3::zeros());
    for e in entries {
        let k = e.node as usize;
        if body.constraints()[k] == NodeConstraint::Free {
            out[k] += e.h * lambda[e.row as usize];
        }
    }
}

/// How well a correction agrees with the body's matrix (see [`consistency`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Consistency {
    /// `Δxᵀ A Δx`: twice the energy the correction stores in the tissue, × h².
    pub(super) stored: f64,
    /// `h² λᵀ H Δx`: what the LCP accounted for, same units.
    pub(super) seen: f64,
    /// The work (J) of the force the correction applies beyond the contact
    /// forces, `g = A Δx / h² − Hᵀ λ`, along the step's displacement
    /// `x + Δx − x_start`: the energy the correction adds that no force
    /// accounts for (0 when `Δx = h² A⁻¹ Hᵀ λ`).
    pub(super) misaccounted: f64,
}

impl Consistency {
    /// `stored / seen` (1 when the correction is zero).
    pub(super) fn ratio(&self) -> f64 {
        if self.stored == 0.0 && self.seen == 0.0 {
            1.0
        } else {
            self.stored / self.seen
        }
    }
}

/// The correction `dx` of `body` against its matrix `A`, with `forces` the
/// pass's nodal contact forces `Hᵀ λ` (zero at constrained nodes), over the
/// free nodes. One sparse product.
pub(super) fn consistency(
    body: &DeformableBody,
    h: f64,
    forces: &[Vec3],
    dx: &[Vec3],
) -> Consistency {
    let free = |i: usize| body.constraints()[i] == NodeConstraint::Free;
    let a = body.system_matrix();
    let p = &a.pattern;
    let (x, x0) = (body.positions(), body.start_positions());
    let h2 = h * h;
    let mut c = Consistency {
        stored: 0.0,
        seen: 0.0,
        misaccounted: 0.0,
    };
    for r in 0..p.n {
        if !free(r) {
            continue;
        }
        let mut row = Vec3::zeros();
        for s in p.row_ptr[r]..p.row_ptr[r + 1] {
            let col = p.col_idx[s];
            if free(col) {
                row += a.values[s] * dx[col];
            }
        }
        c.stored += dx[r].dot(&row);
        c.seen += h2 * forces[r].dot(&dx[r]);
        let g = row / h2 - forces[r];
        c.misaccounted += g.dot(&(x[r] - x0[r] + dx[r]));
    }
    c
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
