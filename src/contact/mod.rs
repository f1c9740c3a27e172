//! Contact response: detection, compliance, friction LCP and correction.
//!
//! This is the paper's section 4. After every body has moved freely
//! ([`DeformableBody::solve_free_motion`]), [`ContactSolver`] runs four phases:
//!
//! 1. **Detect** ([`ContactSolver::detect`], [`detect`]): surface vertices
//!    against rigid [`RigidTool`]s (parry3d-f64) and against the surface triangles of
//!    other bodies (refitted BVH, both directions; inside or not is decided by
//!    the other body's tetrahedra, at any depth). Each contact has a normal,
//!    two tangents and a gap `δ₀` at the free-motion positions. With
//!    [`ContactSettings::predict`] (the default) the first pass looks for
//!    contacts at the free motion plus the previous step's correction, where
//!    held contacts will be, and linearizes its gaps back to the free motion.
//!    Self-collision is out of scope.
//! 2. **Compliance** ([`ContactSolver::build_compliance`]): the constraint
//!    Jacobian `H` — one normal row per contact, plus two tangent rows when
//!    `μ > 0` — and the Delassus matrix `W = Σ_bodies h² H A⁻¹ Hᵀ`, computed per
//!    body with the body's [`ComplianceMode`] (see [`compliance`]).
//!    Deformable–deformable contacts sum both bodies' contributions.
//! 3. **LCP** ([`ContactSolver::solve_lcp`]): projected Gauss–Seidel with a
//!    circular Coulomb cone ([`lcp`]), warm-started from the previous step.
//! 4. **Correct** ([`ContactSolver::correct`]): `Δx = h² A⁻¹ Hᵀ λ` with the
//!    same approximation of `A⁻¹` as `W`, `Δv = Δx / h`, and the reaction force and
//!    torque on each tool.
//!
//! A scene without tools or touching bodies does no detection work, one
//! without contacts no compliance or LCP work, and `μ = 0` adds no friction rows.

pub mod compliance;
pub mod detect;
pub mod lcp;
pub mod tool;

use std::collections::HashMap;
use std::time::Instant;

use crate::body::{DeformableBody, NodeConstraint};
use crate::error::{Result, SoftTissueError, check_positive};
use crate::math::Vec3;

/// A body as the contact phases read it: `&DeformableBody` or
/// `&mut DeformableBody`, so callers that hold either pass their slice as is.
pub trait BodyRef: std::ops::Deref<Target = DeformableBody> {}
impl<B: std::ops::Deref<Target = DeformableBody>> BodyRef for B {}

/// A tool as the contact phases read it: `&RigidTool` or `&mut RigidTool`.
trait ToolRef: std::ops::Deref<Target = RigidTool> {}
impl<T: std::ops::Deref<Target = RigidTool>> ToolRef for T {}
pub use compliance::{BodyCompliance, ComplianceBackend, ComplianceMode, JacEntry};
use detect::{Bvh, boxes_overlap, closest_point_on_triangle, point_in_tet, segment_triangle};
pub use lcp::{LcpReport, LcpSettings};
pub use tool::{Pose, RigidTool, ToolShape};

/// Scene-wide contact settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContactSettings {
    /// Default compliance mode (bodies may override it in their settings).
    pub compliance: ComplianceMode,
    /// Proximity (alarm) distance below which a contact is created, metres.
    pub alarm_distance: f64,
    /// Friction coefficient between deformable bodies.
    pub body_friction: f64,
    /// Friction on or off for the whole scene (off: μ = 0 everywhere, no tangent rows).
    pub friction: bool,
    /// Gauss–Seidel settings.
    pub lcp: LcpSettings,
    /// Maximum contact passes per step. After the first correction, detection
    /// runs again; while some vertex still penetrates deeper than
    /// `penetration_tolerance` (a vertex the correction pushed into a tool, or the
    /// curvature a linearized contact ignores), another frictionless pass corrects it.
    pub max_passes: usize,
    /// Penetration that triggers another pass, metres.
    pub penetration_tolerance: f64,
    /// Steps that `Factorized` compliance keeps using a factor after the
    /// preconditioner swapped in a newer one (0, the default: always the
    /// newest, the most accurate `W`). Node columns and Gram blocks are cached
    /// per factor, so reusing one for a few steps makes more steps' `W` nearly
    /// free. It trades accuracy for time: the rotation warp follows rotations
    /// but not changes of shape, so `W` and the correction drift from the
    /// current stiffness as the tissue deforms. Applies to bodies whose
    /// preconditioner warps (`Periodic`, `Async`).
    pub factor_reuse: u64,
    /// Detect the first pass where the contacts will be, not at the free
    /// motion: each body's free-motion positions plus its previous step's total
    /// correction. Tissue held against a surface springs back in free motion
    /// (in the cataract scene's slit by up to 0.5 mm a step, half the sclera's
    /// thickness) and the correction pushes it out again; detected at the
    /// free motion, such a vertex is deep inside the other body, where the
    /// closest surface point may lie on its far side. At the predicted positions
    /// held contacts sit near their surface, and the linearized gaps account
    /// for the shift exactly (`δ₀ = gap − H·shift`), so the LCP solves the
    /// same problem at a better-chosen linearization point. On by default.
    pub predict: bool,
}

