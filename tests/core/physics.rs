//! `tests/core.rs`: elastic response, convergence, preconditioners, the factorizer.

use super::*;

#[test]
fn rigid_motion_gives_zero_elastic_force() {
    let mesh = beam([4, 2, 2], 0.1, 0.02);
    let scale = force_scale(&mesh, 1e5);
    for method in [RotationMethod::Polar, RotationMethod::Qr] {
        let settings = BodySettings {
            rotation: method,
            preconditioner: PreconditionerKind::None,
            ..Default::default()
        };
        let mut body = DeformableBody::new(
            mesh.clone(),
            TissueMaterial::new(1000.0, 1e5, 0.3),
            settings,
        )
        .unwrap();
        let n = body.num_nodes();
        let mut f = vec![Vec3::zeros(); n];
        for deg in [0.0, 30.0, 90.0, 135.0, 179.0, 180.0] {
            let axis = Unit::new_normalize(v3(1.0, -2.0, 0.5));
            let rot = Rotation3::from_axis_angle(&axis, f64::to_radians(deg));
            let t = v3(0.3, -1.0, 2.0);
            let x: Vec<Vec3> = mesh.positions().iter().map(|p| rot * p + t).collect();
            body.set_state(&x, &vec![Vec3::zeros(); n]).unwrap();
            body.elastic_forces(&mut f);
            let max = f.iter().map(|v| v.norm()).fold(0.0, f64::max);
            assert!(
                max <= 1e-9 * scale,
                "{method:?} {deg}°: elastic force {max:e} vs scale {scale:e}"
            );
        }
    }
}

#[test]
fn uniaxial_stretch_recovers_young_and_poisson() {
    let (lx, ly, lz) = (0.04, 0.02, 0.03);
    let mesh = generate::box_mesh(v3(0.0, 0.0, 0.0), v3(lx, ly, lz), [4, 3, 3]).unwrap();
    let (young, nu) = (2.5e4, 0.37);
    let body_settings = BodySettings {
        preconditioner: PreconditionerKind::None,
        ..Default::default()
    };
    let mut body = DeformableBody::new(
        mesh.clone(),
        TissueMaterial::new(1000.0, young, nu),
        body_settings,
    )
    .unwrap();
    let n = body.num_nodes();
    // Pure longitudinal strain u = (εx, 0, 0): σxx = (λ+2μ)ε, σyy = λε.
    let eps = 1e-7;
    let x: Vec<Vec3> = mesh
        .positions()
        .iter()
        .map(|p| v3(p.x * (1.0 + eps), p.y, p.z))
        .collect();
    body.set_state(&x, &vec![Vec3::zeros(); n]).unwrap();
    let mut f = vec![Vec3::zeros(); n];
    body.elastic_forces(&mut f);
    // Patch test: interior nodes carry no force.
    let fmax = f.iter().map(|v| v.norm()).fold(0.0, f64::max);
    for (p, fi) in mesh.positions().iter().zip(&f) {
        let interior = (0..3).all(|a| p[a] > 1e-9 && p[a] < [lx, ly, lz][a] - 1e-9);
        if interior {
            assert!(fi.norm() <= 1e-8 * fmax, "interior force {fi:?}");
        }
    }
    // External traction needed = −(elastic force on the face).
    let sxx = -face_force(&body, &f, 0, lx).x / (ly * lz);
    let syy = -face_force(&body, &f, 1, ly).y / (lx * lz);
    let nu_measured = syy / (sxx + syy);
    let lambda_plus_2mu = sxx / eps;
    let young_measured =
        lambda_plus_2mu * (1.0 + nu_measured) * (1.0 - 2.0 * nu_measured) / (1.0 - nu_measured);
    assert!(
        ((young_measured - young) / young).abs() < 1e-6,
        "E {young_measured}"
    );
    assert!(((nu_measured - nu) / nu).abs() < 1e-6, "ν {nu_measured}");
    // Uniaxial stress field: lateral faces free, axial stress E ε.
    let x: Vec<Vec3> = mesh
        .positions()
        .iter()
        .map(|p| {
            v3(
                p.x * (1.0 + eps),
                p.y * (1.0 - nu * eps),
                p.z * (1.0 - nu * eps),
            )
        })
        .collect();
    body.set_state(&x, &vec![Vec3::zeros(); n]).unwrap();
    body.elastic_forces(&mut f);
    let sxx = -face_force(&body, &f, 0, lx).x / (ly * lz);
    assert!(((sxx / eps - young) / young).abs() < 1e-6);
    assert!(face_force(&body, &f, 1, ly).y.abs() < 1e-6 * sxx * lx * lz);
}

