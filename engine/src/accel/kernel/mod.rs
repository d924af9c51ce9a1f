//! The SIMD kernels traversal and intersection run on, picked once per query: a
//! portable one (two SSE halves through glam) and AVX2 (one 8-lane register per
//! coordinate), giving the same bits. [`NodeKernel`] names what a kernel does: a wide
//! node's eight box tests (single rays and packets), the traversal loops compiled for
//! it as a whole, a triangle block's exact test and an instance's support-function box.
//! The loops themselves live in [`bvh`](crate::accel::bvh), the triangle and instance
//! tests' scalar forms beside their data; this folder holds only what is ISA-specific,
//! and with it the engine's only `unsafe` (`avx2.rs`, `memory.rs`).

#[cfg(target_arch = "x86_64")]
mod avx2;
mod memory;
mod portable;
#[cfg(test)]
mod tests;

#[cfg(target_arch = "x86_64")]
pub use avx2::Avx2;
pub use memory::{affine_from_columns, prefetch, prefetch_children, prefetch_node};
pub use portable::Portable;

use crate::accel::bvh::{Bvh, LeafVisit, NodeRay, PACKET, PacketBound, WIDTH, WideNode};
use crate::accel::instance_bounds::SupportTable;
use crate::accel::triangle::{BlockHits, TriangleBlock, WatertightRay};
use crate::util::math::{Aabb, Ray};
use crate::util::stats::TraversalStats;
use glam::Affine3A;

/// Evaluates `$body` with `$kernel` bound to the best [`NodeKernel`] of this CPU.
/// Dispatch once per query, at its top: nested traversals inside `$body` take the
/// kernel instead of dispatching again.
macro_rules! with_node_kernel {
    ($kernel:ident => $body:expr) => {{
        #[cfg(target_arch = "x86_64")]
        let avx2 = $crate::accel::kernel::Avx2::detect();
        #[cfg(not(target_arch = "x86_64"))]
        let avx2: Option<()> = None;
        match avx2 {
            #[cfg(target_arch = "x86_64")]
            Some($kernel) => $body,
            _ => {
                let $kernel = $crate::accel::kernel::Portable;
                $body
            }
        }
    }};
}
pub(crate) use with_node_kernel;

/// [`SupportTable::transformed_bounds`] compiled for AVX2 where the CPU has it (an
/// instance's eight support directions then fill one register instead of two SSE
/// halves): the same operations in the same order, so the same bits.
#[inline]
pub fn transformed_bounds(table: &SupportTable, transform: &Affine3A) -> Aabb {
    #[cfg(target_arch = "x86_64")]
    if let Some(avx2) = Avx2::detect() {
        return avx2.transformed_bounds(table, transform);
    }
    table.transformed_bounds(transform)
}
/// Slab tests of a ray against the eight child boxes of a node, and the traversal loop
/// built on them.
pub trait NodeKernel: Copy {
    /// `Bvh::traverse_with` on this kernel: with AVX2, one function compiled for it,
    /// so the box tests inline into the loop (and the caller's leaf test, when it is a
    /// [`LeafVisit`] with an `#[inline(always)]` method).
    fn traverse(
        self,
        bvh: &Bvh,
        ray: &Ray,
        stats: &mut TraversalStats,
        leaves: &mut impl LeafVisit,
    );

    /// Entry distances of the children and a bitmask of the lanes whose box the ray
    /// enters (conservatively) with an entry distance below `limit` (bit `i` for lane
    /// `i`): `limit` is a closest hit widened for the slab test's rounding (`entry_limit`).
    #[inline(always)]
    fn hit_children(self, ray: &NodeRay, node: &WideNode, limit: f32) -> ([f32; WIDTH], u32) {
        let (t, _, mask) = self.hit_children_spans(ray, node, limit);
        (t, mask)
    }

    /// [`hit_children`](Self::hit_children) with each child's span: how far the ray runs
    /// inside its box (the widened exit distance less the entry distance).
    fn hit_children_spans(
        self,
        ray: &NodeRay,
        node: &WideNode,
        limit: f32,
    ) -> ([f32; WIDTH], [f32; WIDTH], u32);

    /// `Bvh::traverse_closest_packet` on this kernel: with AVX2, one function compiled
    /// for it, so the packet's box tests inline into the walk.
    fn traverse_packet(
        self,
        bvh: &Bvh,
        rays: &[Ray],
        stats: &mut TraversalStats,
        visit: impl FnMut(usize, usize, u32, f32, &mut [f32; PACKET]),
        prefetch: impl Fn(usize),
    ) -> Option<[f32; PACKET]>;

    /// The packet's box test of `node` ([`PacketBound`]'s, bit for bit).
    #[inline(always)]
    fn packet_hit_children(
        self,
        bound: &PacketBound,
        node: &WideNode,
        limit: f32,
    ) -> ([f32; WIDTH], u32) {
        bound.hit_children(node, limit)
    }

    /// Bit `i` set when lane `i` of `node` is a leaf (a count above zero).
    #[inline(always)]
    fn leaf_lanes(self, node: &WideNode) -> u32 {
        node.counts
            .iter()
            .enumerate()
            .fold(0, |bits, (lane, &count)| {
                bits | (u32::from(count > 0) << lane)
            })
    }

    /// [`WatertightRay::block_hits`] on this kernel, bit for bit: the exact test on the
    /// first `lanes` lanes of `block`, against `t_max`.
    fn block_hits(
        self,
        ray: &WatertightRay,
        block: &TriangleBlock,
        lanes: usize,
        t_max: f32,
    ) -> BlockHits;
}
