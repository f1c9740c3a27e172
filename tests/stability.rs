//! The hard-case stability suite: stiffness contrast up to 10⁶ in a small,
//! free stiff core, a graded mesh (element sizes 100:1), time steps from
//! 1/240 to 0.04 s, ν = 0.49, a crushed start with inverted elements, a fast
//! tool impact, two bodies squeezed together, the stiff-core lens pressed
//! by a tool with friction, and a rod thinner than the lens's triangles
//! drawn across it with face contacts (`ContactSettings::tool_faces`).
//! Default (`Async`) preconditioner unless a case says otherwise.
//!
//! Every step of every case is checked ([`Monitor::step`]):
//! - no NaN or infinity in positions and velocities;
//! - the conjugate gradient converged (after a rescue, if one was needed);
//! - the total energy (kinetic + elastic + gravity) does not rise from the
//!   step before by more than the work of the contact forces that step
//!   (`Σ f·Δx` over the nodes, with the end-of-step forces of all passes),
//!   plus a stated allowance `ALLOWANCE × E_ref`, with `E_ref` the case's
//!   energy scale and `ALLOWANCE` = 1e-3 (the CG stops at a relative residual
//!   of 1e-6; the allowance covers that, not a tuned margin). This holds for
//!   the implicit step with its exact compliance. Every contact case runs
//!   three times: with the default solver (`Async` preconditioner,
//!   `Factorized` compliance from its factor, rigid modes completed), with
//!   the default solver and its energy guard on
//!   (`ContactSettings::energy_tolerance` = [`GUARD`]), and with the exact
//!   one (`Exact` for both). In steps without contact the bound is asserted
//!   for all three; in steps with contact for the guarded and the exact one,
//!   and for the default in the drops (a free lens landing: a rigid-mode
//!   motion, which `ContactSettings::rigid_modes` answers exactly) and in
//!   the impact (a clamped block at h = 1/240, measured 5–6e-5 `E_ref`);
//! - in every step with contact, whatever the solver, the rise beyond the
//!   contact forces' work stays within the work the solver reports its
//!   correction added (`ContactReport::misaccounted_work`, 0 with the exact
//!   compliance) plus the same allowance: where the default solver's bound is
//!   only recorded (below), its gain is the one it tells the user about;
//! - no surface vertex is deeper than the penetration tolerance inside a tool
//!   or the other body, by a detection of its own at the step's end.
//!
//! With the exact compliance every contact step keeps the bound to round-off
//! (measured: at most 6e-14 `E_ref`). With the default solver the
//! correction `Δx = h² P⁻¹ Hᵀ λ` uses the preconditioner's factor `P`, made
//! from an older matrix and warped by the node rotations since, not `A`. The
//! warp turned a free body's rigid modes into stiff deformation: a lens that
//! landed, or rested on the plate against gravity, gained up to 1.7e-2
//! `E_ref` a step at h = 0.04 (2e-3 at h = 1/60) even with the consistency
//! refresh. The rigid-mode completion (`P⁻¹` replaced by
//! `Q + (I − QA) P⁻¹ (I − AQ)` over the six rigid modes) brought the landings
//! to at most 2e-4 `E_ref`, which is asserted. Where the tissue deforms
//! under a held tool (the pressed lens, the squeezed blocks) the factor's
//! deformation error remains: up to 1.3e-2 `E_ref` measured with the default,
//! recorded and printed, not asserted against the contact forces' work alone
//! (it is against the reported misaccounted work, which no held case's rise
//! exceeded by more than 1e-14 `E_ref` in five runs of the suite, and no
//! case by more than 1.1e-4); the guard,
//! which refreshes the
//! factor when a pass's misaccounted work exceeds [`GUARD`] of the body's
//! energy, keeps the bound there, at the cost of many refreshes (in the
//! cataract scene it halves the jam's steps/s, so it is off by default).
//! The default's figures vary from run to run with the background factor's
//! timing.
//!
//! Run it in release: `cargo test --release --test stability` (about 6 s on
//! two cores; longer in the test profile of `cargo test`).

