//! Binned SAH construction (Wald 2007, "On fast construction of SAH-based bounding
//! volume hierarchies") straight into 8-wide nodes: each wide node takes the two halves
//! of a SAH split and keeps splitting its widest lane until it has eight (what
//! collapsing a binary tree top-down gives, without the binary tree). Parallel over
//! subtrees and split halves with rayon, and over primitives when binning large nodes.
//! The result depends only on the input, never on the number of threads: subtrees are
//! laid out in a fixed order and binning reductions are exact (min/max and integer
//! counts).

mod assemble;
mod grid;
mod params;
mod sah;
#[cfg(test)]
mod tests;

use assemble::align_leaves;
use grid::CellSplit;
pub use params::BuildParams;
use sah::{Bins, axis_scale, bin_on_axis, partition, prefetch_ahead, split_plane};

use super::wide::WideNode;
use super::{Bvh, MAX_DEPTH, PADDING};
use crate::util::math::Aabb;
use glam::{Vec3A, Vec4};
use rayon::prelude::*;

const MAX_BINS: usize = 32;
/// Beyond this depth the builder splits at the median so the depth stays below
/// [`MAX_DEPTH`] whatever the input (each median split halves a node of < 2³² prims).
const FORCED_MEDIAN_DEPTH: usize = MAX_DEPTH - 33;
/// Nodes at least this large bin their primitives in parallel.
const PARALLEL_BINNING: usize = 1 << 16;
/// Nodes of at least this many primitives bin every other one into spare bins.
const PAIRED_BINNING: usize = 64;
/// The top level's [`BuildParams::grid_from`]: builds of at least this many instances
/// sort them into grid cells first.
pub const GRID_FROM: usize = 1 << 15;
/// The bottom level's [`BuildParams::grid_from`]: only meshes the size of a terrain.
/// Plants of 30–200 k triangles split by grid cells cost rays more nodes.
pub const BOTTOM_GRID_FROM: usize = 1 << 18;
/// Splits between grid cells this deep or deeper halve the cells by position, so the
/// cells' own trees keep their depth budget whatever the SAH made of the cells above.
const GRID_MEDIAN_DEPTH: usize = 24;

/// A primitive's box with its index in the `w` lane of the lower corner: 32 bytes, so
/// binning and partitioning move half the memory a separate centroid and index cost.
#[derive(Clone, Copy)]
struct PrimRef {
    lo: Vec4,
    hi: Vec4,
}

impl PrimRef {
    fn new(bounds: &Aabb, index: u32) -> Self {
        Self {
            lo: bounds.min.extend(f32::from_bits(index)),
            hi: bounds.max.extend(0.0),
        }
    }

    fn index(&self) -> u32 {
        self.lo.w.to_bits()
    }

    /// The lower corner with the index bits blended out of `w`: those bits are a
    /// subnormal float, and arithmetic on one (even in an unused lane) takes a microcode
    /// assist of ~100 cycles — it made the SAH sweep a fifth of the build.
    #[inline]
    fn min(&self) -> Vec3A {
        Vec3A::from_vec4(Vec4::select(
            glam::BVec4A::new(true, true, true, false),
            self.lo,
            Vec4::ZERO,
        ))
    }

    #[inline]
    fn bounds(&self) -> Aabb {
        Aabb::new(self.min(), Vec3A::from_vec4(self.hi))
    }

    /// The box centre (halves added, so boxes near the largest float do not overflow).
    #[inline]
    fn centroid(&self) -> Vec3A {
        self.min() * 0.5 + Vec3A::from_vec4(self.hi) * 0.5
    }
}

/// A node's primitives: their box and the box of their centroids.
#[derive(Clone, Copy, Debug)]
struct Extent {
    bounds: Aabb,
    centroids: Aabb,
}

impl Extent {
    const EMPTY: Extent = Extent {
        bounds: Aabb::EMPTY,
        centroids: Aabb::EMPTY,
    };

    fn of(refs: &[PrimRef]) -> Extent {
        refs.iter().fold(Extent::EMPTY, |e, r| e.with(r))
    }

    #[inline]
    fn with(self, r: &PrimRef) -> Extent {
        Extent {
            bounds: self.bounds.union(r.bounds()),
            centroids: self.centroids.grow(r.centroid()),
        }
    }

    fn union(self, other: Extent) -> Extent {
        Extent {
            bounds: self.bounds.union(other.bounds),
            centroids: self.centroids.union(other.centroids),
        }
    }
}

#[derive(Debug)]
enum Split {
    Leaf,
    Median,
    /// A split between bins; the sides' centroid boxes are left to the partition.
    Binned {
        axis: usize,
        bin: usize,
        bins: usize,
        scale: Vec3A,
        min: Vec3A,
        left: Aabb,
        right: Aabb,
    },
}

