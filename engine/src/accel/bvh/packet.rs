//! One closest-hit walk for a packet of up to [`PACKET`] coherent rays (a camera's
//! neighbouring pixels): every node is tested once for the whole packet, with
//! interval arithmetic over the rays' origins and reciprocal directions, and each ray
//! gets its own box test only at the leaves, so it enters just the leaves a walk of its
//! own would enter. Rays from one origin (a pinhole camera's) get a cheaper bound. The
//! top level hands the rays that enter an instance together to its bottom level as a
//! packet again, when they are narrow enough there.

use super::simd::{NodeKernel, prefetch_children, prefetch_node, with_node_kernel};
use super::traverse::{FAR_SCALE, NodeRay, Stack, entry_limit, insert_farthest_first};
use super::{Bvh, TraversalStats, WIDTH, WideNode};
use crate::util::math::Ray;
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
    pub(super) origin_lo: [f32; 3],
    origin_hi: [f32; 3],
    pub(super) inv_lo: [f32; 3],
    pub(super) inv_hi: [f32; 3],
    /// All rays start at the same point (a pinhole camera's): each plane's distance
    /// from it is one value, and only the reciprocals' interval remains.
    pub(super) common_origin: bool,
    /// Per axis, whether the rays meet a box's upper plane first (all alike).
    pub(super) near_is_max: [bool; 3],
}

/// The packet's rays in structure-of-arrays form, four lanes at a time.
#[derive(Clone, Copy, Debug)]
struct PacketLanes {
    origin: [[Vec4; PACKET / 4]; 3],
    inv_dir: [[Vec4; PACKET / 4]; 3],
}

