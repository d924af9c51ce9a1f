//! Binned SAH construction (Wald 2007, "On fast construction of SAH-based bounding
//! volume hierarchies") straight into 8-wide nodes: each wide node takes the two halves
//! of a SAH split and keeps splitting its widest lane until it has eight (what
//! collapsing a binary tree top-down gives, without the binary tree). Parallel over
//! subtrees and split halves with rayon, and over primitives when binning large nodes.
//! The result depends only on the input, never on the number of threads: subtrees are
//! laid out in a fixed order and binning reductions are exact (min/max and integer
//! counts).

use super::wide::{WIDTH, WideNode};
use super::{Bvh, MAX_DEPTH};
use crate::util::math::Aabb;
use glam::{BVec3A, Mat3A, UVec4, Vec3A, Vec4};
use rayon::prelude::*;

/// Settings of the builder; see the presets.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BuildParams {
    /// SAH bins per axis (2 ..= 32).
    pub bins: usize,
    /// Largest leaf the builder may make when the SAH prefers it.
    pub max_leaf_size: usize,
    /// Cost of visiting a node relative to one primitive test.
    pub traversal_cost: f32,
    /// Nodes with at least this many primitives build their two subtrees in parallel.
    pub parallel_threshold: usize,
    /// Bin only along the longest axis of the centroid box (less binning work, slightly
    /// worse trees) instead of along all three.
    pub longest_axis_only: bool,
    /// Primitives a leaf tests together (SIMD lanes): the SAH counts a leaf's cost in
    /// blocks of this many, so three primitives cost as much as four, and every leaf
    /// starts at a multiple of it, the slots after its primitives up to the next
    /// multiple holding [`PADDING`](super::PADDING) (so slot `s` is lane `s % n` of
    /// block `s / n`). 1 counts each primitive and pads nothing.
    pub leaf_block: usize,
    /// Nodes of at most this many primitives (up to [`WIDTH`](super::WIDTH)) are not
    /// split but kept as one cluster, and the wide tree gives each of their primitives a
    /// lane of its own, in the node above when it has the
    /// lanes to spare, else in a node of their own. 1 turns it off; it applies only to
    /// trees of one-primitive leaves (`max_leaf_size` and `leaf_block` 1).
    pub lane_cluster: usize,
    /// Builds of at least `grid_from` primitives first sort them into the cells of a
    /// grid, about this many to a cell: the SAH then splits between whole cells down to
    /// single ones, and each cell's tree is built as usual (0: off; cells hold at least
    /// 64 on average).
    pub grid_cell: usize,
    /// The size from which a build sorts into grid cells (see `grid_cell`).
    pub grid_from: usize,
    /// Subtrees that need at most this many wide levels (leaves of `max_leaf_size`
    /// under nodes of [`WIDTH`](super::WIDTH) lanes) open only the lanes that must open
    /// to keep that depth, and lanes whose leaves all fit in the lanes left, instead of
    /// every lane the node has room for, so their lower nodes come out full. Opening the widest lanes first fills a node's lanes from
    /// the top, and a complete tree whose binary depth is one more than a multiple of
    /// three then ends in nodes of two leaves (0: that greedy opening everywhere).
    pub fill_levels: u32,
    /// For meshes ([`Geometry::new`](crate::accel::geometry::Geometry::new)): a triangle whose
    /// box's surface area is more than this many times twice its area (the least a
    /// triangle's box can have) is built from the boxes of its two halves, so rays
    /// passing near a long slanted blade enter fewer leaves
    /// ([`triangle_boxes`](crate::accel::presplit::triangle_boxes); 0: never). Box builds
    /// ignore it.
    pub split_ratio: f32,
}

