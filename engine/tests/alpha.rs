//! Hit filters inside traversal: alpha-masked quads against an oracle that walks the
//! quads one by one, shadow rays through holes, single-sided surfaces and mirroring.

mod common;

use common::*;
use glam::{Affine3A, Vec2, Vec3, Vec3A};
use std::sync::Arc;
use sylva_engine::bvh::{BuildParams, TraversalStats};
use sylva_engine::geometry::{Geometry, GeometryLibrary};
use sylva_engine::light::{DirectionalLight, LightSet, SkyLight};
use sylva_engine::math::Ray;
use sylva_engine::mesh::TriangleMesh;
use sylva_engine::occluders::OccluderCache;
use sylva_engine::opacity::OpacityMaps;
use sylva_engine::render::{RenderScene, SampleShading};
use sylva_engine::sampling::SampleKey;
use sylva_engine::shading::{Shader, ShaderId, ShaderTable, Texture, UvTransform};
use sylva_engine::tlas::{InstanceDesc, TopLevel};
use sylva_engine::transparency::TransparencyCurve;

/// A unit quad in the XY plane facing +Z (counter-clockwise seen from +Z), UV (0, 0) at
/// its top-left corner (x = 0, y = 1).
fn quad(shader: u32) -> TriangleMesh {
    TriangleMesh {
        positions: vec![
            Vec3::new(0.0, 1.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.0, 0.0, 0.0),
        ],
        normals: vec![],
        uvs: vec![
            Vec2::new(0.0, 0.0),
            Vec2::new(1.0, 0.0),
            Vec2::new(1.0, 1.0),
            Vec2::new(0.0, 1.0),
        ],
        indices: vec![[0, 3, 2], [0, 2, 1]],
        shaders: vec![shader, shader],
    }
}

/// An 8×8 mask with a fraction `holes` of transparent texels.
fn random_mask(rng: &mut TestRng, holes: f32) -> Texture {
    let texels = (0..64)
        .map(|_| {
            let a = if rng.f32() < holes { 0 } else { 255 };
            [60, 160, 40, a]
        })
        .collect();
    Texture::from_srgba8(8, 8, texels).unwrap()
}

struct Stack {
    library: GeometryLibrary,
    top_level: TopLevel,
    shaders: ShaderTable,
    lights: LightSet,
    /// Built over the masks: every oracle test checks the maps' decisions too.
    opacity: OpacityMaps,
    /// Depth of each layer (its z), in instance order.
    depths: Vec<f32>,
}

impl Stack {
    fn scene(&self) -> RenderScene<'_> {
        RenderScene {
            geometry: &self.library,
            top_level: &self.top_level,
            shaders: &self.shaders,
            lights: &self.lights,
            opacity: &self.opacity,
        }
    }
}

/// `layers` quads stacked along −Z, each with its own mask (shader i).
fn stack(rng: &mut TestRng, layers: usize, holes: f32) -> Stack {
    stack_placed(rng, layers, holes, 1.0, |i, rng| {
        let z = -(i as f32) * 0.1 - rng.range(0.0, 0.05);
        Affine3A::from_translation(Vec3::new(0.0, 0.0, z))
    })
}

/// `layers` quads placed by `place`, each with its own mask (shader i) tiled `tiles`
/// times across it.
fn stack_placed(
    rng: &mut TestRng,
    layers: usize,
    holes: f32,
    tiles: f32,
    mut place: impl FnMut(usize, &mut TestRng) -> Affine3A,
) -> Stack {
    let mut library = GeometryLibrary::default();
    let mut shaders = Vec::new();
    let mut descs = Vec::new();
    let mut depths = Vec::new();
    for i in 0..layers {
        let g = library.add(Geometry::new("quad", quad(i as u32), BuildParams::BALANCED).unwrap());
        let mut shader = Shader::alpha_masked(
            ShaderId(i as u32),
            Vec3::ONE,
            Arc::new(random_mask(rng, holes)),
            0.5,
        );
        if tiles != 1.0 {
            shader.uv_transform = Some(UvTransform {
                scale: Vec2::splat(tiles),
                ..Default::default()
            });
        }
        shaders.push(shader);
        let transform = place(i, rng);
        descs.push(InstanceDesc {
            transform,
            geometry: g,
        });
        depths.push(transform.translation.z);
    }
    let top_level = TopLevel::build(&library, &descs, BuildParams::BALANCED);
    let shaders = ShaderTable::new(shaders);
    let opacity = OpacityMaps::build(&library, &shaders);
    Stack {
        library,
        top_level,
        shaders,
        lights: LightSet::default(),
        opacity,
        depths,
    }
}

