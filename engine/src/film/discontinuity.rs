//! The discontinuity buffer (Keller & Heidrich 2001; Wald et al. 2002): the display
//! filter that finishes interleaved sampling. Each pixel averages the *light* it
//! received — its radiance divided by its albedo — over an N×N window of neighbours that
//! see the same surface (same shader, close depth and normal), then multiplies its own
//! albedo back, so textures stay sharp and light does not bleed across edges. It runs on
//! what is shown or written, never on the film being accumulated, so progressive
//! refinement stays unbiased.

use crate::film::SurfaceGuide;
use bevy_ecs::component::Component;
use glam::{UVec4, Vec3, Vec3A, Vec4};
use rayon::prelude::*;

/// What the filter reads: a `width`×`height` image's per-pixel radiance and albedo
/// means and the surface each pixel saw, row-major.
#[derive(Clone, Copy, Debug)]
pub struct GuidedImage<'a> {
    /// Pixels per row.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Mean radiance per pixel.
    pub radiance: &'a [Vec3],
    /// Mean albedo per pixel (what the reflected radiance was modulated by).
    pub albedo: &'a [Vec3],
    /// Mean emitted radiance per pixel: the part of `radiance` the filter leaves as it
    /// is (emission is the surface's own, like its texture, not light it received).
    pub emission: &'a [Vec3],
    /// The surface each pixel saw first.
    pub surfaces: &'a [SurfaceGuide],
}

/// A camera's filtered image: per-pixel means of its film after [`DiscontinuityFilter`],
/// for display and output (the film itself stays unfiltered).
#[derive(Component, Clone, Debug, PartialEq)]
pub struct FilteredImage {
    /// Row-major filtered means.
    pub pixels: Vec<Vec3>,
    /// Frames the film held when it was filtered.
    pub frames: u32,
}

/// Settings of the filter, as a camera component: cameras without it are not filtered.
#[derive(Component, Clone, Copy, Debug, PartialEq)]
pub struct DiscontinuityFilter {
    /// Window size N (the interleaving pattern's): every N×N window holds each of its
    /// pixel classes once. 1 leaves the image as it is.
    pub window: u32,
    /// Largest distance of a neighbour on the same surface from the pixel's tangent
    /// plane, relative to the pixel's distance from the camera.
    pub depth_tolerance: f32,
    /// Smallest cosine between the normals of a neighbour on the same surface.
    pub normal_cosine: f32,
}

impl DiscontinuityFilter {
    /// The filter for interleaving with an N×N pattern: 2 % of the depth off the tangent
    /// plane, 25° between normals.
    pub fn for_pattern(window: u32) -> Self {
        Self {
            window: window.max(1),
            depth_tolerance: 0.02,
            normal_cosine: 0.9,
        }
    }

    /// How much of the filtered image to show over a film of `frames` frames: all of it
    /// for the first frame, fading linearly to none once every pixel has been through
    /// the whole N×N pattern (N² frames). By then the average over the window adds
    /// little but its bias (light smeared within a surface): at 16 frames of `meadow` the
    /// fully filtered image had 3× the error of the raw one.
    pub fn strength(&self, frames: u32) -> f32 {
        let cycle = (self.window * self.window) as f32;
        (1.0 - frames.saturating_sub(1) as f32 / (cycle - 1.0).max(1.0)).clamp(0.0, 1.0)
    }

    /// [`apply`](Self::apply) at the [`strength`](Self::strength) for a film of `frames`
    /// frames: a blend of the filtered and the raw means.
    pub fn apply_progressive(&self, frames: u32, image: &GuidedImage) -> Vec<Vec3> {
        let strength = self.strength(frames);
        if strength == 0.0 {
            return image.radiance.to_vec();
        }
        let filtered = self.apply(image);
        filtered
            .iter()
            .zip(image.radiance)
            .map(|(f, r)| *r + (*f - *r) * strength)
            .collect()
    }

