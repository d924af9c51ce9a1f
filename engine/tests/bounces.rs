//! Indirect light against closed-form answers: inside a closed box whose walls emit E
//! and reflect ρ, the radiance after N bounces is E (1 + ρ + … + ρᴺ); walls that also
//! transmit send that share out of the box, where it is lost.

mod common;

use common::{assert_within_four_sigma, ground_plane, mean_and_error};
use glam::{Affine3A, Vec3, Vec3A};
use sylva_engine::bvh::{BuildParams, TraversalStats};
use sylva_engine::geometry::{Geometry, GeometryLibrary};
use sylva_engine::light::LightSet;
use sylva_engine::math::Ray;
use sylva_engine::mesh::TriangleMesh;
use sylva_engine::opacity::OpacityMaps;
use sylva_engine::render::{RenderScene, SampleShading};
use sylva_engine::sampling::SampleKey;
use sylva_engine::shading::{Emission, Shader, ShaderId, ShaderTable, Transmission};
use sylva_engine::tlas::{InstanceDesc, TopLevel};

const EMITTED: Vec3 = Vec3::new(1.0, 0.5, 0.25);

/// A closed 2 m cube around the origin, shader 0 on every face.
fn closed_box() -> (GeometryLibrary, TopLevel) {
    let corner = |i: u32| {
        Vec3::new(
            if i & 1 == 0 { -1.0 } else { 1.0 },
            if i & 2 == 0 { -1.0 } else { 1.0 },
            if i & 4 == 0 { -1.0 } else { 1.0 },
        )
    };
    let faces: [[u32; 4]; 6] = [
        [0, 1, 3, 2],
        [4, 6, 7, 5],
        [0, 4, 5, 1],
        [2, 3, 7, 6],
        [0, 2, 6, 4],
        [1, 5, 7, 3],
    ];
    let indices = faces
        .iter()
        .flat_map(|[a, b, c, d]| [[*a, *b, *c], [*a, *c, *d]])
        .collect::<Vec<_>>();
    let mesh = TriangleMesh {
        positions: (0..8).map(corner).collect(),
        shaders: vec![0; indices.len()],
        indices,
        ..Default::default()
    };
    let mut library = GeometryLibrary::default();
    let id = library.add(Geometry::new("box", mesh, BuildParams::BALANCED).unwrap());
    let top = TopLevel::build(
        &library,
        &[InstanceDesc {
            transform: Affine3A::IDENTITY,
            geometry: id,
        }],
        BuildParams::BALANCED,
    );
    (library, top)
}

/// Mean radiance and its standard error seen from inside the box over `n` keys.
fn seen_inside(shader: Shader, bounces: u32, n: u32) -> (Vec3, Vec3) {
    let (library, top_level) = closed_box();
    let shaders = ShaderTable::new(vec![shader]);
    let lights = LightSet::default();
    let scene = RenderScene {
        geometry: &library,
        top_level: &top_level,
        shaders: &shaders,
        lights: &lights,
        opacity: &OpacityMaps::default(),
    };
    let shading = SampleShading {
        bounces,
        ..SampleShading::plain(1)
    };
    let direction = Vec3A::new(0.3, -0.5, 0.8).normalize();
    let ray = Ray::new(Vec3A::new(0.1, 0.2, -0.3), direction);
    mean_and_error(n, |k| {
        let key = SampleKey::new(9, 0, 0, k, 0);
        Vec3::from(scene.radiance(&ray, &key, &shading, &mut TraversalStats::default()))
    })
}

fn glowing(reflectance: f32, transmission: Option<Transmission>) -> Shader {
    Shader {
        emission: Some(Emission {
            radiance: EMITTED,
            texture: None,
            uv_transform: None,
        }),
        transmission,
        ..Shader::color(ShaderId(0), Vec3::splat(reflectance))
    }
}

fn series(rho: f32, bounces: u32) -> f32 {
    (0..=bounces).map(|k| rho.powi(k as i32)).sum()
}

#[test]
fn a_closed_glowing_box_gives_the_geometric_series_of_its_reflectance() {
    // No bounce: the wall's own emission; one bounce: every continuation ray meets a
    // wall, so the answer is exact without noise.
    let (zero, _) = seen_inside(glowing(0.5, None), 0, 4);
    assert_eq!(zero, EMITTED);
    let (one, error) = seen_inside(glowing(0.5, None), 1, 64);
    assert!((one - EMITTED * 1.5).abs().max_element() < 1e-5, "{one}");
    assert!(error.max_element() < 1e-5);
    // Four bounces with Russian roulette from the second on: unbiased, within 4 σ.
    let four = seen_inside(glowing(0.5, None), 4, 20_000);
    assert_within_four_sigma(four, EMITTED * series(0.5, 4), 1e-3, "four bounces");
}

#[test]
fn light_transmitted_out_of_a_closed_box_is_lost_and_what_is_reflected_stays() {
    // Walls reflecting 0.3 and transmitting 0.5 (factor 0.5 of tint 1, base 0.6): one
    // bounce sees E (1 + 0.3) on average, whichever side each sample picks.
    let shader = glowing(0.6, Some(Transmission::new(0.5, Vec3::ONE)));
    let estimate = seen_inside(shader, 1, 20_000);
    assert_within_four_sigma(estimate, EMITTED * series(0.3, 1), 1e-3, "one bounce");
}

