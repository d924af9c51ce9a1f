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

pub mod model;
#[cfg(feature = "mpi")]
pub mod mpi;
mod wire;

pub use wire::FrameChecks;

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

/// Moves messages between the ranks of a cluster run.
pub trait Transport: Send + Sync {
    /// This process's rank, `0..size`; rank 0 leads.
    fn rank(&self) -> usize;
    /// Ranks in the run.
    fn size(&self) -> usize;
    /// Sends `bytes` to rank `to`; an error says why it could not be delivered.
    fn send(&self, to: usize, bytes: &[u8]) -> Result<(), String>;
    /// A message that has arrived and its sender, without waiting.
    fn try_receive(&self) -> Option<(usize, Vec<u8>)>;
}

/// Why a cluster run ended early.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ClusterError {
    /// A rank could not build the scene.
    LoadFailed {
        /// The rank.
        rank: usize,
        /// Its error.
        error: String,
    },
    /// A rank is about to render something else than rank 0.
    Mismatch {
        /// The rank.
        rank: usize,
        /// What differs.
        what: &'static str,
    },
    /// A rank sent nothing for longer than the time limit while rank 0 waited for it.
    Silent {
        /// The rank.
        rank: usize,
        /// How long it was silent.
        waited: Duration,
        /// Tiles it had been given and not returned.
        outstanding: usize,
    },
    /// A rank ended the run with an error of its own.
    Failed {
        /// The rank.
        rank: usize,
        /// Its error.
        error: String,
    },
    /// A message could not be read, or came when the protocol does not allow it.
    Protocol {
        /// Its sender.
        rank: usize,
        /// What was wrong.
        problem: String,
    },
    /// A message could not be sent.
    Send {
        /// The rank it was for.
        rank: usize,
        /// Why.
        reason: String,
    },
}

impl std::fmt::Display for ClusterError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ClusterError::LoadFailed { rank, error } => {
                write!(f, "rank {rank} could not build the scene: {error}")
            }
            ClusterError::Mismatch { rank, what } => write!(
                f,
                "rank {rank} would render a different {what} than rank 0: every rank must \
                 be given the same files and arguments (is a file different on its node?)"
            ),
            ClusterError::Silent {
                rank,
                waited,
                outstanding,
            } => write!(
                f,
                "rank {rank} sent nothing for {:.1} s ({outstanding} tiles outstanding): it \
                 died, hangs, or cannot reach rank 0",
                waited.as_secs_f64()
            ),
            ClusterError::Failed { rank, error } => write!(f, "rank {rank} failed: {error}"),
            ClusterError::Protocol { rank, problem } => {
                write!(f, "rank {rank} broke the protocol: {problem}")
            }
            ClusterError::Send { rank, reason } => {
                write!(f, "could not send to rank {rank}: {reason}")
            }
        }
    }
}

impl std::error::Error for ClusterError {}

/// What the cluster did in a frame (or, summed, in a run), as seen from this rank.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ClusterCounters {
    /// Frames shared out.
    pub frames: u64,
    /// Bytes this rank sent.
    pub bytes_sent: u64,
    /// Bytes this rank received.
    pub bytes_received: u64,
    /// Tiles this rank rendered.
    pub tiles_here: u64,
    /// Tiles other ranks rendered (counted on rank 0).
    pub tiles_elsewhere: u64,
    /// Of those, tiles rendered before rank 0 started their frame (pipelined).
    pub tiles_ahead: u64,
    /// Time this rank's threads had no tile to render while the frame was not done: on
    /// rank 0 from its last local tile to the last tile back, on a worker while it had
    /// none in hand.
    pub waited: Duration,
}

impl ClusterCounters {
    fn add(&mut self, other: &ClusterCounters) {
        self.frames += other.frames;
        self.bytes_sent += other.bytes_sent;
        self.bytes_received += other.bytes_received;
        self.tiles_here += other.tiles_here;
        self.tiles_elsewhere += other.tiles_elsewhere;
        self.tiles_ahead += other.tiles_ahead;
        self.waited += other.waited;
    }
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

