//! Schedule tests: spawn a small world, run the frame schedule, assert on what ran.

mod common;

use bevy_ecs::prelude::*;
use glam::{Vec2, Vec3};
use std::collections::HashSet;
use std::sync::{Arc, Mutex};
use sylva_engine::bvh::BuildParams;
use sylva_engine::camera::Camera;
use sylva_engine::components::{Hidden, Instance, Transform};
use sylva_engine::film::Film;
use sylva_engine::geometry::{Geometry, GeometryLibrary};
use sylva_engine::light::LightSet;
use sylva_engine::mesh::TriangleMesh;
use sylva_engine::shading::{Shader, ShaderId};
use sylva_systems::*;

fn quad() -> TriangleMesh {
    TriangleMesh {
        positions: vec![
            Vec3::new(-1.0, 0.0, -1.0),
            Vec3::new(1.0, 0.0, -1.0),
            Vec3::new(1.0, 0.0, 1.0),
            Vec3::new(-1.0, 0.0, 1.0),
        ],
        normals: vec![Vec3::Y; 4],
        uvs: vec![Vec2::ZERO, Vec2::X, Vec2::ONE, Vec2::Y],
        indices: vec![[0, 2, 1], [0, 3, 2]],
        shaders: vec![0, 0],
    }
}

struct TestWorld {
    world: World,
    schedule: Schedule,
    plants: Vec<Entity>,
    camera: Entity,
}

fn test_world(threads: usize) -> TestWorld {
    let mut world = World::new();
    init_render_world(&mut world, threads).unwrap();
    let mut library = GeometryLibrary::default();
    let ground = library.add(
        Geometry::new(
            "ground",
            TriangleMesh {
                positions: quad().positions.iter().map(|p| *p * 20.0).collect(),
                ..quad()
            },
            BuildParams::BALANCED,
        )
        .unwrap(),
    );
    let leaf = library.add(Geometry::new("leaf", quad(), BuildParams::BALANCED).unwrap());
    world.insert_resource(library);
    world.spawn(Shader::color(ShaderId(0), Vec3::splat(0.6)));
    world.spawn((Transform::IDENTITY, Instance { geometry: ground }));
    let plants = (0..5)
        .map(|i| {
            let t = Transform::from_translation(Vec3::new(i as f32 * 2.5 - 5.0, 1.0, -3.0))
                .with_rotation(glam::Quat::from_rotation_x(1.2));
            world.spawn((t, Instance { geometry: leaf })).id()
        })
        .collect();
    common::spawn_sun_and_sky(&mut world);
    let camera = world
        .spawn((
            Camera {
                width: 48,
                height: 32,
                samples_per_pixel: 1,
                light_samples: 1,
                ..Default::default()
            },
            Transform::looking_at(Vec3::new(0.0, 3.0, 8.0), Vec3::ZERO, Vec3::Y),
        ))
        .id();
    TestWorld {
        world,
        schedule: frame_schedule(),
        plants,
        camera,
    }
}

impl TestWorld {
    fn run(&mut self) {
        self.schedule.run(&mut self.world);
    }
    fn rebuilds(&self) -> u64 {
        self.world.resource::<TopLevelState>().rebuilds
    }
    fn refits(&self) -> u64 {
        self.world.resource::<TopLevelState>().refits
    }
    fn film(&self) -> &Film {
        self.world.get::<Film>(self.camera).unwrap()
    }
}

#[test]
fn static_frames_rebuild_nothing_and_accumulate() {
    let mut w = test_world(2);
    w.run();
    assert_eq!(w.rebuilds(), 1, "the first frame builds the top level");
    assert_eq!(w.film().frames(), 1);
    for frame in 2..=4 {
        w.run();
        assert_eq!(w.rebuilds(), 1, "a static frame must not rebuild");
        assert_eq!(w.film().frames(), frame, "static frames accumulate");
    }
    assert_eq!(w.world.resource::<RenderStats>().frames, 4);
}

