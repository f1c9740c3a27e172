//! The Bevy layer: [`SoftTissuePlugin`], components, system sets, diagnostics.
//!
//! The plugin is a thin ECS layer over the numerical core. Bodies and tools
//! are entities:
//!
//! - [`SoftBody`] wraps a [`DeformableBody`] (mesh, material, state, solver);
//!   it requires [`BodyContacts`] and a `Transform`. Positions are simulated
//!   in world space, so keep the body's `Transform` at identity.
//! - [`Tool`] wraps a [`RigidTool`]; its pose follows the entity's
//!   `Transform` (`f32` → `f64` at the edge), so moving a tool is moving its
//!   `Transform` in `FixedUpdate`. The `Transform` is read as a world pose
//!   (not the `GlobalTransform`, which is only propagated later in the frame), so
//!   tools are top-level entities. It requires [`ToolReaction`], where the
//!   tissue's reaction force and torque land for haptic output.
//! - [`FixedNodes`], [`PreconditionerOverride`], [`ComplianceOverride`] adjust one body.
//!
//! ## Pipeline
//! Systems run in the chained sets of [`SoftTissueSystems`], in
//! `FixedPostUpdate` unless another schedule is given, so user systems in
//! `FixedUpdate` move tools before detection:
//!
//! ```text
//! Assemble → Factorize → FreeMotion → Detect → Compliance → Lcp → Correct → Sync
//! ```
//!
//! The plugin is a group of one plugin per concern — [`DeformationPlugin`]
//! (assemble, factorize, free motion), [`ContactPlugin`] (detect, compliance,
//! LCP, correct), [`SyncPlugin`] (reactions, contact components, render
//! meshes with the `viewer` feature) and [`SoftTissueDiagnosticsPlugin`].
//!
//! ## Only the effects a scene calls for
//! Contact phases run only when a tool or a second body exists and
//! [`SoftTissueConfig::contacts`] is on; friction rows only for `μ > 0` and
//! [`SoftTissueConfig::friction`] on; damping terms only for nonzero Rayleigh
//! coefficients and [`SoftTissueConfig::damping`] on; gravity only when
//! [`SoftTissueConfig::gravity`] is set. [`SoftTissueDiagnostics`] counts the
//! work each effect did, so a test can show an absent effect costs nothing.
//!
//! ## Background factorization
//! The asynchronous `LDLᵀ` worker of a body lives inside its
//! [`DeformableBody`]; despawning the entity drops the component, which stops
//! and joins the worker thread.

mod diagnostics;
#[cfg(feature = "viewer")]
pub mod render;

use bevy::app::{FixedPostUpdate, PluginGroup, PluginGroupBuilder};
use bevy::ecs::intern::Interned;
use bevy::ecs::schedule::ScheduleLabel;
use bevy::prelude::*;

pub use diagnostics::{
    SoftTissueDiagnostics, SoftTissueDiagnosticsPlugin, paths as diagnostics_paths,
};

use crate::body::{BodySettings, DeformableBody};
use crate::contact::{ComplianceMode, ContactSettings, ContactSolver, RigidTool, ToolShape};
use crate::error::Result;
use crate::material::TissueMaterial;
use crate::math::Vec3 as DVec3;
use crate::mesh::TetMesh;
use crate::solver::PreconditionerKind;

/// The pipeline's system sets, chained in this order.
#[derive(SystemSet, Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SoftTissueSystems {
    /// Element rotations, forces and the implicit system.
    Assemble,
    /// Preconditioner refresh: factor swap, hand-off to the worker, rotation warp.
    Factorize,
    /// Conjugate gradient and integration to free-motion positions.
    FreeMotion,
    /// Tool poses from transforms; collision detection.
    Detect,
    /// Contact Jacobian and compliance `W`.
    Compliance,
    /// Friction LCP.
    Lcp,
    /// Position/velocity correction, extra passes, tool reactions.
    Correct,
    /// Components, diagnostics and render meshes.
    Sync,
}

/// Where the contact compliance of `Factorized` bodies is built.
///
/// The GPU path needs the `gpu` feature and a render device (`RenderPlugin`);
/// otherwise every mode builds on the CPU.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Reflect)]
pub enum GpuMode {
    /// Always on the CPU.
    #[default]
    Off,
    /// On the GPU whenever there are contacts.
    On,
    /// On the GPU when a body has at least `min_rows` constraint rows
    /// (contacts × 3 with friction, × 1 without).
    Auto {
        /// Crossover in rows.
        min_rows: usize,
    },
}

