//! The cluster protocol with ranks as threads (in-process channels): films bit for bit
//! those of one process, and every failure a clear error naming the rank in bounded time.

use bevy_ecs::prelude::*;
use bevy_ecs::schedule::SingleThreadedExecutor;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};
use sylva::engine::film::Film;
use sylva::scenes::{build_scene, spawn};
use sylva::systems::cluster::{
    ChannelTransport, Cluster, ClusterCounters, ClusterError, Transport,
};
use sylva::systems::{
    Quality, RenderSeed, StopAt, Stopped, frame_schedule, init_render_world, refine,
};

/// The `meadow` at 96×72 (30 tiles) with `threads` workers, interactive quality (filter, light
/// subsets and adaptive transparency all in play); returns the camera.
fn meadow(world: &mut World, seed: u64, threads: usize) -> Entity {
    init_render_world(world, threads).unwrap();
    world.insert_resource(RenderSeed(seed));
    let mut scene = build_scene("meadow", seed).unwrap();
    scene.camera.width = 96;
    scene.camera.height = 72;
    let camera = spawn(world, scene).camera;
    Quality::interactive().apply(world, camera);
    camera
}

/// The film's sums and counts as bits.
fn film_bits(world: &World, camera: Entity) -> (u32, Vec<u64>) {
    let film = world.get::<Film>(camera).unwrap();
    let mut bits = Vec::new();
    for y in 0..film.height() {
        for x in 0..film.width() {
            bits.extend(film.pixel(x, y).map(f64::to_bits));
        }
    }
    (film.frames(), bits)
}

/// One process: `frames` frames of the meadow.
fn alone(frames: u32, threads: usize) -> (u32, Vec<u64>) {
    let mut world = World::new();
    let camera = meadow(&mut world, 7, threads);
    let mut schedule = frame_schedule();
    let stop = StopAt {
        frames: Some(frames),
        ..StopAt::default()
    };
    refine(&mut world, &mut schedule, camera, &stop, |_, _| {
        sylva::systems::Flow::Continue
    });
    film_bits(&world, camera)
}

/// What one rank of a threaded cluster run ended with.
struct RankEnd {
    film: (u32, Vec<u64>),
    stopped: Option<Stopped>,
    failure: Option<ClusterError>,
    counters: ClusterCounters,
}

