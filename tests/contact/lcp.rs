//! The LCP solvers on hand-made and recorded problems: the local Coulomb
//! solve, the shared residual, Signorini and the cone on the cataract's
//! recorded problems, sweeps against projected Gauss–Seidel, and the
//! recorded-problem file format.

use super::*;
use crate::fuzz::seeded;
use bevy_soft_tissue::contact::FACE_ROW_SHIFT;
use bevy_soft_tissue::contact::lcp::{self, ContactProblem};
use proptest::prelude::*;

const SOLVERS: [LcpSolver; 4] = [
    LcpSolver::ProjectedGaussSeidel,
    LcpSolver::BlockGaussSeidel,
    LcpSolver::Nncg,
    LcpSolver::Subspace,
];

/// The problems shipped for the `lcp` bench (recorded from the cataract run).
fn shipped() -> Vec<(String, ContactProblem)> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/data");
    let mut out: Vec<(String, ContactProblem)> = std::fs::read_dir(&dir)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "lcp"))
        .map(|p| {
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            (name, ContactProblem::read(&p).unwrap())
        })
        .collect();
    out.sort_by(|a, b| a.0.cmp(&b.0));
    assert!(out.len() >= 3, "the shipped problems are missing");
    out
}

/// `δ₀ + W λ` of `p`, summed row by row.
fn delta_of(p: &ContactProblem, lambda: &[f64]) -> Vec<f64> {
    let m = p.m();
    (0..m)
        .map(|i| p.delta0[i] + (0..m).map(|j| p.w[i * m + j] * lambda[j]).sum::<f64>())
        .collect()
}

fn settings(solver: LcpSolver, target: f64, limit: usize) -> LcpSettings {
    LcpSettings {
        solver,
        residual_tolerance: target,
        tolerance: 0.0,
        max_iterations: limit,
        ..Default::default()
    }
}

/// Checks Signorini and Coulomb contact by contact, independently of
/// `lcp::residual`: forces in the cone, no penetration, no force on an
/// opening contact, no slip while sticking, slip against the force while
/// sliding. `eps` is relative to the problem's scales (the largest free
/// violation and force).
fn assert_contact_conditions(
    p: &ContactProblem,
    lambda: &[f64],
    delta: &[f64],
    eps: f64,
    what: &str,
) {
    let m = p.m();
    let d_scale = p
        .rows
        .iter()
        .take(p.num_contacts())
        .map(|&r| p.delta0[r].abs())
        .fold(0.0, f64::max);
    let f_scale = lambda.iter().map(|l| l.abs()).fold(0.0, f64::max);
    let (dtol, ftol) = (eps * d_scale, eps * f_scale);
    for c in 0..p.num_contacts() {
        let r = p.rows[c];
        let (ln, dn) = (lambda[r], delta[r]);
        assert!(ln >= 0.0, "{what}: contact {c} pulls ({ln:e})");
        assert!(
            dn >= -dtol,
            "{what}: contact {c} penetrates {dn:e} (tol {dtol:e})"
        );
        // Complementarity: a contact with force is closed, an open one has none.
        assert!(
            (ln * p.w[r * m + r]).min(dn.max(0.0)) <= dtol,
            "{what}: contact {c} has force {ln:e} and gap {dn:e}"
        );
        if p.rows[c + 1] - r == 3 && p.mu[c] > 0.0 {
            let (lt, dt) = ([lambda[r + 1], lambda[r + 2]], [delta[r + 1], delta[r + 2]]);
            let (nt, ndt) = (lt[0].hypot(lt[1]), dt[0].hypot(dt[1]));
            let limit = p.mu[c] * ln;
            assert!(
                nt <= limit * (1.0 + 1e-9) + 1e-300,
                "{what}: contact {c} outside the cone"
            );
            if nt < limit - ftol {
                assert!(ndt <= dtol, "{what}: contact {c} sticks but slips {ndt:e}");
            } else if ndt > dtol {
                // Sliding: the force opposes the slip.
                let cos = -(lt[0] * dt[0] + lt[1] * dt[1]) / (nt * ndt).max(1e-300);
                assert!(
                    nt <= ftol || cos >= 1.0 - 1e-3,
                    "{what}: contact {c} slides with a force at cos {cos} to the slip"
                );
            }
        }
    }
}

