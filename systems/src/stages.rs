//! The systems of the frame schedule and their run conditions.

use crate::cluster::{Cluster, FrameChecks};
use crate::profile::{FrameProfiler, ProfiledSystem};
use crate::{
    BuildSettings, FrameCancel, RenderPool, RenderSeed, RenderStats, TileProgress, TopLevelState,
    WorldOrigin,
};
use bevy_ecs::prelude::*;
use bevy_ecs::system::SystemParam;
use std::collections::HashSet;
use std::time::Instant;
use sylva_engine::camera::{Camera, CameraView};
use sylva_engine::camera_path::CameraPath;
use sylva_engine::components::{Hidden, Instance, Transform};
use sylva_engine::discontinuity::{DiscontinuityFilter, FilteredImage, GuidedImage};
use sylva_engine::environment::EnvironmentLight;
use sylva_engine::film::{Film, FrameBuffer, Tile};
use sylva_engine::geometry::GeometryLibrary;
use sylva_engine::interleave::{LightInterleave, LightSubsets};
use sylva_engine::light::{DirectionalLight, LightSet, SkyLight};
use sylva_engine::node_animation::NodeAnimation;
use sylva_engine::opacity::OpacityMaps;
use sylva_engine::render::{
    FramePlan, RenderParams, RenderScene, render_frame_unless, render_tile,
};
use sylva_engine::sampling::mix64;
use sylva_engine::shading::{Shader, ShaderTable};
use sylva_engine::sway::{AnimationClock, RestPose, Sway, Wind};
use sylva_engine::tlas::{InstanceDesc, TopLevel};
use sylva_engine::transparency::TransparencyCurve;

/// Plants whose placement, geometry or visibility changed since a system last ran.
type ChangedPlants = (
    With<Instance>,
    Or<(Changed<Transform>, Changed<Instance>, Added<Hidden>)>,
);

/// Cameras whose setting of type `S` changed, or which were just given a frame plan.
type NewPlanInput<S> = Or<(Changed<S>, Added<FramePlan>)>;

/// What `render_tiles` reads and writes per camera.
type RenderedCamera<'a> = (
    Ref<'a, Camera>,
    Ref<'a, Transform>,
    Ref<'a, FramePlan>,
    &'a Film,
    &'a mut FrameBuffer,
);

/// Advances the [`AnimationClock`] by its `frame_seconds` in whole sub-steps (which
/// [`animate`] and [`follow_camera_paths`] then play).
pub fn advance_animation_clock(mut clock: ResMut<AnimationClock>) {
    clock.advance();
}

/// Run condition of [`advance_animation_clock`]: something moves with the clock (a
/// swaying plant, a camera on a path or a node animation); otherwise the clock stands
/// still.
pub fn animation_present(
    sways: Query<(), With<Sway>>,
    paths: Query<(), With<CameraPath>>,
    nodes: Option<Res<NodeAnimationPlayer>>,
) -> bool {
    !sways.is_empty() || !paths.is_empty() || nodes.is_some()
}

/// A node animation (from a glTF file) bound to the world: the plant entity that shows
/// each animated instance, its node, and the transform under the node (GPU instancing's).
#[derive(Resource, Clone, Debug)]
pub struct NodeAnimationPlayer {
    /// The hierarchy and its channels.
    pub animation: NodeAnimation,
    /// `(plant, node, local)`: the plant's transform is the node's world transform times
    /// `local`.
    pub instances: Vec<(Entity, usize, glam::Affine3A)>,
}

/// Poses every plant of the [`NodeAnimationPlayer`] as its node is at the clock's time
/// (held at the last key after the end). Unchanged transforms are not written, so only
/// moving plants refit the top level.
pub fn play_node_animation(
    clock: Res<AnimationClock>,
    player: Res<NodeAnimationPlayer>,
    mut transforms: Query<&mut Transform>,
) {
    let world = player.animation.world_transforms(clock.time as f32);
    for &(entity, node, local) in &player.instances {
        let Some(node_world) = world.get(node) else {
            continue;
        };
        let (scale, rotation, translation) = (*node_world * local).to_scale_rotation_translation();
        if let Ok(mut transform) = transforms.get_mut(entity) {
            transform.set_if_neq(Transform {
                translation,
                rotation: rotation.normalize(),
                scale,
            });
        }
    }
}

