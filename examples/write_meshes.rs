//! Writes the meshes shipped in `assets/` from the generators (core only):
//!
//! - `lens.msh`: the paper-size lens (`generate::ellipsoid(LENS_RADII, 12)`,
//!   1183 nodes, 5184 tets), in its own frame;
//! - `eye.msh`: the eye shell with the 3 mm scleral incision of the default
//!   cataract scene (`generate::eye_shell`).
//!
//! ```text
//! cargo run --example write_meshes [-- DIR]     # default DIR: assets
//! ```
//!
//! `tests/core.rs` checks that the shipped files are what this writes.

use bevy_soft_tissue::error::{Result, SoftTissueError};
use bevy_soft_tissue::mesh::generate::{self, LENS_RADII};
use bevy_soft_tissue::mesh::io;
use bevy_soft_tissue::scenes::cataract::CataractParams;
use clap::Parser;

/// Writes the cataract scene's meshes as Gmsh files.
#[derive(Parser)]
#[command(long_about = None)]
struct Args {
    /// Output folder.
    #[arg(default_value = "assets")]
    dir: String,
}

fn main() -> Result<()> {
    let dir = Args::parse().dir;
    let p = CataractParams::default();
    let meshes = [
        ("lens.msh", generate::ellipsoid(LENS_RADII, p.lens_cells)?),
        ("eye.msh", generate::eye_shell(&p.eye)?),
    ];
    std::fs::create_dir_all(&dir).map_err(|e| SoftTissueError::Io {
        path: dir.clone(),
        reason: e.to_string(),
    })?;
    for (name, mesh) in meshes {
        let path = std::path::Path::new(&dir).join(name);
        std::fs::write(&path, io::write_msh(&mesh, false)).map_err(|e| SoftTissueError::Io {
            path: path.display().to_string(),
            reason: e.to_string(),
        })?;
        println!(
            "{}: {} nodes, {} tets",
            path.display(),
            mesh.num_vertices(),
            mesh.num_tets()
        );
    }
    Ok(())
}
