//! Shaders and textures: what a surface looks like. Shader entities carry a [`Shader`];
//! `compile_shaders` packs them into the dense [`ShaderTable`] the kernel reads.

use bevy_ecs::{component::Component, resource::Resource};
use glam::{Vec2, Vec3, Vec4};
use std::sync::{Arc, OnceLock};

/// The id meshes store per triangle to name their shader.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ShaderId(pub u32);

/// An RGBA8 texture stored as sRGB-encoded colour and linear alpha, sampled bilinearly
/// in linear space with repeat wrapping; UV (0, 0) is the image's top-left (glTF).
#[derive(Clone, Debug, PartialEq)]
pub struct Texture {
    width: u32,
    height: u32,
    texels: Vec<[u8; 4]>,
    mean_opaque_color: Vec3,
}

/// Why texture data was refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum TextureError {
    /// Zero width or height.
    #[error("texture has zero size ({width}x{height})")]
    Empty {
        /// Width.
        width: u32,
        /// Height.
        height: u32,
    },
    /// Texel count does not match the dimensions.
    #[error("texture is {width}x{height} but has {found} texels")]
    SizeMismatch {
        /// Width.
        width: u32,
        /// Height.
        height: u32,
        /// Texels given.
        found: usize,
    },
}

fn srgb_to_linear_table() -> &'static [f32; 256] {
    static TABLE: OnceLock<[f32; 256]> = OnceLock::new();
    TABLE.get_or_init(|| std::array::from_fn(|i| srgb_to_linear(i as f32 / 255.0)))
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

impl Texture {
    /// A texture from row-major sRGB RGBA8 texels, top row first.
    pub fn from_srgba8(
        width: u32,
        height: u32,
        texels: Vec<[u8; 4]>,
    ) -> Result<Self, TextureError> {
        if width == 0 || height == 0 {
            return Err(TextureError::Empty { width, height });
        }
        if texels.len() != width as usize * height as usize {
            return Err(TextureError::SizeMismatch {
                width,
                height,
                found: texels.len(),
            });
        }
        let table = srgb_to_linear_table();
        let (mut sum, mut weight) = (Vec3::ZERO, 0.0f64);
        for t in &texels {
            let a = t[3] as f32 / 255.0;
            sum += Vec3::new(
                table[t[0] as usize],
                table[t[1] as usize],
                table[t[2] as usize],
            ) * a;
            weight += a as f64;
        }
        let mean_opaque_color = if weight > 0.0 {
            sum / weight as f32
        } else {
            Vec3::ZERO
        };
        Ok(Self {
            width,
            height,
            texels,
            mean_opaque_color,
        })
    }

    /// Width in texels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in texels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Alpha-weighted mean linear colour (for adaptive transparency's cut-off hits).
    pub fn mean_opaque_color(&self) -> Vec3 {
        self.mean_opaque_color
    }

    #[inline]
    fn texel(&self, x: i64, y: i64) -> Vec4 {
        let (w, h) = (self.width as i64, self.height as i64);
        let t = self.texels[(y.rem_euclid(h) * w + x.rem_euclid(w)) as usize];
        let table = srgb_to_linear_table();
        Vec4::new(
            table[t[0] as usize],
            table[t[1] as usize],
            table[t[2] as usize],
            t[3] as f32 / 255.0,
        )
    }

    /// Bilinear sample in linear RGB + alpha, repeating outside [0, 1]. Non-finite UVs
    /// sample texel (0, 0).
    #[inline]
    pub fn sample(&self, uv: Vec2) -> Vec4 {
        let uv = if uv.is_finite() { uv } else { Vec2::ZERO };
        let x = uv.x * self.width as f32 - 0.5;
        let y = uv.y * self.height as f32 - 0.5;
        let (fx, fy) = (x.floor(), y.floor());
        let (tx, ty) = (x - fx, y - fy);
        // Wrap in f64 space first so huge UVs cannot overflow the integer texel index.
        let ix = (fx as f64).rem_euclid(self.width as f64) as i64;
        let iy = (fy as f64).rem_euclid(self.height as f64) as i64;
        let top = self.texel(ix, iy).lerp(self.texel(ix + 1, iy), tx);
        let bottom = self.texel(ix, iy + 1).lerp(self.texel(ix + 1, iy + 1), tx);
        top.lerp(bottom, ty)
    }

    /// Heap bytes held.
    pub fn memory_bytes(&self) -> usize {
        self.texels.capacity() * 4
    }
}

/// A Lambertian surface: base colour times an optional texture, optionally cut out by
/// the texture's alpha.
#[derive(Component, Clone, Debug, PartialEq)]
pub struct Shader {
    /// The id meshes use for this shader.
    pub id: ShaderId,
    /// Linear RGB reflectance factor.
    pub base_color: Vec3,
    /// Colour/alpha texture multiplied with `base_color`.
    pub texture: Option<Arc<Texture>>,
    /// When set (and a texture is present), texels with alpha below it are holes.
    pub alpha_cutoff: Option<f32>,
}

