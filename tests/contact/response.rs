//! `tests/contact.rs`: W against references, contact conditions, friction, the paper scene.

use super::*;

#[test]
fn factorized_w_matches_dense_reference_from_same_factor() {
    for mode in [ComplianceMode::Factorized, ComplianceMode::DenseRows] {
        let (mut scene, h) = pressed_lens(PreconditionerKind::Periodic { every: 5 }, mode);
        // Recompute W at the current state and compare against the dense reference.
        detect_and_build(&mut scene, h);
        let b = &scene.bodies[0];
        let (w, m) = scene.contact.delassus();
        assert!(
            scene.contact.report().friction_contacts > 3,
            "{:?}",
            scene.contact.report()
        );
        let st = b.preconditioner().factor_state().unwrap();
        assert!(
            st.warped
                || mode == ComplianceMode::DenseRows
                || b.report().preconditioner.factor_age == 0
        );
        let inv = dense_solve_matrix(&st.factor, b.num_nodes());
        let wref = reference_w(scene.contact.jacobian(0), &inv, m, h, true);
        let err = max_rel_diff(w, &wref);
        assert!(err <= 1e-10, "{mode:?}: relative difference {err:e}");
        // The rows are warped by the warp the preconditioner chose (each
        // node's turn or the body's): `W = h² H Q P⁻¹ Qᵀ Hᵀ`.
        let n = b.num_nodes();
        let mut q = DMatrix::<f64>::identity(3 * n, 3 * n);
        if st.warped {
            for (i, w) in st.warp.iter().enumerate() {
                q.view_mut((3 * i, 3 * i), (3, 3)).copy_from(w);
            }
        }
        let warped_inv = &q * &inv * q.transpose();
        let wref = reference_w(scene.contact.jacobian(0), &warped_inv, m, h, false);
        let err = max_rel_diff(w, &wref);
        assert!(
            err <= 1e-10,
            "{mode:?}, warp {:?} (applied: {}): relative difference {err:e}",
            st.warp_kind,
            st.warped
        );
    }
}

#[test]
fn exact_w_matches_dense_inverse_of_current_matrix() {
    let (mut scene, h) = pressed_lens(PreconditionerKind::Jacobi, ComplianceMode::Exact);
    detect_and_build(&mut scene, h);
    let b = &scene.bodies[0];
    let (w, m) = scene.contact.delassus();
    assert!(m > 0);
    let a = b.system_matrix().to_dense();
    let inv = a.try_inverse().unwrap();
    let wref = reference_w(scene.contact.jacobian(0), &inv, m, h, false);
    let err = max_rel_diff(w, &wref);
    assert!(err <= 1e-8, "relative difference {err:e}");
}

#[test]
fn contact_conditions_hold_after_every_step() {
    let mut scene = Scene::new(ContactSettings {
        alarm_distance: 2e-4,
        ..Default::default()
    })
    .unwrap();
    let body = based_lens(8, PreconditionerKind::Periodic { every: 4 });
    let tol = 0.01 * body.mesh().min_edge_length();
    scene.add_body(body);
    let pose = |s: usize| {
        let z = 2.25e-3 + 1e-3 + 1e-4 - 2.5e-5 * s as f64;
        let rot = UnitQuaternion::from_euler_angles(
            0.0,
            0.0,
            std::f64::consts::FRAC_PI_2 + 0.01 * s as f64,
        );
        Isometry3::from_parts(Translation3::new(3e-5 * s as f64, 0.0, z), rot)
    };
    scene.add_tool(
        RigidTool::new(
            ToolShape::Capsule {
                half_height: 2e-3,
                radius: 1e-3,
            },
            pose(0),
        )
        .unwrap()
        .with_friction(0.2)
        .unwrap(),
    );
    let mut active = 0;
    let mut pushed = false;
    for s in 0..80 {
        scene.tools[0].set_pose(pose(s)).unwrap();
        let r = scene.step(0.01).unwrap();
        let pen = active_penetration(&scene);
        assert!(
            pen <= tol,
            "step {s}: penetration at active contacts {pen:e} > {tol:e}"
        );
        let any = penetration(&scene);
        assert!(
            any <= 10.0 * tol,
            "step {s}: penetration of some vertex {any:e} > {:e}",
            10.0 * tol
        );
        for c in scene.contact.contacts() {
            assert!(c.force.x >= 0.0);
            let t = (c.force.y * c.force.y + c.force.z * c.force.z).sqrt();
            assert!(
                t <= c.mu * c.force.x * (1.0 + 1e-9) + 1e-15,
                "outside the friction cone"
            );
        }
        if r.contacts > 0 {
            active += 1;
            assert!(r.lcp.complementarity <= tol, "step {s}: {:?}", r.lcp);
            assert!(r.lcp.friction <= tol, "step {s}: {:?}", r.lcp);
            let (f, _) = scene.tools[0].reaction();
            assert!(f.z >= 0.0, "the tissue pushes the tool up");
            pushed |= f.z > 0.0;
        }
    }
    assert!(active > 20, "only {active} steps had contacts");
    assert!(pushed);
}