use bevy_soft_tissue::contact::{NO_TOOLS, PassKind};
use bevy_soft_tissue::core_prelude::*;
use bevy_soft_tissue::mesh::generate::LENS_RADII;
use nalgebra::{Isometry3, Translation3, UnitQuaternion};

/// Energy rise allowed per step beyond the tools' work, relative to the case's energy scale.
const ALLOWANCE: f64 = 1e-3;

fn at(p: Vec3) -> Pose {
    Isometry3::from_parts(Translation3::from(p), UnitQuaternion::identity())
}

/// Checks every step of a scene (see the module docs).
struct Monitor {
    name: String,
    gravity: Vec3,
    e_ref: f64,
    energy: f64,
    checker: ContactSolver,
    tolerance: f64,
    steps: usize,
    worst_rise: f64,
    /// The largest rise in a step with contacts, relative to `e_ref`.
    contact_rise: f64,
    /// The largest rise in a step with contacts beyond the misaccounted work
    /// the solver reported, relative to `e_ref`.
    unexplained: f64,
    /// Whether the energy bound is asserted in steps with contact too: the
    /// exact compliance, the energy guard, or a case that asks for it
    /// ([`Monitor::asserting_contact`]).
    asserted: bool,
}

/// The solver variants each contact case runs with: the default (`Async`
/// preconditioner, `Factorized` compliance from its factor, rigid modes
/// completed), the default with the energy guard on
/// (`ContactSettings::energy_tolerance` = [`GUARD`]) and the exact one (a
/// fresh factorization every step for both).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Variant {
    Default,
    Guarded,
    Exact,
}

const VARIANTS: [Variant; 3] = [Variant::Default, Variant::Guarded, Variant::Exact];

/// The energy guard of [`Variant::Guarded`]: a correction may add at most
/// this fraction of its body's mechanical energy per pass before the factor
/// is refreshed.
const GUARD: f64 = 1e-5;

impl Variant {
    fn body(self, base: BodySettings) -> BodySettings {
        match self {
            Variant::Default | Variant::Guarded => base,
            Variant::Exact => BodySettings {
                preconditioner: PreconditionerKind::Exact,
                ..base
            },
        }
    }

    fn contact(self) -> ContactSettings {
        let mut c = contact_settings();
        match self {
            Variant::Default => {}
            Variant::Guarded => c.energy_tolerance = GUARD,
            Variant::Exact => c.compliance = ComplianceMode::Exact,
        }
        c
    }
}

fn total_energy(scene: &Scene, g: Vec3) -> f64 {
    scene
        .bodies
        .iter()
        .map(|b| {
            let grav: f64 = b
                .positions()
                .iter()
                .zip(b.mass())
                .map(|(x, m)| -m * g.dot(x))
                .sum();
            b.kinetic_energy() + b.elastic_energy() + grav
        })
        .sum()
}

impl Monitor {
    fn new(name: impl Into<String>, scene: &Scene, gravity: Vec3, e_ref: f64) -> Self {
        let settings = *scene.contact.settings();
        let exact = settings.compliance == ComplianceMode::Exact
            && scene
                .bodies
                .iter()
                .all(|b| b.settings().preconditioner == PreconditionerKind::Exact);
        let guarded = settings.energy_tolerance <= GUARD;
        Self {
            asserted: exact || guarded,
            name: name.into(),
            gravity,
            e_ref,
            energy: total_energy(scene, gravity),
            checker: ContactSolver::new(settings).unwrap(),
            tolerance: settings.penetration_tolerance,
            steps: 0,
            worst_rise: f64::NEG_INFINITY,
            contact_rise: f64::NEG_INFINITY,
            unexplained: f64::NEG_INFINITY,
        }
    }

