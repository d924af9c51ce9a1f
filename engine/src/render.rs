//! The render kernel: a pure function of flat scene data, camera, parameters, tile and
//! frame index. The schedule, benchmarks, tests and (later) MPI workers all call it.
//!
//! Shading: Lambertian surfaces lit by directional lights (one shadow ray each) and by
//! the environment (virtual lights, optionally interleaved) or the gradient sky
//! (cosine-weighted shadow rays). Hit filters run the alpha test in place during
//! traversal, for camera and shadow rays alike; adaptive transparency turns holes beyond
//! a camera's allowance into opaque hits.

use crate::bvh::simd::{NodeKernel, with_node_kernel};
use crate::bvh::{PACKET, TraversalStats};
use crate::camera::{Camera, CameraView};
use crate::environment::luminance;
use crate::film::{FrameBuffer, Tile, TileResult};
use crate::geometry::GeometryLibrary;
use crate::interleave::{LightSubsets, stratified_selection};
use crate::light::LightSet;
use crate::math::{ErrorPoint, Ray};
use crate::occluders::OccluderCache;
use crate::opacity::{Opacity, OpacityMaps};
use crate::sampling::{SampleKey, cosine_hemisphere, orthonormal_basis};
use crate::shading::{Shader, ShaderTable};
use crate::tlas::{Candidate, Hit, InstanceTriangle, TopLevel};
use crate::transparency::{
    COUNTED_HOLES, CandidateHoles, CountedHoles, TransparencyCurve, first_opaque_hole,
};
use crate::triangle::hit_point;
use bevy_ecs::component::Component;
use glam::{Vec2, Vec3, Vec3A};
use rayon::prelude::*;

/// Borrowed flat data the kernel reads: nothing here knows about entities.
#[derive(Clone, Copy)]
pub struct RenderScene<'a> {
    /// Meshes and their BLASes.
    pub geometry: &'a GeometryLibrary,
    /// The TLAS.
    pub top_level: &'a TopLevel,
    /// Shaders by id.
    pub shaders: &'a ShaderTable,
    /// Where alpha masks are decided without their texture ([`OpacityMaps::default`]:
    /// nowhere, every alpha test samples the texture).
    pub opacity: &'a OpacityMaps,
    /// Lights.
    pub lights: &'a LightSet,
}

/// What the planning stages decided for a camera's frames: adaptive transparency (only
/// when the scene has alpha masks) and light subsets (only when it has virtual lights).
#[derive(Component, Clone, Copy, Debug, Default, PartialEq)]
pub struct FramePlan {
    /// The transparency curve in force, if any.
    pub transparency: Option<TransparencyCurve>,
    /// The light-subset assignment in force, if any.
    pub light_subsets: Option<LightSubsets>,
}

/// Per-frame sampling settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RenderParams {
    /// Camera samples per pixel.
    pub samples_per_pixel: u32,
    /// Light samples (sky or virtual-light shadow rays) per camera hit.
    pub light_samples: u32,
    /// Seed of every random number.
    pub seed: u64,
    /// Tile edge in pixels.
    pub tile_size: u32,
    /// Adaptive transparency, off when `None`.
    pub transparency: Option<TransparencyCurve>,
    /// Interleaved light subsets, off when `None`.
    pub light_subsets: Option<LightSubsets>,
    /// Diffuse bounces of indirect light (0: direct light only).
    pub bounces: u32,
}

impl Default for RenderParams {
    fn default() -> Self {
        Self {
            samples_per_pixel: 1,
            light_samples: 2,
            seed: 0,
            tile_size: 16,
            transparency: None,
            light_subsets: None,
            bounces: 0,
        }
    }
}

impl RenderParams {
    /// The sampling settings a camera asks for.
    pub fn for_camera(camera: &Camera, seed: u64) -> Self {
        Self {
            samples_per_pixel: camera.samples_per_pixel.max(1),
            light_samples: camera.light_samples,
            bounces: camera.bounces,
            seed,
            ..Default::default()
        }
    }

    /// These settings with a plan's transparency curve and light subsets.
    pub fn with_plan(self, plan: &FramePlan) -> Self {
        Self {
            transparency: plan.transparency,
            light_subsets: plan.light_subsets,
            ..self
        }
    }
}

/// How one camera sample is shaded.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SampleShading {
    /// Light samples (sky shadow rays) per hit.
    pub light_samples: u32,
    /// Diffuse bounces of indirect light after the first hit (0: direct light only).
    pub bounces: u32,
    /// Adaptive transparency, off when `None`.
    pub transparency: Option<TransparencyCurve>,
    /// The subset assignment and the subset this sample draws its lights from; all
    /// lights when `None`.
    pub light_subset: Option<(LightSubsets, u32)>,
}

impl SampleShading {
    /// Exact shading with `light_samples` independent light samples per hit.
    pub fn plain(light_samples: u32) -> Self {
        Self {
            light_samples,
            ..Default::default()
        }
    }
}

/// One camera sample's shading: its radiance, the albedo that radiance is linear in,
/// and the surface it saw.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ShadedSample {
    /// Radiance along the camera ray.
    pub radiance: Vec3A,
    /// Reflectance the light was multiplied by (1 for the environment seen directly).
    pub albedo: Vec3A,
    /// The part of `radiance` the surface emits itself (not modulated by `albedo`).
    pub emission: Vec3A,
    /// The surface hit, or [`SurfaceGuide::NONE`].
    pub surface: SurfaceGuide,
}

