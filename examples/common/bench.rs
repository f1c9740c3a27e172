//! Bench fixtures shared by the benchmarks, the examples and the tests (not
//! library API): the paper-size lens and synthetic contacts on it. No Bevy types.

use bevy_soft_tissue::body::{BodySettings, DeformableBody};
use bevy_soft_tissue::contact::{Contact, ContactOther, ContactSide, tangent_basis};
use bevy_soft_tissue::error::Result;
use bevy_soft_tissue::material::{StiffnessField, TissueMaterial, Transition};
use bevy_soft_tissue::math::{Vec3, v3};
use bevy_soft_tissue::mesh::generate::{self, LENS_RADII};
use bevy_soft_tissue::solver::PreconditionerKind;

/// The lens material of the benchmarks: 5 kPa periphery, nucleus 5× stiffer
/// (smooth transition), ν = 0.45.
pub fn lens_material() -> TissueMaterial {
    TissueMaterial::new(1000.0, 5e3, 0.45).with_stiffness(StiffnessField::Radial {
        center: Vec3::zeros(),
        radii: Vec3::from(LENS_RADII),
        core_radius: 0.55,
        factor: 5.0,
        transition: Transition::Smooth { width: 0.2 },
    })
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

/// `n` contacts of body 0 with tool 0 at the surface vertices nearest to the
/// body's highest point, with the given normal and friction.
pub fn pole_contacts(body: &DeformableBody, n: usize, normal: Vec3, mu: f64) -> Vec<Contact> {
    let x = body.positions();
    let top = body.surface().vertices.iter().map(|&v| x[v]).fold(
        v3(0.0, 0.0, f64::NEG_INFINITY),
        |a, p| {
            if p.z > a.z { p } else { a }
        },
    );
    let mut verts: Vec<usize> = body.surface().vertices.clone();
    verts.sort_by(|&a, &b| (x[a] - top).norm().total_cmp(&(x[b] - top).norm()));
    let normal = normal.normalize();
    verts
        .iter()
        .take(n)
        .map(|&v| Contact {
            a: ContactSide {
                body: 0,
                nodes: [v as u32, 0, 0],
                weights: [1.0, 0.0, 0.0],
            },
            other: ContactOther::Tool(0),
            normal,
            tangents: tangent_basis(&normal),
            gap: -1e-5,
            slip: [0.0, 0.0],
            mu,
            point: x[v],
            force: Vec3::zeros(),
        })
        .collect()
}