/// Per-subtree scratch memory, so a node pays only for the bins it uses instead of
/// initialising (and copying) fixed worst-case arrays: that cost dominated small nodes.
struct Scratch {
    bins: Box<Bins>,
    /// Bins for every other primitive of a large node (see [`fill_bins`]).
    spare_bins: Box<Bins>,
    /// The SAH sweep's costs of the right sides, the three axes in the lanes.
    right_cost: Vec<Vec3A>,
    /// Each primitive's bin on the one axis binned, in the node's order, written by
    /// [`fill_bins`] and read by [`partition`] (bins < 256).
    prim_bins: Vec<[u8; 3]>,
    /// The evaluated nodes of the wide nodes under construction, a stack: each wide
    /// node's lanes above its parent's, until it is made.
    lanes: Vec<Node>,
    /// The children's extents of the split nodes in `lanes` (and of their ancestors').
    children: Vec<[Extent; 2]>,
}

impl Scratch {
    /// The children's extents of `node` when it is split by the SAH, to hand to another
    /// scratch with [`adopt`](Self::adopt).
    fn children_of(&self, node: &Node) -> Option<[Extent; 2]> {
        match node.split {
            NodeSplit::Binned { children, .. } => Some(self.children[children as usize]),
            _ => None,
        }
    }

    /// `node`, evaluated with another scratch, with `children` (its children's extents
    /// there) pushed here.
    fn adopt(&mut self, mut node: Node, children: Option<[Extent; 2]>) -> Node {
        if let (Some(extents), NodeSplit::Binned { left_count, .. }) = (children, node.split) {
            self.children.push(extents);
            node.split = NodeSplit::Binned {
                left_count,
                children: self.children.len() as u32 - 1,
            };
        }
        node
    }

    fn new() -> Self {
        Self {
            bins: Bins::new(),
            spare_bins: Bins::new(),
            right_cost: vec![Vec3A::ZERO; MAX_BINS],
            prim_bins: Vec::new(),
            lanes: Vec::new(),
            children: Vec::new(),
        }
    }
}

struct Builder {
    params: BuildParams,
}

/// A node of the binary tree the SAH splits make, evaluated (its split found and its
/// primitives partitioned) when it becomes a lane of a wide node under construction.
/// Small, as the lane lists copy it about: its children's extents wait in
/// `Scratch::children`.
#[derive(Clone, Copy)]
struct Node {
    bounds: Aabb,
    /// First slot: the node's primitives are `refs[first .. first + count]`.
    first: u32,
    count: u32,
    /// Depth in the binary tree (the root 0), for the forced median splits.
    depth: u32,
    split: NodeSplit,
}

#[derive(Clone, Copy)]
enum NodeSplit {
    /// Not split: a leaf, or with lane clusters a cluster of one-slot lanes.
    Leaf,
    /// One primitive of an opened cluster, in a lane of its own.
    Slot,
    /// Split by the SAH after the first `left_count` slots; its children's extents are
    /// `Scratch::children[children]`.
    Binned { left_count: u32, children: u32 },
    /// A split of the cells' tree, by its index there.
    Cells(u32),
}

/// Wide nodes built by one task (child indices local to `nodes`), and the pieces other
/// tasks built below them, each with the node and lane that points at its root.
#[derive(Default)]
struct Piece {
    nodes: Vec<WideNode>,
    attached: Vec<(usize, usize, Piece)>,
}

impl Piece {
    /// Lists this piece and the attached ones in the order they are laid out, each with
    /// its first index there, from `base`; returns the end. `links` receives, for each
    /// attached piece, the absolute index of the node and the lane that point at it and
    /// its root's index.
    fn lay_out<'a>(
        &'a self,
        base: usize,
        order: &mut Vec<(&'a Piece, usize)>,
        links: &mut Vec<(usize, usize, u32)>,
    ) -> usize {
        order.push((self, base));
        let mut end = base + self.nodes.len();
        for (node, lane, piece) in &self.attached {
            links.push((base + node, *lane, end as u32));
            end = piece.lay_out(end, order, links);
        }
        end
    }

    /// Writes the nodes of this piece and the attached ones into `out` (cleared first)
    /// with absolute child indices, this piece's root first.
    fn flatten_into(&self, out: &mut Vec<WideNode>) {
        let (mut order, mut links) = (Vec::new(), Vec::new());
        let end = self.lay_out(0, &mut order, &mut links);
        // Copied in parallel straight into the result (an indexed collect): a serial
        // copy of 70 k nodes was 1–2 ms of a 365 k-instance top-level build.
        out.clear();
        out.par_extend((0..end).into_par_iter().map(|index| {
            let (piece, base) = order[order.partition_point(|&(_, base)| base <= index) - 1];
            piece.nodes[index - base].with_children_offset(base as u32)
        }));
        for (node, lane, root) in links {
            out[node].children[lane] = root;
        }
    }
}

