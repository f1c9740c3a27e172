//! Replays recorded contact problems through every LCP solver, in the
//! spirit of FCLIB: sweeps and milliseconds to a relative residual of 1e-3,
//! 1e-4 and 1e-6 (`contact::lcp::residual`, the same for every solver), from
//! each problem's recorded warm start.
//!
//! ```text
//! cargo bench --bench lcp                         # the problems in benches/data
//! cargo bench --bench lcp -- --dir DIR            # and every *.lcp in DIR
//! cargo bench --bench lcp -- --dir benches/data/faces   # a problem with face contacts
//! cargo bench --bench lcp -- --dir DIR --repeats 5 --limit 2000 --solver subspace
//! cargo bench --bench lcp -- --dir DIR --solver subspace --misses   # and name the misses
//! ```
//!
//! Record problems with `cargo run --release --example cataract -- --headless
//! --record-lcp DIR` (steps with more than 90 contacts by default). The
//! problem in `benches/data/faces` is replayed as recorded, its face rows
//! unshifted (a first pass shifts them: `contact::FACE_ROW_SHIFT`; its
//! `.faces` file lists them). Prints a
//! Markdown table per solver and target: the median and largest sweeps, how
//! many problems met the target within 100 sweeps and at all (within
//! `--limit`), and the median and range of the milliseconds per problem
//! (the median over `--repeats` runs of each) and their sum over the
//! problems (the time to solve each once: what the large problems cost,
//! which the median over problems of very different sizes hides).

use std::path::{Path, PathBuf};
use std::time::Instant;

use bevy_soft_tissue::contact::lcp::{ContactProblem, LcpSettings, LcpSolver};

const SOLVERS: [(&str, LcpSolver); 4] = [
    ("pgs", LcpSolver::ProjectedGaussSeidel),
    ("block", LcpSolver::BlockGaussSeidel),
    ("nncg", LcpSolver::Nncg),
    ("subspace", LcpSolver::Subspace),
];
const TARGETS: [f64; 3] = [1e-3, 1e-4, 1e-6];

struct Args {
    dirs: Vec<PathBuf>,
    solvers: Vec<String>,
    repeats: usize,
    limit: usize,
    /// Print the problems that miss a target within 100 sweeps.
    misses: bool,
}

fn parse() -> Result<Args, String> {
    let mut a = Args {
        dirs: vec![Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/data")],
        solvers: Vec::new(),
        repeats: 3,
        limit: 2000,
        misses: false,
    };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        let mut value = |name: &str| it.next().ok_or(format!("{name} needs a value"));
        match arg.as_str() {
            "--dir" => a.dirs.push(value("--dir")?.into()),
            "--solver" => a.solvers.push(value("--solver")?),
            "--repeats" => {
                a.repeats = value("--repeats")?
                    .parse::<usize>()
                    .map_err(|e| e.to_string())?
                    .max(1)
            }
            "--limit" => {
                a.limit = value("--limit")?
                    .parse::<usize>()
                    .map_err(|e| e.to_string())?
                    .max(1)
            }
            "--misses" => a.misses = true,
            // What `cargo bench` passes to every bench binary.
            "--bench" => {}
            other => return Err(format!("unknown argument `{other}`")),
        }
    }
    Ok(a)
}

fn load(dirs: &[PathBuf]) -> Result<Vec<(String, ContactProblem)>, String> {
    let mut files = Vec::new();
    for d in dirs {
        let entries = std::fs::read_dir(d).map_err(|e| format!("{}: {e}", d.display()))?;
        for e in entries.flatten() {
            let p = e.path();
            if p.extension().is_some_and(|x| x == "lcp") {
                files.push(p);
            }
        }
    }
    files.sort();
    files
        .into_iter()
        .map(|p| {
            let name = p
                .file_name()
                .unwrap_or_default()
                .to_string_lossy()
                .into_owned();
            ContactProblem::read(&p)
                .map(|q| (name, q))
                .map_err(|e| e.to_string())
        })
        .collect()
}

struct Run {
    sweeps: usize,
    residual: f64,
    met: bool,
    ms: f64,
}

