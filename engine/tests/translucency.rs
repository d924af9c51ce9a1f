//! Leaf translucency against its analytic answers: light from behind a thin translucent
//! surface reaches its front as transmittance/π · E · cos θ, blocked by what lies
//! behind, and under a uniform sky reflected plus transmitted light is (r + t) × the
//! sky's radiance.

mod common;

use common::{assert_within_four_sigma, ground_plane, mean_and_error};
use glam::{Affine3A, Vec3, Vec3A};
use sylva_engine::bvh::{BuildParams, TraversalStats};
use sylva_engine::light::{DirectionalLight, LightSet, SkyLight};
use sylva_engine::math::Ray;
use sylva_engine::opacity::OpacityMaps;
use sylva_engine::render::{RenderScene, SampleShading};
use sylva_engine::sampling::SampleKey;
use sylva_engine::shading::{Shader, ShaderId, ShaderTable, Transmission};
use sylva_engine::tlas::{InstanceDesc, TopLevel};

const BASE: Vec3 = Vec3::new(0.6, 0.5, 0.4);
const FACTOR: f32 = 0.4;
const TINT: Vec3 = Vec3::new(0.9, 0.8, 0.3);

fn leaf(base: Vec3, transmission: Option<Transmission>) -> ShaderTable {
    ShaderTable::new(vec![Shader {
        transmission,
        ..Shader::color(ShaderId(0), base)
    }])
}

/// Radiance seen straight down onto the plane y = 0 (its front) at the origin.
fn seen_from_above(scene: &RenderScene, light_samples: u32, key: &SampleKey) -> Vec3 {
    let ray = Ray::new(Vec3A::new(0.0, 10.0, 0.0), Vec3A::NEG_Y);
    Vec3::from(scene.radiance(
        &ray,
        key,
        &SampleShading::plain(light_samples),
        &mut TraversalStats::default(),
    ))
}

fn close(a: Vec3, b: Vec3, relative: f32) -> bool {
    (a - b).abs().max_element() <= relative * b.abs().max_element().max(1e-6)
}

#[test]
fn a_leaf_lit_from_behind_shows_transmittance_over_pi_times_irradiance_times_cosine() {
    let (library, top_level) = ground_plane();
    // A second plane 1 m below, to block the sun from behind when it is there.
    let blocked_top = TopLevel::build(
        &library,
        &[
            InstanceDesc {
                transform: Affine3A::IDENTITY,
                geometry: sylva_engine::geometry::GeometryId(0),
            },
            InstanceDesc {
                transform: Affine3A::from_translation(Vec3::new(0.0, -1.0, 0.0)),
                geometry: sylva_engine::geometry::GeometryId(0),
            },
        ],
        BuildParams::BALANCED,
    );
    let irradiance = Vec3::new(3.0, 2.0, 1.0);
    let theta = 30f32.to_radians();
    let sun = |below: bool| LightSet {
        directional: vec![DirectionalLight {
            direction: Vec3::new(
                theta.sin(),
                if below { -theta.cos() } else { theta.cos() },
                0.0,
            ),
            irradiance,
        }],
        ..Default::default()
    };
    let translucent = leaf(BASE, Some(Transmission::new(FACTOR, TINT)));
    let opaque = leaf(BASE, None);
    let key = SampleKey::new(0, 0, 0, 0, 0);
    let render = |shaders: &ShaderTable, top: &TopLevel, below: bool| {
        let lights = sun(below);
        seen_from_above(
            &RenderScene {
                geometry: &library,
                top_level: top,
                shaders,
                lights: &lights,
                opacity: &OpacityMaps::default(),
            },
            1,
            &key,
        )
    };
    let from_behind = render(&translucent, &top_level, true);
    let expected = FACTOR * TINT * irradiance * theta.cos() / std::f32::consts::PI;
    assert!(
        close(from_behind, expected, 1e-5),
        "{from_behind} against {expected}"
    );
    // From the front the same leaf reflects only what it does not transmit.
    let from_front = render(&translucent, &top_level, false);
    let expected = (1.0 - FACTOR) * BASE * irradiance * theta.cos() / std::f32::consts::PI;
    assert!(
        close(from_front, expected, 1e-5),
        "{from_front} against {expected}"
    );
    // An opaque leaf is dark from behind; a plane behind the translucent one shades it.
    assert_eq!(render(&opaque, &top_level, true), Vec3::ZERO);
    assert_eq!(render(&translucent, &blocked_top, true), Vec3::ZERO);
    // The plane behind does not shade the front.
    let front_blocked = render(&translucent, &blocked_top, false);
    assert!(close(front_blocked, from_front, 1e-6));
}

#[test]
fn under_a_uniform_sky_reflected_plus_transmitted_light_is_r_plus_t_times_the_sky() {
    let (library, top_level) = ground_plane();
    let sky = Vec3::new(1.0, 0.8, 0.6);
    let lights = LightSet {
        sky: Some(SkyLight::constant(sky)),
        ..Default::default()
    };
    // r + t = 1: the plane is as bright as the sky around it (a white furnace for a
    // thin sheet); r + t < 1 with colours: (r + t) × sky; opaque: r × sky.
    let cases = [
        (Vec3::ONE, Some(Transmission::new(0.35, Vec3::ONE)), sky),
        (
            BASE,
            Some(Transmission::new(FACTOR, TINT)),
            ((1.0 - FACTOR) * BASE + FACTOR * TINT) * sky,
        ),
        (BASE, None, BASE * sky),
    ];
    for (base, transmission, expected) in cases {
        let shaders = leaf(base, transmission.clone());
        let scene = RenderScene {
            geometry: &library,
            top_level: &top_level,
            shaders: &shaders,
            lights: &lights,
            opacity: &OpacityMaps::default(),
        };
        let estimate = mean_and_error(4000, |k| {
            seen_from_above(&scene, 4, &SampleKey::new(3, 0, 0, k, 0))
        });
        assert_within_four_sigma(estimate, expected, 2e-4, &format!("{transmission:?}"));
    }
}

#[test]
fn transmission_is_clamped_so_reflectance_plus_transmittance_stays_at_most_one() {
    let (clamped, changed) = Transmission::new(1.5, Vec3::new(2.0, 0.5, f32::NAN)).clamped();
    assert!(changed);
    assert_eq!(clamped.factor, 1.0);
    assert_eq!(clamped.color, Vec3::new(1.0, 0.5, 0.0));
    let fine = Transmission::new(0.3, Vec3::splat(0.5));
    assert_eq!(fine.clone().clamped(), (fine, false));
    // Reflectance + transmittance ≤ 1 for any base colour and tint in 0 ..= 1.
    let shader = Shader {
        transmission: Some(Transmission::new(0.7, Vec3::ONE)),
        ..Shader::color(ShaderId(0), Vec3::ONE)
    };
    let uv = glam::Vec2::ZERO;
    assert!((shader.reflectance(uv) + shader.transmittance(uv)).max_element() <= 1.0 + 1e-6);
}
