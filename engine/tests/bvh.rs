//! BVH and TLAS against brute force, and validation of every build preset, including
//! degenerate inputs.

mod common;

use common::*;
use glam::{Affine3A, Vec3, Vec3A};
use proptest::prelude::*;
use sylva_engine::bvh::{
    BOTTOM_GRID_FROM, BuildParams, BuildScratch, Bvh, GRID_FROM, PACKET, PADDING, TraversalStats,
    WIDTH,
};
use sylva_engine::geometry::{Geometry, GeometryId, GeometryLibrary};
use sylva_engine::math::{Aabb, Ray};
use sylva_engine::mesh::TriangleMesh;
use sylva_engine::presplit::triangle_boxes;
use sylva_engine::tlas::{InstanceDesc, TopLevel};

fn bounds_of(mesh: &TriangleMesh) -> Vec<Aabb> {
    (0..mesh.triangle_count())
        .map(|i| mesh.triangle_bounds(i))
        .collect()
}

fn check_mesh_against_brute_force(mesh: TriangleMesh, rays: &[Ray], params: BuildParams) {
    let bounds = triangle_boxes(&mesh, params.split_ratio).boxes;
    let geometry = Geometry::new("random", mesh, params).unwrap();
    geometry.bvh.validate(&bounds).unwrap();
    let mut stats = TraversalStats::default();
    for ray in rays {
        let expected = brute_closest(&geometry.mesh, ray, |_| true);
        let got = geometry.intersect_closest(ray, &mut stats, |_, _| true);
        match (expected, got) {
            (None, None) => {}
            (Some((t, tri)), Some(h)) => {
                assert_eq!(h.hit.t, t, "closest t differs for {ray:?}");
                if h.triangle != tri {
                    // Another triangle at exactly the same distance is an equally right answer.
                    let [a, b, c] = geometry.mesh.triangle(h.triangle as usize);
                    assert!(
                        sylva_engine::triangle::WatertightRay::new(ray)
                            .intersect(a, b, c, f32::INFINITY)
                            .is_some_and(|x| x.t == t)
                    );
                }
            }
            (e, g) => panic!("brute force {e:?} but BVH {g:?} for {ray:?}"),
        }
        if let Some(h) = got {
            assert!(
                h.hit.t.is_finite() && h.hit.barycentrics.is_finite(),
                "non-finite hit {h:?} for {ray:?}"
            );
            assert!((h.hit.barycentrics.element_sum() - 1.0).abs() < 1e-4);
        }
        assert_eq!(
            geometry.intersect_any(ray, &mut stats, |_, _| true),
            expected.is_some(),
            "any-hit differs for {ray:?}"
        );
        // A filter that rejects odd triangles must match brute force with the same filter.
        let filtered = brute_closest(&geometry.mesh, ray, |t| t % 2 == 0).map(|h| h.0);
        assert_eq!(
            geometry
                .intersect_closest(ray, &mut stats, |t, _| t % 2 == 0)
                .map(|h| h.hit.t),
            filtered
        );
        assert_eq!(
            geometry.intersect_any(ray, &mut stats, |t, _| t % 2 == 0),
            filtered.is_some()
        );
    }
}

#[test]
fn blas_matches_brute_force_for_every_preset() {
    for (name, params) in BuildParams::PRESETS {
        let mut rng = TestRng::new(17);
        for (n, size) in [(1, 1.0), (7, 0.5), (300, 0.4), (5000, 0.1)] {
            let mesh = random_mesh(&mut rng, n, 2.0, size);
            let rays: Vec<Ray> = (0..2000).map(|_| random_ray(&mut rng, 3.0)).collect();
            eprintln!("preset {name}, {n} triangles");
            check_mesh_against_brute_force(mesh, &rays, params);
        }
    }
}

/// Rays the slab and triangle tests find hardest: axis-aligned with ±0 components,
/// denormal components, origins exactly on the root's and the triangles' bounding planes,
/// grazing along triangle edges, and NaN, infinite or zero vectors. Every one must agree
/// with brute force, give finite t and barycentrics, and never panic.
#[test]
fn degenerate_rays_match_brute_force_and_never_give_nan() {
    let mut rng = TestRng::new(29);
    let mesh = random_mesh(&mut rng, 400, 2.0, 0.5);
    let bounds = Aabb::from_points(mesh.positions.iter().map(|&p| Vec3A::from(p)));
    let mut rays = Vec::new();
    let zero_directions = [
        Vec3A::new(0.0, 0.0, 1.0),
        Vec3A::new(-0.0, 0.0, -1.0),
        Vec3A::new(0.0, -0.0, 1.0),
        Vec3A::new(1.0, -0.0, -0.0),
        Vec3A::new(-0.0, 1.0, 0.0),
        Vec3A::new(0.0, -1.0, -0.0),
        Vec3A::new(1e-40, 1.0, -1e-42),
        Vec3A::new(-1e-45, 1e-39, 1.0),
        Vec3A::new(1.0, 1e-38, 0.0),
    ];
    for _ in 0..200 {
        let origin = Vec3A::from(rng.vec3(-3.0, 3.0));
        for d in zero_directions {
            rays.push(Ray::new(origin, d));
        }
        // Origins on the root box's planes, and on triangle bounding planes.
        let tri = mesh.triangle_bounds((rng.next_u64() % 400) as usize);
        let mut on_planes = Vec3A::from(rng.vec3(-3.0, 3.0));
        let axis = (rng.next_u64() % 3) as usize;
        on_planes[axis] = if rng.f32() < 0.5 {
            bounds.min[axis]
        } else {
            tri.max[axis]
        };
        rays.push(Ray::new(on_planes, rng.unit().into()));
        rays.push(Ray::new(on_planes, zero_directions[axis % 6]));
        // Grazing: along an edge of a triangle, from just before its first vertex.
        let [a, b, _] = mesh.triangle((rng.next_u64() % 400) as usize);
        let edge = (b - a).normalize_or(Vec3A::X);
        rays.push(Ray::new(a - edge * 0.25, edge));
        rays.push(Ray::new(a - edge * 0.25 + Vec3A::splat(1e-7), edge));
    }
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        rays.push(Ray::new(Vec3A::new(bad, 0.0, 0.0), Vec3A::Z));
        rays.push(Ray::new(Vec3A::ZERO, Vec3A::new(0.3, bad, 1.0)));
        rays.push(Ray::segment(Vec3A::ZERO, Vec3A::Z, bad));
    }
    rays.push(Ray::new(Vec3A::ZERO, Vec3A::ZERO));
    rays.push(Ray::new(Vec3A::ZERO, Vec3A::new(-0.0, 0.0, -0.0)));
    for (_, params) in BuildParams::PRESETS {
        check_mesh_against_brute_force(mesh.clone(), &rays, params);
    }
}

