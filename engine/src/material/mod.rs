//! What surfaces look like and let through: shaders and textures, the alpha masks'
//! opacity micromaps, and adaptive transparency for shadow rays.

pub mod opacity;
pub mod shading;
pub mod transparency;
