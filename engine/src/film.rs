//! Frames and films: a [`FrameBuffer`] holds one frame's per-pixel sample sums; a
//! camera's [`Film`] accumulates frames in f64 so the running mean never stalls; both
//! turn into PNG (exposure, filmic tone curve, sRGB) or EXR (linear radiance).

use crate::bvh::TraversalStats;
use crate::render::SurfaceGuide;
use crate::shading::linear_to_srgb;
use bevy_ecs::component::Component;
use glam::Vec3;
use std::path::{Path, PathBuf};

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

/// One tile's output: per-pixel sums of accepted samples and their counts.
#[derive(Clone, Debug, PartialEq)]
pub struct TileResult {
    /// Where it goes.
    pub tile: Tile,
    /// Sum of accepted radiance samples per pixel, row-major within the tile.
    pub sums: Vec<Vec3>,
    /// Accepted samples per pixel.
    pub counts: Vec<u32>,
    /// Sum of the accepted samples' albedos per pixel.
    pub albedo_sums: Vec<Vec3>,
    /// Sum of the accepted samples' emitted radiance per pixel (part of `sums`).
    pub emission_sums: Vec<Vec3>,
    /// The surface of each pixel's first accepted sample.
    pub surfaces: Vec<SurfaceGuide>,
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
    /// Per-pixel sums of accepted samples.
    pub sums: Vec<Vec3>,
    /// Per-pixel accepted sample counts.
    pub counts: Vec<u32>,
    /// Per-pixel sums of the accepted samples' albedos (see [`TileResult`]).
    pub albedo_sums: Vec<Vec3>,
    /// Per-pixel sums of the accepted samples' emitted radiance (see [`TileResult`]).
    pub emission_sums: Vec<Vec3>,
    /// Per-pixel surface of the first accepted sample.
    pub surfaces: Vec<SurfaceGuide>,
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
        let n = width as usize * height as usize;
        Self {
            width,
            height,
            sums: vec![Vec3::ZERO; n],
            counts: vec![0; n],
            albedo_sums: vec![Vec3::ZERO; n],
            emission_sums: vec![Vec3::ZERO; n],
            surfaces: vec![SurfaceGuide::NONE; n],
            rejected: 0,
            stats: TraversalStats::default(),
            frame_index,
        }
    }

    /// Copies a tile's pixels in and adds its counters.
    pub fn write_tile(&mut self, result: &TileResult) {
        let t = result.tile;
        for row in 0..t.height {
            let src = (row * t.width) as usize;
            let dst = ((t.y + row) * self.width + t.x) as usize;
            let n = t.width as usize;
            self.sums[dst..dst + n].copy_from_slice(&result.sums[src..src + n]);
            self.counts[dst..dst + n].copy_from_slice(&result.counts[src..src + n]);
            self.albedo_sums[dst..dst + n].copy_from_slice(&result.albedo_sums[src..src + n]);
            self.emission_sums[dst..dst + n].copy_from_slice(&result.emission_sums[src..src + n]);
            self.surfaces[dst..dst + n].copy_from_slice(&result.surfaces[src..src + n]);
        }
        self.rejected += result.rejected;
        self.stats.add(&result.stats);
    }

    /// Mean albedo per pixel (zero where no sample was accepted).
    pub fn mean_albedo(&self) -> Vec<Vec3> {
        self.per_sample(&self.albedo_sums)
    }

    /// Mean emitted radiance per pixel (zero where no sample was accepted).
    pub fn mean_emission(&self) -> Vec<Vec3> {
        self.per_sample(&self.emission_sums)
    }

    /// Mean radiance per pixel (zero where no sample was accepted).
    pub fn mean(&self) -> Vec<Vec3> {
        self.per_sample(&self.sums)
    }

    /// Per-pixel `sums` divided by the accepted sample counts.
    fn per_sample(&self, sums: &[Vec3]) -> Vec<Vec3> {
        sums.iter()
            .zip(&self.counts)
            .map(|(s, &c)| if c > 0 { *s / c as f32 } else { Vec3::ZERO })
            .collect()
    }
}