#[test]
fn an_open_sheet_under_a_uniform_sky_gains_nothing_from_bounces() {
    // The white furnace, open: a sheet with r + t = 1 under a constant sky is as bright
    // as the sky with any number of bounces (escaping bounce rays add nothing: direct
    // light already counts the sky, so nothing is counted twice).
    let (library, top_level) = ground_plane();
    let sky = Vec3::new(1.0, 0.8, 0.6);
    let lights = LightSet {
        sky: Some(sylva_engine::light::SkyLight::constant(sky)),
        ..Default::default()
    };
    let shaders = ShaderTable::new(vec![Shader {
        transmission: Some(Transmission::new(0.35, Vec3::ONE)),
        ..Shader::color(ShaderId(0), Vec3::ONE)
    }]);
    let scene = RenderScene {
        geometry: &library,
        top_level: &top_level,
        shaders: &shaders,
        lights: &lights,
        opacity: &OpacityMaps::default(),
    };
    let shading = SampleShading {
        bounces: 3,
        ..SampleShading::plain(4)
    };
    let ray = Ray::new(Vec3A::new(0.0, 10.0, 0.0), Vec3A::NEG_Y);
    let estimate = mean_and_error(4000, |k| {
        let key = SampleKey::new(4, 0, 0, k, 0);
        Vec3::from(scene.radiance(&ray, &key, &shading, &mut TraversalStats::default()))
    });
    assert_within_four_sigma(estimate, sky, 2e-4, "three bounces");
}

/// A `size`-wide square at height `y` facing up, shader `shader`.
fn square(y: f32, size: f32, shader: u32) -> TriangleMesh {
    let h = size / 2.0;
    TriangleMesh {
        positions: vec![
            Vec3::new(-h, y, -h),
            Vec3::new(h, y, -h),
            Vec3::new(h, y, h),
            Vec3::new(-h, y, h),
        ],
        indices: vec![[0, 2, 1], [0, 3, 2]],
        shaders: vec![shader, shader],
        ..Default::default()
    }
}

#[test]
fn ground_under_a_translucent_canopy_gets_the_sky_through_it_bounce_by_bounce() {
    // A ground (reflectance g) 1 m under a translucent canopy (reflectance c, transmits
    // t) in a sky of radiance L above the horizon and none below. The ground's shadow
    // rays end on the canopy, so all its light comes by bounces: the canopy's underside
    // sends down t·L plus c × the ground's radiance. A round trip ground → canopy →
    // ground takes two bounces, so after N the ground shows g·t·L · (1 + g·c + … +
    // (g·c)^(⌈N/2⌉−1)), tending to g·t·L / (1 − g·c).
    let (g, base, factor) = (0.5f32, 0.6f32, 0.5f32);
    let (c, t) = (base * (1.0 - factor), factor);
    let sky = Vec3::new(1.0, 0.9, 0.7);
    let mut library = GeometryLibrary::default();
    let ground = library
        .add(Geometry::new("ground", square(0.0, 4000.0, 0), BuildParams::BALANCED).unwrap());
    let canopy = library
        .add(Geometry::new("canopy", square(1.0, 4000.0, 1), BuildParams::BALANCED).unwrap());
    let top_level = TopLevel::build(
        &library,
        &[ground, canopy].map(|geometry| InstanceDesc {
            transform: Affine3A::IDENTITY,
            geometry,
        }),
        BuildParams::BALANCED,
    );
    let shaders = ShaderTable::new(vec![
        Shader::color(ShaderId(0), Vec3::splat(g)),
        Shader {
            transmission: Some(Transmission::new(factor, Vec3::ONE)),
            ..Shader::color(ShaderId(1), Vec3::splat(base))
        },
    ]);
    let lights = LightSet {
        sky: Some(sylva_engine::light::SkyLight {
            zenith: sky,
            horizon: sky,
            ground: Vec3::ZERO,
        }),
        ..Default::default()
    };
    let scene = RenderScene {
        geometry: &library,
        top_level: &top_level,
        shaders: &shaders,
        lights: &lights,
        opacity: &OpacityMaps::default(),
    };
    for bounces in [0, 1, 2, 3, 5] {
        let shading = SampleShading {
            bounces,
            ..SampleShading::plain(2)
        };
        let ray = Ray::new(Vec3A::new(0.0, 0.5, 0.0), Vec3A::new(0.2, -1.0, 0.1));
        let estimate = mean_and_error(20_000, |k| {
            let key = SampleKey::new(6, 0, 0, k, 0);
            Vec3::from(scene.radiance(&ray, &key, &shading, &mut TraversalStats::default()))
        });
        let expected = if bounces == 0 {
            Vec3::ZERO
        } else {
            g * t * sky * series(g * c, bounces.div_ceil(2) - 1)
        };
        assert_within_four_sigma(estimate, expected, 1e-3, &format!("{bounces} bounces"));
    }
}
