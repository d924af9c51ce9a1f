//! The embedded default scene: a meadow of grass tufts, shrubs and small trees on rolling
//! fBm terrain, under a sun and a gradient sky, seen from eye height.

use crate::random::{SceneRng, fbm};
use crate::species::{SpeciesShaders, grass_tuft, shrub, small_tree};
use crate::terrain::{HeightField, TerrainParams};
use crate::{SceneBuild, SceneError, Species};
use glam::{Quat, Vec3};
use std::sync::Arc;
use std::time::Instant;
use sylva_engine::bvh::BuildParams;
use sylva_engine::camera::Camera;
use sylva_engine::components::Transform;
use sylva_engine::geometry::{Geometry, GeometryLibrary};
use sylva_engine::light::{DirectionalLight, SkyLight};
use sylva_engine::shading::{Shader, ShaderId, Texture, srgb_to_linear};

/// Knobs of the meadow; the defaults are the embedded scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeadowParams {
    /// Terrain shape (default: 200 m, 400×400 cells = 320 k triangles).
    pub terrain: TerrainParams,
    /// Edge of the square planted with vegetation, in metres.
    pub planted_size: f32,
    /// Grass tufts.
    pub grass: u32,
    /// Shrubs.
    pub shrubs: u32,
    /// Small trees.
    pub trees: u32,
}

impl Default for MeadowParams {
    fn default() -> Self {
        Self {
            terrain: TerrainParams {
                size: 200.0,
                cells: 400,
                amplitude: 7.0,
                wavelength: 70.0,
                octaves: 6,
            },
            planted_size: 140.0,
            grass: 6000,
            shrubs: 800,
            trees: 80,
        }
    }
}

const GROUND: u32 = 0;
const GRASS: u32 = 1;
const BARK: u32 = 2;
const SHRUB_LEAF: u32 = 3;
const TREE_LEAF: u32 = 4;

fn srgb(r: f32, g: f32, b: f32) -> Vec3 {
    Vec3::new(srgb_to_linear(r), srgb_to_linear(g), srgb_to_linear(b))
}

/// A 128×128 tileable-looking ground texture: grass green mottled with soil.
fn ground_texture(seed: u64) -> Texture {
    let n = 128u32;
    let mut rng = SceneRng::new(seed, "ground_texture");
    let texels = (0..n * n)
        .map(|i| {
            let (x, y) = ((i % n) as f32 / n as f32, (i / n) as f32 / n as f32);
            let soil = (fbm(seed, x * 6.0, y * 6.0, 4, 0.5) * 1.5 + 0.1).clamp(0.0, 1.0);
            let grain = rng.range(-0.06, 0.06);
            let grass = [0.30, 0.42, 0.16];
            let dirt = [0.42, 0.33, 0.22];
            let c: [f32; 3] = std::array::from_fn(|k| {
                (grass[k] + (dirt[k] - grass[k]) * soil + grain).clamp(0.0, 1.0)
            });
            [
                (c[0] * 255.0) as u8,
                (c[1] * 255.0) as u8,
                (c[2] * 255.0) as u8,
                255,
            ]
        })
        .collect();
    Texture::from_srgba8(n, n, texels).expect("the ground texture has n×n texels")
}