/// The layers a ray parallel to −Z meets, nearest first, each with whether its texel
/// is opaque.
fn layers_along(stack: &Stack, xy: Vec2) -> Vec<(usize, bool)> {
    let uv = Vec2::new(xy.x, 1.0 - xy.y);
    let mut order: Vec<usize> = (0..stack.depths.len()).collect();
    order.sort_by(|&a, &b| stack.depths[b].total_cmp(&stack.depths[a]));
    order
        .into_iter()
        .map(|i| (i, stack.shaders.get(i as u32).is_opaque_at(uv)))
        .collect()
}

/// The oracle: the first layer along a ray parallel to −Z whose texel is opaque.
fn first_opaque_layer(stack: &Stack, xy: Vec2) -> Option<usize> {
    layers_along(stack, xy)
        .into_iter()
        .find_map(|(i, opaque)| opaque.then_some(i))
}

/// A ray down −Z from z = 1 through texel `(x, y)` of the 8×8 masks.
fn texel_ray(x: u64, y: u64) -> (Vec2, Ray) {
    let xy = Vec2::new((x as f32 + 0.5) / 8.0, (y as f32 + 0.5) / 8.0);
    (xy, Ray::new(Vec3A::new(xy.x, xy.y, 1.0), -Vec3A::Z))
}

#[test]
fn closest_and_any_hit_skip_holes_exactly_where_the_oracle_does() {
    let mut rng = TestRng::new(21);
    let stack = stack(&mut rng, 6, 0.6);
    let scene = stack.scene();
    let mut stats = TraversalStats::default();
    let (mut hits, mut misses, mut holes_passed) = (0, 0, 0);
    for _ in 0..4000 {
        // Texel centres only: the bilinear filter then reads exactly one texel.
        let (xy, ray) = texel_ray(rng.next_u64() % 8, rng.next_u64() % 8);
        let expected = first_opaque_layer(&stack, xy);
        let got = scene.closest(&ray, &mut stats).map(|h| h.instance as usize);
        assert_eq!(got, expected, "ray through {xy}");
        assert_eq!(scene.occluded(&ray, &mut stats), expected.is_some());
        holes_passed += layers_along(&stack, xy)
            .iter()
            .take_while(|(_, opaque)| !opaque)
            .count() as u64;
        match expected {
            Some(_) => hits += 1,
            None => misses += 1,
        }
    }
    assert!(hits > 500 && misses > 20, "{hits} hits, {misses} misses");
    assert!(stats.filter_rejections > 0);
    assert!(stats.closest_filter_rejections <= stats.filter_rejections);
    assert_eq!(
        stats.holes_passed, holes_passed,
        "segments in front of the hits"
    );
    assert!(stats.segments_per_closest_ray() > 0.5);
    assert!(stats.hole_tests_per_closest_ray() >= stats.segments_per_closest_ray());
}

/// A curve whose near and far distances fall inside the stacks (layers at 1.0–2.3).
fn stack_curve() -> TransparencyCurve {
    TransparencyCurve {
        near: 1.3,
        far: 2.0,
        depth_near: 4,
        depth_far: 1,
        weight: 0.75,
    }
}

