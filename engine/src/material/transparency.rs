//! Adaptive transparency (Dietrich et al. §4.4): how many alpha holes — transparency
//! segments — a ray may pass before the next hole counts as opaque, as a function of the
//! distance from the camera; and the small fixed-capacity list of the nearest holes a
//! closest-hit query collects to apply it exactly in distance order.

use crate::accel::tlas::Candidate;
use arrayvec::ArrayVec;
use bevy_ecs::component::Component;

/// The largest transparency allowance a curve may set (the hole list holds one more).
pub const MAX_TRANSPARENCY_DEPTH: u32 = 32;

/// Relative distance within which two holes are one transparency segment.
const SAME_SEGMENT: f32 = 1.0 / (1 << 20) as f32;

/// Holes counted per camera ray for the `holes_passed` statistic (it saturates here).
pub const COUNTED_HOLES: usize = 64;

/// A camera's adaptive-transparency curve: up to `near` metres a ray may pass
/// `depth_near` holes, beyond `far` only `depth_far`, linearly (rounded) in between. A
/// hole beyond the allowance is an opaque hit shaded with its shader's mean opaque colour
/// × `weight`. Shadow rays use the allowance at their shading point's camera distance.
#[derive(Component, Clone, Copy, Debug, PartialEq)]
pub struct TransparencyCurve {
    /// Distance (m) up to which `depth_near` applies.
    pub near: f32,
    /// Distance (m) from which `depth_far` applies.
    pub far: f32,
    /// Holes a ray may pass near the camera.
    pub depth_near: u32,
    /// Holes a ray may pass far from the camera.
    pub depth_far: u32,
    /// Darkening of the mean opaque colour where a hole is made opaque (paper: 0.75).
    pub weight: f32,
}

impl Default for TransparencyCurve {
    fn default() -> Self {
        // Measured on `forest` (issue 4 note): 23 % faster still frames at relMSE 1.6e-3.
        Self {
            near: 5.0,
            far: 40.0,
            depth_near: 4,
            depth_far: 1,
            weight: 0.75,
        }
    }
}

impl TransparencyCurve {
    /// Checks the curve: finite `0 ≤ near < far`, depths ≤ [`MAX_TRANSPARENCY_DEPTH`],
    /// weight in [0, 1].
    pub fn validate(&self) -> Result<(), String> {
        if !(self.near.is_finite() && self.far.is_finite() && 0.0 <= self.near) {
            return Err(format!(
                "distances must be finite and non-negative (near {}, far {})",
                self.near, self.far
            ));
        }
        if self.near >= self.far {
            return Err(format!(
                "near ({}) must be less than far ({})",
                self.near, self.far
            ));
        }
        if self.depth_near.max(self.depth_far) > MAX_TRANSPARENCY_DEPTH {
            return Err(format!(
                "depths must be at most {MAX_TRANSPARENCY_DEPTH} (got {} and {})",
                self.depth_near, self.depth_far
            ));
        }
        if !(0.0..=1.0).contains(&self.weight) {
            return Err(format!("weight must be in [0, 1] (got {})", self.weight));
        }
        Ok(())
    }

    /// Holes a ray may pass before a hole at `distance` becomes opaque.
    #[inline]
    pub fn allowance(&self, distance: f32) -> u32 {
        // NaN distances get the near allowance: the exact behaviour is the safe one.
        if distance.is_nan() || distance <= self.near {
            return self.depth_near;
        }
        if distance >= self.far {
            return self.depth_far;
        }
        let f = (distance - self.near) / (self.far - self.near);
        let (a, b) = (self.depth_near as f32, self.depth_far as f32);
        (a + (b - a) * f).round() as u32
    }

    /// The largest allowance anywhere on the curve.
    #[inline]
    pub fn max_allowance(&self) -> u32 {
        self.depth_near
            .max(self.depth_far)
            .min(MAX_TRANSPARENCY_DEPTH)
    }
}

/// The nearest holes met by one ray, at most `N` (fewer if a smaller capacity is asked
/// for), each keyed by its ray parameter. Farther holes are dropped once it is full. A
/// hole at the same distance as a kept one (within 2⁻²⁰ relative) is the same segment —
/// the shared edge of two triangles, or coplanar copies — and is not kept twice.
#[derive(Clone, Debug)]
pub struct NearestHoles<T: Copy + Default, const N: usize> {
    capacity: usize,
    // Left uninitialised past its length: a shadow ray's list was a 256-byte fill.
    items: ArrayVec<(f32, T), N>,
}

