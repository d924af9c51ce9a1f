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
/// The top [`PARALLEL_LEVELS`] wide levels are made first; the subtrees below them are
/// collapsed on the rayon pool and appended in a fixed order, so the result does not
/// depend on the thread count, and the result is written once, in place.
/// The result replaces what `wide` held, in its memory.
pub fn collapse_into(binary: &[BvhNode], wide: &mut Vec<WideNode>) {
    wide.clear();
    let Some(root) = binary.first() else {
        return;
    };
    if root.is_leaf() {
        let mut node = WideNode::empty();
        node.set_box(0, root.bounds());
        node.children[0] = root.first();
        node.counts[0] = root.count();
        wide.push(node);
        return;
    }
    let mut top = Vec::new();
    let mut frontier = Vec::new();
    collapse_top(binary, 0, PARALLEL_LEVELS, &mut top, &mut frontier);
    let pieces: Vec<Vec<WideNode>> = frontier
        .par_iter()
        .map(|lane| {
            let mut piece = Vec::new();
            collapse_subtree(binary, lane.binary, &mut piece);
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

/// The binary nodes that become the lanes of the wide node made from interior node
/// `index`, in tree order.
fn open_lanes(binary: &[BvhNode], index: usize) -> ([usize; WIDTH], usize) {
    // Fixed arrays: a heap-allocated lane list per node cost more than the rest of the
    // collapse together. Leaves get area −1 so they are never opened.
    let area_of = |node: usize| {
        let n = &binary[node];
        if n.is_leaf() {
            -1.0
        } else {
            n.bounds().surface_area()
        }
    };
    let first = binary[index].first() as usize;
    let mut lanes = [0; WIDTH];
    let mut areas = [0.0f32; WIDTH];
    lanes[0] = first;
    lanes[1] = first + 1;
    areas[0] = area_of(first);
    areas[1] = area_of(first + 1);
    let mut len = 2;
    while len < WIDTH {
        let mut widest: Option<(usize, f32)> = None;
        for (position, &area) in areas[..len].iter().enumerate() {
            if area >= 0.0 && widest.is_none_or(|(_, best)| area > best) {
                widest = Some((position, area));
            }
        }
        let Some((position, _)) = widest else {
            break;
        };
        let child = binary[lanes[position]].first() as usize;
        // The opened node's two children take its place, in order.
        lanes.copy_within(position + 1..len, position + 2);
        areas.copy_within(position + 1..len, position + 2);
        lanes[position] = child;
        lanes[position + 1] = child + 1;
        areas[position] = area_of(child);
        areas[position + 1] = area_of(child + 1);
        len += 1;
    }
    (lanes, len)
}

/// The wide node made from interior binary node `index`, with its leaf lanes filled in
/// and its interior lanes' binary nodes.
fn wide_node(binary: &[BvhNode], index: usize) -> (WideNode, [usize; WIDTH], usize) {
    let (lanes, len) = open_lanes(binary, index);
    let mut node = WideNode::empty();
    for (lane, &child) in lanes[..len].iter().enumerate() {
        let c = &binary[child];
        node.set_box(lane, c.bounds());
        if c.is_leaf() {
            node.children[lane] = c.first();
            node.counts[lane] = c.count();
        }
    }
    (node, lanes, len)
}

/// Makes the top `levels` wide levels under interior binary node `index` into `top`,
/// recording the interior lanes below them in `frontier`; returns the node's index.
fn collapse_top(
    binary: &[BvhNode],
    index: usize,
    levels: usize,
    top: &mut Vec<WideNode>,
    frontier: &mut Vec<FrontierLane>,
) -> u32 {
    let (mut node, lanes, len) = wide_node(binary, index);
    let at = top.len();
    top.push(node);
    for lane in 0..len {
        if binary[lanes[lane]].is_leaf() {
            continue;
        }
        if levels > 1 {
            node.children[lane] = collapse_top(binary, lanes[lane], levels - 1, top, frontier);
        } else {
            frontier.push(FrontierLane {
                node: at,
                lane,
                binary: lanes[lane],
            });
        }
    }
    top[at] = node;
    at as u32
}

/// Appends the wide subtree of interior binary node `index` to `wide` (its root first,
/// child indices relative to the start of `wide`); returns the root's index.
fn collapse_subtree(binary: &[BvhNode], index: usize, wide: &mut Vec<WideNode>) -> u32 {
    let (mut node, lanes, len) = wide_node(binary, index);
    let at = wide.len();
    wide.push(node);
    for lane in 0..len {
        if !binary[lanes[lane]].is_leaf() {
            node.children[lane] = collapse_subtree(binary, lanes[lane], wide);
        }
    }
    wide[at] = node;
    at as u32
}
