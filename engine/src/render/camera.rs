//! Cameras: pinhole and thin lens. A camera looks along −Z of its transform with +Y up
//! (the glTF convention); image rows run top to bottom.

use super::plan::RenderParams;
use crate::util::math::Ray;
use crate::util::sampling::concentric_disk;
use bevy_ecs::component::Component;
use glam::{Affine3A, Vec2, Vec3A};

/// How rays leave the camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Lens {
    /// Every ray starts at the camera's position: everything is sharp.
    Pinhole,
    /// Rays start on a disk and meet at the focus plane: depth of field.
    ThinLens {
        /// Lens radius in metres.
        aperture_radius: f32,
        /// Distance to the plane in focus, in metres.
        focus_distance: f32,
    },
}

/// A camera: projection, resolution and sampling quality. Its entity also carries a
/// [`Transform`](crate::components::Transform), its own [`Film`](crate::film::Film) and
/// the [`FrameBuffer`](crate::film::FrameBuffer) of its latest frame.
#[derive(Component, Clone, Copy, Debug, PartialEq)]
#[require(
    crate::components::Transform,
    crate::film::Film,
    crate::film::FrameBuffer,
    super::plan::FramePlan
)]
pub struct Camera {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Vertical field of view in radians.
    pub vertical_fov: f32,
    /// Pinhole or thin lens.
    pub lens: Lens,
    /// Exposure in stops applied before tone mapping.
    pub exposure: f32,
    /// Camera samples per pixel in one frame.
    pub samples_per_pixel: u32,
    /// Light samples per camera hit: shadow rays toward the sky, or toward virtual
    /// lights picked from an environment map (0: the sun only).
    pub light_samples: u32,
    /// Diffuse bounces of indirect light after the first hit (0: direct light only).
    pub bounces: u32,
}

impl Default for Camera {
    fn default() -> Self {
        Self {
            width: 640,
            height: 480,
            vertical_fov: 50f32.to_radians(),
            lens: Lens::Pinhole,
            exposure: 0.0,
            samples_per_pixel: 1,
            light_samples: 2,
            bounces: 0,
        }
    }
}

/// A camera placed in the world, ready to generate rays.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraView {
    origin: Vec3A,
    right: Vec3A,
    up: Vec3A,
    forward: Vec3A,
    tan_half_fov: f32,
    aspect: f32,
    width: u32,
    height: u32,
    lens: Lens,
}

impl CameraView {
    /// The view of `camera` placed by `transform` (object → world; scale is ignored).
    pub fn new(camera: &Camera, transform: &Affine3A) -> Self {
        let forward = transform
            .transform_vector3a(-Vec3A::Z)
            .normalize_or(-Vec3A::Z);
        let up0 = transform.transform_vector3a(Vec3A::Y);
        let right = forward.cross(up0).normalize_or(Vec3A::X);
        let up = right.cross(forward);
        Self {
            origin: transform.translation,
            right,
            up,
            forward,
            tan_half_fov: (camera.vertical_fov.clamp(1e-4, 3.1) * 0.5).tan(),
            aspect: camera.width.max(1) as f32 / camera.height.max(1) as f32,
            width: camera.width.max(1),
            height: camera.height.max(1),
            lens: camera.lens,
        }
    }

    /// Image width.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Image height.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The ray through film position `film` (pixels, (0, 0) the top-left corner) using
    /// `lens_sample` in the unit square for thin lenses.
    #[inline]
    pub fn ray(&self, film: Vec2, lens_sample: Vec2) -> Ray {
        let ndc_x = (2.0 * film.x / self.width as f32 - 1.0) * self.aspect * self.tan_half_fov;
        let ndc_y = (1.0 - 2.0 * film.y / self.height as f32) * self.tan_half_fov;
        let dir = (self.forward + self.right * ndc_x + self.up * ndc_y).normalize();
        match self.lens {
            Lens::Pinhole => Ray::new(self.origin, dir),
            Lens::ThinLens {
                aperture_radius,
                focus_distance,
            } => {
                let focus = self.origin + dir * (focus_distance / dir.dot(self.forward));
                let d = concentric_disk(lens_sample) * aperture_radius;
                let origin = self.origin + self.right * d.x + self.up * d.y;
                Ray::new(origin, (focus - origin).normalize())
            }
        }
    }
}

impl RenderParams {
    /// The sampling settings a camera asks for.
    pub fn for_camera(camera: &Camera, seed: u64) -> Self {
        Self {
            samples_per_pixel: camera.samples_per_pixel.max(1),
            light_samples: camera.light_samples,
            bounces: camera.bounces,
            seed,
            ..Default::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{Quat, Vec3};

    #[test]
    fn centre_ray_looks_down_minus_z_and_corners_are_symmetric() {
        let cam = Camera {
            width: 200,
            height: 100,
            ..Default::default()
        };
        let view = CameraView::new(&cam, &Affine3A::IDENTITY);
        let c = view.ray(Vec2::new(100.0, 50.0), Vec2::ZERO);
        assert!((c.direction - -Vec3A::Z).length() < 1e-6);
        let tl = view.ray(Vec2::new(0.0, 0.0), Vec2::ZERO).direction;
        let br = view.ray(Vec2::new(200.0, 100.0), Vec2::ZERO).direction;
        assert!(tl.x < 0.0 && tl.y > 0.0 && br.x > 0.0 && br.y < 0.0);
        assert!((tl.x + br.x).abs() < 1e-6 && (tl.y + br.y).abs() < 1e-6);
    }

    #[test]
    fn thin_lens_rays_meet_at_focus() {
        let cam = Camera {
            lens: Lens::ThinLens {
                aperture_radius: 0.1,
                focus_distance: 5.0,
            },
            ..Default::default()
        };
        let t = Affine3A::from_rotation_translation(
            Quat::from_rotation_y(0.4),
            Vec3::new(1.0, 2.0, 3.0),
        );
        let view = CameraView::new(&cam, &t);
        let film = Vec2::new(123.0, 321.0);
        let a = view.ray(film, Vec2::new(0.1, 0.9));
        let b = view.ray(film, Vec2::new(0.8, 0.3));
        let fwd = t.transform_vector3a(-Vec3A::Z);
        let pa = a.at((5.0 - (a.origin - t.translation).dot(fwd)) / a.direction.dot(fwd));
        let pb = b.at((5.0 - (b.origin - t.translation).dot(fwd)) / b.direction.dot(fwd));
        assert!((pa - pb).length() < 1e-4);
    }
}
