//! Small dense linear algebra shared by the core (`f64` throughout).
//!
//! The core uses [`nalgebra`] for 3-vectors and 3×3 matrices. Bevy (glam
//! `f32`) and parry (glam `f64`) types are converted only at the edges.

use nalgebra::{Matrix3, Vector3};

/// A 3-vector of `f64`.
pub type Vec3 = Vector3<f64>;
/// A 3×3 matrix of `f64`.
pub type Mat3 = Matrix3<f64>;

/// Builds a [`Vec3`].
#[inline]
pub fn v3(x: f64, y: f64, z: f64) -> Vec3 {
    Vec3::new(x, y, z)
}

/// Rotation part of the polar decomposition `F = R S`, defined for flat and
/// inverted `F`: from the SVD `F = U Σ Vᵀ`, with the sign of the column of `U`
/// belonging to the smallest singular value flipped when `det(U Vᵀ) < 0`, so
/// that `R` is always a proper rotation.
pub fn polar_rotation(f: &Mat3) -> Mat3 {
    let Some((u, sigma, v_t)) = svd3(f) else {
        return Mat3::identity();
    };
    sign_fix(u, &sigma, &v_t)
}

/// `U Vᵀ`, with the column of `U` of the smallest singular value flipped when
/// that makes it proper.
fn sign_fix(mut u: Mat3, sigma: &Vec3, v_t: &Mat3) -> Mat3 {
    let r = u * v_t;
    if r.determinant() < 0.0 {
        let mut smallest = 0;
        for i in 1..3 {
            if sigma[i] < sigma[smallest] {
                smallest = i;
            }
        }
        for k in 0..3 {
            u[(k, smallest)] = -u[(k, smallest)];
        }
        return u * v_t;
    }
    r
}

/// `U`, the singular values and `Vᵀ` of a finite `F` (`None` otherwise).
fn svd3(f: &Mat3) -> Option<(Mat3, Vec3, Mat3)> {
    if !f.iter().all(|x| x.is_finite()) {
        return None;
    }
    let svd = f.svd(true, true);
    Some((svd.u?, svd.singular_values, svd.v_t?))
}

/// Where the smallest singular value of a flat or inverted `F` is at least
/// this fraction of the middle one, [`polar_rotation_near`] keeps the
/// candidate nearest the last rotation (the two can cross, and the plain sign
/// fix would jump); below it, the plain sign fix. In the cataract scene's
/// delivery (`AsyncLagged { lag: 2 }` through the core `Scene`, the vectis held
/// five seconds after its path) the nearest candidate everywhere left five
/// lens elements inverted at rest, 0.5 left one and 0.9 none, with 0.7 % more
/// CG iterations over the run (the plain sign fix everywhere: none, 2.8 %).
pub const SINGULAR_VALUES_CLOSE: f64 = 0.9;

/// The proper rotation of an inverted or flat `F` that is closest to `prev`
/// (largest `tr(prevᵀ R)`), among the rotations `U S Vᵀ` of its SVD
/// `F = U Σ Vᵀ` whose sign matrix `S` makes `det R = 1`; [`polar_rotation_fast`]
/// where `det F` is safely positive (the rotation is unique there).
///
/// The plain sign fix of [`polar_rotation`] flips the direction of the smallest
/// singular value; when two singular values of an inverted element cross, that
/// choice jumps by up to a half turn between steps. Keeping the candidate
/// nearest the previous rotation follows the element's turning without the
/// jumps, but it can also keep a candidate that leaves the element inverted
/// where its neighbours balance its push. So the nearest candidate is taken
/// only where the two smallest singular values are within
/// [`SINGULAR_VALUES_CLOSE`] of each other (where they can cross); elsewhere
/// the plain sign fix, unique and continuous there, which pushes the element
/// back across its thinnest direction.
pub fn polar_rotation_near(f: &Mat3, prev: &Mat3) -> Mat3 {
    let scale2 = f.norm_squared();
    let det = f.determinant();
    if safely_positive(scale2, det) {
        return polar_newton(f, scale2, det).unwrap_or_else(|| polar_rotation(f));
    }
    let Some((u, sigma, v_t)) = svd3(f) else {
        return *prev;
    };
    let mut sorted = [sigma[0], sigma[1], sigma[2]];
    sorted.sort_by(f64::total_cmp);
    if sorted[0] < SINGULAR_VALUES_CLOSE * sorted[1] {
        return sign_fix(u, &sigma, &v_t);
    }
    let base = u * v_t;
    let signs: &[[f64; 3]] = if base.determinant() < 0.0 {
        &[
            [-1.0, 1.0, 1.0],
            [1.0, -1.0, 1.0],
            [1.0, 1.0, -1.0],
            [-1.0, -1.0, -1.0],
        ]
    } else {
        &[
            [1.0, 1.0, 1.0],
            [1.0, -1.0, -1.0],
            [-1.0, 1.0, -1.0],
            [-1.0, -1.0, 1.0],
        ]
    };
    let mut best = base;
    let mut best_fit = f64::NEG_INFINITY;
    for s in signs {
        let r = u * Mat3::from_diagonal(&Vec3::new(s[0], s[1], s[2])) * v_t;
        let fit = (prev.transpose() * r).trace();
        if fit > best_fit {
            best_fit = fit;
            best = r;
        }
    }
    best
}

