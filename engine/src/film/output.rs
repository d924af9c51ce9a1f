//! Images out: PNG (exposure, the filmic tone curve, sRGB; text metadata), EXR (linear
//! radiance in f32), animated PNG, and the atomic write every file goes through.

use super::Film;
use std::path::{Path, PathBuf};

impl Film {
    /// Writes a tone-mapped PNG, atomically (temporary file, then rename).
    pub fn write_png(&self, path: &Path, exposure: f32) -> Result<(), OutputError> {
        self.write_png_with(path, exposure, &[])
    }

    /// [`write_png`](Self::write_png) with `metadata` as tEXt chunks (keywords of 1–79
    /// Latin-1 characters; others are left out).
    pub fn write_png_with(
        &self,
        path: &Path,
        exposure: f32,
        metadata: &[(String, String)],
    ) -> Result<(), OutputError> {
        write_rgba8_png(
            path,
            (self.width, self.height),
            &self.to_srgba8(exposure),
            metadata,
        )
    }

    /// Writes linear mean radiance as an RGBA f32 EXR, atomically.
    pub fn write_exr(&self, path: &Path) -> Result<(), OutputError> {
        self.write_exr_with(path, &[])
    }

    /// [`write_exr`](Self::write_exr) with `metadata` as text attributes of the header.
    #[cfg(feature = "exr")]
    pub fn write_exr_with(
        &self,
        path: &Path,
        metadata: &[(String, String)],
    ) -> Result<(), OutputError> {
        use exr::prelude::*;
        let mean = self.mean_rgb();
        let width = self.width as usize;
        write_atomically(path, |tmp| {
            let channels = SpecificChannels::rgba(|pos: Vec2<usize>| {
                let [r, g, b] = mean[pos.y() * width + pos.x()];
                (r, g, b, 1.0f32)
            });
            // Scan lines in increasing order: the default tiles with unspecified order are
            // written as the compressing threads finish them, so bytes vary run to run.
            let encoding = Encoding {
                compression: Compression::ZIP16,
                blocks: Blocks::ScanLines,
                line_order: LineOrder::Increasing,
            };
            let mut image =
                Image::from_encoded_channels((width, self.height as usize), encoding, channels);
            for (key, value) in metadata {
                if let (Some(key), Some(value)) = (Text::new_or_none(key), Text::new_or_none(value))
                {
                    image
                        .attributes
                        .other
                        .insert(key, exr::meta::attribute::AttributeValue::Text(value));
                }
            }
            // The exr crate keeps custom attributes in a hash map and writes them in its
            // (per-process random) order; sorting them in memory before the one write to
            // disk makes equal images equal files.
            let mut bytes = std::io::Cursor::new(Vec::new());
            image
                .write()
                .to_buffered(&mut bytes)
                .map_err(|e| e.to_string())?;
            let mut bytes = bytes.into_inner();
            sort_exr_header_attributes(&mut bytes)?;
            std::fs::write(tmp, bytes).map_err(|e| e.to_string())
        })
    }

    /// Without the `exr` feature: an error saying how to get EXR output.
    #[cfg(not(feature = "exr"))]
    pub fn write_exr_with(
        &self,
        path: &Path,
        _metadata: &[(String, String)],
    ) -> Result<(), OutputError> {
        Err(OutputError::FeatureDisabled {
            path: path.to_owned(),
            feature: "exr",
        })
    }

    /// Writes PNG or EXR by the path's extension.
    pub fn write(&self, path: &Path, exposure: f32) -> Result<(), OutputError> {
        self.write_with(path, exposure, &[])
    }

    /// [`write`](Self::write) with `metadata` (key, value) pairs stored in the file: PNG
    /// tEXt chunks or EXR header attributes.
    pub fn write_with(
        &self,
        path: &Path,
        exposure: f32,
        metadata: &[(String, String)],
    ) -> Result<(), OutputError> {
        match ImageKind::from_path(path)? {
            ImageKind::Png => self.write_png_with(path, exposure, metadata),
            ImageKind::Exr => self.write_exr_with(path, metadata),
        }
    }
}

/// The output formats.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageKind {
    /// 8-bit tone-mapped sRGB.
    Png,
    /// 32-bit float linear radiance.
    Exr,
}