impl Run {
    /// Whether the solve met its target within 100 sweeps (the issue's target).
    fn within_100(&self) -> bool {
        self.met && self.sweeps <= 100
    }
}

fn run(p: &ContactProblem, solver: LcpSolver, target: f64, args: &Args) -> Run {
    let settings = LcpSettings {
        solver,
        max_iterations: args.limit,
        residual_tolerance: target,
        tolerance: 0.0,
        displacement_tolerance: -1.0,
        ..Default::default()
    };
    let mut times = Vec::with_capacity(args.repeats);
    let mut last = None;
    for _ in 0..args.repeats {
        let t0 = Instant::now();
        let out = p.solve(&settings).expect("a validated problem");
        times.push(t0.elapsed().as_secs_f64() * 1e3);
        last = Some(out.2);
    }
    times.sort_by(f64::total_cmp);
    let r = last.expect("at least one repeat");
    Run {
        sweeps: r.iterations,
        residual: r.residual,
        met: r.residual <= target,
        ms: times[times.len() / 2],
    }
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        f64::NAN
    } else {
        v[v.len() / 2]
    }
}

fn main() {
    let args = match parse() {
        Ok(a) => a,
        Err(e) => {
            eprintln!("lcp bench: {e}");
            std::process::exit(2);
        }
    };
    let problems = match load(&args.dirs) {
        Ok(p) if !p.is_empty() => p,
        Ok(_) => {
            eprintln!("lcp bench: no *.lcp problems found");
            std::process::exit(2);
        }
        Err(e) => {
            eprintln!("lcp bench: {e}");
            std::process::exit(2);
        }
    };
    let contacts: Vec<usize> = problems.iter().map(|(_, p)| p.num_contacts()).collect();
    println!(
        "{} problems, {}..{} contacts, {}..{} rows; {} repeats, sweep limit {}",
        problems.len(),
        contacts.iter().min().unwrap_or(&0),
        contacts.iter().max().unwrap_or(&0),
        problems.iter().map(|(_, p)| p.m()).min().unwrap_or(0),
        problems.iter().map(|(_, p)| p.m()).max().unwrap_or(0),
        args.repeats,
        args.limit
    );
    if problems.len() <= 4 {
        for (name, p) in &problems {
            println!("  {name}: {} contacts, {} rows", p.num_contacts(), p.m());
        }
    }
    println!();
    println!(
        "| solver | target | sweeps median | sweeps max | met in ≤ 100 sweeps | met | ms median | ms range | ms total |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for (name, solver) in SOLVERS {
        if !args.solvers.is_empty() && !args.solvers.iter().any(|s| s == name) {
            continue;
        }
        for target in TARGETS {
            let runs: Vec<Run> = problems
                .iter()
                .map(|(_, p)| run(p, solver, target, &args))
                .collect();
            let mut sweeps: Vec<f64> = runs.iter().map(|r| r.sweeps as f64).collect();
            let mut ms: Vec<f64> = runs.iter().map(|r| r.ms).collect();
            let (lo, hi) = ms
                .iter()
                .fold((f64::INFINITY, 0.0f64), |(a, b), &x| (a.min(x), b.max(x)));
            let total: f64 = ms.iter().sum();
            let within = runs.iter().filter(|r| r.within_100()).count();
            let met = runs.iter().filter(|r| r.met).count();
            println!(
                "| {name} | {target:.0e} | {:.0} | {:.0} | {within}/{} | {met}/{} | {:.2} | {lo:.2}–{hi:.2} | {total:.1} |",
                median(&mut sweeps),
                sweeps.iter().copied().fold(0.0, f64::max),
                runs.len(),
                runs.len(),
                median(&mut ms),
            );
            if args.misses {
                for ((file, p), r) in problems.iter().zip(&runs) {
                    if !r.within_100() {
                        println!(
                            "  miss: {file} ({} contacts): {} sweeps, residual {:.1e}",
                            p.num_contacts(),
                            r.sweeps,
                            r.residual
                        );
                    }
                }
            }
        }
    }
}