/// Puts every camera with a [`CameraPath`] where its path is at the clock's time
/// (position, orientation and field of view; unchanged values are not written, so a
/// camera at rest keeps accumulating).
pub fn follow_camera_paths(
    clock: Res<AnimationClock>,
    mut cameras: Query<(&CameraPath, &mut Transform, &mut Camera)>,
) {
    for (path, mut transform, mut camera) in &mut cameras {
        let (position, rotation, fov) = path.at(clock.time);
        transform.set_if_neq(Transform {
            translation: position,
            rotation,
            ..*transform
        });
        if camera.vertical_fov != fov {
            camera.vertical_fov = fov;
        }
    }
}

/// Sways every plant with a [`Sway`] in the [`Wind`] (none without a `Wind` resource)
/// over the sub-steps the clock took last: its `Transform` becomes its [`RestPose`]
/// tilted about the base. A wind with NaN or ∞ is ignored with a warning.
pub fn animate(
    clock: Res<AnimationClock>,
    wind: Option<Res<Wind>>,
    mut warned: Local<bool>,
    mut plants: Query<(&mut Sway, &RestPose, &mut Transform)>,
    profiler: Res<FrameProfiler>,
) {
    let _timer = profiler.time(ProfiledSystem::Animate);
    let _span = tracing::info_span!("animate").entered();
    let times = clock.latest_times();
    if times.is_empty() {
        return;
    }
    let wind = wind.map(|w| *w).filter(|w| {
        let finite = w.is_finite();
        if !finite && !*warned {
            *warned = true;
            tracing::warn!(?w, "wind with NaN or infinite values ignored");
        }
        finite
    });
    for (mut sway, rest, mut transform) in &mut plants {
        let base = rest.0.translation;
        let position = glam::Vec2::new(base.x, base.z);
        for &t in &times {
            let torque = wind.map_or(glam::DVec2::ZERO, |w| w.torque(sway.wind_gain, position, t));
            sway.substep(torque);
        }
        *transform = rest.0.with_rotation(sway.tilt() * rest.0.rotation);
    }
}

/// Moves the [`WorldOrigin`] to the grid point nearest the first camera when the camera
/// has left its cell (which makes the next TLAS build use it).
pub fn rebase_world_origin(
    cameras: Query<&Transform, With<Camera>>,
    mut origin: ResMut<WorldOrigin>,
    profiler: Res<FrameProfiler>,
) {
    let _timer = profiler.time(ProfiledSystem::RebaseWorldOrigin);
    if let Some(camera) = cameras.iter().next() {
        origin.set_if_neq(WorldOrigin::snapped(camera.translation));
    }
}

/// Run condition of [`rebuild_top_level`]: a plant was added, moved, re-pointed, hidden,
/// shown or removed, the geometry library changed, or the world origin moved.
pub fn instances_changed(
    changed: Query<(), ChangedPlants>,
    mut removed_instances: RemovedComponents<Instance>,
    mut removed_hidden: RemovedComponents<Hidden>,
    library: Res<GeometryLibrary>,
    origin: Res<WorldOrigin>,
) -> bool {
    // Drain both readers every time so old removals are not seen again next frame.
    let removed = removed_instances.read().count() + removed_hidden.read().count();
    removed > 0 || !changed.is_empty() || library.is_changed() || origin.is_changed()
}

