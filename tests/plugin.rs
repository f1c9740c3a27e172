//! Headless app tests of `SoftTissuePlugins` (MinimalPlugins + manual time steps).

use std::sync::atomic::Ordering;
use std::time::Duration;

use bevy::diagnostic::DiagnosticsStore;
use bevy::prelude::*;
use bevy::time::TimeUpdateStrategy;
use bevy_soft_tissue::contact::ToolShape;
use bevy_soft_tissue::material::TissueMaterial;
use bevy_soft_tissue::mesh::generate;
use bevy_soft_tissue::plugin::{
    SoftBody, SoftTissueConfig, SoftTissueDiagnostics, Tool, ToolReaction,
};
use bevy_soft_tissue::prelude::{BodyContacts, v3};
use bevy_soft_tissue::{SoftTissuePlugins, SoftTissueSchedule, SoftTissueSystems};

#[path = "../examples/common/mod.rs"]
mod common;

const H: f64 = 0.01;

fn app(config: SoftTissueConfig) -> App {
    let mut app = App::new();
    app.add_plugins((
        MinimalPlugins,
        SoftTissuePlugins::default().with_config(config),
    ))
    .insert_resource(TimeUpdateStrategy::ManualDuration(Duration::from_secs_f64(
        H,
    )));
    app
}

fn steps(app: &mut App, n: u64) {
    let start = app.world().resource::<SoftTissueDiagnostics>().steps;
    let mut guard = 0;
    while app.world().resource::<SoftTissueDiagnostics>().steps < start + n {
        app.update();
        guard += 1;
        assert!(guard < 10 * n + 10, "fixed steps are not running");
    }
}

fn cube(size: f64, cells: usize, z0: f64) -> SoftBody {
    let mesh = generate::box_mesh(
        v3(-size, -size, z0),
        v3(size, size, z0 + 2.0 * size),
        [cells; 3],
    )
    .unwrap();
    SoftBody::new(
        mesh,
        TissueMaterial::new(1000.0, 3e4, 0.3).with_damping(2.0, 0.0),
    )
    .unwrap()
}

/// A rigid plate (μ = 0.3) whose top is at z = 0.
fn spawn_plate(app: &mut App) -> Entity {
    app.world_mut()
        .spawn((
            Tool::new(
                ToolShape::Box {
                    half_extents: v3(0.05, 0.05, 0.005),
                },
                0.3,
            )
            .unwrap(),
            Transform::from_xyz(0.0, 0.0, -0.005),
        ))
        .id()
}

#[test]
fn body_falls_onto_fixed_tool_and_stays_above_it() {
    let mut app = app(SoftTissueConfig {
        timestep: H,
        gravity: Some(bevy::math::DVec3::new(0.0, 0.0, -9.81)),
        ..Default::default()
    });
    let body = app.world_mut().spawn(cube(4e-3, 3, 1e-3)).id();
    let tool = spawn_plate(&mut app);
    steps(&mut app, 80);
    let w = app.world();
    let b = w.get::<SoftBody>(body).unwrap();
    let min_z = b
        .positions()
        .iter()
        .map(|p| p.z)
        .fold(f64::INFINITY, f64::min);
    let tol = 0.01 * b.mesh().min_edge_length();
    assert!(min_z >= -tol, "body sank into the tool: {min_z}");
    assert!(min_z < 1e-3 - 1e-4, "body did not fall: {min_z}");
    let contacts = w.get::<BodyContacts>(body).unwrap();
    assert!(contacts.count > 0);
    let reaction = w.get::<ToolReaction>(tool).unwrap();
    // At rest the tool carries the body's weight.
    let weight = b.mass().iter().sum::<f64>() * 9.81;
    assert!(
        (reaction.force.z + weight).abs() < 0.1 * weight,
        "reaction {:?} vs weight {weight}",
        reaction.force
    );
    let d = w.resource::<SoftTissueDiagnostics>();
    assert!(d.detect_runs > 0 && d.lcp_solves > 0);
    assert_eq!(d.errors, 0);
    // The step's first LCP ran and met its residual, or was counted at its limit.
    assert!(d.lcp_first_iterations >= 1);
    let target = SoftTissueConfig::default().contact.lcp.residual_tolerance;
    assert!(d.lcp_relative_residual <= target || d.lcp_capped > 0);
    // Bevy's store has the measurements.
    let store = w.resource::<DiagnosticsStore>();
    let step = store
        .get(&bevy_soft_tissue::plugin::diagnostics_paths::STEP)
        .and_then(|d| d.value())
        .unwrap();
    assert!(step > 0.0);
    // The step's wall clock covers every phase's timer.
    assert!(
        d.pipeline_ms >= d.step_ms() && d.step_ms() > 0.0,
        "pipeline {} ms, phases {} ms",
        d.pipeline_ms,
        d.step_ms()
    );
}

