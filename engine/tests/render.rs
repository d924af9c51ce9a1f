//! The render kernel is a pure function: tile order and thread count never change a bit.

mod common;

use common::*;
use glam::{Affine3A, Quat, Vec2, Vec3};
use std::sync::Arc;
use sylva_engine::bvh::BuildParams;
use sylva_engine::camera::{Camera, CameraView};
use sylva_engine::film::{Film, FrameBuffer, Tile};
use sylva_engine::geometry::{Geometry, GeometryLibrary};
use sylva_engine::light::{DirectionalLight, LightSet, SkyLight};
use sylva_engine::mesh::TriangleMesh;
use sylva_engine::opacity::OpacityMaps;
use sylva_engine::render::{RenderData, RenderParams, RenderScene, render_frame, render_tile};
use sylva_engine::shading::{Shader, ShaderId, ShaderTable, Texture};
use sylva_engine::tlas::{InstanceDesc, TopLevel};

/// The fixture is the kernel's owned render data.
type Fixture = RenderData;

/// A square of side 2·`half` at y = 0 facing +Y, its texture repeated 8 times (shader 0).
fn textured_square(half: f32) -> TriangleMesh {
    TriangleMesh {
        positions: vec![
            Vec3::new(-half, 0.0, -half),
            Vec3::new(half, 0.0, -half),
            Vec3::new(half, 0.0, half),
            Vec3::new(-half, 0.0, half),
        ],
        normals: vec![],
        uvs: vec![
            Vec2::ZERO,
            Vec2::new(8.0, 0.0),
            Vec2::new(8.0, 8.0),
            Vec2::new(0.0, 8.0),
        ],
        indices: vec![[0, 2, 1], [0, 3, 2]],
        shaders: vec![0, 0],
    }
}

/// Shader 0: a white material under an 8×8 grey and green checker texture.
fn checker_shader() -> Shader {
    let checker: Vec<[u8; 4]> = (0..64)
        .map(|i| {
            if (i % 8 + i / 8) % 2 == 0 {
                [200, 200, 200, 255]
            } else {
                [40, 90, 40, 255]
            }
        })
        .collect();
    Shader::textured(
        ShaderId(0),
        Vec3::ONE,
        Arc::new(Texture::from_srgba8(8, 8, checker).unwrap()),
    )
}

fn fixture() -> Fixture {
    let mut rng = TestRng::new(4);
    let mut library = GeometryLibrary::default();
    let ground =
        library.add(Geometry::new("ground", textured_square(30.0), BuildParams::BALANCED).unwrap());
    let mut soup = random_mesh(&mut rng, 300, 1.0, 0.4);
    soup.shaders = (0..300).map(|i| 1 + i % 2).collect();
    let soup = library.add(Geometry::new("soup", soup, BuildParams::BALANCED).unwrap());
    let mut descs = vec![InstanceDesc {
        transform: Affine3A::IDENTITY,
        geometry: ground,
    }];
    for _ in 0..40 {
        let t = Affine3A::from_scale_rotation_translation(
            Vec3::splat(rng.range(0.5, 1.5)),
            Quat::from_rotation_y(rng.range(0.0, 6.0)),
            Vec3::new(rng.range(-8.0, 8.0), 1.0, rng.range(-12.0, 2.0)),
        );
        descs.push(InstanceDesc {
            transform: t,
            geometry: soup,
        });
    }
    let top_level = TopLevel::build(&library, &descs, BuildParams::BALANCED);
    let shaders = ShaderTable::new(vec![
        checker_shader(),
        Shader::color(ShaderId(1), Vec3::new(0.2, 0.5, 0.1)),
        Shader::color(ShaderId(2), Vec3::new(0.5, 0.3, 0.1)),
    ]);
    let lights = LightSet {
        directional: vec![DirectionalLight {
            direction: Vec3::new(0.4, 0.8, 0.3).normalize(),
            irradiance: Vec3::splat(3.0),
        }],
        sky: Some(SkyLight {
            zenith: Vec3::new(0.2, 0.4, 0.9),
            horizon: Vec3::splat(0.8),
            ground: Vec3::splat(0.1),
        }),
        environment: None,
    };
    let opacity = OpacityMaps::build(&library, &shaders);
    Fixture {
        library,
        top_level,
        shaders,
        lights,
        opacity,
    }
}

