//! Rigid, kinematically driven tools.
//!
//! A [`RigidTool`] is a rigid shape with a pose that the application moves (for
//! example from a haptic device or a script). Shapes are validated on
//! creation and turned into parry3d-f64 shapes; point queries run in the
//! tool's local frame. The contact solver writes the reaction force and torque
//! the tissue exerts on the tool ([`RigidTool::reaction`]) for haptic output.

use std::sync::Arc;

use nalgebra::{Isometry3, Point3, UnitQuaternion};
use parry3d_f64::math::Vector as PVec;
use parry3d_f64::query::PointQuery;
use parry3d_f64::shape::{Shape, SharedShape, TriMeshFlags};

use crate::error::{Result, SoftTissueError};
use crate::math::Vec3;

/// Rigid pose: rotation then translation (metres).
pub type Pose = Isometry3<f64>;

/// Shape of a rigid tool, in its local frame (metres).
#[derive(Debug, Clone, PartialEq)]
pub enum ToolShape {
    /// A sphere centred at the origin.
    Sphere {
        /// Radius.
        radius: f64,
    },
    /// A capsule along the local y axis.
    Capsule {
        /// Half length of the segment.
        half_height: f64,
        /// Radius.
        radius: f64,
    },
    /// A box centred at the origin.
    Box {
        /// Half extents.
        half_extents: Vec3,
    },
    /// The convex hull of points.
    ConvexHull {
        /// Points (at least 4, not coplanar).
        points: Vec<Vec3>,
    },
    /// A closed, outward-oriented triangle mesh (for instruments like a vectis).
    TriMesh {
        /// Vertices.
        vertices: Vec<Vec3>,
        /// Triangles.
        indices: Vec<[u32; 3]>,
    },
}

fn to_p(v: &Vec3) -> PVec {
    PVec::new(v.x, v.y, v.z)
}

fn from_p(v: PVec) -> Vec3 {
    Vec3::new(v.x, v.y, v.z)
}

fn bad(msg: impl Into<String>) -> SoftTissueError {
    SoftTissueError::InvalidShape(msg.into())
}

fn finite_pos(name: &str, v: f64) -> Result<()> {
    if !v.is_finite() || v <= 0.0 {
        return Err(bad(format!("{name} = {v} must be finite and > 0")));
    }
    Ok(())
}

/// Fails unless some four of `points` span a tetrahedron of non-negligible volume.
fn check_not_flat(points: &[Vec3]) -> Result<()> {
    let p0 = points[0];
    let far = |f: &dyn Fn(&Vec3) -> f64| {
        points
            .iter()
            .copied()
            .max_by(|a, b| f(a).total_cmp(&f(b)))
            .unwrap_or(p0)
    };
    let p1 = far(&|p| (p - p0).norm());
    let ext = (p1 - p0).norm();
    let p2 = far(&|p| (p1 - p0).cross(&(p - p0)).norm());
    let n = (p1 - p0).cross(&(p2 - p0));
    let p3 = far(&|p| n.dot(&(p - p0)).abs());
    let vol = n.dot(&(p3 - p0)).abs();
    if vol.is_nan() || vol <= 1e-9 * ext.powi(3) {
        return Err(bad(
            "convex hull is degenerate (coplanar or coincident points)",
        ));
    }
    Ok(())
}

