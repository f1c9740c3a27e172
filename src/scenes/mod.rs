//! Ready-made scenes: the cataract (MSICS) extraction, as core data
//! ([`cataract`]) and, with the `bevy` feature, as Bevy entities
//! (`CataractScenePlugin`).

pub mod cataract;
#[cfg(feature = "bevy")]
mod plugin;

#[cfg(feature = "bevy")]
pub use plugin::{CataractScenePlugin, Eye, Lens, Vectis, pose_to_transform, spawn_cataract};
