//! The cluster protocol with ranks as threads (in-process channels): films bit for bit
//! those of one process, and every failure a clear error naming the rank in bounded time.

use bevy_ecs::prelude::*;
use bevy_ecs::schedule::SingleThreadedExecutor;
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use sylva::engine::camera::Camera;
use sylva::engine::components::Transform;
use sylva::engine::film::Film;
use sylva::scenes::editor::EditorAction;
use sylva::scenes::{build_scene, spawn};
use sylva::systems::cluster::{
    ChannelTransport, Cluster, ClusterCounters, ClusterError, Transport,
};
use sylva::systems::live::{
    LiveCommand, LiveRender, SharedEdits, ShownImage, SingleThreadedSystems, serve_live,
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
    let plain = Leader {
        frames,
        frames_follow: false,
        after_frame: &|_, _| {},
    };
    cluster_run_with(size, &seed_of, &threads_of, timeout, plain, usize::MAX)
}

/// What a rank does after each of its frames: `(rank, world)`.
type AfterFrame = dyn Fn(usize, &mut World) + Sync;

/// How rank 0 drives a threaded cluster run.
#[derive(Clone, Copy)]
struct Leader<'a> {
    /// Frames rank 0 refines.
    frames: u32,
    /// Rank 0's driver says more frames follow its last (workers may start on them).
    frames_follow: bool,
    /// Run on every rank after each frame (rank 0's part between frames, a worker's
    /// change to its world).
    after_frame: &'a AfterFrame,
}

