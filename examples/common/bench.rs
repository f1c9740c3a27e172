//! Bench fixtures shared by the benchmarks, the examples and the tests (not
//! library API): the paper-size lens and synthetic contacts on it. No Bevy types.

use bevy_soft_tissue::material::TissueMaterial;

/// The lens material of the benchmarks: 5 kPa periphery, nucleus 5× stiffer
/// (smooth transition), ν = 0.45.
pub fn lens_material() -> TissueMaterial {
    bevy_soft_tissue::study::cases::lens_material(5.0)
}

#[allow(unused_imports)]
pub use bevy_soft_tissue::study::compliance::pole_contacts;