#[test]
fn an_environment_light_is_compiled_and_restarts_accumulation() {
    use sylva_engine::environment::{EnvironmentLight, EnvironmentMap};
    let mut w = test_world(2);
    w.run();
    w.run();
    assert_eq!(w.film().frames(), 2);
    assert!(w.world.resource::<LightSet>().environment.is_none());
    let map = EnvironmentMap::constant(Vec3::splat(0.5));
    let entity = w.world.spawn(EnvironmentLight::new(map, 4)).id();
    w.run();
    let lights = w.world.resource::<LightSet>();
    assert_eq!(lights.environment.as_ref().map(|e| e.lights.len()), Some(1));
    assert_eq!(w.film().frames(), 1, "new light, new accumulation");
    w.world.despawn(entity);
    w.run();
    assert!(w.world.resource::<LightSet>().environment.is_none());
    assert_eq!(w.film().frames(), 1);
}

#[test]
fn moving_one_plant_rebuilds_once_and_resets_accumulation() {
    let mut w = test_world(2);
    w.run();
    w.run();
    w.run();
    assert_eq!(w.film().frames(), 3);
    let resets = w.film().resets();
    w.world
        .get_mut::<Transform>(w.plants[2])
        .unwrap()
        .translation
        .x += 0.5;
    w.run();
    assert_eq!(
        (w.rebuilds(), w.refits()),
        (1, 1),
        "moving one plant a little runs exactly one refit"
    );
    assert_eq!(w.film().frames(), 1, "accumulation restarted");
    assert_eq!(w.film().resets(), resets + 1);
    w.run();
    assert_eq!((w.rebuilds(), w.refits()), (1, 1));
    assert_eq!(w.film().frames(), 2);
    // Far away, the plant's old leaf would span the scene: the refitted tree degrades past
    // the limit and is rebuilt.
    w.world
        .get_mut::<Transform>(w.plants[2])
        .unwrap()
        .translation
        .z -= 500.0;
    w.run();
    let state = w.world.resource::<TopLevelState>();
    assert_eq!(
        (state.rebuilds, state.refits, state.degraded_rebuilds),
        (2, 1, 1)
    );
    assert_eq!(state.degradation, 1.0);
}

#[test]
fn hiding_removing_and_camera_moves_are_noticed() {
    let mut w = test_world(1);
    w.run();
    w.world.entity_mut(w.plants[0]).insert(Hidden);
    w.run();
    assert_eq!(
        (w.rebuilds(), w.film().frames()),
        (2, 1),
        "hiding rebuilds and resets"
    );
    assert_eq!(
        w.world.resource::<sylva_engine::tlas::TopLevel>().len(),
        5,
        "ground + 4 visible plants"
    );
    w.world.entity_mut(w.plants[0]).remove::<Hidden>();
    w.run();
    assert_eq!(
        (
            w.rebuilds(),
            w.world.resource::<sylva_engine::tlas::TopLevel>().len()
        ),
        (3, 6)
    );
    w.world.despawn(w.plants[1]);
    w.run();
    assert_eq!(
        (
            w.rebuilds(),
            w.world.resource::<sylva_engine::tlas::TopLevel>().len()
        ),
        (4, 5)
    );
    w.run();
    assert_eq!(w.film().frames(), 2);
    // The camera moving resets the film but rebuilds nothing.
    w.world
        .get_mut::<Transform>(w.camera)
        .unwrap()
        .translation
        .y += 0.1;
    w.run();
    assert_eq!((w.rebuilds(), w.film().frames()), (4, 1));
    // A shader edit recompiles shaders and resets, without a rebuild.
    let mut q = w.world.query::<&mut Shader>();
    q.single_mut(&mut w.world).unwrap().base_color = Vec3::splat(0.2);
    w.run();
    w.run();
    assert_eq!((w.rebuilds(), w.film().frames()), (4, 2));
}

#[test]
fn accumulated_frames_differ_from_a_single_frame() {
    // Progressive frames draw new random numbers: two frames are not the same frame twice.
    let mut w = test_world(2);
    w.run();
    let one = w.film().mean_rgb();
    w.run();
    let two = w.film().mean_rgb();
    assert_ne!(one, two);
}

#[test]
fn images_do_not_depend_on_the_thread_count() {
    let mut images = Vec::new();
    for threads in [1, 2, 4] {
        let mut w = test_world(threads);
        w.run();
        w.run();
        images.push(w.film().mean_rgb());
    }
    assert!(
        images.iter().flatten().any(|p| p.iter().any(|&c| c > 0.0)),
        "the image is not black"
    );
    assert_eq!(images[0], images[1]);
    assert_eq!(images[0], images[2]);
}

