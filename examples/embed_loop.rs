//! A game-style loop that owns a `World`, spawns the default scene through the library
//! API, moves the camera a little each tick, runs the frame schedule and prints per-frame
//! times. Run with `cargo run --release --example embed_loop -- [frames]`.

use std::time::Instant;
use sylva::prelude::*;

fn main() {
    let frames: u32 = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(20);
    let mut world = World::new();
    init_render_world(&mut world, 0).expect("worker threads start");
    let pool = world.resource::<RenderPool>().clone();
    let mut scene = pool
        .install(|| build_scene("meadow", 0))
        .expect("the meadow builds");
    // A small interactive view: 1 sample per pixel, 1 sky ray.
    scene.camera.width = 320;
    scene.camera.height = 240;
    scene.camera.samples_per_pixel = 1;
    scene.camera.light_samples = 1;
    let spawned = spawn(&mut world, scene);
    let mut schedule = frame_schedule();

    println!("frame  time_ms  accumulated  rays");
    for tick in 0..frames {
        // Move for the first half, then hold still so frames accumulate.
        if tick < frames / 2 {
            let mut transform = world
                .get_mut::<Transform>(spawned.camera)
                .expect("the camera exists");
            transform.translation.x += 0.05;
            transform.rotation = Quat::from_rotation_y(0.002) * transform.rotation;
        }
        let start = Instant::now();
        schedule.run(&mut world);
        let elapsed = start.elapsed();
        let film = world
            .get::<Film>(spawned.camera)
            .expect("the camera has a film");
        let rays = world.resource::<RenderStats>().last_frame.rays();
        println!(
            "{tick:>5}  {:>7.1}  {:>11}  {rays}",
            elapsed.as_secs_f64() * 1e3,
            film.frames()
        );
    }
    let out = std::path::Path::new("embed_loop.png");
    let film = world
        .get::<Film>(spawned.camera)
        .expect("the camera has a film");
    match film.write_png(out, 0.0) {
        Ok(()) => println!(
            "wrote {} ({} frames accumulated)",
            out.display(),
            film.frames()
        ),
        Err(e) => eprintln!("error: {e}"),
    }
}
