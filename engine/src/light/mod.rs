//! Lights: a directional sun and a gradient sky. Light entities carry these components;
//! the kernel reads them through [`LightSet`].

pub mod environment;
pub mod interleave;

use crate::light::environment::EnvironmentLight;
use bevy_ecs::{component::Component, resource::Resource};
use glam::{Vec3, Vec3A};
use std::sync::Arc;

/// A distant light such as the sun.
#[derive(Component, Clone, Copy, Debug, PartialEq)]
pub struct DirectionalLight {
    /// Unit direction from the scene toward the light.
    pub direction: Vec3,
    /// Irradiance on a surface facing the light (linear RGB).
    pub irradiance: Vec3,
}

/// A sky whose radiance blends from `horizon` to `zenith` with elevation; below the
/// horizon it is `ground`. Equal colours give a constant sky.
#[derive(Component, Clone, Copy, Debug, PartialEq)]
pub struct SkyLight {
    /// Radiance straight up.
    pub zenith: Vec3,
    /// Radiance at the horizon.
    pub horizon: Vec3,
    /// Radiance from below the horizon.
    pub ground: Vec3,
}

impl SkyLight {
    /// A sky of one radiance in every direction.
    pub fn constant(radiance: Vec3) -> Self {
        Self {
            zenith: radiance,
            horizon: radiance,
            ground: radiance,
        }
    }

    /// Radiance arriving from direction `d` (+Y is up; `d` need not be unit length).
    #[inline]
    pub fn radiance(&self, d: Vec3A) -> Vec3A {
        let len = d.length();
        let y = if len > 0.0 { d.y / len } else { 0.0 };
        if y < 0.0 {
            self.ground.into()
        } else {
            Vec3A::from(self.horizon).lerp(self.zenith.into(), y.sqrt())
        }
    }
}

/// The lights the kernel shades with, compiled from light entities.
#[derive(Clone, Debug, Default, Resource)]
pub struct LightSet {
    /// Directional lights, normalised directions.
    pub directional: Vec<DirectionalLight>,
    /// The sky, if any (black otherwise); unused while an environment map is set.
    pub sky: Option<SkyLight>,
    /// An HDR environment and its virtual lights; replaces the sky.
    pub environment: Option<Arc<EnvironmentLight>>,
}

impl LightSet {
    /// The set the kernel reads from the scene's light components: directional lights
    /// with a usable direction and irradiance (normalised; others are left out with a
    /// warning), the first valid sky and the first environment (a warning when there
    /// are more). The schedule's `compile_lights` and the benchmarks both build it here.
    pub fn compile<'a>(
        suns: impl IntoIterator<Item = &'a DirectionalLight>,
        skies: impl IntoIterator<Item = &'a SkyLight>,
        environments: impl IntoIterator<Item = &'a EnvironmentLight>,
    ) -> LightSet {
        let mut directional = Vec::new();
        for light in suns {
            let direction = light.direction.normalize_or_zero();
            if direction == Vec3::ZERO
                || !light.irradiance.is_finite()
                || light.irradiance.min_element() < 0.0
            {
                tracing::warn!(
                    ?light,
                    "directional light ignored: zero direction or bad irradiance"
                );
                continue;
            }
            directional.push(DirectionalLight {
                direction,
                ..*light
            });
        }
        let skies: Vec<&SkyLight> = skies.into_iter().collect();
        let sky = skies
            .iter()
            .find(|s| s.zenith.is_finite() && s.horizon.is_finite() && s.ground.is_finite())
            .map(|s| **s);
        if skies.len() > 1 {
            tracing::warn!("more than one sky: using the first valid one");
        }
        let mut environments = environments.into_iter();
        let environment = environments.next().map(|e| Arc::new(e.clone()));
        if environments.next().is_some() {
            tracing::warn!("more than one environment light: using the first");
        }
        LightSet {
            directional,
            sky,
            environment,
        }
    }

    /// A hash of every light: directions and colours, the sky, and an environment
    /// map's texels and virtual lights (a cluster's ranks compare it before they render).
    pub fn content_hash(&self) -> u64 {
        let mut hash = crate::util::fingerprint::Fingerprint::new("light set v1");
        hash.text(&format!("{:?} {:?}", self.directional, self.sky));
        if let Some(environment) = &self.environment {
            environment.map.hash_into(&mut hash);
            hash.text(&format!("{:?}", environment.lights));
        }
        hash.finish()
    }

    /// Radiance of the environment seen along `d`.
    #[inline]
    pub fn environment(&self, d: Vec3A) -> Vec3A {
        match &self.environment {
            Some(e) => e.map.radiance(d),
            None => self.sky.map_or(Vec3A::ZERO, |s| s.radiance(d)),
        }
    }
}
