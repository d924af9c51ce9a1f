//! Opacity micromaps: for each alpha-masked triangle, which parts of it are surely opaque,
//! surely holes or mixed, so the hit filter samples the alpha texture only where the
//! mask's edge could pass (the CPU form of the GPU ray tracers' opacity micromaps).
//!
//! A triangle's barycentric domain is cut into `4^level` sub-triangles (each edge in
//! `2^level` parts). A sub-triangle is *opaque* when every texel a bilinear sample
//! anywhere in it (and a margin around it) can read has an alpha above the cut-off,
//! a *hole* when every one is below, *mixed* otherwise. The margins cover the rounding
//! of barycentrics, of the UV interpolation, of the UV transform and of the bilinear
//! sum, so a decided sub-triangle gives the per-texel test's answer bit for bit (the
//! tests check it against [`Shader::is_opaque_at`]). Triangles that share a shader and
//! UVs (every leaf quad of a species) share one map.

use crate::accel::geometry::{GeometryId, GeometryLibrary};
use crate::material::shading::{Shader, ShaderTable};
use bevy_ecs::resource::Resource;
use glam::{DVec2, Vec2, Vec3A};
use rayon::prelude::*;
use std::collections::HashMap;

/// What a micromap knows about the alpha test at a point.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Opacity {
    /// The alpha test passes: the surface is there.
    Opaque,
    /// The alpha test fails: a hole.
    Hole,
    /// Unknown without sampling the texture.
    Mixed,
}

/// A triangle without a map (not alpha-masked, or UVs the map cannot bound).
const NO_MAP: u32 = u32::MAX;
/// Finest subdivision: 4⁷ = 16,384 sub-triangles, 4 KB per map.
const MAX_LEVEL: u32 = 7;
/// Texels a sub-triangle should cover at most (the level grows until it does).
const TARGET_TEXELS: f64 = 1.0;
/// At most this many sub-triangles over all maps (2 bits each: 32 MB); levels are
/// lowered until the maps fit.
const BUDGET_SUBTRIANGLES: u64 = 1 << 27;
/// How far (in barycentric units) a looked-up point may lie outside the sub-triangle
/// it is assigned to: the clamps at the domain's edges and f32 rounding.
const BARYCENTRIC_SLACK: f64 = 4e-5;
/// Relative margin for the rounding of UV interpolation, transform and texel
/// coordinates.
const RELATIVE_SLACK: f64 = 1e-5;
/// Texel coordinates beyond which the map does not try (f32 spacing near 2²²).
const TEXEL_LIMIT: f64 = (1u64 << 22) as f64;

/// Codes of the two-bit states.
const MIXED: u64 = 0;
const OPAQUE: u64 = 1;
const HOLE: u64 = 2;

/// One triangle layout's map: `4^level` two-bit states from `first_word` on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct MapHeader {
    level: u32,
    first_word: u32,
    /// The layout's shader shows one side only: [`OpacityMaps::at`] leaves it to the
    /// full filter, which must first cull the triangle's back.
    single_sided: bool,
    /// False when no map could be built (its shader has no usable cut-off): every
    /// lookup is [`Opacity::Mixed`].
    usable: bool,
}

/// The opacity micromaps of every alpha-masked triangle of a [`GeometryLibrary`] under a
/// [`ShaderTable`]. The default has no maps: every lookup is [`Opacity::Mixed`].
#[derive(Clone, Debug, Default, Resource)]
pub struct OpacityMaps {
    /// Per geometry, the index of its first triangle in `triangle_maps`, or [`NO_MAP`]
    /// when none of its triangles has a map.
    first_triangle: Vec<u32>,
    /// Per triangle of every geometry in turn, its map or none.
    triangle_maps: MapIndices,
    /// Map headers.
    maps: Vec<MapHeader>,
    /// Two-bit states, 32 per word.
    words: Vec<u64>,
}

