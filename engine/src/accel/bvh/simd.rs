//! The box test of a wide node on two kernels that give the same bits: a portable one
//! (two SSE halves through glam) and AVX2 (one 8-lane register per coordinate), picked
//! once at run time; the same choice for the triangle blocks' exact test and the
//! instances' support-function boxes, the prefetch hints, and the instance transforms'
//! packed columns loaded in four SSE2 loads. This module holds the engine's only
//! `unsafe`: calls into `#[target_feature]` functions, allowed by an [`Avx2`] value that
//! exists only when the CPU has AVX2, and raw loads inside arrays whose length the
//! signature fixes.

use super::traverse::{FAR_SCALE, LeafVisit, NodeRay};
use super::{Bvh, PACKET, PacketBound, TraversalStats, WIDTH, WideNode};
use crate::accel::instance_bounds::SupportTable;
use crate::accel::triangle::{BlockHits, TriangleBlock, WatertightRay};
use crate::util::math::{Aabb, Ray};
use glam::{Affine3A, BVec4A, Vec4};

/// Evaluates `$body` with `$kernel` bound to the best [`NodeKernel`] of this CPU.
/// Dispatch once per query, at its top: nested traversals inside `$body` take the
/// kernel instead of dispatching again.
macro_rules! with_node_kernel {
    ($kernel:ident => $body:expr) => {{
        #[cfg(target_arch = "x86_64")]
        let avx2 = $crate::accel::bvh::simd::Avx2::detect();
        #[cfg(not(target_arch = "x86_64"))]
        let avx2: Option<()> = None;
        match avx2 {
            #[cfg(target_arch = "x86_64")]
            Some($kernel) => $body,
            _ => {
                let $kernel = $crate::accel::bvh::simd::Portable;
                $body
            }
        }
    }};
}
pub(crate) use with_node_kernel;

/// [`SupportTable::transformed_bounds`] compiled for AVX2 where the CPU has it (an
/// instance's eight support directions then fill one register instead of two SSE
/// halves): the same operations in the same order, so the same bits.
#[inline]
pub fn transformed_bounds(table: &SupportTable, transform: &Affine3A) -> Aabb {
    #[cfg(target_arch = "x86_64")]
    if let Some(avx2) = Avx2::detect() {
        return avx2.transformed_bounds(table, transform);
    }
    table.transformed_bounds(transform)
}

/// Slab tests of a ray against the eight child boxes of a node, and the traversal loop
/// built on them.
pub trait NodeKernel: Copy {
    /// `Bvh::traverse_with` on this kernel: with AVX2, one function compiled for it,
    /// so the box tests inline into the loop (and the caller's leaf test, when it is a
    /// [`LeafVisit`] with an `#[inline(always)]` method).
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

    /// Entry distances of the children and a bitmask of the lanes whose box the ray
    /// enters (conservatively) with an entry distance below `limit` (bit `i` for lane
    /// `i`): `limit` is a closest hit widened for the slab test's rounding (`entry_limit`).
    #[inline(always)]
    fn hit_children(self, ray: &NodeRay, node: &WideNode, limit: f32) -> ([f32; WIDTH], u32) {
        let (t, _, mask) = self.hit_children_spans(ray, node, limit);
        (t, mask)
    }

    /// [`hit_children`](Self::hit_children) with each child's span: how far the ray runs
    /// inside its box (the widened exit distance less the entry distance).
    fn hit_children_spans(
        self,
        ray: &NodeRay,
        node: &WideNode,
        limit: f32,
    ) -> ([f32; WIDTH], [f32; WIDTH], u32);

    /// `Bvh::traverse_closest_packet` on this kernel: with AVX2, one function compiled
    /// for it, so the packet's box tests inline into the walk.
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

    /// The packet's box test of `node` ([`PacketBound`]'s, bit for bit).
    #[inline(always)]
    fn packet_hit_children(
        self,
        bound: &PacketBound,
        node: &WideNode,
        limit: f32,
    ) -> ([f32; WIDTH], u32) {
        bound.hit_children(node, limit)
    }

    /// Bit `i` set when lane `i` of `node` is a leaf (a count above zero).
    #[inline(always)]
    fn leaf_lanes(self, node: &WideNode) -> u32 {
        node.counts
            .iter()
            .enumerate()
            .fold(0, |bits, (lane, &count)| {
                bits | (u32::from(count > 0) << lane)
            })
    }

    /// [`WatertightRay::block_hits`] on this kernel, bit for bit: the exact test on the
    /// first `lanes` lanes of `block`, against `t_max`.
    fn block_hits(
        self,
        ray: &WatertightRay,
        block: &TriangleBlock,
        lanes: usize,
        t_max: f32,
    ) -> BlockHits;
}

/// The kernel for any CPU: two four-lane halves.
#[derive(Clone, Copy, Debug)]
pub struct Portable;

