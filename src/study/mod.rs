//! What accuracy costs in time: the accuracy study.
//!
//! A study runs one scene ([`StudyScene`]) with a reference configuration
//! and a list of [`Variant`]s, step by step, and compares every variant's
//! node positions with the reference's at every step. Each variant gets its
//! error over time, its time per step and per phase, its CG iterations, its
//! penetration and its energy ([`VariantRun`], summarized in
//! [`VariantSummary`]). The scene is any builder: the paper's experiment
//! ([`cases::LensThroughHole`]), the cataract push
//! ([`cases::CataractPush`]), or a user's own.
//!
//! Beside the trade-off the study measures what the paper's Fig. 4 shows
//! (compliance build time against contacts, [`compliance`]), how cost grows
//! with the mesh ([`growth`]), and two validations against closed forms
//! ([`validation`]: a cantilever against Euler–Bernoulli, Hertz contact).
//! [`full::run`] runs all of it and [`output`] writes CSV tables and a
//! report; with the `study` feature, `plots` draws the figures.
//!
//! ```no_run
//! use bevy_soft_tissue::study::{self, cases::LensThroughHole, variants};
//! # fn main() -> bevy_soft_tissue::error::Result<()> {
//! use bevy_soft_tissue::study::StudyScene;
//! let scene = LensThroughHole { cells: 8, steps: 40, ..Default::default() };
//! let (body, contact) = (scene.body_settings(), scene.contact_settings());
//! let list = variants::standard(body, contact, &variants::Options::default());
//! let reference = variants::reference(body, contact);
//! let result = study::run_case(&scene, &reference, &list, &mut |_| {})?;
//! for s in result.summaries() {
//!     println!("{} {:.2e} m at {:.2} ms/step", s.variant, s.rms_error_mean, s.ms_per_step);
//! }
//! # Ok(())
//! # }
//! ```
//!
//! Nothing here asserts timing: times are measured and reported; the errors
//! do not depend on them, except for the `async` variants, whose factor
//! arrives when the worker thread is done (which is why they run several
//! times, and why [`crate::solver::PreconditionerKind::AsyncLagged`]
//! exists), and for a run that its time budget stops, far longer than the
//! reference's ([`run_case_within`]), which says so.

pub mod cases;
pub mod compliance;
pub mod full;
pub mod growth;
pub mod output;
#[cfg(feature = "study")]
pub mod plots;
pub mod validation;
pub mod variants;

use std::time::{Duration, Instant};

use crate::body::BodySettings;
use crate::contact::{ContactSettings, ContactSolver, PassKind};
use crate::error::{Result, SoftTissueError};
use crate::math::Vec3;
use crate::scene::Scene;

/// A scene the study can run: built fresh for each variant, then driven step
/// by step (tools moved, nodes driven) before each step.
pub trait StudyScene {
    /// Name used in reports.
    fn name(&self) -> &str;
    /// Step size, seconds.
    fn timestep(&self) -> f64;
    /// Number of steps.
    fn steps(&self) -> usize;
    /// A length that errors are compared with (the smallest semi-axis of the
    /// lens, say), metres.
    fn length_scale(&self) -> f64;
    /// The scene's own body settings (gravity, damping, …), which the
    /// variants change only in their solver knobs ([`variants`]).
    fn body_settings(&self) -> BodySettings {
        BodySettings::default()
    }
    /// The scene's own contact settings (alarm distance, passes, …), which
    /// the variants change only in their knobs.
    fn contact_settings(&self) -> ContactSettings {
        ContactSettings::default()
    }
    /// Builds the scene with the bodies' and the contacts' settings.
    fn build(&self, body: BodySettings, contact: ContactSettings) -> Result<Scene>;
    /// Moves tools and driven nodes to where they are at the end of step
    /// `step` (0-based), before it runs.
    fn drive(&self, scene: &mut Scene, step: usize) -> Result<()>;
}

/// How a variant is paced against the wall clock.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Pacing {
    /// Steps run back to back (the background factorization gets the
    /// least time per step).
    #[default]
    BackToBack,
    /// Each step starts `h` after the previous one started, as in an
    /// application at real time (idle time lets the worker catch up).
    RealTime,
}

/// One configuration to compare with the reference.
#[derive(Debug, Clone, PartialEq)]
pub struct Variant {
    /// Name (the `variant` column of the tables).
    pub name: String,
    /// Settings of every body.
    pub body: BodySettings,
    /// Contact settings.
    pub contact: ContactSettings,
    /// Pacing.
    pub pacing: Pacing,
    /// Runs of this variant (results depend on thread timing when > 1 is
    /// useful: the `async` variants); the summary reports their spread.
    pub repeats: usize,
}

