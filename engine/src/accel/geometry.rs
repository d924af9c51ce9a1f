//! Species geometry: each mesh with its bottom-level BVH, built once and shared by every
//! instance, collected in the [`GeometryLibrary`].

use crate::accel::bvh::{BuildParams, Bvh, LeafVisit, PACKET, PADDING, TraversalStats, mask_bits};
use crate::accel::heightfield::Heightfield;
use crate::accel::instance_bounds::SupportTable;
use crate::accel::kernel::{NodeKernel, prefetch, with_node_kernel};
use crate::accel::mesh::{MeshError, TriangleMesh};
use crate::accel::presplit::triangle_boxes;
use crate::accel::triangle::{TriangleBlock, TriangleHit, WatertightRay};
use crate::util::math::{Aabb, Ray};
use glam::{Affine3A, Vec3A};
use rayon::prelude::*;

/// Triangles per [`TriangleBlock`]: the bottom level's leaves are aligned to it.
const TRIANGLE_BLOCK: usize = 4;

/// Index of a mesh in the [`GeometryLibrary`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct GeometryId(pub u32);

/// A mesh and its BLAS, with each leaf's triangles copied into blocks of four (structure
/// of arrays), so a leaf test reads contiguous memory and tests four triangles at once.
#[derive(Clone, Debug)]
pub struct Geometry {
    /// Human-readable name (species or glTF mesh name).
    pub name: String,
    /// The source mesh (attributes for shading).
    pub mesh: TriangleMesh,
    /// The BLAS over the mesh's triangles: its slots index the build boxes of
    /// [`triangle_boxes`] (a long slanted triangle has two), the blocks hold the
    /// triangles themselves.
    pub bvh: Bvh,
    /// The triangles of slots `4b .. 4b + 4` in block `b`: leaves start at multiples of
    /// four ([`BuildParams::leaf_block`]), so a leaf's triangles fill whole blocks.
    blocks: Vec<TriangleBlock>,
    /// The mesh's support function, for tight instance boxes.
    support: SupportTable,
    /// Whether the mesh is nearly flat, as a terrain is: see [`Geometry::is_flat`].
    flat: bool,
    /// For a flat mesh proven a height field: its axis and steepest slope, which rays
    /// leaving it more steeply skip.
    heightfield: Option<Heightfield>,
}

/// The largest ratio of a box's thinnest side to its middle one that
/// [`Geometry::is_flat`] calls flat: a terrain 1 km wide with 10 m of relief is at 0.01,
/// the `paper` ecosystem's at about 0.06; plants stand taller than that.
const FLAT_RATIO: f32 = 0.125;

/// One triangle block of a geometry's leaves, with the lanes its leaf uses: what an
/// any-hit walk reports for the block where it stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BlockRef {
    /// Index of the block in the geometry's block array.
    pub index: u32,
    /// Lanes that hold the leaf's triangles (1–4); the rest repeat the last one.
    pub lanes: u32,
}

/// A hit inside one geometry.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GeometryHit {
    /// Triangle index in the mesh.
    pub triangle: u32,
    /// Distance and barycentrics.
    pub hit: TriangleHit,
}

