//! How cost grows with the mesh: step time, factorization time and `nnz(L)`
//! of the lens at several resolutions, and the fitted exponent of step time
//! against node count ([`super::fit_power_law`]).
//!
//! Each resolution runs the same motion as `examples/core_headless.rs`: the
//! lens clamped at its bottom, its top pressed down by 1.5 mm and twisted by
//! 0.8 rad, with the default solver (`Async` preconditioner, CG to 1e-6), no
//! contacts. The step time is the mean over the steps after the first (the
//! first factorizes on the stepping thread).

use std::time::Instant;

use nalgebra::Rotation3;

use super::cases::lens_material;
use crate::body::{BodySettings, DeformableBody};
use crate::error::{Result, SoftTissueError};
use crate::math::{Vec3, v3};
use crate::mesh::generate::{self, LENS_RADII};

/// One resolution.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct GrowthPoint {
    /// Cells along the lens's long axis.
    pub cells: usize,
    /// Nodes.
    pub nodes: usize,
    /// Tetrahedra.
    pub tets: usize,
    /// Stored scalars of `L` (3×3 blocks below the diagonal and the unit
    /// diagonal blocks' lower entries).
    pub nnz_l: usize,
    /// One numeric factorization, milliseconds (median of three).
    pub factor_ms: f64,
    /// Mean step time, milliseconds.
    pub step_ms: f64,
    /// Mean CG iterations per step.
    pub cg_iterations: f64,
    /// Mean factor age (steps) when the step ran.
    pub factor_age: f64,
}

/// Measures the lens at each of `cells` for `steps` steps of `h = 0.02` s.
pub fn measure(
    cells: &[usize],
    steps: usize,
    progress: &mut dyn FnMut(usize),
) -> Result<Vec<GrowthPoint>> {
    if steps < 2 {
        return Err(SoftTissueError::Study(
            "growth needs at least 2 steps".into(),
        ));
    }
    let h = 0.02;
    let mut out = Vec::with_capacity(cells.len());
    for &c in cells {
        let mesh = generate::ellipsoid(LENS_RADII, c)?;
        let mut body =
            DeformableBody::new(mesh.clone(), lens_material(5.0), BodySettings::default())?;
        let rz = LENS_RADII[2];
        body.fix_where(|p| p.z < -0.7 * rz);
        let top: Vec<usize> = (0..mesh.num_vertices())
            .filter(|&i| mesh.positions()[i].z > 0.7 * rz)
            .collect();
        let (mut ms, mut its, mut age) = (0.0, 0usize, 0u64);
        for s in 0..steps {
            // Squeeze and twist over 2 s, then hold.
            let t = ((s + 1) as f64 * h / 2.0).min(1.0);
            let a = 0.5 * (1.0 - (t * std::f64::consts::PI).cos());
            let rot = Rotation3::from_axis_angle(&Vec3::z_axis(), a * 0.8);
            for &i in &top {
                let p = mesh.positions()[i];
                body.drive_node(i, rot * v3(p.x, p.y, p.z - a * 1.5e-3))?;
            }
            let t0 = Instant::now();
            let r = body.step(h)?;
            if s > 0 {
                ms += t0.elapsed().as_secs_f64() * 1e3;
                its += r.cg.iterations;
                age += r.preconditioner.factor_age;
            }
        }
        let n = (steps - 1) as f64;
        let sym = body.preconditioner().symbolic().cloned().ok_or_else(|| {
            SoftTissueError::Study("the default preconditioner has no factor".into())
        })?;
        let mut factor = sym.alloc_factor();
        let mut work = Vec::with_capacity(sym.n);
        let mut f = Vec::new();
        for _ in 0..3 {
            let t0 = Instant::now();
            sym.factorize(body.system_matrix(), &mut factor, &mut work)?;
            f.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        f.sort_by(f64::total_cmp);
        out.push(GrowthPoint {
            cells: c,
            nodes: body.num_nodes(),
            tets: mesh.num_tets(),
            nnz_l: 9 * sym.nnz_blocks() + 3 * sym.n,
            factor_ms: f[1],
            step_ms: ms / n,
            cg_iterations: its as f64 / n,
            factor_age: age as f64 / n,
        });
        progress(c);
    }
    Ok(out)
}
