//! Watertight ray–triangle intersection (Woop, Benthin, Wald 2013, "Watertight
//! Ray/Triangle Intersection"), with pbrt-v4's conservative bound on `t` and the error
//! bound of the reconstructed hit point.

use crate::util::math::{ErrorPoint, Ray, gamma};
use glam::{Vec3A, Vec4};

/// A ray prepared for the watertight test: axis permutation and shear constants.
#[derive(Clone, Copy, Debug)]
pub struct WatertightRay {
    origin: Vec3A,
    /// The origin's coordinates in the order `kx`, `ky`, `kz`, in f64 (converted once
    /// per ray, not at every leaf).
    origin_permuted: [f64; 3],
    /// The x and y shear constants in f64.
    shear_xy: [f64; 2],
    kx: usize,
    ky: usize,
    kz: usize,
    shear: Vec3A,
}

/// Four triangles in structure-of-arrays form, the unit of the bottom-level leaf test:
/// `corners[c][axis]` holds coordinate `axis` (x, y, z) of corner `c` of the four lanes'
/// triangles, so a ray reads the axes in its own order with plain loads. 160 bytes,
/// aligned to 32 rather than to a cache line: a block spans three lines either way, and
/// the tighter packing saves a sixth of the blocks' memory (30 MB on `paper`).
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(32))]
pub struct TriangleBlock {
    /// Corner `c`, axis `axis`, four lanes.
    pub corners: [[Vec4; 3]; 3],
    /// The mesh's index of each lane's triangle.
    pub triangles: [u32; 4],
}

// The layout the comment above describes: no padding after the triangle indices.
const _: () = assert!(std::mem::size_of::<TriangleBlock>() == 160);

impl TriangleBlock {
    /// The block of up to four triangles `(index, corners)`; lanes past them repeat the
    /// last one (callers mask them by count).
    pub fn new(triangles: &[(u32, [Vec3A; 3])]) -> Self {
        assert!(
            (1..=4).contains(&triangles.len()),
            "a block holds 1 to 4 triangles, not {}",
            triangles.len()
        );
        let lane = |i: usize| triangles[i.min(triangles.len() - 1)];
        let mut block = Self {
            corners: [[Vec4::ZERO; 3]; 3],
            triangles: [0; 4],
        };
        for i in 0..4 {
            let (index, corners) = lane(i);
            block.triangles[i] = index;
            for (c, corner) in corners.iter().enumerate() {
                for axis in 0..3 {
                    block.corners[c][axis][i] = corner[axis];
                }
            }
        }
        block
    }

    /// The corners of lane `lane`'s triangle.
    pub fn triangle(&self, lane: usize) -> [Vec3A; 3] {
        [0, 1, 2].map(|c| {
            let p = &self.corners[c];
            Vec3A::new(p[0][lane], p[1][lane], p[2][lane])
        })
    }
}

/// Where a ray meets a triangle: distance and barycentric weights of vertices 0, 1, 2.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriangleHit {
    /// Ray parameter of the hit.
    pub t: f32,
    /// Weights `(b0, b1, b2)` of the three vertices; they sum to 1.
    pub barycentrics: Vec3A,
}

/// The exact test's results on the four lanes of a [`TriangleBlock`]: bit `i` of `mask`
/// is set when lane `i` is hit, and its hit is [`hit(i)`](Self::hit).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BlockHits {
    /// The lanes hit.
    pub mask: u32,
    /// Each lane's hit distance (meaningful where `mask` is set).
    pub t: [f32; 4],
    /// Each lane's barycentric weights, one array per vertex.
    pub barycentrics: [[f32; 4]; 3],
}

impl BlockHits {
    /// The hit of lane `lane`.
    #[inline(always)]
    pub fn hit(&self, lane: usize) -> TriangleHit {
        let lane = lane & 3;
        TriangleHit {
            t: self.t[lane],
            barycentrics: Vec3A::new(
                self.barycentrics[0][lane],
                self.barycentrics[1][lane],
                self.barycentrics[2][lane],
            ),
        }
    }

    /// Records `hit` as lane `lane`'s.
    #[inline(always)]
    fn set(&mut self, lane: usize, hit: &TriangleHit) {
        let lane = lane & 3;
        self.mask |= 1 << lane;
        self.t[lane] = hit.t;
        for (vertex, weights) in self.barycentrics.iter_mut().enumerate() {
            weights[lane] = hit.barycentrics[vertex];
        }
    }
}

