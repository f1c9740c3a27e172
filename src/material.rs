//! Materials: density, Poisson ratio, per-element Young's modulus and Rayleigh damping.
//!
//! A [`TissueMaterial`] gives the base properties of a body; its
//! [`StiffnessField`] turns the base Young's modulus into one value per
//! element:
//!
//! - [`StiffnessField::Uniform`]: every element has the base modulus;
//! - [`StiffnessField::Radial`]: a core `factor`× stiffer than the periphery,
//!   measured on an ellipsoidal radius around a centre, with a sharp or a
//!   smooth (smoothstep) transition — the cataract lens nucleus;
//! - [`StiffnessField::PerElement`]: explicit values in pascals.
//!
//! Rayleigh damping `B = α M + β K` is given by [`RayleighDamping`]. With both
//! coefficients zero no damping term is assembled at all.
//!
//! [`TissueMaterial::tool_friction`] sets the Coulomb friction of the
//! tissue's surface against every tool, in place of each tool's own μ: a
//! surface lubricated by viscoelastic (the sclera against the vectis in the
//! cataract scene) is `Some(0.0)`, and its contacts get no friction rows.

use crate::error::{Result, SoftTissueError, check_positive, check_range};

/// The largest Young's modulus or density accepted, 1e15 (Pa or kg/m³): six
/// orders above steel's modulus, far from where `h² K` overflows.
pub const MAX_MODULUS: f64 = 1e15;
use crate::math::Vec3;
use crate::mesh::TetMesh;

/// Rayleigh damping coefficients: `B = mass · M + stiffness · K`.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RayleighDamping {
    /// Mass-proportional coefficient α, 1/s.
    pub mass: f64,
    /// Stiffness-proportional coefficient β, s.
    pub stiffness: f64,
}

impl RayleighDamping {
    /// True when both coefficients are zero: no damping term is computed.
    pub fn is_zero(&self) -> bool {
        self.mass == 0.0 && self.stiffness == 0.0
    }
}

/// Transition between core and periphery in [`StiffnessField::Radial`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Transition {
    /// A step at the core radius.
    Sharp,
    /// A smoothstep over `width` (in normalized radius units) centred on the core radius.
    Smooth {
        /// Width of the transition band, normalized radius units.
        width: f64,
    },
}

/// How Young's modulus varies over the elements.
#[derive(Debug, Clone, PartialEq)]
pub enum StiffnessField {
    /// The base modulus everywhere.
    Uniform,
    /// A stiff core: elements whose centroid lies within normalized radius
    /// `core_radius` of `center` (radius normalized by `radii`, so an ellipsoid
    /// of the body's shape) are `factor`× stiffer.
    Radial {
        /// Centre of the core.
        center: Vec3,
        /// Semi-axes used to normalize the radius.
        radii: Vec3,
        /// Core radius in normalized units (0..1 for a core inside the ellipsoid).
        core_radius: f64,
        /// Stiffness ratio core / periphery.
        factor: f64,
        /// Sharp or smooth transition.
        transition: Transition,
    },
    /// One Young's modulus per element, in pascals.
    PerElement(Vec<f64>),
}

/// TissueMaterial of a soft body.
#[derive(Debug, Clone, PartialEq)]
pub struct TissueMaterial {
    /// Mass density, kg/m³.
    pub density: f64,
    /// Poisson ratio, in (-1, 0.5).
    pub poisson: f64,
    /// Base Young's modulus, Pa.
    pub young: f64,
    /// Spatial variation of Young's modulus.
    pub stiffness: StiffnessField,
    /// Rayleigh damping.
    pub damping: RayleighDamping,
    /// Coulomb friction of this tissue against every tool, in place of the
    /// tool's μ ([`crate::contact::RigidTool::friction`]); `None` (the
    /// default) uses each tool's own μ. `Some(0.0)` makes the surface
    /// slippery for all tools (lubricated), and its tool contacts carry no
    /// friction rows.
    pub tool_friction: Option<f64>,
}

impl Default for TissueMaterial {
    fn default() -> Self {
        Self {
            density: 1000.0,
            poisson: 0.45,
            young: 10e3,
            stiffness: StiffnessField::Uniform,
            damping: RayleighDamping::default(),
            tool_friction: None,
        }
    }
}