#[test]
fn data_parallel_work_runs_only_on_the_render_pool() {
    // Every tile must run on a `sylva-worker-*` thread of the one pool, never on bevy's
    // task pool threads, so the cores are shared by exactly `threads` busy workers.
    let threads = 2;
    let mut w = test_world(threads);
    let seen: Arc<Mutex<HashSet<String>>> = Arc::default();
    let record = seen.clone();
    w.world
        .insert_resource(TileProgress(Some(Arc::new(move |_| {
            let name = std::thread::current()
                .name()
                .unwrap_or("<unnamed>")
                .to_owned();
            record.lock().unwrap().insert(name);
        }))));
    for _ in 0..3 {
        w.run();
    }
    let seen = seen.lock().unwrap();
    assert!(!seen.is_empty());
    for name in seen.iter() {
        assert!(
            name.starts_with("sylva-worker-"),
            "tile rendered on thread '{name}'"
        );
    }
    assert!(seen.len() <= threads);
}

#[test]
fn planning_stages_follow_the_scene_and_restart_accumulation_only_on_change() {
    use sylva_engine::environment::{EnvironmentLight, EnvironmentMap};
    use sylva_engine::interleave::LightInterleave;
    use sylva_engine::render::FramePlan;
    use sylva_engine::shading::Texture;
    use sylva_engine::transparency::TransparencyCurve;
    let mut w = test_world(2);
    let curve = TransparencyCurve::default();
    w.world
        .entity_mut(w.camera)
        .insert((curve, LightInterleave::default()));
    let plan = |w: &TestWorld| *w.world.get::<FramePlan>(w.camera).unwrap();
    w.run();
    assert_eq!(
        plan(&w),
        FramePlan::default(),
        "no alpha masks, no virtual lights"
    );

    let mask = Texture::from_srgba8(2, 1, vec![[90, 160, 60, 255], [0, 0, 0, 0]]).unwrap();
    w.world.spawn(Shader::alpha_masked(
        ShaderId(1),
        Vec3::ONE,
        Arc::new(mask),
        0.5,
    ));
    w.run();
    assert_eq!(plan(&w).transparency, Some(curve));
    assert_eq!(w.film().frames(), 1, "a new plan restarts accumulation");
    w.run();
    assert_eq!(w.film().frames(), 2, "an unchanged plan keeps accumulating");

    let texels = (0..32)
        .map(|i| Vec3::splat(0.1 + i as f32 * 0.05))
        .collect();
    let map = EnvironmentMap::new(8, 4, texels).unwrap().0;
    w.world.spawn(EnvironmentLight::new(map, 32));
    w.run();
    let subsets = plan(&w).light_subsets.expect("virtual lights get subsets");
    assert_eq!((subsets.pattern, subsets.count), (4, 16));
    assert!(subsets.offset < 16);
    w.run();
    assert_eq!(w.film().frames(), 2);

    w.world
        .entity_mut(w.camera)
        .remove::<(LightInterleave, TransparencyCurve)>();
    w.run();
    assert_eq!(plan(&w), FramePlan::default());
    assert_eq!(w.film().frames(), 1);
}

/// A world with one swaying plant (and its camera), advancing `frame_seconds` per frame.
fn swaying_world(frame_seconds: f64) -> (TestWorld, Entity) {
    use sylva_engine::sway::{AnimationClock, RestPose, Sway, Wind};
    let mut w = test_world(1);
    let plant = w.plants[2];
    let rest = *w.world.get::<Transform>(plant).unwrap();
    let sway = Sway::new(40.0, 1.5, 2.0, 0.05).unwrap();
    w.world.entity_mut(plant).insert((sway, RestPose(rest)));
    w.world.insert_resource(Wind::default());
    w.world.resource_mut::<AnimationClock>().frame_seconds = frame_seconds;
    (w, plant)
}