/// Each triangle's map index, stored as narrow as the map count allows: the lookup's
/// first load misses the caches, and one byte per triangle keeps four times as many
/// triangles per line (`paper`'s 1.5 M alpha-masked triangles in 1.5 MB, not 6 MB).
/// The largest value of each width means "no map".
#[derive(Clone, Debug)]
enum MapIndices {
    /// Fewer than 255 maps.
    Byte(Vec<u8>),
    /// Fewer than 65,535 maps.
    Short(Vec<u16>),
    /// Any count.
    Word(Vec<u32>),
}

impl Default for MapIndices {
    fn default() -> Self {
        Self::Byte(Vec::new())
    }
}

impl MapIndices {
    /// `indices` (each a map index below `map_count`, or [`NO_MAP`]) at the narrowest
    /// width that holds them.
    fn narrowed(indices: Vec<u32>, map_count: usize) -> Self {
        fn narrow<T: TryFrom<u32> + Copy>(indices: &[u32], none: T) -> Vec<T> {
            indices
                .iter()
                .map(|&i| T::try_from(i).ok().filter(|_| i != NO_MAP).unwrap_or(none))
                .collect()
        }
        if map_count < usize::from(u8::MAX) {
            Self::Byte(narrow(&indices, u8::MAX))
        } else if map_count < usize::from(u16::MAX) {
            Self::Short(narrow(&indices, u16::MAX))
        } else {
            Self::Word(indices)
        }
    }

    /// Entry `i`'s map index, or [`NO_MAP`] (also past the end).
    #[inline(always)]
    fn get(&self, i: usize) -> u32 {
        let widen = |entry: Option<u32>, none: u32| match entry {
            Some(m) if m != none => m,
            _ => NO_MAP,
        };
        match self {
            Self::Byte(v) => widen(v.get(i).map(|&m| u32::from(m)), u32::from(u8::MAX)),
            Self::Short(v) => widen(v.get(i).map(|&m| u32::from(m)), u32::from(u16::MAX)),
            Self::Word(v) => v.get(i).copied().unwrap_or(NO_MAP),
        }
    }

    /// Heap bytes held.
    fn memory_bytes(&self) -> usize {
        match self {
            Self::Byte(v) => v.capacity(),
            Self::Short(v) => v.capacity() * 2,
            Self::Word(v) => v.capacity() * 4,
        }
    }
}

/// A map before it is placed: level and states.
struct BuiltMap {
    level: u32,
    words: Vec<u64>,
}

/// The layout a map depends on: shader and the three UVs' bits.
type LayoutKey = (u32, [u32; 6]);

/// One geometry's triangles as local layout indices, and its distinct layouts.
type LocalLayouts = (Vec<u32>, Vec<(LayoutKey, [Vec2; 3])>);

