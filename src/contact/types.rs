//! The data the phases pass on: contacts, their sides, the pass kind and the report.

use super::lcp::LcpReport;
use crate::math::Vec3;

/// Which pass of a step a phase runs in.
///
/// The first pass detects (with [`super::ContactSettings::predict`], at the
/// predicted positions), solves with friction and warm start, and replaces
/// the tool reactions. Each refinement pass ([`super::ContactSettings::max_passes`])
/// detects at the corrected positions, solves frictionless from zero, and
/// adds to the reactions.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PassKind {
    /// The step's first pass.
    First,
    /// A further pass for residual penetration.
    Refine,
}

/// One side of a contact on a deformable body: up to three weighted nodes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContactSide {
    /// Index of the body in the slice given to the solver.
    pub body: usize,
    /// Nodes (volume indices).
    pub nodes: [u32; 3],
    /// Barycentric weights (unused slots are 0).
    pub weights: [f64; 3],
}

impl ContactSide {
    /// The side's point among positions `x` of its body: its nodes weighted
    /// by their barycentric weights (`None` where a node is out of range).
    pub fn point(&self, x: &[Vec3]) -> Option<Vec3> {
        self.nodes
            .iter()
            .zip(self.weights)
            .filter(|&(_, w)| w != 0.0)
            .map(|(&n, w)| x.get(n as usize).map(|p| p * w))
            .sum()
    }
}

/// What the other side of a contact is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ContactOther {
    /// A rigid tool (index in the tool slice).
    Tool(usize),
    /// A surface triangle of another body.
    Body(ContactSide),
}

/// A contact between a surface vertex and a tool or another body's surface,
/// or between a point inside a surface triangle and a tool
/// ([`super::ContactSettings::tool_faces`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Contact {
    /// The vertex side (weight 1 on one node), or the face side of a tool
    /// inside a surface triangle (the point's barycentric weights on the
    /// triangle's three nodes).
    pub a: ContactSide,
    /// The other side.
    pub other: ContactOther,
    /// Unit normal, pointing from the other side toward `a`.
    pub normal: Vec3,
    /// Unit tangents completing the frame.
    pub tangents: [Vec3; 2],
    /// Gap where the contact was detected, negative when penetrating: at the
    /// free motion, or in a predicted first pass ([`super::ContactSettings::predict`])
    /// at the predicted positions, and the LCP's `δ₀` is then the gap less the
    /// predicted shift along the normal.
    pub gap: f64,
    /// Tangential relative displacement during the step, where the contact
    /// was detected (see [`Self::gap`]).
    pub slip: [f64; 2],
    /// Friction coefficient.
    pub mu: f64,
    /// Contact point on the other side.
    pub point: Vec3,
    /// Solved force `(λ_n, λ_t1, λ_t2)` on side `a`, newtons.
    pub force: Vec3,
}

/// Timings and counters of the contact phases of the last step. Counts
/// (`contacts`, `rows`, `friction_contacts`) describe the first pass; timings and
/// solves add up over all passes.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ContactReport {
    /// Active contacts.
    pub contacts: usize,
    /// Constraint rows.
    pub rows: usize,
    /// Contacts that have friction rows.
    pub friction_contacts: usize,
    /// LCP outcome of the last pass.
    pub lcp: LcpReport,
    /// LCP outcome of the first pass (all contacts, with friction).
    pub lcp_first: LcpReport,
    /// LCP solves of this step that ran to their sweep limit
    /// ([`LcpReport::capped`]).
    pub lcp_capped: usize,
    /// Forward (or full) solves done for `W`.
    pub solves: usize,
    /// Gram blocks computed (cache misses).
    pub gram_blocks: usize,
    /// Seconds in detection.
    pub detect: f64,
    /// Seconds building `H` and `W`.
    pub compliance: f64,
    /// Seconds in the LCP.
    pub lcp_seconds: f64,
    /// Seconds in the correction.
    pub correct: f64,
    /// Seconds the consistency rescues spent getting a factor of the step's
    /// matrix (factorizing it on the stepping thread, or waiting for the
    /// worker's), all passes. The rescue's rebuilt `W`, LCP and correction
    /// count in `compliance`, `lcp_seconds` and `correct`.
    pub rescue: f64,
    /// Vertex–tool pairs tested in detection, and with
    /// [`super::ContactSettings::tool_faces`] the face points tested.
    pub pairs_tested: usize,
    /// Contact passes run (see [`super::ContactSettings::max_passes`]).
    pub passes: usize,
    /// Bodies whose lagging factor was refreshed in this step because its
    /// correction strayed from the matrix
    /// ([`super::ContactSettings::consistency_tolerance`],
    /// [`super::ContactSettings::energy_tolerance`]).
    pub consistency_refactors: usize,
    /// The work, in joules, that this step's corrections from lagging
    /// factors did beyond the contact forces (the force `A Δx / h² − Hᵀ λ`
    /// along the step's displacement), summed over passes and bodies: energy
    /// the approximate compliance added (positive) or took (negative). 0 for
    /// exact compliance; bounded per pass by
    /// [`super::ContactSettings::energy_tolerance`].
    pub misaccounted_work: f64,
    /// Deepest penetration found by the last detection, metres (0 if none).
    pub max_penetration: f64,
    /// Deepest penetration found by the first detection of the step, metres:
    /// how far inside the free motion (or, with [`super::ContactSettings::predict`],
    /// the predicted positions) put a vertex, i.e. how far from its solution
    /// the first pass linearizes.
    pub first_penetration: f64,
}

/// Two unit tangents completing the unit normal `n` to an orthonormal frame.
pub fn tangent_basis(n: &Vec3) -> [Vec3; 2] {
    let e = if n.x.abs() < 0.6 {
        Vec3::x()
    } else if n.y.abs() < 0.6 {
        Vec3::y()
    } else {
        Vec3::z()
    };
    let t1 = n.cross(&e).normalize();
    [t1, n.cross(&t1)]
}
