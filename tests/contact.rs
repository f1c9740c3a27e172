//! Acceptance tests of the contact pipeline: compliance accuracy, contact
//! conditions, friction, the paper's Fig. 3 setting, two bodies, bad input.

use bevy_soft_tissue::contact::NO_TOOLS;
use bevy_soft_tissue::core_prelude::*;
use bevy_soft_tissue::mesh::generate::LENS_RADII;
use nalgebra::{DMatrix, Isometry3, Translation3, UnitQuaternion};

fn lens(cells: usize, kind: PreconditionerKind) -> DeformableBody {
    let mesh = generate::ellipsoid(LENS_RADII, cells).unwrap();
    let material = TissueMaterial::new(1000.0, 5e3, 0.45)
        .with_stiffness(StiffnessField::Radial {
            center: Vec3::zeros(),
            radii: Vec3::from(LENS_RADII),
            core_radius: 0.55,
            factor: 5.0,
            transition: Transition::Sharp,
        })
        .with_damping(1.0, 0.01);
    DeformableBody::new(
        mesh,
        material,
        BodySettings {
            preconditioner: kind,
            ..Default::default()
        },
    )
    .unwrap()
}

/// The test lens with its base (z < −1.8 mm) fixed.
fn based_lens(cells: usize, kind: PreconditionerKind) -> DeformableBody {
    let mut body = lens(cells, kind);
    body.fix_where(|p| p.z < -1.8e-3);
    body
}

/// One step of `body` alone under a sphere (μ = `mu`) that touches its top:
/// the scene and the step's contact report.
fn sphere_touch(body: DeformableBody, mu: f64) -> (Scene, ContactReport) {
    let mut scene = Scene::new(ContactSettings::default()).unwrap();
    scene.add_body(body);
    scene.add_tool(
        RigidTool::new(
            ToolShape::Sphere { radius: 3e-3 },
            at(0.0, 0.0, 2.25e-3 + 3e-3 - 2e-4),
        )
        .unwrap()
        .with_friction(mu)
        .unwrap(),
    );
    let r = scene.step(0.01).unwrap();
    (scene, r)
}

/// A contact solver with default settings but the alarm distance, for
/// detection passes of a test's own.
fn detector(alarm: f64) -> ContactSolver {
    ContactSolver::new(ContactSettings {
        alarm_distance: alarm,
        ..Default::default()
    })
    .unwrap()
}

fn at(x: f64, y: f64, z: f64) -> Pose {
    Isometry3::from_parts(Translation3::new(x, y, z), UnitQuaternion::identity())
}

/// A lens pressed by a sphere from above (contacts with friction) after being
/// turned, so the factor's warp is not the identity.
fn pressed_lens(kind: PreconditionerKind, mode: ComplianceMode) -> (Scene, f64) {
    // Reuse 0: W must come from the preconditioner's current factor.
    let mut scene = Scene::new(ContactSettings {
        compliance: mode,
        alarm_distance: 3e-4,
        factor_reuse: 0,
        ..Default::default()
    })
    .unwrap();
    let body = based_lens(8, kind);
    scene.add_body(body);
    let tool = RigidTool::new(
        ToolShape::Sphere { radius: 3e-3 },
        at(0.5e-3, 0.0, 2.25e-3 + 3e-3 + 1e-4),
    )
    .unwrap()
    .with_friction(0.3)
    .unwrap();
    scene.add_tool(tool);
    let h = 0.01;
    for s in 0..12 {
        let z = 2.25e-3 + 3e-3 - 1e-4 * s as f64;
        scene.tools[0]
            .set_pose(at(0.5e-3 + 2e-5 * s as f64, 0.0, z))
            .unwrap();
        scene.step(h).unwrap();
    }
    (scene, h)
}

fn dense_solve_matrix(f: &bevy_soft_tissue::solver::ldlt::LdltFactor, n: usize) -> DMatrix<f64> {
    let mut inv = DMatrix::zeros(3 * n, 3 * n);
    let (mut b, mut x, mut t) = (
        vec![Vec3::zeros(); n],
        vec![Vec3::zeros(); n],
        vec![Vec3::zeros(); n],
    );
    for k in 0..n {
        for c in 0..3 {
            b[k][c] = 1.0;
            f.solve(&b, &mut x, &mut t);
            b[k][c] = 0.0;
            for i in 0..n {
                for r in 0..3 {
                    inv[(3 * i + r, 3 * k + c)] = x[i][r];
                }
            }
        }
    }
    inv
}