#[test]
fn the_residual_is_zero_exactly_at_open_sticking_and_sliding_solutions() {
    let w = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
    let rows = [0, 3];
    let check = |delta0: [f64; 3], mu: f64, lambda: [f64; 3]| {
        let delta: Vec<f64> = (0..3)
            .map(|i| delta0[i] + (0..3).map(|j| w[i * 3 + j] * lambda[j]).sum::<f64>())
            .collect();
        lcp::residual(&w, &delta0, &rows, &[mu], &lambda, &delta)
    };
    // Open: a positive gap, no force.
    assert_eq!(check([1e-3, 5e-4, 0.0], 0.5, [0.0; 3]), 0.0);
    // Sticking: the force closes the gap and stops the slip, inside the cone.
    assert!(check([-2.0, 0.1, 0.0], 1.0, [2.0, -0.1, 0.0]) < 1e-15);
    // Sliding: δ_n = 0, the force on the rim against the slip (δ_t = 1.5 along x).
    assert!(check([-1.0, 2.0, 0.0], 0.5, [1.0, -0.5, 0.0]) < 1e-15);
    // The same force turned with the slip, a pull, or too little push: not solutions.
    assert!(check([-1.0, 2.0, 0.0], 0.5, [1.0, 0.5, 0.0]) > 0.1);
    assert!(check([1e-3, 0.0, 0.0], 0.5, [-1.0, 0.0, 0.0]) > 0.1);
    assert!(check([-1.0, 0.0, 0.0], 0.5, [0.5, 0.0, 0.0]) > 0.1);
}

#[test]
fn the_reported_friction_residual_separates_slip_from_rounding_at_the_rim() {
    let (mu, wtt) = (0.5, 0.1);
    // Sticking well inside the cone: any slip is the residual.
    assert_eq!(
        lcp::friction_residual([1.0, 0.1, 0.0], [3e-5, 4e-5], mu, wtt),
        5e-5
    );
    assert_eq!(
        lcp::friction_residual([1.0, 0.1, 0.0], [0.0, 0.0], mu, wtt),
        0.0
    );
    // Sliding on the rim against the slip: none.
    assert!(lcp::friction_residual([1.0, -0.5, 0.0], [2e-5, 0.0], mu, wtt) < 1e-20);
    // A rounding error inside the rim, slip opposed: the force's distance to
    // the rim times W_tt (metres), not the whole slip.
    let r = lcp::friction_residual([1.0, -0.5 * (1.0 - 2e-9), 0.0], [2e-5, 0.0], mu, wtt);
    assert!(r > 0.0 && r <= 1e-9 * wtt * 1.01, "{r:e}");
    // On the rim but turned with the slip, or across it: the slip.
    assert_eq!(
        lcp::friction_residual([1.0, 0.5, 0.0], [2e-5, 0.0], mu, wtt),
        2e-5
    );
    assert_eq!(
        lcp::friction_residual([1.0, 0.0, 0.5], [2e-5, 0.0], mu, wtt),
        2e-5
    );
    // Outside the cone: the excess times W_tt comes on top.
    let r = lcp::friction_residual([1.0, -0.6, 0.0], [2e-5, 0.0], mu, wtt);
    assert!((r - 0.1 * wtt).abs() < 1e-12, "{r:e}");
    // No normal force: only a tangential force is wrong.
    assert_eq!(
        lcp::friction_residual([0.0, 0.0, 0.0], [1e-3, 0.0], mu, wtt),
        0.0
    );
    assert!(
        (lcp::friction_residual([0.0, 0.2, 0.0], [0.0, 0.0], mu, wtt) - 0.2 * wtt).abs() < 1e-15
    );
}