impl<T: Copy + Default, const N: usize> NearestHoles<T, N> {
    /// An empty list keeping at most `capacity` (≤ `N`) holes.
    #[inline]
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity: capacity.min(N),
            items: ArrayVec::new(),
        }
    }

    /// Empties the list for another ray, now keeping at most `capacity` (≤ `N`) holes.
    #[inline]
    pub fn reset(&mut self, capacity: usize) {
        self.items.clear();
        self.capacity = capacity.min(N);
    }

    /// Offers a hole at ray parameter `t`; kept when the list has room or `t` is nearer
    /// than its farthest hole (which it replaces).
    #[inline]
    pub fn insert(&mut self, t: f32, item: T) {
        let tolerance = t.abs() * SAME_SEGMENT;
        if self.items.iter().any(|(ti, _)| (ti - t).abs() <= tolerance) {
            return;
        }
        if self.items.len() < self.capacity {
            self.items.push((t, item));
            return;
        }
        let Some((farthest, &(t_far, _))) = self
            .items
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.0.total_cmp(&b.1.0))
        else {
            return;
        };
        if t < t_far {
            self.items[farthest] = (t, item);
        }
    }

    /// Kept holes strictly nearer than `t`.
    #[inline]
    pub fn count_before(&self, t: f32) -> usize {
        self.items.iter().filter(|(ti, _)| *ti < t).count()
    }

    /// Kept holes strictly nearer than `t`, nearest first (ties keep insertion order).
    #[inline]
    pub fn sorted_before(&mut self, t: f32) -> &[(f32, T)] {
        let kept = self.items.as_mut_slice();
        kept.sort_by(|a, b| a.0.total_cmp(&b.0));
        let n = kept.partition_point(|(ti, _)| *ti < t);
        &kept[..n]
    }

    /// Number of holes kept.
    #[inline]
    pub fn len(&self) -> usize {
        self.items.len()
    }

    /// True when no hole was kept.
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }
}

/// The holes a closest-hit query with adaptive transparency keeps.
pub type CandidateHoles = NearestHoles<Candidate, { MAX_TRANSPARENCY_DEPTH as usize + 1 }>;

/// The holes a query keeps only to count them (closest-hit without adaptive
/// transparency, and any-hit with it).
pub type CountedHoles = NearestHoles<(), COUNTED_HOLES>;

/// The first hole (nearest first) that the curve turns opaque: the `i`-th hole at
/// distance `t_i` with `i ≥ allowance(t_i)`. `holes` must hold every hole nearer than
/// the ray's other hit, up to `max_allowance() + 1` of them.
pub fn first_opaque_hole<'a, T>(
    curve: &TransparencyCurve,
    holes: &'a [(f32, T)],
) -> Option<&'a (f32, T)> {
    holes
        .iter()
        .enumerate()
        .find(|(i, (t, _))| *i as u32 >= curve.allowance(*t))
        .map(|(_, hole)| hole)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn allowance_follows_the_curve_and_clamps_outside() {
        let curve = TransparencyCurve {
            near: 10.0,
            far: 20.0,
            depth_near: 8,
            depth_far: 2,
            weight: 0.75,
        };
        assert_eq!(curve.allowance(0.0), 8);
        assert_eq!(curve.allowance(10.0), 8);
        assert_eq!(curve.allowance(15.0), 5);
        assert_eq!(curve.allowance(20.0), 2);
        assert_eq!(curve.allowance(1e30), 2);
        assert_eq!(curve.allowance(f32::NAN), 8);
        assert_eq!(curve.max_allowance(), 8);
        assert!(curve.validate().is_ok());
        for bad in [
            TransparencyCurve {
                near: 5.0,
                far: 5.0,
                ..curve
            },
            TransparencyCurve {
                near: -1.0,
                ..curve
            },
            TransparencyCurve {
                far: f32::INFINITY,
                ..curve
            },
            TransparencyCurve {
                depth_near: 33,
                ..curve
            },
            TransparencyCurve {
                weight: 1.5,
                ..curve
            },
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
    }

    #[test]
    fn the_list_keeps_the_nearest_holes_whatever_the_order() {
        let mut rng = crate::util::sampling::SplitMix64(3);
        for _ in 0..100 {
            let ts: Vec<f32> = (0..40).map(|_| rng.range(0.0, 100.0)).collect();
            let mut holes = NearestHoles::<u32, 16>::new(9);
            for (i, &t) in ts.iter().enumerate() {
                holes.insert(t, i as u32);
            }
            let mut sorted = ts.clone();
            sorted.sort_by(f32::total_cmp);
            let kept: Vec<f32> = holes
                .sorted_before(f32::INFINITY)
                .iter()
                .map(|h| h.0)
                .collect();
            assert_eq!(kept, sorted[..9]);
            assert_eq!(holes.count_before(sorted[4]), 4);
        }
    }

    #[test]
    fn a_hole_met_twice_at_one_distance_is_one_segment() {
        let mut holes = NearestHoles::<(), 8>::new(8);
        for t in [2.0, 1.0, 2.0, 1.0 + 1e-7, 3.0, 2.0001] {
            holes.insert(t, ());
        }
        assert_eq!(holes.len(), 4);
    }

    #[test]
    fn the_first_hole_beyond_the_allowance_is_chosen() {
        let curve = TransparencyCurve {
            near: 10.0,
            far: 20.0,
            depth_near: 3,
            depth_far: 1,
            weight: 0.75,
        };
        // Near holes: the fourth (index 3) is the first beyond the allowance of 3.
        let near = [(1.0, 'a'), (2.0, 'b'), (3.0, 'c'), (4.0, 'd'), (5.0, 'e')];
        assert_eq!(first_opaque_hole(&curve, &near), Some(&(4.0, 'd')));
        assert_eq!(first_opaque_hole(&curve, &near[..3]), None);
        // Far holes: the second (index 1) already exceeds the allowance of 1.
        let far = [(30.0, 'a'), (31.0, 'b'), (32.0, 'c')];
        assert_eq!(first_opaque_hole(&curve, &far), Some(&(31.0, 'b')));
    }
}