/// Meshes: 0.2 × 0.02 × 0.02 m beam, cells 15×3×3, 30×6×6, 60×12×12 (6 tets per cell).
#[test]
fn cantilever_converges_to_euler_bernoulli() {
    let mut errors = Vec::new();
    for cells in [[15, 3, 3], [30, 6, 6], [60, 12, 12]] {
        let (tip, eb) = cantilever_tip(cells);
        let err = (tip - eb).abs() / eb;
        println!(
            "cantilever {cells:?}: tip {tip:.4e} m, Euler–Bernoulli {eb:.4e} m, error {:.1} %",
            100.0 * err
        );
        errors.push(err);
    }
    assert!(
        errors[1] < errors[0] && errors[2] < errors[1],
        "errors {errors:?}"
    );
    assert!(errors[2] < 0.10, "finest error {:?}", errors[2]);
}

#[test]
fn exact_ldlt_converges_in_at_most_two_iterations() {
    let mesh = generate::ellipsoid(LENS_RADII, 8).unwrap();
    let settings = BodySettings {
        preconditioner: PreconditionerKind::Exact,
        gravity: Some(v3(0.0, -9.81, 0.0)),
        ..Default::default()
    };
    let mut body = DeformableBody::new(mesh, lens_material(), settings).unwrap();
    body.fix_where(|p| p.z < -1.5e-3);
    for _ in 0..20 {
        let r = body.step(0.01).unwrap();
        assert!(r.cg.converged && r.cg.iterations <= 2, "{:?}", r.cg);
    }
    // The reference solves in double precision.
    let st = body.preconditioner().factor_state().unwrap();
    assert!(!st.factor.has_single());
}

/// CG iterations per preconditioner on a pressed, twisted lens. The paper's
/// async figure (8.5 iterations) is asserted on `AsyncLagged`, whose factor
/// age does not depend on thread timing; real `Async` is only asserted to
/// converge every step and to beat Jacobi, because its factor age depends on
/// how much CPU the worker gets (on a loaded 2-core CI machine running the
/// other tests beside it, a mean age of 10 steps has been seen).
#[test]
fn lens_cg_iterations_per_preconditioner() {
    let steps = 60;
    let mut table = Vec::new();
    for kind in [
        PreconditionerKind::Jacobi,
        PreconditionerKind::Periodic { every: 1 },
        PreconditionerKind::Periodic { every: 4 },
        PreconditionerKind::Periodic { every: 16 },
        PreconditionerKind::AsyncLagged { lag: 2 },
        PreconditionerKind::Async,
    ] {
        let (it, age) = lens_iterations(kind, steps);
        println!("lens {kind:?}: mean CG iterations {it:.2}, mean factor age {age:.2}");
        table.push((kind, it, age));
    }
    let get = |k: PreconditionerKind| {
        table
            .iter()
            .find(|e| e.0 == k)
            .map(|e| (e.1, e.2))
            .unwrap_or((f64::NAN, f64::NAN))
    };
    let jacobi = get(PreconditionerKind::Jacobi).0;
    let every4 = get(PreconditionerKind::Periodic { every: 4 }).0;
    let every16 = get(PreconditionerKind::Periodic { every: 16 }).0;
    let (lagged, lagged_age) = get(PreconditionerKind::AsyncLagged { lag: 2 });
    assert!(get(PreconditionerKind::Periodic { every: 1 }).0 <= 2.0);
    assert!(every4 < jacobi);
    assert!(every4 <= every16);
    // A factor handed over at step n and used from step n + 2 is never older
    // than a 16-step refresh's, so it must not need more iterations.
    assert!(
        (2.0..16.0).contains(&lagged_age),
        "lag 2: mean factor age {lagged_age}"
    );
    assert!(lagged <= every16, "lag 2 {lagged}, every 16 {every16}");
    assert!(lagged <= 8.5, "lag 2 {lagged} above the paper's 8.5");
    assert!(
        get(PreconditionerKind::Async).0 < jacobi,
        "async {:?}, Jacobi {jacobi}",
        get(PreconditionerKind::Async)
    );
}