impl TissueMaterial {
    /// A material with the given density, Young's modulus and Poisson ratio.
    pub fn new(density: f64, young: f64, poisson: f64) -> Self {
        Self {
            density,
            young,
            poisson,
            ..Default::default()
        }
    }

    /// Sets the stiffness field.
    pub fn with_stiffness(mut self, field: StiffnessField) -> Self {
        self.stiffness = field;
        self
    }

    /// Sets Rayleigh damping.
    pub fn with_damping(mut self, mass: f64, stiffness: f64) -> Self {
        self.damping = RayleighDamping { mass, stiffness };
        self
    }

    /// Sets the friction of this tissue against every tool ([`Self::tool_friction`]).
    pub fn with_tool_friction(mut self, mu: f64) -> Self {
        self.tool_friction = Some(mu);
        self
    }

    /// Checks every parameter and returns a clear error for the first bad one.
    /// Moduli and densities above [`MAX_MODULUS`] are refused: a stiffness
    /// that large makes `h²K` overflow in assembly.
    pub fn validate(&self) -> Result<()> {
        check_range("density", self.density, 1e-12, MAX_MODULUS)?;
        check_range("young", self.young, 1e-12, MAX_MODULUS)?;
        if !self.poisson.is_finite() || self.poisson <= -1.0 || self.poisson >= 0.5 {
            return Err(SoftTissueError::InvalidParameter {
                name: "poisson",
                value: self.poisson,
                reason: "must lie in (-1, 0.5)",
            });
        }
        check_range("damping.mass", self.damping.mass, 0.0, f64::MAX)?;
        check_range("damping.stiffness", self.damping.stiffness, 0.0, f64::MAX)?;
        if let Some(mu) = self.tool_friction {
            check_range("tool_friction", mu, 0.0, f64::MAX)?;
        }
        if let StiffnessField::Radial {
            radii,
            core_radius,
            factor,
            transition,
            center,
        } = &self.stiffness
        {
            for r in radii.iter() {
                check_positive("radial.radii", *r)?;
            }
            if !center.iter().all(|c| c.is_finite()) {
                return Err(SoftTissueError::NonFinite("radial.center"));
            }
            check_positive("radial.core_radius", *core_radius)?;
            check_positive("radial.factor", *factor)?;
            if self.young * factor > MAX_MODULUS {
                return Err(SoftTissueError::InvalidParameter {
                    name: "radial.factor",
                    value: *factor,
                    reason: "young × factor exceeds the largest modulus accepted (1e15 Pa)",
                });
            }
            if let Transition::Smooth { width } = transition {
                check_positive("radial.width", *width)?;
            }
        }
        if let StiffnessField::PerElement(v) = &self.stiffness {
            for &e in v {
                check_positive("per_element_young", e)?;
                check_range("per_element_young", e, 0.0, MAX_MODULUS)?;
            }
        }
        Ok(())
    }

    /// Young's modulus of every element of `mesh`.
    pub fn element_young(&self, mesh: &TetMesh) -> Result<Vec<f64>> {
        self.validate()?;
        match &self.stiffness {
            StiffnessField::Uniform => Ok(vec![self.young; mesh.num_tets()]),
            StiffnessField::PerElement(v) => {
                if v.len() != mesh.num_tets() {
                    return Err(SoftTissueError::LengthMismatch {
                        name: "per_element_young",
                        got: v.len(),
                        expected: mesh.num_tets(),
                    });
                }
                Ok(v.clone())
            }
            StiffnessField::Radial {
                center,
                radii,
                core_radius,
                factor,
                transition,
            } => Ok((0..mesh.num_tets())
                .map(|t| {
                    let d = mesh.tet_centroid(t) - center;
                    let rho = d.component_div(radii).norm();
                    let s = match transition {
                        Transition::Sharp => f64::from(rho < *core_radius),
                        Transition::Smooth { width } => {
                            let u = ((core_radius + 0.5 * width - rho) / width).clamp(0.0, 1.0);
                            u * u * (3.0 - 2.0 * u)
                        }
                    };
                    self.young * (1.0 + (factor - 1.0) * s)
                })
                .collect()),
        }
    }

    /// Lamé parameters `(λ, μ)` for Young's modulus `e`.
    pub fn lame(&self, e: f64) -> (f64, f64) {
        let nu = self.poisson;
        let lambda = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
        let mu = e / (2.0 * (1.0 + nu));
        (lambda, mu)
    }
}