impl Variant {
    /// A variant run once, back to back.
    pub fn new(name: impl Into<String>, body: BodySettings, contact: ContactSettings) -> Self {
        Self {
            name: name.into(),
            body,
            contact,
            pacing: Pacing::BackToBack,
            repeats: 1,
        }
    }
}

/// What one step of one run measured.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct StepRecord {
    /// Step index (0-based).
    pub step: usize,
    /// RMS over all nodes of all bodies of the distance to the reference, metres.
    pub rms_error: f64,
    /// Largest node distance to the reference, metres.
    pub max_error: f64,
    /// Wall time of the step, milliseconds (pacing idle time excluded).
    pub ms: f64,
    /// Per phase, milliseconds: assemble, factorize, CG, detect, compliance, LCP, correct.
    pub phase_ms: [f64; 7],
    /// CG iterations summed over bodies.
    pub cg_iterations: usize,
    /// Whether every body's CG converged.
    pub cg_converged: bool,
    /// Contacts of the step.
    pub contacts: usize,
    /// Deepest penetration left by the step (a detection of its own over the
    /// step's final positions, not timed), metres.
    pub max_penetration: f64,
    /// Bodies whose lagging factor the contact correction refreshed
    /// ([`crate::contact::ContactSettings::consistency_tolerance`]).
    pub consistency_refactors: usize,
    /// Kinetic plus elastic energy of all bodies, joules.
    pub energy: f64,
}

/// Names of [`StepRecord::phase_ms`].
pub const PHASES: [&str; 7] = [
    "assemble",
    "factorize",
    "cg",
    "detect",
    "compliance",
    "lcp",
    "correct",
];

/// One run of a variant.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct VariantRun {
    /// Variant name.
    pub variant: String,
    /// Repeat index.
    pub repeat: usize,
    /// Per step (as many as ran; fewer when the run failed or was stopped).
    pub steps: Vec<StepRecord>,
    /// The error that stopped the run, if any.
    pub failure: Option<String>,
    /// Why the run stopped before its last step without failing: its steps
    /// took longer than its time budget (see [`run_case_within`]). Its
    /// figures are over the steps it ran.
    pub stopped: Option<String>,
}

/// Summary of a variant over its runs.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct VariantSummary {
    /// Variant name.
    pub variant: String,
    /// Runs.
    pub runs: usize,
    /// Mean wall time per step, milliseconds (mean over runs).
    pub ms_per_step: f64,
    /// Smallest and largest of the runs' mean time per step.
    pub ms_range: (f64, f64),
    /// Mean time per phase, milliseconds (see [`PHASES`]).
    pub phase_ms: [f64; 7],
    /// Mean over steps of the RMS error, metres (mean over runs).
    pub rms_error_mean: f64,
    /// Smallest and largest of the runs' mean RMS error.
    pub rms_error_range: (f64, f64),
    /// Largest RMS error of any step, metres.
    pub rms_error_max: f64,
    /// Largest node error of any step, metres.
    pub max_node_error: f64,
    /// Deepest penetration of any step, metres.
    pub max_penetration: f64,
    /// Mean CG iterations per step.
    pub cg_iterations: f64,
    /// Steps whose CG did not converge.
    pub cg_unconverged: usize,
    /// Consistency refactorizations per run (mean over runs).
    pub consistency_refactors: f64,
    /// Energy at the last step, joules (mean over runs).
    pub final_energy: f64,
    /// The first failure of any run.
    pub failure: Option<String>,
    /// Why the first run that was stopped early stopped (see
    /// [`VariantRun::stopped`]); its means are over the steps it ran.
    pub stopped: Option<String>,
}

/// Runs of the reference and of every variant of one scene.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct CaseResult {
    /// Scene name.
    pub scene: String,
    /// Step size, seconds.
    pub timestep: f64,
    /// The scene's length scale, metres.
    pub length_scale: f64,
    /// Node count over all bodies.
    pub nodes: usize,
    /// The reference run (errors are zero by definition).
    pub reference: VariantRun,
    /// Every run of every variant, in order.
    pub runs: Vec<VariantRun>,
}

impl CaseResult {
    /// One summary per variant, in the order they ran.
    pub fn summaries(&self) -> Vec<VariantSummary> {
        let mut names: Vec<&str> = Vec::new();
        for r in &self.runs {
            if !names.contains(&r.variant.as_str()) {
                names.push(&r.variant);
            }
        }
        names
            .iter()
            .map(|n| summarize(self.runs.iter().filter(|r| r.variant == *n)))
            .collect()
    }