/// Orthonormal frame built from two edges by Gram–Schmidt: columns
/// `(x, y, z)` with `x ∥ a`, `z ∥ a × b`. Falls back to the identity for
/// collinear edges.
pub fn edge_frame(a: &Vec3, b: &Vec3) -> Mat3 {
    let x = a.normalize();
    let n = a.cross(b);
    if !x.iter().all(|c| c.is_finite()) || n.norm() <= 1e-300 {
        return Mat3::identity();
    }
    let z = n.normalize();
    let y = z.cross(&x);
    Mat3::from_columns(&[x, y, z])
}

/// Solves `L x = b` for a unit lower-triangular 3×3 `L` given by its three
/// sub-diagonal entries `(l10, l20, l21)`.
#[inline]
pub fn unit_lower_solve(l: &[f64; 3], b: &Vec3) -> Vec3 {
    let x0 = b.x;
    let x1 = b.y - l[0] * x0;
    let x2 = b.z - l[1] * x0 - l[2] * x1;
    Vec3::new(x0, x1, x2)
}

/// Solves `Lᵀ x = b` for a unit lower-triangular 3×3 `L` given by `(l10, l20, l21)`.
#[inline]
pub fn unit_lower_t_solve(l: &[f64; 3], b: &Vec3) -> Vec3 {
    let x2 = b.z;
    let x1 = b.y - l[2] * x2;
    let x0 = b.x - l[0] * x1 - l[1] * x2;
    Vec3::new(x0, x1, x2)
}

/// Applies [`unit_lower_solve`] to each column of `b`.
#[inline]
pub fn unit_lower_solve_mat(l: &[f64; 3], b: &Mat3) -> Mat3 {
    let mut out = Mat3::zeros();
    for c in 0..3 {
        out.set_column(c, &unit_lower_solve(l, &b.column(c).into_owned()));
    }
    out
}

/// Same rotation as [`polar_rotation`], computed by Higham's scaled Newton
/// iteration `X ← ½(γX + γ⁻¹X⁻ᵀ)` (quadratic convergence, a 3×3 cofactor per
/// step) when `det F` is safely positive, and by the SVD with the sign fix for
/// flat, inverted or non-converging cases.
pub fn polar_rotation_fast(f: &Mat3) -> Mat3 {
    let scale2 = f.norm_squared();
    let det = f.determinant();
    safely_positive(scale2, det)
        .then(|| polar_newton(f, scale2, det))
        .flatten()
        .unwrap_or_else(|| polar_rotation(f))
}

/// `Σ aᵢ · bᵢ` over 3-vectors.
#[inline]
pub(crate) fn dot(a: &[Vec3], b: &[Vec3]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x.dot(y)).sum()
}

/// The largest magnitude of any entry of `v` (0 for an empty slice; NaN is
/// passed over, an infinite entry gives ∞).
#[inline]
pub(crate) fn max_abs(v: &[Vec3]) -> f64 {
    v.iter().fold(0.0, |m, x| m.max(x.amax()))
}

/// Whether `det F` is safely positive for the Newton iteration: finite and
/// above `10⁻⁶ ‖F‖³` (`scale2 = ‖F‖²`, Frobenius).
#[inline]
pub(crate) fn safely_positive(scale2: f64, det: f64) -> bool {
    scale2.is_finite() && det > 1e-6 * scale2 * scale2.sqrt()
}

/// Higham's scaled Newton iteration for the rotation of `F` (`scale2 = ‖F‖²`,
/// `det = det F > 0`); `None` if it leaves the positive determinants or does
/// not converge in 12 steps. Per step one cofactor, two divisions and two
/// square roots: with `C = cof X = det X · X⁻ᵀ`,
/// `γ = (‖X⁻ᵀ‖/‖X‖)^½ = (‖C‖² / (det² ‖X‖²))^¼` and
/// `X ← ½ γ X + C / (2 γ det X)`.
#[inline]
fn polar_newton(f: &Mat3, scale2: f64, det: f64) -> Option<Mat3> {
    let mut x = *f;
    let (mut d, mut x2) = (det, scale2);
    for _ in 0..12 {
        let c = Mat3::from_columns(&[
            x.column(1).cross(&x.column(2)),
            x.column(2).cross(&x.column(0)),
            x.column(0).cross(&x.column(1)),
        ]);
        let gamma = (c.norm_squared() / (d * d * x2)).sqrt().sqrt();
        let next = x * (0.5 * gamma) + c * (0.5 / (gamma * d));
        let delta2 = (next - x).norm_squared();
        x = next;
        x2 = x.norm_squared();
        // Quadratic convergence: the error of `next` is of the order of
        // `delta²`, so a step of 1e-8 (relative) leaves it near rounding.
        if delta2 <= 1e-16 * x2 {
            return Some(x);
        }
        d = x.determinant();
        if d.is_nan() || d <= 0.0 {
            return None;
        }
    }
    None
}

