//! Wide nodes straight from SAH splits: a node opens its widest lane until it has
//! eight (what collapsing a binary tree top-down gives, without the binary tree), and
//! subtrees are laid out in a fixed order whatever thread built them; leaves are then
//! aligned to triangle blocks.

use super::*;
use crate::accel::bvh::wide::{WIDTH, WideNode};
use glam::Vec3A;
use rayon::prelude::*;

impl Builder {
    /// Finds the split of the node over `refs` (its primitives, from slot `first`) and
    /// partitions them by it: what the node's parent needs to know of it as a lane.
    /// Nodes of the cells' tree (`cell_node`) are split as that tree says.
    pub(super) fn evaluate(
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
    pub(super) fn clusters(&self) -> bool {
        self.params.lane_cluster > 1
    }

    /// True when `node` becomes a wide node of its own unless opened into its parent:
    /// a split node, or a cluster.
    pub(super) fn makes_node(&self, node: &Node) -> bool {
        match node.split {
            NodeSplit::Binned { .. } | NodeSplit::Cells(_) => true,
            NodeSplit::Leaf => self.clusters() && node.count > 1,
            NodeSplit::Slot => false,
        }
    }

    /// The lanes that opening `node` makes: its two children, or a cluster's slots.
    pub(super) fn opened_lanes(node: &Node) -> usize {
        match node.split {
            NodeSplit::Binned { .. } | NodeSplit::Cells(_) => 2,
            NodeSplit::Leaf => node.count as usize,
            NodeSplit::Slot => 0,
        }
    }

    /// The area of `node` and the lanes opening it adds, or `None` when it cannot be
    /// opened (a leaf, or a slot).
    pub(super) fn opening(&self, node: &Node) -> Option<(f32, usize)> {
        self.makes_node(node)
            .then(|| (node.bounds.surface_area(), Self::opened_lanes(node) - 1))
    }

    /// Evaluates the lanes `node` opens into (its two children, or a cluster's slots),
    /// pushes them on `scratch.lanes` and writes their places there into `out`, which
    /// has room for [`opened_lanes`](Self::opened_lanes). `refs` holds the node's
    /// primitives.
    pub(super) fn open(
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
    pub(super) fn lanes(
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
    pub(super) fn emit(
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
    pub(super) fn leaves_needed(&self, node: &Node) -> usize {
        (node.count as usize).div_ceil(self.params.max_leaf_size.max(1))
    }

    pub(super) fn levels_needed(&self, node: &Node) -> u32 {
        let mut leaves = self.leaves_needed(node);
        let mut levels = 0;
        while leaves > 1 {
            leaves = leaves.div_ceil(WIDTH);
            levels += 1;
        }
        levels
    }
}

/// Writes the primitives of `refs` into `aligned` (empty) in slot order with every
/// leaf's slots moved to start at a multiple of `block`, filling the gaps with
/// [`PADDING`](PADDING), and rewrites the leaf lanes' first slots in `wide` to
/// match. The lanes of a node are in slot order and a subtree's slots are contiguous, so
/// a depth-first walk meets the leaves in slot order (a sort of them was a fiftieth of a
/// bottom-level build).
pub(super) fn align_leaves(
    wide: &mut [WideNode],
    refs: &[PrimRef],
    block: usize,
    aligned: &mut Vec<u32>,
) {
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
        aligned.resize(aligned.len().next_multiple_of(block), PADDING);
    }
}