/// Memory a build needs only while it runs, kept between builds by
/// [`Bvh::rebuild`]'s callers: fresh pages cost a page fault each, a fifth of a
/// 365 k-instance top-level build on this VM.
#[derive(Clone, Default)]
pub struct BuildScratch {
    refs: Vec<PrimRef>,
    /// The primitives sorted by grid cell, in the order of the cells' tree.
    sorted: Vec<PrimRef>,
}

impl std::fmt::Debug for BuildScratch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BuildScratch")
            .field("capacity", &self.refs.capacity())
            .field("sorted_capacity", &self.sorted.capacity())
            .finish()
    }
}

impl BuildScratch {
    /// Heap bytes held.
    pub fn memory_bytes(&self) -> usize {
        (self.refs.capacity() + self.sorted.capacity()) * std::mem::size_of::<PrimRef>()
    }
}

impl Bvh {
    /// Builds over primitives given by their boxes; boxes that are empty or not finite
    /// are left out (they cannot be hit). Runs on the current rayon pool.
    pub fn build(prim_bounds: &[Aabb], params: BuildParams) -> Bvh {
        let mut bvh = Bvh::default();
        bvh.rebuild(prim_bounds, params, &mut BuildScratch::default());
        bvh
    }

    /// [`build`](Self::build) into this BVH, replacing what it held but reusing its
    /// memory and `scratch`'s: the same tree as a fresh build.
    pub fn rebuild(
        &mut self,
        prim_bounds: &[Aabb],
        params: BuildParams,
        scratch: &mut BuildScratch,
    ) {
        let params = BuildParams {
            bins: params.bins.clamp(2, MAX_BINS),
            max_leaf_size: params.max_leaf_size.max(1),
            leaf_block: params.leaf_block.max(1),
            lane_cluster: if params.max_leaf_size <= 1 && params.leaf_block <= 1 {
                params.lane_cluster.clamp(1, super::WIDTH)
            } else {
                1
            },
            ..params
        };
        let usable = |b: &Aabb| !b.is_empty() && b.min.is_finite() && b.max.is_finite();
        let prim = |b: &Aabb, i: usize| usable(b).then(|| PrimRef::new(b, i as u32));
        // One pass over the boxes for the usable ones' number and extent (the index in a
        // primitive's `w` lane does not enter its box or centroid).
        let (usable_count, extent) = prim_bounds
            .par_chunks(16 * 1024)
            .map(|chunk| {
                let mut found = (0, Extent::EMPTY);
                for (i, b) in chunk.iter().enumerate() {
                    prefetch_ahead(chunk, i);
                    if usable(b) {
                        found = (found.0 + 1, found.1.with(&PrimRef::new(b, 0)));
                    }
                }
                found
            })
            .reduce(|| (0, Extent::EMPTY), |(n, e), (m, f)| (n + m, e.union(f)));
        self.wide.clear();
        self.prim_indices.clear();
        self.root_bounds = Aabb::EMPTY;
        if usable_count == 0 {
            return;
        }
        let builder = Builder { params };
        let gridded = params.grid_cell > 0 && usable_count >= params.grid_from;
        // Sorted into grid cells straight from the boxes, without the list in input
        // order first (a pass over the primitives and their memory less).
        let cell_tree = if gridded {
            let sorted = &mut scratch.sorted;
            builder.sort_into_cells(prim_bounds, prim, usable_count, sorted, &extent.centroids)
        } else {
            Vec::new()
        };
        // Sorted into cells (not a grid of one): the cells' tree splits the root.
        let refs = if cell_tree.is_empty() {
            let refs = &mut scratch.refs;
            refs.clear();
            // A filtered parallel extend goes through a list of pieces and a second
            // copy: take the direct, indexed one whenever every box is usable.
            if usable_count == prim_bounds.len() {
                refs.par_extend(
                    prim_bounds
                        .par_iter()
                        .enumerate()
                        .map(|(i, b)| PrimRef::new(b, i as u32)),
                );
            } else {
                refs.par_extend(
                    prim_bounds
                        .par_iter()
                        .enumerate()
                        .filter_map(|(i, b)| prim(b, i)),
                );
            }
            refs.as_mut_slice()
        } else {
            scratch.sorted.as_mut_slice()
        };
        let mut root_scratch = Scratch::new();
        let root = builder.evaluate(
            refs,
            0,
            extent,
            0,
            (!cell_tree.is_empty()).then_some(0),
            &mut root_scratch,
        );
        let mut piece = Piece::default();
        builder.emit(root, refs, &cell_tree, &mut root_scratch, &mut piece);
        piece.flatten_into(&mut self.wide);
        self.root_bounds = extent.bounds;
        if params.leaf_block > 1 {
            align_leaves(
                &mut self.wide,
                refs,
                params.leaf_block,
                &mut self.prim_indices,
            );
        } else {
            self.prim_indices
                .par_extend(refs.par_iter().map(PrimRef::index));
        }
    }
}
