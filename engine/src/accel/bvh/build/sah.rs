//! The binned SAH split (Wald 2007): centroids binned per axis (in parallel for large
//! nodes, exact reductions), the sweep over the bins in SIMD lanes, the partition, and
//! the exact split of small nodes.

use super::*;
use crate::util::math::Aabb;
use glam::{BVec3A, Mat3A, UVec4, Vec3A};
use rayon::prelude::*;

/// A node's bins on the three axes: each bin's box, axis by axis, and each bin's number
/// of primitives with the axes in the lanes, so the SAH sweep reads a bin's three counts
/// as one vector. Their centroids' box is left to the partition (see [`partition`]):
/// keeping it here doubled the stores per primitive and bin, and binning is store-bound.
/// Fixed-size, so bin indices masked below [`MAX_BINS`] index without bounds checks.
#[derive(Clone)]
pub(super) struct Bins {
    bounds: [[Aabb; MAX_BINS]; 3],
    counts: [[u32; 4]; MAX_BINS],
}

impl Bins {
    /// Empty bins, all of them (so also cleared for any number of bins).
    pub(super) fn new() -> Box<Bins> {
        Box::new(Bins {
            bounds: [[Aabb::EMPTY; MAX_BINS]; 3],
            counts: [[0; 4]; MAX_BINS],
        })
    }

    /// Empties the first `bins` bins of every axis.
    pub(super) fn clear(&mut self, bins: usize) {
        for axis in &mut self.bounds {
            axis[..bins].fill(Aabb::EMPTY);
        }
        self.counts[..bins].fill([0; 4]);
    }

    /// Adds `other`'s first `bins` bins of every axis into these.
    pub(super) fn merge(&mut self, other: &Bins, bins: usize) {
        for (axis, other_axis) in self.bounds.iter_mut().zip(&other.bounds) {
            for (bin, other_bin) in axis[..bins].iter_mut().zip(&other_axis[..bins]) {
                *bin = bin.union(*other_bin);
            }
        }
        for (counts, other_counts) in self.counts[..bins].iter_mut().zip(&other.counts) {
            for (count, other_count) in counts.iter_mut().zip(other_counts) {
                *count += other_count;
            }
        }
    }
}

impl Builder {
    /// The cost of testing `count` primitives, in blocks of `leaf_block`.
    #[inline]
    pub(super) fn blocks(&self, count: usize) -> f32 {
        let block = self.params.leaf_block;
        // A shift for the usual power-of-two blocks instead of a division: the SAH
        // sweep asks twice per bin.
        if block.is_power_of_two() {
            ((count + block - 1) >> block.trailing_zeros()) as f32
        } else {
            count.div_ceil(block) as f32
        }
    }

    /// [`blocks`](Self::blocks) of the counts in the first three lanes, all at once (the
    /// SAH sweep's); arbitrary for a count of 0, whose side the sweep masks as empty.
    #[inline]
    pub(super) fn nonempty_blocks(&self, counts: UVec4) -> Vec3A {
        let block = self.params.leaf_block;
        let blocks = if block.is_power_of_two() && block <= 1 << 31 {
            // ⌈c / block⌉ = (c − 1) / block + 1 for c ≥ 1, without overflow.
            (counts.wrapping_sub(UVec4::ONE) >> block.trailing_zeros()).wrapping_add(UVec4::ONE)
        } else {
            UVec4::from_array(
                counts
                    .to_array()
                    .map(|c| (c as usize).div_ceil(block) as u32),
            )
        };
        // Rounded as `blocks` rounds its count.
        Vec3A::from_vec4(blocks.as_vec4())
    }