impl ImageKind {
    /// The format an output path asks for; `.exr` needs the `exr` feature.
    pub fn from_path(path: &Path) -> Result<Self, OutputError> {
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .as_deref()
        {
            Some("png") => Ok(Self::Png),
            Some("exr") if cfg!(feature = "exr") => Ok(Self::Exr),
            Some("exr") => Err(OutputError::FeatureDisabled {
                path: path.to_owned(),
                feature: "exr",
            }),
            _ => Err(OutputError::UnknownFormat {
                path: path.to_owned(),
            }),
        }
    }
}

/// Why an image could not be written.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    /// The extension is neither `.png` nor `.exr`.
    #[error("{}: unknown image format (use a .png or .exr file name)", path.display())]
    UnknownFormat {
        /// The path given.
        path: PathBuf,
    },
    /// The format needs a cargo feature this build was made without.
    #[error("{}: this build has no {feature} support (rebuild with `--features {feature}`)", path.display())]
    FeatureDisabled {
        /// The path given.
        path: PathBuf,
        /// The missing feature.
        feature: &'static str,
    },
    /// Encoding or file system failure.
    #[error("{}: could not write image: {reason}", path.display())]
    Write {
        /// The path given.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
}

/// Sorts the attributes of a single-part EXR header by name, in place. The header keeps
/// its length, so the chunk offsets after it stay valid.
#[cfg(feature = "exr")]
fn sort_exr_header_attributes(file: &mut [u8]) -> Result<(), String> {
    const MULTI_PART: u32 = 1 << 12;
    let malformed = || "EXR header is malformed".to_string();
    let version = file
        .get(4..8)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .ok_or_else(malformed)?;
    if version & MULTI_PART != 0 {
        return Err("multi-part EXR headers are not sorted".into());
    }
    let start = 8;
    let mut attributes: Vec<(usize, usize)> = Vec::new();
    let mut at = start;
    let string_end = |from: usize| {
        file.get(from..)
            .and_then(|rest| rest.iter().position(|&b| b == 0))
            .map(|n| from + n)
            .ok_or_else(malformed)
    };
    while *file.get(at).ok_or_else(malformed)? != 0 {
        let name_end = string_end(at)?;
        let type_end = string_end(name_end + 1)?;
        let size_at = type_end + 1;
        let size = file
            .get(size_at..size_at + 4)
            .map(|b| i32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .ok_or_else(malformed)?;
        let end = usize::try_from(size)
            .ok()
            .and_then(|s| (size_at + 4).checked_add(s))
            .filter(|&end| end <= file.len())
            .ok_or_else(malformed)?;
        attributes.push((at, end));
        at = end;
    }
    let mut sorted: Vec<&[u8]> = attributes.iter().map(|&(a, b)| &file[a..b]).collect();
    sorted.sort_by_key(|attribute| attribute.split(|&b| b == 0).next().unwrap_or_default());
    let header: Vec<u8> = sorted.concat();
    file[start..at].copy_from_slice(&header);
    Ok(())
}

/// Writes `frames` (8-bit RGBA, each `width` × `height`, row by row from the top) as an
/// animated PNG that shows `fps` of them per second and loops, with `metadata` as tEXt
/// chunks, atomically: an animation's preview.
pub fn write_apng(
    path: &Path,
    (width, height): (u32, u32),
    frames: &[Vec<u8>],
    fps: u16,
    metadata: &[(String, String)],
) -> Result<(), OutputError> {
    let size = width as usize * height as usize * 4;
    if frames.is_empty() || frames.iter().any(|f| f.len() != size) {
        return Err(OutputError::Write {
            path: path.to_owned(),
            reason: format!(
                "{} frames for a {width}x{height} RGBA animation, some of another size or none",
                frames.len()
            ),
        });
    }
    write_rgba8_frames(path, (width, height), frames, Some(fps), metadata)
}

/// Reads an 8-bit RGB or RGBA PNG (the first frame of an animated one) as RGBA with its
/// size.
pub fn read_rgba8_png(path: &Path) -> Result<((u32, u32), Vec<u8>), OutputError> {
    let fail = |reason: String| OutputError::Write {
        path: path.to_owned(),
        reason: format!("cannot read it back: {reason}"),
    };
    let file = std::fs::File::open(path).map_err(|e| fail(e.to_string()))?;
    let mut reader = png::Decoder::new(std::io::BufReader::new(file))
        .read_info()
        .map_err(|e| fail(e.to_string()))?;
    let mut buffer = vec![0; reader.output_buffer_size().unwrap_or(0)];
    let info = reader
        .next_frame(&mut buffer)
        .map_err(|e| fail(e.to_string()))?;
    let pixels = &buffer[..info.buffer_size()];
    let rgba = match (info.color_type, info.bit_depth) {
        (png::ColorType::Rgba, png::BitDepth::Eight) => pixels.to_vec(),
        (png::ColorType::Rgb, png::BitDepth::Eight) => pixels
            .chunks_exact(3)
            .flat_map(|p| [p[0], p[1], p[2], 255])
            .collect(),
        (color, depth) => return Err(fail(format!("{color:?} at {depth:?} is not 8-bit RGB(A)"))),
    };
    Ok(((info.width, info.height), rgba))
}

/// Writes `width × height` sRGB8 RGBA pixels (row by row from the top) as a PNG with
/// `metadata` as tEXt chunks (keywords the format cannot hold are left out), atomically
/// (temporary file, then rename): a screenshot is written the way a render is.
pub fn write_rgba8_png(
    path: &Path,
    (width, height): (u32, u32),
    rgba: &[u8],
    metadata: &[(String, String)],
) -> Result<(), OutputError> {
    if rgba.len() != width as usize * height as usize * 4 {
        return Err(OutputError::Write {
            path: path.to_owned(),
            reason: format!("{} bytes for a {width}x{height} RGBA image", rgba.len()),
        });
    }
    write_rgba8_frames(path, (width, height), &[rgba], None, metadata)
}

/// Writes checked 8-bit RGBA `frames` as a PNG, animated at `fps` (looping) when given,
/// with `metadata` as tEXt chunks (keywords the format cannot hold are left out),
/// atomically.
fn write_rgba8_frames(
    path: &Path,
    (width, height): (u32, u32),
    frames: &[impl AsRef<[u8]>],
    fps: Option<u16>,
    metadata: &[(String, String)],
) -> Result<(), OutputError> {
    write_atomically(path, |tmp| {
        let file = std::fs::File::create(tmp).map_err(|e| e.to_string())?;
        let mut encoder = png::Encoder::new(std::io::BufWriter::new(file), width, height);
        encoder.set_color(png::ColorType::Rgba);
        encoder.set_depth(png::BitDepth::Eight);
        if let Some(fps) = fps {
            // A preview is written once and shared: worth a slower, smaller encoding.
            encoder.set_compression(png::Compression::High);
            let count = u32::try_from(frames.len()).map_err(|e| e.to_string())?;
            encoder.set_animated(count, 0).map_err(|e| e.to_string())?;
            encoder
                .set_frame_delay(1, fps.max(1))
                .map_err(|e| e.to_string())?;
        }
        for (key, value) in metadata {
            // A keyword the format cannot hold is skipped rather than failing the image.
            let _ = encoder.add_text_chunk(key.clone(), value.clone());
        }
        let mut writer = encoder.write_header().map_err(|e| e.to_string())?;
        for frame in frames {
            writer
                .write_image_data(frame.as_ref())
                .map_err(|e| e.to_string())?;
        }
        writer.finish().map_err(|e| e.to_string())
    })
}

/// Writes a file through `write(temporary path)` and renames it over `path`, so a
/// reader (or a run killed mid-write) sees the old file or the new one, never half of it.
pub fn write_atomically(
    path: &Path,
    write: impl FnOnce(&Path) -> Result<(), String>,
) -> Result<(), OutputError> {
    let fail = |reason: String| OutputError::Write {
        path: path.to_owned(),
        reason,
    };
    let name = path
        .file_name()
        .ok_or_else(|| fail("not a file name".into()))?;
    // Keep the extension last: the encoders pick the format from it.
    let tmp = path.with_file_name(format!(
        ".{}.{}.tmp.{}",
        name.to_string_lossy(),
        std::process::id(),
        path.extension().and_then(|e| e.to_str()).unwrap_or("")
    ));
    if let Err(reason) = write(&tmp) {
        let _ = std::fs::remove_file(&tmp);
        return Err(fail(reason));
    }
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        fail(e.to_string())
    })
}
