//! Extreme instance transforms and extreme accumulation: tiny, huge, flattened, sheared
//! and mirrored instances give finite normals and keep their outside outside; singular
//! ones are left out and named; films sum 2²⁵ samples exactly and average one huge sample
//! among a million small ones correctly.

use glam::{Affine3A, DAffine3, DVec3, Mat3, Quat, Vec3, Vec3A};
use sylva_engine::bvh::{BuildParams, TraversalStats};
use sylva_engine::film::Film;
use sylva_engine::geometry::{Geometry, GeometryLibrary};
use sylva_engine::light::LightSet;
use sylva_engine::math::Ray;
use sylva_engine::mesh::TriangleMesh;
use sylva_engine::opacity::OpacityMaps;
use sylva_engine::render::RenderScene;
use sylva_engine::shading::{Shader, ShaderId, ShaderTable};
use sylva_engine::tlas::{InstanceDesc, TopLevel};

/// The unit-corner tetrahedron, every face wound counter-clockwise seen from outside.
fn tetrahedron() -> TriangleMesh {
    TriangleMesh {
        positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::Z],
        normals: vec![],
        uvs: vec![],
        indices: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        shaders: vec![0; 4],
    }
}

/// The transforms under test: scale 10⁻³ and 10³, a 10⁻⁷ axis, shear, mirror, and
/// mixtures, each with a rotation and a translation.
fn extreme_transforms() -> Vec<(&'static str, Affine3A)> {
    let rotation = Quat::from_scaled_axis(Vec3::new(0.3, -0.7, 0.2));
    let place = |m: Mat3| {
        Affine3A::from_rotation_translation(rotation, Vec3::new(3.0, -2.0, 5.0))
            * Affine3A::from_mat3(m)
    };
    let shear = Mat3::from_cols(Vec3::X, Vec3::new(0.8, 1.0, 0.0), Vec3::new(0.0, -0.6, 1.0));
    vec![
        ("scale 1e-3", place(Mat3::from_diagonal(Vec3::splat(1e-3)))),
        ("scale 1e3", place(Mat3::from_diagonal(Vec3::splat(1e3)))),
        (
            "scale (1, 1, 1e-7)",
            place(Mat3::from_diagonal(Vec3::new(1.0, 1.0, 1e-7))),
        ),
        ("shear", place(shear)),
        (
            "mirror x",
            place(Mat3::from_diagonal(Vec3::new(-1.0, 1.0, 1.0))),
        ),
        (
            "mirror and shear",
            place(Mat3::from_diagonal(Vec3::new(1.0, -2.0, 1.0)) * shear),
        ),
        (
            "mirror, 1e-7 and 1e3",
            place(Mat3::from_diagonal(Vec3::new(-1e3, 1.0, 1e-7))),
        ),
    ]
}

/// A face's world-space centroid and outward unit normal, in f64.
fn world_face(mesh: &TriangleMesh, face: usize, transform: &Affine3A) -> (DVec3, DVec3) {
    let t = DAffine3::from_mat3_translation(
        glam::DMat3::from_cols_array(&transform.matrix3.to_cols_array().map(f64::from)),
        transform.translation.as_dvec3(),
    );
    let [a, b, c] =
        mesh.indices[face].map(|i| t.transform_point3(mesh.positions[i as usize].as_dvec3()));
    let mut normal = (b - a).cross(c - a).normalize();
    // The winding rule: a mirroring transform turns the object-space outside inward.
    if transform.matrix3.determinant() < 0.0 {
        normal = -normal;
    }
    ((a + b + c) / 3.0, normal)
}

/// The smallest altitude of a face in world space, in f64.
fn thinness(mesh: &TriangleMesh, face: usize, transform: &Affine3A) -> f64 {
    let m = glam::DMat3::from_cols_array(&transform.matrix3.to_cols_array().map(f64::from));
    let [a, b, c] = mesh.indices[face].map(|i| m * mesh.positions[i as usize].as_dvec3());
    let area2 = (b - a).cross(c - a).length();
    let longest = (b - a).length().max((c - b).length()).max((a - c).length());
    area2 / longest
}