impl OpacityMaps {
    /// Builds the maps on the current rayon pool: one per distinct (shader, UVs) of the
    /// alpha-masked triangles, each as fine as `TARGET_TEXELS` asks, within
    /// `BUDGET_SUBTRIANGLES` in all.
    pub fn build(library: &GeometryLibrary, shaders: &ShaderTable) -> Self {
        let _span = tracing::info_span!("build_opacity_maps").entered();
        // Distinct layouts per geometry, in parallel; then merged in geometry order, so
        // the result does not depend on the pool.
        let per_geometry: Vec<LocalLayouts> = library
            .geometries
            .par_iter()
            .map(|geometry| {
                let mesh = &geometry.mesh;
                let mut local: HashMap<LayoutKey, u32> = HashMap::new();
                let mut layouts = Vec::new();
                let mut previous: Option<(LayoutKey, u32)> = None;
                let triangle_maps = (0..mesh.triangle_count())
                    .map(|t| {
                        let shader = shaders.get(mesh.shaders[t]);
                        if !shader.is_alpha_masked() || mesh.uvs.is_empty() {
                            return NO_MAP;
                        }
                        let uvs = mesh.indices[t].map(|i| mesh.uvs[i as usize]);
                        if !uvs.iter().all(|uv| uv.is_finite()) {
                            return NO_MAP;
                        }
                        let [[a, b], [c, d], [e, f]] =
                            uvs.map(|uv| [uv.x.to_bits(), uv.y.to_bits()]);
                        let key = (mesh.shaders[t], [a, b, c, d, e, f]);
                        if let Some((last, index)) = previous
                            && last == key
                        {
                            return index;
                        }
                        let index = *local.entry(key).or_insert_with(|| {
                            layouts.push((key, uvs));
                            layouts.len() as u32 - 1
                        });
                        previous = Some((key, index));
                        index
                    })
                    .collect();
                (triangle_maps, layouts)
            })
            .collect();

        let mut global: HashMap<LayoutKey, u32> = HashMap::new();
        let mut layouts: Vec<(u32, [Vec2; 3])> = Vec::new();
        let mut first_triangle = Vec::with_capacity(per_geometry.len());
        let mut triangle_maps = Vec::new();
        for (local_maps, local_layouts) in per_geometry {
            if local_layouts.is_empty() {
                // No alpha-masked triangle (terrain, bark): no entries at all.
                first_triangle.push(NO_MAP);
                continue;
            }
            let renumber: Vec<u32> = local_layouts
                .iter()
                .map(|&(key, uvs)| {
                    *global.entry(key).or_insert_with(|| {
                        layouts.push((key.0, uvs));
                        layouts.len() as u32 - 1
                    })
                })
                .collect();
            first_triangle.push(triangle_maps.len() as u32);
            triangle_maps.extend(local_maps.into_iter().map(|m| {
                if m == NO_MAP {
                    NO_MAP
                } else {
                    renumber[m as usize]
                }
            }));
        }

        let wanted: Vec<u32> = layouts
            .iter()
            .map(|(shader, uvs)| wanted_level(shaders.get(*shader), uvs))
            .collect();
        let mut cap = MAX_LEVEL;
        while cap > 0
            && wanted
                .iter()
                .map(|&l| 1u64 << (2 * l.min(cap)))
                .sum::<u64>()
                > BUDGET_SUBTRIANGLES
        {
            cap -= 1;
        }
        let built: Vec<Option<BuiltMap>> = layouts
            .par_iter()
            .zip(&wanted)
            .map(|((shader, uvs), &level)| build_map(shaders.get(*shader), uvs, level.min(cap)))
            .collect();

        let mut maps = Vec::with_capacity(built.len());
        let mut words = Vec::new();
        for (map, (shader, _)) in built.into_iter().zip(&layouts) {
            let single_sided = !shaders.get(*shader).double_sided;
            maps.push(MapHeader {
                level: map.as_ref().map_or(0, |m| m.level),
                first_word: words.len() as u32,
                single_sided,
                usable: map.is_some(),
            });
            if let Some(map) = map {
                words.extend(map.words);
            }
        }
        let triangle_maps = MapIndices::narrowed(triangle_maps, maps.len());
        Self {
            first_triangle,
            triangle_maps,
            maps,
            words,
        }
    }

    /// The whole hit filter's answer at barycentrics `b` of `triangle` in `geometry`, as
    /// far as the map knows it without the shader: [`Opacity::Mixed`] for single-sided
    /// triangles (their back must be culled first) and triangles without a map.
    #[inline]
    pub fn at(&self, geometry: GeometryId, triangle: u32, b: Vec3A) -> Opacity {
        self.lookup(geometry, triangle, b, true)
    }

    /// The alpha test's answer at barycentrics `b` of `triangle` in `geometry`, as far as
    /// the map knows it, for a hit already known to be on a side the shader shows.
    #[inline]
    pub fn alpha_at(&self, geometry: GeometryId, triangle: u32, b: Vec3A) -> Opacity {
        self.lookup(geometry, triangle, b, false)
    }

    /// The map's state at `b`; [`Opacity::Mixed`] for a single-sided layout when
    /// `cull_first` (its back is not yet ruled out).
    #[inline]
    fn lookup(&self, geometry: GeometryId, triangle: u32, b: Vec3A, cull_first: bool) -> Opacity {
        let Some(&first) = self.first_triangle.get(geometry.0 as usize) else {
            return Opacity::Mixed;
        };
        if first == NO_MAP {
            return Opacity::Mixed;
        }
        let entry = self.triangle_maps.get(first as usize + triangle as usize);
        // NO_MAP names no header.
        let Some(header) = self.maps.get(entry as usize) else {
            return Opacity::Mixed;
        };
        if !header.usable || (cull_first && header.single_sided) {
            return Opacity::Mixed;
        }
        let Some(index) = subtriangle(header.level, b.y, b.z) else {
            return Opacity::Mixed;
        };
        let word = self.words[header.first_word as usize + (index >> 5) as usize];
        match (word >> (2 * (index & 31))) & 3 {
            OPAQUE => Opacity::Opaque,
            HOLE => Opacity::Hole,
            _ => Opacity::Mixed,
        }
    }

