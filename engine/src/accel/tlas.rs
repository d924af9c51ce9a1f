//! The top-level BVH over instances. Each instance is a transform and a geometry id;
//! traversal moves the ray into the instance's object space and descends its BLAS.

use crate::accel::bvh::{BuildParams, BuildScratch, Bvh, PACKET, TraversalStats, mask_bits};
use crate::accel::geometry::{BlockRef, Geometry, GeometryId, GeometryLibrary};
use crate::accel::kernel::{NodeKernel, affine_from_columns, prefetch, with_node_kernel};
use crate::accel::triangle::TriangleHit;
use crate::util::math::{Aabb, Ray};
use glam::{Affine3A, Vec3A};
use rayon::prelude::*;

/// The widest a camera packet may be where it enters an instance, as a share of the
/// instance's diagonal, for its rays to walk the instance's bottom level together: a
/// packet's box test bounds every ray between its outermost ones, and over a plant
/// that is small on screen that region holds far more nodes than the rays' own paths
/// (`paper` interactive: +73 % instructions with every entry shared, −0.7 to +0.8 %
/// from 1/100 to 1/32; the anchor meadow's camera rays −6.2 % at 1/32).
const SHARED_WALK_WIDTH: f32 = 1.0 / 32.0;

/// An instance as the caller describes it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InstanceDesc {
    /// Object → world.
    pub transform: Affine3A,
    /// Which mesh.
    pub geometry: GeometryId,
}

/// An instance as traversal needs it, stored in TLAS slot order: 104 bytes, the two
/// transforms as packed columns (two `Affine3A`s made it 144: a build of 365 k instances
/// then wrote 15 MB more of fresh memory), what traversal reads at every entry first.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C)]
pub struct InstanceRecord {
    /// Which mesh.
    pub geometry: GeometryId,
    /// The caller's index of the instance (position in the slice given to `build`).
    pub id: u32,
    /// World → object, then object → world: twelve column values each.
    transforms: [f32; 24],
}

const _: () = assert!(std::mem::size_of::<InstanceRecord>() == 104);

impl InstanceRecord {
    /// The record of instance `id` of `geometry` placed by `object_to_world`, with its
    /// inverse `world_to_object`.
    pub fn new(
        object_to_world: &Affine3A,
        world_to_object: &Affine3A,
        geometry: GeometryId,
        id: u32,
    ) -> Self {
        let mut transforms = [0.0; 24];
        transforms[..12].copy_from_slice(&world_to_object.to_cols_array());
        transforms[12..].copy_from_slice(&object_to_world.to_cols_array());
        Self {
            geometry,
            id,
            transforms,
        }
    }

    /// World → object (the inverse of [`object_to_world`](Self::object_to_world)).
    #[inline(always)]
    pub fn world_to_object(&self) -> Affine3A {
        let (columns, _) = self
            .transforms
            .split_first_chunk::<13>()
            .expect("24 values");
        affine_from_columns(columns)
    }

    /// Object → world.
    #[inline(always)]
    pub fn object_to_world(&self) -> Affine3A {
        Affine3A::from_cols_slice(&self.transforms[12..])
    }
}

/// A candidate hit offered to a hit filter during traversal.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Candidate {
    /// TLAS slot of the instance (index into [`TopLevel::instances`]).
    pub slot: u32,
    /// Caller's instance index.
    pub instance: u32,
    /// Its geometry.
    pub geometry: GeometryId,
    /// Triangle index in that geometry's mesh.
    pub triangle: u32,
    /// Barycentric weights of the triangle's vertices.
    pub barycentrics: Vec3A,
    /// Ray parameter.
    pub t: f32,
}

impl Candidate {
    /// The hit `hit` on triangle `triangle` of the instance in TLAS slot `slot`.
    #[inline(always)]
    fn on(slot: usize, record: &InstanceRecord, triangle: u32, hit: &TriangleHit) -> Self {
        Self {
            slot: slot as u32,
            instance: record.id,
            geometry: record.geometry,
            triangle,
            barycentrics: hit.barycentrics,
            t: hit.t,
        }
    }
}

