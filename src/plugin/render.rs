//! Render sync (feature `viewer`): a Bevy `Mesh` of each body's surface,
//! positions and normals rewritten in place after every step, and meshes for tools.
//!
//! Bodies get a smooth-shaded surface mesh with per-vertex colours
//! ([`BodyColoring`]): by default the element stiffness around each vertex,
//! mapped from blue (softest) to red (stiffest), so a stiff nucleus shows.

use bevy::asset::RenderAssetUsages;
use bevy::ecs::intern::Interned;
use bevy::ecs::schedule::ScheduleLabel;
use bevy::mesh::{Indices, PrimitiveTopology, VertexAttributeValues};
use bevy::prelude::*;

use super::components::{SoftBody, Tool};
use super::sets::SoftTissueSystems;
use crate::contact::ToolShape;

/// How a body's render mesh is coloured.
#[derive(Component, Debug, Clone, Copy, PartialEq)]
pub enum BodyColoring {
    /// One colour, with transparency (for example the eye shell around the lens).
    Solid(Color),
    /// Element stiffness around each vertex, blue (soft) to red (stiff).
    Stiffness,
}

/// The render mesh of a body's stiff core (the boundary of its stiffer elements),
/// drawn inside the translucent surface when the body is coloured by stiffness.
#[derive(Component, Debug, Clone)]
pub struct CoreMesh {
    /// The body entity.
    pub body: Entity,
    /// Volume vertices of the core boundary.
    pub vertices: Vec<usize>,
    /// Triangles as indices into `vertices`.
    pub triangles: Vec<[usize; 3]>,
    /// The mesh asset.
    pub handle: Handle<Mesh>,
}

/// Boundary of the elements stiffer than the geometric mean of the softest and
/// stiffest: `(vertices, triangles)`; empty for a uniform body.
fn core_surface(body: &SoftBody) -> (Vec<usize>, Vec<[usize; 3]>) {
    let young = body.element_young();
    let (lo, hi) = young
        .iter()
        .fold((f64::INFINITY, 0.0f64), |(a, b), &e| (a.min(e), b.max(e)));
    if hi <= lo * 1.5 {
        return (Vec::new(), Vec::new());
    }
    let threshold = (lo * hi).sqrt();
    let mut faces: std::collections::HashMap<[usize; 3], (usize, [usize; 3])> =
        std::collections::HashMap::new();
    for (t, tet) in body.mesh().tets().iter().enumerate() {
        if young[t] < threshold {
            continue;
        }
        for f in crate::mesh::TET_FACES {
            let tri = [tet[f[0]], tet[f[1]], tet[f[2]]];
            let mut key = tri;
            key.sort_unstable();
            faces
                .entry(key)
                .and_modify(|e| e.0 += 1)
                .or_insert((1, tri));
        }
    }
    let mut map = std::collections::HashMap::new();
    let mut vertices = Vec::new();
    let mut triangles = Vec::new();
    let mut list: Vec<[usize; 3]> = faces
        .into_values()
        .filter(|e| e.0 == 1)
        .map(|e| e.1)
        .collect();
    list.sort_unstable();
    for tri in list {
        triangles.push(tri.map(|v| {
            *map.entry(v).or_insert_with(|| {
                vertices.push(v);
                vertices.len() - 1
            })
        }));
    }
    (vertices, triangles)
}

/// Links a body to its render mesh.
#[derive(Component, Debug, Clone)]
pub struct SurfaceMesh {
    /// The mesh asset.
    pub handle: Handle<Mesh>,
}

/// Adds render meshes and keeps them in sync.
pub struct RenderSyncPlugin {
    pub(super) schedule: Interned<dyn ScheduleLabel>,
}

impl Plugin for RenderSyncPlugin {
    fn build(&self, app: &mut App) {
        // Headless apps (no asset server or PBR) simply skip render sync.
        let rendering =
            resource_exists::<Assets<Mesh>>.and_then(resource_exists::<Assets<StandardMaterial>>);
        app.add_systems(
            Update,
            (attach_body_meshes, attach_tool_meshes, drop_orphan_cores).run_if(rendering),
        )
        .add_systems(
            self.schedule,
            update_body_meshes
                .in_set(SoftTissueSystems::Sync)
                .run_if(resource_exists::<Assets<Mesh>>),
        );
    }
}

fn stiffness_colors(body: &SoftBody) -> Vec<[f32; 4]> {
    let mesh = body.mesh();
    let young = body.element_young();
    let mut sum = vec![0.0; mesh.num_vertices()];
    let mut count = vec![0.0; mesh.num_vertices()];
    for (t, tet) in mesh.tets().iter().enumerate() {
        for &v in tet {
            sum[v] += young[t].ln();
            count[v] += 1.0;
        }
    }
    let (lo, hi) = young
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &e| {
            (a.min(e.ln()), b.max(e.ln()))
        });
    body.surface()
        .vertices
        .iter()
        .map(|&v| {
            let s = if hi > lo {
                ((sum[v] / count[v] - lo) / (hi - lo)) as f32
            } else {
                0.0
            };
            let c =
                Color::srgb(0.25 + 0.75 * s, 0.35 * (1.0 - s) + 0.15, 1.0 - 0.8 * s).to_linear();
            [c.red, c.green, c.blue, 1.0]
        })
        .collect()
}