/// Adaptive transparency against an oracle that walks the layers nearest first: the
/// i-th hole at distance t is opaque when i ≥ allowance(t); a shadow ray is blocked by
/// an opaque layer or by more holes than its allowance.
#[test]
fn adaptive_transparency_turns_exactly_the_oracles_holes_opaque() {
    let curve = stack_curve();
    let mut stats = TraversalStats::default();
    let (mut made_opaque, mut total_holes_passed) = (0, 0);
    for seed in 0..6 {
        let mut rng = TestRng::new(seed);
        let stack = stack(&mut rng, 14, 0.85);
        let scene = stack.scene();
        for y in 0..8 {
            for x in 0..8 {
                let (xy, ray) = texel_ray(x, y);
                let layers = layers_along(&stack, xy);
                let mut expected = None;
                for (index, &(layer, opaque)) in layers.iter().enumerate() {
                    let t = 1.0 - stack.depths[layer];
                    if opaque {
                        expected = Some((layer, false));
                        break;
                    }
                    if index as u32 >= curve.allowance(t) {
                        expected = Some((layer, true));
                        break;
                    }
                }
                let before = stats.holes_passed;
                let got = scene
                    .closest_adaptive(&ray, Some(&curve), &mut stats)
                    .map(|(hit, opaque_hole)| (hit.instance as usize, opaque_hole));
                assert_eq!(got, expected, "ray through {xy}");
                let passed = layers
                    .iter()
                    .take_while(|(layer, _)| expected.is_none_or(|e| e.0 != *layer))
                    .count() as u64;
                assert_eq!(stats.holes_passed - before, passed, "ray through {xy}");
                made_opaque += usize::from(expected.is_some_and(|e| e.1));
                total_holes_passed += passed;

                let holes = layers.iter().filter(|(_, opaque)| !opaque).count() as u32;
                let any_opaque = layers.iter().any(|(_, opaque)| *opaque);
                for allowance in [0, 1, 3, 20] {
                    assert_eq!(
                        scene.occluded_within(&ray, Some(allowance), &mut stats),
                        any_opaque || holes > allowance,
                        "shadow ray through {xy}, allowance {allowance}"
                    );
                }
            }
        }
    }
    assert!(made_opaque > 50, "{made_opaque} holes made opaque");
    assert!(
        total_holes_passed > 300,
        "{total_holes_passed} holes passed"
    );
}

/// Pixels whose exact hit is nearer than the curve's `near`, and whose shadow rays pass
/// fewer holes than its near allowance, shade bit for bit as without it; farther ones
/// change.
#[test]
fn adaptive_transparency_leaves_near_geometry_exactly_unchanged() {
    let mut rng = TestRng::new(12);
    let mut stack = stack(&mut rng, 14, 0.7);
    stack.lights = LightSet {
        directional: vec![DirectionalLight {
            direction: Vec3::new(0.2, 0.3, 1.0).normalize(),
            irradiance: Vec3::splat(3.0),
        }],
        sky: Some(SkyLight::constant(Vec3::new(0.3, 0.4, 0.6))),
        environment: None,
    };
    let scene = stack.scene();
    let curve = stack_curve();
    let exact = SampleShading::plain(4);
    let adaptive = SampleShading {
        transparency: Some(curve),
        ..exact
    };
    let (mut near, mut far_changed) = (0, 0);
    for i in 0..2000u32 {
        let xy = Vec2::new(rng.range(0.02, 0.98), rng.range(0.02, 0.98));
        let ray = Ray::new(Vec3A::new(xy.x, xy.y, 1.0), -Vec3A::Z);
        let key = SampleKey::new(1, i, 0, 0, 0);
        let mut stats = TraversalStats::default();
        let a = scene.radiance(&ray, &key, &exact, &mut stats);
        let b = scene.radiance(&ray, &key, &adaptive, &mut stats);
        match scene.closest(&ray, &mut stats) {
            Some(hit) if hit.t < curve.near => {
                assert_eq!(
                    a.to_array().map(f32::to_bits),
                    b.to_array().map(f32::to_bits)
                );
                near += 1;
            }
            _ => far_changed += usize::from(a != b),
        }
    }
    assert!(near > 500, "{near} near pixels");
    assert!(far_changed > 100, "{far_changed} far pixels changed");
}

