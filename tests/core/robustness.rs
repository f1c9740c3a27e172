//! `tests/core.rs`: bad input gets a clear error, never a panic, a silent NaN
//! or a silently wrong result — loaders (with proptest fuzzing), parameters,
//! and the background factorizer.

use super::*;
use crate::fuzz::seeded;
use proptest::prelude::*;

/// Cases per loader fuzz property: 2500 (× 5 properties, about 10⁴ cases per
/// CI run), or `PROPTEST_CASES`.
const FUZZ_CASES: u32 = 2500;

/// An ASCII MSH 4.1 file with the given node blocks (tags, positions) and tetrahedra (tags).
fn msh_ascii(blocks: &[(Vec<u64>, Vec<Vec3>)], tets: &[[u64; 4]]) -> String {
    let n: usize = blocks.iter().map(|b| b.0.len()).sum();
    let all = || blocks.iter().flat_map(|b| b.0.iter().copied());
    let mut s = format!(
        "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n{} {n} {} {}\n",
        blocks.len(),
        all().min().unwrap_or(0),
        all().max().unwrap_or(0)
    );
    for (tags, x) in blocks {
        s += &format!("3 1 0 {}\n", tags.len());
        for t in tags {
            s += &format!("{t}\n");
        }
        for p in x {
            s += &format!("{:e} {:e} {:e}\n", p.x, p.y, p.z);
        }
    }
    s += &format!("$EndNodes\n$Elements\n1 {0} 1 {0}\n3 1 4 {0}\n", tets.len());
    for (i, t) in tets.iter().enumerate() {
        s += &format!("{} {} {} {} {}\n", i + 1, t[0], t[1], t[2], t[3]);
    }
    s + "$EndElements\n"
}

fn parse(bytes: &[u8]) -> Result<TetMesh> {
    io::parse_msh(bytes, ValidateOptions::default())
}

fn parse_error(bytes: &[u8]) -> String {
    match parse(bytes) {
        Err(e @ SoftTissueError::Parse { .. }) => e.to_string(),
        other => panic!("expected a parse error, got {other:?}"),
    }
}

#[test]
fn msh_inputs_that_crashed_the_old_parser_are_errors() {
    let good = String::from_utf8(io::write_msh(
        &generate::box_mesh(Vec3::zeros(), v3(1., 1., 1.), [1, 1, 1]).unwrap(),
        false,
    ))
    .unwrap();
    // An absurd data size and a binary flag of 3 in the header.
    let e = parse_error(good.replace("4.1 0 8", "4.1 0 99999999999").as_bytes());
    assert!(e.contains("$MeshFormat") && e.contains("line 2"), "{e}");
    let e = parse_error(good.replace("4.1 0 8", "4.1 3 8").as_bytes());
    assert!(e.contains("file type 3"), "{e}");
    // Node and element counts of 0.
    let n = generate::box_mesh(Vec3::zeros(), v3(1., 1., 1.), [1, 1, 1])
        .unwrap()
        .num_vertices();
    let e = parse_error(
        good.replacen(&format!("1 {n} 1 {n}\n"), "0 0 1 0\n", 1)
            .as_bytes(),
    );
    assert!(e.contains("$Nodes"), "{e}");
    let e = parse_error(b"$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n0 0 0 0\n$EndNodes\n$Elements\n0 0 0 0\n$EndElements\n");
    assert!(e.contains("no tetrahedra"), "{e}");
    // A count far beyond the file's size is refused before anything is reserved.
    let e = parse_error(
        good.replacen(&format!("1 {n} 1 {n}\n"), "1 99999999999999 1 8\n", 1)
            .as_bytes(),
    );
    assert!(e.contains("cannot fit"), "{e}");
    // Messages are readable text, not byte dumps.
    let e = parse_error(good.replace("$EndNodes", "$EndNodez").as_bytes());
    assert!(e.contains("$EndNodes") && e.contains("line"), "{e}");
    let binary = io::write_msh(
        &generate::box_mesh(Vec3::zeros(), v3(1., 1., 1.), [1, 1, 1]).unwrap(),
        true,
    );
    let e = parse_error(&binary[..binary.len() - 40]);
    assert!(e.contains("byte offset"), "{e}");
}

