//! Shaders and textures: what a surface looks like. Shader entities carry a [`Shader`];
//! `compile_shaders` packs them into the dense [`ShaderTable`] the kernel reads.

pub use crate::util::color::{linear_to_srgb, srgb_to_linear};
use bevy_ecs::{component::Component, resource::Resource};
use glam::{Vec2, Vec3, Vec4};
use std::sync::{Arc, OnceLock};

/// The id meshes store per triangle to name their shader.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ShaderId(pub u32);

/// What a texture does outside [0, 1] along one axis (glTF sampler wrap modes).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum WrapMode {
    /// Tile the image (glTF's default).
    #[default]
    Repeat,
    /// Repeat the edge texels.
    ClampToEdge,
    /// Tile the image, mirroring every other copy.
    MirroredRepeat,
}

impl WrapMode {
    /// An integer texel index equivalent to `f` under this mode, small enough that
    /// `index + 1` cannot overflow even for huge UVs.
    #[inline]
    fn reduce(self, f: f32, n: u32) -> i64 {
        const SAFE: f32 = (1u64 << 40) as f32;
        if f.abs() < SAFE {
            return f as i64;
        }
        match self {
            WrapMode::ClampToEdge if f > 0.0 => n as i64,
            WrapMode::ClampToEdge => -1,
            // A period of two images keeps both repeating patterns intact.
            _ => (f as f64).rem_euclid(2.0 * n as f64) as i64,
        }
    }

    /// Maps an integer texel index into `0..n`.
    #[inline]
    fn wrap(self, i: i64, n: i64) -> i64 {
        // Most lookups land inside the image: skip the 64-bit divisions of `rem_euclid`
        // (a few per alpha test, tens of cycles each).
        if (0..n).contains(&i) {
            return i;
        }
        match self {
            WrapMode::Repeat => i.rem_euclid(n),
            WrapMode::ClampToEdge => i.clamp(0, n - 1),
            WrapMode::MirroredRepeat => {
                let k = i.rem_euclid(2 * n);
                if k < n { k } else { 2 * n - 1 - k }
            }
        }
    }
}

/// `x.floor()` without the libm call that the baseline x86-64 target makes of it (no
/// SSE4.1 rounding instruction): exact through integer truncation where `|x| < 2²³`,
/// beyond which every f32 is an integer (and non-finite values take `floor` itself).
#[inline]
fn floor(x: f32) -> f32 {
    const INTEGRAL: f32 = 8_388_608.0;
    if x.abs() < INTEGRAL {
        let truncated = x as i32 as f32;
        if truncated > x {
            truncated - 1.0
        } else {
            truncated
        }
    } else {
        x.floor()
    }
}

/// An RGBA8 texture stored as sRGB-encoded colour and linear alpha, sampled bilinearly
/// in linear space; UV (0, 0) is the image's top-left (glTF), wrapping per axis.
#[derive(Clone, Debug, PartialEq)]
pub struct Texture {
    width: u32,
    height: u32,
    texels: Vec<[u8; 4]>,
    wrap: [WrapMode; 2],
    mean_opaque_color: Vec3,
}

/// `KHR_texture_transform`: scale, then rotate counter-clockwise, then offset, applied
/// to UVs before sampling.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UvTransform {
    /// Added last.
    pub offset: Vec2,
    /// Radians.
    pub rotation: f32,
    /// Applied first.
    pub scale: Vec2,
}

impl Default for UvTransform {
    fn default() -> Self {
        Self {
            offset: Vec2::ZERO,
            rotation: 0.0,
            scale: Vec2::ONE,
        }
    }
}

