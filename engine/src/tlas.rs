//! The top-level BVH over instances. Each instance is a transform and a geometry id;
//! traversal moves the ray into the instance's object space and descends its BLAS.

use crate::bvh::{BuildParams, Bvh, TraversalStats};
use crate::geometry::{GeometryId, GeometryLibrary};
use crate::math::{Aabb, Ray};
use glam::{Affine3A, Vec3A};
use rayon::prelude::*;

/// An instance as the caller describes it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InstanceDesc {
    /// Object → world.
    pub transform: Affine3A,
    /// Which mesh.
    pub geometry: GeometryId,
}

/// An instance as traversal needs it, stored in TLAS slot order.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InstanceRecord {
    /// Object → world.
    pub object_to_world: Affine3A,
    /// World → object (the inverse of `object_to_world`).
    pub world_to_object: Affine3A,
    /// Which mesh.
    pub geometry: GeometryId,
    /// The caller's index of the instance (position in the slice given to `build`).
    pub id: u32,
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

/// The closest accepted hit of a ray.
pub type Hit = Candidate;

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
}

impl TopLevel {
    /// Builds from scratch on the current rayon pool. Instances with singular transforms
    /// or unknown geometry are left out and counted in `skipped`; instances of empty
    /// meshes cannot be hit and are left out of the tree.
    pub fn build(
        library: &GeometryLibrary,
        instances: &[InstanceDesc],
        params: BuildParams,
    ) -> TopLevel {
        let prepared: Vec<(Aabb, Option<InstanceRecord>, u8)> = instances
            .par_iter()
            .enumerate()
            .map(|(i, desc)| {
                let Some(geometry) = library.get(desc.geometry) else {
                    return (Aabb::EMPTY, None, 2);
                };
                let det = desc.transform.matrix3.determinant();
                if !desc.transform.is_finite() || det == 0.0 || !det.is_finite() {
                    return (Aabb::EMPTY, None, 1);
                }
                let world_to_object = desc.transform.inverse();
                if !world_to_object.is_finite() {
                    return (Aabb::EMPTY, None, 1);
                }
                let record = InstanceRecord {
                    object_to_world: desc.transform,
                    world_to_object,
                    geometry: desc.geometry,
                    id: i as u32,
                };
                (
                    geometry.bounds().transformed(&desc.transform),
                    Some(record),
                    0,
                )
            })
            .collect();
        let skipped = SkippedInstances {
            singular: prepared.iter().filter(|p| p.2 == 1).count(),
            unknown_geometry: prepared.iter().filter(|p| p.2 == 2).count(),
            ids: (0..prepared.len() as u32)
                .filter(|&i| prepared[i as usize].2 != 0)
                .collect(),
        };
        let bounds: Vec<Aabb> = prepared.iter().map(|p| p.0).collect();
        let bvh = Bvh::build(&bounds, params);
        let instances = bvh
            .prim_indices
            .iter()
            .map(|&i| prepared[i as usize].1.expect("BVH keeps only valid boxes"))
            .collect();
        TopLevel {
            instances,
            bvh,
            skipped,
        }
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
        self.instances.capacity() * std::mem::size_of::<InstanceRecord>() + self.bvh.memory_bytes()
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
        mut filter: impl FnMut(&Candidate) -> bool,
    ) -> Option<Hit> {
        stats.closest_rays += 1;
        let mut inner = TraversalStats::default();
        let mut best = None;
        self.bvh.traverse_closest(ray, stats, |slot, t_max| {
            let record = &self.instances[slot];
            let geometry = &library.geometries[record.geometry.0 as usize];
            let local = Ray {
                t_max,
                ..ray.transformed(&record.world_to_object)
            };
            let found = geometry.intersect_closest(&local, &mut inner, |triangle, hit| {
                filter(&Candidate {
                    slot: slot as u32,
                    instance: record.id,
                    geometry: record.geometry,
                    triangle,
                    barycentrics: hit.barycentrics,
                    t: hit.t,
                })
            })?;
            best = Some(Candidate {
                slot: slot as u32,
                instance: record.id,
                geometry: record.geometry,
                triangle: found.triangle,
                barycentrics: found.hit.barycentrics,
                t: found.hit.t,
            });
            Some(found.hit.t)
        });
        stats.add(&inner);
        best
    }

    /// True when some hit with `t < ray.t_max` is accepted by `filter`.
    #[inline]
    pub fn intersect_any(
        &self,
        library: &GeometryLibrary,
        ray: &Ray,
        stats: &mut TraversalStats,
        mut filter: impl FnMut(&Candidate) -> bool,
    ) -> bool {
        stats.any_rays += 1;
        let mut inner = TraversalStats::default();
        let occluded = self.bvh.traverse_any(ray, stats, |slot, t_max| {
            let record = &self.instances[slot];
            let geometry = &library.geometries[record.geometry.0 as usize];
            let local = Ray {
                t_max,
                ..ray.transformed(&record.world_to_object)
            };
            geometry.intersect_any(&local, &mut inner, |triangle, hit| {
                filter(&Candidate {
                    slot: slot as u32,
                    instance: record.id,
                    geometry: record.geometry,
                    triangle,
                    barycentrics: hit.barycentrics,
                    t: hit.t,
                })
            })
        });
        stats.add(&inner);
        occluded
    }
}