    /// Rank 0's side of a frame: its own threads take runs of tiles from the same
    /// counter the workers are served from. Ends early when the stop flag is set
    /// (Ctrl-C) or `cancel` is (the frame is given up on every rank).
    fn lead(
        &mut self,
        pool: &rayon::ThreadPool,
        tiles: &[Tile],
        checks: FrameChecks,
        render: &TileRenderer,
        on_tile: &(dyn Fn(&Tile, Duration) + Sync),
        cancel: Option<&AtomicBool>,
    ) -> Result<FrameEnd<Vec<TileResult>>, ClusterError> {
        let number = self.next_job;
        self.next_job += 1;
        let job = self.start_job(number, tiles, checks, on_tile)?;
        let next = job.next.clone();
        let runs = job.runs;
        let give_up = AtomicBool::new(false);
        let local_busy = AtomicUsize::new(pool.current_num_threads());
        let (sender, local) = mpsc::channel::<(usize, TileResult)>();
        let mut lead = Lead { job, checks, tiles };
        let outcome = pool.in_place_scope(|scope| {
            for _ in 0..pool.current_num_threads() {
                let sender = sender.clone();
                let (next, give_up, local_busy) = (&*next, &give_up, &local_busy);
                scope.spawn(move |_| {
                    'runs: loop {
                        let run = next.fetch_add(1, Ordering::Relaxed);
                        if run >= runs {
                            break;
                        }
                        for index in run_tiles(run, tiles.len()) {
                            if give_up.load(Ordering::Relaxed) {
                                break 'runs;
                            }
                            let start = Instant::now();
                            let result = render(tiles[index]);
                            on_tile(&tiles[index], start.elapsed());
                            if sender.send((index, result)).is_err() {
                                break 'runs;
                            }
                        }
                    }
                    local_busy.fetch_sub(1, Ordering::Release);
                });
            }
            drop(sender);
            let outcome = self.lead_loop(&mut lead, &local, &local_busy, on_tile, cancel);
            give_up.store(true, Ordering::Relaxed);
            outcome
        });
        Ok(match outcome? {
            FrameEnd::Done(()) => {
                let results = lead
                    .job
                    .results
                    .into_iter()
                    .map(|r| r.expect("every tile came back"));
                FrameEnd::Done(results.collect())
            }
            FrameEnd::Stopped => FrameEnd::Stopped,
            FrameEnd::Cancelled => FrameEnd::Cancelled,
        })
    }

    /// Rank 0's job `number`: the one workers opened ahead of it, once their checks
    /// equal rank 0's and their tiles are the frame's, or a new one.
    fn start_job(
        &mut self,
        number: u64,
        tiles: &[Tile],
        checks: FrameChecks,
        on_tile: &(dyn Fn(&Tile, Duration) + Sync),
    ) -> Result<Job, ClusterError> {
        let Some(mut job) = self.ahead.take().filter(|job| job.number == number) else {
            return Ok(Job::new(number, tiles.len(), self.size));
        };
        for (rank, worker) in job.workers.iter().enumerate() {
            if let Some(theirs) = worker.checks {
                compare_checks(rank, &checks, &theirs)?;
            }
        }
        if job.tile_count != tiles.len() {
            // Equal view checks mean equal grids; a count that differs is no renderer's.
            let rank = job.workers.iter().position(|w| w.checks.is_some());
            return Err(ClusterError::Protocol {
                rank: rank.unwrap_or(0),
                problem: format!(
                    "it was ready for {} tiles of a frame of {}",
                    job.tile_count,
                    tiles.len()
                ),
            });
        }
        for &(index, rank, time) in &job.early {
            if job.results[index].as_ref().map(|r| r.tile) != Some(tiles[index]) {
                return Err(ClusterError::Protocol {
                    rank,
                    problem: format!("tile {index} came back as another tile"),
                });
            }
            on_tile(&tiles[index], time);
        }
        self.last_frame.tiles_ahead += job.early.len() as u64;
        self.last_frame.tiles_elsewhere += job.early.len() as u64;
        job.early.clear();
        // A worker whose tile count differed from the first one's waited for the checks
        // (which, passed, mean equal frames).
        for rank in 1..self.size {
            let waiting = std::mem::take(&mut job.workers[rank].waiting);
            if waiting > 0
                && let Some(answer) = job.assign(rank, waiting)
            {
                self.send(rank, &answer)?;
            }
        }
        Ok(job)
    }

    /// Polls local results and messages until every tile is back and every worker has
    /// been told the frame is done, or the stop flag or `cancel` ends it first. A
    /// frame is given up only before any worker has been told it is done, so that
    /// every rank gives it up (a worker told so has already kept it, and may be on the
    /// next job).
    fn lead_loop(
        &mut self,
        lead: &mut Lead,
        local: &mpsc::Receiver<(usize, TileResult)>,
        local_busy: &AtomicUsize,
        on_tile: &(dyn Fn(&Tile, Duration) + Sync),
        cancel: Option<&AtomicBool>,
    ) -> Result<FrameEnd<()>, ClusterError> {
        let start = Instant::now();
        for state in &mut lead.job.workers {
            state.last_heard = start;
        }
        let mut pending = std::mem::take(&mut self.deferred);
        pending.reverse();
        let mut waiting_since: Option<Instant> = None;
        loop {
            let mut progressed = false;
            while let Ok((index, result)) = local.try_recv() {
                lead.job.results[index] = Some(result);
                lead.job.received += 1;
                self.last_frame.tiles_here += 1;
                progressed = true;
            }
            loop {
                let next = match pending.pop() {
                    Some(message) => Some(message),
                    None => self.receive()?,
                };
                let Some((rank, message)) = next else { break };
                progressed = true;
                self.lead_message(lead, rank, message, on_tile)?;
            }
            let job = &lead.job;
            let all_told = job.workers.iter().skip(1).all(|w| w.done_sent);
            if job.received == job.tile_count && all_told {
                if let Some(since) = waiting_since {
                    self.last_frame.waited += since.elapsed();
                }
                return Ok(FrameEnd::Done(()));
            }
            if self.stop.load(Ordering::SeqCst) {
                return Ok(FrameEnd::Stopped);
            }
            let none_told = job.workers.iter().all(|w| !w.done_sent);
            if none_told && cancel.is_some_and(|c| c.load(Ordering::SeqCst)) {
                self.end_phase()?;
                return Ok(FrameEnd::Cancelled);
            }
            if progressed {
                continue;
            }
            if local_busy.load(Ordering::Acquire) > 0 {
                // Rank 0's own threads are busy: look at the network every few
                // milliseconds, not at every tile they finish (a worker holds runs in
                // reserve, so it does not wait for the answer); each wake-up takes the
                // core from a render thread.
                std::thread::sleep(POLL_BUSY);
                continue;
            }
            waiting_since.get_or_insert_with(Instant::now);
            let now = Instant::now();
            for (rank, state) in lead.job.workers.iter().enumerate().skip(1) {
                if !state.done_sent {
                    self.check_silence(rank, now - state.last_heard, state.outstanding)?;
                }
            }
            if let Some(ahead) = &self.ahead {
                check_ahead_silence(ahead, self.timeout, now)?;
            }
            std::thread::sleep(POLL);
        }
    }

    /// Rank 0 handles one worker's message during a frame: of the frame, of the next
    /// one (opened ahead), or of a later one (kept for then).
    fn lead_message(
        &mut self,
        lead: &mut Lead,
        rank: usize,
        message: Message,
        on_tile: &(dyn Fn(&Tile, Duration) + Sync),
    ) -> Result<(), ClusterError> {
        lead.job.workers[rank].last_heard = Instant::now();
        let current = lead.job.number;
        match message {
            // A worker's ready message of a phase rank 0 has ended: it was waiting for
            // a frame that never came, and asks again in the new phase.
            Message::Ready { phase, .. } if phase < self.phase => {}
            // The next frame: opened ahead when frames follow (else a ready message is
            // kept for it), its tiles kept for it.
            Message::Ready { job, .. } | Message::Result { job, .. }
                if job == current + 1
                    && (self.frames_follow || matches!(message, Message::Result { .. })) =>
            {
                if let Some(answer) = serve_ahead(&mut self.ahead, job, self.size, rank, message)? {
                    self.send(rank, &answer)?;
                }
            }
            Message::Ready { job, .. } if job > current => {
                self.deferred.push((rank, message));
            }
            Message::Ready {
                job, checks, want, ..
            } if job == current => {
                compare_checks(rank, &lead.checks, &checks)?;
                self.assign(lead, rank, want)?;
            }
            // Tiles of a frame given up: sent before the worker heard so.
            Message::Result { job, .. } if job < current => {}
            Message::Result {
                job,
                first,
                tiles,
                want,
            } if job == current => {
                let taken = lead.job.take_run(rank, first, tiles)?;
                for (index, time) in taken {
                    let result = lead.job.results[index].as_ref();
                    if result.map(|r| r.tile) != Some(lead.tiles[index]) {
                        return Err(ClusterError::Protocol {
                            rank,
                            problem: format!("tile {index} came back as another tile"),
                        });
                    }
                    on_tile(&lead.tiles[index], time);
                    self.last_frame.tiles_elsewhere += 1;
                }
                self.assign(lead, rank, want)?;
            }
            // A worker's answer to a stop that gave a frame up.
            Message::Halted { .. } => {}
            Message::Fail { text } => return Err(ClusterError::Failed { rank, error: text }),
            other => return Err(unexpected(rank, &other)),
        }
        Ok(())
    }

    /// Gives `rank` up to `want` more runs of the frame, or tells it the frame is done.
    fn assign(&mut self, lead: &mut Lead, rank: usize, want: u32) -> Result<(), ClusterError> {
        match lead.job.assign(rank, want) {
            Some(answer) => self.send(rank, &answer),
            None => Ok(()),
        }
    }

    /// Rank 0, its frame done, hands the transport to a thread that keeps serving the
    /// workers until rank 0 next needs it ([`reclaim`](Self::reclaim)): a worker ready
    /// for the next frame is given runs of it at once.
    fn dispatch_until_next_frame(&mut self) {
        if self.size < 2
            || !self.frames_follow
            || self.away.is_some()
            || self.stop.load(Ordering::SeqCst)
        {
            return;
        }
        let desk = Desk {
            transport: self.transport.clone(),
            size: self.size,
            timeout: self.timeout,
            phase: self.phase,
            number: self.next_job,
            deferred: std::mem::take(&mut self.deferred),
            ahead: self.ahead.take(),
            counters: ClusterCounters::default(),
        };
        let halt = Arc::new(AtomicBool::new(false));
        let halted = halt.clone();
        let spawned = std::thread::Builder::new()
            .name("sylva-cluster-desk".into())
            .spawn(move || desk.serve(&halted));
        // Without a thread to spare the workers wait for rank 0's next frame, as
        // without pipelining (the desk went down with the failed spawn).
        if let Ok(handle) = spawned {
            self.away = Some(Away { halt, handle });
        }
    }

    /// Takes the transport back from the thread serving the workers between frames,
    /// with the next job it opened ahead and what else it received. Its failure ends
    /// the run: the other ranks are told, and it is returned.
    fn reclaim(&mut self) -> Result<(), ClusterError> {
        let Some(away) = self.away.take() else {
            return Ok(());
        };
        away.halt.store(true, Ordering::SeqCst);
        away.handle.thread().unpark();
        let (desk, served) = match away.handle.join() {
            Ok(returned) => returned,
            Err(_) => {
                let error = ClusterError::Failed {
                    rank: self.rank,
                    error: "rank 0's thread serving the workers between frames panicked".into(),
                };
                return Err(self.fail_run(error));
            }
        };
        self.deferred = desk.deferred;
        self.ahead = desk.ahead;
        self.carried.add(&desk.counters);
        served.map_err(|error| self.fail_run(error))
    }

    /// Ends the run on `error`: the other ranks are told, the stop flag set.
    fn fail_run(&mut self, error: ClusterError) -> ClusterError {
        self.abandon(&error.to_string());
        self.failure = Some(error.clone());
        self.stop.store(true, Ordering::SeqCst);
        error
    }

    /// A worker's side of a frame: say it is ready, render what rank 0 hands out,
    /// return each run of tiles as it finishes. `None` when rank 0 ended the run
    /// instead.
    fn serve(
        &mut self,
        pool: &rayon::ThreadPool,
        tiles: &[Tile],
        checks: FrameChecks,
        render: &TileRenderer,
    ) -> Result<Option<Vec<TileResult>>, ClusterError> {
        let job = self.next_job;
        self.next_job += 1;
        let threads = pool.current_num_threads();
        self.send(
            0,
            &Message::Ready {
                phase: self.phase,
                job,
                checks,
                tiles: tiles.len() as u32,
                want: threads as u32 + RESERVE_RUNS,
            },
        )?;
        type Run = (usize, Vec<(u64, TileResult)>);
        let (sender, local) = mpsc::channel::<Run>();
        let mut mine = Vec::new();
        let give_up = AtomicBool::new(false);
        let give_up = &give_up;
        pool.in_place_scope(|scope| {
            let mut in_flight = 0usize;
            let mut done = false;
            let mut last_heard = Instant::now();
            let mut idle_since: Option<Instant> = Some(Instant::now());
            let mut finished: Option<Run> = None;
            loop {
                let mut progressed = false;
                while let Some((rank, message)) = self.receive()? {
                    progressed = true;
                    last_heard = Instant::now();
                    match message {
                        Message::Tiles { job: j, runs } if j == job && rank == 0 => {
                            for (first, count) in runs {
                                let (first, count) = (first as usize, count as usize);
                                let Some(run) = tiles.get(first..first.saturating_add(count))
                                else {
                                    return Err(ClusterError::Protocol {
                                        rank,
                                        problem: format!(
                                            "tiles {first}..{} are not in the frame",
                                            first.saturating_add(count)
                                        ),
                                    });
                                };
                                in_flight += 1;
                                let sender = sender.clone();
                                scope.spawn(move |_| {
                                    let mut rendered = Vec::with_capacity(run.len());
                                    for &tile in run {
                                        // A frame given up: the scope ends at the next tile.
                                        if give_up.load(Ordering::Relaxed) {
                                            return;
                                        }
                                        let start = Instant::now();
                                        let result = render(tile);
                                        rendered.push((start.elapsed().as_nanos() as u64, result));
                                    }
                                    let _ = sender.send((first, rendered));
                                });
                            }
                        }
                        Message::Done { job: j } if j == job && rank == 0 => {
                            // What follows (a stop, the next phase) is the next job's.
                            done = true;
                            break;
                        }
                        Message::Stop { next_job } if rank == 0 => {
                            // The job this worker is on, or stood ready for, ends here.
                            give_up.store(true, Ordering::Relaxed);
                            self.halt(next_job)?;
                            return Ok(None);
                        }
                        Message::Fail { text } => {
                            return Err(ClusterError::Failed { rank, error: text });
                        }
                        other => return Err(unexpected(rank, &other)),
                    }
                }
                while let Some((first, rendered)) =
                    finished.take().or_else(|| local.try_recv().ok())
                {
                    in_flight -= 1;
                    progressed = true;
                    self.last_frame.tiles_here += rendered.len() as u64;
                    let message = Message::Result {
                        job,
                        first: first as u32,
                        tiles: rendered,
                        want: 1,
                    };
                    self.send(0, &message)?;
                    if let Message::Result { tiles, .. } = message {
                        mine.extend(tiles.into_iter().map(|(_, result)| result));
                    }
                }
                if in_flight > 0 {
                    if let Some(since) = idle_since.take() {
                        self.last_frame.waited += since.elapsed();
                    }
                } else {
                    if done {
                        if let Some(since) = idle_since.take() {
                            self.last_frame.waited += since.elapsed();
                        }
                        return Ok(Some(()));
                    }
                    idle_since.get_or_insert_with(Instant::now);
                }
                if progressed {
                    continue;
                }
                if in_flight > 0 {
                    // Asleep until a run is done: rank 0's answers can wait for it, as
                    // the worker asked for runs in reserve.
                    finished = local.recv_timeout(WORKER_WAKE).ok();
                } else {
                    self.check_silence(0, last_heard.elapsed(), 0)?;
                    std::thread::sleep(POLL);
                }
            }
        })
        .map(|served| served.map(|()| mine))
    }

    /// Gives up on `rank` once it has been silent longer than the time limit.
    fn check_silence(
        &self,
        rank: usize,
        waited: Duration,
        outstanding: usize,
    ) -> Result<(), ClusterError> {
        if waited > self.timeout {
            Err(ClusterError::Silent {
                rank,
                waited,
                outstanding,
            })
        } else {
            Ok(())
        }
    }

    fn send(&mut self, to: usize, message: &Message) -> Result<(), ClusterError> {
        self.reclaim()?;
        send_counted(&*self.transport, &mut self.last_frame, to, message)
    }

    fn receive(&mut self) -> Result<Option<(usize, Message)>, ClusterError> {
        self.reclaim()?;
        receive_counted(&*self.transport, &mut self.last_frame)
    }
}

