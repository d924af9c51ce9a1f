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

mod document;
mod tables;
#[cfg(test)]
mod tests;

use document::*;
use tables::*;

use crate::ecosystem::{
    CameraAim, CameraKeySpec, CameraPathSpec, CameraSpec, EcosystemSpec, LayerSpec, PRESETS,
    PlacedPlant, SkySpec, SpeciesSource, SpeciesSpec, SunSpec, SwaySpec,
};
use crate::species::{LeafShape, PlantKind};
use crate::terrain::TerrainParams;
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
            terrain(&cx, t, &mut spec.terrain)?;
        }
        if let Some(layers) = &doc.layer {
            spec.layers = layers
                .iter()
                .enumerate()
                .map(|(i, l)| layer(&cx, l, i))
                .collect::<Result<_, _>>()?;
        }
        if let Some(s) = &doc.sun {
            spec.sun = Some(sun(&cx, s)?);
        }
        if let Some(w) = &doc.wind {
            spec.wind = Some(wind(&cx, w)?);
        }
        if let Some(s) = &doc.sky {
            spec.sky = Some(sky(&cx, s)?);
        }
        if let Some(c) = &doc.camera {
            (spec.camera, spec.camera_path) = camera(&cx, c)?;
        }
        if let Some(list) = &doc.plant {
            spec.plants = Some(plants(&cx, list, spec.layers.len())?);
        }
        Ok(SceneFile {
            spec,
            seed: doc.seed,
        })
    }
}