#[test]
fn sway_gives_the_same_transforms_at_30_and_60_fps() {
    let (mut at30, plant30) = swaying_world(1.0 / 30.0);
    let (mut at60, plant60) = swaying_world(1.0 / 60.0);
    let rest = *at30.world.get::<Transform>(plant30).unwrap();
    for second in 1..=2 {
        for _ in 0..30 {
            at30.run();
        }
        for _ in 0..60 {
            at60.run();
        }
        let a = *at30.world.get::<Transform>(plant30).unwrap();
        let b = *at60.world.get::<Transform>(plant60).unwrap();
        assert_eq!(a, b, "after {second} s");
        assert_ne!(a, rest, "the wind moved the plant");
    }
    // Every frame moves the plant, so every frame updates the top level: one build,
    // then refits.
    assert_eq!((at30.rebuilds(), at30.refits()), (1, 59));
}

/// A world whose five plants all sway, refitting the top level up to `refit_limit`.
fn swaying_plants(refit_limit: f32) -> TestWorld {
    use sylva_engine::sway::{AnimationClock, RestPose, Sway, Wind};
    let mut w = test_world(2);
    w.world.resource_mut::<BuildSettings>().refit_limit = refit_limit;
    for (i, &plant) in w.plants.iter().enumerate() {
        let rest = *w.world.get::<Transform>(plant).unwrap();
        let sway = Sway::new(20.0 + 10.0 * i as f64, 1.0, 2.0, 0.2).unwrap();
        w.world.entity_mut(plant).insert((sway, RestPose(rest)));
    }
    w.world.insert_resource(Wind {
        strength: 20.0,
        ..Wind::default()
    });
    w.world.resource_mut::<AnimationClock>().frame_seconds = 1.0 / 30.0;
    w
}

#[test]
fn a_refitted_top_level_renders_what_a_rebuilt_one_renders() {
    let mut refitting = swaying_plants(BuildSettings::REFIT_LIMIT);
    let mut rebuilding = swaying_plants(0.0);
    for frame in 0..30 {
        refitting.run();
        rebuilding.run();
        assert_eq!(
            refitting.film().mean_rgb(),
            rebuilding.film().mean_rgb(),
            "frame {frame}"
        );
    }
    assert_eq!((rebuilding.rebuilds(), rebuilding.refits()), (30, 0));
    let state = refitting.world.resource::<TopLevelState>();
    assert_eq!(state.rebuilds + state.refits, 30);
    assert!(state.refits >= 20, "{state:?}");
    assert!(state.degradation <= BuildSettings::REFIT_LIMIT);
    let moved = refitting
        .plants
        .iter()
        .filter(|&&p| {
            let rest = refitting
                .world
                .get::<sylva_engine::sway::RestPose>(p)
                .unwrap();
            (refitting.world.get::<Transform>(p).unwrap().rotation).angle_between(rest.0.rotation)
                > 0.01
        })
        .count();
    assert!(moved >= 3, "the wind must move the plants: {moved}");
}

#[test]
fn a_thousandfold_gust_stays_bounded_and_a_nan_wind_is_ignored() {
    use sylva_engine::sway::{MAX_TILT, Sway, Wind};
    let (mut w, plant) = swaying_world(1.0 / 30.0);
    for _ in 0..10 {
        w.run();
    }
    w.world.resource_mut::<Wind>().strength = 1000.0;
    w.run();
    w.world.resource_mut::<Wind>().strength = 1.0;
    for _ in 0..90 {
        w.run();
        let sway = w.world.get::<Sway>(plant).unwrap();
        assert!(sway.angle.is_finite() && sway.velocity.is_finite());
        let t = w.world.get::<Transform>(plant).unwrap();
        assert!(t.rotation.is_finite() && t.rotation.is_normalized());
        let (_, tilt) = sway.tilt().to_axis_angle();
        assert!(tilt <= MAX_TILT + 1e-4, "tilt {tilt}");
    }
    assert!(w.film().frames() >= 1);

    let before = *w.world.get::<Sway>(plant).unwrap();
    w.world.resource_mut::<Wind>().speed = f32::NAN;
    w.run();
    let after = *w.world.get::<Sway>(plant).unwrap();
    assert!(after.angle.is_finite() && after.velocity.is_finite());
    assert!(
        after.energy() <= before.energy() + 1e-12,
        "no wind, no energy gained"
    );
}

/// The film's mean pixels.
fn pixels(w: &TestWorld) -> Vec<[f32; 3]> {
    w.film().mean_rgb()
}

