//! # sylva_engine
//!
//! Sylva's data and kernels, independent of any schedule or file format: math and
//! robust floating point, structure-of-arrays meshes, BVH build and traversal (one BVH
//! type for the per-species BLAS and the instance TLAS), watertight triangle tests,
//! textures and shaders, lights, hash-based sampling, cameras, films and the tile render
//! kernel. The ECS components live here too, so every crate agrees on them.

pub mod bvh;
pub mod camera;
pub mod camera_path;
pub mod components;
pub mod discontinuity;
pub mod environment;
pub mod film;
pub mod fingerprint;
pub mod geometry;
pub mod heightfield;
pub mod interleave;
pub mod light;
pub mod math;
pub mod mesh;
pub mod metrics;
pub mod node_animation;
pub mod occluders;
pub mod opacity;
pub mod presplit;
pub mod render;
pub mod sampling;
pub mod shading;
pub mod support;
pub mod sway;
#[cfg(test)]
mod test_random;
pub mod tlas;
pub mod transparency;
pub mod triangle;

pub use bvh::{BuildParams, Bvh, TraversalStats};
pub use camera::{Camera, CameraView, Lens};
pub use components::{Hidden, Instance, Transform};
pub use film::{Film, FrameBuffer, ImageKind, OutputError, Tile};
pub use geometry::{Geometry, GeometryId, GeometryLibrary};
pub use light::{DirectionalLight, LightSet, SkyLight};
pub use math::{Aabb, Ray};
pub use mesh::TriangleMesh;
pub use opacity::OpacityMaps;
pub use render::{
    FramePlan, RenderParams, RenderScene, SampleShading, render_frame, render_frame_unless,
    render_tile,
};
pub use shading::{Shader, ShaderId, ShaderTable, Texture};
pub use tlas::{InstanceDesc, TopLevel};
