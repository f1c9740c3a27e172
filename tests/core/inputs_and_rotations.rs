//! `tests/core.rs`: meshes, files, parameters, materials, rescues and rotations.

use super::*;

#[test]
fn mesh_validation_errors() {
    let p = vec![
        v3(0., 0., 0.),
        v3(1., 0., 0.),
        v3(0., 1., 0.),
        v3(0., 0., 1.),
    ];
    assert!(matches!(
        TetMesh::new(vec![], vec![[0, 1, 2, 3]]),
        Err(SoftTissueError::EmptyMesh(_))
    ));
    assert!(matches!(
        TetMesh::new(p.clone(), vec![]),
        Err(SoftTissueError::EmptyMesh(_))
    ));
    assert!(matches!(
        TetMesh::new(p.clone(), vec![[0, 1, 2, 7]]),
        Err(SoftTissueError::IndexOutOfRange {
            tet: 0,
            index: 7,
            len: 4
        })
    ));
    assert!(matches!(
        TetMesh::new(p.clone(), vec![[0, 1, 1, 3]]),
        Err(SoftTissueError::RepeatedVertex { tet: 0, vertex: 1 })
    ));
    let mut flat = p.clone();
    flat[3] = v3(0.5, 0.5, 0.0);
    assert!(matches!(
        TetMesh::new(flat, vec![[0, 1, 2, 3]]),
        Err(SoftTissueError::DegenerateTet { tet: 0, .. })
    ));
    assert!(matches!(
        TetMesh::new(p.clone(), vec![[0, 2, 1, 3]]),
        Err(SoftTissueError::InvertedTet { tet: 0, .. })
    ));
    let fixed = TetMesh::with_options(
        p.clone(),
        vec![[0, 2, 1, 3]],
        ValidateOptions {
            reorient: true,
            ..Default::default()
        },
    )
    .unwrap();
    assert!(fixed.tet_volume(0) > 0.0);
    let mut nan = p.clone();
    nan[2].y = f64::NAN;
    assert!(matches!(
        TetMesh::new(nan, vec![[0, 1, 2, 3]]),
        Err(SoftTissueError::NonFiniteVertex { vertex: 2, .. })
    ));
    let mut extra = p.clone();
    extra.push(v3(5.0, 5.0, 5.0));
    assert!(matches!(
        TetMesh::new(extra, vec![[0, 1, 2, 3]]),
        Err(SoftTissueError::UnusedVertex { vertex: 4 })
    ));
}