/// What the discontinuity filter compares to decide whether two pixels see the same
/// surface.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceGuide {
    /// Distance from the camera (infinite: no surface).
    pub depth: f32,
    /// The hit point (world space, as rendered).
    pub position: Vec3,
    /// Geometric normal facing the camera.
    pub normal: Vec3,
    /// Shader id.
    pub shader: u32,
}

impl SurfaceGuide {
    /// No surface: the ray left the scene.
    pub const NONE: SurfaceGuide = SurfaceGuide {
        depth: f32::INFINITY,
        position: Vec3::ZERO,
        normal: Vec3::ZERO,
        shader: u32::MAX,
    };

    /// True when a surface was hit.
    pub fn is_surface(&self) -> bool {
        self.depth.is_finite()
    }
}

/// What the hit filter made of a candidate.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum FilterOutcome {
    /// A surface the ray stops at.
    Opaque,
    /// An alpha hole: a transparency segment.
    Hole,
    /// The back of a single-sided surface.
    Culled,
}

/// A surface point reconstructed from a hit, in world space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfacePoint {
    /// Position with its error bound.
    pub point: ErrorPoint,
    /// Unit geometric normal, facing the incoming ray.
    pub geometric_normal: Vec3A,
    /// Unit shading normal, in the same hemisphere as the geometric one.
    pub shading_normal: Vec3A,
    /// Texture coordinates.
    pub uv: Vec2,
    /// The triangle's shader id.
    pub shader: u32,
    /// The instance triangle the point lies on: rays leaving it skip its test.
    pub triangle: InstanceTriangle,
}

/// The side of a surface light arrives from: the viewer's, or (through a translucent
/// surface) the other.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Side {
    Front,
    Back,
}

/// What a surface point does with diffuse light: reflect it, transmit it.
#[derive(Clone, Copy, Debug)]
struct Material {
    reflectance: Vec3A,
    transmittance: Vec3A,
}

impl Material {
    fn is_translucent(&self) -> bool {
        self.transmittance != Vec3A::ZERO
    }

    /// What light arriving on `side` is multiplied by.
    #[inline]
    fn on(&self, side: Side) -> Vec3A {
        match side {
            Side::Front => self.reflectance,
            Side::Back => self.transmittance,
        }
    }

    /// The probability of sampling the front: in proportion to what each side passes on
    /// (1 for an opaque surface).
    #[inline]
    fn front_share(&self) -> f32 {
        if !self.is_translucent() {
            return 1.0;
        }
        let (r, t) = (
            luminance(self.reflectance.into()),
            luminance(self.transmittance.into()),
        );
        if r + t > 0.0 { r / (r + t) } else { 0.5 }
    }
}

/// A cosine-distributed direction on the side `u0` picks (the front with probability
/// `front_share`; `u0`, rescaled, still places the direction), with the side, its
/// probability and the outward normal of that side; `None` below the geometric surface.
#[inline]
fn sided_direction(
    surface: &SurfacePoint,
    (t, b): (Vec3A, Vec3A),
    front_share: f32,
    u0: f32,
    u1: f32,
) -> Option<(Vec3A, Side, f32, Vec3A)> {
    let (side, u0, share) = if u0 < front_share {
        (Side::Front, u0 / front_share, front_share)
    } else {
        let back_share = 1.0 - front_share;
        (
            Side::Back,
            ((u0 - front_share) / back_share).min(1.0),
            back_share,
        )
    };
    let local = cosine_hemisphere(Vec2::new(u0, u1));
    let (outward, normal) = match side {
        Side::Front => (surface.geometric_normal, surface.shading_normal),
        Side::Back => (-surface.geometric_normal, -surface.shading_normal),
    };
    let d = t * local.x + b * local.y + normal * local.z;
    (outward.dot(d) > 0.0).then_some((d, side, share, outward))
}

/// First random dimension used by sky sampling (0–1 pixel jitter, 2–3 lens).
const SKY_DIMENSION: u32 = 4;

