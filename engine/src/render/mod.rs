//! The render kernel: a pure function of flat scene data, camera, parameters, tile and
//! frame index. The schedule, benchmarks, tests and the cluster's workers all call it.
//! Read in order: [`plan`] (what a frame is rendered with), [`camera`] (its rays),
//! [`scene`] (ray queries), [`integrate`] (shading a hit), [`tile`] (tiles and frames).
//!
//! Shading: Lambertian surfaces lit by directional lights (one shadow ray each) and by
//! the environment (virtual lights, optionally interleaved) or the gradient sky
//! (cosine-weighted shadow rays). Hit filters run the alpha test in place during
//! traversal, for camera and shadow rays alike; adaptive transparency turns holes beyond
//! a camera's allowance into opaque hits.

pub mod camera;
pub mod integrate;
pub mod plan;
pub mod scene;
pub mod tile;

pub use integrate::{ShadedSample, SurfacePoint};
pub use plan::{FramePlan, RenderParams, SampleShading};
pub use scene::{PacketScratch, RenderData, RenderScene};
pub use tile::{render_frame, render_frame_unless, render_tile};
