//! TOML scene files: name a preset and override parts of it, or describe an ecosystem
//! from scratch (terrain, layers with species, sun, sky, camera). Unknown keys are
//! errors; every error names the file, the line and column, and the key.
//!
//! ```toml
//! preset = "meadow"        # optional starting point
//! seed = 7                 # optional (the CLI's --seed otherwise)
//!
//! [terrain]
//! size = 150.0             # metres
//! cells = 300              # per edge, two triangles each (≤ 2048)
//! amplitude = 6.0
//! wavelength = 60.0
//! octaves = 6
//! noise = "ridged"         # or "fbm"
//!
//! [[layer]]                # layers given here replace the preset's
//! name = "grass"
//! count = 2000
//! scale = [0.8, 1.2]
//! min_spacing = 0.5        # optional
//! clustering = 0.3         # 0 … 1
//! region = [-40, -40, 40, 40]
//! sway = { stiffness = 2.0, damping = 1.5, inertia = 1.0 }  # optional factors on the
//!                          # spring each plant's height gives (also per species)
//!
//! [[layer.species]]
//! name = "tall grass"
//! kind = "grass"           # grass, herb, low_shrub, high_shrub, low_tree, high_tree, large_tree
//! height = 0.6
//! triangles = 1000
//! leaf = "blades"          # optional: blades, ellipse, lanceolate, lobed, compound, needles
//! leaf_color = [0.3, 0.5, 0.15]   # optional, sRGB
//! seed = 3                 # optional
//! weight = 2.0             # optional
//!
//! [[layer.species]]
//! name = "imported tree"
//! gltf = "models/tree.glb" # relative to this file
//!
//! [sun]
//! elevation = 40.0         # degrees
//! azimuth = -50.0
//! irradiance = [3.2, 3.0, 2.7]
//!
//! [wind]                   # optional: what the wind blows when it is on
//! speed = 6.0              # m/s, 0 … 60
//! direction = 90.0         # degrees from +Z towards +X it blows toward (default 90: +X)
//! gustiness = 0.5          # optional: gusts as a fraction of the speed, 0 … 2
//! gust_frequency = 0.3     # optional, Hz
//! gust_wavelength = 25.0   # optional, metres between gust fronts
//! turbulence = 0.4         # optional: gusts varying across the wind too, 0 … 2
//! seed = 3                 # optional: the turbulence's pattern
//!
//! [sky]                    # the Preetham daylight model for the sun above …
//! turbidity = 3.0
//! # … or a gradient: zenith = [0.22, 0.42, 0.95], horizon = [0.75, 0.85, 1.0],
//! # ground = [0.12, 0.11, 0.08]
//!
//! [camera]
//! eye = [0.0, 45.0]        # x, z; the height is above the ground
//! eye_height = 1.7
//! target = [0.0, 0.0]
//! target_height = 2.0
//! fov = 55.0
//! path_interpolation = "catmull_rom"   # optional, or "linear": how the path runs
//!
//! [[camera.path]]          # optional key frames of a flight for `sylva animate`
//! time = 0.0               # seconds, increasing from key to key
//! eye = [0.0, 45.0]        # as [camera]; eye_height, target_height, fov default to its
//! target = [0.0, 0.0]      # or rotation = [x, y, z, w] (a unit quaternion)
//!
//! [[plant]]                # optional: every plant where it stands (what `sylva view`
//! species = "tall grass"   # saves); the layers then give only the species
//! layer = 0                # index into the layers
//! translation = [1.5, 0.2, -3.0]
//! rotation = [0.0, 0.38, 0.0, 0.92]   # unit quaternion x, y, z, w
//! scale = [1.1, 1.1, 1.1]
//! ```

use crate::ecosystem::{
    CameraAim, CameraKeySpec, CameraPathSpec, CameraSpec, EcosystemSpec, LayerSpec, PRESETS,
    PlacedPlant, SkySpec, SpeciesSource, SpeciesSpec, SunSpec, SwaySpec,
};
use crate::species::{LeafShape, PlantKind};
use glam::{Vec2, Vec3};
use serde::Deserialize;
use std::ops::Range;
use std::path::{Path, PathBuf};
use sylva_engine::camera_path::PathInterpolation;
use sylva_engine::components::Transform;
use sylva_engine::light::SkyLight;
use sylva_engine::shading::srgb_to_linear;
use toml::Spanned;

/// Why a scene file was refused.
#[derive(Debug, thiserror::Error)]
#[error("{}{}: {}{message}", path.display(), location.map(|(l, c)| format!(":{l}:{c}")).unwrap_or_default(), key.as_deref().map(|k| format!("{k}: ")).unwrap_or_default())]
pub struct SceneFileError {
    /// The file.
    pub path: PathBuf,
    /// 1-based line and column, when known.
    pub location: Option<(usize, usize)>,
    /// The key, as a dotted path (`layer[1].species[0].kind`).
    pub key: Option<String>,
    /// What is wrong.
    pub message: String,
}

