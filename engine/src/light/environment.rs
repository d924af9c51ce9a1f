//! HDR environment light (§4.2 of the paper): a latitude–longitude radiance map,
//! discretised into a fixed set of virtual directional lights by median cut, sampled per
//! shading point in proportion to the lights' luminance.
//!
//! Mapping (+Y up), OpenEXR's lat-long convention: a direction `d` lands at
//! `u = 0.5 − atan2(d.x, d.z) / 2π`, `v = acos(d.y) / π`; `v = 0` is the top row (zenith),
//! `u = 0.5` looks along +Z, `u = 0.25` along +X, and moving right in the image turns
//! right (from +X towards +Z). A test pins it to the labelled `OrientationLatLong.exr`.
//!
//! Why median cut (Debevec 2005): every region it makes holds the same energy, so the
//! lights follow the map's importance (a bright sun ends up in many tiny regions of its
//! own, never smeared into a large one — no fireflies from a sun hidden in a big sky
//! light), while the recursive splits keep the set stratified over the whole sphere.
//! Each light sits at its region's energy centroid and carries the region's exact
//! integral of radiance × solid angle, so the set's total power equals the map's.

pub use crate::util::color::luminance;
use glam::{Vec3, Vec3A};
use std::f32::consts::{PI, TAU};

/// Why an environment map was refused.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum EnvironmentError {
    /// Zero width or height.
    #[error("the map has zero size ({width}x{height})")]
    Empty {
        /// Width.
        width: u32,
        /// Height.
        height: u32,
    },
    /// Texel count does not match the dimensions.
    #[error("the map is {width}x{height} but has {found} texels")]
    SizeMismatch {
        /// Width.
        width: u32,
        /// Height.
        height: u32,
        /// Texels given.
        found: usize,
    },
}

/// A latitude–longitude map of linear RGB radiance.
#[derive(Clone, Debug, PartialEq)]
pub struct EnvironmentMap {
    width: u32,
    height: u32,
    texels: Vec<Vec3>,
}

/// The direction at the centre of lat-long coordinates `(u, v)` (see the module doc).
#[inline]
pub fn uv_to_direction(u: f32, v: f32) -> Vec3 {
    let (phi, theta) = ((0.5 - u) * TAU, v * PI);
    let (sin_t, cos_t) = theta.sin_cos();
    Vec3::new(sin_t * phi.sin(), cos_t, sin_t * phi.cos())
}

/// The lat-long coordinates of direction `d` (need not be unit length).
#[inline]
pub fn direction_to_uv(d: Vec3) -> (f32, f32) {
    let d = d.normalize_or(Vec3::Y);
    let u = 0.5 - d.x.atan2(d.z) / TAU;
    let v = d.y.clamp(-1.0, 1.0).acos() / PI;
    (u, v)
}

impl EnvironmentMap {
    /// Feeds the map's size and texels to `hash`.
    pub(crate) fn hash_into(&self, hash: &mut crate::util::fingerprint::Fingerprint) {
        hash.u32(self.width).u32(self.height);
        for texel in &self.texels {
            hash.f32(texel.x).f32(texel.y).f32(texel.z);
        }
    }

    /// A map from row-major texels, top row (zenith) first. Texels that are NaN,
    /// infinite or negative are set to zero; the second value counts them.
    pub fn new(
        width: u32,
        height: u32,
        mut texels: Vec<Vec3>,
    ) -> Result<(Self, usize), EnvironmentError> {
        if width == 0 || height == 0 {
            return Err(EnvironmentError::Empty { width, height });
        }
        if texels.len() != width as usize * height as usize {
            return Err(EnvironmentError::SizeMismatch {
                width,
                height,
                found: texels.len(),
            });
        }
        let mut repaired = 0;
        for t in &mut texels {
            if !t.is_finite() || t.min_element() < 0.0 {
                *t = Vec3::ZERO;
                repaired += 1;
            }
        }
        Ok((
            Self {
                width,
                height,
                texels,
            },
            repaired,
        ))
    }

    /// A map of one radiance everywhere.
    pub fn constant(radiance: Vec3) -> Self {
        Self::new(1, 1, vec![radiance]).expect("1×1").0
    }

