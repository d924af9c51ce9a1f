//! Embedding tests: Sylva's stages installed into a program's own schedule, with only the
//! stages a scene needs, on the program's thread pool, read in place by its systems.

mod common;

use bevy_ecs::prelude::*;
use glam::{Vec2, Vec3};
use std::collections::{BTreeSet, HashSet};
use std::sync::{Arc, Mutex};
use sylva_engine::bvh::BuildParams;
use sylva_engine::camera::Camera;
use sylva_engine::components::{Instance, Transform};
use sylva_engine::discontinuity::DiscontinuityFilter;
use sylva_engine::environment::{EnvironmentLight, EnvironmentMap};
use sylva_engine::film::Film;
use sylva_engine::geometry::{Geometry, GeometryLibrary};

use sylva_engine::mesh::TriangleMesh;
use sylva_engine::render::FramePlan;
use sylva_engine::shading::{Shader, ShaderId};
use sylva_engine::sway::{RestPose, Sway, Wind};
use sylva_systems::embed::FrameImage;
use sylva_systems::*;
use sylva_systems::{RenderOptions, Stages, install, stage_name};

fn quad(scale: f32) -> TriangleMesh {
    TriangleMesh {
        positions: vec![
            Vec3::new(-scale, 0.0, -scale),
            Vec3::new(scale, 0.0, -scale),
            Vec3::new(scale, 0.0, scale),
            Vec3::new(-scale, 0.0, scale),
        ],
        normals: vec![Vec3::Y; 4],
        uvs: vec![Vec2::ZERO, Vec2::X, Vec2::ONE, Vec2::Y],
        indices: vec![[0, 2, 1], [0, 3, 2]],
        shaders: vec![0, 0],
    }
}

/// A ground, three leaves, a sun, a sky and a 40×30 camera; returns (plants, camera).
fn spawn_scene(world: &mut World) -> (Vec<Entity>, Entity) {
    let mut library = GeometryLibrary::default();
    let ground = library.add(Geometry::new("ground", quad(20.0), BuildParams::BALANCED).unwrap());
    let leaf = library.add(Geometry::new("leaf", quad(1.0), BuildParams::BALANCED).unwrap());
    world.insert_resource(library);
    world.spawn(Shader::color(ShaderId(0), Vec3::splat(0.6)));
    world.spawn((Transform::IDENTITY, Instance { geometry: ground }));
    let plants = (0..3)
        .map(|i| {
            let t = Transform::from_translation(Vec3::new(i as f32 * 2.5 - 2.5, 1.0, -3.0))
                .with_rotation(glam::Quat::from_rotation_x(1.2));
            world.spawn((t, Instance { geometry: leaf })).id()
        })
        .collect();
    common::spawn_sun_and_sky(world);
    let camera = world
        .spawn((
            Camera {
                width: 40,
                height: 30,
                samples_per_pixel: 1,
                light_samples: 1,
                ..Default::default()
            },
            Transform::looking_at(Vec3::new(0.0, 3.0, 8.0), Vec3::ZERO, Vec3::Y),
        ))
        .id();
    (plants, camera)
}

/// Adds what every optional stage works on: a swaying plant in a wind, an environment
/// light and a display filter on the camera.
fn add_optional_content(world: &mut World, plants: &[Entity], camera: Entity) {
    let rest = *world.get::<Transform>(plants[0]).unwrap();
    world
        .entity_mut(plants[0])
        .insert((Sway::new(40.0, 1.5, 2.0, 0.05).unwrap(), RestPose(rest)));
    world.insert_resource(Wind::default());
    world.spawn(EnvironmentLight::new(
        EnvironmentMap::constant(Vec3::splat(0.5)),
        4,
    ));
    world
        .entity_mut(camera)
        .insert(DiscontinuityFilter::for_pattern(4));
}

fn system_name(system: &dyn bevy_ecs::system::System<In = (), Out = ()>) -> String {
    stage_name(system)
        .unwrap_or("a program's system")
        .to_owned()
}

/// Runs `schedule` once and returns the names of the systems that ran (their last-run
/// tick moved), and the names of all installed systems.
fn run_and_list(
    world: &mut World,
    schedule: &mut Schedule,
) -> (BTreeSet<String>, BTreeSet<String>) {
    schedule.initialize(world).unwrap();
    let before: Vec<_> = schedule
        .systems()
        .unwrap()
        .map(|(_, s)| (system_name(s.as_ref()), s.get_last_run()))
        .collect();
    schedule.run(world);
    let after = schedule.systems().unwrap().map(|(_, s)| s.get_last_run());
    let ran = before
        .iter()
        .zip(after)
        .filter(|((_, tick), now)| tick != now)
        .map(|((name, _), _)| name.clone())
        .collect();
    let installed = before.into_iter().map(|(name, _)| name).collect();
    (ran, installed)
}

fn names(list: &[&str]) -> BTreeSet<String> {
    list.iter().map(|s| s.to_string()).collect()
}