/// The view of `camera` from `eye`, looking at the origin.
fn view_from(camera: &Camera, eye: Vec3) -> CameraView {
    let transform = sylva_engine::components::Transform::looking_at(eye, Vec3::ZERO, Vec3::Y);
    CameraView::new(camera, &transform.to_affine())
}

#[test]
fn tile_order_and_thread_count_do_not_change_a_bit() {
    let f = fixture();
    let scene = f.scene();
    let camera = Camera {
        width: 57,
        height: 41,
        samples_per_pixel: 2,
        light_samples: 2,
        ..Default::default()
    };
    let view = view_from(&camera, Vec3::new(0.0, 3.0, 8.0));
    let params = RenderParams {
        tile_size: 8,
        ..RenderParams::for_camera(&camera, 99)
    };
    let frames: Vec<FrameBuffer> = [1, 2, 3]
        .iter()
        .map(|&n| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
                .install(|| render_frame(&scene, &view, &params, 5, &|_| {}))
        })
        .collect();
    // Reverse tile order, one tile at a time.
    let mut reversed = FrameBuffer::new(57, 41, 5);
    for tile in Tile::grid(57, 41, 8).into_iter().rev() {
        reversed.write_tile(&render_tile(&scene, &view, &params, tile, 5));
    }
    assert_eq!(frames[0], frames[1]);
    assert_eq!(frames[0], frames[2]);
    assert_eq!(frames[0], reversed);
    // The image has content, and another frame index draws other samples.
    let mean = frames[0].mean();
    assert!(mean.iter().any(|p| *p != mean[0]));
    assert!(frames[0].pixels.counts.iter().all(|&c| c == 2) && frames[0].rejected == 0);
    let other = render_frame(&scene, &view, &params, 6, &|_| {});
    assert_ne!(other.pixels.sums, frames[0].pixels.sums);
}

/// One frame of a scene lit by `sun` alone (no sky: no noise), seen from `eye` towards
/// the origin by a square camera of (`size` pixels, vertical field of view), seed `seed`.
fn render_in_sunlight(
    library: &GeometryLibrary,
    top_level: &TopLevel,
    shaders: &ShaderTable,
    sun: DirectionalLight,
    (size, vertical_fov): (u32, f32),
    eye: Vec3,
    seed: u64,
) -> FrameBuffer {
    let lights = LightSet {
        directional: vec![sun],
        sky: None,
        environment: None,
    };
    let scene = RenderScene {
        geometry: library,
        top_level,
        shaders,
        lights: &lights,
        opacity: &OpacityMaps::build(library, shaders),
    };
    let camera = Camera {
        width: size,
        height: size,
        vertical_fov,
        ..Default::default()
    };
    let view = view_from(&camera, eye);
    render_frame(
        &scene,
        &view,
        &RenderParams::for_camera(&camera, seed),
        0,
        &|_| {},
    )
}

#[test]
fn lambertian_plane_under_sun_matches_the_analytic_radiance() {
    // A white-ish plane lit by a sun only: L = albedo/π · E · cos θ exactly (no noise).
    let (library, top_level) = ground_plane();
    let shaders = ShaderTable::new(vec![Shader::color(ShaderId(0), Vec3::new(0.8, 0.5, 0.2))]);
    let sun = Vec3::new(0.3, 0.7, -0.2).normalize();
    let sun_light = DirectionalLight {
        direction: sun,
        irradiance: Vec3::new(2.0, 3.0, 4.0),
    };
    let frame = render_in_sunlight(
        &library,
        &top_level,
        &shaders,
        sun_light,
        (16, 0.5),
        Vec3::new(0.0, 5.0, 5.0),
        1,
    );
    let expected =
        Vec3::new(0.8, 0.5, 0.2) * Vec3::new(2.0, 3.0, 4.0) * sun.y / std::f32::consts::PI;
    for p in frame.mean() {
        assert!(
            (p - expected).abs().max_element() < 1e-5,
            "{p} vs {expected}"
        );
    }
}

