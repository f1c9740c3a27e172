//! Contact response: detection, compliance, friction LCP and correction.
//!
//! This is the paper's section 4. After every body has moved freely
//! ([`crate::body::DeformableBody::solve_free_motion`]), [`ContactSolver`]
//! runs the phases below, each in its own file that owns its state. This file
//! only orchestrates them.
//!
//! ```text
//!              ┌──────────────── PassKind::First ─────────────────┐
//! free motion → predict → detect → jacobian → compliance → lcp → correct
//!                            ↑                                       │
//!                            └──── PassKind::Refine, while a vertex ─┘
//!                                  penetrates deeper than the tolerance
//! ```
//!
//! | phase | file | owns |
//! |---|---|---|
//! | prediction | `predict.rs` | each body's last correction, the shifted positions of a first pass |
//! | detection | `detect/mod.rs`, `detect/geometry.rs` | BVHs, vertex–tool and vertex–triangle contacts |
//! | Jacobian | `jacobian.rs` | rows, `μ`, `δ₀`, the entries of `H` per body |
//! | compliance | `compliance/` (one file per [`ComplianceMode`]) | per body: factor view, snapshot, cached node columns, rest inverse |
//! | LCP | `lcp/` | the solvers, their shared residual, the warm start, recorded problems |
//! | correction | `correct.rs` | `Δx`, `Δv`, tool reactions |
//! | settings | `settings.rs` | [`ContactSettings`], the one home of every contact setting |
//! | access | `bodies.rs` | [`Bodies`] / [`Tools`]: bodies and tools by index, from slices or ECS views |
//!
//! 1. **Detect** ([`ContactSolver::detect`]): surface vertices against rigid
//!    [`RigidTool`]s (parry3d-f64) and against the surface triangles of other
//!    bodies. Each contact has a normal, two tangents and a gap `δ₀`. With
//!    [`ContactSettings::predict`] (the default) the first pass looks for
//!    contacts where held contacts will be and linearizes its gaps back to the
//!    free motion.
//! 2. **Compliance** ([`ContactSolver::build_compliance`]): the Jacobian `H`
//!    — one normal row per contact, plus two tangent rows when `μ > 0` — and
//!    `W = Σ_bodies h² H A⁻¹ Hᵀ`, per body with its [`ComplianceMode`].
//! 3. **LCP** ([`ContactSolver::solve_lcp`]): Signorini contact with a
//!    circular Coulomb cone ([`lcp`]; by default block Gauss–Seidel with a
//!    semismooth Newton step on the active set, [`LcpSolver::Subspace`]),
//!    warm-started in the first pass.
//! 4. **Correct** ([`ContactSolver::correct`]): `Δx = h² A⁻¹ Hᵀ λ` with the
//!    same approximation of `A⁻¹` as `W`, `Δv = Δx / h`, and the reaction on
//!    each tool.
//! 5. **Refine** ([`ContactSolver::refine`]): further frictionless passes while
//!    a vertex still penetrates ([`ContactSettings::max_passes`]). From the
//!    eighth pass on, a vertex whose normal turned keeps the last pass's
//!    plane as well (`held.rs`), which ends the few steps whose vertices
//!    otherwise alternate between two faces up to the pass limit.
//!
//! A scene without tools or touching bodies does no detection work, one
//! without contacts no compliance or LCP work, and `μ = 0` adds no friction rows.
//!
//! ## Adding things
//! - an LCP solver: a sweep in `lcp/` and a variant of [`LcpSolver`];
//! - a compliance mode: a variant of [`ComplianceMode`] and a file in
//!   `compliance/`; the exhaustive `match`es show every place to handle it;
//! - a tool shape: a variant of [`ToolShape`] in `tool.rs` (detection asks the
//!   tool for its proximity and bounds only).

mod bodies;
pub mod compliance;
mod correct;
pub mod detect;
mod held;
mod jacobian;
pub mod lcp;
pub mod predict;
mod settings;
pub mod tool;
mod tool_problem;
mod types;

use std::time::Instant;

