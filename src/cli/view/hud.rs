//! The heads-up display: the frame's figures rasterised as text over the image.

use super::*;

/// The heads-up display: the frame's figures as text over its top-left corner.
pub(super) struct Hud {
    pub(super) font: ab_glyph::FontRef<'static>,
    /// Instanced triangles of the scene as built.
    pub(super) triangles: u64,
}

/// Text height of the HUD in pixels.
pub(super) const HUD_TEXT: f32 = 14.0;

impl Hud {
    /// What the HUD says about `shown`.
    pub(super) fn lines(
        &self,
        shown: &ShownImage,
        speed: f32,
        responsiveness: &Responsiveness,
    ) -> Vec<String> {
        let ms = |d: Duration| d.as_secs_f64() * 1e3;
        let fps = 1.0 / shown.frame_time.as_secs_f64().max(1e-6);
        let memory =
            current_memory_bytes().map_or("?".to_string(), |b| format!("{:.0} MB", b as f64 / 1e6));
        let latency = responsiveness
            .latency()
            .map_or("-".to_string(), |d| format!("{:.0} ms", ms(d)));
        vec![
            format!(
                "{:.1} fps  {} spp  {:.2} M rays/s",
                fps,
                shown.frames,
                shown.rays_per_second / 1e6
            ),
            format!(
                "shown {} images/s  input to image {latency}",
                responsiveness.shown_per_second()
            ),
            format!(
                "render {:.0} ms  filter {:.1} ms  top level {:.1} ms (refit {:.1})  tone map {:.1} ms",
                ms(shown.frame_time),
                ms(shown.filter),
                ms(shown.top_level.0),
                ms(shown.top_level.1),
                ms(shown.tone_map)
            ),
            format!(
                "{} instances  {} instanced triangles (as built)  memory {memory}",
                group(shown.instances as u64),
                group(self.triangles)
            ),
            format!(
                "{:.1} m/s  {}  H hides this",
                speed,
                shown
                    .selected
                    .map_or("nothing selected".to_string(), |e| format!(
                        "plant {e} selected"
                    ))
            ),
        ]
    }

    /// Draws `lines` in white on a darkened band at the top left of `buffer`.
    pub(super) fn draw(&self, buffer: &mut [u32], width: usize, height: usize, lines: &[String]) {
        use ab_glyph::{Font, ScaleFont, point};
        let scaled = self.font.as_scaled(HUD_TEXT);
        let line_height = scaled.height().ceil() as usize + 2;
        let band = (line_height * lines.len() + 6).min(height);
        let text_width = lines
            .iter()
            .map(|l| {
                l.chars()
                    .map(|c| scaled.h_advance(self.font.glyph_id(c)))
                    .sum::<f32>()
            })
            .fold(0.0f32, f32::max);
        let band_width = ((text_width.ceil() as usize) + 12).min(width);
        for row in buffer.chunks_exact_mut(width).take(band) {
            for pixel in &mut row[..band_width] {
                // Halve each channel: the image stays visible under the text.
                *pixel = (*pixel >> 1) & 0x007f_7f7f;
            }
        }
        for (i, line) in lines.iter().enumerate() {
            let mut x = 6.0;
            let baseline = 3.0 + scaled.ascent() + (i * line_height) as f32;
            for c in line.chars() {
                let glyph = self
                    .font
                    .glyph_id(c)
                    .with_scale_and_position(HUD_TEXT, point(x, baseline));
                x += scaled.h_advance(glyph.id);
                let Some(outline) = self.font.outline_glyph(glyph) else {
                    continue;
                };
                let bounds = outline.px_bounds();
                outline.draw(|gx, gy, coverage| {
                    let px = bounds.min.x as i64 + i64::from(gx);
                    let py = bounds.min.y as i64 + i64::from(gy);
                    if px < 0 || py < 0 || px as usize >= width || py as usize >= height {
                        return;
                    }
                    let pixel = &mut buffer[py as usize * width + px as usize];
                    let blend = |shift: u32| {
                        let under = ((*pixel >> shift) & 0xff) as f32;
                        ((under + (255.0 - under) * coverage.clamp(0.0, 1.0)) as u32) << shift
                    };
                    *pixel = blend(16) | blend(8) | blend(0);
                });
            }
        }
    }
}

/// Resident memory of this process now (Linux `VmRSS`), when known.
pub(super) fn current_memory_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}
