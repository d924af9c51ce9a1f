//! Refitting: the same tree over moved primitives. Every box is recomputed bottom-up, in
//! the binary nodes and in the wide nodes traversal walks; topology and slot order stay.
//! A refit costs a linear pass instead of a SAH build, but the tree's quality decays as
//! primitives move away from where it was built: [`Bvh::sah_cost`] measures by how much,
//! so the caller can rebuild once it has degraded.

use super::{Bvh, PADDING};
use crate::math::Aabb;

/// Why [`Bvh::refit`] refused; the tree is left unchanged.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum RefitError {
    /// The number of boxes differs from the number of leaf slots.
    #[error("refit given {given} boxes for a tree of {expected} slots")]
    SlotCount {
        /// Leaf slots in the tree.
        expected: usize,
        /// Boxes given.
        given: usize,
    },
    /// A box is empty or not finite: that primitive must leave the tree (rebuild).
    #[error("refit given an empty or non-finite box for slot {slot}")]
    InvalidBox {
        /// The leaf slot of the primitive.
        slot: usize,
    },
}

impl Bvh {
    /// Recomputes every box of the tree from `slot_bounds`, indexed by leaf slot (the
    /// primitive of slot `s` is the caller's `prim_indices[s]`). Refuses, changing
    /// nothing, when the count differs or a leaf slot's box is empty or not finite.
    pub fn refit(&mut self, slot_bounds: &[Aabb]) -> Result<(), RefitError> {
        if slot_bounds.len() != self.prim_indices.len() {
            return Err(RefitError::SlotCount {
                expected: self.prim_indices.len(),
                given: slot_bounds.len(),
            });
        }
        // Padding slots belong to no leaf: their boxes are never read.
        if let Some(slot) = (0..slot_bounds.len()).find(|&s| {
            let b = &slot_bounds[s];
            self.prim_indices[s] != PADDING
                && (b.is_empty() || !b.min.is_finite() || !b.max.is_finite())
        }) {
            return Err(RefitError::InvalidBox { slot });
        }
        let union_of_slots = |first: u32, count: u32| {
            slot_bounds[first as usize..(first + count) as usize]
                .iter()
                .fold(Aabb::EMPTY, |acc, b| acc.union(*b))
        };
        // Children come after their parent in both arrays, so a reverse pass sees every
        // child before its parent.
        for index in (0..self.nodes.len()).rev() {
            let node = self.nodes[index];
            self.nodes[index] = if node.is_leaf() {
                super::BvhNode::leaf(
                    union_of_slots(node.first(), node.count()),
                    node.first(),
                    node.count(),
                )
            } else {
                let left = node.first() as usize;
                let bounds = self.nodes[left]
                    .bounds()
                    .union(self.nodes[left + 1].bounds());
                super::BvhNode::interior(bounds, node.first())
            };
        }
        // Wide lanes store boxes grown by a few ulps; parents are refitted from the exact
        // unions kept here, so the growth is applied once and does not compound with depth.
        let mut exact = vec![Aabb::EMPTY; self.wide.len()];
        for index in (0..self.wide.len()).rev() {
            let mut node = self.wide[index];
            let mut whole = Aabb::EMPTY;
            for lane in 0..super::wide::WIDTH {
                if !node.is_used(lane) {
                    continue;
                }
                let bounds = if node.counts[lane] > 0 {
                    union_of_slots(node.children[lane], node.counts[lane])
                } else {
                    exact[node.children[lane] as usize]
                };
                node.set_box(lane, bounds);
                whole = whole.union(bounds);
            }
            self.wide[index] = node;
            exact[index] = whole;
        }
        Ok(())
    }

    /// Surface-area-heuristic cost of the binary tree, not normalised: the sum over nodes
    /// of box area × (1 for a node visit, or the primitive count of a leaf), which is the
    /// expected work of a ray hitting the root times the root's area. Translation leaves
    /// it unchanged; after a refit, its ratio to the cost when built measures the
    /// degradation. (Normalising by the root's area would hide a primitive moved far
    /// away: the grown root makes every node look relatively smaller.) 0 when empty.
    pub fn sah_cost(&self) -> f64 {
        super::chunked_sum(&self.nodes, |node| {
            let weight = if node.is_leaf() { node.count() } else { 1 };
            node.bounds().surface_area() as f64 * weight as f64
        })
    }
}