    /// Asserts the energy bound in steps with contact whatever the solver (the
    /// cases whose bodies are free: the rigid-mode completion makes the
    /// default solver keep it there).
    fn asserting_contact(mut self) -> Self {
        self.asserted = true;
        self
    }

    /// Prints the largest energy rises, relative to `E_ref`.
    fn report(&self) {
        let show = |r: f64| {
            if r.is_finite() {
                format!("{r:.2e} E_ref")
            } else {
                "none".into()
            }
        };
        println!(
            "{}: {} steps, largest energy rise without contact {} (asserted), with contact {} ({}), \
             beyond the reported misaccounted work {} (asserted)",
            self.name,
            self.steps,
            show(self.worst_rise),
            show(self.contact_rise),
            if self.asserted {
                "asserted"
            } else {
                "recorded"
            },
            show(self.unexplained)
        );
    }

    /// Steps the scene by `h` and checks the step.
    fn step(&mut self, scene: &mut Scene, h: f64) {
        let s = self.steps;
        let name = &self.name;
        scene
            .step(h)
            .unwrap_or_else(|e| panic!("{name}, step {s}: {e}"));
        self.steps += 1;
        for (bi, b) in scene.bodies.iter().enumerate() {
            let finite = b
                .positions()
                .iter()
                .chain(b.velocities())
                .all(|p| p.iter().all(|c| c.is_finite()));
            assert!(finite, "{name}, step {s}: body {bi} has a non-finite state");
            let r = b.report();
            assert!(
                r.cg.converged,
                "{name}, step {s}: body {bi}'s CG did not converge ({:?}, {} rescues)",
                r.cg, r.preconditioner.rescues
            );
        }
        // The work of the external forces on the tissue this step: the
        // contact forces (end-of-step forces of the implicit step, all passes)
        // along each node's displacement. Gravity is in the energy itself.
        let mut work = 0.0;
        if scene.can_touch() {
            for (bi, b) in scene.bodies.iter().enumerate() {
                let f = scene.contact.contact_forces(bi);
                for ((x, x0), f) in b.positions().iter().zip(b.start_positions()).zip(f) {
                    work += f.dot(&(x - x0));
                }
            }
        }
        let e = total_energy(scene, self.gravity);
        let rise = e - self.energy - work;
        let contact = scene.contact.report().contacts > 0;
        // The work the default correction adds beyond the contact forces, as
        // the solver reports it (0 with the exact compliance).
        let misaccounted = scene.contact.report().misaccounted_work;
        if contact {
            self.unexplained = self.unexplained.max((rise - misaccounted) / self.e_ref);
            self.contact_rise = self.contact_rise.max(rise / self.e_ref);
        } else {
            self.worst_rise = self.worst_rise.max(rise / self.e_ref);
        }
        if !contact || self.asserted {
            assert!(
                rise <= ALLOWANCE * self.e_ref,
                "{name}, step {s}: energy rose by {rise:.3e} J beyond the contact forces' work \
                 {work:.3e} J (allowance {:.3e} J)",
                ALLOWANCE * self.e_ref
            );
        }
        // Whatever the solver, no energy comes from where the solver does not
        // say: the rise stays within the misaccounted work it reports.
        assert!(
            rise - misaccounted <= ALLOWANCE * self.e_ref,
            "{name}, step {s}: energy rose by {rise:.3e} J beyond the contact forces' work \
             {work:.3e} J, of which the solver reported {misaccounted:.3e} J (allowance {:.3e} J)",
            ALLOWANCE * self.e_ref
        );
        self.energy = e;
        if scene.can_touch() {
            self.checker
                .detect(&scene.bodies, &scene.tools, h, PassKind::First)
                .unwrap();
            let deepest = self
                .checker
                .contacts()
                .iter()
                .map(|c| -c.gap)
                .fold(0.0, f64::max);
            assert!(
                deepest <= self.tolerance,
                "{name}, step {s}: a vertex is {deepest:.3e} m deep (tolerance {:.1e})",
                self.tolerance
            );
        }
    }
}

