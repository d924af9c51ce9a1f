//! # sylva
//!
//! A data-oriented ECS ray tracer for dense plant ecosystems. This facade re-exports the
//! three crates — [`engine`] (data and kernels), [`systems`] (the bevy_ecs schedule) and
//! [`scenes`] (world builders) — and a [`prelude`] with what an embedding program needs.
//!
//! ```no_run
//! use sylva::prelude::*;
//!
//! let mut world = World::new();
//! init_render_world(&mut world, 0).unwrap();
//! let scene = build_scene("meadow", 0).unwrap();
//! let spawned = spawn(&mut world, scene);
//! let mut schedule = frame_schedule();
//! schedule.run(&mut world);
//! let film = world.get::<Film>(spawned.camera).unwrap();
//! film.write_png("meadow.png".as_ref(), 0.0).unwrap();
//! ```

pub use sylva_engine as engine;
pub use sylva_scenes as scenes;
pub use sylva_systems as systems;

/// What an embedding program needs, in one import.
pub mod prelude {
    pub use bevy_ecs::prelude::*;
    pub use glam::{Quat, Vec3};
    pub use sylva_engine::components::Layer;
    pub use sylva_engine::environment::{EnvironmentLight, EnvironmentMap};
    pub use sylva_engine::interleave::LightInterleave;
    pub use sylva_engine::transparency::TransparencyCurve;
    pub use sylva_engine::{
        Camera, DirectionalLight, Film, FrameBuffer, GeometryId, GeometryLibrary, Hidden, Instance,
        Lens, Shader, ShaderId, SkyLight, Transform,
    };
    pub use sylva_scenes::{SceneBuild, build_scene, move_plant, plant_at, spawn};
    pub use sylva_systems::embed::FrameImage;
    pub use sylva_systems::picking::pick;
    pub use sylva_systems::{
        Fingerprint, Flow, Frame, Progress, Quality, RenderPool, RenderSeed, RenderStats,
        RenderSystems, StopAt, Stopped, TileProgress, TopLevelState, frame_schedule,
        init_render_world, refine,
    };
    pub use sylva_systems::{RenderOptions, Stages, install};
}