/// Inputs the `bvh_vs_brute_force` fuzz target once failed on (`fuzz/regressions/`),
/// decoded as it decodes them: 6 floats of ray, then triangles of 9 floats.
#[test]
fn fuzz_regressions_match_brute_force() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../fuzz/regressions/bvh_vs_brute_force");
    let mut checked = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let data = std::fs::read(entry.unwrap().path()).unwrap();
        let floats: Vec<f32> = data
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let (r, soup) = floats.split_at(6);
        let mut mesh = TriangleMesh::default();
        for (i, t) in soup.chunks_exact(9).take(64).enumerate() {
            for k in 0..3 {
                mesh.positions
                    .push(Vec3::new(t[3 * k], t[3 * k + 1], t[3 * k + 2]));
            }
            let b = 3 * i as u32;
            mesh.indices.push([b, b + 1, b + 2]);
            mesh.shaders.push(0);
        }
        let ray = Ray::new(Vec3A::new(r[0], r[1], r[2]), Vec3A::new(r[3], r[4], r[5]));
        if mesh.positions.iter().all(|p| p.is_finite()) {
            check_mesh_against_brute_force(mesh, &[ray], BuildParams::BALANCED);
        } else {
            // Non-finite vertices are refused before any BVH is built.
            assert!(matches!(
                Geometry::new("fuzz", mesh, BuildParams::BALANCED),
                Err(sylva_engine::mesh::MeshError::NonFinitePosition { .. })
            ));
        }
        checked += 1;
    }
    assert!(checked >= 1);
}

#[test]
fn parallel_build_equals_sequential_build() {
    let mut rng = TestRng::new(5);
    let mesh = random_mesh(&mut rng, 50_000, 10.0, 0.3);
    let bounds = bounds_of(&mesh);
    let parallel = Bvh::build(&bounds, BuildParams::BALANCED);
    let sequential = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| {
            Bvh::build(
                &bounds,
                BuildParams {
                    parallel_threshold: usize::MAX,
                    ..BuildParams::BALANCED
                },
            )
        });
    parallel.validate(&bounds).unwrap();
    assert_eq!(parallel.prim_indices, sequential.prim_indices);
    assert_eq!(parallel.wide.len(), sequential.wide.len());
}

/// The tree (nodes and slot order) is the same bits on any pool size: large enough for
/// parallel binning at the root and parallel subtrees, for every preset.
#[test]
fn build_is_identical_on_any_thread_count() {
    let mut rng = TestRng::new(11);
    let mesh = random_mesh(&mut rng, 150_000, 30.0, 0.3);
    let bounds = bounds_of(&mesh);
    let build_on = |threads: usize, params: BuildParams| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| Bvh::build(&bounds, params))
    };
    for (name, params) in BuildParams::PRESETS {
        let one = build_on(1, params);
        let three = build_on(3, params);
        one.validate(&bounds).unwrap();
        assert_eq!(one.prim_indices, three.prim_indices, "{name}: slot order");
        assert!(one.wide == three.wide, "{name}: wide nodes differ");
        assert_eq!(one.content_hash(), three.content_hash(), "{name}: hash");
        // Any change to what traversal reads changes the hash.
        let mut moved = one.clone();
        moved.wide[0].max_x[0] = f32::from_bits(moved.wide[0].max_x[0].to_bits() + 1);
        assert_ne!(
            moved.content_hash(),
            one.content_hash(),
            "{name}: a box moved"
        );
        let mut swapped = one.clone();
        swapped.prim_indices.swap(0, 1);
        assert_ne!(
            swapped.content_hash(),
            one.content_hash(),
            "{name}: slots swapped"
        );
    }
}