/// A parsed scene file.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneFile {
    /// The ecosystem it describes.
    pub spec: EcosystemSpec,
    /// Its seed, when it gives one.
    pub seed: Option<u64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Document {
    preset: Option<Spanned<String>>,
    name: Option<String>,
    seed: Option<u64>,
    clear_radius: Option<Spanned<f32>>,
    terrain: Option<TerrainDoc>,
    layer: Option<Vec<LayerDoc>>,
    sun: Option<SunDoc>,
    sky: Option<SkyDoc>,
    camera: Option<CameraDoc>,
    plant: Option<Vec<Spanned<PlantDoc>>>,
    wind: Option<WindDoc>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct WindDoc {
    speed: Spanned<f32>,
    direction: Option<Spanned<f32>>,
    gustiness: Option<Spanned<f32>>,
    gust_frequency: Option<Spanned<f32>>,
    gust_wavelength: Option<Spanned<f32>>,
    turbulence: Option<Spanned<f32>>,
    seed: Option<u64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PlantDoc {
    species: String,
    layer: u32,
    translation: [f32; 3],
    rotation: [f32; 4],
    scale: [f32; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TerrainDoc {
    size: Option<Spanned<f32>>,
    cells: Option<Spanned<u32>>,
    amplitude: Option<Spanned<f32>>,
    wavelength: Option<Spanned<f32>>,
    octaves: Option<Spanned<u32>>,
    noise: Option<Spanned<String>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct LayerDoc {
    name: String,
    count: Spanned<u32>,
    scale: Option<Spanned<[f32; 2]>>,
    min_spacing: Option<Spanned<f32>>,
    clustering: Option<Spanned<f32>>,
    region: Option<Spanned<[f32; 4]>>,
    sway: Option<SwayDoc>,
    species: Spanned<Vec<SpeciesDoc>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SwayDoc {
    stiffness: Option<Spanned<f32>>,
    damping: Option<Spanned<f32>>,
    inertia: Option<Spanned<f32>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SpeciesDoc {
    name: Spanned<String>,
    kind: Option<Spanned<String>>,
    height: Option<Spanned<f32>>,
    triangles: Option<Spanned<u32>>,
    leaf: Option<Spanned<String>>,
    leaf_color: Option<Spanned<[f32; 3]>>,
    seed: Option<u64>,
    weight: Option<Spanned<f32>>,
    gltf: Option<Spanned<String>>,
    sway: Option<SwayDoc>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SunDoc {
    elevation: Spanned<f32>,
    azimuth: Spanned<f32>,
    irradiance: Option<Spanned<[f32; 3]>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SkyDoc {
    turbidity: Option<Spanned<f32>>,
    zenith: Option<Spanned<[f32; 3]>>,
    horizon: Option<Spanned<[f32; 3]>>,
    ground: Option<Spanned<[f32; 3]>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CameraDoc {
    eye: Option<[f32; 2]>,
    eye_height: Option<Spanned<f32>>,
    target: Option<[f32; 2]>,
    target_height: Option<Spanned<f32>>,
    fov: Option<Spanned<f32>>,
    path: Option<Vec<Spanned<CameraKeyDoc>>>,
    path_interpolation: Option<Spanned<String>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CameraKeyDoc {
    time: Spanned<f64>,
    eye: [f32; 2],
    eye_height: Option<Spanned<f32>>,
    target: Option<[f32; 2]>,
    target_height: Option<Spanned<f32>>,
    rotation: Option<[f32; 4]>,
    fov: Option<Spanned<f32>>,
}

/// Turns byte spans into line/column and builds errors.
struct Context<'a> {
    path: &'a Path,
    text: &'a str,
}

impl Context<'_> {
    fn location(&self, span: Range<usize>) -> (usize, usize) {
        let before = &self.text[..span.start.min(self.text.len())];
        let line = before.matches('\n').count() + 1;
        let column = before.len() - before.rfind('\n').map_or(0, |i| i + 1) + 1;
        (line, column)
    }

    /// The dotted key assigned on the line holding byte `at` (`terrain.cells`), from the
    /// line itself and the nearest table header above it.
    fn key_at(&self, at: usize) -> Option<String> {
        let before = &self.text[..at.min(self.text.len())];
        let line_start = before.rfind('\n').map_or(0, |i| i + 1);
        let line = self.text[line_start..].lines().next()?;
        let (key, _) = line.split_once('=')?;
        let key = key.trim();
        if key.is_empty()
            || !key
                .chars()
                .all(|c| c.is_alphanumeric() || "_.-".contains(c))
        {
            return None;
        }
        let table = before[..line_start]
            .lines()
            .rev()
            .map(str::trim)
            .find(|l| l.starts_with('['))
            .map(|l| l.trim_matches(|c| c == '[' || c == ']').trim().to_string());
        Some(match table {
            Some(t) => format!("{t}.{key}"),
            None => key.to_string(),
        })
    }

    fn error(&self, span: Option<Range<usize>>, key: &str, message: String) -> SceneFileError {
        SceneFileError {
            path: self.path.to_path_buf(),
            location: span.map(|s| self.location(s)),
            key: Some(key.to_string()),
            message,
        }
    }

    /// A number that must lie in `range` (inclusive) and be finite.
    fn check<T: Copy + PartialOrd + std::fmt::Display>(
        &self,
        value: &Spanned<T>,
        key: &str,
        low: T,
        high: T,
    ) -> Result<T, SceneFileError> {
        let v = *value.get_ref();
        // NaN fails both comparisons.
        if v >= low && v <= high {
            Ok(v)
        } else {
            Err(self.error(
                Some(value.span()),
                key,
                format!("{v} is out of range ({low} … {high})"),
            ))
        }
    }

    fn color(
        &self,
        value: &Spanned<[f32; 3]>,
        key: &str,
        high: f32,
    ) -> Result<Vec3, SceneFileError> {
        let c = *value.get_ref();
        if c.iter().all(|v| (0.0..=high).contains(v)) {
            Ok(Vec3::from(c))
        } else {
            Err(self.error(
                Some(value.span()),
                key,
                format!("{c:?}: every component must lie in 0 … {high}"),
            ))
        }
    }
}

impl SceneFile {
    /// Reads and validates a scene file; relative glTF paths resolve against its folder.
    pub fn load(path: &Path) -> Result<Self, SceneFileError> {
        let text = std::fs::read_to_string(path).map_err(|e| SceneFileError {
            path: path.to_path_buf(),
            location: None,
            key: None,
            message: format!("cannot read: {e}"),
        })?;
        Self::parse(&text, path)
    }

    /// Parses scene-file text; `path` names it in errors and anchors relative paths.
    pub fn parse(text: &str, path: &Path) -> Result<Self, SceneFileError> {
        let cx = Context { path, text };
        let doc: Document = toml::from_str(text).map_err(|e| SceneFileError {
            path: path.to_path_buf(),
            location: e.span().map(|s| cx.location(s)),
            key: e.span().and_then(|s| cx.key_at(s.start)),
            message: e.message().trim().to_string(),
        })?;
        let mut spec = match &doc.preset {
            Some(name) => EcosystemSpec::preset(name.get_ref()).ok_or_else(|| {
                cx.error(
                    Some(name.span()),
                    "preset",
                    format!(
                        "unknown preset '{}' (available: {})",
                        name.get_ref(),
                        PRESETS.join(", ")
                    ),
                )
            })?,
            None => {
                let mut empty = EcosystemSpec::meadow();
                empty.layers.clear();
                empty
            }
        };
        spec.name = doc.name.clone().unwrap_or_else(|| {
            path.file_stem()
                .map_or("scene".into(), |s| s.to_string_lossy().into_owned())
        });
        if let Some(r) = &doc.clear_radius {
            spec.clear_radius = cx.check(r, "clear_radius", 0.0, 1e4)?;
        }
        if let Some(t) = &doc.terrain {
            let p = &mut spec.terrain;
            if let Some(v) = &t.size {
                p.size = cx.check(v, "terrain.size", 1.0, 1e5)?;
            }
            if let Some(v) = &t.cells {
                p.cells = cx.check(v, "terrain.cells", 1, 2048)?;
            }
            if let Some(v) = &t.amplitude {
                p.amplitude = cx.check(v, "terrain.amplitude", 0.0, 1e4)?;
            }
            if let Some(v) = &t.wavelength {
                p.wavelength = cx.check(v, "terrain.wavelength", 0.01, 1e6)?;
            }
            if let Some(v) = &t.octaves {
                p.octaves = cx.check(v, "terrain.octaves", 1, 16)?;
            }
            if let Some(v) = &t.noise {
                p.ridged = match v.get_ref().as_str() {
                    "fbm" => false,
                    "ridged" => true,
                    other => {
                        return Err(cx.error(
                            Some(v.span()),
                            "terrain.noise",
                            format!("unknown noise '{other}' (expected fbm or ridged)"),
                        ));
                    }
                };
            }
        }
        if let Some(layers) = &doc.layer {
            spec.layers = layers
                .iter()
                .enumerate()
                .map(|(i, l)| layer(&cx, l, i))
                .collect::<Result<_, _>>()?;
        }
        if let Some(s) = &doc.sun {
            spec.sun = Some(SunSpec {
                elevation: cx.check(&s.elevation, "sun.elevation", -90.0, 90.0)?,
                azimuth: cx.check(&s.azimuth, "sun.azimuth", -360.0, 360.0)?,
                irradiance: match &s.irradiance {
                    Some(v) => cx.color(v, "sun.irradiance", 1e6)?,
                    None => Vec3::new(3.2, 3.0, 2.7),
                },
            });
        }
        if let Some(w) = &doc.wind {
            let calm = sylva_engine::sway::Wind::default();
            let direction = match &w.direction {
                Some(d) => cx.check(d, "wind.direction", -360.0, 360.0)?.to_radians(),
                None => 90f32.to_radians(),
            };
            let optional = |value: &Option<Spanned<f32>>, key, low, high, default| match value {
                Some(v) => cx.check(v, key, low, high),
                None => Ok(default),
            };
            spec.wind = Some(sylva_engine::sway::Wind {
                direction: glam::Vec2::new(direction.sin(), direction.cos()),
                speed: cx.check(&w.speed, "wind.speed", 0.0, 60.0)?,
                gustiness: optional(&w.gustiness, "wind.gustiness", 0.0, 2.0, calm.gustiness)?,
                gust_frequency: optional(
                    &w.gust_frequency,
                    "wind.gust_frequency",
                    0.001,
                    20.0,
                    calm.gust_frequency,
                )?,
                gust_wavelength: optional(
                    &w.gust_wavelength,
                    "wind.gust_wavelength",
                    0.1,
                    10_000.0,
                    calm.gust_wavelength,
                )?,
                strength: 1.0,
                turbulence: optional(&w.turbulence, "wind.turbulence", 0.0, 2.0, 0.0)?,
                seed: w.seed.unwrap_or(0),
            });
        }
        if let Some(s) = &doc.sky {
            spec.sky = Some(match (&s.turbidity, &s.zenith, &s.horizon, &s.ground) {
                (Some(t), None, None, None) => SkySpec::Preetham {
                    turbidity: cx.check(t, "sky.turbidity", 1.7, 10.0)?,
                },
                (None, Some(zenith), Some(horizon), Some(ground)) => SkySpec::Gradient(SkyLight {
                    zenith: cx.color(zenith, "sky.zenith", 1e6)?,
                    horizon: cx.color(horizon, "sky.horizon", 1e6)?,
                    ground: cx.color(ground, "sky.ground", 1e6)?,
                }),
                _ => {
                    return Err(cx.error(
                        None,
                        "sky",
                        "give either `turbidity` (the Preetham sky) or all of `zenith`, `horizon` and `ground` (a gradient)".into(),
                    ));
                }
            });
        }
        if let Some(c) = &doc.camera {
            let finite = |v: [f32; 2], key: &str| {
                if v.iter().all(|x| x.is_finite()) {
                    Ok(Vec2::from(v))
                } else {
                    Err(cx.error(None, key, format!("{v:?} is not finite")))
                }
            };
            let height = |v: &Option<Spanned<f32>>, key: &str, default: f32| match v {
                Some(v) => cx.check(v, key, -1e4, 1e5),
                None => Ok(default),
            };
            let fov = |v: &Option<Spanned<f32>>, key: &str, default: f32| match v {
                Some(v) => cx.check(v, key, 1.0, 170.0),
                None => Ok(default),
            };
            let eye_height = height(&c.eye_height, "camera.eye_height", 1.7)?;
            let target_height = height(&c.target_height, "camera.target_height", 1.7)?;
            let camera_fov = fov(&c.fov, "camera.fov", 55.0)?;
            let path = match &c.path {
                Some(keys) => Some(camera_path(
                    &cx,
                    keys,
                    &c.path_interpolation,
                    (eye_height, target_height, camera_fov),
                )?),
                None => {
                    if let Some(i) = &c.path_interpolation {
                        return Err(cx.error(
                            Some(i.span()),
                            "camera.path_interpolation",
                            "there is no [[camera.path]] to interpolate".into(),
                        ));
                    }
                    None
                }
            };
            // Without its own eye and target, the still camera is the path's first key.
            let first_target = path.as_ref().and_then(|p| match p.keys[0].aim {
                CameraAim::Target(target, height) => Some((p.keys[0], target, height)),
                CameraAim::Rotation(_) => None,
            });
            spec.camera = match (c.eye, c.target, first_target) {
                (Some(eye), Some(target), _) => CameraSpec {
                    eye: finite(eye, "camera.eye")?,
                    eye_height,
                    target: finite(target, "camera.target")?,
                    target_height,
                    fov: camera_fov,
                },
                (None, None, Some((key, target, height))) => CameraSpec {
                    eye: key.eye,
                    eye_height: key.eye_height,
                    target,
                    target_height: height,
                    fov: key.fov,
                },
                _ => {
                    return Err(cx.error(
                        None,
                        "camera",
                        "give `eye` and `target`, or a [[camera.path]] whose first key has a `target`".into(),
                    ));
                }
            };
            spec.camera_path = path;
        }
        if let Some(plants) = &doc.plant {
            let mut list = Vec::with_capacity(plants.len());
            for (i, plant) in plants.iter().enumerate() {
                let p = plant.get_ref();
                let key = format!("plant[{i}]");
                let finite = p
                    .translation
                    .iter()
                    .chain(&p.rotation)
                    .chain(&p.scale)
                    .all(|v| v.is_finite());
                let rotation = glam::Quat::from_array(p.rotation);
                if !finite
                    || (rotation.length() - 1.0).abs() > 1e-3
                    || p.scale.iter().any(|&v| v <= 0.0)
                {
                    return Err(cx.error(
                        Some(plant.span()),
                        &key,
                        "needs finite numbers, a unit rotation quaternion [x, y, z, w] and a positive scale".into(),
                    ));
                }
                if p.layer as usize >= spec.layers.len() {
                    return Err(cx.error(
                        Some(plant.span()),
                        &key,
                        format!(
                            "layer {} does not exist ({} layers)",
                            p.layer,
                            spec.layers.len()
                        ),
                    ));
                }
                list.push(PlacedPlant {
                    species: p.species.clone(),
                    layer: p.layer,
                    transform: Transform {
                        translation: Vec3::from(p.translation),
                        rotation,
                        scale: Vec3::from(p.scale),
                    },
                });
            }
            spec.plants = Some(list);
        }
        Ok(SceneFile {
            spec,
            seed: doc.seed,
        })
    }
}

/// The `[[camera.path]]` key frames, checked by key: times increasing, a `target` or a
/// `rotation` each; heights and field of view default to the camera's.
fn camera_path(
    cx: &Context,
    keys: &[Spanned<CameraKeyDoc>],
    interpolation: &Option<Spanned<String>>,
    (eye_height, target_height, fov): (f32, f32, f32),
) -> Result<CameraPathSpec, SceneFileError> {
    let interpolation = match interpolation {
        None => PathInterpolation::CatmullRom,
        Some(name) => match name.get_ref().as_str() {
            "catmull_rom" => PathInterpolation::CatmullRom,
            "linear" => PathInterpolation::Linear,
            other => {
                return Err(cx.error(
                    Some(name.span()),
                    "camera.path_interpolation",
                    format!("'{other}' is not catmull_rom or linear"),
                ));
            }
        },
    };
    if keys.is_empty() {
        return Err(cx.error(None, "camera.path", "needs at least one key frame".into()));
    }
    let mut out: Vec<CameraKeySpec> = Vec::with_capacity(keys.len());
    for (i, spanned) in keys.iter().enumerate() {
        let k = spanned.get_ref();
        let key = |name: &str| format!("camera.path[{i}].{name}");
        let time = cx.check(&k.time, &key("time"), 0.0, 1e6)?;
        if let Some(previous) = out.last()
            && time <= previous.time
        {
            return Err(cx.error(
                Some(k.time.span()),
                &key("time"),
                format!(
                    "{time} does not come after the key before it ({})",
                    previous.time
                ),
            ));
        }
        let finite2 = |v: [f32; 2]| v.iter().all(|x| x.is_finite());
        if !finite2(k.eye) {
            return Err(cx.error(
                Some(spanned.span()),
                &key("eye"),
                format!("{:?} is not finite", k.eye),
            ));
        }
        let aim = match (k.target, k.rotation) {
            (Some(target), None) if finite2(target) => {
                let height = match &k.target_height {
                    Some(v) => cx.check(v, &key("target_height"), -1e4, 1e5)?,
                    None => target_height,
                };
                CameraAim::Target(Vec2::from(target), height)
            }
            (None, Some(r)) => {
                let rotation = glam::Quat::from_array(r);
                if !rotation.is_finite() || (rotation.length() - 1.0).abs() > 1e-3 {
                    return Err(cx.error(
                        Some(spanned.span()),
                        &key("rotation"),
                        format!("{r:?} is not a unit quaternion [x, y, z, w]"),
                    ));
                }
                CameraAim::Rotation(rotation.normalize())
            }
            _ => {
                return Err(cx.error(
                    Some(spanned.span()),
                    &format!("camera.path[{i}]"),
                    "give either a finite `target` or a `rotation`".into(),
                ));
            }
        };
        out.push(CameraKeySpec {
            time,
            eye: Vec2::from(k.eye),
            eye_height: match &k.eye_height {
                Some(v) => cx.check(v, &key("eye_height"), -1e4, 1e5)?,
                None => eye_height,
            },
            aim,
            fov: match &k.fov {
                Some(v) => cx.check(v, &key("fov"), 1.0, 170.0)?,
                None => fov,
            },
        });
    }
    Ok(CameraPathSpec {
        keys: out,
        interpolation,
    })
}

fn layer(cx: &Context, doc: &LayerDoc, i: usize) -> Result<LayerSpec, SceneFileError> {
    let key = |k: &str| format!("layer[{i}].{k}");
    let count = cx.check(&doc.count, &key("count"), 0, 10_000_000)?;
    let scale = match &doc.scale {
        Some(s) => {
            let [lo, hi] = *s.get_ref();
            if !(lo > 0.0 && hi >= lo && hi < 1e4) {
                return Err(cx.error(
                    Some(s.span()),
                    &key("scale"),
                    format!("[{lo}, {hi}] must satisfy 0 < low ≤ high"),
                ));
            }
            (lo, hi)
        }
        None => (0.8, 1.2),
    };
    let region = match &doc.region {
        Some(r) => {
            let [x0, z0, x1, z1] = *r.get_ref();
            if !(x0 < x1 && z0 < z1) || [x0, z0, x1, z1].iter().any(|v| !v.is_finite()) {
                return Err(cx.error(
                    Some(r.span()),
                    &key("region"),
                    "expected [x0, z0, x1, z1] with x0 < x1 and z0 < z1".into(),
                ));
            }
            Some([x0, z0, x1, z1])
        }
        None => None,
    };
    if doc.species.get_ref().is_empty() && count > 0 {
        return Err(cx.error(
            Some(doc.species.span()),
            &key("species"),
            "a layer with plants needs at least one species".into(),
        ));
    }
    let species = doc
        .species
        .get_ref()
        .iter()
        .enumerate()
        .map(|(j, s)| species(cx, s, &format!("layer[{i}].species[{j}]")))
        .collect::<Result<_, _>>()?;
    Ok(LayerSpec {
        name: doc.name.clone(),
        species,
        count,
        scale,
        min_spacing: doc
            .min_spacing
            .as_ref()
            .map(|v| cx.check(v, &key("min_spacing"), 0.0, 1e4))
            .transpose()?,
        clustering: doc
            .clustering
            .as_ref()
            .map(|v| cx.check(v, &key("clustering"), 0.0, 1.0))
            .transpose()?
            .unwrap_or(0.0),
        region,
        sway: sway(cx, &doc.sway, &key("sway"))?,
    })
}

/// A `sway` table's factors, each in 0.01 … 100.
fn sway(cx: &Context, doc: &Option<SwayDoc>, key: &str) -> Result<SwaySpec, SceneFileError> {
    let Some(doc) = doc else {
        return Ok(SwaySpec::default());
    };
    let factor = |value: &Option<Spanned<f32>>, name: &str| {
        value
            .as_ref()
            .map(|v| cx.check(v, &format!("{key}.{name}"), 0.01, 100.0))
            .transpose()
    };
    Ok(SwaySpec {
        stiffness: factor(&doc.stiffness, "stiffness")?,
        damping: factor(&doc.damping, "damping")?,
        inertia: factor(&doc.inertia, "inertia")?,
    })
}

fn species(cx: &Context, doc: &SpeciesDoc, key: &str) -> Result<SpeciesSpec, SceneFileError> {
    let k = |f: &str| format!("{key}.{f}");
    let sway = sway(cx, &doc.sway, &k("sway"))?;
    let weight = doc
        .weight
        .as_ref()
        .map(|v| cx.check(v, &k("weight"), 0.0, 1e6))
        .transpose()?
        .unwrap_or(1.0);
    let name = doc.name.get_ref().clone();
    if let Some(file) = &doc.gltf {
        if let Some(kind) = &doc.kind {
            return Err(cx.error(
                Some(kind.span()),
                &k("kind"),
                "a species comes either from `gltf` or from `kind`, not both".into(),
            ));
        }
        let base = cx.path.parent().unwrap_or(Path::new("."));
        return Ok(SpeciesSpec {
            name,
            source: SpeciesSource::Gltf {
                path: base.join(file.get_ref()),
            },
            weight,
            sway,
        });
    }
    let Some(kind_name) = &doc.kind else {
        return Err(cx.error(
            Some(doc.name.span()),
            key,
            "a species needs `kind` (procedural) or `gltf` (a model file)".into(),
        ));
    };
    let kind = PlantKind::from_name(kind_name.get_ref()).ok_or_else(|| {
        cx.error(
            Some(kind_name.span()),
            &k("kind"),
            format!(
                "unknown kind '{}' (expected {})",
                kind_name.get_ref(),
                PlantKind::ALL.map(PlantKind::name).join(", ")
            ),
        )
    })?;
    let leaf_shape = doc
        .leaf
        .as_ref()
        .map(|l| {
            LeafShape::from_name(l.get_ref()).ok_or_else(|| {
                cx.error(
                    Some(l.span()),
                    &k("leaf"),
                    format!(
                        "unknown leaf shape '{}' (expected {})",
                        l.get_ref(),
                        LeafShape::ALL.map(LeafShape::name).join(", ")
                    ),
                )
            })
        })
        .transpose()?;
    let leaf_color = doc
        .leaf_color
        .as_ref()
        .map(|c| {
            cx.color(c, &k("leaf_color"), 1.0)
                .map(|c| c.map(srgb_to_linear))
        })
        .transpose()?;
    Ok(SpeciesSpec {
        name,
        source: SpeciesSource::Procedural {
            kind,
            height: doc
                .height
                .as_ref()
                .map(|v| cx.check(v, &k("height"), 0.01, 500.0))
                .transpose()?
                .unwrap_or(kind.typical_height()),
            triangles: doc
                .triangles
                .as_ref()
                .map(|v| cx.check(v, &k("triangles"), 16, 2_000_000))
                .transpose()?
                .unwrap_or(2000),
            leaf_shape,
            leaf_color,
            seed: doc.seed.unwrap_or_else(|| {
                // Stable per name, so reordering species does not change them.
                doc.name
                    .get_ref()
                    .bytes()
                    .fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
                        (h ^ b as u64).wrapping_mul(0x1000_0000_01b3)
                    })
            }),
        },
        weight,
        sway,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<SceneFile, SceneFileError> {
        SceneFile::parse(text, Path::new("scenes/my.toml"))
    }

    #[test]
    fn a_wind_is_read_with_its_defaults() {
        let file = parse("preset = \"meadow\"\n[wind]\nspeed = 8\ndirection = 0\n").unwrap();
        let wind = file.spec.wind.expect("a wind");
        assert_eq!(wind.speed, 8.0);
        assert!(
            (wind.direction - glam::Vec2::Y).length() < 1e-6,
            "toward +Z"
        );
        let calm = sylva_engine::sway::Wind::default();
        assert_eq!(
            (wind.gustiness, wind.gust_frequency, wind.gust_wavelength),
            (calm.gustiness, calm.gust_frequency, calm.gust_wavelength)
        );
        assert_eq!(parse("preset = \"meadow\"\n").unwrap().spec.wind, None);
        let turbulent = parse("[wind]\nspeed = 8\nturbulence = 0.4\nseed = 5\n").unwrap();
        let wind = turbulent.spec.wind.unwrap();
        assert_eq!((wind.turbulence, wind.seed), (0.4, 5));
        let error = parse("[wind]\nspeed = 8\nturbulence = 3\n")
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("wind.turbulence: 3 is out of range"),
            "{error}"
        );
    }

    #[test]
    fn a_preset_with_overrides() {
        let file =
            parse("preset = \"forest\"\nseed = 9\n[terrain]\ncells = 50\nnoise = \"ridged\"\n")
                .unwrap();
        assert_eq!(file.seed, Some(9));
        assert_eq!(file.spec.terrain.cells, 50);
        assert!(file.spec.terrain.ridged);
        assert_eq!(file.spec.layers, EcosystemSpec::forest().layers);
        assert_eq!(file.spec.name, "my");
    }

    #[test]
    fn layers_species_and_relative_gltf_paths() {
        let file = parse(
            r#"
[[layer]]
name = "grass"
count = 40
clustering = 0.5
region = [-5, -5, 5, 5]
[[layer.species]]
name = "g"
kind = "grass"
height = 0.4
triangles = 300
leaf = "blades"
leaf_color = [1.0, 0.5, 0.0]
[[layer.species]]
name = "t"
gltf = "models/tree.glb"
weight = 0.5
[camera]
eye = [0, 8]
target = [0, 0]
"#,
        )
        .unwrap();
        let layer = &file.spec.layers[0];
        assert_eq!((layer.count, layer.clustering), (40, 0.5));
        assert_eq!(layer.region, Some([-5.0, -5.0, 5.0, 5.0]));
        match &layer.species[0].source {
            SpeciesSource::Procedural {
                kind, leaf_color, ..
            } => {
                assert_eq!(*kind, PlantKind::Grass);
                assert_eq!(*leaf_color, Some(Vec3::new(1.0, srgb_to_linear(0.5), 0.0)));
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(
            layer.species[1].source,
            SpeciesSource::Gltf {
                path: PathBuf::from("scenes/models/tree.glb")
            }
        );
        assert_eq!(file.spec.camera.eye, Vec2::new(0.0, 8.0));
    }

    #[test]
    fn a_camera_path_is_read_with_the_cameras_defaults_and_bad_keys_are_refused() {
        let file = parse(
            "preset = \"meadow\"\n[camera]\neye = [0, 10]\ntarget = [0, 0]\neye_height = 3\nfov = 40\npath_interpolation = \"linear\"\n\n[[camera.path]]\ntime = 0\neye = [0, 10]\ntarget = [0, 0]\n\n[[camera.path]]\ntime = 2.5\neye = [5, 5]\nrotation = [0, 0.38268343, 0, 0.9238795]\nfov = 60\n",
        )
        .unwrap();
        let path = file.spec.camera_path.expect("a path");
        assert_eq!(path.interpolation, PathInterpolation::Linear);
        assert_eq!(path.keys.len(), 2);
        assert_eq!(path.keys[0].eye_height, 3.0, "the camera's eye height");
        assert_eq!(path.keys[0].fov, 40.0, "the camera's field of view");
        assert_eq!(path.keys[0].aim, CameraAim::Target(Vec2::ZERO, 1.7));
        assert_eq!(path.keys[1].fov, 60.0);
        assert!(matches!(path.keys[1].aim, CameraAim::Rotation(_)));

        // Without eye and target, the still camera is the first key.
        let only_path = parse(
            "preset = \"meadow\"\n[[camera.path]]\ntime = 0\neye = [3, 4]\ntarget = [1, 1]\n",
        )
        .unwrap();
        assert_eq!(only_path.spec.camera.eye, Vec2::new(3.0, 4.0));
        assert_eq!(only_path.spec.camera.target, Vec2::new(1.0, 1.0));
        assert_eq!(
            only_path.spec.camera_path.unwrap().interpolation,
            PathInterpolation::CatmullRom
        );

        let key = |time: &str, aim: &str| {
            format!("[[camera.path]]\ntime = {time}\neye = [0, 1]\n{aim}\n")
        };
        for (text, says) in [
            (
                format!(
                    "{}{}",
                    key("1", "target = [0, 0]"),
                    key("1", "target = [1, 0]")
                ),
                "my.toml:6:8: camera.path[1].time: 1 does not come after",
            ),
            (
                key("0", ""),
                "camera.path[0]: give either a finite `target` or a `rotation`",
            ),
            (
                key("0", "target = [0, 0]\nrotation = [0, 0, 0, 1]"),
                "camera.path[0]: give either",
            ),
            (
                key("0", "rotation = [0, 0, 0, 2]"),
                "camera.path[0].rotation",
            ),
            (
                key("-1", "target = [0, 0]"),
                "camera.path[0].time: -1 is out of range",
            ),
            (
                format!(
                    "[camera]\npath_interpolation = \"cubic\"\n{}",
                    key("0", "target = [0, 0]")
                ),
                "camera.path_interpolation: 'cubic' is not catmull_rom or linear",
            ),
            (
                key("0", "rotation = [0, 0, 0, 1]"),
                "camera: give `eye` and `target`",
            ),
        ] {
            let error = parse(&text).unwrap_err().to_string();
            assert!(error.contains(says), "{text}\n→ {error}");
        }
    }

    #[test]
    fn sway_factors_are_read_per_layer_and_species_and_checked_by_key() {
        let layer = "[[layer]]\nname = \"a\"\ncount = 3\nsway = { stiffness = 2.5 }\n[[layer.species]]\nname = \"g\"\nkind = \"grass\"\n";
        let file = parse(&format!("{layer}sway = {{ inertia = 0.5 }}\n")).unwrap();
        let spec = &file.spec.layers[0];
        assert_eq!(spec.sway.stiffness, Some(2.5));
        assert_eq!(spec.species[0].sway.inertia, Some(0.5));
        let factors = spec.species[0].sway.over(spec.sway);
        assert_eq!(
            (factors.stiffness, factors.damping, factors.inertia),
            (2.5, 1.0, 0.5)
        );
        for (bad, says) in [
            (
                "sway = { damping = 0 }",
                "layer[0].species[0].sway.damping: 0 is out of range",
            ),
            ("sway = { springiness = 2 }", "springiness"),
        ] {
            let error = parse(&format!("{layer}{bad}\n")).unwrap_err().to_string();
            assert!(error.contains(says), "{bad}: {error}");
        }
    }

    #[test]
    fn explicit_plants_are_read_and_bad_ones_are_refused_by_key() {
        let good = parse(
            "preset = \"meadow\"\n[[plant]]\nspecies = \"meadow grass 1\"\nlayer = 0\ntranslation = [1, 2, 3]\nrotation = [0, 0, 0, 1]\nscale = [2, 2, 2]\n",
        )
        .unwrap();
        let plants = good.spec.plants.unwrap();
        assert_eq!(plants.len(), 1);
        assert_eq!(plants[0].transform.translation, Vec3::new(1.0, 2.0, 3.0));
        for (bad, why) in [
            (
                "rotation = [0, 0, 0, 2]\nscale = [1, 1, 1]\nlayer = 0",
                "unit rotation",
            ),
            (
                "rotation = [0, 0, 0, 1]\nscale = [0, 1, 1]\nlayer = 0",
                "positive scale",
            ),
            (
                "rotation = [0, 0, 0, 1]\nscale = [1, 1, 1]\nlayer = 9",
                "layer 9",
            ),
        ] {
            let text = format!(
                "preset = \"meadow\"\n[[plant]]\nspecies = \"a\"\ntranslation = [0, 0, 0]\n{bad}\n"
            );
            let error = parse(&text).unwrap_err().to_string();
            assert!(error.contains("plant[0]") && error.contains(why), "{error}");
        }
    }

    #[test]
    fn errors_name_file_line_and_key() {
        let cases = [
            (
                "[terrain]\nsize = 10\nbumpiness = 3\n",
                "my.toml:3:1",
                "bumpiness",
            ),
            (
                "[terrain]\ncells = \"many\"\n",
                "my.toml:2:9: terrain.cells",
                "u32",
            ),
            (
                "[terrain]\ncells = 5000\n",
                "my.toml:2:9: terrain.cells",
                "out of range",
            ),
            (
                "preset = \"jungle\"\n",
                "my.toml:1:10: preset",
                "meadow, forest, paper",
            ),
            (
                "[[layer]]\nname = \"a\"\ncount = 3\n[[layer.species]]\nname = \"x\"\nkind = \"tre\"\n",
                "my.toml:6:8: layer[0].species[0].kind",
                "unknown kind 'tre'",
            ),
            (
                "[[layer]]\nname = \"a\"\ncount = 3\nspecies = []\n",
                "layer[0].species",
                "at least one species",
            ),
            (
                "[[layer]]\nname = \"a\"\ncount = 3\nscale = [2, 1]\nspecies = []\n",
                "my.toml:4:9: layer[0].scale",
                "low ≤ high",
            ),
            (
                "[sun]\nelevation = nan\nazimuth = 0\n",
                "my.toml:2:13: sun.elevation",
                "out of range",
            ),
            (
                "[wind]\nspeed = -3\n",
                "my.toml:2:9: wind.speed",
                "out of range",
            ),
            (
                "[wind]\nspeed = 3\ngust_wavelength = 0\n",
                "my.toml:3:19: wind.gust_wavelength",
                "out of range",
            ),
            ("[wind]\ndirection = 90\n", "my.toml", "speed"),
            ("[terrain\n", "my.toml:1:", ""),
            (
                "[sky]\nturbidity = 3\nzenith = [0, 0, 1]\n",
                "my.toml: sky",
                "either",
            ),
            (
                "[sky]\nturbidity = 30\n",
                "my.toml:2:13: sky.turbidity",
                "out of range",
            ),
        ];
        for (text, place, what) in cases {
            let e = parse(text).unwrap_err().to_string();
            assert!(e.contains(place) && e.contains(what), "{text:?} gave: {e}");
        }
        let missing = SceneFile::load(Path::new("/nonexistent/scene.toml")).unwrap_err();
        assert!(
            missing.to_string().contains("/nonexistent/scene.toml"),
            "{missing}"
        );
    }
}
