//! Bounding volume hierarchies: one binary BVH type serves both levels, over triangles
//! (the per-species BLAS) and over instances (the TLAS). It knows nothing of what its
//! primitives are: building takes their boxes, traversal takes a closure that tests a
//! primitive slot (obvhs-style `ray_traverse` / `ray_traverse_anyhit`).

mod build;
mod node;
mod refit;
pub mod simd;
mod traverse;
mod validate;
mod wide;

pub use build::BuildParams;
pub use node::BvhNode;
pub use refit::RefitError;
pub use traverse::{NodeRay, TraversalStats};
pub use validate::BvhReport;
pub use wide::{WIDTH, WideNode};

/// Traversal stack capacity; [`build`](Bvh::build) bounds the depth below it.
pub const MAX_DEPTH: usize = 96;

/// A binary BVH: nodes in depth-first order (root at 0) and the primitive order its
/// leaves refer to.
#[derive(Clone, Debug, Default)]
pub struct Bvh {
    /// Binary nodes as built; empty when the BVH holds no primitive.
    pub nodes: Vec<BvhNode>,
    /// The same tree collapsed to [`WIDTH`] children per node: what traversal walks.
    pub wide: Vec<WideNode>,
    /// `prim_indices[slot]` is the caller's index of the primitive in leaf slot `slot`.
    /// Primitives with empty or non-finite boxes are left out.
    pub prim_indices: Vec<u32>,
}

impl Bvh {
    /// True when there is nothing to hit.
    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// Bytes of heap memory held.
    pub fn memory_bytes(&self) -> usize {
        self.nodes.capacity() * std::mem::size_of::<BvhNode>()
            + self.wide.capacity() * std::mem::size_of::<WideNode>()
            + self.prim_indices.capacity() * 4
    }

    /// The box around everything (empty box when empty).
    pub fn bounds(&self) -> crate::math::Aabb {
        self.nodes.first().map(|n| n.bounds()).unwrap_or_default()
    }
}