/// By default the sets run in the pipeline's own schedule, which
/// `FixedPostUpdate` runs; given another schedule they run there directly.
/// Either way bodies step, and the step's wall clock covers its phases.
#[test]
fn the_pipeline_runs_in_its_own_schedule_or_the_one_given() {
    for own in [true, false] {
        let plugins = if own {
            SoftTissuePlugins::default()
        } else {
            SoftTissuePlugins::new(FixedPostUpdate)
        };
        let mut app = App::new();
        app.add_plugins((
            MinimalPlugins,
            plugins.with_config(SoftTissueConfig {
                timestep: H,
                gravity: Some(bevy::math::DVec3::new(0.0, 0.0, -9.81)),
                ..Default::default()
            }),
        ))
        .insert_resource(TimeUpdateStrategy::ManualDuration(Duration::from_secs_f64(
            H,
        )));
        let body = app.world_mut().spawn(cube(4e-3, 2, 0.0)).id();
        steps(&mut app, 5);
        let w = app.world();
        assert_eq!(
            w.resource::<Schedules>().contains(SoftTissueSchedule),
            own,
            "own schedule: {own}"
        );
        let z = w.get::<SoftBody>(body).unwrap().positions()[0].z;
        assert!(
            z < -1e-5,
            "own schedule: {own}: the body did not fall ({z})"
        );
        let d = w.resource::<SoftTissueDiagnostics>();
        assert!(d.pipeline_ms >= d.step_ms() && d.step_ms() > 0.0);
    }
}

#[test]
fn despawning_a_body_stops_its_worker() {
    let mut app = app(SoftTissueConfig {
        timestep: H,
        ..Default::default()
    });
    let e = app.world_mut().spawn(cube(4e-3, 3, 0.0)).id();
    steps(&mut app, 3);
    let flag = app
        .world()
        .get::<SoftBody>(e)
        .unwrap()
        .preconditioner()
        .worker()
        .unwrap()
        .alive_flag();
    assert!(flag.load(Ordering::SeqCst));
    app.world_mut().despawn(e);
    steps(&mut app, 1);
    assert!(
        !flag.load(Ordering::SeqCst),
        "worker still alive after despawn"
    );
    assert_eq!(app.world().resource::<SoftTissueDiagnostics>().errors, 0);
}

#[test]
fn changing_the_material_at_runtime() {
    let run = |young: f64| {
        let mut app = app(SoftTissueConfig {
            timestep: H,
            gravity: Some(bevy::math::DVec3::new(0.0, 0.0, -9.81)),
            ..Default::default()
        });
        let mesh =
            generate::box_mesh(v3(0.0, -2e-3, -2e-3), v3(0.02, 2e-3, 2e-3), [10, 2, 2]).unwrap();
        let e = app
            .world_mut()
            .spawn((
                SoftBody::new(
                    mesh.clone(),
                    TissueMaterial::new(1000.0, 1e6, 0.3).with_damping(5.0, 0.0),
                )
                .unwrap(),
                bevy_soft_tissue::plugin::FixedNodes(
                    (0..mesh.num_vertices())
                        .filter(|&i| mesh.positions()[i].x < 1e-9)
                        .collect(),
                ),
            ))
            .id();
        steps(&mut app, 2);
        app.world_mut()
            .get_mut::<SoftBody>(e)
            .unwrap()
            .set_material(TissueMaterial::new(1000.0, young, 0.3).with_damping(5.0, 0.0))
            .unwrap();
        steps(&mut app, 150);
        let b = app.world().get::<SoftBody>(e).unwrap();
        b.positions()
            .iter()
            .zip(b.mesh().positions())
            .map(|(p, p0)| p0.z - p.z)
            .fold(f64::NEG_INFINITY, f64::max)
    };
    let (stiff, soft) = (run(1e6), run(1e5));
    assert!(soft > 3.0 * stiff, "soft sag {soft}, stiff sag {stiff}");
}

#[test]
fn absent_effects_cost_nothing() {
    // One body, no tool, no gravity, no damping coefficients.
    let mut app = app(SoftTissueConfig {
        timestep: H,
        ..Default::default()
    });
    let mesh = generate::box_mesh(v3(0.0, 0.0, 0.0), v3(0.01, 0.01, 0.01), [2, 2, 2]).unwrap();
    app.world_mut()
        .spawn(SoftBody::new(mesh, TissueMaterial::new(1000.0, 1e4, 0.3)).unwrap());
    steps(&mut app, 10);
    let d = app.world().resource::<SoftTissueDiagnostics>().clone();
    assert_eq!(
        (
            d.detect_runs,
            d.compliance_builds,
            d.lcp_solves,
            d.friction_rows,
            d.damping_bodies,
            d.gravity_bodies,
            d.gpu_dispatches
        ),
        (0, 0, 0, 0, 0, 0, 0),
        "{d:?}"
    );
    // A frictionless tool far away: detection runs, but finds nothing, so no compliance or LCP.
    app.world_mut().spawn((
        Tool::new(ToolShape::Sphere { radius: 1e-3 }, 0.0).unwrap(),
        Transform::from_xyz(1.0, 0.0, 0.0),
    ));
    steps(&mut app, 5);
    let d = app.world().resource::<SoftTissueDiagnostics>().clone();
    assert!(d.detect_runs > 0);
    assert_eq!(
        (d.compliance_builds, d.lcp_solves, d.friction_rows),
        (0, 0, 0)
    );
    // Touching frictionless tool: contacts, no friction rows.
    let mut q = app.world_mut().query::<(&Tool, &mut Transform)>();
    for (_, mut t) in q.iter_mut(app.world_mut()) {
        t.translation = Vec3::new(0.005, 0.005, 0.0109);
    }
    steps(&mut app, 5);
    let d = app.world().resource::<SoftTissueDiagnostics>().clone();
    assert!(d.compliance_builds > 0 && d.lcp_solves > 0, "{d:?}");
    assert_eq!(d.friction_rows, 0);
    // Damping and gravity switched on show up in the counters.
    app.world_mut().resource_mut::<SoftTissueConfig>().gravity =
        Some(bevy::math::DVec3::new(0.0, 0.0, -9.81));
    steps(&mut app, 2);
    assert!(
        app.world()
            .resource::<SoftTissueDiagnostics>()
            .gravity_bodies
            > 0
    );
    assert_eq!(app.world().resource::<SoftTissueDiagnostics>().errors, 0);
}

