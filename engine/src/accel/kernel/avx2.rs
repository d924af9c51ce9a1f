//! The AVX2 kernel: one 8-lane register per coordinate for a node's box tests (single
//! rays and packets), the traversal loops compiled for AVX2 as a whole, a triangle
//! block's exact test four lanes at a time and an instance's support-function box eight
//! directions at a time; the same bits as the portable kernel. Calling a
//! `#[target_feature]` function is allowed by an [`Avx2`] value, which exists only when
//! the CPU has AVX2.
#![expect(
    unsafe_code,
    reason = "AVX2 kernels are #[target_feature] functions: calling them, and loading and \
              storing 128- and 256-bit registers, is unsafe; an Avx2 value proves the CPU has it"
)]

use super::NodeKernel;
use crate::accel::bvh::{Bvh, FAR_SCALE, LeafVisit, NodeRay, PACKET, PacketBound, WIDTH, WideNode};
use crate::accel::instance_bounds::{CellCorners, DIRECTIONS, SIDE, SupportTable};
use crate::accel::triangle::{BlockHits, TriangleBlock, WatertightRay, gamma64};
use crate::util::math::{Aabb, Ray};
use crate::util::stats::TraversalStats;
use glam::{Affine3A, Vec4};
use std::arch::x86_64::*;
use std::sync::OnceLock;

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
fn gather_cell_corners(samples: &[f32; DIRECTIONS], iu: &[f32; 8], iv: &[f32; 8]) -> CellCorners {
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
fn block_hits(ray: &WatertightRay, block: &TriangleBlock, lanes: usize, t_max: f32) -> BlockHits {
    let ([kx, ky, kz], origin, [sx, sy]) = ray.block_setup();
    let [ox, oy, oz] = origin.map(|o| _mm256_set1_pd(o));
    let (sx, sy) = (_mm256_set1_pd(sx), _mm256_set1_pd(sy));
    // SAFETY: a Vec4 holds four f32.
    let load = |v: &Vec4| unsafe { _mm256_cvtps_pd(_mm_loadu_ps(std::ptr::from_ref(v).cast())) };
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
        let used = _mm256_cmp_ps::<_CMP_LT_OS>(load(&node.min_x), _mm256_set1_ps(f32::INFINITY));
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