proptest! {
    #![proptest_config(seeded(2000))]

    /// The exact local solve of block Gauss–Seidel meets Signorini and
    /// Coulomb for symmetric positive definite 3×3 blocks.
    #[test]
    fn the_local_coulomb_solve_is_exact(
        b in prop::array::uniform9(-1.0f64..1.0),
        shift in 0.05f64..1.0,
        q in prop::array::uniform3(-1.0f64..1.0),
        mu in 0.0f64..1.5,
        guess in prop::array::uniform3(-1.0f64..1.0),
    ) {
        // A = B Bᵀ + shift I, scaled like a compliance block.
        let mut a = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                a[i][j] = 1e-4 * ((0..3).map(|k| b[i * 3 + k] * b[j * 3 + k]).sum::<f64>()
                    + if i == j { shift } else { 0.0 });
            }
        }
        let q = q.map(|x| 1e-5 * x);
        let l = lcp::local_coulomb(&a, q, mu, guess);
        // A solution exists whenever friction cannot turn the normal response
        // around (μ ‖W_nt‖ < W_nn); beyond that the solve may say there is none.
        if mu * a[0][1].hypot(a[0][2]) < a[0][0] {
            prop_assert!(l.is_some(), "no local solution for A {a:?}, q {q:?}, μ {mu}");
        }
        let Some(l) = l else { return Ok(()) };
        let w: Vec<f64> = a.iter().flatten().copied().collect();
        let delta: Vec<f64> = (0..3).map(|i| q[i] + (0..3).map(|j| a[i][j] * l[j]).sum::<f64>()).collect();
        let r = lcp::residual(&w, &q, &[0, 3], &[mu], &l, &delta);
        prop_assert!(r <= 1e-9, "residual {r:e}: λ {l:?}, δ {delta:?}, μ {mu}");
    }
}

#[test]
fn every_solver_finds_the_same_forces_on_a_small_coupled_problem() {
    // A coupled SPD W of 12 contacts with friction 0.3 and gaps that close half of them.
    let nc = 12;
    let m = 3 * nc;
    let b = DMatrix::from_fn(m, m, |i, j| ((i * 7 + j * 13) % 11) as f64 / 11.0 - 0.45);
    let w = (&b * b.transpose() * 0.2 + DMatrix::identity(m, m)) * 1e-4;
    let p = ContactProblem {
        w: (0..m * m).map(|k| w[(k / m, k % m)]).collect(),
        delta0: (0..m)
            .map(|r| match r % 3 {
                0 if (r / 3) % 2 == 0 => -1e-5 * (1.0 + (r / 3) as f64 * 0.1),
                0 => 2e-6,
                _ => 3e-6 * ((r as f64) * 0.7).sin(),
            })
            .collect(),
        rows: (0..=nc).map(|c| 3 * c).collect(),
        mu: vec![0.3; nc],
        lambda0: vec![0.0; m],
    };
    let mut answers = Vec::new();
    for solver in SOLVERS {
        let (lambda, delta, rep) = p.solve(&settings(solver, 1e-10, 20_000)).unwrap();
        assert!(rep.residual <= 1e-10, "{solver:?}: {rep:?}");
        assert!(!rep.capped);
        assert_contact_conditions(&p, &lambda, &delta, 1e-8, &format!("{solver:?}"));
        answers.push(lambda);
    }
    let scale = answers[0].iter().map(|l| l.abs()).fold(0.0, f64::max);
    assert!(scale > 0.0);
    for (s, a) in SOLVERS.iter().zip(&answers) {
        let diff = a
            .iter()
            .zip(&answers[0])
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max);
        assert!(diff <= 1e-6 * scale, "{s:?} differs by {diff:e}");
    }
}