/// A lagging factor's CG solves with the half-precision copy exactly when the
/// body's previous solve took `HALF_FROM_ITERATIONS` iterations or more (where
/// the CPU makes the copy), and converges either way: the lens squeezed and
/// twisted, its factor refreshed every 16 steps.
#[test]
fn half_precision_preconditioner_follows_the_previous_solve() {
    use bevy_soft_tissue::solver::HALF_FROM_ITERATIONS;
    let mesh = generate::ellipsoid(LENS_RADII, 8).unwrap();
    let settings = BodySettings {
        preconditioner: PreconditionerKind::Periodic { every: 16 },
        ..Default::default()
    };
    let mut body = DeformableBody::new(mesh.clone(), lens_material(), settings).unwrap();
    let top: Vec<usize> = (0..mesh.num_vertices())
        .filter(|&i| mesh.positions()[i].z > 1.2e-3)
        .collect();
    body.fix_where(|p| p.z < -1.2e-3);
    let steps = 48;
    let (mut previous, mut half, mut single) = (0, 0, 0);
    for s in 0..steps {
        let t = (s + 1) as f64 / steps as f64;
        press_and_turn(&mut body, &top, t * 1.0e-3, t * 45.0);
        let before = body.preconditioner().stats().half_solves;
        let r = body.step(0.02).unwrap();
        assert!(r.cg.converged, "step {s}: {:?}", r.cg);
        assert_eq!(r.preconditioner.rescues, 0, "step {s}");
        let has_half = body
            .preconditioner()
            .factor_state()
            .is_some_and(|st| st.factor.has_half());
        if !has_half {
            eprintln!("SKIPPED: no half-precision copy on this CPU (no AVX2/FMA/F16C)");
            return;
        }
        let used = body.preconditioner().stats().half_solves - before;
        assert_eq!(
            used,
            u64::from(previous >= HALF_FROM_ITERATIONS),
            "step {s}: previous solve {previous} iterations"
        );
        half += used;
        single += 1 - used;
        previous = r.cg.iterations;
    }
    // Both copies were used.
    assert!(
        half > 0 && single > 0,
        "{half} with binary16, {single} with f32"
    );
}