/// A lens whose core (`core_radius` of the radii) is `factor`× stiffer, sharp edge.
fn cored_lens(cells: usize, factor: f64, poisson: f64, settings: BodySettings) -> DeformableBody {
    let mesh = generate::ellipsoid(LENS_RADII, cells).unwrap();
    let material = TissueMaterial::new(1000.0, 3e3, poisson)
        .with_damping(5.0, 0.0)
        .with_stiffness(StiffnessField::Radial {
            center: Vec3::zeros(),
            radii: Vec3::from(LENS_RADII),
            core_radius: 0.4,
            factor,
            transition: Transition::Sharp,
        });
    DeformableBody::new(mesh, material, settings).unwrap()
}

fn contact_settings() -> ContactSettings {
    ContactSettings {
        alarm_distance: 2e-4,
        max_passes: 32,
        ..Default::default()
    }
}

/// A plate whose top is at `z`, 40 mm thick: far thicker than any step
/// moves a vertex, since detection has no continuous collision (a vertex
/// that ends a step nearer a thin plate's far side is pushed out there).
fn plate(z: f64, mu: f64) -> RigidTool {
    RigidTool::new(
        ToolShape::Box {
            half_extents: v3(0.02, 0.02, 0.02),
        },
        at(v3(0.0, 0.0, z - 0.02)),
    )
    .unwrap()
    .with_friction(mu)
    .unwrap()
}

fn gravity() -> Vec3 {
    v3(0.0, 0.0, -9.81)
}

/// Energy scale of a body: its weight times its size, and its elastic energy
/// at 10 % strain (whichever is larger).
fn energy_scale(b: &DeformableBody) -> f64 {
    let m: f64 = b.mass().iter().sum();
    let size = b.mesh().max_edge_length() * 10.0;
    let vol: f64 = b.elements().iter().map(|e| e.volume).sum();
    let e_min = b
        .element_young()
        .iter()
        .copied()
        .fold(f64::INFINITY, f64::min);
    (m * 9.81 * size).max(0.5 * e_min * 0.01 * vol)
}

/// Drops the stiff-core lens onto a plate for 0.6 s (see [`stiff_core_drop`]).
fn stiff_core_drop(factor: f64, h: f64, v: Variant) {
    let settings = v.body(BodySettings {
        gravity: Some(gravity()),
        ..Default::default()
    });
    let mut scene = Scene::new(v.contact()).unwrap();
    let lens = cored_lens(6, factor, 0.45, settings);
    let e_ref = energy_scale(&lens);
    scene.add_body(lens);
    scene.add_tool(plate(-LENS_RADII[2] - 5e-4, 0.3));
    // The lens is free: its landing is a rigid-mode motion, which the
    // default solver answers exactly (`ContactSettings::rigid_modes`).
    let mut m = Monitor::new(
        format!("contrast {factor:e}, h {h:.4}, {v:?}"),
        &scene,
        gravity(),
        e_ref,
    )
    .asserting_contact();
    let steps = (0.6 / h) as usize;
    for _ in 0..steps {
        m.step(&mut scene, h);
    }
    // It landed and rests on the plate.
    let low = scene.bodies[0]
        .positions()
        .iter()
        .map(|p| p.z)
        .fold(f64::INFINITY, f64::min);
    assert!(
        low < -LENS_RADII[2] - 4e-4,
        "contrast {factor:e}, h {h}: did not fall ({low})"
    );
    m.report();
}

/// The stiff core (40 % of the radii) free inside the soft lens, dropped
/// 0.5 mm onto a plate: contrast 10², 10⁴, 10⁶ at h = 1/240 s.
#[test]
fn stiff_core_in_soft_lens_dropped_on_a_plate() {
    for v in VARIANTS {
        for factor in [1e2, 1e4, 1e6] {
            stiff_core_drop(factor, 1.0 / 240.0, v);
        }
    }
}

