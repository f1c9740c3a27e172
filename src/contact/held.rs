//! Refinement passes: the planes a pass keeps from the pass before.
//!
//! A vertex inside the other side near an edge or a corner of its surface (a
//! lens vertex in the root of the incision's slit, or by the vectis blade's
//! rim) has a closest point that jumps between faces, and so a normal that
//! turns from one pass to the next. Each pass pushed it out along its normal
//! of the moment, into the other face's half-space, and the passes took
//! turns, the depth shrinking by a few per cent a pass, up to the pass limit
//! (traced in the cataract scene: normals about 90° apart, alternating for
//! 50 passes). [`hold_planes`] keeps the last pass's plane of such a vertex
//! next to its new contact, so that one LCP pushes it out of both.

use super::types::{Contact, ContactOther, ContactSide};
use crate::math::Vec3;

/// Planes are held only from this refinement pass on: most steps end
/// within two or three passes, and a held plane at a convex edge of the
/// other side pushes a vertex out of both faces where one would do, which
/// over 47 runs of the cataract scene with planes held from the first
/// refinement pass cost the lens twice. Held late, they act only on the few
/// steps whose vertices alternate between normals.
pub(super) const HOLD_FROM_PASS: usize = 8;
/// A held plane is left out where this pass's contact of the vertex has a
/// normal within this cosine of it (detection kept that plane already).
pub(super) const HELD_PLANE_COSINE: f64 = 0.9;
/// Nor where the two normals are more opposite than this cosine: a vertex
/// that crossed a surface or a thin part cannot be outside both planes.
pub(super) const HELD_PLANE_OPPOSITE: f64 = -0.5;

