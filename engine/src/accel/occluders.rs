//! Recent occluders of one tile's shadow rays: the triangle blocks where earlier shadow
//! rays' walks stopped, tested before the next shadow ray walks the scene.
//!
//! Neighbouring shading points send their shadow rays toward the same lights (most of
//! the sky's light comes from the sun's disc), so a leaf that stopped one ray often stops
//! the next. A cached block is tested exactly as the walk tests it: the same object-space
//! ray (the instance's `world_to_object` applied to the world ray, `t_max` unchanged), the
//! same watertight set-up and the same kernel, so its hits are the walk's bit for bit.
//! Box tests are conservative, so the walk reaches every block that a ray hits. A hit
//! that the hit filter finds opaque therefore makes the ray occluded whatever else the
//! walk would meet: holes counted against an allowance can only add occlusion, never
//! remove it. The cache changes the work and the counters, never a shadow ray's answer.
//!
//! The cache belongs to one tile's render and starts empty there, so its counters do
//! not depend on which thread rendered which tile before.

use crate::accel::bvh::{NodeRay, WIDTH, WideNode};
use crate::accel::geometry::{GeometryId, GeometryLibrary};
use crate::accel::kernel::NodeKernel;
use crate::accel::tlas::{Candidate, InstanceTriangle, Occluder, TopLevel};
use crate::accel::triangle::{TriangleBlock, WatertightRay};
use crate::util::math::Ray;
use glam::{Affine3A, Vec3A};

/// Credit a probe that stops its ray earns. A probe that does not costs one, and
/// without credit only every [`PROBE_EVERY_WITHOUT_CREDIT`]-th ray is probed: where
/// occluders rarely repeat (fine geometry, far from the camera) the probes' cost would
/// exceed the walks they save.
const CREDIT_PER_STOP: i32 = 6;

/// Most credit held: a run of stops is forgotten after this many misses.
const MAX_CREDIT: i32 = 64;

/// How often a cache without credit is still probed, to notice when occluders start to
/// repeat again.
const PROBE_EVERY_WITHOUT_CREDIT: u32 = 16;

/// A cached occluding block with what its test and its hit filter need.
#[derive(Clone, Copy, Debug)]
struct CachedBlock {
    slot: u32,
    instance: u32,
    geometry: GeometryId,
    world_to_object: Affine3A,
    block: TriangleBlock,
    lanes: usize,
}

/// The last [`WIDTH`] occluding blocks of a tile's shadow rays, their world boxes in
/// one wide node's lanes so a single box test picks the blocks worth testing.
#[derive(Clone, Debug)]
pub struct OccluderCache {
    /// Lane `i`: the world box of `entries[i]` (widened a little; an unused lane is
    /// empty).
    boxes: WideNode,
    entries: [Option<CachedBlock>; WIDTH],
    /// The lane the next remembered block replaces.
    next: usize,
    credit: i32,
    rays_without_credit: u32,
    /// Whether the last ray was probed: only then is its occluder remembered, so a
    /// cache without credit costs next to nothing.
    probed: bool,
}

impl Default for OccluderCache {
    fn default() -> Self {
        Self::new()
    }
}

impl OccluderCache {
    /// An empty cache, with the credit to probe its first rays.
    pub fn new() -> Self {
        Self {
            boxes: WideNode::empty(),
            entries: [None; WIDTH],
            next: 0,
            credit: MAX_CREDIT,
            rays_without_credit: 0,
            probed: false,
        }
    }

    /// True when a cached block has a hit before `ray.t_max` that `opaque` accepts (a
    /// hit on the triangle `leaving` is skipped, as the walk skips it). False says
    /// nothing: the ray must still be walked.
    #[inline]
    pub fn stops(
        &mut self,
        kernel: impl NodeKernel,
        ray: &Ray,
        leaving: Option<InstanceTriangle>,
        mut opaque: impl FnMut(&Candidate) -> bool,
    ) -> bool {
        if self.credit <= 0 {
            self.rays_without_credit += 1;
            if !self
                .rays_without_credit
                .is_multiple_of(PROBE_EVERY_WITHOUT_CREDIT)
            {
                self.probed = false;
                return false;
            }
        }
        self.probed = true;
        let (_, mut lanes) = NodeRay::new(ray).hit_children_with(kernel, &self.boxes, ray.t_max);
        while lanes != 0 {
            let lane = lanes.trailing_zeros() as usize;
            lanes &= lanes - 1;
            let Some(cached) = &self.entries[lane] else {
                continue;
            };
            let local = ray.transformed(&cached.world_to_object);
            let hits = kernel.block_hits(
                &WatertightRay::new(&local),
                &cached.block,
                cached.lanes,
                local.t_max,
            );
            let mut hit_lanes = hits.mask;
            while hit_lanes != 0 {
                let hit_lane = hit_lanes.trailing_zeros() as usize;
                hit_lanes &= hit_lanes - 1;
                let triangle = cached.block.triangles[hit_lane & 3];
                if leaving
                    == Some(InstanceTriangle {
                        slot: cached.slot,
                        triangle,
                    })
                {
                    continue;
                }
                let hit = hits.hit(hit_lane);
                let candidate = Candidate {
                    slot: cached.slot,
                    instance: cached.instance,
                    geometry: cached.geometry,
                    triangle,
                    barycentrics: hit.barycentrics,
                    t: hit.t,
                };
                if opaque(&candidate) {
                    self.credit = (self.credit + CREDIT_PER_STOP).min(MAX_CREDIT);
                    return true;
                }
            }
        }
        self.credit -= 1;
        false
    }

    /// Keeps the block where a shadow ray's walk stopped, in place of the oldest one,
    /// when that ray was probed ([`stops`](Self::stops) was asked first).
    pub fn remember(
        &mut self,
        top_level: &TopLevel,
        library: &GeometryLibrary,
        occluder: Occluder,
    ) {
        if !self.probed {
            return;
        }
        let Some(record) = top_level.instances.get(occluder.slot as usize) else {
            return;
        };
        let Some(block) = library
            .get(record.geometry)
            .and_then(|geometry| geometry.block(occluder.block))
        else {
            return;
        };
        let lanes = (occluder.block.lanes as usize).clamp(1, 4);
        let object_to_world = record.object_to_world();
        let (mut low, mut high) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
        for lane in 0..lanes {
            for corner in block.triangle(lane) {
                let world = object_to_world.transform_point3a(corner);
                low = low.min(world);
                high = high.max(world);
            }
        }
        if !(low.is_finite() && high.is_finite()) {
            return;
        }
        // The box only picks which blocks to test: a box too small costs a missed
        // chance, never a wrong answer. The margin covers the transform's rounding.
        let margin = (high - low) * 1e-3 + low.abs().max(high.abs()) * 1e-6;
        let (low, high) = (low - margin, high + margin);
        let lane = self.next;
        self.next = (lane + 1) % WIDTH;
        let boxes = &mut self.boxes;
        (boxes.min_x[lane], boxes.max_x[lane]) = (low.x, high.x);
        (boxes.min_y[lane], boxes.max_y[lane]) = (low.y, high.y);
        (boxes.min_z[lane], boxes.max_z[lane]) = (low.z, high.z);
        self.entries[lane] = Some(CachedBlock {
            slot: occluder.slot,
            instance: record.id,
            geometry: record.geometry,
            world_to_object: record.world_to_object(),
            block: *block,
            lanes,
        });
    }
}
