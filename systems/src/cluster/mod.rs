//! Cluster rendering: several processes (ranks) hold the same world and run the same
//! schedule; each frame's tiles are handed out on demand by rank 0, which renders too
//! and gathers every tile into its frame buffer, so its film is bit for bit the one a
//! single process makes (a tile depends only on the scene, the camera, the settings and
//! the frame index, and every rank checks it has the same ones before it renders).
//!
//! The protocol runs over a [`Transport`]: MPI with the `mpi` feature
//! (`mpi::MpiTransport`), or in-process channels ([`ChannelTransport`], threads as
//! ranks, for tests and for trying the protocol without MPI). Insert a [`Cluster`]
//! resource and [`render_tiles`](crate::render_tiles) shares its frames out; without it
//! nothing here runs.
//!
//! Every wait has a time limit: a rank that stops answering ends the run with a
//! [`ClusterError`] naming it instead of a hang.

mod checks;
mod error;
mod lead;
pub mod model;
#[cfg(feature = "mpi")]
pub mod mpi;
mod serve;
mod transport;
mod wire;

pub use checks::{scene_hash, view_hash};
pub use error::{ClusterCounters, ClusterError};
pub use transport::{ChannelTransport, Transport};
pub use wire::FrameChecks;

use checks::compare_checks;
use lead::{Away, WorkerState};
use transport::{receive_counted, send_counted};

use bevy_ecs::prelude::*;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, mpsc};
use std::time::{Duration, Instant};
use sylva_engine::film::{FrameBuffer, Tile, TileResult};
use sylva_engine::fingerprint::Fingerprint;
use sylva_engine::geometry::GeometryLibrary;
use sylva_engine::light::LightSet;
use sylva_engine::shading::ShaderTable;
use sylva_engine::tlas::TopLevel;
use wire::Message;

/// How long a poll waits before it looks for messages again, when nothing else is to
/// be done.
const POLL: Duration = Duration::from_micros(200);

/// How long rank 0's polling thread sleeps while its own threads render.
const POLL_BUSY: Duration = Duration::from_millis(2);

/// Runs a worker asks for beyond one per thread: its threads keep rendering while rank
/// 0 takes a result and answers, which may take [`POLL_BUSY`].
const RESERVE_RUNS: u32 = 2;

/// The longest a worker sleeps while its threads render (it wakes when one is done).
const WORKER_WAKE: Duration = Duration::from_millis(50);

/// Tiles handed out together: consecutive in the grid, so fewer messages and wake-ups.
const RUN_TILES: usize = 4;

/// The grid indices of run `run` of a frame of `tiles` tiles.
fn run_tiles(run: usize, tiles: usize) -> std::ops::Range<usize> {
    let first = (run * RUN_TILES).min(tiles);
    first..(first + RUN_TILES).min(tiles)
}

/// What a live render's workers do after applying the edits of a [`Cluster::announce`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LiveStep {
    /// Render the next frame with rank 0.
    Render,
    /// Nothing: rank 0 is idle and says it is still there.
    Idle,
    /// The window closed: leave the loop.
    Quit,
}

/// How a frame shared out ended on this rank.
enum FrameEnd<T> {
    /// Every tile is back (on a worker: every tile it was given).
    Done(T),
    /// The stop flag, or rank 0's stop, ended the run.
    Stopped,
    /// The frame was given up for a newer one (the cancel flag).
    Cancelled,
}

/// Renders one tile of the frame being shared out.
pub type TileRenderer<'a> = dyn Fn(Tile) -> TileResult + Sync + 'a;

/// This process's place in a cluster run: insert it as a resource and
/// [`render_tiles`](crate::render_tiles) shares every frame out over its transport.
///
/// Frames are pipelined: a worker done with its share of a frame starts on the next
/// one at once, handed runs of it by rank 0 while rank 0 still finishes the current
/// frame and then does its part between frames (a thread of its own keeps answering
/// the workers meanwhile). Rank 0 keeps those tiles until its own schedule reaches that
/// frame and has checked that the workers rendered what it would.
#[derive(Resource)]
pub struct Cluster {
    transport: Arc<dyn Transport>,
    rank: usize,
    size: usize,
    timeout: Duration,
    next_job: u64,
    /// Phases of the run rank 0 has ended with [`finish`](Self::finish).
    phase: u32,
    /// Workers' ready messages for a job rank 0 has not started and not opened ahead
    /// (a later one, or the next when no frames were said to follow), kept for it.
    deferred: Vec<(usize, Message)>,
    /// The job rank 0 starts next, opened ahead of it by a worker ready for it.
    ahead: Option<Job>,
    /// Rank 0's thread serving the workers between frames, while it has the transport.
    away: Option<Away>,
    /// Counters of the time between frames, for the next frame's.
    carried: ClusterCounters,
    /// Rank 0's driver expects frames after the ones it is rendering.
    frames_follow: bool,
    stop: Arc<AtomicBool>,
    failure: Option<ClusterError>,
    /// The latest frame's counters.
    pub last_frame: ClusterCounters,
    /// Counters summed over the run.
    pub total: ClusterCounters,
}