/// Global settings (a resource; change it at runtime).
#[derive(Resource, Reflect, Debug, Clone)]
#[reflect(Resource)]
pub struct SoftTissueConfig {
    /// Step size `h`, seconds. The fixed timestep of `Time<Fixed>` is set to it.
    pub timestep: f64,
    /// Gravity, m/s² (`None`: no gravity).
    pub gravity: Option<bevy::math::DVec3>,
    /// Contact handling on or off.
    pub contacts: bool,
    /// Friction on or off.
    pub friction: bool,
    /// Rayleigh damping on or off.
    pub damping: bool,
    /// Default preconditioner of new bodies (bodies keep theirs unless overridden).
    #[reflect(ignore)]
    pub preconditioner: PreconditionerKind,
    /// Default contact compliance.
    #[reflect(ignore)]
    pub compliance: ComplianceMode,
    /// Contact detection and LCP settings.
    #[reflect(ignore)]
    pub contact: ContactSettings,
    /// GPU compliance (feature `gpu`).
    pub gpu: GpuMode,
}

impl Default for SoftTissueConfig {
    fn default() -> Self {
        Self {
            timestep: 1.0 / 60.0,
            gravity: None,
            contacts: true,
            friction: true,
            damping: true,
            preconditioner: PreconditionerKind::Async,
            compliance: ComplianceMode::Factorized,
            contact: ContactSettings::default(),
            gpu: GpuMode::Off,
        }
    }
}

/// A deformable body entity (see the module docs).
#[derive(Component, Debug, Deref, DerefMut)]
#[require(Transform, BodyContacts)]
pub struct SoftBody(pub DeformableBody);

impl SoftBody {
    /// A body with default solver settings.
    pub fn new(mesh: TetMesh, material: TissueMaterial) -> Result<Self> {
        Ok(Self(DeformableBody::new(
            mesh,
            material,
            BodySettings::default(),
        )?))
    }

    /// A body with explicit solver settings.
    pub fn with_settings(
        mesh: TetMesh,
        material: TissueMaterial,
        settings: BodySettings,
    ) -> Result<Self> {
        Ok(Self(DeformableBody::new(mesh, material, settings)?))
    }
}

/// A rigid tool entity; its pose follows the entity's `Transform`.
#[derive(Component, Debug, Deref, DerefMut)]
#[require(Transform, ToolReaction)]
pub struct Tool(pub RigidTool);

impl Tool {
    /// A tool of `shape` with friction `mu`, placed by its `Transform`.
    pub fn new(shape: ToolShape, mu: f64) -> Result<Self> {
        Ok(Self(
            RigidTool::new(shape, crate::contact::Pose::identity())?.with_friction(mu)?,
        ))
    }
}

/// Reaction of the tissue on a tool during the last step (for haptics).
#[derive(Component, Reflect, Debug, Clone, Copy, Default, PartialEq)]
#[reflect(Component)]
pub struct ToolReaction {
    /// Force on the tool, newtons.
    pub force: bevy::math::DVec3,
    /// Torque about the tool origin, N·m.
    pub torque: bevy::math::DVec3,
    /// Contacts this tool had.
    pub contacts: usize,
}

/// Contacts of a body during the last step.
#[derive(Component, Reflect, Debug, Clone, Copy, Default, PartialEq)]
#[reflect(Component)]
pub struct BodyContacts {
    /// Contacts involving this body.
    pub count: usize,
    /// Total contact force on the body, newtons.
    pub force: bevy::math::DVec3,
    /// Deepest penetration seen by the last detection, metres.
    pub max_penetration: f64,
}

/// Nodes held in place (volume-vertex indices), applied when added or changed.
#[derive(Component, Reflect, Debug, Clone, Default, PartialEq)]
#[reflect(Component)]
pub struct FixedNodes(pub Vec<usize>);

/// Per-body preconditioner, overriding the body's settings.
#[derive(Component, Debug, Clone, Copy, PartialEq)]
pub struct PreconditionerOverride(pub PreconditionerKind);

/// Per-body contact compliance, overriding [`SoftTissueConfig::compliance`].
#[derive(Component, Debug, Clone, Copy, PartialEq)]
pub struct ComplianceOverride(pub ComplianceMode);