/// A camera's accumulation buffer: f64 sums and sample counts per pixel.
#[derive(Component, Clone, Debug, PartialEq)]
pub struct Film {
    width: u32,
    height: u32,
    sums: Vec<[f64; 3]>,
    counts: Vec<u64>,
    frames: u32,
    rejected: u64,
    resets: u64,
    fireflies: u64,
    resume_pending: bool,
}

/// A frame's pixel counts as a firefly when its luminance exceeds this multiple of the
/// pixel's accumulated mean (see [`Film::fireflies`]).
pub const FIREFLY_RATIO: f64 = 20.0;

/// Frames a pixel must have accumulated before a frame can be judged a firefly against
/// its mean.
pub const FIREFLY_MIN_FRAMES: u32 = 4;

fn luminance64(rgb: [f64; 3]) -> f64 {
    0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]
}

/// Why a checkpoint could not be used.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// Reading failed.
    #[error("{}: cannot read the checkpoint: {source}", path.display())]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Not a checkpoint, or a damaged one.
    #[error("{}: not a Sylva film checkpoint ({reason})", path.display())]
    Format {
        /// The file.
        path: std::path::PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// Written for another scene, view or sampling settings.
    #[error("{}: the checkpoint was rendered with other settings (scene, seed, size or sampling); resume with the same ones", path.display())]
    Mismatch {
        /// The file.
        path: std::path::PathBuf,
    },
}

const CHECKPOINT_MAGIC: &[u8; 8] = b"SYLVAFLM";
const CHECKPOINT_VERSION: u32 = 1;

impl Default for Film {
    fn default() -> Self {
        Self::new(0, 0)
    }
}

impl Film {
    /// An empty film.
    pub fn new(width: u32, height: u32) -> Self {
        let n = width as usize * height as usize;
        Self {
            width,
            height,
            sums: vec![[0.0; 3]; n],
            counts: vec![0; n],
            frames: 0,
            rejected: 0,
            resets: 0,
            fireflies: 0,
            resume_pending: false,
        }
    }

    /// True from loading a checkpoint until the next frame is added: that frame
    /// continues the checkpoint's sequence instead of restarting accumulation.
    pub fn awaiting_resume(&self) -> bool {
        self.resume_pending
    }

