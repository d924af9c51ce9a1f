//! Structural validation of a built BVH: every invariant a traversal relies on.

use super::{Bvh, MAX_DEPTH, PADDING};
use crate::util::math::Aabb;

/// Shape of a valid BVH, returned by [`Bvh::validate`].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BvhReport {
    /// Node count.
    pub nodes: usize,
    /// Leaf count.
    pub leaves: usize,
    /// Deepest leaf (root = 0).
    pub max_depth: usize,
    /// Largest leaf.
    pub max_leaf_size: usize,
    /// SAH cost relative to the root's area (traversal cost 1, primitive cost 1).
    pub sah_cost: f32,
}

impl Bvh {
    /// Checks that the tree is well formed for `prim_bounds` (the boxes it was built from):
    /// children inside the array and after their parent, every node reached once, every
    /// leaf slot owned by exactly one leaf, every valid primitive referenced exactly once,
    /// boxes nested, depth bounded.
    pub fn validate(&self, prim_bounds: &[Aabb]) -> Result<BvhReport, String> {
        let valid = |b: &Aabb| !b.is_empty() && b.min.is_finite() && b.max.is_finite();
        let mut expected: Vec<u32> = (0..prim_bounds.len() as u32)
            .filter(|&i| valid(&prim_bounds[i as usize]))
            .collect();
        let mut referenced: Vec<u32> = self
            .prim_indices
            .iter()
            .copied()
            .filter(|&p| p != PADDING)
            .collect();
        referenced.sort_unstable();
        expected.sort_unstable();
        if referenced != expected {
            return Err(format!(
                "{} primitives referenced, {} valid ones expected (or the sets differ)",
                referenced.len(),
                expected.len()
            ));
        }
        if self.wide.is_empty() {
            return if self.prim_indices.is_empty() {
                Ok(BvhReport::default())
            } else {
                Err("no nodes but primitives".into())
            };
        }
        let root_area = self.root_bounds.surface_area().max(f32::MIN_POSITIVE);
        let mut report = BvhReport {
            nodes: self.wide.len(),
            sah_cost: 1.0,
            ..Default::default()
        };
        let mut seen_node = vec![false; self.wide.len()];
        let mut seen_slot = vec![false; self.prim_indices.len()];
        let mut stack = vec![(0usize, None::<Aabb>, 0usize)];
        while let Some((index, parent_box, depth)) = stack.pop() {
            if std::mem::replace(&mut seen_node[index], true) {
                return Err(format!("node {index} reached twice"));
            }
            if depth >= MAX_DEPTH {
                return Err(format!(
                    "node {index} at depth {depth} exceeds the traversal stack"
                ));
            }
            let node = &self.wide[index];
            for lane in 0..super::wide::WIDTH {
                if !node.is_used(lane) {
                    if node.counts[lane] != 0 {
                        return Err(format!(
                            "node {index} lane {lane} is unused but has primitives"
                        ));
                    }
                    continue;
                }
                let b = node.child_bounds(lane);
                if b.is_empty() || !b.min.is_finite() || !b.max.is_finite() {
                    return Err(format!(
                        "node {index} lane {lane} has an empty or non-finite box"
                    ));
                }
                if parent_box.is_some_and(|p| !p.contains(&b)) {
                    return Err(format!(
                        "node {index} lane {lane} sticks out of its parent's box"
                    ));
                }
                let relative_area = b.surface_area() / root_area;
                let (first, count) = (node.children[lane] as usize, node.counts[lane] as usize);
                if count > 0 {
                    if first + count > self.prim_indices.len() {
                        return Err(format!("node {index} lane {lane} slots out of range"));
                    }
                    for slot in first..first + count {
                        if std::mem::replace(&mut seen_slot[slot], true) {
                            return Err(format!("slot {slot} owned by two leaves"));
                        }
                        if self.prim_indices[slot] == PADDING {
                            return Err(format!("node {index} owns padding slot {slot}"));
                        }
                        if !b.contains(&prim_bounds[self.prim_indices[slot] as usize]) {
                            return Err(format!(
                                "node {index} lane {lane} does not contain primitive {}",
                                self.prim_indices[slot]
                            ));
                        }
                    }
                    report.leaves += 1;
                    report.max_depth = report.max_depth.max(depth + 1);
                    report.max_leaf_size = report.max_leaf_size.max(count);
                    report.sah_cost += relative_area * count as f32;
                } else {
                    if first <= index || first >= self.wide.len() {
                        return Err(format!("node {index} lane {lane} points to node {first}"));
                    }
                    report.sah_cost += relative_area;
                    stack.push((first, Some(b), depth + 1));
                }
            }
        }
        if let Some(i) = seen_node.iter().position(|s| !s) {
            return Err(format!("node {i} is unreachable"));
        }
        if let Some(s) = self.unowned_slot(&seen_slot) {
            return Err(format!("slot {s} belongs to no leaf"));
        }
        Ok(report)
    }

    /// The first slot that no leaf owned (`seen`) and that is not padding.
    fn unowned_slot(&self, seen: &[bool]) -> Option<usize> {
        (0..seen.len()).find(|&s| !seen[s] && self.prim_indices[s] != PADDING)
    }
}
