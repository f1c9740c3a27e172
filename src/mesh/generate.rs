//! Mesh generators with a resolution knob.
//!
//! | generator | shape | paper-size call |
//! |---|---|---|
//! | [`box_mesh`] | axis-aligned box or beam, 6 tets per cell | – |
//! | [`ellipsoid`] | ellipsoidal lens, cube-to-ball mapped grid | `ellipsoid(LENS_RADII, 12)`: 1183 vertices / 5184 tets |
//! | [`eye_shell`] | spherical shell (cube-sphere prisms, 3 tets each) with an optional slit incision | `eye_shell(&EyeShell::default())`: ≈1200 vertices / ≈3500 tets |
//!
//! The paper's meshes are 1113 vertices / 4862 tets (lens) and 1249 vertices /
//! 3734 tets (eye); the defaults above land within about 10 % of both.
//!
//! All lengths are in metres.

use crate::error::{Result, SoftTissueError, check_positive};
use crate::math::{Vec3, v3};
use crate::mesh::{TetMesh, ValidateOptions};

/// Lens radii in metres (≈ 9.5 × 9.5 × 4.5 mm).
pub const LENS_RADII: [f64; 3] = [4.75e-3, 4.75e-3, 2.25e-3];

fn check_cells(name: &'static str, n: usize) -> Result<()> {
    if n == 0 || n > 512 {
        return Err(SoftTissueError::InvalidParameter {
            name,
            value: n as f64,
            reason: "cell count must be in 1..=512",
        });
    }
    Ok(())
}

/// Splits the hexahedral cell with corner vertex ids `c[i][j][k]` into 6 tetrahedra
/// (Kuhn subdivision along the main diagonal, conforming on structured grids).
fn kuhn_split(c: &[[[usize; 2]; 2]; 2], out: &mut Vec<[usize; 4]>) {
    const PERMS: [[usize; 3]; 6] = [
        [0, 1, 2],
        [0, 2, 1],
        [1, 0, 2],
        [1, 2, 0],
        [2, 0, 1],
        [2, 1, 0],
    ];
    for p in PERMS {
        let mut idx = [0usize; 3];
        let mut tet = [c[0][0][0]; 4];
        for (s, &axis) in p.iter().enumerate() {
            idx[axis] = 1;
            tet[s + 1] = c[idx[0]][idx[1]][idx[2]];
        }
        out.push(tet);
    }
}

fn grid(cells: [usize; 3], map: impl Fn([f64; 3]) -> Vec3) -> (Vec<Vec3>, Vec<[usize; 4]>) {
    let [nx, ny, nz] = cells;
    let id = |i: usize, j: usize, k: usize| (k * (ny + 1) + j) * (nx + 1) + i;
    let mut pos = Vec::with_capacity((nx + 1) * (ny + 1) * (nz + 1));
    for k in 0..=nz {
        for j in 0..=ny {
            for i in 0..=nx {
                pos.push(map([
                    i as f64 / nx as f64,
                    j as f64 / ny as f64,
                    k as f64 / nz as f64,
                ]));
            }
        }
    }
    let mut tets = Vec::with_capacity(6 * nx * ny * nz);
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let mut c = [[[0; 2]; 2]; 2];
                for (a, ca) in c.iter_mut().enumerate() {
                    for (b, cb) in ca.iter_mut().enumerate() {
                        for (d, cd) in cb.iter_mut().enumerate() {
                            *cd = id(i + a, j + b, k + d);
                        }
                    }
                }
                kuhn_split(&c, &mut tets);
            }
        }
    }
    (pos, tets)
}

fn oriented(positions: Vec<Vec3>, tets: Vec<[usize; 4]>) -> Result<TetMesh> {
    TetMesh::with_options(
        positions,
        tets,
        ValidateOptions {
            reorient: true,
            ..Default::default()
        },
    )
}

/// An axis-aligned box from `min` to `max` with `cells` hexahedral cells per axis,
/// each split into 6 tetrahedra. Use a long thin box for a beam.
pub fn box_mesh(min: Vec3, max: Vec3, cells: [usize; 3]) -> Result<TetMesh> {
    for (name, n) in ["cells.x", "cells.y", "cells.z"].into_iter().zip(cells) {
        check_cells(name, n)?;
    }
    let size = max - min;
    for (name, s) in ["size.x", "size.y", "size.z"].into_iter().zip(size.iter()) {
        check_positive(name, *s)?;
    }
    let (pos, tets) = grid(cells, |u| {
        min + v3(u[0] * size.x, u[1] * size.y, u[2] * size.z)
    });
    oriented(pos, tets)
}