pub use bodies::{
    AsBody, AsBodyMut, AsTool, AsToolMut, Bodies, BodiesMut, NO_TOOLS, Tools, ToolsMut,
};
use compliance::WBlock;
pub use compliance::{BodyCompliance, ComplianceBackend, ComplianceMode, FactorKey, JacEntry};
pub use lcp::{LcpReport, LcpSettings, LcpSolver};
pub use settings::ContactSettings;
pub use tool::{Pose, RigidTool, ToolShape};
pub use tool_problem::ToolContactProblem;
pub use types::{Contact, ContactOther, ContactReport, ContactSide, PassKind, tangent_basis};

use crate::error::{Result, SoftTissueError, check_timestep};
use crate::math::Vec3;
use detect::{DetectBody, DetectParams};
use jacobian::Jacobian;
use lcp::{ContactKey, ContactProblem, LcpScratch, OtherKey, WarmStart};
use predict::Prediction;

/// The relative shift of the diagonal of each tool face contact's row of `W`
/// in a first pass ([`ContactSettings::tool_faces`]): its solve sees
/// `W_ii (1 + FACE_ROW_SHIFT)`, so a face may stay in by up to
/// `FACE_ROW_SHIFT · W_ii λ_i`, a small part of what its own force moves it;
/// the refinement passes, unshifted, take out what is left beyond the
/// penetration tolerance.
///
/// A face contact's row acts on its triangle's three nodes along nearly the
/// normal of its corners' own contacts, so it is nearly a combination of
/// their rows: in first-pass problems of the cataract jam the smallest pivot
/// of the normal rows' block of `W` was 10⁻⁷–10⁻¹⁶ of its diagonal with the
/// face rows, against 10⁻³ without them. The forces are then not unique,
/// and the subspace LCP ran to its sweep cap in 9 of the 289 first passes
/// of a delivery with more than 90 contacts (test
/// `a_problem_with_face_contacts_solves_with_their_rows_shifted`); with the
/// shift none did, and the 289 took 632 sweeps in all instead of 7 536. A
/// shift of 10⁻¹ let the lens slip off the blade (see "Tool contacts inside
/// faces" in docs/benchmark-log.md).
pub const FACE_ROW_SHIFT: f64 = 3e-3;

/// The contact pipeline (see the module docs). Keep one per scene; it caches
/// per-body data (BVHs, node columns, previous forces) between steps.
#[derive(Debug, Default)]
pub struct ContactSolver {
    settings: ContactSettings,
    /// Per-body compliance modes that differ from the settings' default, by body id.
    overrides: Vec<(u64, ComplianceMode)>,
    /// Per body index: the body's id, and each phase's state.
    ids: Vec<u64>,
    detect: Vec<DetectBody>,
    predict: Vec<Prediction>,
    compliance: Vec<BodyCompliance>,
    modes: Vec<ComplianceMode>,
    contacts: Vec<Contact>,
    jac: Jacobian,
    w: Vec<f64>,
    /// Per row of `w`, during a build: whether a body has written it yet.
    row_written: Vec<bool>,
    lambda: Vec<f64>,
    lcp_scratch: LcpScratch,
    warm: WarmStart,
    /// First-pass problems with at least this many contacts, and every solve
    /// that ran to its sweep limit, are kept for
    /// [`Self::take_recorded_problem`] (see [`Self::record_problems`]).
    record_from: Option<usize>,
    recorded: Option<ContactProblem>,
    dx: Vec<Vec<Vec3>>,
    stale: Vec<usize>,
    /// Scratch of the correction: one body's nodal forces of a pass.
    pass_forces: Vec<Vec3>,
    /// Per body index, per node: the contact force of the step, all passes.
    node_forces: Vec<Vec<Vec3>>,
    report: ContactReport,
    /// The tool whose contact problem is kept (see [`Self::capture_tool`]).
    captured_tool: Option<usize>,
    tool_problem: ToolContactProblem,
    selected: Vec<usize>,
    /// Late refinement passes: the last pass's penetrated contacts, whose
    /// planes the next pass keeps where its detection turned the vertex's
    /// normal (see [`Self::refine`] and [`held::HOLD_FROM_PASS`]).
    held: Vec<Contact>,
    /// The last pass's tool contacts inside faces, which the next
    /// refinement pass keeps ([`detect::keep_faces`]).
    faces: Vec<Contact>,
    /// A first pass's face rows' diagonal entries of `w` (index into `w`,
    /// unshifted value; [`FACE_ROW_SHIFT`]), put back after its solve.
    face_diagonal: Vec<(usize, f64)>,
    h: f64,
    /// First passes so far (the prediction's step count).
    steps: u64,
}