/// Sends `message` to rank `to`, counting its bytes.
fn send_counted(
    transport: &dyn Transport,
    counters: &mut ClusterCounters,
    to: usize,
    message: &Message,
) -> Result<(), ClusterError> {
    let bytes = message.encode();
    counters.bytes_sent += bytes.len() as u64;
    transport
        .send(to, &bytes)
        .map_err(|reason| ClusterError::Send { rank: to, reason })
}

/// A message that has arrived and its sender, its bytes counted.
fn receive_counted(
    transport: &dyn Transport,
    counters: &mut ClusterCounters,
) -> Result<Option<(usize, Message)>, ClusterError> {
    let Some((rank, bytes)) = transport.try_receive() else {
        return Ok(None);
    };
    counters.bytes_received += bytes.len() as u64;
    match Message::decode(&bytes) {
        Ok(message) => Ok(Some((rank, message))),
        Err(wire::Malformed) => Err(ClusterError::Protocol {
            rank,
            problem: format!("a message of {} bytes could not be read", bytes.len()),
        }),
    }
}

/// A worker's checks against rank 0's for the same job: every rank renders the same
/// frame of the same scene through the same camera, or the run ends naming the rank.
fn compare_checks(
    rank: usize,
    ours: &FrameChecks,
    theirs: &FrameChecks,
) -> Result<(), ClusterError> {
    // Causes first: a changed scene or view also restarts the frame sequence.
    for (what, ours, theirs) in [
        (
            "scene (geometry, plants, shaders or lights)",
            ours.scene,
            theirs.scene,
        ),
        ("camera view or sampling settings", ours.view, theirs.view),
        (
            "progressive frame",
            u64::from(ours.frame),
            u64::from(theirs.frame),
        ),
    ] {
        if ours != theirs {
            return Err(ClusterError::Mismatch { rank, what });
        }
    }
    Ok(())
}