    pub(super) fn find_split(
        &self,
        refs: &[PrimRef],
        extent: &Extent,
        depth: usize,
        scratch: &mut Scratch,
    ) -> Split {
        let n = refs.len();
        let max_leaf = self.params.max_leaf_size;
        if n <= 1 || n <= self.params.lane_cluster {
            return Split::Leaf;
        }
        if depth >= FORCED_MEDIAN_DEPTH {
            return if n <= max_leaf {
                Split::Leaf
            } else {
                Split::Median
            };
        }
        // A leaf no dearer than one node visit beats every split (whose cost adds its
        // children's to that visit): decided without binning and sweeping (the
        // bottom level's nodes of one block; a 1 M-triangle build 0.85× the time).
        if n <= max_leaf && self.blocks(n) <= self.params.traversal_cost {
            return Split::Leaf;
        }
        if n == 2 {
            return self.split_pair(refs, extent);
        }
        self.binned_split(refs, extent, scratch)
    }

    /// The SAH split over binned centroids (or a leaf, or a median split when no bin
    /// boundary separates the primitives).
    pub(super) fn binned_split(
        &self,
        refs: &[PrimRef],
        extent: &Extent,
        scratch: &mut Scratch,
    ) -> Split {
        let n = refs.len();
        let max_leaf = self.params.max_leaf_size;
        let cb = &extent.centroids;
        // More bins than primitives cannot find better splits.
        let bins_per_axis = self.params.bins.min(n.max(2));
        let (scale, min) = bin_transform(cb, bins_per_axis);
        let scale = if self.params.longest_axis_only {
            axis_scale(scale, cb.largest_axis())
        } else {
            scale
        };
        // Only a one-axis partition reads the recorded bins (see `fill_bins`); a node
        // binned in parallel gets the slots in any case, so its chunks zip with them
        // (over three axes `fill_bins` leaves them unwritten).
        let record = self.params.longest_axis_only || n >= PARALLEL_BINNING;
        if record && scratch.prim_bins.len() < n {
            scratch.prim_bins.resize(n, [0; 3]);
        }
        let prim_bins: &mut [[u8; 3]] = if record {
            &mut scratch.prim_bins[..n]
        } else {
            &mut []
        };
        if n >= PARALLEL_BINNING {
            const CHUNK: usize = 16 * 1024;
            let merged = refs
                .par_chunks(CHUNK)
                .zip(prim_bins.par_chunks_mut(CHUNK))
                .map(|(chunk, chunk_bins)| {
                    let (mut local, mut spare) = (Bins::new(), Bins::new());
                    let spare = Some(&mut *spare);
                    fill_bins(
                        chunk,
                        scale,
                        min,
                        bins_per_axis,
                        &mut local,
                        spare,
                        chunk_bins,
                    );
                    local
                })
                .reduce(Bins::new, |mut a, b| {
                    a.merge(&b, bins_per_axis);
                    a
                });
            scratch.bins = merged;
        } else {
            scratch.bins.clear(bins_per_axis);
            let spare = (n >= PAIRED_BINNING).then_some(&mut *scratch.spare_bins);
            fill_bins(
                refs,
                scale,
                min,
                bins_per_axis,
                &mut scratch.bins,
                spare,
                prim_bins,
            );
        }

        let Some((cost, axis, bin)) = self.sweep(scratch, bins_per_axis, scale) else {
            return if n <= max_leaf {
                Split::Leaf
            } else {
                Split::Median
            };
        };
        let bins = &scratch.bins.bounds[axis][..bins_per_axis];
        let side = |bins: &[Aabb]| bins.iter().fold(Aabb::EMPTY, |e, b| e.union(*b));
        let (left, right) = (side(&bins[..bin]), side(&bins[bin..]));
        let area = extent.bounds.surface_area();
        let split_cost = self.params.traversal_cost * area + cost;
        let leaf_cost = self.blocks(n) * area;
        if n <= max_leaf && leaf_cost <= split_cost {
            Split::Leaf
        } else {
            Split::Binned {
                axis,
                bin,
                bins: bins_per_axis,
                scale,
                min,
                left,
                right,
            }
        }
    }
}

