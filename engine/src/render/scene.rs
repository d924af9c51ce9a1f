//! The scene as the kernel sees it ([`RenderScene`]: borrowed flat data, nothing of
//! entities) and its ray queries: closest hit and occlusion, for single rays and camera
//! packets, with the alpha test run in place by the hit filters and adaptive
//! transparency's holes turned opaque.

use crate::accel::bvh::PACKET;
use crate::accel::geometry::GeometryLibrary;
use crate::accel::kernel::{NodeKernel, with_node_kernel};
use crate::accel::occluders::OccluderCache;
use crate::accel::tlas::{Candidate, Hit, InstanceTriangle, TopLevel};
use crate::light::LightSet;
use crate::material::opacity::{Opacity, OpacityMaps};
use crate::material::shading::{Shader, ShaderTable};
use crate::material::transparency::{
    COUNTED_HOLES, CandidateHoles, CountedHoles, TransparencyCurve, first_opaque_hole,
};
use crate::util::math::Ray;
use crate::util::stats::TraversalStats;
use glam::{Vec2, Vec3A};

/// Borrowed flat data the kernel reads: nothing here knows about entities.
#[derive(Clone, Copy)]
pub struct RenderScene<'a> {
    /// Meshes and their BLASes.
    pub geometry: &'a GeometryLibrary,
    /// The TLAS.
    pub top_level: &'a TopLevel,
    /// Shaders by id.
    pub shaders: &'a ShaderTable,
    /// Where alpha masks are decided without their texture ([`OpacityMaps::default`]:
    /// nowhere, every alpha test samples the texture).
    pub opacity: &'a OpacityMaps,
    /// Lights.
    pub lights: &'a LightSet,
}

/// The flat render data owned: what a [`RenderScene`] borrows, for a program, bench or
/// test that builds its scene outside a `World` (the schedule keeps the same five as
/// resources).
#[derive(Clone, Debug, Default)]
pub struct RenderData {
    /// Meshes and their BLASes.
    pub library: GeometryLibrary,
    /// The TLAS over the instances.
    pub top_level: TopLevel,
    /// Shaders by id.
    pub shaders: ShaderTable,
    /// Lights.
    pub lights: LightSet,
    /// Opacity micromaps ([`OpacityMaps::default`]: none, every alpha test samples the
    /// texture).
    pub opacity: OpacityMaps,
}

impl RenderData {
    /// The kernel's view of this data.
    pub fn scene(&self) -> RenderScene<'_> {
        RenderScene {
            geometry: &self.library,
            top_level: &self.top_level,
            shaders: &self.shaders,
            lights: &self.lights,
            opacity: &self.opacity,
        }
    }
}

/// What the hit filter made of a candidate.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum FilterOutcome {
    /// A surface the ray stops at.
    Opaque,
    /// An alpha hole: a transparency segment.
    Hole,
    /// The back of a single-sided surface.
    Culled,
}