    /// True when pixel surfaces `a` and `b` are the same surface for the filter: same
    /// shader, normals close, and `b` no farther from `a`'s tangent plane than the depth
    /// tolerance. (Distances from the camera do not separate parallel surfaces seen at a
    /// grazing angle: two floors 1 m apart, 20 m away, lie within 2 % of each other.)
    #[cfg(test)]
    fn same_surface(&self, a: &SurfaceGuide, b: &SurfaceGuide) -> bool {
        a.shader == b.shader
            && b.is_surface()
            && a.normal.dot(b.normal) >= self.normal_cosine
            && a.normal.dot(b.position - a.position).abs() <= self.depth_tolerance * a.depth
    }

    /// Filters an image: its per-pixel radiance guided by albedo and surfaces. Pixels
    /// without a surface, or with an albedo channel too dark to divide by, keep their
    /// radiance; so do neighbours' contributions that cannot be demodulated (they are left
    /// out of the average).
    ///
    /// Each window row's neighbours are judged four at a time: the surfaces are split
    /// into one array per value, and the normal and tangent-plane tests run in four lanes
    /// with the scalar test's operations in its order, so the same neighbours pass and
    /// their light adds up in the same order: the result is the one-by-one filter's to
    /// the bit (`paper`'s interactive frame at 640×480: 19.5–22 → 13.4–15 ms).
    pub fn apply(&self, image: &GuidedImage) -> Vec<Vec3> {
        let &GuidedImage {
            width,
            height,
            radiance,
            albedo,
            emission,
            surfaces,
        } = image;
        let (w, h) = (width as usize, height as usize);
        assert!(
            radiance.len() == w * h
                && albedo.len() == w * h
                && emission.len() == w * h
                && surfaces.len() == w * h,
            "filter buffers must hold width × height pixels"
        );
        let n = self.window as isize;
        // A centred window: offsets -(n/2) .. n - 1 - n/2 cover every pixel class once.
        let (lo, hi) = (-(n / 2), n - 1 - n / 2);
        let mut out = radiance.to_vec();
        if n <= 1 || w == 0 || h == 0 {
            return out;
        }
        let pixels = Pixels::new(image);
        // Rows in parallel on the current rayon pool; each pixel's result depends only on
        // the inputs, so the image is the same for any thread count.
        out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            let rows = y.saturating_add_signed(lo)..=y.saturating_add_signed(hi).min(h - 1);
            for (x, pixel) in row.iter_mut().enumerate() {
                let i = y * w + x;
                if !pixels.usable[i] {
                    continue;
                }
                let key = pixels.keys[i];
                let here = &surfaces[i];
                let columns = x.saturating_add_signed(lo)..=x.saturating_add_signed(hi).min(w - 1);
                let (mut light, mut count) = (Vec3A::ZERO, 0u32);
                let mut gather = |first: usize, mut same: u32| {
                    while same != 0 {
                        light += pixels.lights[first + same.trailing_zeros() as usize];
                        count += 1;
                        same &= same - 1;
                    }
                };
                let width = columns.end() - columns.start() + 1;
                for ny in rows.clone() {
                    let mut first = ny * w + columns.start();
                    if width == LANES {
                        // A whole window row in one group (N = 4 away from the sides).
                        let mut same = pixels.same_surfaces(self, here, key, first, LANES);
                        if ny == y {
                            same |= 1 << (x - columns.start());
                        }
                        gather(first, same);
                        continue;
                    }
                    let last = ny * w + columns.end();
                    while first <= last {
                        let lanes = (last - first + 1).min(LANES);
                        let mut same = pixels.same_surfaces(self, here, key, first, lanes);
                        if (first..first + lanes).contains(&i) {
                            same |= 1 << (i - first);
                        }
                        gather(first, same);
                        first += lanes;
                    }
                }
                *pixel = albedo[i] * Vec3::from(light) / count as f32;
                if emission[i] != Vec3::ZERO {
                    *pixel += emission[i];
                }
            }
        });
        out
    }
}

/// Neighbours judged at once.
const LANES: usize = 4;

/// The key of a pixel that takes no part: no surface, or an albedo too dark to divide
/// by. A usable pixel whose shader id is this value too is still told apart, by
/// [`Pixels::usable`].
const NOT_USABLE: u32 = u32::MAX;

