//! Tetrahedral meshes: storage, validation, boundary surface, generators and loaders.
//!
//! A [`TetMesh`] is a list of `f64` vertex positions and a list of
//! tetrahedra (four vertex indices each, positive orientation). Every
//! constructor validates its input and returns a [`SoftTissueError`] that
//! names the offending element or vertex:
//!
//! - empty mesh, non-finite coordinates, unused vertices;
//! - vertex index out of range, repeated vertex inside a tetrahedron;
//! - zero volume (degenerate) or negative volume (inverted) elements.
//!   Inverted elements can be fixed on load with
//!   [`ValidateOptions::reorient`].
//!
//! [`TetMesh::surface`] extracts the outward boundary triangles together with
//! the surface-to-volume vertex map used by collision detection and
//! rendering.
//!
//! Generators with a resolution knob live in [`generate`]: a box (beam), an
//! ellipsoidal lens and a spherical eye shell with a slit incision. Loaders for
//! Gmsh MSH 4.1 (ASCII and binary) and TetGen `.node`/`.ele` live in [`io`].

pub mod generate;
pub mod io;
mod msh;

use std::collections::HashMap;

use crate::error::{Result, SoftTissueError};
use crate::math::Vec3;

/// How strictly [`TetMesh::with_options`] checks its input.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ValidateOptions {
    /// Swap two vertices of negatively oriented tetrahedra instead of failing.
    pub reorient: bool,
    /// A tetrahedron whose `6·|V|` is below `min_relative_volume · ℓ³`
    /// (ℓ its longest edge) is degenerate.
    pub min_relative_volume: f64,
}

impl Default for ValidateOptions {
    fn default() -> Self {
        Self {
            reorient: false,
            min_relative_volume: 1e-10,
        }
    }
}

/// A validated linear tetrahedral mesh.
#[derive(Debug, Clone, PartialEq)]
pub struct TetMesh {
    positions: Vec<Vec3>,
    tets: Vec<[usize; 4]>,
}

/// The outward boundary of a [`TetMesh`].
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Surface {
    /// Volume-vertex index of each surface vertex.
    pub vertices: Vec<usize>,
    /// Triangles as indices into [`Surface::vertices`], counter-clockwise seen from outside.
    pub triangles: Vec<[usize; 3]>,
    /// For each volume vertex, its surface index, or `u32::MAX` for interior vertices.
    pub volume_to_surface: Vec<u32>,
    /// The tetrahedron each triangle bounds.
    pub triangle_tets: Vec<usize>,
}

impl Surface {
    /// Triangles expressed directly in volume-vertex indices.
    pub fn volume_triangles(&self) -> impl Iterator<Item = [usize; 3]> + '_ {
        self.triangles.iter().map(|t| {
            [
                self.vertices[t[0]],
                self.vertices[t[1]],
                self.vertices[t[2]],
            ]
        })
    }
}

/// Local faces of a positively oriented tetrahedron, each counter-clockwise
/// seen from outside.
pub const TET_FACES: [[usize; 3]; 4] = [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]];

/// Signed volume of the tetrahedron `(a, b, c, d)`.
pub fn signed_volume(a: Vec3, b: Vec3, c: Vec3, d: Vec3) -> f64 {
    (b - a).cross(&(c - a)).dot(&(d - a)) / 6.0
}

impl TetMesh {
    /// Builds and validates a mesh with the default options (no re-orientation).
    pub fn new(positions: Vec<Vec3>, tets: Vec<[usize; 4]>) -> Result<Self> {
        Self::with_options(positions, tets, ValidateOptions::default())
    }

