//! Shading a hit: the surface point rebuilt from it, direct light from the sun and
//! the environment's lights (one side or, through translucent leaves, both), diffuse
//! bounces, and a camera sample's radiance, albedo and surface.

use super::plan::SampleShading;
use super::scene::RenderScene;
use crate::accel::occluders::OccluderCache;
use crate::accel::tlas::{Hit, InstanceTriangle};
use crate::accel::triangle::hit_point;
use crate::film::SurfaceGuide;
use crate::light::interleave::stratified_selection;
use crate::util::color::luminance;
use crate::util::math::{ErrorPoint, Ray};
use crate::util::sampling::{SampleKey, cosine_hemisphere, orthonormal_basis};
use crate::util::stats::TraversalStats;
use glam::{Vec2, Vec3, Vec3A};

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