impl Geometry {
    /// Checks the mesh and builds its BLAS on the current rayon pool (leaves aligned to
    /// blocks of four triangles, whatever `params.leaf_block` says).
    pub fn new(
        name: impl Into<String>,
        mesh: TriangleMesh,
        params: BuildParams,
    ) -> Result<Self, MeshError> {
        mesh.check()?;
        let boxes = triangle_boxes(&mesh, params.split_ratio);
        let bounds = boxes
            .boxes
            .par_iter()
            .copied()
            .reduce(|| Aabb::EMPTY, Aabb::union);
        let extent = bounds.extent();
        let mut sides = extent.to_array();
        sides.sort_by(f32::total_cmp);
        let flat = sides[0] <= FLAT_RATIO * sides[1];
        // The height-field proof runs beside the build, which leaves threads idle near
        // its root.
        let (bvh, heightfield) = rayon::join(
            || {
                Bvh::build(
                    &boxes.boxes,
                    BuildParams {
                        leaf_block: TRIANGLE_BLOCK,
                        ..params
                    },
                )
            },
            || {
                flat.then(|| Heightfield::of(&mesh, extent.min_position()))
                    .flatten()
            },
        );
        let blocks = bvh
            .prim_indices
            .chunks(TRIANGLE_BLOCK)
            .map(|slots| {
                let mut triangles = [(0, [Vec3A::ZERO; 3]); TRIANGLE_BLOCK];
                let mut lanes = 0;
                for &primitive in slots.iter().filter(|&&p| p != PADDING) {
                    let t = boxes.owner(primitive);
                    triangles[lanes] = (t, mesh.triangle(t as usize));
                    lanes += 1;
                }
                TriangleBlock::new(&triangles[..lanes])
            })
            .collect();
        Ok(Self {
            name: name.into(),
            support: SupportTable::new(&mesh.positions),
            flat,
            heightfield,
            mesh,
            bvh,
            blocks,
        })
    }

    /// Whether the mesh is nearly flat, as a terrain is: its box's thinnest side is at
    /// most an eighth of the middle one. A ray leaving one of its triangles then seldom
    /// meets another, so shadow rays walk such an instance after the rest of the scene.
    pub fn is_flat(&self) -> bool {
        self.flat
    }

    /// The mesh's [height field](Heightfield) proof, for a flat mesh that is one.
    pub fn heightfield(&self) -> Option<&Heightfield> {
        self.heightfield.as_ref()
    }

    /// True when `ray` leaves this mesh (a triangle `leaving` of it) and the mesh is a
    /// height field the ray climbs or falls more steeply than: it cannot meet the mesh
    /// again (see `heightfield`), so no walk is needed. The proof is for a ray from a
    /// point of the surface; an origin rounded a hair below it on its way into object
    /// space could only graze a neighbour of the triangle it leaves, the self-hit that
    /// skipping `leaving` is there to avoid.
    #[inline(always)]
    fn cleared_by(&self, ray: &Ray, leaving: Option<u32>) -> bool {
        leaving.is_some()
            && self
                .heightfield
                .is_some_and(|field| field.clears(ray.direction))
    }

    /// Object-space box.
    pub fn bounds(&self) -> Aabb {
        self.bvh.bounds()
    }

    /// A box holding the mesh after `transform` (an instance's world box): from the
    /// support function, within a few percent of the tightest box where the object box's
    /// transformed corners can be √2 wider per axis.
    pub fn transformed_bounds(&self, transform: &Affine3A) -> Aabb {
        if self.bvh.bounds().is_empty() {
            return Aabb::EMPTY;
        }
        crate::accel::kernel::transformed_bounds(&self.support, transform)
    }

    /// Closest hit with `0 < t < ray.t_max` that `accept(triangle, hit)` keeps.
    #[inline]
    pub fn intersect_closest(
        &self,
        ray: &Ray,
        stats: &mut TraversalStats,
        accept: impl FnMut(u32, &TriangleHit) -> bool,
    ) -> Option<GeometryHit> {
        with_node_kernel!(kernel => self.intersect_closest_with(kernel, ray, None, stats, accept))
    }

    /// [`intersect_closest`](Self::intersect_closest) with the box tests of `kernel`,
    /// leaving out triangle `leaving` (as [`intersect_any_with`](Self::intersect_any_with)).
    #[inline(always)]
    pub fn intersect_closest_with(
        &self,
        kernel: impl NodeKernel,
        ray: &Ray,
        leaving: Option<u32>,
        stats: &mut TraversalStats,
        accept: impl FnMut(u32, &TriangleHit) -> bool,
    ) -> Option<GeometryHit> {
        if self.cleared_by(ray, leaving) {
            return None;
        }
        let mut leaves = ClosestLeaves {
            leaf: LeafRay::new(kernel, self, ray),
            accept,
            leaving: leaving.unwrap_or(u32::MAX),
            best: None,
        };
        kernel.traverse(&self.bvh, ray, stats, &mut leaves);
        leaves.best
    }