impl Builder {
    /// The SAH sweep over the bins `fill_bins` left in `scratch` (`bins` per axis, the
    /// axes whose `scale` is non-zero): the cheapest split as its cost, axis and first
    /// bin on the right, the first of equal ones in axis and bin order. The three axes
    /// go together in SIMD lanes (one axis at a time, the sweep was a quarter of a
    /// bottom-level build: near the leaves it runs more steps than there are triangles).
    /// Only the boxes are swept: the sides' centroid boxes come from the partition.
    pub(super) fn sweep(
        &self,
        scratch: &mut Scratch,
        bins: usize,
        scale: Vec3A,
    ) -> Option<(f32, usize, usize)> {
        let all_bins = &scratch.bins;
        // One side of the sweep, the three axes' boxes and counts: `grow` adds bin `i`
        // of each axis, `cost` gives the three costs in the lanes (areas with the same
        // operations in the same order as `Aabb::surface_area`, whose boxes with
        // primitives are not empty, so trees do not depend on the sweep being
        // vectorised) and whether each side is empty.
        let mut side = ([Vec3A::INFINITY; 3], [Vec3A::NEG_INFINITY; 3], UVec4::ZERO);
        let grow = |(lo, hi, counts): &mut ([Vec3A; 3], [Vec3A; 3], UVec4), i: usize| {
            for axis in 0..3 {
                let bin = &all_bins.bounds[axis][i];
                lo[axis] = lo[axis].min(bin.min);
                hi[axis] = hi[axis].max(bin.max);
            }
            *counts += UVec4::from_array(all_bins.counts[i]);
        };
        let cost = |(lo, hi, counts): &([Vec3A; 3], [Vec3A; 3], UVec4)| {
            let e = Mat3A::from_cols(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]).transpose();
            let (x, y, z) = (e.x_axis, e.y_axis, e.z_axis);
            let empty = Vec3A::from_vec4(counts.as_vec4()).cmpeq(Vec3A::ZERO);
            (
                (x * y + y * z + z * x) * 2.0 * self.nonempty_blocks(*counts),
                empty,
            )
        };
        let right_cost = &mut scratch.right_cost;
        for i in (1..bins).rev() {
            grow(&mut side, i);
            let (cost, empty) = cost(&side);
            right_cost[i] = Vec3A::select(empty, Vec3A::INFINITY, cost);
        }
        let active = scale.cmpne(Vec3A::ZERO);
        let mut side = ([Vec3A::INFINITY; 3], [Vec3A::NEG_INFINITY; 3], UVec4::ZERO);
        let (mut best, mut best_bin, mut found) = (Vec3A::ZERO, Vec3A::ZERO, BVec3A::FALSE);
        for (i, &right) in (1..bins).zip(&right_cost[1..bins]) {
            grow(&mut side, i - 1);
            let (left, empty) = cost(&side);
            let (filled, cost) = (!empty, left + right);
            // Per lane, the first candidate is taken and then only cheaper ones, as a
            // scalar `Option` would: a NaN cost stays chosen exactly as it would there.
            let candidate = active & filled & right.is_finite_mask();
            let better = candidate & (!found | cost.cmplt(best));
            best = Vec3A::select(better, cost, best);
            best_bin = Vec3A::select(better, Vec3A::splat(i as f32), best_bin);
            found |= better;
        }
        // Across the axes in order, with the same rule.
        let mut chosen: Option<(f32, usize, usize)> = None;
        for axis in 0..3 {
            if found.test(axis) && chosen.is_none_or(|(cost, ..)| best[axis] < cost) {
                chosen = Some((best[axis], axis, best_bin[axis] as usize));
            }
        }
        chosen
    }

    /// [`find_split`](Self::find_split) for two primitives without the bins: the same
    /// decision to the bit (two bins per axis; the first axis that puts them in
    /// different bins, as every such axis gives the same cost) at a fraction of the
    /// cost. Half of a top-level tree's nodes hold two instances.
    pub(super) fn split_pair(&self, refs: &[PrimRef], extent: &Extent) -> Split {
        let (scale, min) = bin_transform(&extent.centroids, 2);
        let scale = if self.params.longest_axis_only {
            axis_scale(scale, extent.centroids.largest_axis())
        } else {
            scale
        };
        let split = (0..3).filter(|&axis| scale[axis] != 0.0).find_map(|axis| {
            let on_axis = axis_scale(scale, axis);
            let [a, b] = [0, 1].map(|i| bin_on_axis(refs[i].centroid(), on_axis, min, 2));
            (a != b).then(|| {
                let (low, high) = if a < b { (0, 1) } else { (1, 0) };
                (axis, refs[low].bounds(), refs[high].bounds())
            })
        });
        let Some((axis, left, right)) = split else {
            return if 2 <= self.params.max_leaf_size {
                Split::Leaf
            } else {
                Split::Median
            };
        };
        let cost = left.surface_area() * self.blocks(1) + right.surface_area() * self.blocks(1);
        let area = extent.bounds.surface_area();
        let split_cost = self.params.traversal_cost * area + cost;
        let leaf_cost = self.blocks(2) * area;
        if 2 <= self.params.max_leaf_size && leaf_cost <= split_cost {
            Split::Leaf
        } else {
            Split::Binned {
                axis,
                bin: 1,
                bins: 2,
                scale,
                min,
                left,
                right,
            }
        }
    }
}