#[test]
fn a_shadow_ray_passes_a_thousand_transparent_layers_and_counts_each() {
    let mut rng = TestRng::new(3);
    let stack = stack(&mut rng, 1000, 1.0);
    let scene = stack.scene();
    let mut stats = TraversalStats::default();
    let ray = Ray::new(Vec3A::new(0.3, 0.6, 1.0), -Vec3A::Z);
    assert!(!scene.occluded(&ray, &mut stats));
    assert_eq!(stats.filter_rejections, 1000, "one triangle per layer");
    // Work linear in the layer count: no hidden depth cap, no quadratic revisits.
    assert!(
        stats.nodes_visited < 3 * 1000,
        "{} nodes",
        stats.nodes_visited
    );
    assert!(scene.closest(&ray, &mut stats).is_none());
}

/// A thousand copies of one alpha-masked quad in one place behave as the quad: the same
/// hits and misses, one transparency segment where it has a hole, and a shadow ray that
/// may pass one hole passes them all.
#[test]
fn a_thousand_coplanar_copies_behave_as_one() {
    let mut rng = TestRng::new(41);
    let single = stack_placed(&mut rng, 1, 0.5, 1.0, |_, _| Affine3A::IDENTITY);
    let mut copies = GeometryLibrary::default();
    let g = copies.add(Geometry::new("quad", quad(0), BuildParams::BALANCED).unwrap());
    let descs = vec![
        InstanceDesc {
            transform: Affine3A::IDENTITY,
            geometry: g,
        };
        1000
    ];
    let thousand = Stack {
        top_level: TopLevel::build(&copies, &descs, BuildParams::BALANCED),
        opacity: OpacityMaps::build(&copies, &single.shaders),
        library: copies,
        shaders: single.shaders.clone(),
        lights: LightSet::default(),
        depths: vec![0.0; 1000],
    };
    let (one, many) = (single.scene(), thousand.scene());
    let mut stats = TraversalStats::default();
    let (mut holes, mut hits) = (0, 0);
    for y in 0..8 {
        for x in 0..8 {
            let (_, ray) = texel_ray(x, y);
            let expected = one.closest(&ray, &mut TraversalStats::default()).is_some();
            let before = stats.holes_passed;
            assert_eq!(many.closest(&ray, &mut stats).is_some(), expected);
            assert_eq!(stats.holes_passed - before, u64::from(!expected));
            assert_eq!(many.occluded_within(&ray, Some(1), &mut stats), expected);
            assert_eq!(many.occluded(&ray, &mut stats), expected);
            holes += usize::from(!expected);
            hits += usize::from(expected);
        }
    }
    assert!(holes > 10 && hits > 10, "{holes} holes, {hits} hits");
}

/// Shadow rays through 8 randomly rotated and shifted layers of random masks pass with
/// the product of the layers' open fractions (each estimated from the mask alone), within
/// 3 standard deviations.
#[test]
fn random_masks_give_the_expected_transmittance() {
    let mut rng = TestRng::new(77);
    let layers = 8;
    // 10 m quads, masks tiled 20 times (6 cm texels), random yaw and offset.
    let stack = stack_placed(&mut rng, layers, 0.7, 20.0, |i, rng| {
        Affine3A::from_translation(Vec3::new(0.0, 0.0, -(i as f32)))
            * Affine3A::from_rotation_z(rng.range(0.0, std::f32::consts::TAU))
            * Affine3A::from_translation(Vec3::new(
                -5.0 + rng.range(-0.3, 0.3),
                -5.0 + rng.range(-0.3, 0.3),
                0.0,
            ))
            * Affine3A::from_scale(Vec3::splat(10.0))
    });
    let mut expected = 1.0f64;
    for i in 0..layers {
        let shader = stack.shaders.get(i as u32);
        let n = 200_000;
        let open = (0..n)
            .filter(|_| !shader.is_opaque_at(Vec2::new(rng.f32(), rng.f32())))
            .count();
        expected *= open as f64 / n as f64;
    }
    let scene = stack.scene();
    let rays = 40_000;
    let mut stats = TraversalStats::default();
    let passed = (0..rays)
        .filter(|_| {
            let origin = Vec3A::new(rng.range(-3.0, 3.0), rng.range(-3.0, 3.0), 1.0);
            !scene.occluded(&Ray::new(origin, -Vec3A::Z), &mut stats)
        })
        .count();
    let measured = passed as f64 / rays as f64;
    let sigma = (expected * (1.0 - expected) / rays as f64).sqrt();
    assert!(
        (measured - expected).abs() < 3.0 * sigma,
        "transmittance {measured} vs {expected} (sigma {sigma})"
    );
    assert!(expected > 0.02, "{expected}");
}

