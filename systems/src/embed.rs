//! Putting Sylva into a program's own `World` and `Schedule`: which stages are installed
//! ([`Stages`]), whose threads render ([`RenderOptions`]), and a frame's results as slices
//! the program reads in place ([`FrameImage`]).
//!
//! ```no_run
//! use bevy_ecs::prelude::*;
//! use sylva_systems::embed::{RenderOptions, install};
//! use sylva_systems::RenderSystems;
//!
//! fn my_physics() {}
//! fn my_hud() {}
//!
//! let mut world = World::new();
//! let mut schedule = Schedule::default();
//! install(&mut world, &mut schedule, &RenderOptions::default()).unwrap();
//! schedule.add_systems((
//!     my_physics.before(RenderSystems::Prepare),
//!     my_hud.after(RenderSystems::Output),
//! ));
//! ```

use crate::profile::{FrameProfiler, ProfiledSystem, mark_stage, profiling};
use crate::systems::*;
use crate::{RenderPool, RenderSystems, init_resources};
use bevy_ecs::prelude::*;
use bevy_ecs::system::System;
use std::any::TypeId;
use std::sync::Arc;
use sylva_engine::camera::Camera;
use sylva_engine::camera_path::CameraPath;
use sylva_engine::discontinuity::{DiscontinuityFilter, FilteredImage};
use sylva_engine::environment::EnvironmentLight;
use sylva_engine::film::{Film, tone_map_srgba8};
use sylva_engine::shading::Shader;
use sylva_engine::sway::Sway;

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
    // The plan's two systems write the same `FramePlan`s: chained when both run.
    match (stages.alpha_masks, stages.environment) {
        (true, true) => {
            schedule.add_systems(
                (
                    adaptive_transparency_lod.run_if(transparency_inputs_changed),
                    assign_light_subsets.run_if(light_subset_inputs_changed),
                )
                    .chain()
                    .in_set(RenderSystems::Plan),
            );
        }
        (true, false) => {
            schedule.add_systems(
                adaptive_transparency_lod
                    .run_if(transparency_inputs_changed)
                    .in_set(RenderSystems::Plan),
            );
        }
        (false, true) => {
            schedule.add_systems(
                assign_light_subsets
                    .run_if(light_subset_inputs_changed)
                    .in_set(RenderSystems::Plan),
            );
        }
        (false, false) => {}
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

/// A camera's latest image as a program reads it in place: mean linear radiance as
/// RGBA `f32` and the tone-mapped sRGB RGBA bytes of a texture upload, row-major from
/// the top-left pixel. Put `FrameImage::new(exposure)` on a camera and
/// [`publish_frame_images`] refreshes it (in [`RenderSystems::Output`]) whenever the
/// camera's film changes, from the filtered image when the camera has a display filter.
#[derive(Component, Clone, Debug, Default, PartialEq)]
pub struct FrameImage {
    exposure: f32,
    width: u32,
    height: u32,
    frames: u32,
    linear_rgba: Vec<f32>,
    srgba8: Vec<u8>,
}

impl FrameImage {
    /// An empty image to be filled, tone-mapped at `exposure` stops.
    pub fn new(exposure: f32) -> Self {
        Self {
            exposure,
            ..Self::default()
        }
    }

    /// Width in pixels (0 before the first frame).
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels (0 before the first frame).
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Frames accumulated in the image.
    pub fn frames(&self) -> u32 {
        self.frames
    }

    /// Mean linear radiance, four `f32` per pixel (alpha 1).
    pub fn linear_rgba(&self) -> &[f32] {
        &self.linear_rgba
    }

    /// Tone-mapped sRGB, four bytes per pixel (alpha 255), as the PNG writer shows it.
    pub fn srgba8(&self) -> &[u8] {
        &self.srgba8
    }

    /// Refills the buffers from `film`, or from `filtered` means when they belong to the
    /// film's current frame count. The buffers keep their allocation between frames.
    pub fn update(&mut self, film: &Film, filtered: Option<&FilteredImage>) {
        let (width, height) = (film.width(), film.height());
        let pixels = width as usize * height as usize;
        self.width = width;
        self.height = height;
        self.frames = film.frames();
        self.linear_rgba.resize(pixels * 4, 0.0);
        self.srgba8.resize(pixels * 4, 0);
        let filtered = filtered
            .filter(|f| f.frames == film.frames() && f.pixels.len() == pixels)
            .map(|f| &f.pixels);
        let scale = 2f32.powf(self.exposure);
        let rows = self
            .linear_rgba
            .chunks_exact_mut(4)
            .zip(self.srgba8.chunks_exact_mut(4));
        for (i, (linear, srgb)) in rows.enumerate() {
            let rgb = match filtered {
                Some(means) => means[i].to_array(),
                None => {
                    let (x, y) = ((i % width as usize) as u32, (i / width as usize) as u32);
                    film.pixel(x, y).map(|v| v as f32)
                }
            };
            linear.copy_from_slice(&[rgb[0], rgb[1], rgb[2], 1.0]);
            srgb.copy_from_slice(&tone_map_srgba8(rgb, scale));
        }
    }
}

/// Refreshes the [`FrameImage`] of every camera whose film changed.
pub fn publish_frame_images(
    mut cameras: Query<(&Film, Option<&FilteredImage>, &mut FrameImage), Changed<Film>>,
    profiler: Res<FrameProfiler>,
) {
    let _timer = profiler.time(ProfiledSystem::PublishFrameImages);
    let _span = tracing::info_span!("publish_frame_images").entered();
    for (film, filtered, mut image) in &mut cameras {
        image.update(film, filtered);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sylva_engine::film::FrameBuffer;

    #[test]
    fn the_image_holds_the_films_means_and_the_png_bytes() {
        let mut film = Film::new(3, 2);
        film.accumulate(&FrameBuffer::new(3, 2, 0));
        film.add_sample(0, 0, glam::Vec3::new(0.5, 1.0, 2.0));
        film.add_sample(2, 1, glam::Vec3::new(4.0, 0.0, 0.25));
        let mut image = FrameImage::new(0.5);
        image.update(&film, None);
        assert_eq!((image.width(), image.height(), image.frames()), (3, 2, 1));
        assert_eq!(&image.linear_rgba()[..4], &[0.5, 1.0, 2.0, 1.0]);
        assert_eq!(&image.linear_rgba()[20..], &[4.0, 0.0, 0.25, 1.0]);
        assert_eq!(image.srgba8(), film.to_srgba8(0.5).as_slice());
    }

    #[test]
    fn a_filtered_image_of_the_current_frame_is_shown_and_a_stale_one_is_not() {
        let mut film = Film::new(2, 1);
        film.accumulate(&FrameBuffer::new(2, 1, 0));
        film.add_sample(0, 0, glam::Vec3::ONE);
        let filtered = |frames| FilteredImage {
            pixels: vec![glam::Vec3::splat(0.25); 2],
            frames,
        };
        let mut image = FrameImage::new(0.0);
        image.update(&film, Some(&filtered(1)));
        assert_eq!(&image.linear_rgba()[..3], &[0.25, 0.25, 0.25]);
        image.update(&film, Some(&filtered(7)));
        assert_eq!(&image.linear_rgba()[..3], &[1.0, 1.0, 1.0]);
    }
}
