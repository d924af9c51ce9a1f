//! Rays, axis-aligned boxes and the floating-point error helpers (pbrt-v4 §6.8) that
//! robust ray spawning relies on.

use glam::{Affine3A, Vec3A};

/// A ray `origin + t * direction`, valid for `t` in `[0, t_max)`.
///
/// The direction need not be normalised: instance traversal transforms rays into object
/// space without renormalising, so `t` means the same point in every space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    /// Start point.
    pub origin: Vec3A,
    /// Direction (any non-zero length).
    pub direction: Vec3A,
    /// Exclusive upper bound on the hit distance parameter.
    pub t_max: f32,
}

impl Ray {
    /// A ray that reaches to infinity.
    pub fn new(origin: Vec3A, direction: Vec3A) -> Self {
        Self {
            origin,
            direction,
            t_max: f32::INFINITY,
        }
    }

    /// A ray limited to `t < t_max`.
    pub fn segment(origin: Vec3A, direction: Vec3A, t_max: f32) -> Self {
        Self {
            origin,
            direction,
            t_max,
        }
    }

    /// The point at parameter `t`.
    pub fn at(&self, t: f32) -> Vec3A {
        self.origin + self.direction * t
    }

    /// The same ray expressed in the space of `inverse` (world → object).
    pub fn transformed(&self, inverse: &Affine3A) -> Ray {
        Ray {
            origin: inverse.transform_point3a(self.origin),
            direction: inverse.transform_vector3a(self.direction),
            t_max: self.t_max,
        }
    }
}

/// An axis-aligned bounding box; the empty box has `min = +inf`, `max = -inf`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    /// Lower corner.
    pub min: Vec3A,
    /// Upper corner.
    pub max: Vec3A,
}

impl Default for Aabb {
    fn default() -> Self {
        Self::EMPTY
    }
}

impl Aabb {
    /// The box containing nothing; the identity of [`Aabb::union`].
    pub const EMPTY: Aabb = Aabb {
        min: Vec3A::splat(f32::INFINITY),
        max: Vec3A::splat(f32::NEG_INFINITY),
    };

    /// The box spanned by two corners.
    pub fn new(min: Vec3A, max: Vec3A) -> Self {
        Self { min, max }
    }

    /// The tightest box around a point set.
    pub fn from_points(points: impl IntoIterator<Item = Vec3A>) -> Self {
        points.into_iter().fold(Self::EMPTY, |b, p| b.grow(p))
    }

    /// True when the box contains no point.
    pub fn is_empty(&self) -> bool {
        self.min.cmpgt(self.max).any()
    }

    /// This box grown to contain `p`.
    pub fn grow(self, p: Vec3A) -> Self {
        Self {
            min: self.min.min(p),
            max: self.max.max(p),
        }
    }

    /// The smallest box containing both.
    pub fn union(self, other: Aabb) -> Self {
        Self {
            min: self.min.min(other.min),
            max: self.max.max(other.max),
        }
    }

    /// True when `other` lies entirely inside this box (boundaries included).
    pub fn contains(&self, other: &Aabb) -> bool {
        other.is_empty() || (self.min.cmple(other.min).all() && self.max.cmpge(other.max).all())
    }

    /// Edge lengths (zero for the empty box).
    pub fn extent(&self) -> Vec3A {
        if self.is_empty() {
            Vec3A::ZERO
        } else {
            self.max - self.min
        }
    }

    /// Midpoint.
    pub fn center(&self) -> Vec3A {
        (self.min + self.max) * 0.5
    }

    /// Surface area, the SAH's measure of hit probability (zero when empty).
    pub fn surface_area(&self) -> f32 {
        let e = self.extent();
        2.0 * (e.x * e.y + e.y * e.z + e.z * e.x)
    }

    /// Index of the longest axis.
    pub fn largest_axis(&self) -> usize {
        let e = self.extent();
        if e.x >= e.y && e.x >= e.z {
            0
        } else if e.y >= e.z {
            1
        } else {
            2
        }
    }

    /// The box around this box's eight corners after an affine transform.
    pub fn transformed(&self, m: &Affine3A) -> Aabb {
        if self.is_empty() {
            return Aabb::EMPTY;
        }
        // Arvo's method: per axis, the extreme of each matrix column times the box.
        let mut min = m.translation;
        let mut max = m.translation;
        for (i, col) in [m.matrix3.x_axis, m.matrix3.y_axis, m.matrix3.z_axis]
            .into_iter()
            .enumerate()
        {
            let a = col * self.min[i];
            let b = col * self.max[i];
            min += a.min(b);
            max += a.max(b);
        }
        Aabb { min, max }
    }
}

