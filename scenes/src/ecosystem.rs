//! Ecosystems in vegetation layers, after Table 1 of Dietrich et al.: a terrain, layers
//! of species placed by Poisson-disk rules, a sun, a sky and a camera. An
//! [`EcosystemSpec`] is plain data (the presets `meadow`, `forest` and `paper` are three
//! of them; scene files describe others) and [`build`] turns it into a [`SceneBuild`].

use crate::placement::{PlacementRule, poisson_disk};
use crate::random::SceneRng;
use crate::sky::PreethamSky;
use crate::species::{self, LeafShape, PlantKind, PlantParams, SpeciesModel};
use crate::terrain::{HeightField, TerrainParams, ground_texture};
use crate::{Plant, SceneBuild, SceneError, Species};
use glam::{Quat, Vec2, Vec3};
use rayon::prelude::*;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;
use sylva_engine::bvh::BuildParams;
use sylva_engine::camera::Camera;
use sylva_engine::camera_path::{CameraKey, CameraPath};
use sylva_engine::components::Transform;
use sylva_engine::environment::EnvironmentLight;
use sylva_engine::geometry::{Geometry, GeometryLibrary};
use sylva_engine::light::{DirectionalLight, SkyLight};
use sylva_engine::mesh::TriangleMesh;
use sylva_engine::shading::{Shader, ShaderId, Transmission};

/// Where a species' model comes from.
#[derive(Clone, Debug, PartialEq)]
pub enum SpeciesSource {
    /// The procedural generator.
    Procedural {
        /// Growth form.
        kind: PlantKind,
        /// Height in metres.
        height: f32,
        /// Triangle budget.
        triangles: u32,
        /// Leaf outline (the kind's usual one when `None`).
        leaf_shape: Option<LeafShape>,
        /// Linear RGB leaf colour (a seeded one when `None`).
        leaf_color: Option<Vec3>,
        /// Seed of the model.
        seed: u64,
    },
    /// A glTF/GLB file: all its mesh nodes baked into one model, +Y up, base at the
    /// origin as the file has it.
    Gltf {
        /// The file.
        path: PathBuf,
    },
}

/// A species of a layer.
#[derive(Clone, Debug, PartialEq)]
pub struct SpeciesSpec {
    /// Display name.
    pub name: String,
    /// The model.
    pub source: SpeciesSource,
    /// Relative frequency within its layer.
    pub weight: f32,
    /// How its plants sway, where it differs from its layer's.
    pub sway: SwaySpec,
}

/// Factors on the damped spring a plant sways on, whose stiffness, damping and inertia
/// otherwise follow from its height (1 keeps a value as the height gives it).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SwayFactors {
    /// Stiffness factor: > 1 bends less and swings faster.
    pub stiffness: f32,
    /// Damping factor: > 1 settles sooner.
    pub damping: f32,
    /// Inertia factor: > 1 swings slower.
    pub inertia: f32,
}

impl Default for SwayFactors {
    fn default() -> Self {
        Self {
            stiffness: 1.0,
            damping: 1.0,
            inertia: 1.0,
        }
    }
}

/// Sway factors given for a layer or a species, each optional: a species' value wins
/// over its layer's, and a value neither gives is 1.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SwaySpec {
    /// Stiffness factor.
    pub stiffness: Option<f32>,
    /// Damping factor.
    pub damping: Option<f32>,
    /// Inertia factor.
    pub inertia: Option<f32>,
}

impl SwaySpec {
    /// These values, with `layer`'s where this one gives none, as factors.
    pub fn over(self, layer: SwaySpec) -> SwayFactors {
        SwayFactors {
            stiffness: self.stiffness.or(layer.stiffness).unwrap_or(1.0),
            damping: self.damping.or(layer.damping).unwrap_or(1.0),
            inertia: self.inertia.or(layer.inertia).unwrap_or(1.0),
        }
    }
}

/// A vegetation layer: its species and how they are placed.
#[derive(Clone, Debug, PartialEq)]
pub struct LayerSpec {
    /// Display name ("higher haulm", …).
    pub name: String,
    /// Species, picked per plant by weight.
    pub species: Vec<SpeciesSpec>,
    /// Plants in the layer.
    pub count: u32,
    /// Uniform instance scale range.
    pub scale: (f32, f32),
    /// Minimum distance between plants of this layer (automatic when `None`).
    pub min_spacing: Option<f32>,
    /// 0 = uniform, towards 1 = clustered.
    pub clustering: f32,
    /// Rectangle `[x0, z0, x1, z1]`; the whole terrain when `None`.
    pub region: Option<[f32; 4]>,
    /// How its plants sway (its species may say otherwise).
    pub sway: SwaySpec,
}

