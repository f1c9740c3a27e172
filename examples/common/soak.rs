//! The soak run: the cataract scene with the vectis going in and out of the
//! incision again and again, through the core `Scene` with the default
//! solver. Shared by `examples/soak.rs` and the short soak of
//! `tests/stability.rs` (not library API).

use bevy_soft_tissue::body::BodySettings;
use bevy_soft_tissue::contact::{ContactSolver, PassKind};
use bevy_soft_tissue::error::Result;
use bevy_soft_tissue::scene::Scene;
use bevy_soft_tissue::scenes::cataract::{self, CataractParams};

/// What a soak run saw.
#[derive(Debug, Clone, Default)]
pub struct SoakSummary {
    /// Steps run.
    pub steps: usize,
    /// Deepest penetration at a step's end (vectis or lens–sclera), metres.
    pub max_penetration: f64,
    /// The tolerance it is held to: 1 % of the lens's smallest edge, metres.
    pub tolerance: f64,
    /// Largest rise of the total energy (kinetic + elastic) from one step to
    /// the next beyond the contact forces' work that step, joules, and the
    /// step's elastic energy scale it compares to.
    pub max_energy_rise: (f64, f64),
    /// Steps whose state had a NaN or an infinity.
    pub nan_steps: usize,
    /// CG rescues (blocking refactorizations), both bodies.
    pub rescues: u64,
    /// The most CG iterations a body needed in a step.
    pub worst_cg: usize,
    /// Steps where a body's CG did not converge.
    pub unconverged: usize,
    /// Elements flat or inverted (`DeformableBody::inverted_elements`, both
    /// bodies): the most at a step's end, and at the last step's end.
    pub inverted: (usize, usize),
    /// The first error a step returned, if any.
    pub error: Option<String>,
}

impl SoakSummary {
    /// Whether anything failed: an error, a NaN, an unconverged CG, or a
    /// penetration beyond the tolerance.
    pub fn failed(&self) -> bool {
        self.error.is_some()
            || self.nan_steps > 0
            || self.unconverged > 0
            || self.max_penetration > self.tolerance
    }
}

fn energy(scene: &Scene) -> f64 {
    scene
        .bodies
        .iter()
        .map(|b| b.kinetic_energy() + b.elastic_energy())
        .sum()
}

/// Runs `steps` steps of `params`'s scene with the vectis pushed in over its
/// push path (8 s) and drawn back out over the same time, repeatedly;
/// `progress` is called after every step.
pub fn run_soak(
    params: &CataractParams,
    steps: usize,
    mut progress: impl FnMut(usize),
) -> Result<SoakSummary> {
    let params = params.clone().push_only();
    let built = cataract::build(&params, BodySettings::default())?;
    let h = 1.0 / 60.0;
    let period = 2.0 * built.path.duration();
    let mut scene = Scene::new(built.contact)?;
    scene.add_body(built.lens);
    scene.add_body(built.eye);
    scene.add_tool(built.vectis);
    let mut checker = ContactSolver::new(*scene.contact.settings())?;
    let mut s = SoakSummary {
        tolerance: 0.01 * scene.bodies[0].mesh().min_edge_length(),
        max_energy_rise: (f64::NEG_INFINITY, 0.0),
        ..Default::default()
    };
    let mut e_prev = energy(&scene);
    for step in 0..steps {
        let t = (step + 1) as f64 * h;
        let u = t % period;
        let path_t = if u <= 0.5 * period { u } else { period - u };
        let pose = built.path.pose(path_t);
        scene.tools[0].set_pose(pose)?;
        s.steps = step + 1;
        if let Err(e) = scene.step(h) {
            s.error = Some(format!("step {step}: {e}"));
            break;
        }
        let finite = scene.bodies.iter().all(|b| {
            b.positions()
                .iter()
                .chain(b.velocities())
                .all(|p| p.iter().all(|c| c.is_finite()))
        });
        if !finite {
            s.nan_steps += 1;
            break;
        }
        let mut rescues = 0;
        for b in &scene.bodies {
            let r = b.report();
            s.worst_cg = s.worst_cg.max(r.cg.iterations);
            s.unconverged += usize::from(!r.cg.converged);
            rescues += r.preconditioner.rescues;
        }
        s.rescues = rescues;
        // Work of the contact forces this step (end-of-step forces, all passes).
        let mut work = 0.0;
        for (bi, b) in scene.bodies.iter().enumerate() {
            for ((x, x0), f) in b
                .positions()
                .iter()
                .zip(b.start_positions())
                .zip(scene.contact.contact_forces(bi))
            {
                work += f.dot(&(x - x0));
            }
        }
        let e = energy(&scene);
        let rise = e - e_prev - work;
        if rise > s.max_energy_rise.0 {
            let elastic: f64 = scene.bodies.iter().map(|b| b.elastic_energy()).sum();
            s.max_energy_rise = (rise, elastic);
        }
        e_prev = e;
        checker.detect(&scene.bodies, &scene.tools, h, PassKind::First)?;
        let deepest = checker
            .contacts()
            .iter()
            .map(|c| -c.gap)
            .fold(0.0, f64::max);
        s.max_penetration = s.max_penetration.max(deepest);
        let inverted = scene.bodies.iter().map(|b| b.inverted_elements()).sum();
        s.inverted = (s.inverted.0.max(inverted), inverted);
        progress(step);
    }
    Ok(s)
}