impl WatertightRay {
    /// Prepares `ray` (its direction must be non-zero and finite).
    #[inline]
    pub fn new(ray: &Ray) -> Self {
        let d = ray.direction;
        let ad = d.abs();
        // kz is the axis of the largest |component|, the first one on ties, picked without
        // branches (every instance a ray enters prepares its own ray: branches on the
        // direction mispredicted there).
        let x_largest = (ad.x >= ad.y) & (ad.x >= ad.z);
        let y_largest = !x_largest & (ad.y >= ad.z);
        let kz = usize::from(y_largest) | (usize::from(!x_largest & !y_largest) << 1);
        // Padded to four so that indices masked to two bits need no bounds check.
        let along = [d.x, d.y, d.z, 0.0];
        let from_origin = [ray.origin.x, ray.origin.y, ray.origin.z, 0.0];
        let (next, after) = ([1, 2, 0, 0][kz], [2, 0, 1, 0][kz]);
        // Keep the winding of the sheared triangle independent of the direction's sign.
        let negative = along[kz] < 0.0;
        let kx = if negative { after } else { next };
        let ky = if negative { next } else { after };
        let dz = along[kz];
        let shear = Vec3A::new(along[kx & 3], along[ky & 3], 1.0) / Vec3A::new(dz, dz, dz);
        Self {
            origin: ray.origin,
            origin_permuted: [from_origin[kx & 3], from_origin[ky & 3], from_origin[kz]]
                .map(f64::from),
            shear_xy: [f64::from(shear.x), f64::from(shear.y)],
            kx,
            ky,
            kz,
            shear,
        }
    }

    /// Intersects the triangle `(p0, p1, p2)` for `0 < t < t_max`; both faces count.
    ///
    /// Everything after the ray set-up runs in f64 on the f32 inputs. Watertightness
    /// needs only that a vertex is sheared the same way for every triangle and that a
    /// shared edge's function is the negation of its neighbour's, which holds in any
    /// precision; f64 keeps tiny coordinates out of denormals, and keeps the error bound
    /// on t small, so a nearly edge-on triangle's hit is not thrown away as "possibly
    /// behind the origin" (in f32 that bound exceeded t itself for such triangles and
    /// 96 of 10⁷ rays aimed at a closed mesh's edges and vertices leaked).
    ///
    /// Most tested triangles are missed by a wide margin: an f32 pass decides those first
    /// ([`misses_certainly`](Self::misses_certainly)), and only the rest pay for f64. The
    /// result is the f64 test's, bit for bit.
    #[inline]
    pub fn intersect(&self, p0: Vec3A, p1: Vec3A, p2: Vec3A, t_max: f32) -> Option<TriangleHit> {
        if self.misses_certainly(p0, p1, p2) {
            return None;
        }
        self.intersect_exact(p0, p1, p2, t_max)
    }