#[test]
fn friction_sticks_below_and_slides_above_the_cone() {
    let mu = 0.5; // tan θ = μ at θ ≈ 26.6°
    for solver in [
        LcpSolver::Subspace,
        LcpSolver::Nncg,
        LcpSolver::BlockGaussSeidel,
        LcpSolver::ProjectedGaussSeidel,
    ] {
        let stick = block_slide(20.0, mu, solver);
        let slide = block_slide(35.0, mu, solver);
        println!("{solver:?}: displacement: stick {stick:e} m, slide {slide:e} m");
        // Free sliding over 0.6 s: ½ g (sin θ − μ cos θ) t² ≈ 0.29 m at 35° (less mass damping).
        let th = 35f64.to_radians();
        let expected = 0.5 * 9.81 * (th.sin() - mu * th.cos()) * 0.6f64.powi(2);
        assert!(
            stick.abs() < 0.02 * expected,
            "{solver:?}: stick moved {stick}"
        );
        assert!(
            slide > 0.5 * expected,
            "{solver:?}: slide moved {slide}, expected ≈ {expected}"
        );
    }
}

#[test]
fn paper_fig3_lens_through_hole_every_mode() {
    for mode in [
        ComplianceMode::Factorized,
        ComplianceMode::Exact,
        ComplianceMode::Diagonal,
        ComplianceMode::RestPrecomputed,
        ComplianceMode::DenseRows,
    ] {
        let mut scene = Scene::new(ContactSettings {
            compliance: mode,
            alarm_distance: 5e-4,
            ..Default::default()
        })
        .unwrap();
        let mut body = lens(6, PreconditionerKind::Periodic { every: 4 });
        body.translate(v3(0.0, 0.0, 2.25e-3 + 0.6e-3));
        let tol = 0.01 * body.mesh().min_edge_length();
        scene.add_body(body);
        for t in plate_with_hole(3.8e-3) {
            scene.add_tool(t);
        }
        let sphere = scene.add_tool(
            RigidTool::new(ToolShape::Sphere { radius: 2.5e-3 }, at(0.0, 0.0, 8e-3))
                .unwrap()
                .with_friction(0.1)
                .unwrap(),
        );
        let mut max_contacts = 0;
        for s in 0..500 {
            let z = 8e-3 - 2.4e-5 * s as f64;
            scene.tools[sphere].set_pose(at(0.0, 0.0, z)).unwrap();
            let r = scene
                .step(0.01)
                .unwrap_or_else(|e| panic!("{mode:?} step {s}: {e}"));
            max_contacts = max_contacts.max(r.contacts);
            let b = &scene.bodies[0];
            assert!(
                b.positions()
                    .iter()
                    .all(|p| p.iter().all(|c| c.is_finite())),
                "{mode:?}: NaN at step {s}"
            );
            let pen = penetration(&scene);
            assert!(
                pen <= tol,
                "{mode:?} step {s}: penetration {pen:e} > {tol:e}; {r:?}"
            );
        }
        let zc: f64 = scene.bodies[0].positions().iter().map(|p| p.z).sum::<f64>()
            / scene.bodies[0].num_nodes() as f64;
        println!("{mode:?}: lens centre z = {zc:e}, max contacts {max_contacts}");
        // The sphere pressed the lens into the hole (whether the lens squeezes through
        // or springs back out depends on the compliance mode's dynamics).
        assert!(max_contacts > 20, "{mode:?}: only {max_contacts} contacts");
        assert!(zc.is_finite());
    }
}