    /// The summary of the variant named `name`.
    pub fn summary(&self, name: &str) -> Option<VariantSummary> {
        self.summaries().into_iter().find(|s| s.variant == name)
    }
}

fn mean(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    if n == 0 { f64::NAN } else { s / n as f64 }
}

fn summarize<'a>(runs: impl Iterator<Item = &'a VariantRun>) -> VariantSummary {
    let runs: Vec<&VariantRun> = runs.collect();
    let mut s = VariantSummary {
        variant: runs.first().map(|r| r.variant.clone()).unwrap_or_default(),
        runs: runs.len(),
        ms_range: (f64::INFINITY, f64::NEG_INFINITY),
        rms_error_range: (f64::INFINITY, f64::NEG_INFINITY),
        ..Default::default()
    };
    let (mut ms, mut rms, mut energy) = (Vec::new(), Vec::new(), Vec::new());
    let mut steps = 0usize;
    let mut cg = 0usize;
    for r in &runs {
        if s.failure.is_none() {
            s.failure = r.failure.clone();
        }
        if s.stopped.is_none() {
            s.stopped = r.stopped.clone();
        }
        let m = mean(r.steps.iter().map(|x| x.ms));
        let e = mean(r.steps.iter().map(|x| x.rms_error));
        ms.push(m);
        rms.push(e);
        s.ms_range = (s.ms_range.0.min(m), s.ms_range.1.max(m));
        s.rms_error_range = (s.rms_error_range.0.min(e), s.rms_error_range.1.max(e));
        if let Some(last) = r.steps.last() {
            energy.push(last.energy);
        }
        for x in &r.steps {
            s.rms_error_max = s.rms_error_max.max(x.rms_error);
            s.max_node_error = s.max_node_error.max(x.max_error);
            s.max_penetration = s.max_penetration.max(x.max_penetration);
            s.cg_unconverged += usize::from(!x.cg_converged);
            s.consistency_refactors += x.consistency_refactors as f64;
            cg += x.cg_iterations;
            for (a, b) in s.phase_ms.iter_mut().zip(x.phase_ms) {
                *a += b;
            }
        }
        steps += r.steps.len();
    }
    for a in &mut s.phase_ms {
        *a /= steps.max(1) as f64;
    }
    s.cg_iterations = cg as f64 / steps.max(1) as f64;
    s.consistency_refactors /= runs.len().max(1) as f64;
    s.ms_per_step = mean(ms.into_iter());
    s.rms_error_mean = mean(rms.into_iter());
    s.final_energy = mean(energy.into_iter());
    s
}

/// What [`run_case`] and [`full::run`] report as they go.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Progress<'a> {
    /// A run or a stage starts: its label, repeat, and the steps (or items)
    /// it will take.
    Start {
        /// Variant name (`reference` for the reference), or the stage.
        label: &'a str,
        /// Repeat index.
        repeat: usize,
        /// Steps.
        steps: usize,
    },
    /// A step (or item) of the current run or stage is done.
    Step,
}

/// Node positions of all bodies, concatenated.
fn positions(scene: &Scene, out: &mut Vec<Vec3>) {
    out.clear();
    for b in &scene.bodies {
        out.extend_from_slice(b.positions());
    }
}