/// A user system in `FixedUpdate` moves the tool; detection sees the new pose the same step.
#[test]
fn user_systems_move_tools_before_detection() {
    #[derive(Resource, Default)]
    struct Seen(Vec<f32>);
    let mut app = app(SoftTissueConfig {
        timestep: H,
        ..Default::default()
    });
    app.init_resource::<Seen>();
    app.add_systems(FixedUpdate, |mut q: Query<&mut Transform, With<Tool>>| {
        for mut t in &mut q {
            t.translation.x += 1.0;
        }
    });
    app.add_systems(
        SoftTissueSchedule,
        (|q: Query<&Tool>, mut seen: ResMut<Seen>| {
            for t in &q {
                seen.0.push(t.pose().translation.vector.x as f32);
            }
        })
        .after(SoftTissueSystems::Detect)
        .before(SoftTissueSystems::Compliance),
    );
    app.world_mut().spawn(cube(1e-3, 1, 0.0));
    app.world_mut().spawn((
        Tool::new(ToolShape::Sphere { radius: 1e-3 }, 0.0).unwrap(),
        Transform::from_xyz(10.0, 0.0, 0.0),
    ));
    steps(&mut app, 3);
    let seen = &app.world().resource::<Seen>().0;
    assert_eq!(seen[..3], [11.0, 12.0, 13.0]);
}

/// Runs the coarse cataract scene headless for `steps` steps, with a periodic
/// refresh that keeps the run deterministic (the async worker's timing changes
/// the trajectory from run to run).
fn coarse_cataract(
    deliver: bool,
    steps: usize,
) -> (
    bevy_soft_tissue::scenes::cataract::CataractParams,
    common::headless::HeadlessSummary,
) {
    let mut params = bevy_soft_tissue::scenes::cataract::CataractParams::coarse();
    if !deliver {
        params = params.push_only();
    }
    let config = SoftTissueConfig {
        timestep: 1.0 / 60.0,
        ..Default::default()
    };
    let body = bevy_soft_tissue::body::BodySettings {
        preconditioner: bevy_soft_tissue::solver::PreconditionerKind::Periodic { every: 4 },
        ..Default::default()
    };
    let s = common::headless::run_headless(&params, config, body, steps).unwrap();
    println!("{s:?}");
    (params, s)
}

/// Penetration, checked at the end of every step against the vectis and
/// between lens and sclera, stays within the tolerance.
fn assert_no_penetration(s: &common::headless::HeadlessSummary) {
    assert!(
        s.max_penetration <= s.tolerance && s.max_tissue_penetration <= s.tolerance,
        "penetration {} (lens-sclera {}) > {}",
        s.max_penetration,
        s.max_tissue_penetration,
        s.tolerance
    );
}

/// The scene plugin fills in the scene's contact settings only where the
/// app left the crate's defaults: a pass limit the app chose is kept.
#[test]
fn the_scene_plugin_keeps_contact_settings_the_app_chose() {
    use bevy_soft_tissue::contact::ContactSettings;
    use bevy_soft_tissue::scenes::{CataractScenePlugin, cataract};
    let scene = cataract::contact_settings();
    let default = ContactSettings::default();
    assert_ne!(scene.max_passes, default.max_passes);
    for (chosen, expected) in [(None, scene.max_passes), (Some(5), 5)] {
        let mut config = SoftTissueConfig::default();
        if let Some(p) = chosen {
            config.contact.max_passes = p;
        }
        let mut app = app(config);
        app.add_plugins(CataractScenePlugin::default());
        let c = app.world().resource::<SoftTissueConfig>().contact;
        assert_eq!(c.max_passes, expected, "app chose {chosen:?}");
        assert_eq!(c.alarm_distance, scene.alarm_distance);
    }
}

#[test]
fn cataract_scene_runs_headless() {
    let (params, s) = coarse_cataract(false, 240);
    assert_no_penetration(&s);
    assert!(
        s.contacts.1 > 10,
        "the vectis never engaged the lens: {:?}",
        s.contacts
    );
    // The lens moves toward the incision (+y, +z).
    let d = bevy_soft_tissue::scenes::cataract::incision_direction(&params);
    let moved = (s.lens_center.1 - s.lens_center.0).dot(&d);
    assert!(
        moved > 0.5e-3,
        "lens moved only {moved} m toward the incision"
    );
    // Stable: the vectis moves at about 1 mm/s and 7 mm in all; in the
    // scene's viscous medium the squeezed lens follows it and is not shot off.
    let total = (s.lens_center.1 - s.lens_center.0).norm();
    assert!(total < 7e-3, "lens moved {total} m");
    assert!(
        s.max_lens_speed < 0.03,
        "peak lens speed {} m/s",
        s.max_lens_speed
    );
}

