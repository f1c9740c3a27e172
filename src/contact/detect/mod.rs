//! Phase 1, detection: surface vertices against tools and against other bodies.
//!
//! - **Tool – body**: every surface vertex inside the tool's bounds (grown
//!   by the alarm distance) is projected into the tool frame (parry3d-f64);
//!   a signed distance below the alarm distance makes a contact with the
//!   tool's outward normal. With [`DetectParams::tool_faces`] the surface
//!   triangles near the tool are searched for points inside it between
//!   their vertices as well ([`FACE_SAMPLES`]): a tool's edge or corner
//!   pressed into a face, which the vertices alone never see.
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
use super::tool::{RigidTool, ToolProximity};
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
    /// Per node, a lower bound on its signed distance to the tool being
    /// detected (exact where the vertex was queried), for the face samples.
    corner: Vec<f64>,
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
    /// Tool contacts inside surface triangles as well
    /// ([`super::ContactSettings::tool_faces`]).
    pub tool_faces: bool,
    /// A face sample becomes a contact only where it is deeper than all
    /// three corners by more than this, metres (the penetration tolerance):
    /// a tool's edge or corner between the vertices. Against a flat tool face
    /// the signed distance is linear over the triangle, never deeper inside
    /// than at a corner, so the vertex contacts carry it and no redundant
    /// row is added.
    pub face_deeper: f64,
}