/// A box resting on a box fixed at its bottom, pressed down by forces on its
/// top, in a scene with `settings` and every body on `kind`.
fn two_boxes(settings: ContactSettings, kind: PreconditionerKind) -> Scene {
    let lower =
        generate::box_mesh(v3(-4e-3, -4e-3, -4e-3), v3(4e-3, 4e-3, 0.0), [4, 4, 2]).unwrap();
    let upper =
        generate::box_mesh(v3(-3e-3, -3e-3, 0.05e-3), v3(3e-3, 3e-3, 4e-3), [3, 3, 2]).unwrap();
    let body = |mesh| {
        DeformableBody::new(
            mesh,
            TissueMaterial::new(1000.0, 2e4, 0.3),
            BodySettings {
                gravity: Some(v3(0.0, 0.0, -9.81)),
                preconditioner: kind,
                ..Default::default()
            },
        )
        .unwrap()
    };
    let mut a = body(lower);
    a.fix_where(|p| p.z < -4e-3 + 1e-9);
    let mut b = body(upper);
    let top: Vec<usize> = (0..b.num_nodes())
        .filter(|&i| b.mesh().positions()[i].z > 4e-3 - 1e-9)
        .collect();
    for &i in &top {
        b.set_external_force(i, v3(0.0, 0.0, -2e-5)).unwrap();
    }
    let mut scene = Scene::new(settings).unwrap();
    scene.add_body(a);
    scene.add_body(b);
    scene
}

/// Two bodies share every contact row: `W` is the sum of both bodies'
/// `h² J P⁻¹ Jᵀ`, the first body's block built in place in `W` and the
/// second's added through its own buffer.
#[test]
fn two_bodies_w_is_the_sum_of_both_bodies_dense_references() {
    let mut scene = two_boxes(
        ContactSettings {
            alarm_distance: 2e-4,
            factor_reuse: 0,
            rigid_modes: false,
            ..Default::default()
        },
        PreconditionerKind::Periodic { every: 5 },
    );
    let h = 0.003;
    for _ in 0..40 {
        scene.step(h).unwrap();
    }
    detect_and_build(&mut scene, h);
    let (w, m) = scene.contact.delassus();
    assert!(m > 20, "{m} rows");
    let mut wref = DMatrix::zeros(m, m);
    for bi in 0..2 {
        let b = &scene.bodies[bi];
        let entries = scene.contact.jacobian(bi);
        assert!(!entries.is_empty(), "body {bi} has no rows");
        let st = b.preconditioner().factor_state().unwrap();
        let inv = dense_solve_matrix(&st.factor, b.num_nodes());
        wref += reference_w(entries, &inv, m, h, true);
    }
    let err = max_rel_diff(w, &wref);
    assert!(err <= 1e-10, "relative difference {err:e}");
}

#[test]
fn two_bodies_pressed_together() {
    let mut scene = two_boxes(
        ContactSettings {
            alarm_distance: 2e-4,
            ..Default::default()
        },
        BodySettings::default().preconditioner,
    );
    let tol = 0.01 * scene.bodies[1].mesh().min_edge_length();
    let mut touching = 0;
    for s in 0..150 {
        let r = scene.step(0.003).unwrap();
        if r.contacts == 0 {
            continue;
        }
        touching += 1;
        let fa = scene.contact.body_force(0);
        let fb = scene.contact.body_force(1);
        assert!(
            (fa + fb).norm() <= 1e-9 * fa.norm().max(fb.norm()),
            "step {s}: {fa:?} vs {fb:?}"
        );
        assert!(fb.z > 0.0, "the lower body pushes the upper one up");
        // Re-detect at the corrected positions: no vertex deeper than the tolerance.
        let (ba, bb) = (&scene.bodies[0], &scene.bodies[1]);
        let mut probe = detector(2e-4);
        probe
            .detect(&[ba, bb], &NO_TOOLS, 0.003, PassKind::First)
            .unwrap();
        let worst = probe
            .contacts()
            .iter()
            .map(|c| -c.gap)
            .fold(0.0f64, f64::max);
        assert!(worst <= tol, "step {s}: penetration {worst:e}");
    }
    assert!(touching > 100, "{touching}");
    // The upper body rests on the lower one instead of falling through.
    let min_z = scene.bodies[1]
        .positions()
        .iter()
        .map(|p| p.z)
        .fold(f64::INFINITY, f64::min);
    assert!(min_z > -0.5e-3, "upper body sank to {min_z}");
}

