//! TOML scene files: name a preset and override parts of it, or describe an ecosystem
//! from scratch (terrain, layers with species, sun, sky, wind, camera, plants). Unknown
//! keys are errors; every error names the file, the line and column, and the key. The
//! format's reference, every key with an example, is `docs/scene-format.md` (a test
//! parses its example and checks that it names every key the parser reads).

mod document;
mod tables;
#[cfg(test)]
mod tests;

use document::*;
use tables::*;

use crate::ecosystem::{
    CameraAim, CameraKeySpec, CameraPathSpec, CameraSpec, EcosystemSpec, LayerSpec, PlacedPlant,
    SkySpec, SpeciesSource, SpeciesSpec, SunSpec, SwaySpec,
};
use crate::presets::{self, PRESETS};
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
            Some(name) => preset(name.get_ref()).ok_or_else(|| {
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
            None => EcosystemSpec::base(),
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

/// A built-in ecosystem by name (`meadow`, `forest`, `paper`): its embedded scene file,
/// parsed.
pub fn preset(name: &str) -> Option<EcosystemSpec> {
    let text = presets::text(name)?;
    let file = SceneFile::parse(text, Path::new(&format!("{name}.toml")))
        .unwrap_or_else(|e| panic!("the built-in preset does not parse (a test parses it): {e}"));
    Some(file.spec)
}
