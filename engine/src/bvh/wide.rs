//! The 8-wide BVH that traversal walks: the binary build collapsed so each node holds
//! up to eight children whose boxes are tested together, one SIMD lane each (the layout
//! of Embree's BVH8 and obvhs' wide BVHs): one AVX2 register per coordinate, or two SSE
//! registers where AVX2 is missing.

use super::BvhNode;
use crate::math::Aabb;
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
pub fn collapse(binary: &[BvhNode]) -> Vec<WideNode> {
    // Measured: one wide node per 6.5–6.7 binary nodes (a full collapse would give one
    // per 2·(WIDTH − 1) = 14; leaves stop it early). The slack goes at the end.
    let mut wide = Vec::with_capacity(binary.len() / 6 + 1);
    if let Some(root) = binary.first() {
        if root.is_leaf() {
            let mut node = WideNode::empty();
            node.set_box(0, root.bounds());
            node.children[0] = root.first();
            node.counts[0] = root.count();
            wide.push(node);
        } else {
            collapse_node(binary, 0, &mut wide);
        }
    }
    wide.shrink_to_fit();
    wide
}

fn collapse_node(binary: &[BvhNode], index: usize, wide: &mut Vec<WideNode>) -> u32 {
    let first = binary[index].first() as usize;
    // A fixed array: a heap-allocated lane list per node cost more than the rest of the
    // collapse together.
    let mut lanes = [0; WIDTH];
    lanes[0] = first;
    lanes[1] = first + 1;
    let mut len = 2;
    while len < WIDTH {
        let mut widest: Option<(usize, f32)> = None;
        for (position, &node) in lanes[..len].iter().enumerate() {
            let candidate = &binary[node];
            if candidate.is_leaf() {
                continue;
            }
            let area = candidate.bounds().surface_area();
            if widest.is_none_or(|(_, best)| area > best) {
                widest = Some((position, area));
            }
        }
        let Some((position, _)) = widest else {
            break;
        };
        let child = binary[lanes[position]].first() as usize;
        // The opened node's two children take its place, in order.
        lanes.copy_within(position + 1..len, position + 2);
        lanes[position] = child;
        lanes[position + 1] = child + 1;
        len += 1;
    }
    let at = wide.len();
    wide.push(WideNode::empty());
    let mut node = WideNode::empty();
    for (lane, &child) in lanes[..len].iter().enumerate() {
        let c = &binary[child];
        node.set_box(lane, c.bounds());
        if c.is_leaf() {
            node.children[lane] = c.first();
            node.counts[lane] = c.count();
        } else {
            node.children[lane] = collapse_node(binary, child, wide);
        }
    }
    wide[at] = node;
    at as u32
}
