//! `tests/contact.rs`: the stepping loop with contacts allocates nothing once warm.

use super::*;

/// A lens held under a pressing, sliding sphere with friction: after a few
/// steps every buffer of the step (detection, `W`, the LCP, the correction,
/// the warm start, the background worker's hand-over) has its size, and a
/// step allocates nothing on the stepping thread, for the synchronous and
/// the background preconditioners and both `W` paths of the CPU.
#[test]
fn a_contact_step_allocates_nothing_once_warm() {
    for (kind, mode) in [
        (
            PreconditionerKind::Periodic { every: 4 },
            ComplianceMode::Factorized,
        ),
        (
            PreconditionerKind::Periodic { every: 4 },
            ComplianceMode::Exact,
        ),
        (
            PreconditionerKind::AsyncLagged { lag: 2 },
            ComplianceMode::Factorized,
        ),
        (PreconditionerKind::Async, ComplianceMode::Factorized),
    ] {
        let (mut scene, h) = pressed_lens(kind, mode);
        let mut counts = Vec::new();
        for s in 0..40 {
            // Pressed 0.1 mm deeper than `pressed_lens` left it, sliding along x.
            let x = 0.74e-3 + 2e-6 * s as f64;
            scene.tools[0]
                .set_pose(at(x, 0.0, 2.25e-3 + 3e-3 - 1.2e-3))
                .unwrap();
            let before = allocations();
            let r = scene.step(h).unwrap();
            counts.push(allocations() - before);
            assert!(r.contacts > 5, "{mode:?} step {s}: {r:?}");
        }
        assert_steady(kind, &counts, &format!("{kind:?}, {mode:?}"));
    }
}