    /// Distinct maps built.
    pub fn map_count(&self) -> usize {
        self.maps.len()
    }

    /// Heap bytes held.
    pub fn memory_bytes(&self) -> usize {
        self.first_triangle.capacity() * 4
            + self.triangle_maps.memory_bytes()
            + self.maps.capacity() * std::mem::size_of::<MapHeader>()
            + self.words.capacity() * 8
    }
}

/// The index of the sub-triangle holding barycentrics (·, `u`, `v`) at `level`, or
/// `None` when the point lies clearly outside the triangle (or is NaN). Sub-triangles
/// are numbered row by row: row `i` (`i ≤ u·n < i + 1`) starts at `i·(2n − i)` and holds
/// the lower triangle of cell `j` at `2j`, its upper one at `2j + 1`.
#[inline]
fn subtriangle(level: u32, u: f32, v: f32) -> Option<u32> {
    const SLACK: f32 = 1e-5;
    if !(u >= -SLACK && v >= -SLACK && u + v <= 1.0 + SLACK) {
        return None;
    }
    let n = 1i32 << level;
    let (fu, fv) = (u * n as f32, v * n as f32);
    let i = (fu as i32).clamp(0, n - 1);
    let j = (fv as i32).clamp(0, n - 1 - i);
    let upper = i + j < n - 1 && (fu - i as f32) + (fv - j as f32) > 1.0;
    Some((i * (2 * n - i) + 2 * j + i32::from(upper)) as u32)
}

/// The level at which a sub-triangle covers at most [`TARGET_TEXELS`].
fn wanted_level(shader: &Shader, uvs: &[Vec2; 3]) -> u32 {
    let Some(texture) = &shader.texture else {
        return 0;
    };
    let size = DVec2::new(texture.width() as f64, texture.height() as f64);
    let [a, b, c] = uvs.map(|uv| transform_uv(shader, uv.as_dvec2()) * size);
    let area = 0.5 * (b - a).perp_dot(c - a).abs();
    let mut level = 0;
    while level < MAX_LEVEL && area / (1u64 << (2 * level)) as f64 > TARGET_TEXELS {
        level += 1;
    }
    level
}

/// The shader's UV transform in f64, with the f32 sine and cosine `UvTransform::apply`
/// uses.
fn transform_uv(shader: &Shader, uv: DVec2) -> DVec2 {
    match &shader.uv_transform {
        Some(t) => {
            let (sin, cos) = t.rotation.sin_cos();
            let (sin, cos) = (sin as f64, cos as f64);
            let s = uv * t.scale.as_dvec2();
            DVec2::new(s.x * cos + s.y * sin, s.y * cos - s.x * sin) + t.offset.as_dvec2()
        }
        None => uv,
    }
}

