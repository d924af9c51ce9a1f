//! The 8-wide BVH node that traversal walks: the builder makes each node hold up to
//! eight children whose boxes are tested together, one SIMD lane each (the layout
//! of Embree's BVH8 and obvhs' wide BVHs): one AVX2 register per coordinate, or two SSE
//! registers where AVX2 is missing.

use crate::util::math::Aabb;
use glam::Vec3A;

/// Children per wide node.
pub const WIDTH: usize = 8;

/// Eight child boxes in structure-of-arrays form, with what each child is.
///
/// Invariants (checked by [`super::Bvh::validate`]): lane `i` with `counts[i] == 0` and a
/// finite box is an interior child at wide index `children[i]`, after this node; with
/// `counts[i] > 0` it is a leaf over slots `children[i] .. + counts[i]`; an unused lane
/// has the box `min = max = +inf`, which no ray can enter.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(64))]
pub struct WideNode {
    /// Lower x of the children.
    pub min_x: [f32; WIDTH],
    /// Upper x.
    pub max_x: [f32; WIDTH],
    /// Lower y.
    pub min_y: [f32; WIDTH],
    /// Upper y.
    pub max_y: [f32; WIDTH],
    /// Lower z.
    pub min_z: [f32; WIDTH],
    /// Upper z.
    pub max_z: [f32; WIDTH],
    /// Interior child: its wide node index. Leaf child: its first slot.
    pub children: [u32; WIDTH],
    /// Leaf child: its slot count. Interior or unused: 0.
    pub counts: [u32; WIDTH],
}

const _: () = assert!(std::mem::size_of::<WideNode>() == 256);

const UNUSED: f32 = f32::INFINITY;

impl WideNode {
    /// A node with every lane unused: no ray enters any of them.
    pub fn empty() -> Self {
        let inf = [UNUSED; WIDTH];
        Self {
            min_x: inf,
            max_x: inf,
            min_y: inf,
            max_y: inf,
            min_z: inf,
            max_z: inf,
            children: [0; WIDTH],
            counts: [0; WIDTH],
        }
    }

    /// Stores lane `lane`'s box grown outward by a few ulps, so the f32 slab test stays
    /// conservative against the watertight triangle test, which accepts hits within its
    /// own rounding of a face (a ray starting on a bound and leaving it at a denormal rate
    /// was culled at 10¹² m). Growth is monotone, so nested boxes stay nested.
    pub(crate) fn set_box(&mut self, lane: usize, b: Aabb) {
        const GROWTH: f32 = 1.0 / (1 << 21) as f32;
        let grow = |v: Vec3A, outward: f32| {
            (v + (v.abs() * GROWTH + Vec3A::splat(f32::MIN_POSITIVE)) * outward)
                .clamp(Vec3A::splat(f32::MIN), Vec3A::splat(f32::MAX))
        };
        let b = Aabb {
            min: grow(b.min, -1.0),
            max: grow(b.max, 1.0),
        };
        self.min_x[lane] = b.min.x;
        self.min_y[lane] = b.min.y;
        self.min_z[lane] = b.min.z;
        self.max_x[lane] = b.max.x;
        self.max_y[lane] = b.max.y;
        self.max_z[lane] = b.max.z;
    }

    /// The box of lane `lane`.
    pub fn child_bounds(&self, lane: usize) -> Aabb {
        Aabb {
            min: Vec3A::new(self.min_x[lane], self.min_y[lane], self.min_z[lane]),
            max: Vec3A::new(self.max_x[lane], self.max_y[lane], self.max_z[lane]),
        }
    }

    /// True when lane `lane` holds a child.
    pub fn is_used(&self, lane: usize) -> bool {
        self.min_x[lane] != UNUSED
    }
}

