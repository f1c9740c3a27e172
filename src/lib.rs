//! # bevy_soft_tissue
//!
//! Real-time finite-element soft tissue with accurate contacts, for Bevy.
//!
//! The crate has two layers:
//!
//! - **The numerical core** — [`math`], [`error`] → [`mesh`] → [`material`] →
//!   [`fem`] → [`solver`] → [`body`] → [`contact`] → [`scene`] → [`haptics`] (each module
//!   uses only those before it; [`scenes`] builds ready-made scenes on top,
//!   and [`study`] measures what accuracy costs in time on any of them). It
//!   has no Bevy types, works in `f64`, takes its scratch memory explicitly and
//!   allocates nothing inside per-step loops. It builds without Bevy
//!   (`--no-default-features`) and can be used and tested on its own.
//! - **The Bevy plugin** (feature `bevy`, on by default) — `plugin`: a thin ECS
//!   layer over the core. `SoftTissuePlugins` (a plugin group) is the entry;
//!   its systems run in the chained `SoftTissueSystems` sets of the
//!   pipeline's own schedule (`SoftTissueSchedule`, run from
//!   `FixedPostUpdate`) and call the
//!   same phase functions as [`scene::Scene::step`] ([`scene::phases`]). The
//!   cataract scene as a plugin (`scenes::CataractScenePlugin`), the `.msh` /
//!   TetGen asset loader (`plugin::assets`) and, with the `gpu` feature, the
//!   compute-shader compliance (`gpu`) sit beside it.
//!
//! ## Method
//! Co-rotational linear tetrahedra with per-element Young's modulus, the
//! linearized implicit Euler step `(M + hB + h²K) a = b` solved by a
//! conjugate gradient, preconditioned by an `LDLᵀ` factorization that a
//! background thread refreshes at low rate and that is warped by the node
//! rotations since it was made (`P = Rᵀ L D Lᵀ R`), or by the body's one turn
//! since, where that warp fits the current matrix better than the plain
//! factor. See [`solver`] and [`body`].
//!
//! ## Quick start (core only)
//! ```
//! use bevy_soft_tissue::core_prelude::*;
//!
//! let mesh = generate::box_mesh(v3(0.0, 0.0, 0.0), v3(0.1, 0.02, 0.02), [10, 2, 2]).unwrap();
//! let settings = BodySettings { gravity: Some(v3(0.0, 0.0, -9.81)), ..Default::default() };
//! let mut body = DeformableBody::new(mesh, TissueMaterial::new(1000.0, 1e5, 0.3), settings).unwrap();
//! body.fix_where(|p| p.x < 1e-9);
//! for _ in 0..10 {
//!     let report = body.step(0.01).unwrap();
//!     assert!(report.cg.converged);
//! }
//! ```

#![warn(missing_docs)]
#![allow(clippy::needless_range_loop)] // index loops mirror the math of the kernels

pub mod body;
pub mod contact;
pub mod error;
pub mod fem;
#[cfg(feature = "gpu")]
pub mod gpu;
pub mod haptics;
pub mod material;
pub mod math;
pub mod mesh;
#[cfg(feature = "bevy")]
pub mod plugin;
pub mod scene;
pub mod scenes;
pub mod solver;
pub mod study;

#[cfg(feature = "bevy")]
pub use plugin::{SoftTissuePlugins, SoftTissueSchedule, SoftTissueSystems};

/// The most used items, for Bevy apps: import it next to `bevy::prelude::*`
/// (it exports no names that clash with Bevy's prelude; the core's `f64`
/// math types are in [`core_prelude`] and [`math`]).
pub mod prelude {
    pub use crate::body::{BodySettings, DeformableBody, NodeConstraint, StepReport, StepTimings};
    pub use crate::contact::{
        ComplianceMode, Contact, ContactReport, ContactSettings, ContactSolver, LcpSettings,
        LcpSolver, PassKind, Pose, RigidTool, ToolShape,
    };
    pub use crate::error::SoftTissueError;
    pub use crate::fem::RotationMethod;
    pub use crate::material::{RayleighDamping, StiffnessField, TissueMaterial, Transition};
    pub use crate::math::v3;
    pub use crate::mesh::{Surface, TetMesh, ValidateOptions, generate, io};
    #[cfg(feature = "bevy")]
    pub use crate::plugin::{
        BodyContacts, ComplianceOverride, FailedPhase, FixedNodes, GpuMode, HapticTool,
        HapticsPlugin, HapticsStatus, PreconditionerOverride, SoftBody, SoftBodyError,
        SoftBodyFailed, SoftBodyFromAsset, SoftTissueConfig, SoftTissueContacts,
        SoftTissueDiagnostics, SoftTissuePlugins, SoftTissueSchedule, SoftTissueSystems,
        TetMeshAsset, Tool, ToolReaction,
    };
    pub use crate::scene::Scene;
    pub use crate::solver::PreconditionerKind;
    pub use crate::solver::cg::{CgReport, CgSettings};
}

/// [`prelude`] plus the core's `f64` math types and `Result`, for code that
/// uses the numerical core without Bevy's prelude.
pub mod core_prelude {
    pub use crate::error::Result;
    pub use crate::math::{Mat3, Vec3};
    pub use crate::prelude::*;
}