impl NodeKernel for Portable {
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

#[cfg(target_arch = "x86_64")]
pub use avx2::{Avx2, affine_from_columns, prefetch, prefetch_children, prefetch_node};

/// The transform whose twelve column values (x axis, y axis, z axis, translation) start
/// `columns`; the thirteenth value only pads the last load. The same bits as
/// `Affine3A::from_cols_array` in the columns' lanes.
#[cfg(not(target_arch = "x86_64"))]
#[inline(always)]
pub fn affine_from_columns(columns: &[f32; 13]) -> Affine3A {
    Affine3A::from_cols_slice(&columns[..12])
}

/// Prefetching is an x86 hint here; elsewhere nothing.
#[cfg(not(target_arch = "x86_64"))]
#[inline(always)]
pub fn prefetch_node(_node: &WideNode) {}

/// Prefetching is an x86 hint here; elsewhere nothing.
#[cfg(not(target_arch = "x86_64"))]
#[inline(always)]
pub fn prefetch<T>(_value: &T) {}

/// Prefetching is an x86 hint here; elsewhere nothing.
#[cfg(not(target_arch = "x86_64"))]
#[inline(always)]
pub fn prefetch_children(_node: &WideNode) {}

#[cfg(target_arch = "x86_64")]
#[expect(
    unsafe_code,
    reason = "AVX2 kernels are #[target_feature] functions: calling them, and loading and \
              storing 128- and 256-bit registers, is unsafe; an Avx2 value proves the CPU has it"
)]
mod avx2 {
    use super::{
        Aabb, Affine3A, FAR_SCALE, LeafVisit, NodeKernel, NodeRay, PACKET, PacketBound,
        SupportTable, WIDTH, WideNode,
    };
    use crate::accel::bvh::{Bvh, TraversalStats};
    use crate::accel::instance_bounds::{CellCorners, DIRECTIONS, SIDE};
    use crate::accel::triangle::{BlockHits, TriangleBlock, WatertightRay, gamma64};
    use crate::util::math::Ray;
    use glam::Vec4;
    use std::arch::x86_64::*;
    use std::sync::OnceLock;

    /// Starts loading all four cache lines of `node` into the cache (SSE, so any x86-64).
    #[inline(always)]
    pub fn prefetch_node(node: &WideNode) {
        let base = std::ptr::from_ref(node).cast::<i8>();
        for line in 0..std::mem::size_of::<WideNode>() / 64 {
            // SAFETY: a prefetch is a hint that never faults, and the address lies
            // inside `node`.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(base.add(line * 64)) };
        }
    }

    /// Starts loading the cache line of `node`'s child references and counts (its last:
    /// a node is 64-byte aligned), which its visit reads only after the box test.
    #[inline(always)]
    pub fn prefetch_children(node: &WideNode) {
        // SAFETY: a prefetch is a hint that never faults, and the address lies inside
        // `node`.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(std::ptr::from_ref(&node.children).cast::<i8>()) };
    }

    /// Starts loading every cache line of `value` (SSE, so any x86-64): for gathers in an
    /// order unrelated to memory, where each load misses.
    #[inline(always)]
    pub fn prefetch<T>(value: &T) {
        let first = std::ptr::from_ref(value).cast::<i8>();
        let last = std::mem::size_of::<T>().max(1) - 1;
        // SAFETY: a prefetch is a hint that never faults; every address lies inside
        // `value` (for a zero-sized one the first is a valid dangling address).
        unsafe {
            let mut offset = 0;
            while offset < last {
                _mm_prefetch::<_MM_HINT_T0>(first.add(offset));
                offset += 64;
            }
            _mm_prefetch::<_MM_HINT_T0>(first.add(last));
        }
    }

    /// The transform whose twelve column values (x axis, y axis, z axis, translation)
    /// start `columns`, in four unaligned 16-byte loads (SSE2, so any x86-64) instead of
    /// twelve scalar inserts: each column's fourth lane holds the next value, which
    /// `Vec3A` leaves unused (the thirteenth value exists so the last load stays inside
    /// the array).
    #[inline(always)]
    pub fn affine_from_columns(columns: &[f32; 13]) -> Affine3A {
        let base = columns.as_ptr();
        // SAFETY: each load reads four f32 at offsets 0, 3, 6 and 9 of thirteen.
        let column = |at: usize| glam::Vec3A::from(unsafe { _mm_loadu_ps(base.add(at)) });
        Affine3A::from_cols(column(0), column(3), column(6), column(9))
    }

    /// Proof that this CPU runs AVX2: only [`detect`](Self::detect) makes one.
    #[derive(Clone, Copy, Debug)]
    pub struct Avx2 {
        _detected: (),
    }

    /// Whether the AVX2 kernel runs: the CPU has AVX2 and `SYLVA_SIMD` is not `portable`.
    static ENABLED: OnceLock<bool> = OnceLock::new();

    impl Avx2 {
        /// The token when this CPU has AVX2, unless the environment variable
        /// `SYLVA_SIMD=portable` asks for the portable kernel (to compare the two).
        #[inline(always)]
        pub fn detect() -> Option<Self> {
            let enabled = *ENABLED.get_or_init(|| {
                std::env::var("SYLVA_SIMD").map_or(true, |v| v != "portable")
                    && Self::on_this_cpu().is_some()
            });
            enabled.then_some(Self { _detected: () })
        }

        /// The token when this CPU has AVX2, whatever `SYLVA_SIMD` says.
        pub fn on_this_cpu() -> Option<Self> {
            is_x86_feature_detected!("avx2").then_some(Self { _detected: () })
        }

        /// [`super::transformed_bounds`] on AVX2.
        #[inline(always)]
        pub fn transformed_bounds(self, table: &SupportTable, transform: &Affine3A) -> Aabb {
            // SAFETY: `self` exists only when `detect` found AVX2 on this CPU.
            unsafe { transformed_bounds(table, transform) }
        }
    }

    /// The support-function box, its inlined body compiled for AVX2, the samples at
    /// the cells' corners gathered eight at a time.
    #[target_feature(enable = "avx2")]
    fn transformed_bounds(table: &SupportTable, transform: &Affine3A) -> Aabb {
        // The closure inherits this function's target features.
        table.transformed_bounds_with(transform, |samples, iu, iv| {
            gather_cell_corners(samples, iu, iv)
        })
    }

