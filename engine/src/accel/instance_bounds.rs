//! Tight world boxes for instances. A mesh's support function `h(d) = max_p d·p` is
//! sampled once on an octahedral grid of directions; an instance's world box needs `h` at
//! the six directions `±row` of its matrix, and any direction is a non-negative
//! combination of three grid directions, so the same combination of their samples bounds
//! `h` from above (a support function is sublinear). The corners of the object box
//! transformed, the usual instance box, are up to √2 wider per axis for a plant turned
//! 45° about its stem, and every ray through that slack enters the instance for nothing.

use crate::util::math::Aabb;
use glam::{Affine3A, Vec3, Vec3A};
use rayon::prelude::*;

/// Grid cells per side of the octahedral map; even, so the map's folds (the axes and the
/// lines `|u| + |v| = 1`) run along grid lines and cell diagonals.
const CELLS: usize = 8;

/// Grid vertices per side.
pub(crate) const SIDE: usize = CELLS + 1;

/// Grid vertices: the sampled directions.
pub(crate) const DIRECTIONS: usize = SIDE * SIDE;

/// The samples at the four corners `(i, j)`, `(i + 1, j)`, `(i, j + 1)` and `(i + 1,
/// j + 1)` of eight grid cells.
pub(crate) type CellCorners = [[f32; 8]; 4];

/// [`CellCorners`] of the cells at `(iu, iv)` (whole numbers in `0 ..= CELLS − 1`), one
/// load at a time; `crate::accel::bvh::simd` gathers them eight at a time where it can.
#[inline(always)]
pub(crate) fn cell_corners(
    samples: &[f32; DIRECTIONS],
    iu: &[f32; 8],
    iv: &[f32; 8],
) -> CellCorners {
    const MAGIC: f32 = 8_388_608.0;
    let mut corners = [[0.0f32; 8]; 4];
    for k in 0..8 {
        let index = |f: f32| ((f + MAGIC).to_bits() & 0x7f_ffff) as usize;
        let (i, j) = (index(iu[k]), index(iv[k]));
        let at = |di: usize, dj: usize| samples[((i + di) * SIDE + j + dj).min(DIRECTIONS - 1)];
        (corners[0][k], corners[1][k], corners[2][k], corners[3][k]) =
            (at(0, 0), at(1, 0), at(0, 1), at(1, 1));
    }
    corners
}

/// Relative slack added to a bound, far above the rounding of the few operations between
/// the samples and a bound (a few f32 ulps of the mesh's radius).
const SLACK: f32 = 4.0e-6;

/// A mesh's support function sampled on the octahedral grid.
#[derive(Clone, Debug, PartialEq)]
pub struct SupportTable {
    /// `h(o)` at the octahedron point `o` of grid vertex `(i, j)`, at `i * SIDE + j`;
    /// none for a mesh without points.
    samples: Option<[f32; DIRECTIONS]>,
    /// The largest distance of a point from the object origin (scales the slack).
    radius: f32,
}

/// The point of the octahedron `|x| + |y| + |z| = 1` at map coordinates `(u, v)` in
/// `[-1, 1]²`: the upper half inside the diamond `|u| + |v| ≤ 1`, the lower half folded
/// out to the square's corners.
fn octahedron_point(u: f32, v: f32) -> Vec3A {
    let z = 1.0 - u.abs() - v.abs();
    if z >= 0.0 {
        Vec3A::new(u, v, z)
    } else {
        Vec3A::new((1.0 - v.abs()).copysign(u), (1.0 - u.abs()).copysign(v), z)
    }
}

/// Map coordinates of grid vertex `i` along one side.
fn grid_coordinate(i: usize) -> f32 {
    -1.0 + 2.0 * i as f32 / CELLS as f32
}

