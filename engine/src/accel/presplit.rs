//! The boxes a bottom-level build starts from: one per triangle, or two for a long,
//! slanted triangle whose box is mostly empty (a grass blade's), one for each half of it
//! cut at its box's midpoint along the longest side. Rays passing near such a triangle
//! then enter fewer leaves (Ernst and Greiner 2007, "Early split clipping"). A triangle
//! cut in two sits in two leaves; each leaf tests the whole triangle exactly, so either
//! finds the same hit at the same distance.

use crate::accel::mesh::TriangleMesh;
use crate::util::math::Aabb;
use glam::Vec3A;
use rayon::prelude::*;

/// Widening of a half's box, relative to the largest coordinate magnitude of the
/// triangle's box on each axis: the cut points on the triangle's edges are rounded in
/// the other two coordinates by a few ulps of that (about 6ε = 7·10⁻⁷); 4·10⁻⁶ covers
/// them with room to spare. The box is then clamped to the triangle's own box, which
/// holds both halves exactly.
const HALF_MARGIN: f32 = 4e-6;

/// Build boxes of a mesh and the triangle each belongs to.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriangleBoxes {
    /// One box per build primitive: a triangle's box, or one of its halves' boxes.
    pub boxes: Vec<Aabb>,
    /// The mesh triangle of each box; empty when no triangle was cut, and box `i` is
    /// triangle `i`'s.
    pub owners: Vec<u32>,
}

impl TriangleBoxes {
    /// The mesh triangle that build primitive `primitive` belongs to.
    #[inline]
    pub fn owner(&self, primitive: u32) -> u32 {
        if self.owners.is_empty() {
            primitive
        } else {
            self.owners[primitive as usize]
        }
    }
}

/// The build boxes of `mesh`'s triangles: each triangle's box, except that a triangle
/// whose box's surface area exceeds `split_ratio` × twice its area is cut in two and
/// gets its halves' boxes (twice the area is the least surface area a triangle's box
/// can have, reached in an axis plane; a long slanted blade reaches hundreds). Triangles
/// with non-finite corners get an empty box, which a build leaves out; `split_ratio` 0
/// cuts none.
pub fn triangle_boxes(mesh: &TriangleMesh, split_ratio: f32) -> TriangleBoxes {
    let halves: Vec<(Aabb, Option<Aabb>)> = (0..mesh.triangle_count())
        .into_par_iter()
        .map(|i| {
            let whole = mesh.triangle_bounds(i);
            if whole.is_empty() {
                (whole, None)
            } else {
                triangle_halves(mesh.triangle(i), whole, split_ratio)
            }
        })
        .collect();
    if halves.iter().all(|(_, second)| second.is_none()) {
        return TriangleBoxes {
            boxes: halves.into_iter().map(|(first, _)| first).collect(),
            owners: Vec::new(),
        };
    }
    let mut boxes = Vec::with_capacity(halves.len() + halves.len() / 8);
    let mut owners = Vec::with_capacity(boxes.capacity());
    for (triangle, (first, second)) in halves.into_iter().enumerate() {
        for half in std::iter::once(first).chain(second) {
            boxes.push(half);
            owners.push(triangle as u32);
        }
    }
    TriangleBoxes { boxes, owners }
}

/// The box `whole` of the triangle with finite `corners`, or the boxes of its two halves
/// when `whole` is more than `split_ratio` × twice its area.
fn triangle_halves(corners: [Vec3A; 3], whole: Aabb, split_ratio: f32) -> (Aabb, Option<Aabb>) {
    let area = 0.5
        * (corners[1] - corners[0])
            .cross(corners[2] - corners[0])
            .length();
    let box_area = whole.surface_area();
    // Written so that NaN and infinite areas (overflow) keep the whole box.
    if !(split_ratio > 0.0 && area > 0.0 && box_area.is_finite())
        || box_area <= split_ratio * 2.0 * area
    {
        return (whole, None);
    }
    let axis = whole.largest_axis();
    let cut = 0.5 * (whole.min[axis] + whole.max[axis]);
    let (mut below, mut above) = (Aabb::EMPTY, Aabb::EMPTY);
    for i in 0..3 {
        let (p, q) = (corners[i], corners[(i + 1) % 3]);
        if p[axis] <= cut {
            below = below.grow(p);
        }
        if p[axis] >= cut {
            above = above.grow(p);
        }
        if (p[axis] < cut && q[axis] > cut) || (p[axis] > cut && q[axis] < cut) {
            let t = (cut - p[axis]) / (q[axis] - p[axis]);
            let mut crossing = p + (q - p) * t;
            crossing[axis] = cut;
            below = below.grow(crossing);
            above = above.grow(crossing);
        }
    }
    let margin =
        whole.min.abs().max(whole.max.abs()) * HALF_MARGIN + Vec3A::splat(f32::MIN_POSITIVE);
    let widen = |half: Aabb| Aabb {
        min: (half.min - margin).max(whole.min),
        max: (half.max + margin).min(whole.max),
    };
    (widen(below), Some(widen(above)))
}
