//! Shared set-up for the benchmarks: the default scene, its TLAS, and ray batches.

#![allow(
    dead_code,
    missing_docs,
    reason = "shared by several bench binaries, each using a part"
)]

use glam::{Vec2, Vec3A};
use rayon::prelude::*;
use sylva::engine::bvh::{BuildParams, TraversalStats};
use sylva::engine::camera::CameraView;
use sylva::engine::geometry::GeometryLibrary;
use sylva::engine::light::LightSet;
use sylva::engine::math::Ray;
use sylva::engine::opacity::OpacityMaps;
use sylva::engine::render::RenderScene;
use sylva::engine::shading::ShaderTable;
use sylva::engine::tlas::TopLevel;
use sylva::scenes::SceneBuild;

/// The default scene as flat render data, with its camera at 640×480.
pub struct BenchScene {
    pub build: SceneBuild,
    pub top_level: TopLevel,
    pub shaders: ShaderTable,
    pub lights: LightSet,
    pub opacity: OpacityMaps,
    pub view: CameraView,
}

impl BenchScene {
    pub fn meadow() -> Self {
        let build = sylva::scenes::build_scene("meadow", 0).unwrap();
        let descs = build.instance_descs();
        // The schedule's own top-level preset and light compile: the benches time the
        // tree and the lights the product renders.
        let top_level = TopLevel::build(&build.library, &descs, BuildParams::TOP_LEVEL);
        let shaders = ShaderTable::new(build.shaders.clone());
        let lights = LightSet::compile(&build.sun, &build.sky, &build.environment);
        let view = CameraView::new(&build.camera, &build.camera_transform.to_affine());
        let opacity = OpacityMaps::build(&build.library, &shaders);
        Self {
            build,
            top_level,
            shaders,
            lights,
            opacity,
            view,
        }
    }

    pub fn library(&self) -> &GeometryLibrary {
        &self.build.library
    }

    pub fn scene(&self) -> RenderScene<'_> {
        RenderScene {
            geometry: &self.build.library,
            top_level: &self.top_level,
            shaders: &self.shaders,
            lights: &self.lights,
            opacity: &self.opacity,
        }
    }

    /// One primary ray through each pixel centre.
    pub fn primary_rays(&self) -> Vec<Ray> {
        let (w, h) = (self.view.width(), self.view.height());
        (0..w * h)
            .map(|i| {
                self.view.ray(
                    Vec2::new((i % w) as f32 + 0.5, (i / w) as f32 + 0.5),
                    Vec2::ZERO,
                )
            })
            .collect()
    }

    /// Sun shadow rays from every primary hit.
    pub fn shadow_rays(&self) -> Vec<Ray> {
        let scene = self.scene();
        let sun = Vec3A::from(self.lights.directional[0].direction);
        self.primary_rays()
            .par_iter()
            .filter_map(|ray| {
                let hit = scene.closest(ray, &mut TraversalStats::default())?;
                let s = scene.surface(&hit, ray.direction);
                Some(Ray::new(
                    s.point.offset_origin(s.geometric_normal, sun),
                    sun,
                ))
            })
            .collect()
    }

    /// One diffuse bounce from every primary hit: cosine-distributed directions about the
    /// shading normal, the incoherent rays of global illumination.
    pub fn incoherent_rays(&self) -> Vec<Ray> {
        let scene = self.scene();
        self.primary_rays()
            .par_iter()
            .enumerate()
            .filter_map(|(i, ray)| {
                let hit = scene.closest(ray, &mut TraversalStats::default())?;
                let s = scene.surface(&hit, ray.direction);
                let n = s.shading_normal;
                let (t, b) = sylva::engine::sampling::orthonormal_basis(n);
                let u = Vec2::new(unit_hash(2 * i as u64), unit_hash(2 * i as u64 + 1));
                let local = sylva::engine::sampling::cosine_hemisphere(u);
                let direction = (t * local.x + b * local.y + n * local.z).normalize();
                Some(Ray::new(
                    s.point.offset_origin(s.geometric_normal, direction),
                    direction,
                ))
            })
            .collect()
    }
}

/// A number in [0, 1) from a hash of `i` (splitmix64).
fn unit_hash(i: u64) -> f32 {
    let mut z = i.wrapping_add(0x9e37_79b9_7f4a_7c15);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
}

/// The 2-thread pool every benchmark runs on.
pub fn two_thread_pool() -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap()
}

/// How many rays satisfy `test`, in parallel chunks on the current pool.
pub fn count_rays(rays: &[Ray], test: impl Fn(&Ray, &mut TraversalStats) -> bool + Sync) -> usize {
    rays.par_chunks(1024)
        .map(|chunk| {
            let mut stats = TraversalStats::default();
            chunk.iter().filter(|r| test(r, &mut stats)).count()
        })
        .sum()
}