    /// True when the f32 edge functions show, beyond their rounding error, that the ray
    /// passes outside the triangle: two of them have opposite signs. The f64 edge
    /// functions of [`intersect_exact`](Self::intersect_exact) then have the same signs,
    /// so it would reject the triangle too and watertightness is untouched.
    ///
    /// Error bound: each sheared coordinate `x = a_kx − s·a_kz` is within `3u·X` of its
    /// exact value (`u = 2⁻²⁴`, `X` the largest `|a_kx| + |s·a_kz|` of the three
    /// vertices), so an edge function `b_x c_y − b_y c_x` is within `16u·X·Y` (two
    /// perturbed products, their rounding and the subtraction's); the test uses twice
    /// that. Tiny or non-finite magnitudes, where underflow would void the bound, are
    /// left to the exact test.
    #[inline]
    pub fn misses_certainly(&self, p0: Vec3A, p1: Vec3A, p2: Vec3A) -> bool {
        let (a, b, c) = (
            (p0 - self.origin).to_array(),
            (p1 - self.origin).to_array(),
            (p2 - self.origin).to_array(),
        );
        let (kx, ky, kz) = (self.kx, self.ky, self.kz);
        let along = |k: usize| Vec3A::new(a[k], b[k], c[k]);
        let (vx, vy, vz) = (along(kx), along(ky), along(kz));
        let (sx, sy) = (self.shear.x, self.shear.y);
        let x = vx - sx * vz;
        let y = vy - sy * vz;
        // (e0, e1, e2) = (b_x c_y − b_y c_x, c_x a_y − c_y a_x, a_x b_y − a_y b_x).
        let rotate = |v: Vec3A| Vec3A::new(v.y, v.z, v.x);
        let rotate_twice = |v: Vec3A| Vec3A::new(v.z, v.x, v.y);
        let e = rotate(x) * rotate_twice(y) - rotate(y) * rotate_twice(x);
        let magnitude_x = (vx.abs() + (sx * vz).abs()).max_element();
        let magnitude_y = (vy.abs() + (sy * vz).abs()).max_element();
        let bound = 32.0 * f32::EPSILON * 0.5 * magnitude_x * magnitude_y;
        if !(bound.is_finite() && bound >= MIN_RELIABLE_BOUND && e.is_finite()) {
            return false;
        }
        e.cmplt(Vec3A::splat(-bound)).any() && e.cmpgt(Vec3A::splat(bound)).any()
    }

    /// The first step of [`intersect_exact`](Self::intersect_exact) on the four lanes of
    /// `block`: bit `i` is set when lane `i` (of the first `lanes`) passes the exact
    /// test's edge-sign check, computed with its f64 operations in the same order, so a
    /// cleared bit is a lane the exact test rejects. Only set lanes need
    /// [`intersect_lane`](Self::intersect_lane). There is no error margin leaving lanes
    /// undecided, as in the f32 pass of [`misses_certainly`](Self::misses_certainly).
    /// [`block_hits`](Self::block_hits) starts with it.
    pub fn possible_hits(&self, block: &TriangleBlock, lanes: usize) -> u32 {
        let mut mask = 0;
        for lane in 0..lanes.min(4) {
            let [a, b, c] = self.relative_corners(block, lane);
            let edges = edge_functions(self.sheared_xy(a), self.sheared_xy(b), self.sheared_xy(c));
            mask |= u32::from(!passes_outside(edges)) << lane;
        }
        mask
    }

    /// [`intersect_lane`](Self::intersect_lane) on each of the first `lanes` lanes of
    /// `block` that [`possible_hits`](Self::possible_hits) lets through, all against
    /// `t_max`. The portable reference of `NodeKernel::block_hits`, which the AVX2 kernel
    /// computes four lanes per register, bit for bit the same.
    pub fn block_hits(&self, block: &TriangleBlock, lanes: usize, t_max: f32) -> BlockHits {
        let mut hits = BlockHits::default();
        let mut possible = self.possible_hits(block, lanes);
        while possible != 0 {
            let lane = possible.trailing_zeros() as usize;
            possible &= possible - 1;
            if let Some(hit) = self.intersect_lane(block, lane, t_max) {
                hits.set(lane, &hit);
            }
        }
        hits
    }

    /// The shear constant of the z axis (1 / the direction's largest component), in f64.
    #[inline(always)]
    pub(crate) fn shear_z(&self) -> f64 {
        f64::from(self.shear.z)
    }

    /// What the block check needs: the axis order `(kx, ky, kz)`, the origin in that
    /// order and the x and y shear constants.
    #[inline(always)]
    pub(crate) fn block_setup(&self) -> ([usize; 3], [f64; 3], [f64; 2]) {
        (
            [self.kx, self.ky, self.kz],
            self.origin_permuted,
            self.shear_xy,
        )
    }

    /// Corners of lane `lane` of `block` relative to the origin, in the ray's axis order
    /// (x, y, z = kx, ky, kz), in f64.
    #[inline(always)]
    fn relative_corners(&self, block: &TriangleBlock, lane: usize) -> [(f64, f64, f64); 3] {
        let lane = lane & 3;
        let [ox, oy, oz] = self.origin_permuted;
        // Plain indexing: array `map` here stayed an out-of-line call per lane test.
        let relative = |c: usize| {
            let corner = &block.corners[c];
            let along = |axis: usize| -> f64 {
                let lanes: &[f32; 4] = corner[axis].as_ref();
                f64::from(lanes[lane])
            };
            (
                along(self.kx) - ox,
                along(self.ky) - oy,
                along(self.kz) - oz,
            )
        };
        [relative(0), relative(1), relative(2)]
    }

