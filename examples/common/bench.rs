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

/// "min to max, median m" of `v` with `digits` decimals ("none" when empty);
/// sorts `v`.
pub fn spread(v: &mut [f64], digits: usize) -> String {
    if v.is_empty() {
        return "none".into();
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    let median = if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    };
    format!(
        "{:.d$} to {:.d$}, median {:.d$}",
        v[0],
        v[n - 1],
        median,
        d = digits
    )
}