/// The scene's contact solver (a resource).
#[derive(Resource, Debug, Default)]
pub struct SoftTissueContacts {
    /// The core solver.
    pub solver: ContactSolver,
    /// Body entities in the order given to the solver.
    pub bodies: Vec<Entity>,
    /// Tool entities in the order given to the solver.
    pub tools: Vec<Entity>,
    /// Whether the contact phases run this step.
    pub active: bool,
}

/// Adds the soft-tissue pipeline to an app (see the module docs).
pub struct SoftTissuePlugin {
    schedule: Interned<dyn ScheduleLabel>,
    config: SoftTissueConfig,
}

impl Default for SoftTissuePlugin {
    fn default() -> Self {
        Self::new(FixedPostUpdate)
    }
}

impl SoftTissuePlugin {
    /// Runs the pipeline in `schedule` (default `FixedPostUpdate`).
    pub fn new(schedule: impl ScheduleLabel) -> Self {
        Self {
            schedule: schedule.intern(),
            config: SoftTissueConfig::default(),
        }
    }

    /// Starts with `config`.
    pub fn with_config(mut self, config: SoftTissueConfig) -> Self {
        self.config = config;
        self
    }
}

impl Plugin for SoftTissuePlugin {
    fn build(&self, app: &mut App) {
        let schedule = self.schedule;
        app.insert_resource(self.config.clone())
            .register_type::<SoftTissueConfig>()
            .register_type::<ToolReaction>()
            .register_type::<BodyContacts>()
            .register_type::<FixedNodes>()
            .init_resource::<SoftTissueContacts>()
            .configure_sets(
                schedule,
                (
                    SoftTissueSystems::Assemble,
                    SoftTissueSystems::Factorize,
                    SoftTissueSystems::FreeMotion,
                    SoftTissueSystems::Detect,
                    SoftTissueSystems::Compliance,
                    SoftTissueSystems::Lcp,
                    SoftTissueSystems::Correct,
                    SoftTissueSystems::Sync,
                )
                    .chain(),
            );
        if let Some(mut time) = app.world_mut().get_resource_mut::<Time<Fixed>>() {
            time.set_timestep_seconds(self.config.timestep);
        }
        app.add_systems(First, sync_timestep);
        app.add_plugins(SoftTissuePlugins { schedule });
    }
}

/// Keeps `Time<Fixed>` at [`SoftTissueConfig::timestep`] when the config changes.
fn sync_timestep(
    config: Res<SoftTissueConfig>,
    time: Option<ResMut<Time<Fixed>>>,
    mut diag: ResMut<SoftTissueDiagnostics>,
) {
    if !config.is_changed() {
        return;
    }
    if !(config.timestep.is_finite() && config.timestep > 0.0) {
        diag.errors += 1;
        warn!(
            "SoftTissueConfig::timestep = {} is not a positive time step",
            config.timestep
        );
        return;
    }
    if let Some(mut time) = time
        && (time.timestep().as_secs_f64() - config.timestep).abs() > 1e-12
    {
        time.set_timestep_seconds(config.timestep);
    }
}

/// The sub-plugins of [`SoftTissuePlugin`], one per concern.
pub struct SoftTissuePlugins {
    schedule: Interned<dyn ScheduleLabel>,
}

impl PluginGroup for SoftTissuePlugins {
    fn build(self) -> PluginGroupBuilder {
        let s = self.schedule;
        PluginGroupBuilder::start::<Self>()
            .add(DeformationPlugin { schedule: s })
            .add(ContactPlugin { schedule: s })
            .add(SyncPlugin { schedule: s })
            .add(SoftTissueDiagnosticsPlugin { schedule: s })
    }
}

/// Assemble, factorize and free-motion systems.
pub struct DeformationPlugin {
    schedule: Interned<dyn ScheduleLabel>,
}

impl Plugin for DeformationPlugin {
    fn build(&self, app: &mut App) {
        app.add_systems(
            self.schedule,
            (
                (apply_body_overrides, assemble)
                    .chain()
                    .in_set(SoftTissueSystems::Assemble),
                factorize.in_set(SoftTissueSystems::Factorize),
                free_motion.in_set(SoftTissueSystems::FreeMotion),
            ),
        );
    }
}

/// Detection, compliance, LCP and correction systems.
pub struct ContactPlugin {
    schedule: Interned<dyn ScheduleLabel>,
}