/// The same drops at h = 1/60, 0.02 and 0.04 s: the lens falls the whole
/// gap within the first step (2.7, 3.9 and 15.7 mm: at 0.04 s more than
/// three times its own thickness) and lands in one correction.
#[test]
fn stiff_core_dropped_with_large_steps() {
    for h in [1.0 / 60.0, 0.02, 0.04] {
        for factor in [1e2, 1e4, 1e6] {
            for v in VARIANTS {
                stiff_core_drop(factor, h, v);
            }
        }
    }
}

/// A block graded 100:1 in element size along each axis (the smallest cell
/// in one corner, the largest in the other), clamped at one face.
#[test]
fn graded_mesh_with_sizes_100_to_1() {
    let n = 10;
    let base = generate::box_mesh(Vec3::zeros(), v3(1.0, 1.0, 1.0), [n; 3]).unwrap();
    let r: f64 = 100f64.powf(1.0 / (n as f64 - 1.0));
    let grade = |u: f64| 0.02 * (r.powf(u * n as f64) - 1.0) / (r.powi(n as i32) - 1.0);
    let pos: Vec<Vec3> = base
        .positions()
        .iter()
        .map(|p| v3(grade(p.x), grade(p.y), grade(p.z)))
        .collect();
    let mesh = TetMesh::new(pos, base.tets().to_vec()).unwrap();
    let ratio = mesh.max_edge_length() / mesh.min_edge_length();
    assert!(ratio >= 100.0, "element size ratio {ratio}");
    let settings = BodySettings {
        gravity: Some(gravity()),
        ..Default::default()
    };
    let material = TissueMaterial::new(1000.0, 2e4, 0.45).with_damping(2.0, 0.0);
    let mut body = DeformableBody::new(mesh, material, settings).unwrap();
    body.fix_where(|p| p.x < 1e-12);
    let e_ref = energy_scale(&body);
    let mut scene = Scene::new(contact_settings()).unwrap();
    scene.add_body(body);
    let mut m = Monitor::new("graded 100:1", &scene, gravity(), e_ref);
    for _ in 0..90 {
        m.step(&mut scene, 1.0 / 60.0);
    }
    m.report();
}

/// Nearly incompressible (ν = 0.49) lens with a stiff core, pressed by a
/// sphere with friction onto a plate.
#[test]
fn nearly_incompressible_lens_pressed_with_friction() {
    for (poisson, v) in [0.49, 0.45]
        .into_iter()
        .flat_map(|p| VARIANTS.map(|v| (p, v)))
    {
        let mut scene = Scene::new(v.contact()).unwrap();
        let lens = cored_lens(6, 5.0, poisson, v.body(BodySettings::default()));
        let e_ref = energy_scale(&lens);
        scene.add_body(lens);
        scene.add_tool(plate(-LENS_RADII[2], 0.5));
        let r = 3e-3;
        scene.add_tool(
            RigidTool::new(
                ToolShape::Sphere { radius: r },
                at(v3(0.0, 0.0, LENS_RADII[2] + r + 1e-4)),
            )
            .unwrap()
            .with_friction(0.5)
            .unwrap(),
        );
        let mut m = Monitor::new(
            format!("pressed, ν = {poisson}, {v:?}"),
            &scene,
            Vec3::zeros(),
            e_ref,
        );
        let h = 1.0 / 60.0;
        for s in 0..90 {
            // Down 1.2 mm over 1 s (with a sideways drift for friction), then held.
            let t = (s as f64 * h).min(1.0);
            let p = v3(0.3e-3 * t, 0.0, LENS_RADII[2] + r + 1e-4 - 1.3e-3 * t);
            scene.tools[1].set_pose(at(p)).unwrap();
            m.step(&mut scene, h);
        }
        assert!(
            scene.tools[1].reaction().0.z > 0.0,
            "the lens pushes the sphere up"
        );
        m.report();
    }
}