    /// The sheared x and y of a corner relative to the origin (the exact test's first
    /// step).
    #[inline(always)]
    fn sheared_xy(&self, (x, y, z): (f64, f64, f64)) -> (f64, f64) {
        let [sx, sy] = self.shear_xy;
        (x - sx * z, y - sy * z)
    }

    /// [`intersect_exact`](Self::intersect_exact) on lane `lane` of `block`, bit for bit.
    /// Out of line: only lanes that [`possible_hits`](Self::possible_hits) lets through
    /// get here, and inlined into the traversal loop the f64 test crowded its registers.
    #[inline(never)]
    pub fn intersect_lane(
        &self,
        block: &TriangleBlock,
        lane: usize,
        t_max: f32,
    ) -> Option<TriangleHit> {
        let [a, b, c] = self.relative_corners(block, lane);
        self.exact_from_relative(a, b, c, t_max)
    }

    /// The watertight test itself, in f64 after the f32 ray set-up.
    #[inline]
    pub fn intersect_exact(
        &self,
        p0: Vec3A,
        p1: Vec3A,
        p2: Vec3A,
        t_max: f32,
    ) -> Option<TriangleHit> {
        let (kx, ky, kz) = (self.kx, self.ky, self.kz);
        let origin = self.origin.as_dvec3();
        let relative = |p: Vec3A| {
            let r = p.as_dvec3() - origin;
            (r[kx], r[ky], r[kz])
        };
        self.exact_from_relative(relative(p0), relative(p1), relative(p2), t_max)
    }

    /// The f64 test on corners relative to the origin, in the ray's axis order.
    #[inline(always)]
    fn exact_from_relative(
        &self,
        a: (f64, f64, f64),
        b: (f64, f64, f64),
        c: (f64, f64, f64),
        t_max: f32,
    ) -> Option<TriangleHit> {
        let sz = f64::from(self.shear.z);
        let (ax, ay) = self.sheared_xy(a);
        let (bx, by) = self.sheared_xy(b);
        let (cx, cy) = self.sheared_xy(c);
        let (e0, e1, e2) = edge_functions((ax, ay), (bx, by), (cx, cy));
        if passes_outside((e0, e1, e2)) {
            return None;
        }
        let det = e0 + e1 + e2;
        if det == 0.0 || !det.is_finite() {
            return None;
        }
        let az = sz * a.2;
        let bz = sz * b.2;
        let cz = sz * c.2;
        let t_scaled = e0 * az + e1 * bz + e2 * cz;
        let t_max64 = f64::from(t_max);
        if det < 0.0 && (t_scaled >= 0.0 || t_scaled < t_max64 * det) {
            return None;
        }
        if det > 0.0 && (t_scaled <= 0.0 || t_scaled > t_max64 * det) {
            return None;
        }
        let inv_det = 1.0 / det;
        let t = (t_scaled * inv_det) as f32;
        // Also rejects NaN: a comparison with NaN is false.
        if t.partial_cmp(&t_max) != Some(std::cmp::Ordering::Less) {
            return None;
        }

        // Reject hits closer than the error in t (pbrt-v4 §6.8.4, with f64 rounding):
        // they may lie behind the origin.
        let max_zt = az.abs().max(bz.abs()).max(cz.abs());
        let delta_z = gamma64(3) * max_zt;
        let max_xt = ax.abs().max(bx.abs()).max(cx.abs());
        let max_yt = ay.abs().max(by.abs()).max(cy.abs());
        let delta_x = gamma64(5) * (max_xt + max_zt);
        let delta_y = gamma64(5) * (max_yt + max_zt);
        let delta_e = 2.0 * (gamma64(2) * max_xt * max_yt + delta_y * max_xt + delta_x * max_yt);
        let max_e = e0.abs().max(e1.abs()).max(e2.abs());
        let delta_t = 3.0
            * (gamma64(3) * max_e * max_zt + delta_e * max_zt + delta_z * max_e)
            * inv_det.abs();
        if f64::from(t) <= delta_t || t <= 0.0 {
            return None;
        }
        let barycentrics = Vec3A::new(
            (e0 * inv_det) as f32,
            (e1 * inv_det) as f32,
            (e2 * inv_det) as f32,
        );
        if !barycentrics.is_finite() {
            return None;
        }
        Some(TriangleHit { t, barycentrics })
    }
}