#[test]
fn the_progressive_driver_stops_at_the_frame_count_and_matches_a_plain_loop() {
    let mut plain = test_world(2);
    for _ in 0..3 {
        plain.run();
    }
    let mut w = test_world(1);
    let mut seen = Vec::new();
    let stop = StopAt {
        frames: Some(3),
        ..StopAt::default()
    };
    let (stopped, progress) = refine(&mut w.world, &mut w.schedule, w.camera, &stop, |_, p| {
        seen.push((p.frames, p.rendered, p.restarted));
        Flow::Continue
    });
    assert_eq!(stopped, Stopped::Frames);
    assert_eq!(seen, [(1, 1, false), (2, 2, false), (3, 3, false)]);
    assert_eq!(progress.frames, 3);
    assert!(pixels(&w) == pixels(&plain), "the driver changed the image");
    // A second run continues the film up to its new count; with no count and no
    // budget, one frame.
    let (_, progress) = refine(
        &mut w.world,
        &mut w.schedule,
        w.camera,
        &StopAt::default(),
        |_, _| Flow::Continue,
    );
    assert_eq!((progress.frames, progress.rendered), (4, 1));
}

#[test]
fn the_progressive_driver_stops_on_interrupt_budget_and_caller() {
    let mut w = test_world(2);
    let flag = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let stop = StopAt {
        frames: Some(100),
        interrupt: Some(flag.clone()),
        ..StopAt::default()
    };
    let mut calls = 0;
    let (stopped, progress) = refine(&mut w.world, &mut w.schedule, w.camera, &stop, |_, p| {
        calls += 1;
        if p.frames == 2 {
            flag.store(true, std::sync::atomic::Ordering::SeqCst);
        }
        Flow::Continue
    });
    assert_eq!(stopped, Stopped::Interrupted);
    assert_eq!(
        (progress.frames, calls),
        (3, 2),
        "the interrupted frame is kept, not reported"
    );

    let stop = StopAt {
        frames: Some(1000),
        budget: Some(std::time::Duration::ZERO),
        ..StopAt::default()
    };
    let (stopped, progress) = refine(&mut w.world, &mut w.schedule, w.camera, &stop, |_, _| {
        Flow::Continue
    });
    assert_eq!((stopped, progress.rendered), (Stopped::Budget, 1));

    let stop = StopAt {
        frames: Some(1000),
        ..StopAt::default()
    };
    let (stopped, progress) = refine(&mut w.world, &mut w.schedule, w.camera, &stop, |_, p| {
        if p.rendered == 2 {
            Flow::Stop
        } else {
            Flow::Continue
        }
    });
    assert_eq!((stopped, progress.rendered), (Stopped::Caller, 2));
}

#[test]
fn the_progressive_driver_reports_a_restart_when_the_camera_moves() {
    let mut w = test_world(2);
    let camera = w.camera;
    let stop = StopAt {
        frames: Some(5),
        ..StopAt::default()
    };
    let mut seen = Vec::new();
    let (stopped, progress) = refine(&mut w.world, &mut w.schedule, camera, &stop, |world, p| {
        seen.push((p.frames, p.restarted));
        if p.rendered == 3 {
            world.get_mut::<Transform>(camera).unwrap().translation.x += 0.5;
        }
        Flow::Continue
    });
    assert_eq!(stopped, Stopped::Frames);
    assert_eq!(
        seen,
        [
            (1, false),
            (2, false),
            (3, false),
            (1, true),
            (2, false),
            (3, false),
            (4, false),
            (5, false)
        ]
    );
    assert_eq!(progress.rendered, 8);
}