/// The bound `n·ε / (1 − n·ε)` on the relative error of `n` chained floating-point
/// operations (pbrt-v4 eq. 6.40).
#[inline]
pub const fn gamma(n: i32) -> f32 {
    let e = f32::EPSILON * 0.5;
    (n as f32 * e) / (1.0 - n as f32 * e)
}

/// The next representable float above `v` (infinity and NaN stay as they are).
#[inline]
pub fn next_float_up(v: f32) -> f32 {
    if v.is_infinite() && v > 0.0 || v.is_nan() {
        return v;
    }
    let v = if v == -0.0 { 0.0 } else { v };
    let bits = v.to_bits();
    f32::from_bits(if v >= 0.0 { bits + 1 } else { bits - 1 })
}

/// The next representable float below `v`.
#[inline]
pub fn next_float_down(v: f32) -> f32 {
    if v.is_infinite() && v < 0.0 || v.is_nan() {
        return v;
    }
    let v = if v == 0.0 { -0.0 } else { v };
    let bits = v.to_bits();
    f32::from_bits(if v > 0.0 { bits - 1 } else { bits + 1 })
}

/// A point together with a conservative bound on the absolute error of each coordinate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ErrorPoint {
    /// The computed point.
    pub point: Vec3A,
    /// Per-axis absolute error bound of `point`.
    pub error: Vec3A,
}

impl ErrorPoint {
    /// Applies an affine transform and propagates the error bound (pbrt-v4 eq. 6.47–6.48).
    pub fn transformed(&self, m: &Affine3A) -> ErrorPoint {
        let point = m.transform_point3a(self.point);
        let abs = glam::Mat3A::from_cols(
            m.matrix3.x_axis.abs(),
            m.matrix3.y_axis.abs(),
            m.matrix3.z_axis.abs(),
        );
        let g3 = gamma(3);
        let error =
            (g3 + 1.0) * (abs * self.error) + g3 * (abs * self.point.abs() + m.translation.abs());
        ErrorPoint { point, error }
    }

    /// An origin for a ray leaving this surface point in direction `w`: pushed along the
    /// geometric normal `n` just past the error bound, to the side `w` points to, then
    /// rounded away from the surface, so the new ray cannot re-hit the surface it left in
    /// world space. (Moved into an instance's object space it is rounded again and may
    /// land behind its triangle: traversal skips the triangle a ray leaves.)
    pub fn offset_origin(&self, n: Vec3A, w: Vec3A) -> Vec3A {
        let d = n.abs().dot(self.error);
        let mut offset = n * d;
        if w.dot(n) < 0.0 {
            offset = -offset;
        }
        let mut po = self.point + offset;
        for i in 0..3 {
            if offset[i] > 0.0 {
                po[i] = next_float_up(po[i]);
            } else if offset[i] < 0.0 {
                po[i] = next_float_down(po[i]);
            }
        }
        po
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn next_float_steps_one_ulp() {
        assert!(next_float_up(1.0) > 1.0 && next_float_up(1.0) - 1.0 == f32::EPSILON);
        assert!(next_float_down(1.0) < 1.0);
        assert!(next_float_up(0.0) > 0.0 && next_float_up(-0.0) > 0.0);
        assert!(next_float_down(0.0) < 0.0);
        assert_eq!(next_float_up(f32::INFINITY), f32::INFINITY);
    }

    #[test]
    fn transformed_box_contains_transformed_corners() {
        let b = Aabb::new(Vec3A::new(-1.0, 0.5, 2.0), Vec3A::new(3.0, 1.0, 4.0));
        let m = Affine3A::from_scale_rotation_translation(
            Vec3::new(2.0, -0.5, 3.0),
            glam::Quat::from_euler(glam::EulerRot::XYZ, 0.3, 1.1, -0.7),
            Vec3::new(5.0, -2.0, 1.0),
        );
        let t = b.transformed(&m);
        for i in 0..8 {
            let c = Vec3A::new(
                if i & 1 == 0 { b.min.x } else { b.max.x },
                if i & 2 == 0 { b.min.y } else { b.max.y },
                if i & 4 == 0 { b.min.z } else { b.max.z },
            );
            let p = m.transform_point3a(c);
            assert!(t.grow(p) == t || (t.grow(p).extent() - t.extent()).abs().max_element() < 1e-4);
        }
    }

    #[test]
    fn empty_box_behaves() {
        assert!(Aabb::EMPTY.is_empty());
        assert_eq!(Aabb::EMPTY.surface_area(), 0.0);
        let p = Aabb::EMPTY.grow(Vec3A::ONE);
        assert!(!p.is_empty() && p.surface_area() == 0.0);
    }
}