impl Plugin for ContactPlugin {
    fn build(&self, app: &mut App) {
        app.add_systems(
            self.schedule,
            (
                detect.in_set(SoftTissueSystems::Detect),
                compliance.in_set(SoftTissueSystems::Compliance),
                lcp.in_set(SoftTissueSystems::Lcp),
                correct.in_set(SoftTissueSystems::Correct),
            ),
        );
        #[cfg(feature = "gpu")]
        app.add_systems(self.schedule, ensure_gpu.in_set(SoftTissueSystems::Detect));
    }
}

/// Writes contact components and tool reactions (and render meshes with `viewer`).
pub struct SyncPlugin {
    schedule: Interned<dyn ScheduleLabel>,
}

impl Plugin for SyncPlugin {
    fn build(&self, app: &mut App) {
        app.add_systems(
            self.schedule,
            sync_components.in_set(SoftTissueSystems::Sync),
        );
        #[cfg(feature = "viewer")]
        app.add_plugins(render::RenderSyncPlugin {
            schedule: self.schedule,
        });
    }
}

fn to_dvec(v: DVec3) -> bevy::math::DVec3 {
    bevy::math::DVec3::new(v.x, v.y, v.z)
}

#[allow(clippy::type_complexity)]
fn apply_body_overrides(
    config: Res<SoftTissueConfig>,
    mut bodies: Query<(
        &mut SoftBody,
        Option<Ref<FixedNodes>>,
        Option<&PreconditionerOverride>,
        Option<&ComplianceOverride>,
    )>,
    mut diag: ResMut<SoftTissueDiagnostics>,
) {
    for (mut body, fixed, pre, comp) in &mut bodies {
        let mut s = *body.settings();
        s.gravity = config.gravity.map(|g| DVec3::new(g.x, g.y, g.z));
        s.damping = config.damping;
        if let Some(p) = pre {
            s.preconditioner = p.0;
        }
        s.compliance = comp.map(|c| c.0);
        if s != *body.settings()
            && let Err(e) = body.set_settings(s)
        {
            diag.errors += 1;
            warn!("soft body settings rejected: {e}");
        }
        if let Some(f) = fixed
            && f.is_changed()
            && let Err(e) = body.fix_nodes(&f.0)
        {
            diag.errors += 1;
            warn!("fixed nodes rejected: {e}");
        }
    }
}

fn assemble(
    config: Res<SoftTissueConfig>,
    contacts: Res<SoftTissueContacts>,
    mut bodies: Query<&mut SoftBody>,
    mut diag: ResMut<SoftTissueDiagnostics>,
) {
    diag.begin_step();
    for mut body in &mut bodies {
        let rest = body.settings().compliance.unwrap_or(config.compliance)
            == ComplianceMode::RestPrecomputed;
        body.request_node_rotations(rest && contacts.active);
        if let Err(e) = body.assemble(config.timestep) {
            diag.errors += 1;
            warn!("assembly failed: {e}");
            continue;
        }
        let r = *body.report();
        diag.assemble_ms += r.timings.assemble * 1e3;
        diag.damping_bodies += usize::from(r.damping);
        diag.gravity_bodies += usize::from(r.gravity);
    }
}

fn factorize(mut bodies: Query<&mut SoftBody>, mut diag: ResMut<SoftTissueDiagnostics>) {
    for mut body in &mut bodies {
        if let Err(e) = body.update_preconditioner() {
            diag.errors += 1;
            warn!("factorization failed: {e}");
            continue;
        }
        let r = body.report();
        diag.factorize_ms += r.timings.factorize * 1e3;
        diag.factor_age = diag.factor_age.max(r.preconditioner.factor_age);
        diag.refreshes += r.preconditioner.refreshes;
    }
}

fn free_motion(mut bodies: Query<&mut SoftBody>, mut diag: ResMut<SoftTissueDiagnostics>) {
    for mut body in &mut bodies {
        match body.solve_free_motion() {
            Ok(cg) => {
                let r = body.report();
                diag.free_motion_ms += r.timings.cg_total * 1e3;
                diag.cg_iterations += cg.iterations;
                diag.cg_unconverged += usize::from(!cg.converged);
            }
            Err(e) => {
                diag.errors += 1;
                warn!("free motion failed: {e}");
            }
        }
    }
}

