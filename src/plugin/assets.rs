//! Meshes as Bevy assets: a loader for Gmsh `.msh` (4.1, ASCII or binary)
//! and TetGen `.node` (with the `.ele` beside it) giving a [`TetMeshAsset`],
//! and [`SoftBodyFromAsset`], which becomes a [`SoftBody`] once its mesh has
//! loaded.
//!
//! ```no_run
//! use bevy::prelude::*;
//! use bevy_soft_tissue::prelude::*;
//!
//! fn setup(mut commands: Commands, assets: Res<AssetServer>) {
//!     commands.spawn(SoftBodyFromAsset::new(
//!         assets.load("lens.msh"),
//!         TissueMaterial::new(1000.0, 5e3, 0.45),
//!     ));
//! }
//! ```
//!
//! A file the parser rejects fails to load as any Bevy asset does: the
//! `AssetServer` logs the loader's message and sends an
//! `AssetLoadFailedEvent<TetMeshAsset>`, and
//! `AssetServer::load_state` is `LoadState::Failed` with that message.
//! [`MeshAssetPlugin`] registers the loader when an `AssetPlugin` is present
//! (it does nothing in an app without one).

use bevy::asset::io::Reader;
use bevy::asset::{Asset, AssetApp, AssetLoader, LoadContext};
use bevy::prelude::*;
use bevy::reflect::TypePath;

use super::components::SoftBody;
use super::diagnostics::SoftTissueDiagnostics;
use crate::body::BodySettings;
use crate::error::SoftTissueError;
use crate::material::TissueMaterial;
use crate::mesh::{TetMesh, ValidateOptions, io};

/// A tetrahedral mesh loaded by the `AssetServer`.
#[derive(Asset, TypePath, Debug, Clone)]
pub struct TetMeshAsset(pub TetMesh);

/// Loads `.msh` and TetGen `.node` (+ `.ele`) files (see the module docs).
#[derive(Debug, Default, TypePath)]
pub struct TetMeshLoader;

impl AssetLoader for TetMeshLoader {
    type Asset = TetMeshAsset;
    type Settings = ();
    type Error = SoftTissueError;

    async fn load(
        &self,
        reader: &mut dyn Reader,
        _settings: &(),
        load_context: &mut LoadContext<'_>,
    ) -> Result<TetMeshAsset, SoftTissueError> {
        let mut bytes = Vec::new();
        reader
            .read_to_end(&mut bytes)
            .await
            .map_err(|e| SoftTissueError::Io {
                path: load_context.path().to_string(),
                reason: e.to_string(),
            })?;
        let path = load_context.path().path().to_path_buf();
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .unwrap_or_default()
            .to_ascii_lowercase();
        let mesh = if ext == "node" {
            let ele_path = path.with_extension("ele");
            let ele = load_context
                .read_asset_bytes(ele_path.clone())
                .await
                .map_err(|e| SoftTissueError::Io {
                    path: ele_path.display().to_string(),
                    reason: format!("the .ele beside the .node file: {e}"),
                })?;
            let text = |b: &[u8], format: &'static str| {
                String::from_utf8(b.to_vec()).map_err(|_| SoftTissueError::Parse {
                    format,
                    reason: "not UTF-8 text".into(),
                })
            };
            io::parse_tetgen(
                &text(&bytes, "TetGen .node")?,
                &text(&ele, "TetGen .ele")?,
                ValidateOptions::default(),
            )?
        } else {
            io::parse_msh(&bytes, ValidateOptions::default())?
        };
        Ok(TetMeshAsset(mesh))
    }

    fn extensions(&self) -> &[&str] {
        &["msh", "node"]
    }
}

/// A soft body waiting for its mesh: once the [`TetMeshAsset`] has loaded,
/// this component is replaced by a [`SoftBody`] of that mesh, `material` and
/// `settings`. If the mesh fails to load, or the body cannot be built from
/// it, the component stays, the error is logged and counted in
/// [`SoftTissueDiagnostics::errors`].
#[derive(Component, Debug, Clone)]
pub struct SoftBodyFromAsset {
    /// The mesh.
    pub mesh: Handle<TetMeshAsset>,
    /// The material.
    pub material: TissueMaterial,
    /// Solver settings.
    pub settings: BodySettings,
}

impl SoftBodyFromAsset {
    /// A body of `mesh` and `material` with default solver settings.
    pub fn new(mesh: Handle<TetMeshAsset>, material: TissueMaterial) -> Self {
        Self {
            mesh,
            material,
            settings: BodySettings::default(),
        }
    }
}

/// Registers [`TetMeshAsset`], [`TetMeshLoader`] and the system that spawns
/// [`SoftBodyFromAsset`] bodies, when the app has an `AssetPlugin`.
pub struct MeshAssetPlugin;

impl Plugin for MeshAssetPlugin {
    fn build(&self, app: &mut App) {
        // With `AssetPlugin` added first (as in `DefaultPlugins`), register now.
        register(app);
    }

    fn finish(&self, app: &mut App) {
        // Otherwise once every plugin is built, whatever their order.
        register(app);
    }
}

fn register(app: &mut App) {
    if !app.world().contains_resource::<AssetServer>()
        || app.world().contains_resource::<Assets<TetMeshAsset>>()
    {
        return;
    }
    app.init_asset::<TetMeshAsset>()
        .init_asset_loader::<TetMeshLoader>()
        .add_systems(PreUpdate, spawn_loaded_bodies);
}

/// Marks a [`SoftBodyFromAsset`] whose failure was already reported.
#[derive(Component)]
struct AssetBodyFailed;

fn spawn_loaded_bodies(
    mut commands: Commands,
    pending: Query<(Entity, &SoftBodyFromAsset), Without<AssetBodyFailed>>,
    meshes: Res<Assets<TetMeshAsset>>,
    server: Res<AssetServer>,
    mut diag: Option<ResMut<SoftTissueDiagnostics>>,
) {
    for (e, p) in &pending {
        let fail = |commands: &mut Commands, msg: String| {
            error!("{msg}");
            commands.entity(e).insert(AssetBodyFailed);
        };
        if let Some(mesh) = meshes.get(&p.mesh) {
            match SoftBody::with_settings(mesh.0.clone(), p.material.clone(), p.settings) {
                Ok(body) => {
                    commands
                        .entity(e)
                        .remove::<SoftBodyFromAsset>()
                        .insert(body);
                }
                Err(err) => {
                    fail(&mut commands, format!("soft body from mesh asset: {err}"));
                    if let Some(d) = diag.as_mut() {
                        d.errors += 1;
                    }
                }
            }
        } else if let Some(bevy::asset::LoadState::Failed(err)) = server.get_load_state(&p.mesh) {
            fail(
                &mut commands,
                format!("soft body mesh failed to load: {err}"),
            );
            if let Some(d) = diag.as_mut() {
                d.errors += 1;
            }
        }
    }
}