/// Brings the TLAS up to date with every visible plant, on the render pool: a refit when
/// the same plants only moved (same entities, same geometry, same library) and the
/// refitted tree's SAH cost stays within [`BuildSettings::refit_limit`] of its cost when
/// built; a full build otherwise.
#[expect(
    clippy::too_many_arguments,
    reason = "a system's parameters are its data access"
)]
pub fn rebuild_top_level(
    pool: Res<RenderPool>,
    library: Res<GeometryLibrary>,
    settings: Res<BuildSettings>,
    origin: Res<WorldOrigin>,
    plants: Query<(Entity, &Transform, &Instance), Without<Hidden>>,
    mut top_level: ResMut<TopLevel>,
    mut state: ResMut<TopLevelState>,
    profiler: Res<FrameProfiler>,
) {
    let _timer = profiler.time(ProfiledSystem::RebuildTopLevel);
    let _span = tracing::info_span!("rebuild_top_level").entered();
    let start = Instant::now();
    let (entities, descs): (Vec<Entity>, Vec<InstanceDesc>) = plants
        .iter()
        .map(|(e, t, i)| {
            (
                e,
                InstanceDesc {
                    transform: origin.relative(t.to_affine()),
                    geometry: i.geometry,
                },
            )
        })
        .unzip();
    let farthest = plants
        .iter()
        .map(|(_, t, _)| t.translation.abs().max_element())
        .fold(0f32, f32::max);
    if farthest > WorldOrigin::PRECISE_RADIUS && !state.warned_far_positions {
        state.warned_far_positions = true;
        tracing::warn!(
            "plants up to {farthest:.0} m from the world origin: their f32 positions are \
             rounded to {:.1} mm steps there (rendering itself is camera-relative and keeps \
             full precision)",
            f32::EPSILON * farthest * 1e3
        );
    }
    let may_refit = settings.refit_limit > 1.0
        && !library.is_changed()
        && !top_level.is_empty()
        && entities == state.entities;
    if may_refit {
        match pool.install(|| top_level.refit(&library, &descs)) {
            Ok(degradation) if degradation <= settings.refit_limit => {
                state.refits += 1;
                state.last_refit = start.elapsed();
                state.degradation = degradation;
                return;
            }
            Ok(degradation) => {
                tracing::debug!(degradation, "top level degraded by refits: rebuilding");
                state.degraded_rebuilds += 1;
            }
            Err(refusal) => tracing::debug!(%refusal, "top level cannot be refitted"),
        }
    }
    pool.install(|| top_level.rebuild(&library, &descs, settings.top_level));
    let built = &*top_level;
    if !built.skipped.ids.is_empty() {
        let named: Vec<String> = built
            .skipped
            .ids
            .iter()
            .take(10)
            .map(|&i| format!("{:?}", entities[i as usize]))
            .collect();
        tracing::warn!(
            singular = built.skipped.singular,
            unknown_geometry = built.skipped.unknown_geometry,
            "instances left out of the top level (singular or non-finite transform, or unknown geometry): {}{}",
            named.join(", "),
            if built.skipped.ids.len() > 10 {
                ", …"
            } else {
                ""
            }
        );
    }
    state.entities = entities;
    state.rebuilds += 1;
    state.last_build = start.elapsed();
    state.degradation = 1.0;
}

/// Run condition of [`compile_shaders`].
pub fn shaders_changed(
    changed: Query<(), Changed<Shader>>,
    mut removed: RemovedComponents<Shader>,
) -> bool {
    removed.read().count() > 0 || !changed.is_empty()
}

/// Run condition of [`build_opacity_maps`]: the meshes or the shaders changed.
pub fn opacity_inputs_changed(library: Res<GeometryLibrary>, shaders: Res<ShaderTable>) -> bool {
    library.is_changed() || shaders.is_changed()
}

/// Builds the [`OpacityMaps`] of the alpha-masked triangles on the render pool, so
/// traversal decides most alpha tests without the texture.
pub fn build_opacity_maps(
    pool: Res<RenderPool>,
    library: Res<GeometryLibrary>,
    shaders: Res<ShaderTable>,
    mut opacity: ResMut<OpacityMaps>,
    profiler: Res<FrameProfiler>,
) {
    let _timer = profiler.time(ProfiledSystem::BuildOpacityMaps);
    *opacity = pool.install(|| OpacityMaps::build(&library, &shaders));
}

/// Packs shader entities into the dense [`ShaderTable`].
pub fn compile_shaders(
    shaders: Query<&Shader>,
    mut table: ResMut<ShaderTable>,
    profiler: Res<FrameProfiler>,
) {
    let _timer = profiler.time(ProfiledSystem::CompileShaders);
    let _span = tracing::info_span!("compile_shaders").entered();
    let mut all: Vec<Shader> = shaders.iter().cloned().collect();
    all.sort_by_key(|s| s.id);
    *table = ShaderTable::new(all);
}