    /// [`intersect_closest_packet_with`](Self::intersect_closest_packet_with) on this CPU's
    /// best kernel.
    #[inline]
    pub fn intersect_closest_packet(
        &self,
        rays: &[Ray],
        stats: &mut TraversalStats,
        accept: impl FnMut(usize, u32, &TriangleHit) -> bool,
    ) -> Option<[Option<GeometryHit>; PACKET]> {
        with_node_kernel!(kernel => self.intersect_closest_packet_with(kernel, rays, stats, accept))
    }

    /// [`intersect_closest_with`](Self::intersect_closest_with) for a packet of up to
    /// [`PACKET`] coherent rays that start on no surface, in one walk: each ray's
    /// closest hit that `accept(ray, triangle, hit)` keeps (`ray` an index into `rays`),
    /// found by the same leaf tests as its own walk. `None` when the rays cannot be
    /// bounded as a packet (see [`Bvh::traverse_closest_packet`]): nothing was tested.
    #[inline(always)]
    pub fn intersect_closest_packet_with(
        &self,
        kernel: impl NodeKernel,
        rays: &[Ray],
        stats: &mut TraversalStats,
        mut accept: impl FnMut(usize, u32, &TriangleHit) -> bool,
    ) -> Option<[Option<GeometryHit>; PACKET]> {
        let mut watertight: [Option<WatertightRay>; PACKET] = [None; PACKET];
        let mut best = [None; PACKET];
        let mesh = &self.mesh;
        kernel.traverse_packet(
            &self.bvh,
            rays,
            stats,
            |first, count, rays_in, _, t_max| {
                for ray in mask_bits(rays_in) {
                    let wray =
                        &*watertight[ray].get_or_insert_with(|| WatertightRay::new(&rays[ray]));
                    self.for_hits(
                        kernel,
                        wray,
                        first,
                        count,
                        &mut t_max[ray],
                        |triangle, hit, t| {
                            if accept(ray, triangle, hit) {
                                keep_closest(mesh, &mut best[ray], triangle, hit, t);
                            }
                            false
                        },
                    );
                }
            },
            // Leaf lanes put off by the packet's box test are often entered by no ray:
            // their blocks are not asked for ahead.
            |_| {},
        )?;
        Some(best)
    }

    /// Triangle block `block.index`, when the geometry has it.
    #[inline]
    pub fn block(&self, block: BlockRef) -> Option<&TriangleBlock> {
        self.blocks.get(block.index as usize)
    }

    /// True when some triangle that `accept` keeps is hit with `0 < t < ray.t_max`.
    #[inline]
    pub fn intersect_any(
        &self,
        ray: &Ray,
        stats: &mut TraversalStats,
        accept: impl FnMut(u32, &TriangleHit) -> bool,
    ) -> bool {
        with_node_kernel!(kernel => self.intersect_any_with(kernel, ray, None, stats, accept))
    }

    /// [`intersect_any`](Self::intersect_any) with the box tests of `kernel`, leaving out
    /// triangle `leaving` (the one a secondary ray starts on: a plane cannot be hit again
    /// by a ray leaving it, so its exact test is sure to fail and need not run).
    #[inline(always)]
    pub fn intersect_any_with(
        &self,
        kernel: impl NodeKernel,
        ray: &Ray,
        leaving: Option<u32>,
        stats: &mut TraversalStats,
        accept: impl FnMut(u32, &TriangleHit) -> bool,
    ) -> bool {
        self.occluding_block_with(kernel, ray, leaving, stats, accept)
            .is_some()
    }