/// The sun as a direction and an irradiance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SunSpec {
    /// Degrees above the horizon.
    pub elevation: f32,
    /// Degrees from +Z towards +X.
    pub azimuth: f32,
    /// Linear RGB irradiance on a surface facing the sun.
    pub irradiance: Vec3,
}

impl SunSpec {
    /// The light it becomes.
    pub fn light(&self) -> DirectionalLight {
        let (e, a) = (self.elevation.to_radians(), self.azimuth.to_radians());
        DirectionalLight {
            direction: Vec3::new(e.cos() * a.sin(), e.sin(), e.cos() * a.cos()),
            irradiance: self.irradiance,
        }
    }
}

/// One key frame of a camera flight, placed relative to the terrain as [`CameraSpec`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraKeySpec {
    /// Seconds from the start.
    pub time: f64,
    /// Eye `(x, z)` and height above the ground.
    pub eye: Vec2,
    /// Eye height above the ground.
    pub eye_height: f32,
    /// Where the camera looks: a point `(x, z)` and its height above the ground, or an
    /// orientation.
    pub aim: CameraAim,
    /// Vertical field of view in degrees.
    pub fov: f32,
}

/// Where a key frame's camera looks.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CameraAim {
    /// At a point `(x, z)`, this high above the ground.
    Target(Vec2, f32),
    /// With this orientation (looking along its −Z).
    Rotation(glam::Quat),
}

/// A camera flight: key frames and how they are interpolated.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraPathSpec {
    /// Key frames, times increasing.
    pub keys: Vec<CameraKeySpec>,
    /// Linear or Catmull–Rom.
    pub interpolation: sylva_engine::camera_path::PathInterpolation,
}

/// The camera, placed relative to the terrain surface.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraSpec {
    /// Eye `(x, z)` in metres.
    pub eye: Vec2,
    /// Eye height above the ground.
    pub eye_height: f32,
    /// Target `(x, z)`.
    pub target: Vec2,
    /// Target height above the ground.
    pub target_height: f32,
    /// Vertical field of view in degrees.
    pub fov: f32,
}

/// A whole ecosystem as data.
#[derive(Clone, Debug, PartialEq)]
pub struct EcosystemSpec {
    /// Scene name.
    pub name: String,
    /// Terrain shape.
    pub terrain: TerrainParams,
    /// Vegetation layers.
    pub layers: Vec<LayerSpec>,
    /// Plants closer than this to the camera's eye (metres) are pushed out to this
    /// distance, so the camera does not stand in a bush.
    pub clear_radius: f32,
    /// The sun.
    pub sun: Option<SunSpec>,
    /// The sky.
    pub sky: Option<SkySpec>,
    /// The view.
    pub camera: CameraSpec,
    /// Every plant where it stands (a saved, edited ecosystem): when given, the layers'
    /// counts and placement rules are not used, only their species.
    pub plants: Option<Vec<PlacedPlant>>,
    /// The wind that sways the plants when the wind is on (`sylva animate`, the viewer's
    /// G); the engine's default wind when `None`.
    pub wind: Option<sylva_engine::sway::Wind>,
    /// The camera's flight for `sylva animate`, if any.
    pub camera_path: Option<CameraPathSpec>,
}

/// A plant of an explicit plant list: its species by name, its layer and its transform.
#[derive(Clone, Debug, PartialEq)]
pub struct PlacedPlant {
    /// The species' name (one of the layers' species).
    pub species: String,
    /// Index of its layer.
    pub layer: u32,
    /// Where and how it stands.
    pub transform: Transform,
}

/// `n` procedural species of `kind` with heights in `heights` and triangle budgets
/// spread ±25 % around `triangles` (the mean stays `triangles`).
/// `n` generated species of one kind named "PREFIX 1" … "PREFIX n": heights drawn from
/// `heights`, triangle counts spread ±25 % about `triangles`, seeds drawn from `seed`.
pub(crate) fn procedural(
    prefix: &str,
    kind: PlantKind,
    n: u32,
    heights: (f32, f32),
    triangles: u32,
    seed: u64,
) -> Vec<SpeciesSpec> {
    let mut rng = SceneRng::new(seed, prefix);
    (0..n)
        .map(|i| {
            let spread = if n > 1 {
                -0.25 + 0.5 * i as f32 / (n - 1) as f32
            } else {
                0.0
            };
            SpeciesSpec {
                name: format!("{prefix} {}", i + 1),
                source: SpeciesSource::Procedural {
                    kind,
                    height: rng.range(heights.0, heights.1),
                    triangles: (triangles as f32 * (1.0 + spread)).round() as u32,
                    leaf_shape: None,
                    leaf_color: None,
                    seed: rng.next_u64(),
                },
                weight: 1.0,
                sway: SwaySpec::default(),
            }
        })
        .collect()
}