impl<'a> RenderScene<'a> {
    #[inline]
    fn shader_of(&self, candidate: &Candidate) -> &'a Shader {
        let mesh = &self.geometry.geometries[candidate.geometry.0 as usize].mesh;
        self.shaders.get(mesh.shaders[candidate.triangle as usize])
    }

    #[inline]
    fn uv_of(&self, candidate: &Candidate) -> Vec2 {
        let mesh = &self.geometry.geometries[candidate.geometry.0 as usize].mesh;
        mesh.uv_at(candidate.triangle as usize, candidate.barycentrics)
    }

    /// The hit filter run inside traversal: a hole where the shader's alpha mask has
    /// one, culled where a single-sided surface is seen from behind.
    #[inline]
    fn filter(
        &self,
        candidate: &Candidate,
        direction: Vec3A,
        stats: &mut TraversalStats,
    ) -> FilterOutcome {
        let (geometry, triangle, b) = (
            candidate.geometry,
            candidate.triangle,
            candidate.barycentrics,
        );
        // Most leaf hits are decided by the opacity map alone, without the shader's
        // cache miss.
        let decided = match self.opacity.at(geometry, triangle, b) {
            Opacity::Opaque => Some(FilterOutcome::Opaque),
            Opacity::Hole => Some(FilterOutcome::Hole),
            Opacity::Mixed => None,
        };
        if let Some(outcome) = decided {
            stats.filter_tests += 1;
            stats.filter_rejections += u64::from(outcome != FilterOutcome::Opaque);
            return outcome;
        }
        let shader = self.shader_of(candidate);
        if !shader.needs_hit_filter() {
            return FilterOutcome::Opaque;
        }
        stats.filter_tests += 1;
        let outcome = if !(shader.double_sided || self.is_front_side(candidate, direction)) {
            FilterOutcome::Culled
        } else {
            // A double-sided triangle's map has answered above (mixed, or no map).
            let known = if shader.double_sided {
                Opacity::Mixed
            } else {
                self.opacity.alpha_at(geometry, triangle, b)
            };
            match known {
                Opacity::Opaque => FilterOutcome::Opaque,
                Opacity::Hole => FilterOutcome::Hole,
                Opacity::Mixed => {
                    stats.texture_alpha_tests += 1;
                    if shader.is_opaque_at(self.uv_of(candidate)) {
                        FilterOutcome::Opaque
                    } else {
                        FilterOutcome::Hole
                    }
                }
            }
        };
        stats.filter_rejections += u64::from(outcome != FilterOutcome::Opaque);
        outcome
    }

    /// True when `direction` arrives at the candidate triangle's front: the side its
    /// object-space winding normal points to. Testing in object space makes a mirroring
    /// instance flip the winding, as glTF requires of negative determinants.
    #[inline]
    fn is_front_side(&self, candidate: &Candidate, direction: Vec3A) -> bool {
        let record = self.top_level.record(candidate.slot as usize);
        let mesh = &self.geometry.geometries[candidate.geometry.0 as usize].mesh;
        let [p0, p1, p2] = mesh.triangle(candidate.triangle as usize);
        let normal = (p1 - p0).cross(p2 - p0);
        normal.dot(record.world_to_object().transform_vector3a(direction)) < 0.0
    }

    /// The closest hit along `ray` that the hit filter accepts.
    #[inline]
    pub fn closest(&self, ray: &Ray, stats: &mut TraversalStats) -> Option<Hit> {
        self.closest_adaptive(ray, None, stats).map(|(hit, _)| hit)
    }

    /// The closest hit along `ray` (unit direction, so `t` is the camera distance) under
    /// adaptive transparency: the first hole, nearest first, whose index `i` reaches the
    /// curve's allowance at its distance is an opaque hit (flagged `true`). With
    /// `curve = None` it is [`closest`](Self::closest).
    pub fn closest_adaptive(
        &self,
        ray: &Ray,
        curve: Option<&TransparencyCurve>,
        stats: &mut TraversalStats,
    ) -> Option<(Hit, bool)> {
        with_node_kernel!(kernel => self.closest_adaptive_with(kernel, ray, None, curve, stats))
    }

    /// The closest hit of a ray leaving the surface triangle `leaving` (which it cannot
    /// hit again, so it is not tested), passing alpha holes exactly.
    #[inline]
    fn closest_leaving(
        &self,
        ray: &Ray,
        leaving: InstanceTriangle,
        stats: &mut TraversalStats,
    ) -> Option<Hit> {
        with_node_kernel!(
            kernel => self.closest_adaptive_with(kernel, ray, Some(leaving), None, stats)
        )
        .map(|(hit, _)| hit)
    }

    #[inline(always)]
    fn closest_adaptive_with(
        &self,
        kernel: impl NodeKernel,
        ray: &Ray,
        leaving: Option<InstanceTriangle>,
        curve: Option<&TransparencyCurve>,
        stats: &mut TraversalStats,
    ) -> Option<(Hit, bool)> {
        if !self.shaders.needs_hit_filter() {
            return self
                .top_level
                .intersect_closest_with(kernel, self.geometry, ray, leaving, stats, |_| true)
                .map(|hit| (hit, false));
        }
        let mut filter = TraversalStats::default();
        let result = match curve {
            None => {
                let mut holes = CountedHoles::new(COUNTED_HOLES);
                let hit = self.top_level.intersect_closest_with(
                    kernel,
                    self.geometry,
                    ray,
                    leaving,
                    stats,
                    |c| match self.filter(c, ray.direction, &mut filter) {
                        FilterOutcome::Opaque => true,
                        FilterOutcome::Hole => {
                            holes.insert(c.t, ());
                            false
                        }
                        FilterOutcome::Culled => false,
                    },
                );
                let t_hit = hit.map_or(f32::INFINITY, |h| h.t);
                filter.holes_passed = holes.count_before(t_hit) as u64;
                hit.map(|hit| (hit, false))
            }
            Some(curve) => {
                let mut holes = CandidateHoles::new(curve.max_allowance() as usize + 1);
                let mut last_accepted_hole = false;
                let hit = self.top_level.intersect_closest_with(
                    kernel,
                    self.geometry,
                    ray,
                    leaving,
                    stats,
                    |c| {
                        let outcome = self.filter(c, ray.direction, &mut filter);
                        let accept = match outcome {
                            FilterOutcome::Opaque => true,
                            FilterOutcome::Culled => false,
                            FilterOutcome::Hole => {
                                // Enough nearer holes seen already: this one is beyond the
                                // allowance whatever else turns up, so it may end the
                                // search early; the walk below picks the first such hole.
                                let beyond =
                                    holes.count_before(c.t) >= curve.allowance(c.t) as usize;
                                holes.insert(c.t, *c);
                                beyond
                            }
                        };
                        // Each accepted candidate becomes the closest so far.
                        if accept {
                            last_accepted_hole = outcome == FilterOutcome::Hole;
                        }
                        accept
                    },
                );
                adaptive_result(curve, &mut holes, hit, last_accepted_hole, &mut filter)
            }
        };
        filter.closest_filter_rejections = filter.filter_rejections;
        stats.add(&filter);
        result
    }

    /// True when a hit the filter accepts lies before `ray.t_max`.
    #[inline]
    pub fn occluded(&self, ray: &Ray, stats: &mut TraversalStats) -> bool {
        self.occluded_within(ray, None, stats)
    }

    /// [`occluded`](Self::occluded) where a ray may pass at most `allowance` holes: one
    /// more counts as opaque (adaptive transparency for shadow rays).
    #[inline]
    pub fn occluded_within(
        &self,
        ray: &Ray,
        allowance: Option<u32>,
        stats: &mut TraversalStats,
    ) -> bool {
        self.occluded_leaving(ray, None, allowance, None, stats)
    }

    /// [`occluded_within`](Self::occluded_within) for a ray that starts on the triangle
    /// `leaving`, which it cannot hit again: its test is left out. With `occluders`, the
    /// blocks that stopped recent shadow rays are tried first, and a walk that stops on
    /// an opaque hit adds its block to them (the answer is the same either way).
    #[inline]
    pub fn occluded_leaving(
        &self,
        ray: &Ray,
        leaving: Option<InstanceTriangle>,
        allowance: Option<u32>,
        occluders: Option<&mut OccluderCache>,
        stats: &mut TraversalStats,
    ) -> bool {
        with_node_kernel!(
            kernel => self.occluded_leaving_with(kernel, ray, leaving, allowance, occluders, stats)
        )
    }

    #[inline(always)]
    fn occluded_leaving_with(
        &self,
        kernel: impl NodeKernel,
        ray: &Ray,
        leaving: Option<InstanceTriangle>,
        allowance: Option<u32>,
        mut occluders: Option<&mut OccluderCache>,
        stats: &mut TraversalStats,
    ) -> bool {
        let filtered = self.shaders.needs_hit_filter();
        let mut filter = TraversalStats::default();
        if let Some(cache) = occluders.as_deref_mut()
            && cache.stops(kernel, ray, leaving, |c| {
                !filtered || self.filter(c, ray.direction, &mut filter) == FilterOutcome::Opaque
            })
        {
            stats.any_rays += 1;
            stats.cached_occlusions += 1;
            stats.add(&filter);
            return true;
        }
        let mut holes = CountedHoles::new(allowance.map_or(0, |a| a as usize + 1));
        let mut stopped_on_opaque = false;
        let occluder =
            self.top_level
                .occluder_with(kernel, self.geometry, ray, leaving, stats, |c| {
                    if !filtered {
                        stopped_on_opaque = true;
                        return true;
                    }
                    match self.filter(c, ray.direction, &mut filter) {
                        FilterOutcome::Opaque => {
                            stopped_on_opaque = true;
                            true
                        }
                        FilterOutcome::Culled => false,
                        FilterOutcome::Hole => {
                            let Some(allowance) = allowance else {
                                return false;
                            };
                            holes.insert(c.t, ());
                            let beyond = holes.len() > allowance as usize;
                            filter.opaque_holes += u64::from(beyond);
                            beyond
                        }
                    }
                });
        stats.add(&filter);
        // A hole that only the allowance made opaque would stop few other rays.
        if let (Some(cache), Some(occluder), true) = (occluders, occluder, stopped_on_opaque) {
            cache.remember(self.top_level, self.geometry, occluder);
        }
        occluder.is_some()
    }

    /// Rebuilds position (with error bound), normals and UV of a hit in world space.
    pub fn surface(&self, hit: &Hit, incoming: Vec3A) -> SurfacePoint {
        let record = self.top_level.record(hit.slot as usize);
        let mesh = &self.geometry.geometries[record.geometry.0 as usize].mesh;
        let triangle = hit.triangle as usize;
        let [p0, p1, p2] = mesh.triangle(triangle);
        let b = hit.barycentrics;
        let point = hit_point(p0, p1, p2, b).transformed(&record.object_to_world());
        // Normals transform by the inverse transpose; a negative determinant flips them
        // consistently with the mirrored winding.
        let normal_matrix = record.world_to_object().matrix3.transpose();
        let mut geometric_normal = (normal_matrix * (p1 - p0).cross(p2 - p0))
            .normalize_or(-incoming.normalize_or(Vec3A::Y));
        if geometric_normal.dot(incoming) > 0.0 {
            geometric_normal = -geometric_normal;
        }
        let [i0, i1, i2] = mesh.indices[triangle].map(|i| i as usize);
        let mut shading_normal = if mesh.normals.is_empty() {
            geometric_normal
        } else {
            let n = Vec3A::from(mesh.normals[i0]) * b.x
                + Vec3A::from(mesh.normals[i1]) * b.y
                + Vec3A::from(mesh.normals[i2]) * b.z;
            (normal_matrix * n).normalize_or(geometric_normal)
        };
        if shading_normal.dot(geometric_normal) < 0.0 {
            shading_normal = -shading_normal;
        }
        SurfacePoint {
            point,
            geometric_normal,
            shading_normal,
            uv: self.uv_of(hit),
            shader: mesh.shaders[triangle],
            triangle: InstanceTriangle {
                slot: hit.slot,
                triangle: hit.triangle,
            },
        }
    }

    /// The shading cosine toward a directional light at `direction` and the side it
    /// lights, when its shadow ray (which may pass `allowance` holes) is unoccluded: the
    /// front (the light above both normals), or, for a `translucent` surface, the back
    /// (below both; the shadow ray then starts on the far side).
    #[inline]
    fn lit_cosine(
        &self,
        surface: &SurfacePoint,
        direction: Vec3,
        translucent: bool,
        allowance: Option<u32>,
        occluders: &mut OccluderCache,
        stats: &mut TraversalStats,
    ) -> Option<(f32, Side)> {
        let (ng, l) = (surface.geometric_normal, Vec3A::from(direction));
        let cos = surface.shading_normal.dot(l);
        let (cos, side, outward) = if cos > 0.0 && ng.dot(l) > 0.0 {
            (cos, Side::Front, ng)
        } else if translucent && cos < 0.0 && ng.dot(l) < 0.0 {
            (-cos, Side::Back, -ng)
        } else {
            return None;
        };
        let shadow = Ray::new(surface.point.offset_origin(outward, l), l);
        let leaving = Some(surface.triangle);
        (!self.occluded_leaving(&shadow, leaving, allowance, Some(occluders), stats))
            .then_some((cos, side))
    }

    /// Light arriving directly at `surface` from the sun, the sky or the environment's
    /// virtual lights (`shading.light_samples` of them, drawing random numbers from
    /// `dimension` on), reflected or transmitted toward the viewer.
    #[expect(
        clippy::too_many_arguments,
        reason = "the per-vertex inputs of one shading step; a struct would only rename them"
    )]
    #[inline]
    fn direct_light(
        &self,
        surface: &SurfacePoint,
        material: &Material,
        key: &SampleKey,
        dimension: u32,
        shading: &SampleShading,
        allowance: Option<u32>,
        occluders: &mut OccluderCache,
        stats: &mut TraversalStats,
    ) -> Vec3A {
        let translucent = material.is_translucent();
        let side_factor = |side: Side| material.on(side);
        let ns = surface.shading_normal;
        let mut radiance = Vec3A::ZERO;
        for light in &self.lights.directional {
            if let Some((cos, side)) = self.lit_cosine(
                surface,
                light.direction,
                translucent,
                allowance,
                occluders,
                stats,
            ) {
                radiance += side_factor(side)
                    * Vec3A::from(light.irradiance)
                    * (cos * std::f32::consts::FRAC_1_PI);
            }
        }
        let samples = shading.light_samples;
        if let Some(environment) = &self.lights.environment {
            // Unbiased for the discrete set: E[f(L)/p(L)] = Σ_i albedo/π · E_i · cos_i · V_i.
            // With subsets the selection is stratified, each stratum equally likely over
            // the render's random offset, so the expectation is the same.
            // The lights of up to PICKS_AHEAD samples are picked before any of their
            // shadow rays is traced: each pick is a chain of dependent loads (guide table,
            // CDF, light), and picked between two traversals each chain's latency showed.
            const PICKS_AHEAD: u32 = 8;
            for start in (0..samples).step_by(PICKS_AHEAD as usize) {
                let end = (start + PICKS_AHEAD).min(samples);
                let mut picks = [None; PICKS_AHEAD as usize];
                for (k, pick) in (start..end).zip(&mut picks) {
                    let u = key.get(dimension + k);
                    let u = match shading.light_subset {
                        Some((subsets, subset)) => subsets.selection(subset, k, samples, u),
                        None => stratified_selection(k, samples, u),
                    };
                    *pick = environment.lights.sample(u);
                }
                for light in picks.iter().flatten() {
                    if let Some((cos, side)) = self.lit_cosine(
                        surface,
                        light.direction,
                        translucent,
                        allowance,
                        occluders,
                        stats,
                    ) {
                        let weight = cos * std::f32::consts::FRAC_1_PI
                            / (light.probability * samples as f32);
                        radiance += side_factor(side) * Vec3A::from(light.irradiance) * weight;
                    }
                }
            }
        } else if let Some(sky) = &self.lights.sky {
            let (t, b) = orthonormal_basis(ns);
            // A translucent surface picks the side of each sample in proportion to what
            // that side passes on; the first random number, rescaled, still places the
            // direction (an opaque one keeps it as it is: the front every time).
            let front_share = material.front_share();
            for k in 0..samples {
                let [u0, u1] = key.get2(dimension + 2 * k).to_array();
                let Some((d, side, share, outward)) =
                    sided_direction(surface, (t, b), front_share, u0, u1)
                else {
                    continue;
                };
                let shadow = Ray::new(surface.point.offset_origin(outward, d), d);
                let leaving = Some(surface.triangle);
                if !self.occluded_leaving(&shadow, leaving, allowance, Some(occluders), stats) {
                    // Cosine sampling cancels the cos/π of the Lambertian BRDF; the side's
                    // share is its probability.
                    radiance += side_factor(side) * sky.radiance(d) / (share * samples as f32);
                }
            }
        }
        radiance
    }

    /// Light arriving at `surface` after up to `shading.bounces` diffuse bounces: a
    /// cosine-distributed continuation ray (to the front or, through a translucent
    /// surface, the back), direct light at every surface it reaches, Russian roulette
    /// from the second bounce on. Rays that escape add nothing: direct light already
    /// counts the sky. Bounce rays pass alpha holes exactly.
    fn indirect_light(
        &self,
        first: &SurfacePoint,
        material: &Material,
        key: &SampleKey,
        shading: &SampleShading,
        occluders: &mut OccluderCache,
        stats: &mut TraversalStats,
    ) -> Vec3A {
        let stride = 2 * shading.light_samples + 3;
        let mut radiance = Vec3A::ZERO;
        let mut throughput = Vec3A::ONE;
        let (mut surface, mut material) = (*first, *material);
        for bounce in 1..=shading.bounces {
            // The random numbers of vertex `bounce - 1`'s continuation, after its light
            // samples.
            let dimension = SKY_DIMENSION + (bounce - 1) * stride + 2 * shading.light_samples;
            if bounce > 1 {
                let survive = throughput.max_element().min(1.0);
                if survive <= 0.0 || key.get(dimension + 2) >= survive {
                    break;
                }
                throughput /= survive;
            }
            let [u0, u1] = key.get2(dimension).to_array();
            let basis = orthonormal_basis(surface.shading_normal);
            let Some((d, side, share, outward)) =
                sided_direction(&surface, basis, material.front_share(), u0, u1)
            else {
                break;
            };
            // Cosine sampling cancels the cos/π of the Lambertian BSDF.
            throughput *= material.on(side) / share;
            let ray = Ray::new(surface.point.offset_origin(outward, d), d);
            let Some(hit) = self.closest_leaving(&ray, surface.triangle, stats) else {
                break;
            };
            surface = self.surface(&hit, ray.direction);
            let shader = self.shaders.get(surface.shader);
            material = Material {
                reflectance: shader.reflectance(surface.uv).into(),
                transmittance: shader.transmittance(surface.uv).into(),
            };
            let light = Vec3A::from(shader.emission(surface.uv))
                + self.direct_light(
                    &surface,
                    &material,
                    key,
                    SKY_DIMENSION + bounce * stride,
                    shading,
                    None,
                    occluders,
                    stats,
                );
            radiance += throughput * light;
        }
        radiance
    }

    /// Radiance arriving along `ray`: direct sun and sky (or environment: light samples
    /// from the virtual lights, picked by luminance within the sample's subset) on
    /// Lambertian surfaces. A hole made opaque by adaptive transparency is shaded with its
    /// shader's mean opaque colour × the curve's weight.
    pub fn radiance(
        &self,
        ray: &Ray,
        key: &SampleKey,
        shading: &SampleShading,
        stats: &mut TraversalStats,
    ) -> Vec3A {
        self.shade(ray, key, shading, stats).radiance
    }

    /// [`radiance`](Self::radiance) with the albedo it was modulated by and the surface
    /// it came from (for the discontinuity filter); the environment seen directly has
    /// albedo 1 and no surface.
    pub fn shade(
        &self,
        ray: &Ray,
        key: &SampleKey,
        shading: &SampleShading,
        stats: &mut TraversalStats,
    ) -> ShadedSample {
        self.shade_with(ray, key, shading, &mut OccluderCache::new(), stats)
    }

    /// [`shade`](Self::shade) whose shadow rays try the blocks in `occluders` first
    /// and add the blocks that stop them: one cache for a tile's samples (the same
    /// result as without it).
    pub fn shade_with(
        &self,
        ray: &Ray,
        key: &SampleKey,
        shading: &SampleShading,
        occluders: &mut OccluderCache,
        stats: &mut TraversalStats,
    ) -> ShadedSample {
        let primary = self.closest_adaptive(ray, shading.transparency.as_ref(), stats);
        self.shade_primary(ray, primary, key, shading, occluders, stats)
    }

    /// The closest hits of a packet of up to [`PACKET`] camera rays, as
    /// [`closest_adaptive`](Self::closest_adaptive) finds them one by one, from one
    /// top-level walk; `None` when one packet cannot bound the rays (see
    /// [`Bvh::traverse_closest_packet`](crate::bvh::Bvh::traverse_closest_packet)):
    /// then they go one by one.
    pub fn closest_packet(
        &self,
        rays: &[Ray],
        curve: Option<&TransparencyCurve>,
        scratch: &mut PacketScratch,
        stats: &mut TraversalStats,
    ) -> Option<[Option<(Hit, bool)>; PACKET]> {
        with_node_kernel!(
            kernel => self.closest_packet_with(kernel, rays, curve, scratch, stats)
        )
    }

    #[inline(always)]
    fn closest_packet_with(
        &self,
        kernel: impl NodeKernel,
        rays: &[Ray],
        curve: Option<&TransparencyCurve>,
        scratch: &mut PacketScratch,
        stats: &mut TraversalStats,
    ) -> Option<[Option<(Hit, bool)>; PACKET]> {
        let opaque = |hits: [Option<Hit>; PACKET]| hits.map(|hit| hit.map(|hit| (hit, false)));
        if !self.shaders.needs_hit_filter() {
            return self
                .top_level
                .intersect_closest_packet_with(kernel, self.geometry, rays, stats, |_, _| true)
                .map(opaque);
        }
        if let Some(curve) = curve {
            return self.closest_packet_adaptive(kernel, rays, curve, scratch, stats);
        }
        let mut filter = TraversalStats::default();
        let holes = &mut scratch.counted;
        holes.resize_with(PACKET, || CountedHoles::new(COUNTED_HOLES));
        holes.iter_mut().for_each(|h| h.reset(COUNTED_HOLES));
        let hits = self.top_level.intersect_closest_packet_with(
            kernel,
            self.geometry,
            rays,
            stats,
            |ray, c| match self.filter(c, rays[ray].direction, &mut filter) {
                FilterOutcome::Opaque => true,
                FilterOutcome::Hole => {
                    holes[ray].insert(c.t, ());
                    false
                }
                FilterOutcome::Culled => false,
            },
        )?;
        filter.holes_passed = hits
            .iter()
            .zip(holes.iter())
            .map(|(hit, holes)| holes.count_before(hit.map_or(f32::INFINITY, |h| h.t)) as u64)
            .sum();
        filter.closest_filter_rejections = filter.filter_rejections;
        stats.add(&filter);
        Some(opaque(hits))
    }

    /// [`closest_packet`](Self::closest_packet) with adaptive transparency: each ray's
    /// holes judged as [`closest_adaptive`](Self::closest_adaptive) judges them.
    #[inline(always)]
    fn closest_packet_adaptive(
        &self,
        kernel: impl NodeKernel,
        rays: &[Ray],
        curve: &TransparencyCurve,
        scratch: &mut PacketScratch,
        stats: &mut TraversalStats,
    ) -> Option<[Option<(Hit, bool)>; PACKET]> {
        let mut filter = TraversalStats::default();
        let capacity = curve.max_allowance() as usize + 1;
        let holes = &mut scratch.candidates;
        holes.resize_with(PACKET, || CandidateHoles::new(capacity));
        holes.iter_mut().for_each(|h| h.reset(capacity));
        let mut last_accepted_hole = [false; PACKET];
        let hits = self.top_level.intersect_closest_packet_with(
            kernel,
            self.geometry,
            rays,
            stats,
            |ray, c| {
                let outcome = self.filter(c, rays[ray].direction, &mut filter);
                let accept = match outcome {
                    FilterOutcome::Opaque => true,
                    FilterOutcome::Culled => false,
                    FilterOutcome::Hole => {
                        let beyond = holes[ray].count_before(c.t) >= curve.allowance(c.t) as usize;
                        holes[ray].insert(c.t, *c);
                        beyond
                    }
                };
                if accept {
                    last_accepted_hole[ray] = outcome == FilterOutcome::Hole;
                }
                accept
            },
        )?;
        let mut results = [None; PACKET];
        for (ray, result) in results.iter_mut().enumerate().take(rays.len()) {
            let (hit, last) = (hits[ray], last_accepted_hole[ray]);
            *result = adaptive_result(curve, &mut holes[ray], hit, last, &mut filter);
        }
        filter.closest_filter_rejections = filter.filter_rejections;
        stats.add(&filter);
        Some(results)
    }

    /// [`shade_with`](Self::shade_with) for a camera ray whose closest hit `primary`
    /// has been found.
    pub fn shade_primary(
        &self,
        ray: &Ray,
        primary: Option<(Hit, bool)>,
        key: &SampleKey,
        shading: &SampleShading,
        occluders: &mut OccluderCache,
        stats: &mut TraversalStats,
    ) -> ShadedSample {
        let curve = shading.transparency.as_ref();
        let Some((hit, opaque_hole)) = primary else {
            return ShadedSample {
                radiance: self.lights.environment(ray.direction),
                albedo: Vec3A::ONE,
                emission: Vec3A::ZERO,
                surface: SurfaceGuide::NONE,
            };
        };
        let surface = self.surface(&hit, ray.direction);
        let shader = self.shaders.get(surface.shader);
        let (albedo, transmittance, emission) = match (opaque_hole, curve) {
            // A hole made opaque stands for the leaf around it, dimmed the same way.
            (true, Some(curve)) => (
                shader.mean_opaque_color() * (shader.reflected_share(surface.uv) * curve.weight),
                shader.transmittance(surface.uv) * curve.weight,
                shader.emission(surface.uv) * curve.weight,
            ),
            _ => (
                shader.reflectance(surface.uv),
                shader.transmittance(surface.uv),
                shader.emission(surface.uv),
            ),
        };
        let (albedo, transmittance, emission) = (
            Vec3A::from(albedo),
            Vec3A::from(transmittance),
            Vec3A::from(emission),
        );
        let material = Material {
            reflectance: albedo,
            transmittance,
        };
        // Shadow rays get the allowance at their shading point's distance from the camera.
        let allowance = curve.map(|c| c.allowance(hit.t));
        let mut radiance = emission
            + self.direct_light(
                &surface,
                &material,
                key,
                SKY_DIMENSION,
                shading,
                allowance,
                occluders,
                stats,
            );
        if shading.bounces > 0 {
            radiance += self.indirect_light(&surface, &material, key, shading, occluders, stats);
        }
        let ng = surface.geometric_normal;
        ShadedSample {
            radiance,
            albedo,
            emission,
            surface: SurfaceGuide {
                depth: hit.t * ray.direction.length(),
                position: surface.point.point.into(),
                normal: ng.into(),
                shader: surface.shader,
            },
        }
    }
}