impl BuildParams {
    /// Few bins and big leaves: quickest build, slower traversal.
    pub const FAST: BuildParams = BuildParams {
        bins: 8,
        max_leaf_size: 8,
        traversal_cost: 1.0,
        parallel_threshold: 4096,
        longest_axis_only: true,
        leaf_block: 1,
        lane_cluster: 1,
        grid_cell: 0,
        grid_from: usize::MAX,
        fill_levels: 0,
        split_ratio: 0.0,
    };
    /// The default: binned SAH over all three axes.
    pub const BALANCED: BuildParams = BuildParams {
        bins: 16,
        max_leaf_size: 4,
        traversal_cost: 1.0,
        parallel_threshold: 4096,
        longest_axis_only: false,
        leaf_block: 1,
        lane_cluster: 1,
        grid_cell: 0,
        grid_from: usize::MAX,
        fill_levels: 0,
        split_ratio: 0.0,
    };
    /// Many bins and small leaves: best traversal, slowest build.
    pub const QUALITY: BuildParams = BuildParams {
        bins: 32,
        max_leaf_size: 2,
        traversal_cost: 1.0,
        parallel_threshold: 4096,
        longest_axis_only: false,
        leaf_block: 1,
        lane_cluster: 1,
        grid_cell: 0,
        grid_from: usize::MAX,
        fill_levels: 0,
        split_ratio: 0.0,
    };
    /// The top level's default: eight bins along the longest axis of the centroids, and
    /// one instance per leaf. Over plant instances it builds faster than
    /// [`BALANCED`](Self::BALANCED) and its trees cost rays less work, although their SAH
    /// cost is higher: measured per ray, nodes −4 % and primitive tests −5 % on `paper`,
    /// nodes −10 % and tests −3 % on `forest`, nodes −4 % and tests +1 % on the
    /// 10,000-plant anchor meadow (ecosystems are flat, and their rays mostly run near the
    /// ground or up from it, not in the uniform directions SAH assumes). Leaves of one
    /// instance test every instance's own box in the wide node's SIMD lanes before its
    /// bottom level is entered: with leaves of up to four, a shadow ray of the anchor
    /// scene entered 4.25 plant instances, with one 2.53 (TLAS nodes 8.9 → 9.5).
    /// Nodes of up to eight instances are clusters, not split further (seven of every
    /// eight binary splits, and their bins, were in such nodes): a rebuild of 365,041
    /// instances 68–71 → 48–51 ms, rays' nodes and tests within ±1 %, images the same.
    /// Above [`GRID_FROM`] instances the top levels split between grid cells of about
    /// 1,024 instances (a sort instead of the passes over every instance in the 511
    /// nodes of ≥ 1,024 that made 55 % of them): a rebuild of 365,041 instances 73 →
    /// 65–67 ms, and `paper` rays visit fewer nodes (27.8 → 26.4), images the same.
    pub const TOP_LEVEL: BuildParams = BuildParams {
        bins: 8,
        max_leaf_size: 1,
        traversal_cost: 1.0,
        parallel_threshold: 4096,
        longest_axis_only: true,
        leaf_block: 1,
        lane_cluster: 8,
        grid_cell: 1024,
        grid_from: GRID_FROM,
        fill_levels: 0,
        split_ratio: 0.0,
    };
    /// The bottom level's default, over a species' triangles: leaves are tested four
    /// triangles at a time, so the SAH counts them in blocks of four (instructions per
    /// frame of the anchor scene −1.5 % against counting triangles; leaves of up to
    /// eight, or cheaper nodes, changed it by under ±0.5 %). Subtrees of up to two wide
    /// levels fill their nodes (`fill_levels`): the anchor meadow's 2 M-triangle
    /// terrain made 289,994 nodes, 244,016 of them with two leaves, and makes 102,391
    /// (32 with two leaves); its bottom levels 254 → 206 MB, `paper`'s 496 → 442 MB;
    /// nodes per ray 15.4 → 15.1, instructions per frame −0.9 %. Triangles whose box
    /// is over 8 × their least (`split_ratio`) are built from their halves: 0.25 % of the
    /// anchor meadow's triangles (mostly its grass blades), 12 % of `paper`'s; triangle
    /// slots tested per ray −16 % and −19 %.
    pub const BOTTOM_LEVEL: BuildParams = BuildParams {
        bins: 16,
        max_leaf_size: 4,
        traversal_cost: 1.0,
        parallel_threshold: 4096,
        longest_axis_only: false,
        leaf_block: 4,
        lane_cluster: 1,
        grid_cell: 1024,
        grid_from: BOTTOM_GRID_FROM,
        fill_levels: 2,
        split_ratio: 8.0,
    };
    /// Every preset with its name, for tests and benchmarks.
    pub const PRESETS: [(&'static str, BuildParams); 5] = [
        ("fast", Self::FAST),
        ("balanced", Self::BALANCED),
        ("quality", Self::QUALITY),
        ("top-level", Self::TOP_LEVEL),
        ("bottom-level", Self::BOTTOM_LEVEL),
    ];
}

impl Default for BuildParams {
    fn default() -> Self {
        Self::BALANCED
    }
}

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

/// A node's bins on the three axes: each bin's box, axis by axis, and each bin's number
/// of primitives with the axes in the lanes, so the SAH sweep reads a bin's three counts
/// as one vector. Their centroids' box is left to the partition (see [`partition`]):
/// keeping it here doubled the stores per primitive and bin, and binning is store-bound.
/// Fixed-size, so bin indices masked below [`MAX_BINS`] index without bounds checks.
#[derive(Clone)]
struct Bins {
    bounds: [[Aabb; MAX_BINS]; 3],
    counts: [[u32; 4]; MAX_BINS],
}

impl Bins {
    /// Empty bins, all of them (so also cleared for any number of bins).
    fn new() -> Box<Bins> {
        Box::new(Bins {
            bounds: [[Aabb::EMPTY; MAX_BINS]; 3],
            counts: [[0; 4]; MAX_BINS],
        })
    }

