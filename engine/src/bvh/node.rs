//! The BVH node: 32 bytes, two per cache line, each half one aligned SIMD load.

use crate::math::Aabb;
use glam::{Vec3A, Vec4};

/// One node of a binary BVH.
///
/// `lo.xyz` and `hi.xyz` are the box corners; the `w` lanes carry the bits of `first` and
/// `count`, so a box test is two aligned 16-byte loads.
///
/// Invariants (checked by [`super::Bvh::validate`]): an interior node (`count == 0`) has
/// its two children at `first` and `first + 1`, both after itself; a leaf (`count > 0`)
/// owns primitive slots `first .. first + count`; every box contains its children's or
/// its primitives' boxes.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(32))]
pub struct BvhNode {
    /// Lower corner in xyz; `w` holds the bits of `first`.
    lo: Vec4,
    /// Upper corner in xyz; `w` holds the bits of `count`.
    hi: Vec4,
}

const _: () = assert!(std::mem::size_of::<BvhNode>() == 32);

impl BvhNode {
    fn pack(bounds: Aabb, first: u32, count: u32) -> Self {
        Self {
            lo: bounds.min.extend(f32::from_bits(first)),
            hi: bounds.max.extend(f32::from_bits(count)),
        }
    }

    /// A leaf over `count` slots starting at `first`.
    pub fn leaf(bounds: Aabb, first: u32, count: u32) -> Self {
        Self::pack(bounds, first, count)
    }

    /// An interior node whose children sit at `first` and `first + 1`.
    pub fn interior(bounds: Aabb, first: u32) -> Self {
        Self::pack(bounds, first, 0)
    }

    /// Interior: index of the left child (the right one follows). Leaf: first slot.
    #[inline]
    pub fn first(&self) -> u32 {
        self.lo.w.to_bits()
    }

    /// Number of primitive slots in a leaf; 0 marks an interior node.
    #[inline]
    pub fn count(&self) -> u32 {
        self.hi.w.to_bits()
    }

    /// This node with another `first` (used when splicing subtrees).
    pub fn with_first(self, first: u32) -> Self {
        Self {
            lo: self.lo.truncate().extend(f32::from_bits(first)),
            hi: self.hi,
        }
    }

    /// True for leaves.
    #[inline]
    pub fn is_leaf(&self) -> bool {
        self.count() > 0
    }

    /// Lower corner. The `w` lane is cleared: it holds `first`'s bits, a denormal as a
    /// float, and arithmetic on denormals takes a slow microcode path (it made the 4-wide
    /// collapse 10× slower than it needs to be).
    #[inline]
    pub fn min(&self) -> Vec3A {
        Vec3A::from_vec4(self.lo.truncate().extend(0.0))
    }

    /// Upper corner, `w` cleared as in [`min`](Self::min).
    #[inline]
    pub fn max(&self) -> Vec3A {
        Vec3A::from_vec4(self.hi.truncate().extend(0.0))
    }

    /// The node's box.
    #[inline]
    pub fn bounds(&self) -> Aabb {
        Aabb {
            min: self.min(),
            max: self.max(),
        }
    }
}
