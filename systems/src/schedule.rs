//! The frame schedule in one place, as bevy keeps `Render`'s: the [`RenderSystems`] sets
//! and their chain, every stage's `add_systems` with its run condition, which optional
//! stages a world needs ([`Stages`]), and how a program installs them into its own
//! `World` and `Schedule` ([`install`]).

use crate::embed::{FrameImage, publish_frame_images};
use crate::profile::{mark_stage, profiling};
use crate::stages::*;
use crate::{
    BuildSettings, FrameCancel, RenderPool, RenderSeed, RenderStats, TileProgress, TopLevelState,
    WorldOrigin, profile,
};
use bevy_ecs::prelude::*;
use bevy_ecs::schedule::{MultiThreadedExecutor, ScheduleLabel};
use bevy_ecs::system::System;
use std::any::TypeId;
use std::sync::Arc;
use sylva_engine::camera::Camera;
use sylva_engine::camera_path::CameraPath;
use sylva_engine::discontinuity::DiscontinuityFilter;
use sylva_engine::environment::EnvironmentLight;
use sylva_engine::geometry::GeometryLibrary;
use sylva_engine::light::LightSet;
use sylva_engine::opacity::OpacityMaps;
use sylva_engine::shading::{Shader, ShaderTable};
use sylva_engine::sway::Sway;
use sylva_engine::tlas::TopLevel;

/// The stages of a frame, run in this order.
#[derive(SystemSet, Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum RenderSystems {
    /// Rigid motion writes `Transform`s.
    Animate,
    /// Acceleration structures, shaders and lights are brought up to date.
    Prepare,
    /// Each camera's frame plan: transparency curve and light subsets.
    Plan,
    /// Each camera renders a frame.
    Render,
    /// Frames are added to films.
    Accumulate,
    /// Films are filtered for display.
    Display,
    /// A frame's results are read: [`FrameImage`]s are refreshed, and a
    /// program's own systems go here or after (the CLI writes its images after the
    /// schedule).
    Output,
}

/// The label of the frame schedule.
#[derive(ScheduleLabel, Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Frame;

/// The optional stages. Leaving one out never makes an image wrong, only slower or
/// without the effect: without `animation` plants do not sway; without `alpha_masks`
/// every alpha test reads the texture and transparency stays exact at any distance;
/// without `environment` each hit samples all virtual lights' subsets as one (no
/// interleaving); without `display_filter` the shown image is the film's.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Stages {
    /// [`advance_animation_clock`], [`animate`] (`Sway` components in the `Wind`),
    /// [`follow_camera_paths`] (`CameraPath`s) and [`play_node_animation`] (a glTF
    /// file's animation).
    pub animation: bool,
    /// [`build_opacity_maps`] and [`adaptive_transparency_lod`]: alpha-masked shaders.
    pub alpha_masks: bool,
    /// [`assign_light_subsets`]: an `EnvironmentLight`'s interleaved virtual lights.
    pub environment: bool,
    /// [`filter_display`]: cameras with a `DiscontinuityFilter`.
    pub display_filter: bool,
}

impl Stages {
    /// Every stage: what [`frame_schedule`](crate::frame_schedule) runs, for worlds whose
    /// content changes while they run.
    pub const ALL: Stages = Stages {
        animation: true,
        alpha_masks: true,
        environment: true,
        display_filter: true,
    };

    /// Only the stages every frame needs: top level, shaders, lights, tiles,
    /// accumulation and the [`FrameImage`]s.
    pub const NONE: Stages = Stages {
        animation: false,
        alpha_masks: false,
        environment: false,
        display_filter: false,
    };

    /// The stages `world`'s content uses now: a scene that will not gain swaying plants,
    /// alpha-masked shaders, an environment light or a filtered camera later leaves those
    /// systems out of its schedule.
    pub fn needed_by(world: &mut World) -> Stages {
        let alpha_masks = world
            .query::<&Shader>()
            .iter(world)
            .any(|s| s.texture.is_some() && s.alpha_cutoff.is_some());
        Stages {
            animation: has_component::<Sway>(world)
                || has_component::<CameraPath>(world)
                || world.contains_resource::<NodeAnimationPlayer>(),
            alpha_masks,
            environment: has_component::<EnvironmentLight>(world),
            display_filter: has_component::<DiscontinuityFilter>(world),
        }
    }
}