/// A block started crushed: flattened to 5 % of its height, with its top
/// layer pushed through the bottom (inverted elements). It recovers.
#[test]
fn crushed_start_with_inverted_elements_recovers() {
    let mesh = generate::box_mesh(Vec3::zeros(), v3(0.01, 0.01, 0.01), [4, 4, 4]).unwrap();
    let material = TissueMaterial::new(1000.0, 1e4, 0.4).with_damping(5.0, 0.0);
    let mut body = DeformableBody::new(mesh.clone(), material, BodySettings::default()).unwrap();
    let x: Vec<Vec3> = mesh
        .positions()
        .iter()
        .map(|p| {
            let z = if p.z > 0.0099 { -0.0002 } else { 0.05 * p.z };
            v3(p.x, p.y, z)
        })
        .collect();
    body.set_state(&x, &vec![Vec3::zeros(); x.len()]).unwrap();
    let inverted = body.inverted_elements();
    assert!(inverted > 0, "the crushed start has no inverted element");
    let e_ref = body.elastic_energy();
    let mut scene = Scene::new(contact_settings()).unwrap();
    scene.add_body(body);
    let mut m = Monitor::new("crushed start", &scene, Vec3::zeros(), e_ref);
    for _ in 0..240 {
        m.step(&mut scene, 1.0 / 60.0);
    }
    let b = &scene.bodies[0];
    let height = b
        .positions()
        .iter()
        .map(|p| p.z)
        .fold(f64::NEG_INFINITY, f64::max)
        - b.positions()
            .iter()
            .map(|p| p.z)
            .fold(f64::INFINITY, f64::min);
    assert!(height > 0.008, "did not recover its height: {height}");
    assert_eq!(
        b.inverted_elements(),
        0,
        "of {inverted} inverted elements at the start, some stayed inverted"
    );
    assert!(
        b.elastic_energy() < 0.01 * e_ref,
        "energy left {:.3e} of {e_ref:.3e}",
        b.elastic_energy()
    );
    m.report();
}

/// A sphere hits a soft block at 0.5 m/s and goes on into it for 3 mm.
#[test]
fn fast_tool_impact() {
    for variant in VARIANTS {
        let mesh =
            generate::box_mesh(v3(-0.01, -0.01, 0.0), v3(0.01, 0.01, 0.01), [6, 6, 3]).unwrap();
        let material = TissueMaterial::new(1000.0, 2e4, 0.45).with_damping(2.0, 0.0);
        let mut body =
            DeformableBody::new(mesh, material, variant.body(BodySettings::default())).unwrap();
        body.fix_where(|p| p.z < 1e-9);
        let e_ref = energy_scale(&body);
        let mut scene = Scene::new(variant.contact()).unwrap();
        scene.add_body(body);
        let r = 3e-3;
        let z0 = 0.01 + r + 1e-3;
        scene.add_tool(
            RigidTool::new(ToolShape::Sphere { radius: r }, at(v3(0.0, 0.0, z0))).unwrap(),
        );
        // A clamped block (no rigid modes) at a short step: the default's
        // lagging factor is close to the matrix, and the bound is asserted
        // for it too.
        let mut m = Monitor::new(
            format!("impact 0.5 m/s, {variant:?}"),
            &scene,
            Vec3::zeros(),
            e_ref,
        )
        .asserting_contact();
        let h = 1.0 / 240.0;
        let v = 0.5;
        for s in 1..=60 {
            let z = (z0 - v * s as f64 * h).max(z0 - 4e-3);
            scene.tools[0].set_pose(at(v3(0.0, 0.0, z))).unwrap();
            m.step(&mut scene, h);
        }
        assert!(scene.tools[0].reaction().0.z > 0.0);
        m.report();
    }
}