/// Runs one configuration; `reference` holds the reference's positions per
/// step (empty for the reference run itself, which then fills `record`).
/// The run stops after the step at which its steps' wall time, summed,
/// exceeds `budget` (milliseconds, see [`run_case_within`]).
fn run_one(
    scene: &dyn StudyScene,
    variant: &Variant,
    repeat: usize,
    reference: &[Vec<Vec3>],
    mut record: Option<&mut Vec<Vec<Vec3>>>,
    budget: Option<Budget>,
    progress: &mut dyn FnMut(Progress),
) -> VariantRun {
    let mut run = VariantRun {
        variant: variant.name.clone(),
        repeat,
        ..Default::default()
    };
    let steps = scene.steps();
    progress(Progress::Start {
        label: &variant.name,
        repeat,
        steps,
    });
    let h = scene.timestep();
    let mut sc = match scene.build(variant.body, variant.contact) {
        Ok(s) => s,
        Err(e) => {
            run.failure = Some(e.to_string());
            return run;
        }
    };
    let mut x = Vec::new();
    let mut next = Instant::now();
    let mut checker = match ContactSolver::new(variant.contact) {
        Ok(c) => c,
        Err(e) => {
            run.failure = Some(e.to_string());
            return run;
        }
    };
    let mut stepped_ms = 0.0;
    for step in 0..steps {
        if variant.pacing == Pacing::RealTime {
            let now = Instant::now();
            if next > now {
                std::thread::sleep(next - now);
            }
            next = Instant::now() + Duration::from_secs_f64(h);
        }
        let t0 = Instant::now();
        let out = scene.drive(&mut sc, step).and_then(|_| sc.step(h));
        let ms = t0.elapsed().as_secs_f64() * 1e3;
        let report = match out {
            Ok(r) => r,
            Err(e) => {
                run.failure = Some(format!("step {step}: {e}"));
                break;
            }
        };
        positions(&sc, &mut x);
        if x.iter().any(|p| !p.iter().all(|c| c.is_finite())) {
            run.failure = Some(format!("step {step}: non-finite positions"));
            break;
        }
        let mut rec = StepRecord {
            step,
            ms,
            cg_converged: true,
            contacts: report.contacts,
            consistency_refactors: report.consistency_refactors,
            ..Default::default()
        };
        if sc.can_touch() {
            if let Err(e) = checker.detect(&sc.bodies, &sc.tools, h, PassKind::First) {
                run.failure = Some(format!("step {step}: {e}"));
                break;
            }
            rec.max_penetration = checker
                .contacts()
                .iter()
                .map(|c| -c.gap)
                .fold(0.0, f64::max);
        }
        if let Some(r) = reference.get(step) {
            let mut sum = 0.0;
            for (a, b) in x.iter().zip(r) {
                let d = (a - b).norm();
                sum += d * d;
                rec.max_error = rec.max_error.max(d);
            }
            rec.rms_error = (sum / x.len().max(1) as f64).sqrt();
        }
        for b in &sc.bodies {
            let r = b.report();
            rec.cg_iterations += r.cg.iterations;
            rec.cg_converged &= r.cg.converged;
            rec.phase_ms[0] += r.timings.assemble * 1e3;
            rec.phase_ms[1] += r.timings.factorize * 1e3;
            rec.phase_ms[2] += r.timings.cg_total * 1e3;
            rec.energy += b.kinetic_energy() + b.elastic_energy();
        }
        rec.phase_ms[3] = report.detect * 1e3;
        rec.phase_ms[4] = report.compliance * 1e3;
        rec.phase_ms[5] = report.lcp_seconds * 1e3;
        rec.phase_ms[6] = report.correct * 1e3;
        run.steps.push(rec);
        if let Some(rec) = record.as_deref_mut() {
            rec.push(x.clone());
        }
        progress(Progress::Step);
        stepped_ms += ms;
        if let Some(b) = budget
            && stepped_ms > b.factor * b.reference_ms
            && step + 1 < steps
        {
            run.stopped = Some(format!(
                "stopped after {} of {steps} steps: they took {:.1} s, over {}× the \
                 reference's {:.1} s",
                step + 1,
                stepped_ms * 1e-3,
                b.factor,
                b.reference_ms * 1e-3
            ));
            break;
        }
    }
    run
}

/// A variant run's time budget: `factor` times the reference run's
/// stepping time, `reference_ms` (milliseconds).
#[derive(Debug, Clone, Copy)]
struct Budget {
    factor: f64,
    reference_ms: f64,
}

/// How long [`run_case`] lets a variant run step, as a multiple of the
/// reference run's stepping time (the steps' wall time, summed, pacing idle
/// time excluded). The reference factorizes every step and solves its LCPs
/// to 10⁻¹⁰; no standard variant has taken more than 2.8 times as long per
/// step as its rerun (`exact`) in the study kept in `docs/accuracy-study`
/// (`rest_precomputed`, 109 ms against 39.6). A
/// variant whose approximation leaves its contact problems unsolvable to
/// their tolerance (`rest_precomputed` on the paper's experiment, once in
/// about twenty full studies, whose LCP solves then ran to their sweep limit
/// with dense Newton steps over most of the 1 830 rows: stopped by hand
/// after 20 minutes) stops at this budget instead of holding up the study.
pub const DEFAULT_TIME_FACTOR: f64 = 10.0;

/// Runs the reference, then every variant (each `repeats` times), and
/// compares each step's node positions with the reference's. A variant that
/// fails (an error, non-finite positions) is recorded with its failure and
/// the study goes on; a failing reference is an error. Each variant run
/// has [`DEFAULT_TIME_FACTOR`] times the reference's stepping time (see
/// [`run_case_within`]).
pub fn run_case(
    scene: &dyn StudyScene,
    reference: &Variant,
    variants: &[Variant],
    progress: &mut dyn FnMut(Progress),
) -> Result<CaseResult> {
    run_case_within(scene, reference, variants, DEFAULT_TIME_FACTOR, progress)
}

