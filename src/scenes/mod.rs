//! Ready-made scenes: the cataract (MSICS) extraction, as core data
//! ([`cataract`]) and as Bevy entities ([`CataractScenePlugin`], [`run_headless`]).

pub mod bench;
pub mod cataract;

use std::time::Duration;

use bevy::prelude::*;

use crate::body::BodySettings;
use crate::error::{Result, SoftTissueError};
use crate::plugin::{SoftBody, SoftTissueConfig, SoftTissueDiagnostics, Tool};
use cataract::{CataractParams, ExtractionPath};

/// Marks the lens entity.
#[derive(Component, Debug, Clone, Copy)]
pub struct Lens;

/// Marks the eye entity.
#[derive(Component, Debug, Clone, Copy)]
pub struct Eye;

/// The vectis entity and its scripted path.
#[derive(Component, Debug, Clone)]
pub struct Vectis {
    /// Scripted extraction path.
    pub path: ExtractionPath,
    /// When false, the path no longer drives the tool (manual control).
    pub scripted: bool,
    /// Seconds of scripted motion played so far.
    pub time: f64,
}

/// Spawns the cataract scene and drives the vectis along its path in `FixedUpdate`.
/// Add it after `SoftTissuePlugin`: it sets the scene's alarm distance and
/// lens–sclera friction in [`SoftTissueConfig::contact`].
#[derive(Debug, Clone, Default)]
pub struct CataractScenePlugin {
    /// Scene parameters.
    pub params: CataractParams,
}

impl Plugin for CataractScenePlugin {
    fn build(&self, app: &mut App) {
        // The scene's scale-dependent contact settings (other settings are kept).
        if let Some(mut config) = app.world_mut().get_resource_mut::<SoftTissueConfig>() {
            let scene = cataract::contact_settings();
            config.contact.alarm_distance = scene.alarm_distance;
            config.contact.body_friction = scene.body_friction;
            config.contact.max_passes = config.contact.max_passes.max(scene.max_passes);
        }
        let params = self.params.clone();
        app.add_systems(
            Startup,
            move |mut commands: Commands, config: Res<SoftTissueConfig>| {
                if let Err(e) = spawn_cataract(&mut commands, &params, &config) {
                    error!("cataract scene: {e}");
                }
            },
        )
        .add_systems(FixedUpdate, drive_vectis);
    }
}

/// Spawns lens, eye and vectis entities.
pub fn spawn_cataract(
    commands: &mut Commands,
    params: &CataractParams,
    config: &SoftTissueConfig,
) -> Result<()> {
    let settings = BodySettings {
        preconditioner: config.preconditioner,
        ..Default::default()
    };
    let scene = cataract::build(params, settings)?;
    let pose = scene.path.pose(0.0);
    commands.spawn((SoftBody(scene.lens), Lens, Name::new("lens")));
    commands.spawn((SoftBody(scene.eye), Eye, Name::new("eye")));
    commands.spawn((
        Tool(scene.vectis),
        Vectis {
            path: scene.path,
            scripted: true,
            time: 0.0,
        },
        pose_to_transform(&pose),
        Name::new("vectis"),
    ));
    Ok(())
}

/// Converts a core pose to a Bevy transform (`f64` → `f32`).
pub fn pose_to_transform(p: &crate::contact::Pose) -> Transform {
    let t = p.translation.vector;
    let q = p.rotation;
    Transform::from_xyz(t.x as f32, t.y as f32, t.z as f32).with_rotation(Quat::from_xyzw(
        q.i as f32, q.j as f32, q.k as f32, q.w as f32,
    ))
}

fn drive_vectis(config: Res<SoftTissueConfig>, mut q: Query<(&mut Vectis, &mut Transform)>) {
    for (mut v, mut tf) in &mut q {
        if v.scripted {
            v.time += config.timestep;
            *tf = pose_to_transform(&v.path.pose(v.time));
        }
    }
}

/// Summary of a headless run.
#[derive(Debug, Clone, Default)]
pub struct HeadlessSummary {
    /// Steps run.
    pub steps: usize,
    /// Median milliseconds per phase: assemble, factorize, free motion, detect,
    /// compliance, LCP, correct, whole step.
    pub median_ms: [f64; 8],
    /// Steps per second from the median step time.
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
    /// Penetration tolerance used (1 % of the smallest lens edge), metres.
    pub tolerance: f64,
    /// Lens centre at the start and at the end.
    pub lens_center: (crate::math::Vec3, crate::math::Vec3),
    /// Largest speed of the lens's centre of mass (mean node velocity) seen, m/s:
    /// a stability check, as the vectis itself moves at about 1 mm/s.
    pub max_lens_speed: f64,
    /// Median step time over the steps with 50–90 contacts, if any.
    pub median_ms_50_90: Option<f64>,
    /// Mean milliseconds per phase (same order as [`Self::median_ms`]) over the
    /// steps with 50–90 contacts: where the time of those steps goes.
    pub mean_ms_50_90: [f64; 8],
    /// Mean CG iterations per step (both bodies) over the steps with 50–90 contacts.
    pub cg_iterations_50_90: f64,
    /// Mean LCP sweeps and contact passes per step over the steps with 50–90 contacts.
    pub lcp_50_90: (f64, f64),
    /// Steps with more than 90 contacts (the lens jammed in the slit), and their
    /// median step time in ms, if any.
    pub jam: (usize, Option<f64>),
    /// The most contact passes a step ran, and how many steps ran more than
    /// eight (see [`crate::contact::ContactSettings::max_passes`]).
    pub max_passes: (usize, usize),
}

