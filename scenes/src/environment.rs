//! Loading latitude–longitude environment maps: Radiance `.hdr` (image crate) and
//! OpenEXR `.exr` (exr crate, feature `exr`). Dimensions are checked before any pixel is
//! decoded; NaN, infinite and negative texels are zeroed with a warning that names the
//! file and counts them.

use glam::Vec3;
use std::path::{Path, PathBuf};
use sylva_engine::environment::EnvironmentMap;

/// Largest accepted map: 16384 × 8192 texels.
pub const MAX_ENVIRONMENT_TEXELS: u64 = 16_384 * 8_192;

/// Why an environment map could not be loaded.
#[derive(Debug, thiserror::Error)]
#[error("{}: {message}", path.display())]
pub struct EnvironmentFileError {
    /// The file.
    pub path: PathBuf,
    /// What is wrong.
    pub message: String,
}

/// A loaded map and how many texels had to be repaired.
#[derive(Clone, Debug, PartialEq)]
pub struct LoadedEnvironment {
    /// The map.
    pub map: EnvironmentMap,
    /// Texels that were NaN, infinite or negative (now zero).
    pub repaired_texels: usize,
}

fn fail(path: &Path, message: impl Into<String>) -> EnvironmentFileError {
    EnvironmentFileError {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

fn check_size(path: &Path, width: u64, height: u64) -> Result<(), EnvironmentFileError> {
    if width == 0 || height == 0 || width * height > MAX_ENVIRONMENT_TEXELS {
        return Err(fail(
            path,
            format!(
                "the map is {width}x{height}; it must be non-empty and at most {MAX_ENVIRONMENT_TEXELS} texels"
            ),
        ));
    }
    Ok(())
}

/// Loads a `.hdr` or `.exr` lat-long map (top row = zenith).
pub fn load_environment(path: &Path) -> Result<LoadedEnvironment, EnvironmentFileError> {
    let extension = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    let (width, height, texels) = match extension.as_str() {
        "hdr" => load_hdr(path)?,
        "exr" => load_exr(path)?,
        other => {
            return Err(fail(
                path,
                format!("unsupported environment map format '.{other}' (expected .hdr or .exr)"),
            ));
        }
    };
    let (map, repaired_texels) =
        EnvironmentMap::new(width, height, texels).map_err(|e| fail(path, e.to_string()))?;
    if repaired_texels > 0 {
        tracing::warn!(
            "{}: {repaired_texels} NaN, infinite or negative texels set to zero",
            path.display()
        );
    }
    Ok(LoadedEnvironment {
        map,
        repaired_texels,
    })
}

type Texels = (u32, u32, Vec<Vec3>);

fn load_hdr(path: &Path) -> Result<Texels, EnvironmentFileError> {
    let open = || {
        image::ImageReader::open(path)
            .map_err(|e| fail(path, format!("cannot read: {e}")))
            .map(|r| {
                let mut r = r;
                r.set_format(image::ImageFormat::Hdr);
                r
            })
    };
    let (width, height) = open()?
        .into_dimensions()
        .map_err(|e| fail(path, format!("not a Radiance HDR file: {e}")))?;
    check_size(path, width as u64, height as u64)?;
    let image = open()?
        .decode()
        .map_err(|e| fail(path, format!("cannot decode: {e}")))?
        .into_rgb32f();
    let texels = image.pixels().map(|p| Vec3::from(p.0)).collect();
    Ok((width, height, texels))
}

#[cfg(feature = "exr")]
fn load_exr(path: &Path) -> Result<Texels, EnvironmentFileError> {
    use exr::prelude::*;
    let meta = MetaData::read_from_file(path, false)
        .map_err(|e| fail(path, format!("not a readable OpenEXR file: {e}")))?;
    let size = meta
        .headers
        .first()
        .map(|h| h.layer_size)
        .ok_or_else(|| fail(path, "the file has no layers"))?;
    check_size(path, size.width() as u64, size.height() as u64)?;
    let image = read_first_rgba_layer_from_file(
        path,
        |resolution, _| {
            (
                resolution.width(),
                vec![Vec3::ZERO; resolution.width() * resolution.height()],
            )
        },
        |(width, texels): &mut (usize, Vec<Vec3>),
         position,
         (r, g, b, _a): (f32, f32, f32, f32)| {
            texels[position.y() * *width + position.x()] = Vec3::new(r, g, b);
        },
    )
    .map_err(|e| fail(path, format!("cannot decode: {e}")))?;
    let layer = image.layer_data;
    let (w, h) = (layer.size.width() as u32, layer.size.height() as u32);
    Ok((w, h, layer.channel_data.pixels.1))
}

#[cfg(not(feature = "exr"))]
fn load_exr(path: &Path) -> Result<Texels, EnvironmentFileError> {
    Err(fail(
        path,
        "reading OpenEXR needs the 'exr' cargo feature, which this build left out",
    ))
}