    /// Saves the exact accumulation state (f64 sums, counts, frame count), atomically.
    /// `fingerprint` identifies the settings it belongs to; [`Film::read_checkpoint`]
    /// refuses another.
    pub fn write_checkpoint(&self, path: &Path, fingerprint: u64) -> Result<(), OutputError> {
        let mut bytes = Vec::with_capacity(48 + self.sums.len() * 32);
        bytes.extend_from_slice(CHECKPOINT_MAGIC);
        bytes.extend_from_slice(&CHECKPOINT_VERSION.to_le_bytes());
        bytes.extend_from_slice(&fingerprint.to_le_bytes());
        for v in [self.width, self.height, self.frames] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        for v in [self.rejected, self.resets] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        for (sum, count) in self.sums.iter().zip(&self.counts) {
            for v in sum {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
            bytes.extend_from_slice(&count.to_le_bytes());
        }
        write_atomically(path, |tmp| {
            std::fs::write(tmp, &bytes).map_err(|e| e.to_string())
        })
    }

    /// Loads a checkpoint written with the same `fingerprint`; the next frame added
    /// continues it.
    pub fn read_checkpoint(path: &Path, fingerprint: u64) -> Result<Film, CheckpointError> {
        let bytes = std::fs::read(path).map_err(|source| CheckpointError::Io {
            path: path.to_owned(),
            source,
        })?;
        let format = |reason: &str| CheckpointError::Format {
            path: path.to_owned(),
            reason: reason.into(),
        };
        let mut at = 0usize;
        let mut take = |n: usize| -> Result<&[u8], CheckpointError> {
            let slice = bytes.get(at..at + n).ok_or_else(|| format("truncated"))?;
            at += n;
            Ok(slice)
        };
        if take(8)? != CHECKPOINT_MAGIC {
            return Err(format("wrong magic number"));
        }
        let u32_at = |b: &[u8]| u32::from_le_bytes(b.try_into().expect("4 bytes"));
        let u64_at = |b: &[u8]| u64::from_le_bytes(b.try_into().expect("8 bytes"));
        if u32_at(take(4)?) != CHECKPOINT_VERSION {
            return Err(format("unknown version"));
        }
        if u64_at(take(8)?) != fingerprint {
            return Err(CheckpointError::Mismatch {
                path: path.to_owned(),
            });
        }
        let (width, height, frames) = (u32_at(take(4)?), u32_at(take(4)?), u32_at(take(4)?));
        let (rejected, resets) = (u64_at(take(8)?), u64_at(take(8)?));
        let pixels = width as usize * height as usize;
        let body = take(
            pixels
                .checked_mul(32)
                .ok_or_else(|| format("absurd size"))?,
        )?;
        let mut film = Film::new(width, height);
        for (i, chunk) in body.chunks_exact(32).enumerate() {
            let f =
                |k: usize| f64::from_le_bytes(chunk[k * 8..k * 8 + 8].try_into().expect("8 bytes"));
            film.sums[i] = [f(0), f(1), f(2)];
            film.counts[i] = u64_at(&chunk[24..32]);
        }
        film.frames = frames;
        film.rejected = rejected;
        film.resets = resets;
        film.resume_pending = true;
        Ok(film)
    }

    /// Width.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Frames accumulated since the last reset.
    pub fn frames(&self) -> u32 {
        self.frames
    }

    /// NaN/Inf samples dropped since the last reset.
    pub fn rejected_samples(&self) -> u64 {
        self.rejected
    }

    /// Fireflies seen since the last reset (not kept in checkpoints): frames whose pixel
    /// value was more than [`FIREFLY_RATIO`] times that pixel's mean so far, counted
    /// once the film holds [`FIREFLY_MIN_FRAMES`] frames. They are counted, not clamped
    /// (clamping would bias the estimate); a count that stays high says the lighting
    /// needs more light samples or the scene an outlier.
    pub fn fireflies(&self) -> u64 {
        self.fireflies
    }

    /// How many times accumulation restarted (a change of camera or scene).
    pub fn resets(&self) -> u64 {
        self.resets
    }

    /// Forgets everything accumulated, resizing if needed.
    pub fn reset(&mut self, width: u32, height: u32) {
        let resets = self.resets + 1;
        *self = Film::new(width, height);
        self.resets = resets;
    }

    /// Adds a frame; a frame with index 0 (or of another size) restarts accumulation.
    pub fn accumulate(&mut self, frame: &FrameBuffer) {
        if frame.frame_index == 0 || frame.width != self.width || frame.height != self.height {
            self.reset(frame.width, frame.height);
        }
        if self.frames >= FIREFLY_MIN_FRAMES {
            self.fireflies += self.count_fireflies(frame);
        }
        for ((sum, count), (s, &c)) in self
            .sums
            .iter_mut()
            .zip(self.counts.iter_mut())
            .zip(frame.sums.iter().zip(&frame.counts))
        {
            sum[0] += s.x as f64;
            sum[1] += s.y as f64;
            sum[2] += s.z as f64;
            *count += c as u64;
        }
        self.frames += 1;
        self.rejected += frame.rejected;
        self.resume_pending = false;
    }

    /// Pixels of `frame` brighter than [`FIREFLY_RATIO`] times their accumulated mean.
    fn count_fireflies(&self, frame: &FrameBuffer) -> u64 {
        let mut found = 0;
        for ((sum, &count), (s, &c)) in self
            .sums
            .iter()
            .zip(&self.counts)
            .zip(frame.sums.iter().zip(&frame.counts))
        {
            if c == 0 || count == 0 {
                continue;
            }
            let mean = luminance64(*sum) / count as f64;
            let value = luminance64([s.x as f64, s.y as f64, s.z as f64]) / c as f64;
            found += u64::from(value > FIREFLY_RATIO * mean.max(0.0) && value > 0.0);
        }
        found
    }

    /// Adds one sample to one pixel (for tests and tools that splat).
    pub fn add_sample(&mut self, x: u32, y: u32, radiance: Vec3) {
        if !radiance.is_finite() {
            self.rejected += 1;
            return;
        }
        let i = (y * self.width + x) as usize;
        self.sums[i][0] += radiance.x as f64;
        self.sums[i][1] += radiance.y as f64;
        self.sums[i][2] += radiance.z as f64;
        self.counts[i] += 1;
    }

    /// Mean radiance of one pixel.
    pub fn pixel(&self, x: u32, y: u32) -> [f64; 3] {
        let i = (y * self.width + x) as usize;
        let c = self.counts[i].max(1) as f64;
        self.sums[i].map(|s| s / c)
    }

    /// This film with every pixel's mean replaced by `means` (row-major), sample
    /// counts kept: what a display filter hands to the image writers.
    pub fn with_means(&self, means: &[Vec3]) -> Film {
        assert_eq!(means.len(), self.counts.len(), "one mean per pixel");
        let mut film = self.clone();
        for ((sum, &count), mean) in film.sums.iter_mut().zip(&self.counts).zip(means) {
            *sum = mean.to_array().map(|v| v as f64 * count as f64);
        }
        film
    }

    /// Mean radiance of every pixel, row-major, as f32 RGB.
    pub fn mean_rgb(&self) -> Vec<[f32; 3]> {
        self.sums
            .iter()
            .zip(&self.counts)
            .map(|(s, &c)| s.map(|v| (v / c.max(1) as f64) as f32))
            .collect()
    }

    /// Tone-mapped 8-bit sRGB RGBA pixels (exposure in stops, then the ACES filmic fit).
    pub fn to_srgba8(&self, exposure: f32) -> Vec<u8> {
        let scale = 2f32.powf(exposure);
        self.mean_rgb()
            .iter()
            .flat_map(|&p| tone_map_srgba8(p, scale))
            .collect()
    }

    /// Writes a tone-mapped PNG, atomically (temporary file, then rename).
    pub fn write_png(&self, path: &Path, exposure: f32) -> Result<(), OutputError> {
        self.write_png_with(path, exposure, &[])
    }

    /// [`write_png`](Self::write_png) with `metadata` as tEXt chunks (keywords of 1–79
    /// Latin-1 characters; others are left out).
    pub fn write_png_with(
        &self,
        path: &Path,
        exposure: f32,
        metadata: &[(String, String)],
    ) -> Result<(), OutputError> {
        write_rgba8_png(
            path,
            (self.width, self.height),
            &self.to_srgba8(exposure),
            metadata,
        )
    }

    /// Writes linear mean radiance as an RGBA f32 EXR, atomically.
    pub fn write_exr(&self, path: &Path) -> Result<(), OutputError> {
        self.write_exr_with(path, &[])
    }

    /// [`write_exr`](Self::write_exr) with `metadata` as text attributes of the header.
    #[cfg(feature = "exr")]
    pub fn write_exr_with(
        &self,
        path: &Path,
        metadata: &[(String, String)],
    ) -> Result<(), OutputError> {
        use exr::prelude::*;
        let mean = self.mean_rgb();
        let width = self.width as usize;
        write_atomically(path, |tmp| {
            let channels = SpecificChannels::rgba(|pos: Vec2<usize>| {
                let [r, g, b] = mean[pos.y() * width + pos.x()];
                (r, g, b, 1.0f32)
            });
            // Scan lines in increasing order: the default tiles with unspecified order are
            // written as the compressing threads finish them, so bytes vary run to run.
            let encoding = Encoding {
                compression: Compression::ZIP16,
                blocks: Blocks::ScanLines,
                line_order: LineOrder::Increasing,
            };
            let mut image =
                Image::from_encoded_channels((width, self.height as usize), encoding, channels);
            for (key, value) in metadata {
                if let (Some(key), Some(value)) = (Text::new_or_none(key), Text::new_or_none(value))
                {
                    image
                        .attributes
                        .other
                        .insert(key, exr::meta::attribute::AttributeValue::Text(value));
                }
            }
            // The exr crate keeps custom attributes in a hash map and writes them in its
            // (per-process random) order; sorting them in memory before the one write to
            // disk makes equal images equal files.
            let mut bytes = std::io::Cursor::new(Vec::new());
            image
                .write()
                .to_buffered(&mut bytes)
                .map_err(|e| e.to_string())?;
            let mut bytes = bytes.into_inner();
            sort_exr_header_attributes(&mut bytes)?;
            std::fs::write(tmp, bytes).map_err(|e| e.to_string())
        })
    }

    /// Without the `exr` feature: an error saying how to get EXR output.
    #[cfg(not(feature = "exr"))]
    pub fn write_exr_with(
        &self,
        path: &Path,
        _metadata: &[(String, String)],
    ) -> Result<(), OutputError> {
        Err(OutputError::FeatureDisabled {
            path: path.to_owned(),
            feature: "exr",
        })
    }

    /// Writes PNG or EXR by the path's extension.
    pub fn write(&self, path: &Path, exposure: f32) -> Result<(), OutputError> {
        self.write_with(path, exposure, &[])
    }

    /// [`write`](Self::write) with `metadata` (key, value) pairs stored in the file: PNG
    /// tEXt chunks or EXR header attributes.
    pub fn write_with(
        &self,
        path: &Path,
        exposure: f32,
        metadata: &[(String, String)],
    ) -> Result<(), OutputError> {
        match ImageKind::from_path(path)? {
            ImageKind::Png => self.write_png_with(path, exposure, metadata),
            ImageKind::Exr => self.write_exr_with(path, metadata),
        }
    }
}

/// The output formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageKind {
    /// 8-bit tone-mapped sRGB.
    Png,
    /// 32-bit float linear radiance.
    Exr,
}

