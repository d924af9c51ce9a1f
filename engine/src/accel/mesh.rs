//! Triangle meshes in structure-of-arrays form.

use crate::util::math::Aabb;
use glam::{Vec2, Vec3, Vec3A};

/// An indexed triangle mesh, one array per attribute.
///
/// `normals` and `uvs` are either empty or one per position. `shaders[i]` is the
/// [`ShaderId`](crate::material::shading::ShaderId) value of triangle `i`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriangleMesh {
    /// Vertex positions in object space.
    pub positions: Vec<Vec3>,
    /// Unit vertex normals, or empty (flat shading).
    pub normals: Vec<Vec3>,
    /// Texture coordinates (glTF convention: (0, 0) is the image's top-left), or empty.
    pub uvs: Vec<Vec2>,
    /// Vertex indices of each triangle.
    pub indices: Vec<[u32; 3]>,
    /// Shader of each triangle.
    pub shaders: Vec<u32>,
}

/// Why a mesh cannot be used.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum MeshError {
    /// A triangle names a vertex that does not exist.
    #[error("triangle {triangle} uses vertex {index}, but the mesh has {vertices} vertices")]
    IndexOutOfRange {
        /// Offending triangle.
        triangle: usize,
        /// The bad index.
        index: u32,
        /// Vertex count.
        vertices: usize,
    },
    /// An attribute array has the wrong length.
    #[error("{attribute} has {found} entries, expected {expected}")]
    AttributeLength {
        /// Attribute name.
        attribute: &'static str,
        /// Its length.
        found: usize,
        /// The required length.
        expected: usize,
    },
    /// A vertex position is NaN or infinite (the BVH could not bound it).
    #[error("vertex {vertex} has a non-finite position {position}")]
    NonFinitePosition {
        /// The vertex.
        vertex: usize,
        /// Its position.
        position: Vec3,
    },
}

impl TriangleMesh {
    /// A closed UV sphere of radius about 1 whose ring vertices are moved radially by up
    /// to ±`jitter` (seeded); triangles share vertices by index, so it stays watertight.
    /// Watertightness tests and the leak benchmark aim rays at its edges and vertices.
    pub fn jittered_sphere(rings: u32, segments: u32, jitter: f32, seed: u64) -> Self {
        let (rings, segments) = (rings.max(2), segments.max(3));
        let mut rng = crate::util::sampling::SplitMix64(seed);
        let mut mesh = TriangleMesh::default();
        mesh.positions.push(Vec3::Y);
        for r in 1..rings {
            let theta = std::f32::consts::PI * r as f32 / rings as f32;
            for s in 0..segments {
                let phi = std::f32::consts::TAU * s as f32 / segments as f32;
                let radius = rng.range(1.0 - jitter, 1.0 + jitter);
                let direction = Vec3::new(
                    theta.sin() * phi.cos(),
                    theta.cos(),
                    theta.sin() * phi.sin(),
                );
                mesh.positions.push(direction * radius);
            }
        }
        mesh.positions.push(-Vec3::Y);
        let bottom = mesh.positions.len() as u32 - 1;
        let ring = |r: u32, s: u32| 1 + (r - 1) * segments + s % segments;
        for s in 0..segments {
            mesh.indices.push([0, ring(1, s + 1), ring(1, s)]);
            mesh.indices
                .push([bottom, ring(rings - 1, s), ring(rings - 1, s + 1)]);
        }
        for r in 1..rings - 1 {
            for s in 0..segments {
                let (a, b, c, d) = (
                    ring(r, s),
                    ring(r, s + 1),
                    ring(r + 1, s),
                    ring(r + 1, s + 1),
                );
                mesh.indices.push([a, b, d]);
                mesh.indices.push([a, d, c]);
            }
        }
        mesh.shaders = vec![0; mesh.indices.len()];
        mesh
    }

    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.indices.len()
    }

    /// Checks indices and attribute lengths.
    pub fn check(&self) -> Result<(), MeshError> {
        let v = self.positions.len();
        for (attribute, found) in [("normals", self.normals.len()), ("uvs", self.uvs.len())] {
            if found != 0 && found != v {
                return Err(MeshError::AttributeLength {
                    attribute,
                    found,
                    expected: v,
                });
            }
        }
        if self.shaders.len() != self.indices.len() {
            return Err(MeshError::AttributeLength {
                attribute: "shaders",
                found: self.shaders.len(),
                expected: self.indices.len(),
            });
        }
        if let Some((vertex, &position)) = self
            .positions
            .iter()
            .enumerate()
            .find(|(_, p)| !p.is_finite())
        {
            return Err(MeshError::NonFinitePosition { vertex, position });
        }
        for (triangle, tri) in self.indices.iter().enumerate() {
            if let Some(&index) = tri.iter().find(|&&i| i as usize >= v) {
                return Err(MeshError::IndexOutOfRange {
                    triangle,
                    index,
                    vertices: v,
                });
            }
        }
        Ok(())
    }

    /// The three corners of triangle `i`.
    #[inline]
    pub fn triangle(&self, i: usize) -> [Vec3A; 3] {
        let [a, b, c] = self.indices[i];
        [
            self.positions[a as usize].into(),
            self.positions[b as usize].into(),
            self.positions[c as usize].into(),
        ]
    }

    /// The texture coordinates at barycentrics `b` of triangle `i` ((0, 0) without UVs):
    /// the one interpolation the hit filter and shading both use.
    #[inline]
    pub fn uv_at(&self, i: usize, b: Vec3A) -> Vec2 {
        if self.uvs.is_empty() {
            return Vec2::ZERO;
        }
        let [i0, i1, i2] = self.indices[i];
        self.uvs[i0 as usize] * b.x + self.uvs[i1 as usize] * b.y + self.uvs[i2 as usize] * b.z
    }

    /// The box of triangle `i`; empty when a corner is not finite (such a triangle can
    /// never be hit, and min/max would silently drop a NaN).
    pub fn triangle_bounds(&self, i: usize) -> Aabb {
        let corners = self.triangle(i);
        if corners.iter().all(|c| c.is_finite()) {
            Aabb::from_points(corners)
        } else {
            Aabb::EMPTY
        }
    }

    /// The box of the whole mesh.
    pub fn bounds(&self) -> Aabb {
        Aabb::from_points(self.positions.iter().map(|&p| p.into()))
    }

    /// Heap bytes held.
    pub fn memory_bytes(&self) -> usize {
        self.positions.capacity() * 12
            + self.normals.capacity() * 12
            + self.uvs.capacity() * 8
            + self.indices.capacity() * 12
            + self.shaders.capacity() * 4
    }
}
