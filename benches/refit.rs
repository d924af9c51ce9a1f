//! Refit against rebuild for a swaying ecosystem: every plant of a scene sways in the wind
//! through the real frame schedule (`animate` then `rebuild_top_level`, no camera so no
//! rendering), the top level is only ever refitted, and at every frame a fresh build of
//! the same instances is timed beside it. Printed per sampled frame: refit and build
//! times, the refitted tree's SAH degradation, and the traversal work and speed of the
//! scene camera's primary rays in the refitted tree against the rebuilt one.
//!
//! `cargo bench --bench refit [-- SCENE…]` (default: forest paper).

mod support;

use glam::Vec2;
use std::time::{Duration, Instant};
use support::{count_rays, two_thread_pool};
use sylva::engine::bvh::{BuildParams, TraversalStats};
use sylva::engine::camera::CameraView;
use sylva::engine::geometry::GeometryLibrary;
use sylva::engine::math::Ray;
use sylva::engine::sway::{AnimationClock, RestPose, Sway, Wind};
use sylva::engine::tlas::{InstanceDesc, TopLevel};
use sylva::prelude::*;
use sylva::systems::{BuildSettings, TopLevelState, frame_schedule, init_render_world};

const FRAMES: usize = 150;
const SAMPLED: [usize; 5] = [1, 10, 30, 75, 150];

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    values[values.len() / 2]
}

/// Work and time of tracing `rays` (closest hit, every hit accepted) through `tlas`.
fn trace(
    pool: &rayon::ThreadPool,
    library: &GeometryLibrary,
    tlas: &TopLevel,
    rays: &[Ray],
) -> (f64, Duration) {
    let mut stats = TraversalStats::default();
    for ray in rays.iter().step_by(16) {
        tlas.intersect_closest(library, ray, &mut stats, |_| true);
    }
    let work = (stats.nodes_visited + stats.primitive_tests) as f64 / stats.closest_rays as f64;
    let start = Instant::now();
    pool.install(|| {
        count_rays(rays, |r, s| {
            tlas.intersect_closest(library, r, s, |_| true).is_some()
        })
    });
    (work, start.elapsed())
}

fn run(name: &str, wind_gain: f64, pool: &rayon::ThreadPool) {
    let build = sylva::scenes::build_scene(name, 0).unwrap();
    let view = CameraView::new(&build.camera, &build.camera_transform.to_affine());
    let rays: Vec<Ray> = {
        let (w, h) = (view.width(), view.height());
        (0..w * h)
            .map(|i| {
                view.ray(
                    Vec2::new((i % w) as f32 + 0.5, (i / w) as f32 + 0.5),
                    Vec2::ZERO,
                )
            })
            .collect()
    };
    let mut world = World::new();
    init_render_world(&mut world, 2).unwrap();
    world.resource_mut::<BuildSettings>().refit_limit = f32::INFINITY;
    let spawned = spawn(&mut world, build);
    world.despawn(spawned.camera);
    for (i, &plant) in spawned.plants.iter().enumerate() {
        let rest = *world.get::<Transform>(plant).unwrap();
        // Stiffness varies per plant so neighbours do not sway in lock step.
        let stiffness = 30.0 + (i % 17) as f64 * 3.0;
        let sway = Sway::new(stiffness, 2.0, 2.0, wind_gain).unwrap();
        world.entity_mut(plant).insert((sway, RestPose(rest)));
    }
    world.insert_resource(Wind::default());
    world.resource_mut::<AnimationClock>().frame_seconds = 1.0 / 30.0;
    let mut schedule = frame_schedule();
    schedule.run(&mut world);
    let first_build = world.resource::<TopLevelState>().last_build;
    println!(
        "\n{name}: {} plants, wind gain {wind_gain}, 30 fps, first build {:.1} ms",
        spawned.plants.len(),
        first_build.as_secs_f64() * 1e3
    );
    println!(
        "frame | mean tilt | refit ms | build ms | degradation | SAH refit/built | work/ray refit : built | \
         trace ms refit : built (median of 3)"
    );
    let mut query = world.query::<(&Transform, &Instance)>();
    for frame in 1..=FRAMES {
        schedule.run(&mut world);
        if !SAMPLED.contains(&frame) {
            continue;
        }
        let state = world.resource::<TopLevelState>();
        let (refit_time, degradation) = (state.last_refit, state.degradation);
        let tilt: f64 = spawned
            .plants
            .iter()
            .map(|&p| {
                let rest = world.get::<RestPose>(p).unwrap().0.rotation;
                let now = world.get::<Transform>(p).unwrap().rotation;
                now.angle_between(rest).to_degrees() as f64
            })
            .sum::<f64>()
            / spawned.plants.len() as f64;
        // The same instances in the same order as the schedule's query sees them.
        let descs: Vec<InstanceDesc> = query
            .iter(&world)
            .map(|(t, i)| InstanceDesc {
                transform: t.to_affine(),
                geometry: i.geometry,
            })
            .collect();
        let library = world.resource::<GeometryLibrary>();
        let refitted = world.resource::<TopLevel>();
        let mut build_times = Vec::new();
        let mut rebuilt = TopLevel::default();
        for _ in 0..3 {
            let start = Instant::now();
            rebuilt = pool.install(|| TopLevel::build(library, &descs, BuildParams::TOP_LEVEL));
            build_times.push(start.elapsed().as_secs_f64());
        }
        let (mut refit_traces, mut built_traces) = (Vec::new(), Vec::new());
        let (mut refit_work, mut built_work) = (0.0, 0.0);
        for _ in 0..3 {
            let (work, time) = trace(pool, library, refitted, &rays);
            refit_work = work;
            refit_traces.push(time.as_secs_f64());
            let (work, time) = trace(pool, library, &rebuilt, &rays);
            built_work = work;
            built_traces.push(time.as_secs_f64());
        }
        let (refit_trace, built_trace) = (median(refit_traces), median(built_traces));
        println!(
            "{frame:5} | {tilt:8.2}° | {:8.2} | {:8.1} | {degradation:11.4} | {:15.4} | \
             {refit_work:6.1} : {built_work:6.1} ({:+.1} %) | {:6.1} : {:6.1} ({:+.1} %)",
            refit_time.as_secs_f64() * 1e3,
            median(build_times) * 1e3,
            refitted.bvh.sah_cost() / rebuilt.bvh.sah_cost(),
            (refit_work / built_work - 1.0) * 100.0,
            refit_trace * 1e3,
            built_trace * 1e3,
            (refit_trace / built_trace - 1.0) * 100.0,
        );
    }
}

fn main() {
    let scenes: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let scenes = if scenes.is_empty() {
        vec!["forest".to_string(), "paper".to_string()]
    } else {
        scenes
    };
    let pool = two_thread_pool();
    for name in &scenes {
        for wind_gain in [0.1, 1.0] {
            run(name, wind_gain, &pool);
        }
    }
}