impl Drop for Cluster {
    fn drop(&mut self) {
        // The transport must not be in use when MPI finishes after this.
        let _ = self.reclaim();
    }
}

impl Cluster {
    /// This process's place in the run over `transport`; no wait lasts longer than
    /// `timeout`. `stop` is set when the run must end: on a worker when rank 0 says so,
    /// on any rank when the run fails (pass it as the progressive driver's interrupt).
    pub fn new(transport: Box<dyn Transport>, timeout: Duration, stop: Arc<AtomicBool>) -> Self {
        let (rank, size) = (transport.rank(), transport.size());
        Self {
            transport: Arc::from(transport),
            rank,
            size,
            timeout,
            next_job: 0,
            phase: 0,
            deferred: Vec::new(),
            ahead: None,
            away: None,
            carried: ClusterCounters::default(),
            frames_follow: true,
            stop,
            failure: None,
            last_frame: ClusterCounters::default(),
            total: ClusterCounters::default(),
        }
    }

    /// This process's rank.
    pub fn rank(&self) -> usize {
        self.rank
    }

    /// Ranks in the run.
    pub fn size(&self) -> usize {
        self.size
    }

    /// True on rank 0, which leads the run and writes its results.
    pub fn leads(&self) -> bool {
        self.rank() == 0
    }

    /// The flag set when the run must end.
    pub fn stop_flag(&self) -> Arc<AtomicBool> {
        self.stop.clone()
    }

    /// Why the run failed, if it did.
    pub fn failure(&self) -> Option<&ClusterError> {
        self.failure.as_ref()
    }

    /// Every rank says whether its scene built; rank 0 answers all. Returns the first
    /// failed rank's error (on rank 0 with the rank, on the others rank 0's verdict).
    pub fn agree_loaded(&mut self, loaded: Result<(), String>) -> Result<(), ClusterError> {
        if !self.leads() {
            // A rank that failed waits for the verdict too: leaving early would end
            // the run before rank 0 can say which rank failed and why.
            self.send(
                0,
                &Message::Loaded {
                    error: loaded.err(),
                },
            )?;
            let start = Instant::now();
            loop {
                match self.receive()? {
                    Some((0, Message::Go)) => return Ok(()),
                    Some((0, Message::Fail { text })) => {
                        return Err(ClusterError::Failed {
                            rank: 0,
                            error: text,
                        });
                    }
                    Some((rank, message)) => return Err(unexpected(rank, &message)),
                    None => {}
                }
                self.check_silence(0, start.elapsed(), 0)?;
                std::thread::sleep(POLL);
            }
        }
        let mut heard = vec![false; self.size()];
        heard[0] = true;
        let mut first_error = loaded
            .err()
            .map(|error| ClusterError::LoadFailed { rank: 0, error });
        let start = Instant::now();
        while heard.iter().any(|h| !h) {
            match self.receive()? {
                Some((rank, Message::Loaded { error })) if !heard[rank] => {
                    heard[rank] = true;
                    if let Some(error) = error
                        && first_error.is_none()
                    {
                        first_error = Some(ClusterError::LoadFailed { rank, error });
                    }
                }
                Some((rank, message)) => return Err(unexpected(rank, &message)),
                None => {
                    if let Some(rank) = heard.iter().position(|h| !h) {
                        self.check_silence(rank, start.elapsed(), 0)?;
                    }
                    std::thread::sleep(POLL);
                }
            }
        }
        let verdict = match &first_error {
            None => Message::Go,
            Some(error) => Message::Fail {
                text: error.to_string(),
            },
        };
        for rank in 1..self.size() {
            self.send(rank, &verdict)?;
        }
        first_error.map_or(Ok(()), Err)
    }