#[test]
fn msh_node_blocks_in_any_order_map_by_tag() {
    let x = |t: u64| match t {
        1 => v3(0., 0., 0.),
        2 => v3(1., 0., 0.),
        3 => v3(0., 1., 0.),
        4 => v3(0., 0., 1.),
        _ => v3(1., 1., 1.),
    };
    let block = |tags: &[u64]| {
        (
            tags.to_vec(),
            tags.iter().map(|&t| x(t)).collect::<Vec<_>>(),
        )
    };
    let tets = [[1, 2, 3, 4], [2, 3, 4, 5]];
    // Tags 3–5 before 1–2: each block is contiguous, the order is not.
    let text = msh_ascii(&[block(&[3, 4, 5]), block(&[1, 2])], &tets);
    let m = parse(text.as_bytes()).unwrap();
    for (t, tags) in m.tets().iter().zip(&tets) {
        for k in 0..4 {
            assert_eq!(m.positions()[t[k]], x(tags[k]), "tet {tags:?}");
        }
    }
    // A tag listed twice is an error, not a silent overwrite.
    let text = msh_ascii(&[block(&[1, 2, 3]), block(&[3, 4, 5])], &tets);
    assert!(parse_error(text.as_bytes()).contains("appears twice"));
}

#[test]
fn quadratic_tetrahedra_keep_their_corners() {
    // TetGen: 4 corners and 6 midside nodes; the .ele lists all ten.
    let mut node = String::from("10 3 0 0\n");
    let corners = [
        v3(0., 0., 0.),
        v3(1., 0., 0.),
        v3(0., 1., 0.),
        v3(0., 0., 1.),
    ];
    let pairs = [(0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)];
    let mut all: Vec<Vec3> = corners.to_vec();
    all.extend(pairs.iter().map(|&(a, b)| (corners[a] + corners[b]) * 0.5));
    for (i, p) in all.iter().enumerate() {
        node += &format!("{} {} {} {}\n", i + 1, p.x, p.y, p.z);
    }
    let ele = "1 10 0\n1 1 2 3 4 5 6 7 8 9 10\n";
    let m = io::parse_tetgen(&node, ele, ValidateOptions::default()).unwrap();
    assert_eq!((m.num_vertices(), m.num_tets()), (4, 1));
    assert_eq!(m.positions(), &corners[..]);
    // MSH type 11 likewise.
    let mut msh =
        String::from("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n1 10 1 10\n3 1 0 10\n");
    for i in 1..=10 {
        msh += &format!("{i}\n");
    }
    for p in &all {
        msh += &format!("{} {} {}\n", p.x, p.y, p.z);
    }
    msh += "$EndNodes\n$Elements\n1 1 1 1\n3 1 11 1\n1 1 2 3 4 5 6 7 8 9 10\n$EndElements\n";
    let m = parse(msh.as_bytes()).unwrap();
    assert_eq!((m.num_vertices(), m.num_tets()), (4, 1));
}

#[test]
fn tetgen_header_reserves_nothing_it_cannot_fill() {
    reset_max_alloc();
    let r = io::parse_tetgen(
        "400000000 3 0 0\n",
        "1 4 0\n1 1 2 3 4\n",
        ValidateOptions::default(),
    );
    let peak = max_alloc();
    assert!(matches!(r, Err(SoftTissueError::Parse { .. })), "{r:?}");
    assert!(peak < 1 << 20, "a 17-byte header reserved {peak} bytes");
}

