//! Watertightness at scale: about 10⁷ rays from points inside a closed, jittered sphere
//! aimed exactly at its vertices and at points on its edges, with the sphere at the
//! origin and 1.5·10⁵ m away. Prints the leaks (rays that found no triangle) per place.
//! Run: `cargo bench --bench leaks`.

use glam::{Affine3A, Quat, Vec3, Vec3A};
use rayon::prelude::*;
use std::time::Instant;
use sylva::engine::bvh::{BuildParams, TraversalStats};
use sylva::engine::geometry::{Geometry, GeometryId, GeometryLibrary};
use sylva::engine::math::Ray;
use sylva::engine::mesh::TriangleMesh;
use sylva::engine::sampling::SplitMix64;
use sylva::engine::tlas::{InstanceDesc, TopLevel};

fn main() {
    let mesh = TriangleMesh::jittered_sphere(200, 400, 0.1, 7);
    let mut targets: Vec<Vec3A> = mesh.positions.iter().map(|&p| p.into()).collect();
    for tri in &mesh.indices {
        for k in 0..3 {
            let a = Vec3A::from(mesh.positions[tri[k] as usize]);
            let b = Vec3A::from(mesh.positions[tri[(k + 1) % 3] as usize]);
            for s in [0.5, 0.25, 1.0 / 3.0] {
                targets.push(a.lerp(b, s));
            }
        }
    }
    let mut library = GeometryLibrary::default();
    library.add(Geometry::new("sphere", mesh, BuildParams::BALANCED).expect("a valid mesh"));
    let mut rng = SplitMix64(3);
    let origins: Vec<Vec3A> = (0..7)
        .map(|_| {
            Vec3A::new(
                rng.range(-0.4, 0.4),
                rng.range(-0.4, 0.4),
                rng.range(-0.4, 0.4),
            )
        })
        .collect();
    let rotation = Quat::from_scaled_axis(Vec3::new(0.4, 1.1, -0.3));
    for (place, translation) in [
        ("at the origin", Vec3::ZERO),
        ("at 1.5e5 m", Vec3::new(1.5e5, 30.0, -1.5e5)),
    ] {
        let transform = Affine3A::from_rotation_translation(rotation, translation);
        let top_level = TopLevel::build(
            &library,
            &[InstanceDesc {
                transform,
                geometry: GeometryId(0),
            }],
            BuildParams::BALANCED,
        );
        let start = Instant::now();
        let (rays, leaks) = origins
            .iter()
            .map(|&o| {
                let origin = transform.transform_point3a(o);
                let leaks = targets
                    .par_iter()
                    .filter(|&&t| {
                        let target = transform.transform_point3a(t);
                        let ray = Ray::new(origin, target - origin);
                        top_level
                            .intersect_closest(
                                &library,
                                &ray,
                                &mut TraversalStats::default(),
                                |_| true,
                            )
                            .is_none()
                    })
                    .count();
                (targets.len(), leaks)
            })
            .fold((0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
        println!(
            "{place}: {leaks} leaks out of {rays} edge and vertex rays ({:.1} s)",
            start.elapsed().as_secs_f64()
        );
    }
}
