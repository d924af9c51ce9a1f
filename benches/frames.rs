//! Frame time and rays per second of whole frames through the frame schedule: the
//! `paper` scene (365,041 plants, 1.49 G instanced triangles) at 640×480 with the
//! interactive and still presets, on a 2-thread pool. Plain timing (no criterion): a frame
//! takes seconds; the first frame of each preset, which builds the top level, is not
//! counted. `cargo bench --bench frames [-- SCENE]`.

use std::time::Instant;
use sylva::prelude::*;
use sylva::systems::RenderStats;
use sylva::systems::converge::Setting;

fn main() {
    let scene_name = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with('-'))
        .unwrap_or_else(|| "paper".into());
    let start = Instant::now();
    let scene = build_scene(&scene_name, 0).expect("a preset scene");
    println!(
        "{scene_name}: built in {:.2} s; 640x480, 2 threads",
        start.elapsed().as_secs_f64()
    );
    let mut world = World::new();
    init_render_world(&mut world, 2).expect("a thread pool");
    let spawned = spawn(&mut world, scene);
    if let Some(mut camera) = world.get_mut::<Camera>(spawned.camera) {
        camera.width = 640;
        camera.height = 480;
    }
    let mut schedule = frame_schedule();
    for (setting, frames) in [(Setting::interactive(), 8u32), (Setting::still(), 2)] {
        let setting = Setting {
            threads: 2,
            ..setting
        };
        setting
            .apply(&mut world, spawned.camera)
            .expect("a thread pool");
        // The first frame after a change of settings (and the very first, which builds
        // the top level) is not counted.
        schedule.run(&mut world);
        let before = world.resource::<RenderStats>().clone();
        let timer = Instant::now();
        for _ in 0..frames {
            schedule.run(&mut world);
        }
        let seconds = timer.elapsed().as_secs_f64() / f64::from(frames);
        let after = world.resource::<RenderStats>();
        let rays = (after.total.rays() - before.total.rays()) as f64 / f64::from(frames);
        println!(
            "  {:<12} {:.3} s per frame ({:.2} fps), {:.2} M rays/s, {:.0} k rays per frame",
            setting.name,
            seconds,
            1.0 / seconds,
            rays / seconds / 1e6,
            rays / 1e3
        );
    }
}