impl PacketBound {
    /// The bound of `rays`, or `None` when some ray has an open slab (an axis-parallel
    /// or non-finite ray) or the rays' directions differ in sign on some axis.
    pub(super) fn new(rays: &[NodeRay]) -> Option<Self> {
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
    pub(super) fn hit_children(&self, node: &WideNode, limit: f32) -> ([f32; WIDTH], u32) {
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

impl PacketLanes {
    fn new(rays: &[NodeRay]) -> Self {
        let mut origin = [[0.0f32; PACKET]; 3];
        // Rays past the packet's end get a NaN reciprocal: their tests never pass.
        let mut inv_dir = [[f32::NAN; PACKET]; 3];
        for (i, ray) in rays.iter().enumerate() {
            for axis in 0..3 {
                origin[axis][i] = ray.origin[axis];
                inv_dir[axis][i] = ray.inv_dir[axis];
            }
        }
        let chunks = |values: &[f32; PACKET]| {
            std::array::from_fn(|chunk| Vec4::from_slice(&values[chunk * 4..chunk * 4 + 4]))
        };
        Self {
            origin: origin.each_ref().map(chunks),
            inv_dir: inv_dir.each_ref().map(chunks),
        }
    }

    /// Bit `i` set when ray `i` enters lane `lane` of `node` before its own limit
    /// `limits[i]` (four rays to an entry, for as many rays as `limits` covers): each
    /// ray's slab test with the same operations as its own walk's.
    #[inline(always)]
    fn hit_lane(&self, node: &WideNode, lane: usize, limits: &[Vec4]) -> u32 {
        let planes = [
            (node.min_x[lane], node.max_x[lane]),
            (node.min_y[lane], node.max_y[lane]),
            (node.min_z[lane], node.max_z[lane]),
        ];
        let mut mask = 0;
        for (chunk, &limit) in limits.iter().enumerate() {
            let slab = |axis: usize| {
                let (lower, upper) = planes[axis];
                let o = self.origin[axis][chunk];
                let inv = self.inv_dir[axis][chunk];
                (
                    (Vec4::splat(lower) - o) * inv,
                    (Vec4::splat(upper) - o) * inv,
                )
            };
            let (x0, x1) = slab(0);
            let (y0, y1) = slab(1);
            let (z0, z1) = slab(2);
            let t_near = x0.min(x1).max(y0.min(y1)).max(z0.min(z1).max(Vec4::ZERO));
            let t_far = x0.max(x1).min(y0.max(y1)).min(z0.max(z1)) * FAR_SCALE;
            let hit = t_near.cmple(t_far) & t_near.cmplt(limit);
            mask |= hit.bitmask() << (chunk * 4);
        }
        mask
    }
}

/// A pending subtree of the packet walk: an interior node, or a leaf lane of a node.
#[derive(Clone, Copy, Debug, Default)]
struct PacketPending {
    node: u32,
    /// The leaf's lane in `node`, or [`INTERIOR`] for `node` itself.
    lane: u32,
    t: f32,
}

const INTERIOR: u32 = u32::MAX;

impl Bvh {
    /// Closest hits for the packet `rays` (at most [`PACKET`]): `visit(first, count,
    /// rays_in, entry_t, t_max)` tests the leaf over slots `first .. first + count` for
    /// the rays whose bits are set in `rays_in` (bit `i` for `rays[i]`), each as its own
    /// walk would test the leaf, lowering `t_max[i]` to the distance of a closer accepted
    /// hit; `entry_t` is at most any of those rays' entry distance into the leaf's box.
    /// Each ray reaches the leaves its own walk would (and possibly more, never fewer).
    /// `prefetch(slot)` asks for the memory `visit` will read for a leaf starting at
    /// `slot` when that leaf is put off behind a nearer child. Returns the rays' final
    /// `t_max`, or `None` when the packet cannot be bounded (rays parallel to an axis,
    /// non-finite, or with direction signs that differ): then nothing was tested.
    #[inline]
    pub fn traverse_closest_packet(
        &self,
        rays: &[Ray],
        stats: &mut TraversalStats,
        visit: impl FnMut(usize, usize, u32, f32, &mut [f32; PACKET]),
        prefetch: impl Fn(usize),
    ) -> Option<[f32; PACKET]> {
        with_node_kernel!(kernel => kernel.traverse_packet(self, rays, stats, visit, prefetch))
    }

    /// [`traverse_closest_packet`](Self::traverse_closest_packet) with the packet box
    /// tests of `kernel`.
    #[inline(always)]
    pub(super) fn traverse_closest_packet_with(
        &self,
        kernel: impl NodeKernel,
        rays: &[Ray],
        stats: &mut TraversalStats,
        mut visit: impl FnMut(usize, usize, u32, f32, &mut [f32; PACKET]),
        prefetch: impl Fn(usize),
    ) -> Option<[f32; PACKET]> {
        let rays = &rays[..rays.len().min(PACKET)];
        let first = rays.first()?;
        let node_rays: [NodeRay; PACKET] =
            std::array::from_fn(|i| NodeRay::new(rays.get(i).unwrap_or(first)));
        let node_rays = &node_rays[..rays.len()];
        let bound = PacketBound::new(node_rays)?;
        let lanes = PacketLanes::new(node_rays);
        let mut t_max = [f32::NEG_INFINITY; PACKET];
        for (t, ray) in t_max.iter_mut().zip(rays) {
            *t = ray.t_max;
        }
        if self.wide.is_empty() {
            return Some(t_max);
        }
        // The per-ray limits as a ray's own walk computes them.
        let limits_of = |t_max: &[f32; PACKET]| -> [Vec4; PACKET / 4] {
            std::array::from_fn(|chunk| {
                Vec4::from_array(std::array::from_fn(|i| entry_limit(t_max[chunk * 4 + i])))
            })
        };
        let mut limits = limits_of(&t_max);
        let chunks = rays.len().div_ceil(4);
        let packet_limit = |limits: &[Vec4; PACKET / 4]| {
            limits
                .iter()
                .fold(f32::NEG_INFINITY, |m, l| m.max(l.max_element()))
        };
        let mut limit = packet_limit(&limits);
        let (mut nodes, mut primitives) = (0u64, 0u64);
        let mut stack = Stack::<PacketPending>::new();
        let mut current = Some(PacketPending {
            node: 0,
            lane: INTERIOR,
            t: 0.0,
        });
        loop {
            let entry = match current.take() {
                Some(entry) => entry,
                None => loop {
                    match stack.pop() {
                        Some(entry) if entry.t < limit => break entry,
                        Some(_) => {}
                        None => {
                            stats.nodes_visited += nodes;
                            stats.primitive_tests += primitives;
                            return Some(t_max);
                        }
                    }
                },
            };
            let node = &self.wide[entry.node as usize];
            if entry.lane != INTERIOR {
                let lane = entry.lane as usize;
                let rays_in = lanes.hit_lane(node, lane, &limits[..chunks]);
                if rays_in != 0 {
                    let (first, count) = (node.children[lane] as usize, node.counts[lane]);
                    primitives += u64::from(rays_in.count_ones() * count);
                    visit(first, count as usize, rays_in, entry.t, &mut t_max);
                    limits = limits_of(&t_max);
                    limit = packet_limit(&limits);
                }
                continue;
            }
            nodes += 1;
            prefetch_children(node);
            let (t, mut mask) = kernel.packet_hit_children(&bound, node, limit);
            // Nearest first: sorted by entry distance, farthest at the front.
            let mut hits = [entry; WIDTH];
            let mut n = 0;
            while mask != 0 {
                let lane = mask.trailing_zeros() as usize;
                mask &= mask - 1;
                let child = if node.counts[lane] > 0 {
                    PacketPending {
                        node: entry.node,
                        lane: lane as u32,
                        t: t[lane],
                    }
                } else {
                    PacketPending {
                        node: node.children[lane],
                        lane: INTERIOR,
                        t: t[lane],
                    }
                };
                insert_farthest_first(&mut hits, n, child, |e| e.t);
                n += 1;
            }
            if n > 0 {
                for &entry in &hits[..n - 1] {
                    // Node loads that miss the cache are what a walk waits on most.
                    if entry.lane == INTERIOR {
                        prefetch_node(&self.wide[entry.node as usize]);
                    } else {
                        prefetch(node.children[entry.lane as usize] as usize);
                    }
                    stack.push(entry);
                }
                current = Some(hits[n - 1]);
            }
        }
    }
}
