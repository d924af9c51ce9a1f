//! Stack-based, near-child-first traversal with two entry points: closest hit and any
//! hit. The caller's closure tests one primitive slot, so alpha masks and instance
//! transforms live outside the BVH.

use super::{Bvh, WideNode};
use crate::math::{Ray, gamma};
use glam::{BVec4A, Vec3A, Vec4};

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
    /// The part of `filter_rejections` met by closest-hit (camera) rays.
    pub closest_filter_rejections: u64,
    /// Alpha holes in front of the hit that closest-hit (camera) rays returned: the
    /// transparency segments they passed (at most 64 counted per ray).
    pub holes_passed: u64,
    /// Holes adaptive transparency turned opaque (camera and shadow rays).
    pub opaque_holes: u64,
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
        self.closest_filter_rejections += other.closest_filter_rejections;
        self.holes_passed += other.holes_passed;
        self.opaque_holes += other.opaque_holes;
    }

    /// Mean alpha tests that found a hole per closest-hit ray: the transparency work,
    /// including holes behind the final hit that were tested before it was found.
    pub fn hole_tests_per_closest_ray(&self) -> f64 {
        self.closest_filter_rejections as f64 / self.closest_rays.max(1) as f64
    }

    /// Mean transparency segments per closest-hit ray: holes in front of the hit.
    pub fn segments_per_closest_ray(&self) -> f64 {
        self.holes_passed as f64 / self.closest_rays.max(1) as f64
    }

    /// All rays traced.
    pub fn rays(&self) -> u64 {
        self.closest_rays + self.any_rays
    }
}

/// A ray prepared for slab tests against the four boxes of a [`WideNode`].
#[derive(Clone, Copy, Debug)]
pub struct NodeRay {
    origin: [Vec4; 3],
    inv_dir: [Vec4; 3],
    /// Some direction component is ±0 (its reciprocal is infinite) or so small that its
    /// reciprocal overflows (then NaN): such slabs get the open treatment.
    axis_parallel: bool,
}

/// Widening of the far slab distance that makes the box test conservative (Ize 2013,
/// "Robust BVH Ray Traversal"), so watertight triangle tests are never culled early.
const FAR_SCALE: f32 = 1.0 + 2.0 * gamma(3);

/// The matching narrowing of the entry distance: rounded up, it could exceed the distance
/// of a hit on the box's face and prune that box against a farther hit found first (a
/// closest hit 1 ulp too far; fuzz finding).
const NEAR_SCALE: f32 = 1.0 - 2.0 * gamma(3);

impl NodeRay {
    /// Splats origin and reciprocal direction across the four lanes.
    #[inline]
    pub fn new(ray: &Ray) -> Self {
        // A non-zero component below 1/f32::MAX (a denormal) has an infinite reciprocal,
        // which would put its slab entry at ±∞ although the ray does cross the slab, at a
        // distance f32 cannot hold (fuzz finding). NaN marks that slab as open: the test
        // ignores the axis, a conservative superset that only such rays pay for.
        let d = ray.direction;
        let unreliable = d.cmpne(Vec3A::ZERO) & !d.recip().is_finite_mask();
        let inv = Vec3A::select(unreliable, Vec3A::NAN, d.recip());
        Self {
            origin: [
                Vec4::splat(ray.origin.x),
                Vec4::splat(ray.origin.y),
                Vec4::splat(ray.origin.z),
            ],
            inv_dir: [Vec4::splat(inv.x), Vec4::splat(inv.y), Vec4::splat(inv.z)],
            // A NaN ray hits nothing either way; only finite rays get open slabs.
            axis_parallel: !inv.is_finite()
                && ray.origin.is_finite()
                && !ray.direction.is_nan()
                && ray.direction != Vec3A::ZERO,
        }
    }

    /// Entry distances of the four children and a bitmask of the lanes hit before
    /// `t_max` (bit `i` for lane `i`).
    #[inline]
    pub fn hit_children(&self, node: &WideNode, t_max: f32) -> (Vec4, u32) {
        let [ox, oy, oz] = self.origin;
        let [ix, iy, iz] = self.inv_dir;
        let x0 = (node.min_x - ox) * ix;
        let x1 = (node.max_x - ox) * ix;
        let y0 = (node.min_y - oy) * iy;
        let y1 = (node.max_y - oy) * iy;
        let z0 = (node.min_z - oz) * iz;
        let z1 = (node.max_z - oz) * iz;
        let ([x0, x1, y0, y1, z0, z1], used) = if self.axis_parallel {
            // 0 · ∞ is NaN where the origin lies on a face of a slab the ray runs
            // parallel to: that slab does not limit the ray (the face counts as inside,
            // as the watertight triangle test counts edges). A NaN reciprocal (a
            // denormal direction component) makes both distances NaN: the slab is open.
            let open = |a: Vec4, b: Vec4| {
                let a = Vec4::select(a.cmpeq(a), a, -b);
                let b = Vec4::select(b.cmpeq(b), b, -a);
                (
                    Vec4::select(a.cmpeq(a), a, Vec4::NEG_INFINITY),
                    Vec4::select(b.cmpeq(b), b, Vec4::INFINITY),
                )
            };
            let ((x0, x1), (y0, y1), (z0, z1)) = (open(x0, x1), open(y0, y1), open(z0, z1));
            // With every slab open an unused lane (its box at +∞) would pass and send
            // traversal back to the root forever (fuzz finding): mask unused lanes.
            let used = node.min_x.cmplt(Vec4::INFINITY);
            ([x0, x1, y0, y1, z0, z1], used)
        } else {
            ([x0, x1, y0, y1, z0, z1], BVec4A::splat(true))
        };
        let t_near = x0.min(x1).max(y0.min(y1)).max(z0.min(z1)).max(Vec4::ZERO) * NEAR_SCALE;
        let t_far = x0.max(x1).min(y0.max(y1)).min(z0.max(z1)) * FAR_SCALE;
        let hit = t_near.cmple(t_far) & t_near.cmplt(Vec4::splat(t_max)) & used;
        (t_near, hit.bitmask())
    }
}

