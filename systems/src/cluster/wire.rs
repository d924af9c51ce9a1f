//! The cluster protocol's messages and their bytes: little-endian fields in a fixed
//! order, floats by their bits (a tile crosses the wire without changing one bit), a
//! malformed message read as an error, never a panic.

use glam::Vec3;
use sylva_engine::bvh::TraversalStats;
use sylva_engine::film::{PixelSums, SurfaceGuide};
use sylva_engine::film::{Tile, TileResult};

use super::LiveStep;

/// What every rank must agree on before a frame's tiles are shared out: equal checks
/// mean equal inputs to `render_tile`, hence equal tiles whoever renders them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameChecks {
    /// The progressive frame index the samples are drawn for.
    pub frame: u32,
    /// Hash of the species BLASes and the top level (tree and instance records).
    pub scene: u64,
    /// Hash of the camera view and the sampling settings.
    pub view: u64,
}

/// One message between ranks.
#[derive(Clone, Debug, PartialEq)]
pub(crate) enum Message {
    /// A worker's scene is built (or failed to build, with the error).
    Loaded { error: Option<String> },
    /// Rank 0 has heard from everyone and every scene loaded: start.
    Go,
    /// A worker has started job `job` of phase `phase` with these checks and a frame of
    /// `tiles` tiles, and can take `want` runs of them.
    Ready {
        phase: u32,
        job: u64,
        checks: FrameChecks,
        tiles: u32,
        want: u32,
    },
    /// Runs of tiles of job `job` for the worker: (first index in the frame's tile
    /// grid, count).
    Tiles { job: u64, runs: Vec<(u32, u32)> },
    /// A rendered run of tiles of job `job` from grid index `first` on, each with its
    /// render time in nanoseconds, and how many more runs the worker can take.
    Result {
        job: u64,
        first: u32,
        tiles: Vec<(u64, TileResult)>,
        want: u32,
    },
    /// No more tiles of job `job` for this worker: it has returned all it was given.
    Done { job: u64 },
    /// The run or a phase of it is over, or the frame in progress is given up: workers
    /// leave the job they are on (or stood ready for); the next job rank 0 starts is
    /// `next_job`.
    Stop { next_job: u64 },
    /// The sender ends the run because of this error.
    Fail { text: String },
    /// A value rank 0 decided, for every rank to act on alike.
    Share { value: u64 },
    /// Rank 0's changes to the world (each an opaque edit the live render encodes), in
    /// order, and what to do after applying them.
    Step { edits: Vec<Vec<u8>>, next: LiveStep },
    /// A worker has left the live render (its answer to [`LiveStep::Quit`]).
    Left,
    /// A worker has left the job rank 0's stop of phase `phase` ended (its answer to
    /// [`Message::Stop`]): nothing of that job follows it.
    Halted { phase: u32 },
}

/// A message that could not be read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Malformed;

impl Message {
    /// The message's bytes.
    pub(crate) fn encode(&self) -> Vec<u8> {
        let mut out = Writer(Vec::new());
        match self {
            Message::Loaded { error } => {
                out.u8(0);
                match error {
                    None => out.u8(0),
                    Some(text) => {
                        out.u8(1);
                        out.text(text);
                    }
                }
            }
            Message::Go => out.u8(1),
            Message::Ready {
                phase,
                job,
                checks,
                tiles,
                want,
            } => {
                out.u8(2);
                out.u32(*phase);
                out.u64(*job);
                out.u32(checks.frame);
                out.u64(checks.scene);
                out.u64(checks.view);
                out.u32(*tiles);
                out.u32(*want);
            }
            Message::Tiles { job, runs } => {
                out.u8(3);
                out.u64(*job);
                out.u32(runs.len() as u32);
                for &(first, count) in runs {
                    out.u32(first);
                    out.u32(count);
                }
            }
            Message::Result {
                job,
                first,
                tiles,
                want,
            } => {
                out.u8(4);
                out.u64(*job);
                out.u32(*first);
                out.u32(*want);
                out.u32(tiles.len() as u32);
                for (nanos, result) in tiles {
                    out.u64(*nanos);
                    out.tile_result(result);
                }
            }
            Message::Done { job } => {
                out.u8(5);
                out.u64(*job);
            }
            Message::Stop { next_job } => {
                out.u8(6);
                out.u64(*next_job);
            }
            Message::Fail { text } => {
                out.u8(7);
                out.text(text);
            }
            Message::Share { value } => {
                out.u8(8);
                out.u64(*value);
            }
            Message::Step { edits, next } => {
                out.u8(9);
                out.u8(match next {
                    LiveStep::Render => 0,
                    LiveStep::Idle => 1,
                    LiveStep::Quit => 2,
                });
                out.u32(edits.len() as u32);
                for edit in edits {
                    out.blob(edit);
                }
            }
            Message::Left => out.u8(10),
            Message::Halted { phase } => {
                out.u8(11);
                out.u32(*phase);
            }
        }
        out.0
    }

