//! Hit filters inside traversal: alpha-masked quads against an oracle that walks the
//! quads one by one, shadow rays through holes, single-sided surfaces and mirroring.

mod common;

use common::*;
use glam::{Affine3A, Vec2, Vec3, Vec3A};
use std::sync::Arc;
use sylva_engine::bvh::{BuildParams, TraversalStats};
use sylva_engine::geometry::{Geometry, GeometryLibrary};
use sylva_engine::light::LightSet;
use sylva_engine::math::Ray;
use sylva_engine::mesh::TriangleMesh;
use sylva_engine::render::RenderScene;
use sylva_engine::shading::{Shader, ShaderId, ShaderTable, Texture};
use sylva_engine::tlas::{InstanceDesc, TopLevel};

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
        }
    }
}

/// `layers` quads stacked along −Z, each with its own mask (shader i).
fn stack(rng: &mut TestRng, layers: usize, holes: f32) -> Stack {
    let mut library = GeometryLibrary::default();
    let mut shaders = Vec::new();
    let mut descs = Vec::new();
    let mut depths = Vec::new();
    for i in 0..layers {
        let g = library.add(Geometry::new("quad", quad(i as u32), BuildParams::BALANCED).unwrap());
        shaders.push(Shader::alpha_masked(
            ShaderId(i as u32),
            Vec3::ONE,
            Arc::new(random_mask(rng, holes)),
            0.5,
        ));
        let z = -(i as f32) * 0.1 - rng.range(0.0, 0.05);
        descs.push(InstanceDesc {
            transform: Affine3A::from_translation(Vec3::new(0.0, 0.0, z)),
            geometry: g,
        });
        depths.push(z);
    }
    let top_level = TopLevel::build(&library, &descs, BuildParams::BALANCED);
    Stack {
        library,
        top_level,
        shaders: ShaderTable::new(shaders),
        lights: LightSet::default(),
        depths,
    }
}

/// The oracle: the first layer along a ray parallel to −Z whose texel is opaque.
fn first_opaque_layer(stack: &Stack, xy: Vec2) -> Option<usize> {
    let uv = Vec2::new(xy.x, 1.0 - xy.y);
    let mut order: Vec<usize> = (0..stack.depths.len()).collect();
    order.sort_by(|&a, &b| stack.depths[b].total_cmp(&stack.depths[a]));
    order
        .into_iter()
        .find(|&i| stack.shaders.get(i as u32).is_opaque_at(uv))
}

#[test]
fn closest_and_any_hit_skip_holes_exactly_where_the_oracle_does() {
    let mut rng = TestRng::new(21);
    let stack = stack(&mut rng, 6, 0.6);
    let scene = stack.scene();
    let mut stats = TraversalStats::default();
    let (mut hits, mut misses) = (0, 0);
    for _ in 0..4000 {
        // Texel centres only: the bilinear filter then reads exactly one texel.
        let xy = Vec2::new(
            ((rng.next_u64() % 8) as f32 + 0.5) / 8.0,
            ((rng.next_u64() % 8) as f32 + 0.5) / 8.0,
        );
        let ray = Ray::new(Vec3A::new(xy.x, xy.y, 1.0), -Vec3A::Z);
        let expected = first_opaque_layer(&stack, xy);
        let got = scene.closest(&ray, &mut stats).map(|h| h.instance as usize);
        assert_eq!(got, expected, "ray through {xy}");
        assert_eq!(scene.occluded(&ray, &mut stats), expected.is_some());
        match expected {
            Some(_) => hits += 1,
            None => misses += 1,
        }
    }
    assert!(hits > 500 && misses > 20, "{hits} hits, {misses} misses");
    assert!(stats.filter_rejections > 0);
    assert!(stats.closest_filter_rejections <= stats.filter_rejections);
    assert!(stats.segments_per_closest_ray() > 0.5);
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
    assert!(scene.closest(&ray, &mut stats).is_none());
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
        };
        let mut stats = TraversalStats::default();
        assert!(scene.closest(&front, &mut stats).is_some(), "{transform:?}");
        assert!(scene.closest(&back, &mut stats).is_none(), "{transform:?}");
        assert!(scene.occluded(&front, &mut stats));
        assert!(!scene.occluded(&back, &mut stats));
    }
}