/// The closest accepted hit of a ray.
pub type Hit = Candidate;

/// One triangle of one placed instance: the surface a secondary ray starts on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct InstanceTriangle {
    /// TLAS slot of the instance.
    pub slot: u32,
    /// Triangle index in the instance's mesh.
    pub triangle: u32,
}

/// Where an any-hit walk stopped: the instance and the triangle block of the hit its
/// filter accepted.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Occluder {
    /// TLAS slot of the instance.
    pub slot: u32,
    /// The block in the instance's geometry.
    pub block: BlockRef,
}

/// Why instances were left out of a build.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct SkippedInstances {
    /// Transforms that are not invertible or not finite.
    pub singular: usize,
    /// Geometry ids not in the library.
    pub unknown_geometry: usize,
    /// The caller's indices of the left-out instances, in order.
    pub ids: Vec<u32>,
}

/// The TLAS: instance records in slot order and the BVH over their world boxes.
#[derive(Clone, Debug, Default, bevy_ecs::resource::Resource)]
pub struct TopLevel {
    /// Records in BVH slot order.
    pub instances: Vec<InstanceRecord>,
    /// BVH over the instances' world boxes.
    pub bvh: Bvh,
    /// What the last build left out.
    pub skipped: SkippedInstances,
    /// Number of instance descriptions the last build was given.
    pub source_count: usize,
    /// The caller's indices of the instances not in the tree (left out, or of empty
    /// meshes or overflowing boxes), in order.
    pub outside: Vec<u32>,
    /// [`Bvh::sah_cost`] of the tree when it was built over the summed area of its
    /// instances' boxes (refits do not change it).
    pub built_sah_cost: f64,
    /// The same after the latest refit (0 until one).
    pub current_sah_cost: f64,
    /// Instance boxes of the build or refit in progress, kept to reuse the allocation.
    refit_scratch: Vec<Aabb>,
    /// The BVH build's own scratch memory, kept for the next rebuild.
    build_scratch: BuildScratch,
    /// Records of the refit in progress (the previous ones after it), kept to reuse the
    /// allocation.
    refit_records: Vec<InstanceRecord>,
}

/// Why [`TopLevel::refit`] refused; the TLAS is unchanged and must be rebuilt instead.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum RefitRefusal {
    /// Not as many instances as the last build was given.
    #[error("{given} instances given, the tree was built for {built}")]
    InstanceCount {
        /// Instances at the last build.
        built: usize,
        /// Instances given to the refit.
        given: usize,
    },
    /// The instance (the caller's index) now points at another geometry.
    #[error("instance {instance} points at another geometry")]
    GeometryChanged {
        /// The caller's index of the instance.
        instance: u32,
    },
    /// The instance became unusable (singular or non-finite) or usable: the set of
    /// instances in the tree would change.
    #[error("instance {instance} became usable or unusable (singular, non-finite or empty)")]
    UsableSetChanged {
        /// The caller's index of the instance.
        instance: u32,
    },
}

/// Why an instance cannot enter the tree.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Unusable {
    Singular,
    UnknownGeometry,
}

/// The instance's geometry and world → object transform, or why it cannot enter the tree.
fn usable<'a>(
    library: &'a GeometryLibrary,
    desc: &InstanceDesc,
) -> Result<(&'a Geometry, Affine3A), Unusable> {
    let geometry = library
        .get(desc.geometry)
        .ok_or(Unusable::UnknownGeometry)?;
    let det = desc.transform.matrix3.determinant();
    if !desc.transform.is_finite() || det == 0.0 || !det.is_finite() {
        return Err(Unusable::Singular);
    }
    // The inverse can still overflow for tiny but non-zero determinants.
    let world_to_object = desc.transform.inverse();
    if !world_to_object.is_finite() {
        return Err(Unusable::Singular);
    }
    Ok((geometry, world_to_object))
}

