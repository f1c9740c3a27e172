//! Geometry for detection: bounding volume hierarchies and the point,
//! segment and triangle primitives.

use crate::math::Vec3;

/// A node of [`Bvh`].
#[derive(Debug, Clone, Copy, PartialEq)]
struct BvhNode {
    min: Vec3,
    max: Vec3,
    /// Children for inner nodes; `(start, count)` into `order` for leaves.
    a: u32,
    b: u32,
    leaf: bool,
}

/// Bounding volume hierarchy over mesh primitives (surface triangles or
/// tetrahedra, given as vertex-index arrays); the tree is built once, boxes are
/// refitted from current positions.
///
/// With a slack `s > 0` ([`Self::with_slack`]) every box is grown by `s` when
/// it is refitted, and [`Self::refit`] does nothing while no vertex has moved
/// farther than `s` since the last refit: the grown boxes still hold every
/// primitive. Queries then visit a few more primitives but find the same ones.
#[derive(Debug, Clone, Default)]
pub struct Bvh {
    nodes: Vec<BvhNode>,
    order: Vec<u32>,
    stack: Vec<u32>,
    slack: f64,
    /// Positions at the last refit (kept only with a slack).
    at: Vec<Vec3>,
    /// Refits done (for tests).
    pub(crate) refits: u64,
}

const LEAF: usize = 4;

impl Bvh {
    /// Builds the tree over `prims` (vertex indices into `x`) at positions `x`.
    pub fn new<const N: usize>(prims: &[[usize; N]], x: &[Vec3]) -> Self {
        Self::with_slack(prims, x, 0.0)
    }

    /// [`Self::new`] with boxes grown by `slack` (metres; see the type's docs).
    /// A negative or non-finite slack counts as zero.
    pub fn with_slack<const N: usize>(prims: &[[usize; N]], x: &[Vec3], slack: f64) -> Self {
        let mut bvh = Self {
            order: (0..prims.len() as u32).collect(),
            slack: if slack.is_finite() {
                slack.max(0.0)
            } else {
                0.0
            },
            ..Default::default()
        };
        if !prims.is_empty() {
            let centroids: Vec<Vec3> = prims
                .iter()
                .map(|t| t.iter().map(|&v| x[v]).sum::<Vec3>() / N as f64)
                .collect();
            let n = prims.len();
            bvh.build(&centroids, 0, n);
            bvh.refit(prims, x);
        }
        bvh
    }

    fn build(&mut self, c: &[Vec3], start: usize, end: usize) -> u32 {
        let id = self.nodes.len() as u32;
        self.nodes.push(BvhNode {
            min: Vec3::zeros(),
            max: Vec3::zeros(),
            a: start as u32,
            b: (end - start) as u32,
            leaf: true,
        });
        if end - start > LEAF {
            let mut lo = Vec3::repeat(f64::INFINITY);
            let mut hi = Vec3::repeat(f64::NEG_INFINITY);
            for &t in &self.order[start..end] {
                lo = lo.inf(&c[t as usize]);
                hi = hi.sup(&c[t as usize]);
            }
            let axis = (hi - lo).imax();
            let mid = (start + end) / 2;
            self.order[start..end].select_nth_unstable_by(mid - start, |&p, &q| {
                c[p as usize][axis].total_cmp(&c[q as usize][axis])
            });
            let left = self.build(c, start, mid);
            let right = self.build(c, mid, end);
            self.nodes[id as usize] = BvhNode {
                min: Vec3::zeros(),
                max: Vec3::zeros(),
                a: left,
                b: right,
                leaf: false,
            };
        }
        id
    }

