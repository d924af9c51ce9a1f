//! The BVH node: 32 bytes, two per cache line.

use crate::math::Aabb;
use glam::Vec3A;

/// One node of a binary BVH.
///
/// Invariants (checked by [`super::Bvh::validate`]): an interior node (`count == 0`) has
/// its two children at `first` and `first + 1`, both after itself; a leaf (`count > 0`)
/// owns primitive slots `first .. first + count`; every box contains its children's or
/// its primitives' boxes.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(32))]
pub struct BvhNode {
    /// Lower corner of the node's box.
    pub min: [f32; 3],
    /// Interior: index of the left child (the right one follows). Leaf: first slot.
    pub first: u32,
    /// Upper corner of the node's box.
    pub max: [f32; 3],
    /// Number of primitive slots in a leaf; 0 marks an interior node.
    pub count: u32,
}

const _: () = assert!(std::mem::size_of::<BvhNode>() == 32);

impl BvhNode {
    /// A leaf over `count` slots starting at `first`.
    pub fn leaf(bounds: Aabb, first: u32, count: u32) -> Self {
        Self {
            min: bounds.min.to_array(),
            first,
            max: bounds.max.to_array(),
            count,
        }
    }

    /// An interior node whose children sit at `first` and `first + 1`.
    pub fn interior(bounds: Aabb, first: u32) -> Self {
        Self {
            min: bounds.min.to_array(),
            first,
            max: bounds.max.to_array(),
            count: 0,
        }
    }

    /// True for leaves.
    #[inline]
    pub fn is_leaf(&self) -> bool {
        self.count > 0
    }

    /// The node's box.
    #[inline]
    pub fn bounds(&self) -> Aabb {
        Aabb {
            min: Vec3A::from_array(self.min),
            max: Vec3A::from_array(self.max),
        }
    }
}