/// True when `transform`'s inverse is surely finite, without computing it: entries up
/// to 10⁶, a translation up to 10¹² and a determinant of at least 10⁻¹² keep every
/// cofactor over the determinant below 2·10²⁴ and the inverse's translation below
/// 10³⁷, far inside f32. Anything else (NaN included) takes the full check.
fn surely_invertible(transform: &Affine3A) -> bool {
    let m = &transform.matrix3;
    let largest = m
        .x_axis
        .abs()
        .max(m.y_axis.abs())
        .max(m.z_axis.abs())
        .max_element();
    transform.is_finite()
        && largest <= 1e6
        && transform.translation.abs().max_element() <= 1e12
        && m.determinant().abs() >= 1e-12
}

/// About the length of `geometry`'s box diagonal in world space, for an instance
/// placed by the inverse of `world_to_object` (exact for rotations with uniform scale).
#[inline(always)]
fn world_diagonal(geometry: &Geometry, world_to_object: &Affine3A) -> f32 {
    let m = &world_to_object.matrix3;
    let shrink = m
        .x_axis
        .length()
        .max(m.y_axis.length())
        .max(m.z_axis.length());
    let bounds = geometry.bounds();
    (bounds.max - bounds.min).length() / shrink
}

/// An instance's world box, or why it cannot enter the tree.
fn world_bounds(library: &GeometryLibrary, desc: &InstanceDesc) -> Result<Aabb, Unusable> {
    // The usual instance skips the inverse here; `record` computes it once per slot.
    let geometry = match library.get(desc.geometry) {
        Some(geometry) if surely_invertible(&desc.transform) => geometry,
        _ => usable(library, desc)?.0,
    };
    Ok(geometry.transformed_bounds(&desc.transform))
}

/// An instance's world box and record, computing its inverse once, or why it cannot
/// enter the tree.
fn placed(
    library: &GeometryLibrary,
    id: u32,
    desc: &InstanceDesc,
) -> Result<(Aabb, InstanceRecord), Unusable> {
    let (geometry, world_to_object) = usable(library, desc)?;
    let record = InstanceRecord::new(&desc.transform, &world_to_object, desc.geometry, id);
    Ok((geometry.transformed_bounds(&desc.transform), record))
}

/// Summed surface area of the hittable boxes among `bounds` (at least the smallest
/// positive f64, so a ratio of costs stays finite).
fn primitive_area(bounds: &[Aabb]) -> f64 {
    crate::accel::bvh::chunked_sum(bounds, |b| {
        if is_hittable(b) {
            b.surface_area() as f64
        } else {
            0.0
        }
    })
    .max(f64::MIN_POSITIVE)
}

/// The test [`Bvh::build`] applies to keep a box: instances of empty meshes, or whose
/// world box overflowed, cannot be hit.
fn is_hittable(bounds: &Aabb) -> bool {
    !bounds.is_empty() && bounds.min.is_finite() && bounds.max.is_finite()
}

impl TopLevel {
    /// Builds from scratch on the current rayon pool (`params.leaf_block` is taken as 1).
    /// Instances with singular transforms or unknown geometry are left out and counted in
    /// `skipped`; instances of empty meshes cannot be hit and are left out of the tree.
    pub fn build(
        library: &GeometryLibrary,
        instances: &[InstanceDesc],
        params: BuildParams,
    ) -> TopLevel {
        let mut top_level = TopLevel::default();
        top_level.rebuild(library, instances, params);
        top_level
    }

