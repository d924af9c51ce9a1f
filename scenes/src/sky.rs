//! The embedded procedural sky: Preetham, Shirley and Smits, "A Practical Analytic Model
//! for Daylight" (1999). The Perez distribution of luminance and chromaticity for a
//! turbidity and sun position, baked into a latitude–longitude [`EnvironmentMap`] so it
//! lights scenes through the same virtual-light machinery as an HDR file. The sun's disc
//! is left out of the map: scenes add it as a directional light.

use glam::Vec3;
use std::f32::consts::FRAC_PI_2;
use sylva_engine::environment::{EnvironmentMap, uv_to_direction};

/// Parameters of a Preetham sky.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PreethamSky {
    /// Unit direction toward the sun (+Y up).
    pub sun: Vec3,
    /// Atmospheric turbidity (2 = very clear, 10 = hazy); the model holds for 2–10.
    pub turbidity: f32,
    /// Linear scale from the model's kcd/m² to scene radiance.
    pub scale: f32,
    /// Radiance below the horizon.
    pub ground: Vec3,
}

/// Perez coefficients A–E as `slope · T + offset`.
type Coefficients = [(f32, f32); 5];

const LUMINANCE: Coefficients = [
    (0.1787, -1.4630),
    (-0.3554, 0.4275),
    (-0.0227, 5.3251),
    (0.1206, -2.5771),
    (-0.0670, 0.3703),
];
const CHROMA_X: Coefficients = [
    (-0.0193, -0.2592),
    (-0.0665, 0.0008),
    (-0.0004, 0.2125),
    (-0.0641, -0.8989),
    (-0.0033, 0.0452),
];
const CHROMA_Y: Coefficients = [
    (-0.0167, -0.2608),
    (-0.0950, 0.0092),
    (-0.0079, 0.2102),
    (-0.0441, -1.6537),
    (-0.0109, 0.0529),
];

/// The Perez function F(θ, γ) for coefficients at turbidity `t`.
fn perez(c: &Coefficients, t: f32, theta: f32, gamma: f32) -> f32 {
    let [a, b, cc, d, e] = c.map(|(slope, offset)| slope * t + offset);
    let cos_theta = theta.cos().max(0.01);
    (1.0 + a * (b / cos_theta).exp()) * (1.0 + cc * (d * gamma).exp() + e * gamma.cos().powi(2))
}

/// CIE xyY to linear sRGB (Rec. 709 primaries, D65).
fn xyy_to_rgb(x: f32, y: f32, luminance: f32) -> Vec3 {
    if y <= 0.0 {
        return Vec3::ZERO;
    }
    let big_x = x * luminance / y;
    let big_z = (1.0 - x - y) * luminance / y;
    Vec3::new(
        3.2406 * big_x - 1.5372 * luminance - 0.4986 * big_z,
        -0.9689 * big_x + 1.8758 * luminance + 0.0415 * big_z,
        0.0557 * big_x - 0.2040 * luminance + 1.0570 * big_z,
    )
    .max(Vec3::ZERO)
}

impl PreethamSky {
    /// A clear sky for a sun in direction `sun`, scaled so a mid-morning zenith is about
    /// 0.5 — the scale of the scenes' sun irradiance of about 3.
    pub fn new(sun: Vec3, turbidity: f32) -> Self {
        Self {
            sun: sun.normalize_or(Vec3::Y),
            turbidity: turbidity.clamp(1.7, 10.0),
            scale: 1.0 / 12.0,
            ground: Vec3::new(0.12, 0.11, 0.08),
        }
    }

    /// Zenith luminance (kcd/m²) and chromaticity of the model.
    fn zenith(&self) -> (f32, f32, f32) {
        let t = self.turbidity;
        let ts = self.sun.y.clamp(-1.0, 1.0).acos().min(FRAC_PI_2);
        let chi = (4.0 / 9.0 - t / 120.0) * (std::f32::consts::PI - 2.0 * ts);
        let luminance = ((4.0453 * t - 4.9710) * chi.tan() - 0.2155 * t + 2.4192).max(0.0);
        let (t2, ts2, ts3) = (t * t, ts * ts, ts * ts * ts);
        let x = t2 * (0.00166 * ts3 - 0.00375 * ts2 + 0.00209 * ts)
            + t * (-0.02903 * ts3 + 0.06377 * ts2 - 0.03202 * ts + 0.00394)
            + (0.11693 * ts3 - 0.21196 * ts2 + 0.06052 * ts + 0.25886);
        let y = t2 * (0.00275 * ts3 - 0.00610 * ts2 + 0.00317 * ts)
            + t * (-0.04214 * ts3 + 0.08970 * ts2 - 0.04153 * ts + 0.00516)
            + (0.15346 * ts3 - 0.26756 * ts2 + 0.06670 * ts + 0.26688);
        (luminance, x, y)
    }