/// The headless harness's extras: the eye's own preconditioner (a
/// `PreconditionerOverride` on its entity) and the per-step trace. The lens
/// refreshes every 4 steps and the eye every step, and the trace shows each
/// body's factor age, one line per step, ending where the summary's lens does.
#[test]
fn headless_trace_and_the_eyes_own_preconditioner() {
    use bevy_soft_tissue::solver::PreconditionerKind;
    use common::headless::{HeadlessOptions, TRACE_HEADER, run_headless_with};
    let params = bevy_soft_tissue::scenes::cataract::CataractParams::coarse().push_only();
    let config = SoftTissueConfig {
        timestep: 1.0 / 60.0,
        ..Default::default()
    };
    let body = bevy_soft_tissue::body::BodySettings {
        preconditioner: PreconditionerKind::Periodic { every: 4 },
        ..Default::default()
    };
    let path = std::env::temp_dir().join(format!("cataract-trace-{}.csv", std::process::id()));
    let options = HeadlessOptions {
        eye_preconditioner: Some(PreconditionerKind::Periodic { every: 1 }),
        trace: Some(path.clone()),
        ..Default::default()
    };
    let steps = 40;
    let s = run_headless_with(&params, config, body, steps, &options).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    let _ = std::fs::remove_file(&path);
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some(TRACE_HEADER));
    let columns = TRACE_HEADER.split(',').count();
    let rows: Vec<Vec<f64>> = lines
        .map(|l| {
            let row: Vec<f64> = l.split(',').map(|v| v.parse().unwrap()).collect();
            assert_eq!(row.len(), columns, "{l}");
            assert!(row.iter().all(|v| v.is_finite()), "{l}");
            row
        })
        .collect();
    assert_eq!(rows.len(), steps);
    assert!(rows.windows(2).all(|w| w[1][0] == w[0][0] + 1.0));
    let (lens_ages, eye_ages): (Vec<f64>, Vec<f64>) = rows.iter().map(|r| (r[5], r[6])).unzip();
    assert!(eye_ages.iter().all(|&a| a == 0.0), "eye {eye_ages:?}");
    assert!(lens_ages.iter().all(|&a| a < 4.0), "lens {lens_ages:?}");
    assert!(lens_ages.contains(&3.0), "lens {lens_ages:?}");
    let last = rows.last().unwrap();
    let end = s.lens_center.1 * 1e3;
    assert!(
        (last[8] - end.x).abs() < 1e-4
            && (last[9] - end.y).abs() < 1e-4
            && (last[10] - end.z).abs() < 1e-4,
        "trace ends at {:?}, the summary at {end:?}",
        &last[8..11]
    );
}

/// The harness's test of a tool between a surface's vertices: a sphere that
/// dips 50 µm into a triangle's middle while all three corners stay outside
/// it is found at that depth; raised clear of the plane, nothing is.
#[test]
fn a_tool_between_a_triangles_vertices_is_found() {
    use bevy_soft_tissue::contact::RigidTool;
    use common::faces::{FACE_GRID, tool_in_faces};
    let x = [v3(0.0, 0.0, 0.0), v3(1e-3, 0.0, 0.0), v3(0.0, 1e-3, 0.0)];
    let centroid = (x[0] + x[1] + x[2]) / 3.0;
    let (r, tolerance) = (0.2e-3, 1e-6);
    for (height, depth, count) in [(0.15e-3, 0.05e-3, 1), (0.25e-3, 0.0, 0)] {
        let pose = nalgebra::Isometry3::translation(centroid.x, centroid.y, height);
        let tool = RigidTool::new(ToolShape::Sphere { radius: r }, pose).unwrap();
        // The corners are outside the sphere: a vertex test finds nothing.
        assert!(x.iter().all(|p| tool.proximity(p, 0.0).is_none()));
        let (found, n) = tool_in_faces(&tool, &[[0, 1, 2]], &x, tolerance, FACE_GRID);
        assert!(
            (found - depth).abs() < 1e-9,
            "height {height}: {found} m, expected {depth}"
        );
        assert_eq!(n, count, "height {height}");
    }
}

#[test]
fn cataract_scene_delivers_the_lens_through_the_incision() {
    let (params, s) = coarse_cataract(true, 1080);
    assert_no_penetration(&s);
    // The eye is centred at the origin; the lens centre ends outside it, more
    // than the lens's half thickness beyond the sclera, on the incision's side.
    let (end, radius) = (s.lens_center.1, params.eye.radius);
    let half = bevy_soft_tissue::mesh::generate::LENS_RADII[2];
    assert!(
        end.norm() > radius + half,
        "lens centre at {} m",
        end.norm()
    );
    let d = bevy_soft_tissue::scenes::cataract::incision_direction(&params);
    assert!(
        end.normalize().dot(&d) > 0.8,
        "not through the incision: {end:?}"
    );
    // Stable: once its widest part is through, the spread lips squeeze the
    // lens out like a seed, faster than the vectis (1.7 mm/s) — in this
    // coarse scene at about 0.12 m/s, at full size 31-48 mm/s — and the
    // medium slows it. An unstable step would send it off at metres per second.
    assert!(
        s.max_lens_speed < 0.25,
        "peak lens speed {} m/s",
        s.max_lens_speed
    );
}