#[test]
fn parameter_errors() {
    let mesh = beam([2, 1, 1], 0.1, 0.02);
    let bad = [
        TissueMaterial::new(-1.0, 1e4, 0.3),
        TissueMaterial::new(1000.0, 0.0, 0.3),
        TissueMaterial::new(1000.0, f64::NAN, 0.3),
        TissueMaterial::new(1000.0, 1e4, 0.5),
        TissueMaterial::new(1000.0, 1e4, -1.0),
        TissueMaterial::new(1000.0, 1e4, 0.3).with_damping(-1.0, 0.0),
        TissueMaterial::new(1000.0, 1e4, 0.3)
            .with_stiffness(StiffnessField::PerElement(vec![1.0; 3])),
        TissueMaterial::new(1000.0, 1e4, 0.3)
            .with_stiffness(StiffnessField::PerElement(vec![-1.0; mesh.num_tets()])),
        TissueMaterial::new(1000.0, 1e4, 0.3).with_stiffness(StiffnessField::Radial {
            center: Vec3::zeros(),
            radii: v3(1.0, 0.0, 1.0),
            core_radius: 0.5,
            factor: 5.0,
            transition: Transition::Sharp,
        }),
    ];
    for m in bad {
        let r = DeformableBody::new(mesh.clone(), m.clone(), BodySettings::default());
        assert!(r.is_err(), "accepted {m:?}");
    }
    let ok = TissueMaterial::new(1000.0, 1e4, 0.3);
    let mut s = BodySettings::default();
    s.cg.tolerance = 0.0;
    assert!(DeformableBody::new(mesh.clone(), ok.clone(), s).is_err());
    let s = BodySettings {
        preconditioner: PreconditionerKind::Periodic { every: 0 },
        ..Default::default()
    };
    assert!(DeformableBody::new(mesh.clone(), ok.clone(), s).is_err());
    let s = BodySettings {
        gravity: Some(v3(0.0, f64::NAN, 0.0)),
        ..Default::default()
    };
    assert!(DeformableBody::new(mesh.clone(), ok.clone(), s).is_err());
    let mut body = DeformableBody::new(mesh.clone(), ok, BodySettings::default()).unwrap();
    assert!(body.step(0.0).is_err());
    assert!(body.step(f64::NAN).is_err());
    assert!(body.step(-0.01).is_err());
    assert!(matches!(
        body.fix_nodes(&[10_000]),
        Err(SoftTissueError::NodeOutOfRange { .. })
    ));
    assert!(body.drive_node(0, v3(f64::INFINITY, 0.0, 0.0)).is_err());
    assert!(body.set_external_force(0, v3(f64::NAN, 0.0, 0.0)).is_err());
    let n = body.num_nodes();
    let mut x = body.positions().to_vec();
    x[1].x = f64::NAN;
    assert!(matches!(
        body.set_state(&x, &vec![Vec3::zeros(); n]),
        Err(SoftTissueError::NonFinite(_))
    ));
    assert!(body.set_state(&x[..2], &vec![Vec3::zeros(); n]).is_err());
    // Generators.
    assert!(generate::box_mesh(Vec3::zeros(), v3(1.0, 1.0, 1.0), [0, 1, 1]).is_err());
    assert!(generate::box_mesh(Vec3::zeros(), v3(-1.0, 1.0, 1.0), [1, 1, 1]).is_err());
    assert!(generate::ellipsoid([1.0, f64::NAN, 1.0], 4).is_err());
    assert!(
        generate::eye_shell(&EyeShell {
            thickness: 20e-3,
            ..Default::default()
        })
        .is_err()
    );
    assert!(
        generate::eye_shell(&EyeShell {
            incision: Some(Incision {
                length: -1.0,
                ..Default::default()
            }),
            ..Default::default()
        })
        .is_err()
    );
}

#[test]
fn body_with_nan_state_is_rejected_not_propagated() {
    let mesh = beam([3, 1, 1], 0.1, 0.02);
    let mut body = DeformableBody::new(
        mesh,
        TissueMaterial::new(1000.0, 1e4, 0.3),
        BodySettings::default(),
    )
    .unwrap();
    body.step(0.01).unwrap();
    // An external force that overflows is refused at once; forces that
    // overflow only together make the step fail, not propagate.
    assert!(body.set_external_force(0, v3(f64::MAX, 0.0, 0.0)).is_err());
    body.set_external_force(0, v3(1e154, 0.0, 0.0)).unwrap();
    body.set_external_force(1, v3(1e154, 0.0, 0.0)).unwrap();
    let r = body.step(0.01);
    assert!(
        r.is_err()
            || body
                .positions()
                .iter()
                .all(|p| p.iter().all(|c| c.is_finite()))
    );
}

