//! One tool's share of a step's contact problem, linearized in the tool's
//! pose: what a haptic loop needs to compute contact forces between
//! simulation steps (`crate::haptics`).
//!
//! After the first pass's correction the contact solver keeps, for the tool
//! chosen with [`super::ContactSolver::capture_tool`], the rows of the
//! contacts that touch it:
//!
//! - `W_TT`, the tool rows' block of the Delassus operator;
//! - `δ_T = δ₀_T + W_TO λ_O`, their free violation with the forces of every
//!   other contact held at the step's answer;
//! - `J`, how a small tool motion `q = (Δt, Δθ)` (translation of the tool's
//!   origin, then a rotation vector about it) changes each row's violation:
//!   for a row along `d` at the contact point `p`, `J_r = −(d, (p − o) × d)`;
//! - the step's forces `λ_T` (the warm start and, at `q = 0`, the answer).
//!
//! The force and torque on the tool of forces `λ` are `Jᵀ λ`, the same sum
//! as the tool's reaction ([`RigidTool::reaction`]), to which the
//! refinement passes add their own share, kept here as `extra_*`.

use super::tool::{Pose, RigidTool};
use super::types::{Contact, ContactOther};
use crate::math::Vec3;

/// The contact problem of one tool, linearized in its pose (see the module docs).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ToolContactProblem {
    /// The step this problem was captured in (counts first passes), 0 when none.
    pub step: u64,
    /// The tool's index in the scene.
    pub tool: usize,
    /// The tool's pose the contacts were solved at.
    pub pose: Pose,
    /// `W_TT`, dense, `m × m`, row-major (metres per newton).
    pub w: Vec<f64>,
    /// `δ_T`, the free violation of each row (metres).
    pub delta: Vec<f64>,
    /// Row offsets: contact `c` owns rows `rows[c]..rows[c + 1]` (1 or 3).
    pub rows: Vec<usize>,
    /// Friction coefficient per contact.
    pub mu: Vec<f64>,
    /// The step's forces (newtons), one per row.
    pub lambda: Vec<f64>,
    /// `J`, one row of six per constraint row: `∂δ / ∂(Δt, Δθ)`.
    pub jacobian: Vec<[f64; 6]>,
    /// Force of the step's refinement passes on the tool (newtons).
    pub extra_force: Vec3,
    /// Torque of the step's refinement passes on the tool, about its origin.
    pub extra_torque: Vec3,
}

impl ToolContactProblem {
    /// Rows.
    pub fn m(&self) -> usize {
        self.delta.len()
    }

    /// Contacts.
    pub fn num_contacts(&self) -> usize {
        self.rows.len().saturating_sub(1)
    }

    /// Forgets every contact (a step without contact on the tool).
    pub fn clear(&mut self) {
        self.w.clear();
        self.delta.clear();
        self.rows.clear();
        self.rows.push(0);
        self.mu.clear();
        self.lambda.clear();
        self.jacobian.clear();
        self.extra_force = Vec3::zeros();
        self.extra_torque = Vec3::zeros();
    }

    /// `Jᵀ λ`: the force and the torque about the tool's origin of row forces
    /// `lambda` (without the refinement passes' share).
    pub fn wrench(&self, lambda: &[f64]) -> (Vec3, Vec3) {
        let mut out = [0.0; 6];
        for (j, l) in self.jacobian.iter().zip(lambda) {
            for k in 0..6 {
                out[k] += j[k] * l;
            }
        }
        (
            Vec3::new(out[0], out[1], out[2]),
            Vec3::new(out[3], out[4], out[5]),
        )
    }

    /// Copies the rows of the contacts on tool `tool` out of the whole
    /// problem (`w` is `m × m`, `delta0` the free violations, `lambda` the
    /// answer), in place.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn capture(
        &mut self,
        step: u64,
        tool: usize,
        tool_ref: &RigidTool,
        contacts: &[Contact],
        rows: &[usize],
        w: &[f64],
        delta0: &[f64],
        lambda: &[f64],
        selected: &mut Vec<usize>,
    ) {
        self.clear();
        self.step = step;
        self.tool = tool;
        self.pose = *tool_ref.pose();
        let m = delta0.len();
        let origin = self.pose.translation.vector;
        selected.clear();
        for (c, contact) in contacts.iter().enumerate() {
            if contact.other != ContactOther::Tool(tool) {
                continue;
            }
            let (r0, r1) = (rows[c], rows[c + 1]);
            let arm = contact.point - origin;
            let dirs = [contact.normal, contact.tangents[0], contact.tangents[1]];
            for (k, r) in (r0..r1).enumerate() {
                selected.push(r);
                let d = dirs[k];
                let t = arm.cross(&d);
                self.jacobian.push([-d.x, -d.y, -d.z, -t.x, -t.y, -t.z]);
                self.lambda.push(lambda[r]);
            }
            self.rows.push(selected.len());
            self.mu.push(contact.mu);
        }
        let mt = selected.len();
        self.w.resize(mt * mt, 0.0);
        for (i, &ri) in selected.iter().enumerate() {
            let row = &w[ri * m..(ri + 1) * m];
            // δ_T = δ₀ + W λ − W_TT λ_T: the others' forces held.
            let mut d = delta0[ri];
            for (wij, lj) in row.iter().zip(lambda) {
                d += wij * lj;
            }
            for (j, &rj) in selected.iter().enumerate() {
                self.w[i * mt + j] = row[rj];
                d -= row[rj] * lambda[rj];
            }
            self.delta.push(d);
        }
    }

    /// Sets the refinement passes' share from the tool's reaction at the end
    /// of the step (the reaction less this problem's own `Jᵀ λ`).
    pub fn set_reaction(&mut self, force: Vec3, torque: Vec3) {
        let (f, t) = self.wrench(&self.lambda);
        self.extra_force = force - f;
        self.extra_torque = torque - t;
    }
}