/// An ellipsoid with semi-axes `radii`, meshed by mapping a structured grid of
/// the cube onto the ball (`x' = x·√(1 − y²/2 − z²/2 + y²z²/3)` and cyclic).
/// `cells` is the number of cells along the longest axis; the others get
/// proportionally fewer (at least 2).
pub fn ellipsoid(radii: [f64; 3], cells: usize) -> Result<TetMesh> {
    check_cells("cells", cells)?;
    for (name, r) in ["radii.x", "radii.y", "radii.z"].into_iter().zip(radii) {
        check_positive(name, r)?;
    }
    let rmax = radii.iter().cloned().fold(0.0, f64::max);
    let n = radii.map(|r| ((cells as f64 * r / rmax).round() as usize).max(2));
    let (pos, tets) = grid(n, |u| {
        let [x, y, z] = u.map(|t| 2.0 * t - 1.0);
        let (x2, y2, z2) = (x * x, y * y, z * z);
        v3(
            radii[0] * x * (1.0 - y2 / 2.0 - z2 / 2.0 + y2 * z2 / 3.0).max(0.0).sqrt(),
            radii[1] * y * (1.0 - z2 / 2.0 - x2 / 2.0 + z2 * x2 / 3.0).max(0.0).sqrt(),
            radii[2] * z * (1.0 - x2 / 2.0 - y2 / 2.0 + x2 * y2 / 3.0).max(0.0).sqrt(),
        )
    });
    oriented(pos, tets)
}

/// A slit cut through a spherical shell, centred on a direction given in
/// spherical angles about the +z (anterior) axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Incision {
    /// Polar angle of the slit's centre line from +z, radians.
    pub polar: f64,
    /// Azimuth of the slit's centre, radians (0 = +x).
    pub azimuth: f64,
    /// Length of the slit along the azimuthal direction, metres.
    pub length: f64,
    /// Width of the slit across it, metres: every element row the band
    /// `polar ± width / 2` touches is removed, so the slit is at least one row wide.
    pub width: f64,
}

impl Default for Incision {
    fn default() -> Self {
        Self {
            polar: 30f64.to_radians(),
            azimuth: std::f64::consts::FRAC_PI_2,
            length: 6.5e-3,
            width: 2.0e-3,
        }
    }
}

/// Parameters of [`eye_shell`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EyeShell {
    /// Outer radius, metres.
    pub radius: f64,
    /// Shell thickness, metres.
    pub thickness: f64,
    /// Cells along each edge of the cube-sphere faces (resolution knob).
    pub cells: usize,
    /// Prism layers through the thickness.
    pub layers: usize,
    /// Optional slit incision.
    pub incision: Option<Incision>,
}

impl Default for EyeShell {
    fn default() -> Self {
        Self {
            radius: 12e-3,
            thickness: 1e-3,
            cells: 10,
            layers: 1,
            incision: Some(Incision::default()),
        }
    }
}

/// Splits a triangular prism (bottom `p[0..3]`, top `p[3..6]`, `p[i+3]` above `p[i]`)
/// into three tetrahedra whose quad-face diagonals run through each face's smallest
/// vertex id, which makes neighbouring prisms conform.
fn split_prism(p: [usize; 6], out: &mut Vec<[usize; 4]>) {
    const ROT: [[usize; 6]; 6] = [
        [0, 1, 2, 3, 4, 5],
        [1, 2, 0, 4, 5, 3],
        [2, 0, 1, 5, 3, 4],
        [3, 5, 4, 0, 2, 1],
        [4, 3, 5, 1, 0, 2],
        [5, 4, 3, 2, 1, 0],
    ];
    let m = (0..6).min_by_key(|&i| p[i]).unwrap_or(0);
    let v = ROT[m].map(|i| p[i]);
    if v[1].min(v[5]) < v[2].min(v[4]) {
        out.extend([
            [v[0], v[1], v[2], v[5]],
            [v[0], v[1], v[5], v[4]],
            [v[0], v[4], v[5], v[3]],
        ]);
    } else {
        out.extend([
            [v[0], v[1], v[2], v[4]],
            [v[0], v[4], v[2], v[5]],
            [v[0], v[4], v[5], v[3]],
        ]);
    }
}