impl ContactSolver {
    /// A solver with `settings`.
    pub fn new(settings: ContactSettings) -> Result<Self> {
        settings.validate()?;
        Ok(Self {
            settings,
            ..Default::default()
        })
    }

    /// Keeps, after every step, the contact problem of tool `tool` (its
    /// index in the tools given to the phases) linearized in its pose, for a
    /// haptic loop ([`Self::tool_problem`], [`ToolContactProblem`]); `None`
    /// (the default) keeps none. It costs a copy of the tool rows' block of
    /// `W` per step.
    pub fn capture_tool(&mut self, tool: Option<usize>) {
        self.captured_tool = tool;
        self.tool_problem.clear();
    }

    /// The contact problem of the tool chosen with [`Self::capture_tool`] at
    /// the last step (empty when it touched nothing).
    pub fn tool_problem(&self) -> &ToolContactProblem {
        &self.tool_problem
    }

    /// Keeps a copy of every first-pass contact problem with at least
    /// `min_contacts` contacts, and of every problem (any pass) whose solve
    /// ran to its sweep limit (`None`: keep none, the default), to be taken
    /// with [`Self::take_recorded_problem`] and replayed through any solver
    /// ([`ContactProblem`]), as the solver got it: with face contacts, a
    /// first pass's face rows shifted ([`FACE_ROW_SHIFT`]). Recording copies
    /// `W`: a tool for benchmarks, not for every step of a running scene.
    pub fn record_problems(&mut self, min_contacts: Option<usize>) {
        self.record_from = min_contacts;
        if min_contacts.is_none() {
            self.recorded = None;
        }
    }

    /// The last recorded problem (see [`Self::record_problems`]), if one was
    /// recorded since the last take.
    pub fn take_recorded_problem(&mut self) -> Option<ContactProblem> {
        self.recorded.take()
    }

    /// Forgets every body's cached node columns and Gram blocks (their memory is
    /// kept), as a new factor does; for benchmarks of the cold build.
    pub fn forget_columns(&mut self) {
        for c in &mut self.compliance {
            c.forget_columns();
        }
    }

    /// Settings.
    pub fn settings(&self) -> &ContactSettings {
        &self.settings
    }

    /// Replaces the settings.
    pub fn set_settings(&mut self, settings: ContactSettings) -> Result<()> {
        settings.validate()?;
        self.settings = settings;
        Ok(())
    }

    /// Gives the body with id `body_id` its own compliance mode (`None`: the
    /// settings' [`ContactSettings::compliance`]).
    pub fn set_body_compliance(&mut self, body_id: u64, mode: Option<ComplianceMode>) {
        self.overrides.retain(|(id, _)| *id != body_id);
        if let Some(m) = mode {
            self.overrides.push((body_id, m));
        }
    }

    /// The compliance mode of the body with id `body_id`.
    pub fn body_compliance(&self, body_id: u64) -> ComplianceMode {
        self.overrides
            .iter()
            .find(|(id, _)| *id == body_id)
            .map_or(self.settings.compliance, |(_, m)| *m)
    }

    /// Whether the body with id `body_id` must compute node rotations every
    /// step for its compliance ([`ComplianceMode::needs_node_rotations`]).
    pub fn needs_node_rotations(&self, body_id: u64) -> bool {
        self.body_compliance(body_id).needs_node_rotations()
    }

    /// Contacts of the last pass (forces filled after the LCP).
    pub fn contacts(&self) -> &[Contact] {
        &self.contacts
    }

    /// Counters and timings of the last step.
    pub fn report(&self) -> &ContactReport {
        &self.report
    }

    /// The Delassus matrix `W` of the last pass (row-major, `rows × rows`).
    pub fn delassus(&self) -> (&[f64], usize) {
        (&self.w, self.jac.m())
    }