#[test]
fn bad_tools_and_poses_are_errors() {
    let pose = at(0.0, 0.0, 0.0);
    let bad = [
        ToolShape::Sphere { radius: 0.0 },
        ToolShape::Sphere { radius: f64::NAN },
        ToolShape::Capsule {
            half_height: -1.0,
            radius: 1.0,
        },
        ToolShape::Box {
            half_extents: v3(1.0, 0.0, 1.0),
        },
        ToolShape::ConvexHull {
            points: vec![Vec3::zeros(); 3],
        },
        ToolShape::ConvexHull {
            points: vec![
                v3(0., 0., 0.),
                v3(1., 0., 0.),
                v3(0., 1., 0.),
                v3(1., 1., 0.),
            ],
        },
        ToolShape::ConvexHull {
            points: vec![
                v3(0., 0., 0.),
                v3(1., 0., 0.),
                v3(0., 1., 0.),
                v3(0., 0., f64::NAN),
            ],
        },
        ToolShape::TriMesh {
            vertices: vec![Vec3::zeros(); 4],
            indices: vec![[0, 1, 9]; 4],
        },
        ToolShape::TriMesh {
            vertices: vec![Vec3::zeros(); 4],
            indices: vec![[0, 1, 1]; 4],
        },
        ToolShape::TriMesh {
            vertices: vec![],
            indices: vec![],
        },
    ];
    for s in bad {
        assert!(
            matches!(
                RigidTool::new(s.clone(), pose),
                Err(SoftTissueError::InvalidShape(_))
            ),
            "accepted {s:?}"
        );
    }
    let nan_pose = at(f64::NAN, 0.0, 0.0);
    assert!(matches!(
        RigidTool::new(ToolShape::Sphere { radius: 1.0 }, nan_pose),
        Err(SoftTissueError::NonFinite(_))
    ));
    let mut t = RigidTool::new(ToolShape::Sphere { radius: 1.0 }, pose).unwrap();
    assert!(t.set_pose(nan_pose).is_err());
    assert!(t.set_friction(-0.1).is_err());
    assert!(t.set_friction(f64::NAN).is_err());
    assert!(
        ContactSolver::new(ContactSettings {
            alarm_distance: 0.0,
            ..Default::default()
        })
        .is_err()
    );
    let mut s = ContactSettings::default();
    s.lcp.over_relaxation = 2.5;
    assert!(ContactSolver::new(s).is_err());
    // Good shapes answer signed distances with outward normals.
    let hull = RigidTool::new(
        ToolShape::ConvexHull {
            points: vec![
                v3(0., 0., 0.),
                v3(1., 0., 0.),
                v3(0., 1., 0.),
                v3(0., 0., 1.),
            ],
        },
        pose,
    )
    .unwrap();
    let p = hull.proximity(&v3(0.1, 0.1, -0.5), 10.0).unwrap();
    assert!((p.distance - 0.5).abs() < 1e-12 && (p.normal - v3(0.0, 0.0, -1.0)).norm() < 1e-12);
    let p = hull.proximity(&v3(0.1, 0.1, 0.05), 10.0).unwrap();
    assert!(p.distance < 0.0);
}

#[test]
fn no_friction_rows_when_mu_is_zero_and_no_work_without_contact() {
    let (scene, _) = pressed_lens(
        PreconditionerKind::Periodic { every: 4 },
        ComplianceMode::Factorized,
    );
    assert_eq!(
        scene.contact.report().rows,
        3 * scene.contact.report().contacts
    );
    let (mut scene, r) = sphere_touch(lens(6, PreconditionerKind::Periodic { every: 4 }), 0.0);
    assert!(r.contacts > 0);
    assert_eq!(
        r.rows, r.contacts,
        "frictionless contacts must have one row each"
    );
    assert_eq!(r.friction_contacts, 0);
    // RigidTool far away: detection tests no vertex, nothing else runs.
    scene.tools[0].set_pose(at(1.0, 0.0, 0.0)).unwrap();
    let r = scene.step(0.01).unwrap();
    assert_eq!((r.contacts, r.pairs_tested, r.rows, r.solves), (0, 0, 0, 0));
}