    /// Reads a message; every byte must be used.
    pub(crate) fn decode(bytes: &[u8]) -> Result<Message, Malformed> {
        let mut input = Reader { bytes, at: 0 };
        let message = match input.u8()? {
            0 => Message::Loaded {
                error: match input.u8()? {
                    0 => None,
                    1 => Some(input.text()?),
                    _ => return Err(Malformed),
                },
            },
            1 => Message::Go,
            2 => Message::Ready {
                phase: input.u32()?,
                job: input.u64()?,
                checks: FrameChecks {
                    frame: input.u32()?,
                    scene: input.u64()?,
                    view: input.u64()?,
                },
                tiles: input.u32()?,
                want: input.u32()?,
            },
            3 => {
                let job = input.u64()?;
                let count = input.u32()? as usize;
                if count > input.remaining() / 8 {
                    return Err(Malformed);
                }
                let runs = (0..count)
                    .map(|_| Ok((input.u32()?, input.u32()?)))
                    .collect::<Result<_, _>>()?;
                Message::Tiles { job, runs }
            }
            4 => {
                let (job, first, want) = (input.u64()?, input.u32()?, input.u32()?);
                let count = input.u32()? as usize;
                // Each tile takes at least its header: refuse a count the bytes cannot hold.
                if count > input.remaining() / 36 {
                    return Err(Malformed);
                }
                let tiles = (0..count)
                    .map(|_| Ok((input.u64()?, input.tile_result()?)))
                    .collect::<Result<_, _>>()?;
                Message::Result {
                    job,
                    first,
                    tiles,
                    want,
                }
            }
            5 => Message::Done { job: input.u64()? },
            6 => Message::Stop {
                next_job: input.u64()?,
            },
            7 => Message::Fail {
                text: input.text()?,
            },
            8 => Message::Share {
                value: input.u64()?,
            },
            9 => {
                let next = match input.u8()? {
                    0 => LiveStep::Render,
                    1 => LiveStep::Idle,
                    2 => LiveStep::Quit,
                    _ => return Err(Malformed),
                };
                let count = input.u32()? as usize;
                // Each edit takes at least its length: refuse a count the bytes cannot hold.
                if count > input.remaining() / 4 {
                    return Err(Malformed);
                }
                let edits = (0..count).map(|_| input.blob()).collect::<Result<_, _>>()?;
                Message::Step { edits, next }
            }
            10 => Message::Left,
            11 => Message::Halted {
                phase: input.u32()?,
            },
            _ => return Err(Malformed),
        };
        if input.remaining() == 0 {
            Ok(message)
        } else {
            Err(Malformed)
        }
    }
}

/// Bytes of one pixel in a tile result: sums, count, albedo and emission sums, surface.
const PIXEL_BYTES: usize = 12 + 4 + 12 + 12 + (4 + 12 + 12 + 4);

struct Writer(Vec<u8>);