/// A rebuild into a BVH and scratch memory that held another tree (larger, smaller,
/// with unusable boxes, empty) gives exactly the fresh build's tree, at both levels.
#[test]
fn a_rebuild_in_used_memory_equals_a_fresh_build() {
    let mut rng = TestRng::new(17);
    // The first is large enough for the top level's grid cells, and leaves its sorted
    // primitives in the scratch memory the others reuse.
    let mut inputs: Vec<Vec<Aabb>> = [GRID_FROM + 7_000, 300, 9_000]
        .into_iter()
        .map(|n| bounds_of(&random_mesh(&mut rng, n, 10.0, 0.3)))
        .collect();
    inputs[2][5] = Aabb::EMPTY;
    inputs[2][77].max.x = f32::NAN;
    inputs.push(Vec::new());
    inputs.push(bounds_of(&random_mesh(&mut rng, 1, 1.0, 0.3)));
    for (name, params) in BuildParams::PRESETS {
        let mut reused = Bvh::default();
        let mut scratch = BuildScratch::default();
        for (i, bounds) in inputs.iter().enumerate() {
            reused.rebuild(bounds, params, &mut scratch);
            let fresh = Bvh::build(bounds, params);
            assert_eq!(reused.prim_indices, fresh.prim_indices, "{name}, input {i}");
            assert!(reused.wide == fresh.wide, "{name}, input {i}: wide nodes");
        }
    }
    let lib = random_library(&mut rng, 4, 200);
    let mut sets: Vec<Vec<InstanceDesc>> = [2_000, 150, 700]
        .into_iter()
        .map(|n| random_instances(&mut rng, n, 4, (-0.5, 0.7)))
        .collect();
    sets[2][3].transform = Affine3A::from_scale(Vec3::ZERO);
    sets[2][9].geometry = GeometryId(99);
    sets.push(Vec::new());
    let mut reused = TopLevel::default();
    for (i, descs) in sets.iter().enumerate() {
        reused.rebuild(&lib, descs, BuildParams::TOP_LEVEL);
        let fresh = TopLevel::build(&lib, descs, BuildParams::TOP_LEVEL);
        assert_eq!(reused.instances, fresh.instances, "set {i}: records");
        assert!(reused.bvh.wide == fresh.bvh.wide, "set {i}: wide nodes");
        assert_eq!(reused.content_hash(), fresh.content_hash(), "set {i}: hash");
        if !reused.instances.is_empty() {
            let mut other = reused.clone();
            other.instances[0].id ^= 1;
            assert_ne!(
                other.content_hash(),
                fresh.content_hash(),
                "set {i}: a record"
            );
        }
        assert_eq!(reused.bvh.prim_indices, fresh.bvh.prim_indices, "set {i}");
        assert_eq!(reused.outside, fresh.outside, "set {i}: outside");
        assert_eq!(reused.skipped, fresh.skipped, "set {i}: skipped");
        assert_eq!(reused.source_count, fresh.source_count, "set {i}");
        assert_eq!(reused.built_sah_cost, fresh.built_sah_cost, "set {i}");
        assert_eq!(reused.current_sah_cost, fresh.current_sah_cost, "set {i}");
    }
}

#[test]
fn validate_after_every_preset_on_degenerate_input() {
    let mut rng = TestRng::new(3);
    let same_centroid = {
        let mut m = TriangleMesh::default();
        for i in 0..100_000u32 {
            let d = rng.unit() * rng.range(0.01, 1.0);
            m.positions.extend([Vec3::ZERO, d, -d]);
            m.indices.push([3 * i, 3 * i + 1, 3 * i + 2]);
            m.shaders.push(0);
        }
        m
    };
    let zero_area = {
        let mut m = random_mesh(&mut rng, 200, 1.0, 0.5);
        for (i, tri) in m.indices.iter_mut().enumerate() {
            if i % 2 == 0 {
                tri[2] = tri[1];
            }
        }
        m
    };
    let one_point = TriangleMesh {
        positions: vec![Vec3::ONE; 3],
        indices: vec![[0, 1, 2]; 50],
        shaders: vec![0; 50],
        ..Default::default()
    };
    let mut with_nan = random_mesh(&mut rng, 100, 1.0, 0.5);
    with_nan.positions[4] = Vec3::new(f32::NAN, 0.0, 0.0);
    with_nan.positions[10] = Vec3::splat(f32::INFINITY);
    let cases = [
        ("empty", TriangleMesh::default()),
        ("one triangle", random_mesh(&mut rng, 1, 1.0, 1.0)),
        ("1e5 same centroid", same_centroid),
        ("zero-area triangles", zero_area),
        ("all in one point", one_point),
        ("NaN and inf vertices", with_nan),
    ];
    for (name, params) in BuildParams::PRESETS {
        for (case, mesh) in &cases {
            let bounds = bounds_of(mesh);
            let bvh = Bvh::build(&bounds, params);
            let report = bvh
                .validate(&bounds)
                .unwrap_or_else(|e| panic!("{name} / {case}: {e}"));
            assert!(
                report.max_depth < sylva_engine::bvh::MAX_DEPTH,
                "{name} / {case}"
            );
            if *case == "NaN and inf vertices" {
                assert_eq!(
                    bvh.prim_indices.iter().filter(|&&p| p != PADDING).count(),
                    98,
                    "the two triangles with non-finite corners are left out"
                );
            }
        }
    }
    // The same-centroid mesh is still traversable and correct.
    let geometry = Geometry::new("star", cases[2].1.clone(), BuildParams::BALANCED).unwrap();
    let mut stats = TraversalStats::default();
    for _ in 0..200 {
        let ray = random_ray(&mut rng, 2.0);
        let expected = brute_closest(&geometry.mesh, &ray, |_| true).map(|h| h.0);
        assert_eq!(
            geometry
                .intersect_closest(&ray, &mut stats, |_, _| true)
                .map(|h| h.hit.t),
            expected
        );
    }
}

