//! BVH closest hit against brute force over arbitrary triangle soups and rays (raw float
//! bits, so NaN and ∞ too): the same distance, finite hits, no panic.
#![no_main]
use glam::{Vec3, Vec3A};
use libfuzzer_sys::fuzz_target;
use sylva_engine::bvh::{BuildParams, TraversalStats};
use sylva_engine::geometry::Geometry;
use sylva_engine::math::Ray;
use sylva_engine::mesh::TriangleMesh;
use sylva_engine::triangle::WatertightRay;

fuzz_target!(|data: &[u8]| {
    let floats: Vec<f32> = data
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    if floats.len() < 15 {
        return;
    }
    let (ray_part, soup) = floats.split_at(6);
    let mut mesh = TriangleMesh::default();
    for (i, t) in soup.chunks_exact(9).take(64).enumerate() {
        for k in 0..3 {
            mesh.positions.push(Vec3::new(t[3 * k], t[3 * k + 1], t[3 * k + 2]));
        }
        let b = 3 * i as u32;
        mesh.indices.push([b, b + 1, b + 2]);
        mesh.shaders.push(0);
    }
    let Ok(geometry) = Geometry::new("fuzz", mesh, BuildParams::BALANCED) else {
        return;
    };
    let ray = Ray::new(
        Vec3A::new(ray_part[0], ray_part[1], ray_part[2]),
        Vec3A::new(ray_part[3], ray_part[4], ray_part[5]),
    );
    let got = geometry.intersect_closest(&ray, &mut TraversalStats::default(), |_, _| true);
    let w = WatertightRay::new(&ray);
    let mut best: Option<f32> = None;
    for i in 0..geometry.mesh.triangle_count() {
        let [a, b, c] = geometry.mesh.triangle(i);
        if let Some(h) = w.intersect(a, b, c, best.unwrap_or(ray.t_max)) {
            best = Some(h.t);
        }
    }
    assert_eq!(got.map(|h| h.hit.t), best, "{ray:?}");
    if let Some(h) = got {
        assert!(h.hit.t.is_finite() && h.hit.barycentrics.is_finite());
    }
});