    /// Row offsets per contact: rows of contact `c` are `offsets[c]..offsets[c+1]`.
    pub fn row_offsets(&self) -> &[usize] {
        &self.jac.rows
    }

    /// Jacobian entries of body `i` (valid after [`Self::build_compliance`]).
    pub fn jacobian(&self, i: usize) -> &[JacEntry] {
        self.jac.entries.get(i).map(|e| &e[..]).unwrap_or(&[])
    }

    /// The contact force on each node of body `i` in the last step, summed
    /// over its passes (`Σ_passes Hᵀ λ`, newtons). With the implicit step these
    /// are end-of-step forces: their work in the step is `Σ_n f_n · (x_n − x_n,start)`.
    pub fn contact_forces(&self, i: usize) -> &[Vec3] {
        self.node_forces.get(i).map(|f| &f[..]).unwrap_or(&[])
    }

    /// Total contact force exerted on body `i` in the last pass (`Σ Hᵀ λ`).
    pub fn body_force(&self, i: usize) -> Vec3 {
        self.jacobian(i)
            .iter()
            .map(|e| e.h * self.lambda[e.row as usize])
            .sum()
    }

    /// Keeps one state per body index, fresh where the body changed.
    fn sync_bodies<B: Bodies + ?Sized>(&mut self, bodies: &B) {
        let n = bodies.len();
        self.ids.resize(n, 0);
        self.detect.resize_with(n, DetectBody::default);
        self.predict.resize_with(n, Prediction::default);
        self.compliance.resize_with(n, BodyCompliance::new);
        self.modes.resize(n, ComplianceMode::default());
        for i in 0..n {
            let b = bodies.body(i);
            if self.ids[i] != b.id() {
                self.ids[i] = b.id();
                self.detect[i] = DetectBody::new(b.surface().volume_triangles().collect());
                self.predict[i] = Prediction::default();
                self.compliance[i] = BodyCompliance::new();
            }
            self.modes[i] = self.body_compliance(b.id());
        }
    }

    /// Phase 1: finds contacts at the bodies' free-motion positions (in a
    /// first pass with [`ContactSettings::predict`], at the predicted
    /// ones; the gaps `δ₀` are those of the free motion either way).
    pub fn detect<B: Bodies + ?Sized, T: Tools + ?Sized>(
        &mut self,
        bodies: &B,
        tools: &T,
        h: f64,
        pass: PassKind,
    ) -> Result<()> {
        let t0 = Instant::now();
        check_timestep(h)?;
        self.h = h;
        self.contacts.clear();
        match pass {
            PassKind::First => {
                self.report = ContactReport::default();
                self.steps += 1;
                self.tool_problem.clear();
                self.tool_problem.step = self.steps;
                self.node_forces.resize_with(bodies.len(), Vec::new);
                for (i, f) in self.node_forces.iter_mut().enumerate() {
                    f.clear();
                    f.resize(bodies.body(i).num_nodes(), Vec3::zeros());
                }
            }
            PassKind::Refine => self.report.pairs_tested = 0,
        }
        self.sync_bodies(bodies);
        for i in 0..bodies.len() {
            let b = bodies.body(i);
            if pass == PassKind::First {
                self.predict[i].begin_step(b.num_nodes(), self.steps, self.settings.predict);
            }
            self.predict[i].fill(b, pass, &mut self.detect[i]);
        }
        let params = DetectParams {
            margin: self.settings.alarm_distance,
            body_friction: self.settings.body_friction,
            tool_faces: self.settings.tool_faces,
            face_deeper: self.settings.penetration_tolerance,
        };
        self.report.pairs_tested =
            detect::detect(&mut self.detect, bodies, tools, params, &mut self.contacts);
        if params.tool_faces {
            if pass == PassKind::Refine {
                detect::keep_faces(
                    &self.faces,
                    &self.detect,
                    tools,
                    params.margin,
                    &mut self.contacts,
                );
            }
            self.faces.clear();
            let faces = self.contacts.iter().filter(|c| detect::is_tool_face(c));
            self.faces.extend(faces);
        }
        if pass == PassKind::Refine || !self.settings.friction {
            for c in &mut self.contacts {
                c.mu = 0.0;
                c.slip = [0.0; 2];
            }
        }
        self.report.max_penetration = self.contacts.iter().map(|c| -c.gap).fold(0.0, f64::max);
        if pass == PassKind::First {
            self.report.contacts = self.contacts.len();
            self.report.first_penetration = self.report.max_penetration;
        }
        self.report.detect += t0.elapsed().as_secs_f64();
        Ok(())
    }