impl<'a> RenderScene<'a> {
    #[inline]
    fn shader_of(&self, candidate: &Candidate) -> &'a Shader {
        let mesh = &self.geometry.geometries[candidate.geometry.0 as usize].mesh;
        self.shaders.get(mesh.shaders[candidate.triangle as usize])
    }

    #[inline]
    pub(super) fn uv_of(&self, candidate: &Candidate) -> Vec2 {
        let mesh = &self.geometry.geometries[candidate.geometry.0 as usize].mesh;
        mesh.uv_at(candidate.triangle as usize, candidate.barycentrics)
    }

    /// The hit filter run inside traversal: a hole where the shader's alpha mask has
    /// one, culled where a single-sided surface is seen from behind.
    #[inline]
    fn filter(
        &self,
        candidate: &Candidate,
        direction: Vec3A,
        stats: &mut TraversalStats,
    ) -> FilterOutcome {
        let (geometry, triangle, b) = (
            candidate.geometry,
            candidate.triangle,
            candidate.barycentrics,
        );
        // Most leaf hits are decided by the opacity map alone, without the shader's
        // cache miss.
        let decided = match self.opacity.at(geometry, triangle, b) {
            Opacity::Opaque => Some(FilterOutcome::Opaque),
            Opacity::Hole => Some(FilterOutcome::Hole),
            Opacity::Mixed => None,
        };
        if let Some(outcome) = decided {
            stats.filter_tests += 1;
            stats.filter_rejections += u64::from(outcome != FilterOutcome::Opaque);
            return outcome;
        }
        let shader = self.shader_of(candidate);
        if !shader.needs_hit_filter() {
            return FilterOutcome::Opaque;
        }
        stats.filter_tests += 1;
        let outcome = if !(shader.double_sided || self.is_front_side(candidate, direction)) {
            FilterOutcome::Culled
        } else {
            // A double-sided triangle's map has answered above (mixed, or no map).
            let known = if shader.double_sided {
                Opacity::Mixed
            } else {
                self.opacity.alpha_at(geometry, triangle, b)
            };
            match known {
                Opacity::Opaque => FilterOutcome::Opaque,
                Opacity::Hole => FilterOutcome::Hole,
                Opacity::Mixed => {
                    stats.texture_alpha_tests += 1;
                    if shader.is_opaque_at(self.uv_of(candidate)) {
                        FilterOutcome::Opaque
                    } else {
                        FilterOutcome::Hole
                    }
                }
            }
        };
        stats.filter_rejections += u64::from(outcome != FilterOutcome::Opaque);
        outcome
    }

    /// True when `direction` arrives at the candidate triangle's front: the side its
    /// object-space winding normal points to. Testing in object space makes a mirroring
    /// instance flip the winding, as glTF requires of negative determinants.
    #[inline]
    fn is_front_side(&self, candidate: &Candidate, direction: Vec3A) -> bool {
        let record = self.top_level.record(candidate.slot as usize);
        let mesh = &self.geometry.geometries[candidate.geometry.0 as usize].mesh;
        let [p0, p1, p2] = mesh.triangle(candidate.triangle as usize);
        let normal = (p1 - p0).cross(p2 - p0);
        normal.dot(record.world_to_object().transform_vector3a(direction)) < 0.0
    }

    /// The closest hit along `ray` that the hit filter accepts.
    #[inline]
    pub fn closest(&self, ray: &Ray, stats: &mut TraversalStats) -> Option<Hit> {
        self.closest_adaptive(ray, None, stats).map(|(hit, _)| hit)
    }

    /// The closest hit along `ray` (unit direction, so `t` is the camera distance) under
    /// adaptive transparency: the first hole, nearest first, whose index `i` reaches the
    /// curve's allowance at its distance is an opaque hit (flagged `true`). With
    /// `curve = None` it is [`closest`](Self::closest).
    pub fn closest_adaptive(
        &self,
        ray: &Ray,
        curve: Option<&TransparencyCurve>,
        stats: &mut TraversalStats,
    ) -> Option<(Hit, bool)> {
        with_node_kernel!(kernel => self.closest_adaptive_with(kernel, ray, None, curve, stats))
    }

    /// The closest hit of a ray leaving the surface triangle `leaving` (which it cannot
    /// hit again, so it is not tested), passing alpha holes exactly.
    #[inline]
    pub(super) fn closest_leaving(
        &self,
        ray: &Ray,
        leaving: InstanceTriangle,
        stats: &mut TraversalStats,
    ) -> Option<Hit> {
        with_node_kernel!(
            kernel => self.closest_adaptive_with(kernel, ray, Some(leaving), None, stats)
        )
        .map(|(hit, _)| hit)
    }

    #[inline(always)]
    fn closest_adaptive_with(
        &self,
        kernel: impl NodeKernel,
        ray: &Ray,
        leaving: Option<InstanceTriangle>,
        curve: Option<&TransparencyCurve>,
        stats: &mut TraversalStats,
    ) -> Option<(Hit, bool)> {
        if !self.shaders.needs_hit_filter() {
            return self
                .top_level
                .intersect_closest_with(kernel, self.geometry, ray, leaving, stats, |_| true)
                .map(|hit| (hit, false));
        }
        let mut filter = TraversalStats::default();
        let result = match curve {
            None => {
                let mut holes = CountedHoles::new(COUNTED_HOLES);
                let hit = self.top_level.intersect_closest_with(
                    kernel,
                    self.geometry,
                    ray,
                    leaving,
                    stats,
                    |c| match self.filter(c, ray.direction, &mut filter) {
                        FilterOutcome::Opaque => true,
                        FilterOutcome::Hole => {
                            holes.insert(c.t, ());
                            false
                        }
                        FilterOutcome::Culled => false,
                    },
                );
                let t_hit = hit.map_or(f32::INFINITY, |h| h.t);
                filter.holes_passed = holes.count_before(t_hit) as u64;
                hit.map(|hit| (hit, false))
            }
            Some(curve) => {
                let mut holes = CandidateHoles::new(curve.max_allowance() as usize + 1);
                let mut last_accepted_hole = false;
                let hit = self.top_level.intersect_closest_with(
                    kernel,
                    self.geometry,
                    ray,
                    leaving,
                    stats,
                    |c| {
                        let outcome = self.filter(c, ray.direction, &mut filter);
                        let accept = match outcome {
                            FilterOutcome::Opaque => true,
                            FilterOutcome::Culled => false,
                            FilterOutcome::Hole => {
                                // Enough nearer holes seen already: this one is beyond the
                                // allowance whatever else turns up, so it may end the
                                // search early; the walk below picks the first such hole.
                                let beyond =
                                    holes.count_before(c.t) >= curve.allowance(c.t) as usize;
                                holes.insert(c.t, *c);
                                beyond
                            }
                        };
                        // Each accepted candidate becomes the closest so far.
                        if accept {
                            last_accepted_hole = outcome == FilterOutcome::Hole;
                        }
                        accept
                    },
                );
                adaptive_result(curve, &mut holes, hit, last_accepted_hole, &mut filter)
            }
        };
        filter.closest_filter_rejections = filter.filter_rejections;
        stats.add(&filter);
        result
    }

    /// True when a hit the filter accepts lies before `ray.t_max`.
    #[inline]
    pub fn occluded(&self, ray: &Ray, stats: &mut TraversalStats) -> bool {
        self.occluded_within(ray, None, stats)
    }

    /// [`occluded`](Self::occluded) where a ray may pass at most `allowance` holes: one
    /// more counts as opaque (adaptive transparency for shadow rays).
    #[inline]
    pub fn occluded_within(
        &self,
        ray: &Ray,
        allowance: Option<u32>,
        stats: &mut TraversalStats,
    ) -> bool {
        self.occluded_leaving(ray, None, allowance, None, stats)
    }

    /// [`occluded_within`](Self::occluded_within) for a ray that starts on the triangle
    /// `leaving`, which it cannot hit again: its test is left out. With `occluders`, the
    /// blocks that stopped recent shadow rays are tried first, and a walk that stops on
    /// an opaque hit adds its block to them (the answer is the same either way).
    #[inline]
    pub fn occluded_leaving(
        &self,
        ray: &Ray,
        leaving: Option<InstanceTriangle>,
        allowance: Option<u32>,
        occluders: Option<&mut OccluderCache>,
        stats: &mut TraversalStats,
    ) -> bool {
        with_node_kernel!(
            kernel => self.occluded_leaving_with(kernel, ray, leaving, allowance, occluders, stats)
        )
    }

    #[inline(always)]
    fn occluded_leaving_with(
        &self,
        kernel: impl NodeKernel,
        ray: &Ray,
        leaving: Option<InstanceTriangle>,
        allowance: Option<u32>,
        mut occluders: Option<&mut OccluderCache>,
        stats: &mut TraversalStats,
    ) -> bool {
        let filtered = self.shaders.needs_hit_filter();
        let mut filter = TraversalStats::default();
        if let Some(cache) = occluders.as_deref_mut()
            && cache.stops(kernel, ray, leaving, |c| {
                !filtered || self.filter(c, ray.direction, &mut filter) == FilterOutcome::Opaque
            })
        {
            stats.any_rays += 1;
            stats.cached_occlusions += 1;
            stats.add(&filter);
            return true;
        }
        let mut holes = CountedHoles::new(allowance.map_or(0, |a| a as usize + 1));
        let mut stopped_on_opaque = false;
        let occluder =
            self.top_level
                .occluder_with(kernel, self.geometry, ray, leaving, stats, |c| {
                    if !filtered {
                        stopped_on_opaque = true;
                        return true;
                    }
                    match self.filter(c, ray.direction, &mut filter) {
                        FilterOutcome::Opaque => {
                            stopped_on_opaque = true;
                            true
                        }
                        FilterOutcome::Culled => false,
                        FilterOutcome::Hole => {
                            let Some(allowance) = allowance else {
                                return false;
                            };
                            holes.insert(c.t, ());
                            let beyond = holes.len() > allowance as usize;
                            filter.opaque_holes += u64::from(beyond);
                            beyond
                        }
                    }
                });
        stats.add(&filter);
        // A hole that only the allowance made opaque would stop few other rays.
        if let (Some(cache), Some(occluder), true) = (occluders, occluder, stopped_on_opaque) {
            cache.remember(self.top_level, self.geometry, occluder);
        }
        occluder.is_some()
    }

    /// The closest hits of a packet of up to [`PACKET`] camera rays, as
    /// [`closest_adaptive`](Self::closest_adaptive) finds them one by one, from one
    /// top-level walk; `None` when one packet cannot bound the rays (see
    /// [`Bvh::traverse_closest_packet`](crate::accel::bvh::Bvh::traverse_closest_packet)):
    /// then they go one by one.
    pub fn closest_packet(
        &self,
        rays: &[Ray],
        curve: Option<&TransparencyCurve>,
        scratch: &mut PacketScratch,
        stats: &mut TraversalStats,
    ) -> Option<[Option<(Hit, bool)>; PACKET]> {
        with_node_kernel!(
            kernel => self.closest_packet_with(kernel, rays, curve, scratch, stats)
        )
    }

    #[inline(always)]
    fn closest_packet_with(
        &self,
        kernel: impl NodeKernel,
        rays: &[Ray],
        curve: Option<&TransparencyCurve>,
        scratch: &mut PacketScratch,
        stats: &mut TraversalStats,
    ) -> Option<[Option<(Hit, bool)>; PACKET]> {
        let opaque = |hits: [Option<Hit>; PACKET]| hits.map(|hit| hit.map(|hit| (hit, false)));
        if !self.shaders.needs_hit_filter() {
            return self
                .top_level
                .intersect_closest_packet_with(kernel, self.geometry, rays, stats, |_, _| true)
                .map(opaque);
        }
        if let Some(curve) = curve {
            return self.closest_packet_adaptive(kernel, rays, curve, scratch, stats);
        }
        let mut filter = TraversalStats::default();
        let holes = &mut scratch.counted;
        holes.resize_with(PACKET, || CountedHoles::new(COUNTED_HOLES));
        holes.iter_mut().for_each(|h| h.reset(COUNTED_HOLES));
        let hits = self.top_level.intersect_closest_packet_with(
            kernel,
            self.geometry,
            rays,
            stats,
            |ray, c| match self.filter(c, rays[ray].direction, &mut filter) {
                FilterOutcome::Opaque => true,
                FilterOutcome::Hole => {
                    holes[ray].insert(c.t, ());
                    false
                }
                FilterOutcome::Culled => false,
            },
        )?;
        filter.holes_passed = hits
            .iter()
            .zip(holes.iter())
            .map(|(hit, holes)| holes.count_before(hit.map_or(f32::INFINITY, |h| h.t)) as u64)
            .sum();
        filter.closest_filter_rejections = filter.filter_rejections;
        stats.add(&filter);
        Some(opaque(hits))
    }

    /// [`closest_packet`](Self::closest_packet) with adaptive transparency: each ray's
    /// holes judged as [`closest_adaptive`](Self::closest_adaptive) judges them.
    #[inline(always)]
    fn closest_packet_adaptive(
        &self,
        kernel: impl NodeKernel,
        rays: &[Ray],
        curve: &TransparencyCurve,
        scratch: &mut PacketScratch,
        stats: &mut TraversalStats,
    ) -> Option<[Option<(Hit, bool)>; PACKET]> {
        let mut filter = TraversalStats::default();
        let capacity = curve.max_allowance() as usize + 1;
        let holes = &mut scratch.candidates;
        holes.resize_with(PACKET, || CandidateHoles::new(capacity));
        holes.iter_mut().for_each(|h| h.reset(capacity));
        let mut last_accepted_hole = [false; PACKET];
        let hits = self.top_level.intersect_closest_packet_with(
            kernel,
            self.geometry,
            rays,
            stats,
            |ray, c| {
                let outcome = self.filter(c, rays[ray].direction, &mut filter);
                let accept = match outcome {
                    FilterOutcome::Opaque => true,
                    FilterOutcome::Culled => false,
                    FilterOutcome::Hole => {
                        let beyond = holes[ray].count_before(c.t) >= curve.allowance(c.t) as usize;
                        holes[ray].insert(c.t, *c);
                        beyond
                    }
                };
                if accept {
                    last_accepted_hole[ray] = outcome == FilterOutcome::Hole;
                }
                accept
            },
        )?;
        let mut results = [None; PACKET];
        for (ray, result) in results.iter_mut().enumerate().take(rays.len()) {
            let (hit, last) = (hits[ray], last_accepted_hole[ray]);
            *result = adaptive_result(curve, &mut holes[ray], hit, last, &mut filter);
        }
        filter.closest_filter_rejections = filter.filter_rejections;
        stats.add(&filter);
        Some(results)
    }
}

