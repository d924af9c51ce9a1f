//! Picking: which plant (entity) a camera sees at a pixel, by casting the pixel's centre
//! ray through the current top level (closest hit with exact alpha tests, so a hole in a
//! leaf shows what lies behind it) and mapping the hit instance to its entity.

use crate::{TopLevelState, WorldOrigin};
use bevy_ecs::prelude::*;
use glam::{Vec2, Vec3};
use sylva_engine::bvh::TraversalStats;
use sylva_engine::camera::{Camera, CameraView};
use sylva_engine::components::Transform;
use sylva_engine::geometry::GeometryLibrary;

/// The plant an editor has selected, if any.
#[derive(Resource, Clone, Copy, Debug, Default, PartialEq)]
pub struct Selected(pub Option<Entity>);

/// What a pixel shows.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Picked {
    /// The entity of the instance hit (a plant, or the terrain).
    pub entity: Entity,
    /// The hit point in world coordinates.
    pub point: Vec3,
    /// Distance from the camera along the ray.
    pub distance: f32,
}

/// The entity `camera` sees through the centre of pixel `(x, y)` (pixels from the
/// top-left corner) as of the last `rebuild_top_level`; `None` for the sky, a pixel
/// outside the image or a world without a camera or a top level.
pub fn pick(world: &World, camera: Entity, x: u32, y: u32) -> Option<Picked> {
    let (Some(cam), Some(transform)) =
        (world.get::<Camera>(camera), world.get::<Transform>(camera))
    else {
        return None;
    };
    if x >= cam.width || y >= cam.height {
        return None;
    }
    let origin = world
        .get_resource::<WorldOrigin>()
        .copied()
        .unwrap_or_default();
    let scene = crate::scene_in(world)?;
    let view = CameraView::new(cam, &origin.relative(transform.to_affine()));
    let ray = view.ray(Vec2::new(x as f32 + 0.5, y as f32 + 0.5), Vec2::splat(0.5));
    let hit = scene.closest(&ray, &mut TraversalStats::default())?;
    let entity = *world
        .get_resource::<TopLevelState>()?
        .entities
        .get(hit.instance as usize)?;
    Some(Picked {
        entity,
        point: Vec3::from(ray.at(hit.t)) + origin.0,
        distance: hit.t * ray.direction.length(),
    })
}

/// A plant as the editor's top-down map draws it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MapPlant {
    /// Its entity.
    pub entity: Entity,
    /// Where it stands (world x, z).
    pub position: glam::Vec2,
    /// Crown radius in metres: half the larger horizontal extent of its mesh, scaled.
    pub radius: f32,
    /// Its species (geometry index), for the colour.
    pub species: u32,
}

/// Every plant (an entity with an [`Instance`](sylva_engine::components::Instance) and a
/// [`Layer`](sylva_engine::components::Layer)) as the map draws it, in entity order.
pub fn map_plants(world: &mut World) -> Vec<MapPlant> {
    use sylva_engine::components::{Instance, Layer};
    let extents: Vec<f32> = world
        .get_resource::<GeometryLibrary>()
        .map(|library| {
            library
                .geometries
                .iter()
                .map(|g| {
                    let b = g.bounds();
                    if b.is_empty() {
                        0.0
                    } else {
                        0.5 * (b.max.x - b.min.x).max(b.max.z - b.min.z)
                    }
                })
                .collect()
        })
        .unwrap_or_default();
    let mut plants: Vec<MapPlant> = world
        .query_filtered::<(Entity, &Instance, &Transform), With<Layer>>()
        .iter(world)
        .map(|(entity, instance, transform)| MapPlant {
            entity,
            position: glam::Vec2::new(transform.translation.x, transform.translation.z),
            radius: extents
                .get(instance.geometry.0 as usize)
                .copied()
                .unwrap_or(0.0)
                * transform.scale.x.abs().max(transform.scale.z.abs()),
            species: instance.geometry.0,
        })
        .collect();
    plants.sort_by_key(|p| p.entity);
    plants
}
