//! Ecosystem edits with undo and redo: insert a plant on the terrain, move one, delete
//! one. Each edit is an ECS operation ([`plant_at`], [`move_plant`], despawn) that the
//! next `rebuild_top_level` picks up; the history keeps what undoing it needs. An undone
//! delete spawns the plant again as a new entity, and the history follows it there. The
//! pixel operations (`select_at`, `insert_at`, …) are what a viewer's clicks and keys do:
//! they pick through the camera and keep the history and the selection in the world.

use crate::ecosystem::SwayFactors;
use crate::{LayerSpacing, SceneWind, SwayTuning, move_plant, plant_at};
use bevy_ecs::prelude::*;
use sylva_engine::components::{Instance, Layer, Transform};
use sylva_engine::geometry::{GeometryId, GeometryLibrary};
use sylva_engine::sway::{AnimationClock, RestPose, Sway, Wind};
use sylva_systems::picking::{Selected, pick};

/// A plant as a delete found it: what respawning it needs.
#[derive(Clone, Copy, Debug, PartialEq)]
struct PlantSnapshot {
    transform: Transform,
    instance: Instance,
    layer: Option<Layer>,
}

impl PlantSnapshot {
    fn of(world: &World, plant: Entity) -> Option<Self> {
        Some(Self {
            transform: *world.get::<Transform>(plant)?,
            instance: *world.get::<Instance>(plant)?,
            layer: world.get::<Layer>(plant).copied(),
        })
    }

    fn spawn(&self, world: &mut World) -> Entity {
        let mut entity = world.spawn((self.transform, self.instance));
        if let Some(layer) = self.layer {
            entity.insert(layer);
        }
        entity.id()
    }
}

/// One edit, with what undoing it needs.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Edit {
    Insert {
        plant: Entity,
        snapshot: PlantSnapshot,
    },
    Move {
        plant: Entity,
        from: Transform,
        to: Transform,
    },
    Delete {
        plant: Entity,
        snapshot: PlantSnapshot,
    },
}

impl Edit {
    fn plant(&self) -> Entity {
        match *self {
            Edit::Insert { plant, .. } | Edit::Move { plant, .. } | Edit::Delete { plant, .. } => {
                plant
            }
        }
    }

    fn with_plant(self, new: Entity) -> Self {
        match self {
            Edit::Insert { snapshot, .. } => Edit::Insert {
                plant: new,
                snapshot,
            },
            Edit::Move { from, to, .. } => Edit::Move {
                plant: new,
                from,
                to,
            },
            Edit::Delete { snapshot, .. } => Edit::Delete {
                plant: new,
                snapshot,
            },
        }
    }
}

/// The edits made to a world's plants, for undo and redo.
#[derive(Resource, Clone, Debug, Default)]
pub struct EditHistory {
    done: Vec<Edit>,
    undone: Vec<Edit>,
}

impl EditHistory {
    /// Plants a `species` plant on the terrain at `(x, z)` (see [`plant_at`]).
    pub fn insert(
        &mut self,
        world: &mut World,
        species: GeometryId,
        layer: Option<u32>,
        (x, z): (f32, f32),
        yaw: f32,
        scale: f32,
    ) -> Entity {
        let plant = plant_at(world, species, x, z, yaw, scale);
        if let Some(layer) = layer {
            world.entity_mut(plant).insert(Layer(layer));
        }
        let snapshot = PlantSnapshot::of(world, plant).expect("the plant was just spawned");
        self.record(Edit::Insert { plant, snapshot });
        plant
    }

    /// Moves `plant` to stand on the terrain at `(x, z)` (the ground height from
    /// [`move_plant`]), keeping its orientation and size; false when it is not a plant.
    pub fn move_to(&mut self, world: &mut World, plant: Entity, (x, z): (f32, f32)) -> bool {
        let Some(from) = world.get::<Transform>(plant).copied() else {
            return false;
        };
        if !move_plant(world, plant, x, z, 0.0, 1.0) {
            return false;
        }
        let mut transform = world
            .get_mut::<Transform>(plant)
            .expect("moved plants have transforms");
        transform.rotation = from.rotation;
        transform.scale = from.scale;
        let to = *transform;
        place(world, plant, to);
        self.record(Edit::Move { plant, from, to });
        true
    }

