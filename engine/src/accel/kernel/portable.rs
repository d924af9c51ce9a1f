//! The kernel for any CPU: a node's eight box tests as two four-lane halves (SSE
//! through glam), the same operations in the same order as the AVX2 kernel.

use super::NodeKernel;
use crate::accel::bvh::{Bvh, FAR_SCALE, LeafVisit, NodeRay, PACKET, WIDTH, WideNode};
use crate::accel::triangle::{BlockHits, TriangleBlock, WatertightRay};
use crate::util::math::Ray;
use crate::util::stats::TraversalStats;
use glam::{BVec4A, Vec4};

/// The kernel for any CPU: two four-lane halves.
#[derive(Clone, Copy, Debug)]
pub struct Portable;

impl NodeKernel for Portable {
    #[inline(always)]
    fn traverse(
        self,
        bvh: &Bvh,
        ray: &Ray,
        stats: &mut TraversalStats,
        leaves: &mut impl LeafVisit,
    ) {
        bvh.traverse_with(self, ray, stats, leaves)
    }

    #[inline(always)]
    fn traverse_packet(
        self,
        bvh: &Bvh,
        rays: &[Ray],
        stats: &mut TraversalStats,
        visit: impl FnMut(usize, usize, u32, f32, &mut [f32; PACKET]),
        prefetch: impl Fn(usize),
    ) -> Option<[f32; PACKET]> {
        bvh.traverse_closest_packet_with(self, rays, stats, visit, prefetch)
    }

    #[inline(always)]
    fn hit_children_spans(
        self,
        ray: &NodeRay,
        node: &WideNode,
        limit: f32,
    ) -> ([f32; WIDTH], [f32; WIDTH], u32) {
        let (mut t, mut span) = ([0.0; WIDTH], [0.0; WIDTH]);
        let mut mask = 0;
        for half in 0..WIDTH / 4 {
            let (lane_t, lane_span, lane_mask) = hit_half(ray, node, half * 4, limit);
            t[half * 4..half * 4 + 4].copy_from_slice(&lane_t.to_array());
            span[half * 4..half * 4 + 4].copy_from_slice(&lane_span.to_array());
            mask |= lane_mask << (half * 4);
        }
        (t, span, mask)
    }

    #[inline(always)]
    fn block_hits(
        self,
        ray: &WatertightRay,
        block: &TriangleBlock,
        lanes: usize,
        t_max: f32,
    ) -> BlockHits {
        ray.block_hits(block, lanes, t_max)
    }
}

/// Lanes `first .. first + 4` of the slab test, with the same bits as the AVX2 kernel:
/// the same operations in the same order, except that AVX2 reads each axis's near plane
/// by the direction's sign where that equals the min and max taken here.
#[inline(always)]
fn hit_half(ray: &NodeRay, node: &WideNode, first: usize, limit: f32) -> (Vec4, Vec4, u32) {
    let lanes = |a: &[f32; WIDTH]| Vec4::from_slice(&a[first..first + 4]);
    let [ox, oy, oz] = ray.origin.map(Vec4::splat);
    let [ix, iy, iz] = ray.inv_dir.map(Vec4::splat);
    let min_x = lanes(&node.min_x);
    let x0 = (min_x - ox) * ix;
    let x1 = (lanes(&node.max_x) - ox) * ix;
    let y0 = (lanes(&node.min_y) - oy) * iy;
    let y1 = (lanes(&node.max_y) - oy) * iy;
    let z0 = (lanes(&node.min_z) - oz) * iz;
    let z1 = (lanes(&node.max_z) - oz) * iz;
    let ([x0, x1, y0, y1, z0, z1], used) = if ray.axis_parallel {
        // 0 · ∞ is NaN where the origin lies on a face of a slab the ray runs parallel
        // to: that slab does not limit the ray (the face counts as inside, as the
        // watertight triangle test counts edges). A NaN reciprocal (a denormal direction
        // component) makes both distances NaN: the slab is open.
        let open = |a: Vec4, b: Vec4| {
            let a = Vec4::select(a.cmpeq(a), a, -b);
            let b = Vec4::select(b.cmpeq(b), b, -a);
            (
                Vec4::select(a.cmpeq(a), a, Vec4::NEG_INFINITY),
                Vec4::select(b.cmpeq(b), b, Vec4::INFINITY),
            )
        };
        let ((x0, x1), (y0, y1), (z0, z1)) = (open(x0, x1), open(y0, y1), open(z0, z1));
        // With every slab open an unused lane (its box at +∞) would pass and send
        // traversal back to the root forever (fuzz finding): mask unused lanes.
        ([x0, x1, y0, y1, z0, z1], min_x.cmplt(Vec4::INFINITY))
    } else {
        ([x0, x1, y0, y1, z0, z1], BVec4A::splat(true))
    };
    // Two levels of max, not three: this is the chain from a node's load to the next
    // node's address.
    let t_near = x0.min(x1).max(y0.min(y1)).max(z0.min(z1).max(Vec4::ZERO));
    let t_far = x0.max(x1).min(y0.max(y1)).min(z0.max(z1)) * FAR_SCALE;
    let hit = t_near.cmple(t_far) & t_near.cmplt(Vec4::splat(limit)) & used;
    (t_near, t_far - t_near, hit.bitmask())
}