impl Default for ContactSettings {
    fn default() -> Self {
        Self {
            compliance: ComplianceMode::Factorized,
            alarm_distance: 1e-4,
            body_friction: 0.0,
            friction: true,
            lcp: LcpSettings::default(),
            max_passes: 3,
            penetration_tolerance: 1e-6,
            factor_reuse: 0,
            predict: true,
        }
    }
}

impl ContactSettings {
    /// Checks the parameters.
    pub fn validate(&self) -> Result<()> {
        check_positive("alarm_distance", self.alarm_distance)?;
        crate::error::check_range("body_friction", self.body_friction, 0.0, 1e6)?;
        check_positive("lcp.tolerance", self.lcp.tolerance)?;
        let dt = self.lcp.displacement_tolerance;
        if !(dt.is_finite() && dt >= 0.0) {
            return Err(SoftTissueError::InvalidParameter {
                name: "lcp.displacement_tolerance",
                value: dt,
                reason: "must be finite and non-negative",
            });
        }
        if !(self.lcp.over_relaxation > 0.0 && self.lcp.over_relaxation < 2.0) {
            return Err(SoftTissueError::InvalidParameter {
                name: "lcp.over_relaxation",
                value: self.lcp.over_relaxation,
                reason: "must lie in (0, 2)",
            });
        }
        check_positive("penetration_tolerance", self.penetration_tolerance)?;
        if self.max_passes == 0 {
            return Err(SoftTissueError::InvalidParameter {
                name: "max_passes",
                value: 0.0,
                reason: "must be ≥ 1",
            });
        }
        if self.lcp.max_iterations == 0 {
            return Err(SoftTissueError::InvalidParameter {
                name: "lcp.max_iterations",
                value: 0.0,
                reason: "must be ≥ 1",
            });
        }
        Ok(())
    }
}

/// One side of a contact on a deformable body: up to three weighted nodes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ContactSide {
    /// Index of the body in the slice given to the solver.
    pub body: usize,
    /// Nodes (volume indices).
    pub nodes: [u32; 3],
    /// Barycentric weights (unused slots are 0).
    pub weights: [f64; 3],
}

/// What the other side of a contact is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ContactOther {
    /// A rigid tool (index in the tool slice).
    Tool(usize),
    /// A surface triangle of another body.
    Body(ContactSide),
}

/// A contact between a surface vertex and a tool or another body's surface.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Contact {
    /// The vertex side (weight 1 on one node).
    pub a: ContactSide,
    /// The other side.
    pub other: ContactOther,
    /// Unit normal, pointing from the other side toward `a`.
    pub normal: Vec3,
    /// Unit tangents completing the frame.
    pub tangents: [Vec3; 2],
    /// Gap where the contact was detected, negative when penetrating: at the
    /// free motion, or in a predicted first pass ([`ContactSettings::predict`])
    /// at the predicted positions, and the LCP's `δ₀` is then the gap less the
    /// predicted shift along the normal.
    pub gap: f64,
    /// Tangential relative displacement during the step, where the contact
    /// was detected (see [`Self::gap`]).
    pub slip: [f64; 2],
    /// Friction coefficient.
    pub mu: f64,
    /// Contact point on the other side.
    pub point: Vec3,
    /// Solved force `(λ_n, λ_t1, λ_t2)` on side `a`, newtons.
    pub force: Vec3,
}