    /// Rank 0 ends the run, or a phase of it: the workers' drivers stop (their stop
    /// flag is set) and leave the frame they stood ready for. Does nothing elsewhere.
    pub fn finish(&mut self) -> Result<(), ClusterError> {
        if !self.leads() {
            return Ok(());
        }
        let phase = self.phase;
        let holding = self.end_phase()?;
        // A worker holding runs of a frame it started ahead may be sending their tiles:
        // take what comes until it says it has stopped, so that none is left blocked in
        // a send to a rank 0 that has moved on or gone. (Other workers are waiting for
        // a frame, or have left on their own count of frames.) After a failure the
        // workers have been told to leave instead.
        if self.failure.is_none() {
            self.await_halted(phase, holding)?;
        }
        let carried = std::mem::take(&mut self.carried);
        self.total.add(&carried);
        Ok(())
    }

    /// Rank 0 takes messages until each of the workers `holding` has answered the stop
    /// of `phase`.
    fn await_halted(&mut self, phase: u32, holding: Vec<usize>) -> Result<(), ClusterError> {
        let mut halted = vec![true; self.size];
        for rank in holding {
            halted[rank] = false;
        }
        let mut last_heard = vec![Instant::now(); self.size];
        while let Some(waiting) = halted.iter().position(|h| !h) {
            match self.receive()? {
                Some((rank, Message::Halted { phase: p })) if p == phase => halted[rank] = true,
                Some((rank, Message::Fail { text })) => {
                    return Err(self.fail_run(ClusterError::Failed { rank, error: text }));
                }
                // A worker already on into the next phase.
                Some((rank, message @ Message::Ready { phase: p, .. })) if p == self.phase => {
                    last_heard[rank] = Instant::now();
                    self.deferred.push((rank, message));
                }
                // Tiles of the dropped job, ready messages of the ended phase, answers
                // to earlier stops.
                Some((rank, _)) => last_heard[rank] = Instant::now(),
                None => {
                    if let Err(error) =
                        self.check_silence(waiting, last_heard[waiting].elapsed(), 0)
                    {
                        return Err(self.fail_run(error));
                    }
                    std::thread::sleep(POLL);
                }
            }
        }
        Ok(())
    }

    /// Rank 0 tells every worker to leave the job it is on or stands ready for.
    /// Returns the workers that held runs of a job opened ahead, now dropped.
    fn end_phase(&mut self) -> Result<Vec<usize>, ClusterError> {
        self.reclaim()?;
        let mut holding = Vec::new();
        // A job opened ahead ends with its number unused: its tiles still on the way
        // are then recognisably stale.
        if let Some(ahead) = self.ahead.take() {
            self.next_job += 1;
            holding = (1..self.size)
                .filter(|&rank| ahead.workers[rank].outstanding > 0)
                .collect();
        }
        let next_job = self.next_job;
        for rank in 1..self.size() {
            self.send(rank, &Message::Stop { next_job })?;
        }
        self.phase += 1;
        self.deferred.clear();
        Ok(holding)
    }

    /// Rank 0 of a live render sends every worker the edits it applied since the last
    /// step, in order, and what to do next: render a frame with it, nothing (a sign of
    /// life while it idles, more often than the time limit), or quit. On quit it waits
    /// until every worker has left, taking what they still send (tiles of a frame given
    /// up): a worker must not be left blocked in a send to a rank that has gone.
    pub fn announce(&mut self, edits: &[Vec<u8>], next: LiveStep) -> Result<(), ClusterError> {
        let message = Message::Step {
            edits: edits.to_vec(),
            next,
        };
        for rank in 1..self.size() {
            self.send(rank, &message)?;
        }
        if next != LiveStep::Quit {
            return Ok(());
        }
        let mut left = vec![false; self.size()];
        left[0] = true;
        let start = Instant::now();
        while let Some(rank) = left.iter().position(|l| !l) {
            match self.receive()? {
                Some((rank, Message::Left)) => left[rank] = true,
                Some((rank, Message::Fail { text })) => {
                    return Err(ClusterError::Failed { rank, error: text });
                }
                Some(_) => {}
                None => {
                    self.check_silence(rank, start.elapsed(), 0)?;
                    std::thread::sleep(POLL);
                }
            }
        }
        Ok(())
    }

