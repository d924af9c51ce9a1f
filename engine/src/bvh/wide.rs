//! The 8-wide BVH that traversal walks: the binary build collapsed so each node holds
//! up to eight children whose boxes are tested together, one SIMD lane each (the layout
//! of Embree's BVH8 and obvhs' wide BVHs): one AVX2 register per coordinate, or two SSE
//! registers where AVX2 is missing.

use super::BvhNode;
use crate::math::Aabb;
use glam::Vec3A;
use rayon::prelude::*;

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
    pub(super) fn empty() -> Self {
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
    pub(super) fn set_box(&mut self, lane: usize, b: Aabb) {
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

/// Collapses a binary BVH into a wide one: each wide node takes the children of a
/// binary node and keeps opening its largest interior child until it has [`WIDTH`].
///
/// With `clusters` (the box of each leaf slot), a binary leaf of several primitives is
/// a cluster: opened like an interior node when the wide node has a lane left for each
/// of its primitives, it gives each of them a one-slot leaf lane of its own; left
/// closed, it becomes a wide node of such lanes. Without, leaves stay leaves.
///
/// The top [`PARALLEL_LEVELS`] wide levels are made first; the subtrees below them are
/// collapsed on the rayon pool and appended in a fixed order, so the result does not
/// depend on the thread count, and the result is written once, in place.
/// The result replaces what `wide` held, in its memory.
pub fn collapse_into(
    binary: &[BvhNode],
    wide: &mut Vec<WideNode>,
    clusters: Option<&(dyn Fn(u32) -> Aabb + Sync)>,
) {
    wide.clear();
    let Some(root) = binary.first() else {
        return;
    };
    let collapse = Collapse { binary, clusters };
    if !collapse.makes_node(Lane::Node(0)) {
        let mut node = WideNode::empty();
        node.set_box(0, root.bounds());
        node.children[0] = root.first();
        node.counts[0] = root.count();
        wide.push(node);
        return;
    }
    let mut top = Vec::new();
    let mut frontier = Vec::new();
    collapse.top(0, PARALLEL_LEVELS, &mut top, &mut frontier);
    let pieces: Vec<Vec<WideNode>> = frontier
        .par_iter()
        .map(|lane| {
            let mut piece = Vec::new();
            collapse.subtree(lane.binary, &mut piece);
            piece
        })
        .collect();
    // Where each piece starts in the result; the top nodes point at those starts.
    let mut starts = Vec::with_capacity(pieces.len() + 1);
    let mut end = top.len();
    for (lane, piece) in frontier.iter().zip(&pieces) {
        top[lane.node].children[lane.lane] = end as u32;
        starts.push(end);
        end += piece.len();
    }
    starts.push(end);
    // Copied in parallel straight into the result (an indexed collect): a serial copy
    // of the pieces, and the page faults of its fresh memory on one core, were a tenth
    // of a 365 k-instance top-level build.
    wide.par_extend((0..end).into_par_iter().map(|index| {
        if index < top.len() {
            return top[index];
        }
        let piece = starts.partition_point(|&start| start <= index) - 1;
        pieces[piece][index - starts[piece]].with_children_offset(starts[piece] as u32)
    }));
}

/// Wide levels made before the subtrees below them are collapsed in parallel (up to 64
/// subtrees): the collapse is a chain of dependent loads through the binary nodes, and
/// one core walking them all was a fifth of a 365 k-instance top-level build.
const PARALLEL_LEVELS: usize = 2;

/// An interior lane of a top-level wide node whose subtree is collapsed separately.
struct FrontierLane {
    node: usize,
    lane: usize,
    binary: usize,
}

impl WideNode {
    /// This node with `offset` added to its interior children's indices.
    fn with_children_offset(mut self, offset: u32) -> Self {
        for lane in 0..WIDTH {
            if self.is_used(lane) && self.counts[lane] == 0 {
                self.children[lane] += offset;
            }
        }
        self
    }
}

/// What a lane of a wide node under construction holds: a binary node, or one slot of
/// an opened cluster.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Lane {
    Node(usize),
    Slot(u32),
}

/// The binary tree being collapsed, with the slot boxes when leaves are clusters.
#[derive(Clone, Copy)]
struct Collapse<'a> {
    binary: &'a [BvhNode],
    clusters: Option<&'a (dyn Fn(u32) -> Aabb + Sync)>,
}