impl UvTransform {
    /// The transformed coordinates, as the extension's reference shader computes them.
    #[inline]
    pub fn apply(&self, uv: Vec2) -> Vec2 {
        let s = uv * self.scale;
        let (sin, cos) = self.rotation.sin_cos();
        Vec2::new(s.x * cos + s.y * sin, s.y * cos - s.x * sin) + self.offset
    }
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
            wrap: [WrapMode::Repeat; 2],
            mean_opaque_color,
        })
    }

    /// A texture from row-major grey + alpha texels (a two-channel PNG): the grey value
    /// goes to all three colour channels.
    pub fn from_gray_alpha8(
        width: u32,
        height: u32,
        texels: &[[u8; 2]],
    ) -> Result<Self, TextureError> {
        Self::from_srgba8(
            width,
            height,
            texels.iter().map(|&[l, a]| [l, l, l, a]).collect(),
        )
    }

    /// The same texture with other wrap modes along U and V.
    pub fn with_wrap(mut self, u: WrapMode, v: WrapMode) -> Self {
        self.wrap = [u, v];
        self
    }

    /// Wrap modes along U and V.
    pub fn wrap(&self) -> [WrapMode; 2] {
        self.wrap
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

    /// The wrapped indices of the four texels around `uv` — (x0, y0), (x1, y0), (x0, y1),
    /// (x1, y1) — and the bilinear weights along x and y. Non-finite UVs read texel (0, 0).
    #[inline]
    fn footprint(&self, uv: Vec2) -> ([usize; 4], f32, f32) {
        let uv = if uv.is_finite() { uv } else { Vec2::ZERO };
        let x = uv.x * self.width as f32 - 0.5;
        let y = uv.y * self.height as f32 - 0.5;
        let (fx, fy) = (floor(x), floor(y));
        let ix = self.wrap[0].reduce(fx, self.width);
        let iy = self.wrap[1].reduce(fy, self.height);
        let (w, h) = (self.width as i64, self.height as i64);
        let (x0, x1) = (self.wrap[0].wrap(ix, w), self.wrap[0].wrap(ix + 1, w));
        let (y0, y1) = (self.wrap[1].wrap(iy, h), self.wrap[1].wrap(iy + 1, h));
        let at = |x: i64, y: i64| (y * w + x) as usize;
        (
            [at(x0, y0), at(x1, y0), at(x0, y1), at(x1, y1)],
            x - fx,
            y - fy,
        )
    }

    /// Texel `index` in linear RGB + alpha.
    #[inline]
    fn texel(&self, index: usize) -> Vec4 {
        let t = self.texels[index];
        let table = srgb_to_linear_table();
        Vec4::new(
            table[t[0] as usize],
            table[t[1] as usize],
            table[t[2] as usize],
            t[3] as f32 / 255.0,
        )
    }

    /// Bilinear sample in linear RGB + alpha, wrapped outside [0, 1] by the wrap modes.
    /// Non-finite UVs sample texel (0, 0).
    #[inline]
    pub fn sample(&self, uv: Vec2) -> Vec4 {
        let ([a, b, c, d], tx, ty) = self.footprint(uv);
        let top = self.texel(a).lerp(self.texel(b), tx);
        let bottom = self.texel(c).lerp(self.texel(d), tx);
        top.lerp(bottom, ty)
    }

    /// The alpha of [`sample`](Self::sample), bit for bit, reading only the alpha bytes:
    /// the alpha test runs for every candidate leaf hit and needs no colour.
    #[inline]
    pub fn sample_alpha(&self, uv: Vec2) -> f32 {
        let ([a, b, c, d], tx, ty) = self.footprint(uv);
        let alpha = |index: usize| self.texels[index][3] as f32 / 255.0;
        // Vec4::lerp's arithmetic, one lane.
        let lerp = |from: f32, to: f32, s: f32| from * (1.0 - s) + to * s;
        lerp(
            lerp(alpha(a), alpha(b), tx),
            lerp(alpha(c), alpha(d), tx),
            ty,
        )
    }

    /// The least and greatest alpha byte among the texels a bilinear sample can read at
    /// any texel coordinate (`u · width − 0.5`, `v · height − 0.5`, as the footprint
    /// computes them) in `[x[0], x[1]] × [y[0], y[1]]`. Coordinates must lie within
    /// 2²² of the origin (the opacity maps check).
    pub(crate) fn alpha_bounds(&self, x: [f64; 2], y: [f64; 2]) -> [u8; 2] {
        let columns = self.wrap[0].texels_reached(x, self.width);
        let rows = self.wrap[1].texels_reached(y, self.height);
        let (mut least, mut most) = (u8::MAX, u8::MIN);
        let mut row_bounds = |line: &[[u8; 4]]| match &columns {
            TexelsReached::Run(run) => {
                for texel in &line[run.clone()] {
                    least = least.min(texel[3]);
                    most = most.max(texel[3]);
                }
            }
            TexelsReached::Scattered(columns) => {
                for &column in columns {
                    least = least.min(line[column][3]);
                    most = most.max(line[column][3]);
                }
            }
        };
        let width = self.width as usize;
        match rows {
            TexelsReached::Run(run) => {
                run.for_each(|r| row_bounds(&self.texels[r * width..][..width]))
            }
            TexelsReached::Scattered(rows) => rows
                .into_iter()
                .for_each(|r| row_bounds(&self.texels[r * width..][..width])),
        }
        [least, most]
    }

    /// Heap bytes held.
    pub fn memory_bytes(&self) -> usize {
        self.texels.capacity() * 4
    }
}