    /// A worker of a live render waits for rank 0's next step: the edits to apply and
    /// what to do then (a quit is answered at once: rank 0 waits for it). Failures (rank 0 silent for longer than the time limit, or its
    /// error) are returned and remembered.
    pub fn await_step(&mut self) -> Result<(Vec<Vec<u8>>, LiveStep), ClusterError> {
        let start = Instant::now();
        let step = loop {
            match self.receive() {
                Ok(Some((0, Message::Step { edits, next }))) => {
                    if next == LiveStep::Quit
                        && let Err(error) = self.send(0, &Message::Left)
                    {
                        break Err(error);
                    }
                    break Ok((edits, next));
                }
                // The frame a stop gave up had ended here already: nothing to leave.
                Ok(Some((0, Message::Stop { next_job }))) => {
                    if let Err(error) = self.halt(next_job) {
                        break Err(error);
                    }
                }
                Ok(Some((rank, Message::Fail { text }))) => {
                    break Err(ClusterError::Failed { rank, error: text });
                }
                Ok(Some((rank, message))) => break Err(unexpected(rank, &message)),
                Ok(None) => {
                    if let Err(error) = self.check_silence(0, start.elapsed(), 0) {
                        break Err(error);
                    }
                    std::thread::sleep(POLL);
                }
                Err(error) => break Err(error),
            }
        };
        if let Err(error) = &step {
            self.failure = Some(error.clone());
            self.stop.store(true, Ordering::SeqCst);
        }
        step
    }

    /// Rank 0's driver says whether frames follow the ones it is about to render: only
    /// then does a worker done with its share of a frame start on the next one ahead of
    /// rank 0. A hint: a wrong one costs time (workers wait, or render a frame that is
    /// then dropped), never a pixel. Workers ignore it.
    pub fn frames_follow(&mut self, follow: bool) {
        self.frames_follow = follow;
    }

    /// A worker leaves the job rank 0's stop ended: says so (nothing of it follows),
    /// and goes on to the next phase, whose first job is `next_job`.
    fn halt(&mut self, next_job: u64) -> Result<(), ClusterError> {
        self.send(0, &Message::Halted { phase: self.phase })?;
        self.next_job = next_job;
        self.phase += 1;
        Ok(())
    }

    /// A worker goes on into rank 0's next phase after [`finish`](Self::finish) ended
    /// one: its stop flag is cleared. Nothing to do after a failure.
    pub fn resume(&mut self) {
        if self.failure.is_none() {
            self.stop.store(false, Ordering::SeqCst);
        }
    }

    /// Rank 0's `value` on every rank: rank 0 sends it, the others wait for it.
    pub fn share(&mut self, value: u64) -> Result<u64, ClusterError> {
        if self.leads() {
            for rank in 1..self.size() {
                self.send(rank, &Message::Share { value })?;
            }
            return Ok(value);
        }
        let start = Instant::now();
        loop {
            match self.receive()? {
                Some((0, Message::Share { value })) => return Ok(value),
                Some((rank, Message::Fail { text })) => {
                    return Err(ClusterError::Failed { rank, error: text });
                }
                Some((rank, message)) => return Err(unexpected(rank, &message)),
                None => {}
            }
            self.check_silence(0, start.elapsed(), 0)?;
            std::thread::sleep(POLL);
        }
    }

    /// Tells every other rank (rank 0 on a worker) that this one ends the run with
    /// `error`; delivery failures are ignored, the run is ending anyway.
    pub fn abandon(&mut self, error: &str) {
        let ranks: Vec<usize> = if self.leads() {
            (1..self.size()).collect()
        } else {
            vec![0]
        };
        for rank in ranks {
            let _ = self.send(
                rank,
                &Message::Fail {
                    text: error.to_owned(),
                },
            );
        }
    }

    /// One frame, shared out: on rank 0 the whole frame, on a worker a frame buffer
    /// holding only the tiles it rendered. `None` when the run ends instead (the stop
    /// flag is then set, and [`failure`](Self::failure) says why if it failed).
    #[expect(
        clippy::too_many_arguments,
        reason = "the frame's identity, its work and its reporting"
    )]
    pub fn render_frame(
        &mut self,
        pool: &rayon::ThreadPool,
        width: u32,
        height: u32,
        tiles: &[Tile],
        checks: FrameChecks,
        render: &TileRenderer,
        on_tile: &(dyn Fn(&Tile, Duration) + Sync),
        cancel: Option<&AtomicBool>,
    ) -> Option<FrameBuffer> {
        if self.reclaim().is_err() || self.failure.is_some() {
            return None;
        }
        self.last_frame = ClusterCounters {
            frames: 1,
            ..std::mem::take(&mut self.carried)
        };
        let outcome = if self.leads() {
            self.lead(pool, tiles, checks, render, on_tile, cancel)
        } else {
            self.serve(pool, tiles, checks, render)
                .map(|served| match served {
                    Some(results) => FrameEnd::Done(results),
                    None => FrameEnd::Stopped,
                })
        };
        self.total.add(&self.last_frame);
        match outcome {
            Ok(FrameEnd::Done(results)) => {
                if self.leads() {
                    self.dispatch_until_next_frame();
                }
                let mut frame = FrameBuffer::new(width, height, checks.frame);
                for result in &results {
                    frame.write_tile(result);
                }
                Some(frame)
            }
            Ok(FrameEnd::Cancelled) => None,
            Ok(FrameEnd::Stopped) => {
                self.stop.store(true, Ordering::SeqCst);
                None
            }
            Err(error) => {
                self.fail_run(error);
                None
            }
        }
    }
}