/// Runs the cataract scene without a window for `steps` fixed steps and
/// measures it. Fails on NaN or on errors reported by the pipeline; the caller
/// compares [`HeadlessSummary::max_penetration`] with its tolerance.
pub fn run_headless(
    params: &CataractParams,
    config: SoftTissueConfig,
    steps: usize,
) -> Result<HeadlessSummary> {
    let h = config.timestep;
    let mut app = App::new();
    app.add_plugins((
        MinimalPlugins,
        crate::SoftTissuePlugin::default().with_config(config),
    ))
    .add_plugins(CataractScenePlugin {
        params: params.clone(),
    })
    .insert_resource(bevy::time::TimeUpdateStrategy::ManualDuration(
        Duration::from_secs_f64(h),
    ));
    app.update();
    // Queries made once, read after every step.
    let mut lens_q = app.world_mut().query_filtered::<&SoftBody, With<Lens>>();
    let mut tool_q = app.world_mut().query::<&Tool>();
    let mut body_q = app.world_mut().query::<&SoftBody>();
    let centre =
        |b: &SoftBody| b.positions().iter().sum::<crate::math::Vec3>() / b.num_nodes() as f64;
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
    let mut checker = crate::contact::ContactSolver::new(cataract::contact_settings())?;
    let mut jam = Vec::new();
    let mut max_tissue: f64 = 0.0;
    let mut phases: [Vec<f64>; 8] = Default::default();
    let mut contacts = Vec::new();
    let mut band = Vec::new();
    let mut band_sum = [0.0f64; 8];
    let mut band_cg = 0usize;
    let mut band_lcp = (0usize, 0usize);
    let mut cg = 0usize;
    let mut max_pen: f64 = 0.0;
    let mut max_lens_speed: f64 = 0.0;
    let mut max_passes = (0, 0);
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
            d.step_ms(),
        ];
        for (p, x) in phases.iter_mut().zip(v) {
            p.push(x);
        }
        contacts.push(d.contacts);
        if d.contacts > 90 {
            jam.push(d.step_ms());
        }
        if (50..=90).contains(&d.contacts) {
            band.push(d.step_ms());
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
            let mean = v.iter().sum::<crate::math::Vec3>() / v.len().max(1) as f64;
            max_lens_speed = max_lens_speed.max(mean.norm());
        }
        // Penetration left at the end of the step: into the vectis and between the bodies.
        let tools: Vec<&crate::contact::RigidTool> = tool_q.iter(world).map(|t| &t.0).collect();
        let bodies: Vec<&crate::body::DeformableBody> = body_q.iter(world).map(|b| &b.0).collect();
        for b in &bodies {
            if !b
                .positions()
                .iter()
                .all(|p| p.iter().all(|c| c.is_finite()))
            {
                return Err(SoftTissueError::NonFinite("body positions"));
            }
        }
        checker.detect(&bodies, &tools, h)?;
        for c in checker.contacts() {
            max_pen = max_pen.max(-c.gap);
            if matches!(c.other, crate::contact::ContactOther::Body(_)) {
                max_tissue = max_tissue.max(-c.gap);
            }
        }
    }
    let end = lens_q.iter(app.world()).next().map(centre).unwrap_or(start);
    let med = |v: &mut Vec<f64>| {
        if v.is_empty() {
            return f64::NAN;
        }
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let mut median_ms = [0.0; 8];
    for (m, p) in median_ms.iter_mut().zip(phases.iter_mut()) {
        *m = med(p);
    }
    let mut c = contacts;
    c.sort_unstable();
    let band_steps = band.len().max(1) as f64;
    let summary = HeadlessSummary {
        steps,
        median_ms,
        steps_per_second: 1e3 / median_ms[7],
        contacts: (
            c.get(c.len() / 2).copied().unwrap_or(0),
            c.last().copied().unwrap_or(0),
        ),
        cg_iterations: cg as f64 / steps.max(1) as f64,
        max_penetration: max_pen,
        tolerance,
        lens_center: (start, end),
        max_lens_speed,
        mean_ms_50_90: band_sum.map(|x| x / band_steps),
        cg_iterations_50_90: band_cg as f64 / band_steps,
        lcp_50_90: (
            band_lcp.0 as f64 / band_steps,
            band_lcp.1 as f64 / band_steps,
        ),
        median_ms_50_90: (!band.is_empty()).then(|| med(&mut band)),
        max_tissue_penetration: max_tissue,
        jam: (jam.len(), (!jam.is_empty()).then(|| med(&mut jam))),
        max_passes,
    };
    Ok(summary)
}
