//! The cataract scene run without a window and measured: the harness of
//! `examples/cataract.rs --headless` and of the scene test (not library API).

use std::io::Write;
use std::time::Duration;

use super::faces::{FACE_GRID, tool_in_faces};

use bevy::prelude::*;
use bevy_soft_tissue::SoftTissuePlugins;
use bevy_soft_tissue::body::BodySettings;
use bevy_soft_tissue::contact::{ContactSolver, PassKind};
use bevy_soft_tissue::error::{Result, SoftTissueError};
use bevy_soft_tissue::plugin::{
    GpuMode, PreconditionerOverride, SoftBody, SoftTissueConfig, SoftTissueContacts,
    SoftTissueDiagnostics, Tool,
};
use bevy_soft_tissue::scenes::cataract::{self, CataractParams};
use bevy_soft_tissue::scenes::{CataractScenePlugin, Eye, Lens};
use bevy_soft_tissue::solver::PreconditionerKind;

/// The columns of [`HeadlessSummary::median_ms`] and its kin.
pub const PHASES: [&str; 10] = [
    "assemble",
    "factorize",
    "free motion",
    "detect",
    "compliance",
    "lcp",
    "correct",
    "rescue",
    "step",
    "pipeline",
];
/// Index of the pipeline's wall clock in [`PHASES`].
const PIPELINE: usize = 9;

