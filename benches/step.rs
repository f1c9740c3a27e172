//! One implicit step of the paper-size lens (1183 nodes, 5184 tets, nucleus 5× stiffer)
//! for each preconditioner, while the lens is squeezed and twisted.
//!
//! Run: `cargo bench --bench step` (`-- lens_assemble` for the assembly alone, `-- factorize` for one numeric factorization at three resolutions with each kernel, `-- lens_round_to` for its single- and half-precision copies, `-- lens_backward` for one backward sweep with the factor, `-- lens_forward_single` for one forward sweep and `-- lens_solve_single` for one solve with its single-precision copy, `-- lens_solve_half` for one preconditioner solve with its half-precision copy, `-- lens_solve_many6` for six right-hand sides at once (`-- lens_forward_many6` their forward half), `-- lens_w` for `W` of a jam-sized contact set).

use bevy_soft_tissue::core_prelude::*;
use bevy_soft_tissue::mesh::generate::LENS_RADII;

#[path = "../examples/common/mod.rs"]
mod common;
use bevy_soft_tissue::solver::ldlt::{FactorKernel, LdltSymbolic};
use bevy_soft_tissue::solver::ordering::Ordering;
use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::Rotation3;
use std::sync::Arc;

fn lens_body(kind: PreconditionerKind) -> (DeformableBody, Vec<usize>) {
    let mesh = generate::ellipsoid(LENS_RADII, 12).expect("lens mesh");
    let material = common::bench::lens_material();
    let settings = BodySettings {
        preconditioner: kind,
        cg: CgSettings {
            max_iterations: 1000,
            ..Default::default()
        },
        ..Default::default()
    };
    let mut body = DeformableBody::new(mesh.clone(), material, settings).expect("body");
    body.fix_where(|p| p.z < -1.6e-3);
    let top = (0..mesh.num_vertices())
        .filter(|&i| mesh.positions()[i].z > 1.6e-3)
        .collect();
    (body, top)
}

fn bench(c: &mut Criterion) {
    let mut group = c.benchmark_group("lens_step");
    group.sample_size(20);
    for (name, kind) in [
        ("jacobi", PreconditionerKind::Jacobi),
        ("exact", PreconditionerKind::Exact),
        ("periodic4", PreconditionerKind::Periodic { every: 4 }),
        ("periodic16", PreconditionerKind::Periodic { every: 16 }),
        ("async", PreconditionerKind::Async),
    ] {
        let (mut body, top) = lens_body(kind);
        let rest: Vec<Vec3> = body.mesh().positions().to_vec();
        let mut t = 0.0f64;
        group.bench_function(name, |b| {
            b.iter(|| {
                t += 0.02;
                let s = 0.5 * (1.0 - (t * 2.0).cos());
                let rot = Rotation3::from_axis_angle(&Vec3::z_axis(), s * 0.8);
                for &i in &top {
                    let p = rest[i];
                    body.drive_node(i, rot * v3(p.x, p.y, p.z - s * 1.5e-3))
                        .expect("drive");
                }
                body.step(0.02).expect("step")
            })
        });
    }
    group.finish();
}

/// One assembly (element rotations, forces, `A`, `b`) of the lens in a
/// squeezed and twisted state.
fn bench_assemble(c: &mut Criterion) {
    let (mut body, top) = lens_body(PreconditionerKind::Jacobi);
    let rest: Vec<Vec3> = body.mesh().positions().to_vec();
    let rot = Rotation3::from_axis_angle(&Vec3::z_axis(), 0.6);
    for &i in &top {
        let p = rest[i];
        body.drive_node(i, rot * v3(p.x, p.y, p.z - 1.0e-3))
            .expect("drive");
    }
    for _ in 0..5 {
        body.step(0.02).expect("step");
    }
    c.bench_function("lens_assemble", |b| {
        b.iter(|| body.assemble(0.02).expect("assemble"))
    });
}

/// One backward sweep with the lens's factor, from `l` and from its
/// single-precision copy (the contact correction's full sweep).
fn bench_backward(c: &mut Criterion) {
    let (mut body, _) = lens_body(PreconditionerKind::Periodic { every: 1 });
    body.step(0.02).expect("step");
    let mut f = body
        .preconditioner()
        .factor_state()
        .expect("factor")
        .factor
        .clone();
    assert!(f.round_to_single());
    c.bench_function("lens_round_to_single", |b| b.iter(|| f.round_to_single()));
    let n = f.symbolic.n;
    let y0: Vec<Vec3> = (0..n).map(|i| v3(1.0, -0.5, 0.25 * i as f64)).collect();
    let mut y = y0.clone();
    c.bench_function("lens_backward_double", |b| {
        b.iter(|| {
            y.copy_from_slice(&y0);
            f.backward(&mut y)
        })
    });
    c.bench_function("lens_backward_single", |b| {
        b.iter(|| {
            y.copy_from_slice(&y0);
            f.backward_single(&mut y)
        })
    });
    c.bench_function("lens_forward_single", |b| {
        b.iter(|| {
            y.copy_from_slice(&y0);
            f.forward_single(&mut y)
        })
    });
    let (mut x1, mut t1) = (y0.clone(), y0.clone());
    c.bench_function("lens_solve_single", |b| {
        b.iter(|| f.solve_single(&y0, &mut x1, &mut t1))
    });
    if f.round_to_half() {
        c.bench_function("lens_round_to_half", |b| b.iter(|| f.round_to_half()));
        c.bench_function("lens_round_to_single_and_half", |b| {
            b.iter(|| f.round_to_single_and_half())
        });
        let mut t32 = vec![[0.0f32; 4]; n];
        c.bench_function("lens_solve_half", |b| {
            b.iter(|| f.solve_half(&y0, &mut x1, &mut t1, &mut t32))
        });
    } else {
        eprintln!("lens_solve_half: not measured (no AVX2/FMA/F16C)");
    }
    let b6: Vec<[Vec3; 6]> = (0..n)
        .map(|i| std::array::from_fn(|c| v3(1.0, -0.5 * c as f64, 0.25 * i as f64)))
        .collect();
    let (mut x6, mut t6) = (b6.clone(), b6.clone());
    c.bench_function("lens_solve_many6", |b| {
        b.iter(|| f.solve_many(&b6, &mut x6, &mut t6))
    });
    c.bench_function("lens_forward_many6", |b| {
        b.iter(|| f.forward_many(&b6, &mut x6))
    });
}