#[test]
fn single_sided_surfaces_are_seen_from_the_front_only_even_when_mirrored() {
    let mut library = GeometryLibrary::default();
    let g = library.add(Geometry::new("quad", quad(0), BuildParams::BALANCED).unwrap());
    let mut shader = Shader::color(ShaderId(0), Vec3::ONE);
    shader.double_sided = false;
    let shaders = ShaderTable::new(vec![shader]);
    let lights = LightSet::default();
    let from_front = Ray::new(Vec3A::new(0.4, 0.4, 2.0), -Vec3A::Z);
    let from_back = Ray::new(Vec3A::new(0.4, 0.4, -2.0), Vec3A::Z);
    let mirrored_from_front = Ray::new(Vec3A::new(-0.4, 0.4, 2.0), -Vec3A::Z);
    let mirrored_from_back = Ray::new(Vec3A::new(-0.4, 0.4, -2.0), Vec3A::Z);
    for (transform, front, back) in [
        (Affine3A::IDENTITY, from_front, from_back),
        // Mirroring in X keeps the quad's facing (+Z) but reverses its winding as seen
        // in world space: glTF's negative-determinant rule says it still faces +Z.
        (
            Affine3A::from_scale(Vec3::new(-1.0, 1.0, 1.0)),
            mirrored_from_front,
            mirrored_from_back,
        ),
        // Mirroring in Z turns it to face −Z.
        (
            Affine3A::from_scale(Vec3::new(1.0, 1.0, -1.0)),
            from_back,
            from_front,
        ),
    ] {
        let top_level = TopLevel::build(
            &library,
            &[InstanceDesc {
                transform,
                geometry: g,
            }],
            BuildParams::BALANCED,
        );
        let scene = RenderScene {
            geometry: &library,
            top_level: &top_level,
            shaders: &shaders,
            lights: &lights,
            opacity: &OpacityMaps::default(),
        };
        let mut stats = TraversalStats::default();
        assert!(scene.closest(&front, &mut stats).is_some(), "{transform:?}");
        assert!(scene.closest(&back, &mut stats).is_none(), "{transform:?}");
        assert!(scene.occluded(&front, &mut stats));
        assert!(!scene.occluded(&back, &mut stats));
    }
}

/// A single-sided, alpha-masked quad whose mask is opaque everywhere: its opacity map
/// decides every point, and still the back is culled before the map is believed.
#[test]
fn a_single_sided_masked_surface_is_culled_behind_even_where_its_map_is_opaque() {
    let mut library = GeometryLibrary::default();
    let g = library.add(Geometry::new("quad", quad(0), BuildParams::BALANCED).unwrap());
    let opaque = Texture::from_srgba8(4, 4, vec![[80, 120, 40, 255]; 16]).unwrap();
    let mut shader = Shader::alpha_masked(ShaderId(0), Vec3::ONE, Arc::new(opaque), 0.5);
    shader.double_sided = false;
    let shaders = ShaderTable::new(vec![shader]);
    let opacity = OpacityMaps::build(&library, &shaders);
    assert_eq!(opacity.map_count(), 2, "both triangles have maps");
    let top_level = TopLevel::build(
        &library,
        &[InstanceDesc {
            transform: Affine3A::IDENTITY,
            geometry: g,
        }],
        BuildParams::BALANCED,
    );
    let lights = LightSet::default();
    let scene = RenderScene {
        geometry: &library,
        top_level: &top_level,
        shaders: &shaders,
        lights: &lights,
        opacity: &opacity,
    };
    let mut stats = TraversalStats::default();
    for xy in [Vec2::new(0.3, 0.6), Vec2::new(0.7, 0.2)] {
        let front = Ray::new(Vec3A::new(xy.x, xy.y, 2.0), -Vec3A::Z);
        let back = Ray::new(Vec3A::new(xy.x, xy.y, -2.0), Vec3A::Z);
        assert!(scene.closest(&front, &mut stats).is_some(), "{xy}");
        assert!(scene.occluded(&front, &mut stats), "{xy}");
        assert!(scene.closest(&back, &mut stats).is_none(), "{xy}");
        assert!(!scene.occluded(&back, &mut stats), "{xy}");
    }
    assert_eq!(
        stats.texture_alpha_tests, 0,
        "the maps decided every alpha test"
    );
}