/// A graded beam with a 10⁴ stiffness contrast and element size ratio ≥ 20.
#[test]
fn hard_case_stays_stable() {
    let base = generate::box_mesh(v3(0.0, 0.0, 0.0), v3(1.0, 1.0, 1.0), [24, 3, 3]).unwrap();
    // Geometric grading along x: first cell ≈ 25× smaller than the last.
    let ratio: f64 = 25.0;
    let r = ratio.powf(1.0 / 23.0);
    let total = (r.powi(24) - 1.0) / (r - 1.0);
    let grade = |u: f64| {
        let k = u * 24.0;
        0.2 * (r.powf(k) - 1.0) / (r - 1.0) / total
    };
    let pos: Vec<Vec3> = base
        .positions()
        .iter()
        .map(|p| v3(grade(p.x), 0.02 * p.y, 0.02 * p.z))
        .collect();
    let mesh = TetMesh::new(pos, base.tets().to_vec()).unwrap();
    let size_ratio = mesh.max_edge_length() / mesh.min_edge_length();
    assert!(size_ratio >= 20.0, "size ratio {size_ratio}");
    let young: Vec<f64> = (0..mesh.num_tets())
        .map(|t| {
            if mesh.tet_centroid(t).x < 0.1 {
                1e3
            } else {
                1e7
            }
        })
        .collect();
    let material =
        TissueMaterial::new(1000.0, 1e3, 0.4).with_stiffness(StiffnessField::PerElement(young));
    let g = 9.81;
    let settings = BodySettings {
        gravity: Some(v3(0.0, 0.0, -g)),
        ..Default::default()
    };
    let mut body = DeformableBody::new(mesh.clone(), material, settings).unwrap();
    body.fix_where(|p| p.x > 0.2 - 1e-9);
    let m: Vec<f64> = body.mass().to_vec();
    let potential = |b: &DeformableBody| -> f64 {
        b.positions()
            .iter()
            .zip(b.mesh().positions())
            .zip(&m)
            .map(|((x, x0), m)| m * g * (x.z - x0.z))
            .sum()
    };
    let total_mass: f64 = m.iter().sum();
    let scale = total_mass * g * 0.2;
    let mut max_energy = f64::NEG_INFINITY;
    for s in 0..1000 {
        let r = body.step(0.02).unwrap();
        assert!(r.cg.converged, "step {s}: {:?}", r.cg);
        assert!(
            body.positions()
                .iter()
                .all(|p| p.iter().all(|c| c.is_finite()))
        );
        let e = body.kinetic_energy() + body.elastic_energy() + potential(&body);
        max_energy = max_energy.max(e);
        assert!(e.is_finite());
    }
    // Starting at rest with zero energy, a dissipative implicit step must not gain energy.
    assert!(
        max_energy <= 1e-6 * scale,
        "energy grew to {max_energy:e} (scale {scale:e})"
    );
}

#[test]
fn ldlt_solves_and_node_columns_match_dense() {
    // Cells 5: AMD's size; cells 10 (726 nodes): split by nested dissection.
    for cells in [5, 10] {
        let mesh = generate::ellipsoid([1.0, 0.8, 0.6], cells).unwrap();
        let mut body = DeformableBody::new(
            mesh,
            TissueMaterial::new(1000.0, 1e4, 0.3),
            BodySettings {
                preconditioner: PreconditionerKind::Exact,
                ..Default::default()
            },
        )
        .unwrap();
        body.fix_nodes(&[0]).unwrap();
        body.step(0.01).unwrap();
        let a = body.system_matrix();
        check_factor(a, &body.preconditioner().factor_state().unwrap().factor);
        for ordering in [FillOrdering::Amd, FillOrdering::NestedDissection] {
            let sym = Arc::new(LdltSymbolic::with_ordering(&a.pattern, ordering).unwrap());
            let mut f = sym.alloc_factor();
            sym.factorize(a, &mut f, &mut Vec::new()).unwrap();
            check_factor(a, &f);
        }
    }
}

/// `f` solves `a` to round-off, and its node columns are the dense forward
/// solves of unit vectors, nonzero only on the elimination-tree path.
fn check_factor(a: &BlockCsr, f: &bevy_soft_tissue::solver::ldlt::LdltFactor) {
    let n = a.n();
    let b: Vec<Vec3> = (0..n)
        .map(|i| v3(i as f64, 1.0, -(i as f64).sin()))
        .collect();
    let mut x = vec![Vec3::zeros(); n];
    let mut tmp = vec![Vec3::zeros(); n];
    f.solve(&b, &mut x, &mut tmp);
    let mut ax = vec![Vec3::zeros(); n];
    a.mul_vec(&x, &mut ax);
    let res: f64 = ax
        .iter()
        .zip(&b)
        .map(|(p, q)| (p - q).norm_squared())
        .sum::<f64>()
        .sqrt();
    let bn: f64 = b.iter().map(|v| v.norm_squared()).sum::<f64>().sqrt();
    assert!(res <= 1e-10 * bn, "residual {res:e}");
    // Node forward solve equals the dense forward solve of the unit columns.
    let sym = &f.symbolic;
    let mut work = vec![Mat3::zeros(); n];
    for node in [0, 7, n / 2, n - 1] {
        let (mut path, mut blocks) = (Vec::new(), Vec::new());
        f.node_forward_solve(node, &mut work, &mut path, &mut blocks);
        assert!(
            work.iter().all(|m| *m == Mat3::zeros()),
            "scratch left dirty"
        );
        for c in 0..3 {
            let mut y = vec![Vec3::zeros(); n];
            y[sym.iperm[node]][c] = 1.0;
            f.forward(&mut y);
            for (k, yk) in y.iter().enumerate() {
                let got = path
                    .iter()
                    .position(|&p| p == k)
                    .map(|i| blocks[i].column(c).into_owned());
                match got {
                    Some(z) => assert!((z - yk).norm() <= 1e-12 * (1.0 + yk.norm())),
                    None => assert!(yk.norm() == 0.0, "nonzero off the etree path at {k}"),
                }
            }
        }
    }
}