#[test]
fn bad_parameters_are_clear_errors() {
    let mesh = beam([2, 1, 1], 0.1, 0.02);
    // The degenerate-element check cannot be switched off by a bad threshold.
    for v in [-1.0, f64::NAN, f64::INFINITY] {
        let r = TetMesh::with_options(
            mesh.positions().to_vec(),
            mesh.tets().to_vec(),
            ValidateOptions {
                min_relative_volume: v,
                ..Default::default()
            },
        );
        assert!(
            matches!(
                r,
                Err(SoftTissueError::InvalidParameter {
                    name: "min_relative_volume",
                    ..
                })
            ),
            "{v}: {r:?}"
        );
    }
    // Moduli that overflow in assembly are refused up front.
    for m in [
        TissueMaterial::new(1000.0, f64::MAX / 2.0, 0.3),
        TissueMaterial::new(1000.0, 1e10, 0.3).with_stiffness(StiffnessField::Radial {
            center: Vec3::zeros(),
            radii: v3(1.0, 1.0, 1.0),
            core_radius: 0.5,
            factor: 1e300,
            transition: Transition::Sharp,
        }),
    ] {
        let r = DeformableBody::new(mesh.clone(), m, BodySettings::default());
        assert!(
            matches!(r, Err(SoftTissueError::InvalidParameter { .. })),
            "{r:?}"
        );
    }
    // Time steps: zero, negative, NaN, infinite, below 1 ns, above 1e5 s.
    let mut body = DeformableBody::new(
        mesh.clone(),
        TissueMaterial::new(1000.0, 1e4, 0.3),
        BodySettings::default(),
    )
    .unwrap();
    for h in [0.0, -0.01, f64::NAN, f64::INFINITY, 1e-12, 1e7] {
        assert!(
            matches!(body.step(h), Err(SoftTissueError::InvalidParameter { .. })),
            "h = {h}"
        );
    }
    // A force whose squared norm overflows is refused; so is the sum of
    // several that each fit but overflow together (CG used to report
    // "converged" and drop them).
    assert!(body.set_external_force(0, v3(1e200, 0.0, 0.0)).is_err());
    for n in 0..3 {
        body.set_external_force(n, v3(1e154, 0.0, 0.0)).unwrap();
    }
    let before = body.positions().to_vec();
    assert!(matches!(
        body.step(0.01),
        Err(SoftTissueError::NonFinite(_))
    ));
    assert_eq!(
        body.positions(),
        &before[..],
        "a failed step moved the body"
    );
    let s = BodySettings {
        gravity: Some(v3(0.0, 0.0, -1e200)),
        ..Default::default()
    };
    assert!(DeformableBody::new(mesh, TissueMaterial::new(1000.0, 1e4, 0.3), s).is_err());
}

/// A beam clamped at one end under gravity, with the default (`Async`) preconditioner.
fn clamped_beam() -> DeformableBody {
    let mut b = DeformableBody::new(
        beam([6, 2, 2], 0.1, 0.02),
        TissueMaterial::new(1000.0, 1e4, 0.3),
        BodySettings {
            gravity: Some(v3(0.0, 0.0, -9.81)),
            ..Default::default()
        },
    )
    .unwrap();
    b.fix_where(|p| p.x < 1e-9);
    b
}

/// A worker thread that is gone (it died, or could not be started): the
/// body refreshes its factor on the stepping thread every
/// `WORKER_FALLBACK_PERIOD` steps instead of keeping an ever older one.
#[test]
fn a_stopped_worker_falls_back_to_the_stepping_thread() {
    use bevy_soft_tissue::solver::WORKER_FALLBACK_PERIOD;
    let mut b = clamped_beam();
    b.step(0.01).unwrap();
    b.preconditioner().worker().unwrap().inject_stop();
    // The worker exits at its next job, and a job waits for a free background
    // slot, which other tests of this binary share: step until the fallback
    // has refreshed a few times, or for at most 30 s.
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
    let mut steps = 0;
    while std::time::Instant::now() < deadline {
        b.step(0.01).unwrap();
        steps += 1;
        std::thread::sleep(std::time::Duration::from_millis(1));
        let dead = !b.preconditioner().worker().unwrap().is_alive();
        if dead && steps >= 60 && b.report().preconditioner.fallback_refreshes >= 5 {
            break;
        }
    }
    assert!(!b.preconditioner().worker().unwrap().is_alive());
    let st = b.report().preconditioner;
    assert!(st.fallback_refreshes >= 5, "{st:?}");
    assert!(st.factor_age <= WORKER_FALLBACK_PERIOD, "{st:?}");
    assert!(b.report().cg.converged);
}