/// Two soft blocks squeezed together between two rough plates closing at
/// 10 mm/s (the blocks touch each other without friction).
#[test]
fn two_bodies_squeezed_together() {
    for v in VARIANTS {
        let block = |z0: f64| {
            let mesh = generate::box_mesh(
                v3(-0.004, -0.004, z0),
                v3(0.004, 0.004, z0 + 0.004),
                [3, 3, 3],
            )
            .unwrap();
            DeformableBody::new(
                mesh,
                TissueMaterial::new(1000.0, 1e4, 0.45).with_damping(5.0, 0.0),
                v.body(BodySettings::default()),
            )
            .unwrap()
        };
        let mut scene = Scene::new(v.contact()).unwrap();
        let (a, b) = (block(0.0), block(0.0041));
        let e_ref = energy_scale(&a);
        scene.add_body(a);
        scene.add_body(b);
        let box_tool = |z: f64| {
            RigidTool::new(
                ToolShape::Box {
                    half_extents: v3(0.01, 0.01, 0.002),
                },
                at(v3(0.0, 0.0, z)),
            )
            .unwrap()
            .with_friction(0.8)
            .unwrap()
        };
        scene.add_tool(box_tool(-0.002 - 1e-4));
        scene.add_tool(box_tool(0.0081 + 0.002 + 1e-4));
        let mut m = Monitor::new(
            format!("two bodies squeezed, {v:?}"),
            &scene,
            Vec3::zeros(),
            e_ref,
        );
        let h = 1.0 / 60.0;
        for s in 1..=60 {
            let d = (0.01 * s as f64 * h).min(2e-3);
            scene.tools[1]
                .set_pose(at(v3(0.0, 0.0, 0.0081 + 0.002 + 1e-4 - d)))
                .unwrap();
            m.step(&mut scene, h);
        }
        // The squeeze reaches the lower plate through both blocks.
        let (lo, hi) = (scene.tools[0].reaction().0, scene.tools[1].reaction().0);
        assert!(
            lo.z < 0.0 && hi.z > 0.0,
            "lower plate {lo:?}, upper plate {hi:?}"
        );
        // No vertex of one block inside the other, checked by detection alone.
        let mut probe = ContactSolver::new(contact_settings()).unwrap();
        probe
            .detect(&scene.bodies, &NO_TOOLS, h, PassKind::First)
            .unwrap();
        let deepest = probe.contacts().iter().map(|c| -c.gap).fold(0.0, f64::max);
        assert!(
            deepest <= contact_settings().penetration_tolerance,
            "{deepest}"
        );
        m.report();
    }
}

/// A rigid rotation of the rest shape, through the stepping path (the step's
/// own rotations and right-hand side): no elastic force, so the body stays
/// where it is, at rest.
#[test]
fn rigid_rotation_through_the_step_moves_nothing() {
    for kind in [PreconditionerKind::Exact, PreconditionerKind::Async] {
        let mesh = generate::ellipsoid(LENS_RADII, 6).unwrap();
        let mut body = DeformableBody::new(
            mesh.clone(),
            TissueMaterial::new(1000.0, 3e3, 0.45),
            BodySettings {
                preconditioner: kind,
                ..Default::default()
            },
        )
        .unwrap();
        let rot = nalgebra::Rotation3::from_euler_angles(0.7, -1.1, 2.3);
        let x: Vec<Vec3> = mesh.positions().iter().map(|p| rot * p).collect();
        body.set_state(&x, &vec![Vec3::zeros(); x.len()]).unwrap();
        for s in 0..5 {
            body.step(1.0 / 60.0).unwrap();
            let moved = body
                .positions()
                .iter()
                .zip(&x)
                .map(|(p, q)| (p - q).norm())
                .fold(0.0, f64::max);
            assert!(
                moved <= 1e-12 * LENS_RADII[0],
                "{kind:?}, step {s}: a rigid rotation moved a node by {moved:e} m"
            );
        }
    }
}