/// A spherical shell (the sclera) centred at the origin, meshed as a
/// cube-sphere surface extruded into prism layers, each prism split into 3
/// tetrahedra. With an [`Incision`], the elements whose centre lies inside
/// the slit are removed through the whole thickness.
pub fn eye_shell(p: &EyeShell) -> Result<TetMesh> {
    check_positive("radius", p.radius)?;
    check_positive("thickness", p.thickness)?;
    if p.thickness >= p.radius {
        return Err(SoftTissueError::InvalidParameter {
            name: "thickness",
            value: p.thickness,
            reason: "must be smaller than the radius",
        });
    }
    check_cells("cells", p.cells)?;
    check_cells("layers", p.layers)?;
    if let Some(inc) = &p.incision {
        check_positive("incision.length", inc.length)?;
        check_positive("incision.width", inc.width)?;
        crate::error::check_range("incision.polar", inc.polar, 0.0, std::f64::consts::PI)?;
    }
    let n = p.cells;
    // Surface lattice points of the cube {0..n}³.
    let mut lattice = std::collections::HashMap::new();
    let mut dirs: Vec<Vec3> = Vec::new();
    let on_surface =
        |i: usize, j: usize, k: usize| i == 0 || j == 0 || k == 0 || i == n || j == n || k == n;
    for k in 0..=n {
        for j in 0..=n {
            for i in 0..=n {
                if on_surface(i, j, k) {
                    let c = [i, j, k].map(|t| {
                        let u = 2.0 * t as f64 / n as f64 - 1.0;
                        (u * std::f64::consts::FRAC_PI_4).tan()
                    });
                    lattice.insert([i, j, k], dirs.len());
                    dirs.push(v3(c[0], c[1], c[2]).normalize());
                }
            }
        }
    }
    // Quads of the six faces; the incision removes whole quads (both triangles),
    // so the slit has straight walls.
    let mut tris: Vec<[usize; 3]> = Vec::new();
    let r_mid = p.radius - 0.5 * p.thickness;
    // A quad is cut when the slit's band (polar angle ± half the width) overlaps
    // the quad's polar range and the quad's centre is within half the length.
    let in_slit = |q: &[usize; 4]| {
        p.incision.as_ref().is_some_and(|inc| {
            let polar = |d: &Vec3| d.z.clamp(-1.0, 1.0).acos();
            let (lo, hi) = q
                .iter()
                .map(|&v| polar(&dirs[v]))
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
                    (a.min(x), b.max(x))
                });
            let half = 0.5 * inc.width / r_mid;
            let c = (dirs[q[0]] + dirs[q[1]] + dirs[q[2]] + dirs[q[3]]).normalize();
            let dphi = (c.y.atan2(c.x) - inc.azimuth + std::f64::consts::PI)
                .rem_euclid(2.0 * std::f64::consts::PI)
                - std::f64::consts::PI;
            let along = dphi.abs() * r_mid * inc.polar.sin();
            lo <= inc.polar + half && hi >= inc.polar - half && along < 0.5 * inc.length
        })
    };
    for axis in 0..3 {
        for side in [0, n] {
            for a in 0..n {
                for b in 0..n {
                    let corner = |da: usize, db: usize| {
                        let mut c = [0; 3];
                        c[axis] = side;
                        c[(axis + 1) % 3] = a + da;
                        c[(axis + 2) % 3] = b + db;
                        lattice[&c]
                    };
                    let q = [corner(0, 0), corner(1, 0), corner(1, 1), corner(0, 1)];
                    if in_slit(&q) {
                        continue;
                    }
                    let (t1, t2) = if (a + b) % 2 == 0 {
                        ([q[0], q[1], q[2]], [q[0], q[2], q[3]])
                    } else {
                        ([q[0], q[1], q[3]], [q[1], q[2], q[3]])
                    };
                    tris.push(t1);
                    tris.push(t2);
                }
            }
        }
    }
    // Compact the surface vertices that are still used.
    let mut remap = vec![usize::MAX; dirs.len()];
    let mut used_dirs = Vec::new();
    for t in &mut tris {
        for v in t.iter_mut() {
            if remap[*v] == usize::MAX {
                remap[*v] = used_dirs.len();
                used_dirs.push(dirs[*v]);
            }
            *v = remap[*v];
        }
    }
    let ns = used_dirs.len();
    let mut positions = Vec::with_capacity(ns * (p.layers + 1));
    for l in 0..=p.layers {
        let r = p.radius - p.thickness + p.thickness * l as f64 / p.layers as f64;
        positions.extend(used_dirs.iter().map(|d| d * r));
    }
    let mut tets = Vec::with_capacity(3 * tris.len() * p.layers);
    for l in 0..p.layers {
        for t in &tris {
            split_prism(
                [
                    l * ns + t[0],
                    l * ns + t[1],
                    l * ns + t[2],
                    (l + 1) * ns + t[0],
                    (l + 1) * ns + t[1],
                    (l + 1) * ns + t[2],
                ],
                &mut tets,
            );
        }
    }
    oriented(positions, tets)
}