/// Texel indices along one axis: a run inside the image, or wrapped ones in order.
enum TexelsReached {
    /// `start..end`, no wrapping involved.
    Run(std::ops::Range<usize>),
    /// Distinct wrapped indices.
    Scattered(Vec<usize>),
}

impl WrapMode {
    /// The texel indices in `0..n` that footprints at coordinates in `range` read: the
    /// wrapped `floor(c)` and `floor(c) + 1`.
    fn texels_reached(self, range: [f64; 2], n: u32) -> TexelsReached {
        let (first, last) = (range[0].floor() as i64, range[1].floor() as i64 + 1);
        if first >= 0 && last < i64::from(n) {
            return TexelsReached::Run(first as usize..last as usize + 1);
        }
        if last - first + 1 >= 2 * i64::from(n) {
            return TexelsReached::Run(0..n as usize);
        }
        let mut seen = vec![false; n as usize];
        for i in first..=last {
            seen[self.wrap(i, i64::from(n)) as usize] = true;
        }
        TexelsReached::Scattered((0..n as usize).filter(|&i| seen[i]).collect())
    }
}

/// Light a surface gives off by itself (glTF's emissive properties): seen by camera
/// rays, not sampled as a light, so it brightens what it is and not its surroundings.
#[derive(Clone, Debug, PartialEq)]
pub struct Emission {
    /// Linear RGB radiance: the emissive factor times the emissive strength.
    pub radiance: Vec3,
    /// Colour texture multiplied with it (sRGB texels; alpha ignored).
    pub texture: Option<Arc<Texture>>,
    /// Applied to UVs before the texture is sampled.
    pub uv_transform: Option<UvTransform>,
}

impl Emission {
    /// Emitted radiance at `uv`.
    #[inline]
    pub fn at(&self, uv: Vec2) -> Vec3 {
        match &self.texture {
            Some(t) => {
                let uv = self.uv_transform.as_ref().map_or(uv, |x| x.apply(uv));
                self.radiance * t.sample(uv).truncate()
            }
            None => self.radiance,
        }
    }
}