/// Run condition of [`compile_lights`].
pub fn lights_changed(
    suns: Query<(), Changed<DirectionalLight>>,
    skies: Query<(), Changed<SkyLight>>,
    environments: Query<(), Changed<EnvironmentLight>>,
    mut removed_suns: RemovedComponents<DirectionalLight>,
    mut removed_skies: RemovedComponents<SkyLight>,
    mut removed_environments: RemovedComponents<EnvironmentLight>,
) -> bool {
    let removed = removed_suns.read().count()
        + removed_skies.read().count()
        + removed_environments.read().count();
    removed > 0 || !suns.is_empty() || !skies.is_empty() || !environments.is_empty()
}

/// Gathers light entities into the [`LightSet`]; directions are normalised and lights
/// with a zero or non-finite direction or irradiance are dropped with a warning.
pub fn compile_lights(
    suns: Query<&DirectionalLight>,
    skies: Query<&SkyLight>,
    environments: Query<&EnvironmentLight>,
    mut lights: ResMut<LightSet>,
    profiler: Res<FrameProfiler>,
) {
    let _timer = profiler.time(ProfiledSystem::CompileLights);
    let _span = tracing::info_span!("compile_lights").entered();
    *lights = LightSet::compile(suns, skies, environments);
}

/// Run condition of [`adaptive_transparency_lod`]: the shaders or a camera's curve
/// changed.
pub fn transparency_inputs_changed(
    shaders: Res<ShaderTable>,
    cameras: Query<(), NewPlanInput<TransparencyCurve>>,
    mut removed: RemovedComponents<TransparencyCurve>,
) -> bool {
    removed.read().count() > 0 || shaders.is_changed() || !cameras.is_empty()
}

/// Puts each camera's [`TransparencyCurve`] into its [`FramePlan`] when the scene has
/// alpha-masked shaders; otherwise the plan has none and rays keep no hole lists.
pub fn adaptive_transparency_lod(
    shaders: Res<ShaderTable>,
    mut cameras: Query<(Option<&TransparencyCurve>, &mut FramePlan)>,
    profiler: Res<FrameProfiler>,
) {
    let _timer = profiler.time(ProfiledSystem::AdaptiveTransparencyLod);
    let _span = tracing::info_span!("adaptive_transparency_lod").entered();
    for (curve, mut plan) in &mut cameras {
        let transparency = curve.copied().filter(|_| shaders.has_alpha_masks());
        plan.set_if_neq(FramePlan {
            transparency,
            ..*plan
        });
    }
}

/// Run condition of [`assign_light_subsets`]: the lights, the seed or a camera's
/// interleave setting changed.
pub fn light_subset_inputs_changed(
    lights: Res<LightSet>,
    seed: Res<RenderSeed>,
    cameras: Query<(), NewPlanInput<LightInterleave>>,
    mut removed: RemovedComponents<LightInterleave>,
) -> bool {
    removed.read().count() > 0 || lights.is_changed() || seed.is_changed() || !cameras.is_empty()
}

/// Gives each camera with an active [`LightInterleave`] its [`LightSubsets`] when the
/// scene is lit by virtual lights: its pattern, subset count and a random rotation drawn
/// from the seed (over which the estimator is unbiased).
pub fn assign_light_subsets(
    lights: Res<LightSet>,
    seed: Res<RenderSeed>,
    mut cameras: Query<(Option<&LightInterleave>, &mut FramePlan)>,
    profiler: Res<FrameProfiler>,
) {
    let _timer = profiler.time(ProfiledSystem::AssignLightSubsets);
    let _span = tracing::info_span!("assign_light_subsets").entered();
    let has_virtual_lights = lights
        .environment
        .as_ref()
        .is_some_and(|e| e.lights.len() > 1);
    for (interleave, mut plan) in &mut cameras {
        let light_subsets = interleave
            .filter(|i| has_virtual_lights && i.is_active())
            .map(|i| {
                let count = i.subset_count();
                LightSubsets {
                    pattern: i.pattern.max(1),
                    count,
                    offset: (mix64(seed.0 ^ 0x5ab5_e75e) % u64::from(count)) as u32,
                }
            });
        plan.set_if_neq(FramePlan {
            light_subsets,
            ..*plan
        });
    }
}