/// Summary of a headless run.
#[derive(Debug, Clone, Default)]
pub struct HeadlessSummary {
    /// Steps run.
    pub steps: usize,
    /// Median milliseconds per phase ([`PHASES`]): assemble, factorize, free
    /// motion, detect, compliance, LCP, correct, consistency rescues, their
    /// sum (`SoftTissueDiagnostics::step_ms`), and the wall clock of the
    /// whole pipeline (`SoftTissueDiagnostics::pipeline_ms`).
    pub median_ms: [f64; 10],
    /// Steps per second from the median wall-clock step (the pipeline's).
    pub steps_per_second: f64,
    /// Median and maximum contacts per step.
    pub contacts: (usize, usize),
    /// Mean CG iterations per step (both bodies).
    pub cg_iterations: f64,
    /// Largest penetration seen at the end of a step, metres: surface vertices
    /// against the vectis and against the other body's surface (lens–sclera),
    /// found by a detection pass over the final positions of every step.
    pub max_penetration: f64,
    /// The part of [`Self::max_penetration`] between the two bodies (lens–sclera), metres.
    pub max_tissue_penetration: f64,
    /// The step that ended with [`Self::max_penetration`] and its contact
    /// passes (a step past the tolerance has run out of passes where it ran
    /// `ContactSettings::max_passes`).
    pub deepest_step: (u64, usize),
    /// How deep the vectis reaches inside the lens's surface triangles between
    /// their vertices, metres: the deepest point of the [`FACE_GRID`] on each triangle
    /// near the vectis, at the end of every step, and at the end of the run
    /// with the number of triangles deeper than [`Self::tolerance`].
    /// [`Self::max_penetration`] tests the vertices only, and so do the
    /// contacts unless `ContactSettings::tool_faces` is on.
    pub vectis_in_faces: (f64, f64, usize),
    /// Penetration tolerance used (1 % of the smallest lens edge), metres.
    pub tolerance: f64,
    /// Lens centre at the start and at the end.
    pub lens_center: (bevy_soft_tissue::math::Vec3, bevy_soft_tissue::math::Vec3),
    /// Elements flat or inverted at the end (`DeformableBody::inverted_elements`)
    /// and the elements there are: the lens's, then all bodies'.
    pub inverted_at_end: [(usize, usize); 2],
    /// Largest speed of the lens's centre of mass (mean node velocity) seen, m/s:
    /// a stability check, as the vectis itself moves at about 1 mm/s.
    pub max_lens_speed: f64,
    /// Median wall-clock step time (the pipeline's) over the steps with 50–90
    /// contacts, and the median of the phases' sum there, if any.
    pub median_ms_50_90: Option<(f64, f64)>,
    /// Mean milliseconds per phase (same order as [`Self::median_ms`]) over the
    /// steps with 50–90 contacts: where the time of those steps goes.
    pub mean_ms_50_90: [f64; 10],
    /// Mean milliseconds per phase over the jam steps (more than 90 contacts).
    pub mean_ms_jam: [f64; 10],
    /// Mean contact passes per jam step.
    pub passes_jam: f64,
    /// Mean contacts per jam step (runs whose jams differ compare by it).
    pub contacts_jam: f64,
    /// Mean node columns and Gram blocks the compliance computed on the
    /// stepping thread per jam step (the rest came from the cache or the
    /// background worker).
    pub columns_jam: (f64, f64),
    /// Mean CG iterations per step (both bodies) over the steps with 50–90 contacts.
    pub cg_iterations_50_90: f64,
    /// Mean LCP sweeps and contact passes per step over the steps with 50–90 contacts.
    pub lcp_50_90: (f64, f64),
    /// Steps with more than 90 contacts (the lens jammed in the slit), and their
    /// median wall-clock step time and median phases' sum in ms, if any.
    pub jam: (usize, Option<(f64, f64)>),
    /// The most contact passes a step ran, and how many steps ran more than
    /// eight (see [`bevy_soft_tissue::contact::ContactSettings::max_passes`]).
    pub max_passes: (usize, usize),
    /// First-pass LCP sweeps: the most in a step, and the mean over the jam
    /// steps (more than 90 contacts).
    pub lcp_sweeps: (usize, f64),
    /// LCP solves that ran to their sweep limit unconverged.
    pub lcp_capped: u64,
    /// The slowest steps (the pipeline's wall clock): the longest, in ms,
    /// with its step (1-based), contacts, contact passes and LCP solves at
    /// the sweep limit; the 99th percentile in ms; and the steps longer than
    /// the time step (those that fall behind real time on their own).
    pub slowest: SlowestStep,
    /// Lagging factors refreshed by the contact phase (consistency checks).
    pub consistency_refactors: u64,
    /// Rescues of lagging factors (consistency checks and CG), all bodies,
    /// and of those the ones that took the worker's factor of the same step
    /// ([`bevy_soft_tissue::solver::PreconditionerStats::rescues_from_worker`]).
    pub rescues: (u64, u64),
    /// The warps the lagging factors were applied with, all bodies: solves
    /// with a warp to choose, and of those the ones that took the body's one
    /// turn and the ones that took none (see
    /// [`bevy_soft_tissue::solver::WarpKind`]).
    pub warps: (u64, u64, u64),
    /// Contact problems written (see [`Recording`]).
    pub recorded: usize,
    /// The GPU compliance's counters at the end, when it ran.
    pub gpu: Option<GpuCounters>,
}

/// The slowest steps of a headless run (see [`HeadlessSummary::slowest`]).
#[derive(Debug, Clone, Copy, Default)]
pub struct SlowestStep {
    /// The longest step, ms.
    pub ms: f64,
    /// Its step number (1-based), contacts, contact passes and LCP solves
    /// that ran to their sweep limit.
    pub step: u64,
    pub contacts: usize,
    pub passes: usize,
    pub capped: u64,
    /// Its milliseconds per phase ([`PHASES`]).
    pub phase_ms: [f64; 10],
    /// The 99th percentile of the step time, ms.
    pub p99_ms: f64,
    /// Steps longer than the time step.
    pub over_h: usize,
}

