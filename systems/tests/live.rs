//! The live render thread behind a window: poses sent faster than frames finish still
//! produce frames (each showing a newer pose), and a refining frame is still given up
//! for a new pose.

mod common;

use bevy_ecs::prelude::*;
use glam::{Vec2, Vec3};
use std::time::{Duration, Instant};
use sylva_engine::bvh::BuildParams;
use sylva_engine::camera::Camera;
use sylva_engine::components::{Instance, Transform};
use sylva_engine::geometry::{Geometry, GeometryLibrary};

use sylva_engine::mesh::TriangleMesh;
use sylva_engine::shading::{Shader, ShaderId};
use sylva_systems::init_render_world;
use sylva_systems::live::{LiveCommand, LiveRender, ShownImage};

/// A ground and a cloud of small triangles in front of a 160×120 camera at 4 samples a
/// pixel and 4 light samples: a frame takes milliseconds, far longer than the pose
/// interval the tests send at.
fn world_with_camera() -> (World, Entity) {
    let mut world = World::new();
    init_render_world(&mut world, 2).unwrap();
    let mut mesh = TriangleMesh {
        positions: vec![
            Vec3::new(-50.0, 0.0, -50.0),
            Vec3::new(50.0, 0.0, -50.0),
            Vec3::new(50.0, 0.0, 50.0),
            Vec3::new(-50.0, 0.0, 50.0),
        ],
        normals: vec![Vec3::Y; 4],
        uvs: vec![Vec2::ZERO; 4],
        indices: vec![[0, 2, 1], [0, 3, 2]],
        shaders: vec![0, 0],
    };
    let mut state = 1u32;
    let mut next = || {
        state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
        (state >> 8) as f32 / (1u32 << 24) as f32
    };
    for _ in 0..20_000 {
        let centre = Vec3::new(next() * 20.0 - 10.0, next() * 4.0, next() * 20.0 - 10.0);
        let first = mesh.positions.len() as u32;
        for _ in 0..3 {
            mesh.positions
                .push(centre + Vec3::new(next(), next(), next()) * 0.3);
            mesh.normals.push(Vec3::Y);
            mesh.uvs.push(Vec2::ZERO);
        }
        mesh.indices.push([first, first + 1, first + 2]);
        mesh.shaders.push(0);
    }
    let mut library = GeometryLibrary::default();
    let geometry = library.add(Geometry::new("cloud", mesh, BuildParams::BALANCED).unwrap());
    world.insert_resource(library);
    world.spawn(Shader::color(ShaderId(0), Vec3::splat(0.6)));
    world.spawn((Transform::IDENTITY, Instance { geometry }));
    common::spawn_sun_and_sky(&mut world);
    let camera = world
        .spawn((
            Camera {
                width: 160,
                height: 120,
                samples_per_pixel: 4,
                light_samples: 4,
                ..Default::default()
            },
            pose(0),
        ))
        .id();
    (world, camera)
}

/// The camera's `i`-th pose along a slow walk.
fn pose(i: u32) -> Transform {
    let eye = Vec3::new(i as f32 * 0.01, 2.0, 14.0);
    Transform::looking_at(eye, Vec3::new(0.0, 1.0, 0.0), Vec3::Y)
}

#[test]
fn poses_sent_faster_than_frames_finish_still_produce_frames() {
    let (world, camera) = world_with_camera();
    let mut live = LiveRender::start(world, camera, 64, || {}).unwrap();
    // The first frame, and how long one takes.
    let started = Instant::now();
    let first = loop {
        if let Some(image) = live.take_latest() {
            break image;
        }
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "no first frame"
        );
        std::thread::sleep(Duration::from_millis(1));
    };
    assert!(
        first.frame_time > Duration::from_millis(4),
        "a frame of {:?} is too quick for this test",
        first.frame_time
    );
    // A new pose every millisecond for as long as 15 frames take.
    let stream = first.frame_time * 15;
    let (start, mut i) = (Instant::now(), 0);
    let mut shown: Vec<ShownImage> = Vec::new();
    while start.elapsed() < stream {
        i += 1;
        live.send(LiveCommand::Pose(pose(i))).unwrap();
        if let Some(image) = live.take_latest() {
            shown.push(image);
        }
        std::thread::sleep(Duration::from_millis(1));
    }
    let log = live.frame_log();
    live.stop().unwrap();
    // Frames kept coming, each showing poses sent while the one before it rendered.
    assert!(
        shown.len() >= 5,
        "{} frames shown while {i} poses arrived over {stream:?} ({} given up)",
        shown.len(),
        log.cancelled
    );
    assert!(shown.windows(2).all(|w| w[1].applied > w[0].applied));
    assert!(
        shown.iter().all(|image| image.frames == 1),
        "each frame a new view"
    );
}

#[test]
fn a_frame_refining_the_shown_view_is_given_up_for_a_new_pose() {
    let (world, camera) = world_with_camera();
    let mut live = LiveRender::start(world, camera, 1000, || {}).unwrap();
    let started = Instant::now();
    let wait_for = |live: &LiveRender, done: &dyn Fn(&ShownImage) -> bool| loop {
        if let Some(image) = live.take_latest()
            && done(&image)
        {
            return image;
        }
        assert!(started.elapsed() < Duration::from_secs(120), "timed out");
        std::thread::sleep(Duration::from_millis(1));
    };
    // Five times: let the view rest and refine, then move it. A pose that arrives while
    // a refining frame renders gives that frame up (one may arrive between frames).
    for step in 1..=5 {
        wait_for(&live, &|image| image.frames >= 2);
        let sent = live.send(LiveCommand::Pose(pose(100 * step))).unwrap();
        let moved = wait_for(&live, &|image| image.applied >= sent);
        assert_eq!(moved.frames, 1, "the new view starts its own accumulation");
    }
    let log = live.frame_log();
    live.stop().unwrap();
    assert!(log.cancelled >= 1, "no refining frame was given up");
}