#[test]
fn instance_of_an_empty_mesh_and_singular_transforms_are_harmless() {
    let mut lib = GeometryLibrary::default();
    let empty =
        lib.add(Geometry::new("empty", TriangleMesh::default(), BuildParams::BALANCED).unwrap());
    let mut rng = TestRng::new(9);
    let solid = lib.add(
        Geometry::new(
            "solid",
            random_mesh(&mut rng, 50, 1.0, 0.5),
            BuildParams::BALANCED,
        )
        .unwrap(),
    );
    let instances = vec![
        InstanceDesc {
            transform: Affine3A::IDENTITY,
            geometry: empty,
        },
        InstanceDesc {
            transform: Affine3A::from_scale(Vec3::new(1.0, 0.0, 1.0)),
            geometry: solid,
        },
        InstanceDesc {
            transform: Affine3A::from_translation(Vec3::NAN),
            geometry: solid,
        },
        InstanceDesc {
            transform: Affine3A::IDENTITY,
            geometry: GeometryId(99),
        },
        InstanceDesc {
            transform: Affine3A::IDENTITY,
            geometry: solid,
        },
    ];
    for (_, params) in BuildParams::PRESETS {
        let tlas = TopLevel::build(&lib, &instances, params);
        assert_eq!(tlas.len(), 1);
        assert_eq!(tlas.skipped.singular, 2);
        assert_eq!(tlas.skipped.unknown_geometry, 1);
        let mut boxes = vec![Aabb::EMPTY; instances.len()];
        for r in &tlas.instances {
            boxes[r.id as usize] = lib
                .get(r.geometry)
                .unwrap()
                .transformed_bounds(&r.object_to_world());
        }
        tlas.bvh.validate(&boxes).unwrap();
    }
    let tlas = TopLevel::build(&lib, &[], BuildParams::BALANCED);
    let mut stats = TraversalStats::default();
    assert!(
        tlas.intersect_closest(&lib, &Ray::new(Vec3A::ZERO, Vec3A::X), &mut stats, |_| true)
            .is_none()
    );
}

fn check_instances_against_brute_force(
    seed: u64,
    geometries: usize,
    instances: usize,
    rays: usize,
) {
    let mut rng = TestRng::new(seed);
    let lib = random_library(&mut rng, geometries, 200);
    let descs = random_instances(&mut rng, instances, geometries, (-0.5, 0.7));
    for (name, params) in BuildParams::PRESETS {
        let tlas = TopLevel::build(&lib, &descs, params);
        let batch: Vec<Ray> = (0..rays).map(|_| random_ray(&mut rng, 25.0)).collect();
        assert_tlas_matches_brute_force(&lib, &tlas, &descs, &batch, name);
    }
}

#[test]
fn tlas_matches_brute_force_on_random_instance_sets() {
    check_instances_against_brute_force(1, 4, 300, 3000);
    check_instances_against_brute_force(2, 1, 1, 500);
    check_instances_against_brute_force(3, 8, 1000, 300);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, .. ProptestConfig::default() })]

    #[test]
    fn proptest_blas_closest_equals_brute_force(seed in any::<u64>(), n in 1usize..400, size in 0.01f32..2.0, preset in 0usize..BuildParams::PRESETS.len()) {
        let mut rng = TestRng::new(seed);
        let mesh = random_mesh(&mut rng, n, 2.0, size);
        let rays: Vec<Ray> = (0..200).map(|_| random_ray(&mut rng, 3.0)).collect();
        check_mesh_against_brute_force(mesh, &rays, BuildParams::PRESETS[preset].1);
    }

    #[test]
    fn proptest_tlas_closest_equals_brute_force(seed in any::<u64>(), geometries in 1usize..5, instances in 0usize..120) {
        check_instances_against_brute_force(seed, geometries, instances, 150);
    }
}

/// A packet of `n` rays from `origin` (jittered by up to `origin_jitter`) around
/// `direction`, spread by up to `spread` per component.
fn ray_packet(
    rng: &mut TestRng,
    n: usize,
    origin: Vec3,
    origin_jitter: f32,
    direction: Vec3,
    spread: f32,
) -> Vec<Ray> {
    (0..n)
        .map(|_| {
            let o = origin + rng.vec3(-origin_jitter, origin_jitter);
            let d = (direction + rng.vec3(-spread, spread)).normalize();
            Ray::new(o.into(), d.into())
        })
        .collect()
}

/// A hit filter that differs from ray to ray of a packet: a walk that mixed up which ray
/// a candidate belongs to would give some ray another's answer.
fn keeps(ray: usize, triangle: u32) -> bool {
    !(triangle as usize + ray).is_multiple_of(3)
}