/// The filter's per-pixel inputs, computed once per pixel rather than once per window
/// that holds it (N² times), its surfaces one array per value so that four neighbours'
/// load as one register each. Every array is padded by [`LANES`] so that a group of
/// four starting at any pixel can be read whole.
struct Pixels {
    /// Received light: radiance less emission, divided by albedo (in SSE registers:
    /// the adds are the same per channel, one instruction instead of three).
    lights: Vec<Vec3A>,
    /// Shader id where the pixel takes part, [`NOT_USABLE`] where not.
    keys: Vec<u32>,
    /// Whether the pixel takes part (for the shader id equal to [`NOT_USABLE`]).
    usable: Vec<bool>,
    /// The surface normals' x, y and z.
    normal: [Vec<f32>; 3],
    /// The hit points' x, y and z.
    position: [Vec<f32>; 3],
}

impl Pixels {
    fn new(image: &GuidedImage) -> Self {
        const DARKEST: f32 = 1e-4;
        /// Pixels per parallel job of the one pass that fills every array.
        const CHUNK: usize = 4096;
        let len = image.radiance.len() + LANES;
        let mut pixels = Self {
            lights: vec![Vec3A::ZERO; len],
            keys: vec![NOT_USABLE; len],
            usable: vec![false; len],
            normal: std::array::from_fn(|_| vec![0.0; len]),
            position: std::array::from_fn(|_| vec![0.0; len]),
        };
        let Self {
            lights,
            keys,
            usable,
            normal: [nx, ny, nz],
            position: [px, py, pz],
        } = &mut pixels;
        (
            lights.par_chunks_mut(CHUNK),
            keys.par_chunks_mut(CHUNK),
            usable.par_chunks_mut(CHUNK),
            nx.par_chunks_mut(CHUNK),
            ny.par_chunks_mut(CHUNK),
            nz.par_chunks_mut(CHUNK),
            px.par_chunks_mut(CHUNK),
            py.par_chunks_mut(CHUNK),
            pz.par_chunks_mut(CHUNK),
        )
            .into_par_iter()
            .enumerate()
            .for_each(|(chunk, (lights, keys, usable, nx, ny, nz, px, py, pz))| {
                let start = chunk * CHUNK;
                let end = (start + CHUNK).min(image.radiance.len());
                for (k, i) in (start..end).enumerate() {
                    let (r, a, e, s) = (
                        image.radiance[i],
                        image.albedo[i],
                        image.emission[i],
                        &image.surfaces[i],
                    );
                    // Emission comes off before dividing and goes back on after; where
                    // the film's mean and this frame's emission disagree (emissive edges)
                    // the received light is kept from going negative.
                    let received = if e == Vec3::ZERO {
                        r
                    } else {
                        (r - e).max(Vec3::ZERO)
                    };
                    lights[k] = Vec3A::from(received / a);
                    usable[k] = s.is_surface() && a.min_element() > DARKEST;
                    keys[k] = if usable[k] { s.shader } else { NOT_USABLE };
                    [nx[k], ny[k], nz[k]] = s.normal.to_array();
                    [px[k], py[k], pz[k]] = s.position.to_array();
                }
            });
        pixels
    }

