//! The walks' entry points that pick this CPU's kernel: closest and any hit over a
//! leaf's slots, a ray's child boxes, and the packet walk. Each dispatches once, at its
//! top (`with_node_kernel!`); the `_with` forms take the kernel of a walk already under
//! way, so nested walks do not dispatch again.

use super::{Bvh, LeafVisit, NodeRay, PACKET, WIDTH, WideNode, entry_limit};
use crate::accel::kernel::{NodeKernel, with_node_kernel};
use crate::util::math::Ray;
use crate::util::stats::TraversalStats;

impl NodeRay {
    /// Entry distances of the children and a bitmask of the lanes whose box the ray may
    /// enter before `t_max` (bit `i` for lane `i`; a conservative test), on whichever
    /// SIMD kernel this machine runs.
    pub fn hit_children(&self, node: &WideNode, t_max: f32) -> ([f32; WIDTH], u32) {
        with_node_kernel!(kernel => self.hit_children_with(kernel, node, t_max))
    }

    /// [`hit_children`](Self::hit_children) with the box tests of `kernel`.
    #[inline(always)]
    pub fn hit_children_with(
        &self,
        kernel: impl NodeKernel,
        node: &WideNode,
        t_max: f32,
    ) -> ([f32; WIDTH], u32) {
        kernel.hit_children(self, node, entry_limit(t_max))
    }
}

/// The leaf visit of the slot-by-slot traversals: `visit` runs over a leaf's slots,
/// `prefetch(slot)` asks for a put-off leaf's primitives.
struct SlotLeaves<V, P, const ANY_HIT: bool> {
    visit: V,
    prefetch: P,
}

impl<V: FnMut(usize, usize, f32) -> (f32, bool), P: Fn(usize), const ANY_HIT: bool> LeafVisit
    for SlotLeaves<V, P, ANY_HIT>
{
    const ANY_HIT: bool = ANY_HIT;

    #[inline(always)]
    fn visit(&mut self, first: usize, count: usize, t_max: f32) -> (f32, bool) {
        (self.visit)(first, count, t_max)
    }

    #[inline(always)]
    fn prefetch(&self, first: usize, count: usize) {
        (first..first + count).for_each(&self.prefetch);
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
        test: impl FnMut(usize, f32) -> Option<f32>,
    ) -> f32 {
        with_node_kernel!(kernel => self.traverse_closest_with(kernel, ray, stats, test, |_| {}))
    }

    /// [`traverse_closest`](Self::traverse_closest) with the box tests of `kernel`;
    /// `prefetch(slot)` asks for the memory `test` will read for `slot` when its leaf is
    /// put off behind a nearer child.
    #[inline(always)]
    pub fn traverse_closest_with(
        &self,
        kernel: impl NodeKernel,
        ray: &Ray,
        stats: &mut TraversalStats,
        mut test: impl FnMut(usize, f32) -> Option<f32>,
        prefetch: impl Fn(usize),
    ) -> f32 {
        let mut t_max = ray.t_max;
        let visit = |first, count, _| {
            for slot in first..first + count {
                if let Some(hit_t) = test(slot, t_max) {
                    t_max = hit_t;
                }
            }
            (t_max, false)
        };
        kernel.traverse(
            self,
            ray,
            stats,
            &mut SlotLeaves::<_, _, false> { visit, prefetch },
        );
        t_max
    }

    /// True when any primitive accepts a hit closer than `ray.t_max`; stops at the first.
    #[inline]
    pub fn traverse_any(
        &self,
        ray: &Ray,
        stats: &mut TraversalStats,
        test: impl FnMut(usize, f32) -> bool,
    ) -> bool {
        with_node_kernel!(kernel => self.traverse_any_with(kernel, ray, stats, test, |_| {}))
    }

    /// [`traverse_any`](Self::traverse_any) with the box tests of `kernel`; `prefetch`
    /// as for [`traverse_closest_with`](Self::traverse_closest_with).
    #[inline(always)]
    pub fn traverse_any_with(
        &self,
        kernel: impl NodeKernel,
        ray: &Ray,
        stats: &mut TraversalStats,
        mut test: impl FnMut(usize, f32) -> bool,
        prefetch: impl Fn(usize),
    ) -> bool {
        let mut found = false;
        let visit = |first, count, t| {
            found = (first..first + count).any(|slot| test(slot, t));
            (t, found)
        };
        kernel.traverse(
            self,
            ray,
            stats,
            &mut SlotLeaves::<_, _, true> { visit, prefetch },
        );
        found
    }

    /// Closest hits for the packet `rays` (at most [`PACKET`]): `visit(first, count,
    /// rays_in, entry_t, t_max)` tests the leaf over slots `first .. first + count` for
    /// the rays whose bits are set in `rays_in` (bit `i` for `rays[i]`), each as its own
    /// walk would test the leaf, lowering `t_max[i]` to the distance of a closer accepted
    /// hit; `entry_t` is at most any of those rays' entry distance into the leaf's box.
    /// Each ray reaches the leaves its own walk would (and possibly more, never fewer).
    /// `prefetch(slot)` asks for the memory `visit` will read for a leaf starting at
    /// `slot` when that leaf is put off behind a nearer child. Returns the rays' final
    /// `t_max`, or `None` when the packet cannot be bounded (rays parallel to an axis,
    /// non-finite, or with direction signs that differ): then nothing was tested.
    #[inline]
    pub fn traverse_closest_packet(
        &self,
        rays: &[Ray],
        stats: &mut TraversalStats,
        visit: impl FnMut(usize, usize, u32, f32, &mut [f32; PACKET]),
        prefetch: impl Fn(usize),
    ) -> Option<[f32; PACKET]> {
        with_node_kernel!(kernel => kernel.traverse_packet(self, rays, stats, visit, prefetch))
    }
}
