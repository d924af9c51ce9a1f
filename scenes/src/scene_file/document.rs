//! The scene file as TOML reads it: one struct a table, every value kept with its span
//! so an error can name the line and column.

use super::*;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct Document {
    pub(super) preset: Option<Spanned<String>>,
    pub(super) name: Option<String>,
    pub(super) seed: Option<u64>,
    pub(super) clear_radius: Option<Spanned<f32>>,
    pub(super) terrain: Option<TerrainDoc>,
    pub(super) layer: Option<Vec<LayerDoc>>,
    pub(super) sun: Option<SunDoc>,
    pub(super) sky: Option<SkyDoc>,
    pub(super) camera: Option<CameraDoc>,
    pub(super) plant: Option<Vec<Spanned<PlantDoc>>>,
    pub(super) wind: Option<WindDoc>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct WindDoc {
    pub(super) speed: Spanned<f32>,
    pub(super) direction: Option<Spanned<f32>>,
    pub(super) gustiness: Option<Spanned<f32>>,
    pub(super) gust_frequency: Option<Spanned<f32>>,
    pub(super) gust_wavelength: Option<Spanned<f32>>,
    pub(super) turbulence: Option<Spanned<f32>>,
    pub(super) seed: Option<u64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct PlantDoc {
    pub(super) species: String,
    pub(super) layer: u32,
    pub(super) translation: [f32; 3],
    pub(super) rotation: [f32; 4],
    pub(super) scale: [f32; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct TerrainDoc {
    pub(super) size: Option<Spanned<f32>>,
    pub(super) cells: Option<Spanned<u32>>,
    pub(super) amplitude: Option<Spanned<f32>>,
    pub(super) wavelength: Option<Spanned<f32>>,
    pub(super) octaves: Option<Spanned<u32>>,
    pub(super) noise: Option<Spanned<String>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct LayerDoc {
    pub(super) name: String,
    pub(super) count: Spanned<u32>,
    pub(super) scale: Option<Spanned<[f32; 2]>>,
    pub(super) min_spacing: Option<Spanned<f32>>,
    pub(super) clustering: Option<Spanned<f32>>,
    pub(super) region: Option<Spanned<[f32; 4]>>,
    pub(super) sway: Option<SwayDoc>,
    pub(super) species: Spanned<Vec<SpeciesDoc>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct SwayDoc {
    pub(super) stiffness: Option<Spanned<f32>>,
    pub(super) damping: Option<Spanned<f32>>,
    pub(super) inertia: Option<Spanned<f32>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct SpeciesDoc {
    pub(super) name: Spanned<String>,
    pub(super) kind: Option<Spanned<String>>,
    pub(super) height: Option<Spanned<HeightDoc>>,
    pub(super) triangles: Option<Spanned<u32>>,
    pub(super) variants: Option<Spanned<u32>>,
    pub(super) leaf: Option<Spanned<String>>,
    pub(super) leaf_color: Option<Spanned<[f32; 3]>>,
    pub(super) seed: Option<u64>,
    pub(super) weight: Option<Spanned<f32>>,
    pub(super) gltf: Option<Spanned<String>>,
    pub(super) sway: Option<SwayDoc>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct SunDoc {
    pub(super) elevation: Spanned<f32>,
    pub(super) azimuth: Spanned<f32>,
    pub(super) irradiance: Option<Spanned<[f32; 3]>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct SkyDoc {
    pub(super) turbidity: Option<Spanned<f32>>,
    pub(super) zenith: Option<Spanned<[f32; 3]>>,
    pub(super) horizon: Option<Spanned<[f32; 3]>>,
    pub(super) ground: Option<Spanned<[f32; 3]>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct CameraDoc {
    pub(super) eye: Option<[f32; 2]>,
    pub(super) eye_height: Option<Spanned<f32>>,
    pub(super) target: Option<[f32; 2]>,
    pub(super) target_height: Option<Spanned<f32>>,
    pub(super) fov: Option<Spanned<f32>>,
    pub(super) path: Option<Vec<Spanned<CameraKeyDoc>>>,
    pub(super) path_interpolation: Option<Spanned<String>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct CameraKeyDoc {
    pub(super) time: Spanned<f64>,
    pub(super) eye: [f32; 2],
    pub(super) eye_height: Option<Spanned<f32>>,
    pub(super) target: Option<[f32; 2]>,
    pub(super) target_height: Option<Spanned<f32>>,
    pub(super) rotation: Option<[f32; 4]>,
    pub(super) fov: Option<Spanned<f32>>,
}

/// A species' height: one value, or with `variants` the range the variants' heights are
/// drawn from.
#[derive(Deserialize, Clone, Copy)]
#[serde(untagged)]
pub(super) enum HeightDoc {
    One(f32),
    Range([f32; 2]),
}