/// The sky of an ecosystem.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SkySpec {
    /// A zenith–horizon gradient, sampled with cosine-weighted rays.
    Gradient(SkyLight),
    /// The Preetham daylight model for the scene's sun, baked into an environment map
    /// and lit through virtual lights.
    Preetham {
        /// Atmospheric turbidity (2–10).
        turbidity: f32,
    },
}

/// Texels across the baked procedural sky.
const SKY_MAP_WIDTH: u32 = 256;
/// Virtual lights of the baked procedural sky.
const SKY_LIGHTS: usize = 256;

fn default_sky() -> SkySpec {
    SkySpec::Preetham { turbidity: 3.0 }
}

fn default_sun() -> SunSpec {
    SunSpec {
        elevation: 38.0,
        azimuth: -50.0,
        irradiance: Vec3::new(3.2, 3.0, 2.7),
    }
}

impl EcosystemSpec {
    /// The starting point of a scene file that names no preset: the embedded meadow's
    /// terrain, sun, sky and camera, no layers.
    pub fn base() -> Self {
        Self {
            name: "scene".into(),
            terrain: TerrainParams {
                size: 200.0,
                cells: 400,
                amplitude: 7.0,
                wavelength: 70.0,
                octaves: 6,
                ridged: false,
            },
            layers: Vec::new(),
            plants: None,
            wind: None,
            camera_path: None,
            clear_radius: 2.5,
            sun: Some(default_sun()),
            sky: Some(default_sky()),
            camera: CameraSpec {
                eye: Vec2::new(0.0, 45.0),
                eye_height: 1.7,
                target: Vec2::ZERO,
                target_height: 2.0,
                fov: 55.0,
            },
        }
    }
}

/// Bark and alpha-masked leaf shaders for a generated plant.
fn procedural_model(source: &SpeciesSource) -> Option<SpeciesModel> {
    let SpeciesSource::Procedural {
        kind,
        height,
        triangles,
        leaf_shape,
        leaf_color,
        seed,
    } = source
    else {
        return None;
    };
    let mut params = PlantParams::for_kind(*kind, *height, *triangles, *seed);
    if let Some(shape) = leaf_shape {
        params.leaf_shape = *shape;
    }
    if let Some(color) = leaf_color {
        params.leaf_color = *color;
    }
    let model = species::generate(&params, *seed);
    Some(SpeciesModel {
        mesh: model.mesh,
        shaders: vec![
            Shader::color(ShaderId(species::BARK), model.bark_color),
            translucent_leaf(
                Shader::alpha_masked(
                    ShaderId(species::LEAF),
                    Vec3::ONE,
                    Arc::new(model.leaf_texture),
                    0.5,
                ),
                params.leaf_shape.transmission_ratio(),
                params.leaf_color,
            ),
        ],
    })
}

/// A generated leaf shader that also transmits `ratio` × what it reflects, tinted by
/// the leaf colour: half the diffuse light is transmitted and the base colour doubles,
/// so the reflected light is the opaque leaf's to the bit
/// ([`Shader::without_transmission`] gives that leaf back).
fn translucent_leaf(leaf: Shader, ratio: f32, leaf_color: Vec3) -> Shader {
    if ratio <= 0.0 {
        return leaf;
    }
    const SHARE: f32 = 0.5;
    let tint = leaf_color * (ratio / SHARE);
    let (transmission, _) = Transmission::new(SHARE, tint).clamped();
    Shader {
        base_color: leaf.base_color / (1.0 - SHARE),
        transmission: Some(transmission),
        ..leaf
    }
}

fn load_model(spec: &SpeciesSpec, scene: &str) -> Result<SpeciesModel, SceneError> {
    if let Some(model) = procedural_model(&spec.source) {
        return Ok(model);
    }
    let SpeciesSource::Gltf { path } = &spec.source else {
        unreachable!("every non-procedural source is a glTF file");
    };
    load_gltf_species(path).map_err(|source| SceneError::Species {
        scene: scene.into(),
        species: spec.name.clone(),
        source: Box::new(source),
    })
}

#[cfg(feature = "gltf")]
fn load_gltf_species(path: &std::path::Path) -> Result<SpeciesModel, SceneError> {
    let scene = crate::gltf::import(path)?;
    Ok(scene.bake())
}

