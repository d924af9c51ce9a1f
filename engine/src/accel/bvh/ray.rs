//! What a walk is given: a ray prepared for the slab tests of wide nodes ([`NodeRay`])
//! with the bounds that keep those tests conservative, and what the walk does at a leaf
//! ([`LeafVisit`]).

use crate::util::math::{Ray, gamma};
use glam::Vec3A;

/// A ray prepared for slab tests against the boxes of a [`WideNode`](super::WideNode).
#[derive(Clone, Copy, Debug)]
pub struct NodeRay {
    pub(crate) origin: [f32; 3],
    pub(crate) inv_dir: [f32; 3],
    /// Some direction component is ±0 (its reciprocal is infinite) or so small that its
    /// reciprocal overflows (then NaN): such slabs get the open treatment.
    pub(crate) axis_parallel: bool,
    /// Per axis, whether the ray meets a box's upper plane first (its direction is
    /// negative there): the near plane of the slab test, so the kernels read the near and
    /// far planes directly instead of taking the min and max of both distances.
    pub(crate) near_is_max: [bool; 3],
}

/// Widening of the far slab distance that makes the box test conservative (Ize 2013,
/// "Robust BVH Ray Traversal": far × (1 + 2γ₃) against the entry distance), so
/// watertight triangle tests are never culled early. The entry distance is not narrowed
/// by (1 − 2γ₃) as Ize does: the far side and the limit take that factor instead (see
/// [`entry_limit`]), which keeps a multiply off the chain from a node's load to the next
/// node's address. 1 + 6γ₃ covers (1 + 2γ₃)/(1 − 2γ₃) and the roundings of both products.
pub(crate) const FAR_SCALE: f32 = 1.0 + 6.0 * gamma(3);

/// The widening of the closest hit so far that children's entry distances are tested
/// against: a box whose entry rounded up past a hit on its own face must still be
/// entered (a closest hit 1 ulp too far without it; fuzz finding). 1 + 4γ₃ covers the
/// 1/(1 − 2γ₃) of Ize's narrowed entry and the rounding of this product.
const LIMIT_SCALE: f32 = 1.0 + 4.0 * gamma(3);

/// The bound that children's entry distances must stay below for a closest hit (or ray
/// end) at `t_max`: a little beyond it, as the slab test's rounding needs.
#[inline(always)]
pub(crate) fn entry_limit(t_max: f32) -> f32 {
    t_max * LIMIT_SCALE
}

impl NodeRay {
    /// Keeps origin and reciprocal direction for the slab tests.
    #[inline]
    pub fn new(ray: &Ray) -> Self {
        // A non-zero component below 1/f32::MAX (a denormal) has an infinite reciprocal,
        // which would put its slab entry at ±∞ although the ray does cross the slab, at a
        // distance f32 cannot hold (fuzz finding). NaN marks that slab as open: the test
        // ignores the axis, a conservative superset that only such rays pay for.
        let d = ray.direction;
        let unreliable = d.cmpne(Vec3A::ZERO) & !d.recip().is_finite_mask();
        let inv = Vec3A::select(unreliable, Vec3A::NAN, d.recip());
        Self {
            origin: ray.origin.to_array(),
            inv_dir: inv.to_array(),
            // A NaN ray hits nothing either way; only finite rays get open slabs.
            axis_parallel: !inv.is_finite()
                && ray.origin.is_finite()
                && !ray.direction.is_nan()
                && ray.direction != Vec3A::ZERO,
            near_is_max: [inv.x < 0.0, inv.y < 0.0, inv.z < 0.0],
        }
    }
}

/// What a traversal does at each leaf it reaches: `visit(first, count, t_max) -> (new
/// t_max, stop)` tests the leaf's slots `first .. first + count`. Closures implement it;
/// a type with an `#[inline(always)]` method gets its leaf test inlined into the
/// traversal loop (a large closure stays a call, and outside the AVX2 function it is
/// compiled without AVX).
pub trait LeafVisit {
    /// True for an any-hit visit, which never shortens the ray: the traversal then
    /// visits a node's hit leaves as soon as its box test finds them and keeps only
    /// interior nodes pending, with no sort and no branch on whether the next entry is a
    /// leaf (the branch a simulated predictor misses most). A closest-hit visit gets a
    /// node's hit children nearest first. An any-hit visit's returned `t_max` is not
    /// read.
    const ANY_HIT: bool = false;

    /// Tests one leaf; returns the new `t_max` and whether to stop.
    fn visit(&mut self, first: usize, count: usize, t_max: f32) -> (f32, bool);

    /// Asks for the memory of the leaf over slots `first .. first + count` ahead of its
    /// visit, when it has been put off behind a nearer child.
    #[inline(always)]
    fn prefetch(&self, _first: usize, _count: usize) {}
}

impl<F: FnMut(usize, usize, f32) -> (f32, bool)> LeafVisit for F {
    #[inline(always)]
    fn visit(&mut self, first: usize, count: usize, t_max: f32) -> (f32, bool) {
        self(first, count, t_max)
    }
}