impl WideNode {
    /// This node with `offset` added to its interior children's indices.
    pub(super) fn with_children_offset(mut self, offset: u32) -> Self {
        for lane in 0..WIDTH {
            if self.is_used(lane) && self.counts[lane] == 0 {
                self.children[lane] += offset;
            }
        }
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::accel::bvh::{BuildParams, Bvh};

    /// Two unit boxes far apart along x, the first `left` times, the other `right`
    /// times (boxes that coincide cannot be split).
    fn clumps(left: usize, right: usize) -> Vec<Aabb> {
        let at = |x: f32| Aabb::new(Vec3A::new(x, 0.0, 0.0), Vec3A::new(x + 1.0, 1.0, 1.0));
        std::iter::repeat_n(at(0.0), left)
            .chain(std::iter::repeat_n(at(1000.0), right))
            .collect()
    }

    /// Built with leaves of one primitive and clusters of up to eight; checks that each
    /// slot of a cluster got a lane of its own, with its box.
    fn clustered(boxes: &[Aabb]) -> Bvh {
        let bvh = Bvh::build(boxes, BuildParams::TOP_LEVEL);
        bvh.validate(boxes).unwrap();
        for node in &bvh.wide {
            for lane in (0..WIDTH).filter(|&lane| node.is_used(lane) && node.counts[lane] > 0) {
                assert_eq!(
                    node.counts[lane], 1,
                    "a cluster's slot has a lane of its own"
                );
                let slot = node.children[lane] as usize;
                let own = boxes[bvh.prim_indices[slot] as usize];
                let lane_box = node.child_bounds(lane);
                assert!(lane_box.contains(&own));
                assert!((lane_box.min - own.min).abs().max_element() < 1e-3);
                assert!((lane_box.max - own.max).abs().max_element() < 1e-3);
            }
        }
        bvh
    }

    fn used_lanes(node: &WideNode) -> usize {
        (0..WIDTH).filter(|&lane| node.is_used(lane)).count()
    }

    #[test]
    fn clusters_that_fit_are_opened_into_their_parent() {
        // Eight boxes are one cluster: the root's lanes are its slots.
        let bvh = clustered(&clumps(6, 2));
        assert_eq!(bvh.wide.len(), 1);
        assert_eq!(used_lanes(&bvh.wide[0]), 8);
        // Nine split into clusters of six and three: opening the wider takes five more
        // lanes (seven in all), the other would then need two more.
        let bvh = clustered(&clumps(6, 3));
        assert_eq!(bvh.wide.len(), 2);
        assert_eq!(used_lanes(&bvh.wide[0]), 7);
        assert_eq!(used_lanes(&bvh.wide[1]), 3);
    }

    #[test]
    fn a_cluster_without_room_becomes_a_node_of_its_own() {
        // Opening either cluster of five takes four more lanes: one fits, not both.
        let bvh = clustered(&clumps(5, 5));
        let wide = &bvh.wide;
        assert_eq!(wide.len(), 2);
        assert_eq!(used_lanes(&wide[0]), 6);
        assert_eq!(used_lanes(&wide[1]), 5);
        let interior: Vec<usize> = (0..WIDTH)
            .filter(|&lane| wide[0].is_used(lane) && wide[0].counts[lane] == 0)
            .collect();
        assert_eq!(interior.len(), 1);
        assert_eq!(wide[0].children[interior[0]], 1);
    }

    #[test]
    fn without_clusters_a_leaf_stays_one_lane() {
        let params = BuildParams {
            max_leaf_size: 8,
            lane_cluster: 1,
            ..BuildParams::BALANCED
        };
        let boxes = clumps(6, 2);
        let bvh = Bvh::build(&boxes, params);
        bvh.validate(&boxes).unwrap();
        assert_eq!(bvh.wide.len(), 1);
        assert_eq!(used_lanes(&bvh.wide[0]), 2);
        let mut counts = bvh.wide[0].counts[..2].to_vec();
        counts.sort_unstable();
        assert_eq!(counts, [2, 6]);
    }
}