#[test]
fn recorded_cataract_problems_meet_signorini_and_the_cone() {
    for (name, p) in shipped() {
        for solver in SOLVERS {
            let (lambda, delta, rep) = p.solve(&settings(solver, 1e-6, 1000)).unwrap();
            // The `δ` the solve kept (by rows of `W`, not made afresh at the
            // end) is `δ₀ + W λ` of its answer to round-off.
            let fresh = delta_of(&p, &lambda);
            let scale = fresh
                .iter()
                .chain(&p.delta0)
                .fold(0.0f64, |a, v| a.max(v.abs()));
            for (i, (a, b)) in fresh.iter().zip(&delta).enumerate() {
                assert!(
                    (a - b).abs() <= 1e-12 * scale,
                    "{name} {solver:?}: row {i}: {a:e} {b:e}"
                );
            }
            // The report's residual is the shared residual of the answer.
            let r = lcp::residual(&p.w, &p.delta0, &p.rows, &p.mu, &lambda, &delta);
            assert!(
                (r - rep.residual).abs() <= 1e-12 + 1e-9 * r,
                "{name} {solver:?}"
            );
            assert!(
                rep.residual <= 1e-6 || rep.capped,
                "{name} {solver:?}: {rep:?}"
            );
            if rep.residual <= 1e-6 {
                assert_contact_conditions(&p, &lambda, &delta, 1e-4, &format!("{name} {solver:?}"));
            }
        }
    }
}

/// `solve_until` with a stop that never fires is `solve`, to the bit; a stop
/// that fires after `k` sweeps ends the solve there, reported as capped,
/// with `δ = W λ + δ₀` of the forces it stopped at; continuing from those
/// forces reaches the tolerance (where the whole solve did).
#[test]
fn solve_until_stops_where_told_and_is_solve_otherwise() {
    for (name, p) in shipped() {
        let set = settings(LcpSolver::BlockGaussSeidel, 1e-6, 1000);
        let (lambda, delta, rep) = p.solve(&set).unwrap();
        // Solves from the start, stopped by the caller after `stop_at` sweeps (0: never).
        let until = |l: &mut Vec<f64>, scratch: &mut lcp::LcpScratch, stop_at: usize| {
            *l = p.lambda0.clone();
            let mut sweeps = 0;
            lcp::solve_until(&p.w, &p.delta0, &p.rows, &p.mu, l, &set, scratch, || {
                sweeps += 1;
                sweeps == stop_at
            })
        };
        let (mut l, mut scratch) = (Vec::new(), lcp::LcpScratch::default());
        let r = until(&mut l, &mut scratch, 0);
        assert_eq!(l, lambda, "{name}");
        assert_eq!(scratch.delta(), &delta[..], "{name}");
        assert_eq!(r.iterations, rep.iterations, "{name}");
        assert!(rep.iterations > 3, "{name}: {rep:?}");

        let r = until(&mut l, &mut scratch, 3);
        assert_eq!(r.iterations, 3, "{name}");
        assert!(r.capped && r.residual > 1e-6, "{name}: {r:?}");
        for (a, b) in delta_of(&p, &l).iter().zip(scratch.delta()) {
            assert!((a - b).abs() <= 1e-12 * (1.0 + a.abs()), "{name}: {a} {b}");
        }
        let r = lcp::solve(&p.w, &p.delta0, &p.rows, &p.mu, &mut l, &set, &mut scratch);
        assert!(r.residual <= 1e-6 || rep.capped, "{name}: {r:?}");
    }
}