#[test]
fn the_live_render_shows_what_a_plain_render_makes_and_restarts_on_a_move() {
    use std::sync::mpsc;
    use std::time::Duration;
    use sylva_systems::live::{LiveCommand, LiveRender, ShownImage};
    let moved = Transform::looking_at(Vec3::new(2.0, 4.0, 7.0), Vec3::ZERO, Vec3::Y);
    let mut reference = test_world(1);
    *reference
        .world
        .get_mut::<Transform>(reference.camera)
        .unwrap() = moved;
    let stop = StopAt {
        frames: Some(3),
        ..StopAt::default()
    };
    let camera = reference.camera;
    refine(
        &mut reference.world,
        &mut reference.schedule,
        camera,
        &stop,
        |_, _| Flow::Continue,
    );
    let expected = ShownImage::of_film(reference.film(), None, 0.0);

    let w = test_world(2);
    let (ready, frames) = mpsc::channel();
    let mut live = LiveRender::start(w.world, w.camera, 3, move || {
        let _ = ready.send(());
    })
    .unwrap();
    frames
        .recv_timeout(Duration::from_secs(60))
        .expect("a first frame");
    let command = live.send(LiveCommand::Pose(moved)).unwrap();
    let mut after_move = Vec::new();
    let shown = loop {
        frames
            .recv_timeout(Duration::from_secs(60))
            .expect("frames after the move");
        let Some(image) = live.take_latest() else {
            continue;
        };
        if image.applied >= command {
            after_move.push(image.frames);
            if image.frames == 3 {
                break image;
            }
        }
    };
    // The move restarted the film: the frames after it count from 1.
    assert!(
        after_move.iter().all(|&f| (1..=3).contains(&f)),
        "{after_move:?}"
    );
    assert_eq!((shown.width, shown.height), (48, 32));
    assert_eq!(shown.pixels, expected.pixels);
    // At the frame limit the thread rests until told something.
    assert!(frames.recv_timeout(Duration::from_millis(500)).is_err());
    let world = live.stop().expect("the render thread ends cleanly");
    assert_eq!(world.get::<Film>(w.camera).unwrap().frames(), 3);
}

#[test]
fn a_cancelled_frame_leaves_the_film_and_the_next_one_restarts_it_after_a_move() {
    use std::sync::atomic::{AtomicBool, Ordering};
    let mut w = test_world(2);
    w.run();
    w.run();
    let before = pixels(&w);
    let flag = Arc::new(AtomicBool::new(true));
    w.world.insert_resource(FrameCancel(Some(flag.clone())));
    let moved = Transform::looking_at(Vec3::new(-2.0, 2.0, 9.0), Vec3::ZERO, Vec3::Y);
    *w.world.get_mut::<Transform>(w.camera).unwrap() = moved;
    let camera = w.camera;
    let (_, progress) = refine(
        &mut w.world,
        &mut w.schedule,
        camera,
        &StopAt::default(),
        |_, _| Flow::Stop,
    );
    assert_eq!((progress.rendered, progress.cancelled), (0, 1));
    assert!(!progress.restarted);
    assert_eq!(w.film().frames(), 2);
    assert_eq!(pixels(&w), before, "a cancelled frame changed the film");
    assert_eq!(w.world.resource::<RenderStats>().cancelled, 1);

    // The move is still owed: the next complete frame starts the film again, as a
    // world that never saw the cancelled frame does.
    flag.store(false, Ordering::SeqCst);
    w.run();
    assert_eq!(w.film().frames(), 1);
    let mut fresh = test_world(2);
    *fresh.world.get_mut::<Transform>(fresh.camera).unwrap() = moved;
    fresh.run();
    assert_eq!(pixels(&w), pixels(&fresh));
}

#[test]
fn a_render_thread_that_panics_wakes_the_window_and_says_why() {
    use std::sync::mpsc;
    use std::time::Duration;
    use sylva_systems::live::{LiveCommand, LiveRender};
    let w = test_world(1);
    let (ready, wakes) = mpsc::channel();
    let mut live = LiveRender::start(w.world, w.camera, 2, move || {
        let _ = ready.send(());
    })
    .unwrap();
    live.send(LiveCommand::Edit(Arc::new(|_: &mut World| {
        panic!("an edit went wrong")
    })));
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    while live.failure().is_none() {
        assert!(std::time::Instant::now() < deadline, "no failure reported");
        wakes
            .recv_timeout(Duration::from_secs(30))
            .expect("the window is woken");
    }
    assert_eq!(live.failure().as_deref(), Some("an edit went wrong"));
    assert!(
        live.stop().is_none(),
        "a panicked thread hands back no world"
    );
}