/// The barycentric points of a surface triangle that face detection
/// ([`DetectParams::tool_faces`]) starts from: the centroid and the points of
/// the grid of step ¼ other than the corners, three inside and three on each
/// edge.
pub const FACE_SAMPLES: [[f64; 3]; 13] = [
    [1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0],
    [0.5, 0.25, 0.25],
    [0.25, 0.5, 0.25],
    [0.25, 0.25, 0.5],
    [0.75, 0.25, 0.0],
    [0.5, 0.5, 0.0],
    [0.25, 0.75, 0.0],
    [0.0, 0.75, 0.25],
    [0.0, 0.5, 0.5],
    [0.0, 0.25, 0.75],
    [0.25, 0.0, 0.75],
    [0.5, 0.0, 0.5],
    [0.75, 0.0, 0.25],
];

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
    for (bi, st) in state.iter_mut().enumerate().take(bodies.len()) {
        let body = bodies.body(bi);
        let (x, x0, fixed) = (&st.x, body.start_positions(), body.constraints());
        let surface_mu = body.material().tool_friction;
        for ti in 0..tools.len() {
            let tool = tools.tool(ti);
            let tb = tool.aabb(margin + st.max_extra);
            if !boxes_overlap(&st.aabb, &tb, 0.0) {
                continue;
            }
            let inner = tool.inner_radius();
            if params.tool_faces {
                // Outside the grown bounds a vertex is farther than their margin.
                st.corner.clear();
                st.corner.resize(x.len(), margin + st.max_extra);
            }
            for &v in &body.surface().vertices {
                let p = x[v];
                if !boxes_overlap(&(p, p), &tb, 0.0) {
                    continue;
                }
                let band = margin + st.extra[v];
                let reach = band + inner;
                if fixed[v] != NodeConstraint::Free {
                    if params.tool_faces {
                        st.corner[v] = tool.proximity(&p, reach).map_or(reach, |q| q.distance);
                    }
                    continue;
                }
                pairs += 1;
                // Search deep enough to find the surface from anywhere inside the tool.
                let prox = tool.proximity(&p, reach);
                if params.tool_faces {
                    st.corner[v] = prox.map_or(reach, |q| q.distance);
                }
                let Some(prox) = prox else {
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
            if params.tool_faces {
                let face = FaceDetect {
                    body: bi,
                    tool: ti,
                    margin,
                    deeper: params.face_deeper,
                    inner,
                };
                pairs += tool_faces(st, body, tools.tool(ti), &tb, face, out);
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

/// Which body and tool [`tool_faces`] detects, and with what.
#[derive(Debug, Clone, Copy)]
struct FaceDetect {
    body: usize,
    tool: usize,
    margin: f64,
    deeper: f64,
    /// The tool's [`RigidTool::inner_radius`].
    inner: f64,
}

/// Contacts of `tool` inside the surface triangles of body `f.body`
/// ([`DetectParams::tool_faces`]), after the vertex contacts have filled
/// `st.corner` with the corners' signed distances (or lower bounds on them);
/// returns the sample–tool pairs tested.
///
/// Each triangle whose bounds meet the tool's `tb` and that has a free node
/// queries the [`FACE_SAMPLES`] that can lie near a point deep enough (the
/// signed distance is 1-Lipschitz, so a sample is at least a corner's, or
/// a sample's queried before it, distance less its distance to that point),
/// and from the deepest sample
/// near enough a pattern search ([`deepest_near`]) finds the deepest point
/// about it; where that is a corner, a second search starts from the
/// deepest sample at least halfway from it. That point makes a contact on
/// the triangle's three nodes, weighted by its barycentric coordinates,
/// where it is within the band, deeper than every corner by
/// [`DetectParams::face_deeper`] and not a corner (the vertex's contact). A
/// point on an edge may be found by both of the edge's triangles (a rod
/// across the edge is deepest there from both sides); the deeper is kept.
///
/// Face contacts are frictionless: they hold the faces out of the tool, and
/// friction stays with the vertex contacts. A face contact's tangent rows lie
/// in nearly the tangent plane of its corners' own contacts, and with them
/// the cataract jam's first-pass LCP ran to its sweep cap 4–23 times a run
/// (without face contacts, in about one run of thirty) and the lens slid off
/// the blade in 7 of 26 runs; frictionless, in 2 of 26.
fn tool_faces(
    st: &DetectBody,
    body: &crate::body::DeformableBody,
    tool: &RigidTool,
    tb: &(Vec3, Vec3),
    f: FaceDetect,
    out: &mut Vec<Contact>,
) -> usize {
    let (x, fixed) = (&st.x, body.constraints());
    let mut pairs = 0;
    let start = out.len();
    for tri in &st.tris {
        let [i, j, k] = *tri;
        let p = [x[i], x[j], x[k]];
        let (lo, hi) = (p[0].inf(&p[1]).inf(&p[2]), p[0].sup(&p[1]).sup(&p[2]));
        if !boxes_overlap(&(lo, hi), tb, 0.0)
            || tri.iter().all(|&n| fixed[n] != NodeConstraint::Free)
        {
            continue;
        }
        let d = [st.corner[i], st.corner[j], st.corner[k]];
        let shallowest = d[0].min(d[1]).min(d[2]);
        let band = f.margin + tri.iter().map(|&n| st.extra[n]).fold(0.0, f64::max);
        // Deep enough to count: below the band and below every corner.
        let limit = band.min(shallowest - f.deeper);
        // Every point of the triangle is within `cover` of a point of the
        // grid of step ¼ (its small triangles' edges are at most a quarter
        // of the longest edge, and no point of a triangle is farther than
        // its longest edge / √3 from the nearest corner), so a point deeper
        // than `limit` lies near a sample closer than `limit + cover`: a
        // tool thinner than the samples' spacing (a rod across a large
        // triangle) passes between them.
        let longest = (p[1] - p[0])
            .norm()
            .max((p[2] - p[1]).norm())
            .max((p[0] - p[2]).norm());
        let near = limit + longest / (4.0 * 3f64.sqrt());
        // Deep enough to find the surface from anywhere inside the tool.
        let reach = near.max(0.0) + f.inner;
        let found = near_samples(&p, &d, near, reach, tool, &mut pairs);
        let Some((w, prox)) = deepest_sample(&found, |_| true) else {
            continue;
        };
        let Some((mut w, mut prox)) = deepest_near(&p, w, prox, tool, reach, None, &mut pairs)
        else {
            continue;
        };
        // A search that ends at a corner found the vertex's contact; a
        // non-convex tool (the vectis's bowl) can also dip into the face
        // away from that corner, where a sample at least halfway from it
        // starts a second search, given up once it heads back to the corner.
        if let Some(c) = corner_of(&w)
            && let Some((w2, prox2)) = deepest_sample(&found, |s| s[c] <= 0.5)
        {
            let Some(second) = deepest_near(&p, w2, prox2, tool, reach, Some(c), &mut pairs) else {
                continue;
            };
            (w, prox) = second;
        }
        // At a corner: the vertex's contact. On an edge: kept whichever of
        // the edge's triangles found it (below, the deeper of the two).
        if prox.distance >= limit || corner_of(&w).is_some() {
            continue;
        }
        let face = Contact {
            a: ContactSide {
                body: f.body,
                nodes: [i as u32, j as u32, k as u32],
                weights: w,
            },
            other: ContactOther::Tool(f.tool),
            normal: prox.normal,
            tangents: tangent_basis(&prox.normal),
            gap: prox.distance,
            slip: [0.0; 2],
            mu: 0.0,
            point: prox.point,
            force: Vec3::zeros(),
        };
        push_deepest_on_edge(out, start, face);
    }
    pairs
}

/// The [`FACE_SAMPLES`] of the triangle `p` closer to `tool` than `near`,
/// with their proximities (queried within `reach`), where `d` are lower
/// bounds on the corners' signed distances. The signed distance is
/// 1-Lipschitz: a sample is queried only where neither a corner nor a sample
/// queried before it (at least `reach` away where none was found) is far
/// enough to put it at `near` or beyond. Counts the queries in `pairs`.
fn near_samples(
    p: &[Vec3; 3],
    d: &[f64; 3],
    near: f64,
    reach: f64,
    tool: &RigidTool,
    pairs: &mut usize,
) -> [Option<ToolProximity>; FACE_SAMPLES.len()] {
    let mut found = [None; FACE_SAMPLES.len()];
    let mut queried = [(Vec3::zeros(), 0.0); FACE_SAMPLES.len()];
    let mut n_queried = 0;
    for (w, slot) in FACE_SAMPLES.iter().zip(&mut found) {
        let q = at(p, w);
        let bound = (0..3)
            .map(|c| (p[c], d[c]))
            .chain(queried[..n_queried].iter().copied())
            .map(|(r, dr)| dr - (q - r).norm())
            .fold(f64::NEG_INFINITY, f64::max);
        if bound >= near {
            continue;
        }
        *pairs += 1;
        let prox = tool.proximity(&q, reach);
        queried[n_queried] = (q, prox.map_or(reach, |x| x.distance));
        n_queried += 1;
        *slot = prox.filter(|x| x.distance < near);
    }
    found
}

/// Whether a step `along` from a point whose tool normal is `normal` cannot
/// reach a point deeper in the tool, whose signed distance's slope falls
/// along the step by at most `bend` ([`RigidTool::concave_bend`]; 0 for a
/// convex tool, where the normal is a (sub)gradient of a convex function,
/// which then rises along every direction the normal does): the normal
/// rises along it by more than that, by a margin far above round-off.
/// `length` is the step's length, `along.norm()`.
fn cannot_go_deeper(normal: &Vec3, along: &Vec3, length: f64, bend: f64) -> bool {
    normal.dot(along) > (1e-9 + bend) * length
}

/// The corner that the barycentric point `w` is at (the other two weights
/// zero), if any.
fn corner_of(w: &[f64; 3]) -> Option<usize> {
    if w.iter().filter(|&&c| c == 0.0).count() > 1 {
        w.iter().position(|&c| c != 0.0)
    } else {
        None
    }
}

/// The deepest of the samples `found` near enough (see [`tool_faces`]) whose
/// barycentric point `keep` accepts, with its proximity.
fn deepest_sample(
    found: &[Option<ToolProximity>; FACE_SAMPLES.len()],
    keep: impl Fn(&[f64; 3]) -> bool,
) -> Option<([f64; 3], ToolProximity)> {
    FACE_SAMPLES
        .iter()
        .zip(found)
        .filter_map(|(w, f)| Some((*w, (*f)?)))
        .filter(|(w, _)| keep(w))
        .min_by(|a, b| a.1.distance.total_cmp(&b.1.distance))
}

/// The nodes of the edge that the face contact `c` lies on (in ascending
/// order), or `None` inside its triangle.
fn edge_of(c: &Contact) -> Option<(u32, u32)> {
    let z = c.a.weights.iter().position(|&w| w == 0.0)?;
    let (a, b) = (c.a.nodes[(z + 1) % 3], c.a.nodes[(z + 2) % 3]);
    Some((a.min(b), a.max(b)))
}

/// Appends the face contact `face` to `out`, whose face contacts of this
/// body and tool begin at `start`, keeping one contact an edge: a point on
/// an edge that one of them already has is left out where that one is as
/// deep, and replaces it where deeper (the search of either triangle of an
/// edge can end on it: a rod across the edge is deepest there from both
/// sides).
fn push_deepest_on_edge(out: &mut Vec<Contact>, start: usize, face: Contact) {
    if let Some(e) = edge_of(&face) {
        let on_edge = out[start..].iter().position(|c| edge_of(c) == Some(e));
        match on_edge {
            Some(m) if out[start + m].gap <= face.gap => return,
            Some(m) => {
                out.remove(start + m);
            }
            None => {}
        }
    }
    out.push(face);
}

/// The point of weights `w` on the triangle of corners `p`.
fn at(p: &[Vec3; 3], w: &[f64; 3]) -> Vec3 {
    p[0] * w[0] + p[1] * w[1] + p[2] * w[2]
}

/// Refinement levels of [`deepest_near`]: the step halves from an eighth
/// of the triangle (half the spacing of [`FACE_SAMPLES`]) to a 1024th. A rod
/// across a triangle is a valley as narrow as its dip is deep (about 50 µm
/// wide 2 µm down a rod of 0.15 mm radius); five levels, to a 128th (12 µm
/// in a 1.5 mm triangle), stopped up to 2 µm short of its floor.
const DEEPEST_LEVELS: usize = 8;

/// The deepest point inside `tool` of the triangle `p` near the barycentric
/// point `w` (whose proximity is `prox`): a pattern search that moves the
/// point by `step` along the six directions between two corners, to the
/// deepest neighbour inside the triangle, and halves the step where none is
/// deeper. A step along which the tool's outward normal at the point rises
/// more steeply than the tool's concave parts can bend it back is not tried
/// ([`cannot_go_deeper`]; where the tool is convex no step the normal rises
/// along is deeper, so there the search takes the same path). Counts its
/// proximity queries in `pairs`. With `away_from` a
/// corner, the search gives up (`None`) once it moves more than halfway
/// toward that corner: back to where a search before it ended.
fn deepest_near(
    p: &[Vec3; 3],
    mut w: [f64; 3],
    mut prox: ToolProximity,
    tool: &RigidTool,
    reach: f64,
    away_from: Option<usize>,
    pairs: &mut usize,
) -> Option<([f64; 3], ToolProximity)> {
    let mut step: f64 = 1.0 / 8.0;
    for _ in 0..DEEPEST_LEVELS {
        loop {
            let mut moved = false;
            for (from, to) in [(0, 1), (1, 0), (1, 2), (2, 1), (2, 0), (0, 2)] {
                let mut v = w;
                let s = step.min(v[from]);
                let along = (p[to] - p[from]) * s;
                let length = along.norm();
                if s <= 0.0
                    || cannot_go_deeper(&prox.normal, &along, length, tool.concave_bend(length))
                {
                    continue;
                }
                v[from] -= s;
                v[to] += s;
                if v[from] < 1e-12 {
                    v[from] = 0.0;
                }
                *pairs += 1;
                if let Some(near) = tool.proximity(&at(p, &v), reach)
                    && near.distance < prox.distance
                {
                    (w, prox, moved) = (v, near, true);
                }
            }
            if !moved {
                break;
            }
            if away_from.is_some_and(|c| w[c] > 0.5) {
                return None;
            }
        }
        step *= 0.5;
    }
    Some((w, prox))
}

/// Whether `c` is a tool's contact inside a surface triangle
/// ([`DetectParams::tool_faces`]).
pub fn is_tool_face(c: &Contact) -> bool {
    matches!(c.other, ContactOther::Tool(_)) && c.a.weights[0] < 1.0
}

/// Adds to a refinement pass's contacts `out` the face contacts `kept` of
/// the pass before that this pass did not detect again (the same body,
/// triangle, barycentric point and tool), measured at the positions
/// `state[body].x`, where they are within the alarm distance `margin`.
///
/// A pass's face contact is the deepest point of its triangle; the pass
/// pushes that point out, which can tilt the triangle and leave another of
/// its points the deepest. Detected alone, the next pass's contact would
/// push the new point out and let the first one sink back, and the passes
/// take turns (in the cataract scene up to 64 passes in a step). Kept, each
/// pass adds the new point to those pushed out so far.
pub fn keep_faces<T: Tools + ?Sized>(
    kept: &[Contact],
    state: &[DetectBody],
    tools: &T,
    margin: f64,
    out: &mut Vec<Contact>,
) {
    let detected = out.len();
    for c in kept {
        let ContactOther::Tool(ti) = c.other else {
            continue;
        };
        if ti >= tools.len()
            || out[..detected]
                .iter()
                .any(|d| d.other == c.other && d.a == c.a)
        {
            continue;
        }
        let Some(q) = state.get(c.a.body).and_then(|s| c.a.point(&s.x)) else {
            continue;
        };
        let tool = tools.tool(ti);
        let Some(prox) = tool.proximity(&q, margin + tool.inner_radius()) else {
            continue;
        };
        if prox.distance >= margin {
            continue;
        }
        out.push(Contact {
            normal: prox.normal,
            tangents: tangent_basis(&prox.normal),
            gap: prox.distance,
            slip: [0.0; 2],
            point: prox.point,
            force: Vec3::zeros(),
            ..*c
        });
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::contact::tool::{Pose, ToolShape};
    use proptest::prelude::*;
    use proptest::test_runner::{Config, RngSeed};

    /// A convex tool of size about 1 mm at the origin, turned by `angles`:
    /// a sphere, a box, or a box's triangle mesh (as parry builds it), by
    /// `kind`.
    fn convex_tool(kind: usize, angles: Vec3) -> RigidTool {
        let half = Vec3::new(0.6e-3, 0.4e-3, 0.25e-3);
        let shape = match kind {
            0 => ToolShape::Sphere { radius: 0.5e-3 },
            1 => ToolShape::Box { half_extents: half },
            _ => crate::contact::tool::box_trimesh(half),
        };
        let pose = Pose::from_parts(
            nalgebra::Translation3::identity(),
            nalgebra::UnitQuaternion::from_euler_angles(angles.x, angles.y, angles.z),
        );
        RigidTool::new(shape, pose).unwrap()
    }

    fn vec3(r: f64) -> impl Strategy<Value = Vec3> {
        (-r..r, -r..r, -r..r).prop_map(|(x, y, z)| Vec3::new(x, y, z))
    }

    proptest! {
        #![proptest_config(Config {
            cases: 512,
            rng_seed: RngSeed::Fixed(20_261_128),
            failure_persistence: None,
            ..Config::default()
        })]

        /// The bounds only leave out samples that a query would have found
        /// too far: the samples kept are those of querying all thirteen.
        #[test]
        fn a_sample_is_left_unqueried_only_where_it_is_too_far(
            kind in 0..3usize,
            angles in vec3(3.0),
            corners in [vec3(1.2e-3), vec3(1.2e-3), vec3(1.2e-3)],
            slack in [0.0..1e-4, 0.0..1e-4, 0.0..1e-4],
            near in -2e-4..4e-4f64,
        ) {
            let tool = convex_tool(kind, angles);
            let reach = near.max(0.0) + 1e-3;
            let far = |q: &Vec3| tool.proximity(q, reach).map_or(reach, |x| x.distance);
            let d = [0, 1, 2].map(|c| far(&corners[c]) - slack[c]);
            let mut pairs = 0;
            let found = near_samples(&corners, &d, near, reach, &tool, &mut pairs);
            for (w, f) in FACE_SAMPLES.iter().zip(&found) {
                let all = tool
                    .proximity(&at(&corners, w), reach)
                    .filter(|x| x.distance < near);
                prop_assert_eq!(f.map(|x| x.distance), all.map(|x| x.distance));
            }
            prop_assert!(pairs <= FACE_SAMPLES.len());
        }

        /// A step along a direction that [`cannot_go_deeper`] leaves out
        /// never reaches a point deeper in a convex tool, at any length.
        #[test]
        fn a_direction_left_out_cannot_go_deeper_in_a_convex_tool(
            kind in 0..3usize,
            angles in vec3(3.0),
            x in vec3(0.8e-3),
            along in vec3(1e-3),
            steps in prop::collection::vec(1e-4..1.0f64, 1..8),
        ) {
            let tool = convex_tool(kind, angles);
            prop_assert_eq!(tool.concave_bend(1.0), 0.0);
            let here = tool.proximity(&x, 1.0).unwrap();
            // One of the two ways is left out (unless square to the normal).
            let left_out = [along, -along].map(|a| cannot_go_deeper(&here.normal, &a, a.norm(), 0.0));
            prop_assert!(
                left_out[0] != left_out[1] || here.normal.dot(&along).abs() <= 1e-9 * along.norm()
            );
            for (a, out) in [along, -along].iter().zip(left_out) {
                for &t in steps.iter().filter(|_| out) {
                    let there = tool.proximity(&(x + a * t), 1.0).unwrap();
                    prop_assert!(
                        there.distance >= here.distance,
                        "{} deeper at {t}",
                        here.distance - there.distance
                    );
                }
            }
        }
    }

    #[test]
    fn the_samples_are_points_of_the_triangle_on_the_quarter_grid() {
        for w in FACE_SAMPLES {
            assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-15);
            assert!(w.iter().all(|&c| (0.0..1.0).contains(&c)));
            assert!(
                w == [1.0 / 3.0; 3] || w.iter().all(|&c| (c * 4.0).fract() == 0.0),
                "{w:?}"
            );
        }
    }

    /// A frictionless face contact of tool 0 on the nodes `nodes` at the
    /// barycentric point `weights`, `gap` deep.
    fn face_contact(nodes: [u32; 3], weights: [f64; 3], gap: f64) -> Contact {
        Contact {
            a: ContactSide {
                body: 0,
                nodes,
                weights,
            },
            other: ContactOther::Tool(0),
            normal: Vec3::z(),
            tangents: tangent_basis(&Vec3::z()),
            gap,
            slip: [0.0; 2],
            mu: 0.0,
            point: Vec3::zeros(),
            force: Vec3::zeros(),
        }
    }

    #[test]
    fn an_edge_keeps_the_deepest_of_its_two_triangles_points() {
        // Triangles 0-1-2 and 3-2-1 share the edge 1–2; both searches end
        // on it, the second deeper. A point inside the first stays, as does
        // one on another edge.
        let faces = [
            face_contact([0, 1, 2], [0.0, 0.4, 0.6], -3e-6),
            face_contact([0, 1, 2], [0.2, 0.3, 0.5], -4e-6),
            face_contact([3, 2, 1], [0.0, 0.5, 0.5], -5e-6),
            face_contact([3, 2, 1], [0.5, 0.0, 0.5], -1e-6),
        ];
        let mut out = Vec::new();
        for f in faces {
            push_deepest_on_edge(&mut out, 0, f);
        }
        let kept: Vec<f64> = out.iter().map(|c| c.gap).collect();
        assert_eq!(kept, [-4e-6, -5e-6, -1e-6]);
        assert_eq!(edge_of(&faces[2]), Some((1, 2)));
        assert_eq!(edge_of(&faces[3]), Some((1, 3)));
        assert_eq!(edge_of(&faces[1]), None);
        // Two equally deep points of an edge: one is kept.
        let mut tie = Vec::new();
        push_deepest_on_edge(&mut tie, 0, face_contact([0, 1, 2], [0.0, 0.5, 0.5], -2e-6));
        push_deepest_on_edge(&mut tie, 0, face_contact([3, 2, 1], [0.0, 0.5, 0.5], -2e-6));
        assert_eq!(tie.len(), 1);
    }

    #[test]
    fn a_refinement_pass_keeps_the_last_passs_face_contacts() {
        // A 0.3 mm sphere 50 µm into a 1 mm triangle at (0.3, 0.2) mm.
        let pose = Pose::translation(0.3e-3, 0.2e-3, 0.25e-3);
        let tools = [RigidTool::new(ToolShape::Sphere { radius: 0.3e-3 }, pose).unwrap()];
        let mut st = DetectBody::new(vec![[0, 1, 2]]);
        st.x = vec![
            Vec3::zeros(),
            Vec3::new(1e-3, 0.0, 0.0),
            Vec3::new(0.0, 1e-3, 0.0),
        ];
        let face = |weights: [f64; 3]| Contact {
            a: ContactSide {
                body: 0,
                nodes: [0, 1, 2],
                weights,
            },
            other: ContactOther::Tool(0),
            normal: Vec3::x(),
            tangents: tangent_basis(&Vec3::x()),
            gap: 1.0,
            slip: [0.0; 2],
            mu: 0.0,
            point: Vec3::zeros(),
            force: Vec3::zeros(),
        };
        // Kept: the point under the sphere, one 0.27 mm from it (outside
        // the alarm distance), and one this pass detected again.
        let kept = [
            face([0.5, 0.3, 0.2]),
            face([0.1, 0.8, 0.1]),
            face([0.4, 0.3, 0.3]),
        ];
        let mut out = vec![face([0.4, 0.3, 0.3])];
        keep_faces(&kept, &[st], &tools, 1e-4, &mut out);
        assert_eq!(out.len(), 2, "{out:?}");
        let c = &out[1];
        assert_eq!(c.a, kept[0].a);
        // Measured again where the face is now.
        assert!((c.gap + 50e-6).abs() < 1e-12, "{}", c.gap);
        assert!((c.normal + Vec3::z()).norm() < 1e-9, "{}", c.normal);
        assert!(
            is_tool_face(c)
                && !is_tool_face(&Contact {
                    a: ContactSide {
                        body: 0,
                        nodes: [0, 0, 0],
                        weights: [1.0, 0.0, 0.0],
                    },
                    ..*c
                })
        );
    }

    #[test]
    fn the_pattern_search_finds_the_deepest_point_of_a_face() {
        // A sphere of 0.3 mm whose centre is 0.25 mm above the point
        // (0.3, 0.2) mm of a 1 mm triangle in the plane z = 0: 50 µm deep there.
        let p = [
            Vec3::zeros(),
            Vec3::new(1e-3, 0.0, 0.0),
            Vec3::new(0.0, 1e-3, 0.0),
        ];
        let pose = Pose::translation(0.3e-3, 0.2e-3, 0.25e-3);
        let tool = RigidTool::new(ToolShape::Sphere { radius: 0.3e-3 }, pose).unwrap();
        let w = FACE_SAMPLES[0];
        let start = tool.proximity(&((p[0] + p[1] + p[2]) / 3.0), 1.0).unwrap();
        let mut pairs = 0;
        let (w, prox) = deepest_near(&p, w, start, &tool, 1.0, None, &mut pairs).unwrap();
        assert!(prox.distance < start.distance);
        assert!((prox.distance + 50e-6).abs() < 5e-7, "{}", prox.distance);
        let q = at(&p, &w);
        assert!((q - Vec3::new(0.3e-3, 0.2e-3, 0.0)).norm() < 1e-5, "{q}");
        assert!(pairs > 0);
    }
}