impl SupportTable {
    /// Samples the support function of `points` (all finite).
    pub fn new(points: &[Vec3]) -> Self {
        if points.is_empty() {
            return Self {
                samples: None,
                radius: 0.0,
            };
        }
        let mut ox = [0.0f32; DIRECTIONS];
        let mut oy = [0.0f32; DIRECTIONS];
        let mut oz = [0.0f32; DIRECTIONS];
        for k in 0..DIRECTIONS {
            let o = octahedron_point(grid_coordinate(k / SIDE), grid_coordinate(k % SIDE));
            (ox[k], oy[k], oz[k]) = (o.x, o.y, o.z);
        }
        // One pass over the points per chunk, all directions per point (fixed-length
        // arrays, a loop the compiler vectorizes); f32 products are within a few ulps of
        // the radius, far inside the slack every bound adds.
        let (samples, radius) = points
            .par_chunks(1 << 14)
            .map(|chunk| {
                let mut best = [f32::NEG_INFINITY; DIRECTIONS];
                let mut radius = 0.0f32;
                for p in chunk {
                    for k in 0..DIRECTIONS {
                        let dot = ox[k] * p.x + oy[k] * p.y + oz[k] * p.z;
                        best[k] = if dot > best[k] { dot } else { best[k] };
                    }
                    radius = radius.max(p.length());
                }
                (best, radius)
            })
            .reduce_with(|(mut a, ra), (b, rb)| {
                for (a, b) in a.iter_mut().zip(b) {
                    *a = a.max(b);
                }
                (a, ra.max(rb))
            })
            .map_or((None, 0.0), |(best, radius)| (Some(best), radius));
        Self { samples, radius }
    }

    /// Upper bounds on `max_p d·p` over the sampled points at eight directions `d`
    /// (finite, non-zero), given as structure of arrays; `-∞` for a table without points.
    /// Branch-free but for the table's presence (an instance's directions fall anywhere,
    /// and branches on them mispredicted), in loops the compiler turns into SIMD; only the
    /// four sample loads per lane stay scalar. One direction at a time, the six of an
    /// instance box were a sixth of a 365 k-instance top-level build.
    #[inline(always)]
    pub fn support8(&self, dx: [f32; 8], dy: [f32; 8], dz: [f32; 8]) -> [f32; 8] {
        self.support8_with(dx, dy, dz, cell_corners)
    }

    /// [`support8`](Self::support8) with the sample loads of `corners`, which must
    /// return what [`cell_corners`] returns.
    #[inline(always)]
    pub(crate) fn support8_with(
        &self,
        dx: [f32; 8],
        dy: [f32; 8],
        dz: [f32; 8],
        corners: impl FnOnce(&[f32; DIRECTIONS], &[f32; 8], &[f32; 8]) -> CellCorners,
    ) -> [f32; 8] {
        let Some(samples) = &self.samples else {
            return [f32::NEG_INFINITY; 8];
        };
        let half_cells = 0.5 * CELLS as f32;
        let (mut length, mut fu, mut fv) = ([0.0f32; 8], [0.0f32; 8], [0.0f32; 8]);
        let (mut iu, mut iv) = ([0.0f32; 8], [0.0f32; 8]);
        // Floors without `floor` (a library call below SSE4.1) or integer casts (Rust's
        // saturating casts do not vectorize): round to nearest by adding 2²³, step down
        // where that rounded up. Exact for values in [0, CELLS].
        const MAGIC: f32 = 8_388_608.0;
        let floor = |f: f32| {
            let nearest = (f + MAGIC) - MAGIC;
            if nearest > f { nearest - 1.0 } else { nearest }
        };
        for k in 0..8 {
            let (ax, ay, az) = (dx[k].abs(), dy[k].abs(), dz[k].abs());
            length[k] = ax + ay + az;
            let scale = 1.0 / length[k];
            let lower = dz[k] < 0.0;
            let u = if lower {
                (1.0 - ay * scale).copysign(dx[k])
            } else {
                dx[k] * scale
            };
            let v = if lower {
                (1.0 - ax * scale).copysign(dy[k])
            } else {
                dy[k] * scale
            };
            let f = ((u + 1.0) * half_cells).max(0.0).min(CELLS as f32);
            iu[k] = floor(f).min((CELLS - 1) as f32);
            fu[k] = f - iu[k];
            let f = ((v + 1.0) * half_cells).max(0.0).min(CELLS as f32);
            iv[k] = floor(f).min((CELLS - 1) as f32);
            fv[k] = f - iv[k];
        }
        let [h00, h10, h01, h11] = corners(samples, &iu, &iv);
        // The cell splits along the diagonal the octahedron's fold takes in its quadrant,
        // so each half lies on one face, where the map is affine and the corners'
        // directions combine into the direction exactly, with weights ≥ 0. On either
        // half that interpolation is the bilinear one's first three terms plus
        // `twist · w`, `w` the distance past the split diagonal.
        let mut out = [0.0f32; 8];
        for k in 0..8 {
            let upper_u = iu[k] >= (CELLS / 2) as f32;
            let upper_v = iv[k] >= (CELLS / 2) as f32;
            let past = if upper_u == upper_v {
                (fu[k] + fv[k] - 1.0).max(0.0)
            } else {
                fu[k].min(fv[k])
            };
            let twist = h11[k] + h00[k] - h10[k] - h01[k];
            let interpolated =
                h00[k] + fu[k] * (h10[k] - h00[k]) + fv[k] * (h01[k] - h00[k]) + twist * past;
            out[k] = length[k] * (interpolated + SLACK * self.radius);
        }
        out
    }