/// The edge functions `(e0, e1, e2) = (b_x c_y − b_y c_x, c_x a_y − c_y a_x, a_x b_y −
/// a_y b_x)` of the sheared corners `a`, `b`, `c` (x, y).
#[inline(always)]
fn edge_functions(
    (ax, ay): (f64, f64),
    (bx, by): (f64, f64),
    (cx, cy): (f64, f64),
) -> (f64, f64, f64) {
    (bx * cy - by * cx, cx * ay - cy * ax, ax * by - ay * bx)
}

/// True when edge functions of both signs show the ray passing outside the triangle
/// (zeros, on an edge, count as inside).
#[inline(always)]
fn passes_outside((e0, e1, e2): (f64, f64, f64)) -> bool {
    (e0 < 0.0 || e1 < 0.0 || e2 < 0.0) && (e0 > 0.0 || e1 > 0.0 || e2 > 0.0)
}

/// Below this error bound (2⁻¹⁰⁰) the f32 products may have underflowed: the f32 pass
/// abstains.
const MIN_RELIABLE_BOUND: f32 = 7.888_609e-31;

/// pbrt's γ(n) = nε/(1 − nε) for f64 arithmetic.
#[inline]
pub(crate) fn gamma64(n: i32) -> f64 {
    let e = f64::EPSILON * 0.5;
    (f64::from(n) * e) / (1.0 - f64::from(n) * e)
}

