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
        Ok(Self {
            shape,
            parry,
            pose,
            prev_pose: pose,
            friction: 0.0,
            reaction_force: Vec3::zeros(),
            reaction_torque: Vec3::zeros(),
        })
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