impl ToolShape {
    fn build(&self) -> Result<SharedShape> {
        match self {
            ToolShape::Sphere { radius } => {
                finite_pos("sphere radius", *radius)?;
                Ok(SharedShape::ball(*radius))
            }
            ToolShape::Capsule {
                half_height,
                radius,
            } => {
                finite_pos("capsule radius", *radius)?;
                finite_pos("capsule half height", *half_height)?;
                Ok(SharedShape::capsule_y(*half_height, *radius))
            }
            ToolShape::Box { half_extents } => {
                for c in half_extents.iter() {
                    finite_pos("box half extent", *c)?;
                }
                Ok(SharedShape::cuboid(
                    half_extents.x,
                    half_extents.y,
                    half_extents.z,
                ))
            }
            ToolShape::ConvexHull { points } => {
                if points.len() < 4 {
                    return Err(bad(format!(
                        "convex hull needs ≥ 4 points, got {}",
                        points.len()
                    )));
                }
                if !points.iter().all(|p| p.iter().all(|c| c.is_finite())) {
                    return Err(bad("convex hull point is not finite"));
                }
                check_not_flat(points)?;
                let pts: Vec<PVec> = points.iter().map(to_p).collect();
                SharedShape::convex_hull(&pts)
                    .ok_or_else(|| bad("convex hull is degenerate (coplanar or coincident points)"))
            }
            ToolShape::TriMesh { vertices, indices } => {
                if vertices.len() < 4 || indices.len() < 4 {
                    return Err(bad("triangle mesh needs ≥ 4 vertices and ≥ 4 triangles"));
                }
                if !vertices.iter().all(|p| p.iter().all(|c| c.is_finite())) {
                    return Err(bad("triangle mesh vertex is not finite"));
                }
                for (t, tri) in indices.iter().enumerate() {
                    for &i in tri {
                        if i as usize >= vertices.len() {
                            return Err(bad(format!(
                                "triangle {t} references vertex {i}, mesh has {}",
                                vertices.len()
                            )));
                        }
                    }
                    if tri[0] == tri[1] || tri[1] == tri[2] || tri[0] == tri[2] {
                        return Err(bad(format!("triangle {t} repeats a vertex")));
                    }
                }
                SharedShape::trimesh_with_flags(
                    vertices.iter().map(to_p).collect(),
                    indices.clone(),
                    TriMeshFlags::ORIENTED | TriMeshFlags::MERGE_DUPLICATE_VERTICES,
                )
                .map_err(|e| bad(format!("triangle mesh rejected: {e:?}")))
            }
        }
    }
}

/// A rigid, kinematic tool (see the module docs).
#[derive(Clone)]
pub struct RigidTool {
    shape: ToolShape,
    parry: SharedShape,
    pose: Pose,
    prev_pose: Pose,
    friction: f64,
    reaction_force: Vec3,
    reaction_torque: Vec3,
    concave: Concavity,
}

/// How much a tool's surface bends back toward a point outside it: its
/// concave (reflex) edges' largest turn between the two faces' normals, as
/// the largest slope its signed distance along a straight line can lose,
/// and per length (the turn over the distance between the faces'
/// centroids, as a curvature). Zero for a convex tool.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Concavity {
    /// `2 sin(θ/2)` of the largest turn θ: how much the unit normal changes.
    turn: f64,
    /// The largest turn per the distance between the faces' centroids (1/m).
    curvature: f64,
}

impl Concavity {
    const CONVEX: Self = Self {
        turn: 0.0,
        curvature: 0.0,
    };
    /// For a mesh whose edges are not each shared by two triangles, or of
    /// more than one piece (the signed distance of two convex pieces is not
    /// convex where the nearer one changes): so large that no direction is
    /// ruled out.
    const UNKNOWN: Self = Self {
        turn: 2.0,
        curvature: f64::INFINITY,
    };