impl Writer {
    fn u8(&mut self, v: u8) {
        self.0.push(v);
    }
    fn u32(&mut self, v: u32) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn u64(&mut self, v: u64) {
        self.0.extend_from_slice(&v.to_le_bytes());
    }
    fn f32(&mut self, v: f32) {
        self.u32(v.to_bits());
    }
    fn vec3(&mut self, v: Vec3) {
        self.f32(v.x);
        self.f32(v.y);
        self.f32(v.z);
    }
    fn text(&mut self, text: &str) {
        self.blob(text.as_bytes());
    }
    fn blob(&mut self, bytes: &[u8]) {
        self.u32(bytes.len() as u32);
        self.0.extend_from_slice(bytes);
    }
    fn tile_result(&mut self, result: &TileResult) {
        let t = result.tile;
        for v in [t.x, t.y, t.width, t.height] {
            self.u32(v);
        }
        let p = &result.pixels;
        let pixels = p.len();
        self.u32(pixels as u32);
        self.0.reserve(pixels * PIXEL_BYTES + 8 + 11 * 8);
        for i in 0..pixels {
            self.vec3(p.sums[i]);
            self.u32(p.counts[i]);
            self.vec3(p.albedo_sums[i]);
            self.vec3(p.emission_sums[i]);
            let s = p.surfaces[i];
            self.f32(s.depth);
            self.vec3(s.position);
            self.vec3(s.normal);
            self.u32(s.shader);
        }
        self.u64(result.rejected);
        let s = &result.stats;
        for v in [
            s.closest_rays,
            s.any_rays,
            s.nodes_visited,
            s.primitive_tests,
            s.filter_tests,
            s.texture_alpha_tests,
            s.filter_rejections,
            s.closest_filter_rejections,
            s.holes_passed,
            s.opaque_holes,
            s.cached_occlusions,
        ] {
            self.u64(v);
        }
    }
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    fn remaining(&self) -> usize {
        self.bytes.len() - self.at
    }
    fn take<const N: usize>(&mut self) -> Result<[u8; N], Malformed> {
        let end = self.at.checked_add(N).ok_or(Malformed)?;
        let bytes = self.bytes.get(self.at..end).ok_or(Malformed)?;
        self.at = end;
        Ok(bytes.try_into().expect("the slice has N bytes"))
    }
    fn u8(&mut self) -> Result<u8, Malformed> {
        Ok(self.take::<1>()?[0])
    }
    fn u32(&mut self) -> Result<u32, Malformed> {
        Ok(u32::from_le_bytes(self.take()?))
    }
    fn u64(&mut self) -> Result<u64, Malformed> {
        Ok(u64::from_le_bytes(self.take()?))
    }
    fn f32(&mut self) -> Result<f32, Malformed> {
        Ok(f32::from_bits(self.u32()?))
    }
    fn vec3(&mut self) -> Result<Vec3, Malformed> {
        Ok(Vec3::new(self.f32()?, self.f32()?, self.f32()?))
    }
    fn text(&mut self) -> Result<String, Malformed> {
        String::from_utf8(self.blob()?).map_err(|_| Malformed)
    }
    fn blob(&mut self) -> Result<Vec<u8>, Malformed> {
        let len = self.u32()? as usize;
        if len > self.remaining() {
            return Err(Malformed);
        }
        let bytes = self.bytes[self.at..self.at + len].to_vec();
        self.at += len;
        Ok(bytes)
    }
    fn tile_result(&mut self) -> Result<TileResult, Malformed> {
        let tile = Tile {
            x: self.u32()?,
            y: self.u32()?,
            width: self.u32()?,
            height: self.u32()?,
        };
        let pixels = self.u32()? as usize;
        if pixels != tile.pixel_count() || pixels > self.remaining() / PIXEL_BYTES {
            return Err(Malformed);
        }
        let mut result = TileResult {
            tile,
            pixels: PixelSums::with_capacity(pixels),
            rejected: 0,
            stats: TraversalStats::default(),
        };
        for _ in 0..pixels {
            let (sum, count, albedo_sum, emission_sum) =
                (self.vec3()?, self.u32()?, self.vec3()?, self.vec3()?);
            let surface = SurfaceGuide {
                depth: self.f32()?,
                position: self.vec3()?,
                normal: self.vec3()?,
                shader: self.u32()?,
            };
            result
                .pixels
                .push(sum, count, albedo_sum, emission_sum, surface);
        }
        result.rejected = self.u64()?;
        let s = &mut result.stats;
        for v in [
            &mut s.closest_rays,
            &mut s.any_rays,
            &mut s.nodes_visited,
            &mut s.primitive_tests,
            &mut s.filter_tests,
            &mut s.texture_alpha_tests,
            &mut s.filter_rejections,
            &mut s.closest_filter_rejections,
            &mut s.holes_passed,
            &mut s.opaque_holes,
            &mut s.cached_occlusions,
        ] {
            *v = self.u64()?;
        }
        Ok(result)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tile_result() -> TileResult {
        let tile = Tile {
            x: 16,
            y: 32,
            width: 3,
            height: 2,
        };
        let n = tile.pixel_count();
        let odd = [f32::NAN, -0.0, f32::INFINITY, 1e-42, 3.5, -7.25];
        TileResult {
            tile,
            pixels: PixelSums {
                sums: (0..n).map(|i| Vec3::new(odd[i], i as f32, 0.1)).collect(),
                counts: (0..n as u32).collect(),
                albedo_sums: (0..n).map(|i| Vec3::splat(i as f32 * 0.3)).collect(),
                emission_sums: (0..n).map(|i| Vec3::new(0.0, odd[5 - i], 2.0)).collect(),
                surfaces: (0..n)
                    .map(|i| {
                        if i == 2 {
                            SurfaceGuide::NONE
                        } else {
                            SurfaceGuide {
                                depth: i as f32,
                                position: Vec3::new(1.0, 2.0, odd[i]),
                                normal: Vec3::Y,
                                shader: i as u32,
                            }
                        }
                    })
                    .collect(),
            },
            rejected: 7,
            stats: TraversalStats {
                closest_rays: 1,
                any_rays: 2,
                nodes_visited: 3,
                primitive_tests: 4,
                filter_tests: 5,
                texture_alpha_tests: 6,
                filter_rejections: 7,
                closest_filter_rejections: 8,
                holes_passed: 9,
                opaque_holes: u64::MAX,
                cached_occlusions: 10,
            },
        }
    }

    /// Equal bits, so NaN payloads and the sign of zero count.
    fn same_bits(a: &TileResult, b: &TileResult) -> bool {
        let bits = |v: &[Vec3]| -> Vec<u32> {
            v.iter()
                .flat_map(|v| v.to_array().map(f32::to_bits))
                .collect()
        };
        let surface_bits = |s: &[SurfaceGuide]| -> Vec<u32> {
            s.iter()
                .flat_map(|s| {
                    let mut v = vec![s.depth.to_bits(), s.shader];
                    v.extend(s.position.to_array().map(f32::to_bits));
                    v.extend(s.normal.to_array().map(f32::to_bits));
                    v
                })
                .collect()
        };
        a.tile == b.tile
            && bits(&a.pixels.sums) == bits(&b.pixels.sums)
            && a.pixels.counts == b.pixels.counts
            && bits(&a.pixels.albedo_sums) == bits(&b.pixels.albedo_sums)
            && bits(&a.pixels.emission_sums) == bits(&b.pixels.emission_sums)
            && surface_bits(&a.pixels.surfaces) == surface_bits(&b.pixels.surfaces)
            && a.rejected == b.rejected
            && a.stats == b.stats
    }

    #[test]
    fn every_message_reads_back_as_written_bit_for_bit() {
        let result = tile_result();
        let messages = [
            Message::Loaded { error: None },
            Message::Loaded {
                error: Some("cannot read «forest.toml»".into()),
            },
            Message::Go,
            Message::Ready {
                phase: 2,
                job: 3,
                checks: FrameChecks {
                    frame: 9,
                    scene: u64::MAX,
                    view: 17,
                },
                tiles: 1_200,
                want: 2,
            },
            Message::Tiles {
                job: 1 << 40,
                runs: vec![(0, 4), (5, 1), (u32::MAX, 2)],
            },
            Message::Result {
                job: 4,
                first: 11,
                tiles: vec![(123_456, result.clone()), (7, result.clone())],
                want: 1,
            },
            Message::Done { job: 8 },
            Message::Stop { next_job: 5 },
            Message::Fail {
                text: "rank 2: disk full".into(),
            },
            Message::Share { value: u64::MAX },
            Message::Step {
                edits: vec![vec![], vec![1, 2, 3], vec![255; 40]],
                next: LiveStep::Render,
            },
            Message::Step {
                edits: Vec::new(),
                next: LiveStep::Idle,
            },
            Message::Step {
                edits: vec![vec![0]],
                next: LiveStep::Quit,
            },
            Message::Left,
            Message::Halted { phase: u32::MAX },
        ];
        for message in messages {
            let decoded = Message::decode(&message.encode()).expect("reads back");
            match (&message, &decoded) {
                (
                    Message::Result { tiles: a, .. },
                    Message::Result {
                        tiles: b,
                        job,
                        first,
                        want,
                    },
                ) => {
                    assert_eq!(a.len(), b.len());
                    for ((nanos_a, a), (nanos_b, b)) in a.iter().zip(b) {
                        assert!(same_bits(a, b));
                        assert_eq!(nanos_a, nanos_b);
                    }
                    assert_eq!((*job, *first, *want), (4, 11, 1));
                }
                _ => assert_eq!(decoded, message),
            }
        }
    }

    #[test]
    fn truncated_extended_and_unknown_messages_are_malformed() {
        let bytes = Message::Result {
            job: 1,
            first: 2,
            tiles: vec![(3, tile_result())],
            want: 1,
        }
        .encode();
        for len in 0..bytes.len() {
            assert_eq!(
                Message::decode(&bytes[..len]),
                Err(Malformed),
                "{len} bytes"
            );
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert_eq!(Message::decode(&longer), Err(Malformed));
        assert_eq!(Message::decode(&[200]), Err(Malformed));
        // A tile count larger than the bytes that follow is refused before allocating.
        let mut tiles = vec![3];
        tiles.extend_from_slice(&0u64.to_le_bytes());
        tiles.extend_from_slice(&u32::MAX.to_le_bytes());
        assert_eq!(Message::decode(&tiles), Err(Malformed));
        let step = Message::Step {
            edits: vec![vec![7; 9], vec![]],
            next: LiveStep::Idle,
        }
        .encode();
        for len in 0..step.len() {
            assert_eq!(Message::decode(&step[..len]), Err(Malformed), "{len} bytes");
        }
        let mut unknown_step = step.clone();
        unknown_step[1] = 3;
        assert_eq!(Message::decode(&unknown_step), Err(Malformed));
    }
}