/// The most tiles a worker's frame may have (a 32k × 32k image in 16-pixel tiles):
/// rank 0 sizes the next job from a worker's word before it can check it.
const MAX_TILES: u32 = 1 << 22;

/// A worker's message for job `number`, the one after rank 0's current frame: a worker
/// ready for it opens it ahead of rank 0 and is handed runs at once; the tiles it
/// returns are kept until rank 0 starts the job and checks them. Returns the answer
/// to send the worker.
fn serve_ahead(
    ahead: &mut Option<Job>,
    number: u64,
    size: usize,
    rank: usize,
    message: Message,
) -> Result<Option<Message>, ClusterError> {
    match message {
        Message::Ready {
            checks,
            tiles,
            want,
            ..
        } => {
            if tiles > MAX_TILES {
                return Err(ClusterError::Protocol {
                    rank,
                    problem: format!("it was ready for a frame of {tiles} tiles"),
                });
            }
            let job = ahead.get_or_insert_with(|| Job::new(number, tiles as usize, size));
            let worker = &mut job.workers[rank];
            worker.last_heard = Instant::now();
            worker.checks = Some(checks);
            if tiles as usize != job.tile_count {
                // Rank 0 tells which rank's frame differs from its own when it starts
                // the job; this one waits for that.
                worker.waiting = want;
                return Ok(None);
            }
            Ok(job.assign(rank, want))
        }
        Message::Result {
            first, tiles, want, ..
        } => {
            let Some(job) = ahead.as_mut() else {
                return Err(ClusterError::Protocol {
                    rank,
                    problem: format!("it returned tiles of job {number} before it had any"),
                });
            };
            job.workers[rank].last_heard = Instant::now();
            for (index, time) in job.take_run(rank, first, tiles)? {
                job.early.push((index, rank, time));
            }
            Ok(job.assign(rank, want))
        }
        other => Err(unexpected(rank, &other)),
    }
}

