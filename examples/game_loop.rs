//! A game that embeds Sylva in its own schedule: its systems move plants as rigid bodies
//! (a gust knocks the plants near its path over, and a damped spring brings each back
//! up), it spawns and despawns plants while running, picks the plant under a moving
//! cursor, and reads each frame's image in place as a texture upload would. Sylva renders
//! on the game's own rayon pool, so the two share the cores. Run with
//! `cargo run --release --example game_loop -- [ticks] [trace.json]`; with a trace file
//! it also writes a Chrome trace (chrome://tracing or Perfetto) in which the game's
//! spring spans and Sylva's tile spans share the same `game-worker` threads.

use std::collections::BTreeSet;
use std::sync::{Arc, Mutex};
use std::time::Instant;
use sylva::prelude::*;

/// A plant's tilt about its base: a damped spring on the angle, pushed by gusts.
#[derive(Component, Clone, Copy)]
struct Tilt {
    /// Where the plant stands up.
    rest: Transform,
    /// Horizontal axis the plant tilts about (perpendicular to the gust).
    axis: Vec3,
    /// Angle from upright in radians, and its rate.
    angle: f32,
    velocity: f32,
}

/// The gust: a front sweeping along +x, pushing plants within `width` of it.
#[derive(Resource)]
struct Gust {
    x: f32,
    speed: f32,
    width: f32,
    push: f32,
}

/// Seconds per tick of the game's fixed step.
const STEP: f32 = 1.0 / 30.0;

/// Plants near the gust front get an angular kick (once per tick they are inside it).
fn blow(mut gust: ResMut<Gust>, mut plants: Query<(&Transform, &mut Tilt)>) {
    gust.x += gust.speed * STEP;
    for (transform, mut tilt) in &mut plants {
        if (transform.translation.x - gust.x).abs() < gust.width {
            tilt.velocity += gust.push * STEP;
        }
    }
}

/// Integrates every plant's spring on the game's pool (the same workers Sylva renders
/// on, between frames) and writes its transform: only moved plants change, so the top
/// level is refitted, not rebuilt.
fn spring(pool: Res<RenderPool>, mut plants: Query<(&mut Transform, &mut Tilt)>) {
    const STIFFNESS: f32 = 30.0;
    const DAMPING: f32 = 3.0;
    pool.install(|| {
        let _span = tracing::info_span!("game: spring").entered();
        plants.par_iter_mut().for_each(|(mut transform, mut tilt)| {
            if tilt.angle == 0.0 && tilt.velocity == 0.0 {
                return;
            }
            let acceleration = -STIFFNESS * tilt.angle - DAMPING * tilt.velocity;
            tilt.velocity += acceleration * STEP;
            tilt.angle = (tilt.angle + tilt.velocity * STEP).clamp(-1.4, 1.4);
            if tilt.angle.abs() < 1e-4 && tilt.velocity.abs() < 1e-3 {
                tilt.angle = 0.0;
                tilt.velocity = 0.0;
            }
            let rest = tilt.rest;
            *transform = Transform {
                rotation: Quat::from_axis_angle(tilt.axis, tilt.angle) * rest.rotation,
                ..rest
            };
        });
    });
}

