//! One closest-hit walk for a packet of up to [`PACKET`] coherent rays (a camera's
//! neighbouring pixels): every node is tested once for the whole packet, with
//! interval arithmetic over the rays' origins and reciprocal directions, and each ray
//! gets its own box test only at the leaves, so it enters just the leaves a walk of its
//! own would enter. Rays from one origin (a pinhole camera's) get a cheaper bound. The
//! top level hands the rays that enter an instance together to its bottom level as a
//! packet again, when they are narrow enough there.

use super::{FAR_SCALE, NodeRay, WIDTH, WideNode};
use glam::Vec4;

/// Rays a packet holds at most.
pub const PACKET: usize = 16;

/// The indices of the bits set in `mask`, lowest first.
#[inline(always)]
pub(crate) fn mask_bits(mut mask: u32) -> impl Iterator<Item = usize> {
    std::iter::from_fn(move || {
        (mask != 0).then(|| {
            let bit = mask.trailing_zeros() as usize;
            mask &= mask - 1;
            bit
        })
    })
}

/// Per axis, the smallest and largest origin and reciprocal direction over a packet's
/// rays; every ray's reciprocal has one sign per axis (no ray runs parallel to an axis).
#[derive(Clone, Copy, Debug)]
pub struct PacketBound {
    pub(crate) origin_lo: [f32; 3],
    origin_hi: [f32; 3],
    pub(crate) inv_lo: [f32; 3],
    pub(crate) inv_hi: [f32; 3],
    /// All rays start at the same point (a pinhole camera's): each plane's distance
    /// from it is one value, and only the reciprocals' interval remains.
    pub(crate) common_origin: bool,
    /// Per axis, whether the rays meet a box's upper plane first (all alike).
    pub(crate) near_is_max: [bool; 3],
}

impl PacketBound {
    /// The bound of `rays`, or `None` when some ray has an open slab (an axis-parallel
    /// or non-finite ray) or the rays' directions differ in sign on some axis.
    pub(crate) fn new(rays: &[NodeRay]) -> Option<Self> {
        let first = rays.first()?;
        let mut bound = Self {
            origin_lo: first.origin,
            origin_hi: first.origin,
            inv_lo: first.inv_dir,
            inv_hi: first.inv_dir,
            common_origin: true,
            near_is_max: first.near_is_max,
        };
        for ray in rays {
            if ray.axis_parallel || ray.near_is_max != first.near_is_max {
                return None;
            }
            for axis in 0..3 {
                let (o, inv) = (ray.origin[axis], ray.inv_dir[axis]);
                if !o.is_finite() || !inv.is_finite() || inv == 0.0 {
                    return None;
                }
                bound.origin_lo[axis] = bound.origin_lo[axis].min(o);
                bound.origin_hi[axis] = bound.origin_hi[axis].max(o);
                bound.inv_lo[axis] = bound.inv_lo[axis].min(inv);
                bound.inv_hi[axis] = bound.inv_hi[axis].max(inv);
            }
            bound.common_origin &= ray.origin == first.origin;
        }
        Some(bound)
    }

    /// Per lane of `node`, the least entry distance any ray of the packet can have and
    /// whether some ray may enter the box before `limit`: a superset of the lanes each
    /// ray's own slab test passes, since rounding is monotonic in each operand, so the
    /// products at the interval corners bound every ray's rounded product.
    #[inline(always)]
    pub(crate) fn hit_children(&self, node: &WideNode, limit: f32) -> ([f32; WIDTH], u32) {
        if self.common_origin {
            return self.hit_children_from_one_origin(node, limit);
        }
        let mut near_out = [0.0; WIDTH];
        let mut mask = 0;
        for half in 0..WIDTH / 4 {
            let lanes = |a: &[f32; WIDTH]| Vec4::from_slice(&a[half * 4..half * 4 + 4]);
            let planes = [
                (lanes(&node.min_x), lanes(&node.max_x)),
                (lanes(&node.min_y), lanes(&node.max_y)),
                (lanes(&node.min_z), lanes(&node.max_z)),
            ];
            let mut near = Vec4::ZERO;
            let mut far = Vec4::INFINITY;
            for (axis, (lower, upper)) in planes.into_iter().enumerate() {
                let (o_lo, o_hi) = (
                    Vec4::splat(self.origin_lo[axis]),
                    Vec4::splat(self.origin_hi[axis]),
                );
                let (i_lo, i_hi) = (
                    Vec4::splat(self.inv_lo[axis]),
                    Vec4::splat(self.inv_hi[axis]),
                );
                let range = |plane: Vec4| {
                    let (d_lo, d_hi) = (plane - o_hi, plane - o_lo);
                    let (a, b, c, d) = (d_lo * i_lo, d_lo * i_hi, d_hi * i_lo, d_hi * i_hi);
                    (a.min(b).min(c.min(d)), a.max(b).max(c.max(d)))
                };
                let (lo0, hi0) = range(lower);
                let (lo1, hi1) = range(upper);
                near = near.max(lo0.min(lo1));
                far = far.min(hi0.max(hi1));
            }
            let far = far * FAR_SCALE;
            let hit = near.cmple(far) & near.cmplt(Vec4::splat(limit));
            near_out[half * 4..half * 4 + 4].copy_from_slice(&near.to_array());
            mask |= hit.bitmask() << (half * 4);
        }
        (near_out, mask)
    }

    /// [`hit_children`](Self::hit_children) for rays from one origin: the distance from
    /// it to each plane is the same value for every ray, and the rays meet the same
    /// plane of each axis first, so a ray's near (far) distance on an axis is that
    /// plane's distance times its reciprocal, and the two ends of the reciprocals'
    /// interval bound it from both sides (rounding is monotonic in each operand).
    #[inline(always)]
    fn hit_children_from_one_origin(&self, node: &WideNode, limit: f32) -> ([f32; WIDTH], u32) {
        let mut near_out = [0.0; WIDTH];
        let mut mask = 0;
        let planes = [
            (&node.min_x, &node.max_x),
            (&node.min_y, &node.max_y),
            (&node.min_z, &node.max_z),
        ];
        for half in 0..WIDTH / 4 {
            let lanes = |a: &[f32; WIDTH]| Vec4::from_slice(&a[half * 4..half * 4 + 4]);
            let mut near = Vec4::ZERO;
            let mut far = Vec4::INFINITY;
            for (axis, &(lower, upper)) in planes.iter().enumerate() {
                let (near_plane, far_plane) = if self.near_is_max[axis] {
                    (upper, lower)
                } else {
                    (lower, upper)
                };
                let origin = Vec4::splat(self.origin_lo[axis]);
                let (i_lo, i_hi) = (
                    Vec4::splat(self.inv_lo[axis]),
                    Vec4::splat(self.inv_hi[axis]),
                );
                let to_near = lanes(near_plane) - origin;
                let to_far = lanes(far_plane) - origin;
                near = near.max((to_near * i_lo).min(to_near * i_hi));
                far = far.min((to_far * i_lo).max(to_far * i_hi));
            }
            let far = far * FAR_SCALE;
            let hit = near.cmple(far) & near.cmplt(Vec4::splat(limit));
            near_out[half * 4..half * 4 + 4].copy_from_slice(&near.to_array());
            mask |= hit.bitmask() << (half * 4);
        }
        (near_out, mask)
    }
}
