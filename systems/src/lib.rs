//! # sylva_systems
//!
//! The bevy_ecs side of Sylva: resources, the [`RenderSystems`] sets and the frame
//! schedule. Each stage is its own system with a run condition, so a frame that needs
//! no rebuild, no shader compile or no filter does not pay for it:
//!
//! 1. `Animate` — [`animate`] sways plants with a `Sway` component in the `Wind` (only
//!    when some plant has one), advancing the `AnimationClock` by fixed sub-steps;
//! 2. `Prepare` — [`rebase_world_origin`] then [`rebuild_top_level`] (a refit when only
//!    transforms moved and the tree has not degraded), beside
//!    [`compile_shaders`] and [`compile_lights`] on the multi-threaded executor;
//! 3. `Plan` — per camera: [`adaptive_transparency_lod`] (only when the scene has
//!    alpha-masked shaders) and [`assign_light_subsets`] (only when it has virtual
//!    lights), run when their inputs change;
//! 4. `Render` — [`render_tiles`], tiles in parallel on the one [`RenderPool`];
//! 5. `Accumulate` — [`accumulate`] into each camera's `Film`;
//! 6. `Display` — [`filter_display`]: the discontinuity filter of cameras with a
//!    `DiscontinuityFilter` (only when some camera has one), into a `FilteredImage`;
//! 7. `Output` — [`embed::publish_frame_images`] for cameras with an
//!    [`embed::FrameImage`], and where a program puts its own systems that read a frame's
//!    results. The CLI writes its images after the schedule has run (with their
//!    metadata, snapshots and checkpoints, on the progressive driver [`refine`]).
//!
//! A program with its own schedule installs the stages with [`install`], choosing
//! which optional stages it needs and whose threads render.
//!
//! Threads: all data-parallel work (tiles, BVH builds) runs on the rayon [`RenderPool`];
//! bevy's task pool only runs the systems themselves, whose threads block while the pool
//! works, so the cores are not oversubscribed.

pub mod animation;
pub mod cluster;
pub mod converge;
pub mod embed;
pub mod live;
pub mod picking;
pub mod profile;
mod progressive;
mod quality;
mod schedule;
mod stages;
pub mod walkthrough;

pub use progressive::{Flow, Progress, StopAt, Stopped, refine};
pub use quality::{Fingerprint, Quality};
pub use schedule::{
    Frame, RenderOptions, RenderSystems, Stages, add_render_systems, frame_schedule,
    init_render_world, install, stage_name,
};
pub use stages::*;

use bevy_ecs::prelude::*;
use std::sync::Arc;
use std::time::Duration;
use sylva_engine::bvh::{BuildParams, TraversalStats};
use sylva_engine::film::Tile;

/// The one thread pool for data-parallel work: render tiles and BVH builds.
#[derive(Resource, Clone)]
pub struct RenderPool(pub Arc<rayon::ThreadPool>);

impl RenderPool {
    /// A pool of `threads` workers named `sylva-worker-N` (0 = one per core).
    pub fn new(threads: usize) -> Result<Self, rayon::ThreadPoolBuildError> {
        let threads = if threads == 0 {
            std::thread::available_parallelism().map_or(1, |n| n.get())
        } else {
            threads
        };
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("sylva-worker-{i}"))
            .build()?;
        Ok(Self(Arc::new(pool)))
    }

    /// Number of worker threads.
    pub fn threads(&self) -> usize {
        self.0.current_num_threads()
    }

    /// Runs `f` inside the pool.
    pub fn install<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        self.0.install(f)
    }
}

/// BVH build settings for both levels.
#[derive(Resource, Clone, Copy, Debug, PartialEq)]
pub struct BuildSettings {
    /// Settings of the top level, built whenever the set of instances changes.
    pub top_level: BuildParams,
    /// When only transforms changed, the top level is refitted instead of rebuilt while
    /// its SAH cost stays within this multiple of its cost when built (see
    /// `benches/README.md` for the measurement behind the default); 0 rebuilds always.
    pub refit_limit: f32,
}

impl BuildSettings {
    /// Default [`refit_limit`](Self::refit_limit).
    pub const REFIT_LIMIT: f32 = 1.2;
}