impl Default for Stages {
    fn default() -> Self {
        Self::ALL
    }
}

/// True when some entity of `world` has a `C`.
pub(crate) fn has_component<C: Component>(world: &mut World) -> bool {
    world
        .query_filtered::<(), With<C>>()
        .iter(world)
        .next()
        .is_some()
}

/// How [`install`] sets Sylva up.
#[derive(Clone, Default)]
pub struct RenderOptions {
    /// Workers of Sylva's own pool (0 = one per core); unused with [`pool`](Self::pool).
    pub threads: usize,
    /// A rayon pool the program already runs its own parallel work on: Sylva's tiles and
    /// builds then run on the same workers, so the cores are shared rather than
    /// oversubscribed by a second pool.
    pub pool: Option<Arc<rayon::ThreadPool>>,
    /// The optional stages to install.
    pub stages: Stages,
}

/// Inserts every resource the schedule needs (keeping those already present) and a
/// render pool of `threads` workers (0 = one per core).
pub fn init_render_world(
    world: &mut World,
    threads: usize,
) -> Result<(), rayon::ThreadPoolBuildError> {
    world.insert_resource(RenderPool::new(threads)?);
    init_resources(world);
    Ok(())
}

/// Inserts the resources the stages read, keeping those already present.
fn init_resources(world: &mut World) {
    world.init_resource::<GeometryLibrary>();
    world.init_resource::<TopLevel>();
    world.init_resource::<ShaderTable>();
    world.init_resource::<OpacityMaps>();
    world.init_resource::<LightSet>();
    world.init_resource::<BuildSettings>();
    world.init_resource::<RenderSeed>();
    world.init_resource::<WorldOrigin>();
    world.init_resource::<sylva_engine::sway::AnimationClock>();
    world.init_resource::<TileProgress>();
    world.init_resource::<TopLevelState>();
    world.init_resource::<RenderStats>();
    world.init_resource::<FrameCancel>();
    world.init_resource::<profile::FrameProfiler>();
}

/// The frame schedule with every stage ([`Stages::ALL`]), each with its run
/// condition, on the multi-threaded executor.
pub fn frame_schedule() -> Schedule {
    let mut schedule = Schedule::new(Frame);
    schedule.set_executor(MultiThreadedExecutor::new());
    add_render_systems(&mut schedule, Stages::ALL);
    schedule
}

/// Inserts Sylva's resources into `world` (keeping those already present) and adds its
/// stages to `schedule` in the [`RenderSystems`] sets, chained in their order. A
/// program orders its own systems against the sets.
pub fn install(
    world: &mut World,
    schedule: &mut Schedule,
    options: &RenderOptions,
) -> Result<(), rayon::ThreadPoolBuildError> {
    let pool = match &options.pool {
        Some(pool) => RenderPool(pool.clone()),
        None => RenderPool::new(options.threads)?,
    };
    world.insert_resource(pool);
    init_resources(world);
    add_render_systems(schedule, options.stages);
    Ok(())
}