    /// [`intersect_any_with`](Self::intersect_any_with) that reports the block holding the
    /// triangle `accept` kept.
    #[inline(always)]
    pub fn occluding_block_with(
        &self,
        kernel: impl NodeKernel,
        ray: &Ray,
        leaving: Option<u32>,
        stats: &mut TraversalStats,
        accept: impl FnMut(u32, &TriangleHit) -> bool,
    ) -> Option<BlockRef> {
        if self.cleared_by(ray, leaving) {
            return None;
        }
        let mut leaves = AnyLeaves {
            leaf: LeafRay::new(kernel, self, ray),
            accept,
            leaving: leaving.unwrap_or(u32::MAX),
            found: None,
        };
        kernel.traverse(&self.bvh, ray, stats, &mut leaves);
        leaves.found
    }

    /// Calls `test(triangle, hit, t_max)` in slot order for the triangles of the leaf
    /// over slots `first .. first + count` that the ray hits before `*t_max` (the exact
    /// test, a block of four at a time against the `*t_max` of its start, each lane then
    /// held to the current one) until it returns true; returns the block where it did.
    /// `test` may lower `*t_max`.
    #[inline(always)]
    fn for_hits(
        &self,
        kernel: impl NodeKernel,
        wray: &WatertightRay,
        first: usize,
        count: usize,
        t_max: &mut f32,
        mut test: impl FnMut(u32, &TriangleHit, &mut f32) -> bool,
    ) -> Option<BlockRef> {
        let start = first / TRIANGLE_BLOCK;
        let mut remaining = count;
        for (index, block) in
            (start..).zip(&self.blocks[start..start + count.div_ceil(TRIANGLE_BLOCK)])
        {
            let lanes = remaining.min(TRIANGLE_BLOCK);
            let hits = kernel.block_hits(wray, block, lanes, *t_max);
            remaining = remaining.saturating_sub(TRIANGLE_BLOCK);
            let mut hit_lanes = hits.mask;
            while hit_lanes != 0 {
                let lane = hit_lanes.trailing_zeros() as usize;
                hit_lanes &= hit_lanes - 1;
                let hit = hits.hit(lane);
                // A lane before this one may have lowered `t_max`: the lane-by-lane
                // test would have met the lower bound.
                if hit.t < *t_max && test(block.triangles[lane & 3], &hit, t_max) {
                    return Some(BlockRef {
                        index: index as u32,
                        lanes: lanes as u32,
                    });
                }
            }
        }
        None
    }

    /// Heap bytes held (mesh, BVH, triangle blocks).
    pub fn memory_bytes(&self) -> usize {
        self.mesh.memory_bytes()
            + self.bvh.memory_bytes()
            + self.blocks.capacity() * std::mem::size_of::<TriangleBlock>()
    }
}

/// What both leaf tests of a bottom level hold: kernel, geometry and ray, with the
/// watertight set-up made at the first leaf (many instance entries reach none).
struct LeafRay<'a, K> {
    kernel: K,
    geometry: &'a Geometry,
    ray: &'a Ray,
    watertight: Option<WatertightRay>,
}

impl<'a, K: NodeKernel> LeafRay<'a, K> {
    #[inline(always)]
    fn new(kernel: K, geometry: &'a Geometry, ray: &'a Ray) -> Self {
        Self {
            kernel,
            geometry,
            ray,
            watertight: None,
        }
    }

    /// Asks for the first triangle block of the leaf starting at slot `first`.
    #[inline(always)]
    fn prefetch(&self, first: usize) {
        if let Some(block) = self.geometry.blocks.get(first / TRIANGLE_BLOCK) {
            prefetch(block);
        }
    }

    /// [`Geometry::for_hits`] with the prepared ray.
    #[inline(always)]
    fn for_hits(
        &mut self,
        first: usize,
        count: usize,
        t_max: &mut f32,
        test: impl FnMut(u32, &TriangleHit, &mut f32) -> bool,
    ) -> Option<BlockRef> {
        let ray = self.ray;
        let wray = &*self
            .watertight
            .get_or_insert_with(|| WatertightRay::new(ray));
        self.geometry
            .for_hits(self.kernel, wray, first, count, t_max, test)
    }
}

