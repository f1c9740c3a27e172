//! The cataract scene as Bevy entities: [`CataractScenePlugin`].

use bevy::prelude::*;

use super::cataract::{self, CataractParams, ExtractionPath};
use crate::body::BodySettings;
use crate::contact::ContactSettings;
use crate::error::Result;
use crate::plugin::{SoftBody, SoftTissueConfig, Tool};

/// Marks the lens entity.
#[derive(Component, Debug, Clone, Copy)]
pub struct Lens;

/// Marks the eye entity.
#[derive(Component, Debug, Clone, Copy)]
pub struct Eye;

/// The vectis entity and its scripted path.
#[derive(Component, Debug, Clone)]
pub struct Vectis {
    /// Scripted extraction path.
    pub path: ExtractionPath,
    /// When false, the path no longer drives the tool (manual control).
    pub scripted: bool,
    /// Seconds of scripted motion played so far.
    pub time: f64,
}

/// Spawns the cataract scene and drives the vectis along its path in `FixedUpdate`.
/// Add it after `SoftTissuePlugins`: it sets the scene's alarm distance,
/// lens–sclera friction and contact-pass limit
/// ([`cataract::contact_settings`]) in [`SoftTissueConfig::contact`] wherever
/// the app left the crate's default there; a value the app set itself is
/// kept.
#[derive(Debug, Clone, Default)]
pub struct CataractScenePlugin {
    /// Scene parameters.
    pub params: CataractParams,
    /// Solver settings of the lens and the eye (a body's own home of its
    /// preconditioner; `PreconditionerOverride` changes it later).
    pub body: BodySettings,
}

/// Sets `value` to the scene's where the app left the crate's default.
fn fill_default<T: PartialEq>(value: &mut T, default: T, scene: T) {
    if *value == default {
        *value = scene;
    }
}

impl Plugin for CataractScenePlugin {
    fn build(&self, app: &mut App) {
        // The scene's scale-dependent contact settings, where the app kept
        // the defaults (other settings are kept).
        if let Some(mut config) = app.world_mut().get_resource_mut::<SoftTissueConfig>() {
            let (scene, default) = (cataract::contact_settings(), ContactSettings::default());
            let c = &mut config.contact;
            fill_default(
                &mut c.alarm_distance,
                default.alarm_distance,
                scene.alarm_distance,
            );
            fill_default(
                &mut c.body_friction,
                default.body_friction,
                scene.body_friction,
            );
            fill_default(&mut c.max_passes, default.max_passes, scene.max_passes);
        }
        let (params, body) = (self.params.clone(), self.body);
        app.add_systems(Startup, move |mut commands: Commands| {
            if let Err(e) = spawn_cataract(&mut commands, &params, body) {
                error!("cataract scene: {e}");
            }
        })
        .add_systems(FixedUpdate, drive_vectis);
    }
}

/// Spawns lens, eye and vectis entities.
pub fn spawn_cataract(
    commands: &mut Commands,
    params: &CataractParams,
    settings: BodySettings,
) -> Result<()> {
    let scene = cataract::build(params, settings)?;
    let pose = scene.path.pose(0.0);
    commands.spawn((SoftBody(scene.lens), Lens, Name::new("lens")));
    commands.spawn((SoftBody(scene.eye), Eye, Name::new("eye")));
    commands.spawn((
        Tool(scene.vectis),
        Vectis {
            path: scene.path,
            scripted: true,
            time: 0.0,
        },
        pose_to_transform(&pose),
        Name::new("vectis"),
    ));
    Ok(())
}

/// Converts a core pose to a Bevy transform (`f64` → `f32`).
pub fn pose_to_transform(p: &crate::contact::Pose) -> Transform {
    let t = p.translation.vector;
    let q = p.rotation;
    Transform::from_xyz(t.x as f32, t.y as f32, t.z as f32).with_rotation(Quat::from_xyzw(
        q.i as f32, q.j as f32, q.k as f32, q.w as f32,
    ))
}

fn drive_vectis(config: Res<SoftTissueConfig>, mut q: Query<(&mut Vectis, &mut Transform)>) {
    for (mut v, mut tf) in &mut q {
        if v.scripted {
            v.time += config.timestep;
            *tf = pose_to_transform(&v.path.pose(v.time));
        }
    }
}