/// Whether the CPU runs the AVX2/FMA kernels of the solver and the compliance
/// (x86-64 only; detected once by the standard library, then a cached load).
#[inline]
pub(crate) fn has_avx2_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// AVX2 helpers shared by the kernels (the factor's solves, the system
/// matrix's product): 3-vectors and 3×3 column-major blocks
/// moved in and out of four-lane registers without touching memory past them.
#[cfg(target_arch = "x86_64")]
pub(crate) mod x86 {
    use super::{Mat3, Vec3};
    use std::arch::x86_64::*;

    /// Three `f64` at `p` in lanes 0–2, lane 3 zero.
    ///
    /// # Safety
    /// `p..p + 3` must be readable.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    pub(crate) unsafe fn load3_ptr(p: *const f64) -> __m256d {
        // SAFETY: the caller guarantees three readable values.
        unsafe { _mm256_set_m128d(_mm_load_sd(p.add(2)), _mm_loadu_pd(p)) }
    }

    /// Lanes 0–2 of `v` to `p..p + 3`.
    ///
    /// # Safety
    /// `p..p + 3` must be writable.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    pub(crate) unsafe fn store3_ptr(p: *mut f64, v: __m256d) {
        // SAFETY: the caller guarantees three writable values.
        unsafe {
            _mm_storeu_pd(p, _mm256_castpd256_pd128(v));
            _mm_store_sd(p.add(2), _mm256_extractf128_pd(v, 1));
        }
    }

    /// `v` in lanes 0–2, lane 3 zero.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    pub(crate) fn load3(v: &Vec3) -> __m256d {
        // SAFETY: a `Vec3` holds three contiguous f64.
        unsafe { load3_ptr(v.as_slice().as_ptr()) }
    }

    /// Lanes 0–2 of `v` into `dst`.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    pub(crate) fn store3(dst: &mut Vec3, v: __m256d) {
        // SAFETY: a `Vec3` holds three contiguous f64.
        unsafe { store3_ptr(dst.as_mut_slice().as_mut_ptr(), v) }
    }

    /// The three columns of `m`, each in lanes 0–2 with lane 3 zero.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    pub(crate) fn columns(m: &Mat3) -> [__m256d; 3] {
        let p = m.as_slice().as_ptr();
        let zero = _mm256_setzero_pd();
        // SAFETY: the nine entries are contiguous; the four-lane loads read
        // offsets 0..4 and 3..7, and the last column reads 6..9.
        unsafe {
            [
                _mm256_blend_pd(_mm256_loadu_pd(p), zero, 0b1000),
                _mm256_blend_pd(_mm256_loadu_pd(p.add(3)), zero, 0b1000),
                load3_ptr(p.add(6)),
            ]
        }
    }

    /// `acc + A x` (lanes 0–2): `A`'s columns times broadcast entries of `x`.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    pub(crate) fn add_product(acc: __m256d, a: &Mat3, x: &Vec3) -> __m256d {
        let c = columns(a);
        let acc = _mm256_fmadd_pd(c[0], _mm256_set1_pd(x.x), acc);
        let acc = _mm256_fmadd_pd(c[1], _mm256_set1_pd(x.y), acc);
        _mm256_fmadd_pd(c[2], _mm256_set1_pd(x.z), acc)
    }

    /// The sums of the four lanes of each of `v`, as a vector.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    pub(crate) fn sums3(v: [__m256d; 3]) -> Vec3 {
        // [a0+a1, b0+b1, a2+a3, b2+b3] and [c0+c1, c0+c1, c2+c3, c2+c3].
        let ab = _mm256_hadd_pd(v[0], v[1]);
        let cc = _mm256_hadd_pd(v[2], v[2]);
        let lo = _mm256_permute2f128_pd(ab, cc, 0x20);
        let hi = _mm256_permute2f128_pd(ab, cc, 0x31);
        let mut out = Vec3::zeros();
        store3(&mut out, _mm256_add_pd(lo, hi));
        out
    }

    /// The sum of the four lanes.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    pub(crate) fn sum(v: __m256d) -> f64 {
        let mut lanes = [0.0f64; 4];
        // SAFETY: `lanes` holds four f64.
        unsafe { _mm256_storeu_pd(lanes.as_mut_ptr(), v) };
        (lanes[0] + lanes[1]) + (lanes[2] + lanes[3])
    }
}

/// Irregular, reproducible values for the kernels' unit tests: entry `i` of
/// stream `s`, in `[−13, 14)`.
#[cfg(test)]
pub(crate) fn test_value(i: usize, s: usize) -> f64 {
    (((i + 3) * (s + 7) * 2654435761usize) % 1000) as f64 / 37.0 - 13.0
}