/// [`run_case`] with each variant run's time budget `time_factor` times the
/// reference run's stepping time (the steps' wall time, summed, pacing idle
/// time excluded; `f64::INFINITY`: no budget). A run whose steps have taken
/// longer stops after the step it is in, and says so in
/// [`VariantRun::stopped`] (its figures are over the steps it ran, and the
/// study goes on); a budget cannot cut a step short. An error if
/// `time_factor` is negative or NaN.
pub fn run_case_within(
    scene: &dyn StudyScene,
    reference: &Variant,
    variants: &[Variant],
    time_factor: f64,
    progress: &mut dyn FnMut(Progress),
) -> Result<CaseResult> {
    if time_factor.is_nan() || time_factor < 0.0 {
        return Err(SoftTissueError::InvalidParameter {
            name: "time_factor",
            value: time_factor,
            reason: "a variant's time budget is a multiple (≥ 0) of the reference's time",
        });
    }
    let mut ref_x = Vec::with_capacity(scene.steps());
    let reference_run = run_one(scene, reference, 0, &[], Some(&mut ref_x), None, progress);
    if let Some(f) = &reference_run.failure {
        return Err(SoftTissueError::Study(format!(
            "the reference run of {} failed: {f}",
            scene.name()
        )));
    }
    let reference_ms: f64 = reference_run.steps.iter().map(|x| x.ms).sum();
    let budget = time_factor.is_finite().then_some(Budget {
        factor: time_factor,
        reference_ms,
    });
    let nodes = ref_x.first().map_or(0, Vec::len);
    let mut runs = Vec::new();
    for v in variants {
        for repeat in 0..v.repeats.max(1) {
            runs.push(run_one(scene, v, repeat, &ref_x, None, budget, progress));
        }
    }
    Ok(CaseResult {
        scene: scene.name().to_string(),
        timestep: scene.timestep(),
        length_scale: scene.length_scale(),
        nodes,
        reference: reference_run,
        runs,
    })
}

/// Least-squares slope and intercept of `ln y` against `ln x` (the exponent
/// `p` of `y ≈ c xᵖ`), over the pairs with both positive and finite.
pub fn fit_power_law(points: &[(f64, f64)]) -> Option<(f64, f64)> {
    let pts: Vec<(f64, f64)> = points
        .iter()
        .filter(|(x, y)| *x > 0.0 && *y > 0.0 && x.is_finite() && y.is_finite())
        .map(|(x, y)| (x.ln(), y.ln()))
        .collect();
    if pts.len() < 2 {
        return None;
    }
    let n = pts.len() as f64;
    let mx = pts.iter().map(|p| p.0).sum::<f64>() / n;
    let my = pts.iter().map(|p| p.1).sum::<f64>() / n;
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    if sxx <= 0.0 {
        return None;
    }
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let slope = sxy / sxx;
    Some((slope, (my - slope * mx).exp()))
}

/// Indices of the Pareto front of `(cost, error)` points: those no other
/// point beats in both (lower is better), sorted by cost.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<usize> {
    let mut idx: Vec<usize> = (0..points.len())
        .filter(|&i| points[i].0.is_finite() && points[i].1.is_finite())
        .collect();
    idx.sort_by(|&a, &b| {
        points[a]
            .0
            .total_cmp(&points[b].0)
            .then(points[a].1.total_cmp(&points[b].1))
    });
    let mut front = Vec::new();
    let mut best = f64::INFINITY;
    for i in idx {
        if points[i].1 < best {
            best = points[i].1;
            front.push(i);
        }
    }
    front
}

/// Penetration above which a variant is not a valid choice: kept off the
/// Pareto front (and drawn hollow), metres.
pub const PARETO_MAX_PENETRATION: f64 = 1e-5;

/// The knee of a Pareto front of `(cost, error)` points, both on log
/// scales: the front point farthest from the line through the front's
/// ends (where buying more accuracy starts to cost much more time).
pub fn knee(points: &[(f64, f64)], front: &[usize]) -> Option<usize> {
    if front.len() < 3 {
        return front.first().copied();
    }
    let l = |i: usize| (points[i].0.ln(), points[i].1.max(1e-300).ln());
    let (a, b) = (l(front[0]), l(front[front.len() - 1]));
    let (dx, dy) = (b.0 - a.0, b.1 - a.1);
    let norm = (dx * dx + dy * dy).sqrt().max(1e-300);
    front.iter().copied().max_by(|&i, &j| {
        let d = |k: usize| {
            let p = l(k);
            ((p.0 - a.0) * dy - (p.1 - a.1) * dx).abs() / norm
        };
        d(i).total_cmp(&d(j))
    })
}