    /// Replaces the detected contacts with `contacts` (for custom detection and
    /// benchmarks) as a first pass; `h` is the step size used by the following phases.
    pub fn set_contacts<B: Bodies + ?Sized>(
        &mut self,
        contacts: &[Contact],
        bodies: &B,
        h: f64,
    ) -> Result<()> {
        check_timestep(h)?;
        for c in contacts {
            let sides = std::iter::once(&c.a).chain(match &c.other {
                ContactOther::Body(b) => Some(b),
                ContactOther::Tool(_) => None,
            });
            for side in sides {
                if side.body >= bodies.len() {
                    return Err(SoftTissueError::NodeOutOfRange {
                        node: side.body,
                        len: bodies.len(),
                    });
                }
                let body = bodies.body(side.body);
                for &n in &side.nodes {
                    if n as usize >= body.num_nodes() {
                        return Err(SoftTissueError::NodeOutOfRange {
                            node: n as usize,
                            len: body.num_nodes(),
                        });
                    }
                }
            }
            let finite = c
                .normal
                .iter()
                .chain(c.tangents.iter().flatten())
                .all(|v| v.is_finite())
                && c.gap.is_finite()
                && c.mu.is_finite()
                && c.mu >= 0.0;
            if !finite {
                return Err(SoftTissueError::NonFinite("contact"));
            }
        }
        self.h = h;
        self.steps += 1;
        self.sync_bodies(bodies);
        for i in 0..bodies.len() {
            let b = bodies.body(i);
            self.predict[i].begin_step(b.num_nodes(), self.steps, false);
        }
        self.contacts.clear();
        self.contacts.extend_from_slice(contacts);
        self.report = ContactReport {
            contacts: contacts.len(),
            ..Default::default()
        };
        Ok(())
    }

    /// Phase 2: builds `H` and `W = Σ_b h² H_b A_b⁻¹ H_bᵀ`, on the CPU or,
    /// for `Factorized` bodies, with `backend` (the GPU).
    pub fn build_compliance<B: BodiesMut + ?Sized>(
        &mut self,
        bodies: &mut B,
        pass: PassKind,
        mut backend: Option<&mut dyn ComplianceBackend>,
    ) -> Result<()> {
        let t0 = Instant::now();
        self.sync_bodies(&*bodies);
        self.jac.build(&self.contacts, &*bodies);
        let m = self.jac.m();
        // `w` is left as it was (only grown with zeros): the first body with
        // entries writes every entry of it or zeroes it first
        // ([`compliance::WBlock::Unset`]).
        let first = (0..bodies.len()).find(|&bi| !self.jac.entries[bi].is_empty());
        if first.is_none() {
            self.w.clear();
        }
        self.w.resize(m * m, 0.0);
        self.row_written.clear();
        self.row_written.resize(m, false);
        for bi in 0..bodies.len() {
            let entries = &mut self.jac.entries[bi];
            if entries.is_empty() {
                continue;
            }
            self.predict[bi].linearize_back(pass, entries, &mut self.jac.delta0);
            let compliance = &mut self.compliance[bi];
            compliance.reuse_steps = self.settings.factor_reuse;
            compliance.rigid_modes = self.settings.rigid_modes;
            // The body's block of `w` is still zero when no body before it
            // wrote any of its rows, and not even zeroed for the first.
            compliance.block = if Some(bi) == first {
                WBlock::Unset
            } else if entries.iter().all(|e| !self.row_written[e.row as usize]) {
                WBlock::Zero
            } else {
                WBlock::Written
            };
            for e in entries.iter() {
                self.row_written[e.row as usize] = true;
            }
            // The body's node-column hand-over, passed openly and put back.
            let mut prefetch = std::mem::take(bodies.body_mut(bi).column_prefetch_mut());
            let result = compliance.accumulate(
                bodies.body(bi),
                &mut prefetch,
                self.modes[bi],
                self.h,
                entries,
                &mut self.w,
                m,
                backend
                    .as_mut()
                    .map(|b| &mut **b as &mut dyn ComplianceBackend),
            );
            *bodies.body_mut(bi).column_prefetch_mut() = prefetch;
            if result.is_err() {
                // Whatever the failed build got to, `w` is left defined.
                self.w.fill(0.0);
            }
            result?;
            self.report.solves += compliance.solves();
            self.report.gram_blocks += compliance.gram_blocks();
        }
        if pass == PassKind::First {
            self.report.rows = m;
            self.report.friction_contacts = self.jac.friction_contacts;
        }
        self.report.compliance += t0.elapsed().as_secs_f64();
        Ok(())
    }

