//! A soft body from a mesh file loaded through Bevy's `AssetServer`: the
//! shipped paper-size lens (`assets/lens.msh`) falls under gravity onto a
//! rigid plate, headless.
//!
//! ```text
//! cargo run --release --example mesh_asset
//! ```
//!
//! (Bevy finds `assets/` through `CARGO_MANIFEST_DIR`, which `cargo run`
//! sets; run the binary directly with `BEVY_ASSET_ROOT` set to the crate's folder.)
//!
//! The lens is spawned as a `SoftBodyFromAsset`; once the `.msh` has loaded
//! it becomes a `SoftBody`. A file the loader rejects shows up as Bevy's
//! asset load error with the loader's message (try a broken copy of the file).

use std::process::ExitCode;
use std::time::Duration;

use bevy::prelude::*;
use bevy::time::TimeUpdateStrategy;
use bevy_soft_tissue::prelude::*;

const H: f64 = 1.0 / 60.0;

fn setup(mut commands: Commands, assets: Res<AssetServer>) {
    let material = TissueMaterial::new(1000.0, 5e3, 0.45).with_damping(2.0, 0.0);
    commands.spawn(SoftBodyFromAsset::new(assets.load("lens.msh"), material));
    // A thick plate 0.2 mm below the lens's lowest point (the lens is 4.5 mm
    // thick). The first step of a fall already moves 2.7 mm: the plate must be
    // thicker than that, or a vertex ends nearer its far side (no continuous
    // collision detection).
    commands.spawn((
        Tool::new(
            ToolShape::Box {
                half_extents: v3(0.01, 0.01, 0.01),
            },
            0.3,
        )
        .expect("valid tool"),
        Transform::from_xyz(0.0, 0.0, -0.00245 - 0.01),
    ));
}

fn main() -> ExitCode {
    let mut app = App::new();
    app.add_plugins((
        MinimalPlugins,
        bevy::log::LogPlugin::default(),
        AssetPlugin::default(),
        SoftTissuePlugins::default().with_config(SoftTissueConfig {
            timestep: H,
            gravity: Some(bevy::math::DVec3::new(0.0, 0.0, -9.81)),
            ..Default::default()
        }),
    ))
    .insert_resource(TimeUpdateStrategy::ManualDuration(Duration::from_secs_f64(
        H,
    )))
    .add_systems(Startup, setup);
    // Driving `update` by hand: finish the plugins' set-up first, as `run` does.
    app.finish();
    app.cleanup();
    let mut updates = 0;
    let mut loaded_at = None;
    loop {
        app.update();
        updates += 1;
        let world = app.world_mut();
        let steps = world.resource::<SoftTissueDiagnostics>().steps;
        let reaction = world
            .query::<&ToolReaction>()
            .iter(world)
            .next()
            .copied()
            .unwrap_or_default();
        let mut q = world.query::<&SoftBody>();
        let body = q.iter(world).next();
        if body.is_some() && loaded_at.is_none() {
            loaded_at = Some(steps);
        }
        let since = steps - loaded_at.unwrap_or(steps);
        if let Some(body) = body
            && since >= 120
        {
            let low = body
                .positions()
                .iter()
                .map(|p| p.z)
                .fold(f64::INFINITY, f64::min);
            println!(
                "lens.msh loaded: {} nodes, {} tets; after {since} steps its lowest point is at {:.3} mm, \
                 the plate (top at -2.45 mm) carries {:.4} N over {} contacts",
                body.num_nodes(),
                body.mesh().num_tets(),
                low * 1e3,
                reaction.force.z,
                reaction.contacts
            );
            return ExitCode::SUCCESS;
        }
        if updates > 2000 {
            eprintln!("the lens mesh did not load (see the log above)");
            return ExitCode::FAILURE;
        }
        if loaded_at.is_none() {
            // The loader runs on the IO task pool: give it time.
            std::thread::sleep(Duration::from_millis(2));
        }
    }
}