/// A based lens whose never-refreshed factor was made by one step of
/// `factor_h`, under a sphere 0.2 mm deep, in a scene with `settings`;
/// returns the scene after one 0.01 s step, its report, and the body's
/// preconditioner rescues before that step.
fn lagging_lens_pressed(factor_h: f64, settings: ContactSettings) -> (Scene, ContactReport, u64) {
    let mut body = based_lens(6, PreconditionerKind::Periodic { every: 1_000_000 });
    body.step(factor_h).unwrap();
    let rescues = body.report().preconditioner.rescues;
    let mut scene = Scene::new(settings).unwrap();
    scene.add_body(body);
    scene.add_tool(
        RigidTool::new(
            ToolShape::Sphere { radius: 3e-3 },
            at(0.0, 0.0, 2.25e-3 + 3e-3 - 2e-4),
        )
        .unwrap(),
    );
    let r = scene.step(0.01).unwrap();
    assert!(r.contacts > 0);
    (scene, r, rescues)
}

/// A lagging factor that does not fit the matrix (here made at h = 1 s, ten
/// thousand times stiffer than the matrix of an h = 0.01 s step) makes a
/// correction that strays from it: the contact phase factorizes the current
/// matrix on the spot and redoes the pass (counted in the report and in the
/// preconditioner's rescues). With the check off nothing is refreshed.
#[test]
fn a_correction_that_strays_from_the_matrix_refreshes_the_factor() {
    for (tolerance, refresh) in [(0.1, true), (f64::INFINITY, false)] {
        let settings = ContactSettings {
            consistency_tolerance: tolerance,
            ..Default::default()
        };
        let (scene, r, rescues) = lagging_lens_pressed(1.0, settings);
        let p = scene.bodies[0].report().preconditioner;
        assert_eq!(
            r.consistency_refactors > 0,
            refresh,
            "tolerance {tolerance}: {} refreshes",
            r.consistency_refactors
        );
        assert_eq!(p.rescues > rescues, refresh);
        // The time the rescue spent on its factor is reported (and only then).
        assert_eq!(r.rescue > 0.0, refresh, "rescue {} s", r.rescue);
        if refresh {
            assert_eq!(p.factor_age, 0, "the refreshed factor is of this step");
            // The redone pass is consistent: no penetration left.
            assert!(penetration(&scene) <= 1e-6, "{:e}", penetration(&scene));
        }
    }
    // The tolerance is validated.
    for bad in [0.0, -1.0, f64::NAN] {
        assert!(
            ContactSettings {
                consistency_tolerance: bad,
                ..Default::default()
            }
            .validate()
            .is_err()
        );
    }
}

/// A lagging factor softer than the matrix (made at h = 1e-4 s, nearly the
/// mass matrix alone, for an h = 0.01 s step) makes a correction that moves
/// the tissue more than the contact forces account for: the report counts
/// the energy it adds (`misaccounted_work` > 0). With the energy guard on,
/// the contact phase refreshes the factor and the redone pass adds none;
/// exact compliance never adds any. The guard is validated.
#[test]
fn the_energy_guard_refreshes_a_factor_whose_correction_adds_energy() {
    let run = |guard: f64, mode: ComplianceMode| {
        let settings = ContactSettings {
            consistency_tolerance: f64::INFINITY,
            energy_tolerance: guard,
            compliance: mode,
            ..Default::default()
        };
        let (_, r, _) = lagging_lens_pressed(1e-4, settings);
        (r.consistency_refactors, r.misaccounted_work)
    };
    let (refreshed, added) = run(f64::INFINITY, ComplianceMode::Factorized);
    assert_eq!(refreshed, 0);
    assert!(added > 0.0, "the soft factor's correction adds {added:e} J");
    let (refreshed, guarded) = run(1e-5, ComplianceMode::Factorized);
    assert!(refreshed > 0, "the guard refreshes the factor");
    assert!(
        guarded.abs() < 1e-3 * added,
        "after the refresh {guarded:e} J, before {added:e} J"
    );
    let (_, exact) = run(f64::INFINITY, ComplianceMode::Exact);
    assert_eq!(exact, 0.0, "exact compliance is not a lagging factor");
    for bad in [0.0, -1.0, f64::NAN] {
        assert!(
            ContactSettings {
                energy_tolerance: bad,
                ..Default::default()
            }
            .validate()
            .is_err()
        );
    }
}
