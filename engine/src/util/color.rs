//! Colour: Rec. 709 luminance, the sRGB transfer functions, and the tone curve that
//! turns linear radiance into the 8-bit pixels of PNGs and the window.

use glam::Vec3;

/// Rec. 709 luminance of linear RGB.
#[inline]
pub fn luminance(c: Vec3) -> f32 {
    0.2126 * c.x + 0.7152 * c.y + 0.0722 * c.z
}

/// Rec. 709 luminance of linear RGB in f64 (the film's sums).
#[inline]
pub fn luminance64(rgb: [f64; 3]) -> f64 {
    0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]
}

/// The sRGB electro-optical transfer function.
pub fn srgb_to_linear(c: f32) -> f32 {
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}

/// The inverse of [`srgb_to_linear`].
pub fn linear_to_srgb(c: f32) -> f32 {
    if c <= 0.003_130_8 {
        c * 12.92
    } else {
        1.055 * c.powf(1.0 / 2.4) - 0.055
    }
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
