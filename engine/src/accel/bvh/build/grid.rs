//! Grid cells before the SAH for large inputs: primitives sorted into the cells of a
//! grid over their centroids, the cells' own tree split by median, each cell's
//! primitives then split by the SAH as usual.

use super::*;
use crate::util::math::Aabb;
use glam::Vec3A;
use rayon::prelude::*;

/// A grid cell's primitives: their extent, their number, and the cell's index in the
/// grid.
#[derive(Clone, Copy)]
pub(super) struct Cell {
    extent: Extent,
    count: u32,
    grid: u32,
}

/// A split of the cells' tree: the first `left_count` slots of the node (whole cells)
/// go left; the children's extents; which children are splits of this tree too (their
/// index), `None` marking a single cell, whose primitives the SAH splits as usual.
#[derive(Clone, Copy)]
pub(super) struct CellSplit {
    pub(super) left_count: u32,
    pub(super) left: Extent,
    pub(super) right: Extent,
    pub(super) children: [Option<u32>; 2],
}

impl Builder {
    /// Sorts the primitives `prim(item, index)` makes of `items` (`prims` of them; an
    /// item that makes none is left out) into `out` by the cell of a grid over
    /// `centroids` whose cells hold `grid_cell` primitives on average (cubes, as many
    /// along each axis as its extent takes), the cells in the order of the tree
    /// [`split_cells`](Self::split_cells) makes over them and the primitives of a cell
    /// in their items' order; returns
    /// that tree, its root first, or nothing (and `out` untouched) when the primitives
    /// fill fewer than two cells.
    pub(super) fn sort_into_cells<T: Sync>(
        &self,
        items: &[T],
        prim: impl Fn(&T, usize) -> Option<PrimRef> + Sync,
        prims: usize,
        out: &mut Vec<PrimRef>,
        centroids: &Aabb,
    ) -> Vec<CellSplit> {
        let extent = centroids.extent();
        // Cells of fewer than 64 would cost more pieces and bookkeeping than they save.
        let wanted = (prims / self.params.grid_cell.max(64)).max(1);
        let cells_along = |side: f32| -> [usize; 3] {
            [0, 1, 2].map(|axis| {
                let cells = (extent[axis] / side).ceil();
                // NaN (side or extent not finite) and 0 both make one cell.
                if cells >= 1.0 {
                    (cells as usize).min(1 << 10)
                } else {
                    1
                }
            })
        };
        let mut side = extent.max_element();
        let mut dims = cells_along(side);
        while dims.iter().product::<usize>() < wanted && side > 0.0 && side.is_finite() {
            side *= 0.95;
            dims = cells_along(side);
        }
        let count = dims.iter().product::<usize>();
        if count == 1 {
            return Vec::new();
        }
        let cells_per_axis = Vec3A::new(dims[0] as f32, dims[1] as f32, dims[2] as f32);
        let scale = cells_per_axis / Vec3A::select(extent.cmpgt(Vec3A::ZERO), extent, Vec3A::ONE);
        let last_cell = cells_per_axis - Vec3A::ONE;
        let cell_of = |r: &PrimRef| -> u32 {
            // A NaN (which finite boxes and extents should not make) lands in cell 0, a
            // rounding past the end in the last: as saturating casts would, but floored
            // and clamped in SIMD, then 2²³ added so each lane's whole number is its low mantissa bits
            // (three casts a primitive were half of the histogram pass).
            const MAGIC: f32 = 8_388_608.0; // 2²³
            let k = (r.centroid() - centroids.min) * scale;
            // A select, not `max`: what `max` makes of a NaN differs between SSE and NEON.
            let k = Vec3A::select(k.cmpge(Vec3A::ZERO), k, Vec3A::ZERO);
            let k = k.floor().min(last_cell) + Vec3A::splat(MAGIC);
            let [i, j, l] = k.to_array().map(|v| v.to_bits() & 0x7f_ffff);
            (i * dims[1] as u32 + j) * dims[2] as u32 + l
        };
        // A counting sort in fixed chunks (the same order on any thread count): each
        // chunk's histogram and cell extents, the cells' tree over their totals, every
        // (cell, chunk) pair's place in `out` in the tree's cell order, then each chunk
        // moves its primitives into its places, all chunks at once. At most 16
        // chunks, so the pieces below number at most 16 per cell.
        let chunk_size = items.len().div_ceil(16).max(1 << 12);
        let chunks: Vec<(Vec<u32>, Vec<u32>, Vec<Extent>)> = items
            .par_chunks(chunk_size)
            .enumerate()
            .map(|(index, chunk)| {
                let base = index * chunk_size;
                let mut cells = Vec::with_capacity(chunk.len());
                let mut counts = vec![0u32; count];
                let mut extents = vec![Extent::EMPTY; count];
                for (i, item) in chunk.iter().enumerate() {
                    prefetch_ahead(chunk, i);
                    let cell = prim(item, base + i).map_or(u32::MAX, |r| {
                        let cell = cell_of(&r);
                        counts[cell as usize] += 1;
                        extents[cell as usize] = extents[cell as usize].with(&r);
                        cell
                    });
                    cells.push(cell);
                }
                (cells, counts, extents)
            })
            .collect();
        let mut cells: Vec<Cell> = (0..count)
            .filter_map(|grid| {
                let count: u32 = chunks.iter().map(|(_, counts, _)| counts[grid]).sum();
                (count > 0).then(|| Cell {
                    extent: chunks
                        .iter()
                        .fold(Extent::EMPTY, |e, (_, _, extents)| e.union(extents[grid])),
                    count,
                    grid: grid as u32,
                })
            })
            .collect();
        if cells.len() < 2 {
            return Vec::new();
        }
        let mut tree = Vec::with_capacity(cells.len());
        self.split_cells(&mut cells, &mut tree, 0);
        // Filled on all threads: on fresh memory a serial fill was a tenth of the sort.
        out.clear();
        out.par_extend(rayon::iter::repeat_n(PrimRef::new(&Aabb::EMPTY, 0), prims));
        // Cut `out` into one piece per cell and chunk, handed to the chunks.
        let mut places: Vec<Vec<&mut [PrimRef]>> = (0..chunks.len())
            .map(|_| (0..count).map(|_| Default::default()).collect())
            .collect();
        let mut rest = out.as_mut_slice();
        for cell in &cells {
            for (chunk, (_, counts, _)) in chunks.iter().enumerate() {
                let grid = cell.grid as usize;
                let (piece, tail) = rest.split_at_mut(counts[grid] as usize);
                places[chunk][grid] = piece;
                rest = tail;
            }
        }
        items
            .par_chunks(chunk_size)
            .enumerate()
            .zip(places.par_iter_mut())
            .zip(chunks.par_iter())
            .for_each(|(((index, chunk), pieces), (cells, _, _))| {
                let base = index * chunk_size;
                let mut filled = vec![0usize; count];
                for (i, (item, &cell)) in chunk.iter().zip(cells).enumerate() {
                    prefetch_ahead(chunk, i);
                    if let Some(r) = prim(item, base + i) {
                        let cell = cell as usize;
                        pieces[cell][filled[cell]] = r;
                        filled[cell] += 1;
                    }
                }
            });
        tree
    }

