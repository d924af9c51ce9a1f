//! Proof that a mesh is a height field, and its steepest slope: then a ray leaving the
//! mesh more steeply than any of its triangles cannot meet it again, and a shadow ray
//! leaving a terrain skips the terrain's walk.
//!
//! A mesh is a height field over an axis `up` when its triangles, projected along `up`,
//! cover a convex polygon exactly once and meet edge to edge: the surface is then the
//! graph of a continuous piecewise-linear function `f` over that polygon. Along any
//! segment of the (convex) polygon `f` changes by at most the steepest triangle's
//! slope `G` times the segment's length, so a ray from a point of the surface climbing
//! (or falling) faster than `G` stays above (or below) the surface everywhere else.
//!
//! The check, on exact vertex positions:
//! - every triangle's projection has the same orientation and a non-negligible area;
//! - every edge (a pair of positions) is used once (a boundary edge) or twice in
//!   opposite directions (an inner edge);
//! - the boundary edges form a single loop that turns one way only, once round: a convex
//!   polygon.
//!
//! Inner edges then cancel in the sum of the triangles' winding numbers, which leaves the
//! loop's: 1 inside the polygon and 0 outside, so each point is covered once. Triangles
//! around a shared corner meet edge to edge, with that corner's height: `f` is
//! continuous. A T-junction, a crack, an overlap, a fold or a hole leaves an edge
//! unmatched or a second loop, and the mesh is not called a height field.

use crate::accel::mesh::TriangleMesh;
use glam::Vec3A;
use rayon::prelude::*;
use std::collections::HashMap;

/// The least area of a triangle's projection, relative to the product of its two edge
/// lengths (the sine of its angle in projection): below it the sign of the area, computed
/// in f64 from f32 corners, might be wrong; such a triangle stands nearly upright, and
/// the mesh is not called a height field.
const LEAST_PROJECTED_SINE: f64 = 1e-9;

/// Relative widening of the steepest slope: covers the f32 rounding of the comparison
/// in [`Heightfield::clears`] (a few ulps of each square) with room to spare.
const SLOPE_MARGIN: f64 = 1e-4;

/// A mesh proven to be a height field over one axis, with its steepest slope.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Heightfield {
    /// The axis the surface's height runs along (0 = x, 1 = y, 2 = z).
    pub up: usize,
    /// The square of the steepest slope (rise over run) of any triangle, widened by a
    /// relative 10⁻⁴ for the rounding of [`Heightfield::clears`].
    pub max_slope_squared: f32,
    /// 1 on the two axes across `up`, 0 on `up`: picks a direction's run.
    across: Vec3A,
}

impl Heightfield {
    /// Proves `mesh` a height field over `up` and finds its steepest slope; `None` when
    /// it is not one, when `mesh` fails [`TriangleMesh::check`] or `up` is not an axis, or
    /// when the proof cannot be made in f64 (a triangle standing nearly upright).
    pub fn of(mesh: &TriangleMesh, up: usize) -> Option<Self> {
        let (u, v) = ((up + 1) % 3, (up + 2) % 3);
        let corner = |index: u32| {
            let p = mesh.positions[index as usize];
            (p[u] as f64, p[v] as f64, p[up] as f64)
        };
        // Indices in range and finite corners (`TriangleMesh::check`), or no proof.
        if mesh.indices.is_empty() || mesh.check().is_err() || up > 2 {
            return None;
        }
        // Which orientations the triangles have in projection (1 counter-clockwise, 2
        // clockwise) and the steepest slope's square.
        let (orientations, max_slope_squared) =
            mesh.indices
                .par_iter()
                .map(|&[a, b, c]| {
                    let (a, b, c) = (corner(a), corner(b), corner(c));
                    let e1 = (b.0 - a.0, b.1 - a.1, b.2 - a.2);
                    let e2 = (c.0 - a.0, c.1 - a.1, c.2 - a.2);
                    // The normal: its `up` part is twice the projected area.
                    let n_up = e1.0 * e2.1 - e1.1 * e2.0;
                    let n_u = e1.1 * e2.2 - e1.2 * e2.1;
                    let n_v = e1.2 * e2.0 - e1.0 * e2.2;
                    let lengths_squared = (e1.0 * e1.0 + e1.1 * e1.1) * (e2.0 * e2.0 + e2.1 * e2.1);
                    (n_up * n_up > LEAST_PROJECTED_SINE * LEAST_PROJECTED_SINE * lengths_squared)
                        .then(|| {
                            (
                                1 + u8::from(n_up < 0.0),
                                (n_u * n_u + n_v * n_v) / (n_up * n_up),
                            )
                        })
                })
                .try_reduce(|| (0, 0.0), |a, b| Some((a.0 | b.0, f64::max(a.1, b.1))))?;
        if orientations == 3 {
            return None;
        }
        let positive = orientations == 1;
        let max_slope = max_slope_squared.sqrt();
        let boundary = boundary_edges(mesh)?;
        if !is_convex_loop(&boundary, positive, |id| {
            let (x, y, _) = corner(id);
            (x, y)
        }) {
            return None;
        }
        let widened = max_slope * (1.0 + SLOPE_MARGIN);
        let mut across = Vec3A::ONE;
        across[up] = 0.0;
        Some(Self {
            up,
            max_slope_squared: (widened * widened) as f32,
            across,
        })
    }