/// The GPU compliance's counters at the end of a headless run.
#[derive(Debug, Clone, Copy, Default)]
pub struct GpuCounters {
    /// Compute dispatches.
    pub dispatches: u64,
    /// `W` blocks built on the GPU.
    pub builds: u64,
    /// Factors written to the device.
    pub uploads: u64,
    /// Seconds writing factors.
    pub upload_seconds: f64,
    /// Seconds waiting for the device.
    pub wait_seconds: f64,
    /// Seconds in the GPU builds in all.
    pub compute_seconds: f64,
    /// Builds the device timed with timestamps (0 where it has none).
    pub timed: u64,
    /// Device seconds from the first kernel's start to the last one's end,
    /// summed over the timed builds.
    pub span_seconds: f64,
    /// Device seconds of the forward, Gram and contraction kernels.
    pub kernel_seconds: [f64; 3],
    /// The longest path of any build (nodes).
    pub longest_path: usize,
    /// Each build's longest path, summed over the builds.
    pub path_sum: u64,
    /// Builds whose forward solves ran in workgroup memory.
    pub shared_forwards: u64,
    /// Builds whose forward solves walked by pieces.
    pub piece_forwards: u64,
    /// Each build's forward depth (steps along its deepest path), summed.
    pub depth_sum: u64,
}

/// Where and from how many contacts the first-pass contact problems are
/// written ([`bevy_soft_tissue::contact::lcp::ContactProblem`] files named
/// `step00042_c123.lcp`).
#[derive(Debug, Clone)]
pub struct Recording {
    /// The folder (created if missing).
    pub dir: std::path::PathBuf,
    /// Steps with fewer contacts are not written.
    pub min_contacts: usize,
}

/// What a headless run does beyond stepping and measuring.
#[derive(Debug, Clone, Default)]
pub struct HeadlessOptions {
    /// Write the first-pass contact problems (see [`Recording`]).
    pub recording: Option<Recording>,
    /// The pipeline's sets straight in `FixedPostUpdate`
    /// (`SoftTissuePlugins::new(FixedPostUpdate)`, Bevy's multi-threaded
    /// executor) instead of their own schedule.
    pub in_fixed_post_update: bool,
    /// The eye's preconditioner, where it differs from the lens's: a
    /// [`PreconditionerOverride`] on the eye's entity.
    pub eye_preconditioner: Option<PreconditionerKind>,
    /// Write one line per step to this CSV file (see [`TRACE_HEADER`]).
    pub trace: Option<std::path::PathBuf>,
}

/// The columns of [`HeadlessOptions::trace`]: the step; its contacts, contact
/// passes and first-pass LCP sweeps; the consistency refreshes so far; the
/// lens's and the eye's factor ages (steps); the work the step's corrections
/// added beyond the contact forces' (J, `ContactReport::misaccounted_work`);
/// the lens's centre (mm) and mean velocity (mm/s); the vectis's position
/// (mm); the lens's elements flat or inverted (`DeformableBody::inverted_elements`);
/// how deep the vectis reaches inside the lens's surface triangles between their
/// vertices (m, see [`HeadlessSummary::vectis_in_faces`]).
pub const TRACE_HEADER: &str = "step,contacts,passes,lcp_sweeps,consistency_refactors,\
lens_factor_age,eye_factor_age,misaccounted_work_j,lens_x_mm,lens_y_mm,lens_z_mm,\
lens_vx_mm_s,lens_vy_mm_s,lens_vz_mm_s,vectis_x_mm,vectis_y_mm,vectis_z_mm,lens_inverted,\
vectis_in_faces_m";

/// Runs the cataract scene without a window for `steps` fixed steps and
/// measures it. Fails on NaN or on errors reported by the pipeline; the caller
/// compares [`HeadlessSummary::max_penetration`] with its tolerance.
pub fn run_headless(
    params: &CataractParams,
    config: SoftTissueConfig,
    body: BodySettings,
    steps: usize,
) -> Result<HeadlessSummary> {
    run_headless_with(params, config, body, steps, &HeadlessOptions::default())
}

