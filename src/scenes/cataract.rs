//! The cataract (MSICS) nucleus-extraction scene.
//!
//! - **Eye**: a scleral shell, outer radius 12 mm, 1 mm thick, with a
//!   scleral-tunnel slit incision at 30° from the anterior pole (+z), on the
//!   +y side: 6.5 mm long and 3 mm wide as asked of
//!   [`generate::eye_shell`], which removes whole rows of the shell's quads,
//!   so at the default resolution the opening between the lips' vertices is
//!   about 5.6 mm long and 5.1 mm across (3.4 mm across for a 2 mm width). The
//!   lens (9.5 × 4.5 mm) passes edge first, squeezed along the slit. The
//!   posterior third is fixed. Viscoelastic lubricates the sclera: no friction
//!   against the vectis ([`TissueMaterial::tool_friction`]) or the lens.
//! - **Lens**: an ellipsoid 9.5 × 9.5 × 4.5 mm, nucleus 5× stiffer than the
//!   periphery (smooth transition), inside the eye behind the incision, turned
//!   so that its thin edge faces the slit (the nucleus leaves edge first).
//! - **Vectis**: a rigid, spoon-like blade (closed triangle mesh) with friction
//!   against the lens. Along [`ExtractionPath`] it meets the lens's rim on the
//!   side away from the incision and, withdrawn through the incision, pushes
//!   the lens edge first into the slit, through it and out of the eye
//!   ([`CataractParams::deliver`]; [`CataractParams::push_only`] stops with
//!   the lens pressed into the slit). The blade (8 mm across the slit) is
//!   wider than the opening: it spreads the lips as it passes.
//! - **Medium**: the viscoelastic and aqueous around the lens, as mass
//!   damping of both bodies ([`CataractParams::medium_drag`]).
//!
//! Mesh sizes default to about the paper's (lens 1183 vertices / 5184 tets,
//! eye ≈ 1200 / ≈ 3550). [`CataractParams::coarse`] gives a light version for
//! tests. Units are SI (metres, pascals, kilograms).

use nalgebra::{Isometry3, Translation3, UnitQuaternion};

use crate::body::{BodySettings, DeformableBody};
use crate::contact::{ContactSettings, Pose, RigidTool, ToolShape};
use crate::error::Result;
use crate::material::{StiffnessField, TissueMaterial, Transition};
use crate::math::{Vec3, v3};
use crate::mesh::generate::{self, EyeShell, Incision, LENS_RADII};

/// Parameters of the scene.
#[derive(Debug, Clone, PartialEq)]
pub struct CataractParams {
    /// Lens resolution (cells along its long axis).
    pub lens_cells: usize,
    /// Eye shell mesh.
    pub eye: EyeShell,
    /// Young's modulus of the lens periphery, Pa.
    pub lens_young: f64,
    /// Nucleus / periphery stiffness ratio.
    pub nucleus_factor: f64,
    /// Young's modulus of the sclera, Pa.
    pub eye_young: f64,
    /// Friction between vectis and tissue.
    pub vectis_friction: f64,
    /// Distance of the lens centre from the eye centre, toward the incision, metres.
    pub lens_offset: f64,
    /// Drag of the medium around the lens (viscoelastic and aqueous), as the
    /// mass-proportional damping α of both bodies, 1/s. A lens squeezed into the
    /// slit stores elastic energy; when it slips, that energy turns into speed,
    /// and without a medium to take it up the lens flies off (α = 2/s let it
    /// leave at up to 75 mm/s in about one run of twenty).
    pub medium_drag: f64,
    /// Continue the scripted path through the slit until the lens is
    /// delivered out of the eye (17 s instead of 8). On by default; off
    /// ([`Self::push_only`]) the vectis stops with the lens pressed into the
    /// slit. Squeezing the whole lens through the slit is the hardest part
    /// numerically and runs below real time at full size (see
    /// [`ExtractionPath::new`]).
    pub deliver: bool,
}

impl Default for CataractParams {
    fn default() -> Self {
        Self {
            lens_cells: 12,
            eye: EyeShell {
                incision: Some(Incision {
                    width: 3.0e-3,
                    ..Default::default()
                }),
                ..Default::default()
            },
            lens_young: 3e3,
            nucleus_factor: 5.0,
            eye_young: 30e3,
            vectis_friction: 0.5,
            lens_offset: 5.4e-3,
            medium_drag: 10.0,
            deliver: true,
        }
    }
}

impl CataractParams {
    /// The same scene with the vectis stopping after the push (8 s): the lens
    /// is pressed into the slit, not delivered ([`Self::deliver`] off).
    pub fn push_only(mut self) -> Self {
        self.deliver = false;
        self
    }

    /// A coarse version (≈ 300-node lens, ≈ 300-node eye) for tests.
    pub fn coarse() -> Self {
        let mut p = Self {
            lens_cells: 6,
            ..Default::default()
        };
        p.eye.cells = 6;
        p
    }
}