    /// Bit `l` set when pixel `first + l` (of the first `lanes`) is usable and on the
    /// same surface as `here` (whose key is `key`), as
    /// the one-by-one rule (`same_surface`, which the tests keep as the oracle) judges.
    #[inline(always)]
    fn same_surfaces(
        &self,
        filter: &DiscontinuityFilter,
        here: &SurfaceGuide,
        key: u32,
        first: usize,
        lanes: usize,
    ) -> u32 {
        let mut candidates = UVec4::from_slice(&self.keys[first..first + LANES])
            .cmpeq(UVec4::splat(key))
            .bitmask();
        if key == NOT_USABLE {
            for lane in 0..LANES {
                candidates &= !(u32::from(!self.usable[first + lane]) << lane);
            }
        }
        candidates &= (1 << lanes) - 1;
        if candidates == 0 {
            return 0;
        }
        let load = |values: &[f32]| Vec4::from_slice(&values[first..first + LANES]);
        let [nx, ny, nz] = self.normal.each_ref().map(|v| load(v));
        let [px, py, pz] = self.position.each_ref().map(|v| load(v));
        let (a, p) = (here.normal, here.position);
        // `a.normal.dot(b.normal)` and `a.normal.dot(b.position - a.position)` as glam's
        // scalar `Vec3::dot` computes them: (x·x + y·y) + z·z.
        let facing = Vec4::splat(a.x) * nx + Vec4::splat(a.y) * ny + Vec4::splat(a.z) * nz;
        let off_plane = Vec4::splat(a.x) * (px - Vec4::splat(p.x))
            + Vec4::splat(a.y) * (py - Vec4::splat(p.y))
            + Vec4::splat(a.z) * (pz - Vec4::splat(p.z));
        let close = facing.cmpge(Vec4::splat(filter.normal_cosine))
            & off_plane
                .abs()
                .cmple(Vec4::splat(filter.depth_tolerance * here.depth));
        candidates & close.bitmask()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::test_random::uniform;

    /// The filter neighbour by neighbour, as it was before the four-lane judging: the
    /// oracle the fast filter must equal to the bit.
    fn apply_one_by_one(filter: &DiscontinuityFilter, image: &GuidedImage) -> Vec<Vec3> {
        const DARKEST: f32 = 1e-4;
        let (w, h) = (image.width as usize, image.height as usize);
        let n = filter.window as isize;
        let (lo, hi) = (-(n / 2), n - 1 - n / 2);
        let mut out = image.radiance.to_vec();
        if n <= 1 || w == 0 || h == 0 {
            return out;
        }
        let lights: Vec<Vec3> = (0..w * h)
            .map(|i| {
                let (r, e) = (image.radiance[i], image.emission[i]);
                let received = if e == Vec3::ZERO {
                    r
                } else {
                    (r - e).max(Vec3::ZERO)
                };
                received / image.albedo[i]
            })
            .collect();
        let usable: Vec<bool> = (0..w * h)
            .map(|i| image.surfaces[i].is_surface() && image.albedo[i].min_element() > DARKEST)
            .collect();
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                if !usable[i] {
                    continue;
                }
                let (mut light, mut count) = (Vec3::ZERO, 0u32);
                for ny in y.saturating_add_signed(lo)..=y.saturating_add_signed(hi).min(h - 1) {
                    for nx in x.saturating_add_signed(lo)..=x.saturating_add_signed(hi).min(w - 1) {
                        let j = ny * w + nx;
                        if j == i
                            || (usable[j]
                                && filter.same_surface(&image.surfaces[i], &image.surfaces[j]))
                        {
                            light += lights[j];
                            count += 1;
                        }
                    }
                }
                out[i] = image.albedo[i] * light / count as f32;
                if image.emission[i] != Vec3::ZERO {
                    out[i] += image.emission[i];
                }
            }
        }
        out
    }

    #[test]
    fn four_neighbours_at_once_give_the_one_by_one_filter_to_the_bit() {
        let mut state = 0x5eed_f11e_u64;
        let mut random = move || uniform(&mut state);
        for (width, height) in [(1, 1), (2, 3), (5, 1), (7, 5), (33, 17), (64, 48), (3, 40)] {
            let len = width * height;
            let mut surfaces = Vec::with_capacity(len);
            let (mut radiance, mut albedo, mut emission) = (vec![], vec![], vec![]);
            for _ in 0..len {
                let kind = random();
                let surface = if kind < 0.1 {
                    SurfaceGuide::NONE
                } else {
                    let shader = [0, 1, 2, u32::MAX][(random() * 4.0) as usize];
                    let normal = match (random() * 10.0) as u32 {
                        0 => Vec3::ZERO,
                        1 => Vec3::NAN,
                        k => {
                            let base = [Vec3::Z, Vec3::Y, Vec3::new(0.6, 0.8, 0.0)][k as usize % 3];
                            (base + 0.3 * Vec3::new(random(), random(), random()) - 0.15)
                                .normalize()
                        }
                    };
                    let depth = 1.0 + 9.0 * random();
                    let position = Vec3::new(random(), random(), -depth)
                        * [1.0, 1.0, 1.01][(random() * 3.0) as usize];
                    SurfaceGuide {
                        depth,
                        position,
                        normal,
                        shader,
                    }
                };
                surfaces.push(surface);
                let texture = Vec3::new(random(), random(), random());
                albedo.push(if random() < 0.05 {
                    texture * 1e-5
                } else {
                    texture
                });
                radiance.push(texture * 3.0 * random());
                emission.push(if random() < 0.1 {
                    Vec3::splat(random())
                } else {
                    Vec3::ZERO
                });
            }
            let image = GuidedImage {
                width: width as u32,
                height: height as u32,
                radiance: &radiance,
                albedo: &albedo,
                emission: &emission,
                surfaces: &surfaces,
            };
            for window in 1..=6 {
                let filter = DiscontinuityFilter {
                    window,
                    depth_tolerance: 0.02 + 0.2 * random(),
                    normal_cosine: 0.5 + 0.5 * random(),
                };
                let bits = |pixels: Vec<Vec3>| -> Vec<[u32; 3]> {
                    pixels
                        .iter()
                        .map(|p| p.to_array().map(f32::to_bits))
                        .collect()
                };
                assert_eq!(
                    bits(filter.apply(&image)),
                    bits(apply_one_by_one(&filter, &image)),
                    "{width}×{height}, window {window}"
                );
            }
        }
    }

    /// A point of the plane z = −depth facing a camera at the origin.
    fn plane(x: f32, y: f32, depth: f32, shader: u32) -> SurfaceGuide {
        SurfaceGuide {
            depth,
            position: Vec3::new(x, y, -depth),
            normal: Vec3::Z,
            shader,
        }
    }

    /// An 8×8 image, left half a near plane, right half a far one with another shader;
    /// light alternates per pixel (the interleaving pattern) around a different mean on
    /// each side; albedo is a checkerboard texture.
    fn two_planes() -> (Vec<Vec3>, Vec<Vec3>, Vec<SurfaceGuide>) {
        let (mut radiance, mut albedo, mut surfaces) = (vec![], vec![], vec![]);
        for y in 0..8 {
            for x in 0..8 {
                let texture = if (x + y) % 2 == 0 { 0.2 } else { 0.8 };
                let (mean_light, surface) = if x < 4 {
                    (1.0, plane(x as f32 * 0.01, y as f32 * 0.01, 2.0, 0))
                } else {
                    (10.0, plane(x as f32 * 0.1, y as f32 * 0.1, 20.0, 1))
                };
                let light = mean_light * if (x + 2 * y) % 4 < 2 { 0.5 } else { 1.5 };
                radiance.push(Vec3::splat(texture * light));
                albedo.push(Vec3::splat(texture));
                surfaces.push(surface);
            }
        }
        (radiance, albedo, surfaces)
    }

    /// No emission, for images of up to 64 pixels.
    static DARK: [Vec3; 64] = [Vec3::ZERO; 64];

    fn image<'a>(
        width: u32,
        height: u32,
        radiance: &'a [Vec3],
        albedo: &'a [Vec3],
        surfaces: &'a [SurfaceGuide],
    ) -> GuidedImage<'a> {
        GuidedImage {
            width,
            height,
            radiance,
            albedo,
            emission: &DARK[..radiance.len()],
            surfaces,
        }
    }

    #[test]
    fn emission_stays_sharp_while_received_light_is_averaged() {
        let (radiance, albedo, surfaces) = two_planes();
        let plain =
            DiscontinuityFilter::for_pattern(4).apply(&image(8, 8, &radiance, &albedo, &surfaces));
        // Every third pixel glows on top of the light it receives.
        let emission: Vec<Vec3> = (0..64)
            .map(|i| {
                if i % 3 == 0 {
                    Vec3::new(4.0, 2.0, 1.0)
                } else {
                    Vec3::ZERO
                }
            })
            .collect();
        let glowing: Vec<Vec3> = radiance
            .iter()
            .zip(&emission)
            .map(|(r, e)| *r + *e)
            .collect();
        let filtered = DiscontinuityFilter::for_pattern(4).apply(&GuidedImage {
            emission: &emission,
            ..image(8, 8, &glowing, &albedo, &surfaces)
        });
        for i in 0..64 {
            let expected = plain[i] + emission[i];
            assert!(
                (filtered[i] - expected).abs().max_element() < 1e-5 * expected.max_element(),
                "pixel {i}: {} against {expected}",
                filtered[i]
            );
        }
    }

    #[test]
    fn light_is_averaged_on_a_surface_and_never_across_an_edge() {
        let (radiance, albedo, surfaces) = two_planes();
        let filtered =
            DiscontinuityFilter::for_pattern(4).apply(&image(8, 8, &radiance, &albedo, &surfaces));
        for y in 0..8 {
            for x in 0..8 {
                let i = y * 8 + x;
                let light = filtered[i].x / albedo[i].x;
                // Each side's light lies between its own extremes, whatever the window
                // reaches across the edge at x = 4.
                let (low, high) = if x < 4 { (0.5, 1.5) } else { (5.0, 15.0) };
                assert!(
                    (low..=high).contains(&light),
                    "pixel ({x}, {y}): light {light} leaked across the edge"
                );
            }
        }
        // Inside each half, away from the image border, the window holds both phases of
        // the pattern equally: the light is the half's mean.
        for (x, mean) in [(2, 1.0), (6, 10.0)] {
            let i = 4 * 8 + x;
            let light = filtered[i].x / albedo[i].x;
            assert!(
                (light - mean).abs() < 1e-5,
                "x = {x}: {light} instead of {mean}"
            );
        }
        // The texture survives: vertical neighbours with full windows keep their albedo
        // ratio (0.8 against 0.2).
        assert!((filtered[5 * 8 + 2].x / filtered[4 * 8 + 2].x - 4.0).abs() < 1e-4);
    }

    /// Two parallel floors 1 m apart seen at a grazing angle: their pixels lie within 2 %
    /// of each other's distance from the camera, so only the distance from the tangent
    /// plane tells them apart (a test on camera distance let the light through).
    #[test]
    fn parallel_surfaces_at_a_grazing_angle_stay_apart() {
        let floor = |y: f32, z: f32| SurfaceGuide {
            depth: Vec3::new(0.0, y, z).length(),
            position: Vec3::new(0.0, y, z),
            normal: Vec3::Y,
            shader: 0,
        };
        let surfaces = [
            floor(-1.0, -20.0),
            floor(-1.0, -20.1),
            floor(-2.0, -20.3),
            floor(-2.0, -20.4),
        ];
        assert!((surfaces[2].depth - surfaces[1].depth).abs() < 0.02 * surfaces[1].depth);
        let albedo = [Vec3::splat(0.5); 4];
        let radiance = [0.5, 0.5, 5.0, 5.0].map(Vec3::splat);
        let filtered =
            DiscontinuityFilter::for_pattern(4).apply(&image(4, 1, &radiance, &albedo, &surfaces));
        assert_eq!(filtered, radiance);
    }

    #[test]
    fn strength_fades_from_full_to_none_over_one_pattern_cycle() {
        let filter = DiscontinuityFilter::for_pattern(4);
        assert_eq!(filter.strength(1), 1.0);
        assert!((filter.strength(6) - 2.0 / 3.0).abs() < 1e-6);
        assert_eq!(filter.strength(16), 0.0);
        assert_eq!(filter.strength(1000), 0.0);
        let (radiance, albedo, surfaces) = two_planes();
        let late = filter.apply_progressive(16, &image(8, 8, &radiance, &albedo, &surfaces));
        assert_eq!(late, radiance);
        let first = filter.apply_progressive(1, &image(8, 8, &radiance, &albedo, &surfaces));
        assert_eq!(
            first,
            filter.apply(&image(8, 8, &radiance, &albedo, &surfaces))
        );
    }

    #[test]
    fn sky_pixels_dark_albedo_and_window_one_are_left_alone() {
        let (mut radiance, mut albedo, mut surfaces) = two_planes();
        surfaces[9] = SurfaceGuide::NONE;
        albedo[18] = Vec3::new(0.5, 0.0, 0.5);
        radiance[18] = Vec3::new(0.3, 0.0, 0.4);
        let filtered =
            DiscontinuityFilter::for_pattern(4).apply(&image(8, 8, &radiance, &albedo, &surfaces));
        assert_eq!(filtered[9], radiance[9]);
        assert_eq!(filtered[18], radiance[18]);
        let unfiltered =
            DiscontinuityFilter::for_pattern(1).apply(&image(8, 8, &radiance, &albedo, &surfaces));
        assert_eq!(unfiltered, radiance);
    }
}