impl ImageKind {
    /// The format an output path asks for; `.exr` needs the `exr` feature.
    pub fn from_path(path: &Path) -> Result<Self, OutputError> {
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .as_deref()
        {
            Some("png") => Ok(Self::Png),
            Some("exr") if cfg!(feature = "exr") => Ok(Self::Exr),
            Some("exr") => Err(OutputError::FeatureDisabled {
                path: path.to_owned(),
                feature: "exr",
            }),
            _ => Err(OutputError::UnknownFormat {
                path: path.to_owned(),
            }),
        }
    }
}

/// Why an image could not be written.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    /// The extension is neither `.png` nor `.exr`.
    #[error("{}: unknown image format (use a .png or .exr file name)", path.display())]
    UnknownFormat {
        /// The path given.
        path: PathBuf,
    },
    /// The format needs a cargo feature this build was made without.
    #[error("{}: this build has no {feature} support (rebuild with `--features {feature}`)", path.display())]
    FeatureDisabled {
        /// The path given.
        path: PathBuf,
        /// The missing feature.
        feature: &'static str,
    },
    /// Encoding or file system failure.
    #[error("{}: could not write image: {reason}", path.display())]
    Write {
        /// The path given.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
}

/// Sorts the attributes of a single-part EXR header by name, in place. The header keeps
/// its length, so the chunk offsets after it stay valid.
#[cfg(feature = "exr")]
fn sort_exr_header_attributes(file: &mut [u8]) -> Result<(), String> {
    const MULTI_PART: u32 = 1 << 12;
    let malformed = || "EXR header is malformed".to_string();
    let version = file
        .get(4..8)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .ok_or_else(malformed)?;
    if version & MULTI_PART != 0 {
        return Err("multi-part EXR headers are not sorted".into());
    }
    let start = 8;
    let mut attributes: Vec<(usize, usize)> = Vec::new();
    let mut at = start;
    let string_end = |from: usize| {
        file.get(from..)
            .and_then(|rest| rest.iter().position(|&b| b == 0))
            .map(|n| from + n)
            .ok_or_else(malformed)
    };
    while *file.get(at).ok_or_else(malformed)? != 0 {
        let name_end = string_end(at)?;
        let type_end = string_end(name_end + 1)?;
        let size_at = type_end + 1;
        let size = file
            .get(size_at..size_at + 4)
            .map(|b| i32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .ok_or_else(malformed)?;
        let end = usize::try_from(size)
            .ok()
            .and_then(|s| (size_at + 4).checked_add(s))
            .filter(|&end| end <= file.len())
            .ok_or_else(malformed)?;
        attributes.push((at, end));
        at = end;
    }
    let mut sorted: Vec<&[u8]> = attributes.iter().map(|&(a, b)| &file[a..b]).collect();
    sorted.sort_by_key(|attribute| attribute.split(|&b| b == 0).next().unwrap_or_default());
    let header: Vec<u8> = sorted.concat();
    file[start..at].copy_from_slice(&header);
    Ok(())
}

/// Writes `frames` (8-bit RGBA, each `width` × `height`, row by row from the top) as an
/// animated PNG that shows `fps` of them per second and loops, with `metadata` as tEXt
/// chunks, atomically: an animation's preview.
pub fn write_apng(
    path: &Path,
    (width, height): (u32, u32),
    frames: &[Vec<u8>],
    fps: u16,
    metadata: &[(String, String)],
) -> Result<(), OutputError> {
    let size = width as usize * height as usize * 4;
    if frames.is_empty() || frames.iter().any(|f| f.len() != size) {
        return Err(OutputError::Write {
            path: path.to_owned(),
            reason: format!(
                "{} frames for a {width}x{height} RGBA animation, some of another size or none",
                frames.len()
            ),
        });
    }
    write_rgba8_frames(path, (width, height), frames, Some(fps), metadata)
}

/// Reads an 8-bit RGB or RGBA PNG (the first frame of an animated one) as RGBA with its
/// size.
pub fn read_rgba8_png(path: &Path) -> Result<((u32, u32), Vec<u8>), OutputError> {
    let fail = |reason: String| OutputError::Write {
        path: path.to_owned(),
        reason: format!("cannot read it back: {reason}"),
    };
    let file = std::fs::File::open(path).map_err(|e| fail(e.to_string()))?;
    let mut reader = png::Decoder::new(std::io::BufReader::new(file))
        .read_info()
        .map_err(|e| fail(e.to_string()))?;
    let mut buffer = vec![0; reader.output_buffer_size().unwrap_or(0)];
    let info = reader
        .next_frame(&mut buffer)
        .map_err(|e| fail(e.to_string()))?;
    let pixels = &buffer[..info.buffer_size()];
    let rgba = match (info.color_type, info.bit_depth) {
        (png::ColorType::Rgba, png::BitDepth::Eight) => pixels.to_vec(),
        (png::ColorType::Rgb, png::BitDepth::Eight) => pixels
            .chunks_exact(3)
            .flat_map(|p| [p[0], p[1], p[2], 255])
            .collect(),
        (color, depth) => return Err(fail(format!("{color:?} at {depth:?} is not 8-bit RGB(A)"))),
    };
    Ok(((info.width, info.height), rgba))
}

/// Writes `width × height` sRGB8 RGBA pixels (row by row from the top) as a PNG with
/// `metadata` as tEXt chunks (keywords the format cannot hold are left out), atomically
/// (temporary file, then rename): a screenshot is written the way a render is.
pub fn write_rgba8_png(
    path: &Path,
    (width, height): (u32, u32),
    rgba: &[u8],
    metadata: &[(String, String)],
) -> Result<(), OutputError> {
    if rgba.len() != width as usize * height as usize * 4 {
        return Err(OutputError::Write {
            path: path.to_owned(),
            reason: format!("{} bytes for a {width}x{height} RGBA image", rgba.len()),
        });
    }
    write_rgba8_frames(path, (width, height), &[rgba], None, metadata)
}

/// Writes checked 8-bit RGBA `frames` as a PNG, animated at `fps` (looping) when given,
/// with `metadata` as tEXt chunks (keywords the format cannot hold are left out),
/// atomically.
fn write_rgba8_frames(
    path: &Path,
    (width, height): (u32, u32),
    frames: &[impl AsRef<[u8]>],
    fps: Option<u16>,
    metadata: &[(String, String)],
) -> Result<(), OutputError> {
    write_atomically(path, |tmp| {
        let file = std::fs::File::create(tmp).map_err(|e| e.to_string())?;
        let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), width, height);
        encoder.set_color(png::ColorType::Rgba);
        encoder.set_depth(png::BitDepth::Eight);
        if let Some(fps) = fps {
            // A preview is written once and shared: worth a slower, smaller encoding.
            encoder.set_compression(png::Compression::High);
            let count = u32::try_from(frames.len()).map_err(|e| e.to_string())?;
            encoder.set_animated(count, 0).map_err(|e| e.to_string())?;
            encoder
                .set_frame_delay(1, fps.max(1))
                .map_err(|e| e.to_string())?;
        }
        for (key, value) in metadata {
            // A keyword the format cannot hold is skipped rather than failing the image.
            let _ = encoder.add_text_chunk(key.clone(), value.clone());
        }
        let mut writer = encoder.write_header().map_err(|e| e.to_string())?;
        for frame in frames {
            writer
                .write_image_data(frame.as_ref())
                .map_err(|e| e.to_string())?;
        }
        writer.finish().map_err(|e| e.to_string())
    })
}