fn fixed_timestep(app: &App) -> f64 {
    app.world()
        .resource::<Time<Fixed>>()
        .timestep()
        .as_secs_f64()
}

#[test]
fn timestep_changes_reach_the_fixed_clock() {
    let mut app = app(SoftTissueConfig {
        timestep: H,
        ..Default::default()
    });
    app.update();
    assert!((fixed_timestep(&app) - H).abs() < 1e-9);
    app.world_mut().resource_mut::<SoftTissueConfig>().timestep = 0.004;
    app.update();
    assert!((fixed_timestep(&app) - 0.004).abs() < 1e-9);
    // An impossible step size is rejected with an error count, not a panic.
    app.world_mut().resource_mut::<SoftTissueConfig>().timestep = -1.0;
    app.update();
    assert!(app.world().resource::<SoftTissueDiagnostics>().errors > 0);
    assert!((fixed_timestep(&app) - 0.004).abs() < 1e-9);
}

/// The plugin group's members can be left out: without `ContactPlugin` the
/// same falling cube that `body_falls_onto_fixed_tool_and_stays_above_it`
/// keeps above the plate falls through it, and no contact work runs.
#[test]
fn contact_plugin_can_be_disabled() {
    use bevy::app::PluginGroup;
    use bevy_soft_tissue::plugin::ContactPlugin;
    let mut app = App::new();
    app.add_plugins((
        MinimalPlugins,
        SoftTissuePlugins::default()
            .with_config(SoftTissueConfig {
                timestep: H,
                gravity: Some(bevy::math::DVec3::new(0.0, 0.0, -9.81)),
                ..Default::default()
            })
            .build()
            .disable::<ContactPlugin>(),
    ))
    .insert_resource(TimeUpdateStrategy::ManualDuration(Duration::from_secs_f64(
        H,
    )));
    let body = app.world_mut().spawn(cube(4e-3, 3, 1e-3)).id();
    spawn_plate(&mut app);
    steps(&mut app, 80);
    let w = app.world();
    let min_z = w
        .get::<SoftBody>(body)
        .unwrap()
        .positions()
        .iter()
        .map(|p| p.z)
        .fold(f64::INFINITY, f64::min);
    assert!(
        min_z < -1e-3,
        "without contacts the body falls into the plate: {min_z}"
    );
    let d = w.resource::<SoftTissueDiagnostics>();
    assert_eq!(
        (d.detect_runs, d.compliance_builds, d.lcp_solves),
        (0, 0, 0)
    );
    assert_eq!(d.errors, 0);
}

/// A `.msh` file through the `AssetServer`: the shipped lens loads as a
/// `TetMeshAsset` and a `SoftBodyFromAsset` becomes a stepping `SoftBody`; a
/// malformed file fails to load with the parser's message.
#[test]
fn lens_loads_through_the_asset_server() {
    use bevy::asset::LoadState;
    use bevy_soft_tissue::plugin::{SoftBodyFromAsset, TetMeshAsset};
    let mut app = App::new();
    app.add_plugins((
        MinimalPlugins,
        AssetPlugin::default(),
        SoftTissuePlugins::default().with_config(SoftTissueConfig {
            timestep: H,
            ..Default::default()
        }),
    ))
    .insert_resource(TimeUpdateStrategy::ManualDuration(Duration::from_secs_f64(
        H,
    )));
    app.finish();
    app.cleanup();
    let server = app.world().resource::<AssetServer>().clone();
    let lens: Handle<TetMeshAsset> = server.load("lens.msh");
    let entity = app
        .world_mut()
        .spawn(SoftBodyFromAsset::new(
            lens.clone(),
            TissueMaterial::new(1000.0, 5e3, 0.45),
        ))
        .id();
    // A malformed file, written where the asset server reads (removed when
    // the guard drops, also when an assertion below fails).
    struct Removed(std::path::PathBuf);
    impl Drop for Removed {
        fn drop(&mut self) {
            let _ = std::fs::remove_file(&self.0);
        }
    }
    // Where the asset server reads: its root is taken from the environment
    // at run time, which can differ from the directory this test was
    // compiled in.
    let dir = bevy::asset::io::file::FileAssetReader::get_base_path().join("assets");
    let bad_name = format!("broken-{}.msh", std::process::id());
    let bad_file = Removed(dir.join(&bad_name));
    std::fs::write(
        &bad_file.0,
        b"$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n1 2 1\n",
    )
    .unwrap();
    let bad: Handle<TetMeshAsset> = server.load(bad_name.clone());
    let mut guard = 0;
    while app.world().get::<SoftBody>(entity).is_none()
        || !matches!(server.get_load_state(&bad), Some(LoadState::Failed(_)))
    {
        app.update();
        std::thread::sleep(Duration::from_millis(2));
        guard += 1;
        assert!(
            guard < 5000,
            "assets did not settle: {:?}",
            server.get_load_state(&bad)
        );
    }
    drop(bad_file);
    let mesh = app
        .world()
        .resource::<Assets<TetMeshAsset>>()
        .get(&lens)
        .unwrap()
        .0
        .clone();
    let expected = generate::ellipsoid(bevy_soft_tissue::mesh::generate::LENS_RADII, 12).unwrap();
    assert_eq!(mesh.num_vertices(), expected.num_vertices());
    assert_eq!(mesh.tets(), expected.tets());
    assert!(app.world().get::<SoftBodyFromAsset>(entity).is_none());
    steps(&mut app, 3);
    let body = app.world().get::<SoftBody>(entity).unwrap();
    assert_eq!(body.num_nodes(), expected.num_vertices());
    assert!(body.step_index() >= 3, "{}", body.step_index());
    assert!(body.report().cg.converged);
    let Some(LoadState::Failed(err)) = server.get_load_state(&bad) else {
        unreachable!()
    };
    let msg = err.to_string();
    assert!(msg.contains("malformed") && msg.contains("msh"), "{msg}");
}