/// `mul_vecs` gives, to the bit, `mul_vec` of each of its vectors.
#[test]
fn block_matrix_products_of_several_vectors_match_one_at_a_time() {
    let mesh = generate::ellipsoid(LENS_RADII, 6).unwrap();
    let mut body = DeformableBody::new(mesh, lens_material(), BodySettings::default()).unwrap();
    body.step(0.01).unwrap();
    let a = body.system_matrix();
    let n = a.n();
    let x: Vec<[Vec3; 6]> = (0..n)
        .map(|i| std::array::from_fn(|k| v3((i + k) as f64, (i * k) as f64 * 0.5, -(k as f64))))
        .collect();
    let mut y = vec![[Vec3::zeros(); 6]; n];
    a.mul_vecs(&x, &mut y);
    for k in 0..6 {
        let xk: Vec<Vec3> = x.iter().map(|v| v[k]).collect();
        let mut yk = vec![Vec3::zeros(); n];
        a.mul_vec(&xk, &mut yk);
        assert!(yk.iter().zip(&y).all(|(p, q)| *p == q[k]), "vector {k}");
    }
}

/// Every ordering is a permutation, its counted cost matches the symbolic
/// factor, `Auto` keeps the cheaper one, and on a large 3-D mesh nested
/// dissection needs fewer operations and shorter column paths than minimum
/// degree (why it exists).
#[test]
fn orderings_are_permutations_and_nested_dissection_wins_on_large_meshes() {
    let is_perm = |p: &ordering::Permutation, n: usize| {
        let mut seen = vec![false; n];
        p.perm.len() == n
            && p.perm
                .iter()
                .all(|&o| o < n && !std::mem::replace(&mut seen[o], true))
            && (0..n).all(|o| p.perm[p.iperm[o]] == o)
    };
    let mean_path = |s: &LdltSymbolic| {
        let mut total = 0usize;
        for k in 0..s.n {
            let mut j = k;
            while j != bevy_soft_tissue::solver::ldlt::NONE {
                total += 1;
                j = s.parent[j];
            }
        }
        total as f64 / s.n as f64
    };
    let mesh = generate::ellipsoid(LENS_RADII, 20).unwrap();
    let pattern = BlockPattern::new(mesh.num_vertices(), mesh.tets());
    let n = pattern.n;
    let mut cost = Vec::new();
    for which in [
        FillOrdering::Amd,
        FillOrdering::NestedDissection,
        FillOrdering::Auto,
    ] {
        let p = ordering::order(&pattern, which).unwrap();
        assert!(is_perm(&p, n), "{which:?} is not a permutation");
        let (nnz, flops) = ordering::factor_cost(&pattern, &p);
        let sym = LdltSymbolic::with_ordering(&pattern, which).unwrap();
        assert_eq!(sym.perm, p.perm);
        assert_eq!(nnz, sym.nnz_blocks(), "{which:?}: counted nnz(L)");
        cost.push((flops, mean_path(&sym)));
    }
    let (amd, nd, auto) = (cost[0], cost[1], cost[2]);
    assert!(nd.0 < amd.0, "nested dissection {nd:?} against AMD {amd:?}");
    assert!(nd.1 < amd.1, "nested dissection {nd:?} against AMD {amd:?}");
    assert_eq!(auto.0, amd.0.min(nd.0));
}