#[test]
fn packet_walks_find_each_rays_own_closest_hit() {
    let mut rng = TestRng::new(77);
    let lib = random_library(&mut rng, 5, 300);
    let descs = random_instances(&mut rng, 600, 5, (-0.5, 0.7));
    let tlas = TopLevel::build(&lib, &descs, BuildParams::TOP_LEVEL);
    let (mut packets, mut hits) = (0, 0);
    for round in 0..400 {
        let origin = rng.vec3(-25.0, 25.0);
        let towards = rng.vec3(-20.0, 20.0) - origin;
        // Camera-like packets (one origin, a narrow cone), wide ones, and ones whose
        // origins differ (a lens).
        // The narrowest are narrow enough to walk the bottom levels together too.
        let (jitter, spread) = [(0.0, 0.02), (0.0, 0.3), (0.5, 0.05), (0.0, 0.0005)][round % 4];
        let n = 1 + round % PACKET;
        let rays = ray_packet(&mut rng, n, origin, jitter, towards.normalize(), spread);
        let mut stats = TraversalStats::default();
        let Some(found) =
            tlas.intersect_closest_packet(&lib, &rays, &mut stats, |ray, c| keeps(ray, c.triangle))
        else {
            continue;
        };
        packets += 1;
        assert_eq!(stats.closest_rays, n as u64);
        assert!(found[n..].iter().all(Option::is_none));
        for (i, (ray, got)) in rays.iter().zip(&found).enumerate() {
            let expected = tlas.intersect_closest(&lib, ray, &mut stats, |c| keeps(i, c.triangle));
            assert_eq!(
                got.map(|h| (h.t, h.instance, h.triangle)),
                expected.map(|h| (h.t, h.instance, h.triangle)),
                "round {round}, ray {ray:?}"
            );
            hits += usize::from(got.is_some());
        }
    }
    assert!(packets > 300, "only {packets} packets could be bounded");
    assert!(
        hits > 500,
        "only {hits} hits: the test would not see a wrong walk"
    );
}

#[test]
fn bottom_level_packets_find_each_rays_own_closest_accepted_hit() {
    let mut rng = TestRng::new(91);
    let geometry = Geometry::new(
        "dense",
        random_mesh(&mut rng, 3000, 2.0, 0.3),
        BuildParams::BOTTOM_LEVEL,
    )
    .unwrap();
    let (mut packets, mut hits) = (0, 0);
    for round in 0..300 {
        let origin = rng.vec3(-6.0, 6.0);
        let towards = rng.vec3(-1.5, 1.5) - origin;
        let (jitter, spread) = [(0.0, 0.01), (0.0, 0.2), (0.3, 0.05)][round % 3];
        let n = 2 + round % (PACKET - 1);
        let mut rays = ray_packet(&mut rng, n, origin, jitter, towards.normalize(), spread);
        // Some rays already have a nearer hit elsewhere.
        for ray in rays.iter_mut().step_by(4) {
            ray.t_max = rng.range(1.0, 9.0);
        }
        let mut stats = TraversalStats::default();
        let Some(found) =
            geometry.intersect_closest_packet(&rays, &mut stats, |ray, triangle, _| {
                keeps(ray, triangle)
            })
        else {
            continue;
        };
        packets += 1;
        assert!(found[n..].iter().all(Option::is_none));
        for (i, (ray, got)) in rays.iter().zip(&found).enumerate() {
            let expected =
                geometry.intersect_closest(ray, &mut stats, |triangle, _| keeps(i, triangle));
            assert_eq!(
                got.map(|h| (h.hit.t, h.triangle)),
                expected.map(|h| (h.hit.t, h.triangle)),
                "round {round}, ray {i}: {ray:?}"
            );
            hits += usize::from(got.is_some());
        }
    }
    assert!(packets > 250, "only {packets} packets could be bounded");
    assert!(
        hits > 1000,
        "only {hits} hits: the test would not see a wrong walk"
    );
}

#[test]
fn packets_the_walk_cannot_bound_are_left_to_single_rays() {
    let mut rng = TestRng::new(5);
    let lib = random_library(&mut rng, 2, 50);
    let descs = random_instances(&mut rng, 50, 2, (-0.5, 0.5));
    let tlas = TopLevel::build(&lib, &descs, BuildParams::TOP_LEVEL);
    let mut stats = TraversalStats::default();
    let opposite = [
        Ray::new(Vec3A::ZERO, Vec3A::new(1.0, 0.2, 0.3).normalize()),
        Ray::new(Vec3A::ZERO, Vec3A::new(-1.0, 0.2, 0.3).normalize()),
    ];
    let parallel = [Ray::new(Vec3A::ZERO, Vec3A::X)];
    let no_filter_calls = |_: usize, _: &sylva_engine::tlas::Candidate| -> bool {
        panic!("a packet that cannot be bounded tests nothing")
    };
    for rays in [&opposite[..], &parallel[..], &[]] {
        assert!(
            tlas.intersect_closest_packet(&lib, rays, &mut stats, no_filter_calls)
                .is_none()
        );
    }
    assert_eq!(stats, TraversalStats::default());
}