/// The five resources the kernel reads, as one system parameter.
#[derive(SystemParam)]
pub struct SceneResources<'w> {
    /// Meshes and their BLASes.
    pub library: Res<'w, GeometryLibrary>,
    /// The TLAS.
    pub top_level: Res<'w, TopLevel>,
    /// Shaders by id.
    pub shaders: Res<'w, ShaderTable>,
    /// Lights.
    pub lights: Res<'w, LightSet>,
    /// Opacity micromaps.
    pub opacity: Res<'w, OpacityMaps>,
}

impl SceneResources<'_> {
    /// The kernel's view of the resources.
    pub fn scene(&self) -> RenderScene<'_> {
        RenderScene {
            geometry: &self.library,
            top_level: &self.top_level,
            shaders: &self.shaders,
            lights: &self.lights,
            opacity: &self.opacity,
        }
    }

    /// True when what a frame shows changed since the system last ran: the geometry,
    /// the top level, a shader or a light (opacity maps follow the shaders).
    pub fn changed(&self) -> bool {
        self.library.is_changed()
            || self.top_level.is_changed()
            || self.shaders.is_changed()
            || self.lights.is_changed()
    }
}

/// The kernel's view of `world`'s render resources, when it has them all.
pub fn scene_in(world: &World) -> Option<RenderScene<'_>> {
    Some(RenderScene {
        geometry: world.get_resource::<GeometryLibrary>()?,
        top_level: world.get_resource::<TopLevel>()?,
        shaders: world.get_resource::<ShaderTable>()?,
        lights: world.get_resource::<LightSet>()?,
        opacity: world.get_resource::<OpacityMaps>()?,
    })
}

/// Renders one frame per camera, tiles in parallel on the render pool. The frame index
/// is the film's frame count, or 0 — restarting accumulation — when the camera or the
/// scene changed since the last frame.
#[expect(
    clippy::too_many_arguments,
    reason = "a system's parameters are its data access"
)]
pub fn render_tiles(
    pool: Res<RenderPool>,
    data: SceneResources,
    seed: Res<RenderSeed>,
    origin: Res<WorldOrigin>,
    progress: Res<TileProgress>,
    cancel: Res<FrameCancel>,
    mut cameras: Query<(Entity, RenderedCamera)>,
    mut stats: ResMut<RenderStats>,
    mut restart_owed: Local<HashSet<Entity>>,
    profiler: Res<FrameProfiler>,
    mut cluster: Option<ResMut<Cluster>>,
    mut cluster_scene: Local<Option<u64>>,
) {
    let _timer = profiler.time(ProfiledSystem::RenderTiles);
    let _span = tracing::info_span!("render_tiles").entered();
    let start = Instant::now();
    let scene_changed = data.changed();
    let scene = data.scene();
    let on_tile = |tile: &Tile, time: std::time::Duration| {
        profiler.tile(*tile, time);
        if let Some(callback) = &progress.0 {
            callback(tile);
        }
    };
    if cluster.is_some() && (cluster_scene.is_none() || scene_changed) {
        *cluster_scene = Some(crate::cluster::scene_hash(
            &data.library,
            &data.top_level,
            &data.shaders,
            &data.lights,
        ));
    }
    let mut frame_stats = sylva_engine::bvh::TraversalStats::default();
    let mut cancelled = false;
    for (entity, (camera, transform, plan, film, mut frame)) in &mut cameras {
        let resized = film.width() != camera.width || film.height() != camera.height;
        // A film loaded from a checkpoint continues its frame sequence even though the
        // world around it is new. A change seen by a cancelled frame is still owed.
        let changed = scene_changed
            || camera.is_changed()
            || transform.is_changed()
            || plan.is_changed()
            || restart_owed.contains(&entity);
        let restart = resized || (changed && !film.awaiting_resume());
        let frame_index = if restart { 0 } else { film.frames() };
        let view = CameraView::new(&camera, &origin.relative(transform.to_affine()));
        let params = RenderParams::for_camera(&camera, seed.0)
            .with_plan(&plan)
            .at_frame(frame_index);
        let rendered = match cluster.as_deref_mut() {
            Some(cluster) => {
                let checks = FrameChecks {
                    frame: frame_index,
                    scene: cluster_scene.unwrap_or_default(),
                    view: crate::cluster::view_hash(&view, &params),
                };
                let tiles = Tile::grid(view.width(), view.height(), params.tile_size);
                cluster.render_frame(
                    &pool.0,
                    view.width(),
                    view.height(),
                    &tiles,
                    checks,
                    &|tile| render_tile(&scene, &view, &params, tile, frame_index),
                    &on_tile,
                    cancel.0.as_deref(),
                )
            }
            None => pool.install(|| {
                render_frame_unless(
                    &scene,
                    &view,
                    &params,
                    frame_index,
                    &on_tile,
                    cancel.0.as_deref(),
                )
            }),
        };
        match rendered {
            Some(rendered) => {
                *frame = rendered;
                frame_stats.add(&frame.stats);
                restart_owed.remove(&entity);
            }
            None => {
                cancelled = true;
                if restart {
                    restart_owed.insert(entity);
                }
            }
        }
    }
    if cancelled {
        stats.cancelled += 1;
        return;
    }
    stats.frames += 1;
    stats.last_frame = frame_stats;
    stats.total.add(&frame_stats);
    let elapsed = start.elapsed();
    stats.last_render = elapsed;
    stats.total_render += elapsed;
}