/// Writes a file through `write(temporary path)` and renames it over `path`, so a
/// reader (or a run killed mid-write) sees the old file or the new one, never half of it.
pub fn write_atomically(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), String>,
) -> Result<(), OutputError> {
    let fail = |reason: String| OutputError::Write {
        path: path.to_owned(),
        reason,
    };
    let name = path
        .file_name()
        .ok_or_else(|| fail("not a file name".into()))?;
    // Keep the extension last: the encoders pick the format from it.
    let tmp = path.with_file_name(format!(
        ".{}.{}.tmp.{}",
        name.to_string_lossy(),
        std::process::id(),
        path.extension().and_then(|e| e.to_str()).unwrap_or("")
    ));
    if let Err(reason) = write(&tmp) {
        let _ = std::fs::remove_file(&tmp);
        return Err(fail(reason));
    }
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        fail(e.to_string())
    })
}

/// One linear RGB value as the 8-bit sRGB RGBA pixel every PNG and display shows:
/// scaled by `scale` (2^exposure), the ACES filmic fit, then sRGB encoding; alpha 255.
#[inline]
pub fn tone_map_srgba8(rgb: [f32; 3], scale: f32) -> [u8; 4] {
    let [r, g, b] = rgb.map(|v| (linear_to_srgb(filmic(v * scale)) * 255.0 + 0.5) as u8);
    [r, g, b, 255]
}

