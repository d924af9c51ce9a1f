//! # sylva_scenes
//!
//! Builds worlds: procedural species, terrain, ecosystems in vegetation layers (the
//! presets `meadow`, `forest`, `paper`), TOML scene files and glTF import. A
//! [`SceneBuild`] is plain data (geometry with BLASes, shaders, placements, lights,
//! camera); [`spawn`] turns it into entities and resources of a bevy `World`, and
//! [`plant_at`] / [`move_plant`] place plants one by one afterwards. Same seed, same scene.

pub mod ecosystem;
pub mod editor;
pub mod environment;
#[cfg(feature = "gltf")]
pub mod gltf;
pub mod placement;
pub mod presets;
pub mod random;
pub mod scene_file;
pub mod sky;
pub mod species;
pub mod terrain;

use bevy_ecs::prelude::*;
use std::path::PathBuf;
use std::time::Duration;
use sylva_engine::camera::Camera;
use sylva_engine::components::{Instance, Layer, Transform};
use sylva_engine::geometry::{GeometryId, GeometryLibrary};
use sylva_engine::light::{DirectionalLight, SkyLight};
use sylva_engine::mesh::MeshError;
use sylva_engine::shading::Shader;
use sylva_engine::tlas::{InstanceDesc, InstanceRecord};

pub use presets::PRESETS as SCENE_NAMES;
use terrain::HeightField;

/// Why a scene could not be built.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The name is not a built-in scene.
    #[error("unknown scene '{name}' (available: {})", SCENE_NAMES.join(", "))]
    UnknownScene {
        /// The name given.
        name: String,
    },
    /// An explicit plant names a species no layer has.
    #[error("scene '{scene}': plant {plant} is of species '{species}', which no layer has")]
    UnknownSpecies {
        /// The scene.
        scene: String,
        /// Index of the plant in the list.
        plant: usize,
        /// The name it gives.
        species: String,
    },
    /// A generated mesh is malformed (a bug in a generator).
    #[error("scene '{scene}', mesh '{mesh}': {source}")]
    Mesh {
        /// Scene name.
        scene: String,
        /// Mesh name.
        mesh: String,
        /// The defect.
        source: MeshError,
    },
    /// The camera path's key frames do not make a path.
    #[error("scene '{scene}', camera path: {source}")]
    CameraPath {
        /// Scene name.
        scene: String,
        /// What is wrong.
        source: sylva_engine::camera_path::CameraPathError,
    },
    /// A species' model could not be loaded.
    #[error("scene '{scene}', species '{species}': {source}")]
    Species {
        /// Scene name.
        scene: String,
        /// Species name.
        species: String,
        /// Why.
        source: Box<SceneError>,
    },
    /// A scene file could not be read or is invalid.
    #[error(transparent)]
    SceneFile(#[from] scene_file::SceneFileError),
    /// A glTF file could not be imported.
    #[cfg(feature = "gltf")]
    #[error(transparent)]
    Gltf(#[from] gltf::GltfError),
    /// The input needs a cargo feature this build left out.
    #[error("{}: reading this needs the '{feature}' cargo feature, which this build left out", path.display())]
    FeatureDisabled {
        /// The feature.
        feature: &'static str,
        /// The file.
        path: PathBuf,
    },
}

/// A plant species: a name and its mesh.
#[derive(Clone, Debug, PartialEq)]
pub struct Species {
    /// Display name.
    pub name: String,
    /// Its mesh in the library.
    pub geometry: GeometryId,
}

/// One placed plant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plant {
    /// Its species' mesh.
    pub geometry: GeometryId,
    /// Where it stands.
    pub transform: Transform,
    /// Its layer (index into [`SceneBuild::layers`]).
    pub layer: u32,
}

/// Per layer, the least distance between two of its plants
/// ([`SceneBuild::layer_spacing`]), as a world resource for the editor.
#[derive(Clone, Debug, Default, Resource)]
pub struct LayerSpacing(pub Vec<f32>);

/// A node animation and the plants it moves: `(index into the plants, node, transform
/// under the node)` each.
pub type BoundAnimation = (
    sylva_engine::node_animation::NodeAnimation,
    Vec<(usize, usize, glam::Affine3A)>,
);