/// `W` of the lens from its factor for a jam-sized contact set: 160
/// contacts (480 rows) on 240 nodes of one side, every other contact on two
/// nodes. `lens_w_cached`: every column and Gram block cached (the Gram
/// lookups and the contraction with `J`); `lens_w_new_factor`: the cache
/// forgotten first, as with a new factor (the columns and Gram blocks solved
/// too).
fn bench_compliance(c: &mut Criterion) {
    use bevy_soft_tissue::contact::{BodyCompliance, ComplianceMode, JacEntry, tangent_basis};
    use bevy_soft_tissue::solver::columns::ColumnPrefetch;
    let (mut body, _) = lens_body(PreconditionerKind::Periodic { every: 1 });
    body.step(0.02).expect("step");
    let mut side: Vec<usize> = (0..body.num_nodes()).collect();
    let x = body.positions();
    side.sort_by(|&a, &b| x[b].x.total_cmp(&x[a].x));
    let mut entries = Vec::new();
    for contact in 0..160usize {
        let n = v3(
            1.0,
            0.1 * (contact % 7) as f64,
            -0.05 * (contact % 5) as f64,
        )
        .normalize();
        let [t1, t2] = tangent_basis(&n);
        let nodes: &[(usize, f64)] = if contact % 2 == 0 {
            &[(side[contact], 0.6), (side[160 + contact / 2], 0.4)]
        } else {
            &[(side[contact], 1.0)]
        };
        for (r, dir) in [n, t1, t2].into_iter().enumerate() {
            for &(node, weight) in nodes {
                entries.push(JacEntry {
                    node: node as u32,
                    row: (3 * contact + r) as u32,
                    h: dir * weight,
                    j: Vec3::zeros(),
                });
            }
        }
    }
    entries.sort_by_key(|e| (e.node, e.row));
    let m = 480;
    let mut w = vec![0.0; m * m];
    let mut comp = BodyCompliance::new();
    let mut prefetch = ColumnPrefetch::default();
    let mut build = |comp: &mut BodyCompliance, w: &mut Vec<f64>| {
        w.fill(0.0);
        comp.accumulate(
            &body,
            &mut prefetch,
            ComplianceMode::Factorized,
            0.02,
            &mut entries,
            w,
            m,
            None,
        )
        .expect("compliance")
    };
    build(&mut comp, &mut w);
    c.bench_function("lens_w_cached", |b| b.iter(|| build(&mut comp, &mut w)));
    c.bench_function("lens_w_new_factor", |b| {
        b.iter(|| {
            comp.forget_columns();
            build(&mut comp, &mut w)
        })
    });
}

/// One numeric factorization of the lens's matrix at three resolutions
/// (`lens`: the benchmark's, 1 183 nodes; `lens18`, `lens24`), with each
/// kernel (`…_blocked`, `…_supernodal`; see `solver::ldlt::FactorKernel`), in
/// the same ordering.
fn bench_factorize(c: &mut Criterion) {
    for (prefix, divisions) in [("lens", 12), ("lens18", 18), ("lens24", 24)] {
        let mesh = generate::ellipsoid(LENS_RADII, divisions).expect("lens mesh");
        let settings = BodySettings {
            preconditioner: PreconditionerKind::Periodic { every: 1 },
            ..Default::default()
        };
        let mut body =
            DeformableBody::new(mesh, common::bench::lens_material(), settings).expect("body");
        body.fix_where(|p| p.z < -1.6e-3);
        body.step(0.02).expect("step");
        let a = body.system_matrix();
        let mut group = c.benchmark_group(format!("{prefix}_factorize"));
        group.sample_size(if divisions > 12 { 10 } else { 50 });
        for (name, kernel) in [
            ("blocked", FactorKernel::Blocked),
            ("supernodal", FactorKernel::Supernodal),
        ] {
            let sym = Arc::new(
                LdltSymbolic::with_kernel(&a.pattern, Ordering::Auto, kernel).expect("symbolic"),
            );
            assert_eq!(sym.kernel(), kernel);
            if name == "blocked" {
                println!(
                    "{prefix}: {} nodes, {} blocks of L",
                    a.n(),
                    sym.nnz_blocks()
                );
            }
            let (mut out, mut work) = (sym.alloc_factor(), Vec::new());
            group.bench_function(name, |b| {
                b.iter(|| sym.factorize(a, &mut out, &mut work).expect("factorize"))
            });
        }
        group.finish();
    }
}

criterion_group!(
    benches,
    bench,
    bench_assemble,
    bench_backward,
    bench_factorize,
    bench_compliance
);
criterion_main!(benches);