#[test]
fn the_subspace_solver_needs_no_more_sweeps_than_projected_gauss_seidel() {
    for (name, p) in shipped() {
        let sweeps = |solver, target| {
            let (_, _, rep) = p.solve(&settings(solver, target, 1000)).unwrap();
            (rep.iterations, rep.residual <= target)
        };
        for target in [1e-3, 1e-4] {
            let (pgs, _) = sweeps(LcpSolver::ProjectedGaussSeidel, target);
            let (sub, met) = sweeps(LcpSolver::Subspace, target);
            println!("{name} to {target:e}: pgs {pgs} sweeps, subspace {sub}");
            assert!(met, "{name}: subspace missed {target:e}");
            assert!(
                sub <= pgs,
                "{name} to {target:e}: subspace {sub} > pgs {pgs}"
            );
        }
    }
    // The target on the recorded jam and band problems: 1e-6 within
    // 100 sweeps. On `jam_hard_c135` and `_c169` the Newton step's
    // classification cycles (coupled contacts flipping together) until the
    // step enumerates their classes: before that, 256 sweeps and 2 000
    // (capped at 3e-5). `jam_hard_c206` needs more than three classifications
    // in phase 2: with three, 512 sweeps. On `jam_stall_c151` an undamped
    // Newton step (a diagonal shift of 1e-10 in every step instead of
    // `NEWTON_SHIFTS` in turn) sends a residual near 1e-5 back to 1e-2
    // whenever one contact changes class: 2 000 sweeps, capped at 9.6e-5.
    for (name, p) in shipped() {
        let (lambda, delta, rep) = p.solve(&settings(LcpSolver::Subspace, 1e-6, 100)).unwrap();
        assert!(rep.residual <= 1e-6, "{name}: {rep:?}");
        assert_contact_conditions(&p, &lambda, &delta, 1e-4, &name);
    }
}

/// A first-pass problem of the cataract jam with tool contacts inside faces
/// (`ContactSettings::tool_faces`; 140 of its contacts, 46 of them inside
/// faces, listed in the `.faces` file beside it). A face contact's row is
/// nearly a combination of its corners' rows, so the normal rows together are
/// singular: as recorded, the subspace solver misses 10⁻⁶ within 100 sweeps
/// (it runs to its cap of 500). With the diagonal of the face rows shifted
/// by `FACE_ROW_SHIFT`, as a first pass solves it, it meets 10⁻⁶ within
/// 100, Signorini and the cone hold on the shifted problem, and on the
/// recorded one each face stays in by at most `FACE_ROW_SHIFT · W_ii λ_i`
/// (which the unshifted refinement passes then take out).
#[test]
fn a_problem_with_face_contacts_solves_with_their_rows_shifted() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/data/faces");
    let p = ContactProblem::read(&dir.join("jam_faces_c140.lcp")).unwrap();
    let faces: Vec<usize> = std::fs::read_to_string(dir.join("jam_faces_c140.faces"))
        .unwrap()
        .split_whitespace()
        .map(|c| c.parse().unwrap())
        .collect();
    let m = p.m();
    assert!(
        faces
            .iter()
            .all(|&c| p.rows[c + 1] - p.rows[c] == 1 && p.mu[c] == 0.0)
    );
    let (_, _, rep) = p.solve(&settings(LcpSolver::Subspace, 1e-6, 100)).unwrap();
    assert!(rep.residual > 1e-6, "as recorded: {rep:?}");
    let mut shifted = p.clone();
    for &c in &faces {
        let r = p.rows[c];
        shifted.w[r * m + r] *= 1.0 + FACE_ROW_SHIFT;
    }
    let (lambda, delta, rep) = shifted
        .solve(&settings(LcpSolver::Subspace, 1e-6, 100))
        .unwrap();
    assert!(rep.residual <= 1e-6, "shifted: {rep:?}");
    assert_contact_conditions(&shifted, &lambda, &delta, 1e-4, "shifted");
    // On the recorded problem a face stays in by at most its shift's share
    // of what its own force moves it (the refinement passes take that out).
    // The allowance of `assert_contact_conditions`: 1e-4 of the largest
    // free violation.
    let allowance = 1e-4
        * p.rows[..p.num_contacts()]
            .iter()
            .map(|&r| p.delta0[r].abs())
            .fold(0.0, f64::max);
    let (mut deepest, mut free) = (0.0f64, 0.0f64);
    for &c in &faces {
        let r = p.rows[c];
        let gap = p.delta0[r] + (0..m).map(|j| p.w[r * m + j] * lambda[j]).sum::<f64>();
        let share = FACE_ROW_SHIFT * p.w[r * m + r] * lambda[r];
        assert!(
            gap >= -share - allowance,
            "face contact {c}: {gap:e} m in, its share {share:e} m"
        );
        (deepest, free) = (deepest.max(-gap), free.max(-p.delta0[r]));
    }
    println!("faces in by at most {deepest:.2e} m after the shifted solve, {free:.2e} m before");
}