/// The sway factors a scene gives per `(layer, species geometry)`, for when the wind is
/// turned on (`editor::set_wind`); plants not listed sway as their height gives.
#[derive(Clone, Debug, Default, Resource)]
pub struct SwayTuning(pub std::collections::HashMap<(u32, GeometryId), ecosystem::SwayFactors>);

/// The wind a scene file describes: what turning the wind on blows (`editor::set_wind`),
/// a world resource while the wind is off too.
#[derive(Clone, Copy, Debug, Resource)]
pub struct SceneWind(pub sylva_engine::sway::Wind);

/// The height field plants stand on, as a world resource for placing plants later.
#[derive(Clone, Debug, Resource)]
pub struct Terrain(pub HeightField);

/// A scene as plain data, ready to [`spawn`].
#[derive(Clone, Debug)]
pub struct SceneBuild {
    /// Scene name.
    pub name: String,
    /// Every mesh with its BLAS.
    pub library: GeometryLibrary,
    /// The plant species (the terrain is not one).
    pub species: Vec<Species>,
    /// Names of the vegetation layers.
    pub layers: Vec<String>,
    /// Per layer, the spacing its placement ended with, which every two of its plants
    /// keep (dense layers relax the asked one; 0 for none): the editor keeps inserted
    /// plants this far from the layer's.
    pub layer_spacing: Vec<f32>,
    /// The terrain mesh, instanced once at the origin.
    pub terrain: Option<GeometryId>,
    /// The terrain's height field (for placing plants on it).
    pub height_field: Option<HeightField>,
    /// Shaders (one entity each).
    pub shaders: Vec<Shader>,
    /// Plant placements (one entity each).
    pub plants: Vec<Plant>,
    /// The sun.
    pub sun: Option<DirectionalLight>,
    /// The scene's wind, for when the wind is turned on ([`SceneWind`]).
    pub wind: Option<sylva_engine::sway::Wind>,
    /// Sway factors per `(layer, species geometry)` where they differ from those the
    /// plants' heights give ([`SwayTuning`]).
    pub sway_factors: Vec<(u32, GeometryId, ecosystem::SwayFactors)>,
    /// A glTF file's node animation and, per animated plant, `(index into plants, node,
    /// transform under the node)`: what `sylva animate` plays
    /// (`sylva_systems::NodeAnimationPlayer`).
    pub node_animation: Option<BoundAnimation>,
    /// The camera's flight, which `sylva animate` puts on the camera (`render` and
    /// `view` use the scene's camera).
    pub camera_path: Option<sylva_engine::camera_path::CameraPath>,
    /// The gradient sky, if any.
    pub sky: Option<SkyLight>,
    /// An environment light (the baked procedural sky, or a map), if any.
    pub environment: Option<sylva_engine::environment::EnvironmentLight>,
    /// The camera.
    pub camera: Camera,
    /// Where the camera stands.
    pub camera_transform: Transform,
    /// Time spent generating meshes and placements.
    pub generate_time: Duration,
    /// Time spent building BLASes.
    pub blas_time: Duration,
}

/// Size figures of a scene.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SceneStats {
    /// Plant species.
    pub species: usize,
    /// Triangles stored once (all meshes, terrain included).
    pub unique_triangles: usize,
    /// Instances (plants plus the terrain).
    pub instances: usize,
    /// Triangles summed over every instance.
    pub instanced_triangles: u64,
    /// Bytes of geometry, BLASes and an estimate of the TLAS.
    pub memory_bytes: usize,
}

impl SceneBuild {
    /// Makes every translucent shader opaque, keeping what it reflects
    /// ([`Shader::without_transmission`]): the scene as it looks without leaf
    /// translucency, and without the shadow rays it costs.
    pub fn without_translucency(&mut self) {
        for shader in &mut self.shaders {
            *shader = std::mem::replace(shader, Shader::color(shader.id, glam::Vec3::ZERO))
                .without_transmission();
        }
    }