    /// [`build`](Self::build) in place: the same tree and records as a fresh build,
    /// written into this one's memory. Fresh memory costs a page fault per page, and a
    /// build of 365 k instances fills some 150 MB.
    pub fn rebuild(
        &mut self,
        library: &GeometryLibrary,
        instances: &[InstanceDesc],
        params: BuildParams,
    ) {
        // Boxes first, with a cheap usability check; records (with their inverses) only
        // for what enters the tree, written once in slot order. A per-instance
        // intermediate holding both cost more (allocation, page faults, copies) than the
        // BVH build itself at 365 k instances. Unusable instances get an empty box, and
        // only those are checked again for the reason.
        let mut bounds = std::mem::take(&mut self.refit_scratch);
        bounds.clear();
        bounds.par_extend(
            instances
                .par_iter()
                .map(|desc| world_bounds(library, desc).unwrap_or(Aabb::EMPTY)),
        );
        // The tree leaves out exactly the boxes that cannot be hit: found on all threads
        // (a serial pass over every box, and another over the tree's slots to find what
        // it left out, were 3 ms of a 365 k-instance build).
        let outside: Vec<u32> = bounds
            .par_iter()
            .enumerate()
            .filter(|(_, b)| !is_hittable(b))
            .map(|(i, _)| i as u32)
            .collect();
        let mut skipped = SkippedInstances::default();
        for &i in &outside {
            if let Err(reason) = usable(library, &instances[i as usize]) {
                match reason {
                    Unusable::Singular => skipped.singular += 1,
                    Unusable::UnknownGeometry => skipped.unknown_geometry += 1,
                }
                skipped.ids.push(i);
            }
        }
        // Records are stored one per slot: no padding slots.
        self.bvh.rebuild(
            &bounds,
            BuildParams {
                leaf_block: 1,
                ..params
            },
            &mut self.build_scratch,
        );
        // Slots are in tree order, unrelated to the callers': each description read here
        // misses the cache (and the TLB), so the one a few slots ahead is prefetched
        // (43 ms of a 220 ms build without it, 28 ms with it, mostly page faults).
        const AHEAD: usize = 16;
        let slots = &self.bvh.prim_indices;
        self.instances.clear();
        self.instances
            .par_extend((0..slots.len()).into_par_iter().map(|slot| {
                if let Some(&ahead) = slots.get(slot + AHEAD) {
                    prefetch(&instances[ahead as usize]);
                }
                let i = slots[slot];
                // The tree holds usable instances only: their inverses are finite.
                let desc = &instances[i as usize];
                InstanceRecord::new(&desc.transform, &desc.transform.inverse(), desc.geometry, i)
            }));
        debug_assert_eq!(slots.len() + outside.len(), instances.len());
        self.outside = outside;
        // The boxes in the tree are the hittable ones: summed in the callers' order, no
        // gather needed.
        self.built_sah_cost = self.bvh.sah_cost() / primitive_area(&bounds);
        self.current_sah_cost = self.built_sah_cost;
        self.skipped = skipped;
        self.source_count = instances.len();
        self.refit_scratch = bounds;
    }

    /// Moves the instances of the last build to `instances` (the same list, in the same
    /// order, with new transforms) keeping the tree's topology: boxes are refitted
    /// bottom-up in a linear pass instead of a SAH build. Returns the tree's SAH cost
    /// over its cost when built (1 = as good as built; rebuild when it has grown).
    ///
    /// Refuses, changing nothing, when the list differs in length, an instance points at
    /// another geometry, or the set of instances that can be hit would change (a
    /// transform became singular or a left-out one became usable): those need a build.
    pub fn refit(
        &mut self,
        library: &GeometryLibrary,
        instances: &[InstanceDesc],
    ) -> Result<f32, RefitRefusal> {
        if instances.len() != self.source_count {
            return Err(RefitRefusal::InstanceCount {
                built: self.source_count,
                given: instances.len(),
            });
        }
        // First compute every slot's box and record into scratch vectors, so a refusal
        // leaves the tree as it was; then swap the records in. One pass computes each
        // inverse once (checking and recomputing them in place cost twice the time),
        // for a second set of records kept between refits.
        let mut slot_bounds = std::mem::take(&mut self.refit_scratch);
        let mut records = std::mem::take(&mut self.refit_records);
        slot_bounds.resize(self.instances.len(), Aabb::EMPTY);
        if let Some(&any) = self.instances.first() {
            records.resize(self.instances.len(), any);
        }
        let checked = slot_bounds
            .par_iter_mut()
            .zip(records.par_iter_mut())
            .zip(self.instances.par_iter())
            .try_for_each(|((out_bounds, out_record), old)| {
                let instance = old.id;
                let desc = &instances[instance as usize];
                match placed(library, instance, desc) {
                    Ok(_) if desc.geometry != old.geometry => {
                        Err(RefitRefusal::GeometryChanged { instance })
                    }
                    Ok((bounds, record)) if is_hittable(&bounds) => {
                        *out_bounds = bounds;
                        *out_record = record;
                        Ok(())
                    }
                    _ => Err(RefitRefusal::UsableSetChanged { instance }),
                }
            })
            .and_then(|()| {
                let newcomer = self.outside.par_iter().find_any(|&&instance| {
                    world_bounds(library, &instances[instance as usize])
                        .is_ok_and(|bounds| is_hittable(&bounds))
                });
                match newcomer {
                    Some(&instance) => Err(RefitRefusal::UsableSetChanged { instance }),
                    None => Ok(()),
                }
            });
        if let Err(refusal) = checked {
            self.refit_scratch = slot_bounds;
            self.refit_records = records;
            return Err(refusal);
        }
        self.bvh
            .refit(&slot_bounds)
            .expect("every slot box was checked finite and non-empty");
        std::mem::swap(&mut self.instances, &mut records);
        self.refit_records = records;
        self.current_sah_cost = self.bvh.sah_cost() / primitive_area(&slot_bounds);
        self.refit_scratch = slot_bounds;
        Ok(self.degradation())
    }

