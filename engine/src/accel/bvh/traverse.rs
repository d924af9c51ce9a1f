//! Stack-based, near-child-first traversal with two entry points: closest hit and any
//! hit. The caller's closure tests a leaf's primitive slots (or one slot, through the
//! slot-wise entry points), so alpha masks and instance transforms live outside the BVH.

use super::simd::{NodeKernel, prefetch_children, prefetch_node, with_node_kernel};
use super::{Bvh, WIDTH, WideNode};
use crate::util::math::{Ray, gamma};
use crate::util::stats::TraversalStats;
use arrayvec::ArrayVec;
use glam::Vec3A;

/// A ray prepared for slab tests against the boxes of a [`WideNode`].
#[derive(Clone, Copy, Debug)]
pub struct NodeRay {
    pub(super) origin: [f32; 3],
    pub(super) inv_dir: [f32; 3],
    /// Some direction component is ±0 (its reciprocal is infinite) or so small that its
    /// reciprocal overflows (then NaN): such slabs get the open treatment.
    pub(super) axis_parallel: bool,
    /// Per axis, whether the ray meets a box's upper plane first (its direction is
    /// negative there): the near plane of the slab test, so the kernels read the near and
    /// far planes directly instead of taking the min and max of both distances.
    pub(super) near_is_max: [bool; 3],
}

/// Widening of the far slab distance that makes the box test conservative (Ize 2013,
/// "Robust BVH Ray Traversal": far × (1 + 2γ₃) against the entry distance), so
/// watertight triangle tests are never culled early. The entry distance is not narrowed
/// by (1 − 2γ₃) as Ize does: the far side and the limit take that factor instead (see
/// [`entry_limit`]), which keeps a multiply off the chain from a node's load to the next
/// node's address. 1 + 6γ₃ covers (1 + 2γ₃)/(1 − 2γ₃) and the roundings of both products.
pub(super) const FAR_SCALE: f32 = 1.0 + 6.0 * gamma(3);

/// The widening of the closest hit so far that children's entry distances are tested
/// against: a box whose entry rounded up past a hit on its own face must still be
/// entered (a closest hit 1 ulp too far without it; fuzz finding). 1 + 4γ₃ covers the
/// 1/(1 − 2γ₃) of Ize's narrowed entry and the rounding of this product.
const LIMIT_SCALE: f32 = 1.0 + 4.0 * gamma(3);

/// The bound that children's entry distances must stay below for a closest hit (or ray
/// end) at `t_max`: a little beyond it, as the slab test's rounding needs.
#[inline(always)]
pub(super) fn entry_limit(t_max: f32) -> f32 {
    t_max * LIMIT_SCALE
}

impl NodeRay {
    /// Keeps origin and reciprocal direction for the slab tests.
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
            origin: ray.origin.to_array(),
            inv_dir: inv.to_array(),
            // A NaN ray hits nothing either way; only finite rays get open slabs.
            axis_parallel: !inv.is_finite()
                && ray.origin.is_finite()
                && !ray.direction.is_nan()
                && ray.direction != Vec3A::ZERO,
            near_is_max: [inv.x < 0.0, inv.y < 0.0, inv.z < 0.0],
        }
    }

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

/// What a traversal does at each leaf it reaches: `visit(first, count, t_max) -> (new
/// t_max, stop)` tests the leaf's slots `first .. first + count`. Closures implement it;
/// a type with an `#[inline(always)]` method gets its leaf test inlined into the
/// traversal loop (a large closure stays a call, and outside the AVX2 function it is
/// compiled without AVX).
pub trait LeafVisit {
    /// True for an any-hit visit, which never shortens the ray: the traversal then
    /// visits a node's hit leaves as soon as its box test finds them and keeps only
    /// interior nodes pending, with no sort and no branch on whether the next entry is a
    /// leaf (the branch a simulated predictor misses most). A closest-hit visit gets a
    /// node's hit children nearest first. An any-hit visit's returned `t_max` is not
    /// read.
    const ANY_HIT: bool = false;

    /// Tests one leaf; returns the new `t_max` and whether to stop.
    fn visit(&mut self, first: usize, count: usize, t_max: f32) -> (f32, bool);

    /// Asks for the memory of the leaf over slots `first .. first + count` ahead of its
    /// visit, when it has been put off behind a nearer child.
    #[inline(always)]
    fn prefetch(&self, _first: usize, _count: usize) {}
}