    /// Every instance as the TLAS takes it: the plants, then the terrain at the origin.
    pub fn instance_descs(&self) -> Vec<InstanceDesc> {
        let plants = self.plants.iter().map(|p| InstanceDesc {
            transform: p.transform.to_affine(),
            geometry: p.geometry,
        });
        let terrain = self.terrain.map(|geometry| InstanceDesc {
            transform: glam::Affine3A::IDENTITY,
            geometry,
        });
        plants.chain(terrain).collect()
    }

    /// Counts species, triangles, instances and memory.
    pub fn stats(&self) -> SceneStats {
        let tri = |g: GeometryId| self.library.get(g).map_or(0, |g| g.mesh.triangle_count()) as u64;
        let instances = self.plants.len() + usize::from(self.terrain.is_some());
        let instanced_triangles =
            self.plants.iter().map(|p| tri(p.geometry)).sum::<u64>() + self.terrain.map_or(0, tri);
        // A TLAS holds one record per instance and about two nodes per leaf of four.
        let tlas_bytes = instances * (std::mem::size_of::<InstanceRecord>() + 4 + 16);
        SceneStats {
            species: self.species.len(),
            unique_triangles: self.library.triangle_count(),
            instances,
            instanced_triangles,
            memory_bytes: self.library.memory_bytes() + tlas_bytes,
        }
    }
}

/// Builds a preset by name, or the scene file at that path when it ends in `.toml`.
pub fn build_scene(name: &str, seed: u64) -> Result<SceneBuild, SceneError> {
    if name.ends_with(".toml") {
        let file = scene_file::SceneFile::load(std::path::Path::new(name))?;
        return ecosystem::build(&file.spec, file.seed.unwrap_or(seed));
    }
    match scene_file::preset(name) {
        Some(spec) => ecosystem::build(&spec, seed),
        None => Err(SceneError::UnknownScene { name: name.into() }),
    }
}

/// Entities made by [`spawn`].
#[derive(Clone, Debug, PartialEq)]
pub struct SpawnedScene {
    /// The camera.
    pub camera: Entity,
    /// The plants, in the order of `SceneBuild::plants`.
    pub plants: Vec<Entity>,
}

/// Moves a scene into `world`: the geometry library and the terrain's height field become
/// resources; shaders, plants, the terrain, lights and the camera become entities.
pub fn spawn(world: &mut World, scene: SceneBuild) -> SpawnedScene {
    world.insert_resource(scene.library);
    world.insert_resource(LayerSpacing(scene.layer_spacing));
    if let Some(wind) = scene.wind {
        world.insert_resource(SceneWind(wind));
    }
    world.insert_resource(SwayTuning(
        scene
            .sway_factors
            .into_iter()
            .map(|(layer, geometry, factors)| ((layer, geometry), factors))
            .collect(),
    ));
    if let Some(field) = scene.height_field {
        world.insert_resource(Terrain(field));
    }
    for shader in scene.shaders {
        world.spawn(shader);
    }
    if let Some(terrain) = scene.terrain {
        world.spawn((Transform::IDENTITY, Instance { geometry: terrain }));
    }
    let plants = world
        .spawn_batch(scene.plants.into_iter().map(|p| {
            (
                p.transform,
                Instance {
                    geometry: p.geometry,
                },
                Layer(p.layer),
            )
        }))
        .collect();
    if let Some(sun) = scene.sun {
        world.spawn(sun);
    }
    if let Some(sky) = scene.sky {
        world.spawn(sky);
    }
    if let Some(environment) = scene.environment {
        world.spawn(environment);
    }
    let camera = world.spawn((scene.camera, scene.camera_transform)).id();
    SpawnedScene { camera, plants }
}

/// Spawns one plant of `species` standing on the terrain at `(x, z)`, turned by `yaw`
/// radians and scaled by `scale` (at height 0 when the world has no [`Terrain`]). The
/// next frame's `rebuild_top_level` picks it up.
pub fn plant_at(
    world: &mut World,
    species: GeometryId,
    x: f32,
    z: f32,
    yaw: f32,
    scale: f32,
) -> Entity {
    let transform = ground_transform(world, x, z, yaw, scale);
    world
        .spawn((transform, Instance { geometry: species }))
        .id()
}

