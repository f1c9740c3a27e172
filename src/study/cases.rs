//! The study's scenes.
//!
//! - [`LensThroughHole`]: the paper's Fig. 3 experiment, an inhomogeneous
//!   lens (nucleus 5× stiffer) pushed by a sphere through a small hole in a
//!   rigid plate.
//! - [`CataractPush`]: the cataract scene's push ([`crate::scenes::cataract`]
//!   without the delivery): the vectis presses the lens into the incision.

use nalgebra::{Isometry3, Translation3};

use super::StudyScene;
use crate::body::{BodySettings, DeformableBody};
use crate::contact::{ContactSettings, RigidTool, ToolShape};
use crate::error::Result;
use crate::material::{StiffnessField, TissueMaterial, Transition};
use crate::math::{Vec3, v3};
use crate::mesh::generate::{self, LENS_RADII};
use crate::scene::Scene;
use crate::scenes::cataract::{self, CataractParams};

/// The paper's lens material: 5 kPa periphery, nucleus `factor`× stiffer
/// (smooth transition), ν = 0.45, density 1000 kg/m³.
pub fn lens_material(factor: f64) -> TissueMaterial {
    TissueMaterial::new(1000.0, 5e3, 0.45).with_stiffness(StiffnessField::Radial {
        center: Vec3::zeros(),
        radii: Vec3::from(LENS_RADII),
        core_radius: 0.55,
        factor,
        transition: Transition::Smooth { width: 0.2 },
    })
}

/// The lens (semi-axes [`LENS_RADII`], flat along z) pushed along −z by a
/// sphere through a square hole in a rigid plate (four boxes). The sphere
/// starts 0.1 mm above the lens and moves at constant speed; the lens rim
/// catches on the plate and its middle bulges through the hole.
#[derive(Debug, Clone, PartialEq)]
pub struct LensThroughHole {
    /// Lens resolution (cells along its long axis; 12 is the paper's
    /// 1183-node lens).
    pub cells: usize,
    /// Steps.
    pub steps: usize,
    /// Step size, seconds.
    pub timestep: f64,
    /// Sphere speed, m/s.
    pub speed: f64,
    /// Sphere radius, metres.
    pub sphere_radius: f64,
    /// Half width of the square hole, metres.
    pub hole_half_width: f64,
    /// Nucleus / periphery stiffness ratio.
    pub nucleus_factor: f64,
    /// Friction between the sphere and the lens.
    pub sphere_friction: f64,
    /// Friction between the plate and the lens.
    pub plate_friction: f64,
    /// Mass-proportional damping of the lens (the surrounding medium), 1/s.
    pub medium_drag: f64,
}

impl Default for LensThroughHole {
    fn default() -> Self {
        Self {
            cells: 12,
            steps: 150,
            timestep: 0.02,
            speed: 1.5e-3,
            sphere_radius: 4.0e-3,
            hole_half_width: 2.5e-3,
            nucleus_factor: 5.0,
            sphere_friction: 0.5,
            plate_friction: 0.5,
            medium_drag: 10.0,
        }
    }
}

impl LensThroughHole {
    /// Height of the plate's top face.
    fn plate_top(&self) -> f64 {
        -LENS_RADII[2] - 0.2e-3
    }

    /// Sphere centre before step `step` runs to its end.
    fn sphere_center(&self, step: usize) -> Vec3 {
        let z0 = LENS_RADII[2] + self.sphere_radius + 0.1e-3;
        v3(0.0, 0.0, z0 - self.speed * self.timestep * step as f64)
    }
}

fn at(p: Vec3) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::from(p), Default::default())
}