#[path = "../examples/common/mod.rs"]
mod common;

/// A short soak: the coarse cataract scene, the vectis in and out for 1500
/// steps (25 s, one and a half cycles), default solver. Nothing fails: no
/// error, no NaN, every CG converged, every step's end within the
/// penetration tolerance (`examples/soak.rs` runs the long one).
#[test]
fn short_soak_of_the_cataract_scene() {
    let s = common::soak::run_soak(
        &bevy_soft_tissue::scenes::cataract::CataractParams::coarse(),
        1500,
        |_| {},
    )
    .unwrap();
    println!("{s:?}");
    assert_eq!(s.steps, 1500);
    assert!(!s.failed(), "{s:?}");
}

/// A rod far thinner than the lens's surface triangles (0.3 mm thick, the
/// triangles about 1.5 mm across), pressed 0.6 mm into the top of the
/// stiff-core lens and then drawn 1 mm sideways, with face contacts
/// (`ContactSettings::tool_faces`). Beyond the [`Monitor`]'s checks, every
/// step ends with the lens's faces out of the rod to twice the tolerance, on
/// a grid of 48 points a triangle edge, and the lens pushes the rod up once
/// it is pressed in. Without face contacts the rod sinks between the
/// vertices by more than half its radius.
#[test]
fn thin_rod_drawn_across_the_lens_with_face_contacts() {
    let r = 0.15e-3;
    let top = LENS_RADII[2] + r + 1e-4;
    let rod = |p: Vec3| {
        Isometry3::from_parts(
            Translation3::from(p),
            UnitQuaternion::from_axis_angle(&Vec3::z_axis(), 0.3),
        )
    };
    let run = |v: Variant, on: bool| {
        let mut c = v.contact();
        c.tool_faces = on;
        let tol = c.penetration_tolerance;
        let mut scene = Scene::new(c).unwrap();
        let lens = cored_lens(6, 5.0, 0.45, v.body(BodySettings::default()));
        let e_ref = energy_scale(&lens);
        let triangles: Vec<[usize; 3]> = lens.surface().volume_triangles().collect();
        scene.add_body(lens);
        scene.add_tool(plate(-LENS_RADII[2], 0.5));
        let shape = ToolShape::Capsule {
            half_height: 3e-3,
            radius: r,
        };
        scene.add_tool(RigidTool::new(shape, rod(v3(0.0, 0.0, top))).unwrap());
        let name = format!("thin rod, faces {on}, {v:?}");
        let mut m = Monitor::new(&name, &scene, Vec3::zeros(), e_ref);
        let h = 1.0 / 60.0;
        let mut deepest: f64 = 0.0;
        for s in 0..60 {
            // Down 0.6 mm over 0.5 s, then 1 mm sideways over 0.5 s.
            let t = s as f64 * h;
            let down = (t / 0.5).min(1.0) * 0.6e-3;
            let side = ((t - 0.5) / 0.5).clamp(0.0, 1.0) * 1e-3;
            scene.tools[1]
                .set_pose(rod(v3(side, 0.0, top - down)))
                .unwrap();
            m.step(&mut scene, h);
            if on && s == 29 {
                assert!(
                    scene.tools[1].reaction().0.z > 0.0,
                    "{name}: the lens pushes the rod up"
                );
            }
            let x = scene.bodies[0].positions();
            let depth = common::faces::tool_in_faces(&scene.tools[1], &triangles, x, 0.0, 48).0;
            assert!(
                !on || depth <= 2.0 * tol,
                "{name}, step {s}: the rod {depth:.3e} m inside a face"
            );
            deepest = deepest.max(depth);
        }
        m.report();
        println!("{name}: the rod at most {deepest:.2e} m inside a face");
        deepest
    };
    for v in VARIANTS {
        run(v, true);
    }
    let sunk = run(Variant::Default, false);
    assert!(sunk > 0.5 * r, "without face contacts: {sunk:.3e} m");
}