/// A panic inside the background factorization releases the worker's slot
/// and is reported; the body keeps its factor and refreshes again, and
/// another body's worker keeps getting turns.
#[test]
fn a_panicking_background_factorization_is_contained() {
    let (mut a, mut b) = (clamped_beam(), clamped_beam());
    a.step(0.01).unwrap();
    b.step(0.01).unwrap();
    a.preconditioner().worker().unwrap().inject_panic();
    let refreshes = |x: &DeformableBody| x.report().preconditioner.refreshes;
    let mut panicked = false;
    // Other tests of this binary share the background slots: step until the
    // outcome is in, or for at most 30 s.
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
    while std::time::Instant::now() < deadline {
        a.step(0.01).unwrap();
        b.step(0.01).unwrap();
        std::thread::sleep(std::time::Duration::from_millis(1));
        panicked |= a.report().preconditioner.worker_panics > 0;
        if panicked && refreshes(&a) >= 3 && refreshes(&b) >= 3 {
            break;
        }
    }
    let st = a.report().preconditioner;
    assert_eq!(st.worker_panics, 1, "{st:?}");
    assert!(st.failures >= 1);
    assert!(matches!(
        a.preconditioner().last_error(),
        Some(SoftTissueError::WorkerPanic(_))
    ));
    assert!(refreshes(&a) >= 3, "body a no longer refreshes: {st:?}");
    assert!(
        refreshes(&b) >= 3,
        "body b no longer refreshes: {:?}",
        b.report().preconditioner
    );
    assert!(
        a.positions()
            .iter()
            .all(|p| p.iter().all(|c| c.is_finite()))
    );
}

/// `AsyncLagged` keeps its promise with more bodies than background slots:
/// every body's factor is of the matrix handed over `lag` steps before (its
/// age stays in `[lag, 2 lag − 1]`), and two runs agree to the bit. A lagged
/// body does not wait for a turn among the bodies' background
/// factorizations (at most `cores − 1` at once); when it did, a factor came
/// later than promised, at a step that depended on thread timing.
#[test]
fn async_lagged_keeps_its_lag_with_more_bodies_than_cores() {
    let lag = 2;
    let n = std::thread::available_parallelism().map_or(2, |c| c.get()) + 2;
    let run = || {
        let mut bodies: Vec<DeformableBody> = (0..n)
            .map(|k| {
                let mut b = clamped_beam();
                let mut s = *b.settings();
                s.preconditioner = PreconditionerKind::AsyncLagged { lag };
                b.set_settings(s).unwrap();
                // Different loads, so the bodies' matrices differ.
                b.set_external_force(b.num_nodes() - 1, v3(0.0, 1e-3 * k as f64, 0.0))
                    .unwrap();
                // Factorizations as long as a large body's: the bodies' jobs
                // overlap, so the slots run out.
                b.step(0.01).unwrap();
                b.preconditioner()
                    .worker()
                    .unwrap()
                    .inject_delay(std::time::Duration::from_millis(5));
                b
            })
            .collect();
        for step in 1..14u64 {
            for (k, b) in bodies.iter_mut().enumerate() {
                b.step(0.01).unwrap();
                let age = b.report().preconditioner.factor_age;
                if step >= 2 * lag as u64 {
                    assert!(
                        (lag as u64..2 * lag as u64).contains(&age),
                        "body {k} of {n}, step {step}: factor age {age}, lag {lag}"
                    );
                }
            }
        }
        bodies
            .iter()
            .map(|b| b.positions().to_vec())
            .collect::<Vec<_>>()
    };
    let (x1, x2) = (run(), run());
    assert!(x1 == x2, "two runs of {n} lagged bodies differ");
}

/// `‖A x − r‖ / ‖r‖` for `x` the solve of `r` with the body's factor: about
/// the round-off when the factor is of the body's current matrix `A`.
fn factor_residual(b: &DeformableBody) -> f64 {
    let a = b.system_matrix();
    let f = &b.preconditioner().factor_state().unwrap().factor;
    let n = a.n();
    let r: Vec<Vec3> = (0..n)
        .map(|i| v3(1.0, -0.5 + (i % 7) as f64 * 0.1, 0.25))
        .collect();
    let (mut x, mut tmp, mut ax) = (
        vec![Vec3::zeros(); n],
        vec![Vec3::zeros(); n],
        vec![Vec3::zeros(); n],
    );
    f.solve(&r, &mut x, &mut tmp);
    a.mul_vec(&x, &mut ax);
    let num: f64 = ax.iter().zip(&r).map(|(p, q)| (p - q).norm_squared()).sum();
    let den: f64 = r.iter().map(|q| q.norm_squared()).sum();
    (num / den).sqrt()
}