    fn key<B: Bodies + ?Sized>(c: &Contact, bodies: &B) -> ContactKey {
        ContactKey {
            body: bodies.body(c.a.body).id(),
            nodes: c.a.nodes,
            other: match c.other {
                ContactOther::Tool(t) => OtherKey::Tool(t),
                ContactOther::Body(s) => OtherKey::Body(bodies.body(s.body).id()),
            },
        }
    }

    /// Phase 3: the LCP on `W λ + δ₀` with [`LcpSettings::solver`]
    /// (warm-started in a first pass).
    pub fn solve_lcp<B: Bodies + ?Sized>(&mut self, bodies: &B, pass: PassKind) -> LcpReport {
        let t0 = Instant::now();
        let m = self.jac.m();
        self.lambda.clear();
        self.lambda.resize(m, 0.0);
        let first = pass == PassKind::First;
        if self.settings.lcp.warm_start && first {
            let keys = self.contacts.iter().map(|c| Self::key(c, bodies));
            self.warm.apply(keys, &self.jac.rows, &mut self.lambda);
        }
        // The start, if recording: the solve overwrites it, and whether the
        // problem is kept is known only after (a solve at its sweep limit).
        let lambda0 = self.record_from.map(|_| self.lambda.clone());
        let shift = first && self.settings.tool_faces;
        if shift {
            self.shift_face_rows();
        }
        let report = lcp::solve(
            &self.w,
            &self.jac.delta0,
            &self.jac.rows,
            &self.jac.mu,
            &mut self.lambda,
            &self.settings.lcp,
            &mut self.lcp_scratch,
        );
        if let Some(lambda0) = lambda0
            && (report.capped
                || first && self.record_from.is_some_and(|n| self.contacts.len() >= n))
        {
            self.recorded = Some(ContactProblem {
                w: self.w.clone(),
                delta0: self.jac.delta0.clone(),
                rows: self.jac.rows.clone(),
                mu: self.jac.mu.clone(),
                lambda0,
            });
        }
        if shift {
            self.unshift_face_rows();
        }
        if first {
            self.warm.clear();
        }
        for ci in 0..self.contacts.len() {
            let r = self.jac.rows[ci];
            let mut f = [0.0; 3];
            let k = self.jac.rows[ci + 1] - r;
            f[..k].copy_from_slice(&self.lambda[r..r + k]);
            if first {
                self.warm.remember(Self::key(&self.contacts[ci], bodies), f);
            }
            self.contacts[ci].force = Vec3::new(f[0], f[1], f[2]);
        }
        self.report.lcp = report;
        if first {
            self.report.lcp_first = report;
        }
        self.report.lcp_capped += usize::from(report.capped);
        self.report.lcp_seconds += t0.elapsed().as_secs_f64();
        report
    }

    /// Multiplies the diagonal entry of each face contact's row of `w` by
    /// `1 + FACE_ROW_SHIFT`, keeping the entries for
    /// [`Self::unshift_face_rows`].
    fn shift_face_rows(&mut self) {
        let m = self.jac.m();
        self.face_diagonal.clear();
        for (c, &r) in self.contacts.iter().zip(&self.jac.rows) {
            if detect::is_tool_face(c) {
                let k = r * m + r;
                self.face_diagonal.push((k, self.w[k]));
                self.w[k] *= 1.0 + FACE_ROW_SHIFT;
            }
        }
    }

