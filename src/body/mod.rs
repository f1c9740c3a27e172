//! A deformable body and its linearized implicit Euler step.
//!
//! [`DeformableBody`] owns a mesh, its material, its state (positions `x`,
//! velocities `v`), the assembled system and the preconditioner. One step of
//! size `h` solves the paper's equation (2):
//!
//! ```text
//! (M + hB + h²K) a = f(x, v) − h K v + f_ext + M g,   v ← v + h a,   x ← x + h v
//! ```
//!
//! with `K` the co-rotated stiffness and `B = αM + βK`. (The paper writes
//! `+hKv` with `K = ∂f/∂x`; here `K` is the positive stiffness, hence the
//! minus.) Damping terms are assembled only when `α` or `β` is nonzero;
//! gravity only when set.
//!
//! The step is split into the phases the plugin schedules separately, so that
//! contacts can be solved between free motion and the final positions:
//!
//! 1. [`DeformableBody::assemble`] — element rotations, forces and `A`, `b`, in place;
//! 2. [`DeformableBody::update_preconditioner`] — factor refresh / swap and rotation warp;
//! 3. [`DeformableBody::solve_free_motion`] — conjugate gradient and integration;
//! 4. (contacts) [`DeformableBody::apply_correction`] — positions and velocities corrected.
//!
//! [`DeformableBody::step`] runs 1–3.
//!
//! Only phase 3, once its checks have passed, and phase 4 change the state
//! (`x`, `v`): a phase that fails returns its error with the body still in
//! its state of the start of the step.
//!
//! ## Inverted elements
//! For an element pressed flat or through itself (`det F ≤ 0`) the rotation is
//! not unique: any `U S Vᵀ` of the SVD `F = U Σ Vᵀ` with a sign matrix `S` that
//! makes it proper is a candidate. [`RotationMethod::Polar`] takes the
//! candidate nearest the element's rotation of the step before
//! ([`crate::math::polar_rotation_near`]). The usual choice, flipping the
//! direction of the smallest singular value, jumps by a half turn when two
//! singular values cross: the matrix then changes by a rank-12 term per
//! flipping element, and the conjugate gradient, preconditioned by the factor
//! of a slightly older matrix, needs many more iterations (in the cataract
//! scene's squeezed lens, up to the 200-iteration limit). Keeping the last
//! rotation outright (no turning while inverted) is continuous too, but an
//! element that turns while inverted then carries a wrong rotation and a large
//! spurious force: it shot the coarse lens out of the eye at 87 mm/s. The
//! nearest candidate is kept only where the two smallest singular values are
//! close enough to cross ([`crate::math::SINGULAR_VALUES_CLOSE`]); elsewhere
//! the plain sign fix, which pushes the element back across its thinnest
//! direction: the nearest candidate there left elements of the delivered lens
//! inverted at rest, held by their neighbours
//! ([`DeformableBody::inverted_elements`] counts them).
//! [`DeformableBody::elastic_forces`] and [`DeformableBody::elastic_energy`]
//! have no history and use the plain sign fix.
//!
//! ## Constrained nodes
//! Fixed and kinematically driven nodes get a prescribed acceleration `a_i`.
//! Their columns are moved to the right-hand side and their rows and columns
//! replaced by a scaled identity, so `A` stays symmetric positive definite and
//! its pattern (and symbolic factorization) never changes.

mod settings;

use std::time::Instant;

use crate::error::{Result, SoftTissueError, check_timestep, check_vector};
use crate::fem::assembly::{BlockCsr, BlockPattern};
use crate::fem::{AssemblyInput, AssemblyOutput, Element, RotationMethod, assemble_element, lanes};
use crate::material::TissueMaterial;
use crate::math::{Mat3, Vec3, polar_rotation_fast};
use crate::mesh::{Surface, TetMesh};
use crate::solver::PreconditionerState;
use crate::solver::cg::{self, CgReport, CgScratch};
use crate::solver::columns::ColumnPrefetch;
use settings::validate_settings;
pub use settings::{BodySettings, NodeConstraint, StepReport, StepTimings};
use std::sync::Arc;