/// Diffuse transmission of a thin surface (a leaf): a share of the light arriving from
/// behind passes through, tinted, and leaves diffusely on the other side (glTF's
/// `KHR_materials_diffuse_transmission`). Reflectance becomes `(1 − factor) × albedo`
/// and transmittance `factor × color × texture`, so their sum stays at most 1 when
/// colours do.
#[derive(Clone, Debug, PartialEq)]
pub struct Transmission {
    /// Share of the diffuse light transmitted instead of reflected (0 ..= 1).
    pub factor: f32,
    /// Tint of the transmitted light (linear RGB, each channel 0 ..= 1).
    pub color: Vec3,
    /// Colour texture multiplied with `color` (sRGB texels; alpha ignored).
    pub color_texture: Option<Arc<Texture>>,
    /// Applied to UVs before the colour texture is sampled.
    pub uv_transform: Option<UvTransform>,
    /// Texture whose alpha multiplies `factor`.
    pub factor_texture: Option<Arc<Texture>>,
    /// Applied to UVs before the factor texture is sampled.
    pub factor_uv_transform: Option<UvTransform>,
}

impl Transmission {
    /// Transmission of `factor` tinted by `color`, untextured.
    pub fn new(factor: f32, color: Vec3) -> Self {
        Self {
            factor,
            color,
            color_texture: None,
            uv_transform: None,
            factor_texture: None,
            factor_uv_transform: None,
        }
    }

    /// The transmitted share at `uv`.
    #[inline]
    pub fn factor_at(&self, uv: Vec2) -> f32 {
        match &self.factor_texture {
            Some(t) => {
                let uv = self
                    .factor_uv_transform
                    .as_ref()
                    .map_or(uv, |x| x.apply(uv));
                self.factor * t.sample(uv).w
            }
            None => self.factor,
        }
    }

    /// The same with `factor` and `color` clamped to 0 ..= 1 (NaN to 0), so that
    /// reflectance plus transmittance never exceeds 1; the flag says whether anything
    /// changed (callers warn, naming the material).
    pub fn clamped(mut self) -> (Self, bool) {
        let unit = |v: f32| if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
        let (factor, color) = (unit(self.factor), self.color.to_array().map(unit).into());
        let changed = factor.to_bits() != self.factor.to_bits() || color != self.color;
        self.factor = factor;
        self.color = color;
        (self, changed)
    }

    /// Transmittance at `uv`.
    #[inline]
    pub fn at(&self, uv: Vec2) -> Vec3 {
        let tint = match &self.color_texture {
            Some(t) => {
                let uv = self.uv_transform.as_ref().map_or(uv, |x| x.apply(uv));
                self.color * t.sample(uv).truncate()
            }
            None => self.color,
        };
        tint * self.factor_at(uv)
    }
}

/// A Lambertian surface: base colour times an optional texture, optionally cut out by
/// the texture's alpha, optionally emitting light of its own or transmitting it.
#[derive(Component, Clone, Debug, PartialEq)]
pub struct Shader {
    /// The id meshes use for this shader.
    pub id: ShaderId,
    /// Linear RGB reflectance factor.
    pub base_color: Vec3,
    /// Colour/alpha texture multiplied with `base_color`.
    pub texture: Option<Arc<Texture>>,
    /// Applied to UVs before the texture is sampled.
    pub uv_transform: Option<UvTransform>,
    /// When set (and a texture is present), texels with alpha below it are holes.
    pub alpha_cutoff: Option<f32>,
    /// When false, the surface is seen from its front only: every ray passes through
    /// its back (glTF's single-sided materials; the front is where the winding normal,
    /// transformed by the instance, points).
    pub double_sided: bool,
    /// Light the surface emits, if any.
    pub emission: Option<Emission>,
    /// Light the surface lets through from behind, if any.
    pub transmission: Option<Transmission>,
}

impl Shader {
    /// An untextured shader.
    pub fn color(id: ShaderId, base_color: Vec3) -> Self {
        Self {
            id,
            base_color,
            texture: None,
            uv_transform: None,
            alpha_cutoff: None,
            double_sided: true,
            emission: None,
            transmission: None,
        }
    }

    /// A textured shader.
    pub fn textured(id: ShaderId, base_color: Vec3, texture: Arc<Texture>) -> Self {
        Self {
            id,
            base_color,
            texture: Some(texture),
            uv_transform: None,
            alpha_cutoff: None,
            double_sided: true,
            emission: None,
            transmission: None,
        }
    }

