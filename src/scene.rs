//! A complete simulation without Bevy: bodies, tools and the contact pipeline.
//!
//! [`Scene::step`] runs the same phases, in the same order, as the plugin's
//! system sets: assemble → factorize → free motion → detect → compliance →
//! LCP → correct. Contact phases are skipped when nothing can touch.

use crate::body::DeformableBody;
use crate::contact::{ContactReport, ContactSettings, ContactSolver, RigidTool};
use crate::error::Result;

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
        !self.bodies.is_empty() && (!self.tools.is_empty() || self.bodies.len() > 1)
    }

    /// Advances the scene by `h` seconds.
    pub fn step(&mut self, h: f64) -> Result<ContactReport> {
        let touch = self.can_touch();
        for b in &mut self.bodies {
            let rest_mode = b
                .settings()
                .compliance
                .unwrap_or(self.contact.settings().compliance)
                == crate::contact::ComplianceMode::RestPrecomputed;
            b.request_node_rotations(rest_mode && touch);
            b.assemble(h)?;
            b.update_preconditioner()?;
        }
        for b in &mut self.bodies {
            b.solve_free_motion()?;
        }
        if self.can_touch() {
            let mut bodies: Vec<&mut DeformableBody> = self.bodies.iter_mut().collect();
            let mut tools: Vec<&mut RigidTool> = self.tools.iter_mut().collect();
            self.contact.step(&mut bodies, &mut tools, h)?;
        }
        for t in &mut self.tools {
            t.end_step();
        }
        Ok(*self.contact.report())
    }
}