/// The NaN firewall: samples made NaN by a shader with a NaN colour are counted and
/// dropped in the tile, so neither the frame nor the film ever holds a NaN.
#[test]
fn injected_nan_samples_are_counted_and_never_reach_the_film() {
    let mut f = fixture();
    f.shaders = ShaderTable::new(vec![
        f.shaders.get(0).clone(),
        f.shaders.get(1).clone(),
        Shader::color(ShaderId(2), Vec3::new(f32::NAN, 0.3, 0.1)),
    ]);
    let scene = f.scene();
    let camera = Camera {
        width: 64,
        height: 48,
        samples_per_pixel: 3,
        ..Default::default()
    };
    let view = view_from(&camera, Vec3::new(0.0, 3.0, 8.0));
    let params = RenderParams::for_camera(&camera, 7);
    let mut film = Film::new(64, 48);
    for frame_index in 0..2 {
        let frame = render_frame(&scene, &view, &params, frame_index, &|_| {});
        let dropped: u64 = frame.pixels.counts.iter().map(|&c| u64::from(3 - c)).sum();
        assert_eq!(frame.rejected, dropped);
        assert!(frame.rejected > 50, "{} samples rejected", frame.rejected);
        assert!(frame.pixels.sums.iter().all(|s| s.is_finite()));
        film.accumulate(&frame);
    }
    assert!(film.rejected_samples() > 100);
    assert!(film.mean_rgb().iter().flatten().all(|v| v.is_finite()));
    assert!(film.to_srgba8(0.0).len() == 64 * 48 * 4);
}

/// The discontinuity filter on a rendered edge: a textured plane 8 m above a ground with
/// the same texture and shader, the sun low enough that the raised plane shadows all the
/// ground in view (no sky: every pixel is exact). Depth alone tells the two apart,
/// and no light may cross: shadowed ground stays black, lit pixels keep their value.
#[test]
fn the_discontinuity_filter_keeps_light_on_its_side_of_a_depth_edge() {
    use sylva_engine::discontinuity::{DiscontinuityFilter, GuidedImage};
    let mut library = GeometryLibrary::default();
    let square =
        library.add(Geometry::new("square", textured_square(1.0), BuildParams::BALANCED).unwrap());
    let descs = [
        Affine3A::from_scale(Vec3::new(30.0, 1.0, 30.0)),
        Affine3A::from_scale_rotation_translation(
            Vec3::new(15.0, 1.0, 30.0),
            Quat::IDENTITY,
            Vec3::new(-15.0, 8.0, 0.0),
        ),
    ]
    .map(|transform| InstanceDesc {
        transform,
        geometry: square,
    });
    let top_level = TopLevel::build(&library, &descs, BuildParams::BALANCED);
    let shaders = ShaderTable::new(vec![checker_shader()]);
    // From −x: the plane (x < 0, 8 m up) shadows the ground out to x = 10.7 m.
    let sun_light = DirectionalLight {
        direction: Vec3::new(-0.8, 0.6, 0.0),
        irradiance: Vec3::splat(3.0),
    };
    let frame = render_in_sunlight(
        &library,
        &top_level,
        &shaders,
        sun_light,
        (48, 0.6),
        Vec3::new(0.0, 20.0, 6.0),
        3,
    );
    let raw = frame.mean();
    let albedo = frame.mean_albedo();
    let filter = |depth_tolerance: f32| {
        DiscontinuityFilter {
            depth_tolerance,
            ..DiscontinuityFilter::for_pattern(4)
        }
        .apply(&GuidedImage {
            width: 48,
            height: 48,
            radiance: &raw,
            albedo: &albedo,
            emission: &frame.mean_emission(),
            surfaces: &frame.pixels.surfaces,
        })
    };
    let filtered = filter(0.05);
    let (mut dark, mut lit, mut dark_beside_lit) = (0, 0, 0);
    for y in 0..48usize {
        for x in 0..48usize {
            let i = y * 48 + x;
            if raw[i] == Vec3::ZERO {
                dark += 1;
                assert_eq!(filtered[i], Vec3::ZERO, "light leaked into ({x}, {y})");
                let beside_lit = (x.saturating_sub(2)..(x + 2).min(47))
                    .any(|nx| raw[y * 48 + nx].max_element() > 0.1);
                dark_beside_lit += beside_lit as u32;
            } else {
                lit += 1;
                let relative = (filtered[i] - raw[i]).abs().max_element() / raw[i].max_element();
                assert!(
                    relative < 1e-4,
                    "({x}, {y}): {} against {}",
                    filtered[i],
                    raw[i]
                );
            }
        }
    }
    assert!(
        dark > 100 && lit > 100 && dark_beside_lit > 20,
        "{dark} {lit} {dark_beside_lit}"
    );
    // The test can fail: a filter blind to depth does carry light into the shadow.
    let blind = filter(10.0);
    assert!(
        (0..48 * 48).any(|i| raw[i] == Vec3::ZERO && blind[i] != Vec3::ZERO),
        "the scene does not put lit and shadowed pixels of one shader side by side"
    );
}