/// A rescue (`refactor_preconditioner_now`, which the contact phase's
/// consistency check calls after the free motion) waits for the background
/// worker when the worker is factorizing the same step's matrix, and takes its
/// factor instead of factorizing again; when the worker's job is of an older
/// step, or the worker has exited, it factorizes on the stepping thread.
/// Either way the factor is then of the current matrix.
#[test]
fn a_rescue_takes_the_workers_factor_only_of_the_same_step() {
    let h = 0.01;
    // `(lag, stop the worker)`: the rescue comes at step 3 with the worker's
    // job of step 3 (lag 1), of step 2 (lag 2), or with no worker left.
    for (lag, stop) in [(1u32, false), (2, false), (1, true)] {
        let mut b = clamped_beam();
        let mut s = *b.settings();
        s.preconditioner = PreconditionerKind::AsyncLagged { lag };
        b.set_settings(s).unwrap();
        for _ in 0..3 {
            b.step(h).unwrap();
        }
        let w = b.preconditioner().worker().unwrap();
        // The job is still running when the rescue asks for it.
        w.inject_delay(std::time::Duration::from_millis(30));
        if stop {
            w.inject_stop();
        }
        b.assemble(h).unwrap();
        b.update_preconditioner().unwrap();
        b.solve_free_motion().unwrap();
        let before = factor_residual(&b);
        let current = b.step_index() - 1;
        assert!(b.preconditioner().factor_state().unwrap().step < current);
        assert!(b.refactor_preconditioner_now().unwrap());
        let stats = b.report().preconditioner;
        let after = factor_residual(&b);
        let case = format!("lag {lag}, worker stopped {stop}: {stats:?}");
        assert_eq!(stats.rescues, 1, "{case}");
        let from_worker = lag == 1 && !stop;
        assert_eq!(stats.rescues_from_worker, u64::from(from_worker), "{case}");
        assert_eq!(
            b.preconditioner().factor_state().unwrap().step,
            current,
            "{case}"
        );
        assert_eq!(stats.factor_age, 0, "{case}");
        // The old factor's residual shows how far the matrix has moved: the
        // new one must be of the current matrix, not of the old ones.
        assert!(
            after < 1e-9 && after * 1e3 < before,
            "{case}: residual {after:e} after the rescue, {before:e} before"
        );
        // The body steps on, and the worker's next factors come in (or, once
        // it has exited, the stepping thread's fallback refreshes).
        for _ in 0..6 {
            b.step(h).unwrap();
        }
        let after_steps = b.report().preconditioner;
        assert!(
            after_steps.refreshes + after_steps.fallback_refreshes
                > stats.refreshes + stats.fallback_refreshes,
            "{case}: no refresh after the rescue: {after_steps:?}"
        );
    }
}

/// Mutations of valid files: truncation, byte flips, numbers replaced by
/// huge or odd values, lines dropped or repeated.
#[derive(Debug, Clone)]
enum Mutation {
    Truncate(usize),
    Flip(usize, u8),
    Number(usize, &'static str),
    DropLine(usize),
    RepeatLine(usize),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        any::<usize>().prop_map(Mutation::Truncate),
        (any::<usize>(), any::<u8>()).prop_map(|(i, b)| Mutation::Flip(i, b)),
        (
            any::<usize>(),
            prop::sample::select(vec![
                "0",
                "-1",
                "4294967296",
                "18446744073709551615",
                "99999999999999999999",
                "nan",
                "inf",
                "1e308",
                "-0",
                "3.5",
            ])
        )
            .prop_map(|(i, v)| Mutation::Number(i, v)),
        any::<usize>().prop_map(Mutation::DropLine),
        any::<usize>().prop_map(Mutation::RepeatLine),
    ]
}

