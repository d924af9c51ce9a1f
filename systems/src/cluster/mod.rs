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
#[derive(Resource)]
pub struct Cluster {
    transport: Box<dyn Transport>,
    timeout: Duration,
    next_job: u64,
    /// Phases of the run rank 0 has ended with [`finish`](Self::finish).
    phase: u32,
    /// Messages rank 0 received for a job it has not started yet.
    deferred: Vec<(usize, Message)>,
    stop: Arc<AtomicBool>,
    failure: Option<ClusterError>,
    /// The latest frame's counters.
    pub last_frame: ClusterCounters,
    /// Counters summed over the run.
    pub total: ClusterCounters,
}

impl Cluster {
    /// This process's place in the run over `transport`; no wait lasts longer than
    /// `timeout`. `stop` is set when the run must end: on a worker when rank 0 says so,
    /// on any rank when the run fails (pass it as the progressive driver's interrupt).
    pub fn new(transport: Box<dyn Transport>, timeout: Duration, stop: Arc<AtomicBool>) -> Self {
        Self {
            transport,
            timeout,
            next_job: 0,
            phase: 0,
            deferred: Vec::new(),
            stop,
            failure: None,
            last_frame: ClusterCounters::default(),
            total: ClusterCounters::default(),
        }
    }

    /// This process's rank.
    pub fn rank(&self) -> usize {
        self.transport.rank()
    }

    /// Ranks in the run.
    pub fn size(&self) -> usize {
        self.transport.size()
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
        if self.leads() {
            self.end_phase()?;
        }
        Ok(())
    }