    /// Despawns `plant`; false when it is not a plant.
    pub fn delete(&mut self, world: &mut World, plant: Entity) -> bool {
        let Some(snapshot) = PlantSnapshot::of(world, plant) else {
            return false;
        };
        world.despawn(plant);
        self.record(Edit::Delete { plant, snapshot });
        true
    }

    /// Takes back the latest edit; false when there is none.
    pub fn undo(&mut self, world: &mut World) -> bool {
        let Some(edit) = self.done.pop() else {
            return false;
        };
        let edit = match edit {
            Edit::Insert { plant, .. } => {
                world.despawn(plant);
                edit
            }
            Edit::Move { plant, from, .. } => {
                place(world, plant, from);
                edit
            }
            Edit::Delete { plant, snapshot } => {
                let again = snapshot.spawn(world);
                self.follow(plant, again);
                edit.with_plant(again)
            }
        };
        self.undone.push(edit);
        true
    }

    /// Makes the latest undone edit again; false when there is none.
    pub fn redo(&mut self, world: &mut World) -> bool {
        let Some(edit) = self.undone.pop() else {
            return false;
        };
        let edit = match edit {
            Edit::Insert { plant, snapshot } => {
                let again = snapshot.spawn(world);
                self.follow(plant, again);
                edit.with_plant(again)
            }
            Edit::Move { plant, to, .. } => {
                place(world, plant, to);
                edit
            }
            Edit::Delete { plant, .. } => {
                world.despawn(plant);
                edit
            }
        };
        self.done.push(edit);
        true
    }

    /// Edits that [`undo`](Self::undo) can take back.
    pub fn undoable(&self) -> usize {
        self.done.len()
    }

    /// A new edit: it ends the redo chain.
    fn record(&mut self, edit: Edit) {
        self.done.push(edit);
        self.undone.clear();
    }

    /// Points every recorded edit of `old` at `new` (a plant spawned again).
    fn follow(&mut self, old: Entity, new: Entity) {
        for edit in self.done.iter_mut().chain(self.undone.iter_mut()) {
            if edit.plant() == old {
                *edit = edit.with_plant(new);
            }
        }
    }
}

/// Selects the plant `camera` sees at pixel `(x, y)` (nothing for the sky or the
/// terrain: plants are the entities with a [`Layer`]); returns it.
pub fn select_at(world: &mut World, camera: Entity, (x, y): (u32, u32)) -> Option<Entity> {
    let plant = pick(world, camera, x, y)
        .map(|p| p.entity)
        .filter(|&e| world.get::<Layer>(e).is_some());
    world.insert_resource(Selected(plant));
    plant
}

/// Deletes the selected plant (through the world's [`EditHistory`]); false when none is
/// selected.
pub fn delete_selected(world: &mut World) -> bool {
    let Some(plant) = world.get_resource::<Selected>().and_then(|s| s.0) else {
        return false;
    };
    world.insert_resource(Selected(None));
    with_history(world, |history, world| history.delete(world, plant))
}

/// Plants one of the selected plant's species and layer (or of the first plant's) where
/// pixel `(x, y)` meets the scene, upright, unturned, at the template's size; returns it.
pub fn insert_at(world: &mut World, camera: Entity, (x, y): (u32, u32)) -> Option<Entity> {
    let point = pick(world, camera, x, y)?.point;
    insert_at_ground(world, (point.x, point.z))
}

/// Plants one of the selected plant's species and layer (or of the first plant's) on
/// the terrain at `(x, z)`, upright, unturned, at the template's size; returns it. The
/// layer's spacing rule holds: nothing is planted closer than [`LayerSpacing`] to a
/// plant of the same layer (`None`, and no edit), so repeated inserts along a path (the
/// viewer's brush) space themselves.
pub fn insert_at_ground(world: &mut World, (x, z): (f32, f32)) -> Option<Entity> {
    let selected = world.get_resource::<Selected>().and_then(|s| s.0);
    let template = selected
        .filter(|&e| world.get::<Instance>(e).is_some())
        .or_else(|| {
            world
                .query_filtered::<Entity, (With<Instance>, With<Layer>)>()
                .iter(world)
                .next()
        })?;
    let species = world.get::<Instance>(template)?.geometry;
    let layer = world.get::<Layer>(template).map(|l| l.0);
    let scale = world.get::<Transform>(template).map_or(1.0, |t| t.scale.y);
    if let Some(layer) = layer
        && crowds_its_layer(world, layer, glam::Vec2::new(x, z))
    {
        return None;
    }
    let plant = with_history(world, |history, world| {
        history.insert(world, species, layer, (x, z), 0.0, scale)
    });
    world.insert_resource(Selected(Some(plant)));
    Some(plant)
}

