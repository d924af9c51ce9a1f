//! One frame's pixels: the tiles a frame is cut into, the per-pixel sample sums a tile
//! renders and a frame assembles ([`PixelSums`]), and the surface each pixel saw
//! ([`SurfaceGuide`], the G-buffer the display filter reads).

use crate::util::stats::TraversalStats;
use bevy_ecs::component::Component;
use glam::Vec3;

/// A rectangle of pixels rendered as one unit of work.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Tile {
    /// Left column.
    pub x: u32,
    /// Top row.
    pub y: u32,
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
}

impl Tile {
    /// Tiles of `size`×`size` covering a `width`×`height` image, row by row.
    pub fn grid(width: u32, height: u32, size: u32) -> Vec<Tile> {
        let size = size.max(1);
        let mut tiles = Vec::new();
        for y in (0..height).step_by(size as usize) {
            for x in (0..width).step_by(size as usize) {
                tiles.push(Tile {
                    x,
                    y,
                    width: size.min(width - x),
                    height: size.min(height - y),
                });
            }
        }
        tiles
    }

    /// Pixels in the tile.
    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }
}

/// Per-pixel sums of one frame's accepted samples, row-major: what a tile renders, a
/// frame assembles and the cluster's wire carries.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PixelSums {
    /// Sum of accepted radiance samples per pixel.
    pub sums: Vec<Vec3>,
    /// Accepted samples per pixel.
    pub counts: Vec<u32>,
    /// Sum of the accepted samples' albedos per pixel.
    pub albedo_sums: Vec<Vec3>,
    /// Sum of the accepted samples' emitted radiance per pixel (part of `sums`).
    pub emission_sums: Vec<Vec3>,
    /// The surface of each pixel's first accepted sample.
    pub surfaces: Vec<SurfaceGuide>,
}

impl PixelSums {
    /// `pixels` pixels without a sample.
    pub fn new(pixels: usize) -> Self {
        Self {
            sums: vec![Vec3::ZERO; pixels],
            counts: vec![0; pixels],
            albedo_sums: vec![Vec3::ZERO; pixels],
            emission_sums: vec![Vec3::ZERO; pixels],
            surfaces: vec![SurfaceGuide::NONE; pixels],
        }
    }

    /// Room for `pixels` pixels, none yet (pixels arrive by [`push`](Self::push)).
    pub fn with_capacity(pixels: usize) -> Self {
        Self {
            sums: Vec::with_capacity(pixels),
            counts: Vec::with_capacity(pixels),
            albedo_sums: Vec::with_capacity(pixels),
            emission_sums: Vec::with_capacity(pixels),
            surfaces: Vec::with_capacity(pixels),
        }
    }

    /// Number of pixels.
    pub fn len(&self) -> usize {
        self.counts.len()
    }

    /// True when there is no pixel.
    pub fn is_empty(&self) -> bool {
        self.counts.is_empty()
    }

    /// Adds one accepted sample to pixel `pixel`; the first one's surface is kept.
    #[inline]
    pub fn add_sample(
        &mut self,
        pixel: usize,
        radiance: Vec3,
        albedo: Vec3,
        emission: Vec3,
        surface: SurfaceGuide,
    ) {
        if self.counts[pixel] == 0 {
            self.surfaces[pixel] = surface;
        }
        self.sums[pixel] += radiance;
        self.albedo_sums[pixel] += albedo;
        self.emission_sums[pixel] += emission;
        self.counts[pixel] += 1;
    }

    /// Appends one pixel's sums.
    pub fn push(
        &mut self,
        sum: Vec3,
        count: u32,
        albedo_sum: Vec3,
        emission_sum: Vec3,
        surface: SurfaceGuide,
    ) {
        self.sums.push(sum);
        self.counts.push(count);
        self.albedo_sums.push(albedo_sum);
        self.emission_sums.push(emission_sum);
        self.surfaces.push(surface);
    }

    /// Copies `n` pixels of `source` from `from` to `to` in this one.
    pub fn copy_span(&mut self, to: usize, source: &PixelSums, from: usize, n: usize) {
        self.sums[to..to + n].copy_from_slice(&source.sums[from..from + n]);
        self.counts[to..to + n].copy_from_slice(&source.counts[from..from + n]);
        self.albedo_sums[to..to + n].copy_from_slice(&source.albedo_sums[from..from + n]);
        self.emission_sums[to..to + n].copy_from_slice(&source.emission_sums[from..from + n]);
        self.surfaces[to..to + n].copy_from_slice(&source.surfaces[from..from + n]);
    }