    /// Recomputes every box from positions `x` (children before parents);
    /// with a slack, only once some vertex has moved farther than it since the
    /// last refit.
    pub fn refit<const N: usize>(&mut self, prims: &[[usize; N]], x: &[Vec3]) {
        let slack = self.slack;
        if slack > 0.0 {
            let s2 = slack * slack;
            if self.at.len() == x.len()
                && x.iter()
                    .zip(&self.at)
                    .all(|(p, q)| (p - q).norm_squared() <= s2)
            {
                return;
            }
            self.at.clear();
            self.at.extend_from_slice(x);
        }
        self.refits += 1;
        for i in (0..self.nodes.len()).rev() {
            let n = self.nodes[i];
            let (mut lo, mut hi) = (Vec3::repeat(f64::INFINITY), Vec3::repeat(f64::NEG_INFINITY));
            if n.leaf {
                for &t in &self.order[n.a as usize..(n.a + n.b) as usize] {
                    for &v in &prims[t as usize] {
                        lo = lo.inf(&x[v]);
                        hi = hi.sup(&x[v]);
                    }
                }
                lo.add_scalar_mut(-slack);
                hi.add_scalar_mut(slack);
            } else {
                let (l, r) = (self.nodes[n.a as usize], self.nodes[n.b as usize]);
                lo = l.min.inf(&r.min);
                hi = l.max.sup(&r.max);
            }
            self.nodes[i].min = lo;
            self.nodes[i].max = hi;
        }
    }

    /// Bounds of the whole tree (grown by the slack).
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        self.nodes.first().map(|n| (n.min, n.max))
    }

    /// Calls `f(primitive)` for every primitive whose box is within `radius` of `p`.
    pub fn query(&mut self, p: &Vec3, radius: f64, mut f: impl FnMut(usize)) {
        self.query_until(p, radius, |t| {
            f(t);
            false
        });
    }

    /// [`Self::query`] that stops as soon as `f` returns `true`; returns whether it did.
    pub fn query_until(&mut self, p: &Vec3, radius: f64, mut f: impl FnMut(usize) -> bool) -> bool {
        if self.nodes.is_empty() {
            return false;
        }
        self.stack.clear();
        self.stack.push(0);
        while let Some(i) = self.stack.pop() {
            let n = self.nodes[i as usize];
            let outside = (0..3).any(|k| p[k] < n.min[k] - radius || p[k] > n.max[k] + radius);
            if outside {
                continue;
            }
            if n.leaf {
                for &t in &self.order[n.a as usize..(n.a + n.b) as usize] {
                    if f(t as usize) {
                        return true;
                    }
                }
            } else {
                self.stack.push(n.a);
                self.stack.push(n.b);
            }
        }
        false
    }
}

/// Where the segment `o → p` crosses triangle `(a, b, c)`: the fraction `t`
/// along the segment and the crossing point's barycentric weights; `None` when
/// it misses or runs parallel to the triangle's plane.
pub fn segment_triangle(
    o: &Vec3,
    p: &Vec3,
    a: &Vec3,
    b: &Vec3,
    c: &Vec3,
) -> Option<(f64, [f64; 3])> {
    let d = p - o;
    let (e1, e2) = (b - a, c - a);
    let q = d.cross(&e2);
    let det = e1.dot(&q);
    if det.abs() <= 1e-30 * e1.norm_squared() * d.norm() {
        return None;
    }
    let s = o - a;
    let u = s.dot(&q) / det;
    let r = s.cross(&e1);
    let v = d.dot(&r) / det;
    let t = e2.dot(&r) / det;
    let eps = 1e-9;
    (u >= -eps && v >= -eps && u + v <= 1.0 + eps && (-eps..=1.0 + eps).contains(&t))
        .then_some((t, [1.0 - u - v, u, v]))
}

/// Whether `p` lies in the tetrahedron with corners `x` (a closed test with a
/// relative tolerance of 1e-9 in barycentric coordinates; false for a
/// degenerate tetrahedron).
pub fn point_in_tet(p: &Vec3, x: [Vec3; 4]) -> bool {
    let [a, b, c, d] = x;
    let m = crate::math::Mat3::from_columns(&[b - a, c - a, d - a]);
    match m.try_inverse() {
        Some(inv) => {
            let l = inv * (p - a);
            let eps = -1e-9;
            l.x >= eps && l.y >= eps && l.z >= eps && l.x + l.y + l.z <= 1.0 - eps
        }
        None => false,
    }
}

