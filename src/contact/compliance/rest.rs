//! `RestPrecomputed` compliance: the dense inverse of the first `A` (at
//! rest), rotated by the node rotations (the paper's reference \[11\]).

use nalgebra::DMatrix;

use super::entries::{JacEntry, Scratch};
use crate::body::DeformableBody;
use crate::error::{Result, SoftTissueError};
use crate::math::Vec3;
use crate::solver::ldlt::LdltSymbolic;

/// Largest body (in nodes) accepted by [`super::ComplianceMode::RestPrecomputed`].
pub const REST_PRECOMPUTED_MAX_NODES: usize = 2000;

/// The dense inverse, made at the first build.
#[derive(Debug, Default)]
pub(super) struct RestInverse {
    inverse: Option<DMatrix<f64>>,
}

fn dense_inverse(body: &DeformableBody) -> Result<DMatrix<f64>> {
    let n = body.num_nodes();
    let sym = std::sync::Arc::new(LdltSymbolic::new(&body.system_matrix().pattern)?);
    let mut f = sym.alloc_factor();
    let mut work = Vec::with_capacity(n);
    sym.factorize(body.system_matrix(), &mut f, &mut work)?;
    let mut inv = DMatrix::zeros(3 * n, 3 * n);
    let mut b = vec![Vec3::zeros(); n];
    let mut x = vec![Vec3::zeros(); n];
    let mut t = vec![Vec3::zeros(); n];
    for k in 0..n {
        for c in 0..3 {
            b[k][c] = 1.0;
            f.solve(&b, &mut x, &mut t);
            b[k][c] = 0.0;
            for (i, xi) in x.iter().enumerate() {
                for r in 0..3 {
                    inv[(3 * i + r, 3 * k + c)] = xi[r];
                }
            }
        }
    }
    Ok(inv)
}

impl RestInverse {
    /// `W += h² J A₀⁻¹ Jᵀ` with `J = H R` (fills `j`).
    pub(super) fn accumulate(
        &mut self,
        body: &DeformableBody,
        h2: f64,
        entries: &mut [JacEntry],
        w: &mut [f64],
        m: usize,
    ) -> Result<()> {
        let n = body.num_nodes();
        if n > REST_PRECOMPUTED_MAX_NODES {
            return Err(SoftTissueError::TooLarge {
                what: "RestPrecomputed compliance (dense 3n×3n inverse)",
                size: n,
                limit: REST_PRECOMPUTED_MAX_NODES,
            });
        }
        if self.inverse.is_none() {
            self.inverse = Some(dense_inverse(body)?);
        }
        let rot = body.node_rotations();
        for e in entries.iter_mut() {
            e.j = rot[e.node as usize].transpose() * e.h;
        }
        let inv = self
            .inverse
            .as_ref()
            .ok_or(SoftTissueError::NonFinite("rest inverse"))?;
        for a in entries.iter() {
            for b in entries.iter() {
                let blk = inv.fixed_view::<3, 3>(3 * a.node as usize, 3 * b.node as usize);
                w[a.row as usize * m + b.row as usize] += h2 * a.j.dot(&(blk * b.j));
            }
        }
        Ok(())
    }

    /// `dx = h² R A₀⁻¹ Jᵀ λ`; `sc.groups` holds the node runs of `entries`.
    pub(super) fn correction(
        &self,
        body: &DeformableBody,
        h2: f64,
        entries: &[JacEntry],
        lambda: &[f64],
        sc: &mut Scratch,
        dx: &mut [Vec3],
    ) -> Result<()> {
        let n = body.num_nodes();
        let inv = self
            .inverse
            .as_ref()
            .ok_or(SoftTissueError::NonFinite("rest inverse"))?;
        sc.a.clear();
        sc.a.resize(n, Vec3::zeros());
        for e in entries {
            sc.a[e.node as usize] += e.j * lambda[e.row as usize];
        }
        let rot = body.node_rotations();
        for i in 0..n {
            let mut acc = Vec3::zeros();
            for &(s, _) in &sc.groups {
                let k = entries[s].node as usize;
                acc += inv.fixed_view::<3, 3>(3 * i, 3 * k) * sc.a[k];
            }
            dx[i] = rot[i] * acc * h2;
        }
        Ok(())
    }
}
