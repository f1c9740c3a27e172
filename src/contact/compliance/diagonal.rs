//! `Diagonal` compliance: uncoupled, from the 3×3 diagonal blocks of `A`.

use super::entries::JacEntry;
use crate::body::DeformableBody;
use crate::error::{Result, SoftTissueError};
use crate::math::{Mat3, Vec3};

/// `W += h² H diag(A)⁻¹ Hᵀ`; `groups` are the node runs of `entries`.
pub(super) fn accumulate(
    body: &DeformableBody,
    groups: &[(usize, usize)],
    h2: f64,
    entries: &[JacEntry],
    w: &mut [f64],
    m: usize,
) -> Result<()> {
    for &(s, e) in groups {
        let k = entries[s].node as usize;
        let inv = body.system_matrix().diag(k).try_inverse().ok_or(
            SoftTissueError::NotPositiveDefinite {
                node: k,
                pivot: 0.0,
            },
        )?;
        for a in s..e {
            for b in s..e {
                w[entries[a].row as usize * m + entries[b].row as usize] +=
                    h2 * entries[a].h.dot(&(inv * entries[b].h));
            }
        }
    }
    Ok(())
}

/// `dx = h² diag(A)⁻¹ Hᵀ λ`.
pub(super) fn correction(
    body: &DeformableBody,
    h2: f64,
    entries: &[JacEntry],
    lambda: &[f64],
    dx: &mut [Vec3],
) {
    for e in entries {
        let k = e.node as usize;
        let inv = body
            .system_matrix()
            .diag(k)
            .try_inverse()
            .unwrap_or_else(Mat3::zeros);
        dx[k] += inv * e.h * (h2 * lambda[e.row as usize]);
    }
}
