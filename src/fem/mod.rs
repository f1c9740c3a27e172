//! Co-rotational linear tetrahedral finite elements and system assembly.
//!
//! Each element keeps its rest shape: the gradients `g_a` of its four linear
//! shape functions and its volume `V`. At every step the element rotation `R`
//! is extracted from the deformation gradient `F = Σ_a x_a g_aᵀ`
//! ([`RotationMethod::Polar`]: polar decomposition by SVD with a sign fix,
//! defined for flat and inverted elements; [`RotationMethod::Qr`]: the
//! Gram–Schmidt frame of two edges, SOFA's "large" method). With
//! `u_b = Rᵀ x_b − X_b` the elastic force is
//!
//! ```text
//! f_a = −R (K₀ u)_a = −R · V σ(ε) g_a,   ε = sym(Rᵀ F − I),   σ = λ tr(ε) I + 2 μ ε
//! ```
//!
//! and the rotated stiffness block is
//! `R K₀_ab Rᵀ = V (λ r_a r_bᵀ + μ r_b r_aᵀ + μ (g_a·g_b) I)` with `r = R g`.
//!
//! [`assembly`] holds the 3×3-block sparse pattern, computed once per mesh
//! with an element-to-slot scatter map, and the in-place refill of
//! `A = M + hB + h²K`. Each element's share of the step (rotation, forces,
//! stiffness blocks) is `assemble_element`; `lanes` does the same for four
//! elements at a time, one per AVX2 register lane, where the CPU has AVX2 and
//! FMA (2.5× faster on the lens; the scalar path serves the elements left
//! over, [`RotationMethod::Qr`] and other CPUs).

pub mod assembly;
pub(crate) mod lanes;

use crate::math::{Mat3, Vec3, edge_frame, polar_rotation_fast, polar_rotation_near};

/// How element rotations are extracted from the deformation gradient.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum RotationMethod {
    /// Polar decomposition (scaled Newton iteration; SVD with a sign fix for flat and
    /// inverted elements), see [`crate::math::polar_rotation_fast`].
    #[default]
    Polar,
    /// Gram–Schmidt frame of the first two edges ("large" / QR variant): cheaper, not
    /// invariant to vertex order.
    Qr,
}

/// Rest-shape data of one linear tetrahedron.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Element {
    /// Vertex indices.
    pub nodes: [usize; 4],
    /// Shape-function gradients at rest.
    pub grads: [Vec3; 4],
    /// Rest volume.
    pub volume: f64,
    /// First Lamé parameter.
    pub lambda: f64,
    /// Shear modulus.
    pub mu: f64,
    /// Edge frame at rest (for [`RotationMethod::Qr`]).
    pub rest_frame: Mat3,
}

impl Element {
    /// Builds the rest data of a tetrahedron with rest positions `x` (positive orientation).
    pub fn new(nodes: [usize; 4], x: [Vec3; 4], lambda: f64, mu: f64) -> Self {
        let dm = Mat3::from_columns(&[x[1] - x[0], x[2] - x[0], x[3] - x[0]]);
        let volume = dm.determinant() / 6.0;
        let bm = dm.try_inverse().unwrap_or_else(Mat3::zeros);
        let g1 = bm.row(0).transpose();
        let g2 = bm.row(1).transpose();
        let g3 = bm.row(2).transpose();
        Self {
            nodes,
            grads: [-(g1 + g2 + g3), g1, g2, g3],
            volume,
            lambda,
            mu,
            rest_frame: edge_frame(&(x[1] - x[0]), &(x[2] - x[0])),
        }
    }

    /// Deformation gradient `F = Σ x_a g_aᵀ` for current positions `x`.
    #[inline]
    pub fn deformation_gradient(&self, x: &[Vec3; 4]) -> Mat3 {
        let mut f = Mat3::zeros();
        for a in 0..4 {
            f += x[a] * self.grads[a].transpose();
        }
        f
    }

    /// Element rotation for current positions `x`.
    #[inline]
    pub fn rotation(&self, method: RotationMethod, x: &[Vec3; 4]) -> Mat3 {
        match method {
            RotationMethod::Polar => polar_rotation_fast(&self.deformation_gradient(x)),
            RotationMethod::Qr => {
                edge_frame(&(x[1] - x[0]), &(x[2] - x[0])) * self.rest_frame.transpose()
            }
        }
    }