/// Adds the stages to `schedule`: the required ones and the optional ones `stages`
/// selects, each with its run condition, in the chained [`RenderSystems`] sets.
pub fn add_render_systems(schedule: &mut Schedule, stages: Stages) {
    schedule.configure_sets(
        (
            RenderSystems::Animate,
            RenderSystems::Prepare,
            RenderSystems::Plan,
            RenderSystems::Render,
            RenderSystems::Accumulate,
            RenderSystems::Display,
            RenderSystems::Output,
        )
            .chain(),
    );
    schedule.add_systems((
        (
            rebase_world_origin,
            rebuild_top_level.run_if(instances_changed),
        )
            .chain()
            .in_set(RenderSystems::Prepare),
        compile_shaders
            .run_if(shaders_changed)
            .in_set(RenderSystems::Prepare),
        compile_lights
            .run_if(lights_changed)
            .in_set(RenderSystems::Prepare),
        render_tiles
            .run_if(any_with_component::<Camera>)
            .in_set(RenderSystems::Render),
        accumulate.in_set(RenderSystems::Accumulate),
        publish_frame_images
            .run_if(any_with_component::<FrameImage>)
            .in_set(RenderSystems::Output),
    ));
    // The profile's stage boundaries (they run only while a profiler is enabled).
    schedule.add_systems((
        mark_stage::<0>
            .run_if(profiling)
            .before(RenderSystems::Animate),
        mark_stage::<1>
            .run_if(profiling)
            .after(RenderSystems::Animate)
            .before(RenderSystems::Prepare),
        mark_stage::<2>
            .run_if(profiling)
            .after(RenderSystems::Prepare)
            .before(RenderSystems::Plan),
        mark_stage::<3>
            .run_if(profiling)
            .after(RenderSystems::Plan)
            .before(RenderSystems::Render),
        mark_stage::<4>
            .run_if(profiling)
            .after(RenderSystems::Render)
            .before(RenderSystems::Accumulate),
        mark_stage::<5>
            .run_if(profiling)
            .after(RenderSystems::Accumulate)
            .before(RenderSystems::Display),
        mark_stage::<6>
            .run_if(profiling)
            .after(RenderSystems::Display)
            .before(RenderSystems::Output),
        mark_stage::<7>
            .run_if(profiling)
            .after(RenderSystems::Output),
    ));
    if stages.animation {
        schedule.add_systems(
            (
                advance_animation_clock.run_if(animation_present),
                animate.run_if(any_with_component::<Sway>),
                follow_camera_paths.run_if(any_with_component::<CameraPath>),
                play_node_animation.run_if(resource_exists::<NodeAnimationPlayer>),
            )
                .chain()
                .in_set(RenderSystems::Animate),
        );
    }
    // The plan's two systems write the same `FramePlan`s: light subsets after the
    // transparency curve (an ordering against a system the schedule lacks does nothing).
    if stages.alpha_masks {
        schedule.add_systems(
            adaptive_transparency_lod
                .run_if(transparency_inputs_changed)
                .in_set(RenderSystems::Plan),
        );
    }
    if stages.environment {
        schedule.add_systems(
            assign_light_subsets
                .run_if(light_subset_inputs_changed)
                .after(adaptive_transparency_lod)
                .in_set(RenderSystems::Plan),
        );
    }
    if stages.alpha_masks {
        schedule.add_systems(
            build_opacity_maps
                .run_if(opacity_inputs_changed)
                .in_set(RenderSystems::Plan),
        );
    }
    if stages.display_filter {
        schedule.add_systems(
            filter_display
                .run_if(any_with_component::<DiscontinuityFilter>)
                .in_set(RenderSystems::Display),
        );
    }
}

/// The name of `system` when it is one of Sylva's stages (found by its type, so a
/// program can list its schedule without bevy_ecs's `debug` feature, which names
/// systems); `None` for any other system.
pub fn stage_name(system: &dyn System<In = (), Out = ()>) -> Option<&'static str> {
    fn type_of<M>(s: impl IntoSystem<(), (), M>) -> TypeId {
        IntoSystem::into_system(s).system_type()
    }
    let stages = [
        (type_of(advance_animation_clock), "advance_animation_clock"),
        (type_of(animate), "animate"),
        (type_of(follow_camera_paths), "follow_camera_paths"),
        (type_of(play_node_animation), "play_node_animation"),
        (type_of(rebase_world_origin), "rebase_world_origin"),
        (type_of(rebuild_top_level), "rebuild_top_level"),
        (type_of(compile_shaders), "compile_shaders"),
        (type_of(compile_lights), "compile_lights"),
        (
            type_of(adaptive_transparency_lod),
            "adaptive_transparency_lod",
        ),
        (type_of(assign_light_subsets), "assign_light_subsets"),
        (type_of(build_opacity_maps), "build_opacity_maps"),
        (type_of(render_tiles), "render_tiles"),
        (type_of(accumulate), "accumulate"),
        (type_of(filter_display), "filter_display"),
        (type_of(publish_frame_images), "publish_frame_images"),
        (type_of(mark_stage::<0>), "mark_stage"),
        (type_of(mark_stage::<1>), "mark_stage"),
        (type_of(mark_stage::<2>), "mark_stage"),
        (type_of(mark_stage::<3>), "mark_stage"),
        (type_of(mark_stage::<4>), "mark_stage"),
        (type_of(mark_stage::<5>), "mark_stage"),
        (type_of(mark_stage::<6>), "mark_stage"),
        (type_of(mark_stage::<7>), "mark_stage"),
    ];
    let id = system.system_type();
    stages.iter().find(|(t, _)| *t == id).map(|(_, name)| *name)
}