    /// Rank 0 tells every worker to leave the job it is on or stands ready for.
    fn end_phase(&mut self) -> Result<(), ClusterError> {
        let next_job = self.next_job;
        for rank in 1..self.size() {
            self.send(rank, &Message::Stop { next_job })?;
        }
        self.phase += 1;
        self.deferred.clear();
        Ok(())
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
                    self.next_job = next_job;
                    self.phase += 1;
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
        if self.failure.is_some() {
            return None;
        }
        self.last_frame = ClusterCounters {
            frames: 1,
            ..ClusterCounters::default()
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
                self.abandon(&error.to_string());
                self.failure = Some(error);
                self.stop.store(true, Ordering::SeqCst);
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
        let job = self.next_job;
        self.next_job += 1;
        let next = AtomicUsize::new(0);
        let give_up = AtomicBool::new(false);
        let local_busy = AtomicUsize::new(pool.current_num_threads());
        let (sender, local) = mpsc::channel::<(usize, TileResult)>();
        let runs = tiles.len().div_ceil(RUN_TILES);
        let mut lead = Lead {
            job,
            checks,
            tiles,
            next: &next,
            runs,
            owners: vec![None; runs],
            results: (0..tiles.len()).map(|_| None).collect(),
            received: 0,
            workers: vec![WorkerState::default(); self.size()],
        };
        let outcome = pool.in_place_scope(|scope| {
            for _ in 0..pool.current_num_threads() {
                let sender = sender.clone();
                let (next, give_up, local_busy) = (&next, &give_up, &local_busy);
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
                    .results
                    .into_iter()
                    .map(|r| r.expect("every tile came back"));
                FrameEnd::Done(results.collect())
            }
            FrameEnd::Stopped => FrameEnd::Stopped,
            FrameEnd::Cancelled => FrameEnd::Cancelled,
        })
    }

    /// Polls local results and messages until every tile is back and every worker has
    /// been told the frame is done, or the stop flag or `cancel` ends it first. A
    /// frame is given up only before any worker has been told it is done, so that
    /// every rank gives it up (a worker told so has already kept it).
    fn lead_loop(
        &mut self,
        lead: &mut Lead,
        local: &mpsc::Receiver<(usize, TileResult)>,
        local_busy: &AtomicUsize,
        on_tile: &(dyn Fn(&Tile, Duration) + Sync),
        cancel: Option<&AtomicBool>,
    ) -> Result<FrameEnd<()>, ClusterError> {
        let start = Instant::now();
        for state in &mut lead.workers {
            state.last_heard = start;
        }
        let mut pending = std::mem::take(&mut self.deferred);
        pending.reverse();
        let mut waiting_since: Option<Instant> = None;
        loop {
            let mut progressed = false;
            while let Ok((index, result)) = local.try_recv() {
                lead.store_local(index, result);
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
            let all_told = lead.workers.iter().skip(1).all(|w| w.done_sent);
            if lead.received == lead.tiles.len() && all_told {
                if let Some(since) = waiting_since {
                    self.last_frame.waited += since.elapsed();
                }
                return Ok(FrameEnd::Done(()));
            }
            if self.stop.load(Ordering::SeqCst) {
                return Ok(FrameEnd::Stopped);
            }
            let none_told = lead.workers.iter().all(|w| !w.done_sent);
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
            for (rank, state) in lead.workers.iter().enumerate().skip(1) {
                if !state.done_sent {
                    self.check_silence(rank, now - state.last_heard, state.outstanding)?;
                }
            }
            std::thread::sleep(POLL);
        }
    }

    /// Rank 0 handles one worker's message of the frame in progress.
    fn lead_message(
        &mut self,
        lead: &mut Lead,
        rank: usize,
        message: Message,
        on_tile: &(dyn Fn(&Tile, Duration) + Sync),
    ) -> Result<(), ClusterError> {
        lead.workers[rank].last_heard = Instant::now();
        match message {
            // A worker's ready message of a phase rank 0 has ended: it was waiting for
            // a frame that never came, and asks again in the new phase.
            Message::Ready { phase, .. } if phase < self.phase => {}
            Message::Ready { job, .. } if job > lead.job => {
                self.deferred.push((rank, message));
            }
            Message::Ready {
                job, checks, want, ..
            } if job == lead.job => {
                for (what, ours, theirs) in [
                    (
                        "progressive frame",
                        u64::from(lead.checks.frame),
                        u64::from(checks.frame),
                    ),
                    (
                        "scene (geometry, plants, shaders or lights)",
                        lead.checks.scene,
                        checks.scene,
                    ),
                    (
                        "camera view or sampling settings",
                        lead.checks.view,
                        checks.view,
                    ),
                ] {
                    if ours != theirs {
                        return Err(ClusterError::Mismatch { rank, what });
                    }
                }
                self.assign(lead, rank, want)?;
            }
            // Tiles of a frame given up: sent before the worker heard so.
            Message::Result { job, .. } if job < lead.job => {}
            Message::Result {
                job,
                first,
                tiles,
                want,
            } if job == lead.job => {
                let first = first as usize;
                let run = first / RUN_TILES;
                let expected = run_tiles(run, lead.tiles.len());
                if !first.is_multiple_of(RUN_TILES)
                    || run >= lead.runs
                    || lead.owners[run] != Some(rank)
                    || tiles.len() != expected.len()
                {
                    return Err(ClusterError::Protocol {
                        rank,
                        problem: format!("tiles from {first} on were not its to return"),
                    });
                }
                lead.owners[run] = None;
                for (index, (nanos, result)) in expected.zip(tiles) {
                    if result.tile != lead.tiles[index] {
                        return Err(ClusterError::Protocol {
                            rank,
                            problem: format!("tile {index} came back as another tile"),
                        });
                    }
                    on_tile(&lead.tiles[index], Duration::from_nanos(nanos));
                    lead.results[index] = Some(result);
                    lead.received += 1;
                    self.last_frame.tiles_elsewhere += 1;
                }
                lead.workers[rank].outstanding -= 1;
                self.assign(lead, rank, want)?;
            }
            Message::Fail { text } => return Err(ClusterError::Failed { rank, error: text }),
            other => return Err(unexpected(rank, &other)),
        }
        Ok(())
    }

    /// Gives `rank` up to `want` more runs of tiles; tells it the frame is done once
    /// the counter has run out and it has returned all it was given.
    fn assign(&mut self, lead: &mut Lead, rank: usize, want: u32) -> Result<(), ClusterError> {
        let mut given = Vec::new();
        while given.len() < want as usize {
            let run = lead.next.fetch_add(1, Ordering::Relaxed);
            if run >= lead.runs {
                break;
            }
            lead.owners[run] = Some(rank);
            let tiles = run_tiles(run, lead.tiles.len());
            given.push((tiles.start as u32, tiles.len() as u32));
        }
        let job = lead.job;
        if !given.is_empty() {
            lead.workers[rank].outstanding += given.len();
            self.send(rank, &Message::Tiles { job, runs: given })?;
        } else if lead.workers[rank].outstanding == 0 && !lead.workers[rank].done_sent {
            lead.workers[rank].done_sent = true;
            self.send(rank, &Message::Done { job })?;
        }
        Ok(())
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
                            self.next_job = next_job;
                            self.phase += 1;
                            give_up.store(true, Ordering::Relaxed);
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
        let bytes = message.encode();
        self.last_frame.bytes_sent += bytes.len() as u64;
        self.transport
            .send(to, &bytes)
            .map_err(|reason| ClusterError::Send { rank: to, reason })
    }

    fn receive(&mut self) -> Result<Option<(usize, Message)>, ClusterError> {
        let Some((rank, bytes)) = self.transport.try_receive() else {
            return Ok(None);
        };
        self.last_frame.bytes_received += bytes.len() as u64;
        match Message::decode(&bytes) {
            Ok(message) => Ok(Some((rank, message))),
            Err(wire::Malformed) => Err(ClusterError::Protocol {
                rank,
                problem: format!("a message of {} bytes could not be read", bytes.len()),
            }),
        }
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
        Message::Fail { .. } => "a failure",
    };
    ClusterError::Protocol {
        rank,
        problem: format!("{name} arrived out of turn"),
    }
}

/// Rank 0's view of one worker during a frame.
#[derive(Clone, Copy, Debug)]
struct WorkerState {
    outstanding: usize,
    done_sent: bool,
    last_heard: Instant,
}

impl Default for WorkerState {
    fn default() -> Self {
        Self {
            outstanding: 0,
            done_sent: false,
            last_heard: Instant::now(),
        }
    }
}

/// Rank 0's frame in progress.
struct Lead<'a> {
    job: u64,
    checks: FrameChecks,
    tiles: &'a [Tile],
    /// The next run of tiles to hand out.
    next: &'a AtomicUsize,
    /// Runs in the frame.
    runs: usize,
    /// The worker each run handed out and not yet back is with.
    owners: Vec<Option<usize>>,
    results: Vec<Option<TileResult>>,
    received: usize,
    workers: Vec<WorkerState>,
}

impl Lead<'_> {
    /// A tile rank 0's own threads rendered.
    fn store_local(&mut self, index: usize, result: TileResult) {
        self.results[index] = Some(result);
        self.received += 1;
    }
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