/// A pending subtree: a wide node (`count == 0`) or a leaf's slot range, with its entry
/// distance.
#[derive(Clone, Copy, Debug, Default)]
struct Pending {
    first: u32,
    count: u32,
    t: f32,
}

/// Entries kept inline; deeper trees spill to the heap. Zero-filling a stack sized for
/// the worst case cost more than the traversal itself (every instance runs one).
const INLINE_STACK: usize = 24;

/// The traversal stack: a small inline array with a heap spill for deep trees.
struct Stack {
    inline: [Pending; INLINE_STACK],
    len: usize,
    spill: Vec<Pending>,
}

impl Stack {
    #[inline(always)]
    fn new() -> Self {
        Self {
            inline: [Pending::default(); INLINE_STACK],
            len: 0,
            spill: Vec::new(),
        }
    }

    #[inline(always)]
    fn push(&mut self, entry: Pending) {
        if self.len < INLINE_STACK {
            self.inline[self.len] = entry;
        } else {
            self.spill.push(entry);
        }
        self.len += 1;
    }

    #[inline(always)]
    fn pop(&mut self) -> Option<Pending> {
        if self.len == 0 {
            return None;
        }
        self.len -= 1;
        if self.len < INLINE_STACK {
            Some(self.inline[self.len])
        } else {
            self.spill.pop()
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

    /// The shared loop over the wide tree: `visit(slot, t_max) -> (new t_max, stop)`.
    #[inline(always)]
    fn traverse(
        &self,
        ray: &Ray,
        stats: &mut TraversalStats,
        mut visit: impl FnMut(usize, f32) -> (f32, bool),
    ) {
        if self.wide.is_empty() {
            return;
        }
        let node_ray = NodeRay::new(ray);
        let mut t_max = ray.t_max;
        // The nearest hit child stays in `current` instead of going through the stack:
        // most nodes hand on exactly one child, and a push and pop per node cost as much
        // as its box test.
        let mut current = Pending {
            first: 0,
            count: 0,
            t: 0.0,
        };
        let mut stack = Stack::new();
        loop {
            if current.count > 0 {
                let first = current.first as usize;
                for slot in first..first + current.count as usize {
                    stats.primitive_tests += 1;
                    let (t, stop) = visit(slot, t_max);
                    t_max = t;
                    if stop {
                        return;
                    }
                }
            } else {
                let node = &self.wide[current.first as usize];
                stats.nodes_visited += 1;
                let (t, mut mask) = node_ray.hit_children(node, t_max);
                let t = t.to_array();
                let child = |lane: usize| Pending {
                    first: node.children[lane],
                    count: node.counts[lane],
                    t: t[lane],
                };
                if mask != 0 {
                    let a = child(mask.trailing_zeros() as usize);
                    mask &= mask - 1;
                    if mask == 0 {
                        current = a;
                        continue;
                    }
                    let b = child(mask.trailing_zeros() as usize);
                    mask &= mask - 1;
                    if mask == 0 {
                        let (near, far) = if b.t < a.t { (b, a) } else { (a, b) };
                        stack.push(far);
                        current = near;
                        continue;
                    }
                    // Three or four: sort them, push all but the nearest farthest first.
                    let mut hits = [a, b, a, a];
                    let mut n = 2;
                    if hits[1].t > hits[0].t {
                        hits.swap(0, 1);
                    }
                    while mask != 0 {
                        let entry = child(mask.trailing_zeros() as usize);
                        mask &= mask - 1;
                        let mut i = n;
                        while i > 0 && hits[i - 1].t < entry.t {
                            hits[i] = hits[i - 1];
                            i -= 1;
                        }
                        hits[i] = entry;
                        n += 1;
                    }
                    for entry in &hits[..n - 1] {
                        stack.push(*entry);
                    }
                    current = hits[n - 1];
                    continue;
                }
            }
            // Next: the nearest pending subtree still in front of the closest hit.
            loop {
                let Some(entry) = stack.pop() else {
                    return;
                };
                if entry.t < t_max {
                    current = entry;
                    break;
                }
            }
        }
    }
}
