//! Shared helpers for the engine's integration tests: a seeded generator, random
//! meshes and rays, and brute-force oracles.

#![allow(
    dead_code,
    missing_docs,
    reason = "each test binary uses a part of these helpers"
)]

use glam::{Affine3A, Quat, Vec3, Vec3A};
use sylva_engine::bvh::{BuildParams, TraversalStats};
use sylva_engine::geometry::{Geometry, GeometryLibrary};
use sylva_engine::math::Ray;
use sylva_engine::mesh::TriangleMesh;
use sylva_engine::sampling::SplitMix64;
use sylva_engine::tlas::{InstanceDesc, TopLevel};
use sylva_engine::triangle::WatertightRay;

/// The engine's SplitMix64 with the vector helpers tests need.
pub struct TestRng(SplitMix64);

impl TestRng {
    pub fn new(seed: u64) -> Self {
        Self(SplitMix64(seed))
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0.next_u64()
    }
    pub fn f32(&mut self) -> f32 {
        self.0.f32()
    }
    pub fn range(&mut self, lo: f32, hi: f32) -> f32 {
        self.0.range(lo, hi)
    }
    pub fn vec3(&mut self, lo: f32, hi: f32) -> Vec3 {
        Vec3::new(self.range(lo, hi), self.range(lo, hi), self.range(lo, hi))
    }
    pub fn unit(&mut self) -> Vec3 {
        loop {
            let v = self.vec3(-1.0, 1.0);
            let l = v.length();
            if l > 1e-3 && l <= 1.0 {
                return v / l;
            }
        }
    }
}

/// `n` random triangles of size up to `size` inside a cube of half-width `extent`.
pub fn random_mesh(rng: &mut TestRng, n: usize, extent: f32, size: f32) -> TriangleMesh {
    let mut mesh = TriangleMesh::default();
    for i in 0..n {
        let c = rng.vec3(-extent, extent);
        for _ in 0..3 {
            mesh.positions.push(c + rng.vec3(-size, size));
        }
        let b = 3 * i as u32;
        mesh.indices.push([b, b + 1, b + 2]);
        mesh.shaders.push(0);
    }
    mesh
}

/// A random ray starting inside a cube of half-width `extent`.
pub fn random_ray(rng: &mut TestRng, extent: f32) -> Ray {
    Ray::new(rng.vec3(-extent, extent).into(), rng.unit().into())
}

/// Closest (t, triangle) over all triangles, testing each with the engine's own
/// watertight test.
pub fn brute_closest(
    mesh: &TriangleMesh,
    ray: &Ray,
    accept: impl Fn(u32) -> bool,
) -> Option<(f32, u32)> {
    let w = WatertightRay::new(ray);
    let mut best: Option<(f32, u32)> = None;
    for i in 0..mesh.triangle_count() {
        let [a, b, c] = mesh.triangle(i);
        let t_max = best.map_or(ray.t_max, |b| b.0);
        if let Some(h) = w.intersect(a, b, c, t_max)
            && accept(i as u32)
        {
            best = Some((h.t, i as u32));
        }
    }
    best
}

/// Closest (t, instance, triangle) over all instances and triangles.
pub fn brute_closest_instances(
    lib: &GeometryLibrary,
    instances: &[InstanceDesc],
    ray: &Ray,
) -> Option<(f32, u32, u32)> {
    let mut best: Option<(f32, u32, u32)> = None;
    for (i, inst) in instances.iter().enumerate() {
        if inst.transform.matrix3.determinant() == 0.0 {
            continue;
        }
        let local = Ray {
            t_max: best.map_or(ray.t_max, |b| b.0),
            ..ray.transformed(&inst.transform.inverse())
        };
        let mesh = &lib.geometries[inst.geometry.0 as usize].mesh;
        if let Some((t, tri)) = brute_closest(mesh, &local, |_| true) {
            best = Some((t, i as u32, tri));
        }
    }
    best
}

/// Asserts that `tlas` finds, for every ray, the closest hit and the any-hit answer of a
/// brute force over `descs`; returns how many rays hit something.
pub fn assert_tlas_matches_brute_force(
    lib: &GeometryLibrary,
    tlas: &TopLevel,
    descs: &[InstanceDesc],
    rays: &[Ray],
    label: &str,
) -> usize {
    let mut stats = TraversalStats::default();
    let mut hits = 0;
    for ray in rays {
        let expected = brute_closest_instances(lib, descs, ray);
        let got = tlas.intersect_closest(lib, ray, &mut stats, |_| true);
        assert_eq!(
            got.map(|h| h.t),
            expected.map(|e| e.0),
            "{label}: closest t for {ray:?}"
        );
        if let (Some(g), Some(e)) = (got, expected) {
            assert!(g.instance == e.1 || g.t == e.0);
        }
        assert_eq!(
            tlas.intersect_any(lib, ray, &mut stats, |_| true),
            expected.is_some(),
            "{label}: any-hit for {ray:?}"
        );
        hits += usize::from(expected.is_some());
    }
    assert_eq!(stats.closest_rays, rays.len() as u64);
    hits
}