#[test]
fn a_turned_instance_gets_a_box_that_hugs_its_mesh() {
    // A round crown of triangles, turned 45° about its stem and tilted: the corners of
    // its object box, transformed, give a box twice the exact one's ground area; the
    // instance's box must stay within 10 % of exact, and hold every vertex.
    let mut rng = TestRng::new(21);
    let mut mesh = TriangleMesh::default();
    for i in 0..3_000u32 {
        mesh.positions.push(rng.unit() * 2.0 + Vec3::Y * 3.0);
        if i % 3 == 2 {
            mesh.indices.push([i - 2, i - 1, i]);
            mesh.shaders.push(0);
        }
    }
    let mut lib = GeometryLibrary::default();
    let crown = lib.add(Geometry::new("crown", mesh.clone(), BuildParams::BALANCED).unwrap());
    let transform = Affine3A::from_scale_rotation_translation(
        Vec3::splat(1.2),
        glam::Quat::from_rotation_x(0.15)
            * glam::Quat::from_rotation_y(std::f32::consts::FRAC_PI_4),
        Vec3::new(40.0, -1.0, 7.0),
    );
    let tlas = TopLevel::build(
        &lib,
        &[InstanceDesc {
            transform,
            geometry: crown,
        }],
        BuildParams::BALANCED,
    );
    let exact = Aabb::from_points(
        mesh.positions
            .iter()
            .map(|&p| transform.transform_point3a(p.into())),
    );
    let ground = |b: Aabb| b.extent().x * b.extent().z;
    let got = tlas.bounds();
    assert!(got.contains(&exact), "{got:?} does not hold {exact:?}");
    assert!(
        ground(got) < 1.1 * ground(exact),
        "instance box {got:?}, exact {exact:?}"
    );
}

#[test]
fn validate_rejects_corrupted_trees() {
    let mut rng = TestRng::new(77);
    let mesh = random_mesh(&mut rng, 500, 3.0, 0.3);
    let bounds = bounds_of(&mesh);
    let good = Bvh::build(&bounds, BuildParams::BALANCED);
    good.validate(&bounds).unwrap();

    let mut shrunk_wide = good.clone();
    shrunk_wide.wide[1].max_x = shrunk_wide.wide[1].min_x;
    assert!(
        shrunk_wide.validate(&bounds).is_err(),
        "a wide box too small to hold its primitives"
    );

    let mut duplicated = good.clone();
    duplicated.prim_indices[1] = duplicated.prim_indices[0];
    assert!(
        duplicated.validate(&bounds).is_err(),
        "a primitive referenced twice"
    );

    let mut cycle = good.clone();
    cycle.wide[0].children[0] = 0;
    cycle.wide[0].counts[0] = 0;
    assert!(
        cycle.validate(&bounds).is_err(),
        "a wide child pointing back at its parent"
    );

    let mut lost = good.clone();
    lost.prim_indices.pop();
    assert!(lost.validate(&bounds).is_err(), "a primitive left out");
}

#[test]
fn block_aligned_leaves_start_at_multiples_and_pad_only_their_ends() {
    let mut rng = TestRng::new(91);
    let mesh = random_mesh(&mut rng, 700, 3.0, 0.3);
    let bounds = bounds_of(&mesh);
    for block in [1, 3, 4] {
        let bvh = Bvh::build(
            &bounds,
            BuildParams {
                leaf_block: block,
                ..BuildParams::FAST
            },
        );
        bvh.validate(&bounds).unwrap();
        let padding = bvh.prim_indices.iter().filter(|&&p| p == PADDING).count();
        assert_eq!(bvh.prim_indices.len() - padding, 700, "block {block}");
        let mut owned = vec![false; bvh.prim_indices.len()];
        for node in bvh.wide.iter() {
            for lane in (0..WIDTH).filter(|&l| node.counts[l] > 0) {
                let (first, count) = (node.children[lane] as usize, node.counts[lane] as usize);
                assert_eq!(first % block, 0, "block {block}: leaf at slot {first}");
                owned[first..first + count].fill(true);
                // The slots after the leaf up to the next multiple are padding.
                let end = (first + count).next_multiple_of(block);
                assert!(
                    bvh.prim_indices[first + count..end]
                        .iter()
                        .all(|&p| p == PADDING)
                );
            }
        }
        let unowned = owned.iter().filter(|&&o| !o).count();
        assert_eq!(
            unowned, padding,
            "block {block}: padding is exactly the unowned slots"
        );
        if block == 1 {
            assert_eq!(padding, 0);
        }
    }

    // A leaf that claims a padding slot is corrupt.
    let padded = Bvh::build(
        &bounds,
        BuildParams {
            leaf_block: 4,
            ..BuildParams::FAST
        },
    );
    let (node, lane) = padded
        .wide
        .iter()
        .enumerate()
        .find_map(|(i, n)| {
            (0..WIDTH)
                .find(|&l| {
                    let (first, count) = (n.children[l] as usize, n.counts[l] as usize);
                    count > 0 && padded.prim_indices.get(first + count) == Some(&PADDING)
                })
                .map(|l| (i, l))
        })
        .expect("some leaf is followed by padding");
    let mut grown = padded.clone();
    grown.wide[node].counts[lane] += 1;
    assert!(
        grown.validate(&bounds).is_err(),
        "a wide leaf owning padding"
    );
}

/// Nodes whose lanes are all leaves, by their number of leaf lanes.
fn leaf_nodes_by_lanes(bvh: &Bvh) -> Vec<usize> {
    let mut nodes = vec![0; WIDTH + 1];
    for node in &bvh.wide {
        let leaves = (0..WIDTH).filter(|&l| node.counts[l] > 0).count();
        let used = (0..WIDTH).filter(|&l| node.is_used(l)).count();
        if leaves == used {
            nodes[leaves] += 1;
        }
    }
    nodes
}