    /// The concave edges of a closed, outward-oriented triangle mesh of one
    /// piece.
    fn of_mesh(vertices: &[Vec3], indices: &[[u32; 3]]) -> Self {
        if indices.is_empty() {
            return Self::UNKNOWN;
        }
        let mut faces_of = std::collections::HashMap::new();
        for (f, t) in indices.iter().enumerate() {
            for e in 0..3 {
                let (a, b) = (t[e], t[(e + 1) % 3]);
                faces_of
                    .entry((a.min(b), a.max(b)))
                    .or_insert_with(Vec::new)
                    .push((f, t[(e + 2) % 3]));
            }
        }
        let v = |i: u32| vertices[i as usize];
        let normal = |t: &[u32; 3]| (v(t[1]) - v(t[0])).cross(&(v(t[2]) - v(t[0])));
        let centroid = |t: &[u32; 3]| (v(t[0]) + v(t[1]) + v(t[2])) / 3.0;
        // The pieces: triangles joined across their shared edges.
        let mut piece: Vec<usize> = (0..indices.len()).collect();
        fn root(piece: &mut [usize], mut f: usize) -> usize {
            while piece[f] != f {
                piece[f] = piece[piece[f]];
                f = piece[f];
            }
            f
        }
        let mut out = Self::CONVEX;
        for (&(a, b), faces) in &faces_of {
            let &[(f1, _), (f2, opposite)] = faces.as_slice() else {
                return Self::UNKNOWN;
            };
            let (r1, r2) = (root(&mut piece, f1), root(&mut piece, f2));
            piece[r1] = r2;
            let (Some(n1), Some(n2)) = (
                normal(&indices[f1]).try_normalize(1e-300),
                normal(&indices[f2]).try_normalize(1e-300),
            ) else {
                return Self::UNKNOWN;
            };
            // Concave where the second face's far corner lies outside the
            // first face's plane.
            let length = (v(b) - v(a)).norm();
            if n1.dot(&(v(opposite) - v(a))) <= 1e-9 * length {
                continue;
            }
            let theta = n1.cross(&n2).norm().atan2(n1.dot(&n2));
            let apart = (centroid(&indices[f1]) - centroid(&indices[f2])).norm();
            out.turn = out.turn.max(2.0 * (theta / 2.0).sin());
            out.curvature = out.curvature.max(theta / apart);
        }
        let first = root(&mut piece, 0);
        if (1..indices.len()).any(|f| root(&mut piece, f) != first) {
            return Self::UNKNOWN;
        }
        out
    }
}

impl std::fmt::Debug for RigidTool {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RigidTool")
            .field("shape", &self.shape)
            .field("pose", &self.pose)
            .field("friction", &self.friction)
            .finish()
    }
}

/// Signed distance query result in world frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToolProximity {
    /// Signed distance (negative inside the tool).
    pub distance: f64,
    /// Unit normal pointing out of the tool at the closest point.
    pub normal: Vec3,
    /// Closest point on the tool surface.
    pub point: Vec3,
}

fn check_pose(p: &Pose) -> Result<()> {
    let ok = p.translation.vector.iter().all(|c| c.is_finite())
        && p.rotation.coords.iter().all(|c| c.is_finite());
    if !ok {
        return Err(SoftTissueError::NonFinite("tool pose"));
    }
    Ok(())
}

impl RigidTool {
    /// A tool of `shape` at `pose`, frictionless.
    pub fn new(shape: ToolShape, pose: Pose) -> Result<Self> {
        check_pose(&pose)?;
        let parry = shape.build()?;
        let concave = match parry.as_trimesh() {
            Some(mesh) => {
                let vertices: Vec<Vec3> = mesh.vertices().iter().map(|p| from_p(*p)).collect();
                Concavity::of_mesh(&vertices, mesh.indices())
            }
            None => Concavity::CONVEX,
        };
        Ok(Self {
            shape,
            parry,
            pose,
            prev_pose: pose,
            friction: 0.0,
            reaction_force: Vec3::zeros(),
            reaction_torque: Vec3::zeros(),
            concave,
        })
    }

    /// How much the slope of the tool's signed distance along a straight
    /// step of `length` can fall below its slope at the start, as estimated
    /// from the tool's concave edges: the curvature times the length, at
    /// most the largest turn of the normal (0 for a convex tool; no bound for
    /// a mesh of more than one piece or whose edges are not each shared by
    /// two triangles). On a surface of curvature κ that bends toward the
    /// point the distance falls below its tangent by κt²/2 over a step t;
    /// this allows twice that.
    pub(crate) fn concave_bend(&self, length: f64) -> f64 {
        self.concave.turn.min(self.concave.curvature * length)
    }

    /// Sets the Coulomb friction coefficient μ ≥ 0.
    pub fn with_friction(mut self, mu: f64) -> Result<Self> {
        self.set_friction(mu)?;
        Ok(self)
    }

    /// Sets the Coulomb friction coefficient μ ≥ 0.
    pub fn set_friction(&mut self, mu: f64) -> Result<()> {
        crate::error::check_range("friction", mu, 0.0, 1e6)?;
        self.friction = mu;
        Ok(())
    }

    /// Friction coefficient.
    pub fn friction(&self) -> f64 {
        self.friction
    }

    /// The shape description.
    pub fn shape(&self) -> &ToolShape {
        &self.shape
    }