impl Shader {
    /// An untextured shader.
    pub fn color(id: ShaderId, base_color: Vec3) -> Self {
        Self {
            id,
            base_color,
            texture: None,
            alpha_cutoff: None,
        }
    }

    /// A textured shader.
    pub fn textured(id: ShaderId, base_color: Vec3, texture: Arc<Texture>) -> Self {
        Self {
            id,
            base_color,
            texture: Some(texture),
            alpha_cutoff: None,
        }
    }

    /// True when the texture's alpha can cut holes.
    pub fn is_alpha_masked(&self) -> bool {
        self.alpha_cutoff.is_some() && self.texture.is_some()
    }

    /// Reflectance at `uv`.
    #[inline]
    pub fn albedo(&self, uv: Vec2) -> Vec3 {
        match &self.texture {
            Some(t) => self.base_color * t.sample(uv).truncate(),
            None => self.base_color,
        }
    }

    /// False where the alpha mask makes a hole at `uv`.
    #[inline]
    pub fn is_opaque_at(&self, uv: Vec2) -> bool {
        match (&self.texture, self.alpha_cutoff) {
            (Some(t), Some(cutoff)) => t.sample(uv).w >= cutoff,
            _ => true,
        }
    }
}

/// Shaders packed densely by id for the kernel; unknown ids get a neutral grey.
#[derive(Clone, Debug, Resource)]
pub struct ShaderTable {
    shaders: Vec<Shader>,
    fallback: Shader,
    any_alpha_masked: bool,
}

impl Default for ShaderTable {
    fn default() -> Self {
        Self::new(Vec::new())
    }
}

impl ShaderTable {
    /// Packs shaders by id; a later shader with the same id replaces an earlier one.
    pub fn new(shaders: Vec<Shader>) -> Self {
        let fallback = Shader::color(ShaderId(u32::MAX), Vec3::splat(0.5));
        let len = shaders
            .iter()
            .map(|s| s.id.0 as usize + 1)
            .max()
            .unwrap_or(0);
        let mut table = vec![fallback.clone(); len];
        for s in shaders {
            let index = s.id.0 as usize;
            table[index] = s;
        }
        let any_alpha_masked = table.iter().any(Shader::is_alpha_masked);
        Self {
            shaders: table,
            fallback,
            any_alpha_masked,
        }
    }

    /// The shader for a triangle's stored id.
    #[inline]
    pub fn get(&self, id: u32) -> &Shader {
        self.shaders.get(id as usize).unwrap_or(&self.fallback)
    }

    /// True when any shader cuts holes (the kernel skips alpha tests otherwise).
    pub fn any_alpha_masked(&self) -> bool {
        self.any_alpha_masked
    }

    /// Number of slots.
    pub fn len(&self) -> usize {
        self.shaders.len()
    }

    /// True when no shader was compiled.
    pub fn is_empty(&self) -> bool {
        self.shaders.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn texture_top_left_is_uv_origin_and_repeats() {
        let red = [255, 0, 0, 255];
        let blue = [0, 0, 255, 255];
        let t = Texture::from_srgba8(2, 2, vec![red, blue, blue, blue]).unwrap();
        // Texel centres: (0.25, 0.25) is the top-left texel.
        assert_eq!(
            t.sample(Vec2::new(0.25, 0.25)),
            Vec4::new(1.0, 0.0, 0.0, 1.0)
        );
        assert_eq!(
            t.sample(Vec2::new(1.25, -0.75)),
            Vec4::new(1.0, 0.0, 0.0, 1.0)
        );
        assert_eq!(
            t.sample(Vec2::new(0.75, 0.75)),
            Vec4::new(0.0, 0.0, 1.0, 1.0)
        );
        assert!(t.sample(Vec2::new(f32::NAN, 0.0)).is_finite());
        assert!(t.sample(Vec2::new(1e30, -1e30)).is_finite());
    }

    #[test]
    fn bad_texture_sizes_are_errors() {
        assert!(Texture::from_srgba8(0, 4, vec![]).is_err());
        assert!(Texture::from_srgba8(2, 2, vec![[0; 4]; 3]).is_err());
    }

    #[test]
    fn mean_opaque_color_ignores_holes() {
        let t = Texture::from_srgba8(2, 1, vec![[255, 255, 255, 255], [0, 0, 0, 0]]).unwrap();
        assert_eq!(t.mean_opaque_color(), Vec3::ONE);
    }

    #[test]
    fn srgb_round_trip() {
        for i in 0..=255 {
            let c = i as f32 / 255.0;
            assert!((linear_to_srgb(srgb_to_linear(c)) - c).abs() < 1e-5);
        }
    }
}