    /// Width in texels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in texels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Texel `(x, y)`.
    pub fn texel(&self, x: u32, y: u32) -> Vec3 {
        self.texels[(y * self.width + x) as usize]
    }

    /// Solid angle of a texel in row `y`.
    pub fn texel_solid_angle(&self, y: u32) -> f32 {
        let (t0, t1) = (
            y as f32 / self.height as f32 * PI,
            (y + 1) as f32 / self.height as f32 * PI,
        );
        TAU / self.width as f32 * (t0.cos() - t1.cos())
    }

    /// Radiance seen along `d` (nearest texel).
    #[inline]
    pub fn radiance(&self, d: Vec3A) -> Vec3A {
        let (u, v) = direction_to_uv(d.into());
        let x = ((u.rem_euclid(1.0) * self.width as f32) as u32).min(self.width - 1);
        let y = ((v * self.height as f32) as u32).min(self.height - 1);
        self.texel(x, y).into()
    }

    /// ∫ L dω over the sphere, per channel.
    pub fn integral(&self) -> Vec3 {
        let mut sum = [0f64; 3];
        for y in 0..self.height {
            let omega = self.texel_solid_angle(y) as f64;
            for x in 0..self.width {
                let t = self.texel(x, y);
                for c in 0..3 {
                    sum[c] += t[c] as f64 * omega;
                }
            }
        }
        Vec3::new(sum[0] as f32, sum[1] as f32, sum[2] as f32)
    }
}

/// One light of the discretised environment.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VirtualLight {
    /// Unit direction toward the light.
    pub direction: Vec3,
    /// Irradiance on a surface facing it: the region's ∫ L dω (linear RGB).
    pub irradiance: Vec3,
    /// Probability of picking this light.
    pub probability: f32,
}

/// A fixed set of virtual directional lights and the CDF to sample them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct VirtualLights {
    lights: Vec<VirtualLight>,
    cdf: Vec<f32>,
    /// `guide[k]`: the CDF entries ≤ k / (guide.len() − 1), so a sample in bucket k
    /// searches only `guide[k]..guide[k + 1]` (the guide-table method: the same index
    /// as a binary search over the whole CDF, without its chain of dependent loads).
    guide: Vec<u32>,
}

/// A rectangle of texels `[x0, x1) × [y0, y1)` and its energy.
#[derive(Clone, Copy, Debug)]
struct Region {
    x0: u32,
    x1: u32,
    y0: u32,
    y1: u32,
    energy: f64,
}

/// Summed-area table of luminance × solid angle, for O(1) region energies.
struct EnergyTable {
    width: usize,
    sums: Vec<f64>,
}

impl EnergyTable {
    fn new(map: &EnvironmentMap) -> Self {
        let (w, h) = (map.width as usize, map.height as usize);
        let mut sums = vec![0f64; (w + 1) * (h + 1)];
        for y in 0..h {
            let omega = map.texel_solid_angle(y as u32) as f64;
            let mut row = 0f64;
            for x in 0..w {
                row += luminance(map.texel(x as u32, y as u32)) as f64 * omega;
                sums[(y + 1) * (w + 1) + x + 1] = sums[y * (w + 1) + x + 1] + row;
            }
        }
        Self { width: w, sums }
    }

    fn energy(&self, x0: u32, x1: u32, y0: u32, y1: u32) -> f64 {
        let at = |x: u32, y: u32| self.sums[y as usize * (self.width + 1) + x as usize];
        at(x1, y1) - at(x0, y1) - at(x1, y0) + at(x0, y0)
    }
}