/// Asks for `items[i + 32]`: the passes over a build's input boxes stream 32 MB for a
/// million triangles, and without the hint each waited on the memory of its next box (a
/// load that missed was half the grid sort's histogram, which took twice a pass of pure
/// reads). The passes inside the tree work on nodes the caches hold, and go without.
#[inline(always)]
pub(super) fn prefetch_ahead<T>(items: &[T], i: usize) {
    if let Some(ahead) = items.get(i + 32) {
        crate::accel::kernel::prefetch(ahead);
    }
}

/// Per-axis scale and offset mapping a centroid to a bin; scale 0 marks an
/// axis with no extent (nothing to split).
pub(super) fn bin_transform(cb: &Aabb, bins: usize) -> (Vec3A, Vec3A) {
    let extent = cb.extent();
    let scale = Vec3A::select(
        extent.cmpgt(Vec3A::ZERO) & extent.cmplt(Vec3A::splat(f32::INFINITY)),
        Vec3A::splat(bins as f32) / extent,
        Vec3A::ZERO,
    );
    // A non-finite scale (huge bins / tiny extent) would break the bin mapping.
    let scale = Vec3A::select(scale.is_finite_mask(), scale, Vec3A::ZERO);
    (scale, cb.min)
}

/// The bin of a centroid along the one axis whose `scale` lane is non-zero (the others
/// are 0): that lane's value of [`bin_indices`], the same IEEE operations in the same
/// order, so binning and partitioning agree bit for bit. The zero lanes clamp to +0 and
/// adding them is exact: a horizontal sum picks the lane without indexing a register by
/// a run-time axis (which went through the stack, a third of the partition loop).
#[inline]
pub(super) fn bin_on_axis(centroid: Vec3A, scale: Vec3A, min: Vec3A, bins: usize) -> usize {
    const MAGIC: f32 = 8_388_608.0; // 2²³
    let k = ((centroid - min) * scale - Vec3A::splat(0.5))
        .clamp(Vec3A::ZERO, Vec3A::splat(bins as f32 - 1.0));
    let k = (k.x + k.y) + k.z + MAGIC;
    (k.to_bits() & 0x7f_ffff) as usize
}