/// Gives up on a worker holding runs of the job opened ahead once it has been silent
/// longer than `timeout`.
fn check_ahead_silence(ahead: &Job, timeout: Duration, now: Instant) -> Result<(), ClusterError> {
    for (rank, worker) in ahead.workers.iter().enumerate().skip(1) {
        let waited = now - worker.last_heard;
        if worker.outstanding > 0 && waited > timeout {
            return Err(ClusterError::Silent {
                rank,
                waited,
                outstanding: worker.outstanding,
            });
        }
    }
    Ok(())
}

/// What rank 0's thread serving the workers between frames holds: the transport, the
/// next job (opened ahead by the first worker ready for it) and what came for later.
struct Desk {
    transport: Arc<dyn Transport>,
    size: usize,
    timeout: Duration,
    phase: u32,
    /// The job rank 0 starts next.
    number: u64,
    deferred: Vec<(usize, Message)>,
    ahead: Option<Job>,
    counters: ClusterCounters,
}

impl Desk {
    /// Serves until `halt` is set (the thread is unparked then); returns itself for
    /// rank 0 to take back, and the failure that ended it early, if one did.
    fn serve(mut self, halt: &AtomicBool) -> (Desk, Result<(), ClusterError>) {
        let served = self.serve_until(halt);
        (self, served)
    }