    /// Puts back the diagonal entries [`Self::shift_face_rows`] changed.
    fn unshift_face_rows(&mut self) {
        for &(k, d) in &self.face_diagonal {
            self.w[k] = d;
        }
    }

    /// Phase 4: applies `Δx = h² A⁻¹ Hᵀ λ` to every body and sets the tool reactions.
    pub fn correct<B: BodiesMut + ?Sized, T: ToolsMut + ?Sized>(
        &mut self,
        bodies: &mut B,
        tools: &mut T,
        pass: PassKind,
    ) -> Result<()> {
        // Refinement passes correct what the first left, with small forces:
        // only the first pass's energy ratio is checked; every pass's work.
        let tolerance = correct::Tolerances {
            ratio: match pass {
                PassKind::First => self.settings.consistency_tolerance,
                PassKind::Refine => f64::INFINITY,
            },
            energy: self.settings.energy_tolerance,
        };
        self.compute_corrections(bodies, tolerance)?;
        if !self.stale.is_empty() {
            self.redo_with_current_factor(bodies, pass)?;
        }
        let t0 = Instant::now();
        let dx = std::mem::take(&mut self.dx);
        correct::apply(bodies, &mut self.per_body(), &dx);
        self.dx = dx;
        for (forces, entries) in self.node_forces.iter_mut().zip(&self.jac.entries) {
            for e in entries {
                if let Some(f) = forces.get_mut(e.node as usize) {
                    *f += e.h * self.lambda[e.row as usize];
                }
            }
        }
        correct::tool_reactions(tools, &self.contacts, pass);
        if let Some(ti) = self.captured_tool.filter(|&ti| ti < tools.len()) {
            let tool = tools.tool(ti);
            if pass == PassKind::First {
                self.tool_problem.capture(
                    self.steps,
                    ti,
                    tool,
                    &self.contacts,
                    &self.jac.rows,
                    &self.w,
                    &self.jac.delta0,
                    &self.lambda,
                    &mut self.selected,
                );
            }
            let (f, t) = tool.reaction();
            self.tool_problem.set_reaction(f, t);
        }
        self.report.correct += t0.elapsed().as_secs_f64();
        Ok(())
    }