impl<F: FnMut(usize, usize, f32) -> (f32, bool)> LeafVisit for F {
    #[inline(always)]
    fn visit(&mut self, first: usize, count: usize, t_max: f32) -> (f32, bool) {
        self(first, count, t_max)
    }
}

/// Puts `entry` into `hits[..=n]`, which holds `n` entries sorted farthest first by
/// `t`, after every entry at least as far (so equal distances keep arrival order).
#[inline(always)]
pub(super) fn insert_farthest_first<T: Copy>(
    hits: &mut [T; WIDTH],
    n: usize,
    entry: T,
    t: impl Fn(&T) -> f32,
) {
    let mut i = n;
    while i > 0 && t(&hits[i - 1]) < t(&entry) {
        hits[i] = hits[i - 1];
        i -= 1;
    }
    hits[i] = entry;
}

/// A pending subtree: a wide node (`count == 0`) or a leaf's slot range, with its entry
/// distance.
#[derive(Clone, Copy, Debug, Default)]
struct Pending {
    first: u32,
    count: u32,
    t: f32,
}

/// Entries kept inline; deeper trees spill to the heap.
const INLINE_STACK: usize = 24;

/// A traversal stack: a small inline array with a heap spill for deep trees. The inline
/// part starts uninitialised (`ArrayVec`): zero-filling it cost 2.2 % of a `paper`
/// frame's instructions, every bottom-level entry making a stack of its own.
pub(super) struct Stack<T> {
    inline: ArrayVec<T, INLINE_STACK>,
    spill: Vec<T>,
}

impl<T> Stack<T> {
    #[inline(always)]
    pub(super) fn new() -> Self {
        Self {
            inline: ArrayVec::new(),
            spill: Vec::new(),
        }
    }

    #[inline(always)]
    pub(super) fn push(&mut self, entry: T) {
        if self.inline.is_full() {
            self.spill.push(entry);
        } else {
            self.inline.push(entry);
        }
    }