    /// A textured shader whose texels with alpha below `cutoff` are holes.
    pub fn alpha_masked(
        id: ShaderId,
        base_color: Vec3,
        texture: Arc<Texture>,
        cutoff: f32,
    ) -> Self {
        Self {
            alpha_cutoff: Some(cutoff),
            ..Self::textured(id, base_color, texture)
        }
    }

    /// True when the texture's alpha can cut holes.
    pub fn is_alpha_masked(&self) -> bool {
        self.alpha_cutoff.is_some() && self.texture.is_some()
    }

    /// True when rays must be tested against something during traversal: an alpha mask
    /// or a single-sided surface.
    pub fn needs_hit_filter(&self) -> bool {
        self.is_alpha_masked() || !self.double_sided
    }

    /// The texture coordinates after the shader's UV transform.
    #[inline]
    fn texture_uv(&self, uv: Vec2) -> Vec2 {
        match &self.uv_transform {
            Some(t) => t.apply(uv),
            None => uv,
        }
    }

    /// Reflectance at `uv`.
    #[inline]
    pub fn albedo(&self, uv: Vec2) -> Vec3 {
        match &self.texture {
            Some(t) => self.base_color * t.sample(self.texture_uv(uv)).truncate(),
            None => self.base_color,
        }
    }

    /// The same surface made opaque with its reflectance kept: the base colour takes
    /// the reflected share `1 − factor` and the transmission goes (exactly so for an
    /// untextured factor; a factor texture is represented by its scalar factor).
    pub fn without_transmission(mut self) -> Self {
        if let Some(t) = self.transmission.take() {
            self.base_color *= 1.0 - t.factor;
        }
        self
    }

    /// Diffuse reflectance at `uv`: the albedo less the share transmitted.
    #[inline]
    pub fn reflectance(&self, uv: Vec2) -> Vec3 {
        self.reflected_share(uv) * self.albedo(uv)
    }

    /// The share of diffuse light reflected rather than transmitted at `uv`.
    #[inline]
    pub fn reflected_share(&self, uv: Vec2) -> f32 {
        self.transmission
            .as_ref()
            .map_or(1.0, |t| 1.0 - t.factor_at(uv))
    }

    /// Diffuse transmittance at `uv` (zero for opaque surfaces).
    #[inline]
    pub fn transmittance(&self, uv: Vec2) -> Vec3 {
        self.transmission.as_ref().map_or(Vec3::ZERO, |t| t.at(uv))
    }

    /// Emitted radiance at `uv` (zero for surfaces that emit nothing).
    #[inline]
    pub fn emission(&self, uv: Vec2) -> Vec3 {
        self.emission.as_ref().map_or(Vec3::ZERO, |e| e.at(uv))
    }

    /// The mean colour of the opaque part (base colour × the texture's alpha-weighted
    /// mean): what adaptive transparency substitutes for a cut-off hit.
    pub fn mean_opaque_color(&self) -> Vec3 {
        match &self.texture {
            Some(t) => self.base_color * t.mean_opaque_color(),
            None => self.base_color,
        }
    }

    /// False where the alpha mask makes a hole at `uv`.
    #[inline]
    pub fn is_opaque_at(&self, uv: Vec2) -> bool {
        match (&self.texture, self.alpha_cutoff) {
            (Some(t), Some(cutoff)) => t.sample_alpha(self.texture_uv(uv)) >= cutoff,
            _ => true,
        }
    }
}

/// Shaders packed densely by id for the kernel; unknown ids get a neutral grey.
#[derive(Clone, Debug, Resource)]
pub struct ShaderTable {
    shaders: Vec<Shader>,
    fallback: Shader,
    any_hit_filter: bool,
    any_alpha_mask: bool,
}