/// Narkowicz's fit of the ACES filmic curve, clamped to [0, 1]; NaN maps to 0.
#[inline]
pub fn filmic(x: f32) -> f32 {
    // Clamp first: inf/inf would be NaN, and the curve is flat at 1 long before 1e9.
    let x = if x.is_nan() { 0.0 } else { x.clamp(0.0, 1e9) };
    ((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)).clamp(0.0, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_cover_the_image_once() {
        let (w, h) = (37, 23);
        let mut hits = vec![0u8; (w * h) as usize];
        for t in Tile::grid(w, h, 8) {
            for y in t.y..t.y + t.height {
                for x in t.x..t.x + t.width {
                    hits[(y * w + x) as usize] += 1;
                }
            }
        }
        assert!(hits.iter().all(|&c| c == 1));
    }

    #[test]
    fn accumulation_of_many_unit_samples_is_exact() {
        let mut film = Film::new(1, 1);
        let mut frame = FrameBuffer::new(1, 1, 0);
        frame.sums[0] = Vec3::splat(1024.0);
        frame.counts[0] = 1024;
        for i in 0..(1 << 15) {
            frame.frame_index = i;
            film.accumulate(&frame);
        }
        assert_eq!(film.pixel(0, 0), [1.0; 3]);
        assert_eq!(film.counts[0], 1 << 25);
    }

    #[test]
    fn a_pixel_far_above_its_mean_is_counted_as_a_firefly() {
        let mut film = Film::new(3, 1);
        let frame_of = |index: u32, values: [f32; 3]| {
            let mut frame = FrameBuffer::new(3, 1, index);
            for (i, v) in values.into_iter().enumerate() {
                frame.sums[i] = Vec3::splat(v * 2.0);
                frame.counts[i] = 2;
            }
            frame
        };
        // Too early to judge: the first frames set the mean.
        film.accumulate(&frame_of(0, [1.0, 1.0, 0.0]));
        film.accumulate(&frame_of(1, [500.0, 1.0, 0.0]));
        assert_eq!(film.fireflies(), 0);
        for i in 2..6 {
            film.accumulate(&frame_of(i, [1.0, 1.0, 0.0]));
        }
        assert_eq!(film.fireflies(), 0, "steady pixels are not fireflies");
        let mean = film.pixel(1, 0)[0];
        // Just below the ratio, far above it, and light on a pixel dark so far.
        let just_below = (FIREFLY_RATIO * mean * 0.99) as f32;
        film.accumulate(&frame_of(6, [1e6, just_below, 0.5]));
        assert_eq!(film.fireflies(), 2);
        film.accumulate(&frame_of(0, [1.0, 1.0, 1.0]));
        assert_eq!(film.fireflies(), 0, "a restart forgets them");
    }

    #[test]
    fn non_finite_samples_are_counted_not_added() {
        let mut film = Film::new(1, 1);
        film.add_sample(0, 0, Vec3::ONE);
        film.add_sample(0, 0, Vec3::new(f32::NAN, 0.0, 0.0));
        film.add_sample(0, 0, Vec3::splat(f32::INFINITY));
        assert_eq!(film.pixel(0, 0), [1.0; 3]);
        assert_eq!(film.rejected_samples(), 2);
    }

    #[test]
    fn checkpoints_round_trip_exactly_and_refuse_damage() {
        let mut film = Film::new(3, 2);
        film.add_sample(1, 1, Vec3::new(0.1, 1e-30, 7.0));
        film.add_sample(2, 0, Vec3::new(1e30, 0.3, 0.0));
        film.frames = 5;
        let dir = std::env::temp_dir().join(format!("sylva-film-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("f.film");
        film.write_checkpoint(&path, 42).unwrap();
        let loaded = Film::read_checkpoint(&path, 42).unwrap();
        assert!(loaded.awaiting_resume());
        assert_eq!(
            (loaded.sums.clone(), loaded.counts.clone(), loaded.frames),
            (film.sums.clone(), film.counts.clone(), 5)
        );
        assert!(matches!(
            Film::read_checkpoint(&path, 43),
            Err(CheckpointError::Mismatch { .. })
        ));
        let bytes = std::fs::read(&path).unwrap();
        for cut in [0, 7, 20, bytes.len() - 1] {
            std::fs::write(&path, &bytes[..cut]).unwrap();
            let e = Film::read_checkpoint(&path, 42).unwrap_err();
            assert!(matches!(e, CheckpointError::Format { .. }), "{cut}: {e}");
        }
    }

    #[test]
    fn filmic_is_monotone_and_bounded() {
        let mut last = 0.0;
        for i in 0..1000 {
            let v = filmic(i as f32 * 0.05);
            assert!(v >= last && v <= 1.0);
            last = v;
        }
        assert_eq!(filmic(f32::NAN), 0.0);
        assert_eq!(filmic(f32::INFINITY), 1.0);
    }

    #[test]
    fn an_animated_png_holds_every_frame_and_loops() {
        let dir = std::env::temp_dir().join(format!("sylva-apng-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("preview.png");
        let frames: Vec<Vec<u8>> = (0..3u8)
            .map(|k| {
                (0..2 * 3 * 4)
                    .map(|i| (i as u8).wrapping_mul(7) ^ (k * 40))
                    .collect()
            })
            .collect();
        write_apng(&path, (2, 3), &frames, 12, &[]).unwrap();
        let file = std::fs::File::open(&path).unwrap();
        let mut reader = png::Decoder::new(std::io::BufReader::new(file))
            .read_info()
            .unwrap();
        let control = reader.info().animation_control().copied().unwrap();
        assert_eq!((control.num_frames, control.num_plays), (3, 0));
        for frame in &frames {
            let mut buffer = vec![0; reader.output_buffer_size().unwrap()];
            let info = reader.next_frame(&mut buffer).unwrap();
            assert_eq!(&buffer[..info.buffer_size()], &frame[..]);
            let control = reader.info().frame_control().copied().unwrap();
            assert_eq!((control.delay_num, control.delay_den), (1, 12));
        }
        assert_eq!(read_rgba8_png(&path).unwrap(), ((2, 3), frames[0].clone()));
        let wrong = write_apng(&dir.join("bad.png"), (2, 3), &[vec![0; 5]], 12, &[]);
        assert!(wrong.unwrap_err().to_string().contains("bad.png"));
        std::fs::remove_dir_all(&dir).ok();
    }
}