    /// The tree's SAH cost over its cost when last built, each per unit of instance box
    /// area: 1 right after a build, growing as refits move instances away from the layout
    /// the tree was built for. Dividing by the instances' own box area keeps boxes that
    /// merely grew (a plant tilting in the wind) from counting as degradation, while a
    /// plant moved far away or instances trading places still do.
    pub fn degradation(&self) -> f32 {
        if self.built_sah_cost > 0.0 && self.current_sah_cost > 0.0 {
            (self.current_sah_cost / self.built_sah_cost) as f32
        } else {
            1.0
        }
    }

    /// A hash of the tree and the instance records in slot order (transforms, inverses,
    /// geometries, ids): equal top levels give equal hashes on any machine.
    pub fn content_hash(&self) -> u64 {
        let mut hash = crate::util::fingerprint::Fingerprint::untagged();
        self.bvh.hash_into(&mut hash);
        for record in &self.instances {
            for transform in [record.object_to_world(), record.world_to_object()] {
                for v in transform.to_cols_array() {
                    hash.f32(v);
                }
            }
            hash.u32(record.geometry.0).u32(record.id);
        }
        hash.finish()
    }

    /// Number of instances that can be hit.
    pub fn len(&self) -> usize {
        self.instances.len()
    }

    /// True when nothing can be hit.
    pub fn is_empty(&self) -> bool {
        self.instances.is_empty()
    }

    /// World-space box of the scene.
    pub fn bounds(&self) -> Aabb {
        self.bvh.bounds()
    }

    /// Heap bytes held.
    pub fn memory_bytes(&self) -> usize {
        (self.instances.capacity() + self.refit_records.capacity())
            * std::mem::size_of::<InstanceRecord>()
            + self.refit_scratch.capacity() * std::mem::size_of::<Aabb>()
            + self.build_scratch.memory_bytes()
            + self.bvh.memory_bytes()
    }

    /// The record of slot `slot`.
    pub fn record(&self, slot: usize) -> &InstanceRecord {
        &self.instances[slot]
    }

    /// Closest hit that `filter` accepts (`filter` runs in place during traversal).
    #[inline]
    pub fn intersect_closest(
        &self,
        library: &GeometryLibrary,
        ray: &Ray,
        stats: &mut TraversalStats,
        filter: impl FnMut(&Candidate) -> bool,
    ) -> Option<Hit> {
        with_node_kernel!(
            kernel => self.intersect_closest_with(kernel, library, ray, None, stats, filter)
        )
    }