/// [`cluster_run`] driven by `leader`, over transports whose sends above `eager_limit`
/// bytes wait until taken (as MPI's large sends do).
fn cluster_run_with(
    size: usize,
    seed_of: &(dyn Fn(usize) -> u64 + Sync),
    threads_of: &(dyn Fn(usize) -> usize + Sync),
    timeout: Duration,
    leader: Leader,
    eager_limit: usize,
) -> Vec<RankEnd> {
    let transports = ChannelTransport::mesh_with_eager_limit(size, eager_limit);
    std::thread::scope(|scope| {
        let handles: Vec<_> = transports
            .into_iter()
            .map(|transport| {
                scope.spawn(move || run_rank(transport, seed_of, threads_of, timeout, leader))
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    })
}

fn run_rank(
    transport: ChannelTransport,
    seed_of: &(dyn Fn(usize) -> u64 + Sync),
    threads_of: &(dyn Fn(usize) -> usize + Sync),
    timeout: Duration,
    leader: Leader,
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
            frames: Some(if leads { leader.frames } else { u32::MAX }),
            interrupt: Some(stop_flag),
            frames_follow: leader.frames_follow,
            ..StopAt::default()
        };
        let (why, _) = refine(&mut world, &mut schedule, camera, &stop, |world, _| {
            (leader.after_frame)(rank, world);
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
fn workers_render_the_next_frame_while_rank_0_is_between_frames_and_the_film_stays_exact() {
    let reference = alone(3, 2);
    for (size, threads) in [(2, 1), (3, 2)] {
        // Rank 0's part between frames takes 300 ms: time enough for a worker to start
        // on the next frame with what rank 0's thread for it hands out.
        let pausing = Leader {
            frames: 3,
            frames_follow: false,
            after_frame: &|rank, _| {
                if rank == 0 {
                    std::thread::sleep(Duration::from_millis(300));
                }
            },
        };
        let ends = cluster_run_with(
            size,
            &|_| 7,
            &|_| threads,
            Duration::from_secs(60),
            pausing,
            usize::MAX,
        );
        assert_eq!(ends[0].failure, None);
        assert!(
            ends[0].film == reference,
            "{size} ranks × {threads} threads: rank 0's film differs from one process's"
        );
        let ahead = ends[0].counters.tiles_ahead;
        assert!(
            ahead > 0 && ahead <= ends[0].counters.tiles_elsewhere,
            "{size} ranks: {ahead} tiles rendered ahead of rank 0"
        );
        // No worker starts on a frame after the last: every tile rendered was used.
        let rendered: u64 = ends.iter().map(|e| e.counters.tiles_here).sum();
        assert_eq!(rendered, 3 * 30, "{size} ranks");
    }
}

#[test]
fn a_run_that_ends_while_workers_render_ahead_leaves_none_blocked_in_a_send() {
    // Rank 0 says frames follow its last, pauses after each frame (so the workers are
    // surely on the next one: without the pause they sometimes were not yet, and the
    // case went untested), then ends the run: its workers are on a frame that will not
    // come, sending tiles that wait until rank 0 takes them.
    let ending = Leader {
        frames: 2,
        frames_follow: true,
        after_frame: &|rank, _| {
            if rank == 0 {
                std::thread::sleep(Duration::from_millis(300));
            }
        },
    };
    let (done, finished) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let ends = cluster_run_with(3, &|_| 7, &|_| 1, Duration::from_secs(60), ending, 4096);
        let _ = done.send(ends);
    });
    let ends = finished
        .recv_timeout(Duration::from_secs(30))
        .expect("every rank ends");
    assert_eq!(ends[0].film, alone(2, 1));
    for end in &ends {
        assert_eq!(end.failure, None);
    }
    // The workers did start on the third frame, which was dropped.
    let rendered: u64 = ends.iter().map(|e| e.counters.tiles_here).sum();
    assert!(rendered > 2 * 30, "{rendered} tiles rendered");
}

#[test]
fn a_worker_ahead_of_rank_0_on_another_view_is_refused_by_name_when_rank_0_gets_there() {
    // After its first frame rank 2 turns its camera, rank 0 pauses: rank 2 renders
    // tiles of its second frame ahead of rank 0, which refuses them on reaching it.
    let turning = Leader {
        frames: 3,
        frames_follow: false,
        after_frame: &|rank, world| match rank {
            0 => std::thread::sleep(Duration::from_millis(300)),
            2 => {
                let mut cameras = world.query_filtered::<&mut Transform, With<Camera>>();
                for mut transform in cameras.iter_mut(world) {
                    transform.translation.x += 0.5;
                }
            }
            _ => {}
        },
    };
    let ends = cluster_run_with(
        3,
        &|_| 7,
        &|_| 1,
        Duration::from_secs(60),
        turning,
        usize::MAX,
    );
    let failure = ends[0].failure.clone().expect("rank 0 refuses the run");
    assert_eq!(
        failure,
        ClusterError::Mismatch {
            rank: 2,
            what: "camera view or sampling settings"
        }
    );
    // The first frame is in the film; the second, rendered partly ahead, is not.
    assert_eq!(ends[0].film, alone(1, 1));
    for end in &ends[1..] {
        assert!(
            matches!(&end.failure, Some(ClusterError::Failed { rank: 0, error }) if error.contains("rank 2")),
            "{:?}",
            end.failure
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
        let _cluster = joined(silent, Duration::from_secs(60));
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
        interrupt: Some(stop_flag),
        ..StopAt::default()
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

/// The meadow as the viewer sets it up for a live render: editor actions as shared
/// edits, systems on the rank's own thread.
fn live_meadow(threads: usize) -> (World, Entity) {
    let mut world = World::new();
    let camera = meadow(&mut world, 7, threads);
    world.insert_resource(RenderSeed(7));
    world.insert_resource(SharedEdits(Arc::new(
        move |world: &mut World, bytes: &[u8]| {
            EditorAction::from_bytes(bytes)?.apply(world, camera);
            Ok(())
        },
    )));
    world.insert_resource(SingleThreadedSystems);
    (world, camera)
}

/// A rank's place in a run over `transport`, its scene reported loaded and the run
/// agreed on.
fn joined(transport: impl Transport + 'static, timeout: Duration) -> Cluster {
    let stop = Arc::new(AtomicBool::new(false));
    let mut cluster = Cluster::new(Box::new(transport), timeout, stop);
    cluster.agree_loaded(Ok(())).unwrap();
    cluster
}

/// Commands sent with a pause after each (a pause shorter than a frame gives the frame
/// in progress up), then the accumulated frames to wait for.
type Burst = (Vec<(LiveCommand, Duration)>, u32);

/// Sends each burst to `live`, waits for the frame that shows it with `frames`
/// accumulated, idles for `idle`; returns the image shown after each burst and, once
/// stopped, the film's bits.
fn drive_live(
    mut live: LiveRender,
    camera: Entity,
    bursts: &[Burst],
    idle: Duration,
) -> (Vec<ShownImage>, (u32, Vec<u64>)) {
    let mut shown = Vec::new();
    for (burst, (commands, frames)) in bursts.iter().enumerate() {
        let mut last = live.last_sent();
        for (command, pause) in commands {
            last = live.send(command.clone()).expect("the render thread runs");
            std::thread::sleep(*pause);
        }
        let start = Instant::now();
        let mut seen = None;
        let image = loop {
            if let Some(image) = live.take_latest() {
                if image.applied >= last && image.frames >= *frames {
                    break image;
                }
                seen = Some((image.applied, image.frames));
            }
            assert!(live.failure().is_none(), "{:?}", live.failure());
            assert!(
                start.elapsed() < Duration::from_secs(60),
                "burst {burst}: no frame came (last shown: command and frames {seen:?}, waiting for {last} and {frames}; {:?})",
                live.frame_log()
            );
            std::thread::sleep(Duration::from_millis(2));
        };
        shown.push(image);
        std::thread::sleep(idle);
    }
    let failure = live.failure();
    let world = live.stop().unwrap_or_else(|| panic!("{failure:?}"));
    (shown, film_bits(&world, camera))
}

/// Moves, edits (undone), the wind on (with a move) and off, bursts that give frames up.
fn walkthrough() -> Vec<Burst> {
    let edit = |action: EditorAction| LiveCommand::Shared(action.to_bytes());
    let moved = Transform::looking_at(
        glam::Vec3::new(5.0, 3.0, 20.0),
        glam::Vec3::Y,
        glam::Vec3::Y,
    );
    let turned = Transform::looking_at(
        glam::Vec3::new(-4.0, 2.5, 18.0),
        glam::Vec3::Y,
        glam::Vec3::Y,
    );
    let quick = Duration::from_millis(3);
    vec![
        (vec![], 2),
        (
            vec![
                // A pixel on the big tree at the left (a pixel of sky selected nothing
                // here, so the delete did nothing and the test raced on frame counts).
                (edit(EditorAction::Select(12, 8)), quick),
                (edit(EditorAction::Delete), Duration::ZERO),
            ],
            2,
        ),
        (
            vec![
                (LiveCommand::Pose(moved), quick),
                (edit(EditorAction::Undo), quick),
                (edit(EditorAction::InsertAtGround(1.5, 2.0)), Duration::ZERO),
            ],
            2,
        ),
        (vec![(edit(EditorAction::Wind(true)), Duration::ZERO)], 1),
        // A move while the wind blows: every rank must have run as many frames.
        (vec![(LiveCommand::Pose(turned), Duration::ZERO)], 1),
        (
            vec![
                (edit(EditorAction::Wind(false)), quick),
                (LiveCommand::Pose(Transform::default()), quick),
                (LiveCommand::Pose(moved), Duration::ZERO),
            ],
            2,
        ),
    ]
}

#[test]
fn a_live_render_on_a_cluster_shows_what_one_process_shows_through_moves_edits_and_idling() {
    let bursts = walkthrough();
    let (world, camera) = live_meadow(2);
    let live = LiveRender::start(world, camera, 2, || {}).unwrap();
    let (alone_shown, alone_film) = drive_live(live, camera, &bursts, Duration::ZERO);

    let mut transports = ChannelTransport::mesh(3).into_iter();
    let leader = transports.next().unwrap();
    // Idle pauses longer than the time limit: rank 0's signs of life keep the run going.
    let timeout = Duration::from_millis(600);
    let workers: Vec<_> = transports
        .map(|transport| {
            std::thread::spawn(move || {
                let (world, camera) = live_meadow(1);
                serve_live(world, camera, joined(transport, timeout))
                    .map(|world| world.resource::<Cluster>().total)
            })
        })
        .collect();
    let (mut world, camera) = live_meadow(1);
    world.insert_resource(joined(leader, timeout));
    let live = LiveRender::start(world, camera, 2, || {}).unwrap();
    let (shown, film) = drive_live(live, camera, &bursts, Duration::from_millis(1500));
    for worker in workers {
        let counters = worker
            .join()
            .unwrap()
            .expect("a worker ends when rank 0 quits");
        assert!(counters.tiles_here > 0, "a worker rendered nothing");
    }
    assert_eq!(film, alone_film, "the last film differs from one process's");
    for (i, (a, b)) in shown.iter().zip(&alone_shown).enumerate() {
        // The wind's pose depends on how many frames ran while it blew.
        if i != 3 && i != 4 {
            let differing = a
                .pixels
                .iter()
                .zip(&b.pixels)
                .filter(|(a, b)| a != b)
                .count();
            assert!(
                differing == 0,
                "burst {i}: {differing} pixels differ from one process's"
            );
        }
    }
    for run in [&shown, &alone_shown] {
        let planted = run[0].instances;
        assert_eq!(run[1].instances, planted - 1, "the delete removed no plant");
        assert_eq!(run[2].instances, planted + 1, "undo and insert");
    }
    assert!(
        shown[1].pixels != shown[0].pixels,
        "the delete changed nothing"
    );
}

#[test]
fn a_live_worker_whose_rank_0_falls_silent_ends_naming_it() {
    let mut transports = ChannelTransport::mesh(2);
    let worker = transports.pop().unwrap();
    let leader = transports.pop().unwrap();
    let silent = std::thread::spawn(move || {
        let _cluster = joined(leader, Duration::from_secs(60));
        // Loaded, then no frame and no sign of life.
        std::thread::sleep(Duration::from_secs(2));
    });
    let (world, camera) = live_meadow(1);
    let cluster = joined(worker, Duration::from_millis(400));
    let stop = cluster.stop_flag();
    let start = Instant::now();
    let failure = serve_live(world, camera, cluster).expect_err("it ends failing");
    assert!(
        matches!(failure, ClusterError::Silent { rank: 0, .. }),
        "{failure:?}"
    );
    assert!(start.elapsed() < Duration::from_secs(5));
    assert!(stop.load(std::sync::atomic::Ordering::SeqCst));
    silent.join().unwrap();
}

/// [`live_meadow`] at 320×240: a frame of 75 runs of tiles, so that a worker is often
/// in the middle of sending one.
fn larger_live_meadow() -> (World, Entity) {
    let (mut world, camera) = live_meadow(1);
    let mut view = world.get_mut::<Camera>(camera).unwrap();
    (view.width, view.height) = (320, 240);
    (world, camera)
}

/// A rank that sees each message only 20 ms after it arrived, as a rank busy outside
/// MPI's calls does: it goes on sending for a while after it has been told to stop.
struct Late {
    transport: ChannelTransport,
    arrived: Mutex<std::collections::VecDeque<(Instant, usize, Vec<u8>)>>,
}

impl Transport for Late {
    fn rank(&self) -> usize {
        self.transport.rank()
    }
    fn size(&self) -> usize {
        self.transport.size()
    }
    fn send(&self, to: usize, bytes: &[u8]) -> Result<(), String> {
        self.transport.send(to, bytes)
    }
    fn try_receive(&self) -> Option<(usize, Vec<u8>)> {
        let mut arrived = self.arrived.lock().unwrap();
        while let Some((from, bytes)) = self.transport.try_receive() {
            arrived.push_back((Instant::now(), from, bytes));
        }
        match arrived.front() {
            Some((at, ..)) if at.elapsed() >= Duration::from_millis(20) => {
                arrived.pop_front().map(|(_, from, bytes)| (from, bytes))
            }
            _ => None,
        }
    }
}

/// Three ranks render a live walk whose window closes while frames are in progress;
/// returns how each worker ended, or `None` for one still blocked 10 s later. Sends of
/// tiles wait until rank 0 takes them, as MPI's large sends do, and workers hear rank 0
/// late, so they still send tiles of a frame rank 0 has given up.
fn close_mid_walk() -> Vec<Option<Result<(), ClusterError>>> {
    let mut transports = ChannelTransport::mesh_with_eager_limit(3, 4096).into_iter();
    let leader = transports.next().unwrap();
    let timeout = Duration::from_secs(20);
    let (left, workers_left) = std::sync::mpsc::channel();
    for transport in transports {
        let left = left.clone();
        std::thread::spawn(move || {
            let (world, camera) = larger_live_meadow();
            let late = Late {
                transport,
                arrived: Mutex::default(),
            };
            let _ = left.send(serve_live(world, camera, joined(late, timeout)).map(|_| ()));
        });
    }
    let (mut world, camera) = larger_live_meadow();
    world.insert_resource(joined(leader, timeout));
    let mut live = LiveRender::start(world, camera, 1000, || {}).unwrap();
    for step in 0..5 {
        let pose = Transform::looking_at(
            glam::Vec3::new(step as f32, 3.0, 20.0),
            glam::Vec3::Y,
            glam::Vec3::Y,
        );
        live.send(LiveCommand::Pose(pose)).unwrap();
        std::thread::sleep(Duration::from_millis(40));
    }
    let failure = live.failure();
    assert!(live.stop().is_some(), "{failure:?}");
    (0..2)
        .map(|_| workers_left.recv_timeout(Duration::from_secs(10)).ok())
        .collect()
}

#[test]
fn closing_the_live_render_mid_frame_leaves_no_rank_blocked_in_a_send() {
    // A worker sending tiles of the frame the quit gave up must still be taken in
    // (before rank 0 waited for every worker to leave, the first walk hung in 4 of 4
    // runs).
    for walk in 0..3 {
        for end in close_mid_walk() {
            let end = end.unwrap_or_else(|| panic!("walk {walk}: a worker is still blocked"));
            assert_eq!(end, Ok(()), "walk {walk}");
        }
    }
}