#[test]
fn a_first_frame_cancelled_before_the_film_exists_leaves_nothing_to_filter() {
    // A viewer's command can arrive during a new world's first frame (a scene opened
    // with the camera kept where it was): the frame is given up while the film is still
    // empty, and the display filter must not run over an empty image.
    use std::sync::atomic::{AtomicBool, Ordering};
    let mut w = test_world(2);
    Quality::interactive().apply(&mut w.world, w.camera);
    let flag = Arc::new(AtomicBool::new(true));
    w.world.insert_resource(FrameCancel(Some(flag.clone())));
    w.run();
    assert_eq!(w.world.resource::<RenderStats>().cancelled, 1);
    flag.store(false, Ordering::SeqCst);
    w.run();
    assert_eq!(w.film().frames(), 1);
    assert!(
        w.world.resource::<RenderStats>().last_filter > std::time::Duration::ZERO,
        "the display filter's time is reported"
    );
    let mut fresh = test_world(2);
    Quality::interactive().apply(&mut fresh.world, fresh.camera);
    fresh.run();
    assert_eq!(pixels(&w), pixels(&fresh));
}

#[test]
fn picking_names_the_entity_whose_surface_the_pixel_shows() {
    use sylva_systems::picking::pick;
    let mut w = test_world(1);
    w.run();
    let ground = w
        .world
        .query_filtered::<Entity, With<Instance>>()
        .iter(&w.world)
        .find(|e| !w.plants.contains(e))
        .unwrap();
    let (mut plant_pixels, mut ground_pixels, mut sky_pixels) = (Vec::new(), 0, 0);
    for y in 0..32 {
        for x in 0..48 {
            let Some(picked) = pick(&w.world, w.camera, x, y) else {
                sky_pixels += 1;
                continue;
            };
            let transform = w.world.get::<Transform>(picked.entity).unwrap();
            // The hit point lies on the picked entity's quad (object-space y = 0 within
            // the quad's half-size, 20 for the ground and 1 for a leaf).
            let local = transform
                .to_affine()
                .inverse()
                .transform_point3(picked.point);
            let half = if picked.entity == ground { 20.0 } else { 1.0 };
            assert!(local.y.abs() < 1e-3, "({x}, {y}): {local}");
            assert!(local.x.abs() <= half + 1e-3 && local.z.abs() <= half + 1e-3);
            assert!(picked.distance > 0.0);
            if picked.entity == ground {
                ground_pixels += 1;
            } else {
                assert!(w.plants.contains(&picked.entity));
                plant_pixels.push((x, y, picked.entity));
            }
        }
    }
    assert!(ground_pixels > 100 && plant_pixels.len() > 20 && sky_pixels > 20);
    assert!(
        pick(&w.world, w.camera, 48, 0).is_none(),
        "outside the image"
    );

    // A removed plant is not picked once the top level is rebuilt.
    let (x, y, plant) = plant_pixels[plant_pixels.len() / 2];
    w.world.despawn(plant);
    w.run();
    assert_ne!(
        pick(&w.world, w.camera, x, y).map(|p| p.entity),
        Some(plant)
    );
}

#[test]
fn the_map_lists_every_plant_with_its_crown_and_not_the_ground() {
    use sylva_engine::components::Layer;
    use sylva_systems::picking::map_plants;
    let mut w = test_world(1);
    for &plant in &w.plants {
        w.world.entity_mut(plant).insert(Layer(0));
    }
    let map = map_plants(&mut w.world);
    assert_eq!(map.len(), w.plants.len());
    for entry in &map {
        let t = w.world.get::<Transform>(entry.entity).unwrap();
        assert_eq!(entry.position, Vec2::new(t.translation.x, t.translation.z));
        // The leaf quad is 2 m wide: a crown radius of 1 m at scale 1.
        assert!((entry.radius - 1.0).abs() < 1e-3, "{}", entry.radius);
    }
}

/// Images `from..to` of a swaying test world's sequence at 10 fps, 2 frames each,
/// rendered after skipping the images before `from`.
fn sequence_images(threads: usize, from: u32, to: u32) -> Vec<Vec<[f32; 3]>> {
    use sylva_engine::sway::{RestPose, Sway, Wind};
    use sylva_systems::animation::Sequence;
    let mut w = test_world(threads);
    for &plant in &w.plants {
        let rest = *w.world.get::<Transform>(plant).unwrap();
        w.world
            .entity_mut(plant)
            .insert((Sway::new(40.0, 1.5, 2.0, 0.05).unwrap(), RestPose(rest)));
    }
    w.world.insert_resource(Wind::default());
    let sequence = Sequence {
        fps: 10.0,
        frames_per_image: 2,
        seed: 7,
    };
    render_sequence(&mut w, &sequence, from, to, |w| {
        assert_eq!(w.film().frames(), 2);
        pixels(w)
    })
}