/// The map of one layout, or `None` when its shader has no usable cut-off.
fn build_map(shader: &Shader, uvs: &[Vec2; 3], level: u32) -> Option<BuiltMap> {
    let texture = shader.texture.as_ref()?;
    let cutoff = f64::from(shader.alpha_cutoff?);
    if !cutoff.is_finite() {
        return None;
    }
    let [p0, p1, p2] = uvs.map(|uv| uv.as_dvec2());
    let (e1, e2) = (p1 - p0, p2 - p0);
    // Corner slack: points assigned to a sub-triangle lie within BARYCENTRIC_SLACK of it
    // in each coordinate; the interpolation rounds relative to the UVs' size.
    let slack = (e1.abs() + e2.abs()) * (2.0 * BARYCENTRIC_SLACK)
        + (p0.abs() + p1.abs() + p2.abs()) * RELATIVE_SLACK;
    let size = DVec2::new(texture.width() as f64, texture.height() as f64);
    let n = 1u32 << level;
    let at = |u: u32, v: u32| p0 + e1 * (u as f64 / n as f64) + e2 * (v as f64 / n as f64);
    let classify = |corners: [DVec2; 3]| -> u64 {
        let lo = corners[0].min(corners[1]).min(corners[2]) - slack;
        let hi = corners[0].max(corners[1]).max(corners[2]) + slack;
        let box_corners = [lo, DVec2::new(hi.x, lo.y), DVec2::new(lo.x, hi.y), hi];
        let moved = box_corners.map(|c| transform_uv(shader, c));
        let (mut tlo, mut thi) = (moved[0], moved[0]);
        for c in &moved[1..] {
            tlo = tlo.min(*c);
            thi = thi.max(*c);
        }
        let reach = tlo.abs().max(thi.abs()).max_element() + 1.0;
        let (tlo, thi) = (tlo - reach * RELATIVE_SLACK, thi + reach * RELATIVE_SLACK);
        // Texel coordinates as the bilinear footprint computes them.
        let xlo = tlo * size - 0.5;
        let xhi = thi * size - 0.5;
        let texel_slack = 1e-4 + RELATIVE_SLACK * xlo.abs().max(xhi.abs()).max_element();
        let (xlo, xhi) = (xlo - texel_slack, xhi + texel_slack);
        let within = xlo.abs().max(xhi.abs()).max_element() < TEXEL_LIMIT;
        if !within {
            // Also NaN: a comparison with NaN is false.
            return MIXED;
        }
        let [least, most] = texture.alpha_bounds([xlo.x, xhi.x], [xlo.y, xhi.y]);
        // The texels' alphas as the sample computes them (f32), then the bilinear sum's
        // rounding.
        let alpha = |byte: u8| f64::from(f32::from(byte) / 255.0);
        if alpha(least) * (1.0 - RELATIVE_SLACK) >= cutoff {
            OPAQUE
        } else if alpha(most) * (1.0 + RELATIVE_SLACK) < cutoff {
            HOLE
        } else {
            MIXED
        }
    };
    let count = 1usize << (2 * level);
    let mut words = vec![0u64; count.div_ceil(32)];
    let mut index = 0usize;
    for i in 0..n {
        for j in 0..n - i {
            let lower = classify([at(i, j), at(i + 1, j), at(i, j + 1)]);
            words[index >> 5] |= lower << (2 * (index & 31));
            index += 1;
            if i + j < n - 1 {
                let upper = classify([at(i + 1, j), at(i, j + 1), at(i + 1, j + 1)]);
                words[index >> 5] |= upper << (2 * (index & 31));
                index += 1;
            }
        }
    }
    debug_assert_eq!(index, count);
    Some(BuiltMap { level, words })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::accel::bvh::BuildParams;
    use crate::accel::geometry::Geometry;
    use crate::accel::mesh::TriangleMesh;
    use crate::material::shading::{ShaderId, Texture, UvTransform, WrapMode};
    use crate::util::test_random::uniform;
    use glam::Vec3;
    use std::sync::Arc;

    #[test]
    fn map_indices_keep_every_index_and_the_absent_map_at_each_width() {
        for (map_count, width) in [(1, 1), (254, 1), (255, 2), (65_534, 2), (65_535, 4)] {
            let indices: Vec<u32> = (0..1_000u32)
                .map(|i| {
                    if i % 7 == 3 {
                        NO_MAP
                    } else {
                        (i * 7919) % map_count
                    }
                })
                .chain([map_count - 1, 0, NO_MAP])
                .collect();
            let narrowed = MapIndices::narrowed(indices.clone(), map_count as usize);
            assert_eq!(
                narrowed.memory_bytes(),
                indices.len() * width,
                "{map_count} maps"
            );
            for (i, &index) in indices.iter().enumerate() {
                assert_eq!(narrowed.get(i), index, "entry {i} of {map_count} maps");
            }
            assert_eq!(narrowed.get(indices.len()), NO_MAP, "past the end");
        }
    }

    /// A `width`×`height` mask shaped like a leaf: opaque inside an ellipse, a hole
    /// outside, with a rim of random texels, some at the cut-off's own byte (exact ties).
    fn leaf_mask(state: &mut u64, width: u32, height: u32) -> Texture {
        let texels = (0..width * height)
            .map(|i| {
                let x = ((i % width) as f32 + 0.5) / width as f32 - 0.5;
                let y = ((i / width) as f32 + 0.5) / height as f32 - 0.5;
                let r = (x * x / 0.16 + y * y / 0.09).sqrt();
                let alpha = if r < 0.8 {
                    255
                } else if r > 1.0 {
                    0
                } else {
                    [0, 128, 255, 127][(uniform(state) * 4.0) as usize]
                };
                [90, 140, 30, alpha]
            })
            .collect();
        Texture::from_srgba8(width, height, texels).unwrap()
    }

    /// One triangle with these UVs and shader 0.
    fn library_of(uvs: [Vec2; 3]) -> GeometryLibrary {
        let mesh = TriangleMesh {
            positions: vec![Vec3::ZERO, Vec3::X, Vec3::Y],
            normals: vec![],
            uvs: uvs.to_vec(),
            indices: vec![[0, 1, 2]],
            shaders: vec![0],
        };
        let mut library = GeometryLibrary::default();
        library.add(Geometry::new("triangle", mesh, BuildParams::BALANCED).unwrap());
        library
    }

    /// Barycentrics as the triangle test returns them: each weight rounded to f32.
    fn barycentrics(u: f64, v: f64) -> Vec3A {
        Vec3A::new((1.0 - u - v) as f32, u as f32, v as f32)
    }

    #[test]
    fn every_decided_point_gives_the_texture_tests_answer() {
        let mut state = 0x5eed_0f0c_u64;
        let (mut decided, mut points) = (0u64, 0u64);
        for case in 0..400 {
            let (w, h) = (
                1 + (uniform(&mut state) * 40.0) as u32,
                1 + (uniform(&mut state) * 40.0) as u32,
            );
            let modes = [
                WrapMode::Repeat,
                WrapMode::ClampToEdge,
                WrapMode::MirroredRepeat,
            ];
            let wrap = [0, 1].map(|_| modes[(uniform(&mut state) * 3.0) as usize]);
            let texture = leaf_mask(&mut state, w, h).with_wrap(wrap[0], wrap[1]);
            // Cut-offs on and between the alpha bytes.
            let cutoff = [0.5, 128.0 / 255.0, 0.0, 1.0, uniform(&mut state)][case % 5];
            let mut shader =
                Shader::alpha_masked(ShaderId(0), Vec3::ONE, Arc::new(texture), cutoff);
            if case % 3 == 0 {
                shader.uv_transform = Some(UvTransform {
                    offset: Vec2::new(uniform(&mut state), -uniform(&mut state)),
                    rotation: uniform(&mut state) * 6.0,
                    scale: Vec2::new(0.5 + uniform(&mut state) * 2.0, -1.5),
                });
            }
            // UVs on texel boundaries and centres half the time, random otherwise.
            let corner = |state: &mut u64| {
                let snap = |c: f32, n: u32| (c * 2.0 * n as f32).round() / (2.0 * n as f32);
                let c = Vec2::new(uniform(state) * 5.0 - 2.0, uniform(state) * 5.0 - 2.0);
                if case % 2 == 0 {
                    Vec2::new(snap(c.x, w), snap(c.y, h))
                } else {
                    c
                }
            };
            let uvs = [corner(&mut state), corner(&mut state), corner(&mut state)];
            let library = library_of(uvs);
            let shaders = ShaderTable::new(vec![shader.clone()]);
            let maps = OpacityMaps::build(&library, &shaders);
            let level = maps.maps.first().map_or(0, |m| m.level);
            let n = f64::from(1u32 << level);
            let mesh = &library.geometries[0].mesh;
            for k in 0..600 {
                let (u, v) = match k % 3 {
                    // On the sub-triangles' edges and corners.
                    0 => {
                        let i = (uniform(&mut state) as f64 * (n + 1.0)).floor();
                        let j = (uniform(&mut state) as f64 * (n + 1.0 - i)).floor();
                        let t = if k % 2 == 0 {
                            0.0
                        } else {
                            uniform(&mut state) as f64 / n
                        };
                        (i / n + t, (j / n - t).max(0.0))
                    }
                    _ => {
                        let (a, b) = (uniform(&mut state) as f64, uniform(&mut state) as f64);
                        if a + b > 1.0 {
                            (1.0 - a, 1.0 - b)
                        } else {
                            (a, b)
                        }
                    }
                };
                let b = barycentrics(u, v);
                let truth = shader.is_opaque_at(mesh.uv_at(0, b));
                points += 1;
                match maps.at(GeometryId(0), 0, b) {
                    Opacity::Opaque => assert!(truth, "case {case}: opaque at {b} of {uvs:?}"),
                    Opacity::Hole => assert!(!truth, "case {case}: hole at {b} of {uvs:?}"),
                    Opacity::Mixed => continue,
                }
                decided += 1;
            }
        }
        // The maps must decide most points, or the test proves little.
        assert!(decided * 2 > points, "decided {decided} of {points}");
    }

    #[test]
    fn ties_at_the_cutoff_on_a_texel_boundary_stay_exact() {
        // Columns of alpha 0 | 128 … 128 | 0 and the cut-off at 128: a point whose
        // interpolated u rounds a hair below the boundary u = 1.5 / 8 reads column 0
        // with a tiny weight: a hole, though the triangle lies right of the boundary.
        let texels = [0, 128, 128, 128, 128, 128, 128, 0]
            .map(|a| [50, 50, 50, a])
            .to_vec();
        let texture = Texture::from_srgba8(8, 1, texels)
            .unwrap()
            .with_wrap(WrapMode::ClampToEdge, WrapMode::Repeat);
        let shader = Shader::alpha_masked(ShaderId(0), Vec3::ONE, Arc::new(texture), 128.0 / 255.0);
        let uvs = [
            Vec2::new(0.1875, 0.0),
            Vec2::new(0.25, 0.0),
            Vec2::new(0.1875, 1.0),
        ];
        let library = library_of(uvs);
        let maps = OpacityMaps::build(&library, &ShaderTable::new(vec![shader.clone()]));
        let mesh = &library.geometries[0].mesh;
        let mut state = 11u64;
        let mut holes = 0;
        for _ in 0..20_000 {
            // On the edge u = 0.1875 (no weight on the second corner), the weights' sum a
            // rounding below, at or above 1, as the triangle test's f32 weights can be.
            let v = uniform(&mut state);
            let w = (1.0 - f64::from(v)) as f32;
            let w = [w.next_down(), w, w.next_up()][(uniform(&mut state) * 3.0) as usize];
            let b = Vec3A::new(w, 0.0, v);
            let truth = shader.is_opaque_at(mesh.uv_at(0, b));
            holes += usize::from(!truth);
            match maps.at(GeometryId(0), 0, b) {
                Opacity::Opaque => assert!(truth, "opaque at {b}"),
                Opacity::Hole => assert!(!truth, "hole at {b}"),
                Opacity::Mixed => {}
            }
        }
        assert!(holes > 0, "the rounding this test is about never happened");
    }

    #[test]
    fn a_leaf_quad_shares_one_map_per_triangle_layout_and_decides_most_of_it() {
        let mut state = 7u64;
        let texture = Arc::new(leaf_mask(&mut state, 64, 64));
        let quad = |x: f32| TriangleMesh {
            positions: vec![
                Vec3::new(x, 0.0, 0.0),
                Vec3::new(x + 1.0, 0.0, 0.0),
                Vec3::new(x + 1.0, 1.0, 0.0),
                Vec3::new(x, 1.0, 0.0),
            ],
            normals: vec![],
            uvs: vec![
                Vec2::new(0.0, 1.0),
                Vec2::new(1.0, 1.0),
                Vec2::ONE,
                Vec2::ZERO,
            ],
            indices: vec![[0, 1, 2], [0, 2, 3]],
            shaders: vec![0, 0],
        };
        let mut mesh = quad(0.0);
        for k in 1..50 {
            let next = quad(k as f32);
            let base = mesh.positions.len() as u32;
            mesh.positions.extend(next.positions);
            mesh.uvs.extend(next.uvs);
            mesh.indices
                .extend(next.indices.iter().map(|t| t.map(|i| i + base)));
            mesh.shaders.extend(next.shaders);
        }
        let mut library = GeometryLibrary::default();
        library.add(Geometry::new("leaves", mesh.clone(), BuildParams::BALANCED).unwrap());
        library.add(Geometry::new("more leaves", mesh, BuildParams::BALANCED).unwrap());
        let shaders = ShaderTable::new(vec![Shader::alpha_masked(
            ShaderId(0),
            Vec3::ONE,
            texture,
            0.5,
        )]);
        let maps = OpacityMaps::build(&library, &shaders);
        assert_eq!(
            maps.map_count(),
            2,
            "one map per triangle of the quad's layout"
        );
        let (mut decided, mut points) = (0, 0);
        for _ in 0..10_000 {
            let (a, b) = (uniform(&mut state) as f64, uniform(&mut state) as f64);
            let (u, v) = if a + b > 1.0 {
                (1.0 - a, 1.0 - b)
            } else {
                (a, b)
            };
            points += 1;
            decided +=
                usize::from(maps.at(GeometryId(1), 37, barycentrics(u, v)) != Opacity::Mixed);
        }
        // All but the rim of random texels and the footprints reaching it.
        assert!(decided * 3 > points * 2, "decided {decided} of {points}");
    }

    #[test]
    fn single_sided_triangles_and_unmapped_ones_are_left_to_the_full_filter() {
        let mut state = 3u64;
        let texture = Arc::new(leaf_mask(&mut state, 32, 32));
        let uvs = [Vec2::ZERO, Vec2::X, Vec2::Y];
        let mut shader = Shader::alpha_masked(ShaderId(0), Vec3::ONE, texture.clone(), 0.5);
        shader.double_sided = false;
        let maps = OpacityMaps::build(&library_of(uvs), &ShaderTable::new(vec![shader]));
        // The middle of the texture, inside the leaf.
        let b = barycentrics(0.45, 0.45);
        assert_eq!(maps.at(GeometryId(0), 0, b), Opacity::Mixed);
        assert_ne!(maps.alpha_at(GeometryId(0), 0, b), Opacity::Mixed);
        let plain = Shader::textured(ShaderId(0), Vec3::ONE, texture);
        let maps = OpacityMaps::build(&library_of(uvs), &ShaderTable::new(vec![plain]));
        assert_eq!(maps.map_count(), 0);
        assert_eq!(maps.alpha_at(GeometryId(0), 0, b), Opacity::Mixed);
        assert_eq!(
            OpacityMaps::default().at(GeometryId(3), 9, b),
            Opacity::Mixed
        );
        // Points outside the triangle or NaN are never decided.
        for outside in [Vec3A::new(0.5, 0.6, -0.1), Vec3A::splat(f32::NAN)] {
            assert_eq!(subtriangle(3, outside.y, outside.z), None);
        }
    }

    #[test]
    fn sub_triangles_are_numbered_densely() {
        for level in 0..5 {
            let n = 1u32 << level;
            let mut seen = vec![false; (n * n) as usize];
            for i in 0..n {
                for j in 0..n - i {
                    let centre = |du: f32, dv: f32| {
                        subtriangle(
                            level,
                            (i as f32 + du) / n as f32,
                            (j as f32 + dv) / n as f32,
                        )
                    };
                    let mut mark = |index: Option<u32>| {
                        let index = index.unwrap() as usize;
                        assert!(!seen[index], "level {level}: {index} twice");
                        seen[index] = true;
                    };
                    mark(centre(1.0 / 3.0, 1.0 / 3.0));
                    if i + j < n - 1 {
                        mark(centre(2.0 / 3.0, 2.0 / 3.0));
                    }
                }
            }
            assert!(seen.iter().all(|&s| s), "level {level}");
        }
    }
}
