//! The packet walk: one top-level walk for up to [`PACKET`] camera rays, each node's
//! box test done once for the packet (its [`PacketBound`]), each ray's own slab test at
//! the leaves.

use super::traverse::{Stack, insert_farthest_first};
use super::{Bvh, FAR_SCALE, NodeRay, PACKET, PacketBound, WIDTH, WideNode, entry_limit};
use crate::accel::kernel::{NodeKernel, prefetch_children, prefetch_node};
use crate::util::math::Ray;
use crate::util::stats::TraversalStats;
use glam::Vec4;

/// The packet's rays in structure-of-arrays form, four lanes at a time.
#[derive(Clone, Copy, Debug)]
struct PacketLanes {
    origin: [[Vec4; PACKET / 4]; 3],
    inv_dir: [[Vec4; PACKET / 4]; 3],
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
    /// [`traverse_closest_packet`](Self::traverse_closest_packet) with the packet box
    /// tests of `kernel`.
    #[inline(always)]
    pub(crate) fn traverse_closest_packet_with(
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