impl StudyScene for LensThroughHole {
    fn name(&self) -> &str {
        "lens_through_hole"
    }
    fn timestep(&self) -> f64 {
        self.timestep
    }
    fn steps(&self) -> usize {
        self.steps
    }
    fn length_scale(&self) -> f64 {
        LENS_RADII[2]
    }
    fn contact_settings(&self) -> ContactSettings {
        ContactSettings {
            alarm_distance: 0.1e-3,
            max_passes: 8,
            ..Default::default()
        }
    }
    fn build(&self, body: BodySettings, contact: ContactSettings) -> Result<Scene> {
        let mesh = generate::ellipsoid(LENS_RADII, self.cells)?;
        let material = lens_material(self.nucleus_factor).with_damping(self.medium_drag, 0.0);
        let lens = DeformableBody::new(mesh, material, body)?;
        let mut scene = Scene::new(contact)?;
        scene.add_body(lens);
        let sphere = RigidTool::new(
            ToolShape::Sphere {
                radius: self.sphere_radius,
            },
            at(self.sphere_center(0)),
        )?
        .with_friction(self.sphere_friction)?;
        scene.add_tool(sphere);
        // The plate: four boxes around the square hole, 1 mm thick.
        let (a, e, t) = (self.hole_half_width, LENS_RADII[0] + 3e-3, 0.5e-3);
        let zc = self.plate_top() - t;
        let side = (e - a) / 2.0;
        let mid = (e + a) / 2.0;
        for (c, half) in [
            (v3(-mid, 0.0, zc), v3(side, e, t)),
            (v3(mid, 0.0, zc), v3(side, e, t)),
            (v3(0.0, -mid, zc), v3(a, side, t)),
            (v3(0.0, mid, zc), v3(a, side, t)),
        ] {
            scene.add_tool(
                RigidTool::new(ToolShape::Box { half_extents: half }, at(c))?
                    .with_friction(self.plate_friction)?,
            );
        }
        Ok(scene)
    }
    fn drive(&self, scene: &mut Scene, step: usize) -> Result<()> {
        let c = self.sphere_center(step + 1);
        scene.tools[0].set_pose(at(c))
    }
}

/// The cataract scene's push ([`CataractParams::push_only`]): lens, eye and
/// vectis as core types, the vectis on its scripted path.
#[derive(Debug, Clone, PartialEq)]
pub struct CataractPush {
    /// Scene parameters (`deliver` is ignored: the push only).
    pub params: CataractParams,
    /// Step size, seconds.
    pub timestep: f64,
    /// Steps (the push lasts 8 s).
    pub steps: usize,
}

impl Default for CataractPush {
    fn default() -> Self {
        Self {
            params: CataractParams::default().push_only(),
            timestep: 1.0 / 60.0,
            steps: 480,
        }
    }
}

impl CataractPush {
    /// The coarse scene ([`CataractParams::coarse`]) at `h = 1/30` s, 8 s.
    pub fn coarse() -> Self {
        Self {
            params: CataractParams::coarse().push_only(),
            timestep: 1.0 / 30.0,
            steps: 240,
        }
    }
}

impl StudyScene for CataractPush {
    fn name(&self) -> &str {
        "cataract_push"
    }
    fn timestep(&self) -> f64 {
        self.timestep
    }
    fn steps(&self) -> usize {
        self.steps
    }
    fn length_scale(&self) -> f64 {
        LENS_RADII[2]
    }
    fn contact_settings(&self) -> ContactSettings {
        cataract::contact_settings()
    }
    fn build(&self, body: BodySettings, contact: ContactSettings) -> Result<Scene> {
        let p = CataractParams {
            deliver: false,
            ..self.params.clone()
        };
        let s = cataract::build(&p, body)?;
        let mut scene = Scene::new(contact)?;
        scene.add_body(s.lens);
        scene.add_body(s.eye);
        scene.add_tool(s.vectis);
        Ok(scene)
    }
    fn drive(&self, scene: &mut Scene, step: usize) -> Result<()> {
        let p = CataractParams {
            deliver: false,
            ..self.params.clone()
        };
        let path = cataract::ExtractionPath::new(&p);
        let t = (step + 1) as f64 * self.timestep;
        scene.tools[0].set_pose(path.pose(t))
    }
}