/// Rank 0's state of a job (a frame shared out): its frame in progress, or the next
/// one opened ahead of it.
struct Job {
    number: u64,
    tile_count: usize,
    /// The next run of tiles to hand out (rank 0's threads take from it too).
    next: Arc<AtomicUsize>,
    /// Runs in the frame.
    runs: usize,
    /// The worker each run handed out and not yet back is with.
    owners: Vec<Option<usize>>,
    results: Vec<Option<TileResult>>,
    /// Tiles that came back before rank 0 started the job: grid index, sender, render
    /// time (checked and reported when it starts).
    early: Vec<(usize, usize, Duration)>,
    received: usize,
    workers: Vec<WorkerState>,
}

impl Job {
    /// Job `number`, of `tile_count` tiles, none handed out, among `size` ranks.
    fn new(number: u64, tile_count: usize, size: usize) -> Job {
        let runs = tile_count.div_ceil(RUN_TILES);
        Job {
            number,
            tile_count,
            next: Arc::new(AtomicUsize::new(0)),
            runs,
            owners: vec![None; runs],
            results: (0..tile_count).map(|_| None).collect(),
            early: Vec::new(),
            received: 0,
            workers: vec![WorkerState::default(); size],
        }
    }

    /// Up to `want` more runs for `rank`, or word that the job is done for it once the
    /// runs are all handed out and it has returned its own; `None` when neither.
    fn assign(&mut self, rank: usize, want: u32) -> Option<Message> {
        let mut given = Vec::new();
        while given.len() < want as usize {
            let run = self.next.fetch_add(1, Ordering::Relaxed);
            if run >= self.runs {
                break;
            }
            self.owners[run] = Some(rank);
            let tiles = run_tiles(run, self.tile_count);
            given.push((tiles.start as u32, tiles.len() as u32));
        }
        let worker = &mut self.workers[rank];
        if !given.is_empty() {
            worker.outstanding += given.len();
            Some(Message::Tiles {
                job: self.number,
                runs: given,
            })
        } else if worker.outstanding == 0 && !worker.done_sent {
            worker.done_sent = true;
            Some(Message::Done { job: self.number })
        } else {
            None
        }
    }

    /// Takes back a run of tiles `rank` rendered from grid index `first` on, once it
    /// is one the rank was given; returns each tile's grid index and render time.
    fn take_run(
        &mut self,
        rank: usize,
        first: u32,
        tiles: Vec<(u64, TileResult)>,
    ) -> Result<Vec<(usize, Duration)>, ClusterError> {
        let first = first as usize;
        let run = first / RUN_TILES;
        let expected = run_tiles(run, self.tile_count);
        if !first.is_multiple_of(RUN_TILES)
            || run >= self.runs
            || self.owners[run] != Some(rank)
            || tiles.len() != expected.len()
        {
            return Err(ClusterError::Protocol {
                rank,
                problem: format!("tiles from {first} on were not its to return"),
            });
        }
        self.owners[run] = None;
        self.workers[rank].outstanding -= 1;
        let mut taken = Vec::with_capacity(tiles.len());
        for (index, (nanos, result)) in expected.zip(tiles) {
            self.results[index] = Some(result);
            self.received += 1;
            taken.push((index, Duration::from_nanos(nanos)));
        }
        Ok(taken)
    }
}

fn unexpected(rank: usize, message: &Message) -> ClusterError {
    let name = match message {
        Message::Loaded { .. } => "a scene-loaded report",
        Message::Go => "a start",
        Message::Ready { .. } => "a ready message",
        Message::Tiles { .. } => "tiles",
        Message::Result { .. } => "a tile",
        Message::Done { .. } => "a frame end",
        Message::Stop { .. } => "a stop",
        Message::Share { .. } => "a shared value",
        Message::Step { .. } => "a live step",
        Message::Left => "a farewell",
        Message::Halted { .. } => "a stop's answer",
        Message::Fail { .. } => "a failure",
    };
    ClusterError::Protocol {
        rank,
        problem: format!("{name} arrived out of turn"),
    }
}