/// Images `from..to` of `sequence` in `w`, after skipping the images before `from`,
/// each read by `read` once rendered.
fn render_sequence<T>(
    w: &mut TestWorld,
    sequence: &sylva_systems::animation::Sequence,
    from: u32,
    to: u32,
    mut read: impl FnMut(&TestWorld) -> T,
) -> Vec<T> {
    sequence.skip(&mut w.world, 0, from.saturating_sub(1));
    let camera = w.camera;
    (from..to)
        .map(|index| {
            let stopped = sequence.render_image(
                &mut w.world,
                &mut w.schedule,
                camera,
                index,
                &StopAt::default(),
                |_, _| Flow::Continue,
            );
            assert_eq!(stopped, Stopped::Frames);
            read(w)
        })
        .collect()
}

#[test]
fn a_sequence_resumed_at_any_image_or_on_any_threads_gives_the_same_images() {
    let whole = sequence_images(1, 0, 4);
    for (i, pair) in whole.windows(2).enumerate() {
        assert_ne!(pair[0], pair[1], "images {i} and {} are the same", i + 1);
    }
    assert_eq!(sequence_images(2, 0, 4), whole, "on 2 threads");
    for from in [1, 3] {
        assert_eq!(
            sequence_images(2, from, 4),
            whole[from as usize..],
            "resumed at image {from}"
        );
    }
    assert_eq!(
        sylva_systems::animation::Sequence {
            fps: 30.0,
            frames_per_image: 1,
            seed: 0
        }
        .images(2.0),
        60
    );
}

/// The camera path of the path tests: three keys over 0.5 s, looking at the origin.
fn test_camera_path() -> sylva_engine::camera_path::CameraPath {
    use sylva_engine::camera_path::{CameraKey, CameraPath, PathInterpolation};
    let key = |time: f64, eye: Vec3, fov: f32| CameraKey {
        time,
        position: eye,
        rotation: Transform::looking_at(eye, Vec3::ZERO, Vec3::Y).rotation,
        vertical_fov: fov,
    };
    CameraPath::new(
        vec![
            key(0.0, Vec3::new(0.0, 3.0, 8.0), 0.8),
            key(0.2, Vec3::new(3.0, 2.0, 7.0), 0.9),
            key(0.5, Vec3::new(6.0, 4.0, 4.0), 0.7),
        ],
        PathInterpolation::CatmullRom,
    )
    .unwrap()
}

/// Images `from..to` at 10 fps of the test world with its camera flying a path (nothing
/// sways), with the camera's pose at each.
fn path_images(from: u32, to: u32) -> Vec<(Vec<[f32; 3]>, Transform, f32)> {
    use sylva_systems::animation::Sequence;
    let mut w = test_world(2);
    w.world.entity_mut(w.camera).insert(test_camera_path());
    let sequence = Sequence {
        fps: 10.0,
        frames_per_image: 1,
        seed: 3,
    };
    render_sequence(&mut w, &sequence, from, to, |w| {
        let pose = *w.world.get::<Transform>(w.camera).unwrap();
        let fov = w.world.get::<Camera>(w.camera).unwrap().vertical_fov;
        (pixels(w), pose, fov)
    })
}

#[test]
fn a_camera_on_a_path_is_where_the_path_is_at_each_images_time_also_after_a_resume() {
    let whole = path_images(0, 6);
    // The path evaluated at image k's time k / 10 s.
    let path = test_camera_path();
    for (k, (_, pose, fov)) in whole.iter().enumerate() {
        let (position, rotation, expected_fov) = path.at(k as f64 / 10.0);
        assert!((pose.translation - position).length() < 1e-4, "image {k}");
        assert!(pose.rotation.angle_between(rotation) < 1e-4, "image {k}");
        assert_eq!(*fov, expected_fov, "image {k}");
    }
    assert_ne!(whole[0].0, whole[1].0, "the camera moved");
    for from in [2, 5] {
        let resumed = path_images(from, 6);
        for (a, b) in resumed.iter().zip(&whole[from as usize..]) {
            assert_eq!(a.0, b.0, "resumed at image {from}: the same image");
            assert_eq!(a.1, b.1);
        }
    }
}