/// A deformable tetrahedral body (see the module docs).
#[derive(Debug)]
pub struct DeformableBody {
    id: u64,
    mesh: TetMesh,
    surface: Surface,
    material: TissueMaterial,
    young: Vec<f64>,
    elements: Vec<Element>,
    mass: Vec<f64>,
    x: Vec<Vec3>,
    x_start: Vec<Vec3>,
    v: Vec<Vec3>,
    accel: Vec<Vec3>,
    prescribed: Vec<Vec3>,
    constraint: Vec<NodeConstraint>,
    drive_target: Vec<Vec3>,
    external: Vec<Vec3>,
    has_external: bool,
    matrix: BlockCsr,
    rhs: Vec<Vec3>,
    elem_rot: Vec<Mat3>,
    node_rot: Vec<Mat3>,
    want_node_rotations: bool,
    precond: PreconditionerState,
    settings: BodySettings,
    step_index: u64,
    h: f64,
    scratch: CgScratch,
    report: StepReport,
}

fn build_elements(mesh: &TetMesh, material: &TissueMaterial, young: &[f64]) -> Vec<Element> {
    mesh.tets()
        .iter()
        .zip(young)
        .map(|(t, &e)| {
            let (lambda, mu) = material.lame(e);
            Element::new(*t, t.map(|v| mesh.positions()[v]), lambda, mu)
        })
        .collect()
}

fn lumped_mass(mesh: &TetMesh, elements: &[Element], density: f64) -> Vec<f64> {
    let mut m = vec![0.0; mesh.num_vertices()];
    for e in elements {
        for &n in &e.nodes {
            m[n] += density * e.volume / 4.0;
        }
    }
    m
}