/// The frame of the incision: `(e_r, e_θ)`, the unit direction from the eye
/// centre to the incision and the polar tangent there (across the slit).
pub fn incision_frame(p: &CataractParams) -> (Vec3, Vec3) {
    let inc = p.eye.incision.unwrap_or_default();
    let (st, ct) = inc.polar.sin_cos();
    let (sa, ca) = inc.azimuth.sin_cos();
    (v3(st * ca, st * sa, ct), v3(ct * ca, ct * sa, -st))
}

/// Rotation taking the lens's thin axis (z) to `e_θ`, i.e. its edge toward the incision.
pub fn lens_rotation(p: &CataractParams) -> nalgebra::Rotation3<f64> {
    let (er, et) = incision_frame(p);
    let ex = et.cross(&er);
    nalgebra::Rotation3::from_matrix_unchecked(crate::math::Mat3::from_columns(&[ex, -er, et]))
}

/// Centre of the lens.
pub fn lens_center(p: &CataractParams) -> Vec3 {
    incision_frame(p).0 * p.lens_offset
}

/// Lens and eye materials. The lens material is for the lens mesh in its own
/// (unrotated, centred) frame; [`build`] turns it into per-element values.
pub fn materials(p: &CataractParams) -> (TissueMaterial, TissueMaterial) {
    let lens = TissueMaterial::new(1050.0, p.lens_young, 0.45)
        .with_stiffness(StiffnessField::Radial {
            center: Vec3::zeros(),
            radii: Vec3::from(LENS_RADII),
            core_radius: 0.6,
            factor: p.nucleus_factor,
            transition: Transition::Smooth { width: 0.2 },
        })
        .with_damping(p.medium_drag, 0.005);
    // Lubricated by viscoelastic: the vectis slides along the lips it spreads.
    // With the vectis's μ = 0.5 it dragged them out of the eye, up to 10.7 mm,
    // before they sprang back, and the lens left at up to 66 mm/s.
    let eye = TissueMaterial::new(1050.0, p.eye_young, 0.45)
        .with_damping(p.medium_drag, 0.005)
        .with_tool_friction(0.0);
    (lens, eye)
}

/// The vectis blade: a flattened, slightly curved spoon, 4 mm wide, 8 mm long,
/// 0.8 mm thick, in its local frame (long axis +y, concave side +z, both
/// along and across).
pub fn vectis_shape() -> ToolShape {
    let (nu, nv) = (16usize, 10usize);
    let (a, b, c) = (2.0e-3, 4.0e-3, 0.4e-3);
    let mut vertices = vec![v3(0.0, 0.0, -c)];
    for j in 1..nv {
        let th = std::f64::consts::PI * j as f64 / nv as f64;
        for i in 0..nu {
            let ph = 2.0 * std::f64::consts::PI * i as f64 / nu as f64;
            let (x, y, z) = (
                a * th.sin() * ph.cos(),
                b * th.sin() * ph.sin(),
                -c * th.cos(),
            );
            vertices.push(v3(x, y, z));
        }
    }
    vertices.push(v3(0.0, 0.0, c));
    // Bend: the spoon's tip and heel curve upward (0.32 mm), and so do its
    // sides (1 mm), a bowl that keeps the lens's rim centred. With a blade
    // flat across its width, the squeezed lens slid sideways along it,
    // around its edge and back into the eye in about one run of four; with
    // sides raised 0.5 mm, in two runs of about sixty; with 1 mm, in
    // none of twenty-four.
    for p in &mut vertices {
        p.z += 0.08 * (p.y * p.y) / b + 0.5 * (p.x * p.x) / a;
    }
    let mut indices = Vec::new();
    let ring = |j: usize, i: usize| (1 + (j - 1) * nu + i % nu) as u32;
    for i in 0..nu {
        indices.push([0, ring(1, i + 1), ring(1, i)]);
    }
    for j in 1..nv - 1 {
        for i in 0..nu {
            let (p, q, r, s) = (
                ring(j, i),
                ring(j, i + 1),
                ring(j + 1, i),
                ring(j + 1, i + 1),
            );
            indices.push([p, q, s]);
            indices.push([p, s, r]);
        }
    }
    let top = (vertices.len() - 1) as u32;
    for i in 0..nu {
        indices.push([top, ring(nv - 1, i), ring(nv - 1, i + 1)]);
    }
    ToolShape::TriMesh { vertices, indices }
}

/// Direction from the lens centre to the incision.
pub fn incision_direction(p: &CataractParams) -> Vec3 {
    incision_frame(p).0
}

/// The scripted extraction: the vectis starts under the lens, rises to engage
/// it, then draws it toward and out through the incision. Poses are for a
/// time in seconds; after the last key the vectis stays.
#[derive(Debug, Clone, PartialEq)]
pub struct ExtractionPath {
    keys: Vec<(f64, Vec3)>,
    rotation: UnitQuaternion<f64>,
}