    /// Sky radiance toward `d` (unit, +Y up); the ground colour below the horizon.
    pub fn radiance(&self, d: Vec3) -> Vec3 {
        if d.y <= 0.0 {
            return self.ground;
        }
        let t = self.turbidity;
        let theta = d.y.clamp(-1.0, 1.0).acos();
        let gamma = d.dot(self.sun).clamp(-1.0, 1.0).acos();
        let ts = self.sun.y.clamp(-1.0, 1.0).acos().min(FRAC_PI_2);
        let (zy, zx, zyy) = self.zenith();
        let ratio = |c: &Coefficients| perez(c, t, theta, gamma) / perez(c, t, 0.0, ts);
        let luminance = zy * ratio(&LUMINANCE);
        let x = zx * ratio(&CHROMA_X);
        let y = zyy * ratio(&CHROMA_Y);
        xyy_to_rgb(x, y, luminance) * self.scale
    }

    /// The sky baked into a `width × width/2` lat-long map.
    pub fn to_map(&self, width: u32) -> EnvironmentMap {
        let (w, h) = (width.max(2), (width / 2).max(1));
        let texels = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let d = uv_to_direction((x as f32 + 0.5) / w as f32, (y as f32 + 0.5) / h as f32);
                self.radiance(d)
            })
            .collect();
        EnvironmentMap::new(w, h, texels).expect("w×h texels").0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sun_at(elevation_deg: f32) -> Vec3 {
        let e = elevation_deg.to_radians();
        Vec3::new(0.0, e.sin(), e.cos())
    }

    #[test]
    fn the_zenith_matches_the_papers_zenith_luminance() {
        let sky = PreethamSky::new(sun_at(38.0), 3.0);
        let (zenith, _, _) = sky.zenith();
        // Y_z at T = 3, θs = 52°: (4.0453·3 − 4.9710)·tan χ − 0.2155·3 + 2.4192.
        let ts = 52f32.to_radians();
        let chi = (4.0 / 9.0 - 3.0 / 120.0) * (std::f32::consts::PI - 2.0 * ts);
        let expected = (4.0453 * 3.0 - 4.9710) * chi.tan() - 0.2155 * 3.0 + 2.4192;
        assert!((zenith - expected).abs() < 1e-4);
        let up = sky.radiance(Vec3::Y);
        assert!((luminance(up) / sky.scale - zenith).abs() < 0.05 * zenith);
    }

    fn luminance(c: Vec3) -> f32 {
        sylva_engine::environment::luminance(c)
    }

    #[test]
    fn brighter_towards_the_sun_blue_overhead_finite_everywhere() {
        let sun = sun_at(30.0);
        let sky = PreethamSky::new(sun, 3.0);
        let near_sun = sky.radiance((sun + Vec3::new(0.1, 0.02, 0.0)).normalize());
        let away = sky.radiance(Vec3::new(0.0, 0.5, -1.0).normalize());
        assert!(
            luminance(near_sun) > 2.0 * luminance(away),
            "{near_sun} vs {away}"
        );
        let zenith = sky.radiance(Vec3::Y);
        assert!(zenith.z > zenith.x, "a clear zenith is blue: {zenith}");
        let map = sky.to_map(64);
        for y in 0..map.height() {
            for x in 0..map.width() {
                let t = map.texel(x, y);
                assert!(t.is_finite() && t.min_element() >= 0.0);
            }
        }
        // Haze scatters more light: the zenith of a hazy sky is brighter.
        let clear = PreethamSky::new(sun, 2.0).radiance(Vec3::Y);
        let hazy = PreethamSky::new(sun, 8.0).radiance(Vec3::Y);
        assert!(luminance(hazy) > luminance(clear), "{hazy} vs {clear}");
    }
}
