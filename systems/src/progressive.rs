//! The progressive driver: runs a world's frame schedule, frame after frame, refining a
//! camera's film until a frame count, a rendering-time budget, an interrupt or the
//! caller says stop. `sylva render`, `sylva converge` and embedding programs share it; a
//! change of scene or camera restarts the film's accumulation (the `Accumulate` stage
//! does that) and the driver reports it.

use bevy_ecs::prelude::*;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use sylva_engine::film::Film;

use crate::cluster::Cluster;

/// When a progressive run stops; the first condition met ends it. With neither a frame
/// count nor a budget it renders one frame.
#[derive(Clone, Debug, Default)]
pub struct StopAt {
    /// Frames accumulated in the camera's film, counting those it held at the start (a
    /// resumed checkpoint) and starting again after a restart.
    pub frames: Option<u32>,
    /// Time spent running the schedule; the per-frame callback is not counted.
    pub budget: Option<Duration>,
    /// Set from elsewhere (Ctrl-C, a window's input) to stop after the frame in progress.
    pub interrupt: Option<Arc<AtomicBool>>,
    /// Frames follow this run's last one (the next image of an animation): a cluster's
    /// workers may start on them before rank 0 has finished this run.
    pub frames_follow: bool,
}

/// Why a progressive run stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stopped {
    /// The film holds the frames asked for.
    Frames,
    /// The budget is spent.
    Budget,
    /// The interrupt flag was set (the frame it interrupted is in the film).
    Interrupted,
    /// The per-frame callback asked to stop.
    Caller,
}

/// Where a progressive run stands after a frame.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Progress {
    /// Frames in the camera's film.
    pub frames: u32,
    /// Frames this run has rendered.
    pub rendered: u32,
    /// Time spent running the schedule in this run.
    pub rendering: Duration,
    /// The last frame started the film again, dropping the frames it held (the scene or
    /// the camera changed).
    pub restarted: bool,
    /// Frames this run gave up half-way ([`FrameCancel`](crate::FrameCancel)); they are
    /// not in `rendered`.
    pub cancelled: u32,
}

/// What the per-frame callback tells the driver.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Flow {
    /// Render the next frame.
    Continue,
    /// Stop now.
    Stop,
}

/// Runs `schedule` on `world` until `stop` says so, calling `on_frame` after each frame
/// (not after one the interrupt ended); returns why it stopped and where it stood.
pub fn refine(
    world: &mut World,
    schedule: &mut Schedule,
    camera: Entity,
    stop: &StopAt,
    mut on_frame: impl FnMut(&mut World, &Progress) -> Flow,
) -> (Stopped, Progress) {
    let film_frames = |world: &World| world.get::<Film>(camera).map_or(0, Film::frames);
    let target = match (stop.frames, stop.budget) {
        (None, None) => Some(film_frames(world).saturating_add(1)),
        (frames, _) => frames,
    };
    let mut progress = Progress {
        frames: film_frames(world),
        ..Progress::default()
    };
    let cancelled_frames = |world: &World| {
        world
            .get_resource::<crate::RenderStats>()
            .map_or(0, |s| s.cancelled)
    };
    loop {
        if let Some(mut cluster) = world.get_resource_mut::<Cluster>() {
            // After a run's last frame only the caller knows what comes: workers start
            // on the next frame ahead of rank 0 only when it says one follows.
            let last = target.is_some_and(|target| progress.frames.saturating_add(1) >= target);
            cluster.frames_follow(!last || stop.frames_follow);
        }
        let start = Instant::now();
        let cancelled_before = cancelled_frames(world);
        schedule.run(world);
        progress.rendering += start.elapsed();
        let frames = film_frames(world);
        if cancelled_frames(world) > cancelled_before {
            progress.cancelled += 1;
            progress.restarted = false;
        } else {
            progress.rendered += 1;
            progress.restarted = frames <= progress.frames;
        }
        progress.frames = frames;
        if stop
            .interrupt
            .as_ref()
            .is_some_and(|flag| flag.load(Ordering::SeqCst))
        {
            return (Stopped::Interrupted, progress);
        }
        if on_frame(world, &progress) == Flow::Stop {
            return (Stopped::Caller, progress);
        }
        if target.is_some_and(|target| frames >= target) {
            return (Stopped::Frames, progress);
        }
        if stop
            .budget
            .is_some_and(|budget| progress.rendering >= budget)
        {
            return (Stopped::Budget, progress);
        }
    }
}
