//! Validation beside the trade-off: the solver against two closed forms.
//!
//! - [`cantilever`]: a clamped beam under its own weight, tip deflection
//!   against Euler–Bernoulli, `w = q L⁴ / (8 E I)`, over refinements (linear
//!   tetrahedra are too stiff in bending on coarse meshes; the error falls as
//!   the mesh is refined).
//! - [`hertz`]: a rigid frictionless sphere pressed into a soft block, the
//!   total normal force against indentation compared with
//!   `F = 4/3 E* √R d^{3/2}`, `E* = E / (1 − ν²)` (a rigid indenter on an
//!   elastic half-space; the block is finite, so its bottom and sides add a
//!   little stiffness).
//!
//! Both are quasi-static: steps of `h = 1 s` with the exact preconditioner
//! and CG to 1e-10, where backward Euler's inertia is negligible next to the
//! stiffness (`h² k / m` ≫ 1), repeated until the state settles.

use nalgebra::{Isometry3, Translation3};

use crate::body::{BodySettings, DeformableBody};
use crate::contact::{ContactSettings, RigidTool, ToolShape};
use crate::error::{Result, SoftTissueError};
use crate::material::TissueMaterial;
use crate::math::v3;
use crate::mesh::generate;
use crate::scene::Scene;
use crate::solver::PreconditionerKind;
use crate::solver::cg::CgSettings;

fn quasi_static() -> BodySettings {
    BodySettings {
        preconditioner: PreconditionerKind::Exact,
        cg: CgSettings {
            tolerance: 1e-10,
            max_iterations: 1000,
            warm_start: true,
        },
        damping: false,
        ..Default::default()
    }
}

/// One refinement of the cantilever.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CantileverPoint {
    /// Cells across the beam (`10×` along it).
    pub cells_across: usize,
    /// Nodes.
    pub nodes: usize,
    /// Tip deflection of the model (mean over the tip face), metres.
    pub deflection: f64,
    /// Euler–Bernoulli tip deflection, metres.
    pub analytic: f64,
    /// `|model − analytic| / analytic`.
    pub relative_error: f64,
}

/// The cantilever: 20 mm × 2 mm × 2 mm, E = 1 MPa, ν = 0.3, ρ = 1000 kg/m³,
/// clamped at `x = 0`, under gravity, with `across` cells across for each
/// entry of `refinements`.
pub fn cantilever(refinements: &[usize]) -> Result<Vec<CantileverPoint>> {
    let (l, b, e, rho, g): (f64, f64, f64, f64, f64) = (20e-3, 2e-3, 1e6, 1000.0, 9.81);
    let i = b.powi(4) / 12.0;
    let q = rho * g * b * b;
    let analytic = q * l.powi(4) / (8.0 * e * i);
    let mut out = Vec::new();
    for &n in refinements {
        let mesh = generate::box_mesh(
            v3(0.0, -b / 2.0, -b / 2.0),
            v3(l, b / 2.0, b / 2.0),
            [10 * n, n, n],
        )?;
        let settings = BodySettings {
            gravity: Some(v3(0.0, 0.0, -g)),
            ..quasi_static()
        };
        let mut body = DeformableBody::new(mesh, TissueMaterial::new(rho, e, 0.3), settings)?;
        body.fix_where(|p| p.x < 1e-9);
        let tip: Vec<usize> = (0..body.num_nodes())
            .filter(|&k| body.mesh().positions()[k].x > l - 1e-9)
            .collect();
        let deflection = |body: &DeformableBody| {
            tip.iter()
                .map(|&k| body.mesh().positions()[k].z - body.positions()[k].z)
                .sum::<f64>()
                / tip.len() as f64
        };
        let mut w = 0.0;
        let mut settled = false;
        for _ in 0..200 {
            body.step(1.0)?;
            let w1 = deflection(&body);
            if (w1 - w).abs() <= 1e-9 * w1.abs() {
                settled = true;
                w = w1;
                break;
            }
            w = w1;
        }
        if !settled {
            return Err(SoftTissueError::Study(format!(
                "the cantilever with {n} cells across did not settle"
            )));
        }
        out.push(CantileverPoint {
            cells_across: n,
            nodes: body.num_nodes(),
            deflection: w,
            analytic,
            relative_error: (w - analytic).abs() / analytic,
        });
    }
    Ok(out)
}

/// One indentation depth of the Hertz test.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HertzPoint {
    /// Indentation depth, metres.
    pub depth: f64,
    /// Total normal force of the model (the tissue's reaction on the sphere), newtons.
    pub force: f64,
    /// Hertz force, newtons.
    pub analytic: f64,
    /// `|model − analytic| / analytic`.
    pub relative_error: f64,
}

/// The Hertz test's result.
#[derive(Debug, Clone, PartialEq)]
pub struct HertzResult {
    /// Nodes of the block.
    pub nodes: usize,
    /// Edge length of the block's cells, metres.
    pub cell_size: f64,
    /// Per depth.
    pub points: Vec<HertzPoint>,
}

/// A rigid sphere of radius 5 mm pressed into a 20 × 20 × 10 mm block
/// (E = 10 kPa, ν = 0.3, bottom clamped) with `cells` cells along its
/// width (half as many in height), to depths of 0.25 … 1 mm.
pub fn hertz(cells: usize) -> Result<HertzResult> {
    let (r, w, t, e, nu) = (5e-3, 20e-3, 10e-3, 1e4, 0.3);
    let cells = cells.max(2) & !1; // even: a node under the sphere's axis
    let mesh = generate::box_mesh(
        v3(-w / 2.0, -w / 2.0, -t),
        v3(w / 2.0, w / 2.0, 0.0),
        [cells, cells, cells / 2],
    )?;
    let mut body = DeformableBody::new(mesh, TissueMaterial::new(1000.0, e, nu), quasi_static())?;
    body.fix_where(|p| p.z < -t + 1e-9);
    let nodes = body.num_nodes();
    let mut scene = Scene::new(ContactSettings {
        alarm_distance: 0.05e-3,
        max_passes: 8,
        friction: false,
        ..Default::default()
    })?;
    scene.add_body(body);
    let at = |d: f64| Isometry3::from_parts(Translation3::new(0.0, 0.0, r - d), Default::default());
    scene.add_tool(RigidTool::new(ToolShape::Sphere { radius: r }, at(-1e-4))?.with_friction(0.0)?);
    let e_star = e / (1.0 - nu * nu);
    let mut points = Vec::new();
    let mut d: f64 = 0.0;
    for target in [0.25e-3, 0.5e-3, 0.75e-3, 1.0e-3] {
        // Down in 0.05 mm steps, then settle.
        while d < target - 1e-12 {
            d = (d + 0.05e-3).min(target);
            scene.tools[0].set_pose(at(d))?;
            scene.step(1.0)?;
        }
        let mut f = 0.0;
        for _ in 0..50 {
            scene.step(1.0)?;
            let f1 = scene.tools[0].reaction().0.z;
            let done = (f1 - f).abs() <= 1e-6 * f1.abs();
            f = f1;
            if done {
                break;
            }
        }
        let analytic = 4.0 / 3.0 * e_star * r.sqrt() * target.powf(1.5);
        points.push(HertzPoint {
            depth: target,
            force: f,
            analytic,
            relative_error: (f - analytic).abs() / analytic,
        });
    }
    Ok(HertzResult {
        nodes,
        cell_size: w / cells as f64,
        points,
    })
}
