//! A tool between a surface's vertices: how deep it reaches into the
//! triangles, for the cataract harness and the tests (no Bevy).

use bevy_soft_tissue::contact::detect::boxes_overlap;

/// How finely the cataract harness tests each lens surface triangle with
/// [`tool_in_faces`]: the barycentric grid of step `1 / FACE_GRID` (91 points
/// with the corners), a finer set than the contacts' own face samples
/// (`bevy_soft_tissue::contact::detect::FACE_SAMPLES`, with
/// `ContactSettings::tool_faces`), so that the check does not only confirm
/// the points the contacts hold out.
pub const FACE_GRID: usize = 12;

/// The deepest point of the barycentric grid of step `1 / grid` (corners
/// left out) inside `tool` over the surface triangles `triangles` of
/// positions `x` whose bounds meet the tool's (0 where none is inside), and
/// how many triangles reach deeper than `tolerance`. A grid point is
/// queried only where its corners' distances to the tool allow it inside (a
/// signed distance changes no faster than the distance moved).
pub fn tool_in_faces(
    tool: &bevy_soft_tissue::contact::RigidTool,
    triangles: &[[usize; 3]],
    x: &[bevy_soft_tissue::math::Vec3],
    tolerance: f64,
    grid: usize,
) -> (f64, usize) {
    let bounds = tool.aabb(0.0);
    // A point inside the tool is nearer its surface than the box's diagonal.
    let reach = (bounds.1 - bounds.0).norm();
    let distance =
        |q: &bevy_soft_tissue::math::Vec3| tool.proximity(q, reach).map_or(reach, |pr| pr.distance);
    let (mut deepest, mut count) = (0.0f64, 0);
    for t in triangles {
        let p = t.map(|i| x[i]);
        let tb = (p[0].inf(&p[1]).inf(&p[2]), p[0].sup(&p[1]).sup(&p[2]));
        if !boxes_overlap(&tb, &bounds, 0.0) {
            continue;
        }
        let d = p.map(|c| distance(&c));
        let mut tri = 0.0f64;
        for i in 0..=grid {
            for j in 0..=grid - i {
                if i == grid || j == grid || i + j == 0 {
                    continue; // a corner: the vertex contacts' own
                }
                let (a, b) = (i as f64 / grid as f64, j as f64 / grid as f64);
                let q = p[0] + (p[1] - p[0]) * a + (p[2] - p[0]) * b;
                let bound = (0..3)
                    .map(|c| d[c] - (q - p[c]).norm())
                    .fold(f64::NEG_INFINITY, f64::max);
                if bound < tri {
                    tri = tri.min(distance(&q));
                }
            }
        }
        deepest = deepest.min(tri);
        count += usize::from(-tri > tolerance);
    }
    (-deepest, count)
}