#[test]
fn without_optional_stages_only_the_required_systems_are_installed_and_run() {
    let mut world = World::new();
    let mut schedule = Schedule::default();
    let options = RenderOptions {
        threads: 1,
        stages: Stages::NONE,
        ..Default::default()
    };
    install(&mut world, &mut schedule, &options).unwrap();
    let (plants, camera) = spawn_scene(&mut world);
    // The world has what every optional stage would work on; they are not installed.
    add_optional_content(&mut world, &plants, camera);
    world.entity_mut(camera).insert(FrameImage::new(0.0));
    let (ran, installed) = run_and_list(&mut world, &mut schedule);
    let required = names(&[
        "rebase_world_origin",
        "rebuild_top_level",
        "compile_shaders",
        "compile_lights",
        "render_tiles",
        "accumulate",
        "publish_frame_images",
    ]);
    let mut with_marks = required.clone();
    with_marks.insert("mark_stage".to_owned());
    assert_eq!(
        installed, with_marks,
        "the profile's stage marks are installed too"
    );
    assert_eq!(
        ran, required,
        "the first frame runs every installed system but the marks"
    );
    let (ran, _) = run_and_list(&mut world, &mut schedule);
    assert_eq!(
        ran,
        names(&[
            "rebase_world_origin",
            "render_tiles",
            "accumulate",
            "publish_frame_images"
        ]),
        "a static frame runs what it must"
    );
    assert_eq!(world.get::<Film>(camera).unwrap().frames(), 2);
}

#[test]
fn every_stage_runs_when_installed_and_the_scene_needs_it() {
    let mut world = World::new();
    let mut schedule = Schedule::default();
    let options = RenderOptions {
        threads: 1,
        ..Default::default()
    };
    install(&mut world, &mut schedule, &options).unwrap();
    let (plants, camera) = spawn_scene(&mut world);
    add_optional_content(&mut world, &plants, camera);
    let (ran, installed) = run_and_list(&mut world, &mut schedule);
    let optional = names(&[
        "animate",
        "adaptive_transparency_lod",
        "assign_light_subsets",
        "build_opacity_maps",
        "filter_display",
    ]);
    assert!(installed.is_superset(&optional), "{installed:?}");
    // No alpha-masked shader yet, but the opacity maps and the plan's transparency
    // follow the shader table, which the first frame fills.
    assert!(ran.is_superset(&optional), "{ran:?}");
    assert!(
        !ran.contains("publish_frame_images"),
        "no camera has a FrameImage"
    );
}

#[test]
fn light_subsets_run_without_the_transparency_stage_they_are_ordered_after() {
    let mut world = World::new();
    let mut schedule = Schedule::default();
    let options = RenderOptions {
        threads: 1,
        stages: Stages {
            environment: true,
            ..Stages::NONE
        },
        ..Default::default()
    };
    install(&mut world, &mut schedule, &options).unwrap();
    let (_, camera) = spawn_scene(&mut world);
    world
        .entity_mut(camera)
        .insert(sylva_engine::interleave::LightInterleave::default());
    // A sky brighter towards the zenith: median cut makes many lights of it.
    let texels = (0..16 * 8)
        .map(|i| Vec3::splat(1.0 + (8 - i / 16) as f32))
        .collect();
    let (map, _) = EnvironmentMap::new(16, 8, texels).unwrap();
    world.spawn(EnvironmentLight::new(map, 16));
    let (ran, installed) = run_and_list(&mut world, &mut schedule);
    assert!(
        !installed.contains("adaptive_transparency_lod"),
        "{installed:?}"
    );
    assert!(ran.contains("assign_light_subsets"), "{ran:?}");
    let plan = *world.get::<FramePlan>(camera).unwrap();
    assert!(
        plan.light_subsets.is_some() && plan.transparency.is_none(),
        "{plan:?}"
    );
}

#[test]
fn stages_needed_follow_the_worlds_content() {
    let mut world = World::new();
    let (plants, camera) = spawn_scene(&mut world);
    assert_eq!(Stages::needed_by(&mut world), Stages::NONE);
    add_optional_content(&mut world, &plants, camera);
    assert_eq!(
        Stages::needed_by(&mut world),
        Stages {
            alpha_masks: false,
            ..Stages::ALL
        }
    );
}

#[test]
fn a_scene_needing_no_optional_stage_renders_the_same_image_without_them() {
    let render = |stages| {
        let mut world = World::new();
        let mut schedule = Schedule::default();
        let options = RenderOptions {
            threads: 2,
            stages,
            ..Default::default()
        };
        install(&mut world, &mut schedule, &options).unwrap();
        let (_, camera) = spawn_scene(&mut world);
        for _ in 0..2 {
            schedule.run(&mut world);
        }
        world.get::<Film>(camera).unwrap().mean_rgb()
    };
    let all = render(Stages::ALL);
    assert_eq!(all, render(Stages::NONE));
    assert!(all.iter().any(|p| p[1] > 0.0), "the image is not black");
}

