//! The smallest complete app: a soft cube falls on a rigid plate.
//! (This is the program shown in the README.)
//!
//! ```text
//! cargo run --example minimal
//! ```

use bevy::prelude::*;
use bevy_soft_tissue::prelude::*;

fn main() {
    App::new()
        .add_plugins((
            MinimalPlugins,
            SoftTissuePlugins::default().with_config(SoftTissueConfig {
                gravity: Some(bevy::math::DVec3::new(0.0, 0.0, -9.81)),
                ..Default::default()
            }),
        ))
        .add_systems(Startup, setup)
        .add_systems(Update, report)
        .run();
}

fn setup(mut commands: Commands) -> Result {
    // A 1 cm soft cube (30 kPa), 2 mm above a rigid plate.
    let mesh = generate::box_mesh(
        v3(-0.005, -0.005, 0.002),
        v3(0.005, 0.005, 0.012),
        [4, 4, 4],
    )?;
    commands.spawn(SoftBody::new(
        mesh,
        TissueMaterial::new(1000.0, 30e3, 0.45).with_damping(2.0, 0.0),
    )?);
    commands.spawn((
        Tool::new(
            ToolShape::Box {
                half_extents: v3(0.05, 0.05, 0.005),
            },
            0.4,
        )?,
        Transform::from_xyz(0.0, 0.0, -0.005),
    ));
    Ok(())
}

fn report(
    plate: Query<&ToolReaction>,
    diag: Res<SoftTissueDiagnostics>,
    mut exit: MessageWriter<AppExit>,
) {
    if diag.steps > 0 && diag.steps.is_multiple_of(30) {
        for r in &plate {
            println!(
                "step {:4}: {} contacts, force on plate {:.4} N",
                diag.steps, r.contacts, r.force.z
            );
        }
    }
    if diag.steps >= 150 {
        exit.write(AppExit::Success);
    }
}
