//! The environment-light estimator is unbiased with respect to its virtual lights, and
//! a sun a million times brighter than the sky gives bounded per-sample values.

mod common;

use common::{TestRng, ground_plane};
use glam::{Vec3, Vec3A};
use std::sync::Arc;
use sylva_engine::bvh::TraversalStats;
use sylva_engine::environment::{EnvironmentLight, EnvironmentMap, luminance};
use sylva_engine::geometry::GeometryLibrary;
use sylva_engine::interleave::LightSubsets;
use sylva_engine::light::LightSet;
use sylva_engine::math::Ray;
use sylva_engine::opacity::OpacityMaps;
use sylva_engine::render::{RenderScene, SampleShading};
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
    estimate_with(scene, ray, n, 5, |_| SampleShading::plain(light_samples))
}

/// Mean and standard error per channel of `radiance` over frames `0..n` of pixel (0, 0)
/// with seed `seed`, frame `k` shaded by `shading(k)`.
fn estimate_with(
    scene: &RenderScene,
    ray: &Ray,
    n: u32,
    seed: u64,
    shading: impl Fn(u32) -> SampleShading,
) -> (Vec3, Vec3, f32) {
    let (mut sum, mut sum_sq, mut max_luminance) = (Vec3::ZERO, Vec3::ZERO, 0f32);
    let mut stats = TraversalStats::default();
    for k in 0..n {
        let key = SampleKey::new(seed, 0, 0, k, 0);
        let v = Vec3::from(scene.radiance(ray, &key, &shading(k), &mut stats));
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
            opacity: &OpacityMaps::default(),
        })
    }
}

/// The analytic answer for the discrete set on the upward plane:
/// Σ albedo/π · E_i · max(cos, 0).
fn discrete_sum(environment: &EnvironmentLight) -> Vec3 {
    environment
        .lights
        .lights()
        .iter()
        .map(|l| ALBEDO * l.irradiance * l.direction.y.max(0.0) / std::f32::consts::PI)
        .sum()
}

#[test]
fn a_lambertian_plane_converges_to_the_sum_over_the_virtual_lights() {
    let plane = Plane::new();
    let environment = Arc::new(EnvironmentLight::new(test_map(30.0), 64));
    let expected = discrete_sum(&environment);
    let ray = Ray::new(
        Vec3A::new(0.3, 2.0, 0.1),
        Vec3A::new(0.1, -1.0, 0.2).normalize(),
    );
    plane.lit_by(environment, |scene| {
        for light_samples in [1, 4] {
            let (mean, standard_error, _) = estimate(scene, &ray, light_samples, 40_000);
            for c in 0..3 {
                assert!(
                    (mean[c] - expected[c]).abs() < 3.0 * standard_error[c],
                    "{light_samples} samples: {mean} vs {expected} (standard error {standard_error})"
                );
            }
            assert!(standard_error.max_element() < 0.05 * expected.min_element());
        }
    });
}

/// Per run `r` (seed `seed + r`, subset rotation `r mod 16`), the luminance of the mean
/// of `frames` one-sample estimates along `ray`: with interleaved subsets, and with
/// independent picks.
fn interleaved_and_independent(
    scene: &RenderScene,
    ray: &Ray,
    runs: u32,
    frames: u32,
    light_samples: u32,
    seed: u64,
) -> [Vec<f32>; 2] {
    let mut values = [Vec::new(), Vec::new()];
    for run in 0..runs {
        let subsets = LightSubsets {
            pattern: 4,
            count: 16,
            offset: run % 16,
        };
        let seed = u64::from(run) + seed;
        let interleaved = estimate_with(scene, ray, frames, seed, |k| SampleShading {
            light_subset: Some((subsets, subsets.subset(0, 0, k, 0, 1))),
            ..SampleShading::plain(light_samples)
        });
        let independent = estimate_with(scene, ray, frames, seed, |_| {
            SampleShading::plain(light_samples)
        });
        values[0].push(luminance(interleaved.0));
        values[1].push(luminance(independent.0));
    }
    values
}

/// Mean and sample variance.
fn mean_and_variance(values: &[f32]) -> (f32, f32) {
    let mean = values.iter().sum::<f32>() / values.len() as f32;
    let variance =
        values.iter().map(|x| (x - mean).powi(2)).sum::<f32>() / (values.len() - 1) as f32;
    (mean, variance)
}

