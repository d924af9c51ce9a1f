//! Counters of the work a frame did, kept on in release builds: rays by kind, BVH
//! nodes and primitives tested, alpha tests and transparency. Summed per tile, then per
//! frame, and what profiles and summaries report.

/// Counters a traversal updates: cheap enough to leave on in release builds. Summed per
/// tile, then per frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TraversalStats {
    /// Closest-hit rays traced.
    pub closest_rays: u64,
    /// Any-hit (occlusion) rays traced.
    pub any_rays: u64,
    /// BVH nodes visited, both levels.
    pub nodes_visited: u64,
    /// Primitive tests: instances at the top level, triangles at the bottom. Every slot
    /// of a visited leaf counts (a leaf's triangles are tested together), also when an
    /// any-hit ray stops inside it.
    pub primitive_tests: u64,
    /// Candidate hits handed to a hit filter (alpha tests).
    pub filter_tests: u64,
    /// The part of `filter_tests` that sampled a texture: the opacity map left them
    /// undecided (or the shader has no map).
    pub texture_alpha_tests: u64,
    /// Candidate hits a filter rejected: transparency segments passed through.
    pub filter_rejections: u64,
    /// The part of `filter_rejections` met by closest-hit (camera) rays.
    pub closest_filter_rejections: u64,
    /// Alpha holes in front of the hit that closest-hit (camera) rays returned: the
    /// transparency segments they passed (at most 64 counted per ray).
    pub holes_passed: u64,
    /// Holes adaptive transparency turned opaque (camera and shadow rays).
    pub opaque_holes: u64,
    /// Shadow rays (counted in `any_rays`) that a block where a recent shadow ray
    /// stopped stopped too, without a walk.
    pub cached_occlusions: u64,
}

impl TraversalStats {
    /// Adds another set of counters into this one.
    pub fn add(&mut self, other: &TraversalStats) {
        self.closest_rays += other.closest_rays;
        self.any_rays += other.any_rays;
        self.nodes_visited += other.nodes_visited;
        self.primitive_tests += other.primitive_tests;
        self.filter_tests += other.filter_tests;
        self.texture_alpha_tests += other.texture_alpha_tests;
        self.filter_rejections += other.filter_rejections;
        self.closest_filter_rejections += other.closest_filter_rejections;
        self.holes_passed += other.holes_passed;
        self.opaque_holes += other.opaque_holes;
        self.cached_occlusions += other.cached_occlusions;
    }

    /// Mean alpha tests that found a hole per closest-hit ray: the transparency work,
    /// including holes behind the final hit that were tested before it was found.
    pub fn hole_tests_per_closest_ray(&self) -> f64 {
        self.closest_filter_rejections as f64 / self.closest_rays.max(1) as f64
    }

    /// Mean transparency segments per closest-hit ray: holes in front of the hit.
    pub fn segments_per_closest_ray(&self) -> f64 {
        self.holes_passed as f64 / self.closest_rays.max(1) as f64
    }

    /// All rays traced.
    pub fn rays(&self) -> u64 {
        self.closest_rays + self.any_rays
    }
}
