//! A camera flight as key frames in time: position, orientation and field of view,
//! interpolated linearly or along a Catmull–Rom spline, as a camera component that the
//! animation stage follows.

use bevy_ecs::component::Component;
use glam::{Quat, Vec3};

/// One key frame: where the camera is at `time`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraKey {
    /// Seconds from the start of the animation.
    pub time: f64,
    /// Eye position in world space.
    pub position: Vec3,
    /// Orientation (the camera looks along its local −Z).
    pub rotation: Quat,
    /// Vertical field of view in radians.
    pub vertical_fov: f32,
}

/// How positions and fields of view move between key frames. Orientations are always
/// slerped between the two keys around the time (the shortest way).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PathInterpolation {
    /// Straight from key to key at constant speed.
    Linear,
    /// A Catmull–Rom spline through the keys, parameterised by their times (Barry and
    /// Goldman's pyramid), so the speed changes smoothly at every key; the end keys are
    /// continued by reflection.
    #[default]
    CatmullRom,
}

/// Why a path was refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum CameraPathError {
    /// No keys.
    #[error("a camera path needs at least one key frame")]
    Empty,
    /// Key `index`'s time is not after the one before it, or not finite.
    #[error("key frame {index}: time {time} does not come after the key before it")]
    TimeOrder {
        /// The key.
        index: usize,
        /// Its time.
        time: f64,
    },
    /// Key `index` has a non-finite position, a rotation that is not a unit quaternion
    /// or a field of view outside (0°, 180°).
    #[error("key frame {index}: {reason}")]
    BadKey {
        /// The key.
        index: usize,
        /// What is wrong.
        reason: &'static str,
    },
}

/// A camera's flight: the key frames, checked, and how to interpolate them. Before the
/// first key the camera stands at it, after the last one at the last.
#[derive(Component, Clone, Debug, PartialEq)]
pub struct CameraPath {
    keys: Vec<CameraKey>,
    interpolation: PathInterpolation,
}

impl CameraPath {
    /// A path through `keys`, whose times must increase.
    pub fn new(
        keys: Vec<CameraKey>,
        interpolation: PathInterpolation,
    ) -> Result<Self, CameraPathError> {
        if keys.is_empty() {
            return Err(CameraPathError::Empty);
        }
        for (index, key) in keys.iter().enumerate() {
            let bad = |reason| Err(CameraPathError::BadKey { index, reason });
            if !key.position.is_finite() {
                return bad("the position is not finite");
            }
            if !key.rotation.is_finite() || (key.rotation.length() - 1.0).abs() > 1e-3 {
                return bad("the rotation is not a unit quaternion");
            }
            if !(key.vertical_fov > 0.0 && key.vertical_fov < std::f32::consts::PI) {
                return bad("the field of view is not between 0° and 180°");
            }
            let after_previous = index == 0 || key.time > keys[index - 1].time;
            if !key.time.is_finite() || !after_previous {
                return Err(CameraPathError::TimeOrder {
                    index,
                    time: key.time,
                });
            }
        }
        let keys = keys
            .into_iter()
            .map(|k| CameraKey {
                rotation: k.rotation.normalize(),
                ..k
            })
            .collect();
        Ok(Self {
            keys,
            interpolation,
        })
    }

    /// The key frames.
    pub fn keys(&self) -> &[CameraKey] {
        &self.keys
    }

    /// How the path interpolates.
    pub fn interpolation(&self) -> PathInterpolation {
        self.interpolation
    }

    /// Seconds from the first key to the last.
    pub fn duration(&self) -> f64 {
        self.keys[self.keys.len() - 1].time - self.keys[0].time
    }

    /// Position, orientation and vertical field of view at `time`.
    pub fn at(&self, time: f64) -> (Vec3, Quat, f32) {
        let keys = &self.keys;
        let last = keys.len() - 1;
        if keys.len() == 1 || time.is_nan() || time <= keys[0].time {
            let k = keys[0];
            return (k.position, k.rotation, k.vertical_fov);
        }
        if time >= keys[last].time {
            let k = keys[last];
            return (k.position, k.rotation, k.vertical_fov);
        }
        // The segment [i, i + 1] holding `time`.
        let i = keys.partition_point(|k| k.time <= time) - 1;
        let (a, b) = (keys[i], keys[i + 1]);
        let s = ((time - a.time) / (b.time - a.time)) as f32;
        let rotation = a.rotation.slerp(b.rotation, s);
        match self.interpolation {
            PathInterpolation::Linear => (
                a.position.lerp(b.position, s),
                rotation,
                a.vertical_fov + (b.vertical_fov - a.vertical_fov) * s,
            ),
            PathInterpolation::CatmullRom => {
                let before = self.extended(i as isize - 1);
                let after = self.extended(i as isize + 2);
                let knots = [before.0, a.time, b.time, after.0];
                let position = catmull_rom(
                    knots,
                    [
                        before.1.as_dvec3(),
                        a.position.as_dvec3(),
                        b.position.as_dvec3(),
                        after.1.as_dvec3(),
                    ],
                    time,
                );
                let fov = catmull_rom(
                    knots,
                    [
                        glam::DVec3::splat(f64::from(before.2)),
                        glam::DVec3::splat(f64::from(a.vertical_fov)),
                        glam::DVec3::splat(f64::from(b.vertical_fov)),
                        glam::DVec3::splat(f64::from(after.2)),
                    ],
                    time,
                );
                let fov = (fov.x as f32).clamp(1e-3, std::f32::consts::PI - 1e-3);
                (position.as_vec3(), rotation, fov)
            }
        }
    }