fn main() {
    let ticks: u32 = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(60);
    let _trace = std::env::args().nth(2).map(|path| {
        use tracing_subscriber::prelude::*;
        let (chrome, guard) = tracing_chrome::ChromeLayerBuilder::new().file(path).build();
        tracing_subscriber::registry().with(chrome).init();
        guard
    });

    // The game's pool: its own parallel work and Sylva's tiles and builds run here.
    let game_pool = Arc::new(
        rayon::ThreadPoolBuilder::new()
            .thread_name(|i| format!("game-worker-{i}"))
            .build()
            .expect("the game's workers start"),
    );
    let mut world = World::new();
    let mut schedule = Schedule::default();
    let options = RenderOptions {
        pool: Some(game_pool.clone()),
        ..Default::default()
    };
    install(&mut world, &mut schedule, &options).expect("Sylva installs");
    schedule.add_systems((blow, spring).chain().before(RenderSystems::Animate));

    let mut scene = game_pool
        .install(|| build_scene("meadow", 0))
        .expect("the meadow builds");
    scene.camera.width = 320;
    scene.camera.height = 240;
    let spawned = spawn(&mut world, scene);
    Quality::interactive().apply(&mut world, spawned.camera);
    world
        .entity_mut(spawned.camera)
        .insert(FrameImage::new(0.0));
    for &plant in &spawned.plants {
        let rest = *world.get::<Transform>(plant).expect("a plant has a place");
        world.entity_mut(plant).insert(Tilt {
            rest,
            axis: Vec3::Z,
            angle: 0.0,
            velocity: 0.0,
        });
    }
    // The gust crosses the plants within 30 m of the camera over the run.
    let eye = world
        .get::<Transform>(spawned.camera)
        .expect("a camera has a place")
        .translation;
    let near_x: Vec<f32> = world
        .query_filtered::<&Transform, With<Tilt>>()
        .iter(&world)
        .map(|t| t.translation)
        .filter(|p| p.distance(eye) < 30.0)
        .map(|p| p.x)
        .collect();
    let lo = near_x.iter().copied().fold(eye.x - 10.0, f32::min);
    let hi = near_x.iter().copied().fold(eye.x + 10.0, f32::max);
    world.insert_resource(Gust {
        x: lo,
        speed: (hi - lo) / (ticks.max(1) as f32 * STEP),
        width: 3.0,
        push: -40.0,
    });

    let tile_threads: Arc<Mutex<BTreeSet<String>>> = Arc::default();
    let record = tile_threads.clone();
    world.insert_resource(TileProgress(Some(Arc::new(move |_| {
        let name = std::thread::current().name().unwrap_or("?").to_owned();
        record.lock().expect("not poisoned").insert(name);
    }))));

    let species = world
        .get::<Instance>(spawned.plants[0])
        .expect("a plant")
        .geometry;
    let mut planted = Vec::new();
    println!("tick  frame_ms  tilted  top_level  under_cursor");
    for tick in 0..ticks {
        // Plants come and go while the game runs: one planted every 10 ticks near the
        // camera, the oldest removed after 30.
        if tick % 10 == 5 {
            let x = lo + (hi - lo) * (tick as f32 / ticks.max(1) as f32);
            let plant = plant_at(&mut world, species, x, eye.z - 8.0, tick as f32, 1.0);
            let rest = *world.get::<Transform>(plant).expect("planted");
            world.entity_mut(plant).insert(Tilt {
                rest,
                axis: Vec3::Z,
                angle: 0.0,
                velocity: 0.0,
            });
            planted.push(plant);
        }
        if planted.len() > 3 {
            let old = planted.remove(0);
            world.despawn(old);
        }

        let start = Instant::now();
        schedule.run(&mut world);
        let frame_ms = start.elapsed().as_secs_f64() * 1e3;

        // The frame's bytes, read where Sylva left them (a texture upload would take
        // this slice as it is).
        let image = world
            .get::<FrameImage>(spawned.camera)
            .expect("the camera publishes its image");
        assert_eq!(image.srgba8().len(), 320 * 240 * 4);

        // The plant under a cursor sweeping the image's middle row.
        let cursor_x = (tick * 320 / ticks.max(1)).min(319);
        let picked = pick(&world, spawned.camera, cursor_x, 120);
        let under = match picked {
            Some(hit) if world.get::<Tilt>(hit.entity).is_some() => {
                format!("plant {:?} at {:.1} m", hit.entity, hit.distance)
            }
            Some(hit) => format!("ground at {:.1} m", hit.distance),
            None => "sky".to_owned(),
        };
        let tilted = world
            .query::<&Tilt>()
            .iter(&world)
            .filter(|t| t.angle.abs() > 0.05)
            .count();
        let state = world.resource::<TopLevelState>();
        println!(
            "{tick:>4}  {frame_ms:>8.1}  {tilted:>6}  {:>3} builds {:>3} refits  {under}",
            state.rebuilds, state.refits
        );
    }
    println!(
        "tiles rendered on: {:?} (the game's pool of {} workers; no second pool)",
        tile_threads.lock().expect("not poisoned"),
        game_pool.current_num_threads()
    );
    let film = world.get::<Film>(spawned.camera).expect("a film");
    match film.write_png(std::path::Path::new("game_loop.png"), 0.0) {
        Ok(()) => println!("wrote game_loop.png"),
        Err(e) => eprintln!("error: {e}"),
    }
}
