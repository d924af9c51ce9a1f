//! Refitting: the same tree over moved primitives. Every box is recomputed bottom-up;
//! topology and slot order stay.
//! A refit costs a linear pass instead of a SAH build, but the tree's quality decays as
//! primitives move away from where it was built: [`Bvh::sah_cost`] measures by how much,
//! so the caller can rebuild once it has degraded.

use super::{Bvh, PADDING};
use crate::util::math::Aabb;

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
        // Children come after their parent, so a reverse pass sees every child before
        // its parent. Lanes store boxes grown by a few ulps; parents are refitted from
        // the exact unions kept here, so the growth is applied once and does not compound
        // with depth.
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
        self.root_bounds = exact.first().copied().unwrap_or(Aabb::EMPTY);
        Ok(())
    }

    /// Surface-area-heuristic cost of the tree, not normalised: the root's area (its
    /// visit) plus, over every lane, its box's area × (1 for a node visit, or the
    /// primitive count of a leaf), which is the expected work of a ray hitting the root
    /// times the root's area. Translation leaves it unchanged; after a refit, its ratio
    /// to the cost when built measures the degradation. (Normalising by the root's area
    /// would hide a primitive moved far away: the grown root makes every node look
    /// relatively smaller.) 0 when empty.
    pub fn sah_cost(&self) -> f64 {
        if self.wide.is_empty() {
            return 0.0;
        }
        let lanes = super::chunked_sum(&self.wide, |node| {
            (0..super::wide::WIDTH)
                .filter(|&lane| node.is_used(lane))
                .map(|lane| {
                    let weight = node.counts[lane].max(1);
                    node.child_bounds(lane).surface_area() as f64 * weight as f64
                })
                .sum()
        });
        self.root_bounds.surface_area() as f64 + lanes
    }
}