/// True when a plant of `layer` stands closer to ground position `at` than the layer's
/// spacing.
fn crowds_its_layer(world: &mut World, layer: u32, at: glam::Vec2) -> bool {
    let spacing = world
        .get_resource::<LayerSpacing>()
        .and_then(|s| s.0.get(layer as usize).copied())
        .unwrap_or(0.0);
    spacing > 0.0
        && world
            .query::<(&Transform, &Layer)>()
            .iter(world)
            .any(|(t, l)| {
                l.0 == layer
                    && glam::Vec2::new(t.translation.x, t.translation.z).distance(at) < spacing
            })
}

/// Moves the selected plant to where pixel `(x, y)` meets the scene; false when none is
/// selected or the pixel shows the sky.
pub fn move_selected_to(world: &mut World, camera: Entity, (x, y): (u32, u32)) -> bool {
    pick(world, camera, x, y)
        .is_some_and(|p| move_selected_to_ground(world, (p.point.x, p.point.z)))
}

/// Moves the selected plant onto the terrain at `(x, z)`; false when none is selected.
pub fn move_selected_to_ground(world: &mut World, (x, z): (f32, f32)) -> bool {
    let Some(plant) = world.get_resource::<Selected>().and_then(|s| s.0) else {
        return false;
    };
    with_history(world, |history, world| {
        history.move_to(world, plant, (x, z))
    })
}

/// Selects the plant whose stem stands nearest to ground position `(x, z)` among those
/// whose crown covers it (ties to the first in entity order), or nothing; returns it.
/// What a click on the map does, as a script replays it.
pub fn select_at_ground(world: &mut World, (x, z): (f32, f32)) -> Option<Entity> {
    let at = glam::Vec2::new(x, z);
    let nearest = sylva_systems::picking::map_plants(world)
        .into_iter()
        .map(|plant| (plant.position.distance(at), plant))
        .filter(|(distance, plant)| *distance <= plant.radius)
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, plant)| plant.entity);
    select(world, nearest)
}

/// Selects `plant` when it is a plant (an entity with a [`Layer`]), or nothing.
pub fn select(world: &mut World, plant: Option<Entity>) -> Option<Entity> {
    let plant = plant.filter(|&e| world.get::<Layer>(e).is_some());
    world.insert_resource(Selected(plant));
    plant
}

/// Takes back the latest edit of the world's [`EditHistory`].
pub fn undo(world: &mut World) -> bool {
    world.insert_resource(Selected(None));
    with_history(world, |history, world| history.undo(world))
}

/// Makes the latest undone edit of the world's [`EditHistory`] again.
pub fn redo(world: &mut World) -> bool {
    world.insert_resource(Selected(None));
    with_history(world, |history, world| history.redo(world))
}

/// Turns the wind on (the default [`Wind`], every plant swaying from its current pose
/// with spring parameters from its height, the animation advancing `frame_seconds` of
/// simulated time per frame) or off (every swaying plant back at its rest pose,
/// exactly); returns whether the wind is now on.
pub fn set_wind(world: &mut World, on: bool, frame_seconds: f64) -> bool {
    if on {
        world
            .get_resource_or_insert_with(AnimationClock::default)
            .frame_seconds = frame_seconds;
        let plants: Vec<(Entity, GeometryId, Layer, f32)> = world
            .query_filtered::<(Entity, &Instance, &Layer, &Transform), Without<Sway>>()
            .iter(world)
            .map(|(e, i, l, t)| (e, i.geometry, *l, t.scale.y))
            .collect();
        let library = world.get_resource::<GeometryLibrary>();
        let tuning = world.get_resource::<SwayTuning>();
        let springs: Vec<(Entity, f32, SwayFactors)> = plants
            .into_iter()
            .map(|(e, geometry, layer, scale)| {
                let top = library
                    .and_then(|l| l.get(geometry))
                    .map_or(1.0, |g| g.bounds().max.y);
                let factors = tuning
                    .and_then(|t| t.0.get(&(layer.0, geometry)).copied())
                    .unwrap_or_default();
                (e, (top * scale).clamp(0.05, 100.0), factors)
            })
            .collect();
        for (plant, height, factors) in springs {
            let rest = *world
                .get::<Transform>(plant)
                .expect("queried with a transform");
            world
                .entity_mut(plant)
                .insert((sway_for_height(height, factors), RestPose(rest)));
        }
        let wind = world
            .get_resource::<SceneWind>()
            .map_or_else(Wind::default, |w| w.0);
        world.insert_resource(wind);
    } else {
        world.remove_resource::<Wind>();
        let swaying: Vec<(Entity, Transform)> = world
            .query::<(Entity, &RestPose)>()
            .iter(world)
            .map(|(e, r)| (e, r.0))
            .collect();
        for (plant, rest) in swaying {
            let mut entity = world.entity_mut(plant);
            entity.insert(rest);
            entity.remove::<(Sway, RestPose)>();
        }
    }
    on
}