/// Moves a plant to stand on the terrain at `(x, z)`; false when the entity is not a plant.
pub fn move_plant(world: &mut World, plant: Entity, x: f32, z: f32, yaw: f32, scale: f32) -> bool {
    let transform = ground_transform(world, x, z, yaw, scale);
    if world.get::<Instance>(plant).is_none() {
        return false;
    }
    match world.get_mut::<Transform>(plant) {
        Some(mut t) => {
            *t = transform;
            true
        }
        None => false,
    }
}

fn ground_transform(world: &World, x: f32, z: f32, yaw: f32, scale: f32) -> Transform {
    let y = world
        .get_resource::<Terrain>()
        .map_or(0.0, |t| t.0.height_at(x, z));
    Transform::from_translation(glam::Vec3::new(x, y, z))
        .with_rotation(glam::Quat::from_rotation_y(yaw))
        .with_scale(glam::Vec3::splat(scale))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every plant's geometry and transform bits, and every mesh's positions.
    type Fingerprint = (Vec<(u32, [u32; 10])>, Vec<Vec<glam::Vec3>>);

    fn fingerprint(scene: &SceneBuild) -> Fingerprint {
        let plants = scene
            .plants
            .iter()
            .map(|p| {
                let a = p.transform.to_affine().to_cols_array();
                (
                    p.geometry.0,
                    [0, 1, 2, 3, 4, 5, 6, 7, 8, 9].map(|i| a[i].to_bits()),
                )
            })
            .collect();
        let meshes = scene
            .library
            .geometries
            .iter()
            .map(|g| g.mesh.positions.clone())
            .collect();
        (plants, meshes)
    }

    #[test]
    fn generated_leaves_are_translucent_and_turning_it_off_keeps_their_reflectance() {
        let mut scene = build_scene("forest", 1).unwrap();
        let translucent: Vec<&Shader> = scene
            .shaders
            .iter()
            .filter(|s| s.transmission.is_some())
            .collect();
        assert!(
            !translucent.is_empty(),
            "the forest's broadleaves and grass"
        );
        assert!(
            translucent.iter().all(|s| s.is_alpha_masked()),
            "only leaves transmit, never bark or the ground"
        );
        let uvs = [glam::Vec2::new(0.3, 0.6), glam::Vec2::new(0.71, 0.2)];
        let before: Vec<Vec<glam::Vec3>> = scene
            .shaders
            .iter()
            .map(|s| uvs.map(|uv| s.reflectance(uv)).to_vec())
            .collect();
        scene.without_translucency();
        assert!(scene.shaders.iter().all(|s| s.transmission.is_none()));
        let after: Vec<Vec<glam::Vec3>> = scene
            .shaders
            .iter()
            .map(|s| uvs.map(|uv| s.reflectance(uv)).to_vec())
            .collect();
        assert_eq!(before, after, "the reflected light is the same to the bit");
    }

    #[test]
    fn same_seed_same_scene_other_seed_other_scene() {
        let a = build_scene("meadow", 3).unwrap();
        let b = build_scene("meadow", 3).unwrap();
        let c = build_scene("meadow", 4).unwrap();
        assert_eq!(fingerprint(&a), fingerprint(&b));
        assert_ne!(fingerprint(&a).0, fingerprint(&c).0);
        let stats = a.stats();
        assert_eq!(stats.species, 5);
        assert!(
            stats.instances > 2000 && stats.unique_triangles > 300_000,
            "{stats:?}"
        );
        assert!(stats.instanced_triangles > stats.unique_triangles as u64);
    }

    #[test]
    fn unknown_scene_is_an_error_naming_it() {
        let e = build_scene("jungle", 0).unwrap_err().to_string();
        assert!(e.contains("jungle") && e.contains("meadow"), "{e}");
    }

    #[test]
    fn spawn_makes_one_entity_per_plant_and_a_camera() {
        let mut world = World::new();
        let scene = build_scene("meadow", 0).unwrap();
        let plants = scene.plants.len();
        let spawned = spawn(&mut world, scene);
        assert_eq!(spawned.plants.len(), plants);
        assert!(world.get::<Camera>(spawned.camera).is_some());
        let instances = world.query::<&Instance>().iter(&world).count();
        assert_eq!(instances, plants + 1, "plants plus the terrain");
        assert_eq!(world.query::<&Shader>().iter(&world).count(), 11);
    }
}