    /// [`intersect_closest`](Self::intersect_closest) with the box tests of `kernel`, at
    /// both levels; the triangle `leaving` (the one the ray starts on) is not tested, as
    /// in [`intersect_any_leaving`](Self::intersect_any_leaving).
    #[inline(always)]
    pub fn intersect_closest_with(
        &self,
        kernel: impl NodeKernel,
        library: &GeometryLibrary,
        ray: &Ray,
        leaving: Option<InstanceTriangle>,
        stats: &mut TraversalStats,
        mut filter: impl FnMut(&Candidate) -> bool,
    ) -> Option<Hit> {
        stats.closest_rays += 1;
        let mut inner = TraversalStats::default();
        let leaving_in = |slot: usize| {
            leaving
                .filter(|leaving| leaving.slot as usize == slot)
                .map(|leaving| leaving.triangle)
        };
        let mut best = None;
        self.bvh.traverse_closest_with(
            kernel,
            ray,
            stats,
            |slot, t_max| {
                let record = &self.instances[slot];
                let geometry = &library.geometries[record.geometry.0 as usize];
                let local = Ray {
                    t_max,
                    ..ray.transformed(&record.world_to_object())
                };
                let found = geometry.intersect_closest_with(
                    kernel,
                    &local,
                    leaving_in(slot),
                    &mut inner,
                    |triangle, hit| filter(&Candidate::on(slot, record, triangle, hit)),
                )?;
                best = Some(Candidate::on(slot, record, found.triangle, &found.hit));
                Some(found.hit.t)
            },
            |slot| prefetch(&self.instances[slot]),
        );
        stats.add(&inner);
        best
    }

    /// [`intersect_closest_packet_with`](Self::intersect_closest_packet_with) on this
    /// CPU's best kernel.
    #[inline]
    pub fn intersect_closest_packet(
        &self,
        library: &GeometryLibrary,
        rays: &[Ray],
        stats: &mut TraversalStats,
        filter: impl FnMut(usize, &Candidate) -> bool,
    ) -> Option<[Option<Hit>; PACKET]> {
        with_node_kernel!(
            kernel => self.intersect_closest_packet_with(kernel, library, rays, stats, filter)
        )
    }

    /// [`intersect_closest_with`](Self::intersect_closest_with) for a packet of up to
    /// [`PACKET`] coherent rays that start on no surface (a camera's neighbouring
    /// pixels): one top-level walk for all of them, then each ray's own bottom-level
    /// walks; `filter(ray, candidate)` judges ray `ray`'s candidates. `None` when the
    /// packet cannot be bounded (see [`Bvh::traverse_closest_packet`]): nothing was
    /// traced, and the rays go one by one.
    #[inline(always)]
    pub fn intersect_closest_packet_with(
        &self,
        kernel: impl NodeKernel,
        library: &GeometryLibrary,
        rays: &[Ray],
        stats: &mut TraversalStats,
        mut filter: impl FnMut(usize, &Candidate) -> bool,
    ) -> Option<[Option<Hit>; PACKET]> {
        let mut inner = TraversalStats::default();
        let mut best = [None; PACKET];
        // The packet's spread of directions: its width per unit of distance.
        let first = rays
            .first()
            .map_or(Vec3A::X, |ray| ray.direction.normalize_or_zero());
        let spread = rays.iter().fold(0.0f32, |widest, ray| {
            widest.max((ray.direction.normalize_or_zero() - first).length())
        });
        kernel.traverse_packet(
            &self.bvh,
            rays,
            stats,
            |first, count, rays_in, entry_t, t_max| {
                for slot in first..first + count {
                    let record = &self.instances[slot];
                    let geometry = &library.geometries[record.geometry.0 as usize];
                    let world_to_object = record.world_to_object();
                    let local = |ray: usize, t_max: f32| Ray {
                        t_max,
                        ..rays[ray].transformed(&world_to_object)
                    };
                    let shared = rays_in.count_ones() > 1
                        && spread * entry_t
                            <= SHARED_WALK_WIDTH * world_diagonal(geometry, &world_to_object);
                    let mut alone = rays_in;
                    if shared {
                        let mut group = [0u8; PACKET];
                        let mut local_rays = [Ray::new(Vec3A::ZERO, Vec3A::X); PACKET];
                        for (i, ray) in mask_bits(rays_in).enumerate() {
                            group[i] = ray as u8;
                            local_rays[i] = local(ray, t_max[ray]);
                        }
                        let n = rays_in.count_ones() as usize;
                        let found = geometry.intersect_closest_packet_with(
                            kernel,
                            &local_rays[..n],
                            &mut inner,
                            |i, triangle, hit| {
                                let ray = usize::from(group[i]);
                                filter(ray, &Candidate::on(slot, record, triangle, hit))
                            },
                        );
                        if let Some(found) = found {
                            alone = 0;
                            for (&ray, found) in group.iter().zip(&found).take(n) {
                                if let Some(found) = found {
                                    let ray = usize::from(ray);
                                    best[ray] = Some(Candidate::on(
                                        slot,
                                        record,
                                        found.triangle,
                                        &found.hit,
                                    ));
                                    t_max[ray] = found.hit.t;
                                }
                            }
                        }
                    }
                    for ray in mask_bits(alone) {
                        let found = geometry.intersect_closest_with(
                            kernel,
                            &local(ray, t_max[ray]),
                            None,
                            &mut inner,
                            |triangle, hit| {
                                filter(ray, &Candidate::on(slot, record, triangle, hit))
                            },
                        );
                        if let Some(found) = found {
                            best[ray] =
                                Some(Candidate::on(slot, record, found.triangle, &found.hit));
                            t_max[ray] = found.hit.t;
                        }
                    }
                }
            },
            |slot| prefetch(&self.instances[slot]),
        )?;
        stats.closest_rays += rays.len().min(PACKET) as u64;
        stats.add(&inner);
        Some(best)
    }