#[test]
fn a_programs_pool_renders_the_tiles_and_its_systems_order_against_the_stages() {
    let game_pool = Arc::new(
        rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .thread_name(|i| format!("game-worker-{i}"))
            .build()
            .unwrap(),
    );
    let mut world = World::new();
    let mut schedule = Schedule::default();
    let options = RenderOptions {
        pool: Some(game_pool.clone()),
        ..Default::default()
    };
    install(&mut world, &mut schedule, &options).unwrap();
    let (plants, camera) = spawn_scene(&mut world);
    world.entity_mut(camera).insert(FrameImage::new(0.0));
    let threads: Arc<Mutex<HashSet<String>>> = Arc::default();
    let record = threads.clone();
    world.insert_resource(TileProgress(Some(Arc::new(move |_| {
        let name = std::thread::current().name().unwrap_or("").to_owned();
        record.lock().unwrap().insert(name);
    }))));

    // The program's own systems: one moves a plant before the top level is prepared,
    // one reads the published image after the frame.
    #[derive(Resource, Default)]
    struct Seen(Vec<(u64, u64, u32)>);
    let moved = plants[1];
    let push = move |mut q: Query<&mut Transform>| {
        q.get_mut(moved).unwrap().translation.x += 0.5;
    };
    let read =
        move |images: Query<&FrameImage>, state: Res<TopLevelState>, mut seen: ResMut<Seen>| {
            let image = images.get(camera).unwrap();
            let lit = image.srgba8().chunks_exact(4).filter(|p| p[1] > 0).count() as u32;
            seen.0.push((state.rebuilds, state.refits, lit));
        };
    world.init_resource::<Seen>();
    schedule.add_systems((
        push.before(RenderSystems::Prepare),
        read.after(RenderSystems::Output),
    ));
    for _ in 0..3 {
        schedule.run(&mut world);
    }
    let seen = &world.resource::<Seen>().0;
    // Each frame's top level already holds that frame's move (a build, then refits),
    // and the reader sees the image of the same frame.
    assert_eq!(
        seen.iter().map(|s| (s.0, s.1)).collect::<Vec<_>>(),
        vec![(1, 0), (1, 1), (1, 2)]
    );
    assert!(seen.iter().all(|s| s.2 > 600), "{seen:?}");
    let threads = threads.lock().unwrap();
    assert!(!threads.is_empty());
    assert!(
        threads.iter().all(|t| t.starts_with("game-worker-")),
        "tiles ran on {threads:?}"
    );
    assert_eq!(world.resource::<RenderPool>().threads(), 2);
}

#[test]
fn an_enabled_profiler_times_every_stage_system_and_tile_of_each_frame() {
    use sylva_systems::profile::{FrameProfiler, ProfileLog, ProfiledSystem, TopLevelAction};
    let mut world = World::new();
    let mut schedule = Schedule::default();
    let options = RenderOptions {
        threads: 2,
        ..Default::default()
    };
    install(&mut world, &mut schedule, &options).unwrap();
    let (plants, _) = spawn_scene(&mut world);
    world.insert_resource(FrameProfiler::enabled());
    let mut log = ProfileLog::in_memory();
    let mut walls = Vec::new();
    for frame in 0..3 {
        if frame == 2 {
            world.get_mut::<Transform>(plants[1]).unwrap().translation.y += 0.1;
        }
        let start = std::time::Instant::now();
        schedule.run(&mut world);
        walls.push(start.elapsed());
        log.record(&world).unwrap();
    }
    let rows = log.rows();
    assert_eq!(rows.len(), 3);
    assert_eq!(
        rows.iter().map(|r| r.top_level).collect::<Vec<_>>(),
        vec![
            TopLevelAction::Rebuild,
            TopLevelAction::Kept,
            TopLevelAction::Refit
        ]
    );
    for (row, wall) in rows.iter().zip(&walls) {
        assert!(row.times.stages.iter().all(Option::is_some), "{row:?}");
        assert!(row.times.schedule() <= *wall, "stages within the run");
        let render = row.times.systems[ProfiledSystem::RenderTiles as usize].unwrap();
        assert!(render <= row.times.stages[3].unwrap());
        // 40×30 in 16-pixel tiles (the default size): 3 × 2 tiles, each timed.
        assert_eq!(row.times.tiles.len(), 6);
        let tiles: std::time::Duration = row.times.tiles.iter().map(|t| t.1).sum();
        assert!(
            tiles <= render * 2,
            "two workers: tiles {tiles:?}, render {render:?}"
        );
        assert!(row.counters.closest_rays >= 40 * 30);
    }
    let rebuilt = ProfiledSystem::RebuildTopLevel as usize;
    assert!(rows[0].times.systems[rebuilt].is_some());
    assert!(
        rows[1].times.systems[rebuilt].is_none(),
        "a static frame does not rebuild"
    );
    let summary = log.summary();
    for line in [
        "render ",
        "  render_tiles",
        "frame ",
        "1 rebuilds, 1 refits, 1 kept",
    ] {
        assert!(summary.contains(line), "{line:?} in\n{summary}");
    }
}
