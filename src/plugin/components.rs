//! Components and the contact resource of the plugin.

use bevy::prelude::*;

use crate::body::{BodySettings, DeformableBody};
use crate::contact::{ComplianceMode, ContactSolver, RigidTool, ToolShape};
use crate::error::Result;
use crate::material::TissueMaterial;
use crate::mesh::TetMesh;
use crate::solver::PreconditionerKind;

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

/// Nodes held in place (volume-vertex indices), applied when added or
/// changed. Nodes taken out of the list, or all of them when the component is
/// removed, are freed again (nodes fixed through the core API, e.g.
/// `DeformableBody::fix_where`, are not touched).
#[derive(Component, Reflect, Debug, Clone, Default, PartialEq)]
#[reflect(Component)]
pub struct FixedNodes(pub Vec<usize>);

/// The nodes a [`FixedNodes`] component fixed, to free them when it changes
/// or goes.
#[derive(Component, Debug, Clone, Default, PartialEq)]
pub(crate) struct AppliedFixedNodes(pub(crate) Vec<usize>);

/// Per-body preconditioner: written into the body's
/// [`BodySettings::preconditioner`] (its home) when added or changed.
#[derive(Component, Debug, Clone, Copy, PartialEq)]
pub struct PreconditionerOverride(pub PreconditionerKind);

/// Per-body contact compliance: written into the contact solver's per-body
/// mode ([`ContactSolver::set_body_compliance`], its home) when added or
/// changed; removing it returns the body to [`crate::contact::ContactSettings::compliance`].
#[derive(Component, Debug, Clone, Copy, PartialEq)]
pub struct ComplianceOverride(pub ComplianceMode);

/// The phase of the pipeline in which a body failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Reflect)]
pub enum FailedPhase {
    /// Element rotations, forces, `A` and `b`.
    Assemble,
    /// The preconditioner refresh.
    Factorize,
    /// The conjugate gradient and integration.
    FreeMotion,
}

/// Marks a body whose step failed: it kept its state of the start of that
/// step (a failing phase changes no position or velocity), and the pipeline
/// leaves it alone (it does not move,
/// and takes part in no contact) until this component is removed. To go on,
/// fix the cause (its forces, settings or state, `set_state` to start over)
/// and remove the component; the other bodies never stop.
#[derive(Component, Debug, Clone, PartialEq)]
pub struct SoftBodyFailed {
    /// Where it failed.
    pub phase: FailedPhase,
    /// Why.
    pub error: crate::error::SoftTissueError,
}

/// Sent when a body fails a phase (see [`SoftBodyFailed`]), or when the
/// contact response of a step fails (then `entity` is `None`: the step's
/// contact forces were not applied, and the next step detects afresh).
#[derive(Message, Debug, Clone, PartialEq)]
pub struct SoftBodyError {
    /// The body, if one failed.
    pub entity: Option<Entity>,
    /// The phase, for a body.
    pub phase: Option<FailedPhase>,
    /// What went wrong.
    pub error: crate::error::SoftTissueError,
}

/// The scene's contact solver (a resource).
#[derive(Resource, Debug, Default)]
pub struct SoftTissueContacts {
    /// The core solver.
    pub solver: ContactSolver,
    /// Body entities in the order given to the solver (sorted).
    pub bodies: Vec<Entity>,
    /// Tool entities in the order given to the solver (sorted).
    pub tools: Vec<Entity>,
    /// Whether the contact phases run this step.
    pub active: bool,
}