/// Builds the meadow: geometry with BLASes, shaders, placements, lights and camera.
pub fn build(seed: u64, params: &MeadowParams) -> Result<SceneBuild, SceneError> {
    let start = Instant::now();
    let terrain = HeightField::fbm(seed, &params.terrain);
    let shaders = vec![
        Shader::textured(ShaderId(GROUND), Vec3::ONE, Arc::new(ground_texture(seed))),
        Shader::color(ShaderId(GRASS), srgb(0.33, 0.55, 0.17)),
        Shader::color(ShaderId(BARK), srgb(0.36, 0.27, 0.20)),
        Shader::color(ShaderId(SHRUB_LEAF), srgb(0.24, 0.44, 0.12)),
        Shader::color(ShaderId(TREE_LEAF), srgb(0.35, 0.55, 0.15)),
    ];
    let meshes = vec![
        ("terrain", terrain.to_mesh(GROUND, 4.0)),
        (
            "grass tuft",
            grass_tuft(
                seed,
                16,
                0.45,
                SpeciesShaders {
                    bark: GRASS,
                    leaf: GRASS,
                },
            ),
        ),
        (
            "shrub",
            shrub(
                seed,
                6,
                14,
                0.9,
                SpeciesShaders {
                    bark: BARK,
                    leaf: SHRUB_LEAF,
                },
            ),
        ),
        (
            "small tree",
            small_tree(
                seed,
                5.0,
                14,
                40,
                SpeciesShaders {
                    bark: BARK,
                    leaf: TREE_LEAF,
                },
            ),
        ),
    ];
    let generate_time = start.elapsed();

    let build_start = Instant::now();
    let geometries: Vec<Geometry> = meshes
        .into_iter()
        .map(|(name, mesh)| {
            Geometry::new(name, mesh, BuildParams::BALANCED).map_err(|e| SceneError::Mesh {
                scene: "meadow".into(),
                mesh: name.into(),
                source: e,
            })
        })
        .collect::<Result<_, _>>()?;
    let mut library = GeometryLibrary::default();
    let ids: Vec<_> = geometries.into_iter().map(|g| library.add(g)).collect();
    let blas_time = build_start.elapsed();

    let place_start = Instant::now();
    let camera_eye = Vec3::new(0.0, terrain.height_at(0.0, 45.0) + 1.7, 45.0);
    let half = params.planted_size / 2.0;
    let mut plants = Vec::new();
    let mut place = |rng: &mut SceneRng, geometry, x: f32, z: f32, scale: f32| {
        if Vec3::new(x - camera_eye.x, 0.0, z - camera_eye.z).length() < 2.5 {
            return;
        }
        let yaw = Quat::from_rotation_y(rng.range(0.0, std::f32::consts::TAU));
        let tilt = Quat::from_rotation_x(rng.range(-0.06, 0.06))
            * Quat::from_rotation_z(rng.range(-0.06, 0.06));
        let t =
            Transform::from_translation(Vec3::new(x, terrain.height_at(x, z) - 0.02 * scale, z))
                .with_rotation(tilt * yaw)
                .with_scale(Vec3::splat(scale));
        plants.push((geometry, t));
    };
    // Trees by dart throwing with a minimum spacing.
    let mut rng = SceneRng::new(seed, "trees");
    let mut trees: Vec<(f32, f32)> = Vec::new();
    for _ in 0..params.trees * 30 {
        if trees.len() as u32 >= params.trees {
            break;
        }
        let (x, z) = (rng.range(-half, half), rng.range(-half, half));
        if trees.iter().all(|&(tx, tz)| (tx - x).hypot(tz - z) > 7.0) {
            trees.push((x, z));
            let s = rng.range(0.7, 1.3);
            place(&mut rng, ids[3], x, z, s);
        }
    }
    // Shrubs in clusters where a low-frequency noise is high.
    let mut rng = SceneRng::new(seed, "shrubs");
    let mut placed = 0;
    for _ in 0..params.shrubs * 40 {
        if placed >= params.shrubs {
            break;
        }
        let (x, z) = (rng.range(-half, half), rng.range(-half, half));
        if fbm(seed ^ 0x5eed, x / 25.0, z / 25.0, 3, 0.5) > 0.1 {
            let s = rng.range(0.6, 1.4);
            place(&mut rng, ids[2], x, z, s);
            placed += 1;
        }
    }
    // Grass everywhere, denser near the camera where it shows.
    let mut rng = SceneRng::new(seed, "grass");
    for _ in 0..params.grass {
        let (x, z) = if rng.f32() < 0.5 {
            (rng.range(-20.0, 20.0), rng.range(10.0, 50.0))
        } else {
            (rng.range(-half, half), rng.range(-half, half))
        };
        let s = rng.range(0.7, 1.4);
        place(&mut rng, ids[1], x, z, s);
    }
    let place_time = place_start.elapsed();

    let target = Vec3::new(0.0, terrain.height_at(0.0, 0.0) + 2.0, 0.0);
    Ok(SceneBuild {
        name: "meadow".into(),
        library,
        species: vec![
            Species {
                name: "grass tuft".into(),
                geometry: ids[1],
            },
            Species {
                name: "shrub".into(),
                geometry: ids[2],
            },
            Species {
                name: "small tree".into(),
                geometry: ids[3],
            },
        ],
        terrain: Some(ids[0]),
        shaders,
        plants,
        sun: Some(DirectionalLight {
            direction: Vec3::new(-0.6, 0.62, 0.5).normalize(),
            irradiance: Vec3::new(3.2, 3.0, 2.7),
        }),
        sky: Some(SkyLight {
            zenith: Vec3::new(0.22, 0.42, 0.95),
            horizon: Vec3::new(0.75, 0.85, 1.0),
            ground: Vec3::new(0.12, 0.11, 0.08),
        }),
        camera: Camera {
            vertical_fov: 55f32.to_radians(),
            ..Camera::default()
        },
        camera_transform: Transform::looking_at(camera_eye, target, Vec3::Y),
        generate_time: generate_time + place_time,
        blas_time,
    })
}