impl Collapse<'_> {
    /// True when `lane` becomes a wide node of its own (unless opened into its parent):
    /// an interior binary node, or a cluster.
    fn makes_node(&self, lane: Lane) -> bool {
        match lane {
            Lane::Node(index) => {
                let node = &self.binary[index];
                !node.is_leaf() || (self.clusters.is_some() && node.count() > 1)
            }
            Lane::Slot(_) => false,
        }
    }

    /// The area and the lanes it adds when `lane` is opened, or `None` when it cannot be
    /// (a leaf, or a slot).
    fn opening(&self, lane: Lane) -> Option<(f32, usize)> {
        let Lane::Node(index) = lane else {
            return None;
        };
        let node = &self.binary[index];
        self.makes_node(lane).then(|| {
            let added = if node.is_leaf() {
                node.count() as usize - 1
            } else {
                1
            };
            (node.bounds().surface_area(), added)
        })
    }

    /// Writes the lanes `lane` opens into (its two children, or a cluster's slots) at
    /// `out`; returns how many.
    fn open(&self, lane: Lane, out: &mut [Lane]) -> usize {
        let Lane::Node(index) = lane else {
            return 0;
        };
        let node = &self.binary[index];
        let first = node.first();
        if node.is_leaf() {
            let count = node.count() as usize;
            for (offset, slot) in out[..count].iter_mut().enumerate() {
                *slot = Lane::Slot(first + offset as u32);
            }
            count
        } else {
            out[0] = Lane::Node(first as usize);
            out[1] = Lane::Node(first as usize + 1);
            2
        }
    }

    /// The lanes of the wide node made from binary node `index` (interior, or a
    /// cluster), in tree order.
    fn lanes(&self, index: usize) -> ([Lane; WIDTH], usize) {
        // Fixed arrays: a heap-allocated lane list per node cost more than the rest of
        // the collapse together.
        let mut lanes = [Lane::Slot(0); WIDTH];
        let mut openings = [None; WIDTH];
        let mut len = self.open(Lane::Node(index), &mut lanes);
        for position in 0..len {
            openings[position] = self.opening(lanes[position]);
        }
        while len < WIDTH {
            let mut widest: Option<(usize, f32)> = None;
            for (position, opening) in openings[..len].iter().enumerate() {
                if let Some((area, added)) = *opening
                    && len + added <= WIDTH
                    && widest.is_none_or(|(_, best)| area > best)
                {
                    widest = Some((position, area));
                }
            }
            let Some((position, _)) = widest else {
                break;
            };
            // The opened node's lanes take its place, in order.
            let mut opened = [Lane::Slot(0); WIDTH];
            let count = self.open(lanes[position], &mut opened);
            lanes.copy_within(position + 1..len, position + count);
            openings.copy_within(position + 1..len, position + count);
            for (offset, &lane) in opened[..count].iter().enumerate() {
                lanes[position + offset] = lane;
                openings[position + offset] = self.opening(lane);
            }
            len += count - 1;
        }
        (lanes, len)
    }

    /// The wide node made from binary node `index`, with its leaf lanes filled in, and
    /// its lanes.
    fn wide_node(&self, index: usize) -> (WideNode, [Lane; WIDTH], usize) {
        let (lanes, len) = self.lanes(index);
        let mut node = WideNode::empty();
        for (position, &lane) in lanes[..len].iter().enumerate() {
            match lane {
                Lane::Slot(slot) => {
                    let bounds = self.clusters.map_or(Aabb::EMPTY, |boxes| boxes(slot));
                    node.set_box(position, bounds);
                    node.children[position] = slot;
                    node.counts[position] = 1;
                }
                Lane::Node(child) => {
                    let c = &self.binary[child];
                    node.set_box(position, c.bounds());
                    if !self.makes_node(lane) {
                        node.children[position] = c.first();
                        node.counts[position] = c.count();
                    }
                }
            }
        }
        (node, lanes, len)
    }

    /// Makes the top `levels` wide levels under binary node `index` into `top`,
    /// recording the lanes below them that make nodes in `frontier`; returns the node's
    /// index.
    fn top(
        &self,
        index: usize,
        levels: usize,
        top: &mut Vec<WideNode>,
        frontier: &mut Vec<FrontierLane>,
    ) -> u32 {
        let (mut node, lanes, len) = self.wide_node(index);
        let at = top.len();
        top.push(node);
        for (position, &lane) in lanes[..len].iter().enumerate() {
            let Lane::Node(child) = lane else {
                continue;
            };
            if !self.makes_node(lane) {
                continue;
            }
            if levels > 1 {
                node.children[position] = self.top(child, levels - 1, top, frontier);
            } else {
                frontier.push(FrontierLane {
                    node: at,
                    lane: position,
                    binary: child,
                });
            }
        }
        top[at] = node;
        at as u32
    }

    /// Appends the wide subtree of binary node `index` to `wide` (its root first, child
    /// indices relative to the start of `wide`); returns the root's index.
    fn subtree(&self, index: usize, wide: &mut Vec<WideNode>) -> u32 {
        let (mut node, lanes, len) = self.wide_node(index);
        let at = wide.len();
        wide.push(node);
        for (position, &lane) in lanes[..len].iter().enumerate() {
            if let Lane::Node(child) = lane
                && self.makes_node(lane)
            {
                node.children[position] = self.subtree(child, wide);
            }
        }
        wide[at] = node;
        at as u32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unit box at `x`.
    fn unit(x: f32) -> Aabb {
        Aabb::new(Vec3A::new(x, 0.0, 0.0), Vec3A::new(x + 1.0, 1.0, 1.0))
    }

    /// The tree collapsed from a root over two clusters of `left` and `right` slots;
    /// checks that each slot got a lane of its own, with its box.
    fn two_clusters(left: u32, right: u32) -> Vec<WideNode> {
        let slots: Vec<Aabb> = (0..left + right).map(|s| unit(s as f32 * 2.0)).collect();
        let union = |range: std::ops::Range<u32>| {
            range.fold(Aabb::EMPTY, |b, s| b.union(slots[s as usize]))
        };
        let binary = [
            BvhNode::interior(union(0..left + right), 1),
            BvhNode::leaf(union(0..left), 0, left),
            BvhNode::leaf(union(left..left + right), left, right),
        ];
        let mut wide = Vec::new();
        collapse_into(&binary, &mut wide, Some(&|slot: u32| slots[slot as usize]));
        for node in &wide {
            for lane in (0..WIDTH).filter(|&lane| node.is_used(lane) && node.counts[lane] > 0) {
                assert_eq!(
                    node.counts[lane], 1,
                    "a cluster's slot has a lane of its own"
                );
                let slot = node.children[lane] as usize;
                assert!(node.child_bounds(lane).contains(&slots[slot]));
                let lane_box = node.child_bounds(lane);
                assert!((lane_box.min - slots[slot].min).abs().max_element() < 1e-5);
                assert!((lane_box.max - slots[slot].max).abs().max_element() < 1e-5);
            }
        }
        wide
    }

    fn used_lanes(node: &WideNode) -> usize {
        (0..WIDTH).filter(|&lane| node.is_used(lane)).count()
    }

    #[test]
    fn clusters_that_fit_are_opened_into_their_parent() {
        let wide = two_clusters(6, 2);
        assert_eq!(wide.len(), 1);
        assert_eq!(used_lanes(&wide[0]), 8);
        let mut slots: Vec<u32> = wide[0].children.to_vec();
        slots.sort_unstable();
        assert_eq!(slots, (0..8).collect::<Vec<u32>>());
    }

    #[test]
    fn a_cluster_without_room_becomes_a_node_of_its_own() {
        // Opening either cluster of five takes four more lanes: one fits, not both.
        let wide = two_clusters(5, 5);
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
    fn without_slot_boxes_a_leaf_stays_one_lane() {
        let binary = [
            BvhNode::interior(unit(0.0).union(unit(9.0)), 1),
            BvhNode::leaf(unit(0.0), 0, 6),
            BvhNode::leaf(unit(9.0), 6, 2),
        ];
        let mut wide = Vec::new();
        collapse_into(&binary, &mut wide, None);
        assert_eq!(wide.len(), 1);
        assert_eq!(used_lanes(&wide[0]), 2);
        assert_eq!(wide[0].counts[..2], [6, 2]);
    }
}
