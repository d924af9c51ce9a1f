//! Checkpoints: a film's exact accumulation state (f64 sums and counts) written to a
//! file and read back, refusing files of another scene or a damaged one.

use super::{Film, OutputError, write_atomically};
use std::path::Path;

/// Why a checkpoint could not be used.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    /// Reading failed.
    #[error("{}: cannot read the checkpoint: {source}", path.display())]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Not a checkpoint, or a damaged one.
    #[error("{}: not a Sylva film checkpoint ({reason})", path.display())]
    Format {
        /// The file.
        path: std::path::PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// Written for another scene, view or sampling settings.
    #[error("{}: the checkpoint was rendered with other settings (scene, seed, size or sampling); resume with the same ones", path.display())]
    Mismatch {
        /// The file.
        path: std::path::PathBuf,
    },
}

const CHECKPOINT_MAGIC: &[u8; 8] = b"SYLVAFLM";
const CHECKPOINT_VERSION: u32 = 1;

impl Film {
    /// Saves the exact accumulation state (f64 sums, counts, frame count), atomically.
    /// `fingerprint` identifies the settings it belongs to; [`Film::read_checkpoint`]
    /// refuses another.
    pub fn write_checkpoint(&self, path: &Path, fingerprint: u64) -> Result<(), OutputError> {
        let mut bytes = Vec::with_capacity(48 + self.sums.len() * 32);
        bytes.extend_from_slice(CHECKPOINT_MAGIC);
        bytes.extend_from_slice(&CHECKPOINT_VERSION.to_le_bytes());
        bytes.extend_from_slice(&fingerprint.to_le_bytes());
        for v in [self.width, self.height, self.frames] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        for v in [self.rejected, self.resets] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        for (sum, count) in self.sums.iter().zip(&self.counts) {
            for v in sum {
                bytes.extend_from_slice(&v.to_le_bytes());
            }
            bytes.extend_from_slice(&count.to_le_bytes());
        }
        write_atomically(path, |tmp| {
            std::fs::write(tmp, &bytes).map_err(|e| e.to_string())
        })
    }

    /// Loads a checkpoint written with the same `fingerprint`; the next frame added
    /// continues it.
    pub fn read_checkpoint(path: &Path, fingerprint: u64) -> Result<Film, CheckpointError> {
        let bytes = std::fs::read(path).map_err(|source| CheckpointError::Io {
            path: path.to_owned(),
            source,
        })?;
        let format = |reason: &str| CheckpointError::Format {
            path: path.to_owned(),
            reason: reason.into(),
        };
        let mut at = 0usize;
        let mut take = |n: usize| -> Result<&[u8], CheckpointError> {
            let slice = bytes.get(at..at + n).ok_or_else(|| format("truncated"))?;
            at += n;
            Ok(slice)
        };
        if take(8)? != CHECKPOINT_MAGIC {
            return Err(format("wrong magic number"));
        }
        let u32_at = |b: &[u8]| u32::from_le_bytes(b.try_into().expect("4 bytes"));
        let u64_at = |b: &[u8]| u64::from_le_bytes(b.try_into().expect("8 bytes"));
        if u32_at(take(4)?) != CHECKPOINT_VERSION {
            return Err(format("unknown version"));
        }
        if u64_at(take(8)?) != fingerprint {
            return Err(CheckpointError::Mismatch {
                path: path.to_owned(),
            });
        }
        let (width, height, frames) = (u32_at(take(4)?), u32_at(take(4)?), u32_at(take(4)?));
        let (rejected, resets) = (u64_at(take(8)?), u64_at(take(8)?));
        let pixels = width as usize * height as usize;
        let body = take(
            pixels
                .checked_mul(32)
                .ok_or_else(|| format("absurd size"))?,
        )?;
        let mut film = Film::new(width, height);
        for (i, chunk) in body.chunks_exact(32).enumerate() {
            let f =
                |k: usize| f64::from_le_bytes(chunk[k * 8..k * 8 + 8].try_into().expect("8 bytes"));
            film.sums[i] = [f(0), f(1), f(2)];
            film.counts[i] = u64_at(&chunk[24..32]);
        }
        film.frames = frames;
        film.rejected = rejected;
        film.resets = resets;
        film.resume_pending = true;
        Ok(film)
    }
}