    /// The parry shape.
    pub fn parry_shape(&self) -> &Arc<dyn Shape> {
        &self.parry.0
    }

    /// Current pose.
    pub fn pose(&self) -> &Pose {
        &self.pose
    }

    /// Moves the tool (kinematically) to `pose`. The motion since the last
    /// [`RigidTool::end_step`] drives friction.
    pub fn set_pose(&mut self, pose: Pose) -> Result<()> {
        check_pose(&pose)?;
        self.pose = pose;
        Ok(())
    }

    /// Sets position and orientation from parts.
    pub fn set_position(&mut self, translation: Vec3, rotation: UnitQuaternion<f64>) -> Result<()> {
        self.set_pose(Isometry3::from_parts(translation.into(), rotation))
    }

    /// Marks the end of a step: the current pose becomes the reference for the next
    /// step's tool motion.
    pub fn end_step(&mut self) {
        self.prev_pose = self.pose;
    }

    /// Displacement during the current step of the tool's material point now at `p`.
    pub fn displacement_at(&self, p: &Vec3) -> Vec3 {
        let local = self.pose.inverse_transform_point(&Point3::from(*p));
        p - self.prev_pose.transform_point(&local).coords
    }

    /// Smallest half extent of the shape's local bounds: no interior point is
    /// farther than this from the surface.
    pub fn inner_radius(&self) -> f64 {
        let b = self.parry.compute_local_aabb();
        let h = (from_p(b.maxs) - from_p(b.mins)) * 0.5;
        h.min()
    }

    /// Axis-aligned bounds in world frame, grown by `margin`.
    pub fn aabb(&self, margin: f64) -> (Vec3, Vec3) {
        let local = self.parry.compute_local_aabb();
        let (lo, hi) = (from_p(local.mins), from_p(local.maxs));
        let mut wlo = Vec3::repeat(f64::INFINITY);
        let mut whi = Vec3::repeat(f64::NEG_INFINITY);
        for i in 0..8 {
            let c = Vec3::new(
                if i & 1 == 0 { lo.x } else { hi.x },
                if i & 2 == 0 { lo.y } else { hi.y },
                if i & 4 == 0 { lo.z } else { hi.z },
            );
            let w = self.pose.transform_point(&Point3::from(c)).coords;
            wlo = wlo.inf(&w);
            whi = whi.sup(&w);
        }
        (wlo.add_scalar(-margin), whi.add_scalar(margin))
    }

    /// Signed distance, outward normal and closest point for the world point `p`,
    /// or `None` when `p` is farther than `max_distance`.
    pub fn proximity(&self, p: &Vec3, max_distance: f64) -> Option<ToolProximity> {
        let local = self.pose.inverse_transform_point(&Point3::from(*p)).coords;
        let lp = to_p(&local);
        let proj = match &self.shape {
            ToolShape::TriMesh { .. } => {
                let mesh = self.parry.as_trimesh()?;
                mesh.project_local_point_with_max_dist(lp, false, max_distance)?
            }
            _ => self.parry.project_local_point(lp, false),
        };
        let q = from_p(proj.point);
        let d = local - q;
        let dist = d.norm();
        let (distance, n_local) = if dist > 1e-15 {
            if proj.is_inside {
                (-dist, -d / dist)
            } else {
                (dist, d / dist)
            }
        } else {
            // On the surface: use the direction from the shape's centre.
            let c = from_p(self.parry.compute_local_aabb().center());
            let dir = (local - c).try_normalize(1e-300).unwrap_or(Vec3::z());
            (0.0, dir)
        };
        if distance > max_distance {
            return None;
        }
        Some(ToolProximity {
            distance,
            normal: self.pose.rotation * n_local,
            point: self.pose.transform_point(&Point3::from(q)).coords,
        })
    }

    /// Reaction force and torque (about the tool origin) of the last contact solve,
    /// exerted by the tissue on the tool.
    pub fn reaction(&self) -> (Vec3, Vec3) {
        (self.reaction_force, self.reaction_torque)
    }

    pub(crate) fn set_reaction(&mut self, force: Vec3, torque: Vec3) {
        self.reaction_force = force;
        self.reaction_torque = torque;
    }
}