/// `subspace_max_rows` bounds the subspace step's LU: with 0 no step is
/// taken and the solve is block Gauss–Seidel to the bit; with no bound the
/// steps are taken. A stop that fires inside a subspace step ends the step
/// there (its best iterate is kept only if it lowers the residual) and the
/// solve right after it: the stop is asked at most twice.
#[test]
fn the_subspace_step_keeps_to_its_row_bound_and_its_stop() {
    for (name, p) in shipped() {
        let block = settings(LcpSolver::BlockGaussSeidel, 1e-6, 300);
        let (lb, _, rb) = p.solve(&block).unwrap();
        let bounded = LcpSettings {
            subspace_max_rows: 0,
            ..settings(LcpSolver::Subspace, 1e-6, 300)
        };
        let (ls, _, rs) = p.solve(&bounded).unwrap();
        assert_eq!(rs.subspace_steps, 0, "{name}: {rs:?}");
        assert_eq!(ls, lb, "{name}");
        assert_eq!(rs.iterations, rb.iterations, "{name}");
        let free = settings(LcpSolver::Subspace, 1e-6, 300);
        let (_, _, rf) = p.solve(&free).unwrap();
        assert!(rf.subspace_steps >= 1, "{name}: {rf:?}");

        // A stop that always fires: the subspace step after the first sweep
        // ends after its first Newton iteration, the solve right after it.
        let mut l = p.lambda0.clone();
        let mut calls = 0;
        let mut scratch = lcp::LcpScratch::default();
        let r = lcp::solve_until(
            &p.w,
            &p.delta0,
            &p.rows,
            &p.mu,
            &mut l,
            &free,
            &mut scratch,
            || {
                calls += 1;
                true
            },
        );
        let first = {
            let mut one = p.lambda0.clone();
            let s1 = LcpSettings {
                max_iterations: 1,
                subspace_max_rows: 0,
                ..free
            };
            lcp::solve(&p.w, &p.delta0, &p.rows, &p.mu, &mut one, &s1, &mut scratch)
        };
        if first.residual <= 1e-6 {
            continue; // met by the first sweep: no subspace step to stop
        }
        assert_eq!(r.iterations, 1, "{name}: {r:?}");
        assert!(r.capped || r.residual <= 1e-6, "{name}: {r:?}");
        assert!(
            r.residual <= first.residual,
            "{name}: {r:?} after a sweep {first:?}"
        );
        assert!(calls <= 2, "{name}: {calls} calls");
    }
}

#[test]
fn contact_problem_files_round_trip_and_refuse_malformed_input() {
    let (_, p) = shipped().into_iter().next().unwrap();
    let bytes = p.to_bytes();
    assert_eq!(ContactProblem::from_bytes(&bytes).unwrap(), p);
    let err = |b: &[u8]| ContactProblem::from_bytes(b).unwrap_err().to_string();
    assert!(err(&bytes[..bytes.len() - 1]).contains("bytes"));
    assert!(err(&bytes[..10]).contains("magic"));
    let mut bad = bytes.clone();
    bad[0] = b'X';
    assert!(err(&bad).contains("magic"));
    // A header that promises more than the file holds: refused before allocating.
    let mut huge = bytes.clone();
    huge[8..16].copy_from_slice(&(u64::MAX / 2).to_le_bytes());
    assert!(err(&huge).contains("need"));
    // A NaN in W, and a row offset past m.
    let mut nan = bytes.clone();
    let last = nan.len() - 8;
    nan[last..].copy_from_slice(&f64::NAN.to_le_bytes());
    assert!(err(&nan).contains("finite"));
    let mut rows = bytes.clone();
    rows[24 + 8..24 + 16].copy_from_slice(&2u64.to_le_bytes());
    assert!(ContactProblem::from_bytes(&rows).is_err());
    // A problem built by hand is checked before it is solved.
    let mut q = p.clone();
    q.mu[0] = -1.0;
    assert!(q.solve(&LcpSettings::default()).is_err());
    assert!(ContactProblem::read(std::path::Path::new("/nonexistent.lcp")).is_err());
}