impl DeformableBody {
    /// Creates a body at rest in its mesh's configuration.
    pub fn new(mesh: TetMesh, material: TissueMaterial, settings: BodySettings) -> Result<Self> {
        validate_settings(&settings)?;
        let young = material.element_young(&mesh)?;
        let elements = build_elements(&mesh, &material, &young);
        let mass = lumped_mass(&mesh, &elements, material.density);
        let n = mesh.num_vertices();
        let pattern = Arc::new(BlockPattern::new(n, mesh.tets()));
        let matrix = BlockCsr::zeros(pattern);
        let precond = PreconditionerState::new(settings.preconditioner, &matrix)?;
        let surface = mesh.surface();
        let x = mesh.positions().to_vec();
        static NEXT_ID: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);
        Ok(Self {
            id: NEXT_ID.fetch_add(1, std::sync::atomic::Ordering::Relaxed),
            x_start: x.clone(),
            surface,
            young,
            elements,
            mass,
            v: vec![Vec3::zeros(); n],
            accel: vec![Vec3::zeros(); n],
            prescribed: vec![Vec3::zeros(); n],
            constraint: vec![NodeConstraint::Free; n],
            drive_target: x.clone(),
            external: vec![Vec3::zeros(); n],
            has_external: false,
            rhs: vec![Vec3::zeros(); n],
            elem_rot: vec![Mat3::identity(); mesh.num_tets()],
            node_rot: vec![Mat3::identity(); n],
            want_node_rotations: false,
            precond,
            settings,
            step_index: 0,
            h: 0.0,
            scratch: CgScratch::new(n),
            report: StepReport::default(),
            matrix,
            x,
            material,
            mesh,
        })
    }

    /// A process-unique id (contact caches are keyed by it).
    pub fn id(&self) -> u64 {
        self.id
    }

    /// Positions at the start of the current step (before free motion).
    pub fn start_positions(&self) -> &[Vec3] {
        &self.x_start
    }

    /// The rest mesh.
    pub fn mesh(&self) -> &TetMesh {
        &self.mesh
    }

    /// The boundary surface.
    pub fn surface(&self) -> &Surface {
        &self.surface
    }

    /// The material.
    pub fn material(&self) -> &TissueMaterial {
        &self.material
    }

    /// Young's modulus of every element.
    pub fn element_young(&self) -> &[f64] {
        &self.young
    }

    /// Rest data of every element.
    pub fn elements(&self) -> &[Element] {
        &self.elements
    }

    /// Lumped nodal masses.
    pub fn mass(&self) -> &[f64] {
        &self.mass
    }

    /// Number of nodes.
    pub fn num_nodes(&self) -> usize {
        self.x.len()
    }

    /// Current positions.
    pub fn positions(&self) -> &[Vec3] {
        &self.x
    }

    /// Current velocities.
    pub fn velocities(&self) -> &[Vec3] {
        &self.v
    }

    /// Solver settings.
    pub fn settings(&self) -> &BodySettings {
        &self.settings
    }

    /// Step size of the last assembly (0 before the first).
    pub fn step_size(&self) -> f64 {
        self.h
    }

    /// Number of steps taken.
    pub fn step_index(&self) -> u64 {
        self.step_index
    }

    /// Report of the last step.
    pub fn report(&self) -> &StepReport {
        &self.report
    }

    /// The assembled system matrix `A` of the last step.
    pub fn system_matrix(&self) -> &BlockCsr {
        &self.matrix
    }

    /// The preconditioner (its factor is reused by contact compliance).
    pub fn preconditioner(&self) -> &PreconditionerState {
        &self.precond
    }

    /// The node-column hand-over between the contact compliance and the
    /// background factorizer (see [`ColumnPrefetch`]).
    pub fn column_prefetch_mut(&mut self) -> &mut ColumnPrefetch {
        self.precond.column_prefetch_mut()
    }

    /// Node rotations of the last step (identity unless computed).
    pub fn node_rotations(&self) -> &[Mat3] {
        &self.node_rot
    }

    /// Element rotations of the last step.
    pub fn element_rotations(&self) -> &[Mat3] {
        &self.elem_rot
    }

    /// Boundary condition of every node.
    pub fn constraints(&self) -> &[NodeConstraint] {
        &self.constraint
    }

    /// Asks for node rotations every step even when the preconditioner does not
    /// need them (contacts warp the Jacobian with them).
    pub fn request_node_rotations(&mut self, on: bool) {
        self.want_node_rotations = on;
    }

    fn check_node(&self, node: usize) -> Result<()> {
        if node >= self.x.len() {
            return Err(SoftTissueError::NodeOutOfRange {
                node,
                len: self.x.len(),
            });
        }
        Ok(())
    }

    /// Holds `nodes` in place.
    pub fn fix_nodes(&mut self, nodes: &[usize]) -> Result<()> {
        for &n in nodes {
            self.check_node(n)?;
        }
        for &n in nodes {
            self.constraint[n] = NodeConstraint::Fixed;
        }
        Ok(())
    }

    /// Holds every node whose rest position satisfies `pred`; returns how many.
    pub fn fix_where(&mut self, pred: impl Fn(&Vec3) -> bool) -> usize {
        let mut count = 0;
        for (i, p) in self.mesh.positions().iter().enumerate() {
            if pred(p) {
                self.constraint[i] = NodeConstraint::Fixed;
                count += 1;
            }
        }
        count
    }

    /// Drives `node` to `target` by the end of each following step.
    pub fn drive_node(&mut self, node: usize, target: Vec3) -> Result<()> {
        self.check_node(node)?;
        if !target.iter().all(|c| c.is_finite()) {
            return Err(SoftTissueError::NonFinite("drive target"));
        }
        self.constraint[node] = NodeConstraint::Driven;
        self.drive_target[node] = target;
        Ok(())
    }

    /// Releases `node`.
    pub fn free_node(&mut self, node: usize) -> Result<()> {
        self.check_node(node)?;
        self.constraint[node] = NodeConstraint::Free;
        Ok(())
    }

    /// Sets a constant external force on `node` (newtons).
    pub fn set_external_force(&mut self, node: usize, force: Vec3) -> Result<()> {
        self.check_node(node)?;
        check_vector("external force", &force)?;
        self.external[node] = force;
        self.has_external = self.external.iter().any(|f| *f != Vec3::zeros());
        Ok(())
    }

    /// Removes all external forces.
    pub fn clear_external_forces(&mut self) {
        self.external.fill(Vec3::zeros());
        self.has_external = false;
    }

    /// Replaces the material (for example a new stiffness field) keeping the state.
    pub fn set_material(&mut self, material: TissueMaterial) -> Result<()> {
        let young = material.element_young(&self.mesh)?;
        self.elements = build_elements(&self.mesh, &material, &young);
        self.mass = lumped_mass(&self.mesh, &self.elements, material.density);
        self.young = young;
        self.material = material;
        Ok(())
    }

    /// Replaces the solver settings (a new preconditioner restarts its factor).
    pub fn set_settings(&mut self, settings: BodySettings) -> Result<()> {
        validate_settings(&settings)?;
        if settings.preconditioner != self.settings.preconditioner {
            self.precond = PreconditionerState::new(settings.preconditioner, &self.matrix)?;
        }
        self.settings = settings;
        Ok(())
    }

    /// Overwrites positions and velocities (for example to start deformed).
    pub fn set_state(&mut self, x: &[Vec3], v: &[Vec3]) -> Result<()> {
        let n = self.x.len();
        for (name, len) in [("positions", x.len()), ("velocities", v.len())] {
            if len != n {
                return Err(SoftTissueError::LengthMismatch {
                    name,
                    got: len,
                    expected: n,
                });
            }
        }
        if !x.iter().chain(v).all(|p| p.iter().all(|c| c.is_finite())) {
            return Err(SoftTissueError::NonFinite("state"));
        }
        self.x.copy_from_slice(x);
        self.v.copy_from_slice(v);
        Ok(())
    }

    /// Moves every node by `offset` (positions only).
    pub fn translate(&mut self, offset: Vec3) {
        for p in &mut self.x {
            *p += offset;
        }
        for p in &mut self.drive_target {
            *p += offset;
        }
    }

    /// Elastic forces at the current positions (no damping, no gravity), per node.
    pub fn elastic_forces(&self, out: &mut [Vec3]) {
        out.fill(Vec3::zeros());
        for e in &self.elements {
            let xe = e.nodes.map(|n| self.x[n]);
            let r = e.rotation(self.settings.rotation, &xe);
            let f = e.forces(&r, &xe);
            for a in 0..4 {
                out[e.nodes[a]] += f[a];
            }
        }
    }

    /// Strain energy of the co-rotated model at the current positions.
    pub fn elastic_energy(&self) -> f64 {
        self.elements
            .iter()
            .map(|e| {
                let xe = e.nodes.map(|n| self.x[n]);
                e.energy(&e.rotation(self.settings.rotation, &xe), &xe)
            })
            .sum()
    }

    /// Elements flat or inverted at the current positions (`det F ≤ 0`):
    /// tissue pressed through itself, which the co-rotated model pushes back
    /// (see the module docs, "Inverted elements") but which a scene can leave
    /// behind, held by its neighbours. A check of the local deformation, not
    /// used by the step; one pass over the elements.
    pub fn inverted_elements(&self) -> usize {
        self.elements
            .iter()
            .filter(|e| {
                let xe = e.nodes.map(|n| self.x[n]);
                e.deformation_gradient(&xe).determinant() <= 0.0
            })
            .count()
    }

    /// Kinetic energy.
    pub fn kinetic_energy(&self) -> f64 {
        self.v
            .iter()
            .zip(&self.mass)
            .map(|(v, m)| 0.5 * m * v.norm_squared())
            .sum()
    }

    /// Phase 1: element rotations, forces and the system `A a = b`, in place.
    pub fn assemble(&mut self, h: f64) -> Result<()> {
        check_timestep(h)?;
        let t0 = Instant::now();
        if !self
            .x
            .iter()
            .chain(&self.v)
            .all(|p| p.iter().all(|c| c.is_finite()))
        {
            return Err(SoftTissueError::NonFinite("body state"));
        }
        self.h = h;
        let damp = if self.settings.damping {
            self.material.damping
        } else {
            crate::material::RayleighDamping::default()
        };
        self.report.damping = !damp.is_zero();
        self.report.gravity = self.settings.gravity.is_some();
        let c_m = 1.0 + h * damp.mass;
        let c_k = h * damp.stiffness + h * h;
        let c_v = damp.stiffness + h;
        self.matrix.clear();
        let pattern = Arc::clone(&self.matrix.pattern);
        let g = self.settings.gravity;
        for i in 0..self.x.len() {
            let m = self.mass[i];
            self.matrix.values[pattern.diag[i]] = Mat3::identity() * (c_m * m);
            let mut b = Vec3::zeros();
            if let Some(g) = g {
                b += g * m;
            }
            if self.has_external {
                b += self.external[i];
            }
            if damp.mass != 0.0 {
                b -= self.v[i] * (damp.mass * m);
            }
            self.rhs[i] = b;
        }
        let method = self.settings.rotation;
        let input = AssemblyInput {
            x: &self.x,
            v: &self.v,
            c_k,
            c_v,
        };
        let mut out = AssemblyOutput {
            values: &mut self.matrix.values,
            rhs: &mut self.rhs,
        };
        let slots = &pattern.element_slots;
        // Four elements at a time where the CPU allows; the rest below.
        let first = match method {
            RotationMethod::Polar => {
                lanes::assemble_polar(&self.elements, slots, input, &mut self.elem_rot, &mut out)
            }
            RotationMethod::Qr => 0,
        };
        for ei in first..self.elements.len() {
            let (e, rot) = (&self.elements[ei], &mut self.elem_rot[ei]);
            assemble_element(e, method, input, &slots[ei], rot, &mut out);
        }
        self.apply_constraints(h);
        self.report.timings.assemble = t0.elapsed().as_secs_f64();
        Ok(())
    }

    fn apply_constraints(&mut self, h: f64) {
        if self.constraint.iter().all(|c| *c == NodeConstraint::Free) {
            return;
        }
        for i in 0..self.x.len() {
            self.prescribed[i] = match self.constraint[i] {
                NodeConstraint::Free => continue,
                NodeConstraint::Fixed => -self.v[i] / h,
                NodeConstraint::Driven => ((self.drive_target[i] - self.x[i]) / h - self.v[i]) / h,
            };
        }
        let p = Arc::clone(&self.matrix.pattern);
        for r in 0..p.n {
            let row_fixed = self.constraint[r] != NodeConstraint::Free;
            let diag_scale = self.matrix.values[p.diag[r]].trace() / 3.0;
            for s in p.row_ptr[r]..p.row_ptr[r + 1] {
                let c = p.col_idx[s];
                let col_fixed = self.constraint[c] != NodeConstraint::Free;
                if !row_fixed && col_fixed {
                    let moved = self.matrix.values[s] * self.prescribed[c];
                    self.rhs[r] -= moved;
                }
                if row_fixed || col_fixed {
                    self.matrix.values[s] = Mat3::zeros();
                }
            }
            if row_fixed {
                self.matrix.values[p.diag[r]] = Mat3::identity() * diag_scale;
                self.rhs[r] = self.prescribed[r] * diag_scale;
            }
        }
    }

    fn compute_node_rotations(&mut self) {
        self.node_rot.fill(Mat3::zeros());
        for (e, r) in self.elements.iter().zip(&self.elem_rot) {
            for &n in &e.nodes {
                self.node_rot[n] += r;
            }
        }
        let done = lanes::polar_rotations(&mut self.node_rot);
        for r in &mut self.node_rot[done..] {
            *r = polar_rotation_fast(r);
        }
    }

    /// Phase 2: preconditioner refresh (factor swap or factorization) and warp.
    pub fn update_preconditioner(&mut self) -> Result<()> {
        let t0 = Instant::now();
        if self.settings.preconditioner.needs_rotations() || self.want_node_rotations {
            self.compute_node_rotations();
        }
        self.precond
            .update(&self.matrix, &self.node_rot, self.step_index)?;
        self.report.preconditioner = self.precond.stats();
        self.report.timings.factorize = t0.elapsed().as_secs_f64();
        Ok(())
    }

    /// Phase 3: solves `A a = b` by CG and integrates to the free-motion state.
    pub fn solve_free_motion(&mut self) -> Result<CgReport> {
        let h = self.h;
        if h <= 0.0 {
            return Err(SoftTissueError::InvalidParameter {
                name: "h",
                value: h,
                reason: "assemble must run before solve_free_motion",
            });
        }
        // Finite components are not enough: CG measures `|b|²`, and if that
        // overflows it would stop at once and drop the force.
        let b2: f64 = self.rhs.iter().map(|b| b.norm_squared()).sum();
        if !b2.is_finite() {
            return Err(SoftTissueError::NonFinite(
                "right-hand side (forces too large: |b|² overflows)",
            ));
        }
        let t0 = Instant::now();
        if !self.settings.cg.warm_start {
            self.accel.fill(Vec3::zeros());
        }
        for i in 0..self.x.len() {
            if self.constraint[i] != NodeConstraint::Free {
                self.accel[i] = self.prescribed[i];
            }
        }
        let mut report = CgReport::default();
        for attempt in 0..2 {
            let r = cg::solve(
                &self.matrix,
                &self.rhs,
                &mut self.accel,
                &mut self.precond,
                &self.settings.cg,
                &mut self.scratch,
            );
            report.iterations += r.iterations;
            report.precond_seconds += r.precond_seconds;
            report.converged = r.converged;
            report.residual = r.residual;
            // Rescue: the factor in use may be from a shape the matrix has left
            // (a sudden large deformation). Rather than take an unconverged step,
            // factorize the current matrix now, once, and go on from the last
            // iterate. This blocks the step, so it is the exception.
            let rescue = attempt == 0
                && !r.converged
                && self
                    .precond
                    .refactor_now(&self.matrix, &self.node_rot, self.step_index)?;
            if !rescue {
                break;
            }
            self.report.preconditioner = self.precond.stats();
        }
        self.x_start.copy_from_slice(&self.x);
        for i in 0..self.x.len() {
            self.v[i] += self.accel[i] * h;
            self.x[i] += self.v[i] * h;
        }
        self.report.cg = report;
        self.report.timings.cg_total = t0.elapsed().as_secs_f64();
        self.report.timings.precond_apply = report.precond_seconds;
        self.step_index += 1;
        Ok(report)
    }

    /// Factorizes this step's matrix now, on the stepping thread, for a
    /// preconditioner whose factor lags the matrix (`Periodic`, `Async`,
    /// `AsyncLagged`); for the other kinds does nothing and returns `false`.
    /// The contact correction calls it when the lagging factor's correction
    /// would not be consistent with the matrix
    /// ([`crate::contact::ContactSettings::consistency_tolerance`]). Counted in
    /// [`crate::solver::PreconditionerStats::rescues`].
    pub fn refactor_preconditioner_now(&mut self) -> Result<bool> {
        // After the free motion the step index already names the next step.
        let step = self.step_index.saturating_sub(1);
        let made = self
            .precond
            .refactor_now(&self.matrix, &self.node_rot, step)?;
        self.report.preconditioner = self.precond.stats();
        Ok(made)
    }

    /// Runs assembly, preconditioner update and free motion: one full step without contacts.
    pub fn step(&mut self, h: f64) -> Result<StepReport> {
        self.assemble(h)?;
        self.update_preconditioner()?;
        self.solve_free_motion()?;
        Ok(self.report)
    }

    /// Phase 4: adds a position correction `dx` (and `dx / h` to the velocities)
    /// to every free node.
    pub fn apply_correction(&mut self, dx: &[Vec3]) {
        let inv_h = if self.h > 0.0 { 1.0 / self.h } else { 0.0 };
        for i in 0..self.x.len() {
            if self.constraint[i] == NodeConstraint::Free {
                self.x[i] += dx[i];
                self.v[i] += dx[i] * inv_h;
            }
        }
    }
}