/// [`run_headless`] with the extras of `options`.
pub fn run_headless_with(
    params: &CataractParams,
    config: SoftTissueConfig,
    body: BodySettings,
    steps: usize,
    options: &HeadlessOptions,
) -> Result<HeadlessSummary> {
    let (recording, in_fixed_post_update) =
        (options.recording.as_ref(), options.in_fixed_post_update);
    let h = config.timestep;
    let mut app = App::new();
    // The GPU path needs a render device: a windowless render app (which
    // brings the minimal plugins with it).
    let gpu = config.gpu != GpuMode::Off;
    if gpu {
        #[cfg(feature = "gpu")]
        bevy_soft_tissue::gpu::add_headless_render(&mut app, None)?;
        #[cfg(not(feature = "gpu"))]
        return Err(SoftTissueError::Gpu(
            "GpuMode other than Off needs the `gpu` feature".into(),
        ));
    } else {
        app.add_plugins(MinimalPlugins);
    }
    let plugins = if in_fixed_post_update {
        SoftTissuePlugins::new(FixedPostUpdate)
    } else {
        SoftTissuePlugins::default()
    };
    app.add_plugins(plugins.with_config(config))
        .add_plugins(CataractScenePlugin {
            params: params.clone(),
            body,
        })
        .insert_resource(bevy::time::TimeUpdateStrategy::ManualDuration(
            Duration::from_secs_f64(h),
        ));
    if gpu {
        app.finish();
        app.cleanup();
    }
    app.update();
    if let Some(kind) = options.eye_preconditioner {
        let mut eyes = app.world_mut().query_filtered::<Entity, With<Eye>>();
        let eye = eyes
            .iter(app.world())
            .next()
            .ok_or(SoftTissueError::EmptyMesh("cataract scene did not spawn"))?;
        app.world_mut()
            .entity_mut(eye)
            .insert(PreconditionerOverride(kind));
    }
    let io = |path: &std::path::Path, e: std::io::Error| SoftTissueError::Io {
        path: path.display().to_string(),
        reason: e.to_string(),
    };
    let mut trace = match &options.trace {
        Some(path) => {
            let mut f =
                std::io::BufWriter::new(std::fs::File::create(path).map_err(|e| io(path, e))?);
            writeln!(f, "{TRACE_HEADER}").map_err(|e| io(path, e))?;
            Some((path, f))
        }
        None => None,
    };
    if let Some(r) = recording {
        std::fs::create_dir_all(&r.dir).map_err(|e| io(&r.dir, e))?;
        app.world_mut()
            .resource_mut::<SoftTissueContacts>()
            .solver
            .record_problems(Some(r.min_contacts));
    }
    let mut recorded = 0;
    let mut lcp_sweeps = (0usize, 0usize);
    // Queries made once, read after every step.
    let mut lens_q = app.world_mut().query_filtered::<&SoftBody, With<Lens>>();
    let mut eye_q = app.world_mut().query_filtered::<&SoftBody, With<Eye>>();
    let mut tool_q = app.world_mut().query::<&Tool>();
    let mut body_q = app.world_mut().query::<&SoftBody>();
    let centre = |b: &SoftBody| {
        b.positions().iter().sum::<bevy_soft_tissue::math::Vec3>() / b.num_nodes() as f64
    };
    let start = lens_q
        .iter(app.world())
        .next()
        .map(centre)
        .ok_or(SoftTissueError::EmptyMesh("cataract scene did not spawn"))?;
    let tolerance = lens_q
        .iter(app.world())
        .next()
        .map(|b| 0.01 * b.mesh().min_edge_length())
        .unwrap_or(0.0);
    // A detection pass of its own over each step's final positions: what the
    // pipeline left penetrating, tools and bodies alike.
    let mut checker = ContactSolver::new(cataract::contact_settings())?;
    // The lens's surface triangles in its node indices, for the test of the
    // vectis between their vertices.
    let lens_triangles: Vec<[usize; 3]> = lens_q
        .iter(app.world())
        .next()
        .map(|b| b.surface().volume_triangles().collect())
        .unwrap_or_default();
    let mut vectis_in_faces = (0.0f64, 0.0f64, 0usize);
    let mut jam = (Vec::new(), Vec::new());
    let mut max_tissue: f64 = 0.0;
    let mut phases: [Vec<f64>; 10] = Default::default();
    let mut contacts = Vec::new();
    let mut band = (Vec::new(), Vec::new());
    let mut band_sum = [0.0f64; 10];
    let mut jam_sum = [0.0f64; 10];
    let mut jam_passes = 0usize;
    let mut jam_contacts = 0usize;
    let mut jam_columns = (0usize, 0usize);
    let mut band_cg = 0usize;
    let mut band_lcp = (0usize, 0usize);
    let mut cg = 0usize;
    let mut max_pen: f64 = 0.0;
    let mut deepest_step = (0, 0);
    let mut max_lens_speed: f64 = 0.0;
    let mut max_passes = (0, 0);
    let mut slowest = SlowestStep::default();
    let mut capped_before = app.world().resource::<SoftTissueDiagnostics>().lcp_capped;
    let mut done = 0;
    let mut last = app.world().resource::<SoftTissueDiagnostics>().steps;
    let mut guard = 0;
    while done < steps {
        app.update();
        guard += 1;
        if guard > 4 * steps + 10 {
            return Err(SoftTissueError::InvalidParameter {
                name: "steps",
                value: steps as f64,
                reason: "fixed steps are not advancing",
            });
        }
        let d = app.world().resource::<SoftTissueDiagnostics>().clone();
        if d.steps == last {
            continue;
        }
        last = d.steps;
        done += 1;
        if d.errors > 0 {
            return Err(SoftTissueError::NonFinite(
                "the pipeline reported an error (see the log)",
            ));
        }
        let v = [
            d.assemble_ms,
            d.factorize_ms,
            d.free_motion_ms,
            d.detect_ms,
            d.compliance_ms,
            d.lcp_ms,
            d.correct_ms,
            d.rescue_ms,
            d.step_ms(),
            d.pipeline_ms,
        ];
        for (p, x) in phases.iter_mut().zip(v) {
            p.push(x);
        }
        contacts.push(d.contacts);
        if d.pipeline_ms > slowest.ms {
            slowest = SlowestStep {
                ms: d.pipeline_ms,
                step: d.steps,
                contacts: d.contacts,
                passes: d.contact_passes,
                capped: d.lcp_capped - capped_before,
                phase_ms: v,
                ..slowest
            };
        }
        slowest.over_h += usize::from(d.pipeline_ms > 1e3 * h);
        capped_before = d.lcp_capped;
        lcp_sweeps.0 = lcp_sweeps.0.max(d.lcp_first_iterations);
        if d.contacts > 90 {
            jam.0.push(d.pipeline_ms);
            jam.1.push(d.step_ms());
            lcp_sweeps.1 += d.lcp_first_iterations;
            jam_passes += d.contact_passes;
            jam_contacts += d.contacts;
            jam_columns.0 += d.compliance_solves;
            jam_columns.1 += d.gram_blocks;
            for (acc, x) in jam_sum.iter_mut().zip(v) {
                *acc += x;
            }
        }
        if let Some(r) = recording
            && let Some(p) = app
                .world_mut()
                .resource_mut::<SoftTissueContacts>()
                .solver
                .take_recorded_problem()
        {
            let name = format!("step{:05}_c{}.lcp", d.steps, p.num_contacts());
            p.write(&r.dir.join(name))?;
            recorded += 1;
        }
        if (50..=90).contains(&d.contacts) {
            band.0.push(d.pipeline_ms);
            band.1.push(d.step_ms());
            for (acc, x) in band_sum.iter_mut().zip(v) {
                *acc += x;
            }
            band_cg += d.cg_iterations;
            band_lcp.0 += d.lcp_iterations;
            band_lcp.1 += d.contact_passes;
        }
        cg += d.cg_iterations;
        max_passes.0 = max_passes.0.max(d.contact_passes);
        max_passes.1 += usize::from(d.contact_passes > 8);
        let world = app.world();
        if let Some(b) = lens_q.iter(world).next() {
            let v = b.velocities();
            let mean = v.iter().sum::<bevy_soft_tissue::math::Vec3>() / v.len().max(1) as f64;
            max_lens_speed = max_lens_speed.max(mean.norm());
            let vectis = tool_q.iter(world).next().map(|t| &t.0);
            // The last step's figures are the run's end figures.
            let (in_faces, over) = vectis.map_or((0.0, 0), |t| {
                tool_in_faces(t, &lens_triangles, b.positions(), tolerance, FACE_GRID)
            });
            vectis_in_faces = (vectis_in_faces.0.max(in_faces), in_faces, over);
            if let Some((path, f)) = trace.as_mut() {
                let c = centre(b) * 1e3;
                let v = mean * 1e3;
                let t = vectis
                    .map(|t| t.pose().translation.vector * 1e3)
                    .unwrap_or_default();
                let eye_age = eye_q
                    .iter(world)
                    .next()
                    .map_or(0, |e| e.report().preconditioner.factor_age);
                let misaccounted = world
                    .resource::<SoftTissueContacts>()
                    .solver
                    .report()
                    .misaccounted_work;
                writeln!(
                    f,
                    "{},{},{},{},{},{},{},{:e},{:.5},{:.5},{:.5},{:.4},{:.4},{:.4},{:.5},{:.5},{:.5},{},{:e}",
                    d.steps,
                    d.contacts,
                    d.contact_passes,
                    d.lcp_first_iterations,
                    d.consistency_refactors,
                    b.report().preconditioner.factor_age,
                    eye_age,
                    misaccounted,
                    c.x,
                    c.y,
                    c.z,
                    v.x,
                    v.y,
                    v.z,
                    t.x,
                    t.y,
                    t.z,
                    b.inverted_elements(),
                    in_faces
                )
                .map_err(|e| io(path, e))?;
            }
        }
        // Penetration left at the end of the step: into the vectis and between the bodies.
        let tools: Vec<&bevy_soft_tissue::contact::RigidTool> =
            tool_q.iter(world).map(|t| &t.0).collect();
        let bodies: Vec<&bevy_soft_tissue::body::DeformableBody> =
            body_q.iter(world).map(|b| &b.0).collect();
        for b in &bodies {
            if !b
                .positions()
                .iter()
                .all(|p| p.iter().all(|c| c.is_finite()))
            {
                return Err(SoftTissueError::NonFinite("body positions"));
            }
        }
        checker.detect(&bodies, &tools, h, PassKind::First)?;
        for c in checker.contacts() {
            if -c.gap > max_pen {
                max_pen = -c.gap;
                deepest_step = (d.steps, d.contact_passes);
            }
            if matches!(c.other, bevy_soft_tissue::contact::ContactOther::Body(_)) {
                max_tissue = max_tissue.max(-c.gap);
            }
        }
    }
    if let Some((path, mut f)) = trace {
        f.flush().map_err(|e| io(path, e))?;
    }
    let end = lens_q.iter(app.world()).next().map(centre).unwrap_or(start);
    let count = |b: &SoftBody| (b.inverted_elements(), b.elements().len());
    let lens_inverted = lens_q.iter(app.world()).next().map_or((0, 0), count);
    let all_inverted = body_q
        .iter(app.world())
        .map(count)
        .fold((0, 0), |(a, b), (c, d)| (a + c, b + d));
    let med = |v: &mut Vec<f64>| {
        if v.is_empty() {
            return f64::NAN;
        }
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let mut median_ms = [0.0; 10];
    for (m, p) in median_ms.iter_mut().zip(phases.iter_mut()) {
        *m = med(p);
    }
    // Sorted by `med`.
    let wall = &phases[PIPELINE];
    slowest.p99_ms = wall
        .get((0.99 * wall.len().saturating_sub(1) as f64).round() as usize)
        .copied()
        .unwrap_or(f64::NAN);
    let mut c = contacts;
    c.sort_unstable();
    let band_steps = band.0.len().max(1) as f64;
    let jam_steps = jam.0.len().max(1) as f64;
    let summary = HeadlessSummary {
        steps,
        median_ms,
        steps_per_second: 1e3 / median_ms[PIPELINE],
        contacts: (
            c.get(c.len() / 2).copied().unwrap_or(0),
            c.last().copied().unwrap_or(0),
        ),
        cg_iterations: cg as f64 / steps.max(1) as f64,
        max_penetration: max_pen,
        tolerance,
        lens_center: (start, end),
        inverted_at_end: [lens_inverted, all_inverted],
        max_lens_speed,
        mean_ms_50_90: band_sum.map(|x| x / band_steps),
        mean_ms_jam: jam_sum.map(|x| x / jam_steps),
        passes_jam: jam_passes as f64 / jam_steps,
        contacts_jam: jam_contacts as f64 / jam_steps,
        columns_jam: (
            jam_columns.0 as f64 / jam_steps,
            jam_columns.1 as f64 / jam_steps,
        ),
        cg_iterations_50_90: band_cg as f64 / band_steps,
        lcp_50_90: (
            band_lcp.0 as f64 / band_steps,
            band_lcp.1 as f64 / band_steps,
        ),
        median_ms_50_90: (!band.0.is_empty()).then(|| (med(&mut band.0), med(&mut band.1))),
        max_tissue_penetration: max_tissue,
        deepest_step,
        vectis_in_faces,
        lcp_sweeps: (lcp_sweeps.0, lcp_sweeps.1 as f64 / jam_steps),
        jam: (
            jam.0.len(),
            (!jam.0.is_empty()).then(|| (med(&mut jam.0), med(&mut jam.1))),
        ),
        max_passes,
        lcp_capped: app.world().resource::<SoftTissueDiagnostics>().lcp_capped,
        slowest,
        consistency_refactors: app
            .world()
            .resource::<SoftTissueDiagnostics>()
            .consistency_refactors,
        rescues: body_q.iter(app.world()).fold((0, 0), |(r, w), b| {
            let p = b.0.report().preconditioner;
            (r + p.rescues, w + p.rescues_from_worker)
        }),
        warps: body_q.iter(app.world()).fold((0, 0, 0), |(o, b, d), body| {
            let p = body.0.report().preconditioner;
            (o + p.warp_offered, b + p.warp_body, d + p.warp_declined)
        }),
        recorded,
        gpu: gpu_counters(&app),
    };
    Ok(summary)
}

#[cfg(feature = "gpu")]
fn gpu_counters(app: &App) -> Option<GpuCounters> {
    app.world()
        .get_resource::<bevy_soft_tissue::plugin::GpuBackend>()
        .map(|g| GpuCounters {
            dispatches: g.0.dispatches,
            builds: g.0.built,
            uploads: g.0.uploads,
            upload_seconds: g.0.upload_seconds,
            wait_seconds: g.0.wait_seconds,
            compute_seconds: g.0.compute_seconds,
            timed: g.0.timed,
            span_seconds: g.0.span_seconds,
            kernel_seconds: g.0.kernel_seconds,
            longest_path: g.0.longest_path,
            path_sum: g.0.path_sum,
            shared_forwards: g.0.shared_forwards,
            piece_forwards: g.0.piece_forwards,
            depth_sum: g.0.depth_sum,
        })
}

#[cfg(not(feature = "gpu"))]
fn gpu_counters(_: &App) -> Option<GpuCounters> {
    None
}