impl ExtractionPath {
    /// The default path for `p`: the blade faces the lens's rim from the side
    /// opposite the incision and pushes it toward and into the slit (0–8 s,
    /// 7 mm). The lens moves about 4 mm toward the incision, and its rim is
    /// pressed into the slit, deforming the sclera around it.
    ///
    /// With [`CataractParams::deliver`] (the default) the blade goes on
    /// (8–17 s, 15 mm more, out of the eye) and the lens squeezes through the
    /// incision and out; its centre ends about 20–23 mm from the eye's
    /// centre, the whole lens outside. That phase is the hardest numerically:
    /// 300–500 contacts hold the lens in the slit, with 20–60 CG iterations
    /// per step and, in a few steps, 20–40 contact passes (see
    /// [`contact_settings`]). (A path that stopped 6 mm
    /// earlier, at 14 s, left the lens in the incision in about two runs of
    /// nine.)
    pub fn new(p: &CataractParams) -> Self {
        let (er, et) = incision_frame(p);
        let c = lens_center(p);
        let behind = c - er * (LENS_RADII[0] + 0.4e-3 + 0.4e-3);
        let blade = crate::math::Mat3::from_columns(&[et.cross(&er), et, er]);
        let mut keys = vec![
            (0.0, behind),
            (0.5, behind + er * 0.3e-3),
            (4.5, behind + er * 4.0e-3),
            (8.0, behind + er * 7.0e-3),
        ];
        if p.deliver {
            // On through the slit: the lens is delivered out of the eye.
            keys.push((17.0, behind + er * 22.0e-3));
        }
        Self {
            keys,
            rotation: UnitQuaternion::from_rotation_matrix(
                &nalgebra::Rotation3::from_matrix_unchecked(blade),
            ),
        }
    }

    /// Duration of the scripted motion, seconds.
    pub fn duration(&self) -> f64 {
        self.keys.last().map(|k| k.0).unwrap_or(0.0)
    }

    /// Pose at time `t` (smooth interpolation between keys).
    pub fn pose(&self, t: f64) -> Pose {
        let mut k = 0;
        while k + 1 < self.keys.len() && self.keys[k + 1].0 <= t {
            k += 1;
        }
        let p = if k + 1 >= self.keys.len() {
            self.keys[self.keys.len() - 1].1
        } else {
            let (t0, p0) = self.keys[k];
            let (t1, p1) = self.keys[k + 1];
            let u = ((t - t0) / (t1 - t0)).clamp(0.0, 1.0);
            p0 + (p1 - p0) * (u * u * (3.0 - 2.0 * u))
        };
        // Blade normal (local z) along e_r against the lens rim, long axis along e_θ.
        Isometry3::from_parts(Translation3::from(p), self.rotation)
    }
}

/// Contact settings of the scene: a 0.1 mm alarm distance (a wider band adds
/// many inactive contacts and slows `W` more than it helps) and a frictionless
/// lens–sclera interface (viscoelastic-lubricated); the vectis has its own μ.
/// Up to 64 contact passes. When the lens rim is jammed in the slit, or
/// pops through it, each correction's recoil slides other lens vertices into
/// the curved lips of the incision. The next pass finds them, and only a step
/// that runs out of passes keeps them: during delivery sixteen passes left
/// up to 14 µm in one run of three, and 32 left 4.1 µm in one run of nine.
/// Where the squeezed lens folds against a lip, a sclera vertex caught in the
/// fold can need 20–40 passes, each leaving some 10 % less; 64 kept every step
/// of 35 runs within 1 µm. A pass runs only while something still penetrates,
/// so quiet steps pay nothing, and a step needs more than eight passes about
/// once in a hundred.
pub fn contact_settings() -> ContactSettings {
    ContactSettings {
        alarm_distance: 0.1e-3,
        body_friction: 0.0,
        max_passes: 64,
        ..Default::default()
    }
}

/// The two bodies, the vectis and the extraction path.
#[derive(Debug)]
pub struct CataractScene {
    /// The lens (nucleus 5× stiffer).
    pub lens: DeformableBody,
    /// The eye shell, posterior part fixed.
    pub eye: DeformableBody,
    /// The vectis.
    pub vectis: RigidTool,
    /// Scripted motion of the vectis.
    pub path: ExtractionPath,
    /// Contact settings that suit the scene's scale.
    pub contact: ContactSettings,
}

/// Builds the scene.
pub fn build(p: &CataractParams, settings: BodySettings) -> Result<CataractScene> {
    let (lens_mat, eye_mat) = materials(p);
    let local = generate::ellipsoid(LENS_RADII, p.lens_cells)?;
    let young = lens_mat.element_young(&local)?;
    let lens_mesh = local.rotated(&lens_rotation(p)).translated(lens_center(p));
    let lens_mat = lens_mat.with_stiffness(StiffnessField::PerElement(young));
    let lens = DeformableBody::new(lens_mesh, lens_mat, settings)?;
    let eye_mesh = generate::eye_shell(&p.eye)?;
    let mut eye = DeformableBody::new(eye_mesh, eye_mat, settings)?;
    let r = p.eye.radius;
    eye.fix_where(|x| x.z < -0.35 * r);
    let path = ExtractionPath::new(p);
    let vectis =
        RigidTool::new(vectis_shape(), path.pose(0.0))?.with_friction(p.vectis_friction)?;
    let contact = contact_settings();
    Ok(CataractScene {
        lens,
        eye,
        vectis,
        path,
        contact,
    })
}
