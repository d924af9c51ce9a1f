//! Ray throughput on the default scene at 640×480 (primary closest-hit, sun shadow
//! any-hit, incoherent diffuse-bounce closest-hit) and the time of a full 4 spp frame,
//! on a 2-thread pool; and the discontinuity filter over that frame's pixels, as an
//! interactive frame shows them.

mod support;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use std::time::Duration;
use support::{BenchScene, count_rays, two_thread_pool};
use sylva::engine::discontinuity::{DiscontinuityFilter, GuidedImage};
use sylva::engine::render::{RenderParams, render_frame};

fn rays(c: &mut Criterion) {
    let bench = BenchScene::meadow();
    let pool = two_thread_pool();
    let scene = bench.scene();
    let primary = bench.primary_rays();
    let shadow = pool.install(|| bench.shadow_rays());
    let incoherent = pool.install(|| bench.incoherent_rays());
    let mut group = c.benchmark_group("meadow_640x480_2_threads");
    group
        .sample_size(20)
        .measurement_time(Duration::from_secs(8));
    group.throughput(Throughput::Elements(primary.len() as u64));
    group.bench_function("primary_closest_hit_rays", |b| {
        b.iter(|| {
            pool.install(|| count_rays(&primary, |r, stats| scene.closest(r, stats).is_some()))
        })
    });
    group.throughput(Throughput::Elements(shadow.len() as u64));
    group.bench_function("sun_shadow_any_hit_rays", |b| {
        b.iter(|| pool.install(|| count_rays(&shadow, |r, stats| scene.occluded(r, stats))))
    });
    group.throughput(Throughput::Elements(incoherent.len() as u64));
    group.bench_function("incoherent_closest_hit_rays", |b| {
        b.iter(|| {
            pool.install(|| count_rays(&incoherent, |r, stats| scene.closest(r, stats).is_some()))
        })
    });
    group.finish();

    let mut group = c.benchmark_group("meadow_frame_640x480");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(20));
    let params = RenderParams {
        samples_per_pixel: 4,
        light_samples: 2,
        ..RenderParams::default()
    };
    group.bench_function("render_4spp_2_threads", |b| {
        b.iter(|| pool.install(|| render_frame(&scene, &bench.view, &params, 0, &|_| {})))
    });
    group.finish();

    // One frame's surfaces, albedo and radiance at 1 spp, the interactive preset's
    // sampling, for the filter that shows it.
    let frame = pool.install(|| {
        render_frame(
            &scene,
            &bench.view,
            &RenderParams {
                samples_per_pixel: 1,
                light_samples: 1,
                ..RenderParams::default()
            },
            0,
            &|_| {},
        )
    });
    let (radiance, albedo, emission) = (frame.mean(), frame.mean_albedo(), frame.mean_emission());
    let image = GuidedImage {
        width: frame.width,
        height: frame.height,
        radiance: &radiance,
        albedo: &albedo,
        emission: &emission,
        surfaces: &frame.pixels.surfaces,
    };
    let filter = DiscontinuityFilter::for_pattern(4);
    let mut group = c.benchmark_group("meadow_display_640x480");
    group.sample_size(30);
    group.throughput(Throughput::Elements(radiance.len() as u64));
    group.bench_function("discontinuity_filter_4x4_2_threads", |b| {
        b.iter(|| pool.install(|| filter.apply(&image)))
    });
    group.finish();
}

criterion_group!(benches, rays);
criterion_main!(benches);
