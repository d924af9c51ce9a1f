//! The build presets: how many primitives a leaf holds, how finely to bin, when to
//! sort into grid cells first, and the cost model of the SAH.

use super::*;

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
    /// Nodes of at most this many primitives (up to [`WIDTH`](crate::accel::bvh::WIDTH)) are not
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
    /// under nodes of [`WIDTH`](crate::accel::bvh::WIDTH) lanes) open only the lanes that must open
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