/// A closest-hit query's answer under adaptive transparency, from the hit the walk
/// accepted (`last_accepted_hole`: it was a hole taken as opaque) and the holes it kept:
/// the nearest hole the curve turns opaque, if one lies before that hit. Adds the holes
/// passed and the holes made opaque to `filter`.
fn adaptive_result(
    curve: &TransparencyCurve,
    holes: &mut CandidateHoles,
    hit: Option<Hit>,
    last_accepted_hole: bool,
    filter: &mut TraversalStats,
) -> Option<(Hit, bool)> {
    let nearer = holes.sorted_before(hit.map_or(f32::INFINITY, |h| h.t));
    if let Some(&(_, hole)) = first_opaque_hole(curve, nearer) {
        filter.holes_passed += nearer.iter().take_while(|h| h.0 < hole.t).count() as u64;
        filter.opaque_holes += 1;
        Some((hole, true))
    } else {
        filter.holes_passed += nearer.len() as u64;
        filter.opaque_holes += u64::from(hit.is_some() && last_accepted_hole);
        hit.map(|hit| (hit, last_accepted_hole))
    }
}

/// The per-ray hole lists a packet of camera rays fills, kept from packet to packet (an
/// array of them built for every packet cost more in copies than the walk it shared).
#[derive(Debug, Default)]
pub struct PacketScratch {
    counted: Vec<CountedHoles>,
    candidates: Vec<CandidateHoles>,
}