/// Nested dissection of graphs it must split into components: two separate
/// meshes and isolated nodes, and the degenerate sizes.
#[test]
fn nested_dissection_handles_disconnected_and_tiny_graphs() {
    let a = generate::ellipsoid(LENS_RADII, 8).unwrap();
    let na = a.num_vertices();
    let mut tets: Vec<[usize; 4]> = a.tets().to_vec();
    tets.extend(a.tets().iter().map(|t| t.map(|i| i + na)));
    // 2 meshes and 150 isolated nodes after them.
    for n in [0, 1, 2 * na + 150] {
        let tets: Vec<[usize; 4]> = if n == 0 || n == 1 {
            Vec::new()
        } else {
            tets.clone()
        };
        let pattern = Arc::new(BlockPattern::new(n, &tets));
        let p = ordering::nested_dissection(&pattern).unwrap();
        let mut seen = vec![false; n];
        for &o in &p.perm {
            assert!(!std::mem::replace(&mut seen[o], true), "node {o} twice");
        }
        assert_eq!(p.perm.len(), n);
        if n > 1 {
            // Factorize a positive definite matrix of that pattern.
            let mut m = BlockCsr::zeros(pattern.clone());
            // Diagonally dominant: the row's size on the diagonal, -1 off it.
            for i in 0..n {
                let row = (pattern.row_ptr[i + 1] - pattern.row_ptr[i]) as f64;
                m.values[pattern.diag[i]] = Mat3::identity() * row;
            }
            for t in &tets {
                for &r in t {
                    for &c in t {
                        if r != c {
                            let s = pattern.slot(r, c).unwrap();
                            m.values[s] = Mat3::identity() * -1.0;
                        }
                    }
                }
            }
            let sym = Arc::new(
                LdltSymbolic::with_ordering(&pattern, FillOrdering::NestedDissection).unwrap(),
            );
            let mut f = sym.alloc_factor();
            sym.factorize(&m, &mut f, &mut Vec::new()).unwrap();
            check_factor(&m, &f);
        }
    }
}

#[test]
fn ldlt_rejects_indefinite_matrix() {
    let mesh = generate::box_mesh(v3(0.0, 0.0, 0.0), v3(1.0, 1.0, 1.0), [1, 1, 1]).unwrap();
    let pattern = Arc::new(BlockPattern::new(mesh.num_vertices(), mesh.tets()));
    let mut a = BlockCsr::zeros(pattern.clone());
    for i in 0..pattern.n {
        a.values[pattern.diag[i]] = Mat3::identity() * if i == 3 { -1.0 } else { 1.0 };
    }
    let sym = Arc::new(LdltSymbolic::new(&pattern).unwrap());
    let mut f = sym.alloc_factor();
    let err = sym.factorize(&a, &mut f, &mut Vec::new()).unwrap_err();
    assert!(
        matches!(err, SoftTissueError::NotPositiveDefinite { node: 3, .. }),
        "{err}"
    );
}

#[test]
fn async_worker_stops_when_body_dropped() {
    let mesh = generate::ellipsoid(LENS_RADII, 6).unwrap();
    let mut body = DeformableBody::new(mesh, lens_material(), BodySettings::default()).unwrap();
    for _ in 0..5 {
        body.step(0.01).unwrap();
    }
    let flag = body.preconditioner().worker().unwrap().alive_flag();
    assert!(flag.load(Ordering::SeqCst));
    drop(body);
    assert!(
        !flag.load(Ordering::SeqCst),
        "worker thread still running after drop"
    );
}

#[test]
fn async_factor_is_refreshed_and_used() {
    let mesh = generate::ellipsoid(LENS_RADII, 8).unwrap();
    let mut body = DeformableBody::new(
        mesh,
        lens_material(),
        BodySettings {
            gravity: Some(v3(0.0, -9.81, 0.0)),
            ..Default::default()
        },
    )
    .unwrap();
    body.fix_where(|p| p.z < -1.5e-3);
    for _ in 0..200 {
        body.step(0.01).unwrap();
        if body.report().preconditioner.refreshes >= 3 {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(2));
    }
    let r = body.report();
    assert!(r.preconditioner.refreshes >= 3, "{:?}", r.preconditioner);
    assert_eq!(r.preconditioner.failures, 0);
    // The worker's factors come with their single-precision copy, which the
    // preconditioner's solves use.
    let st = body.preconditioner().factor_state().unwrap();
    assert!(st.version >= 2 && st.factor.has_single());
}