fn detect(
    config: Res<SoftTissueConfig>,
    mut contacts: ResMut<SoftTissueContacts>,
    bodies: Query<(Entity, &SoftBody)>,
    mut tools: Query<(Entity, &mut Tool, &Transform)>,
    mut diag: ResMut<SoftTissueDiagnostics>,
) {
    let contacts = &mut *contacts;
    contacts.bodies.clear();
    contacts.bodies.extend(bodies.iter().map(|(e, _)| e));
    contacts.bodies.sort_unstable();
    contacts.tools.clear();
    for (e, mut tool, tf) in &mut tools {
        let (rot, pos) = (tf.rotation, tf.translation);
        let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            rot.w as f64,
            rot.x as f64,
            rot.y as f64,
            rot.z as f64,
        ));
        let t = DVec3::new(pos.x as f64, pos.y as f64, pos.z as f64);
        if let Err(e) = tool.set_position(t, q) {
            diag.errors += 1;
            warn!("tool pose rejected: {e}");
        }
        contacts.tools.push(e);
    }
    contacts.tools.sort_unstable();
    let can_touch =
        !contacts.bodies.is_empty() && (!contacts.tools.is_empty() || contacts.bodies.len() > 1);
    contacts.active = config.contacts && can_touch;
    if !contacts.active {
        return;
    }
    let mut settings = config.contact;
    settings.compliance = config.compliance;
    settings.friction = config.friction;
    if *contacts.solver.settings() != settings
        && let Err(e) = contacts.solver.set_settings(settings)
    {
        diag.errors += 1;
        warn!("contact settings rejected: {e}");
    }
    let b: Vec<&DeformableBody> = contacts
        .bodies
        .iter()
        .filter_map(|e| bodies.get(*e).ok().map(|(_, b)| &b.0))
        .collect();
    let t: Vec<&RigidTool> = contacts
        .tools
        .iter()
        .filter_map(|e| tools.get(*e).ok().map(|(_, t, _)| &t.0))
        .collect();
    diag.detect_runs += 1;
    if let Err(e) = contacts.solver.detect(&b, &t, config.timestep) {
        diag.errors += 1;
        warn!("detection failed: {e}");
        contacts.active = false;
        return;
    }
    if contacts.solver.contacts().is_empty() {
        contacts.active = false;
    }
}

/// The GPU compliance builder, created once a render device exists.
#[cfg(feature = "gpu")]
#[derive(Resource, Debug)]
pub struct GpuBackend(pub crate::gpu::GpuCompliance);

#[cfg(feature = "gpu")]
fn ensure_gpu(
    mut commands: Commands,
    config: Res<SoftTissueConfig>,
    existing: Option<Res<GpuBackend>>,
    device: Option<Res<bevy::render::renderer::RenderDevice>>,
    queue: Option<Res<bevy::render::renderer::RenderQueue>>,
) {
    if config.gpu != GpuMode::Off
        && existing.is_none()
        && let (Some(d), Some(q)) = (device, queue)
    {
        commands.insert_resource(GpuBackend(crate::gpu::GpuCompliance::new(
            d.clone(),
            q.clone(),
            config.gpu,
        )));
    }
}

fn compliance(
    config: Res<SoftTissueConfig>,
    mut contacts: ResMut<SoftTissueContacts>,
    bodies: Query<&SoftBody>,
    mut diag: ResMut<SoftTissueDiagnostics>,
    #[cfg(feature = "gpu")] gpu: Option<ResMut<GpuBackend>>,
) {
    if !contacts.active {
        return;
    }
    let contacts = &mut *contacts;
    let b: Vec<&DeformableBody> = contacts
        .bodies
        .iter()
        .filter_map(|e| bodies.get(*e).ok().map(|b| &b.0))
        .collect();
    diag.compliance_builds += 1;
    #[cfg(feature = "gpu")]
    let result = match gpu {
        Some(mut g) if config.gpu != GpuMode::Off => {
            let g = &mut g.0;
            g.mode = config.gpu;
            let before = g.dispatches;
            let r = contacts.solver.build_compliance_with(&b, Some(g));
            diag.gpu_dispatches += g.dispatches - before;
            r
        }
        _ => contacts.solver.build_compliance(&b),
    };
    #[cfg(not(feature = "gpu"))]
    let result = {
        let _ = &config;
        contacts.solver.build_compliance(&b)
    };
    if let Err(e) = result {
        diag.errors += 1;
        warn!("compliance failed: {e}");
        contacts.active = false;
    }
}

