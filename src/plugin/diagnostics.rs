//! Per-step diagnostics: a resource with the last step's numbers and effect
//! counters, mirrored into Bevy's `DiagnosticsStore`.

use bevy::diagnostic::{Diagnostic, DiagnosticPath, Diagnostics, RegisterDiagnostic};
use bevy::ecs::intern::Interned;
use bevy::ecs::schedule::ScheduleLabel;
use bevy::prelude::*;

use bevy::platform::time::Instant;

/// Numbers of the last step (times in ms) and counters of work done since start.
///
/// The counters let a test show that an effect the scene does not use costs
/// nothing: `detect_runs`, `compliance_builds`, `lcp_solves`, `friction_rows`,
/// `damping_bodies`, `gravity_bodies` and `gpu_dispatches` stay at zero.
#[derive(Resource, Reflect, Debug, Clone, Default, PartialEq)]
#[reflect(Resource)]
pub struct SoftTissueDiagnostics {
    /// Steps run.
    pub steps: u64,
    /// Assembly, all bodies, ms.
    pub assemble_ms: f64,
    /// Preconditioner update on the stepping thread, ms.
    pub factorize_ms: f64,
    /// Conjugate gradient and integration, ms.
    pub free_motion_ms: f64,
    /// Detection, ms.
    pub detect_ms: f64,
    /// Compliance, ms.
    pub compliance_ms: f64,
    /// LCP, ms.
    pub lcp_ms: f64,
    /// Correction (all passes), ms.
    pub correct_ms: f64,
    /// Consistency rescues: a factor of the step's matrix made on the
    /// stepping thread or waited for
    /// ([`crate::contact::ContactReport::rescue`]), ms.
    pub rescue_ms: f64,
    /// Wall-clock time of the whole step, ms: from the start of the
    /// [`SoftTissueSystems::Assemble`](super::SoftTissueSystems::Assemble)
    /// set to the end of the
    /// [`SoftTissueSystems::Sync`](super::SoftTissueSystems::Sync) set,
    /// every system of the pipeline and the scheduling between them.
    /// [`Self::step_ms`] sums the phases' own timers; the difference is what
    /// no phase times (settings, components, the scheduler).
    pub pipeline_ms: f64,
    /// When this step's pipeline started.
    #[reflect(ignore)]
    started: Option<Instant>,
    /// CG iterations summed over bodies.
    pub cg_iterations: usize,
    /// Bodies whose CG did not converge.
    pub cg_unconverged: usize,
    /// Oldest factor in use, steps.
    pub factor_age: u64,
    /// Factorizations swapped in (summed over bodies, since creation).
    pub refreshes: u64,
    /// Contacts (first pass).
    pub contacts: usize,
    /// LCP residual (max of complementarity and friction), metres.
    pub lcp_residual: f64,
    /// LCP sweeps (last pass).
    pub lcp_iterations: usize,
    /// LCP sweeps of the first pass.
    pub lcp_first_iterations: usize,
    /// Relative residual of the first pass's LCP answer
    /// ([`crate::contact::lcp::residual`]), dimensionless.
    pub lcp_relative_residual: f64,
    /// Counter: LCP solves that ran to their sweep limit unconverged.
    pub lcp_capped: u64,
    /// Contact passes run.
    pub contact_passes: usize,
    /// Node columns (or full solves) the compliance solved on the stepping
    /// thread this step, all passes ([`crate::contact::ContactReport::solves`]).
    pub compliance_solves: usize,
    /// Gram blocks the compliance computed on the stepping thread this step.
    pub gram_blocks: usize,
    /// Counter: lagging factors refreshed by the contact phase because a
    /// correction strayed from the matrix
    /// ([`crate::contact::ContactReport::consistency_refactors`]).
    pub consistency_refactors: u64,
    /// Counter: detection runs.
    pub detect_runs: u64,
    /// Counter: compliance builds.
    pub compliance_builds: u64,
    /// Counter: LCP solves.
    pub lcp_solves: u64,
    /// Counter: friction rows built.
    pub friction_rows: usize,
    /// Counter: body assemblies with damping terms.
    pub damping_bodies: usize,
    /// Counter: body assemblies with gravity.
    pub gravity_bodies: usize,
    /// Counter: GPU compute dispatches.
    pub gpu_dispatches: u64,
    /// Time the compliance waited for the GPU this step (part of
    /// `compliance_ms`), ms: what the device's round trip costs the step.
    pub gpu_wait_ms: f64,
    /// Counter: errors reported (each also logged as a warning).
    pub errors: u64,
    /// Counter: bodies that failed a phase and were marked `SoftBodyFailed`.
    pub failed_bodies: u64,
    /// Counter: background factorizations that failed or panicked (the body
    /// kept its factor; see `PreconditionerState::last_error`).
    pub worker_failures: u64,
}