    /// Mean radiance per pixel (zero where no sample was accepted).
    pub fn mean(&self) -> Vec<Vec3> {
        self.per_sample(&self.sums)
    }

    /// Mean albedo per pixel (zero where no sample was accepted).
    pub fn mean_albedo(&self) -> Vec<Vec3> {
        self.per_sample(&self.albedo_sums)
    }

    /// Mean emitted radiance per pixel (zero where no sample was accepted).
    pub fn mean_emission(&self) -> Vec<Vec3> {
        self.per_sample(&self.emission_sums)
    }

    /// Per-pixel `sums` divided by the accepted sample counts.
    fn per_sample(&self, sums: &[Vec3]) -> Vec<Vec3> {
        sums.iter()
            .zip(&self.counts)
            .map(|(s, &c)| if c > 0 { *s / c as f32 } else { Vec3::ZERO })
            .collect()
    }
}

/// One tile's output: per-pixel sums of accepted samples and their counts.
#[derive(Clone, Debug, PartialEq)]
pub struct TileResult {
    /// Where it goes.
    pub tile: Tile,
    /// The tile's pixels, row-major within the tile.
    pub pixels: PixelSums,
    /// Samples dropped because they were NaN or infinite.
    pub rejected: u64,
    /// Traversal counters.
    pub stats: TraversalStats,
}

/// One rendered frame of one camera.
#[derive(Component, Clone, Debug, PartialEq)]
pub struct FrameBuffer {
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
    /// The frame's pixels.
    pub pixels: PixelSums,
    /// NaN/Inf samples dropped in this frame.
    pub rejected: u64,
    /// Counters of this frame.
    pub stats: TraversalStats,
    /// Progressive frame index the samples were drawn for (0 starts a new accumulation).
    pub frame_index: u32,
}

impl Default for FrameBuffer {
    fn default() -> Self {
        Self::new(0, 0, 0)
    }
}

impl FrameBuffer {
    /// An empty frame.
    pub fn new(width: u32, height: u32, frame_index: u32) -> Self {
        Self {
            width,
            height,
            pixels: PixelSums::new(width as usize * height as usize),
            rejected: 0,
            stats: TraversalStats::default(),
            frame_index,
        }
    }

    /// Copies a tile's pixels in and adds its counters.
    pub fn write_tile(&mut self, result: &TileResult) {
        let t = result.tile;
        for row in 0..t.height {
            let from = (row * t.width) as usize;
            let to = ((t.y + row) * self.width + t.x) as usize;
            self.pixels
                .copy_span(to, &result.pixels, from, t.width as usize);
        }
        self.rejected += result.rejected;
        self.stats.add(&result.stats);
    }

    /// Mean albedo per pixel (zero where no sample was accepted).
    pub fn mean_albedo(&self) -> Vec<Vec3> {
        self.pixels.mean_albedo()
    }

    /// Mean emitted radiance per pixel (zero where no sample was accepted).
    pub fn mean_emission(&self) -> Vec<Vec3> {
        self.pixels.mean_emission()
    }

    /// Mean radiance per pixel (zero where no sample was accepted).
    pub fn mean(&self) -> Vec<Vec3> {
        self.pixels.mean()
    }
}

/// What the discontinuity filter compares to decide whether two pixels see the same
/// surface.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceGuide {
    /// Distance from the camera (infinite: no surface).
    pub depth: f32,
    /// The hit point (world space, as rendered).
    pub position: Vec3,
    /// Geometric normal facing the camera.
    pub normal: Vec3,
    /// Shader id.
    pub shader: u32,
}

impl SurfaceGuide {
    /// No surface: the ray left the scene.
    pub const NONE: SurfaceGuide = SurfaceGuide {
        depth: f32::INFINITY,
        position: Vec3::ZERO,
        normal: Vec3::ZERO,
        shader: u32::MAX,
    };

    /// True when a surface was hit.
    pub fn is_surface(&self) -> bool {
        self.depth.is_finite()
    }
}