    /// Splits `cells` by the SAH over their boxes (binned by their centroid boxes'
    /// centres, costs weighted by primitive counts) down to single cells, pushing the
    /// splits on `tree` (parents first) and leaving `cells` in the tree's order; returns
    /// the index of the split made, or `None` for a single cell.
    pub(super) fn split_cells(
        &self,
        cells: &mut [Cell],
        tree: &mut Vec<CellSplit>,
        depth: usize,
    ) -> Option<u32> {
        if cells.len() < 2 {
            return None;
        }
        const BINS: usize = 16;
        let centre = |cell: &Cell| cell.extent.centroids.center();
        let centres = cells
            .iter()
            .fold(Aabb::EMPTY, |b, cell| b.grow(centre(cell)));
        let axis = centres.largest_axis();
        let (low, width) = (centres.min[axis], centres.extent()[axis]);
        let bin_of = |cell: &Cell| {
            let k = (centre(cell)[axis] - low) / width * BINS as f32;
            // A zero width gives NaN: bin 0.
            (k as usize).min(BINS - 1)
        };
        let split = if depth < GRID_MEDIAN_DEPTH {
            let (mut boxes, mut counts) = ([Aabb::EMPTY; BINS], [0u64; BINS]);
            for cell in cells.iter() {
                let k = bin_of(cell);
                boxes[k] = boxes[k].union(cell.extent.bounds);
                counts[k] += u64::from(cell.count);
            }
            let mut right_cost = [f32::INFINITY; BINS];
            let (mut acc, mut count) = (Aabb::EMPTY, 0u64);
            for k in (1..BINS).rev() {
                acc = acc.union(boxes[k]);
                count += counts[k];
                if count > 0 {
                    right_cost[k] = acc.surface_area() * count as f32;
                }
            }
            let (mut acc, mut count) = (Aabb::EMPTY, 0u64);
            let mut best: Option<(f32, usize)> = None;
            for k in 1..BINS {
                acc = acc.union(boxes[k - 1]);
                count += counts[k - 1];
                let cost = acc.surface_area() * count as f32 + right_cost[k];
                if count > 0 && right_cost[k].is_finite() && best.is_none_or(|(b, _)| cost < b) {
                    best = Some((cost, k));
                }
            }
            best.map(|(_, k)| k)
        } else {
            None
        };
        let mid = match split {
            Some(k) => {
                let mut left = 0;
                for i in 0..cells.len() {
                    if bin_of(&cells[i]) < k {
                        cells.swap(i, left);
                        left += 1;
                    }
                }
                left
            }
            // No bin boundary separates the centres, or deep: halve by position.
            None => {
                cells.sort_by(|a, b| centre(a)[axis].total_cmp(&centre(b)[axis]));
                cells.len() / 2
            }
        };
        let (left, right) = cells.split_at_mut(mid);
        let extent = |cells: &[Cell]| {
            cells
                .iter()
                .fold(Extent::EMPTY, |e, cell| e.union(cell.extent))
        };
        let at = tree.len();
        tree.push(CellSplit {
            left_count: left.iter().map(|cell| cell.count).sum(),
            left: extent(left),
            right: extent(right),
            children: [None; 2],
        });
        let children = [
            self.split_cells(left, tree, depth + 1),
            self.split_cells(right, tree, depth + 1),
        ];
        tree[at].children = children;
        Some(at as u32)
    }
}