/// Adds each camera's new frame to its film (a frame with index 0 resets the film).
pub fn accumulate(
    mut cameras: Query<(&FrameBuffer, &mut Film), Changed<FrameBuffer>>,
    profiler: Res<FrameProfiler>,
) {
    let _timer = profiler.time(ProfiledSystem::Accumulate);
    for (frame, mut film) in &mut cameras {
        if frame.width > 0 {
            film.accumulate(frame);
        }
    }
}

/// Filters the film of each camera with a [`DiscontinuityFilter`] into its
/// [`FilteredImage`]: the film's means, demodulated by the latest frame's albedo and
/// compared by its surfaces. The film itself is left as accumulated.
pub fn filter_display(
    mut commands: Commands,
    pool: Res<RenderPool>,
    cameras: Query<(Entity, &Film, &FrameBuffer, &DiscontinuityFilter), Changed<Film>>,
    mut stats: ResMut<RenderStats>,
    profiler: Res<FrameProfiler>,
) {
    let _timer = profiler.time(ProfiledSystem::FilterDisplay);
    let _span = tracing::info_span!("filter_display").entered();
    let start = Instant::now();
    let mut filtered = false;
    for (entity, film, frame, filter) in &cameras {
        // An empty film (its first frame given up) has nothing to filter.
        if frame.width != film.width()
            || frame.height != film.height()
            || film.frames() == 0
            || filter.strength(film.frames()) == 0.0
        {
            // Nothing to show but the film itself.
            commands.entity(entity).remove::<FilteredImage>();
            continue;
        }
        let means: Vec<glam::Vec3> = film.mean_rgb().into_iter().map(glam::Vec3::from).collect();
        let pixels = pool.install(|| {
            filter.apply_progressive(
                film.frames(),
                &GuidedImage {
                    width: film.width(),
                    height: film.height(),
                    radiance: &means,
                    albedo: &frame.mean_albedo(),
                    emission: &frame.mean_emission(),
                    surfaces: &frame.pixels.surfaces,
                },
            )
        });
        commands.entity(entity).insert(FilteredImage {
            pixels,
            frames: film.frames(),
        });
        filtered = true;
    }
    if filtered {
        stats.last_filter = start.elapsed();
    }
}

/// The image a camera shows: its film, with the filtered means when a [`FilteredImage`]
/// of the film's current frame count exists.
pub fn shown_film<'a>(
    film: &'a Film,
    filtered: Option<&FilteredImage>,
) -> std::borrow::Cow<'a, Film> {
    match filtered {
        Some(image) if image.frames == film.frames() => {
            std::borrow::Cow::Owned(film.with_means(&image.pixels))
        }
        _ => std::borrow::Cow::Borrowed(film),
    }
}
