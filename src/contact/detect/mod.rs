//! Phase 1, detection: surface vertices against tools and against other bodies.
//!
//! - **Tool – body**: every surface vertex inside the tool's bounds (grown
//!   by the alarm distance) is projected into the tool frame (parry3d-f64);
//!   a signed distance below the alarm distance makes a contact with the
//!   tool's outward normal.
//! - **Body – body**: the surface vertices of one body against the surface
//!   triangles of the other, in both directions. Each body keeps a bounding
//!   volume hierarchy of its surface triangles and one of its tetrahedra, both
//!   built once, their boxes grown by a quarter of the alarm distance and
//!   refitted once a vertex has moved farther than that ([`Bvh`]). The closest
//!   triangle gives barycentric weights. Whether a vertex is *inside* the other
//!   body is decided by the tetrahedra (a point-in-tet query), never by the side
//!   of a triangle's plane alone: near a cut (an incision's wall) an outside
//!   vertex can lie behind the closest triangle's plane, and a vertex that went
//!   deeper than the alarm distance in one step has no triangle near it at all.
//!   An outside vertex within the alarm distance gets the triangle's outward
//!   normal; an inside vertex is pushed back out where it came in (its
//!   start-of-step position carried along with the other body), however deep
//!   it is.
//!
//! Detection reads the positions `DetectBody::x` that the prediction phase
//! ([`super::predict`]) fills: the free motion, or in a predicted first pass
//! the free motion plus the last step's correction. Self-collision is out of
//! scope.

mod geometry;

pub use geometry::{Bvh, boxes_overlap, closest_point_on_triangle, point_in_tet, segment_triangle};

use super::bodies::{Bodies, Tools};
use super::types::{Contact, ContactOther, ContactSide, tangent_basis};
use crate::body::NodeConstraint;
use crate::math::Vec3;

/// Detection state of one body, kept between steps.
#[derive(Debug, Default)]
pub struct DetectBody {
    bvh: Option<Bvh>,
    tet_bvh: Option<Bvh>,
    tris: Vec<[usize; 3]>,
    /// Positions this pass detects at.
    pub(crate) x: Vec<Vec3>,
    /// Per node, how much farther than the alarm distance this pass searches.
    pub(crate) extra: Vec<f64>,
    /// The largest of `extra`.
    pub(crate) max_extra: f64,
    aabb: (Vec3, Vec3),
}

impl DetectBody {
    /// State for a body with these surface triangles (volume indices).
    pub fn new(tris: Vec<[usize; 3]>) -> Self {
        Self {
            tris,
            ..Default::default()
        }
    }

    /// Recomputes the bounds of the surface at [`Self::x`].
    pub(crate) fn update_bounds(&mut self, surface_vertices: &[usize]) {
        let mut lo = Vec3::repeat(f64::INFINITY);
        let mut hi = Vec3::repeat(f64::NEG_INFINITY);
        for &v in surface_vertices {
            lo = lo.inf(&self.x[v]);
            hi = hi.sup(&self.x[v]);
        }
        self.aabb = (lo, hi);
    }
}

/// The slack of the bodies' bounding volume hierarchies, as a fraction of
/// the alarm distance ([`Bvh::with_slack`]): the passes of a step move the
/// surfaces by far less, so most passes skip the refit of both trees.
const BVH_SLACK: f64 = 0.25;

/// What detection needs of the contact settings.
#[derive(Debug, Clone, Copy)]
pub struct DetectParams {
    /// Alarm distance, metres.
    pub margin: f64,
    /// Friction between bodies.
    pub body_friction: f64,
}