/// Closest point on triangle `(a, b, c)` to `p`, as barycentric weights.
pub fn closest_point_on_triangle(p: &Vec3, a: &Vec3, b: &Vec3, c: &Vec3) -> [f64; 3] {
    let ab = b - a;
    let ac = c - a;
    let ap = p - a;
    let d1 = ab.dot(&ap);
    let d2 = ac.dot(&ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return [1.0, 0.0, 0.0];
    }
    let bp = p - b;
    let d3 = ab.dot(&bp);
    let d4 = ac.dot(&bp);
    if d3 >= 0.0 && d4 <= d3 {
        return [0.0, 1.0, 0.0];
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return [1.0 - v, v, 0.0];
    }
    let cp = p - c;
    let d5 = ab.dot(&cp);
    let d6 = ac.dot(&cp);
    if d6 >= 0.0 && d5 <= d6 {
        return [0.0, 0.0, 1.0];
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return [1.0 - w, 0.0, w];
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return [0.0, 1.0 - w, w];
    }
    let denom = 1.0 / (va + vb + vc);
    let v = vb * denom;
    let w = vc * denom;
    [1.0 - v - w, v, w]
}

/// Whether two boxes overlap after growing by `margin`.
pub fn boxes_overlap(a: &(Vec3, Vec3), b: &(Vec3, Vec3), margin: f64) -> bool {
    (0..3).all(|k| a.0[k] - margin <= b.1[k] && b.0[k] - margin <= a.1[k])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::test_value as val;
    use crate::mesh::generate;

    /// A tree with a slack skips refits while the vertices stay within it and
    /// still finds every tetrahedron a point lies in and every tetrahedron
    /// with a vertex within the query radius; once a vertex moves farther it
    /// refits, and after a large move it finds the moved tetrahedra.
    #[test]
    fn a_slack_tree_skips_refits_and_finds_what_an_exact_one_finds() {
        let mesh = generate::ellipsoid([4e-3, 3e-3, 2e-3], 4).expect("mesh");
        let tets = mesh.tets();
        let mut x = mesh.positions().to_vec();
        let slack = 2e-5;
        let mut fat = Bvh::with_slack(tets, &x, slack);
        let check = |fat: &mut Bvh, x: &[Vec3], seed: usize| {
            for (k, t) in tets.iter().enumerate() {
                let c = t.iter().map(|&v| x[v]).sum::<Vec3>() / 4.0;
                let inside = fat.query_until(&c, 0.0, |e| point_in_tet(&c, tets[e].map(|i| x[i])));
                assert!(inside, "tetrahedron {k}'s centroid not found");
            }
            // Every tetrahedron at every vertex, found from the vertex itself.
            for (v, p) in x.iter().enumerate() {
                let mut found = vec![false; tets.len()];
                fat.query(p, 0.05 * slack, |e| found[e] = true);
                for (e, t) in tets.iter().enumerate() {
                    assert!(!t.contains(&v) || found[e], "tetrahedron {e} at vertex {v}");
                }
            }
            let r = 3e-4;
            for i in 0..40 {
                let p = x[(i * 37 + seed) % x.len()]
                    + Vec3::new(val(i, seed), val(i, seed + 1), val(i, seed + 2)) * 2e-5;
                let mut found = vec![false; tets.len()];
                fat.query(&p, r, |e| found[e] = true);
                for (e, t) in tets.iter().enumerate() {
                    if t.iter().any(|&v| (x[v] - p).norm() <= r) {
                        assert!(found[e], "tetrahedron {e} within {r} of {p} not found");
                    }
                }
            }
        };
        check(&mut fat, &x, 1);
        let refits = fat.refits;
        // Small moves: every vertex within 0.9 of the slack of where the tree
        // last saw it.
        let base = x.clone();
        for round in 0..3 {
            for (i, p) in x.iter_mut().enumerate() {
                let d = Vec3::new(val(i, round + 3), val(i, round + 4), val(i, round + 5));
                *p = base[i] + d * (0.9 * slack / d.norm().max(1e-300)).min(1.0);
            }
            fat.refit(tets, &x);
            assert_eq!(fat.refits, refits, "refitted after moves within the slack");
            check(&mut fat, &x, round + 7);
        }
        // One vertex past the slack: a refit.
        x[0].x += 1.5 * slack;
        fat.refit(tets, &x);
        assert_eq!(fat.refits, refits + 1);
        check(&mut fat, &x, 11);
        // The whole mesh moved by far more than the slack.
        for p in &mut x {
            *p += Vec3::new(3e-3, -1e-3, 2e-3);
        }
        fat.refit(tets, &x);
        assert_eq!(fat.refits, refits + 2);
        check(&mut fat, &x, 13);
    }
}