fn apply(mut bytes: Vec<u8>, muts: &[Mutation], text: bool) -> Vec<u8> {
    for m in muts {
        if bytes.is_empty() {
            break;
        }
        let n = bytes.len();
        match m {
            Mutation::Truncate(i) => bytes.truncate(i % n),
            Mutation::Flip(i, b) => bytes[i % n] ^= b.max(&1),
            Mutation::Number(i, v) if text => {
                let s = String::from_utf8_lossy(&bytes).into_owned();
                let toks: Vec<(usize, &str)> = s
                    .split(|c: char| c.is_ascii_whitespace())
                    .scan(0, |pos, t| {
                        let at = *pos;
                        *pos += t.len() + 1;
                        Some((at, t))
                    })
                    .filter(|(_, t)| t.parse::<f64>().is_ok())
                    .collect();
                if let Some(&(at, t)) = toks.get(i % toks.len().max(1)) {
                    let mut out = s[..at].to_string();
                    out += v;
                    out += &s[at + t.len()..];
                    bytes = out.into_bytes();
                }
            }
            Mutation::Number(i, _) => {
                // Binary: overwrite eight bytes with a huge count.
                let at = i % n;
                for (k, b) in u64::MAX.to_le_bytes().iter().enumerate() {
                    if at + k < n {
                        bytes[at + k] = *b;
                    }
                }
            }
            Mutation::DropLine(i) | Mutation::RepeatLine(i) => {
                let lines: Vec<&[u8]> = bytes.split(|&c| c == b'\n').collect();
                let k = i % lines.len();
                let mut out = Vec::with_capacity(n + 64);
                for (j, l) in lines.iter().enumerate() {
                    let times = match m {
                        Mutation::DropLine(_) if j == k => 0,
                        Mutation::RepeatLine(_) if j == k => 2,
                        _ => 1,
                    };
                    for _ in 0..times {
                        out.extend_from_slice(l);
                        out.push(b'\n');
                    }
                }
                bytes = out;
            }
        }
    }
    bytes
}

/// What a parser may return: a clear error, or a valid mesh.
fn well_formed(r: Result<TetMesh>) -> std::result::Result<(), TestCaseError> {
    match r {
        Ok(m) => {
            prop_assert!(m.num_tets() > 0);
            prop_assert!(
                m.positions()
                    .iter()
                    .all(|p| p.iter().all(|c| c.is_finite()))
            );
        }
        Err(e) => prop_assert!(!e.to_string().is_empty()),
    }
    Ok(())
}

/// Steps `scene` `steps` times: each step keeps the first body's positions
/// finite, or ends the run with an error that says something.
fn steps_stay_finite(scene: &mut Scene, steps: usize) -> std::result::Result<(), TestCaseError> {
    for _ in 0..steps {
        match scene.step(0.01) {
            Ok(_) => prop_assert!(
                scene.bodies[0]
                    .positions()
                    .iter()
                    .all(|x| x.iter().all(|c| c.is_finite()))
            ),
            Err(e) => {
                prop_assert!(!e.to_string().is_empty());
                break;
            }
        }
    }
    Ok(())
}

/// A value in `range` eight times in nine, else a special one.
fn param(range: std::ops::Range<f64>) -> impl Strategy<Value = f64> {
    prop_oneof![
        8 => range,
        1 => prop::sample::select(vec![f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 0.0, -1.0, 1e-300, 1e300, f64::MAX]),
    ]
}

fn sample_mesh() -> TetMesh {
    generate::box_mesh(Vec3::zeros(), v3(1., 1., 1.), [2, 1, 1]).unwrap()
}