/// Shadow rays tested against a cache of recent occluders, one cache kept across all of
/// them as a tile keeps it, answer exactly as walks without it: rays from random points
/// and rays leaving a layer they hit (whose own block the cache may hold), with and
/// without a hole allowance. Enough of them stop on a cached block that a wrong cached
/// answer would show.
#[test]
fn remembered_occluders_never_change_a_shadow_rays_answer() {
    let mut stats = TraversalStats::default();
    let (mut rays, mut occluded) = (0u64, 0u64);
    for seed in 0..4 {
        let mut rng = TestRng::new(100 + seed);
        let stack = stack(&mut rng, 10, 0.6);
        let scene = stack.scene();
        let mut cache = OccluderCache::new();
        for _ in 0..3000 {
            let origin = Vec3A::new(rng.range(-0.2, 1.2), rng.range(-0.2, 1.2), 1.0);
            let tilt = Vec3A::new(rng.range(-0.3, 0.3), rng.range(-0.3, 0.3), 0.0);
            let ray = Ray::new(origin, (tilt - Vec3A::Z).normalize());
            let allowance = [None, Some(0), Some(2)][rng.next_u64() as usize % 3];
            let expected = scene.occluded_within(&ray, allowance, &mut TraversalStats::default());
            let got = scene.occluded_leaving(&ray, None, allowance, Some(&mut cache), &mut stats);
            assert_eq!(got, expected, "ray {ray:?}, allowance {allowance:?}");
            rays += 1;
            occluded += u64::from(got);

            // A shadow ray leaving the surface this ray first meets, toward a light on
            // either side of it.
            let Some(hit) = scene.closest(&ray, &mut TraversalStats::default()) else {
                continue;
            };
            let surface = scene.surface(&hit, ray.direction);
            let light = Vec3A::from(rng.unit());
            let outward = if light.dot(surface.geometric_normal) >= 0.0 {
                surface.geometric_normal
            } else {
                -surface.geometric_normal
            };
            // From the computed point itself half the time, with no offset off the surface.
            let origin = if rng.f32() < 0.5 {
                surface.point.point
            } else {
                surface.point.offset_origin(outward, light)
            };
            let shadow = Ray::new(origin, light);
            let leaving = Some(surface.triangle);
            let expected = scene.occluded_leaving(
                &shadow,
                leaving,
                allowance,
                None,
                &mut TraversalStats::default(),
            );
            let got =
                scene.occluded_leaving(&shadow, leaving, allowance, Some(&mut cache), &mut stats);
            assert_eq!(got, expected, "shadow ray {shadow:?} leaving {leaving:?}");
            rays += 1;
            occluded += u64::from(got);
        }
    }
    assert!(
        stats.cached_occlusions > rays / 10,
        "{} of {rays} rays stopped by the cache",
        stats.cached_occlusions
    );
    assert!(
        occluded > stats.cached_occlusions + rays / 50 && occluded < rays * 9 / 10,
        "{occluded} of {rays} rays occluded, {} by the cache",
        stats.cached_occlusions
    );
}
