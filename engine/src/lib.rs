//! # sylva_engine
//!
//! Sylva's data and kernels, independent of any schedule or file format: math and
//! robust floating point, structure-of-arrays meshes, BVH build and traversal (one BVH
//! type for the per-species BLAS and the instance TLAS), watertight triangle tests,
//! textures and shaders, lights, hash-based sampling, cameras, films and the tile render
//! kernel. The ECS components live here too, so every crate agrees on them.

pub mod accel;
pub mod components;
pub mod film;
pub mod light;
pub mod material;
pub mod motion;
pub mod render;
pub mod util;

// The modules' paths from before the engine had folders, kept for the other crates.
pub use accel::{
    bvh, geometry, heightfield, instance_bounds as support, mesh, occluders, presplit, tlas,
    triangle,
};
pub use film::{discontinuity, metrics};
pub use light::{environment, interleave};
pub use material::{opacity, shading, transparency};
pub use motion::{camera_path, node_animation, sway};
pub use render::camera;
pub use util::{fingerprint, math, sampling};

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