/// Spring parameters for a plant `height` metres tall: inertia grows with the cube of
/// the height and stiffness with its square, so grass sways at about 1 Hz and a 15 m
/// tree at about 0.2 Hz; damping at a tenth of critical; wind torque from a drag area
/// growing with the square of the height.
fn sway_for_height(height: f32, factors: SwayFactors) -> Sway {
    let h = f64::from(height);
    let (stiffness, inertia) = (40.0 * h * h, 2.0 * h * h * h);
    let damping = 0.2 * (stiffness * inertia).sqrt();
    Sway::new(
        stiffness * f64::from(factors.stiffness),
        damping * f64::from(factors.damping),
        inertia * f64::from(factors.inertia),
        0.05 * h * h,
    )
    .expect("positive finite parameters for a height in 0.05 ..= 100 m and factors in 0.01 ..= 100")
}

/// Simulated seconds of wind per rendered frame: about real time at the interactive
/// frame rates of the larger scenes.
pub const WIND_FRAME_SECONDS: f64 = 0.1;

/// One of the viewer's editing operations as data: what a click, key or script step
/// asks for, applied to a world by [`apply`](Self::apply) and carried as bytes
/// ([`to_bytes`](Self::to_bytes)) to the other ranks of a cluster, which apply it alike.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum EditorAction {
    /// Select the plant seen at a pixel.
    Select(u32, u32),
    /// Plant where a pixel meets the scene.
    Insert(u32, u32),
    /// Move the selection to where a pixel meets the scene.
    Move(u32, u32),
    /// Delete the selection.
    Delete,
    /// Take back the latest edit.
    Undo,
    /// Make the latest undone edit again.
    Redo,
    /// Wind on or off.
    Wind(bool),
    /// Select this plant (from the map).
    SelectPlant(Entity),
    /// Select the plant whose crown covers a ground position (x, z) (a script's map
    /// click).
    SelectAtGround(f32, f32),
    /// Plant at a ground position (x, z) (from the map).
    InsertAtGround(f32, f32),
    /// Move the selection to a ground position (x, z) (from the map).
    MoveToGround(f32, f32),
}

impl EditorAction {
    /// Does it to `world`, whose pixels are `camera`'s.
    pub fn apply(self, world: &mut World, camera: Entity) {
        match self {
            EditorAction::Select(x, y) => {
                select_at(world, camera, (x, y));
            }
            EditorAction::SelectPlant(plant) => {
                select(world, Some(plant));
            }
            EditorAction::SelectAtGround(x, z) => {
                select_at_ground(world, (x, z));
            }
            EditorAction::InsertAtGround(x, z) => {
                insert_at_ground(world, (x, z));
            }
            EditorAction::MoveToGround(x, z) => {
                move_selected_to_ground(world, (x, z));
            }
            EditorAction::Insert(x, y) => {
                insert_at(world, camera, (x, y));
            }
            EditorAction::Move(x, y) => {
                move_selected_to(world, camera, (x, y));
            }
            EditorAction::Delete => {
                delete_selected(world);
            }
            EditorAction::Undo => {
                undo(world);
            }
            EditorAction::Redo => {
                redo(world);
            }
            EditorAction::Wind(on) => {
                set_wind(world, on, WIND_FRAME_SECONDS);
            }
        }
    }