#[test]
fn msh_roundtrip_ascii_and_binary() {
    let mesh = generate::ellipsoid([1.0, 1.0, 0.5], 4).unwrap();
    for binary in [false, true] {
        let bytes = io::write_msh(&mesh, binary);
        let back = io::parse_msh(&bytes, ValidateOptions::default()).unwrap();
        assert_eq!(back.num_vertices(), mesh.num_vertices());
        assert_eq!(back.tets(), mesh.tets());
        for (a, b) in back.positions().iter().zip(mesh.positions()) {
            assert!((a - b).norm() < 1e-12);
        }
    }
    let dir = std::env::temp_dir().join(format!("bst-msh-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("m.msh");
    std::fs::write(&path, io::write_msh(&mesh, true)).unwrap();
    assert_eq!(
        io::load_msh(&path, ValidateOptions::default())
            .unwrap()
            .num_tets(),
        mesh.num_tets()
    );
    assert!(matches!(
        io::load_msh(dir.join("missing.msh"), ValidateOptions::default()),
        Err(SoftTissueError::Io { .. })
    ));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn msh_malformed_inputs_are_errors() {
    let good = String::from_utf8(io::write_msh(
        &generate::box_mesh(Vec3::zeros(), v3(1., 1., 1.), [1, 1, 1]).unwrap(),
        false,
    ))
    .unwrap();
    let cases = [
        String::new(),
        "garbage".to_string(),
        good.replace("$EndNodes", "$EndNodez"),
        good.replace("4.1 0 8", "2.2 0 8"),
        good[..good.len() / 2].to_string(),
        // An element pointing to a node that does not exist.
        good.replace("\n1 1 2 4 8\n", "\n1 1 2 4 99\n"),
    ];
    for (i, c) in cases.iter().enumerate() {
        let r = io::parse_msh(c.as_bytes(), ValidateOptions::default());
        assert!(
            matches!(r, Err(SoftTissueError::Parse { .. })),
            "case {i}: {r:?}"
        );
    }
    let binary = io::write_msh(
        &generate::box_mesh(Vec3::zeros(), v3(1., 1., 1.), [1, 1, 1]).unwrap(),
        true,
    );
    assert!(io::parse_msh(&binary[..binary.len() - 40], ValidateOptions::default()).is_err());
}

#[test]
fn tetgen_loader() {
    let node1 = "# unit tet\n5 3 0 0\n1 0 0 0\n2 1 0 0\n3 0 1 0\n4 0 0 1\n5 1 1 1\n";
    let ele1 = "2 4 0\n1 1 2 3 4\n2 2 3 4 5  # second\n";
    let m = io::parse_tetgen(
        node1,
        ele1,
        ValidateOptions {
            reorient: true,
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!((m.num_vertices(), m.num_tets()), (5, 2));
    assert!(m.tet_volume(1) > 0.0);
    let node0 = "4 3 0 0\n0 0 0 0\n1 1 0 0\n2 0 1 0\n3 0 0 1\n";
    let ele0 = "1 4 0\n0 0 1 2 3\n";
    assert_eq!(
        io::parse_tetgen(node0, ele0, ValidateOptions::default())
            .unwrap()
            .num_tets(),
        1
    );
    let bad = [
        ("", ele0),
        ("4 2 0 0\n", ele0),
        ("4 3 0 0\n0 0 0 0\n1 1 0 0\n", ele0),
        ("4 3 0 0\n0 0 0 0\n1 1 0 0\n2 0 x 0\n3 0 0 1\n", ele0),
        ("4 3 0 0\n0 0 0 0\n2 1 0 0\n2 0 1 0\n3 0 0 1\n", ele0),
        (node0, "1 3 0\n0 0 1 2\n"),
        (node0, "2 4 0\n0 0 1 2 3\n"),
        (node0, "1 4 0\n0 0 1 2 9\n"),
    ];
    for (i, (n, e)) in bad.iter().enumerate() {
        assert!(
            io::parse_tetgen(n, e, ValidateOptions::default()).is_err(),
            "case {i}"
        );
    }
}

#[test]
fn radial_field_makes_core_stiffer() {
    let mesh = generate::ellipsoid(LENS_RADII, 10).unwrap();
    let young = lens_material().element_young(&mesh).unwrap();
    let (mut core, mut rim) = (f64::NAN, f64::NAN);
    for t in 0..mesh.num_tets() {
        let rho = mesh
            .tet_centroid(t)
            .component_div(&Vec3::from(LENS_RADII))
            .norm();
        if rho < 0.3 {
            core = young[t];
        }
        if rho > 0.9 {
            rim = young[t];
        }
    }
    assert!((core / rim - 5.0).abs() < 1e-9, "core {core}, rim {rim}");
    let sharp = TissueMaterial::new(1000.0, 1.0, 0.3).with_stiffness(StiffnessField::Radial {
        center: Vec3::zeros(),
        radii: Vec3::from(LENS_RADII),
        core_radius: 0.5,
        factor: 3.0,
        transition: Transition::Sharp,
    });
    let e = sharp.element_young(&mesh).unwrap();
    assert!(e.iter().all(|&v| v == 1.0 || v == 3.0));
    assert!(e.contains(&3.0) && e.contains(&1.0));
}

#[test]
fn material_change_at_runtime_changes_stiffness() {
    let mesh = beam([6, 1, 1], 0.1, 0.02);
    let settings = BodySettings {
        preconditioner: PreconditionerKind::Exact,
        gravity: Some(v3(0.0, 0.0, -9.81)),
        ..Default::default()
    };
    let sag = |young: f64| {
        let mut b = DeformableBody::new(
            mesh.clone(),
            TissueMaterial::new(1000.0, 1e5, 0.3).with_damping(1.0, 0.0),
            settings,
        )
        .unwrap();
        b.fix_where(|p| p.x < 1e-9);
        b.set_material(TissueMaterial::new(1000.0, young, 0.3).with_damping(1.0, 0.0))
            .unwrap();
        for _ in 0..20 {
            b.step(5.0).unwrap();
        }
        b.positions()
            .iter()
            .map(|p| -p.z)
            .fold(f64::NEG_INFINITY, f64::max)
    };
    let (soft, stiff) = (sag(1e5), sag(1e6));
    assert!(soft > 5.0 * stiff, "soft {soft}, stiff {stiff}");
}

/// When CG does not converge with an old factor (here: the core became 10⁵×
/// stiffer than the rest since the factor was made, and CG may run only 20 iterations), the
/// step factorizes the current matrix on the spot and converges.
#[test]
fn unconverged_cg_rescues_with_a_fresh_factor() {
    for kind in [
        PreconditionerKind::Periodic { every: 1_000_000 },
        PreconditionerKind::Async,
    ] {
        let mesh = generate::ellipsoid(LENS_RADII, 6).unwrap();
        let mut settings = BodySettings {
            preconditioner: kind,
            gravity: Some(v3(0.0, -9.81, 0.0)),
            ..Default::default()
        };
        settings.cg.max_iterations = 20;
        let mut body = DeformableBody::new(mesh, lens_material(), settings).unwrap();
        body.fix_where(|p| p.z < -1.5e-3);
        for _ in 0..3 {
            let r = body.step(0.01).unwrap();
            assert!(r.cg.converged, "{kind:?}: {:?}", r.cg);
        }
        assert_eq!(body.report().preconditioner.rescues, 0, "{kind:?}");
        // Periodic never refreshes by itself; Async may hand in a factor of the
        // new matrix a step later, so stiffen and step at once.
        let stiff = TissueMaterial::new(1000.0, 5e3, 0.45)
            .with_stiffness(StiffnessField::Radial {
                center: Vec3::zeros(),
                radii: Vec3::from(LENS_RADII),
                core_radius: 0.5,
                factor: 1e5,
                transition: Transition::Sharp,
            })
            .with_damping(1.0, 0.01);
        body.set_material(stiff).unwrap();
        let r = body.step(0.01).unwrap();
        assert!(r.cg.converged, "{kind:?}: {:?}", r.cg);
        assert!(
            r.cg.iterations > 20,
            "{kind:?}: the old factor failed first"
        );
        assert_eq!(r.preconditioner.rescues, 1, "{kind:?}");
        assert_eq!(r.preconditioner.factor_age, 0);
        assert!(
            body.positions()
                .iter()
                .all(|p| p.iter().all(|c| c.is_finite()))
        );
    }
}

/// An element pushed through itself turns continuously while it is inverted,
/// and once let go its force turns it back the way it came: with one face
/// held, the pushed vertex returns to its place, not to the mirror image below.
/// (What the rotation of an inverted element avoids is checked in
/// `inverted_rotation_follows_the_last_one`.)
#[test]
fn inverted_element_turns_continuously_and_recovers() {
    let s = 0.01;
    let rest = [
        v3(0.0, 0.0, 0.0),
        v3(s, 0.0, 0.0),
        v3(0.0, s, 0.0),
        v3(0.0, 0.0, s),
    ];
    let mesh = TetMesh::new(rest.to_vec(), vec![[0, 1, 2, 3]]).unwrap();
    let settings = BodySettings {
        preconditioner: PreconditionerKind::Exact,
        ..Default::default()
    };
    let material = TissueMaterial::new(1000.0, 1e4, 0.3).with_damping(5.0, 0.0);
    let mut body = DeformableBody::new(mesh, material, settings).unwrap();
    let h = 1e-3;
    // A quarter turn about z, at rest: the element's rotation is that turn.
    let q = *Rotation3::from_axis_angle(&Vec3::z_axis(), std::f64::consts::FRAC_PI_2).matrix();
    let turned: Vec<Vec3> = rest.iter().map(|p| q * p).collect();
    body.set_state(&turned, &[Vec3::zeros(); 4]).unwrap();
    body.fix_nodes(&[0, 1, 2]).unwrap();
    body.step(h).unwrap();
    assert!((body.element_rotations()[0] - q).norm() < 1e-9);
    let volume = |b: &DeformableBody| {
        let x = b.positions();
        (x[1] - x[0]).cross(&(x[2] - x[0])).dot(&(x[3] - x[0])) / 6.0
    };
    // Vertex 3 driven down through the opposite face and sideways, then let go.
    let target = turned[0] + q * v3(0.4 * s, 0.3 * s, -0.6 * s);
    let mut prev = q;
    let mut inverted_steps = 0;
    for k in 1..=3000 {
        if k <= 100 {
            let t = k as f64 / 100.0;
            body.drive_node(3, turned[3] * (1.0 - t) + target * t)
                .unwrap();
        } else if k == 101 {
            body.free_node(3).unwrap();
        }
        body.step(h).unwrap();
        let r = body.element_rotations()[0];
        if volume(&body) <= 0.0 {
            inverted_steps += 1;
        }
        assert!(
            angle(prev.transpose() * r) < 15.0,
            "step {k}: the rotation jumped by {:.1}°",
            angle(prev.transpose() * r)
        );
        prev = r;
        assert!(
            body.positions()
                .iter()
                .all(|p| p.iter().all(|c| c.is_finite()))
        );
    }
    assert!(inverted_steps >= 10, "only {inverted_steps} steps inverted");
    // Back to the rest shape in the turned orientation.
    let x = body.positions();
    assert!(volume(&body) > 0.0);
    assert!(
        (x[3] - turned[3]).norm() < 0.02 * s,
        "vertex 3 at {:?}, rest {:?}",
        x[3],
        turned[3]
    );
}

/// The rotation warps are tried against the unwarped factor on each solve's
/// first residual, and the best fit is kept: a warp that is pure noise (the
/// matrix has not changed, the rotations say it turned) is left out, a warp
/// that is exact (the matrix turned rigidly) is kept, and where the body
/// turned rigidly but the node rotations scatter about that turn (as they do
/// in a tissue that turns while it deforms) the body's one turn is kept.
/// Each time CG converges as if the factor were current.
#[test]
fn rotation_warp_is_kept_only_where_it_fits() {
    use bevy_soft_tissue::solver::cg::{self, CgScratch};
    use bevy_soft_tissue::solver::{PreconditionerState, WarpKind, body_turn};
    let mut body = DeformableBody::new(
        beam([6, 2, 2], 0.06, 0.02),
        TissueMaterial::new(1000.0, 1e5, 0.3),
        BodySettings {
            preconditioner: PreconditionerKind::None,
            ..Default::default()
        },
    )
    .unwrap();
    body.fix_where(|p| p.x < 1e-9);
    body.step(0.01).unwrap();
    let a = body.system_matrix().clone();
    let n = a.n();
    let kind = PreconditionerKind::Periodic { every: 1000 };
    let b: Vec<Vec3> = (0..n)
        .map(|i| v3((i as f64).sin(), (0.7 * i as f64).cos(), 0.3))
        .collect();
    let settings = CgSettings {
        warm_start: false,
        ..Default::default()
    };
    let solve = |pc: &mut PreconditionerState, a: &BlockCsr, b: &[Vec3]| {
        let mut x = vec![Vec3::zeros(); n];
        let mut scratch = CgScratch::new(n);
        let r = cg::solve(a, b, &mut x, pc, &settings, &mut scratch);
        assert!(r.converged);
        r.iterations
    };
    let identity = vec![Mat3::identity(); n];
    // A factor of `a` with the identity rotations, then the step of `now`
    // with the node rotations `rot`.
    let lagging = |now: &BlockCsr, rot: &[Mat3]| {
        let mut pc = PreconditionerState::new(kind, &a).unwrap();
        pc.update(&a, &identity, 0).unwrap();
        pc.update(now, rot, 1).unwrap();
        pc
    };
    // Noise: random node rotations over an unchanged matrix.
    let noise: Vec<Mat3> = (0..n)
        .map(|i| {
            let axis = Unit::new_normalize(v3(1.0, i as f64, 2.0));
            *Rotation3::from_axis_angle(&axis, 0.3 + 0.1 * (i % 5) as f64).matrix()
        })
        .collect();
    let mut pc = lagging(&a, &noise);
    let it = solve(&mut pc, &a, &b);
    assert_eq!(pc.stats().warp_offered, 1);
    assert_eq!(pc.stats().warp_declined, 1);
    assert!(it <= 2, "{it} iterations with the noise left out");
    // Exact: the whole matrix turned by q, and so did every node.
    let q = *Rotation3::from_axis_angle(&Unit::new_normalize(v3(1.0, 2.0, 3.0)), 1.2).matrix();
    let mut turned = a.clone();
    for v in &mut turned.values {
        *v = q * *v * q.transpose();
    }
    let bq: Vec<Vec3> = b.iter().map(|v| q * v).collect();
    let mut pc = lagging(&turned, &vec![q; n]);
    let it = solve(&mut pc, &turned, &bq);
    assert_eq!(pc.stats().warp_offered, 1);
    assert_eq!(pc.stats().warp_declined, 0);
    assert!(it <= 2, "{it} iterations with the exact warp");
    // The same turn, with each node's rotation off it by ±0.5 rad about its
    // own axis (in pairs, so that the body's turn is `q` exactly; an odd last
    // node has `q`): the nodes' warps are wrong, and so is no warp; the
    // body's one turn is exact.
    let scattered: Vec<Mat3> = (0..n)
        .map(|i| {
            let axis = Unit::new_normalize(v3(1.0, (i / 2) as f64, 2.0 - (i / 2 % 3) as f64));
            let sign = match (i % 2, i + 1 == n) {
                (0, true) => 0.0,
                (0, false) => 1.0,
                _ => -1.0,
            };
            q * *Rotation3::from_axis_angle(&axis, sign * 0.5).matrix()
        })
        .collect();
    assert!((body_turn(&scattered, &identity) - q).norm() < 1e-12);
    let mut pc = lagging(&turned, &scattered);
    let it = solve(&mut pc, &turned, &bq);
    assert_eq!(pc.stats().warp_declined, 0);
    assert_eq!(pc.stats().warp_body, 1);
    let st = pc.factor_state().unwrap();
    assert_eq!(st.warp_kind, WarpKind::Body);
    assert!(st.warped && st.warp.iter().all(|w| (w - q).norm() < 1e-12));
    assert!(it <= 2, "{it} iterations with the body's turn");
    // The body's turn follows any rigid turn of scattered rotations.
    let then: Vec<Mat3> = noise.iter().map(|r| r * r).collect();
    let now: Vec<Mat3> = then.iter().map(|r| q * r).collect();
    assert!((body_turn(&now, &then) - q).norm() < 1e-12);
}

/// Where the two smallest singular values of an inverted `F` cross, the plain
/// sign fix (flip the smallest) jumps by a half turn; the rotation nearest the
/// last one does not.
#[test]
fn inverted_rotation_follows_the_last_one() {
    use bevy_soft_tissue::math::polar_rotation_near;
    let turn = *Rotation3::from_axis_angle(&Unit::new_normalize(v3(1.0, 2.0, 0.5)), 0.7).matrix();
    // Singular values 2, 0.5 ± d, and det F < 0.
    let f = |d: f64| turn * Mat3::from_diagonal(&v3(2.0, 0.5 + d, -(0.5 - d)));
    let (before, after) = (f(0.01), f(-0.01));
    let plain = angle(polar_rotation(&before).transpose() * polar_rotation(&after));
    assert!(plain > 170.0, "the plain sign fix turned by {plain:.1}°");
    let first = polar_rotation_near(&before, &turn);
    let next = polar_rotation_near(&after, &first);
    assert!(angle(first.transpose() * next) < 1.0);
    for r in [first, next] {
        assert!((r.determinant() - 1.0).abs() < 1e-12);
        assert!((r.transpose() * r - Mat3::identity()).norm() < 1e-12);
    }
    // Positive determinant: the polar rotation, whatever the last one was.
    let g = turn * Mat3::from_diagonal(&v3(1.2, 0.9, 0.8));
    assert!((polar_rotation_near(&g, &Mat3::identity()) - turn).norm() < 1e-12);
}

/// Where the smallest singular value of an inverted `F` is well below the
/// others, the rotation is the plain sign fix (the element pushed back across
/// its thinnest direction) even when the last rotation was another candidate:
/// the nearest candidate there could leave the element inverted.
#[test]
fn an_inverted_element_with_one_thin_direction_takes_the_plain_sign_fix() {
    use bevy_soft_tissue::math::{SINGULAR_VALUES_CLOSE, polar_rotation_near};
    let turn = *Rotation3::from_axis_angle(&Unit::new_normalize(v3(1.0, 2.0, 0.5)), 0.7).matrix();
    // Singular values 2, 1 and 0.2, inverted along the thin one.
    let f = turn * Mat3::from_diagonal(&v3(2.0, 1.0, -0.2));
    const { assert!(0.2 < SINGULAR_VALUES_CLOSE * 1.0) };
    let plain = polar_rotation(&f);
    assert!((plain - turn).norm() < 1e-12);
    // The candidate that flips the largest direction instead, as the last rotation.
    let other = turn * Mat3::from_diagonal(&v3(-1.0, 1.0, -1.0));
    assert!((other.determinant() - 1.0).abs() < 1e-12);
    let r = polar_rotation_near(&f, &other);
    assert!(
        (r - plain).norm() < 1e-12,
        "the nearest candidate was kept: {:.1}° from the plain sign fix",
        angle(plain.transpose() * r)
    );
    // Rᵀ F then has the thin direction inverted only.
    let d = r.transpose() * f;
    assert!(d[(0, 0)] > 0.0 && d[(1, 1)] > 0.0 && d[(2, 2)] < 0.0, "{d}");
}

/// The meshes shipped in `assets/` are what `examples/write_meshes.rs` writes
/// from the generators (the paper-size lens and the default scene's eye).
#[test]
fn shipped_meshes_match_their_generators() {
    let p = bevy_soft_tissue::scenes::cataract::CataractParams::default();
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("assets");
    for (name, mesh) in [
        (
            "lens.msh",
            generate::ellipsoid(LENS_RADII, p.lens_cells).unwrap(),
        ),
        ("eye.msh", generate::eye_shell(&p.eye).unwrap()),
    ] {
        let shipped = io::load_msh(dir.join(name), ValidateOptions::default()).unwrap();
        assert_eq!(shipped.tets(), mesh.tets(), "{name}");
        assert_eq!(shipped.positions(), mesh.positions(), "{name}");
    }
}