/// Renders one tile of frame `frame`. Deterministic: depends only on its arguments.
pub fn render_tile(
    scene: &RenderScene,
    view: &CameraView,
    params: &RenderParams,
    tile: Tile,
    frame: u32,
) -> TileResult {
    let _span = tracing::trace_span!("render_tile", x = tile.x, y = tile.y).entered();
    let mut result = TileResult {
        tile,
        sums: Vec::new(),
        counts: Vec::new(),
        albedo_sums: Vec::new(),
        emission_sums: Vec::new(),
        surfaces: Vec::new(),
        rejected: 0,
        stats: TraversalStats::default(),
    };
    let spp = params.samples_per_pixel;
    let mut shading = SampleShading {
        transparency: params.transparency,
        bounces: params.bounces,
        ..SampleShading::plain(params.light_samples)
    };
    // One per tile, starting empty: its counters then do not depend on which thread
    // rendered which tile before.
    let mut occluders = OccluderCache::new();
    let pixels = tile.pixel_count();
    let mut sums = vec![Vec3::ZERO; pixels];
    let mut counts = vec![0u32; pixels];
    let mut albedo_sums = vec![Vec3::ZERO; pixels];
    let mut emission_sums = vec![Vec3::ZERO; pixels];
    let mut surfaces = vec![SurfaceGuide::NONE; pixels];
    let curve = shading.transparency.as_ref();
    // The camera rays of up to PACKET consecutive samples of a row share one top-level
    // walk; the samples are still shaded in the order of a walk of their own (pixel by
    // pixel along the row), which keeps each one's shadow rays near the last ones' in
    // memory (ordering them in square blocks instead cost more than the packets saved).
    let mut rays = Vec::with_capacity(PACKET);
    let mut samples = Vec::with_capacity(PACKET);
    let mut scratch = PacketScratch::default();
    let mut row = Vec::with_capacity(tile.width as usize * spp as usize);
    for y in tile.y..tile.y + tile.height {
        row.clear();
        row.extend(
            (tile.x..tile.x + tile.width).flat_map(|x| (0..spp).map(move |sample| (x, y, sample))),
        );
        for chunk in row.chunks(PACKET) {
            samples.clear();
            rays.clear();
            for &(x, y, sample) in chunk {
                let key = SampleKey::new(params.seed, x, y, frame, sample);
                let film = Vec2::new(x as f32, y as f32) + key.get2(0);
                rays.push(view.ray(film, key.get2(2)));
                samples.push(key);
            }
            let primaries = scene.closest_packet(&rays, curve, &mut scratch, &mut result.stats);
            for (i, &(x, y, sample)) in chunk.iter().enumerate() {
                shading.light_subset = params
                    .light_subsets
                    .map(|subsets| (subsets, subsets.subset(x, y, frame, sample, spp)));
                let (ray, key) = (&rays[i], &samples[i]);
                let shaded = match &primaries {
                    Some(primaries) => scene.shade_primary(
                        ray,
                        primaries[i],
                        key,
                        &shading,
                        &mut occluders,
                        &mut result.stats,
                    ),
                    None => scene.shade_with(ray, key, &shading, &mut occluders, &mut result.stats),
                };
                let pixel = ((y - tile.y) * tile.width + (x - tile.x)) as usize;
                let radiance = Vec3::from(shaded.radiance);
                // The NaN firewall: a bad sample is counted and dropped, never averaged.
                if radiance.is_finite() {
                    if counts[pixel] == 0 {
                        surfaces[pixel] = shaded.surface;
                    }
                    sums[pixel] += radiance;
                    albedo_sums[pixel] += Vec3::from(shaded.albedo);
                    emission_sums[pixel] += Vec3::from(shaded.emission);
                    counts[pixel] += 1;
                } else {
                    result.rejected += 1;
                }
            }
        }
    }
    result.sums = sums;
    result.counts = counts;
    result.albedo_sums = albedo_sums;
    result.emission_sums = emission_sums;
    result.surfaces = surfaces;
    result
}