    /// Its bytes: a kind byte, then its numbers little-endian (floats by their bits).
    pub fn to_bytes(self) -> Vec<u8> {
        let pair = |kind: u8, a: u32, b: u32| {
            let mut bytes = vec![kind];
            bytes.extend(a.to_le_bytes());
            bytes.extend(b.to_le_bytes());
            bytes
        };
        match self {
            EditorAction::Select(x, y) => pair(0, x, y),
            EditorAction::Insert(x, y) => pair(1, x, y),
            EditorAction::Move(x, y) => pair(2, x, y),
            EditorAction::Delete => vec![3],
            EditorAction::Undo => vec![4],
            EditorAction::Redo => vec![5],
            EditorAction::Wind(on) => vec![6, u8::from(on)],
            EditorAction::SelectPlant(plant) => std::iter::once(7)
                .chain(plant.to_bits().to_le_bytes())
                .collect(),
            EditorAction::SelectAtGround(x, z) => pair(8, x.to_bits(), z.to_bits()),
            EditorAction::InsertAtGround(x, z) => pair(9, x.to_bits(), z.to_bits()),
            EditorAction::MoveToGround(x, z) => pair(10, x.to_bits(), z.to_bits()),
        }
    }

    /// Reads [`to_bytes`](Self::to_bytes)' output; an error says what is wrong.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, String> {
        let malformed = || format!("an editor action of {} bytes cannot be read", bytes.len());
        let (&kind, rest) = bytes.split_first().ok_or_else(malformed)?;
        let pair = || match *rest {
            [a0, a1, a2, a3, b0, b1, b2, b3] => Ok((
                u32::from_le_bytes([a0, a1, a2, a3]),
                u32::from_le_bytes([b0, b1, b2, b3]),
            )),
            _ => Err(malformed()),
        };
        let ground = || pair().map(|(x, z)| (f32::from_bits(x), f32::from_bits(z)));
        let nothing = |action: EditorAction| match rest {
            [] => Ok(action),
            _ => Err(malformed()),
        };
        match kind {
            0 => pair().map(|(x, y)| EditorAction::Select(x, y)),
            1 => pair().map(|(x, y)| EditorAction::Insert(x, y)),
            2 => pair().map(|(x, y)| EditorAction::Move(x, y)),
            3 => nothing(EditorAction::Delete),
            4 => nothing(EditorAction::Undo),
            5 => nothing(EditorAction::Redo),
            6 => match rest {
                [on @ (0 | 1)] => Ok(EditorAction::Wind(*on == 1)),
                _ => Err(malformed()),
            },
            7 => {
                let bits: [u8; 8] = rest.try_into().map_err(|_| malformed())?;
                Entity::try_from_bits(u64::from_le_bytes(bits))
                    .map(EditorAction::SelectPlant)
                    .ok_or_else(malformed)
            }
            8 => ground().map(|(x, z)| EditorAction::SelectAtGround(x, z)),
            9 => ground().map(|(x, z)| EditorAction::InsertAtGround(x, z)),
            10 => ground().map(|(x, z)| EditorAction::MoveToGround(x, z)),
            _ => Err(format!("an editor action of unknown kind {kind}")),
        }
    }
}

/// Where a scene came from: what a saved ecosystem starts from.
#[derive(Clone, Debug, PartialEq)]
pub enum SceneSource {
    /// A built-in preset, by name.
    Preset(String),
    /// A TOML scene file.
    File(std::path::PathBuf),
}

/// Why an ecosystem could not be saved.
#[derive(Debug, thiserror::Error)]
pub enum SaveError {
    /// The source scene file could not be read or parsed again.
    #[error("{}: {reason}", path.display())]
    Source {
        /// The scene file.
        path: std::path::PathBuf,
        /// What went wrong.
        reason: String,
    },
    /// The seed does not fit a TOML integer.
    #[error("seed {0} is larger than a scene file can hold ({max})", max = i64::MAX)]
    Seed(u64),
    /// Writing failed (the file at the path is as it was).
    #[error("{}: could not save the scene: {reason}", path.display())]
    Write {
        /// The path given.
        path: std::path::PathBuf,
        /// What went wrong.
        reason: String,
    },
}