#[test]
fn small_bottom_level_subtrees_fill_their_nodes() {
    // 64 boxes in a row: 16 leaves of four, a binary tree four levels deep. Opening
    // the widest lanes first gives a root of eight lanes over eight nodes of two
    // leaves; the bottom level's preset makes a root of two lanes over two nodes of
    // eight leaves, as deep and a third of the nodes.
    let row: Vec<Aabb> = (0..64)
        .map(|i| {
            let x = i as f32;
            Aabb::new(Vec3A::new(x, 0.0, 0.0), Vec3A::new(x + 0.5, 0.5, 0.5))
        })
        .collect();
    let greedy = BuildParams {
        fill_levels: 0,
        ..BuildParams::BOTTOM_LEVEL
    };
    let (filled, greedy) = (
        Bvh::build(&row, BuildParams::BOTTOM_LEVEL),
        Bvh::build(&row, greedy),
    );
    filled.validate(&row).unwrap();
    greedy.validate(&row).unwrap();
    assert_eq!(greedy.wide.len(), 9);
    assert_eq!(leaf_nodes_by_lanes(&greedy)[2], 8);
    assert_eq!(filled.wide.len(), 3);
    assert_eq!(leaf_nodes_by_lanes(&filled)[8], 2);
    // 40 boxes, 10 leaves: one half's five leaves fit beside the other half's lane, so
    // the root takes them and only the other half is a node of its own.
    let ten = Bvh::build(&row[..40], BuildParams::BOTTOM_LEVEL);
    ten.validate(&row[..40]).unwrap();
    assert_eq!(ten.wide.len(), 2);
    assert_eq!(leaf_nodes_by_lanes(&ten)[5], 1);
    // Larger trees: every leaf still reached by the rays that reach it without the rule.
    let mut rng = TestRng::new(17);
    let mesh = random_mesh(&mut rng, 5_000, 10.0, 0.3);
    let rays: Vec<Ray> = (0..300).map(|_| random_ray(&mut rng, 12.0)).collect();
    check_mesh_against_brute_force(mesh, &rays, BuildParams::BOTTOM_LEVEL);
}

#[test]
fn clustered_top_level_trees_give_every_primitive_a_lane_and_stay_as_good() {
    let mut rng = TestRng::new(17);
    let bounds = bounds_of(&random_mesh(&mut rng, 3000, 20.0, 0.5));
    let unclustered = BuildParams {
        lane_cluster: 1,
        ..BuildParams::TOP_LEVEL
    };
    let (clustered, plain) = (
        Bvh::build(&bounds, BuildParams::TOP_LEVEL),
        Bvh::build(&bounds, unclustered),
    );
    clustered.validate(&bounds).unwrap();
    let leaf_lanes = |bvh: &Bvh| {
        bvh.wide
            .iter()
            .flat_map(|n| (0..WIDTH).filter(|&l| n.counts[l] > 0).map(|l| n.counts[l]))
            .collect::<Vec<u32>>()
    };
    assert!(leaf_lanes(&clustered).iter().all(|&c| c == 1));
    assert_eq!(leaf_lanes(&clustered).len(), 3000);
    // Clusters of up to eight fill the lanes: fewer nodes than leaves of one make.
    assert!(
        clustered.wide.len() < plain.wide.len(),
        "{} nodes clustered, {} not",
        clustered.wide.len(),
        plain.wide.len()
    );
    // The wide trees cost rays about the same: the surface-area cost of their nodes.
    let node_cost = |bvh: &Bvh| {
        bvh.wide
            .iter()
            .flat_map(|n| {
                (0..WIDTH)
                    .filter(|&l| n.is_used(l) && n.counts[l] == 0)
                    .map(|l| n.child_bounds(l))
            })
            .map(|b| f64::from(b.surface_area()))
            .sum::<f64>()
    };
    let ratio = node_cost(&clustered) / node_cost(&plain);
    assert!((0.9..1.1).contains(&ratio), "node cost ratio {ratio}");
}

/// Above [`GRID_FROM`] primitives the top level splits between grid cells first, and
/// so does the bottom level above [`BOTTOM_GRID_FROM`] (here from `GRID_FROM` on, to
/// keep the brute force short): that path runs (its tree differs from the one without
/// cells), and its hits equal brute force, for triangles spread over a plane as plants
/// and terrains are and over a volume.
#[test]
fn grid_cell_trees_match_brute_force() {
    let mut rng = TestRng::new(41);
    let n = GRID_FROM + 5_000;
    let flat = {
        let mut mesh = random_mesh(&mut rng, n, 60.0, 0.8);
        for p in &mut mesh.positions {
            p.y *= 0.05;
        }
        mesh
    };
    let volume = random_mesh(&mut rng, n, 20.0, 0.8);
    let bottom = BuildParams {
        grid_from: GRID_FROM,
        ..BuildParams::BOTTOM_LEVEL
    };
    for (level, params) in [("top", BuildParams::TOP_LEVEL), ("bottom", bottom)] {
        let without_cells = BuildParams {
            grid_cell: 0,
            ..params
        };
        for (name, mesh) in [("flat", &flat), ("volume", &volume)] {
            let bounds = bounds_of(mesh);
            let (gridded, plain) = (
                Bvh::build(&bounds, params),
                Bvh::build(&bounds, without_cells),
            );
            gridded.validate(&bounds).unwrap();
            assert_ne!(
                gridded.content_hash(),
                plain.content_hash(),
                "{level} level, {name}: no cells made"
            );
            let rays: Vec<Ray> = (0..400).map(|_| random_ray(&mut rng, 70.0)).collect();
            check_mesh_against_brute_force(mesh.clone(), &rays, params);
            // Boxes that cannot be hit are left out on the way into the cells, and every
            // other primitive is held once.
            let mut with_unusable = bounds.clone();
            let unusable = [3, 4_000, n - 1];
            with_unusable[unusable[0]] = Aabb::EMPTY;
            with_unusable[unusable[1]].max.y = f32::NAN;
            with_unusable[unusable[2]].min.z = f32::NEG_INFINITY;
            let gridded = Bvh::build(&with_unusable, params);
            gridded.validate(&with_unusable).unwrap();
            let held = gridded
                .prim_indices
                .iter()
                .filter(|&&p| p != PADDING)
                .count();
            assert_eq!(
                held,
                n - unusable.len(),
                "{level} level, {name}: primitives held"
            );
            for slot in unusable {
                assert!(!gridded.prim_indices.contains(&(slot as u32)));
            }
        }
    }
    // The preset itself: cells from BOTTOM_GRID_FROM triangles on, none below.
    let terrain = bounds_of(&random_mesh(&mut rng, BOTTOM_GRID_FROM, 300.0, 0.8));
    for (n, cells) in [(BOTTOM_GRID_FROM, true), (BOTTOM_GRID_FROM - 1, false)] {
        let plain = BuildParams {
            grid_cell: 0,
            ..BuildParams::BOTTOM_LEVEL
        };
        let (preset, plain) = (
            Bvh::build(&terrain[..n], BuildParams::BOTTOM_LEVEL),
            Bvh::build(&terrain[..n], plain),
        );
        assert_eq!(preset.content_hash() != plain.content_hash(), cells, "{n}");
    }
}

