//! The map panel (Tab): the ecosystem from above, every plant a disc by species and
//! crown, clicks and drags that select, move and plant.

use super::*;

/// The editor's top-down map: a square panel at the bottom right of the window with
/// every plant as a circle coloured by species and sized by its crown.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct MapView {
    /// Panel's top-left pixel and side.
    pub(super) left: f32,
    pub(super) top: f32,
    pub(super) side: f32,
    /// World (x, z) at the panel's top-left, and pixels per metre.
    pub(super) origin: glam::Vec2,
    pub(super) scale: f32,
}

impl MapView {
    /// The panel for a `width × height` window showing `plants` (their spread, padded).
    pub(super) fn new(
        width: u32,
        height: u32,
        plants: &[sylva::systems::picking::MapPlant],
    ) -> Self {
        let side = (width.min(height) as f32 * 0.45).floor();
        let (lo, hi) = plants.iter().fold(
            (
                glam::Vec2::splat(f32::INFINITY),
                glam::Vec2::splat(f32::NEG_INFINITY),
            ),
            |(lo, hi), p| (lo.min(p.position), hi.max(p.position)),
        );
        let (lo, hi) = if lo.x <= hi.x {
            (lo, hi)
        } else {
            (glam::Vec2::ZERO, glam::Vec2::ONE)
        };
        let extent = (hi - lo).max_element().max(1.0) * 1.04;
        let centre = (lo + hi) * 0.5;
        Self {
            left: width as f32 - side - 6.0,
            top: height as f32 - side - 6.0,
            side,
            origin: centre - glam::Vec2::splat(extent * 0.5),
            scale: side / extent,
        }
    }

    pub(super) fn contains(self, x: f32, y: f32) -> bool {
        x >= self.left && y >= self.top && x < self.left + self.side && y < self.top + self.side
    }

    pub(super) fn to_panel(self, world: glam::Vec2) -> glam::Vec2 {
        glam::Vec2::new(self.left, self.top) + (world - self.origin) * self.scale
    }

    pub(super) fn to_world(self, x: f32, y: f32) -> glam::Vec2 {
        self.origin + (glam::Vec2::new(x, y) - glam::Vec2::new(self.left, self.top)) / self.scale
    }

    /// The plant drawn under panel pixel `(x, y)`: the nearest whose circle (at least
    /// three pixels wide) holds it.
    pub(super) fn plant_at(
        &self,
        plants: &[sylva::systems::picking::MapPlant],
        x: f32,
        y: f32,
    ) -> Option<Entity> {
        let at = self.to_world(x, y);
        plants
            .iter()
            .map(|p| (p, p.position.distance(at)))
            .filter(|(p, d)| *d <= p.radius.max(3.0 / self.scale))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(p, _)| p.entity)
    }

    /// Draws the panel into `buffer` (`width` pixels a row).
    pub(super) fn draw(
        &self,
        buffer: &mut [u32],
        width: usize,
        plants: &[sylva::systems::picking::MapPlant],
        selected: Option<Entity>,
    ) {
        let height = buffer.len() / width.max(1);
        let (x0, y0, side) = (self.left as usize, self.top as usize, self.side as usize);
        for row in y0..(y0 + side).min(height) {
            for pixel in
                &mut buffer[row * width + x0..(row * width + x0 + side).min((row + 1) * width)]
            {
                *pixel = 0x0020_2820;
            }
        }
        let mut disc = |centre: glam::Vec2, radius: f32, colour: u32| {
            let r = radius.max(0.7);
            let (lo, hi) = (centre - r, centre + r);
            for y in lo.y.floor().max(self.top) as usize
                ..=hi.y.ceil().min(self.top + self.side - 1.0) as usize
            {
                for x in lo.x.floor().max(self.left) as usize
                    ..=hi.x.ceil().min(self.left + self.side - 1.0) as usize
                {
                    let d = glam::Vec2::new(x as f32 + 0.5, y as f32 + 0.5) - centre;
                    if (d.length() <= r || r < 1.0) && y < height && x < width {
                        buffer[y * width + x] = colour;
                    }
                }
            }
        };
        // Larger plants first, so the small ones under them stay visible.
        let mut order: Vec<&sylva::systems::picking::MapPlant> = plants.iter().collect();
        order.sort_by(|a, b| b.radius.total_cmp(&a.radius));
        for plant in order {
            disc(
                self.to_panel(plant.position),
                plant.radius * self.scale,
                species_colour(plant.species),
            );
        }
        if let Some(p) = plants.iter().find(|p| Some(p.entity) == selected) {
            let centre = self.to_panel(p.position);
            disc(centre, (p.radius * self.scale).max(3.0) + 2.0, 0x00ff_ffff);
            disc(
                centre,
                (p.radius * self.scale).max(3.0),
                species_colour(p.species),
            );
        }
    }
}

/// A bright, stable colour per species.
pub(super) fn species_colour(species: u32) -> u32 {
    let h = sylva::engine::sampling::mix64(u64::from(species) + 17);
    let channel = |shift: u32| 0x40 + ((h >> shift) & 0xff) as u32 * 3 / 4;
    (channel(0) << 16) | (channel(8) << 8) | channel(16)
}
