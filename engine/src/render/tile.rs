//! Rendering tiles and frames: a tile's camera rays traced in packets and shaded
//! pixel by pixel into [`PixelSums`], a frame's tiles in
//! parallel on the rayon pool, optionally given up when a cancel flag is set.

use super::camera::CameraView;
use super::plan::{RenderParams, SampleShading};
use super::scene::{PacketScratch, RenderScene};
use crate::accel::bvh::PACKET;
use crate::accel::occluders::OccluderCache;
use crate::film::{FrameBuffer, PixelSums, Tile, TileResult};
use crate::util::sampling::SampleKey;
use crate::util::stats::TraversalStats;
use glam::{Vec2, Vec3};
use rayon::prelude::*;

/// Renders one tile of frame `frame`. Deterministic: depends only on its arguments.
pub fn render_tile(
    scene: &RenderScene,
    view: &CameraView,
    params: &RenderParams,
    tile: Tile,
    frame: u32,
) -> TileResult {
    let _span = tracing::trace_span!("render_tile", x = tile.x, y = tile.y).entered();
    let mut result = TileResult {
        tile,
        pixels: PixelSums::new(tile.pixel_count()),
        rejected: 0,
        stats: TraversalStats::default(),
    };
    let spp = params.samples_per_pixel;
    let mut shading = SampleShading {
        transparency: params.transparency,
        bounces: params.bounces,
        ..SampleShading::plain(params.light_samples)
    };
    // One per tile, starting empty: its counters then do not depend on which thread
    // rendered which tile before.
    let mut occluders = OccluderCache::new();
    let curve = shading.transparency.as_ref();
    // The camera rays of up to PACKET consecutive samples of a row share one top-level
    // walk; the samples are still shaded in the order of a walk of their own (pixel by
    // pixel along the row), which keeps each one's shadow rays near the last ones' in
    // memory (ordering them in square blocks instead cost more than the packets saved).
    let mut rays = Vec::with_capacity(PACKET);
    let mut samples = Vec::with_capacity(PACKET);
    let mut scratch = PacketScratch::default();
    let mut row = Vec::with_capacity(tile.width as usize * spp as usize);
    for y in tile.y..tile.y + tile.height {
        row.clear();
        row.extend(
            (tile.x..tile.x + tile.width).flat_map(|x| (0..spp).map(move |sample| (x, y, sample))),
        );
        for chunk in row.chunks(PACKET) {
            samples.clear();
            rays.clear();
            for &(x, y, sample) in chunk {
                let key = SampleKey::new(params.seed, x, y, frame, sample);
                let film = Vec2::new(x as f32, y as f32) + key.get2(0);
                rays.push(view.ray(film, key.get2(2)));
                samples.push(key);
            }
            let primaries = scene.closest_packet(&rays, curve, &mut scratch, &mut result.stats);
            for (i, &(x, y, sample)) in chunk.iter().enumerate() {
                shading.light_subset = params
                    .light_subsets
                    .map(|subsets| (subsets, subsets.subset(x, y, frame, sample, spp)));
                let (ray, key) = (&rays[i], &samples[i]);
                let shaded = match &primaries {
                    Some(primaries) => scene.shade_primary(
                        ray,
                        primaries[i],
                        key,
                        &shading,
                        &mut occluders,
                        &mut result.stats,
                    ),
                    None => scene.shade_with(ray, key, &shading, &mut occluders, &mut result.stats),
                };
                let pixel = ((y - tile.y) * tile.width + (x - tile.x)) as usize;
                let radiance = Vec3::from(shaded.radiance);
                // The NaN firewall: a bad sample is counted and dropped, never averaged.
                if radiance.is_finite() {
                    result.pixels.add_sample(
                        pixel,
                        radiance,
                        Vec3::from(shaded.albedo),
                        Vec3::from(shaded.emission),
                        shaded.surface,
                    );
                } else {
                    result.rejected += 1;
                }
            }
        }
    }
    result
}

/// Renders a whole frame, tiles in parallel on the current rayon pool; `on_tile` is
/// called once per finished tile (progress reporting).
pub fn render_frame(
    scene: &RenderScene,
    view: &CameraView,
    params: &RenderParams,
    frame: u32,
    on_tile: &(dyn Fn(&Tile) + Sync),
) -> FrameBuffer {
    render_frame_unless(scene, view, params, frame, &|tile, _| on_tile(tile), None)
        .expect("a frame without a cancel flag completes")
}

/// [`render_frame`] that gives up when `cancel` is set: tiles not yet started are
/// skipped and `None` is returned (a window's input cancels a frame that would only show
/// the old view). `on_tile` is also given the tile's render time (profiles).
pub fn render_frame_unless(
    scene: &RenderScene,
    view: &CameraView,
    params: &RenderParams,
    frame: u32,
    on_tile: &(dyn Fn(&Tile, std::time::Duration) + Sync),
    cancel: Option<&std::sync::atomic::AtomicBool>,
) -> Option<FrameBuffer> {
    use std::sync::atomic::Ordering;
    let cancelled = || cancel.is_some_and(|flag| flag.load(Ordering::Relaxed));
    let tiles = Tile::grid(view.width(), view.height(), params.tile_size);
    let results: Vec<Option<TileResult>> = tiles
        .par_iter()
        .map(|&tile| {
            if cancelled() {
                return None;
            }
            let start = std::time::Instant::now();
            let result = render_tile(scene, view, params, tile, frame);
            on_tile(&tile, start.elapsed());
            Some(result)
        })
        .collect();
    let mut frame_buffer = FrameBuffer::new(view.width(), view.height(), frame);
    for result in &results {
        frame_buffer.write_tile(result.as_ref()?);
    }
    Some(frame_buffer)
}