proptest! {
    #![proptest_config(seeded(FUZZ_CASES))]

    #[test]
    fn fuzz_msh_ascii(muts in prop::collection::vec(mutation(), 1..4)) {
        let bytes = apply(io::write_msh(&sample_mesh(), false), &muts, true);
        well_formed(parse(&bytes))?;
    }

    #[test]
    fn fuzz_msh_binary(muts in prop::collection::vec(mutation(), 1..4)) {
        let bytes = apply(io::write_msh(&sample_mesh(), true), &muts, false);
        well_formed(parse(&bytes))?;
    }

    #[test]
    fn fuzz_tetgen(muts in prop::collection::vec(mutation(), 1..4), which in 0..2usize) {
        let m = sample_mesh();
        let mut node = format!("{} 3 0 0\n", m.num_vertices());
        for (i, p) in m.positions().iter().enumerate() {
            node += &format!("{} {:e} {:e} {:e}\n", i + 1, p.x, p.y, p.z);
        }
        let mut ele = format!("{} 4 0\n", m.num_tets());
        for (i, t) in m.tets().iter().enumerate() {
            ele += &format!("{} {} {} {} {}\n", i + 1, t[0] + 1, t[1] + 1, t[2] + 1, t[3] + 1);
        }
        let (node, ele) = if which == 0 {
            (String::from_utf8_lossy(&apply(node.into_bytes(), &muts, true)).into_owned(), ele)
        } else {
            (node, String::from_utf8_lossy(&apply(ele.into_bytes(), &muts, true)).into_owned())
        };
        well_formed(io::parse_tetgen(&node, &ele, ValidateOptions::default()))?;
    }

    /// Node blocks in any order, split anywhere: the same mesh.
    #[test]
    fn fuzz_msh_block_order(cuts in prop::collection::vec(1..12usize, 0..4), order in any::<u64>()) {
        let m = sample_mesh();
        let n = m.num_vertices();
        let mut bounds: Vec<usize> = cuts.iter().map(|c| c % n).filter(|&c| c > 0).collect();
        bounds.sort_unstable();
        bounds.dedup();
        bounds.insert(0, 0);
        bounds.push(n);
        let mut blocks: Vec<(Vec<u64>, Vec<Vec3>)> = bounds
            .windows(2)
            .map(|w| ((w[0] as u64 + 1..=w[1] as u64).collect(), m.positions()[w[0]..w[1]].to_vec()))
            .collect();
        // A permutation of the blocks from the drawn number.
        let mut key = order;
        for i in (1..blocks.len()).rev() {
            blocks.swap(i, (key % (i as u64 + 1)) as usize);
            key /= i as u64 + 1;
        }
        let tets: Vec<[u64; 4]> = m.tets().iter().map(|t| t.map(|v| v as u64 + 1)).collect();
        let back = parse(msh_ascii(&blocks, &tets).as_bytes()).unwrap();
        for (a, b) in back.tets().iter().zip(m.tets()) {
            for k in 0..4 {
                prop_assert_eq!(back.positions()[a[k]], m.positions()[b[k]]);
            }
        }
    }

    /// Material, body, contact and LCP settings and tool shapes: each
    /// parameter mostly in its usable range, one time in nine a special value
    /// (NaN, ±∞, 0, −1, tiny, huge). A clear error, or a scene whose steps
    /// stay finite (or end in a clear error).
    #[test]
    fn fuzz_parameters(
        p in (
            (param(500.0..2000.0), param(1e2..1e7), param(-0.5..0.49), param(0.0..20.0)),
            (param(0.0..20.0), param(1e-10..1e-2), param(1e-5..1e-3), param(0.0..1.0)),
            (param(1e-8..1e-4), param(1e-10..1e-3), param(0.1..1.9), param(1e-3..2e-2)),
        ),
        iters in 0..50usize,
    ) {
        let ((d, e, nu, damp), (g, cg_tol, alarm, mu), (pen, lcp_tol, omega, radius)) = p;
        let p = [d, e, nu, damp, g, cg_tol, alarm, mu, pen, lcp_tol, omega, radius];
        let mesh = generate::box_mesh(Vec3::zeros(), v3(0.01, 0.01, 0.01), [1, 1, 1]).unwrap();
        let material = TissueMaterial::new(p[0], p[1], p[2]).with_damping(p[3].abs(), 0.0);
        let mut settings = BodySettings { gravity: Some(v3(0.0, 0.0, -p[4])), ..Default::default() };
        settings.cg.tolerance = p[5];
        settings.cg.max_iterations = iters;
        let contact = ContactSettings {
            alarm_distance: p[6],
            body_friction: p[7],
            penetration_tolerance: p[8],
            lcp: LcpSettings { tolerance: p[9], over_relaxation: p[10], max_iterations: iters, ..Default::default() },
            ..Default::default()
        };
        let tool = RigidTool::new(ToolShape::Sphere { radius: p[11] }, Pose::identity());
        let (Ok(body), Ok(mut scene), Ok(tool)) = (DeformableBody::new(mesh, material, settings), Scene::new(contact), tool) else {
            return Ok(());
        };
        scene.add_body(body);
        scene.add_tool(tool);
        steps_stay_finite(&mut scene, 3)?;
    }
}

