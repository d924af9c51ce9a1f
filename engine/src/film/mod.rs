//! Frames and films: a [`FrameBuffer`] holds one frame's per-pixel sample sums; a
//! camera's [`Film`] accumulates frames in f64 so the running mean never stalls; both
//! turn into PNG (exposure, filmic tone curve, sRGB) or EXR (linear radiance).

pub mod checkpoint;
pub mod discontinuity;
pub mod frame;
pub mod metrics;
pub mod output;

pub use checkpoint::CheckpointError;
pub use frame::{FrameBuffer, PixelSums, SurfaceGuide, Tile, TileResult};
pub use output::{
    ImageKind, OutputError, read_rgba8_png, write_apng, write_atomically, write_rgba8_png,
};

use crate::util::color::luminance64;
pub use crate::util::color::{filmic, tone_map_srgba8};
use bevy_ecs::component::Component;
use glam::Vec3;

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
            .zip(frame.pixels.sums.iter().zip(&frame.pixels.counts))
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
            .zip(frame.pixels.sums.iter().zip(&frame.pixels.counts))
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
        frame.pixels.sums[0] = Vec3::splat(1024.0);
        frame.pixels.counts[0] = 1024;
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
                frame.pixels.sums[i] = Vec3::splat(v * 2.0);
                frame.pixels.counts[i] = 2;
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