impl Default for BuildSettings {
    fn default() -> Self {
        Self {
            top_level: BuildParams::TOP_LEVEL,
            refit_limit: Self::REFIT_LIMIT,
        }
    }
}

/// Where the renderer's coordinate origin sits in the world. Instances and cameras are
/// moved by −origin before the TLAS is built and rays are made, so a scene far from the
/// world origin keeps the precision it has near it (f32 carries ~7 digits: at 10⁵ m a
/// coordinate's step is 8 mm, at 10³ m 0.06 mm). `rebase_world_origin` keeps it on a
/// 1024 m grid near the first camera.
#[derive(Resource, Clone, Copy, Debug, Default, PartialEq)]
pub struct WorldOrigin(pub glam::Vec3);

impl WorldOrigin {
    /// Spacing of the grid the origin snaps to: the TLAS is rebuilt only when the camera
    /// crosses a cell, and coordinates stay within a few cells of zero.
    pub const GRID: f32 = 1024.0;

    /// Distance from the world origin beyond which f32 positions step by more than 1 mm
    /// (2¹⁴ m: steps of 2 mm); plants there are placed with that rounding.
    pub const PRECISE_RADIUS: f32 = 16384.0;

    /// The grid point nearest to `position`.
    pub fn snapped(position: glam::Vec3) -> Self {
        if !position.is_finite() {
            return Self::default();
        }
        Self((position / Self::GRID).round() * Self::GRID)
    }

    /// `transform` seen from this origin.
    pub fn relative(&self, transform: glam::Affine3A) -> glam::Affine3A {
        glam::Affine3A {
            translation: transform.translation - glam::Vec3A::from(self.0),
            ..transform
        }
    }
}

/// The seed of every random number the renderer draws.
#[derive(Resource, Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RenderSeed(pub u64);

/// Called once per finished tile, from a worker thread (progress bars, tracing).
pub type TileCallback = Arc<dyn Fn(&Tile) + Send + Sync>;

/// The optional per-tile callback.
#[derive(Resource, Clone, Default)]
pub struct TileProgress(pub Option<TileCallback>);

/// What `rebuild_top_level` has done: counts, timing and the entity of each TLAS id.
#[derive(Resource, Clone, Debug, Default)]
pub struct TopLevelState {
    /// Rebuilds since the world was set up.
    pub rebuilds: u64,
    /// Rebuilds made because a refit had degraded the tree past the refit limit.
    pub degraded_rebuilds: u64,
    /// Refits since the world was set up.
    pub refits: u64,
    /// Duration of the latest rebuild.
    pub last_build: Duration,
    /// Duration of the latest refit.
    pub last_refit: Duration,
    /// SAH cost of the current tree over its cost when built (1 after a build).
    pub degradation: f32,
    /// `entities[id]` is the plant entity of TLAS instance id `id`.
    pub entities: Vec<Entity>,
    /// True once the warning about coarse far-away positions has been given.
    pub warned_far_positions: bool,
}

/// What `render_tiles` has done.
#[derive(Resource, Clone, Debug, Default)]
pub struct RenderStats {
    /// Frames rendered since the world was set up (all cameras).
    pub frames: u64,
    /// Counters of the latest frame (all cameras).
    pub last_frame: TraversalStats,
    /// Wall time of the latest `render_tiles` run.
    pub last_render: Duration,
    /// Counters summed over every frame.
    pub total: TraversalStats,
    /// Wall time summed over every frame.
    pub total_render: Duration,
    /// Frames given up because [`FrameCancel`] was set (not counted in `frames`).
    pub cancelled: u64,
    /// Wall time of the latest `filter_display` run that filtered something.
    pub last_filter: Duration,
}

/// Set from another thread to give up the frame in progress at its next tile: the
/// cameras' films and frame buffers stay as they were, and a camera that moved before
/// it restarts its film with the next complete frame. `render_tiles` clears nothing: the
/// setter clears the flag before the next frame.
#[derive(Resource, Clone, Debug, Default)]
pub struct FrameCancel(pub Option<Arc<std::sync::atomic::AtomicBool>>);