#[test]
fn polar_rotation_is_proper_for_flat_and_inverted() {
    let inverted = Mat3::from_diagonal(&v3(1.0, 1.0, -0.5));
    let r = polar_rotation(&inverted);
    assert!((r.determinant() - 1.0).abs() < 1e-12);
    assert!((r.transpose() * r - Mat3::identity()).norm() < 1e-12);
    let flat = Mat3::from_diagonal(&v3(2.0, 1.0, 0.0));
    let r = polar_rotation(&flat);
    assert!((r.determinant() - 1.0).abs() < 1e-12);
    let nan = Mat3::from_element(f64::NAN);
    assert_eq!(polar_rotation(&nan), Mat3::identity());
    // An inverted element still gets finite forces.
    let x = [
        v3(0., 0., 0.),
        v3(1., 0., 0.),
        v3(0., 1., 0.),
        v3(0., 0., 1.),
    ];
    let e = Element::new([0, 1, 2, 3], x, 1.0, 1.0);
    let xi = [x[0], x[1], x[2], v3(0.0, 0.0, -0.5)];
    let r = e.rotation(RotationMethod::Polar, &xi);
    assert!(
        e.forces(&r, &xi)
            .iter()
            .all(|f| f.iter().all(|c| c.is_finite()))
    );
}

#[test]
fn generators_reach_paper_sizes() {
    let lens = generate::ellipsoid(LENS_RADII, 12).unwrap();
    println!(
        "lens: {} vertices, {} tets",
        lens.num_vertices(),
        lens.num_tets()
    );
    assert!((1000..=1300).contains(&lens.num_vertices()));
    assert!((4300..=5500).contains(&lens.num_tets()));
    let (lo, hi) = lens.bounds();
    assert!(((hi - lo).x - 9.5e-3).abs() < 1e-6 && ((hi - lo).z - 4.5e-3).abs() < 1e-6);
    let eye = generate::eye_shell(&EyeShell::default()).unwrap();
    println!(
        "eye: {} vertices, {} tets",
        eye.num_vertices(),
        eye.num_tets()
    );
    assert!((1100..=1400).contains(&eye.num_vertices()));
    assert!((3300..=4100).contains(&eye.num_tets()));
    // Closed lens surface: every edge shared by exactly two triangles.
    let closed = |s: &Surface| {
        let mut edges = std::collections::HashMap::new();
        for t in &s.triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                *edges.entry((a.min(b), a.max(b))).or_insert(0) += 1;
            }
        }
        edges.values().all(|&c| c == 2)
    };
    assert!(closed(&lens.surface()));
    // The eye without an incision is closed too; the incision opens it.
    let full = generate::eye_shell(&EyeShell {
        incision: None,
        ..Default::default()
    })
    .unwrap();
    assert!(closed(&full.surface()));
    assert!(closed(&eye.surface()));
    // Without an incision the boundary is two spheres (outer and inner wall); the
    // slit through the wall joins them into one surface.
    let components = |s: &Surface| {
        let mut parent: Vec<usize> = (0..s.vertices.len()).collect();
        fn find(p: &mut [usize], x: usize) -> usize {
            let mut r = x;
            while p[r] != r {
                r = p[r];
            }
            p[x] = r;
            r
        }
        for t in &s.triangles {
            for k in 1..3 {
                let (a, b) = (find(&mut parent, t[0]), find(&mut parent, t[k]));
                parent[a] = b;
            }
        }
        (0..s.vertices.len())
            .filter(|&v| find(&mut parent, v) == v)
            .count()
    };
    assert_eq!(components(&full.surface()), 2);
    assert_eq!(components(&eye.surface()), 1);
    assert!(eye.num_tets() < full.num_tets());
    // Outward surface: the signed volume from the surface equals the mesh volume.
    for m in [&lens, &full] {
        let s = m.surface();
        let vol: f64 = s
            .volume_triangles()
            .map(|t| {
                let [a, b, c] = t.map(|v| m.positions()[v]);
                a.dot(&b.cross(&c)) / 6.0
            })
            .sum();
        assert!(
            (vol - m.volume()).abs() < 1e-9 * m.volume().abs(),
            "{vol} vs {}",
            m.volume()
        );
    }
    let shell_r: Vec<f64> = full.positions().iter().map(|p| p.norm()).collect();
    assert!(
        shell_r
            .iter()
            .all(|&r| r > 11e-3 - 1e-9 && r < 12e-3 + 1e-9)
    );
}