/// Saves the world's ecosystem as a scene file at `path`: the source's settings (a
/// preset by name, or the source file's tables with relative glTF paths made absolute)
/// with `seed` and every plant as a `[[plant]]` table (species, layer, exact transform),
/// so `--scene path` builds the same terrain, species and plants. The write is atomic.
/// Returns the number of plants saved.
pub fn save_ecosystem(
    world: &mut World,
    source: &SceneSource,
    seed: u64,
    path: &std::path::Path,
) -> Result<usize, SaveError> {
    use toml::{Table, Value};
    let mut table = match source {
        SceneSource::Preset(name) => {
            let mut t = Table::new();
            t.insert("preset".into(), Value::String(name.clone()));
            t
        }
        SceneSource::File(file) => {
            let fail = |reason: String| SaveError::Source {
                path: file.clone(),
                reason,
            };
            let text = std::fs::read_to_string(file).map_err(|e| fail(e.to_string()))?;
            let mut t: Table = toml::from_str(&text).map_err(|e| fail(e.to_string()))?;
            absolute_gltf_paths(&mut t, file.parent().unwrap_or(std::path::Path::new(".")));
            t
        }
    };
    table.remove("plant");
    let seed_value = i64::try_from(seed).map_err(|_| SaveError::Seed(seed))?;
    table.insert("seed".into(), Value::Integer(seed_value));
    let names: Vec<String> = world
        .get_resource::<GeometryLibrary>()
        .map(|l| l.geometries.iter().map(|g| g.name.clone()).collect())
        .unwrap_or_default();
    let mut plants: Vec<(u32, Layer, Transform)> = world
        .query::<(&Instance, &Layer, &Transform)>()
        .iter(world)
        .map(|(i, l, t)| (i.geometry.0, *l, *t))
        .collect();
    plants.sort_by_key(|p| (p.1.0, p.0));
    let floats = |v: &[f32]| Value::Array(v.iter().map(|&x| Value::Float(f64::from(x))).collect());
    let list: Vec<Value> = plants
        .iter()
        .map(|(geometry, layer, t)| {
            let mut p = Table::new();
            let name = names.get(*geometry as usize).cloned().unwrap_or_default();
            p.insert("species".into(), Value::String(name));
            p.insert("layer".into(), Value::Integer(i64::from(layer.0)));
            p.insert("translation".into(), floats(&t.translation.to_array()));
            p.insert("rotation".into(), floats(&t.rotation.to_array()));
            p.insert("scale".into(), floats(&t.scale.to_array()));
            Value::Table(p)
        })
        .collect();
    let count = list.len();
    table.insert("plant".into(), Value::Array(list));
    let text = toml::to_string(&table).map_err(|e| SaveError::Write {
        path: path.to_path_buf(),
        reason: e.to_string(),
    })?;
    sylva_engine::film::write_atomically(path, |tmp| {
        std::fs::write(
            tmp,
            format!(
                "# Saved by sylva view: the ecosystem with every plant where it stands.\n{text}"
            ),
        )
        .map_err(|e| e.to_string())
    })
    .map_err(|e| SaveError::Write {
        path: path.to_path_buf(),
        reason: match e {
            sylva_engine::film::OutputError::Write { reason, .. } => reason,
            other => other.to_string(),
        },
    })?;
    Ok(count)
}

/// Makes every relative `layer[*].species[*].gltf` path absolute against `dir`, so a saved
/// copy of a scene file finds the models from anywhere.
fn absolute_gltf_paths(table: &mut toml::Table, dir: &std::path::Path) {
    let Some(toml::Value::Array(layers)) = table.get_mut("layer") else {
        return;
    };
    for layer in layers {
        let Some(toml::Value::Array(species)) = layer.get_mut("species") else {
            continue;
        };
        for s in species {
            if let Some(toml::Value::String(path)) = s.get_mut("gltf")
                && std::path::Path::new(path.as_str()).is_relative()
            {
                *path = dir.join(path.as_str()).to_string_lossy().into_owned();
            }
        }
    }
}

/// Puts `plant` at `transform`, and its rest pose there too when it sways (the wind
/// would otherwise pull it back).
fn place(world: &mut World, plant: Entity, transform: Transform) {
    if let Some(mut current) = world.get_mut::<Transform>(plant) {
        *current = transform;
    }
    if let Some(mut rest) = world.get_mut::<RestPose>(plant) {
        rest.0 = transform;
    }
}

/// Runs `edit` with the world's history (created when missing) taken out of the world.
fn with_history<R>(world: &mut World, edit: impl FnOnce(&mut EditHistory, &mut World) -> R) -> R {
    let mut history = world.remove_resource::<EditHistory>().unwrap_or_default();
    let result = edit(&mut history, world);
    world.insert_resource(history);
    result
}

#[cfg(test)]
mod tests;