proptest! {
    #![proptest_config(seeded(3000))]

    /// Byte flips and truncations of a valid file give a problem or an
    /// error, never a panic.
    #[test]
    fn mutated_contact_problem_files_never_panic(
        flips in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..8),
        cut in any::<prop::sample::Index>(),
        truncate in any::<bool>(),
    ) {
        let p = ContactProblem {
            // Rows: contact 0 (normal, two tangents), contact 1 (normal only).
            w: vec![
                2.0, 0.5, 0.1, 0.2, //
                0.5, 1.0, 0.0, 0.0, //
                0.1, 0.0, 1.0, 0.0, //
                0.2, 0.0, 0.0, 1.5,
            ],
            delta0: vec![-1e-5, 2e-6, 0.0, 3e-6],
            rows: vec![0, 3, 4],
            mu: vec![0.3, 0.0],
            lambda0: vec![0.0; 4],
        };
        let mut bytes = p.to_bytes();
        for (i, v) in flips {
            let k = i.index(bytes.len());
            bytes[k] ^= v;
        }
        if truncate {
            bytes.truncate(cut.index(bytes.len() + 1));
        }
        if let Ok(q) = ContactProblem::from_bytes(&bytes) {
            prop_assert!(q.validate().is_ok());
            let _ = q.solve(&LcpSettings { max_iterations: 50, ..Default::default() });
        }
    }
}

#[test]
fn the_contact_solver_records_its_first_pass_problem() {
    let mut scene = Scene::new(ContactSettings::default()).unwrap();
    scene.add_body(based_lens(5, PreconditionerKind::Exact));
    scene.add_tool(
        RigidTool::new(
            ToolShape::Sphere { radius: 3e-3 },
            at(0.0, 0.0, 2.25e-3 + 3e-3 - 2e-4),
        )
        .unwrap()
        .with_friction(0.4)
        .unwrap(),
    );
    scene.contact.record_problems(Some(1));
    let r = scene.step(0.01).unwrap();
    let p = scene.contact.take_recorded_problem().unwrap();
    assert_eq!(p.num_contacts(), r.contacts);
    assert!(p.num_contacts() > 0);
    assert!(p.validate().is_ok());
    let (_, _, rep) = p.solve(&LcpSettings::default()).unwrap();
    assert!(rep.residual <= LcpSettings::default().residual_tolerance);
    assert!(scene.contact.take_recorded_problem().is_none());
    // Off again: nothing more is kept.
    scene.contact.record_problems(None);
    scene.step(0.01).unwrap();
    assert!(scene.contact.take_recorded_problem().is_none());
}

