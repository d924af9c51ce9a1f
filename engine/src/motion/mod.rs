//! What moves between frames: plants swaying in the wind, glTF node animation and the
//! camera's key-frame paths.

pub mod camera_path;
pub mod node_animation;
pub mod sway;