/// Renders a whole frame, tiles in parallel on the current rayon pool; `on_tile` is
/// called once per finished tile (progress reporting).
pub fn render_frame(
    scene: &RenderScene,
    view: &CameraView,
    params: &RenderParams,
    frame: u32,
    on_tile: &(dyn Fn(&Tile) + Sync),
) -> FrameBuffer {
    render_frame_unless(scene, view, params, frame, &|tile, _| on_tile(tile), None)
        .expect("a frame without a cancel flag completes")
}

/// [`render_frame`] that gives up when `cancel` is set: tiles not yet started are
/// skipped and `None` is returned (a window's input cancels a frame that would only show
/// the old view). `on_tile` is also given the tile's render time (profiles).
pub fn render_frame_unless(
    scene: &RenderScene,
    view: &CameraView,
    params: &RenderParams,
    frame: u32,
    on_tile: &(dyn Fn(&Tile, std::time::Duration) + Sync),
    cancel: Option<&std::sync::atomic::AtomicBool>,
) -> Option<FrameBuffer> {
    use std::sync::atomic::Ordering;
    let cancelled = || cancel.is_some_and(|flag| flag.load(Ordering::Relaxed));
    let tiles = Tile::grid(view.width(), view.height(), params.tile_size);
    let results: Vec<Option<TileResult>> = tiles
        .par_iter()
        .map(|&tile| {
            if cancelled() {
                return None;
            }
            let start = std::time::Instant::now();
            let result = render_tile(scene, view, params, tile, frame);
            on_tile(&tile, start.elapsed());
            Some(result)
        })
        .collect();
    let mut frame_buffer = FrameBuffer::new(view.width(), view.height(), frame);
    for result in &results {
        frame_buffer.write_tile(result.as_ref()?);
    }
    Some(frame_buffer)
}