/// Timings and counters of the contact phases of the last step. Counts
/// (`contacts`, `rows`, `friction_contacts`) describe the first pass; timings and
/// solves add up over all passes.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ContactReport {
    /// Active contacts.
    pub contacts: usize,
    /// Constraint rows.
    pub rows: usize,
    /// Contacts that have friction rows.
    pub friction_contacts: usize,
    /// LCP outcome.
    pub lcp: LcpReport,
    /// Forward (or full) solves done for `W`.
    pub solves: usize,
    /// Gram blocks computed (cache misses).
    pub gram_blocks: usize,
    /// Seconds in detection.
    pub detect: f64,
    /// Seconds building `H` and `W`.
    pub compliance: f64,
    /// Seconds in the LCP.
    pub lcp_seconds: f64,
    /// Seconds in the correction.
    pub correct: f64,
    /// Vertex–tool pairs tested in detection.
    pub pairs_tested: usize,
    /// Contact passes run (see [`ContactSettings::max_passes`]).
    pub passes: usize,
    /// Deepest penetration found by the last detection, metres (0 if none).
    pub max_penetration: f64,
    /// Deepest penetration found by the first detection of the step, metres:
    /// how far inside the free motion (or, with [`ContactSettings::predict`],
    /// the predicted positions) put a vertex, i.e. how far from its solution
    /// the first pass linearizes.
    pub first_penetration: f64,
}

#[derive(Debug, Default)]
struct BodySlot {
    id: u64,
    compliance: BodyCompliance,
    bvh: Option<Bvh>,
    tet_bvh: Option<Bvh>,
    tris: Vec<[usize; 3]>,
    entries: Vec<JacEntry>,
    dx: Vec<Vec3>,
    /// Positions detection reads: the body's, plus `shift` in a predicted pass.
    xp: Vec<Vec3>,
    /// The previous step's total correction, the prediction of this step's.
    shift: Vec<Vec3>,
    /// Whether this step's first pass detects at predicted positions.
    shifted: bool,
    /// Per node, how much farther than the alarm distance this pass searches
    /// (the length of its predicted shift, zero when not shifted).
    extra: Vec<f64>,
    /// The largest of `extra`.
    max_extra: f64,
    /// This step's corrections so far (all passes).
    acc: Vec<Vec3>,
    /// Whether `acc` holds a correction.
    has_acc: bool,
    /// The detection count at which `acc` was started.
    acc_step: u64,
    aabb: (Vec3, Vec3),
    mode: ComplianceMode,
}

type ContactKey = (u64, u32, u64);

/// The contact pipeline (see the module docs). Keep one per scene; it caches
/// per-body data (BVHs, node columns, previous forces) between steps.
#[derive(Debug, Default)]
pub struct ContactSolver {
    settings: ContactSettings,
    slots: Vec<BodySlot>,
    contacts: Vec<Contact>,
    rows: Vec<usize>,
    mu: Vec<f64>,
    delta0: Vec<f64>,
    w: Vec<f64>,
    lambda: Vec<f64>,
    lcp_delta: Vec<f64>,
    previous: HashMap<ContactKey, [f64; 3]>,
    report: ContactReport,
    h: f64,
    pass: usize,
    /// First-pass detections so far.
    detections: u64,
}

