//! Acceleration and geometry: what a ray is tested against. The BVH (one wide type for
//! both levels), meshes and their watertight triangle test, the per-species bottom level
//! ([`geometry`]), the instance top level ([`tlas`]) with its tight instance boxes, and the
//! shadow rays' occluder cache.

pub mod bvh;
pub mod geometry;
pub mod heightfield;
pub mod instance_bounds;
pub mod kernel;
pub mod mesh;
pub mod occluders;
pub mod presplit;
pub mod tlas;
pub mod triangle;