/// Finds the contacts of all bodies at their positions `DetectBody::x`; returns the
/// vertex–tool pairs tested.
pub fn detect<B: Bodies + ?Sized, T: Tools + ?Sized>(
    state: &mut [DetectBody],
    bodies: &B,
    tools: &T,
    params: DetectParams,
    out: &mut Vec<Contact>,
) -> usize {
    let margin = params.margin;
    let mut pairs = 0;
    for (bi, st) in state.iter().enumerate().take(bodies.len()) {
        let body = bodies.body(bi);
        let (x, x0, fixed) = (&st.x, body.start_positions(), body.constraints());
        let surface_mu = body.material().tool_friction;
        for ti in 0..tools.len() {
            let tool = tools.tool(ti);
            let tb = tool.aabb(margin + st.max_extra);
            if !boxes_overlap(&st.aabb, &tb, 0.0) {
                continue;
            }
            for &v in &body.surface().vertices {
                let p = x[v];
                if fixed[v] != NodeConstraint::Free || !boxes_overlap(&(p, p), &tb, 0.0) {
                    continue;
                }
                pairs += 1;
                let band = margin + st.extra[v];
                // Search deep enough to find the surface from anywhere inside the tool.
                let Some(prox) = tool.proximity(&p, band + tool.inner_radius()) else {
                    continue;
                };
                if prox.distance >= band {
                    continue;
                }
                let t = tangent_basis(&prox.normal);
                let rel = (p - x0[v]) - tool.displacement_at(&prox.point);
                out.push(Contact {
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
    let n = bodies.len().min(state.len());
    for a in 0..n {
        for b in 0..n {
            let band = margin + state[a].max_extra;
            if a == b || !boxes_overlap(&state[a].aabb, &state[b].aabb, band) {
                continue;
            }
            let sb = &mut state[b];
            let tets = bodies.body(b).mesh().tets();
            let slack = BVH_SLACK * margin;
            let bvh = sb
                .bvh
                .get_or_insert_with(|| Bvh::with_slack(&sb.tris, &sb.x, slack));
            bvh.refit(&sb.tris, &sb.x);
            let tet_bvh = sb
                .tet_bvh
                .get_or_insert_with(|| Bvh::with_slack(tets, &sb.x, slack));
            tet_bvh.refit(tets, &sb.x);
            vertex_triangle(state, bodies, a, b, params, out);
        }
    }
    pairs
}

/// State `a` to read and state `b` to update (`a ≠ b`).
fn pair(state: &mut [DetectBody], a: usize, b: usize) -> (&DetectBody, &mut DetectBody) {
    if a < b {
        let (lo, hi) = state.split_at_mut(b);
        (&lo[a], &mut hi[0])
    } else {
        let (lo, hi) = state.split_at_mut(a);
        (&hi[0], &mut lo[b])
    }
}

/// Surface vertices of body `a` against the surface of body `b`.
fn vertex_triangle<B: Bodies + ?Sized>(
    state: &mut [DetectBody],
    bodies: &B,
    a: usize,
    b: usize,
    params: DetectParams,
    out: &mut Vec<Contact>,
) {
    let margin = params.margin;
    let (sa, sb) = (
        bodies.body(a).start_positions(),
        bodies.body(b).start_positions(),
    );
    let tets = bodies.body(b).mesh().tets();
    let mu = params.body_friction;
    let (slot_a, slot_b) = pair(state, a, b);
    let (xa, extra, max_extra) = (&slot_a.x, &slot_a.extra, slot_a.max_extra);
    let xb = &slot_b.x;
    let (Some(bvh), Some(tet_bvh)) = (slot_b.bvh.as_mut(), slot_b.tet_bvh.as_mut()) else {
        return;
    };
    let tris = &slot_b.tris;
    // The bounds of `b`'s surface (kept by `update_bounds`), grown by the band.
    let grow = margin + max_extra;
    let bbox = (
        slot_b.aabb.0.add_scalar(-grow),
        slot_b.aabb.1.add_scalar(grow),
    );
    // Far enough to reach the surface from anywhere inside `b`.
    let reach = (bbox.1 - bbox.0).norm();
    for &v in &bodies.body(a).surface().vertices {
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
        out.push(Contact {
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