fn reference_w(
    entries: &[bevy_soft_tissue::contact::JacEntry],
    inv: &DMatrix<f64>,
    m: usize,
    h: f64,
    use_j: bool,
) -> DMatrix<f64> {
    let n3 = inv.nrows();
    let mut jm = DMatrix::zeros(m, n3);
    for e in entries {
        let v = if use_j { e.j } else { e.h };
        for c in 0..3 {
            jm[(e.row as usize, 3 * e.node as usize + c)] += v[c];
        }
    }
    &jm * inv * jm.transpose() * (h * h)
}

fn max_rel_diff(w: &[f64], reference: &DMatrix<f64>) -> f64 {
    let m = reference.nrows();
    let scale = reference.iter().fold(0.0f64, |a, v| a.max(v.abs()));
    let mut d = 0.0f64;
    for r in 0..m {
        for c in 0..m {
            d = d.max((w[r * m + c] - reference[(r, c)]).abs());
        }
    }
    d / scale
}

/// Detection and compliance of the first pass at the scene's current state.
fn detect_and_build(scene: &mut Scene, h: f64) {
    scene
        .contact
        .detect(&scene.bodies, &scene.tools, h, PassKind::First)
        .unwrap();
    scene
        .contact
        .build_compliance(&mut scene.bodies, PassKind::First, None)
        .unwrap();
}

/// Max penetration, measured again after the step, of the vertices of the active
/// contacts (those with a positive normal force) into their tools.
fn active_penetration(scene: &Scene) -> f64 {
    let mut worst: f64 = 0.0;
    for c in scene.contact.contacts() {
        if let bevy_soft_tissue::contact::ContactOther::Tool(t) = c.other
            && c.force.x > 0.0
        {
            let p = scene.bodies[c.a.body].positions()[c.a.nodes[0] as usize];
            if let Some(q) = scene.tools[t].proximity(&p, 1.0) {
                worst = worst.max(-q.distance);
            }
        }
    }
    worst
}

/// Max penetration of any free surface vertex into any tool.
fn penetration(scene: &Scene) -> f64 {
    let mut worst: f64 = 0.0;
    for b in &scene.bodies {
        for &v in &b.surface().vertices {
            if b.constraints()[v] != NodeConstraint::Free {
                continue;
            }
            for t in &scene.tools {
                if let Some(p) = t.proximity(&b.positions()[v], 1.0) {
                    worst = worst.max(-p.distance);
                }
            }
        }
    }
    worst
}

/// A soft block on a rigid plane tilted by θ (gravity tilted instead).
fn block_slide(theta_deg: f64, mu: f64, solver: LcpSolver) -> f64 {
    let mesh = generate::box_mesh(v3(-5e-3, -5e-3, 0.0), v3(5e-3, 5e-3, 4e-3), [4, 4, 2]).unwrap();
    let th = theta_deg.to_radians();
    let g = 9.81;
    let settings = BodySettings {
        gravity: Some(v3(g * th.sin(), 0.0, -g * th.cos())),
        ..Default::default()
    };
    let body = DeformableBody::new(
        mesh,
        TissueMaterial::new(1000.0, 5e4, 0.3).with_damping(2.0, 0.0),
        settings,
    )
    .unwrap();
    let mut contact = ContactSettings {
        alarm_distance: 2e-4,
        ..Default::default()
    };
    contact.lcp.solver = solver;
    let mut scene = Scene::new(contact).unwrap();
    scene.add_body(body);
    let plane = RigidTool::new(
        ToolShape::Box {
            half_extents: v3(0.2, 0.2, 0.01),
        },
        at(0.0, 0.0, -0.01 - 1e-5),
    )
    .unwrap()
    .with_friction(mu)
    .unwrap();
    scene.add_tool(plane);
    let x0: f64 = scene.bodies[0].positions().iter().map(|p| p.x).sum::<f64>()
        / scene.bodies[0].num_nodes() as f64;
    for _ in 0..60 {
        scene.step(0.01).unwrap();
    }
    let x1: f64 = scene.bodies[0].positions().iter().map(|p| p.x).sum::<f64>()
        / scene.bodies[0].num_nodes() as f64;
    x1 - x0
}