fn positions(app: &App, e: Entity) -> Vec<bevy_soft_tissue::math::Vec3> {
    app.world().get::<SoftBody>(e).unwrap().positions().to_vec()
}

/// A body whose step fails is put back, marked and reported; the others go
/// on; the user clears the cause and the mark and it steps again.
#[test]
fn a_failing_body_is_stopped_reported_and_resumes() {
    use bevy::ecs::message::Messages;
    use bevy_soft_tissue::plugin::{FailedPhase, SoftBodyError, SoftBodyFailed};
    let mut app = app(SoftTissueConfig {
        timestep: H,
        gravity: Some(bevy::math::DVec3::new(0.0, 0.0, -9.81)),
        ..Default::default()
    });
    let a = app.world_mut().spawn(cube(4e-3, 2, 0.0)).id();
    let b = app.world_mut().spawn(cube(4e-3, 2, 0.05)).id();
    steps(&mut app, 3);
    // Forces that fit one by one but whose squared norms overflow together.
    {
        let mut body = app.world_mut().get_mut::<SoftBody>(a).unwrap();
        for n in 0..3 {
            body.set_external_force(n, v3(1e154, 0.0, 0.0)).unwrap();
        }
    }
    let (a0, b0) = (positions(&app, a), positions(&app, b));
    steps(&mut app, 1);
    let failed = app.world().get::<SoftBodyFailed>(a).expect("marked");
    assert_eq!(failed.phase, FailedPhase::FreeMotion);
    assert_eq!(
        positions(&app, a),
        a0,
        "not put back to its state before the step"
    );
    assert_ne!(positions(&app, b), b0, "the other body stopped too");
    let messages = app.world().resource::<Messages<SoftBodyError>>();
    let sent: Vec<_> = messages.get_cursor().read(messages).cloned().collect();
    assert!(
        sent.iter()
            .any(|m| m.entity == Some(a) && m.phase == Some(FailedPhase::FreeMotion)),
        "{sent:?}"
    );
    steps(&mut app, 5);
    assert_eq!(positions(&app, a), a0, "a failed body is left alone");
    let d = app.world().resource::<SoftTissueDiagnostics>();
    assert_eq!(d.failed_bodies, 1);
    // The user removes the cause and the mark: it steps again.
    app.world_mut()
        .get_mut::<SoftBody>(a)
        .unwrap()
        .clear_external_forces();
    app.world_mut().entity_mut(a).remove::<SoftBodyFailed>();
    steps(&mut app, 5);
    assert!(app.world().get::<SoftBodyFailed>(a).is_none());
    assert!(
        positions(&app, a)[0].z < a0[0].z,
        "it did not resume falling"
    );
    assert_eq!(
        app.world()
            .resource::<SoftTissueDiagnostics>()
            .failed_bodies,
        1
    );
}

/// Nodes fixed by `FixedNodes` are freed when taken out of the list or when
/// the component is removed.
#[test]
fn fixed_nodes_are_freed_again() {
    use bevy_soft_tissue::body::NodeConstraint;
    use bevy_soft_tissue::plugin::FixedNodes;
    let mut app = app(SoftTissueConfig {
        timestep: H,
        ..Default::default()
    });
    let e = app
        .world_mut()
        .spawn((cube(4e-3, 1, 0.0), FixedNodes(vec![0, 1, 2])))
        .id();
    steps(&mut app, 1);
    let constraint = |app: &App, n: usize| app.world().get::<SoftBody>(e).unwrap().constraints()[n];
    assert_eq!(constraint(&app, 2), NodeConstraint::Fixed);
    app.world_mut().get_mut::<FixedNodes>(e).unwrap().0 = vec![0, 1];
    steps(&mut app, 1);
    assert_eq!(constraint(&app, 2), NodeConstraint::Free);
    assert_eq!(constraint(&app, 1), NodeConstraint::Fixed);
    app.world_mut().entity_mut(e).remove::<FixedNodes>();
    steps(&mut app, 1);
    assert_eq!(constraint(&app, 0), NodeConstraint::Free);
    assert_eq!(constraint(&app, 1), NodeConstraint::Free);
}

