//! Height-field terrain: a grid of heights from fBm noise, sampled bilinearly for plant
//! placement and meshed as two triangles per cell.

use crate::random::{SceneRng, fbm};
use glam::{Vec2, Vec3};
use sylva_engine::mesh::TriangleMesh;
use sylva_engine::shading::Texture;

/// A 128×128 ground texture: grass green mottled with soil.
pub fn ground_texture(seed: u64) -> Texture {
    let n = 128u32;
    let mut rng = SceneRng::new(seed, "ground_texture");
    let texels = (0..n * n)
        .map(|i| {
            let (x, y) = ((i % n) as f32 / n as f32, (i / n) as f32 / n as f32);
            let soil = (fbm(seed, x * 6.0, y * 6.0, 4, 0.5) * 1.5 + 0.1).clamp(0.0, 1.0);
            let grain = rng.range(-0.06, 0.06);
            let grass = [0.30, 0.42, 0.16];
            let dirt = [0.42, 0.33, 0.22];
            let c: [f32; 3] = std::array::from_fn(|k| {
                (grass[k] + (dirt[k] - grass[k]) * soil + grain).clamp(0.0, 1.0)
            });
            [
                (c[0] * 255.0) as u8,
                (c[1] * 255.0) as u8,
                (c[2] * 255.0) as u8,
                255,
            ]
        })
        .collect();
    Texture::from_srgba8(n, n, texels).expect("the ground texture has n×n texels")
}

/// A square height field centred on the origin, +Y up.
#[derive(Clone, Debug, PartialEq)]
pub struct HeightField {
    /// Edge length in metres.
    pub size: f32,
    /// Cells per edge.
    pub cells: u32,
    /// `(cells + 1)²` heights, row-major from −Z to +Z, −X to +X.
    pub heights: Vec<f32>,
}

/// Shape of an fBm terrain.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TerrainParams {
    /// Edge length in metres.
    pub size: f32,
    /// Cells per edge (two triangles each).
    pub cells: u32,
    /// Height of the largest hills in metres.
    pub amplitude: f32,
    /// Wavelength of the largest hills in metres.
    pub wavelength: f32,
    /// Noise octaves.
    pub octaves: u32,
    /// Ridged noise (sharp crests, 1 − |fBm|) instead of rolling fBm hills.
    pub ridged: bool,
}

impl HeightField {
    /// A height field of fBm noise.
    pub fn fbm(seed: u64, p: &TerrainParams) -> Self {
        let cells = p.cells.max(1);
        let n = cells + 1;
        let step = p.size / cells as f32;
        let heights = (0..n * n)
            .map(|i| {
                let (x, z) = (
                    (i % n) as f32 * step - p.size / 2.0,
                    (i / n) as f32 * step - p.size / 2.0,
                );
                let v = fbm(seed, x / p.wavelength, z / p.wavelength, p.octaves, 0.45);
                let v = if p.ridged { 1.0 - 2.0 * v.abs() } else { v };
                p.amplitude * v
            })
            .collect();
        Self {
            size: p.size,
            cells,
            heights,
        }
    }

    fn grid(&self, ix: u32, iz: u32) -> f32 {
        let n = self.cells + 1;
        self.heights[(iz.min(self.cells) * n + ix.min(self.cells)) as usize]
    }

    /// Height at world `(x, z)`, bilinear; clamped to the edge outside the field.
    pub fn height_at(&self, x: f32, z: f32) -> f32 {
        let step = self.size / self.cells as f32;
        let gx = ((x + self.size / 2.0) / step).clamp(0.0, self.cells as f32);
        let gz = ((z + self.size / 2.0) / step).clamp(0.0, self.cells as f32);
        let (ix, iz) = (
            gx.floor().min(self.cells as f32 - 1.0) as u32,
            gz.floor().min(self.cells as f32 - 1.0) as u32,
        );
        let (tx, tz) = (gx - ix as f32, gz - iz as f32);
        // a·(1 − t) + b·t is exact at both ends, so grid points return their stored height.
        let lerp = |a: f32, b: f32, t: f32| a * (1.0 - t) + b * t;
        let a = lerp(self.grid(ix, iz), self.grid(ix + 1, iz), tx);
        let b = lerp(self.grid(ix, iz + 1), self.grid(ix + 1, iz + 1), tx);
        lerp(a, b, tz)
    }

    /// The mesh: vertex normals from central differences, UVs repeating every
    /// `uv_period` metres, one shader.
    pub fn to_mesh(&self, shader: u32, uv_period: f32) -> TriangleMesh {
        let n = self.cells + 1;
        let step = self.size / self.cells as f32;
        let mut mesh = TriangleMesh::default();
        for iz in 0..n {
            for ix in 0..n {
                let (x, z) = (
                    ix as f32 * step - self.size / 2.0,
                    iz as f32 * step - self.size / 2.0,
                );
                mesh.positions.push(Vec3::new(x, self.grid(ix, iz), z));
                let dx = self.grid(ix + 1, iz) - self.grid(ix.saturating_sub(1), iz);
                let dz = self.grid(ix, iz + 1) - self.grid(ix, iz.saturating_sub(1));
                let span_x = step * ((ix + 1).min(self.cells) - ix.saturating_sub(1)) as f32;
                let span_z = step * ((iz + 1).min(self.cells) - iz.saturating_sub(1)) as f32;
                mesh.normals
                    .push(Vec3::new(-dx / span_x, 1.0, -dz / span_z).normalize());
                mesh.uvs.push(Vec2::new(x, z) / uv_period);
            }
        }
        for iz in 0..self.cells {
            for ix in 0..self.cells {
                let a = iz * n + ix;
                let (b, c, d) = (a + 1, a + n, a + n + 1);
                mesh.indices.push([a, c, b]);
                mesh.indices.push([b, c, d]);
            }
        }
        mesh.shaders = vec![shader; mesh.indices.len()];
        mesh
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn height_at_matches_grid_and_mesh_faces_up() {
        let p = TerrainParams {
            size: 10.0,
            cells: 10,
            amplitude: 2.0,
            wavelength: 5.0,
            octaves: 3,
            ridged: false,
        };
        let h = HeightField::fbm(3, &p);
        assert_eq!(h.height_at(-5.0, -5.0), h.heights[0]);
        assert_eq!(h.height_at(5.0, 5.0), *h.heights.last().unwrap());
        assert_eq!(h.height_at(-50.0, 0.0), h.height_at(-5.0, 0.0));
        let mesh = h.to_mesh(0, 4.0);
        mesh.check().unwrap();
        assert_eq!(mesh.triangle_count(), 200);
        for i in 0..mesh.triangle_count() {
            let [a, b, c] = mesh.triangle(i);
            assert!((b - a).cross(c - a).y > 0.0, "triangle {i} faces down");
        }
    }
}