    fn serve_until(&mut self, halt: &AtomicBool) -> Result<(), ClusterError> {
        while !halt.load(Ordering::SeqCst) {
            while let Some((rank, message)) = receive_counted(&*self.transport, &mut self.counters)?
            {
                match message {
                    Message::Ready { phase, .. } if phase < self.phase => {}
                    Message::Ready { job, .. } | Message::Result { job, .. }
                        if job == self.number =>
                    {
                        let answer = serve_ahead(&mut self.ahead, job, self.size, rank, message)?;
                        if let Some(answer) = answer {
                            send_counted(&*self.transport, &mut self.counters, rank, &answer)?;
                        }
                    }
                    Message::Ready { job, .. } if job > self.number => {
                        self.deferred.push((rank, message));
                    }
                    // Tiles of a frame given up, answers to the stop that gave it up.
                    Message::Result { job, .. } if job < self.number => {}
                    Message::Halted { .. } => {}
                    Message::Fail { text } => {
                        return Err(ClusterError::Failed { rank, error: text });
                    }
                    other => return Err(unexpected(rank, &other)),
                }
            }
            if let Some(ahead) = &self.ahead {
                check_ahead_silence(ahead, self.timeout, Instant::now())?;
            }
            // Rank 0's threads are busy with its part between frames: look every few
            // milliseconds (workers hold runs in reserve).
            std::thread::park_timeout(POLL_BUSY);
        }
        Ok(())
    }
}

