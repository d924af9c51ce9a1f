//! The environment-light estimator is unbiased with respect to its virtual lights, and
//! a sun a million times brighter than the sky gives bounded per-sample values.

mod common;

use common::{TestRng, ground_plane};
use glam::{Vec3, Vec3A};
use std::sync::Arc;
use sylva_engine::bvh::TraversalStats;
use sylva_engine::environment::{EnvironmentLight, EnvironmentMap, luminance};
use sylva_engine::geometry::GeometryLibrary;
use sylva_engine::light::LightSet;
use sylva_engine::math::Ray;
use sylva_engine::render::RenderScene;
use sylva_engine::sampling::SampleKey;
use sylva_engine::shading::{Shader, ShaderId, ShaderTable};
use sylva_engine::tlas::TopLevel;

const ALBEDO: Vec3 = Vec3::new(0.7, 0.5, 0.3);

/// A 32×16 map of random sky radiance with one texel `sun` times brighter.
fn test_map(sun: f32) -> EnvironmentMap {
    let mut rng = TestRng::new(12);
    let texels = (0..32 * 16)
        .map(|i| {
            let base = Vec3::new(
                rng.range(0.1, 1.0),
                rng.range(0.1, 1.0),
                rng.range(0.1, 1.0),
            );
            if i == 3 * 32 + 9 { base * sun } else { base }
        })
        .collect();
    EnvironmentMap::new(32, 16, texels).unwrap().0
}

/// Mean and standard error per channel of `radiance` over `n` independent keys.
fn estimate(scene: &RenderScene, ray: &Ray, light_samples: u32, n: u32) -> (Vec3, Vec3, f32) {
    let (mut sum, mut sum_sq, mut max_luminance) = (Vec3::ZERO, Vec3::ZERO, 0f32);
    let mut stats = TraversalStats::default();
    for k in 0..n {
        let key = SampleKey::new(5, 0, 0, k, 0);
        let v = Vec3::from(scene.radiance(ray, &key, light_samples, &mut stats));
        assert!(v.is_finite());
        sum += v;
        sum_sq += v * v;
        max_luminance = max_luminance.max(luminance(v));
    }
    let mean = sum / n as f32;
    let variance = (sum_sq / n as f32 - mean * mean).max(Vec3::ZERO);
    (mean, (variance / n as f32).sqrt(), max_luminance)
}

struct Plane {
    library: GeometryLibrary,
    top_level: TopLevel,
    shaders: ShaderTable,
}

impl Plane {
    fn new() -> Self {
        let (library, top_level) = ground_plane();
        Self {
            library,
            top_level,
            shaders: ShaderTable::new(vec![Shader::color(ShaderId(0), ALBEDO)]),
        }
    }

    /// Runs `f` on the plane lit by `environment` alone.
    fn lit_by<R>(
        &self,
        environment: Arc<EnvironmentLight>,
        f: impl FnOnce(&RenderScene) -> R,
    ) -> R {
        let lights = LightSet {
            environment: Some(environment),
            ..Default::default()
        };
        f(&RenderScene {
            geometry: &self.library,
            top_level: &self.top_level,
            shaders: &self.shaders,
            lights: &lights,
        })
    }
}

#[test]
fn a_lambertian_plane_converges_to_the_sum_over_the_virtual_lights() {
    let plane = Plane::new();
    let environment = Arc::new(EnvironmentLight::new(test_map(30.0), 64));
    // The analytic answer for the discrete set: Σ albedo/π · E_i · max(cos, 0).
    let expected: Vec3 = environment
        .lights
        .lights()
        .iter()
        .map(|l| ALBEDO * l.irradiance * l.direction.y.max(0.0) / std::f32::consts::PI)
        .sum();
    let lights = LightSet {
        environment: Some(environment),
        ..Default::default()
    };
    let scene = RenderScene {
        geometry: &plane.library,
        top_level: &plane.top_level,
        shaders: &plane.shaders,
        lights: &lights,
    };
    let ray = Ray::new(
        Vec3A::new(0.3, 2.0, 0.1),
        Vec3A::new(0.1, -1.0, 0.2).normalize(),
    );
    for light_samples in [1, 4] {
        let (mean, standard_error, _) = estimate(&scene, &ray, light_samples, 40_000);
        for c in 0..3 {
            assert!(
                (mean[c] - expected[c]).abs() < 3.0 * standard_error[c],
                "{light_samples} samples: {mean} vs {expected} (standard error {standard_error})"
            );
        }
        assert!(standard_error.max_element() < 0.05 * expected.min_element());
    }
}

#[test]
fn a_sun_a_million_times_brighter_gives_bounded_samples() {
    let plane = Plane::new();
    let environment = Arc::new(EnvironmentLight::new(test_map(1e6), 256));
    let total_luminance: f32 = environment
        .lights
        .lights()
        .iter()
        .map(|l| luminance(l.irradiance))
        .sum();
    let ray = Ray::new(Vec3A::new(0.0, 2.0, 0.0), -Vec3A::Y);
    let (mean, _, max_luminance) =
        plane.lit_by(environment, |scene| estimate(scene, &ray, 1, 5_000));
    // Luminance-proportional picking makes every sample's luminance at most
    // albedo_max/π · Σ luminance(E_i): no fireflies, whatever the sun's strength.
    let bound = ALBEDO.max_element() / std::f32::consts::PI * total_luminance;
    assert!(max_luminance <= bound * 1.001, "{max_luminance} > {bound}");
    assert!(luminance(mean) > 0.0 && mean.is_finite());
}