/// The plane that splits bins below `split` from the rest on `axis` (`scale` zero on the
/// other axes): the least coordinate whose [`bin_on_axis`] is at least `split`, so a
/// centroid goes left exactly when its coordinate is below it (the binning is monotone).
/// A partition then compares one lane instead of binning again. Found by galloping from
/// the bin's nominal start, then bisecting, over the floats in order; `None` when the
/// start is not finite (the caller bins each centroid instead).
pub(super) fn split_plane(
    scale: Vec3A,
    min: Vec3A,
    bins: usize,
    axis: usize,
    split: usize,
) -> Option<f32> {
    // Floats as integers in the floats' order (-0.0 just below +0.0), and back.
    let key = |x: f32| {
        let bits = x.to_bits() as i32;
        bits ^ ((bits >> 31) & 0x7fff_ffff)
    };
    let float = |k: i32| f32::from_bits((k ^ ((k >> 31) & 0x7fff_ffff)) as u32);
    let right_of_plane = |k: i32| {
        let mut centroid = min;
        centroid[axis] = float(k);
        bin_on_axis(centroid, scale, min, bins) >= split
    };
    let start = min[axis] + split as f32 / scale[axis];
    if !start.is_finite() {
        return None;
    }
    let (lowest, highest) = (key(f32::MIN), key(f32::MAX));
    // Bracket the plane between a key left of it (`below`) and one right of it
    // (`above`), with steps doubling from the start.
    let start = key(start);
    let (below, above) = if right_of_plane(start) {
        let mut step = 1i64;
        loop {
            let k = (i64::from(start) - step).max(i64::from(lowest)) as i32;
            if !right_of_plane(k) {
                break (k, start);
            }
            if k == lowest {
                return Some(f32::MIN);
            }
            step *= 2;
        }
    } else {
        let mut step = 1i64;
        loop {
            let k = (i64::from(start) + step).min(i64::from(highest)) as i32;
            if right_of_plane(k) {
                break (start, k);
            }
            if k == highest {
                return None;
            }
            step *= 2;
        }
    };
    // In i64: the keys of all floats span more than an i32.
    let (mut below, mut above) = (i64::from(below), i64::from(above));
    while above - below > 1 {
        let middle = below + (above - below) / 2;
        if right_of_plane(middle as i32) {
            above = middle;
        } else {
            below = middle;
        }
    }
    Some(float(above as i32))
}

/// `scale` with every lane but `axis` zeroed, for [`bin_on_axis`].
pub(super) fn axis_scale(scale: Vec3A, axis: usize) -> Vec3A {
    Vec3A::select(
        glam::BVec3A::new(axis == 0, axis == 1, axis == 2),
        scale,
        Vec3A::ZERO,
    )
}

/// The bin of a centroid on all three axes at once, without float-to-integer casts
/// (Rust's saturating casts were a fifth of all build instructions): clamp in SIMD, then
/// add 2²³ so the integer lands in the low mantissa bits. Rounding to nearest after
/// subtracting ½ maps `[i, i + 1)` to bin `i`; all that matters is that the mapping is
/// monotone, in range, and the same in binning and partitioning.
#[inline]
pub(super) fn bin_indices(centroid: Vec3A, scale: Vec3A, min: Vec3A, bins: usize) -> [usize; 3] {
    const MAGIC: f32 = 8_388_608.0; // 2²³
    let k = ((centroid - min) * scale - Vec3A::splat(0.5))
        .clamp(Vec3A::ZERO, Vec3A::splat(bins as f32 - 1.0))
        + Vec3A::splat(MAGIC);
    // The clamp keeps the bins below `MAX_BINS`: masking with it only tells the compiler.
    k.to_array()
        .map(|v| (v.to_bits() as usize) & (MAX_BINS - 1))
}