impl Default for ShaderTable {
    fn default() -> Self {
        Self::new(Vec::new())
    }
}

impl ShaderTable {
    /// A hash of every shader's settings and texture texels: equal tables give equal
    /// hashes on any machine (a cluster's ranks compare it before they render).
    pub fn content_hash(&self) -> u64 {
        let mut hash = crate::util::fingerprint::Fingerprint::new("shader table v1");
        for shader in self.shaders.iter().chain([&self.fallback]) {
            let Shader {
                id,
                base_color,
                texture,
                uv_transform,
                alpha_cutoff,
                double_sided,
                emission,
                transmission,
            } = shader;
            hash.text(&format!(
                "{id:?} {base_color:?} {uv_transform:?} {alpha_cutoff:?} {double_sided} {emission:?} {transmission:?}"
            ));
            if let Some(texture) = texture {
                hash.u32(texture.width).u32(texture.height);
                hash.text(&format!("{:?}", texture.wrap));
                for texel in &texture.texels {
                    hash.bytes(texel);
                }
            }
        }
        hash.finish()
    }

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
        let any_hit_filter = table.iter().any(Shader::needs_hit_filter);
        let any_alpha_mask = table.iter().any(Shader::is_alpha_masked);
        Self {
            shaders: table,
            fallback,
            any_hit_filter,
            any_alpha_mask,
        }
    }

    /// The shader for a triangle's stored id.
    #[inline]
    pub fn get(&self, id: u32) -> &Shader {
        self.shaders.get(id as usize).unwrap_or(&self.fallback)
    }

    /// True when any shader cuts holes or is single-sided (the kernel skips hit filters
    /// otherwise).
    pub fn needs_hit_filter(&self) -> bool {
        self.any_hit_filter
    }

    /// True when any shader cuts holes with an alpha mask.
    pub fn has_alpha_masks(&self) -> bool {
        self.any_alpha_mask
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
    fn alpha_sampling_equals_the_full_sample_bit_for_bit() {
        let texels: Vec<[u8; 4]> = (0..7 * 5u32)
            .map(|i| [i as u8, (i * 7) as u8, (i * 13) as u8, (i * 37 % 256) as u8])
            .collect();
        let mut state = 0x2545_f491u32;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            (state as f32 / u32::MAX as f32 - 0.5) * 6.0
        };
        for wrap in [
            WrapMode::Repeat,
            WrapMode::ClampToEdge,
            WrapMode::MirroredRepeat,
        ] {
            let t = Texture::from_srgba8(7, 5, texels.clone())
                .unwrap()
                .with_wrap(wrap, WrapMode::Repeat);
            let special = [Vec2::new(f32::NAN, 0.2), Vec2::new(1e30, -1e30), Vec2::ZERO];
            for uv in (0..10_000)
                .map(|_| Vec2::new(next(), next()))
                .chain(special)
            {
                assert_eq!(
                    t.sample_alpha(uv).to_bits(),
                    t.sample(uv).w.to_bits(),
                    "{wrap:?} at {uv}"
                );
            }
        }
    }

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
    fn the_fast_floor_is_floor() {
        let mut bits = 0x9e37_79b9u32;
        for i in 0..200_000 {
            bits = bits.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let x = match i % 4 {
                0 => f32::from_bits(bits),
                1 => (bits as i32) as f32 / 4096.0,
                2 => (bits % 64) as f32 * 0.25 - 8.0,
                _ => [
                    0.5,
                    -0.5,
                    8_388_607.5,
                    -8_388_607.5,
                    8_388_608.0,
                    -1e-30,
                    f32::MAX,
                ][i / 4 % 7],
            };
            let (fast, exact) = (floor(x), x.floor());
            // Equal as values (a -0 may come back as +0: both index texel 0).
            assert!(
                fast == exact || (fast.is_nan() && exact.is_nan()),
                "floor({x}) = {fast}, not {exact}"
            );
        }
    }

    #[test]
    fn wrap_modes_follow_gltf() {
        // One row: black, white. Texel centres at u = 0.25 and 0.75.
        let t = Texture::from_srgba8(2, 1, vec![[0, 0, 0, 255], [255, 255, 255, 255]]).unwrap();
        let red = |t: &Texture, u: f32| t.sample(Vec2::new(u, 0.5)).x;
        // Repeat: u + 1 is u.
        assert_eq!(red(&t, 1.25), 0.0);
        assert_eq!(red(&t, -0.25), 1.0);
        let clamp = t
            .clone()
            .with_wrap(WrapMode::ClampToEdge, WrapMode::ClampToEdge);
        assert_eq!(red(&clamp, 1.25), 1.0);
        assert_eq!(red(&clamp, 7.0), 1.0);
        assert_eq!(red(&clamp, -3.0), 0.0);
        assert_eq!(red(&clamp, 1e30), 1.0);
        assert_eq!(red(&clamp, -1e30), 0.0);
        let mirror = t.with_wrap(WrapMode::MirroredRepeat, WrapMode::Repeat);
        // [1, 2) is the image mirrored: white then black.
        assert_eq!(red(&mirror, 1.25), 1.0);
        assert_eq!(red(&mirror, 1.75), 0.0);
        assert_eq!(red(&mirror, 2.25), 0.0);
        assert_eq!(red(&mirror, -0.25), 0.0);
        assert_eq!(red(&mirror, -0.75), 1.0);
        assert!(mirror.sample(Vec2::new(3e9, -7e12)).is_finite());
    }

    #[test]
    fn gray_alpha_expands_to_grey_colour_and_keeps_alpha() {
        let t = Texture::from_gray_alpha8(1, 1, &[[128, 64]]).unwrap();
        let s = t.sample(Vec2::splat(0.5));
        let grey = srgb_to_linear(128.0 / 255.0);
        assert!(
            (s - Vec4::new(grey, grey, grey, 64.0 / 255.0))
                .abs()
                .max_element()
                < 1e-6
        );
    }

    #[test]
    fn colour_is_decoded_to_linear_before_filtering() {
        // Halfway between sRGB black and white is linear 0.5, not sRGB 0.5.
        let t = Texture::from_srgba8(2, 1, vec![[0, 0, 0, 255], [255, 255, 255, 255]])
            .unwrap()
            .with_wrap(WrapMode::ClampToEdge, WrapMode::ClampToEdge);
        assert!((t.sample(Vec2::new(0.5, 0.5)).x - 0.5).abs() < 1e-6);
    }

    #[test]
    fn uv_transform_matches_the_extension() {
        let t = UvTransform {
            offset: Vec2::new(0.5, 0.25),
            rotation: std::f32::consts::FRAC_PI_2,
            scale: Vec2::new(2.0, 3.0),
        };
        // (1, 0) → scaled (2, 0) → rotated (0, -2) → offset (0.5, -1.75).
        assert!((t.apply(Vec2::X) - Vec2::new(0.5, -1.75)).length() < 1e-6);
        assert_eq!(
            UvTransform::default().apply(Vec2::new(0.3, 0.7)),
            Vec2::new(0.3, 0.7)
        );
        let texture =
            Arc::new(Texture::from_srgba8(2, 1, vec![[0, 0, 0, 0], [255, 255, 255, 255]]).unwrap());
        let mut shader = Shader::alpha_masked(ShaderId(0), Vec3::ONE, texture, 0.5);
        assert!(!shader.is_opaque_at(Vec2::new(0.25, 0.5)));
        shader.uv_transform = Some(UvTransform {
            offset: Vec2::new(0.5, 0.0),
            ..Default::default()
        });
        assert!(shader.is_opaque_at(Vec2::new(0.25, 0.5)));
        assert_eq!(shader.albedo(Vec2::new(0.25, 0.5)), Vec3::ONE);
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