    /// Empties the first `bins` bins of every axis.
    fn clear(&mut self, bins: usize) {
        for axis in &mut self.bounds {
            axis[..bins].fill(Aabb::EMPTY);
        }
        self.counts[..bins].fill([0; 4]);
    }

    /// Adds `other`'s first `bins` bins of every axis into these.
    fn merge(&mut self, other: &Bins, bins: usize) {
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

impl Builder {
    /// Finds the split of the node over `refs` (its primitives, from slot `first`) and
    /// partitions them by it: what the node's parent needs to know of it as a lane.
    /// Nodes of the cells' tree (`cell_node`) are split as that tree says.
    fn evaluate(
        &self,
        refs: &mut [PrimRef],
        first: u32,
        extent: Extent,
        depth: u32,
        cell_node: Option<u32>,
        scratch: &mut Scratch,
    ) -> Node {
        let n = refs.len();
        let node = |split| Node {
            bounds: extent.bounds,
            first,
            count: n as u32,
            depth,
            split,
        };
        if let Some(index) = cell_node {
            return node(NodeSplit::Cells(index));
        }
        let (mid, left, right) = match self.find_split(refs, &extent, depth as usize, scratch) {
            Split::Leaf => return node(NodeSplit::Leaf),
            Split::Median => {
                let mid = n / 2;
                (mid, Extent::of(&refs[..mid]), Extent::of(&refs[mid..]))
            }
            Split::Binned {
                axis,
                bin,
                bins,
                scale,
                min,
                left,
                right,
            } => {
                // Binning along one axis records each primitive's bin (a pair's split
                // is made without binning).
                let (mid, [left_centroids, right_centroids]) =
                    if self.params.longest_axis_only && n > 2 {
                        let prim_bins = &scratch.prim_bins[..n];
                        partition(refs, |i, _| usize::from(prim_bins[i][axis]) < bin)
                    } else {
                        let scale = axis_scale(scale, axis);
                        match split_plane(scale, min, bins, axis, bin) {
                            Some(plane) => {
                                let (plane, lane) = (Vec3A::splat(plane), 1 << axis);
                                partition(refs, |_, c| c.cmplt(plane).bitmask() & lane != 0)
                            }
                            None => partition(refs, |_, c| bin_on_axis(c, scale, min, bins) < bin),
                        }
                    };
                let side = |bounds, centroids| Extent { bounds, centroids };
                (
                    mid,
                    side(left, left_centroids),
                    side(right, right_centroids),
                )
            }
        };
        scratch.children.push([left, right]);
        node(NodeSplit::Binned {
            left_count: mid as u32,
            children: scratch.children.len() as u32 - 1,
        })
    }

    /// True when lanes may be clusters of one-slot lanes.
    fn clusters(&self) -> bool {
        self.params.lane_cluster > 1
    }

    /// True when `node` becomes a wide node of its own unless opened into its parent:
    /// a split node, or a cluster.
    fn makes_node(&self, node: &Node) -> bool {
        match node.split {
            NodeSplit::Binned { .. } | NodeSplit::Cells(_) => true,
            NodeSplit::Leaf => self.clusters() && node.count > 1,
            NodeSplit::Slot => false,
        }
    }

    /// The lanes that opening `node` makes: its two children, or a cluster's slots.
    fn opened_lanes(node: &Node) -> usize {
        match node.split {
            NodeSplit::Binned { .. } | NodeSplit::Cells(_) => 2,
            NodeSplit::Leaf => node.count as usize,
            NodeSplit::Slot => 0,
        }
    }

    /// The area of `node` and the lanes opening it adds, or `None` when it cannot be
    /// opened (a leaf, or a slot).
    fn opening(&self, node: &Node) -> Option<(f32, usize)> {
        self.makes_node(node)
            .then(|| (node.bounds.surface_area(), Self::opened_lanes(node) - 1))
    }

    /// Evaluates the lanes `node` opens into (its two children, or a cluster's slots),
    /// pushes them on `scratch.lanes` and writes their places there into `out`, which
    /// has room for [`opened_lanes`](Self::opened_lanes). `refs` holds the node's
    /// primitives.
    fn open(
        &self,
        node: &Node,
        refs: &mut [PrimRef],
        cell_tree: &[CellSplit],
        scratch: &mut Scratch,
        out: &mut [u32],
    ) {
        match node.split {
            NodeSplit::Binned { .. } | NodeSplit::Cells(_) => {
                let (left_count, [left, right], cell_nodes) = match node.split {
                    NodeSplit::Cells(index) => {
                        let cells = &cell_tree[index as usize];
                        (cells.left_count, [cells.left, cells.right], cells.children)
                    }
                    NodeSplit::Binned {
                        left_count,
                        children,
                    } => (left_count, scratch.children[children as usize], [None; 2]),
                    _ => unreachable!("only split nodes open into two"),
                };
                let (left_refs, right_refs) = refs.split_at_mut(left_count as usize);
                let right_first = node.first + left_count;
                let half =
                    |refs: &mut [PrimRef], first, extent, cell_node, scratch: &mut Scratch| {
                        self.evaluate(refs, first, extent, node.depth + 1, cell_node, scratch)
                    };
                let evaluated = if node.count as usize >= self.params.parallel_threshold {
                    // Both halves at once, as a binary build splits its subtrees: the
                    // top wide node alone evaluates about three levels of the tree.
                    let mut own = Scratch::new();
                    let (left_node, right_node) = rayon::join(
                        || half(left_refs, node.first, left, cell_nodes[0], scratch),
                        || half(right_refs, right_first, right, cell_nodes[1], &mut own),
                    );
                    [
                        left_node,
                        scratch.adopt(right_node, own.children_of(&right_node)),
                    ]
                } else {
                    [
                        half(left_refs, node.first, left, cell_nodes[0], scratch),
                        half(right_refs, right_first, right, cell_nodes[1], scratch),
                    ]
                };
                for (child, place) in evaluated.into_iter().zip(out) {
                    *place = scratch.lanes.len() as u32;
                    scratch.lanes.push(child);
                }
            }
            NodeSplit::Leaf => {
                for ((offset, r), place) in refs.iter().enumerate().zip(out) {
                    *place = scratch.lanes.len() as u32;
                    scratch.lanes.push(Node {
                        bounds: r.bounds(),
                        first: node.first + offset as u32,
                        count: 1,
                        depth: node.depth + 1,
                        split: NodeSplit::Slot,
                    });
                }
            }
            NodeSplit::Slot => {}
        }
    }

    /// The lanes of the wide node made from `node` (a split node or a cluster, over
    /// `refs`), as places in `scratch.lanes`: its children, then, while lanes are left,
    /// the widest child that can be opened is replaced by its own children, in order
    /// (so the lanes stay in slot order). This makes the tree that collapsing the
    /// binary tree top-down would make, without building the binary tree.
    fn lanes(
        &self,
        node: &Node,
        refs: &mut [PrimRef],
        cell_tree: &[CellSplit],
        scratch: &mut Scratch,
    ) -> ([u32; WIDTH], usize) {
        let mut lanes = [0u32; WIDTH];
        let mut openings = [None; WIDTH];
        let mut len = Self::opened_lanes(node);
        self.open(node, refs, cell_tree, scratch, &mut lanes[..len]);
        for position in 0..len {
            openings[position] = self.opening(&scratch.lanes[lanes[position] as usize]);
        }
        // A subtree of at most `fill_levels` wide levels opens the lanes that must open
        // to keep it that shallow (widest first), then lanes whose leaves all fit in the
        // lanes left (fewest leaves first, so one is flattened before the next starts),
        // so the nodes below fill up (see `fill_levels`). Elsewhere the widest lane opens.
        let levels = self.levels_needed(node);
        let fill = levels <= self.params.fill_levels;
        let below = levels.saturating_sub(1);
        while len < WIDTH {
            // The lane to open: the greatest (must open, score).
            let mut widest: Option<(usize, (bool, f32))> = None;
            for (position, opening) in openings[..len].iter().enumerate() {
                let Some((area, added)) = *opening else {
                    continue;
                };
                if len + added > WIDTH {
                    continue;
                }
                let key = if fill {
                    let lane = &scratch.lanes[lanes[position] as usize];
                    let leaves = self.leaves_needed(lane);
                    if self.levels_needed(lane) > below {
                        (true, area)
                    } else if leaves + len <= WIDTH + 1 {
                        (false, -(leaves as f32))
                    } else {
                        continue;
                    }
                } else {
                    (true, area)
                };
                if widest.is_none_or(|(_, best)| key > best) {
                    widest = Some((position, key));
                }
            }
            let Some((position, _)) = widest else {
                break;
            };
            let opened = scratch.lanes[lanes[position] as usize];
            let start = (opened.first - node.first) as usize;
            let opened_refs = &mut refs[start..start + opened.count as usize];
            let count = Self::opened_lanes(&opened);
            // The opened node's lanes take its place, in order.
            lanes.copy_within(position + 1..len, position + count);
            openings.copy_within(position + 1..len, position + count);
            let places = &mut lanes[position..position + count];
            self.open(&opened, opened_refs, cell_tree, scratch, places);
            for offset in position..position + count {
                openings[offset] = self.opening(&scratch.lanes[lanes[offset] as usize]);
            }
            len += count - 1;
        }
        (lanes, len)
    }

    /// Appends the wide subtree of `node` (evaluated, over `refs`) to `piece`, its
    /// root first, and returns the root's index in the piece. A node that makes no
    /// wide node of its own (only the root can be one) becomes a root of one lane.
    /// Children of at least `parallel_threshold` primitives are built on the rayon
    /// pool as pieces of their own, attached to this one.
    fn emit(
        &self,
        node: Node,
        refs: &mut [PrimRef],
        cell_tree: &[CellSplit],
        scratch: &mut Scratch,
        piece: &mut Piece,
    ) -> u32 {
        let at = piece.nodes.len();
        piece.nodes.push(WideNode::empty());
        let (base, children_base) = (scratch.lanes.len(), scratch.children.len());
        let (lanes, len) = if self.makes_node(&node) {
            self.lanes(&node, refs, cell_tree, scratch)
        } else {
            scratch.lanes.push(node);
            ([base as u32; WIDTH], 1)
        };
        let mut wide = WideNode::empty();
        let big = |lane: &Node| lane.count as usize >= self.params.parallel_threshold;
        let parallel = lanes[..len].iter().any(|&place| {
            let lane = &scratch.lanes[place as usize];
            self.makes_node(lane) && big(lane)
        });
        let mut rest = refs;
        if !parallel {
            for (position, &place) in lanes[..len].iter().enumerate() {
                let lane = scratch.lanes[place as usize];
                let (lane_refs, tail) = rest.split_at_mut(lane.count as usize);
                rest = tail;
                wide.set_box(position, lane.bounds);
                if self.makes_node(&lane) {
                    wide.children[position] = self.emit(lane, lane_refs, cell_tree, scratch, piece);
                } else {
                    wide.children[position] = lane.first;
                    wide.counts[position] = lane.count;
                }
            }
        } else {
            let mut serial = Vec::with_capacity(len);
            let mut parallel = Vec::with_capacity(len);
            for (position, &place) in lanes[..len].iter().enumerate() {
                let lane = scratch.lanes[place as usize];
                let (lane_refs, tail) = rest.split_at_mut(lane.count as usize);
                rest = tail;
                wide.set_box(position, lane.bounds);
                if !self.makes_node(&lane) {
                    wide.children[position] = lane.first;
                    wide.counts[position] = lane.count;
                } else if big(&lane) {
                    // Its own task has scratch of its own: the children's extents go along.
                    parallel.push((position, lane, scratch.children_of(&lane), lane_refs));
                } else {
                    serial.push((position, lane, lane_refs));
                }
            }
            let (pieces, ()) = rayon::join(
                || {
                    parallel
                        .into_par_iter()
                        .map(|(position, lane, children, lane_refs)| {
                            let mut own = Piece {
                                nodes: Vec::with_capacity(lane.count as usize / 4 + 1),
                                attached: Vec::new(),
                            };
                            let mut own_scratch = Scratch::new();
                            let lane = own_scratch.adopt(lane, children);
                            self.emit(lane, lane_refs, cell_tree, &mut own_scratch, &mut own);
                            (position, own)
                        })
                        .collect::<Vec<_>>()
                },
                || {
                    for (position, lane, lane_refs) in serial {
                        wide.children[position] =
                            self.emit(lane, lane_refs, cell_tree, scratch, piece);
                    }
                },
            );
            for (position, own) in pieces {
                piece.attached.push((at, position, own));
            }
        }
        piece.nodes[at] = wide;
        scratch.lanes.truncate(base);
        scratch.children.truncate(children_base);
        at as u32
    }

    /// Wide levels a subtree of `node`'s primitives needs at least: leaves of up to
    /// `max_leaf_size` primitives under nodes of [`WIDTH`] lanes.
    /// Leaves a subtree of `node`'s primitives needs at least.
    fn leaves_needed(&self, node: &Node) -> usize {
        (node.count as usize).div_ceil(self.params.max_leaf_size.max(1))
    }

    fn levels_needed(&self, node: &Node) -> u32 {
        let mut leaves = self.leaves_needed(node);
        let mut levels = 0;
        while leaves > 1 {
            leaves = leaves.div_ceil(WIDTH);
            levels += 1;
        }
        levels
    }

    /// The cost of testing `count` primitives, in blocks of `leaf_block`.
    #[inline]
    fn blocks(&self, count: usize) -> f32 {
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
    fn nonempty_blocks(&self, counts: UVec4) -> Vec3A {
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

    fn find_split(
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
    fn binned_split(&self, refs: &[PrimRef], extent: &Extent, scratch: &mut Scratch) -> Split {
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
    fn sweep(
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
    fn split_pair(&self, refs: &[PrimRef], extent: &Extent) -> Split {
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

/// Writes the primitives of `refs` into `aligned` (empty) in slot order with every
/// leaf's slots moved to start at a multiple of `block`, filling the gaps with
/// [`PADDING`](super::PADDING), and rewrites the leaf lanes' first slots in `wide` to
/// match. The lanes of a node are in slot order and a subtree's slots are contiguous, so
/// a depth-first walk meets the leaves in slot order (a sort of them was a fiftieth of a
/// bottom-level build).
fn align_leaves(wide: &mut [WideNode], refs: &[PrimRef], block: usize, aligned: &mut Vec<u32>) {
    aligned.reserve(refs.len() + refs.len() / 2);
    let mut stack = vec![(0usize, 0usize)];
    while let Some((index, lane)) = stack.pop() {
        if lane == WIDTH || !wide[index].is_used(lane) {
            continue;
        }
        stack.push((index, lane + 1));
        let node = &mut wide[index];
        let (first, count) = (node.children[lane] as usize, node.counts[lane] as usize);
        if count == 0 {
            stack.push((first, 0));
            continue;
        }
        node.children[lane] = aligned.len() as u32;
        aligned.extend(refs[first..first + count].iter().map(PrimRef::index));
        aligned.resize(aligned.len().next_multiple_of(block), super::PADDING);
    }
}

/// Asks for `items[i + 32]`: the passes over a build's input boxes stream 32 MB for a
/// million triangles, and without the hint each waited on the memory of its next box (a
/// load that missed was half the grid sort's histogram, which took twice a pass of pure
/// reads). The passes inside the tree work on nodes the caches hold, and go without.
#[inline(always)]
fn prefetch_ahead<T>(items: &[T], i: usize) {
    if let Some(ahead) = items.get(i + 32) {
        crate::accel::kernel::prefetch(ahead);
    }
}

/// Per-axis scale and offset mapping a centroid to a bin; scale 0 marks an
/// axis with no extent (nothing to split).
fn bin_transform(cb: &Aabb, bins: usize) -> (Vec3A, Vec3A) {
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
fn bin_on_axis(centroid: Vec3A, scale: Vec3A, min: Vec3A, bins: usize) -> usize {
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
fn split_plane(scale: Vec3A, min: Vec3A, bins: usize, axis: usize, split: usize) -> Option<f32> {
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
fn axis_scale(scale: Vec3A, axis: usize) -> Vec3A {
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
fn bin_indices(centroid: Vec3A, scale: Vec3A, min: Vec3A, bins: usize) -> [usize; 3] {
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
fn fill_bins(
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
fn partition(refs: &mut [PrimRef], goes_left: impl Fn(usize, Vec3A) -> bool) -> (usize, [Aabb; 2]) {
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

/// A grid cell's primitives: their extent, their number, and the cell's index in the
/// grid.
#[derive(Clone, Copy)]
struct Cell {
    extent: Extent,
    count: u32,
    grid: u32,
}

/// A split of the cells' tree: the first `left_count` slots of the node (whole cells)
/// go left; the children's extents; which children are splits of this tree too (their
/// index), `None` marking a single cell, whose primitives the SAH splits as usual.
#[derive(Clone, Copy)]
struct CellSplit {
    left_count: u32,
    left: Extent,
    right: Extent,
    children: [Option<u32>; 2],
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
    fn sort_into_cells<T: Sync>(
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
    fn split_cells(
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::test_random::uniform;

    #[test]
    fn split_planes_part_centroids_as_their_bins_do() {
        let mut state = 0x5b1a_9e11u64;
        for case in 0..2_000 {
            // Centroid boxes near and far from the origin, wide and a few ulps thin.
            let offset = [0.0, -3.0, 1.0e5, -2.5e4][case % 4];
            let width = [1.0e-3, 1.0, 300.0, 4.0e-2][(case / 4) % 4];
            let lo = Vec3A::new(
                offset + uniform(&mut state) * width,
                offset - uniform(&mut state) * width,
                offset,
            );
            let hi = lo + Vec3A::new(width, width * uniform(&mut state), width * 1.0e-4);
            let bins = [2, 8, 16, 32][case % 4];
            let (scale, min) = bin_transform(&Aabb::new(lo, hi), bins);
            for axis in (0..3).filter(|&axis| scale[axis] != 0.0) {
                let on_axis = axis_scale(scale, axis);
                for split in 1..bins {
                    let plane = split_plane(on_axis, min, bins, axis, split)
                        .unwrap_or_else(|| panic!("case {case}: no plane for bin {split}"));
                    let goes_left = |x: f32| {
                        let mut centroid = min;
                        centroid[axis] = x;
                        bin_on_axis(centroid, on_axis, min, bins) < split
                    };
                    let near = [plane, plane.next_down(), plane.next_up(), 0.0, -0.0];
                    let spread = (0..20).map(|_| {
                        lo[axis] + (uniform(&mut state) * 1.2 - 0.1) * (hi[axis] - lo[axis])
                    });
                    for x in near.into_iter().chain(spread) {
                        assert_eq!(x < plane, goes_left(x), "case {case}, axis {axis}, x {x}");
                    }
                }
            }
        }
    }

    #[test]
    fn a_pair_splits_as_the_bins_would_split_it() {
        let mut state = 0x9a1e_5eedu64;
        let coordinate = |state: &mut u64| match (uniform(state) * 4.0) as u32 {
            // Shared coordinates and coincident centroids take the other branches.
            0 => 0.25,
            _ => uniform(state) * 2.0 - 1.0,
        };
        for case in 0..20_000 {
            let refs: Vec<PrimRef> = (0..2)
                .map(|i| {
                    let lo = Vec3A::new(
                        coordinate(&mut state),
                        coordinate(&mut state),
                        coordinate(&mut state),
                    );
                    let size = Vec3A::new(uniform(&mut state), uniform(&mut state), 0.1);
                    PrimRef::new(&Aabb::new(lo, lo + size * (case % 3) as f32), i)
                })
                .collect();
            let extent = Extent::of(&refs);
            for (name, params) in BuildParams::PRESETS {
                let builder = Builder { params };
                let pair = builder.split_pair(&refs, &extent);
                let binned = builder.binned_split(&refs, &extent, &mut Scratch::new());
                assert_eq!(
                    format!("{pair:?}"),
                    format!("{binned:?}"),
                    "case {case}, {name}"
                );
            }
        }
    }
}