impl VirtualLights {
    /// Median-cut discretisation into `count` lights (at most one per texel). Each split
    /// divides the most energetic splittable region along its longer side (measured in
    /// angle, the width shrunk by the cosine of the latitude) at the energy median.
    pub fn median_cut(map: &EnvironmentMap, count: usize) -> Self {
        let table = EnergyTable::new(map);
        let (w, h) = (map.width, map.height);
        let mut regions = vec![Region {
            x0: 0,
            x1: w,
            y0: 0,
            y1: h,
            energy: table.energy(0, w, 0, h),
        }];
        let count = count.clamp(1, (w * h) as usize);
        while regions.len() < count {
            let splittable = |r: &Region| r.x1 - r.x0 > 1 || r.y1 - r.y0 > 1;
            // Ties broken by index keep the result deterministic.
            let Some((index, _)) = regions
                .iter()
                .enumerate()
                .filter(|(_, r)| splittable(r))
                .max_by(|a, b| a.1.energy.total_cmp(&b.1.energy).then(b.0.cmp(&a.0)))
            else {
                break;
            };
            let r = regions[index];
            let latitude = ((r.y0 + r.y1) as f32 * 0.5 / h as f32 - 0.5) * PI;
            let angular_width = (r.x1 - r.x0) as f32 / w as f32 * TAU * latitude.cos();
            let angular_height = (r.y1 - r.y0) as f32 / h as f32 * PI;
            let split_x = r.x1 - r.x0 > 1 && (angular_width >= angular_height || r.y1 - r.y0 == 1);
            let (a, b) = if split_x {
                let cut = median(r.x0, r.x1, r.energy, |m| table.energy(r.x0, m, r.y0, r.y1));
                (
                    Region {
                        x1: cut,
                        energy: table.energy(r.x0, cut, r.y0, r.y1),
                        ..r
                    },
                    Region {
                        x0: cut,
                        energy: table.energy(cut, r.x1, r.y0, r.y1),
                        ..r
                    },
                )
            } else {
                let cut = median(r.y0, r.y1, r.energy, |m| table.energy(r.x0, r.x1, r.y0, m));
                (
                    Region {
                        y1: cut,
                        energy: table.energy(r.x0, r.x1, r.y0, cut),
                        ..r
                    },
                    Region {
                        y0: cut,
                        energy: table.energy(r.x0, r.x1, cut, r.y1),
                        ..r
                    },
                )
            };
            regions[index] = a;
            regions.push(b);
        }
        let mut lights: Vec<VirtualLight> = regions.iter().map(|r| region_light(map, r)).collect();
        // Neighbours in the list are neighbours on the sphere, so a stratum of the CDF
        // (an interleaved-sampling subset) is a compact patch of sky.
        lights.sort_by_key(|l| hilbert_key(l.direction));
        Self::from_lights(lights)
    }

    /// A set from given lights; probabilities are set proportional to luminance.
    pub fn from_lights(mut lights: Vec<VirtualLight>) -> Self {
        let total: f64 = lights.iter().map(|l| luminance(l.irradiance) as f64).sum();
        let mut cdf = Vec::with_capacity(lights.len());
        let mut running = 0f64;
        for l in &mut lights {
            let p = if total > 0.0 {
                luminance(l.irradiance) as f64 / total
            } else {
                0.0
            };
            l.probability = p as f32;
            running += p;
            cdf.push(running as f32);
        }
        if let Some(last) = cdf.last_mut() {
            *last = 1.0;
        }
        // A power of two of buckets, so `u · buckets` is exact and bucket k holds
        // exactly the u in [k / buckets, (k + 1) / buckets).
        let buckets = cdf.len().next_power_of_two().clamp(1, 1 << 16);
        let guide = (0..=buckets)
            .map(|k| {
                let at = k as f32 / buckets as f32;
                cdf.partition_point(|&c| c <= at) as u32
            })
            .collect();
        Self { lights, cdf, guide }
    }

    /// The lights.
    pub fn lights(&self) -> &[VirtualLight] {
        &self.lights
    }

    /// Number of lights.
    pub fn len(&self) -> usize {
        self.lights.len()
    }

    /// True when there are no lights (or none carries energy).
    pub fn is_empty(&self) -> bool {
        self.lights.is_empty() || self.cdf.is_empty()
    }

    /// The light a uniform number `u` in [0, 1) picks, with probability `probability`.
    #[inline]
    pub fn sample(&self, u: f32) -> Option<&VirtualLight> {
        let i = self.cdf_index(u).min(self.lights.len().checked_sub(1)?);
        let light = &self.lights[i];
        (light.probability > 0.0).then_some(light)
    }