impl SoftTissueDiagnostics {
    /// Resets the per-step numbers (counters keep counting).
    pub fn begin_step(&mut self) {
        self.started = Some(Instant::now());
        self.steps += 1;
        self.assemble_ms = 0.0;
        self.factorize_ms = 0.0;
        self.free_motion_ms = 0.0;
        self.detect_ms = 0.0;
        self.compliance_ms = 0.0;
        self.lcp_ms = 0.0;
        self.correct_ms = 0.0;
        self.rescue_ms = 0.0;
        self.pipeline_ms = 0.0;
        self.cg_iterations = 0;
        self.cg_unconverged = 0;
        self.factor_age = 0;
        self.refreshes = 0;
        self.contacts = 0;
        self.lcp_residual = 0.0;
        self.lcp_iterations = 0;
        self.lcp_first_iterations = 0;
        self.lcp_relative_residual = 0.0;
        self.contact_passes = 0;
        self.compliance_solves = 0;
        self.gram_blocks = 0;
        self.gpu_wait_ms = 0.0;
    }

    /// Total step time, ms: the phases' timers summed (see also
    /// [`Self::pipeline_ms`]).
    pub fn step_ms(&self) -> f64 {
        self.assemble_ms
            + self.factorize_ms
            + self.free_motion_ms
            + self.detect_ms
            + self.compliance_ms
            + self.lcp_ms
            + self.correct_ms
            + self.rescue_ms
    }

    /// Ends the step's wall clock ([`Self::pipeline_ms`]).
    fn end_step(&mut self) {
        if let Some(t0) = self.started.take() {
            self.pipeline_ms = t0.elapsed().as_secs_f64() * 1e3;
        }
    }
}

/// Diagnostic paths registered in Bevy's `DiagnosticsStore`.
pub mod paths {
    use super::DiagnosticPath;
    /// Assembly, ms.
    pub const ASSEMBLE: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/assemble_ms");
    /// Factorize phase, ms.
    pub const FACTORIZE: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/factorize_ms");
    /// Free motion (CG), ms.
    pub const FREE_MOTION: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/free_motion_ms");
    /// Detection, ms.
    pub const DETECT: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/detect_ms");
    /// Compliance, ms.
    pub const COMPLIANCE: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/compliance_ms");
    /// LCP, ms.
    pub const LCP: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/lcp_ms");
    /// Correction, ms.
    pub const CORRECT: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/correct_ms");
    /// Whole step, ms.
    pub const STEP: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/step_ms");
    /// Consistency rescues, ms.
    pub const RESCUE: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/rescue_ms");
    /// The whole pipeline, wall clock, ms.
    pub const PIPELINE: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/pipeline_ms");
    /// CG iterations.
    pub const CG_ITERATIONS: DiagnosticPath =
        DiagnosticPath::const_new("soft_tissue/cg_iterations");
    /// Factor age, steps.
    pub const FACTOR_AGE: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/factor_age");
    /// Contacts.
    pub const CONTACTS: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/contacts");
    /// LCP residual, metres.
    pub const LCP_RESIDUAL: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/lcp_residual");
    /// Time the compliance waited for the GPU, ms.
    pub const GPU_WAIT: DiagnosticPath = DiagnosticPath::const_new("soft_tissue/gpu_wait_ms");
    /// All of them.
    pub const ALL: [DiagnosticPath; 15] = [
        ASSEMBLE,
        FACTORIZE,
        FREE_MOTION,
        DETECT,
        COMPLIANCE,
        LCP,
        CORRECT,
        RESCUE,
        STEP,
        PIPELINE,
        CG_ITERATIONS,
        FACTOR_AGE,
        CONTACTS,
        LCP_RESIDUAL,
        GPU_WAIT,
    ];
}

/// Registers [`SoftTissueDiagnostics`] and the `DiagnosticsStore` entries.
pub struct SoftTissueDiagnosticsPlugin {
    pub(super) schedule: Interned<dyn ScheduleLabel>,
}

impl Plugin for SoftTissueDiagnosticsPlugin {
    fn build(&self, app: &mut App) {
        app.init_resource::<SoftTissueDiagnostics>()
            .register_type::<SoftTissueDiagnostics>();
        for p in paths::ALL {
            app.register_diagnostic(Diagnostic::new(p).with_max_history_length(240));
        }
        app.add_systems(self.schedule, publish.after(end_step_clock));
    }
}

/// Stops the step's wall clock ([`SoftTissueDiagnostics::pipeline_ms`]),
/// after every system of the pipeline.
pub(super) fn end_step_clock(mut diag: ResMut<SoftTissueDiagnostics>) {
    diag.end_step();
}

fn publish(diag: Res<SoftTissueDiagnostics>, mut store: Diagnostics) {
    use paths::*;
    let d = &*diag;
    for (p, v) in [
        (&ASSEMBLE, d.assemble_ms),
        (&FACTORIZE, d.factorize_ms),
        (&FREE_MOTION, d.free_motion_ms),
        (&DETECT, d.detect_ms),
        (&COMPLIANCE, d.compliance_ms),
        (&LCP, d.lcp_ms),
        (&CORRECT, d.correct_ms),
        (&RESCUE, d.rescue_ms),
        (&STEP, d.step_ms()),
        (&PIPELINE, d.pipeline_ms),
        (&CG_ITERATIONS, d.cg_iterations as f64),
        (&FACTOR_AGE, d.factor_age as f64),
        (&CONTACTS, d.contacts as f64),
        (&LCP_RESIDUAL, d.lcp_residual),
        (&GPU_WAIT, d.gpu_wait_ms),
    ] {
        store.add_measurement(p, || v);
    }
}
