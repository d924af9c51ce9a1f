//! Procedural plant species: stems and branches as generalised cylinders, leaves as small
//! fans, grass blades as tapered strips. Each species is one mesh, deterministic from its
//! parameters and seed; instances give the variety.

use crate::random::SceneRng;
use glam::{Quat, Vec2, Vec3};
use sylva_engine::mesh::TriangleMesh;

/// The shader ids a species uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SpeciesShaders {
    /// Bark or stem.
    pub bark: u32,
    /// Leaves or blades.
    pub leaf: u32,
}

/// Appends meshes piece by piece.
#[derive(Default)]
struct MeshBuilder {
    mesh: TriangleMesh,
}

impl MeshBuilder {
    fn vertex(&mut self, p: Vec3, n: Vec3, uv: Vec2) -> u32 {
        self.mesh.positions.push(p);
        self.mesh.normals.push(n.normalize_or(Vec3::Y));
        self.mesh.uvs.push(uv);
        self.mesh.positions.len() as u32 - 1
    }

    fn triangle(&mut self, a: u32, b: u32, c: u32, shader: u32) {
        self.mesh.indices.push([a, b, c]);
        self.mesh.shaders.push(shader);
    }

    /// A generalised cylinder along `path` with radius `radii[i]` at point `i`, frames
    /// carried by parallel transport so the tube does not twist.
    fn tube(&mut self, path: &[Vec3], radii: &[f32], sides: u32, shader: u32) {
        if path.len() < 2 {
            return;
        }
        let first_dir = (path[1] - path[0]).normalize_or(Vec3::Y);
        let mut normal = first_dir.any_orthonormal_vector();
        let mut prev_dir = first_dir;
        let base = self.mesh.positions.len() as u32;
        for (i, &p) in path.iter().enumerate() {
            let dir = if i + 1 < path.len() {
                (path[i + 1] - p).normalize_or(prev_dir)
            } else {
                prev_dir
            };
            normal = (Quat::from_rotation_arc(prev_dir, dir) * normal).normalize();
            prev_dir = dir;
            let binormal = dir.cross(normal);
            for s in 0..=sides {
                let a = std::f32::consts::TAU * s as f32 / sides as f32;
                let n = normal * a.cos() + binormal * a.sin();
                self.vertex(
                    p + n * radii[i],
                    n,
                    Vec2::new(s as f32 / sides as f32, i as f32),
                );
            }
        }
        let ring = sides + 1;
        for i in 0..path.len() as u32 - 1 {
            for s in 0..sides {
                let a = base + i * ring + s;
                let (b, c, d) = (a + 1, a + ring, a + ring + 1);
                self.triangle(a, c, b, shader);
                self.triangle(b, c, d, shader);
            }
        }
    }

    /// A leaf: a six-vertex fan (pointed ellipse) starting at `base`, along `dir`, facing
    /// `up` as well as it can.
    fn leaf(&mut self, base: Vec3, dir: Vec3, up: Vec3, length: f32, width: f32, shader: u32) {
        let dir = dir.normalize_or(Vec3::Y);
        let side = dir.cross(up).normalize_or(dir.any_orthonormal_vector());
        let normal = side.cross(dir);
        // A slight fold along the midrib so leaves are not perfectly flat.
        let fold = normal * width * 0.15;
        let pts = [
            (base, Vec2::new(0.5, 1.0)),
            (
                base + dir * length * 0.3 + side * width * 0.45 + fold,
                Vec2::new(0.05, 0.7),
            ),
            (
                base + dir * length * 0.7 + side * width * 0.35 + fold,
                Vec2::new(0.15, 0.3),
            ),
            (base + dir * length, Vec2::new(0.5, 0.0)),
            (
                base + dir * length * 0.7 - side * width * 0.35 + fold,
                Vec2::new(0.85, 0.3),
            ),
            (
                base + dir * length * 0.3 - side * width * 0.45 + fold,
                Vec2::new(0.95, 0.7),
            ),
        ];
        let ids: Vec<u32> = pts
            .iter()
            .map(|&(p, uv)| self.vertex(p, normal, uv))
            .collect();
        for k in 1..5 {
            self.triangle(ids[0], ids[k], ids[k + 1], shader);
        }
    }
}

/// A tuft of `blades` curved grass blades about `height` metres tall (8 triangles per
/// blade).
pub fn grass_tuft(seed: u64, blades: u32, height: f32, shaders: SpeciesShaders) -> TriangleMesh {
    let mut rng = SceneRng::new(seed, "grass_tuft");
    let mut b = MeshBuilder::default();
    for _ in 0..blades {
        let angle = rng.range(0.0, std::f32::consts::TAU);
        let root = Vec3::new(angle.cos(), 0.0, angle.sin()) * rng.range(0.0, 0.08);
        let lean = Vec3::new(angle.cos(), 0.0, angle.sin()) * rng.range(0.1, 0.5);
        let h = height * rng.range(0.6, 1.2);
        let w = rng.range(0.008, 0.016);
        let side = Vec3::new(-angle.sin(), 0.0, angle.cos());
        let segments = 4;
        let mut rows = Vec::new();
        for s in 0..=segments {
            let t = s as f32 / segments as f32;
            let p = root + Vec3::Y * h * t + lean * h * t * t;
            let half = w * (1.0 - t * 0.9);
            let tangent = (Vec3::Y + lean * 2.0 * t).normalize();
            let n = side.cross(tangent);
            rows.push((
                b.vertex(p - side * half, n, Vec2::new(0.0, 1.0 - t)),
                b.vertex(p + side * half, n, Vec2::new(1.0, 1.0 - t)),
            ));
        }
        for s in 0..segments as usize {
            let (a0, a1) = rows[s];
            let (b0, b1) = rows[s + 1];
            b.triangle(a0, b0, a1, shaders.leaf);
            b.triangle(a1, b0, b1, shaders.leaf);
        }
    }
    b.mesh
}