    #[inline(always)]
    pub(super) fn pop(&mut self) -> Option<T> {
        if self.spill.is_empty() {
            self.inline.pop()
        } else {
            self.spill.pop()
        }
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

    /// Asks for a pending interior node's memory ahead of its visit: node loads that miss
    /// the cache are a fifth of traversal time.
    #[inline(always)]
    fn prefetch(&self, entry: Pending, leaves: &impl LeafVisit) {
        if entry.count > 0 {
            leaves.prefetch(entry.first as usize, entry.count as usize);
        } else if let Some(node) = self.wide.get(entry.first as usize) {
            prefetch_node(node);
        }
    }

    /// The shared loop over the wide tree: [`LeafVisit::visit`] for each leaf the ray
    /// reaches, with the box tests of `kernel`; an any-hit visit
    /// ([`LeafVisit::ANY_HIT`]) gets the any-hit loop.
    #[inline(always)]
    pub(super) fn traverse_with<L: LeafVisit>(
        &self,
        kernel: impl NodeKernel,
        ray: &Ray,
        stats: &mut TraversalStats,
        leaves: &mut L,
    ) {
        if self.wide.is_empty() {
            return;
        }
        if L::ANY_HIT {
            return self.traverse_any_hit(kernel, ray, stats, leaves);
        }
        let node_ray = NodeRay::new(ray);
        let mut t_max = ray.t_max;
        let mut limit = entry_limit(t_max);
        // Counted in registers and added once: `stats` lives in memory across `visit`.
        let (mut nodes, mut primitives) = (0u64, 0u64);
        // The nearest hit child stays in `current` instead of going through the stack:
        // most nodes hand on exactly one child, and a push and pop per node cost as much
        // as its box test.
        let mut current = Pending {
            first: 0,
            count: 0,
            t: 0.0,
        };
        let mut stack = Stack::new();
        'walk: loop {
            if current.count > 0 {
                primitives += u64::from(current.count);
                let (t, stop) = leaves.visit(current.first as usize, current.count as usize, t_max);
                t_max = t;
                limit = entry_limit(t);
                if stop {
                    break 'walk;
                }
            } else {
                let node = &self.wide[current.first as usize];
                // The children's line is read only after the box test: ask for it now.
                prefetch_children(node);
                nodes += 1;
                let (t, mut mask) = kernel.hit_children(&node_ray, node, limit);
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
                        self.prefetch(far, leaves);
                        stack.push(far);
                        current = near;
                        continue;
                    }
                    // More: sort them, push all but the nearest farthest first.
                    let mut hits = [a; WIDTH];
                    hits[1] = b;
                    let mut n = 2;
                    if hits[1].t > hits[0].t {
                        hits.swap(0, 1);
                    }
                    while mask != 0 {
                        let entry = child(mask.trailing_zeros() as usize);
                        mask &= mask - 1;
                        insert_farthest_first(&mut hits, n, entry, |e| e.t);
                        n += 1;
                    }
                    for entry in &hits[..n - 1] {
                        self.prefetch(*entry, leaves);
                        stack.push(*entry);
                    }
                    current = hits[n - 1];
                    continue;
                }
            }
            // Next: the nearest pending subtree still in front of the closest hit.
            loop {
                let Some(entry) = stack.pop() else {
                    break 'walk;
                };
                if entry.t < limit {
                    current = entry;
                    break;
                }
            }
        }
        stats.nodes_visited += nodes;
        stats.primitive_tests += primitives;
    }

    /// The any-hit loop: a node's hit leaves are visited as its box test finds them (in
    /// lane order), its hit interior children go on: the one the ray runs through
    /// longest next, the rest pending in any order. The ray never shortens, so pending
    /// entries need no distance check.
    #[inline(always)]
    fn traverse_any_hit(
        &self,
        kernel: impl NodeKernel,
        ray: &Ray,
        stats: &mut TraversalStats,
        leaves: &mut impl LeafVisit,
    ) {
        let node_ray = NodeRay::new(ray);
        let t_max = ray.t_max;
        let limit = entry_limit(t_max);
        let (mut nodes, mut primitives) = (0u64, 0u64);
        let mut current = 0u32;
        let mut stack = Stack::new();
        'walk: loop {
            let node = &self.wide[current as usize];
            nodes += 1;
            let (_, span, mask) = kernel.hit_children_spans(&node_ray, node, limit);
            let leaf_lanes = kernel.leaf_lanes(node);
            let mut hit_leaves = mask & leaf_lanes;
            let mut hit_nodes = mask & !leaf_lanes;
            while hit_leaves != 0 {
                let lane = hit_leaves.trailing_zeros() as usize;
                hit_leaves &= hit_leaves - 1;
                let count = node.counts[lane];
                primitives += u64::from(count);
                if leaves
                    .visit(node.children[lane] as usize, count as usize, t_max)
                    .1
                {
                    break 'walk;
                }
            }
            if hit_nodes != 0 {
                // The child the ray runs through longest next: a shadow ray leaving a
                // surface starts inside many boxes (all entered at 0), and the one it
                // crosses longest is likeliest to hold what stops it (nodes per `paper`
                // ray 17.0 → 16.0 against the nearest first). The others pending in any
                // order.
                let lane = hit_nodes.trailing_zeros() as usize;
                hit_nodes &= hit_nodes - 1;
                let (mut next, mut next_span) = (node.children[lane], span[lane]);
                while hit_nodes != 0 {
                    let lane = hit_nodes.trailing_zeros() as usize;
                    hit_nodes &= hit_nodes - 1;
                    let (child, child_span) = (node.children[lane], span[lane]);
                    let (keep, keep_span, put_off) = if child_span > next_span {
                        (child, child_span, next)
                    } else {
                        (next, next_span, child)
                    };
                    (next, next_span) = (keep, keep_span);
                    let pending = Pending {
                        first: put_off,
                        count: 0,
                        t: 0.0,
                    };
                    self.prefetch(pending, leaves);
                    stack.push(pending);
                }
                current = next;
                continue;
            }
            match stack.pop() {
                Some(entry) => current = entry.first,
                None => break,
            }
        }
        stats.nodes_visited += nodes;
        stats.primitive_tests += primitives;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_stack_spills_past_its_inline_part_and_stays_last_in_first_out() {
        let mut stack = Stack::new();
        let mut model = Vec::new();
        // Up past the inline part, down into it, up again, then empty.
        for (pushes, pops) in [(INLINE_STACK + 10, 15), (20, 5), (0, 200)] {
            for i in 0..pushes {
                let value = (model.len() * 7 + i) as u32;
                stack.push(value);
                model.push(value);
            }
            for _ in 0..pops {
                assert_eq!(stack.pop(), model.pop());
            }
        }
        assert_eq!(stack.pop(), None);
    }
}