proptest! {
    #![proptest_config(seeded(FUZZ_CASES / 5))]

    /// Tool meshes of random triangles over a few points (repeated corners,
    /// open, folded, in several pieces, flat): a clear error, or a tool whose
    /// face search (`ContactSettings::tool_faces`) over a cube pressed under
    /// it keeps every step finite.
    #[test]
    fn fuzz_tool_meshes(
        (points, triangles) in (4..10usize).prop_flat_map(|n| (
            prop::collection::vec((0..4u8, 0..4u8, 0..4u8), n),
            prop::collection::vec(
                (prop::sample::subsequence((0..n as u32).collect::<Vec<_>>(), 3), any::<bool>()),
                4..16,
            ),
        )),
    ) {
        let vertices: Vec<Vec3> = points
            .iter()
            .map(|&(x, y, z)| v3(f64::from(x), f64::from(y), f64::from(z)) * 2.5e-3)
            .collect();
        let indices: Vec<[u32; 3]> = triangles
            .iter()
            .map(|(t, flip)| if *flip { [t[0], t[2], t[1]] } else { [t[0], t[1], t[2]] })
            .collect();
        let Ok(tool) = RigidTool::new(ToolShape::TriMesh { vertices, indices }, Pose::identity()) else {
            return Ok(());
        };
        let mesh = generate::box_mesh(v3(0.0, 0.0, -0.002), v3(0.008, 0.008, 0.004), [2, 2, 2]).unwrap();
        let body = DeformableBody::new(mesh, TissueMaterial::new(1000.0, 3e4, 0.45), BodySettings::default()).unwrap();
        let mut scene = Scene::new(ContactSettings { tool_faces: true, ..Default::default() }).unwrap();
        scene.add_body(body);
        scene.add_tool(tool);
        steps_stay_finite(&mut scene, 2)?;
    }
}

proptest! {
    #![proptest_config(seeded(256))]

    /// Nested dissection of random meshes (boxes with tetrahedra dropped, so
    /// parts fall apart, and isolated nodes after them) is a permutation, and
    /// the symbolic factor built on it has the nonzeros its cost count says.
    #[test]
    fn nested_dissection_of_random_meshes_is_a_permutation(
        cells in (1usize..7, 1usize..7, 1usize..7),
        keep in 0.3f64..1.0,
        seed in any::<u64>(),
        isolated in 0usize..80,
    ) {
        let mesh = generate::box_mesh(
            v3(0.0, 0.0, 0.0),
            v3(1.0, 1.0, 1.0),
            [cells.0, cells.1, cells.2],
        )
        .unwrap();
        // Drop tetrahedra by a hash of their index and the seed.
        let tets: Vec<[usize; 4]> = mesh
            .tets()
            .iter()
            .enumerate()
            .filter(|(i, _)| {
                let h = (*i as u64 ^ seed).wrapping_mul(0x9E37_79B9_7F4A_7C15);
                ((h >> 11) as f64 / (1u64 << 53) as f64) < keep
            })
            .map(|(_, t)| *t)
            .collect();
        let n = mesh.num_vertices() + isolated;
        let pattern = BlockPattern::new(n, &tets);
        let p = ordering::nested_dissection(&pattern).unwrap();
        let mut seen = vec![false; n];
        for &o in &p.perm {
            prop_assert!(o < n && !std::mem::replace(&mut seen[o], true));
        }
        prop_assert_eq!(p.perm.len(), n);
        for o in 0..n {
            prop_assert_eq!(p.perm[p.iperm[o]], o);
        }
        let sym = LdltSymbolic::with_ordering(&pattern, FillOrdering::NestedDissection).unwrap();
        prop_assert_eq!(ordering::factor_cost(&pattern, &p).0, sym.nnz_blocks());
    }
}