    /// The CDF entries ≤ `u`: `cdf.partition_point(|&c| c <= u)`, through the guide
    /// table for `u` in [0, 1).
    #[inline]
    fn cdf_index(&self, u: f32) -> usize {
        let buckets = self.guide.len().saturating_sub(1);
        if !(0.0..1.0).contains(&u) || buckets == 0 {
            return self.cdf.partition_point(|&c| c <= u);
        }
        let k = ((u * buckets as f32) as usize).min(buckets - 1);
        let (lo, hi) = (self.guide[k] as usize, self.guide[k + 1] as usize);
        lo + self.cdf[lo..hi].partition_point(|&c| c <= u)
    }

    /// Sum of the lights' irradiance.
    pub fn total_irradiance(&self) -> Vec3 {
        self.lights.iter().map(|l| l.irradiance).sum()
    }
}

/// The energy median along one axis: the first cut `m` in `(lo, hi)` whose left part
/// holds at least half; falls back to the middle for regions without energy.
fn median(lo: u32, hi: u32, total: f64, left_energy: impl Fn(u32) -> f64) -> u32 {
    if total <= 0.0 {
        return lo + (hi - lo) / 2;
    }
    let (mut a, mut b) = (lo + 1, hi - 1);
    while a < b {
        let m = a + (b - a) / 2;
        if left_energy(m) >= total * 0.5 {
            b = m;
        } else {
            a = m + 1;
        }
    }
    a.clamp(lo + 1, hi - 1)
}

/// A region's light: exact ∫ L dω and the luminance-weighted centroid direction.
fn region_light(map: &EnvironmentMap, r: &Region) -> VirtualLight {
    let mut irradiance = [0f64; 3];
    let mut centroid = [0f64; 3];
    let mut plain = [0f64; 3];
    for y in r.y0..r.y1 {
        let omega = map.texel_solid_angle(y) as f64;
        for x in r.x0..r.x1 {
            let t = map.texel(x, y);
            let d = uv_to_direction(
                (x as f32 + 0.5) / map.width as f32,
                (y as f32 + 0.5) / map.height as f32,
            );
            let weight = luminance(t) as f64 * omega;
            for c in 0..3 {
                irradiance[c] += t[c] as f64 * omega;
                centroid[c] += d[c] as f64 * weight;
                plain[c] += d[c] as f64 * omega;
            }
        }
    }
    let to_vec = |a: [f64; 3]| Vec3::new(a[0] as f32, a[1] as f32, a[2] as f32);
    let direction = to_vec(centroid)
        .try_normalize()
        .or_else(|| to_vec(plain).try_normalize())
        .unwrap_or(Vec3::Y);
    VirtualLight {
        direction,
        irradiance: to_vec(irradiance),
        probability: 0.0,
    }
}

/// Position of direction `d` along a Hilbert curve over the octahedral map of the
/// sphere: nearby keys are nearby directions.
fn hilbert_key(d: Vec3) -> u64 {
    let n = d / (d.x.abs() + d.y.abs() + d.z.abs()).max(f32::MIN_POSITIVE);
    let (mut u, mut v) = (n.x, n.z);
    if n.y < 0.0 {
        (u, v) = (
            (1.0 - n.z.abs()) * n.x.signum(),
            (1.0 - n.x.abs()) * n.z.signum(),
        );
    }
    const SIDE: u32 = 1 << 16;
    let cell = |a: f32| (((a * 0.5 + 0.5) * SIDE as f32) as u32).min(SIDE - 1);
    let (mut x, mut y) = (cell(u), cell(v));
    let mut key = 0u64;
    let mut s = SIDE / 2;
    while s > 0 {
        let (rx, ry) = (u32::from(x & s > 0), u32::from(y & s > 0));
        key += u64::from(s) * u64::from(s) * u64::from((3 * rx) ^ ry);
        if ry == 0 {
            if rx == 1 {
                x = SIDE - 1 - x;
                y = SIDE - 1 - y;
            }
            std::mem::swap(&mut x, &mut y);
        }
        s /= 2;
    }
    key
}