/// Runs every rank's world as a thread: rank 0 refines `frames` frames and ends the run,
/// workers serve until told to stop. `seed_of(rank)` builds each rank's scene;
/// `threads_of(rank)` its workers.
fn cluster_run(
    size: usize,
    frames: u32,
    seed_of: impl Fn(usize) -> u64 + Sync,
    threads_of: impl Fn(usize) -> usize + Sync,
    timeout: Duration,
) -> Vec<RankEnd> {
    let transports = ChannelTransport::mesh(size);
    std::thread::scope(|scope| {
        let handles: Vec<_> = transports
            .into_iter()
            .map(|transport| {
                let (seed_of, threads_of) = (&seed_of, &threads_of);
                scope.spawn(move || run_rank(transport, frames, seed_of, threads_of, timeout))
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    })
}

fn run_rank(
    transport: ChannelTransport,
    frames: u32,
    seed_of: &(dyn Fn(usize) -> u64 + Sync),
    threads_of: &(dyn Fn(usize) -> usize + Sync),
    timeout: Duration,
) -> RankEnd {
    let rank = transport.rank();
    let mut world = World::new();
    let camera = meadow(&mut world, seed_of(rank), threads_of(rank));
    // The render seed is the run's, whatever scene seed a rank was (wrongly) given.
    world.insert_resource(RenderSeed(7));
    let stop_flag = Arc::new(AtomicBool::new(false));
    let mut cluster = Cluster::new(Box::new(transport), timeout, stop_flag.clone());
    let load = cluster.agree_loaded(Ok(()));
    let leads = cluster.leads();
    world.insert_resource(cluster);
    let mut stopped = None;
    if load.is_ok() {
        // bevy's task pool is one per process: ranks as threads would wait for each
        // other on its few threads, so each runs its systems on its own thread.
        let mut schedule = frame_schedule();
        schedule.set_executor(SingleThreadedExecutor::new());
        let stop = StopAt {
            frames: Some(if leads { frames } else { u32::MAX }),
            budget: None,
            interrupt: Some(stop_flag),
        };
        let (why, _) = refine(&mut world, &mut schedule, camera, &stop, |_, _| {
            sylva::systems::Flow::Continue
        });
        stopped = Some(why);
        if leads {
            world.resource_mut::<Cluster>().finish().unwrap();
        }
    }
    RankEnd {
        film: film_bits(&world, camera),
        stopped,
        failure: world.resource::<Cluster>().failure().cloned(),
        counters: world.resource::<Cluster>().total,
    }
}

#[test]
fn rank_zeros_film_is_one_process_film_bit_for_bit_for_any_ranks_and_threads() {
    let reference = alone(3, 2);
    assert_eq!(reference, alone(3, 1), "one process, 1 and 2 threads");
    for (size, threads) in [(1, 2), (2, 1), (3, 1), (3, 2)] {
        let ends = cluster_run(size, 3, |_| 7, |_| threads, Duration::from_secs(60));
        assert_eq!(ends[0].failure, None);
        assert_eq!(ends[0].stopped, Some(Stopped::Frames));
        assert!(
            ends[0].film == reference,
            "{size} ranks × {threads} threads: rank 0's film differs from one process's"
        );
        for end in &ends[1..] {
            assert_eq!(end.failure, None);
            assert_eq!(
                end.stopped,
                Some(Stopped::Interrupted),
                "workers stop when told"
            );
        }
        // Every tile of the 3 frames was rendered once, some of them by the workers.
        let rendered: u64 = ends.iter().map(|e| e.counters.tiles_here).sum();
        assert_eq!(rendered, 3 * 30);
        let by_workers: u64 = ends[1..].iter().map(|e| e.counters.tiles_here).sum();
        assert_eq!(ends[0].counters.tiles_elsewhere, by_workers);
        assert_eq!(
            by_workers > 0,
            size > 1,
            "{size} ranks: {by_workers} tiles elsewhere"
        );
    }
}

#[test]
fn a_rank_with_another_scene_is_refused_by_name() {
    let ends = cluster_run(
        3,
        2,
        |rank| if rank == 2 { 8 } else { 7 },
        |_| 1,
        Duration::from_secs(60),
    );
    let failure = ends[0].failure.clone().expect("rank 0 refuses the run");
    assert_eq!(
        failure,
        ClusterError::Mismatch {
            rank: 2,
            what: "scene (geometry, plants, shaders or lights)"
        }
    );
    assert!(
        failure
            .to_string()
            .contains("rank 2 would render a different scene")
    );
    // Rank 0 rendered nothing into its film, and told the workers why.
    assert_eq!(ends[0].film.0, 0);
    for end in &ends[1..] {
        let told = end.failure.clone().expect("workers are told");
        assert!(
            matches!(&told, ClusterError::Failed { rank: 0, error } if error.contains("rank 2")),
            "{told:?}"
        );
    }
}

#[test]
fn a_rank_that_fails_to_load_ends_the_run_with_its_error() {
    let transports = ChannelTransport::mesh(3);
    let ends: Vec<Result<(), ClusterError>> = std::thread::scope(|scope| {
        let handles: Vec<_> = transports
            .into_iter()
            .map(|transport| {
                scope.spawn(move || {
                    let rank = transport.rank();
                    let stop = Arc::new(AtomicBool::new(false));
                    let mut cluster =
                        Cluster::new(Box::new(transport), Duration::from_secs(60), stop);
                    let loaded = if rank == 1 {
                        Err("cannot read forest.toml: No such file or directory".to_owned())
                    } else {
                        Ok(())
                    };
                    cluster.agree_loaded(loaded)
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let error = ends[0].clone().unwrap_err();
    assert_eq!(
        error.to_string(),
        "rank 1 could not build the scene: cannot read forest.toml: No such file or directory"
    );
    for end in &ends[1..] {
        assert!(
            matches!(end, Err(ClusterError::Failed { rank: 0, error }) if error.contains("rank 1")),
            "{end:?}"
        );
    }
}

#[test]
fn a_silent_rank_ends_the_frame_in_bounded_time_naming_it() {
    // Rank 1 says its scene loaded, then never renders: rank 0 gives up on it.
    let mut transports = ChannelTransport::mesh(2);
    let silent = transports.pop().unwrap();
    let leader = transports.pop().unwrap();
    let silent_thread = std::thread::spawn(move || {
        let stop = Arc::new(AtomicBool::new(false));
        let mut cluster = Cluster::new(Box::new(silent), Duration::from_secs(60), stop);
        cluster.agree_loaded(Ok(())).unwrap();
        // Keep the transport alive, silent, until rank 0 is done.
        std::thread::sleep(Duration::from_secs(3));
    });
    let mut world = World::new();
    let camera = meadow(&mut world, 7, 1);
    let stop_flag = Arc::new(AtomicBool::new(false));
    let mut cluster = Cluster::new(
        Box::new(leader),
        Duration::from_millis(500),
        stop_flag.clone(),
    );
    cluster.agree_loaded(Ok(())).unwrap();
    world.insert_resource(cluster);
    let start = Instant::now();
    let stop = StopAt {
        frames: Some(4),
        budget: None,
        interrupt: Some(stop_flag),
    };
    let (why, _) = refine(&mut world, &mut frame_schedule(), camera, &stop, |_, _| {
        sylva::systems::Flow::Continue
    });
    let waited = start.elapsed();
    assert_eq!(why, Stopped::Interrupted);
    let failure = world.resource::<Cluster>().failure().cloned().unwrap();
    assert!(
        matches!(failure, ClusterError::Silent { rank: 1, outstanding, .. } if outstanding <= 2),
        "{failure:?}"
    );
    assert!(failure.to_string().starts_with("rank 1 sent nothing for"));
    assert!(waited < Duration::from_secs(20), "gave up after {waited:?}");
    silent_thread.join().unwrap();
}