    /// True when a ray leaving a point of the surface in `direction` (any length) rises
    /// or falls more steeply than any of its triangles, and so cannot meet the surface
    /// anywhere else.
    #[inline]
    pub fn clears(&self, direction: Vec3A) -> bool {
        let rise = direction[self.up] * direction[self.up];
        // Summed, not |direction|² − rise: no cancellation for a nearly upright ray.
        let run = (direction * self.across).length_squared();
        rise > self.max_slope_squared * run
    }
}

/// The boundary edges of `mesh` (each as its first corner's vertex index → its second's,
/// one vertex index standing for all vertices at its position), when every edge is used
/// once or twice in opposite directions; `None` otherwise.
fn boundary_edges(mesh: &TriangleMesh) -> Option<HashMap<u32, u32>> {
    // One id per distinct position: the least vertex index there. Each vertex as its
    // position's bits above its index, sorted: a position's vertices come together.
    let mut keyed: Vec<u128> = mesh
        .positions
        .par_iter()
        .enumerate()
        .map(|(i, p)| {
            let [x, y, z] = p.to_array().map(|c| if c == 0.0 { 0 } else { c.to_bits() });
            (u128::from(x) << 96) | (u128::from(y) << 64) | (u128::from(z) << 32) | i as u128
        })
        .collect();
    keyed.par_sort_unstable();
    let mut id = vec![0u32; mesh.positions.len()];
    let mut current = keyed[0];
    for &vertex in &keyed {
        if vertex >> 32 != current >> 32 {
            current = vertex;
        }
        id[vertex as u32 as usize] = current as u32;
    }
    // Each id's outgoing edges (the ends of the directed edges that start there).
    let mut first = vec![0u32; mesh.positions.len() + 1];
    for &from in mesh.indices.iter().flatten() {
        first[id[from as usize] as usize + 1] += 1;
    }
    for i in 1..first.len() {
        first[i] += first[i - 1];
    }
    let mut ends = vec![0u32; first[mesh.positions.len()] as usize];
    let mut filled = first.clone();
    for &[a, b, c] in &mesh.indices {
        let [a, b, c] = [a, b, c].map(|i| id[i as usize]);
        for (from, to) in [(a, b), (b, c), (c, a)] {
            ends[filled[from as usize] as usize] = to;
            filled[from as usize] += 1;
        }
    }
    let outgoing =
        |from: u32| &ends[first[from as usize] as usize..first[from as usize + 1] as usize];
    // An edge used twice in one direction (or three times) shows as a repeated end; one
    // used once has no edge back: a boundary edge.
    let boundary = (0..mesh.positions.len() as u32)
        .into_par_iter()
        .filter(|&from| id[from as usize] == from)
        .map(|from| {
            let ends = outgoing(from);
            let mut open = Vec::new();
            for (k, &to) in ends.iter().enumerate() {
                if to == from || ends[..k].contains(&to) {
                    return None;
                }
                if !outgoing(to).contains(&from) {
                    open.push((from, to));
                }
            }
            Some(open)
        })
        .try_reduce(Vec::new, |mut open, more| {
            open.extend(more);
            Some(open)
        })?;
    let mut next = HashMap::with_capacity(boundary.len());
    for (from, to) in boundary {
        // Two boundary edges leaving one corner: not a single simple loop.
        if next.insert(from, to).is_some() {
            return None;
        }
    }
    Some(next)
}

/// Whether the directed edges `next` (start → end) form one closed loop that turns only
/// left (`positive`) or only right, once round: the boundary of a convex polygon.
fn is_convex_loop(
    next: &HashMap<u32, u32>,
    positive: bool,
    at: impl Fn(u32) -> (f64, f64),
) -> bool {
    let Some(&start) = next.keys().next() else {
        return false;
    };
    let sign = if positive { 1.0 } else { -1.0 };
    let mut turning = 0.0;
    let (mut previous, mut current) = (start, next[&start]);
    for _ in 0..next.len() {
        let Some(&following) = next.get(&current) else {
            return false;
        };
        let (a, b, c) = (at(previous), at(current), at(following));
        let (d1, d2) = ((b.0 - a.0, b.1 - a.1), (c.0 - b.0, c.1 - b.1));
        let cross = sign * (d1.0 * d2.1 - d1.1 * d2.0);
        let dot = d1.0 * d2.0 + d1.1 * d2.1;
        // A right turn, or a turn straight back, is not convex.
        if cross < 0.0 || (cross == 0.0 && dot <= 0.0) {
            return false;
        }
        turning += cross.atan2(dot);
        (previous, current) = (current, following);
    }
    // Back at the start after as many steps as edges: one loop holds them all.
    previous == start && (turning - std::f64::consts::TAU).abs() < std::f64::consts::PI
}