/// A time step of 0, NaN, infinite or absurd does not panic, at build or at
/// run time: it is reported and the bodies wait for a usable one.
#[test]
fn bad_timesteps_are_reported_not_panics() {
    for h in [0.0, -1.0, f64::NAN, f64::INFINITY, 1e-12, 1e9] {
        let mut app = App::new();
        app.add_plugins((
            MinimalPlugins,
            SoftTissuePlugins::default().with_config(SoftTissueConfig {
                timestep: h,
                ..Default::default()
            }),
        ))
        .insert_resource(TimeUpdateStrategy::ManualDuration(Duration::from_secs_f64(
            H,
        )));
        let e = app.world_mut().spawn(cube(4e-3, 1, 0.0)).id();
        for _ in 0..5 {
            app.update();
        }
        assert!(
            app.world().resource::<SoftTissueDiagnostics>().errors > 0,
            "h = {h}"
        );
        assert_eq!(
            app.world().get::<SoftBody>(e).unwrap().step_index(),
            0,
            "h = {h}"
        );
        // A usable step at run time: it goes on.
        app.world_mut().resource_mut::<SoftTissueConfig>().timestep = H;
        for _ in 0..5 {
            app.update();
        }
        let d = app.world().resource::<SoftTissueDiagnostics>();
        assert!(
            app.world().get::<SoftBody>(e).unwrap().step_index() > 0,
            "h = {h}: {} steps, {} errors, fixed step {:?}, body h {}, failed {:?}",
            d.steps,
            d.errors,
            app.world().resource::<Time<Fixed>>().timestep(),
            app.world().get::<SoftBody>(e).unwrap().step_size(),
            app.world()
                .get::<bevy_soft_tissue::plugin::SoftBodyFailed>(e)
        );
    }
}

/// A body despawned between detection and correction (by a user system in
/// the middle of the pipeline): that step's contact response is skipped and
/// reported, the tool's reaction is not left stale, and the next steps go on
/// with the bodies that remain.
#[test]
fn a_body_removed_mid_pipeline_is_reported_not_stale() {
    use bevy::ecs::message::Messages;
    use bevy_soft_tissue::plugin::SoftBodyError;
    #[derive(Resource)]
    struct Doomed(Option<Entity>);
    fn despawn_mid_step(mut doomed: ResMut<Doomed>, mut commands: Commands) {
        if let Some(e) = doomed.0.take() {
            commands.entity(e).despawn();
        }
    }
    let mut app = app(SoftTissueConfig {
        timestep: H,
        gravity: Some(bevy::math::DVec3::new(0.0, 0.0, -9.81)),
        ..Default::default()
    });
    app.add_systems(
        SoftTissueSchedule,
        despawn_mid_step
            .after(SoftTissueSystems::Compliance)
            .before(SoftTissueSystems::Lcp),
    );
    app.insert_resource(Doomed(None));
    let keep = app.world_mut().spawn(cube(4e-3, 2, 1e-4)).id();
    let gone = app.world_mut().spawn(cube(4e-3, 2, 0.02)).id();
    let plate = spawn_plate(&mut app);
    steps(&mut app, 30);
    assert!(app.world().get::<ToolReaction>(plate).unwrap().force.z < 0.0);
    let errors = app.world().resource::<SoftTissueDiagnostics>().errors;
    app.world_mut().resource_mut::<Doomed>().0 = Some(gone);
    steps(&mut app, 1);
    assert!(app.world().get_entity(gone).is_err());
    let d = app.world().resource::<SoftTissueDiagnostics>();
    assert!(d.errors > errors, "the skipped response was not reported");
    let messages = app.world().resource::<Messages<SoftBodyError>>();
    assert!(messages.get_cursor().read(messages).next().is_some());
    assert_eq!(
        *app.world().get::<ToolReaction>(plate).unwrap(),
        ToolReaction::default(),
        "a stale reaction was left on the tool"
    );
    // The remaining body rests on the plate again.
    steps(&mut app, 10);
    let r = app.world().get::<ToolReaction>(plate).unwrap();
    assert!(r.force.z < 0.0 && r.contacts > 0, "{r:?}");
    let min_z = positions(&app, keep)
        .iter()
        .map(|p| p.z)
        .fold(f64::INFINITY, f64::min);
    assert!(min_z > -1e-5, "{min_z}");
}