    fn per_body(&mut self) -> correct::PerBody<'_> {
        correct::PerBody {
            compliance: &mut self.compliance,
            modes: &self.modes,
            predictions: &mut self.predict,
            entries: &self.jac.entries,
            forces: &mut self.pass_forces,
        }
    }

    /// Every body's correction of this pass into `self.dx`; the bodies whose
    /// correction strays beyond `tolerance` into `self.stale`.
    fn compute_corrections<B: BodiesMut + ?Sized>(
        &mut self,
        bodies: &mut B,
        tolerance: correct::Tolerances,
    ) -> Result<()> {
        let t0 = Instant::now();
        let (mut dx, mut stale) = (
            std::mem::take(&mut self.dx),
            std::mem::take(&mut self.stale),
        );
        let (h, lambda) = (self.h, std::mem::take(&mut self.lambda));
        let mut per = self.per_body();
        let res = correct::compute(bodies, &mut per, h, &lambda, tolerance, &mut dx, &mut stale);
        (self.dx, self.stale, self.lambda) = (dx, stale, lambda);
        self.report.correct += t0.elapsed().as_secs_f64();
        self.report.misaccounted_work += res?;
        Ok(())
    }

    /// A factor of the current matrix for each body in `self.stale`.
    fn refactor_stale<B: BodiesMut + ?Sized>(&mut self, bodies: &mut B) -> Result<()> {
        for i in 0..self.stale.len() {
            let bi = self.stale[i];
            if bodies.body_mut(bi).refactor_preconditioner_now()? {
                self.compliance[bi].drop_snapshot();
                self.report.consistency_refactors += 1;
            }
        }
        Ok(())
    }

    /// The rescue of [`Self::correct`]: the bodies in `self.stale` get a factor
    /// of their current matrix, and the pass's `W`, LCP and correction are
    /// redone (on the CPU) with it; the new correction is consistent by
    /// construction.
    fn redo_with_current_factor<B: BodiesMut + ?Sized>(
        &mut self,
        bodies: &mut B,
        pass: PassKind,
    ) -> Result<()> {
        let t0 = Instant::now();
        let refactored = self.refactor_stale(bodies);
        self.report.rescue += t0.elapsed().as_secs_f64();
        refactored?;
        self.build_compliance(bodies, pass, None)?;
        self.solve_lcp(&*bodies, pass);
        let unchecked = correct::Tolerances {
            ratio: f64::INFINITY,
            energy: f64::INFINITY,
        };
        self.compute_corrections(bodies, unchecked)
    }

    /// Runs the first pass (detection, compliance, LCP, correction), then the
    /// refinement passes ([`Self::refine`]). Skips everything after detection
    /// when there is no contact. `backend` builds the first pass's `W` of
    /// `Factorized` bodies (the GPU); refinement passes build on the CPU.
    pub fn step<B: BodiesMut + ?Sized, T: ToolsMut + ?Sized>(
        &mut self,
        bodies: &mut B,
        tools: &mut T,
        h: f64,
        backend: Option<&mut dyn ComplianceBackend>,
    ) -> Result<()> {
        self.detect(&*bodies, &*tools, h, PassKind::First)?;
        if self.contacts.is_empty() {
            self.clear_forces(tools);
            return Ok(());
        }
        self.build_compliance(bodies, PassKind::First, backend)?;
        self.solve_lcp(&*bodies, PassKind::First);
        self.correct(bodies, tools, PassKind::First)?;
        self.refine(bodies, tools, h)
    }

    /// Forgets warm-start forces and zeroes tool reactions (a step without contact).
    pub fn clear_forces<T: ToolsMut + ?Sized>(&mut self, tools: &mut T) {
        self.warm.clear();
        self.lambda.clear();
        for e in &mut self.jac.entries {
            e.clear();
        }
        for p in &mut self.predict {
            p.forget();
        }
        for f in &mut self.node_forces {
            f.fill(Vec3::zeros());
        }
        for i in 0..tools.len() {
            tools.tool_mut(i).set_reaction(Vec3::zeros(), Vec3::zeros());
        }
    }

    /// Runs the extra frictionless passes after the first correction, while a
    /// vertex still penetrates deeper than the tolerance (see
    /// [`ContactSettings::max_passes`]). Passes from the eighth on also keep
    /// the plane of each vertex the last pass found penetrated, where this
    /// pass's normal of it turned by about 25° to 120°, so that one LCP
    /// pushes it out of both faces.
    pub fn refine<B: BodiesMut + ?Sized, T: ToolsMut + ?Sized>(
        &mut self,
        bodies: &mut B,
        tools: &mut T,
        h: f64,
    ) -> Result<()> {
        self.report.passes = 1;
        for pass in 1..self.settings.max_passes {
            self.detect(&*bodies, &*tools, h, PassKind::Refine)?;
            if self.report.max_penetration <= self.settings.penetration_tolerance {
                break;
            }
            if pass >= held::HOLD_FROM_PASS {
                self.hold_planes();
            }
            self.build_compliance(bodies, PassKind::Refine, None)?;
            self.solve_lcp(&*bodies, PassKind::Refine);
            self.correct(bodies, tools, PassKind::Refine)?;
            // The planes this pass found penetrated, for the next pass to
            // hold where its normals turn.
            self.held.clear();
            if pass + 1 >= held::HOLD_FROM_PASS {
                self.held
                    .extend(self.contacts.iter().filter(|c| c.gap < 0.0).copied());
            }
            self.report.passes = pass + 1;
        }
        Ok(())
    }

    /// Adds the held planes to a refinement pass ([`held::hold_planes`]).
    fn hold_planes(&mut self) {
        let detect = &self.detect;
        held::hold_planes(
            &self.held,
            &mut self.contacts,
            |b| detect.get(b).map(|d| d.x.as_slice()),
            self.settings.alarm_distance,
        );
    }
}