/// Four boxes around a square hole: the paper's rigid plate.
fn plate_with_hole(half_hole: f64) -> Vec<RigidTool> {
    let (t, big) = (0.5e-3, 20e-3);
    let w = 0.5 * (big - half_hole);
    let c = half_hole + w;
    vec![
        RigidTool::new(
            ToolShape::Box {
                half_extents: v3(w, big, t),
            },
            at(c, 0.0, 0.0),
        )
        .unwrap(),
        RigidTool::new(
            ToolShape::Box {
                half_extents: v3(w, big, t),
            },
            at(-c, 0.0, 0.0),
        )
        .unwrap(),
        RigidTool::new(
            ToolShape::Box {
                half_extents: v3(half_hole, w, t),
            },
            at(0.0, c, 0.0),
        )
        .unwrap(),
        RigidTool::new(
            ToolShape::Box {
                half_extents: v3(half_hole, w, t),
            },
            at(0.0, -c, 0.0),
        )
        .unwrap(),
    ]
}

/// A slab 1 mm thick and a small block above it whose corner vertex has gone
/// 0.7 mm into the slab in one step: deeper than twice the alarm distance and
/// past the slab's mid-plane, so the closest surface is the bottom face.
fn block_corner_in_slab(depth: f64) -> (DeformableBody, DeformableBody, usize) {
    let slab =
        generate::box_mesh(v3(-2e-3, -2e-3, -0.5e-3), v3(2e-3, 2e-3, 0.5e-3), [4, 4, 2]).unwrap();
    let block = generate::box_mesh(
        v3(-0.3e-3, -0.3e-3, 0.6e-3),
        v3(0.7e-3, 0.7e-3, 1.6e-3),
        [1, 1, 1],
    )
    .unwrap();
    let m = TissueMaterial::new(1000.0, 1e4, 0.3);
    let slab = DeformableBody::new(slab, m.clone(), BodySettings::default()).unwrap();
    let mut block = DeformableBody::new(block, m, BodySettings::default()).unwrap();
    let corner = (0..block.num_nodes())
        .min_by(|&i, &j| {
            let (p, q) = (block.positions()[i], block.positions()[j]);
            (p.x + p.y + p.z).total_cmp(&(q.x + q.y + q.z))
        })
        .unwrap();
    let mut x = block.positions().to_vec();
    x[corner].z = 0.5e-3 - depth;
    let v = vec![Vec3::zeros(); x.len()];
    block.set_state(&x, &v).unwrap();
    (slab, block, corner)
}

/// Detects slab against block; the contact of the block's `corner`, if any,
/// and the deepest penetration found.
fn corner_contact(
    slab: &DeformableBody,
    block: &DeformableBody,
    corner: usize,
    alarm: f64,
) -> Option<(bevy_soft_tissue::contact::Contact, f64)> {
    let mut solver = detector(alarm);
    solver
        .detect(&[slab, block], &NO_TOOLS, 0.01, PassKind::First)
        .unwrap();
    let c = solver
        .contacts()
        .iter()
        .find(|c| c.a.body == 1 && c.a.nodes[0] as usize == corner)?;
    Some((*c, solver.report().max_penetration))
}

/// The harness's test of a tool between a surface's vertices.
#[path = "../examples/common/faces.rs"]
#[allow(dead_code)]
mod faces;

/// Tests: node columns, the LCP, detection and prediction.
#[path = "contact/columns_and_detection.rs"]
mod columns_and_detection;
/// Tests: W against references, contact conditions, friction, the paper scene.
#[path = "contact/response.rs"]
mod response;

#[path = "contact/lcp.rs"]
mod lcp;

#[path = "shared/fuzz.rs"]
mod fuzz;

#[path = "contact/haptics.rs"]
mod haptics;

#[path = "shared/alloc.rs"]
mod alloc;
use alloc::{allocations, assert_steady};

/// Tests: allocation in the stepping loop.
#[path = "contact/steady_state.rs"]
mod steady_state;
