//! `--frames-out`: every shown frame written as a numbered PNG on a thread of its own.

use super::*;

/// Writes shown frames as numbered PNGs on a thread of its own, so the window does not
/// wait on the encoder; a bounded queue makes the window wait rather than drop a frame.
pub(super) struct FrameWriter {
    pub(super) queue: Option<std::sync::mpsc::SyncSender<ShownImage>>,
    pub(super) writer: std::thread::JoinHandle<Result<u32>>,
}

impl FrameWriter {
    pub(super) fn start(dir: PathBuf) -> Self {
        let (queue, frames) = std::sync::mpsc::sync_channel::<ShownImage>(4);
        let writer = std::thread::spawn(move || {
            let mut written = 0;
            for image in frames {
                written += 1;
                let path = dir.join(format!("frame_{written:05}.png"));
                let rgba: Vec<u8> = image
                    .pixels
                    .iter()
                    .flat_map(|p| [(p >> 16) as u8, (p >> 8) as u8, *p as u8, 255])
                    .collect();
                let metadata = [
                    (
                        "Software",
                        format!("sylva {} view", env!("CARGO_PKG_VERSION")),
                    ),
                    ("sylva.frames", image.frames.to_string()),
                    ("sylva.quality", "interactive".to_string()),
                ]
                .map(|(k, v)| (k.to_string(), v));
                sylva::engine::film::write_rgba8_png(
                    &path,
                    (image.width, image.height),
                    &rgba,
                    &metadata,
                )?;
            }
            Ok(written)
        });
        Self {
            queue: Some(queue),
            writer,
        }
    }

    /// Queues a frame; false when the writer has stopped (its error comes with `finish`).
    pub(super) fn push(&self, image: &ShownImage) -> bool {
        self.queue
            .as_ref()
            .is_some_and(|queue| queue.send(image.clone()).is_ok())
    }

    /// Waits for the queued frames to be written; how many were.
    pub(super) fn finish(mut self) -> Result<u32> {
        self.queue.take();
        self.writer
            .join()
            .map_err(|_| anyhow::anyhow!("the frame writer panicked"))?
    }
}
