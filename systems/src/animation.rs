//! Image sequences of a moving scene: image `k` shows the world `k / fps` seconds after
//! the start, refined over a fixed number of progressive frames with a seed of its own,
//! so every image is the same whatever ran before it in the process — a sequence
//! resumed at any image, or rendered on any number of threads, is bit for bit the one
//! rendered in one go.

use crate::schedule::has_component;
use crate::stages::{
    NodeAnimationPlayer, advance_animation_clock, animate, follow_camera_paths, play_node_animation,
};
use crate::{Flow, Progress, RenderSeed, StopAt, Stopped, refine};
use bevy_ecs::prelude::*;
use bevy_ecs::system::RunSystemOnce;
use sylva_engine::camera_path::CameraPath;
use sylva_engine::film::Film;
use sylva_engine::sampling::mix64;
use sylva_engine::sway::AnimationClock;
use sylva_engine::sway::Sway;

/// How a sequence is timed and refined.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sequence {
    /// Images per second of animated time.
    pub fps: f64,
    /// Progressive frames accumulated into each image.
    pub frames_per_image: u32,
    /// The render seed the images' seeds are derived from.
    pub seed: u64,
}

impl Sequence {
    /// Images in `seconds` of animation: the first at time 0, the last before `seconds`
    /// (at least one).
    pub fn images(&self, seconds: f64) -> u32 {
        ((seconds * self.fps - 1e-9).ceil().max(1.0)).min(f64::from(u32::MAX)) as u32
    }

    /// Advances the world's animation from image `from` to image `to` without rendering
    /// (the `animate` stage alone, one image's time per step), as rendering them would
    /// have.
    pub fn skip(&self, world: &mut World, from: u32, to: u32) {
        world.init_resource::<AnimationClock>();
        // The schedule's animation stage, with its run conditions: the clock moves only
        // while something moves with it.
        let sways = has_component::<Sway>(world);
        let paths = has_component::<CameraPath>(world);
        let nodes = world.contains_resource::<NodeAnimationPlayer>();
        for _ in (from..to).filter(|_| sways || paths || nodes) {
            world.resource_mut::<AnimationClock>().frame_seconds = 1.0 / self.fps;
            // These cannot fail to run: every parameter they take exists.
            let _ = world.run_system_once(advance_animation_clock);
            if sways {
                let _ = world.run_system_once(animate);
            }
        }
        if paths {
            let _ = world.run_system_once(follow_camera_paths);
        }
        if nodes {
            let _ = world.run_system_once(play_node_animation);
        }
        world.resource_mut::<AnimationClock>().frame_seconds = 0.0;
    }

    /// Renders image `index` of `camera` after image `index − 1` (or, for image 0, the
    /// start): one image's time of animation, then `frames_per_image` frames into a fresh
    /// film, seeded for this image. `on_frame` sees each frame (progress bars);
    /// `interrupt` stops after the frame in progress.
    pub fn render_image(
        &self,
        world: &mut World,
        schedule: &mut Schedule,
        camera: Entity,
        index: u32,
        stop: &StopAt,
        mut on_frame: impl FnMut(&mut World, &Progress) -> Flow,
    ) -> Stopped {
        world.init_resource::<AnimationClock>();
        world.resource_mut::<AnimationClock>().frame_seconds =
            if index == 0 { 0.0 } else { 1.0 / self.fps };
        world.insert_resource(RenderSeed(self.seed ^ mix64(u64::from(index) + 1)));
        // An empty film: the image starts afresh even where nothing moved.
        world.entity_mut(camera).insert(Film::default());
        let stop = StopAt {
            frames: Some(self.frames_per_image.max(1)),
            budget: None,
            interrupt: stop.interrupt.clone(),
            frames_follow: stop.frames_follow,
        };
        let (stopped, _) = refine(world, schedule, camera, &stop, |world, progress| {
            // Time moves once per image, not once per accumulated frame.
            world.resource_mut::<AnimationClock>().frame_seconds = 0.0;
            on_frame(world, progress)
        });
        stopped
    }
}