#[cfg(not(feature = "gltf"))]
fn load_gltf_species(path: &std::path::Path) -> Result<SpeciesModel, SceneError> {
    Err(SceneError::FeatureDisabled {
        feature: "gltf",
        path: path.to_path_buf(),
    })
}

/// Builds the ecosystem: terrain, every species (generated and BLAS-built in parallel on
/// the current rayon pool), placements layer by layer, lights and camera.
pub fn build(spec: &EcosystemSpec, seed: u64) -> Result<SceneBuild, SceneError> {
    let start = Instant::now();
    let terrain = HeightField::fbm(seed, &spec.terrain);
    let species_specs: Vec<(usize, &SpeciesSpec)> = spec
        .layers
        .iter()
        .enumerate()
        .flat_map(|(l, layer)| layer.species.iter().map(move |s| (l, s)))
        .collect();
    // One model per distinct species (layers may share species).
    let mut distinct: Vec<&SpeciesSpec> = Vec::new();
    for (_, s) in &species_specs {
        if !distinct.contains(s) {
            distinct.push(s);
        }
    }
    let (terrain_mesh, models) = rayon::join(
        || terrain.to_mesh(0, 4.0),
        || {
            distinct
                .par_iter()
                .map(|s| load_model(s, &spec.name))
                .collect::<Result<Vec<_>, _>>()
        },
    );
    let models = models?;
    let mut shaders = vec![Shader::textured(
        ShaderId(0),
        Vec3::ONE,
        Arc::new(ground_texture(seed)),
    )];
    let meshes: Vec<(String, TriangleMesh)> =
        std::iter::once(("terrain".to_string(), terrain_mesh))
            .chain(distinct.iter().zip(models).map(|(s, model)| {
                let offset = shaders.len() as u32;
                let mut mesh = model.mesh;
                let local = model.shaders.len() as u32;
                for id in &mut mesh.shaders {
                    *id = offset + (*id).min(local.saturating_sub(1));
                }
                for (k, mut shader) in model.shaders.into_iter().enumerate() {
                    shader.id = ShaderId(offset + k as u32);
                    shaders.push(shader);
                }
                (s.name.clone(), mesh)
            }))
            .collect();
    let generate_time = start.elapsed();

    let build_start = Instant::now();
    let geometries: Vec<Geometry> = meshes
        .into_par_iter()
        .map(|(name, mesh)| {
            Geometry::new(&name, mesh, BuildParams::BOTTOM_LEVEL).map_err(|e| SceneError::Mesh {
                scene: spec.name.clone(),
                mesh: name.clone(),
                source: e,
            })
        })
        .collect::<Result<_, _>>()?;
    let mut library = GeometryLibrary::default();
    let ids: Vec<_> = geometries.into_iter().map(|g| library.add(g)).collect();
    let blas_time = build_start.elapsed();

    let place_start = Instant::now();
    let eye = spec.camera.eye;
    let half = spec.terrain.size / 2.0;
    let layer_plants: Vec<(Vec<Plant>, f32)> = spec
        .layers
        .par_iter()
        .enumerate()
        .map(|(l, layer)| {
            let layer_seed = seed ^ sylva_engine::sampling::mix64(l as u64 + 1);
            let (points, spacing) = poisson_disk(&layer_rule(layer, half), layer_seed);
            let weights: Vec<f32> = layer.species.iter().map(|s| s.weight.max(0.0)).collect();
            let total: f32 = weights.iter().sum();
            let mut rng = SceneRng::new(layer_seed, "plants");
            let plants = points
                .into_iter()
                .map(|p| {
                    // Push plants out of the clearing rather than dropping them, so a
                    // layer keeps its exact count.
                    let away = p - eye;
                    if away.length() < spec.clear_radius {
                        eye + away.normalize_or(Vec2::X) * spec.clear_radius
                    } else {
                        p
                    }
                })
                .filter_map(|p| {
                    let mut pick = rng.f32() * total;
                    let chosen = weights
                        .iter()
                        .position(|&w| {
                            pick -= w;
                            pick < 0.0
                        })
                        .unwrap_or(weights.len().checked_sub(1)?);
                    let index = distinct.iter().position(|d| *d == &layer.species[chosen])?;
                    let scale = rng.range(layer.scale.0, layer.scale.1.max(layer.scale.0));
                    let yaw = Quat::from_rotation_y(rng.range(0.0, std::f32::consts::TAU));
                    let tilt = Quat::from_rotation_x(rng.range(-0.05, 0.05))
                        * Quat::from_rotation_z(rng.range(-0.05, 0.05));
                    let y = terrain.height_at(p.x, p.y) - 0.02 * scale;
                    Some(Plant {
                        geometry: ids[1 + index],
                        transform: Transform::from_translation(Vec3::new(p.x, y, p.y))
                            .with_rotation(tilt * yaw)
                            .with_scale(Vec3::splat(scale)),
                        layer: l as u32,
                    })
                })
                .collect::<Vec<Plant>>();
            (plants, spacing)
        })
        .collect();
    let (layer_plants, layer_spacing): (Vec<Vec<Plant>>, Vec<f32>) =
        layer_plants.into_iter().unzip();
    // The sway factors that differ from the height's, per layer and species.
    let mut sway_factors = Vec::new();
    for (l, layer) in spec.layers.iter().enumerate() {
        for species in &layer.species {
            let factors = species.sway.over(layer.sway);
            if let Some(index) = distinct.iter().position(|d| *d == species)
                && factors != SwayFactors::default()
            {
                sway_factors.push((l as u32, ids[1 + index], factors));
            }
        }
    }
    let plants: Vec<Plant> = match &spec.plants {
        None => layer_plants.into_iter().flatten().collect(),
        Some(list) => list
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let index = distinct
                    .iter()
                    .position(|d| d.name == p.species)
                    .ok_or_else(|| SceneError::UnknownSpecies {
                        scene: spec.name.clone(),
                        plant: i,
                        species: p.species.clone(),
                    })?;
                Ok(Plant {
                    geometry: ids[1 + index],
                    transform: p.transform,
                    layer: p.layer,
                })
            })
            .collect::<Result<_, SceneError>>()?,
    };
    let place_time = place_start.elapsed();

    let ground =
        |xz: Vec2, above: f32| Vec3::new(xz.x, terrain.height_at(xz.x, xz.y) + above, xz.y);
    let camera_transform = Transform::looking_at(
        ground(spec.camera.eye, spec.camera.eye_height),
        ground(spec.camera.target, spec.camera.target_height),
        Vec3::Y,
    );
    let camera_path = match &spec.camera_path {
        Some(path) => {
            let keys = path
                .keys
                .iter()
                .map(|k| {
                    let position = ground(k.eye, k.eye_height);
                    let rotation = match k.aim {
                        CameraAim::Target(target, height) => {
                            Transform::looking_at(position, ground(target, height), Vec3::Y)
                                .rotation
                        }
                        CameraAim::Rotation(rotation) => rotation,
                    };
                    CameraKey {
                        time: k.time,
                        position,
                        rotation,
                        vertical_fov: k.fov.to_radians(),
                    }
                })
                .collect();
            Some(CameraPath::new(keys, path.interpolation).map_err(|source| {
                SceneError::CameraPath {
                    scene: spec.name.clone(),
                    source,
                }
            })?)
        }
        None => None,
    };
    Ok(SceneBuild {
        name: spec.name.clone(),
        library,
        species: distinct
            .iter()
            .enumerate()
            .map(|(i, s)| Species {
                name: s.name.clone(),
                geometry: ids[1 + i],
            })
            .collect(),
        layers: spec.layers.iter().map(|l| l.name.clone()).collect(),
        layer_spacing,
        terrain: Some(ids[0]),
        height_field: Some(terrain),
        shaders,
        plants,
        sun: spec.sun.map(|s| s.light()),
        wind: spec.wind,
        node_animation: None,
        sway_factors,
        camera_path,
        sky: match spec.sky {
            Some(SkySpec::Gradient(gradient)) => Some(gradient),
            _ => None,
        },
        environment: match spec.sky {
            Some(SkySpec::Preetham { turbidity }) => {
                let sun = spec
                    .sun
                    .map_or(Vec3::new(0.3, 0.8, 0.5), |s| s.light().direction);
                let map = PreethamSky::new(sun, turbidity).to_map(SKY_MAP_WIDTH);
                Some(EnvironmentLight::new(map, SKY_LIGHTS))
            }
            _ => None,
        },
        camera: Camera {
            vertical_fov: spec.camera.fov.to_radians(),
            ..Camera::default()
        },
        camera_transform,
        generate_time: generate_time + place_time,
        blas_time,
    })
}

/// How a layer's plants are placed over a terrain of half-size `half`.
fn layer_rule(layer: &LayerSpec, half: f32) -> PlacementRule {
    PlacementRule {
        count: layer.count,
        region: layer.region.unwrap_or([-half, -half, half, half]),
        min_spacing: layer.min_spacing,
        clustering: layer.clustering,
        cluster_size: 12.0,
    }
}