/// `geometries` random meshes of 1 ..= `max_triangles` triangles each, named g0, g1, ….
pub fn random_library(rng: &mut TestRng, geometries: usize, max_triangles: u64) -> GeometryLibrary {
    let mut lib = GeometryLibrary::default();
    for g in 0..geometries {
        let n = 1 + (rng.next_u64() % max_triangles) as usize;
        lib.add(
            Geometry::new(
                format!("g{g}"),
                random_mesh(rng, n, 1.0, 0.4),
                BuildParams::BALANCED,
            )
            .unwrap(),
        );
    }
    lib
}

/// `count` instances of random geometries of `geometries`, placed by [`random_transform`]
/// within 20 units of the origin.
pub fn random_instances(
    rng: &mut TestRng,
    count: usize,
    geometries: usize,
    log_scale: (f32, f32),
) -> Vec<InstanceDesc> {
    (0..count)
        .map(|_| InstanceDesc {
            transform: random_transform(rng, 20.0, log_scale),
            geometry: sylva_engine::geometry::GeometryId(
                (rng.next_u64() % geometries as u64) as u32,
            ),
        })
        .collect()
}

/// A random instance transform with scales in `[10^lo, 10^hi]`.
pub fn random_transform(rng: &mut TestRng, extent: f32, log_scale: (f32, f32)) -> Affine3A {
    let s = 10f32.powf(rng.range(log_scale.0, log_scale.1));
    let rot = Quat::from_scaled_axis(rng.unit() * rng.range(0.0, 3.1));
    let scale = Vec3::new(
        s * rng.range(0.5, 2.0),
        s * rng.range(0.5, 2.0),
        s * rng.range(0.5, 2.0),
    );
    Affine3A::from_scale_rotation_translation(scale, rot, rng.vec3(-extent, extent))
}

/// A point in a random direction from `Vec3A::ZERO` at distance `d`.
pub fn on_sphere(rng: &mut TestRng, d: f32) -> Vec3A {
    Vec3A::from(rng.unit()) * d
}

/// A 100 m × 100 m plane at y = 0 facing +Y (shader 0), instanced once.
pub fn ground_plane() -> (GeometryLibrary, TopLevel) {
    let mut library = GeometryLibrary::default();
    let plane = TriangleMesh {
        positions: vec![
            Vec3::new(-50.0, 0.0, -50.0),
            Vec3::new(50.0, 0.0, -50.0),
            Vec3::new(50.0, 0.0, 50.0),
            Vec3::new(-50.0, 0.0, 50.0),
        ],
        indices: vec![[0, 2, 1], [0, 3, 2]],
        shaders: vec![0, 0],
        ..Default::default()
    };
    let id = library.add(Geometry::new("plane", plane, BuildParams::BALANCED).unwrap());
    let top_level = TopLevel::build(
        &library,
        &[InstanceDesc {
            transform: Affine3A::IDENTITY,
            geometry: id,
        }],
        BuildParams::BALANCED,
    );
    (library, top_level)
}

/// Mean and standard error per channel of `sample(k)` over `k = 0 .. n`.
pub fn mean_and_error(n: u32, mut sample: impl FnMut(u32) -> Vec3) -> (Vec3, Vec3) {
    let (mut sum, mut sum_sq) = (Vec3::ZERO, Vec3::ZERO);
    for k in 0..n {
        let v = sample(k);
        sum += v;
        sum_sq += v * v;
    }
    let mean = sum / n as f32;
    let error = ((sum_sq / n as f32 - mean * mean).max(Vec3::ZERO) / n as f32).powf(0.5);
    (mean, error)
}

/// Asserts that an estimate `(mean, error)` agrees with `expected` within four standard
/// errors plus `slack` (per channel); `what` names the case in the failure message.
pub fn assert_within_four_sigma(
    (mean, error): (Vec3, Vec3),
    expected: Vec3,
    slack: f32,
    what: &str,
) {
    assert!(
        ((mean - expected).abs() - 4.0 * error).max_element() <= slack,
        "{what}: {mean} ± {error} against {expected}"
    );
}
