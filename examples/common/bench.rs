//! Bench fixtures shared by the benchmarks, the examples and the tests (not
//! library API): the paper-size lens and synthetic contacts on it. No Bevy types.

use bevy_soft_tissue::body::{BodySettings, DeformableBody};
use bevy_soft_tissue::error::Result;
use bevy_soft_tissue::material::TissueMaterial;
use bevy_soft_tissue::mesh::generate::{self, LENS_RADII};
use bevy_soft_tissue::solver::PreconditionerKind;

/// The lens material of the benchmarks: 5 kPa periphery, nucleus 5× stiffer
/// (smooth transition), ν = 0.45.
pub fn lens_material() -> TissueMaterial {
    bevy_soft_tissue::study::cases::lens_material(5.0)
}

/// The paper-size lens (`cells = 12`: 1183 nodes, 5184 tets) with preconditioner `kind`.
pub fn lens_body(kind: PreconditionerKind, cells: usize) -> Result<DeformableBody> {
    let mesh = generate::ellipsoid(LENS_RADII, cells)?;
    let settings = BodySettings {
        preconditioner: kind,
        ..Default::default()
    };
    DeformableBody::new(mesh, lens_material(), settings)
}

#[allow(unused_imports)]
pub use bevy_soft_tissue::study::compliance::pole_contacts;