/// The hit point rebuilt from barycentrics, with its error bound (pbrt-v4 eq. 6.42).
#[inline]
pub fn hit_point(p0: Vec3A, p1: Vec3A, p2: Vec3A, barycentrics: Vec3A) -> ErrorPoint {
    let t0 = p0 * barycentrics.x;
    let t1 = p1 * barycentrics.y;
    let t2 = p2 * barycentrics.z;
    ErrorPoint {
        point: t0 + t1 + t2,
        error: gamma(7) * (t0.abs() + t1.abs() + t2.abs()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::test_random::uniform;

    fn tri() -> (Vec3A, Vec3A, Vec3A) {
        (
            Vec3A::new(0.0, 0.0, 0.0),
            Vec3A::new(1.0, 0.0, 0.0),
            Vec3A::new(0.0, 1.0, 0.0),
        )
    }

    #[test]
    fn hits_front_and_back() {
        let (p0, p1, p2) = tri();
        for dz in [-1.0f32, 1.0] {
            let ray = Ray::new(Vec3A::new(0.25, 0.25, dz * -2.0), Vec3A::new(0.0, 0.0, dz));
            let h = WatertightRay::new(&ray)
                .intersect(p0, p1, p2, f32::INFINITY)
                .expect("hit");
            assert!((h.t - 2.0).abs() < 1e-6);
            assert!(
                (h.barycentrics - Vec3A::new(0.5, 0.25, 0.25))
                    .abs()
                    .max_element()
                    < 1e-6
            );
        }
    }

    #[test]
    fn respects_t_max_and_misses_outside() {
        let (p0, p1, p2) = tri();
        let ray = Ray::new(Vec3A::new(0.25, 0.25, -2.0), Vec3A::Z);
        assert!(
            WatertightRay::new(&ray)
                .intersect(p0, p1, p2, 1.5)
                .is_none()
        );
        let ray = Ray::new(Vec3A::new(0.75, 0.75, -2.0), Vec3A::Z);
        assert!(
            WatertightRay::new(&ray)
                .intersect(p0, p1, p2, f32::INFINITY)
                .is_none()
        );
        let behind = Ray::new(Vec3A::new(0.25, 0.25, 2.0), Vec3A::Z);
        assert!(
            WatertightRay::new(&behind)
                .intersect(p0, p1, p2, f32::INFINITY)
                .is_none()
        );
    }

    #[test]
    fn the_f32_pass_rejects_only_what_the_exact_test_misses() {
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let (mut rejected, mut misses) = (0u32, 0u32);
        for i in 0..200_000 {
            let point = |state: &mut u64, scale: f32| {
                Vec3A::new(
                    (uniform(state) - 0.5) * scale,
                    (uniform(state) - 0.5) * scale,
                    (uniform(state) - 0.5) * scale,
                )
            };
            // Scales from 10⁻³ to 10⁵ m, and a far-away offset on some.
            let scale = 10f32.powi(i % 9 - 3);
            let offset = if i % 5 == 0 {
                Vec3A::splat(1.5e5)
            } else {
                Vec3A::ZERO
            };
            let (p0, p1, p2) = (
                point(&mut state, scale) + offset,
                point(&mut state, scale) + offset,
                point(&mut state, scale) + offset,
            );
            // Aim at a vertex, an edge point or an interior point: the hard cases.
            let w = (uniform(&mut state), uniform(&mut state));
            // Or anywhere near it, as most rays a leaf sees are.
            let target = match i % 4 {
                0 => p0,
                1 => p0 + (p1 - p0) * w.0,
                2 => p0 + (p1 - p0) * w.0 + (p2 - p0) * (w.1 * (1.0 - w.0)),
                _ => point(&mut state, 2.0 * scale) + offset,
            };
            let origin = point(&mut state, 4.0 * scale) + offset;
            let ray = Ray::new(origin, target - origin + point(&mut state, scale * 1e-6));
            if !ray.direction.is_finite() || ray.direction == Vec3A::ZERO {
                continue;
            }
            let watertight = WatertightRay::new(&ray);
            let exact = watertight.intersect_exact(p0, p1, p2, f32::INFINITY);
            let random_target = i % 4 == 3;
            if watertight.misses_certainly(p0, p1, p2) {
                rejected += u32::from(random_target);
                assert!(
                    exact.is_none(),
                    "f32 pass rejected a hit: {p0} {p1} {p2} {ray:?}"
                );
            }
            misses += u32::from(exact.is_none() && random_target);
            assert_eq!(exact, watertight.intersect(p0, p1, p2, f32::INFINITY));
        }
        // The pass must do its job too: nearly every miss away from an edge is decided
        // in f32.
        assert!(
            rejected as f32 > 0.95 * misses as f32,
            "{rejected} of {misses} misses decided in f32"
        );
    }

    #[test]
    fn the_axis_order_is_the_largest_component_first_on_ties_and_keeps_the_winding() {
        let values = [0.0, -0.0, 1.0, -1.0, 0.5, -0.5, 2.0, -2.0, 1e-40, f32::NAN];
        let mut checked = 0;
        for &x in &values {
            for &y in &values {
                for &z in &values {
                    let d = Vec3A::new(x, y, z);
                    let ray = Ray::new(Vec3A::new(1.0, 2.0, 3.0), d);
                    let w = WatertightRay::new(&ray);
                    // The textbook choice, with branches.
                    let a = d.abs();
                    let kz = if a.x >= a.y && a.x >= a.z {
                        0
                    } else if a.y >= a.z {
                        1
                    } else {
                        2
                    };
                    let (mut kx, mut ky) = ((kz + 1) % 3, (kz + 2) % 3);
                    if d[kz] < 0.0 {
                        std::mem::swap(&mut kx, &mut ky);
                    }
                    assert_eq!((w.kx, w.ky, w.kz), (kx, ky, kz), "direction {d}");
                    let o = ray.origin;
                    assert_eq!(w.origin_permuted, [o[kx], o[ky], o[kz]].map(f64::from));
                    let shear = [d[kx] / d[kz], d[ky] / d[kz], 1.0 / d[kz]];
                    for (got, want) in w.shear.to_array().into_iter().zip(shear) {
                        assert!(got.to_bits() == want.to_bits() || (got.is_nan() && want.is_nan()));
                    }
                    checked += 1;
                }
            }
        }
        assert_eq!(checked, 1000);
    }

    #[test]
    fn the_block_tests_decide_as_the_scalar_tests() {
        let mut state = 0x51ed_2701_aa3c_9e4du64;
        let point = |state: &mut u64, scale: f32| {
            Vec3A::new(
                (uniform(state) - 0.5) * scale,
                (uniform(state) - 0.5) * scale,
                (uniform(state) - 0.5) * scale,
            )
        };
        let (mut possible, mut hits, mut lanes) = (0u32, 0u32, 0u32);
        for i in 0..50_000 {
            let scale = 10f32.powi(i % 7 - 3);
            let offset = if i % 3 == 0 {
                Vec3A::splat(1.5e5)
            } else {
                Vec3A::ZERO
            };
            let count = 1 + i as usize % 4;
            let mut triangles = Vec::new();
            for _ in 0..count {
                let mut corners = [0; 3].map(|_| point(&mut state, scale) + offset);
                if i % 11 == 0 {
                    // A degenerate triangle: one corner repeated.
                    corners[2] = corners[0];
                }
                triangles.push(corners);
            }
            // Aim near the first triangle, so some lanes are hit and some are not.
            let target = triangles[0][0] * 0.4 + triangles[0][1] * 0.3 + triangles[0][2] * 0.3;
            let origin = point(&mut state, 4.0 * scale) + offset;
            let mut direction = target - origin + point(&mut state, scale * 0.5);
            if i % 13 == 0 {
                direction.y = 0.0;
            }
            let ray = Ray::new(origin, direction);
            if !ray.direction.is_finite() || ray.direction == Vec3A::ZERO {
                continue;
            }
            let watertight = WatertightRay::new(&ray);
            let block = TriangleBlock::new(
                &triangles
                    .iter()
                    .enumerate()
                    .map(|(i, &t)| (i as u32 * 7, t))
                    .collect::<Vec<_>>(),
            );
            let mask = watertight.possible_hits(&block, count);
            let t_max = [f32::INFINITY, 2.0 * scale][i as usize % 2];
            for (lane, [p0, p1, p2]) in triangles.iter().enumerate() {
                assert_eq!(block.triangle(lane), [*p0, *p1, *p2]);
                assert_eq!(block.triangles[lane], lane as u32 * 7);
                let passed = mask >> lane & 1 == 1;
                // The block check decides with the exact test's f64 edge signs: never
                // looser than the f32 pass, which leaves a margin for its rounding.
                assert!(
                    !passed || !watertight.misses_certainly(*p0, *p1, *p2),
                    "lane {lane} passed what the f32 pass rejects: {triangles:?}, {ray:?}"
                );
                let exact = watertight.intersect_exact(*p0, *p1, *p2, t_max);
                assert!(
                    passed || exact.is_none(),
                    "lane {lane} rejected a hit: {triangles:?}, {ray:?}"
                );
                let from_block = watertight.intersect_lane(&block, lane, t_max);
                assert_eq!(
                    exact.map(|h| (h.t.to_bits(), h.barycentrics.to_array().map(f32::to_bits))),
                    from_block
                        .map(|h| (h.t.to_bits(), h.barycentrics.to_array().map(f32::to_bits))),
                    "lane {lane} of {triangles:?}, {ray:?}"
                );
                possible += u32::from(passed);
                hits += u32::from(exact.is_some());
                lanes += 1;
            }
            assert_eq!(mask >> count, 0, "lanes past the triangles are set");
        }
        // Both outcomes must occur often enough for the comparison to mean something.
        assert!(
            possible > lanes / 20 && possible < lanes * 19 / 20 && hits > lanes / 50,
            "{possible} possible and {hits} hits of {lanes}"
        );
    }

    #[test]
    fn shared_edge_is_hit_by_exactly_one_side_or_both() {
        // Two triangles sharing the diagonal of the unit square: a ray through the
        // diagonal must hit at least one of them.
        let q = [
            Vec3A::new(0.0, 0.0, 0.0),
            Vec3A::new(1.0, 0.0, 0.0),
            Vec3A::new(1.0, 1.0, 0.0),
            Vec3A::new(0.0, 1.0, 0.0),
        ];
        for i in 0..1000 {
            let s = i as f32 / 999.0;
            let ray = Ray::new(Vec3A::new(s, s, -1.0), Vec3A::new(0.0, 0.0, 1.0));
            let w = WatertightRay::new(&ray);
            let a = w.intersect(q[0], q[1], q[2], f32::INFINITY);
            let b = w.intersect(q[0], q[2], q[3], f32::INFINITY);
            assert!(a.is_some() || b.is_some(), "leak at s = {s}");
        }
    }
}
