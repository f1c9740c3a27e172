//! A complete simulation without Bevy, and the step's phases that
//! [`Scene::step`] and the plugin's systems share.
//!
//! The pipeline, written once in [`phases`]:
//!
//! ```text
//! per body:   phases::assemble → phases::factorize → phases::free_motion
//! contacts:   ContactSolver::detect → build_compliance → solve_lcp → correct   (PassKind::First)
//!             ContactSolver::refine                                             (PassKind::Refine)
//! per tool:   phases::end_step
//! ```
//!
//! [`Scene::step`] runs them in that order; the plugin runs each in its own
//! system set (`SoftTissueSystems`). Contact phases are skipped when nothing
//! can touch ([`phases::can_touch`]).

use crate::body::DeformableBody;
use crate::contact::{ComplianceBackend, ContactReport, ContactSettings, ContactSolver, RigidTool};
use crate::error::Result;

/// The phases of a step, shared by [`Scene::step`] and the plugin.
pub mod phases {
    use crate::body::DeformableBody;
    use crate::contact::{ContactSolver, RigidTool};
    use crate::error::Result;
    use crate::solver::cg::CgReport;

    /// Whether contact work is needed: a body, and a tool or a second body.
    pub fn can_touch(bodies: usize, tools: usize) -> bool {
        bodies > 0 && (tools > 0 || bodies > 1)
    }

    /// Assembly of one body: asks for the node rotations its compliance
    /// needs when contacts can happen, then element rotations, forces, `A`, `b`.
    pub fn assemble(
        body: &mut DeformableBody,
        contact: &ContactSolver,
        touch: bool,
        h: f64,
    ) -> Result<()> {
        body.request_node_rotations(touch && contact.needs_node_rotations(body.id()));
        body.assemble(h)
    }

    /// Preconditioner refresh of one body (factor swap, hand-off to the worker, warp).
    pub fn factorize(body: &mut DeformableBody) -> Result<()> {
        body.update_preconditioner()
    }

    /// Conjugate gradient and integration of one body to its free motion.
    pub fn free_motion(body: &mut DeformableBody) -> Result<CgReport> {
        body.solve_free_motion()
    }

    /// The end of a step for a tool: its pose becomes the reference for the
    /// next step's motion.
    pub fn end_step(tool: &mut RigidTool) {
        tool.end_step();
    }
}

/// Bodies, tools and their contact solver.
#[derive(Debug, Default)]
pub struct Scene {
    /// Deformable bodies.
    pub bodies: Vec<DeformableBody>,
    /// Rigid tools.
    pub tools: Vec<RigidTool>,
    /// The contact pipeline.
    pub contact: ContactSolver,
}

impl Scene {
    /// An empty scene with `settings` for contacts.
    pub fn new(settings: ContactSettings) -> Result<Self> {
        Ok(Self {
            bodies: Vec::new(),
            tools: Vec::new(),
            contact: ContactSolver::new(settings)?,
        })
    }

    /// Adds a body; returns its index.
    pub fn add_body(&mut self, body: DeformableBody) -> usize {
        self.bodies.push(body);
        self.bodies.len() - 1
    }

    /// Adds a tool; returns its index.
    pub fn add_tool(&mut self, tool: RigidTool) -> usize {
        self.tools.push(tool);
        self.tools.len() - 1
    }

    /// Whether contact work is needed: a tool, or at least two bodies.
    pub fn can_touch(&self) -> bool {
        phases::can_touch(self.bodies.len(), self.tools.len())
    }

    /// Advances the scene by `h` seconds.
    pub fn step(&mut self, h: f64) -> Result<ContactReport> {
        self.step_with(h, None)
    }

    /// [`Self::step`] with a compliance backend (the GPU) for the first
    /// contact pass of `Factorized` bodies.
    pub fn step_with(
        &mut self,
        h: f64,
        backend: Option<&mut dyn ComplianceBackend>,
    ) -> Result<ContactReport> {
        let touch = self.can_touch();
        for b in &mut self.bodies {
            phases::assemble(b, &self.contact, touch, h)?;
            phases::factorize(b)?;
        }
        for b in &mut self.bodies {
            phases::free_motion(b)?;
        }
        if touch {
            self.contact
                .step(&mut self.bodies, &mut self.tools, h, backend)?;
        }
        for t in &mut self.tools {
            phases::end_step(t);
        }
        Ok(*self.contact.report())
    }
}