    /// True when some hit with `t < ray.t_max` is accepted by `filter`.
    #[inline]
    pub fn intersect_any(
        &self,
        library: &GeometryLibrary,
        ray: &Ray,
        stats: &mut TraversalStats,
        filter: impl FnMut(&Candidate) -> bool,
    ) -> bool {
        self.intersect_any_leaving(library, ray, None, stats, filter)
    }

    /// [`intersect_any`](Self::intersect_any) for a ray that starts on the instance
    /// triangle `leaving`, which is not tested: a ray leaving a plane cannot meet it
    /// again, but the ray's origin, offset past the error of the world-space point, is
    /// rounded again on its way into the instance's object space and may land a hair
    /// behind the triangle there.
    #[inline]
    pub fn intersect_any_leaving(
        &self,
        library: &GeometryLibrary,
        ray: &Ray,
        leaving: Option<InstanceTriangle>,
        stats: &mut TraversalStats,
        filter: impl FnMut(&Candidate) -> bool,
    ) -> bool {
        with_node_kernel!(
            kernel => self.intersect_any_with(kernel, library, ray, leaving, stats, filter)
        )
    }

    /// [`intersect_any`](Self::intersect_any) with the box tests of `kernel`, at both
    /// levels; the triangle `leaving` (the one the ray starts on) is not tested, and its
    /// instance is tested before the rest of the top level is walked, or after it when
    /// its mesh [is flat](Geometry::is_flat).
    #[inline(always)]
    pub fn intersect_any_with(
        &self,
        kernel: impl NodeKernel,
        library: &GeometryLibrary,
        ray: &Ray,
        leaving: Option<InstanceTriangle>,
        stats: &mut TraversalStats,
        filter: impl FnMut(&Candidate) -> bool,
    ) -> bool {
        self.occluder_with(kernel, library, ray, leaving, stats, filter)
            .is_some()
    }

