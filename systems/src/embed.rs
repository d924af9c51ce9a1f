//! A frame's results as a program that embeds Sylva reads them in place
//! ([`FrameImage`], refreshed by [`publish_frame_images`]). Installing the stages into the
//! program's own `World` and `Schedule` is [`install`](crate::install), which chooses
//! the optional stages ([`Stages`](crate::Stages)) and whose threads render
//! ([`RenderOptions`](crate::RenderOptions)):
//!
//! ```no_run
//! use bevy_ecs::prelude::*;
//! use sylva_systems::{RenderOptions, RenderSystems, install};
//!
//! fn my_physics() {}
//! fn my_hud() {}
//!
//! let mut world = World::new();
//! let mut schedule = Schedule::default();
//! install(&mut world, &mut schedule, &RenderOptions::default()).unwrap();
//! schedule.add_systems((
//!     my_physics.before(RenderSystems::Prepare),
//!     my_hud.after(RenderSystems::Output),
//! ));
//! ```

use crate::profile::{FrameProfiler, ProfiledSystem};
use bevy_ecs::prelude::*;
use sylva_engine::discontinuity::FilteredImage;
use sylva_engine::film::{Film, tone_map_srgba8};

/// A camera's latest image as a program reads it in place: mean linear radiance as
/// RGBA `f32` and the tone-mapped sRGB RGBA bytes of a texture upload, row-major from
/// the top-left pixel. Put `FrameImage::new(exposure)` on a camera and
/// [`publish_frame_images`] refreshes it (in [`RenderSystems::Output`](crate::RenderSystems::Output)) whenever the
/// camera's film changes, from the filtered image when the camera has a display filter.
#[derive(Component, Clone, Debug, Default, PartialEq)]
pub struct FrameImage {
    exposure: f32,
    width: u32,
    height: u32,
    frames: u32,
    linear_rgba: Vec<f32>,
    srgba8: Vec<u8>,
}

impl FrameImage {
    /// An empty image to be filled, tone-mapped at `exposure` stops.
    pub fn new(exposure: f32) -> Self {
        Self {
            exposure,
            ..Self::default()
        }
    }

    /// Width in pixels (0 before the first frame).
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels (0 before the first frame).
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Frames accumulated in the image.
    pub fn frames(&self) -> u32 {
        self.frames
    }

    /// Mean linear radiance, four `f32` per pixel (alpha 1).
    pub fn linear_rgba(&self) -> &[f32] {
        &self.linear_rgba
    }

    /// Tone-mapped sRGB, four bytes per pixel (alpha 255), as the PNG writer shows it.
    pub fn srgba8(&self) -> &[u8] {
        &self.srgba8
    }

    /// Refills the buffers from `film`, or from `filtered` means when they belong to the
    /// film's current frame count. The buffers keep their allocation between frames.
    pub fn update(&mut self, film: &Film, filtered: Option<&FilteredImage>) {
        let (width, height) = (film.width(), film.height());
        let pixels = width as usize * height as usize;
        self.width = width;
        self.height = height;
        self.frames = film.frames();
        self.linear_rgba.resize(pixels * 4, 0.0);
        self.srgba8.resize(pixels * 4, 0);
        let filtered = filtered
            .filter(|f| f.frames == film.frames() && f.pixels.len() == pixels)
            .map(|f| &f.pixels);
        let scale = 2f32.powf(self.exposure);
        let rows = self
            .linear_rgba
            .chunks_exact_mut(4)
            .zip(self.srgba8.chunks_exact_mut(4));
        for (i, (linear, srgb)) in rows.enumerate() {
            let rgb = match filtered {
                Some(means) => means[i].to_array(),
                None => {
                    let (x, y) = ((i % width as usize) as u32, (i / width as usize) as u32);
                    film.pixel(x, y).map(|v| v as f32)
                }
            };
            linear.copy_from_slice(&[rgb[0], rgb[1], rgb[2], 1.0]);
            srgb.copy_from_slice(&tone_map_srgba8(rgb, scale));
        }
    }
}

/// Refreshes the [`FrameImage`] of every camera whose film changed.
pub fn publish_frame_images(
    mut cameras: Query<(&Film, Option<&FilteredImage>, &mut FrameImage), Changed<Film>>,
    profiler: Res<FrameProfiler>,
) {
    let _timer = profiler.time(ProfiledSystem::PublishFrameImages);
    let _span = tracing::info_span!("publish_frame_images").entered();
    for (film, filtered, mut image) in &mut cameras {
        image.update(film, filtered);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use sylva_engine::film::FrameBuffer;

    #[test]
    fn the_image_holds_the_films_means_and_the_png_bytes() {
        let mut film = Film::new(3, 2);
        film.accumulate(&FrameBuffer::new(3, 2, 0));
        film.add_sample(0, 0, glam::Vec3::new(0.5, 1.0, 2.0));
        film.add_sample(2, 1, glam::Vec3::new(4.0, 0.0, 0.25));
        let mut image = FrameImage::new(0.5);
        image.update(&film, None);
        assert_eq!((image.width(), image.height(), image.frames()), (3, 2, 1));
        assert_eq!(&image.linear_rgba()[..4], &[0.5, 1.0, 2.0, 1.0]);
        assert_eq!(&image.linear_rgba()[20..], &[4.0, 0.0, 0.25, 1.0]);
        assert_eq!(image.srgba8(), film.to_srgba8(0.5).as_slice());
    }

    #[test]
    fn a_filtered_image_of_the_current_frame_is_shown_and_a_stale_one_is_not() {
        let mut film = Film::new(2, 1);
        film.accumulate(&FrameBuffer::new(2, 1, 0));
        film.add_sample(0, 0, glam::Vec3::ONE);
        let filtered = |frames| FilteredImage {
            pixels: vec![glam::Vec3::splat(0.25); 2],
            frames,
        };
        let mut image = FrameImage::new(0.0);
        image.update(&film, Some(&filtered(1)));
        assert_eq!(&image.linear_rgba()[..3], &[0.25, 0.25, 0.25]);
        image.update(&film, Some(&filtered(7)));
        assert_eq!(&image.linear_rgba()[..3], &[1.0, 1.0, 1.0]);
    }
}
