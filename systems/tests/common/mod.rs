//! What the systems tests' worlds share.

use bevy_ecs::prelude::*;
use glam::Vec3;
use sylva_engine::light::{DirectionalLight, SkyLight};

/// The tests' light: a sun from the upper right and a constant grey sky.
pub fn spawn_sun_and_sky(world: &mut World) {
    world.spawn(DirectionalLight {
        direction: Vec3::new(0.3, 1.0, 0.2),
        irradiance: Vec3::splat(3.0),
    });
    world.spawn(SkyLight::constant(Vec3::splat(0.5)));
}
