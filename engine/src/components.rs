//! ECS components of plants: where they stand and what they are. Cameras, films,
//! shaders and lights define theirs in their own modules.

use crate::accel::geometry::GeometryId;
use bevy_ecs::component::Component;
use glam::{Affine3A, Quat, Vec3};

/// Placement of an entity: scale, then rotation, then translation.
#[derive(Component, Clone, Copy, Debug, PartialEq)]
pub struct Transform {
    /// Position.
    pub translation: Vec3,
    /// Orientation.
    pub rotation: Quat,
    /// Per-axis scale.
    pub scale: Vec3,
}

impl Default for Transform {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Transform {
    /// No change.
    pub const IDENTITY: Transform = Transform {
        translation: Vec3::ZERO,
        rotation: Quat::IDENTITY,
        scale: Vec3::ONE,
    };

    /// A pure translation.
    pub fn from_translation(translation: Vec3) -> Self {
        Self {
            translation,
            ..Self::IDENTITY
        }
    }

    /// Positioned at `eye`, looking at `target` (−Z forward), with `up` as the upward hint.
    pub fn looking_at(eye: Vec3, target: Vec3, up: Vec3) -> Self {
        let forward = (target - eye).normalize_or(-Vec3::Z);
        let right = forward.cross(up).normalize_or(Vec3::X);
        let true_up = right.cross(forward);
        let rotation = Quat::from_mat3(&glam::Mat3::from_cols(right, true_up, -forward));
        Self {
            translation: eye,
            rotation,
            scale: Vec3::ONE,
        }
    }

    /// This transform with another scale.
    pub fn with_scale(self, scale: Vec3) -> Self {
        Self { scale, ..self }
    }

    /// This transform with another rotation.
    pub fn with_rotation(self, rotation: Quat) -> Self {
        Self { rotation, ..self }
    }

    /// Object → world matrix.
    pub fn to_affine(&self) -> Affine3A {
        Affine3A::from_scale_rotation_translation(self.scale, self.rotation, self.translation)
    }
}

/// Makes an entity a placed copy of a mesh from the `GeometryLibrary`.
#[derive(Component, Clone, Copy, Debug, PartialEq, Eq)]
pub struct Instance {
    /// Which mesh.
    pub geometry: GeometryId,
}

/// An instance left out of rendering while it has this marker.
#[derive(Component, Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Hidden;

/// The vegetation layer a plant belongs to (index into its scene's layer list).
#[derive(Component, Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Layer(pub u32);