#[test]
fn extreme_instance_transforms_give_finite_normals_and_keep_the_outside_outside() {
    let mut library = GeometryLibrary::default();
    let g = library.add(Geometry::new("tet", tetrahedron(), BuildParams::BALANCED).unwrap());
    let mut single_sided = Shader::color(ShaderId(0), Vec3::ONE);
    single_sided.double_sided = false;
    let shaders = ShaderTable::new(vec![single_sided]);
    let lights = LightSet::default();
    let mesh = tetrahedron();
    for (name, transform) in extreme_transforms() {
        let top_level = TopLevel::build(
            &library,
            &[InstanceDesc {
                transform,
                geometry: g,
            }],
            BuildParams::BALANCED,
        );
        assert_eq!(top_level.len(), 1, "{name}: the instance is kept");
        let scene = RenderScene {
            geometry: &library,
            top_level: &top_level,
            shaders: &shaders,
            lights: &lights,
            opacity: &OpacityMaps::default(),
        };
        let size = transform
            .matrix3
            .to_cols_array()
            .iter()
            .fold(0f32, |m, v| m.max(v.abs()));
        for face in 0..4 {
            let (centre, outward) = world_face(&mesh, face, &transform);
            let distance = 2.0 * f64::from(size);
            let origin = centre + outward * distance;
            let ray = Ray::new(origin.as_vec3a(), (-outward).as_vec3a());
            let Some(hit) = scene.closest(&ray, &mut TraversalStats::default()) else {
                // A sliver thinner than an f32 step at its position cannot be hit reliably.
                assert!(
                    thinness(&mesh, face, &transform) < 1e-5 * (centre.length() + 1.0),
                    "{name}, face {face}: seen from outside, it must be hit"
                );
                continue;
            };
            assert!(
                hit.t.is_finite() && hit.barycentrics.is_finite(),
                "{name}, face {face}: {hit:?}"
            );
            assert!(
                (f64::from(hit.t) - distance).abs() <= 1e-3 * distance,
                "{name}, face {face}: t {} vs {distance}",
                hit.t
            );
            let surface = scene.surface(&hit, ray.direction);
            let n = surface.geometric_normal;
            assert!(
                n.is_finite() && (n.length() - 1.0).abs() < 1e-4,
                "{name}: normal {n}"
            );
            assert!(
                n.as_dvec3().dot(outward) > 0.999,
                "{name}, face {face}: normal {n} vs outward {outward}"
            );
            assert!(surface.shading_normal.is_finite());
            // From inside every face is seen from behind: a single-sided solid is invisible.
            let inside = transform.transform_point3a(Vec3A::splat(0.25));
            let toward = centre.as_vec3a() - inside;
            if let Some(h) =
                scene.closest(&Ray::new(inside, toward), &mut TraversalStats::default())
            {
                panic!("{name}, face {face}: hit {h:?} from inside a single-sided solid");
            }
        }
    }
}

#[test]
fn singular_and_non_finite_instances_are_left_out_and_named() {
    let mut library = GeometryLibrary::default();
    let g = library.add(Geometry::new("tet", tetrahedron(), BuildParams::BALANCED).unwrap());
    let good = Affine3A::from_translation(Vec3::X);
    let descs: Vec<InstanceDesc> = [
        good,
        Affine3A::from_scale(Vec3::ZERO),
        good,
        Affine3A::from_scale(Vec3::new(1.0, 0.0, 1.0)),
        Affine3A::from_translation(Vec3::new(f32::NAN, 0.0, 0.0)),
        Affine3A::from_scale(Vec3::splat(f32::INFINITY)),
        // Invertible in exact arithmetic, but its inverse overflows f32.
        Affine3A::from_scale(Vec3::splat(1e-30)),
    ]
    .into_iter()
    .map(|transform| InstanceDesc {
        transform,
        geometry: g,
    })
    .collect();
    let top_level = TopLevel::build(&library, &descs, BuildParams::BALANCED);
    assert_eq!(top_level.len(), 2);
    assert_eq!(top_level.skipped.singular, 5);
    assert_eq!(top_level.skipped.ids, vec![1, 3, 4, 5, 6]);
    let mut stats = TraversalStats::default();
    let ray = Ray::new(Vec3A::new(1.2, 0.2, 5.0), -Vec3A::Z);
    let hit = top_level.intersect_closest(&library, &ray, &mut stats, |_| true);
    assert!(hit.is_some_and(|h| h.instance == 0 || h.instance == 2));
}

#[test]
fn a_film_sums_two_to_the_25_samples_exactly() {
    let mut film = Film::new(1, 1);
    for _ in 0..1u32 << 25 {
        film.add_sample(0, 0, Vec3::ONE);
    }
    assert_eq!(film.pixel(0, 0), [1.0; 3]);
    assert_eq!(film.mean_rgb()[0], [1.0; 3]);
}

#[test]
fn one_huge_sample_among_a_million_small_ones_is_averaged_correctly() {
    let mut film = Film::new(1, 1);
    film.add_sample(0, 0, Vec3::splat(1e6));
    for _ in 0..1_000_000 {
        film.add_sample(0, 0, Vec3::splat(1e-3));
    }
    let expected = (1e6 + 1e6 * 1e-3f64 as f32 as f64) / 1_000_001.0;
    let got = film.pixel(0, 0)[0];
    assert!(
        ((got - expected) / expected).abs() < 1e-12,
        "{got} vs {expected}"
    );
    // In f32 the small samples would stall: 1e6 + 1e-3 == 1e6.
    assert_eq!(1e6f32 + 1e-3f32, 1e6f32);
}