/// A closest-hit query's answer under adaptive transparency, from the hit the walk
/// accepted (`last_accepted_hole`: it was a hole taken as opaque) and the holes it kept:
/// the nearest hole the curve turns opaque, if one lies before that hit. Adds the holes
/// passed and the holes made opaque to `filter`.
fn adaptive_result(
    curve: &TransparencyCurve,
    holes: &mut CandidateHoles,
    hit: Option<Hit>,
    last_accepted_hole: bool,
    filter: &mut TraversalStats,
) -> Option<(Hit, bool)> {
    let nearer = holes.sorted_before(hit.map_or(f32::INFINITY, |h| h.t));
    if let Some(&(_, hole)) = first_opaque_hole(curve, nearer) {
        filter.holes_passed += nearer.iter().take_while(|h| h.0 < hole.t).count() as u64;
        filter.opaque_holes += 1;
        Some((hole, true))
    } else {
        filter.holes_passed += nearer.len() as u64;
        filter.opaque_holes += u64::from(hit.is_some() && last_accepted_hole);
        hit.map(|hit| (hit, last_accepted_hole))
    }
}

/// The per-ray hole lists a packet of camera rays fills, kept from packet to packet (an
/// array of them built for every packet cost more in copies than the walk it shared).
#[derive(Debug, Default)]
pub struct PacketScratch {
    counted: Vec<CountedHoles>,
    candidates: Vec<CandidateHoles>,
}