    /// Key `index`'s time, position and field of view, with the path continued past its
    /// ends by reflecting the neighbouring key through the end key.
    fn extended(&self, index: isize) -> (f64, Vec3, f32) {
        let keys = &self.keys;
        let last = keys.len() as isize - 1;
        let key = |i: isize| keys[i as usize];
        let reflect = |end: CameraKey, inner: CameraKey| {
            (
                2.0 * end.time - inner.time,
                2.0 * end.position - inner.position,
                2.0 * end.vertical_fov - inner.vertical_fov,
            )
        };
        if index < 0 {
            reflect(key(0), key(1))
        } else if index > last {
            reflect(key(last), key(last - 1))
        } else {
            let k = key(index);
            (k.time, k.position, k.vertical_fov)
        }
    }
}

/// The Catmull–Rom curve through `p[1]` at `t[1]` and `p[2]` at `t[2]` with neighbours
/// `p[0]`, `p[3]`, evaluated at `time` by Barry and Goldman's pyramid of linear
/// interpolations (exact for points moving at constant velocity).
fn catmull_rom(t: [f64; 4], p: [glam::DVec3; 4], time: f64) -> glam::DVec3 {
    let lerp = |pa: glam::DVec3, pb: glam::DVec3, ta: f64, tb: f64| {
        pa * ((tb - time) / (tb - ta)) + pb * ((time - ta) / (tb - ta))
    };
    let a1 = lerp(p[0], p[1], t[0], t[1]);
    let a2 = lerp(p[1], p[2], t[1], t[2]);
    let a3 = lerp(p[2], p[3], t[2], t[3]);
    let b1 = lerp(a1, a2, t[0], t[2]);
    let b2 = lerp(a2, a3, t[1], t[3]);
    lerp(b1, b2, t[1], t[2])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key(time: f64, position: Vec3, yaw: f32) -> CameraKey {
        CameraKey {
            time,
            position,
            rotation: Quat::from_rotation_y(yaw),
            vertical_fov: 0.9,
        }
    }

    #[test]
    fn the_path_passes_through_its_keys_and_holds_still_outside_them() {
        let keys = vec![
            key(0.0, Vec3::ZERO, 0.0),
            key(1.0, Vec3::new(4.0, 1.0, 0.0), 0.5),
            key(3.0, Vec3::new(4.0, 1.0, -6.0), 1.0),
        ];
        for interpolation in [PathInterpolation::Linear, PathInterpolation::CatmullRom] {
            let path = CameraPath::new(keys.clone(), interpolation).unwrap();
            for k in &keys {
                let (p, r, f) = path.at(k.time);
                assert!((p - k.position).length() < 1e-5, "{interpolation:?} {p}");
                assert!(r.angle_between(k.rotation) < 1e-4);
                assert!((f - k.vertical_fov).abs() < 1e-6);
            }
            assert_eq!(path.at(-2.0).0, keys[0].position);
            assert_eq!(path.at(9.0).0, keys[2].position);
            assert_eq!(path.duration(), 3.0);
        }
    }

    #[test]
    fn linear_goes_straight_and_catmull_rom_keeps_constant_velocity_exact() {
        // Keys on a line at uneven times but constant velocity: both interpolations give
        // the uniform motion.
        let velocity = Vec3::new(2.0, 0.5, -1.0);
        let times = [0.0, 0.4, 1.5, 2.0, 3.7];
        let keys: Vec<_> = times
            .iter()
            .map(|&t| key(t, velocity * t as f32, 0.0))
            .collect();
        for interpolation in [PathInterpolation::Linear, PathInterpolation::CatmullRom] {
            let path = CameraPath::new(keys.clone(), interpolation).unwrap();
            for i in 0..=37 {
                let t = f64::from(i) * 0.1;
                let expected = velocity * t as f32;
                assert!(
                    (path.at(t).0 - expected).length() < 1e-4,
                    "{interpolation:?} at {t}"
                );
            }
        }
    }

    #[test]
    fn catmull_rom_has_no_kink_at_a_key_where_linear_has_one() {
        let keys = vec![
            key(0.0, Vec3::ZERO, 0.0),
            key(1.0, Vec3::new(4.0, 0.0, 0.0), 0.0),
            key(2.0, Vec3::new(4.0, 0.0, 4.0), 0.0),
        ];
        let velocity_change = |path: &CameraPath| {
            let h = 1e-3;
            let before = (path.at(1.0).0 - path.at(1.0 - h).0) / h as f32;
            let after = (path.at(1.0 + h).0 - path.at(1.0).0) / h as f32;
            (after - before).length()
        };
        let smooth = CameraPath::new(keys.clone(), PathInterpolation::CatmullRom).unwrap();
        let straight = CameraPath::new(keys, PathInterpolation::Linear).unwrap();
        assert!(
            velocity_change(&smooth) < 0.05,
            "{}",
            velocity_change(&smooth)
        );
        assert!(velocity_change(&straight) > 5.0);
    }

    #[test]
    fn bad_paths_are_refused_with_the_key() {
        let good = key(0.0, Vec3::ZERO, 0.0);
        let path = |keys| CameraPath::new(keys, PathInterpolation::Linear);
        assert_eq!(path(vec![]), Err(CameraPathError::Empty));
        assert_eq!(
            path(vec![good, good]),
            Err(CameraPathError::TimeOrder {
                index: 1,
                time: 0.0
            })
        );
        let nan = CameraKey {
            time: 1.0,
            position: Vec3::NAN,
            ..good
        };
        assert!(matches!(
            path(vec![good, nan]),
            Err(CameraPathError::BadKey { index: 1, .. })
        ));
        let wide = CameraKey {
            vertical_fov: 3.2,
            ..good
        };
        assert!(matches!(
            path(vec![wide]),
            Err(CameraPathError::BadKey { index: 0, .. })
        ));
    }
}