/// Takes the accepted hit `hit` on `triangle` as the ray's closest so far, and shortens
/// the ray to it.
#[inline(always)]
fn keep_closest(
    mesh: &TriangleMesh,
    best: &mut Option<GeometryHit>,
    triangle: u32,
    hit: &TriangleHit,
    t_max: &mut f32,
) {
    *best = Some(GeometryHit {
        triangle,
        hit: *hit,
    });
    *t_max = hit.t;
    // Shading the hit starts with its vertex indices: ask for them while the walk goes on.
    if let Some(indices) = mesh.indices.get(triangle as usize) {
        prefetch(indices);
    }
}

/// The closest-hit leaf test of a bottom level, inlined into the traversal loop.
struct ClosestLeaves<'a, K, A> {
    leaf: LeafRay<'a, K>,
    accept: A,
    /// The triangle the ray starts on, or `u32::MAX`.
    leaving: u32,
    best: Option<GeometryHit>,
}

impl<K: NodeKernel, A: FnMut(u32, &TriangleHit) -> bool> LeafVisit for ClosestLeaves<'_, K, A> {
    #[inline(always)]
    fn visit(&mut self, first: usize, count: usize, mut t_max: f32) -> (f32, bool) {
        let Self {
            leaf,
            accept,
            leaving,
            best,
        } = self;
        let mesh = &leaf.geometry.mesh;
        leaf.for_hits(first, count, &mut t_max, |triangle, hit, t_max| {
            if triangle != *leaving && accept(triangle, hit) {
                keep_closest(mesh, best, triangle, hit, t_max);
            }
            false
        });
        (t_max, false)
    }

    #[inline(always)]
    fn prefetch(&self, first: usize, _count: usize) {
        self.leaf.prefetch(first);
    }
}

/// The any-hit leaf test of a bottom level, inlined into the traversal loop: stops at
/// the first triangle `accept` keeps.
struct AnyLeaves<'a, K, A> {
    leaf: LeafRay<'a, K>,
    accept: A,
    /// The triangle the ray starts on, or `u32::MAX`.
    leaving: u32,
    /// The block of the triangle `accept` kept.
    found: Option<BlockRef>,
}

impl<K: NodeKernel, A: FnMut(u32, &TriangleHit) -> bool> LeafVisit for AnyLeaves<'_, K, A> {
    const ANY_HIT: bool = true;

    #[inline(always)]
    fn visit(&mut self, first: usize, count: usize, t_max: f32) -> (f32, bool) {
        let Self {
            leaf,
            accept,
            leaving,
            found,
        } = self;
        let mut limit = t_max;
        *found = leaf.for_hits(first, count, &mut limit, |triangle, hit, _| {
            triangle != *leaving && accept(triangle, hit)
        });
        (t_max, found.is_some())
    }

    #[inline(always)]
    fn prefetch(&self, first: usize, _count: usize) {
        self.leaf.prefetch(first);
    }
}

/// Every mesh of the scene; instances refer to them by [`GeometryId`].
#[derive(Clone, Debug, Default, bevy_ecs::resource::Resource)]
pub struct GeometryLibrary {
    /// Meshes with their BLAS, indexed by `GeometryId.0`.
    pub geometries: Vec<Geometry>,
}

impl GeometryLibrary {
    /// Adds a built geometry and returns its id.
    pub fn add(&mut self, geometry: Geometry) -> GeometryId {
        self.geometries.push(geometry);
        GeometryId(self.geometries.len() as u32 - 1)
    }

    /// The geometry with this id.
    pub fn get(&self, id: GeometryId) -> Option<&Geometry> {
        self.geometries.get(id.0 as usize)
    }

    /// Total unique triangles.
    pub fn triangle_count(&self) -> usize {
        self.geometries
            .iter()
            .map(|g| g.mesh.triangle_count())
            .sum()
    }

    /// Heap bytes held.
    pub fn memory_bytes(&self) -> usize {
        self.geometries.iter().map(Geometry::memory_bytes).sum()
    }
}