    /// [`cell_corners`](crate::accel::instance_bounds::cell_corners) with AVX2 gathers: the same
    /// samples, indices clamped into the table as there.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn gather_cell_corners(
        samples: &[f32; DIRECTIONS],
        iu: &[f32; 8],
        iv: &[f32; 8],
    ) -> CellCorners {
        // SAFETY: 8 f32 each; loads need no alignment.
        let (iu, iv) = unsafe { (_mm256_loadu_ps(iu.as_ptr()), _mm256_loadu_ps(iv.as_ptr())) };
        // Whole numbers in 0 ..= CELLS − 1: the truncation is exact.
        let (i, j) = (_mm256_cvttps_epi32(iu), _mm256_cvttps_epi32(iv));
        let base = _mm256_add_epi32(_mm256_mullo_epi32(i, _mm256_set1_epi32(SIDE as i32)), j);
        let last = _mm256_set1_epi32(DIRECTIONS as i32 - 1);
        let gather = |offset: usize| {
            let index = _mm256_add_epi32(base, _mm256_set1_epi32(offset as i32));
            // In the table whatever the inputs: 0 ..= DIRECTIONS − 1.
            let index = _mm256_max_epi32(_mm256_min_epi32(index, last), _mm256_setzero_si256());
            let mut out = [0.0f32; 8];
            // SAFETY: every index lies in `samples` (clamped above); the store is of
            // eight f32 into `out`.
            unsafe {
                let v = _mm256_i32gather_ps::<4>(samples.as_ptr(), index);
                _mm256_storeu_ps(out.as_mut_ptr(), v);
            }
            out
        };
        [gather(0), gather(SIDE), gather(1), gather(SIDE + 1)]
    }

    /// One traversal loop, kept out of line: inlined into the top level's instance
    /// visit, the bottom-level loop made one function too large for the registers and
    /// the instruction cache (spilled ray constants, a frame 3–8 % slower).
    #[target_feature(enable = "avx2")]
    #[inline(never)]
    fn traverse(bvh: &Bvh, ray: &Ray, stats: &mut TraversalStats, leaves: &mut impl LeafVisit) {
        bvh.traverse_with(Avx2 { _detected: () }, ray, stats, leaves)
    }

    /// The packet walk, kept out of line as [`traverse`] is.
    #[target_feature(enable = "avx2")]
    #[inline(never)]
    fn traverse_packet(
        bvh: &Bvh,
        rays: &[Ray],
        stats: &mut TraversalStats,
        visit: impl FnMut(usize, usize, u32, f32, &mut [f32; PACKET]),
        prefetch: impl Fn(usize),
    ) -> Option<[f32; PACKET]> {
        bvh.traverse_closest_packet_with(Avx2 { _detected: () }, rays, stats, visit, prefetch)
    }

    impl NodeKernel for Avx2 {
        #[inline(always)]
        fn traverse_packet(
            self,
            bvh: &Bvh,
            rays: &[Ray],
            stats: &mut TraversalStats,
            visit: impl FnMut(usize, usize, u32, f32, &mut [f32; PACKET]),
            prefetch: impl Fn(usize),
        ) -> Option<[f32; PACKET]> {
            // SAFETY: `self` exists only when `detect` found AVX2 on this CPU.
            unsafe { traverse_packet(bvh, rays, stats, visit, prefetch) }
        }

        #[inline(always)]
        fn packet_hit_children(
            self,
            bound: &PacketBound,
            node: &WideNode,
            limit: f32,
        ) -> ([f32; WIDTH], u32) {
            if bound.common_origin {
                // SAFETY: `self` exists only when `detect` found AVX2 on this CPU.
                unsafe { packet_hit_children_from_one_origin(bound, node, limit) }
            } else {
                bound.hit_children(node, limit)
            }
        }

        #[inline(always)]
        fn traverse(
            self,
            bvh: &Bvh,
            ray: &Ray,
            stats: &mut TraversalStats,
            leaves: &mut impl LeafVisit,
        ) {
            // SAFETY: `self` exists only when `detect` found AVX2 on this CPU.
            unsafe { traverse(bvh, ray, stats, leaves) }
        }

        #[inline(always)]
        fn hit_children_spans(
            self,
            ray: &NodeRay,
            node: &WideNode,
            limit: f32,
        ) -> ([f32; WIDTH], [f32; WIDTH], u32) {
            // SAFETY: `self` exists only when `detect` found AVX2 on this CPU.
            unsafe { hit_children_spans(ray, node, limit) }
        }

        #[inline(always)]
        fn block_hits(
            self,
            ray: &WatertightRay,
            block: &TriangleBlock,
            lanes: usize,
            t_max: f32,
        ) -> BlockHits {
            // SAFETY: `self` exists only when `detect` found AVX2 on this CPU.
            unsafe { block_hits(ray, block, lanes, t_max) }
        }

        #[inline(always)]
        fn leaf_lanes(self, node: &WideNode) -> u32 {
            // SAFETY: `self` exists only when `detect` found AVX2 on this CPU.
            unsafe { leaf_lanes(node) }
        }
    }

    /// The portable `leaf_lanes` in one compare: eight counts in one register (the
    /// scalar fold took 18 instructions a node, 8 % of a shadow ray's).
    #[target_feature(enable = "avx2")]
    #[inline]
    fn leaf_lanes(node: &WideNode) -> u32 {
        // SAFETY: `counts` holds WIDTH = 8 u32, one 256-bit register's worth.
        let counts = unsafe { _mm256_loadu_si256(node.counts.as_ptr().cast()) };
        let empty = _mm256_cmpeq_epi32(counts, _mm256_setzero_si256());
        !(_mm256_movemask_ps(_mm256_castsi256_ps(empty)) as u32) & 0xff
    }

    /// The portable exact test's f64 operations in the same order on the four lanes of
    /// `block`, one register per value: the edge-sign check, and where a lane passes it,
    /// the rest of the test for all four at once (one division instead of one per lane,
    /// and no chain of scalar calls).
    #[target_feature(enable = "avx2")]
    #[inline]
    fn block_hits(
        ray: &WatertightRay,
        block: &TriangleBlock,
        lanes: usize,
        t_max: f32,
    ) -> BlockHits {
        let ([kx, ky, kz], origin, [sx, sy]) = ray.block_setup();
        let [ox, oy, oz] = origin.map(|o| _mm256_set1_pd(o));
        let (sx, sy) = (_mm256_set1_pd(sx), _mm256_set1_pd(sy));
        // SAFETY: a Vec4 holds four f32.
        let load =
            |v: &Vec4| unsafe { _mm256_cvtps_pd(_mm_loadu_ps(std::ptr::from_ref(v).cast())) };
        let relative = |c: usize| {
            let p = &block.corners[c];
            (
                _mm256_sub_pd(load(&p[kx]), ox),
                _mm256_sub_pd(load(&p[ky]), oy),
                _mm256_sub_pd(load(&p[kz]), oz),
            )
        };
        let sheared = |(x, y, z): (__m256d, __m256d, __m256d)| {
            (
                _mm256_sub_pd(x, _mm256_mul_pd(sx, z)),
                _mm256_sub_pd(y, _mm256_mul_pd(sy, z)),
            )
        };
        let (a, b, c) = (relative(0), relative(1), relative(2));
        let ((ax, ay), (bx, by), (cx, cy)) = (sheared(a), sheared(b), sheared(c));
        let e0 = _mm256_sub_pd(_mm256_mul_pd(bx, cy), _mm256_mul_pd(by, cx));
        let e1 = _mm256_sub_pd(_mm256_mul_pd(cx, ay), _mm256_mul_pd(cy, ax));
        let e2 = _mm256_sub_pd(_mm256_mul_pd(ax, by), _mm256_mul_pd(ay, bx));
        let zero = _mm256_setzero_pd();
        let below = |e: __m256d| _mm256_cmp_pd::<_CMP_LT_OQ>(e, zero);
        let above = |e: __m256d| _mm256_cmp_pd::<_CMP_GT_OQ>(e, zero);
        let negative = _mm256_or_pd(_mm256_or_pd(below(e0), below(e1)), below(e2));
        let positive = _mm256_or_pd(_mm256_or_pd(above(e0), above(e1)), above(e2));
        let outside = _mm256_movemask_pd(_mm256_and_pd(negative, positive)) as u32;
        let possible = !outside & ((1 << lanes.min(4)) - 1);
        if possible == 0 {
            return BlockHits::default();
        }
        let splat = |v: f64| _mm256_set1_pd(v);
        let abs = |v: __m256d| _mm256_andnot_pd(splat(-0.0), v);
        let det = _mm256_add_pd(_mm256_add_pd(e0, e1), e2);
        // det ≠ 0 and finite (an ordered compare is false for NaN).
        let usable = _mm256_and_pd(
            _mm256_cmp_pd::<_CMP_NEQ_OQ>(det, zero),
            _mm256_cmp_pd::<_CMP_LT_OQ>(abs(det), splat(f64::INFINITY)),
        );
        let sz = splat(ray.shear_z());
        let (az, bz, cz) = (
            _mm256_mul_pd(sz, a.2),
            _mm256_mul_pd(sz, b.2),
            _mm256_mul_pd(sz, c.2),
        );
        let t_scaled = _mm256_add_pd(
            _mm256_add_pd(_mm256_mul_pd(e0, az), _mm256_mul_pd(e1, bz)),
            _mm256_mul_pd(e2, cz),
        );
        let t_max_det = _mm256_mul_pd(splat(f64::from(t_max)), det);
        // det < 0: 0 > t_scaled ≥ t_max·det; det > 0: 0 < t_scaled ≤ t_max·det.
        let ahead_negative = _mm256_and_pd(
            _mm256_cmp_pd::<_CMP_LT_OQ>(det, zero),
            _mm256_and_pd(
                _mm256_cmp_pd::<_CMP_LT_OQ>(t_scaled, zero),
                _mm256_cmp_pd::<_CMP_GE_OQ>(t_scaled, t_max_det),
            ),
        );
        let ahead_positive = _mm256_and_pd(
            _mm256_cmp_pd::<_CMP_GT_OQ>(det, zero),
            _mm256_and_pd(
                _mm256_cmp_pd::<_CMP_GT_OQ>(t_scaled, zero),
                _mm256_cmp_pd::<_CMP_LE_OQ>(t_scaled, t_max_det),
            ),
        );
        let ahead = _mm256_or_pd(ahead_negative, ahead_positive);
        let candidates = possible & _mm256_movemask_pd(_mm256_and_pd(usable, ahead)) as u32;
        if candidates == 0 {
            return BlockHits::default();
        }
        let inv_det = _mm256_div_pd(splat(1.0), det);
        let t = _mm256_cvtpd_ps(_mm256_mul_pd(t_scaled, inv_det));
        let before_end = _mm_cmplt_ps(t, _mm_set1_ps(t_max));
        // The bound on t's error (pbrt-v4 §6.8.4 in f64), as the portable test.
        let max3 = |a: __m256d, b: __m256d, c: __m256d| _mm256_max_pd(_mm256_max_pd(a, b), c);
        let max_zt = max3(abs(az), abs(bz), abs(cz));
        let delta_z = _mm256_mul_pd(splat(gamma64(3)), max_zt);
        let max_xt = max3(abs(ax), abs(bx), abs(cx));
        let max_yt = max3(abs(ay), abs(by), abs(cy));
        let delta_x = _mm256_mul_pd(splat(gamma64(5)), _mm256_add_pd(max_xt, max_zt));
        let delta_y = _mm256_mul_pd(splat(gamma64(5)), _mm256_add_pd(max_yt, max_zt));
        let delta_e = _mm256_mul_pd(
            splat(2.0),
            _mm256_add_pd(
                _mm256_add_pd(
                    _mm256_mul_pd(_mm256_mul_pd(splat(gamma64(2)), max_xt), max_yt),
                    _mm256_mul_pd(delta_y, max_xt),
                ),
                _mm256_mul_pd(delta_x, max_yt),
            ),
        );
        let max_e = max3(abs(e0), abs(e1), abs(e2));
        let delta_t = _mm256_mul_pd(
            _mm256_mul_pd(
                splat(3.0),
                _mm256_add_pd(
                    _mm256_add_pd(
                        _mm256_mul_pd(_mm256_mul_pd(splat(gamma64(3)), max_e), max_zt),
                        _mm256_mul_pd(delta_e, max_zt),
                    ),
                    _mm256_mul_pd(delta_z, max_e),
                ),
            ),
            abs(inv_det),
        );
        let t_wide = _mm256_cvtps_pd(t);
        // Not (t ≤ δt or t ≤ 0), NaN included, as the portable test rejects.
        let clear_of_origin = _mm256_and_pd(
            _mm256_cmp_pd::<_CMP_NLE_UQ>(t_wide, delta_t),
            _mm256_cmp_pd::<_CMP_NLE_UQ>(t_wide, zero),
        );
        let weight = |e: __m256d| _mm256_cvtpd_ps(_mm256_mul_pd(e, inv_det));
        let (w0, w1, w2) = (weight(e0), weight(e1), weight(e2));
        let finite = |w: __m128| {
            _mm_cmplt_ps(
                _mm_andnot_ps(_mm_set1_ps(-0.0), w),
                _mm_set1_ps(f32::INFINITY),
            )
        };
        let weights_finite = _mm_and_ps(_mm_and_ps(finite(w0), finite(w1)), finite(w2));
        let accepted = _mm_movemask_ps(_mm_and_ps(before_end, weights_finite)) as u32
            & _mm256_movemask_pd(clear_of_origin) as u32;
        let mut hits = BlockHits {
            mask: candidates & accepted,
            ..BlockHits::default()
        };
        // SAFETY: each destination holds four f32.
        unsafe {
            _mm_storeu_ps(hits.t.as_mut_ptr(), t);
            _mm_storeu_ps(hits.barycentrics[0].as_mut_ptr(), w0);
            _mm_storeu_ps(hits.barycentrics[1].as_mut_ptr(), w1);
            _mm_storeu_ps(hits.barycentrics[2].as_mut_ptr(), w2);
        }
        hits
    }

    /// The box planes of `node` on `axis`, the near one first: the upper plane first when
    /// `near_is_max`.
    #[inline(always)]
    fn near_far_planes(
        node: &WideNode,
        axis: usize,
        near_is_max: bool,
    ) -> (&[f32; WIDTH], &[f32; WIDTH]) {
        let lower = 2 * (axis % 3);
        let near = lower + usize::from(near_is_max);
        let far = lower + usize::from(!near_is_max);
        let planes = std::ptr::from_ref(node).cast::<[f32; WIDTH]>();
        // SAFETY: `WideNode` is `repr(C)` and starts with its six plane arrays in the
        // order min x, max x, min y, max y, min z, max z; both indices are below 6.
        unsafe { (&*planes.add(near), &*planes.add(far)) }
    }

    /// `PacketBound::hit_children_from_one_origin` bit for bit (the same operations in
    /// the same order and operand order), eight lanes at once.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn packet_hit_children_from_one_origin(
        bound: &PacketBound,
        node: &WideNode,
        limit: f32,
    ) -> ([f32; WIDTH], u32) {
        // SAFETY: the arrays hold WIDTH = 8 floats, one 256-bit register's worth.
        let load = |a: &[f32; WIDTH]| unsafe { _mm256_loadu_ps(a.as_ptr()) };
        let mut near = _mm256_setzero_ps();
        let mut far = _mm256_set1_ps(f32::INFINITY);
        for axis in 0..3 {
            let (near_plane, far_plane) = near_far_planes(node, axis, bound.near_is_max[axis]);
            let origin = _mm256_set1_ps(bound.origin_lo[axis]);
            let (i_lo, i_hi) = (
                _mm256_set1_ps(bound.inv_lo[axis]),
                _mm256_set1_ps(bound.inv_hi[axis]),
            );
            let to_near = _mm256_sub_ps(load(near_plane), origin);
            let to_far = _mm256_sub_ps(load(far_plane), origin);
            near = _mm256_max_ps(
                near,
                _mm256_min_ps(_mm256_mul_ps(to_near, i_lo), _mm256_mul_ps(to_near, i_hi)),
            );
            far = _mm256_min_ps(
                far,
                _mm256_max_ps(_mm256_mul_ps(to_far, i_lo), _mm256_mul_ps(to_far, i_hi)),
            );
        }
        let far = _mm256_mul_ps(far, _mm256_set1_ps(FAR_SCALE));
        let hit = _mm256_and_ps(
            _mm256_cmp_ps::<_CMP_LE_OS>(near, far),
            _mm256_cmp_ps::<_CMP_LT_OS>(near, _mm256_set1_ps(limit)),
        );
        let mut t = [0.0; WIDTH];
        // SAFETY: `t` holds WIDTH = 8 floats.
        unsafe { _mm256_storeu_ps(t.as_mut_ptr(), near) };
        (t, _mm256_movemask_ps(hit) as u32)
    }

    /// The portable kernel's results bit for bit, eight lanes at once.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn hit_children_spans(
        ray: &NodeRay,
        node: &WideNode,
        limit: f32,
    ) -> ([f32; WIDTH], [f32; WIDTH], u32) {
        // SAFETY: the arrays hold WIDTH = 8 floats, one 256-bit register's worth.
        let load = |a: &[f32; WIDTH]| unsafe { _mm256_loadu_ps(a.as_ptr()) };
        let [ox, oy, oz] = ray.origin.map(|v| _mm256_set1_ps(v));
        let [ix, iy, iz] = ray.inv_dir.map(|v| _mm256_set1_ps(v));
        let zero = _mm256_setzero_ps();
        let (near, far, used) = if ray.axis_parallel {
            let x0 = _mm256_mul_ps(_mm256_sub_ps(load(&node.min_x), ox), ix);
            let x1 = _mm256_mul_ps(_mm256_sub_ps(load(&node.max_x), ox), ix);
            let y0 = _mm256_mul_ps(_mm256_sub_ps(load(&node.min_y), oy), iy);
            let y1 = _mm256_mul_ps(_mm256_sub_ps(load(&node.max_y), oy), iy);
            let z0 = _mm256_mul_ps(_mm256_sub_ps(load(&node.min_z), oz), iz);
            let z1 = _mm256_mul_ps(_mm256_sub_ps(load(&node.max_z), oz), iz);
            let is_number = |a: __m256| _mm256_cmp_ps::<_CMP_EQ_OQ>(a, a);
            let negate = |a: __m256| _mm256_xor_ps(a, _mm256_set1_ps(-0.0));
            // See the portable kernel: NaN distances open their slab.
            let open = |a: __m256, b: __m256| {
                let a = _mm256_blendv_ps(negate(b), a, is_number(a));
                let b = _mm256_blendv_ps(negate(a), b, is_number(b));
                (
                    _mm256_blendv_ps(_mm256_set1_ps(f32::NEG_INFINITY), a, is_number(a)),
                    _mm256_blendv_ps(_mm256_set1_ps(f32::INFINITY), b, is_number(b)),
                )
            };
            let ((x0, x1), (y0, y1), (z0, z1)) = (open(x0, x1), open(y0, y1), open(z0, z1));
            let near = _mm256_max_ps(
                _mm256_max_ps(_mm256_min_ps(x0, x1), _mm256_min_ps(y0, y1)),
                _mm256_max_ps(_mm256_min_ps(z0, z1), zero),
            );
            let far = _mm256_min_ps(
                _mm256_min_ps(_mm256_max_ps(x0, x1), _mm256_max_ps(y0, y1)),
                _mm256_max_ps(z0, z1),
            );
            let used =
                _mm256_cmp_ps::<_CMP_LT_OS>(load(&node.min_x), _mm256_set1_ps(f32::INFINITY));
            (near, far, Some(used))
        } else {
            // Every reciprocal here is finite and non-zero (or NaN, which poisons both
            // planes alike) and every plane is finite or +∞ in both arrays of a lane, so
            // of an axis's two distances the near plane's is the smaller (both equal
            // when both are ±∞ or NaN): the portable kernel's min and max, bit for bit,
            // for six fewer operations.
            let distances = |axis: usize, origin: __m256, inv_dir: __m256| {
                let (near, far) = near_far_planes(node, axis, ray.near_is_max[axis]);
                (
                    _mm256_mul_ps(_mm256_sub_ps(load(near), origin), inv_dir),
                    _mm256_mul_ps(_mm256_sub_ps(load(far), origin), inv_dir),
                )
            };
            let (near_x, far_x) = distances(0, ox, ix);
            let (near_y, far_y) = distances(1, oy, iy);
            let (near_z, far_z) = distances(2, oz, iz);
            let near = _mm256_max_ps(_mm256_max_ps(near_x, near_y), _mm256_max_ps(near_z, zero));
            let far = _mm256_min_ps(_mm256_min_ps(far_x, far_y), far_z);
            (near, far, None)
        };
        let t_far = _mm256_mul_ps(far, _mm256_set1_ps(FAR_SCALE));
        let mut hit = _mm256_and_ps(
            _mm256_cmp_ps::<_CMP_LE_OS>(near, t_far),
            _mm256_cmp_ps::<_CMP_LT_OS>(near, _mm256_set1_ps(limit)),
        );
        if let Some(used) = used {
            hit = _mm256_and_ps(hit, used);
        }
        let (mut t, mut span) = ([0.0; WIDTH], [0.0; WIDTH]);
        // SAFETY: `t` and `span` hold WIDTH = 8 floats each.
        unsafe {
            _mm256_storeu_ps(t.as_mut_ptr(), near);
            _mm256_storeu_ps(span.as_mut_ptr(), _mm256_sub_ps(t_far, near));
        }
        (t, span, _mm256_movemask_ps(hit) as u32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn uniform(state: &mut u64) -> f32 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (*state >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Nodes and rays with the awkward values: unused lanes, boxes the origin sits on,
    /// axis-parallel and denormal directions, NaN.
    fn cases() -> Vec<(NodeRay, WideNode, f32)> {
        let mut state = 7;
        let specials = [0.0, -0.0, 1e-40, -1e-40, f32::INFINITY, f32::NAN, 1.0, -1.0];
        let mut out = Vec::new();
        for i in 0..4000 {
            let mut node = WideNode::empty();
            for lane in 0..WIDTH {
                if (i + lane) % 5 == 0 {
                    continue;
                }
                let mut c = [0.0; 6];
                for v in &mut c {
                    *v = (uniform(&mut state) - 0.5) * 8.0;
                }
                if (i + lane) % 3 == 0 {
                    // Flat, as a leaf's box can be: entry and exit coincide.
                    c[3 + lane % 3] = c[lane % 3];
                }
                let b = crate::util::math::Aabb {
                    min: glam::Vec3A::new(c[0].min(c[3]), c[1].min(c[4]), c[2].min(c[5])),
                    max: glam::Vec3A::new(c[0].max(c[3]), c[1].max(c[4]), c[2].max(c[5])),
                };
                node.set_box(lane, b);
            }
            let mut origin = [0.0; 3].map(|_: f32| (uniform(&mut state) - 0.5) * 10.0);
            let mut direction = [0.0; 3].map(|_: f32| uniform(&mut state) - 0.5);
            if i % 3 == 0 {
                direction[i % 3] = specials[(i / 3) % specials.len()];
            }
            if i % 7 == 0 {
                // On a face of lane 1's box.
                origin[0] = node.min_x[1];
            }
            let ray = crate::util::math::Ray::new(origin.into(), direction.into());
            let t_max = [f32::INFINITY, 3.0, 0.5][i % 3];
            out.push((NodeRay::new(&ray), node, t_max));
        }
        out
    }

    /// The AVX2 token; these tests need an AVX2 machine (CI has one).
    #[cfg(target_arch = "x86_64")]
    fn avx2_here() -> Avx2 {
        Avx2::on_this_cpu().expect("this test needs an AVX2 machine (CI has one)")
    }

    #[test]
    fn transforms_from_packed_columns_transform_as_the_scalar_ones() {
        let mut state = 11;
        for case in 0..1000 {
            let mut values = [0.0f32; 13];
            for v in &mut values {
                *v = (uniform(&mut state) - 0.5) * 10f32.powi(case % 7 - 3);
            }
            // The padding value must not leak into any lane the transform uses.
            values[12] = [f32::NAN, f32::INFINITY, 1e-40, -7.0][case as usize % 4];
            let packed = affine_from_columns(&values);
            let scalar = Affine3A::from_cols_slice(&values[..12]);
            assert_eq!(packed.to_cols_array(), scalar.to_cols_array());
            let p = glam::Vec3A::new(uniform(&mut state), -2.0, uniform(&mut state) * 1e3);
            let (a, b) = (packed.transform_point3a(p), scalar.transform_point3a(p));
            assert_eq!(
                a.to_array().map(f32::to_bits),
                b.to_array().map(f32::to_bits)
            );
            let (a, b) = (packed.transform_vector3a(p), scalar.transform_vector3a(p));
            assert_eq!(
                a.to_array().map(f32::to_bits),
                b.to_array().map(f32::to_bits)
            );
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_and_portable_kernels_give_the_same_bits() {
        let avx2 = avx2_here();
        let mut hits = 0;
        for (ray, node, t_max) in cases() {
            let (t_a, s_a, m_a) = avx2.hit_children_spans(&ray, &node, t_max);
            let (t_p, s_p, m_p) = Portable.hit_children_spans(&ray, &node, t_max);
            assert_eq!(m_a, m_p, "masks differ for {ray:?} {node:?}");
            for lane in 0..WIDTH {
                assert_eq!(t_a[lane].to_bits(), t_p[lane].to_bits(), "lane {lane}");
                assert_eq!(
                    s_a[lane].to_bits(),
                    s_p[lane].to_bits(),
                    "span, lane {lane}"
                );
            }
            hits += m_a.count_ones();
        }
        assert!(hits > 1000, "too few boxes hit ({hits}) to compare");
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_and_portable_packet_bounds_give_the_same_bits() {
        let avx2 = avx2_here();
        let (mut bounds, mut hits) = (0, 0);
        for (i, (ray, node, t_max)) in cases().into_iter().enumerate() {
            // A packet from the case's origin, its directions spread around the case's.
            let mut state = i as u64 + 1;
            let spread = [0.001, 0.05, 0.5][i % 3];
            let rays: Vec<NodeRay> = (0..1 + i % PACKET)
                .map(|_| {
                    let d = glam::Vec3A::from(ray.inv_dir).recip()
                        + glam::Vec3A::new(
                            uniform(&mut state) - 0.5,
                            uniform(&mut state) - 0.5,
                            uniform(&mut state) - 0.5,
                        ) * spread;
                    NodeRay::new(&crate::util::math::Ray::new(ray.origin.into(), d))
                })
                .collect();
            let Some(bound) = PacketBound::new(&rays) else {
                continue;
            };
            bounds += 1;
            // A packet's limit is its farthest ray's: mostly open.
            let limit = if i % 4 == 0 { t_max } else { f32::INFINITY };
            let (t_a, m_a) = avx2.packet_hit_children(&bound, &node, limit);
            let (t_p, m_p) = Portable.packet_hit_children(&bound, &node, limit);
            assert_eq!(m_a, m_p, "masks differ for {bound:?} {node:?}");
            for lane in 0..WIDTH {
                assert_eq!(t_a[lane].to_bits(), t_p[lane].to_bits(), "lane {lane}");
            }
            hits += m_a.count_ones();
        }
        assert!(bounds > 1000, "only {bounds} packets could be bounded");
        assert!(hits > 500, "too few boxes hit ({hits}) to compare");
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_and_portable_leaf_lanes_agree() {
        let avx2 = avx2_here();
        let mut node = WideNode::empty();
        // Every pattern of leaf lanes, with counts up to the largest a lane can hold.
        for pattern in 0..256u32 {
            for lane in 0..WIDTH {
                let leaf = pattern >> lane & 1 == 1;
                node.counts[lane] = if leaf {
                    [1, 4, 255, u32::MAX][lane % 4]
                } else {
                    0
                };
            }
            assert_eq!(Portable.leaf_lanes(&node), pattern);
            assert_eq!(avx2.leaf_lanes(&node), pattern, "counts {:?}", node.counts);
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_and_portable_instance_boxes_give_the_same_bits() {
        let avx2 = avx2_here();
        let mut state = 5;
        let points: Vec<glam::Vec3> = (0..300)
            .map(|_| glam::Vec3::new(uniform(&mut state) - 0.5, uniform(&mut state) * 4.0, 0.3))
            .collect();
        let table = SupportTable::new(&points);
        for i in 0..5_000 {
            let scale = 10f32.powi(i % 7 - 3);
            let mut entry = || (uniform(&mut state) - 0.5) * scale;
            let mut transform = Affine3A::from_cols_array(&[0.0; 12].map(|_: f32| entry()));
            if i % 5 == 0 {
                // Plant-like: a turn about the stem, axis-aligned rows included.
                transform = Affine3A::from_rotation_y(i as f32 * 0.25);
            }
            let (a, p) = (
                avx2.transformed_bounds(&table, &transform),
                table.transformed_bounds(&transform),
            );
            let bits = |b: Aabb| [b.min.to_array(), b.max.to_array()].map(|v| v.map(f32::to_bits));
            assert_eq!(bits(a), bits(p), "case {i}: {transform:?}");
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_and_portable_block_tests_give_the_same_bits() {
        let avx2 = avx2_here();
        let mut state = 11;
        let specials = [0.0, -0.0, 1e-40, f32::INFINITY, f32::NAN, 1e30, -1e-30];
        let (mut passed, mut compared, mut hits) = (0, 0, 0);
        for i in 0..20_000 {
            let scale = 10f32.powi(i % 5 - 2);
            let mut corner =
                || glam::Vec3A::from([0.0; 3].map(|_: f32| (uniform(&mut state) - 0.5) * scale));
            let count = 1 + i as usize % 4;
            let mut triangles: Vec<(u32, [glam::Vec3A; 3])> = (0..count)
                .map(|t| (t as u32, [corner(), corner(), corner()]))
                .collect();
            if i % 7 == 0 {
                // Degenerate: an edge function is exactly zero.
                let last = triangles.len() - 1;
                triangles[last].1[2] = triangles[last].1[1];
            }
            if i % 17 == 0 {
                triangles[0].1[1].y = specials[(i / 17) as usize % specials.len()];
            }
            let mut origin = [0.0; 3].map(|_: f32| (uniform(&mut state) - 0.5) * 2.0 * scale);
            let on_edge = i % 11 == 0;
            if on_edge {
                // An axis-parallel ray through the edge p0 p1 (made parallel to y): an
                // edge function is exactly zero and the others agree in sign.
                let [p0, p1, _] = &mut triangles[0].1;
                p1.x = p0.x;
                origin[0] = p0.x;
                origin[1] = 0.5 * (p0.y + p1.y);
            }
            let block = TriangleBlock::new(&triangles);
            // Aimed near the first triangle, so lanes pass and fail in about equal shares.
            let [p0, p1, p2] = triangles[0].1;
            let noise = [0.0; 3].map(|_: f32| (uniform(&mut state) - 0.5) * scale * 0.6);
            let target = (p0 + p1 + p2) / 3.0 + glam::Vec3A::from(noise);
            let mut direction = (target - glam::Vec3A::from(origin)).to_array();
            if i % 5 == 0 {
                direction[i as usize % 3] = specials[(i / 5) as usize % specials.len()];
            }
            if on_edge {
                direction = [0.0, 0.0, if i % 2 == 0 { 1.0 } else { -1.0 }];
            }
            let ray = crate::util::math::Ray::new(origin.into(), direction.into());
            if !ray.direction.is_finite() || ray.direction == glam::Vec3A::ZERO {
                continue;
            }
            let watertight = WatertightRay::new(&ray);
            passed += watertight.possible_hits(&block, count).count_ones();
            compared += count as u32;
            // Ends that cut some hits off.
            let reach = (target - glam::Vec3A::from(origin)).length();
            let t_max = [f32::INFINITY, reach, 0.5 * reach, 0.0][i as usize % 4];
            let a = avx2.block_hits(&watertight, &block, count, t_max);
            let p = Portable.block_hits(&watertight, &block, count, t_max);
            assert_eq!(
                a.mask, p.mask,
                "block {triangles:?}, {ray:?}, t_max {t_max}"
            );
            for lane in (0..4).filter(|lane| a.mask >> lane & 1 == 1) {
                let bits = |hits: &BlockHits| {
                    let hit = hits.hit(lane);
                    (
                        hit.t.to_bits(),
                        hit.barycentrics.to_array().map(f32::to_bits),
                    )
                };
                assert_eq!(bits(&a), bits(&p), "lane {lane} of {triangles:?}, {ray:?}");
            }
            hits += a.mask.count_ones();
        }
        assert!(
            passed > compared / 20 && passed < compared * 19 / 20,
            "{passed} of {compared} lanes passed: too one-sided to compare"
        );
        assert!(
            hits > compared / 20 && hits < passed,
            "{hits} of {passed} passing lanes hit: too one-sided to compare"
        );
    }
}