/// Interleaved light subsets: over the render's random rotation the estimator keeps the
/// discrete sum as its mean, and stratifying light selection across frames lowers the
/// variance of a pixel's progressive mean against independent selection.
#[test]
fn interleaved_subsets_are_unbiased_and_beat_independent_selection() {
    let plane = Plane::new();
    let environment = Arc::new(EnvironmentLight::new(test_map(30.0), 64));
    let expected = discrete_sum(&environment);
    let ray = Ray::new(Vec3A::new(0.3, 2.0, 0.1), -Vec3A::Y);
    let (runs, frames) = (300u32, 32u32);
    plane.lit_by(environment, |scene| {
        for light_samples in [1, 2] {
            let means = interleaved_and_independent(scene, &ray, runs, frames, light_samples, 100);
            let truth = luminance(expected);
            let [(m_int, v_int), (m_ind, v_ind)] = means.map(|m| mean_and_variance(&m));
            for (mean, var) in [(m_int, v_int), (m_ind, v_ind)] {
                let standard_error = (var / runs as f32).sqrt();
                assert!(
                    (mean - truth).abs() < 3.0 * standard_error,
                    "{light_samples} samples: {mean} vs {truth} (standard error {standard_error})"
                );
            }
            assert!(
                v_int < 0.5 * v_ind,
                "{light_samples} samples: interleaved variance {v_int} vs independent {v_ind}"
            );
        }
    });
}

/// One camera sample with several light samples: under interleaving the sample's lights
/// must still span the whole luminance CDF (one per stratum, as independent picks
/// draw them), so a 1-spp image is no noisier than with independent picks. Packing all
/// of a sample's lights into its subset's narrow slice of the CDF made the single-sample
/// variance several times larger.
#[test]
fn one_interleaved_sample_is_no_noisier_than_independent_picks() {
    let plane = Plane::new();
    let environment = Arc::new(EnvironmentLight::new(test_map(30.0), 64));
    let ray = Ray::new(Vec3A::new(0.3, 2.0, 0.1), -Vec3A::Y);
    let runs = 4000u32;
    plane.lit_by(environment, |scene| {
        for light_samples in [2, 4] {
            let values = interleaved_and_independent(scene, &ray, runs, 1, light_samples, 7_000);
            let [(_, v_int), (_, v_ind)] = values.map(|v| mean_and_variance(&v));
            assert!(
                v_int < 1.15 * v_ind,
                "{light_samples} light samples: one interleaved sample's variance {v_int} \
                 against independent picks' {v_ind}"
            );
        }
    });
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

#[test]
fn a_sun_up_to_a_million_times_brighter_makes_no_fireflies_on_an_open_plane() {
    use sylva_engine::film::{Film, FrameBuffer};
    let plane = Plane::new();
    let ray = Ray::new(Vec3A::new(0.0, 2.0, 0.0), -Vec3A::Y);
    let frames = 256;
    // A dim sun leaves the sky most of the light, a bright one takes nearly all: either
    // way luminance-proportional picking keeps every sample within a cosine factor of
    // the mean. A picker blind to the sun's share (uniform over the 256 lights) would
    // give about one sample in 256 a value 256 × the sun's share: a firefly.
    for sun in [1.0, 1e2, 1e6] {
        let environment = Arc::new(EnvironmentLight::new(test_map(sun), 256));
        let film = plane.lit_by(environment, |scene| {
            let mut film = Film::new(1, 1);
            let mut stats = TraversalStats::default();
            for k in 0..frames {
                let key = SampleKey::new(3, 0, 0, k, 0);
                let shading = SampleShading::plain(1);
                let value = Vec3::from(scene.radiance(&ray, &key, &shading, &mut stats));
                let mut frame = FrameBuffer::new(1, 1, k);
                frame.pixels.sums[0] = value;
                frame.pixels.counts[0] = 1;
                film.accumulate(&frame);
            }
            film
        });
        assert_eq!(film.frames(), frames);
        assert_eq!(film.rejected_samples(), 0);
        assert!(film.pixel(0, 0).iter().all(|c| c.is_finite() && *c > 0.0));
        assert_eq!(film.fireflies(), 0, "sun {sun}");
    }
}
