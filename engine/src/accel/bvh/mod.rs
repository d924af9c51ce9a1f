//! Bounding volume hierarchies: one 8-wide BVH type serves both levels, over triangles
//! (the per-species BLAS) and over instances (the TLAS). It knows nothing of what its
//! primitives are: building takes their boxes, traversal takes a closure that tests a
//! primitive slot (obvhs-style `ray_traverse` / `ray_traverse_anyhit`). The box tests
//! run on the ISA kernels of [`kernel`](crate::accel::kernel).
//!
//! Files: `build` (binned SAH and grid cells into wide nodes), `wide` (the node),
//! `ray` (a walk's inputs), `traverse` and `traverse_packet` (the loops, generic over the
//! kernel), `query` (entry points that pick the kernel), `packet` (a packet's bound),
//! `refit`, `validate`.

use crate::util::fingerprint::Fingerprint;

mod build;
mod packet;
mod query;
mod ray;
mod refit;
mod traverse;
mod traverse_packet;
mod validate;
mod wide;

pub use crate::util::stats::TraversalStats;
pub use build::{BOTTOM_GRID_FROM, BuildParams, BuildScratch, GRID_FROM};
pub(crate) use packet::mask_bits;
pub use packet::{PACKET, PacketBound};
pub(crate) use ray::{FAR_SCALE, entry_limit};
pub use ray::{LeafVisit, NodeRay};
pub use refit::RefitError;
pub use validate::BvhReport;
pub use wide::{WIDTH, WideNode};

/// The `prim_indices` entry of a slot that only pads a leaf to a whole block.
pub const PADDING: u32 = u32::MAX;

/// The deepest tree [`build`](Bvh::build) makes (median splits take over before it);
/// traversal stacks hold 24 entries inline and spill to the heap beyond them.
pub const MAX_DEPTH: usize = 96;

/// A BVH of [`WIDTH`] children per node, built top-down by binned SAH splits: nodes
/// with every parent before its children (root at 0) and the primitive order its leaves
/// refer to.
#[derive(Clone, Debug, Default)]
pub struct Bvh {
    /// The nodes traversal walks; empty when the BVH holds no primitive.
    pub wide: Vec<WideNode>,
    /// `prim_indices[slot]` is the caller's index of the primitive in leaf slot `slot`,
    /// or [`PADDING`] after a leaf's primitives when leaves are aligned to blocks
    /// ([`BuildParams::leaf_block`]). Primitives with empty or non-finite boxes are left
    /// out.
    pub prim_indices: Vec<u32>,
    /// The box around every primitive, exact (the nodes' lanes are grown a little).
    root_bounds: crate::util::math::Aabb,
}

impl Bvh {
    /// True when there is nothing to hit.
    pub fn is_empty(&self) -> bool {
        self.wide.is_empty()
    }

    /// Bytes of heap memory held.
    pub fn memory_bytes(&self) -> usize {
        self.wide.capacity() * std::mem::size_of::<WideNode>() + self.prim_indices.capacity() * 4
    }

    /// A hash of the tree traversal walks (every wide node's boxes and children, and
    /// the slot order), to check that two builds made the same tree: equal trees give
    /// equal hashes on any machine.
    pub fn content_hash(&self) -> u64 {
        let mut hash = Fingerprint::untagged();
        self.hash_into(&mut hash);
        hash.finish()
    }

    /// Feeds what [`content_hash`](Self::content_hash) covers to `hash`.
    pub(crate) fn hash_into(&self, hash: &mut Fingerprint) {
        for node in &self.wide {
            let boxes = [
                &node.min_x,
                &node.max_x,
                &node.min_y,
                &node.max_y,
                &node.min_z,
                &node.max_z,
            ];
            for &v in boxes.into_iter().flatten() {
                hash.f32(v);
            }
            for &v in node.children.iter().chain(&node.counts) {
                hash.u32(v);
            }
        }
        for &v in &self.prim_indices {
            hash.u32(v);
        }
    }

    /// The box around everything (empty box when empty).
    pub fn bounds(&self) -> crate::util::math::Aabb {
        self.root_bounds
    }
}

/// Sum of `term` over `items` on the rayon pool, in fixed chunks added in order, so the
/// floating-point result does not depend on the thread count.
pub(crate) fn chunked_sum<T: Sync>(items: &[T], term: impl Fn(&T) -> f64 + Sync) -> f64 {
    use rayon::prelude::*;
    let partial: Vec<f64> = items
        .par_chunks(16 * 1024)
        .map(|chunk| chunk.iter().map(&term).sum::<f64>())
        .collect();
    partial.iter().sum()
}