/// Appends to `contacts` (this pass's detected contacts) the plane of each
/// `held` contact (the last pass's penetrating ones) whose vertex (or face,
/// the same nodes) this pass
/// detected against the same side (the same tool, or the same body) with a
/// normal turned by a cosine in `[HELD_PLANE_OPPOSITE, HELD_PLANE_COSINE)`,
/// or not at all. The plane keeps its normal and, on a body, its barycentric
/// point (carried along with that body's positions); on a tool its point
/// (tools do not move between the passes of a step). Its gap is measured
/// from the vertex (or the face's barycentric point) at `positions(body)`,
/// and it is added only within `alarm` distance.
pub(super) fn hold_planes<'a, F>(
    held: &[Contact],
    contacts: &mut Vec<Contact>,
    positions: F,
    alarm: f64,
) where
    F: Fn(usize) -> Option<&'a [Vec3]>,
{
    let detected = contacts.len();
    for held in held {
        let (body, nodes) = (held.a.body, held.a.nodes);
        let same_side = |c: &Contact| match (&c.other, &held.other) {
            (ContactOther::Tool(a), ContactOther::Tool(b)) => a == b,
            (ContactOther::Body(a), ContactOther::Body(b)) => a.body == b.body,
            _ => false,
        };
        // The largest cosine between the held normal and this pass's normals
        // of the vertex against the same side.
        let cosine = contacts[..detected]
            .iter()
            .filter(|c| c.a.body == body && c.a.nodes == nodes && same_side(c))
            .map(|c| c.normal.dot(&held.normal))
            .reduce(f64::max);
        if cosine.is_some_and(|k| !(HELD_PLANE_OPPOSITE..HELD_PLANE_COSINE).contains(&k)) {
            continue;
        }
        // The side's barycentric point where its body is now.
        let at = |side: &ContactSide| positions(side.body).and_then(|x| side.point(x));
        let Some(p) = at(&held.a) else {
            continue;
        };
        let q = match &held.other {
            ContactOther::Tool(_) => held.point,
            ContactOther::Body(side) => match at(side) {
                Some(q) => q,
                None => continue,
            },
        };
        let gap = held.normal.dot(&(p - q));
        if gap < alarm {
            contacts.push(Contact {
                gap,
                point: q,
                force: Vec3::zeros(),
                ..*held
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::contact::types::tangent_basis;

    fn contact(node: u32, other: ContactOther, normal: Vec3, gap: f64, point: Vec3) -> Contact {
        Contact {
            a: ContactSide {
                body: 0,
                nodes: [node, 0, 0],
                weights: [1.0, 0.0, 0.0],
            },
            other,
            normal,
            tangents: tangent_basis(&normal),
            gap,
            slip: [0.0; 2],
            mu: 0.0,
            point,
            force: Vec3::zeros(),
        }
    }

    fn unit(x: f64, y: f64, z: f64) -> Vec3 {
        Vec3::new(x, y, z).normalize()
    }

    /// Vertex 0 of body 0 was 5 µm deep under a tool face with normal +z;
    /// this pass it lies at `p`, detected against the tool with `normal`.
    fn one(normal: Option<Vec3>, p: Vec3) -> Vec<Contact> {
        let x = [p];
        let held = [contact(
            0,
            ContactOther::Tool(0),
            Vec3::z(),
            -5e-6,
            Vec3::zeros(),
        )];
        let mut contacts: Vec<Contact> = normal
            .map(|n| contact(0, ContactOther::Tool(0), n, -2e-6, p))
            .into_iter()
            .collect();
        hold_planes(&held, &mut contacts, |b| (b == 0).then_some(&x[..]), 1e-4);
        contacts
    }

    #[test]
    fn a_turned_normal_keeps_the_last_plane_with_its_gap_now() {
        // Pushed out of the +z face into the x face's half-space: the +z
        // plane comes back with the vertex's depth below it now.
        let p = Vec3::new(-1e-6, 0.0, -3e-6);
        let c = one(Some(unit(1.0, 0.0, 0.0)), p);
        assert_eq!(c.len(), 2);
        assert_eq!(c[1].normal, Vec3::z());
        assert!((c[1].gap + 3e-6).abs() < 1e-18, "{}", c[1].gap);
        assert_eq!(c[1].point, Vec3::zeros());
        assert_eq!(c[1].force, Vec3::zeros());
    }

    #[test]
    fn a_kept_or_reversed_normal_adds_nothing() {
        let p = Vec3::new(0.0, 0.0, -3e-6);
        // Within about 25°: detection has that plane already.
        assert_eq!(one(Some(unit(0.3, 0.0, 1.0)), p).len(), 1);
        // Turned round (crossed a thin part): both planes cannot hold.
        assert_eq!(one(Some(unit(0.2, 0.0, -1.0)), p).len(), 1);
        // Turned by 90° or 110°: kept.
        assert_eq!(one(Some(unit(1.0, 0.0, 0.0)), p).len(), 2);
        assert_eq!(one(Some(unit(1.0, 0.0, -0.36)), p).len(), 2);
    }

    #[test]
    fn a_face_keeps_its_plane_at_its_barycentric_point() {
        // A tool inside a face (nodes 0, 1, 2 at weights ½, ¼, ¼) 5 µm
        // under a +z plane; this pass the face's point is 2 µm under it and
        // its only contact of the tool turned to +x.
        let x = [
            Vec3::new(0.0, 0.0, -4e-6),
            Vec3::new(1e-3, 0.0, 0.0),
            Vec3::new(0.0, 1e-3, 0.0),
            Vec3::new(5.0, 5.0, 5.0),
        ];
        let face = |normal: Vec3, gap: f64| Contact {
            a: ContactSide {
                body: 0,
                nodes: [0, 1, 2],
                weights: [0.5, 0.25, 0.25],
            },
            ..contact(3, ContactOther::Tool(0), normal, gap, Vec3::zeros())
        };
        let held = [face(Vec3::z(), -5e-6)];
        let mut contacts = vec![face(unit(1.0, 0.0, 0.0), -1e-6)];
        hold_planes(&held, &mut contacts, |b| (b == 0).then_some(&x[..]), 1e-4);
        assert_eq!(contacts.len(), 2);
        assert_eq!(contacts[1].a, held[0].a);
        // Measured from the face's point, (0.25 mm, 0.25 mm, −2 µm), not
        // from node 0 (4 µm under the plane).
        assert!(
            (contacts[1].gap + 2e-6).abs() < 1e-15,
            "{}",
            contacts[1].gap
        );
        // The same plane on a vertex contact of node 0 is another contact:
        // the face's is held beside it.
        let mut beside = vec![contact(0, ContactOther::Tool(0), Vec3::z(), -2e-6, x[0])];
        hold_planes(&held, &mut beside, |b| (b == 0).then_some(&x[..]), 1e-4);
        assert_eq!(beside.len(), 2);
    }

    #[test]
    fn an_undetected_vertex_keeps_its_plane_within_the_alarm_distance() {
        // No contact with the tool this pass, still under the old plane.
        assert_eq!(one(None, Vec3::new(0.0, 0.0, -1e-6)).len(), 1);
        // Far above it: nothing.
        assert!(one(None, Vec3::new(0.0, 0.0, 1e-3)).is_empty());
    }

    #[test]
    fn a_body_plane_follows_the_other_body() {
        // Vertex 0 of body 0 was under a face of body 1 (nodes 0, 1, 2, at
        // the barycentric point (0.2, 0.3, 0.5)); body 1 has moved up 2 µm.
        let side = ContactSide {
            body: 1,
            nodes: [0, 1, 2],
            weights: [0.2, 0.3, 0.5],
        };
        let held = [contact(
            0,
            ContactOther::Body(side),
            Vec3::z(),
            -5e-6,
            Vec3::zeros(),
        )];
        let lift = Vec3::new(0.0, 0.0, 2e-6);
        let xb = [
            Vec3::new(0.0, 0.0, 0.0) + lift,
            Vec3::new(1e-3, 0.0, 0.0) + lift,
            Vec3::new(0.0, 1e-3, 0.0) + lift,
        ];
        let xa = [Vec3::new(0.3e-3, 0.5e-3, 1e-6)];
        // Detected against a different body: not the same side, so the
        // plane is kept.
        let other = ContactSide { body: 2, ..side };
        let mut contacts = vec![contact(
            0,
            ContactOther::Body(other),
            Vec3::z(),
            -1e-6,
            xa[0],
        )];
        hold_planes(
            &held,
            &mut contacts,
            |b| match b {
                0 => Some(&xa[..]),
                1 => Some(&xb[..]),
                _ => None,
            },
            1e-4,
        );
        assert_eq!(contacts.len(), 2);
        let q = xb[0] * 0.2 + xb[1] * 0.3 + xb[2] * 0.5;
        assert_eq!(contacts[1].point, q);
        assert!((contacts[1].gap - (xa[0].z - q.z)).abs() < 1e-18);
        assert!(contacts[1].gap < 0.0);
    }
}