/// A shrub of about `height` metres: a few stems carrying `leaves_per_stem` leaves each.
pub fn shrub(
    seed: u64,
    stems: u32,
    leaves_per_stem: u32,
    height: f32,
    shaders: SpeciesShaders,
) -> TriangleMesh {
    let mut rng = SceneRng::new(seed, "shrub");
    let mut b = MeshBuilder::default();
    for _ in 0..stems {
        let dir = (Vec3::Y * 2.0 + rng.unit() * Vec3::new(1.0, 0.0, 1.0)).normalize();
        let len = height * rng.range(0.7, 1.1);
        let bend = rng.unit() * Vec3::new(1.0, 0.0, 1.0) * 0.25;
        let path: Vec<Vec3> = (0..=4)
            .map(|i| {
                let t = i as f32 / 4.0;
                (dir + bend * t) * len * t
            })
            .collect();
        let radii: Vec<f32> = (0..=4).map(|i| 0.015 * (1.0 - i as f32 / 5.0)).collect();
        b.tube(&path, &radii, 4, shaders.bark);
        for _ in 0..leaves_per_stem {
            let t = rng.range(0.25, 1.0);
            let at = (dir + bend * t) * len * t;
            let leaf_dir = (rng.unit() + Vec3::Y * 0.6).normalize();
            b.leaf(
                at,
                leaf_dir,
                Vec3::Y,
                rng.range(0.08, 0.14),
                rng.range(0.04, 0.07),
                shaders.leaf,
            );
        }
    }
    b.mesh
}

/// A small tree of about `height` metres: a tapered trunk, `branches` branches with
/// twigs, and `leaves_per_branch` leaves on each branch.
pub fn small_tree(
    seed: u64,
    height: f32,
    branches: u32,
    leaves_per_branch: u32,
    shaders: SpeciesShaders,
) -> TriangleMesh {
    let mut rng = SceneRng::new(seed, "small_tree");
    let mut b = MeshBuilder::default();
    let trunk_top = height * 0.55;
    let sway = Vec3::new(rng.range(-0.1, 0.1), 0.0, rng.range(-0.1, 0.1));
    let trunk: Vec<Vec3> = (0..=6)
        .map(|i| {
            let t = i as f32 / 6.0;
            Vec3::Y * trunk_top * t + sway * t * t * height
        })
        .collect();
    let trunk_radius = height * 0.022;
    let radii: Vec<f32> = (0..=6)
        .map(|i| trunk_radius * (1.0 - 0.6 * i as f32 / 6.0))
        .collect();
    b.tube(&trunk, &radii, 8, shaders.bark);
    for k in 0..branches {
        let t = rng.range(0.45, 1.0);
        let start = Vec3::Y * trunk_top * t + sway * t * t * height;
        let azimuth = k as f32 * 2.399_963 + rng.range(-0.3, 0.3); // golden angle
        let out = Vec3::new(azimuth.cos(), 0.0, azimuth.sin());
        let up = rng.range(0.5, 1.3);
        let len = height * rng.range(0.25, 0.4) * (1.2 - t * 0.5);
        let dir = (out + Vec3::Y * up).normalize();
        let path: Vec<Vec3> = (0..=3)
            .map(|i| {
                let s = i as f32 / 3.0;
                start + dir * len * s - Vec3::Y * len * 0.15 * s * s
            })
            .collect();
        let r0 = trunk_radius * 0.45;
        b.tube(&path, &[r0, r0 * 0.7, r0 * 0.45, r0 * 0.2], 5, shaders.bark);
        for _ in 0..leaves_per_branch {
            let s = rng.range(0.2, 1.0);
            let at = start + dir * len * s - Vec3::Y * len * 0.15 * s * s + rng.unit() * len * 0.25;
            let leaf_dir = (rng.unit() + dir * 0.5 - Vec3::Y * 0.3).normalize();
            b.leaf(
                at,
                leaf_dir,
                Vec3::Y,
                rng.range(0.12, 0.2),
                rng.range(0.06, 0.1),
                shaders.leaf,
            );
        }
    }
    b.mesh
}

#[cfg(test)]
mod tests {
    use super::*;

    const SHADERS: SpeciesShaders = SpeciesShaders { bark: 1, leaf: 2 };

    #[test]
    fn species_are_valid_deterministic_and_grounded() {
        for mesh in [
            grass_tuft(1, 12, 0.4, SHADERS),
            shrub(1, 5, 12, 0.8, SHADERS),
            small_tree(1, 4.0, 12, 30, SHADERS),
        ] {
            mesh.check().unwrap();
            assert!(mesh.triangle_count() > 50);
            assert!(mesh.positions.iter().all(|p| p.is_finite()));
            assert!(mesh.normals.iter().all(|n| (n.length() - 1.0).abs() < 1e-3));
            let b = mesh.bounds();
            assert!(
                b.min.y > -0.2 && b.max.y > 0.3,
                "plants stand on their base: {b:?}"
            );
        }
        assert_eq!(
            small_tree(7, 4.0, 12, 30, SHADERS),
            small_tree(7, 4.0, 12, 30, SHADERS)
        );
        assert_ne!(
            small_tree(7, 4.0, 12, 30, SHADERS),
            small_tree(8, 4.0, 12, 30, SHADERS)
        );
    }
}