/// Adds each primitive to its bin on every axis; `out` holds `bins` bins per axis. When
/// one axis is binned and `prim_bins` has an entry per primitive, `prim_bins[i][axis]`
/// receives primitive `i`'s bin, so the partition that follows reads it instead of
/// computing it again (over three axes, recording the bins cost more instructions than
/// recomputing the one chosen). Over three axes, `spare` (when given) takes every other
/// primitive, and is merged into `out` at the end.
pub(super) fn fill_bins(
    refs: &[PrimRef],
    scale: Vec3A,
    min: Vec3A,
    bins: usize,
    out: &mut Bins,
    spare: Option<&mut Bins>,
    prim_bins: &mut [[u8; 3]],
) {
    // Axes with scale 0 cannot be split: skip their bins.
    let active = [scale.x != 0.0, scale.y != 0.0, scale.z != 0.0];
    if active.iter().filter(|&&a| a).count() == 1 {
        let axis = active.iter().position(|&a| a).unwrap_or(0);
        // One axis (the top level bins only the longest): one bin per primitive.
        let mut add = |r: &PrimRef| {
            let k = bin_on_axis(r.centroid(), scale, min, bins);
            let b = &mut out.bounds[axis][k];
            *b = b.union(r.bounds());
            out.counts[k][axis] += 1;
            k as u8
        };
        if prim_bins.len() == refs.len() {
            for (r, prim_bin) in refs.iter().zip(prim_bins) {
                prim_bin[axis] = add(r);
            }
        } else {
            refs.iter().for_each(|r| {
                add(r);
            });
        }
        return;
    }
    // Every axis, also one that cannot be split (its primitives all land in its first
    // bin, which the sweep then ignores): no test per axis and primitive.
    let add = |out: &mut Bins, r: &PrimRef| {
        let k = bin_indices(r.centroid(), scale, min, bins);
        let bounds = r.bounds();
        for (axis, &k) in k.iter().enumerate() {
            let b = &mut out.bounds[axis][k];
            *b = b.union(bounds);
            out.counts[k][axis] += 1;
        }
    };
    match spare {
        // Neighbouring primitives mostly share their bins, so each waited for the
        // previous one's store to its bin: every other one goes into the spare bins.
        Some(spare) => {
            spare.clear(bins);
            let (pairs, rest) = refs.as_chunks::<2>();
            for [a, b] in pairs {
                add(out, a);
                add(spare, b);
            }
            rest.iter().for_each(|r| add(out, r));
            out.merge(spare, bins);
        }
        None => refs.iter().for_each(|r| add(out, r)),
    }
}

/// Moves the primitives that `goes_left(i, centroid)` (`i` their position before the
/// move) to the front; returns their count and the two sides' centroid boxes. Branch-free
/// (Lomuto with unconditional swaps): the side of a primitive is a coin flip the branch
/// predictor cannot learn, and the mispredicted swaps of a two-cursor partition were a
/// third of the whole build. Lomuto's loop reads position `i` before anything writes it,
/// so what `goes_left` knows of position `i` (a recorded bin) is of the primitive there.
pub(super) fn partition(
    refs: &mut [PrimRef],
    goes_left: impl Fn(usize, Vec3A) -> bool,
) -> (usize, [Aabb; 2]) {
    let mut k = 0;
    let (mut left, mut right) = (Aabb::EMPTY, Aabb::EMPTY);
    for i in 0..refs.len() {
        let r = refs[i];
        let c = r.centroid();
        let is_left = goes_left(i, c);
        refs[i] = refs[k];
        refs[k] = r;
        k += is_left as usize;
        // Selects, not a branch or an indexed box: both boxes stay in registers.
        let mask = glam::BVec3A::splat(is_left);
        let (inf, neg_inf) = (Vec3A::INFINITY, Vec3A::NEG_INFINITY);
        left.min = left.min.min(Vec3A::select(mask, c, inf));
        left.max = left.max.max(Vec3A::select(mask, c, neg_inf));
        right.min = right.min.min(Vec3A::select(mask, inf, c));
        right.max = right.max.max(Vec3A::select(mask, neg_inf, c));
    }
    (k, [left, right])
}