    /// Co-rotated stress `σ` for the rotated displacement gradient `Rᵀ F − I`.
    #[inline]
    pub fn stress(&self, r: &Mat3, f: &Mat3) -> Mat3 {
        let grad_u = r.transpose() * f - Mat3::identity();
        let eps = 0.5 * (grad_u + grad_u.transpose());
        Mat3::identity() * (self.lambda * eps.trace()) + eps * (2.0 * self.mu)
    }

    /// Elastic forces `f_a = −R V σ g_a` on the four nodes.
    #[inline]
    pub fn forces(&self, r: &Mat3, x: &[Vec3; 4]) -> [Vec3; 4] {
        let s = r * self.stress(r, &self.deformation_gradient(x)) * self.volume;
        self.grads.map(|g| -(s * g))
    }

    /// Strain energy `V (μ ε:ε + λ/2 tr(ε)²)` of the co-rotated linear model.
    pub fn energy(&self, r: &Mat3, x: &[Vec3; 4]) -> f64 {
        let grad_u = r.transpose() * self.deformation_gradient(x) - Mat3::identity();
        let eps = 0.5 * (grad_u + grad_u.transpose());
        self.volume * (self.mu * eps.norm_squared() + 0.5 * self.lambda * eps.trace().powi(2))
    }

    /// Rotated stiffness block `R K₀_ab Rᵀ` given the rotated gradients `rg = R g`.
    #[inline]
    pub fn stiffness_block(&self, rg: &[Vec3; 4], a: usize, b: usize) -> Mat3 {
        let v = self.volume;
        let (ra, rb) = (&rg[a], &rg[b]);
        (ra * rb.transpose()) * (v * self.lambda)
            + (rb * ra.transpose()) * (v * self.mu)
            + Mat3::identity() * (v * self.mu * self.grads[a].dot(&self.grads[b]))
    }
}

/// What every element of one assembly reads: positions, velocities and the
/// step's coefficients (stiffness blocks times `c_k`, the velocity term of
/// the stress times `c_v`).
#[derive(Clone, Copy)]
pub(crate) struct AssemblyInput<'a> {
    /// Node positions.
    pub x: &'a [Vec3],
    /// Node velocities.
    pub v: &'a [Vec3],
    /// Factor of the stiffness blocks (`h β + h²`).
    pub c_k: f64,
    /// Factor of the velocity term of the stress (`β + h`).
    pub c_v: f64,
}

/// Where an assembly adds to: the system's blocks and its right-hand side.
pub(crate) struct AssemblyOutput<'a> {
    /// One block per slot of the matrix's pattern.
    pub values: &'a mut [Mat3],
    /// One force per node.
    pub rhs: &'a mut [Vec3],
}

/// Adds one element to the system: its rotation into `rot` (for
/// [`RotationMethod::Polar`], the candidate nearest the `rot` it had when the
/// element is flat or inverted), its elastic and damping forces into
/// `out.rhs`, and its rotated stiffness blocks into `out.values` at `slots`
/// (block `(a, b)` at `slots[4a + b]`). [`lanes`] does the same four elements
/// at a time.
#[inline]
pub(crate) fn assemble_element(
    e: &Element,
    method: RotationMethod,
    input: AssemblyInput<'_>,
    slots: &[usize; 16],
    rot: &mut Mat3,
    out: &mut AssemblyOutput<'_>,
) {
    let AssemblyInput { x, v, c_k, c_v } = input;
    let xe = e.nodes.map(|n| x[n]);
    let ve = e.nodes.map(|n| v[n]);
    let fx = e.deformation_gradient(&xe);
    let r = match method {
        // Flat or inverted: the candidate nearest the last rotation.
        RotationMethod::Polar => polar_rotation_near(&fx, rot),
        RotationMethod::Qr => e.rotation(method, &xe),
    };
    *rot = r;
    let f = fx + e.deformation_gradient(&ve) * c_v;
    let s = r * e.stress(&r, &f) * e.volume;
    let rg = e.grads.map(|g| r * g);
    for a in 0..4 {
        out.rhs[e.nodes[a]] -= s * e.grads[a];
        // K_ba = K_abᵀ: each off-diagonal pair is computed once.
        out.values[slots[5 * a]] += e.stiffness_block(&rg, a, a) * c_k;
        for b in a + 1..4 {
            let k = e.stiffness_block(&rg, a, b) * c_k;
            out.values[slots[4 * a + b]] += k;
            out.values[slots[4 * b + a]] += k.transpose();
        }
    }
}