/// A device that reports when it is dropped.
struct DropFlag {
    inner: bevy_soft_tissue::haptics::SimulatedDevice,
    dropped: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

impl bevy_soft_tissue::haptics::HapticDevice for DropFlag {
    fn pose(&mut self, time: f64) -> bevy_soft_tissue::contact::Pose {
        self.inner.pose(time)
    }
    fn set_output(&mut self, f: bevy_soft_tissue::math::Vec3, t: bevy_soft_tissue::math::Vec3) {
        self.inner.set_output(f, t);
    }
}

impl Drop for DropFlag {
    fn drop(&mut self) {
        self.dropped.store(true, Ordering::SeqCst);
    }
}

/// `HapticsPlugin`: a scripted device presses a sphere into a cube resting
/// on a plate; the tool follows the coupled pose, the force pushes the tool
/// back, the status and diagnostics fill, and dropping the app stops the
/// haptic thread and releases the device.
#[test]
fn a_haptic_device_drives_a_tool_and_stops_with_the_app() {
    use bevy_soft_tissue::haptics::{HapticSettings, SimulatedDevice};
    use bevy_soft_tissue::plugin::{HapticTool, HapticsPlugin, HapticsStatus, haptic_paths};
    let mut app = app(SoftTissueConfig {
        timestep: H,
        gravity: Some(bevy::math::DVec3::new(0.0, 0.0, -9.81)),
        ..Default::default()
    });
    let dropped = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (top, radius) = (8e-3, 4e-3);
    let target = nalgebra::Isometry3::translation(0.0, 0.0, top + radius - 1e-3);
    let device = DropFlag {
        inner: SimulatedDevice::scripted(move |_| target),
        dropped: dropped.clone(),
    };
    let settings = HapticSettings::default();
    app.add_plugins(HapticsPlugin::new(device, settings));
    app.world_mut().spawn(cube(4e-3, 3, 0.0));
    spawn_plate(&mut app);
    let tool = app
        .world_mut()
        .spawn((
            Tool::new(ToolShape::Sphere { radius }, 0.0).unwrap(),
            Transform::from_xyz(0.0, 0.0, (top + 2.0 * radius) as f32),
            HapticTool,
        ))
        .id();
    for _ in 0..60 {
        steps(&mut app, 1);
        std::thread::sleep(Duration::from_millis(2));
    }
    // The balance below holds once the proxy stands still (the coupling's
    // damper adds `c v` while it moves; on a loaded machine the cube may
    // still be settling after 60 steps): step on until the tool has moved by
    // less than 1 % of its lift over three steps in a row, each with new
    // haptic ticks, at most 240 more steps.
    let read = |app: &App| {
        let lift = app.world().get::<Transform>(tool).unwrap().translation.z as f64
            - target.translation.vector.z;
        let ticks = app.world().resource::<HapticsStatus>().state.stats.ticks;
        (lift, ticks)
    };
    let (mut last, mut last_ticks) = read(&app);
    let mut still = 0;
    for _ in 0..240 {
        steps(&mut app, 1);
        std::thread::sleep(Duration::from_millis(2));
        let (now, ticks) = read(&app);
        if ticks > last_ticks && (now - last).abs() <= 0.01 * now.abs() {
            still += 1;
        } else if ticks > last_ticks {
            still = 0;
        }
        (last, last_ticks) = (now, ticks);
        if still == 3 {
            break;
        }
    }
    let w = app.world();
    let status = w.resource::<HapticsStatus>();
    assert!(status.running, "{:?}", status.error);
    let s = status.state;
    assert!(s.stats.ticks > 10 && s.stats.problems >= 3, "{:?}", s.stats);
    assert!(s.contacts > 0, "the sphere touches the cube");
    assert!(
        s.force.z > 0.0,
        "the tissue pushes the tool back: {}",
        s.force
    );
    // The tool stands where the coupling and the contact balance: above the
    // device by the force over the coupling's stiffness.
    let tf = w.get::<Transform>(tool).unwrap();
    let lift = tf.translation.z as f64 - target.translation.vector.z;
    let expected = s.contact_force.z / settings.coupling.stiffness;
    assert!(
        (lift - expected).abs() <= 0.1 * expected + 1e-6,
        "proxy lift {lift} vs F/k {expected}"
    );
    assert!(w.get::<ToolReaction>(tool).unwrap().force.z > 0.0);
    let rate = w
        .resource::<DiagnosticsStore>()
        .get(&haptic_paths::RATE)
        .and_then(|d| d.value());
    assert!(rate.is_some_and(|r| r > 0.0), "{rate:?}");
    assert!(!dropped.load(Ordering::SeqCst));
    drop(app);
    assert!(dropped.load(Ordering::SeqCst), "the haptic thread stopped");
}

/// The viewer's display probe (examples/common/display.rs): winit panics
/// inside Bevy's plugin build without an X server it can reach, so the
/// cataract example asks first. Empty, malformed and silent displays are
/// refused with a reason; a listening local socket is accepted.
#[test]
fn the_viewer_probes_its_display_before_opening_a_window() {
    use common::display::x11_display_at;
    for bad in ["", "foo", ":x", "host:"] {
        let why = x11_display_at(bad).expect_err(bad);
        assert!(!why.is_empty());
    }
    #[cfg(target_os = "linux")]
    {
        use std::os::linux::net::SocketAddrExt;
        // A display number no server uses on this machine.
        let free = (6000..6100)
            .find(|n| !std::path::Path::new(&format!("/tmp/.X11-unix/X{n}")).exists())
            .expect("a free display number");
        use std::os::unix::net::{SocketAddr, UnixListener};
        let name = format!("/tmp/.X11-unix/X{free}");
        let silent = x11_display_at(&format!(":{free}"));
        assert!(silent.is_err(), "{silent:?}");
        // A server on the abstract socket of that name (as Linux X servers
        // listen) answers, with or without a screen number.
        let addr = SocketAddr::from_abstract_name(name.as_bytes()).unwrap();
        let _server = UnixListener::bind_addr(&addr).unwrap();
        assert_eq!(x11_display_at(&format!(":{free}")), Ok(format!(":{free}")));
        assert!(x11_display_at(&format!("unix:{free}.0")).is_ok());
    }
}