/// The environment as the kernel uses it: the map for what camera rays see, and its
/// virtual lights for shading. As a component it makes a light entity; it replaces the
/// gradient sky while present.
#[derive(bevy_ecs::component::Component, Clone, Debug, PartialEq)]
pub struct EnvironmentLight {
    /// The radiance map.
    pub map: EnvironmentMap,
    /// Its discretisation.
    pub lights: VirtualLights,
}

impl EnvironmentLight {
    /// Discretises `map` into `count` virtual lights.
    pub fn new(map: EnvironmentMap, count: usize) -> Self {
        let lights = VirtualLights::median_cut(&map, count);
        Self { map, lights }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A map with a smooth sky and a small, very bright sun.
    fn sky_with_sun() -> EnvironmentMap {
        let (w, h) = (128, 64);
        let texels = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let sky = Vec3::new(0.3, 0.5, 0.9) * (1.0 - y as f32 / h as f32);
                if (40..42).contains(&x) && (10..12).contains(&y) {
                    Vec3::splat(50_000.0)
                } else {
                    sky
                }
            })
            .collect();
        EnvironmentMap::new(w, h, texels).unwrap().0
    }

    #[test]
    fn directions_and_coordinates_round_trip() {
        for i in 0..200 {
            let (u, v) = ((i as f32 * 0.618) % 1.0, 0.01 + (i as f32 * 0.377) % 0.98);
            let (u2, v2) = direction_to_uv(uv_to_direction(u, v));
            let du = (u - u2).rem_euclid(1.0).min((u2 - u).rem_euclid(1.0));
            assert!(du < 1e-4 && (v - v2).abs() < 1e-4, "{u},{v} -> {u2},{v2}");
        }
        assert!((uv_to_direction(0.5, 0.5) - Vec3::Z).length() < 1e-6);
        assert!((uv_to_direction(0.25, 0.5) - Vec3::X).length() < 1e-6);
        assert!((uv_to_direction(0.3, 0.0) - Vec3::Y).length() < 1e-6);
    }

    #[test]
    fn solid_angles_cover_the_sphere() {
        let map = EnvironmentMap::constant(Vec3::ONE);
        assert!((map.integral() - Vec3::splat(4.0 * PI)).abs().max_element() < 1e-4);
        let map = sky_with_sun();
        let total: f32 = (0..map.height())
            .map(|y| map.texel_solid_angle(y) * map.width() as f32)
            .sum();
        assert!((total - 4.0 * PI).abs() < 1e-3);
    }

    #[test]
    fn virtual_lights_carry_exactly_the_maps_power() {
        let map = sky_with_sun();
        for count in [1, 7, 64, 256, 1024] {
            let lights = VirtualLights::median_cut(&map, count);
            assert_eq!(lights.len(), count);
            let (total, expected) = (lights.total_irradiance(), map.integral());
            assert!(
                ((total - expected) / expected).abs().max_element() < 1e-4,
                "{count}: {total} vs {expected}"
            );
            let p: f32 = lights.lights().iter().map(|l| l.probability).sum();
            assert!((p - 1.0).abs() < 1e-4);
        }
    }

    #[test]
    fn the_sun_gets_its_own_lights_and_the_sky_is_still_covered() {
        let map = sky_with_sun();
        let lights = VirtualLights::median_cut(&map, 256);
        let sun = uv_to_direction(41.0 / 128.0, 11.0 / 64.0);
        // The sun covers 4 texels: median cut isolates each in a light of its own.
        let near_sun = lights
            .lights()
            .iter()
            .filter(|l| l.direction.dot(sun) > 0.995)
            .count();
        assert_eq!(near_sun, 4, "lights on the sun");
        // No light mixes the sun with a large part of the sky: every light far from the
        // sun is dim.
        for l in lights.lights() {
            if l.direction.dot(sun) < 0.9 {
                assert!(luminance(l.irradiance) < 1.0, "{l:?}");
            }
        }
        // Lights in every octant of the upper hemisphere's azimuths.
        for k in 0..8 {
            let az = k as f32 / 8.0;
            let any = lights.lights().iter().any(|l| {
                let (u, v) = direction_to_uv(l.direction);
                (u - az).rem_euclid(1.0) < 0.125 && v < 0.5
            });
            assert!(any, "no light in azimuth octant {k}");
        }
    }

    #[test]
    fn sampling_follows_the_probabilities() {
        // χ² over 64 lights with 200,000 stratified-random draws.
        let map = sky_with_sun();
        let lights = VirtualLights::median_cut(&map, 64);
        let n = 200_000;
        let mut counts = vec![0u32; lights.len()];
        let mut rng = crate::util::sampling::SplitMix64(7);
        for _ in 0..n {
            let l = lights.sample(rng.f32()).unwrap();
            let i = lights
                .lights()
                .iter()
                .position(|x| std::ptr::eq(x, l))
                .unwrap();
            counts[i] += 1;
        }
        let mut chi2 = 0.0;
        let mut dof = 0;
        for (c, l) in counts.iter().zip(lights.lights()) {
            let expected = l.probability as f64 * n as f64;
            if expected > 5.0 {
                chi2 += (*c as f64 - expected).powi(2) / expected;
                dof += 1;
            } else {
                assert!(*c as f64 <= expected * 10.0 + 10.0);
            }
        }
        // 99.9th percentile of χ² with ~63 degrees of freedom is about 104.
        assert!(
            dof > 20 && chi2 < 1.65 * dof as f64,
            "χ² = {chi2} over {dof} bins"
        );
    }

    #[test]
    fn the_guide_table_finds_the_binary_searchs_light() {
        let mut rng = crate::util::sampling::SplitMix64(11);
        let sky = VirtualLights::median_cut(&sky_with_sun(), 4096);
        let uneven = |n: usize, rng: &mut crate::util::sampling::SplitMix64| {
            let lights = (0..n)
                .map(|i| VirtualLight {
                    direction: Vec3::Y,
                    // Some dark lights (empty CDF steps), some a thousand times brighter.
                    irradiance: Vec3::splat(match i % 5 {
                        0 => 0.0,
                        1 => 1000.0 * rng.f32(),
                        _ => rng.f32(),
                    }),
                    probability: 0.0,
                })
                .collect();
            VirtualLights::from_lights(lights)
        };
        let sets = [
            sky,
            uneven(1, &mut rng),
            uneven(3, &mut rng),
            uneven(1000, &mut rng),
        ];
        for lights in &sets {
            let buckets = (lights.guide.len() - 1) as f32;
            let special = [0.0, 0.5, 1.0f32.next_down(), 1.0, -0.0, -1.0, 2.0, f32::NAN];
            let near_edges = lights
                .cdf
                .iter()
                .flat_map(|&c| [c.next_down(), c, c.next_up()]);
            let bucket_edges = (0..=64).map(|k| (k as f32 / 64.0 * buckets).floor() / buckets);
            let random = (0..100_000).map(|_| rng.f32());
            for u in special
                .into_iter()
                .chain(near_edges)
                .chain(bucket_edges)
                .chain(random)
            {
                assert_eq!(
                    lights.cdf_index(u),
                    lights.cdf.partition_point(|&c| c <= u),
                    "u = {u} over {} lights",
                    lights.len()
                );
            }
        }
    }

    #[test]
    fn bad_texels_are_zeroed_and_counted() {
        let (map, repaired) = EnvironmentMap::new(
            2,
            1,
            vec![
                Vec3::new(f32::NAN, 1.0, 1.0),
                Vec3::new(-1.0, f32::INFINITY, 0.0),
            ],
        )
        .unwrap();
        assert_eq!(repaired, 2);
        assert_eq!(map.integral(), Vec3::ZERO);
        assert!(EnvironmentMap::new(0, 4, vec![]).is_err());
        assert!(EnvironmentMap::new(2, 2, vec![Vec3::ONE; 3]).is_err());
        let lights = VirtualLights::median_cut(&map, 4);
        assert!(
            lights.sample(0.5).is_none(),
            "a black map has nothing to sample"
        );
    }
}