fn lcp(
    mut contacts: ResMut<SoftTissueContacts>,
    bodies: Query<&SoftBody>,
    mut diag: ResMut<SoftTissueDiagnostics>,
) {
    if !contacts.active {
        return;
    }
    let contacts = &mut *contacts;
    let b: Vec<&DeformableBody> = contacts
        .bodies
        .iter()
        .filter_map(|e| bodies.get(*e).ok().map(|b| &b.0))
        .collect();
    diag.lcp_solves += 1;
    contacts.solver.solve_lcp(&b);
}

fn correct(
    config: Res<SoftTissueConfig>,
    mut contacts: ResMut<SoftTissueContacts>,
    mut bodies: Query<(Entity, &mut SoftBody)>,
    mut tools: Query<(Entity, &mut Tool)>,
    mut diag: ResMut<SoftTissueDiagnostics>,
) {
    let contacts = &mut *contacts;
    let mut t: Vec<(Entity, Mut<Tool>)> = tools.iter_mut().collect();
    t.sort_unstable_by_key(|(e, _)| *e);
    if !contacts.active {
        let mut tr: Vec<&mut RigidTool> = t.iter_mut().map(|(_, t)| &mut t.0).collect();
        contacts.solver.clear_forces(&mut tr);
        for t in tr {
            t.end_step();
        }
        return;
    }
    let mut b: Vec<(Entity, Mut<SoftBody>)> = bodies.iter_mut().collect();
    b.sort_unstable_by_key(|(e, _)| *e);
    b.retain(|(e, _)| contacts.bodies.binary_search(e).is_ok());
    t.retain(|(e, _)| contacts.tools.binary_search(e).is_ok());
    let mut tr: Vec<&mut RigidTool> = t.iter_mut().map(|(_, t)| &mut t.0).collect();
    if b.len() != contacts.bodies.len() || tr.len() != contacts.tools.len() {
        // An entity vanished between detection and correction: skip this step's response.
        for t in tr {
            t.end_step();
        }
        return;
    }
    let mut br: Vec<&mut DeformableBody> = b.iter_mut().map(|(_, b)| &mut b.0).collect();
    let res = contacts
        .solver
        .correct(&mut br, &mut tr)
        .and_then(|_| contacts.solver.refine(&mut br, &mut tr, config.timestep));
    if let Err(e) = res {
        diag.errors += 1;
        warn!("contact correction failed: {e}");
    }
    for t in tr {
        t.end_step();
    }
}

fn sync_components(
    contacts: Res<SoftTissueContacts>,
    mut bodies: Query<(Entity, &mut BodyContacts)>,
    mut tools: Query<(Entity, &Tool, &mut ToolReaction)>,
    mut diag: ResMut<SoftTissueDiagnostics>,
) {
    let report = *contacts.solver.report();
    let active = contacts.active;
    for (e, mut bc) in &mut bodies {
        let idx = contacts.bodies.iter().position(|b| *b == e);
        let new = match (active, idx) {
            (true, Some(i)) => BodyContacts {
                count: contacts
                    .solver
                    .contacts()
                    .iter()
                    .filter(|c| {
                        c.a.body == i
                            || matches!(c.other, crate::contact::ContactOther::Body(s) if s.body == i)
                    })
                    .count(),
                force: to_dvec(contacts.solver.body_force(i)),
                max_penetration: report.max_penetration,
            },
            _ => BodyContacts::default(),
        };
        if *bc != new {
            *bc = new;
        }
    }
    for (e, tool, mut reaction) in &mut tools {
        let idx = contacts.tools.iter().position(|t| *t == e);
        let (f, tau) = tool.reaction();
        let count = match (active, idx) {
            (true, Some(i)) => contacts
                .solver
                .contacts()
                .iter()
                .filter(|c| c.other == crate::contact::ContactOther::Tool(i))
                .count(),
            _ => 0,
        };
        let new = ToolReaction {
            force: to_dvec(f),
            torque: to_dvec(tau),
            contacts: count,
        };
        if *reaction != new {
            *reaction = new;
        }
    }
    if active {
        diag.contacts = report.contacts;
        diag.friction_rows += report.rows - report.contacts;
        diag.lcp_residual = report.lcp.complementarity.max(report.lcp.friction);
        diag.lcp_iterations = report.lcp.iterations;
        diag.detect_ms = report.detect * 1e3;
        diag.compliance_ms = report.compliance * 1e3;
        diag.lcp_ms = report.lcp_seconds * 1e3;
        diag.correct_ms = report.correct * 1e3;
        diag.contact_passes = report.passes;
    }
}