fn surface_positions(body: &SoftBody) -> Vec<[f32; 3]> {
    body.surface()
        .vertices
        .iter()
        .map(|&v| {
            let p = body.positions()[v];
            [p.x as f32, p.y as f32, p.z as f32]
        })
        .collect()
}

fn normals(pos: &[[f32; 3]], tris: &[[usize; 3]]) -> Vec<[f32; 3]> {
    let mut n = vec![Vec3::ZERO; pos.len()];
    for t in tris {
        let [a, b, c] = t.map(|i| Vec3::from(pos[i]));
        let f = (b - a).cross(c - a);
        for &i in t {
            n[i] += f;
        }
    }
    n.iter().map(|v| v.normalize_or_zero().to_array()).collect()
}

#[allow(clippy::type_complexity)]
fn attach_body_meshes(
    mut commands: Commands,
    bodies: Query<(Entity, &SoftBody, Option<&BodyColoring>), Without<SurfaceMesh>>,
    mut meshes: ResMut<Assets<Mesh>>,
    mut materials: ResMut<Assets<StandardMaterial>>,
) {
    for (e, body, coloring) in &bodies {
        let pos = surface_positions(body);
        let tris = &body.surface().triangles;
        let idx: Vec<u32> = tris.iter().flat_map(|t| t.map(|i| i as u32)).collect();
        let coloring = coloring.copied().unwrap_or(BodyColoring::Stiffness);
        let colors = match coloring {
            BodyColoring::Stiffness => stiffness_colors(body),
            BodyColoring::Solid(_) => vec![[1.0; 4]; pos.len()],
        };
        let mesh = Mesh::new(
            PrimitiveTopology::TriangleList,
            RenderAssetUsages::default(),
        )
        .with_inserted_attribute(Mesh::ATTRIBUTE_NORMAL, normals(&pos, tris))
        .with_inserted_attribute(Mesh::ATTRIBUTE_POSITION, pos)
        .with_inserted_attribute(Mesh::ATTRIBUTE_COLOR, colors)
        .with_inserted_indices(Indices::U32(idx));
        let handle = meshes.add(mesh);
        let (core_vertices, core_triangles) = match coloring {
            BodyColoring::Stiffness => core_surface(body),
            BodyColoring::Solid(_) => (Vec::new(), Vec::new()),
        };
        let has_core = !core_triangles.is_empty();
        if has_core {
            let pos: Vec<[f32; 3]> = core_vertices
                .iter()
                .map(|&v| body.positions()[v].map(|c| c as f32).into())
                .collect();
            let idx: Vec<u32> = core_triangles
                .iter()
                .flat_map(|t| t.map(|i| i as u32))
                .collect();
            let core = Mesh::new(
                PrimitiveTopology::TriangleList,
                RenderAssetUsages::default(),
            )
            .with_inserted_attribute(Mesh::ATTRIBUTE_NORMAL, normals(&pos, &core_triangles))
            .with_inserted_attribute(Mesh::ATTRIBUTE_POSITION, pos)
            .with_inserted_indices(Indices::U32(idx));
            let core_handle = meshes.add(core);
            commands.spawn((
                CoreMesh {
                    body: e,
                    vertices: core_vertices,
                    triangles: core_triangles,
                    handle: core_handle.clone(),
                },
                Mesh3d(core_handle),
                MeshMaterial3d(materials.add(StandardMaterial {
                    base_color: Color::srgb(0.85, 0.15, 0.1),
                    perceptual_roughness: 0.5,
                    ..Default::default()
                })),
                Transform::default(),
            ));
        }
        let material = match coloring {
            BodyColoring::Solid(c) => StandardMaterial {
                base_color: c,
                alpha_mode: if c.alpha() < 1.0 {
                    AlphaMode::Blend
                } else {
                    AlphaMode::Opaque
                },
                double_sided: true,
                cull_mode: None,
                perceptual_roughness: 0.6,
                ..Default::default()
            },
            BodyColoring::Stiffness => StandardMaterial {
                perceptual_roughness: 0.5,
                // See the stiff core through a translucent surface.
                base_color: Color::srgba(1.0, 1.0, 1.0, if has_core { 0.45 } else { 1.0 }),
                alpha_mode: if has_core {
                    AlphaMode::Blend
                } else {
                    AlphaMode::Opaque
                },
                ..Default::default()
            },
        };
        commands.entity(e).insert((
            SurfaceMesh {
                handle: handle.clone(),
            },
            Mesh3d(handle),
            MeshMaterial3d(materials.add(material)),
        ));
    }
}