    /// A box holding every sampled point after `transform`: per axis, the translation
    /// plus the support at the matrix row and minus it at the negated row, each sum
    /// moved outward by more than its rounding (half an ulp of the sum). Inlined into
    /// [`crate::accel::kernel::transformed_bounds`], which compiles it for AVX2.
    #[inline(always)]
    pub fn transformed_bounds(&self, transform: &Affine3A) -> Aabb {
        self.transformed_bounds_with(transform, cell_corners)
    }

    /// [`transformed_bounds`](Self::transformed_bounds) with the sample loads of
    /// `corners`, as in [`support8_with`](Self::support8_with).
    #[inline(always)]
    pub(crate) fn transformed_bounds_with(
        &self,
        transform: &Affine3A,
        corners: impl FnOnce(&[f32; DIRECTIONS], &[f32; 8], &[f32; 8]) -> CellCorners,
    ) -> Aabb {
        if self.samples.is_none() {
            return Aabb::EMPTY;
        }
        let rows = transform.matrix3.transpose();
        let [x, y, z] = [rows.x_axis, rows.y_axis, rows.z_axis];
        // The six directions ±row, and two spare lanes on a harmless direction.
        let h = self.support8_with(
            [x.x, y.x, z.x, -x.x, -y.x, -z.x, 1.0, 1.0],
            [x.y, y.y, z.y, -x.y, -y.y, -z.y, 0.0, 0.0],
            [x.z, y.z, z.z, -x.z, -y.z, -z.z, 0.0, 0.0],
            corners,
        );
        let t = transform.translation;
        let max = t + Vec3A::new(h[0], h[1], h[2]);
        let min = t - Vec3A::new(h[3], h[4], h[5]);
        // 2⁻²³ relative is two half-ulps; the constant covers results in the denormals.
        let rounding = |v: Vec3A| v.abs() * f32::EPSILON + Vec3A::splat(1e-30);
        Aabb {
            min: min - rounding(min),
            max: max + rounding(max),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::test_random::uniform;

    /// The reference for [`SupportTable::support8`]: one direction, written plainly
    /// (integer casts, the cell's corners by index), the same operations in order.
    fn support_one(table: &SupportTable, d: Vec3A) -> f32 {
        let Some(samples) = &table.samples else {
            return f32::NEG_INFINITY;
        };
        let a = d.abs();
        let length = a.x + a.y + a.z;
        let scale = 1.0 / length;
        let lower = d.z < 0.0;
        let u = if lower {
            (1.0 - a.y * scale).copysign(d.x)
        } else {
            d.x * scale
        };
        let v = if lower {
            (1.0 - a.x * scale).copysign(d.y)
        } else {
            d.y * scale
        };
        let cell = |w: f32| {
            let f = ((w + 1.0) * (0.5 * CELLS as f32))
                .max(0.0)
                .min(CELLS as f32);
            let i = (f as usize).min(CELLS - 1);
            (i, f - i as f32)
        };
        let ((i, fu), (j, fv)) = (cell(u), cell(v));
        // `i, j < CELLS`, so the index never exceeds the last sample; the `min` only spares
        // a bounds check.
        let at = |di: usize, dj: usize| samples[((i + di) * SIDE + j + dj).min(DIRECTIONS - 1)];
        let (h00, h10, h01, h11) = (at(0, 0), at(1, 0), at(0, 1), at(1, 1));
        let fold_falls = (i >= CELLS / 2) == (j >= CELLS / 2);
        let past = if fold_falls {
            (fu + fv - 1.0).max(0.0)
        } else {
            fu.min(fv)
        };
        let twist = h11 + h00 - h10 - h01;
        let interpolated = h00 + fu * (h10 - h00) + fv * (h01 - h00) + twist * past;
        length * (interpolated + SLACK * table.radius)
    }

    use glam::{DVec3, Quat};

    fn exact_bounds(points: &[Vec3], m: &Affine3A) -> (DVec3, DVec3) {
        let rows = m.matrix3.transpose();
        let t = m.translation.as_dvec3();
        let mut lo = DVec3::INFINITY;
        let mut hi = DVec3::NEG_INFINITY;
        for p in points {
            let p = p.as_dvec3();
            let q = DVec3::new(
                rows.x_axis.as_dvec3().dot(p),
                rows.y_axis.as_dvec3().dot(p),
                rows.z_axis.as_dvec3().dot(p),
            ) + t;
            lo = lo.min(q);
            hi = hi.max(q);
        }
        (lo, hi)
    }

    #[test]
    fn eight_directions_at_once_give_the_bits_of_one_at_a_time() {
        let mut state = 0x05ee_d0fe_1647_u64;
        let points: Vec<Vec3> = (0..200)
            .map(|_| {
                Vec3::new(
                    uniform(&mut state) - 0.5,
                    uniform(&mut state) * 3.0,
                    uniform(&mut state) - 0.3,
                )
            })
            .collect();
        let table = SupportTable::new(&points);
        let mut component = |k: usize| match k % 9 {
            // Grid directions, axes and folds, where the cell split changes side.
            0 => 0.0,
            1 => 1.0,
            2 => -1.0,
            3 => 0.5,
            _ => uniform(&mut state) * 2.0 - 1.0,
        };
        for case in 0..4_000 {
            let mut d = [[0.0f32; 8]; 3];
            for lane in 0..8 {
                let mut v = [0, 1, 2].map(|axis| component(case + 3 * lane + axis));
                // The zero direction has no support; a unit one takes its place.
                if v == [0.0; 3] {
                    v[0] = 1.0;
                }
                for (axis, lanes) in d.iter_mut().enumerate() {
                    lanes[lane] = v[axis];
                }
            }
            let batch = table.support8(d[0], d[1], d[2]);
            for lane in 0..8 {
                let one = support_one(&table, Vec3A::new(d[0][lane], d[1][lane], d[2][lane]));
                assert_eq!(
                    batch[lane].to_bits(),
                    one.to_bits(),
                    "lane {lane} of case {case}"
                );
            }
        }
    }

    #[test]
    fn the_bound_holds_every_point_under_any_affine_map() {
        let mut state = 0x0dd_ba11_cafe_f00du64;
        for case in 0..2_000 {
            let n = 1 + case % 40;
            let offset = Vec3::new(
                uniform(&mut state) - 0.5,
                uniform(&mut state) * 3.0,
                uniform(&mut state) - 0.5,
            ) * if case % 7 == 0 { 1e4 } else { 1.0 };
            let points: Vec<Vec3> = (0..n)
                .map(|_| {
                    offset
                        + Vec3::new(
                            uniform(&mut state) - 0.5,
                            uniform(&mut state) - 0.5,
                            uniform(&mut state) - 0.5,
                        ) * Vec3::new(1.0, 4.0, 0.2)
                })
                .collect();
            let table = SupportTable::new(&points);
            // Rotations, non-uniform scales, shears, mirrors and axis-aligned maps (on
            // the grid's own directions, where folds and edges meet).
            let mut column = || {
                let v = Vec3::new(
                    uniform(&mut state) * 2.0 - 1.0,
                    uniform(&mut state) * 2.0 - 1.0,
                    uniform(&mut state) * 2.0 - 1.0,
                );
                if case % 5 == 0 { v.round() } else { v }
            };
            let matrix = glam::Mat3::from_cols(column(), column(), column());
            if matrix.determinant().abs() < 1e-3 {
                continue;
            }
            let m = Affine3A::from_mat3_translation(matrix, Vec3::new(3.0, -2.0, 1e3));
            let b = table.transformed_bounds(&m);
            let (lo, hi) = exact_bounds(&points, &m);
            assert!(
                b.min.as_dvec3().cmple(lo).all() && b.max.as_dvec3().cmpge(hi).all(),
                "case {case}: {b:?} does not hold {lo} .. {hi}"
            );
        }
    }

    #[test]
    fn the_bound_of_a_turned_plant_hugs_it() {
        // A round crown on a stem: turned about its stem and tilted as plants are placed,
        // the corners of its object box give a box up to √2 wider; the table's stays
        // within a few percent of the exact one (the sampling's error for a sphere, the
        // worst case for interpolating between directions).
        let mut state = 0x5eed_1234_u64;
        let points: Vec<Vec3> = (0..4_000)
            .map(|_| {
                let (a, b, r) = (
                    uniform(&mut state) * std::f32::consts::TAU,
                    uniform(&mut state) * 2.0 - 1.0,
                    uniform(&mut state).cbrt(),
                );
                let s = (1.0 - b * b).sqrt();
                Vec3::new(s * a.cos() * r, 2.0 + b * r, s * a.sin() * r)
            })
            .chain([Vec3::ZERO])
            .collect();
        let table = SupportTable::new(&points);
        let object_box = Aabb::from_points(points.iter().map(|&p| p.into()));
        let mut worst_table = 0.0f64;
        let mut worst_corners = 0.0f64;
        for k in 0..64 {
            let yaw = k as f32 * 0.1;
            let m = Affine3A::from_scale_rotation_translation(
                Vec3::splat(1.3),
                Quat::from_rotation_x(0.1 * (k % 3) as f32) * Quat::from_rotation_y(yaw),
                Vec3::new(10.0, 0.0, -4.0),
            );
            let (lo, hi) = exact_bounds(&points, &m);
            let exact = (hi - lo).x * (hi - lo).z;
            let area = |b: Aabb| {
                let e = b.extent().as_dvec3();
                e.x * e.z / exact - 1.0
            };
            worst_table = worst_table.max(area(table.transformed_bounds(&m)));
            worst_corners = worst_corners.max(area(object_box.transformed(&m)));
        }
        assert!(worst_table < 0.1, "table box {worst_table:.3} too large");
        assert!(
            worst_corners > 0.5,
            "corner box only {worst_corners:.3} too large"
        );
    }

    #[test]
    fn an_empty_mesh_has_an_empty_box() {
        let table = SupportTable::new(&[]);
        assert!(table.transformed_bounds(&Affine3A::IDENTITY).is_empty());
    }
}