/// Rank 0's thread serving the workers between frames.
struct Away {
    halt: Arc<AtomicBool>,
    handle: std::thread::JoinHandle<(Desk, Result<(), ClusterError>)>,
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

/// Rank 0's view of one worker during a job.
#[derive(Clone, Copy, Debug)]
struct WorkerState {
    /// Runs handed out and not yet back.
    outstanding: usize,
    done_sent: bool,
    last_heard: Instant,
    /// Its checks, from its ready message for a job opened ahead (checked when rank 0
    /// starts the job).
    checks: Option<FrameChecks>,
    /// Runs it asked for while ahead of rank 0 and has not been given.
    waiting: u32,
}

impl Default for WorkerState {
    fn default() -> Self {
        Self {
            outstanding: 0,
            done_sent: false,
            last_heard: Instant::now(),
            checks: None,
            waiting: 0,
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

/// Rank 0's frame in progress: its job, its checks and its tiles.
struct Lead<'a> {
    job: Job,
    checks: FrameChecks,
    tiles: &'a [Tile],
}

/// The hash every rank compares before a frame: the species BLASes (tree and slot
/// order), the top level (tree and instance records), the shaders and the lights.
pub fn scene_hash(
    library: &GeometryLibrary,
    top_level: &TopLevel,
    shaders: &ShaderTable,
    lights: &LightSet,
) -> u64 {
    let mut hash = Fingerprint::new("sylva cluster scene v2");
    for geometry in &library.geometries {
        hash.u64(geometry.bvh.content_hash());
    }
    hash.u64(top_level.content_hash())
        .u64(shaders.content_hash())
        .u64(lights.content_hash());
    hash.finish()
}

/// The hash of what a camera's frame is drawn with besides the scene: its view and
/// the sampling settings (their `Debug` text, which prints floats exactly).
pub fn view_hash(view: &impl std::fmt::Debug, params: &impl std::fmt::Debug) -> u64 {
    Fingerprint::new("sylva cluster view v1")
        .text(&format!("{view:?}"))
        .text(&format!("{params:?}"))
        .finish()
}

/// Ranks as threads of one process, joined by channels: the protocol without MPI. As
/// with MPI, a message to a rank whose thread has ended is delivered and never read,
/// and (with [`mesh_with_eager_limit`](Self::mesh_with_eager_limit)) a large message's
/// send waits until the rank takes it, as MPI's rendezvous sends do.
/// bevy's task pool is one per process, so each rank's schedule should run on the
/// single-threaded executor: blocked in `render_tiles` waiting for each other, ranks
/// would otherwise hold all of the pool's threads.
pub struct ChannelTransport {
    rank: usize,
    eager_limit: usize,
    senders: Vec<mpsc::Sender<Envelope>>,
    receivers: Arc<Vec<Mutex<mpsc::Receiver<Envelope>>>>,
}

/// A message's bytes, the rank that sent them, and the sender waiting for it to be
/// taken (a rendezvous send).
type Envelope = (usize, Vec<u8>, Option<mpsc::SyncSender<()>>);

impl ChannelTransport {
    /// `size` transports that reach each other, one per rank; every send returns at
    /// once.
    pub fn mesh(size: usize) -> Vec<ChannelTransport> {
        Self::mesh_with_eager_limit(size, usize::MAX)
    }

    /// [`mesh`](Self::mesh) whose sends of more than `eager_limit` bytes wait until the
    /// receiving rank takes the message (as MPI's large sends do).
    pub fn mesh_with_eager_limit(size: usize, eager_limit: usize) -> Vec<ChannelTransport> {
        let (senders, receivers): (Vec<_>, Vec<_>) = (0..size).map(|_| mpsc::channel()).unzip();
        let receivers = Arc::new(receivers.into_iter().map(Mutex::new).collect::<Vec<_>>());
        (0..size)
            .map(|rank| ChannelTransport {
                rank,
                eager_limit,
                senders: senders.clone(),
                receivers: receivers.clone(),
            })
            .collect()
    }
}

impl Transport for ChannelTransport {
    fn rank(&self) -> usize {
        self.rank
    }

    fn size(&self) -> usize {
        self.senders.len()
    }

    fn send(&self, to: usize, bytes: &[u8]) -> Result<(), String> {
        let sender = self
            .senders
            .get(to)
            .ok_or_else(|| format!("there is no rank {to}"))?;
        let (taken, wait) = match bytes.len() > self.eager_limit {
            true => {
                let (taken, wait) = mpsc::sync_channel(1);
                (Some(taken), Some(wait))
            }
            false => (None, None),
        };
        sender
            .send((self.rank, bytes.to_vec(), taken))
            .map_err(|_| "the rank has ended".to_owned())?;
        if let Some(wait) = wait {
            wait.recv().map_err(|_| "the rank has ended".to_owned())?;
        }
        Ok(())
    }

    fn try_receive(&self) -> Option<(usize, Vec<u8>)> {
        let (rank, bytes, taken) = self.receivers[self.rank].lock().ok()?.try_recv().ok()?;
        if let Some(taken) = taken {
            let _ = taken.send(());
        }
        Some((rank, bytes))
    }
}