fn update_body_meshes(
    bodies: Query<(&SoftBody, &SurfaceMesh)>,
    cores: Query<&CoreMesh>,
    mut meshes: ResMut<Assets<Mesh>>,
    mut normals: Local<Vec<Vec3>>,
) {
    for core in &cores {
        let (Ok((body, _)), Some(mut mesh)) = (bodies.get(core.body), meshes.get_mut(&core.handle))
        else {
            continue;
        };
        write_positions(
            &mut mesh,
            body.positions(),
            &core.vertices,
            &core.triangles,
            &mut normals,
        );
    }
    for (body, sm) in &bodies {
        let Some(mut mesh) = meshes.get_mut(&sm.handle) else {
            continue;
        };
        let surface = body.surface();
        write_positions(
            &mut mesh,
            body.positions(),
            &surface.vertices,
            &surface.triangles,
            &mut normals,
        );
    }
}

/// Rewrites a mesh's positions (`x` at `vertices`) and smooth normals in
/// place; `tris` index into `vertices`. `n` is scratch (no allocation once
/// it has grown to the largest mesh).
fn write_positions(
    mesh: &mut Mesh,
    x: &[crate::math::Vec3],
    vertices: &[usize],
    tris: &[[usize; 3]],
    n: &mut Vec<Vec3>,
) {
    let p = |i: usize| {
        let q = x[vertices[i]];
        Vec3::new(q.x as f32, q.y as f32, q.z as f32)
    };
    n.clear();
    n.resize(vertices.len(), Vec3::ZERO);
    for t in tris {
        let [a, b, c] = t.map(p);
        let f = (b - a).cross(c - a);
        for &i in t {
            n[i] += f;
        }
    }
    if let Some(VertexAttributeValues::Float32x3(pa)) = mesh.attribute_mut(Mesh::ATTRIBUTE_POSITION)
    {
        for (i, out) in pa.iter_mut().enumerate().take(vertices.len()) {
            *out = p(i).to_array();
        }
    }
    if let Some(VertexAttributeValues::Float32x3(na)) = mesh.attribute_mut(Mesh::ATTRIBUTE_NORMAL) {
        for (out, v) in na.iter_mut().zip(n.iter()) {
            *out = v.normalize_or_zero().to_array();
        }
    }
}

/// Despawns core meshes whose body is gone.
fn drop_orphan_cores(
    mut commands: Commands,
    cores: Query<(Entity, &CoreMesh)>,
    bodies: Query<(), With<SoftBody>>,
) {
    for (e, core) in &cores {
        if bodies.get(core.body).is_err() {
            commands.entity(e).despawn();
        }
    }
}

/// A render mesh for a tool shape, in the tool's local frame.
pub fn tool_mesh(shape: &ToolShape) -> Mesh {
    match shape {
        ToolShape::Sphere { radius } => Sphere::new(*radius as f32).mesh().build(),
        ToolShape::Capsule {
            half_height,
            radius,
        } => Capsule3d::new(*radius as f32, 2.0 * *half_height as f32)
            .mesh()
            .build(),
        ToolShape::Box { half_extents } => Cuboid::new(
            2.0 * half_extents.x as f32,
            2.0 * half_extents.y as f32,
            2.0 * half_extents.z as f32,
        )
        .mesh()
        .build(),
        ToolShape::ConvexHull { points } => {
            // Render the points' bounding box (hulls are for collision).
            let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
            for p in points {
                let v = Vec3::new(p.x as f32, p.y as f32, p.z as f32);
                lo = lo.min(v);
                hi = hi.max(v);
            }
            Cuboid::from_corners(lo, hi).mesh().build()
        }
        ToolShape::TriMesh { vertices, indices } => {
            let pos: Vec<[f32; 3]> = vertices
                .iter()
                .map(|p| [p.x as f32, p.y as f32, p.z as f32])
                .collect();
            let tris: Vec<[usize; 3]> = indices.iter().map(|t| t.map(|i| i as usize)).collect();
            let idx: Vec<u32> = indices.iter().flatten().copied().collect();
            Mesh::new(
                PrimitiveTopology::TriangleList,
                RenderAssetUsages::default(),
            )
            .with_inserted_attribute(Mesh::ATTRIBUTE_NORMAL, normals(&pos, &tris))
            .with_inserted_attribute(Mesh::ATTRIBUTE_POSITION, pos)
            .with_inserted_indices(Indices::U32(idx))
        }
    }
}

fn attach_tool_meshes(
    mut commands: Commands,
    tools: Query<(Entity, &Tool), Without<Mesh3d>>,
    mut meshes: ResMut<Assets<Mesh>>,
    mut materials: ResMut<Assets<StandardMaterial>>,
) {
    for (e, tool) in &tools {
        commands.entity(e).insert((
            Mesh3d(meshes.add(tool_mesh(tool.shape()))),
            MeshMaterial3d(materials.add(StandardMaterial {
                base_color: Color::srgb(0.8, 0.82, 0.85),
                metallic: 0.9,
                perceptual_roughness: 0.3,
                ..Default::default()
            })),
        ));
    }
}