    /// Builds and validates a mesh.
    pub fn with_options(
        positions: Vec<Vec3>,
        mut tets: Vec<[usize; 4]>,
        options: ValidateOptions,
    ) -> Result<Self> {
        let mrv = options.min_relative_volume;
        if !(mrv.is_finite() && (0.0..1.0).contains(&mrv)) {
            return Err(SoftTissueError::InvalidParameter {
                name: "min_relative_volume",
                value: mrv,
                reason: "must be finite and in [0, 1)",
            });
        }
        if positions.is_empty() {
            return Err(SoftTissueError::EmptyMesh("no vertices"));
        }
        if tets.is_empty() {
            return Err(SoftTissueError::EmptyMesh("no tetrahedra"));
        }
        for (i, p) in positions.iter().enumerate() {
            if !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()) {
                return Err(SoftTissueError::NonFiniteVertex {
                    vertex: i,
                    value: [p.x, p.y, p.z],
                });
            }
        }
        let mut used = vec![false; positions.len()];
        for (t, tet) in tets.iter_mut().enumerate() {
            for (k, &v) in tet.iter().enumerate() {
                if v >= positions.len() {
                    return Err(SoftTissueError::IndexOutOfRange {
                        tet: t,
                        index: v,
                        len: positions.len(),
                    });
                }
                if tet[..k].contains(&v) {
                    return Err(SoftTissueError::RepeatedVertex { tet: t, vertex: v });
                }
            }
            let [a, b, c, d] = tet.map(|v| positions[v]);
            let vol = signed_volume(a, b, c, d);
            let longest = [b - a, c - a, d - a, c - b, d - b, d - c]
                .iter()
                .map(|e| e.norm())
                .fold(0.0, f64::max);
            if !vol.is_finite() || 6.0 * vol.abs() <= options.min_relative_volume * longest.powi(3)
            {
                return Err(SoftTissueError::DegenerateTet {
                    tet: t,
                    volume: vol,
                });
            }
            if vol < 0.0 {
                if options.reorient {
                    tet.swap(2, 3);
                } else {
                    return Err(SoftTissueError::InvertedTet {
                        tet: t,
                        volume: vol,
                    });
                }
            }
            for &v in tet.iter() {
                used[v] = true;
            }
        }
        if let Some(vertex) = used.iter().position(|u| !u) {
            return Err(SoftTissueError::UnusedVertex { vertex });
        }
        Ok(Self { positions, tets })
    }

    /// Vertex positions.
    pub fn positions(&self) -> &[Vec3] {
        &self.positions
    }

    /// Tetrahedra (positively oriented).
    pub fn tets(&self) -> &[[usize; 4]] {
        &self.tets
    }

    /// Number of vertices.
    pub fn num_vertices(&self) -> usize {
        self.positions.len()
    }

    /// Number of tetrahedra.
    pub fn num_tets(&self) -> usize {
        self.tets.len()
    }

    /// Signed volume of tetrahedron `t`.
    pub fn tet_volume(&self, t: usize) -> f64 {
        let [a, b, c, d] = self.tets[t].map(|v| self.positions[v]);
        signed_volume(a, b, c, d)
    }

    /// Total volume.
    pub fn volume(&self) -> f64 {
        (0..self.tets.len()).map(|t| self.tet_volume(t)).sum()
    }

    /// Centroid of tetrahedron `t`.
    pub fn tet_centroid(&self, t: usize) -> Vec3 {
        self.tets[t]
            .iter()
            .map(|&v| self.positions[v])
            .sum::<Vec3>()
            / 4.0
    }

    /// Shortest edge length over all tetrahedra.
    pub fn min_edge_length(&self) -> f64 {
        self.edge_lengths().fold(f64::INFINITY, f64::min)
    }

    /// Longest edge length over all tetrahedra.
    pub fn max_edge_length(&self) -> f64 {
        self.edge_lengths().fold(0.0, f64::max)
    }

    fn edge_lengths(&self) -> impl Iterator<Item = f64> + '_ {
        self.tets.iter().flat_map(move |t| {
            const E: [(usize, usize); 6] = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)];
            E.iter()
                .map(move |&(a, b)| (self.positions[t[a]] - self.positions[t[b]]).norm())
        })
    }

    /// Axis-aligned bounds `(min, max)`.
    pub fn bounds(&self) -> (Vec3, Vec3) {
        let mut lo = Vec3::repeat(f64::INFINITY);
        let mut hi = Vec3::repeat(f64::NEG_INFINITY);
        for p in &self.positions {
            lo = lo.inf(p);
            hi = hi.sup(p);
        }
        (lo, hi)
    }

    /// Returns a copy moved by `offset`.
    pub fn translated(mut self, offset: Vec3) -> Self {
        for p in &mut self.positions {
            *p += offset;
        }
        self
    }

    /// Returns a copy rotated by `rotation` about the origin (orientation is kept).
    pub fn rotated(mut self, rotation: &nalgebra::Rotation3<f64>) -> Self {
        for p in &mut self.positions {
            *p = rotation * *p;
        }
        self
    }

    /// Extracts the outward boundary triangles (faces used by exactly one tetrahedron).
    pub fn surface(&self) -> Surface {
        let mut count: HashMap<[usize; 3], (usize, [usize; 3], usize)> = HashMap::new();
        for (ti, tet) in self.tets.iter().enumerate() {
            for f in TET_FACES {
                let tri = [tet[f[0]], tet[f[1]], tet[f[2]]];
                let mut key = tri;
                key.sort_unstable();
                count
                    .entry(key)
                    .and_modify(|e| e.0 += 1)
                    .or_insert((1, tri, ti));
            }
        }
        let mut boundary: Vec<([usize; 3], usize)> = count
            .into_values()
            .filter(|(n, _, _)| *n == 1)
            .map(|(_, t, ti)| (t, ti))
            .collect();
        boundary.sort_unstable();
        let triangle_tets = boundary.iter().map(|b| b.1).collect();
        let mut volume_to_surface = vec![u32::MAX; self.positions.len()];
        let mut vertices = Vec::new();
        let triangles = boundary
            .iter()
            .map(|(tri, _)| {
                tri.map(|v| {
                    if volume_to_surface[v] == u32::MAX {
                        volume_to_surface[v] = vertices.len() as u32;
                        vertices.push(v);
                    }
                    volume_to_surface[v] as usize
                })
            })
            .collect();
        Surface {
            vertices,
            triangles,
            volume_to_surface,
            triangle_tets,
        }
    }

    /// Node adjacency: for every vertex, the sorted list of vertices sharing a tetrahedron
    /// with it (itself included).
    pub fn node_adjacency(&self) -> Vec<Vec<usize>> {
        let mut adj = vec![Vec::new(); self.positions.len()];
        for tet in &self.tets {
            for &a in tet {
                for &b in tet {
                    adj[a].push(b);
                }
            }
        }
        for list in &mut adj {
            list.sort_unstable();
            list.dedup();
        }
        adj
    }
}