    /// [`intersect_any_with`](Self::intersect_any_with) that reports where the walk
    /// stopped: the instance and triangle block of the hit `filter` accepted.
    #[inline(always)]
    pub fn occluder_with(
        &self,
        kernel: impl NodeKernel,
        library: &GeometryLibrary,
        ray: &Ray,
        leaving: Option<InstanceTriangle>,
        stats: &mut TraversalStats,
        mut filter: impl FnMut(&Candidate) -> bool,
    ) -> Option<Occluder> {
        stats.any_rays += 1;
        let mut inner = TraversalStats::default();
        let mut occluder = None;
        let mut test = |slot: usize, t_max: f32, leaving: Option<u32>| {
            let record = &self.instances[slot];
            let geometry = &library.geometries[record.geometry.0 as usize];
            let local = Ray {
                t_max,
                ..ray.transformed(&record.world_to_object())
            };
            let block = geometry.occluding_block_with(
                kernel,
                &local,
                leaving,
                &mut inner,
                |triangle, hit| filter(&Candidate::on(slot, record, triangle, hit)),
            );
            occluder = block.map(|block| Occluder {
                slot: slot as u32,
                block,
            });
            occluder.is_some()
        };
        // A ray leaving a plant is most often stopped by that plant: its own instance
        // first, then the rest of the top level without it (whose walk still counts the
        // slot among its primitive tests when it reaches it). A ray leaving a flat mesh
        // (a terrain) is seldom stopped by it, and its walk there misses the caches: that
        // instance comes last, when nothing else stopped the ray.
        let own = leaving.filter(|leaving| (leaving.slot as usize) < self.instances.len());
        let own_last = own.is_some_and(|leaving| {
            let record = &self.instances[leaving.slot as usize];
            library.geometries[record.geometry.0 as usize].is_flat()
        });
        #[inline(always)]
        fn test_own(
            own: Option<InstanceTriangle>,
            t_max: f32,
            stats: &mut TraversalStats,
            test: &mut impl FnMut(usize, f32, Option<u32>) -> bool,
        ) -> bool {
            own.is_some_and(|leaving| {
                stats.primitive_tests += 1;
                test(leaving.slot as usize, t_max, Some(leaving.triangle))
            })
        }
        let own_slot = own.map(|leaving| leaving.slot as usize);
        let occluded = (!own_last && test_own(own, ray.t_max, stats, &mut test))
            || self.bvh.traverse_any_with(
                kernel,
                ray,
                stats,
                |slot, t_max| Some(slot) != own_slot && test(slot, t_max, None),
                |slot| prefetch(&self.instances[slot]),
            )
            || (own_last && test_own(own, ray.t_max, stats, &mut test));
        stats.add(&inner);
        debug_assert_eq!(occluded, occluder.is_some());
        occluder
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::test_random::uniform;
    use glam::{Mat3, Vec3};

    #[test]
    fn a_surely_invertible_transform_has_a_finite_inverse() {
        let mut state = 0x1ee7_c0de_u64;
        let s = &mut state;
        let mut checked = 0;
        for case in 0..200_000 {
            // Entries up to the limit, determinants down to the denormals (scales from
            // 10⁻⁴⁵ up, or rows that nearly repeat), translations at the limit.
            let row = |s: &mut u64| Vec3::new(uniform(s) - 0.5, uniform(s) - 0.5, uniform(s) - 0.5);
            let power =
                |s: &mut u64, low: f32, high: f32| 10f32.powf(low + uniform(s) * (high - low));
            let matrix = if case % 2 == 0 {
                let scales = Vec3::new(
                    power(s, -6.0, 6.0),
                    power(s, -6.0, 6.0),
                    power(s, -45.0, 6.0),
                );
                let shear =
                    Mat3::from_cols(Vec3::X, Vec3::new(power(s, -6.0, 6.0), 1.0, 0.0), Vec3::Z);
                shear * Mat3::from_diagonal(scales)
            } else {
                let (a, b) = (row(s), row(s));
                let c = a + Vec3::Z * power(s, -8.0, 0.0);
                Mat3::from_cols(a, b, c).transpose() * power(s, -6.0, 6.0)
            };
            let translation = row(s) * 2.0 * if case % 3 == 0 { 1.0 } else { 1e12 };
            let transform = Affine3A::from_mat3_translation(matrix, translation);
            if surely_invertible(&transform) {
                checked += 1;
                assert!(
                    transform.inverse().is_finite(),
                    "case {case}: {transform:?}"
                );
            }
        }
        assert!(checked > 10_000, "only {checked} cases near the limits");
    }
}
