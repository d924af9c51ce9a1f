//! An embedding that leaves out every optional stage (no sway, no opacity maps or
//! adaptive transparency, no interleaved environment lights, no display filter) and
//! prints the schedule that remains, then renders the default meadow with it. Leaving a
//! stage out never makes the image wrong, only slower or without that effect. Run with
//! `cargo run --release --example lean_schedule`.

use std::time::Instant;
use sylva::prelude::*;
use sylva::systems::stage_name;

fn main() {
    let mut world = World::new();
    let mut schedule = Schedule::default();
    let options = RenderOptions {
        stages: Stages::NONE,
        ..Default::default()
    };
    install(&mut world, &mut schedule, &options).expect("Sylva installs");
    let pool = world.resource::<RenderPool>().clone();
    let mut scene = pool
        .install(|| build_scene("meadow", 0))
        .expect("the meadow builds");
    scene.camera.width = 320;
    scene.camera.height = 240;
    let spawned = spawn(&mut world, scene);
    println!(
        "the meadow would use: {:?}; installed: {:?}",
        Stages::needed_by(&mut world),
        options.stages
    );

    schedule
        .initialize(&mut world)
        .expect("the schedule builds");
    println!("the schedule's systems:");
    for (_, system) in schedule.systems().expect("initialized") {
        println!(
            "  {}",
            stage_name(system.as_ref()).unwrap_or("(a program's system)")
        );
    }

    for frame in 0..4 {
        let start = Instant::now();
        schedule.run(&mut world);
        println!(
            "frame {frame}: {:.1} ms",
            start.elapsed().as_secs_f64() * 1e3
        );
    }
    let film = world.get::<Film>(spawned.camera).expect("a film");
    match film.write_png(std::path::Path::new("lean_schedule.png"), 0.0) {
        Ok(()) => println!("wrote lean_schedule.png ({} frames)", film.frames()),
        Err(e) => eprintln!("error: {e}"),
    }
}
