//! Stack-based, near-child-first traversal with two entry points: closest hit and any
//! hit. The caller's closure tests one primitive slot, so alpha masks and instance
//! transforms live outside the BVH.

use super::{Bvh, BvhNode, MAX_DEPTH};
use crate::math::{Ray, gamma};
use glam::Vec3A;

/// Counters a traversal updates: cheap enough to leave on in release builds. Summed per
/// tile, then per frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TraversalStats {
    /// Closest-hit rays traced.
    pub closest_rays: u64,
    /// Any-hit (occlusion) rays traced.
    pub any_rays: u64,
    /// BVH nodes visited, both levels.
    pub nodes_visited: u64,
    /// Primitive tests: instances at the top level, triangles at the bottom.
    pub primitive_tests: u64,
    /// Candidate hits handed to a hit filter (alpha tests).
    pub filter_tests: u64,
    /// Candidate hits a filter rejected: transparency segments passed through.
    pub filter_rejections: u64,
}

impl TraversalStats {
    /// Adds another set of counters into this one.
    pub fn add(&mut self, other: &TraversalStats) {
        self.closest_rays += other.closest_rays;
        self.any_rays += other.any_rays;
        self.nodes_visited += other.nodes_visited;
        self.primitive_tests += other.primitive_tests;
        self.filter_tests += other.filter_tests;
        self.filter_rejections += other.filter_rejections;
    }

    /// All rays traced.
    pub fn rays(&self) -> u64 {
        self.closest_rays + self.any_rays
    }
}

/// A ray prepared for slab tests against node boxes.
#[derive(Clone, Copy, Debug)]
pub struct NodeRay {
    origin: Vec3A,
    inv_dir: Vec3A,
}

/// Widening of the far slab distance that makes the box test conservative (Ize 2013,
/// "Robust BVH Ray Traversal"), so watertight triangle tests are never culled early.
const FAR_SCALE: f32 = 1.0 + 2.0 * gamma(3);

impl NodeRay {
    /// Precomputes the reciprocal direction.
    #[inline]
    pub fn new(ray: &Ray) -> Self {
        Self {
            origin: ray.origin,
            inv_dir: ray.direction.recip(),
        }
    }

    /// Entry distance into `node`'s box if the ray meets it before `t_max`, else infinity.
    #[inline]
    pub fn hit_node(&self, node: &BvhNode, t_max: f32) -> f32 {
        let t0 = (Vec3A::from_array(node.min) - self.origin) * self.inv_dir;
        let t1 = (Vec3A::from_array(node.max) - self.origin) * self.inv_dir;
        let t_near = t0.min(t1).max_element().max(0.0);
        let t_far = t0.max(t1).min_element() * FAR_SCALE;
        if t_near <= t_far && t_near < t_max {
            t_near
        } else {
            f32::INFINITY
        }
    }
}

impl Bvh {
    /// Finds the closest hit. `test(slot, t_max)` tests the primitive in leaf slot `slot`
    /// and returns its hit distance when it is hit closer than `t_max` (and accepted).
    /// Returns the final `t_max`: `ray.t_max` when nothing was hit.
    #[inline]
    pub fn traverse_closest(
        &self,
        ray: &Ray,
        stats: &mut TraversalStats,
        mut test: impl FnMut(usize, f32) -> Option<f32>,
    ) -> f32 {
        let mut t_max = ray.t_max;
        self.traverse(ray, stats, |slot, t| {
            if let Some(hit_t) = test(slot, t) {
                t_max = hit_t;
            }
            (t_max, false)
        });
        t_max
    }

    /// True when any primitive accepts a hit closer than `ray.t_max`; stops at the first.
    #[inline]
    pub fn traverse_any(
        &self,
        ray: &Ray,
        stats: &mut TraversalStats,
        mut test: impl FnMut(usize, f32) -> bool,
    ) -> bool {
        let mut found = false;
        self.traverse(ray, stats, |slot, t| {
            found = test(slot, t);
            (t, found)
        });
        found
    }

    /// The shared loop: `visit(slot, t_max) -> (new t_max, stop)`.
    #[inline(always)]
    fn traverse(
        &self,
        ray: &Ray,
        stats: &mut TraversalStats,
        mut visit: impl FnMut(usize, f32) -> (f32, bool),
    ) {
        let Some(root) = self.nodes.first() else {
            return;
        };
        let node_ray = NodeRay::new(ray);
        let mut t_max = ray.t_max;
        if node_ray.hit_node(root, t_max) == f32::INFINITY {
            stats.nodes_visited += 1;
            return;
        }
        let mut stack = [(0u32, 0.0f32); MAX_DEPTH];
        let mut sp = 0usize;
        let mut current = 0usize;
        loop {
            let node = &self.nodes[current];
            stats.nodes_visited += 1;
            if node.is_leaf() {
                let first = node.first as usize;
                for slot in first..first + node.count as usize {
                    stats.primitive_tests += 1;
                    let (t, stop) = visit(slot, t_max);
                    t_max = t;
                    if stop {
                        return;
                    }
                }
            } else {
                let left = node.first as usize;
                let t_left = node_ray.hit_node(&self.nodes[left], t_max);
                let t_right = node_ray.hit_node(&self.nodes[left + 1], t_max);
                let (near, t_near, far, t_far) = if t_left <= t_right {
                    (left, t_left, left + 1, t_right)
                } else {
                    (left + 1, t_right, left, t_left)
                };
                if t_near < f32::INFINITY {
                    if t_far < f32::INFINITY {
                        stack[sp] = (far as u32, t_far);
                        sp += 1;
                    }
                    current = near;
                    continue;
                }
            }
            // Pop the next node still closer than the closest hit so far.
            loop {
                if sp == 0 {
                    return;
                }
                sp -= 1;
                let (index, t_entry) = stack[sp];
                if t_entry < t_max {
                    current = index as usize;
                    break;
                }
            }
        }
    }
}