/// `n` blades: triangles a metre long and two centimetres wide, half of them slanted at
/// random, half lying along an axis, inside a cube of half-width `extent`.
fn blades(rng: &mut TestRng, n: usize, extent: f32) -> TriangleMesh {
    let mut mesh = TriangleMesh::default();
    for i in 0..n {
        let base = Vec3A::from(rng.vec3(-extent, extent));
        let (along, across) = if i % 2 == 0 {
            let along = Vec3A::from(rng.unit());
            (along, along.any_orthonormal_vector())
        } else {
            (Vec3A::Y, Vec3A::X)
        };
        for corner in [base, base + 0.02 * across, base + along + 0.01 * across] {
            mesh.positions.push(corner.into());
        }
        let first = 3 * i as u32;
        mesh.indices.push([first, first + 1, first + 2]);
        mesh.shaders.push(0);
    }
    mesh
}

/// The bottom level's preset cuts long slanted triangles in two before its build:
/// rays aimed at their corners, edges and cut lines still find every hit a brute force
/// finds, and rays through a field of blades test fewer triangles than without the cut.
#[test]
fn slanted_blades_are_built_from_their_halves() {
    let mut rng = TestRng::new(59);
    let mesh = blades(&mut rng, 400, 1.0);
    let boxes = triangle_boxes(&mesh, BuildParams::BOTTOM_LEVEL.split_ratio);
    let cut: Vec<u32> = (0..400)
        .filter(|&t| boxes.owners.iter().filter(|&&o| o == t).count() == 2)
        .collect();
    assert!(
        cut.len() > 150,
        "only {} of 200 slanted blades cut",
        cut.len()
    );
    assert!(
        cut.iter().all(|&t| t % 2 == 0),
        "an axis-aligned blade was cut"
    );
    for (primitive, half) in boxes.boxes.iter().enumerate() {
        let whole = mesh.triangle_bounds(boxes.owner(primitive as u32) as usize);
        assert!(
            whole.contains(half),
            "a half's box leaves its triangle's box"
        );
    }
    // Targets on the cut triangles: corners, edge points, and points spread over the
    // surface (the cut runs through the middle).
    let mut rays = Vec::new();
    for &t in &cut {
        let [a, b, c] = mesh.triangle(t as usize);
        let mut targets = vec![a, b, c, (a + b) * 0.5, (b + c) * 0.5, (c + a) * 0.5];
        for _ in 0..12 {
            let (u, v) = (rng.f32(), rng.f32());
            let (u, v) = if u + v > 1.0 {
                (1.0 - u, 1.0 - v)
            } else {
                (u, v)
            };
            targets.push(a + (b - a) * u + (c - a) * v);
        }
        for target in targets {
            let origin = target + Vec3A::from(rng.unit()) * rng.range(0.5, 5.0);
            rays.push(Ray::new(origin, (target - origin).normalize()));
        }
    }
    check_mesh_against_brute_force(mesh.clone(), &rays, BuildParams::BOTTOM_LEVEL);
    let uncut = BuildParams {
        split_ratio: 0.0,
        ..BuildParams::BOTTOM_LEVEL
    };
    // Rays across the field, most passing between blades.
    let across: Vec<Ray> = (0..20_000).map(|_| random_ray(&mut rng, 1.5)).collect();
    let tests = |params: BuildParams| {
        let geometry = Geometry::new("blades", mesh.clone(), params).unwrap();
        let mut stats = TraversalStats::default();
        for ray in &across {
            geometry.intersect_any(ray, &mut stats, |_, _| true);
        }
        stats.primitive_tests as f64 / across.len() as f64
    };
    let (with_cuts, without) = (tests(BuildParams::BOTTOM_LEVEL), tests(uncut));
    eprintln!("triangle slots tested per ray: {with_cuts:.1} cut, {without:.1} whole");
    assert!(
        with_cuts < 0.85 * without,
        "cutting did not make rays test fewer triangles ({with_cuts:.1} against {without:.1})"
    );
}
