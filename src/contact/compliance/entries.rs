//! The compliance's shared types: the mode, the Jacobian entry, the factor
//! view, scratch.

use crate::math::{Mat3, Vec3};
use crate::solver::columns::FactorKey;
use crate::solver::ldlt::LdltFactor;

/// How the contact compliance of a body is computed (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ComplianceMode {
    /// From the body's preconditioner factor, warped (reach-restricted forward solves).
    #[default]
    Factorized,
    /// From a fresh factorization of the current matrix.
    Exact,
    /// Uncoupled: diagonal blocks of the current matrix only.
    Diagonal,
    /// Dense inverse of the matrix at rest, rotated (small meshes only).
    RestPrecomputed,
    /// The paper's CPU method: two full solves per Jacobian row (benchmark baseline).
    DenseRows,
}

impl ComplianceMode {
    /// Whether the body must compute node rotations every step for this mode
    /// (`RestPrecomputed` rotates its rest inverse by them; the other modes
    /// take their warp from the preconditioner, which computes them itself
    /// when it needs them).
    pub fn needs_node_rotations(self) -> bool {
        match self {
            ComplianceMode::RestPrecomputed => true,
            ComplianceMode::Factorized
            | ComplianceMode::Exact
            | ComplianceMode::Diagonal
            | ComplianceMode::DenseRows => false,
        }
    }
}

/// One nonzero 3-vector of the contact Jacobian.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JacEntry {
    /// Node of the body.
    pub node: u32,
    /// Constraint row.
    pub row: u32,
    /// `H` block (world frame): the row's direction times the node's weight and sign.
    pub h: Vec3,
    /// `Qᵀ h`, in the frame of the factor.
    pub j: Vec3,
}

/// The factor, warp and key that `W` and the correction of one step use.
#[derive(Debug, Clone, Copy)]
pub(super) struct FactorView<'a> {
    pub(super) factor: &'a LdltFactor,
    /// `Q_i = R_i R̂_iᵀ` per node, or `None` for the identity.
    pub(super) warp: Option<&'a [Mat3]>,
    pub(super) key: FactorKey,
}

impl FactorView<'_> {
    /// `j = Qᵀ h`: the entries in the frame of the factor.
    pub(super) fn fill_j(&self, entries: &mut [JacEntry]) {
        for e in entries.iter_mut() {
            e.j = match self.warp {
                Some(q) => q[e.node as usize].transpose() * e.h,
                None => e.h,
            };
        }
    }
}

/// Reusable vectors.
#[derive(Debug, Default)]
pub(super) struct Scratch {
    pub(super) a: Vec<Vec3>,
    pub(super) b: Vec<Vec3>,
    pub(super) c: Vec<Vec3>,
    pub(super) groups: Vec<(usize, usize)>,
    pub(super) by_row: Vec<u32>,
    pub(super) cols: Vec<u32>,
    /// `Factorized`: the rows a body touches (ascending), the local number
    /// of each row of `w` (`slot`) and of each entry's row (`local_of`), the
    /// groups in the order of their column ids, one group's three rows of
    /// `J G` over the local rows (`t`), and `W`'s pairs of groups over the
    /// local rows, each once (`tri`).
    pub(super) rows: Vec<u32>,
    pub(super) slot: Vec<u32>,
    pub(super) local_of: Vec<u32>,
    pub(super) order: Vec<u32>,
    pub(super) t: Vec<f64>,
    pub(super) tri: Vec<f64>,
    /// Per local row, whether a write has set it (`WBlock::Unset` in place).
    pub(super) row_set: Vec<bool>,
}

/// Runs of entries with the same node: `(start, end)` per node.
pub(super) fn group(entries: &[JacEntry], groups: &mut Vec<(usize, usize)>) {
    groups.clear();
    let mut s = 0;
    for i in 1..=entries.len() {
        if i == entries.len() || entries[i].node != entries[s].node {
            groups.push((s, i));
            s = i;
        }
    }
}

/// What a body's build of `W` may assume of `w`, set by the contact solver
/// for one [`BodyCompliance::accumulate`](super::BodyCompliance::accumulate).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) enum WBlock {
    /// Another body has written some of this body's rows: the build only
    /// adds to `w`.
    #[default]
    Written,
    /// This body's block of `w` (its rows by its rows) is zero, no body
    /// before it having written any of its rows, so the `Factorized` build
    /// may write it in place (see `factorized::contract`).
    Zero,
    /// Nothing of `w` is written or zeroed yet (the first body with
    /// entries): the build writes every entry of `w`, or zeroes `w` first.
    /// A `Factorized` build in place whose rows are all of `w`'s does the
    /// former and so saves a pass over `w`; every other build the latter.
    /// A build that fails may leave `w` partly unset: the contact solver
    /// then zeroes it.
    Unset,
}