/// The supernodal kernel (`FactorKernel::Supernodal`, large bodies)
/// refactorizes into its factor without allocating: its buffers and scratch
/// are sized with the factor.
#[test]
fn a_supernodal_factorization_allocates_nothing() {
    use bevy_soft_tissue::solver::ldlt::FactorKernel;
    let mesh = generate::ellipsoid(LENS_RADII, 6).unwrap();
    let mut body = DeformableBody::new(mesh, lens_material(), BodySettings::default()).unwrap();
    body.fix_where(|p| p.z < -1.6e-3);
    body.step(0.01).unwrap();
    let a = body.system_matrix().clone();
    let sym = Arc::new(
        LdltSymbolic::with_kernel(&a.pattern, FillOrdering::Auto, FactorKernel::Supernodal)
            .unwrap(),
    );
    assert_eq!(sym.kernel(), FactorKernel::Supernodal);
    let (mut f, mut work) = (sym.alloc_factor(), Vec::new());
    sym.factorize(&a, &mut f, &mut work).unwrap();
    let before = allocations();
    for _ in 0..3 {
        sym.factorize(&a, &mut f, &mut work).unwrap();
    }
    assert_eq!(allocations() - before, 0);
}

/// The core promises explicit scratch and no allocation in per-step loops:
/// once a body has stepped a few times, a step (assembly, preconditioner
/// update, CG, integration) allocates nothing on the stepping thread, for
/// every preconditioner. `Async` hands its matrix to the worker in recycled
/// buffers; what the worker thread allocates is its own. A per-step
/// allocation would show in every step of the 30 counted.
#[test]
fn a_body_step_allocates_nothing_once_warm() {
    for kind in [
        PreconditionerKind::Jacobi,
        PreconditionerKind::Exact,
        PreconditionerKind::Periodic { every: 3 },
        PreconditionerKind::AsyncLagged { lag: 2 },
        PreconditionerKind::Async,
    ] {
        let mesh = generate::ellipsoid(LENS_RADII, 6).unwrap();
        let settings = BodySettings {
            preconditioner: kind,
            gravity: Some(v3(0.0, -9.81, 0.0)),
            ..Default::default()
        };
        let mut body = DeformableBody::new(mesh.clone(), lens_material(), settings).unwrap();
        let top: Vec<usize> = (0..mesh.num_vertices())
            .filter(|&i| mesh.positions()[i].z > 1.6e-3)
            .collect();
        body.fix_where(|p| p.z < -1.6e-3);
        let mut counts = Vec::new();
        for s in 0..40 {
            // A pressed, twisting top face keeps the matrix changing.
            let t = s as f64 / 40.0;
            let rot = Rotation3::from_axis_angle(&Vec3::z_axis(), t * 0.5);
            for &i in &top {
                let p = mesh.positions()[i];
                body.drive_node(i, rot * v3(p.x, p.y, p.z - t * 5e-4))
                    .unwrap();
            }
            let before = allocations();
            let r = body.step(0.01).unwrap();
            counts.push(allocations() - before);
            assert!(r.cg.converged, "{kind:?} step {s}: {:?}", r.cg);
        }
        assert_steady(kind, &counts, &format!("{kind:?}"));
    }
}