/// Two unit tangents completing the unit normal `n` to an orthonormal frame.
pub fn tangent_basis(n: &Vec3) -> [Vec3; 2] {
    let e = if n.x.abs() < 0.6 {
        Vec3::x()
    } else if n.y.abs() < 0.6 {
        Vec3::y()
    } else {
        Vec3::z()
    };
    let t1 = n.cross(&e).normalize();
    [t1, n.cross(&t1)]
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

    /// Forgets every body's cached node columns and Gram blocks (their memory is
    /// kept), as a new factor does; for benchmarks of the cold build.
    pub fn forget_columns(&mut self) {
        for s in &mut self.slots {
            s.compliance.forget_columns();
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

    /// Contacts of the last step (forces filled after the LCP).
    pub fn contacts(&self) -> &[Contact] {
        &self.contacts
    }

    /// Counters and timings of the last step.
    pub fn report(&self) -> &ContactReport {
        &self.report
    }

    /// The Delassus matrix `W` of the last step (row-major, `rows × rows`).
    pub fn delassus(&self) -> (&[f64], usize) {
        (&self.w, self.delta0.len())
    }

    /// Row offsets per contact: rows of contact `c` are `offsets[c]..offsets[c+1]`.
    pub fn row_offsets(&self) -> &[usize] {
        &self.rows
    }

    /// Jacobian entries of body slot `i` (valid after [`Self::build_compliance`]).
    pub fn jacobian(&self, i: usize) -> &[JacEntry] {
        self.slots.get(i).map(|s| &s.entries[..]).unwrap_or(&[])
    }

    /// Total contact force exerted on body `i` in the last step (`Σ Hᵀ λ`).
    pub fn body_force(&self, i: usize) -> Vec3 {
        self.jacobian(i)
            .iter()
            .map(|e| e.h * self.lambda[e.row as usize])
            .sum()
    }

    fn prepare_slots<B: BodyRef>(&mut self, bodies: &[B]) {
        self.slots.resize_with(bodies.len(), BodySlot::default);
        let predict = self.settings.predict && self.pass == 0;
        if self.pass == 0 {
            self.detections += 1;
        }
        for (slot, b) in self.slots.iter_mut().zip(bodies) {
            if slot.id != b.id() {
                *slot = BodySlot {
                    id: b.id(),
                    compliance: BodyCompliance::new(),
                    tris: b.surface().volume_triangles().collect(),
                    ..Default::default()
                };
            }
            let x = b.positions();
            if self.pass == 0 {
                // The last step's correction becomes this step's prediction
                // (only the step just before: a body that was left alone, or a
                // pipeline that skipped steps, predicts nothing).
                std::mem::swap(&mut slot.shift, &mut slot.acc);
                slot.shifted = predict
                    && slot.has_acc
                    && slot.acc_step + 1 == self.detections
                    && slot.shift.len() == x.len();
                slot.has_acc = false;
                slot.acc_step = self.detections;
                slot.acc.clear();
                slot.acc.resize(x.len(), Vec3::zeros());
            }
            slot.xp.clear();
            slot.extra.clear();
            if slot.shifted && self.pass == 0 {
                slot.xp
                    .extend(x.iter().zip(&slot.shift).map(|(p, s)| p + s));
                // A vertex whose shift overshoots would leave the alarm band of
                // a contact it still has at the free motion: search as much
                // farther as it was shifted.
                slot.extra.extend(slot.shift.iter().map(|s| s.norm()));
            } else {
                slot.xp.extend_from_slice(x);
                slot.extra.resize(x.len(), 0.0);
            }
            slot.max_extra = slot.extra.iter().copied().fold(0.0, f64::max);
            let mut lo = Vec3::repeat(f64::INFINITY);
            let mut hi = Vec3::repeat(f64::NEG_INFINITY);
            for &v in &b.surface().vertices {
                lo = lo.inf(&slot.xp[v]);
                hi = hi.sup(&slot.xp[v]);
            }
            slot.aabb = (lo, hi);
        }
    }

    /// Phase 1: finds contacts at the bodies' free-motion positions (in a
    /// step's first pass, with [`ContactSettings::predict`], at the predicted
    /// ones; the gaps `δ₀` are those of the free motion either way).
    pub fn detect(
        &mut self,
        bodies: &[&DeformableBody],
        tools: &[&RigidTool],
        h: f64,
    ) -> Result<()> {
        self.detect_in(bodies, tools, h)
    }

    /// [`Self::detect`] for any slice of body and tool references (the passes of
    /// [`Self::step`] hold `&mut` ones), without collecting new slices.
    fn detect_in<B: BodyRef, T: ToolRef>(
        &mut self,
        bodies: &[B],
        tools: &[T],
        h: f64,
    ) -> Result<()> {
        let t0 = Instant::now();
        check_positive("h", h)?;
        self.h = h;
        self.contacts.clear();
        if self.pass == 0 {
            self.report = ContactReport::default();
        } else {
            self.report.pairs_tested = 0;
        }
        self.prepare_slots(bodies);
        let margin = self.settings.alarm_distance;
        for (bi, body) in bodies.iter().enumerate() {
            let x = &self.slots[bi].xp;
            let x0 = body.start_positions();
            let fixed = body.constraints();
            let extra = &self.slots[bi].extra;
            let surface_mu = body.material().tool_friction;
            for (ti, tool) in tools.iter().enumerate() {
                let tb = tool.aabb(margin + self.slots[bi].max_extra);
                if !boxes_overlap(&self.slots[bi].aabb, &tb, 0.0) {
                    continue;
                }
                for &v in &body.surface().vertices {
                    let p = x[v];
                    if fixed[v] != NodeConstraint::Free || !boxes_overlap(&(p, p), &tb, 0.0) {
                        continue;
                    }
                    self.report.pairs_tested += 1;
                    let band = margin + extra[v];
                    // Search deep enough to find the surface from anywhere inside the tool.
                    let Some(prox) = tool.proximity(&p, band + tool.inner_radius()) else {
                        continue;
                    };
                    if prox.distance >= band {
                        continue;
                    }
                    let t = tangent_basis(&prox.normal);
                    let rel = (p - x0[v]) - tool.displacement_at(&prox.point);
                    self.contacts.push(Contact {
                        a: ContactSide {
                            body: bi,
                            nodes: [v as u32, 0, 0],
                            weights: [1.0, 0.0, 0.0],
                        },
                        other: ContactOther::Tool(ti),
                        normal: prox.normal,
                        tangents: t,
                        gap: prox.distance,
                        slip: [t[0].dot(&rel), t[1].dot(&rel)],
                        mu: surface_mu.unwrap_or(tool.friction()),
                        point: prox.point,
                        force: Vec3::zeros(),
                    });
                }
            }
        }
        // Deformable against deformable, both directions.
        for a in 0..bodies.len() {
            for b in 0..bodies.len() {
                let band = margin + self.slots[a].max_extra;
                if a == b || !boxes_overlap(&self.slots[a].aabb, &self.slots[b].aabb, band) {
                    continue;
                }
                let slot_b = &mut self.slots[b];
                let (xb, tets) = (&slot_b.xp, bodies[b].mesh().tets());
                let bvh = slot_b.bvh.get_or_insert_with(|| Bvh::new(&slot_b.tris, xb));
                bvh.refit(&slot_b.tris, xb);
                let tet_bvh = slot_b.tet_bvh.get_or_insert_with(|| Bvh::new(tets, xb));
                tet_bvh.refit(tets, xb);
                self.vertex_triangle(bodies, a, b, margin);
            }
        }
        if self.pass > 0 || !self.settings.friction {
            for c in &mut self.contacts {
                c.mu = 0.0;
                c.slip = [0.0; 2];
            }
        }
        self.report.max_penetration = self.contacts.iter().map(|c| -c.gap).fold(0.0, f64::max);
        if self.pass == 0 {
            self.report.contacts = self.contacts.len();
            self.report.first_penetration = self.report.max_penetration;
        }
        self.report.detect += t0.elapsed().as_secs_f64();
        Ok(())
    }

    fn vertex_triangle<B: BodyRef>(&mut self, bodies: &[B], a: usize, b: usize, margin: f64) {
        let (sa, sb) = (bodies[a].start_positions(), bodies[b].start_positions());
        let tets = bodies[b].mesh().tets();
        let mu = self.settings.body_friction;
        let (slot_a, slot_b) = slot_pair(&mut self.slots, a, b);
        let (xa, extra, max_extra) = (&slot_a.xp, &slot_a.extra, slot_a.max_extra);
        let xb = &slot_b.xp;
        let (Some(bvh), Some(tet_bvh)) = (slot_b.bvh.as_mut(), slot_b.tet_bvh.as_mut()) else {
            return;
        };
        let tris = &slot_b.tris;
        let bbox = slot_b_aabb(tris, xb, margin + max_extra);
        // Far enough to reach the surface from anywhere inside `b`.
        let reach = (bbox.1 - bbox.0).norm();
        for &v in &bodies[a].surface().vertices {
            let p = xa[v];
            if !boxes_overlap(&(p, p), &bbox, 0.0) {
                continue;
            }
            let mut best: Option<(f64, usize, [f64; 3])> = None;
            let mut closest = |r: f64, best: &mut Option<(f64, usize, [f64; 3])>| {
                bvh.query(&p, r, |t| {
                    let [i, j, k] = tris[t];
                    let w = closest_point_on_triangle(&p, &xb[i], &xb[j], &xb[k]);
                    let q = xb[i] * w[0] + xb[j] * w[1] + xb[k] * w[2];
                    let d2 = (p - q).norm_squared();
                    if best.is_none_or(|bst| d2 < bst.0) {
                        *best = Some((d2, t, w));
                    }
                });
            };
            let band = margin + extra[v];
            closest(band, &mut best);
            let face_normal = |t: usize| {
                let [i, j, k] = tris[t];
                (xb[j] - xb[i])
                    .cross(&(xb[k] - xb[i]))
                    .try_normalize(1e-300)
            };
            let point = |x: &[Vec3], t: usize, w: [f64; 3]| {
                let [i, j, k] = tris[t];
                x[i] * w[0] + x[j] * w[1] + x[k] * w[2]
            };
            let inside = tet_bvh.query_until(&p, 0.0, |e| point_in_tet(&p, tets[e].map(|i| xb[i])));
            if inside {
                // However deep: widen the search until the closest triangle
                // found is provably the closest.
                let mut r = band;
                while best.is_none_or(|bst| bst.0 > r * r) && r < reach {
                    r = (4.0 * r).min(reach);
                    closest(r, &mut best);
                }
            }
            let Some((d2, mut t, mut w)) = best else {
                continue;
            };
            if !inside && d2 >= band * band {
                continue;
            }
            let mut entry = None;
            if inside && d2 > margin * margin {
                // Deep: push it back out where it came in, not toward the
                // closest surface point, which in a thin part (the sclera's
                // lips) may lie on the far side. The vertex's start-of-step
                // position, carried along with `b` near the closest point, is
                // where it came from; the first face the path crosses inward is
                // the entry.
                let o = sa[v] + point(xb, t, w) - point(sb, t, w);
                let mid = (o + p) * 0.5;
                let mut first: Option<(f64, usize, [f64; 3])> = None;
                bvh.query(&mid, 0.5 * (p - o).norm(), |f| {
                    let [i, j, k] = tris[f];
                    if let Some((s, wf)) = segment_triangle(&o, &p, &xb[i], &xb[j], &xb[k])
                        && (xb[j] - xb[i]).cross(&(xb[k] - xb[i])).dot(&(p - o)) < 0.0
                        && first.is_none_or(|fst| s < fst.0)
                    {
                        first = Some((s, f, wf));
                    }
                });
                if let Some((_, f, wf)) = first {
                    (t, w) = (f, wf);
                    entry = face_normal(f);
                }
            }
            let q = point(xb, t, w);
            // Outward from `b`: the entry face's normal for a deep vertex;
            // otherwise the direction between the points (over a face's
            // interior that is the face normal; over an edge or a corner only
            // the direction is well defined, one of several equally close
            // triangles is `t`), the face normal where the points touch.
            let dir = if inside { q - p } else { p - q };
            let n = match (entry, dir.try_normalize(1e-6 * margin)) {
                (Some(nf), _) => nf,
                (None, Some(d)) => d,
                (None, None) => match face_normal(t) {
                    Some(nf) => nf,
                    None => continue,
                },
            };
            let gap = (p - q).dot(&n);
            // The side is the tetrahedra's call: a face plane alone misjudges
            // vertices near a cut or an edge.
            let gap = if inside { gap.min(0.0) } else { gap.max(0.0) };
            let [i, j, k] = tris[t];
            let tg = tangent_basis(&n);
            let rel = (p - sa[v]) - (q - point(sb, t, w));
            self.contacts.push(Contact {
                a: ContactSide {
                    body: a,
                    nodes: [v as u32, 0, 0],
                    weights: [1.0, 0.0, 0.0],
                },
                other: ContactOther::Body(ContactSide {
                    body: b,
                    nodes: [i as u32, j as u32, k as u32],
                    weights: w,
                }),
                normal: n,
                tangents: tg,
                gap,
                slip: [tg[0].dot(&rel), tg[1].dot(&rel)],
                mu,
                point: q,
                force: Vec3::zeros(),
            });
        }
    }

    /// Replaces the detected contacts with `contacts` (for custom detection and
    /// benchmarks); `h` is the step size used by the following phases.
    pub fn set_contacts<B: BodyRef>(
        &mut self,
        contacts: &[Contact],
        bodies: &[B],
        h: f64,
    ) -> Result<()> {
        check_positive("h", h)?;
        for c in contacts {
            let sides = std::iter::once(&c.a).chain(match &c.other {
                ContactOther::Body(b) => Some(b),
                ContactOther::Tool(_) => None,
            });
            for side in sides {
                let body = bodies
                    .get(side.body)
                    .ok_or(SoftTissueError::NodeOutOfRange {
                        node: side.body,
                        len: bodies.len(),
                    })?;
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
        self.prepare_slots(bodies);
        self.contacts.clear();
        self.contacts.extend_from_slice(contacts);
        self.report = ContactReport {
            contacts: contacts.len(),
            ..Default::default()
        };
        Ok(())
    }

    /// Phase 2: builds `H` and `W = Σ_b h² H_b A_b⁻¹ H_bᵀ` on the CPU.
    pub fn build_compliance<B: BodyRef>(&mut self, bodies: &[B]) -> Result<()> {
        self.build_compliance_with(bodies, None)
    }

    /// Phase 2 with an optional [`ComplianceBackend`] (the GPU) for `Factorized` bodies.
    pub fn build_compliance_with<B: BodyRef>(
        &mut self,
        bodies: &[B],
        mut backend: Option<&mut dyn ComplianceBackend>,
    ) -> Result<()> {
        let t0 = Instant::now();
        self.rows.clear();
        self.mu.clear();
        self.delta0.clear();
        for s in &mut self.slots {
            s.entries.clear();
        }
        let mut friction_contacts = 0;
        for c in &self.contacts {
            self.rows.push(self.delta0.len());
            self.mu.push(c.mu);
            self.delta0.push(c.gap);
            if c.mu > 0.0 {
                self.delta0.push(c.slip[0]);
                self.delta0.push(c.slip[1]);
                friction_contacts += 1;
            }
        }
        self.rows.push(self.delta0.len());
        let m = self.delta0.len();
        for (ci, c) in self.contacts.iter().enumerate() {
            let r0 = self.rows[ci];
            let dirs = [c.normal, c.tangents[0], c.tangents[1]];
            let nrows = self.rows[ci + 1] - r0;
            let mut push = |side: &ContactSide, sign: f64| {
                let body: &DeformableBody = &bodies[side.body];
                for k in 0..3 {
                    let (node, wgt) = (side.nodes[k] as usize, side.weights[k]);
                    if wgt == 0.0 || body.constraints()[node] != NodeConstraint::Free {
                        continue;
                    }
                    for (r, d) in dirs.iter().enumerate().take(nrows) {
                        self.slots[side.body].entries.push(JacEntry {
                            node: node as u32,
                            row: (r0 + r) as u32,
                            h: d * (sign * wgt),
                            j: Vec3::zeros(),
                        });
                    }
                }
            };
            push(&c.a, 1.0);
            if let ContactOther::Body(b) = &c.other {
                push(b, -1.0);
            }
        }
        self.w.clear();
        self.w.resize(m * m, 0.0);
        for (bi, body) in bodies.iter().enumerate() {
            let slot = &mut self.slots[bi];
            if slot.entries.is_empty() {
                continue;
            }
            slot.entries.sort_unstable_by_key(|e| (e.node, e.row));
            if slot.shifted && self.pass == 0 {
                // Detected at `x + shift`: the gaps at the free motion.
                for e in &slot.entries {
                    self.delta0[e.row as usize] -= e.h.dot(&slot.shift[e.node as usize]);
                }
            }
            slot.mode = body
                .settings()
                .compliance
                .unwrap_or(self.settings.compliance);
            slot.compliance.reuse_steps = self.settings.factor_reuse;
            slot.compliance.accumulate(
                body,
                slot.mode,
                self.h,
                &mut slot.entries,
                &mut self.w,
                m,
                match backend {
                    Some(ref mut b) => Some(&mut **b),
                    None => None,
                },
            )?;
            self.report.solves += slot.compliance.solves();
            self.report.gram_blocks += slot.compliance.gram_blocks();
        }
        if self.pass == 0 {
            self.report.rows = m;
            self.report.friction_contacts = friction_contacts;
        }
        self.report.compliance += t0.elapsed().as_secs_f64();
        Ok(())
    }

    fn key<B: BodyRef>(&self, c: &Contact, bodies: &[B]) -> ContactKey {
        let other = match c.other {
            ContactOther::Tool(t) => t as u64,
            ContactOther::Body(s) => (1 << 62) | bodies[s.body].id(),
        };
        (bodies[c.a.body].id(), c.a.nodes[0], other)
    }

    /// Phase 3: projected Gauss–Seidel on `W λ + δ₀`.
    pub fn solve_lcp<B: BodyRef>(&mut self, bodies: &[B]) -> LcpReport {
        let t0 = Instant::now();
        let m = self.delta0.len();
        self.lambda.clear();
        self.lambda.resize(m, 0.0);
        if self.settings.lcp.warm_start && self.pass == 0 {
            for (ci, c) in self.contacts.iter().enumerate() {
                if let Some(prev) = self.previous.get(&self.key(c, bodies)) {
                    let r = self.rows[ci];
                    let k = self.rows[ci + 1] - r;
                    self.lambda[r..r + k].copy_from_slice(&prev[..k]);
                }
            }
        }
        let report = lcp::solve(
            &self.w,
            &self.delta0,
            &self.rows,
            &self.mu,
            &mut self.lambda,
            &self.settings.lcp,
            &mut self.lcp_delta,
        );
        if self.pass == 0 {
            self.previous.clear();
        }
        for ci in 0..self.contacts.len() {
            let r = self.rows[ci];
            let mut f = [0.0; 3];
            let k = self.rows[ci + 1] - r;
            f[..k].copy_from_slice(&self.lambda[r..r + k]);
            if self.pass == 0 {
                let key = self.key(&self.contacts[ci], bodies);
                self.previous.insert(key, f);
            }
            self.contacts[ci].force = Vec3::new(f[0], f[1], f[2]);
        }
        self.report.lcp = report;
        self.report.lcp_seconds += t0.elapsed().as_secs_f64();
        report
    }

    /// Phase 4: applies `Δx = h² A⁻¹ Hᵀ λ` to every body and sets tool reactions.
    pub fn correct(
        &mut self,
        bodies: &mut [&mut DeformableBody],
        tools: &mut [&mut RigidTool],
    ) -> Result<()> {
        let t0 = Instant::now();
        for (bi, body) in bodies.iter_mut().enumerate() {
            let Some(slot) = self.slots.get_mut(bi) else {
                continue;
            };
            if slot.entries.is_empty() {
                continue;
            }
            slot.compliance.correction(
                body,
                slot.mode,
                self.h,
                &slot.entries,
                &self.lambda,
                &mut slot.dx,
            )?;
            if !slot.dx.iter().all(|d| d.iter().all(|c| c.is_finite())) {
                return Err(SoftTissueError::NonFinite("contact correction"));
            }
            body.apply_correction(&slot.dx);
            if slot.acc.len() == slot.dx.len() {
                for (a, d) in slot.acc.iter_mut().zip(&slot.dx) {
                    *a += d;
                }
                slot.has_acc = true;
            }
        }
        for (ti, t) in tools.iter_mut().enumerate() {
            let (mut force, mut torque) = if self.pass == 0 {
                (Vec3::zeros(), Vec3::zeros())
            } else {
                t.reaction()
            };
            for c in &self.contacts {
                if c.other == ContactOther::Tool(ti) {
                    let f = c.normal * c.force.x
                        + c.tangents[0] * c.force.y
                        + c.tangents[1] * c.force.z;
                    let arm = c.point - t.pose().translation.vector;
                    force -= f;
                    torque -= arm.cross(&f);
                }
            }
            t.set_reaction(force, torque);
        }
        self.report.correct += t0.elapsed().as_secs_f64();
        Ok(())
    }

    /// Runs detection, compliance, LCP and correction, then further
    /// frictionless passes while a vertex still penetrates (see
    /// [`ContactSettings::max_passes`]). Skips everything after detection when
    /// there is no contact.
    pub fn step(
        &mut self,
        bodies: &mut [&mut DeformableBody],
        tools: &mut [&mut RigidTool],
        h: f64,
    ) -> Result<()> {
        self.pass = 0;
        self.detect_in(bodies, tools, h)?;
        if self.contacts.is_empty() {
            self.clear_forces(tools);
            return Ok(());
        }
        self.build_compliance(bodies)?;
        self.solve_lcp(bodies);
        self.correct(bodies, tools)?;
        self.refine(bodies, tools, h)
    }

    /// Forgets warm-start forces and zeroes tool reactions (a step without contact).
    pub fn clear_forces(&mut self, tools: &mut [&mut RigidTool]) {
        self.previous.clear();
        self.lambda.clear();
        for s in &mut self.slots {
            s.entries.clear();
            s.has_acc = false;
        }
        for t in tools.iter_mut() {
            t.set_reaction(Vec3::zeros(), Vec3::zeros());
        }
    }

    /// Runs the extra frictionless passes after the first correction, while a
    /// vertex still penetrates deeper than the tolerance (see
    /// [`ContactSettings::max_passes`]).
    pub fn refine(
        &mut self,
        bodies: &mut [&mut DeformableBody],
        tools: &mut [&mut RigidTool],
        h: f64,
    ) -> Result<()> {
        self.report.passes = 1;
        let result = (|| {
            for pass in 1..self.settings.max_passes {
                self.pass = pass;
                self.detect_in(bodies, tools, h)?;
                if self.report.max_penetration <= self.settings.penetration_tolerance {
                    break;
                }
                self.build_compliance(bodies)?;
                self.solve_lcp(bodies);
                self.correct(bodies, tools)?;
                self.report.passes = pass + 1;
            }
            Ok(())
        })();
        self.pass = 0;
        result
    }
}

/// Slot `a` to read and slot `b` to update (`a ≠ b`).
fn slot_pair(slots: &mut [BodySlot], a: usize, b: usize) -> (&BodySlot, &mut BodySlot) {
    if a < b {
        let (lo, hi) = slots.split_at_mut(b);
        (&lo[a], &mut hi[0])
    } else {
        let (lo, hi) = slots.split_at_mut(a);
        (&hi[0], &mut lo[b])
    }
}

fn slot_b_aabb(tris: &[[usize; 3]], x: &[Vec3], margin: f64) -> (Vec3, Vec3) {
    let mut lo = Vec3::repeat(f64::INFINITY);
    let mut hi = Vec3::repeat(f64::NEG_INFINITY);
    for t in tris {
        for &v in t {
            lo = lo.inf(&x[v]);
            hi = hi.sup(&x[v]);
        }
    }
    (lo.add_scalar(-margin), hi.add_scalar(margin))
}