/// Parry's triangle mesh of a box of half extents `half` centred at the
/// origin, as a tool shape (for tests).
#[cfg(test)]
pub(crate) fn box_trimesh(half: Vec3) -> ToolShape {
    let cuboid = parry3d_f64::shape::Cuboid::new(PVec::new(half.x, half.y, half.z));
    let (corners, indices) = cuboid.to_trimesh();
    let vertices = corners.iter().map(|c| Vec3::new(c.x, c.y, c.z)).collect();
    ToolShape::TriMesh { vertices, indices }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A cube of half size 1 mm whose top face is an inverted square pyramid
    /// `h` mm deep (its four triangles meeting at the sunken centre), or with
    /// `open` the cube with one of its triangles left out.
    fn dented_cube(h: f64, open: bool) -> ToolShape {
        let s = 1e-3;
        let ToolShape::TriMesh {
            mut vertices,
            indices: triangles,
        } = box_trimesh(Vec3::new(s, s, s))
        else {
            unreachable!()
        };
        let top = |i: u32| vertices[i as usize].z > 0.0;
        let mut indices: Vec<[u32; 3]> = triangles
            .iter()
            .filter(|t| !t.iter().all(|&i| top(i)))
            .copied()
            .collect();
        let corner = |x: f64, y: f64| {
            vertices
                .iter()
                .position(|v| v.x * x > 0.0 && v.y * y > 0.0 && v.z > 0.0)
                .unwrap() as u32
        };
        let ring = [
            corner(-1.0, -1.0),
            corner(1.0, -1.0),
            corner(1.0, 1.0),
            corner(-1.0, 1.0),
        ];
        vertices.push(Vec3::new(0.0, 0.0, s * (1.0 - h)));
        let m = (vertices.len() - 1) as u32;
        for k in 0..4 {
            indices.push([ring[k], ring[(k + 1) % 4], m]);
        }
        if open {
            indices.pop();
        }
        ToolShape::TriMesh { vertices, indices }
    }

    #[test]
    fn convex_tools_do_not_bend_back_and_a_dent_does_by_its_turn() {
        let pose = Pose::identity();
        for shape in [
            ToolShape::Sphere { radius: 1e-3 },
            ToolShape::Box {
                half_extents: Vec3::new(1e-3, 2e-3, 3e-3),
            },
            dented_cube(0.0, false),
        ] {
            let tool = RigidTool::new(shape, pose).unwrap();
            assert_eq!(tool.concave_bend(1.0), 0.0);
        }
        // Two neighbouring faces of the dent have normals (-h, 0, 1) and
        // (0, -h, 1) (in units of the half size), a turn θ with
        // cos θ = 1 / (1 + h²), and centroids (2/3)·√2 apart.
        let h = 0.3;
        let tool = RigidTool::new(dented_cube(h, false), pose).unwrap();
        let theta = (1.0 / (1.0 + h * h)).acos();
        let curvature = theta / (2.0 / 3.0 * 2f64.sqrt() * 1e-3);
        let turn = 2.0 * (theta / 2.0).sin();
        let short = 1e-6;
        assert!((tool.concave_bend(short) - curvature * short).abs() < 1e-9 * curvature * short);
        assert!((tool.concave_bend(1.0) - turn).abs() < 1e-12);
        // An open mesh: no bound, nothing is ruled out.
        if let Ok(tool) = RigidTool::new(dented_cube(h, true), pose) {
            assert!(tool.concave_bend(1e-9) >= 1.0);
        }
        // Two cubes apart, each convex: their union is not.
        let ToolShape::TriMesh {
            mut vertices,
            mut indices,
        } = dented_cube(0.0, false)
        else {
            unreachable!()
        };
        let n = vertices.len() as u32;
        vertices.extend(
            vertices
                .clone()
                .iter()
                .map(|v| v + Vec3::new(3e-3, 0.0, 0.0)),
        );
        indices.extend(indices.clone().iter().map(|t| t.map(|i| i + n)));
        let two = RigidTool::new(ToolShape::TriMesh { vertices, indices }, pose).unwrap();
        assert!(two.concave_bend(1e-9) >= 1.0);
    }
}