/// A caller that solves the same `W` again with a slowly moving `δ₀` (the
/// haptic tick) may let the subspace step start from the last solve's LU
/// (`LcpScratch::reuse_factorization`): on each shipped problem, a sequence
/// of such solves meets the tolerance and the contact conditions with the
/// forces of solves that start cold, and factorizes less often.
#[test]
fn reusing_the_last_factorization_keeps_the_answer_and_saves_lus() {
    let settings = settings(LcpSolver::Subspace, 1e-8, 300);
    for (name, p) in shipped() {
        let mut cold = lcp::LcpScratch::default();
        let mut warm = lcp::LcpScratch::default();
        warm.reuse_factorization(true);
        let (mut lc, mut lw) = (p.lambda0.clone(), p.lambda0.clone());
        let (mut fc, mut fw, mut all_met) = (0, 0, true);
        // δ₀ drifts by up to 0.1 % of its scale per solve, as a device moves.
        let scale = p.delta0.iter().fold(0.0f64, |m, d| m.max(d.abs()));
        for k in 0..12 {
            let delta0: Vec<f64> = p
                .delta0
                .iter()
                .enumerate()
                .map(|(i, d)| d + 1e-3 * scale * k as f64 * ((i % 7) as f64 / 7.0 - 0.5))
                .collect();
            let rc = lcp::solve(&p.w, &delta0, &p.rows, &p.mu, &mut lc, &settings, &mut cold);
            let rw = lcp::solve(&p.w, &delta0, &p.rows, &p.mu, &mut lw, &settings, &mut warm);
            fc += rc.factorizations;
            fw += rw.factorizations;
            if rc.capped {
                all_met = false;
                continue; // a problem the step cannot finish (jam_hard_c169)
            }
            assert!(
                !rw.capped && rw.residual <= 1e-8,
                "{name}, solve {k}: {rw:?}"
            );
            assert_contact_conditions(&p, &lw, warm.delta(), 1e-6, &name);
            let norm = lc.iter().fold(0.0f64, |m, l| m.max(l.abs()));
            let apart = lc
                .iter()
                .zip(&lw)
                .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
            assert!(
                apart <= 1e-4 * norm,
                "{name}, solve {k}: forces {apart:e} apart"
            );
        }
        println!("{name}: {fw} factorizations with reuse, {fc} without");
        if all_met {
            assert!(
                fw < fc,
                "{name}: {fw} factorizations with reuse, {fc} without"
            );
        }
        // After `forget_factorization` a solve starts cold again: the same
        // forces to the bit as a fresh scratch's (reusing too, which within
        // one solve lets a later step start from an earlier one's LU).
        warm.forget_factorization();
        let (mut a, mut b) = (p.lambda0.clone(), p.lambda0.clone());
        lcp::solve(
            &p.w, &p.delta0, &p.rows, &p.mu, &mut a, &settings, &mut warm,
        );
        let mut fresh = lcp::LcpScratch::default();
        fresh.reuse_factorization(true);
        lcp::solve(
            &p.w, &p.delta0, &p.rows, &p.mu, &mut b, &settings, &mut fresh,
        );
        assert_eq!(a, b, "{name}");
    }
}

/// A scratch that solved another problem before (here the same contacts
/// with `W` scaled: the subspace step may see the same free rows and
/// sliding contacts) gives the forces of a fresh scratch, to the bit: no
/// factor of the old `W` is reused.
#[test]
fn a_used_scratch_solves_a_new_w_as_a_fresh_one() {
    let settings = settings(LcpSolver::Subspace, 1e-8, 300);
    for (name, p) in shipped() {
        let mut used = lcp::LcpScratch::default();
        let mut l = p.lambda0.clone();
        lcp::solve(
            &p.w, &p.delta0, &p.rows, &p.mu, &mut l, &settings, &mut used,
        );
        for scale in [1.0 + 1e-9, 1.25] {
            let w: Vec<f64> = p.w.iter().map(|x| x * scale).collect();
            let (mut a, mut b) = (p.lambda0.clone(), p.lambda0.clone());
            let ra = lcp::solve(&w, &p.delta0, &p.rows, &p.mu, &mut a, &settings, &mut used);
            let mut fresh = lcp::LcpScratch::default();
            let rb = lcp::solve(&w, &p.delta0, &p.rows, &p.mu, &mut b, &settings, &mut fresh);
            assert_eq!(a, b, "{name}, W × {scale}");
            assert_eq!(ra.factorizations, rb.factorizations, "{name}, W × {scale}");
        }
    }
}
