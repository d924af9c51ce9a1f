//! BVH build speed: a 1 M-triangle BLAS, and the TLAS over 10 k, 100 k and 365 k
//! instances (the paper's count), built fresh, rebuilt in place and refitted, on a
//! 2-thread pool.

mod support;

use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use glam::{Affine3A, Quat, Vec3};
use std::time::Duration;
use sylva::engine::bvh::{BuildParams, Bvh};
use sylva::engine::geometry::GeometryId;
use sylva::engine::math::Aabb;
use sylva::engine::tlas::{InstanceDesc, TopLevel};
use sylva::scenes::random::SceneRng;
use sylva::scenes::terrain::{HeightField, TerrainParams};

fn blas(c: &mut Criterion) {
    let pool = support::two_thread_pool();
    // 708² cells × 2 = 1,002,528 triangles of rolling terrain.
    let mesh = HeightField::fbm(
        1,
        &TerrainParams {
            size: 300.0,
            cells: 708,
            amplitude: 10.0,
            wavelength: 80.0,
            octaves: 6,
            ridged: false,
        },
    )
    .to_mesh(0, 4.0);
    let bounds: Vec<Aabb> = (0..mesh.triangle_count())
        .map(|i| mesh.triangle_bounds(i))
        .collect();
    let mut group = c.benchmark_group("blas_build_1M_triangles");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(15));
    group.throughput(Throughput::Elements(bounds.len() as u64));
    for (name, params) in BuildParams::PRESETS {
        group.bench_function(name, |b| {
            b.iter(|| pool.install(|| Bvh::build(&bounds, params)))
        });
    }
    group.finish();
}

fn tlas(c: &mut Criterion) {
    let pool = support::two_thread_pool();
    let meadow = sylva::scenes::build_scene("meadow", 0).unwrap();
    let species: Vec<GeometryId> = meadow.species.iter().map(|s| s.geometry).collect();
    let mut group = c.benchmark_group("tlas_build");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(10));
    for count in [10_000usize, 100_000, 365_041] {
        let mut rng = SceneRng::new(7, "bench");
        let descs: Vec<InstanceDesc> = (0..count)
            .map(|_| InstanceDesc {
                transform: Affine3A::from_scale_rotation_translation(
                    Vec3::splat(rng.range(0.6, 1.6)),
                    Quat::from_rotation_y(rng.range(0.0, 6.3)),
                    Vec3::new(
                        rng.range(-150.0, 150.0),
                        rng.range(0.0, 5.0),
                        rng.range(-150.0, 150.0),
                    ),
                ),
                geometry: species[rng.below(species.len() as u32) as usize],
            })
            .collect();
        group.throughput(Throughput::Elements(count as u64));
        group.bench_with_input(BenchmarkId::new("build", count), &descs, |b, descs| {
            b.iter(|| {
                pool.install(|| TopLevel::build(&meadow.library, descs, BuildParams::TOP_LEVEL))
            })
        });
        // A rebuild into the memory of an earlier build, as the schedule rebuilds.
        group.bench_with_input(BenchmarkId::new("rebuild", count), &descs, |b, descs| {
            let mut top_level =
                pool.install(|| TopLevel::build(&meadow.library, descs, BuildParams::TOP_LEVEL));
            b.iter(|| {
                pool.install(|| top_level.rebuild(&meadow.library, descs, BuildParams::TOP_LEVEL))
            })
        });
        // A refit to the same instances each tilted by 0.1 rad about its base.
        let tilted: Vec<InstanceDesc> = descs
            .iter()
            .map(|d| InstanceDesc {
                transform: Affine3A::from_translation(d.transform.translation.into())
                    * Affine3A::from_rotation_x(0.1)
                    * Affine3A::from_translation(-Vec3::from(d.transform.translation))
                    * d.transform,
                ..*d
            })
            .collect();
        let built =
            pool.install(|| TopLevel::build(&meadow.library, &descs, BuildParams::TOP_LEVEL));
        group.bench_with_input(BenchmarkId::new("refit", count), &tilted, |b, tilted| {
            let mut top_level = built.clone();
            b.iter(|| pool.install(|| top_level.refit(&meadow.library, tilted).unwrap()))
        });
    }
    group.finish();
}

criterion_group!(benches, blas, tlas);
criterion_main!(benches);
