//! A progressive render on a thread of its own, for a window: the world and its
//! schedule live on that thread, camera moves arrive as commands, and each finished
//! frame is published as display pixels. The window never waits for a frame; it shows
//! the latest one. Accumulation restarts when the camera moves (the `Accumulate` stage
//! sees the changed transform) and stops at a frame limit, after which the thread sleeps
//! until the next command.
//!
//! Frames never starve: a command gives up only a frame that refines the view already
//! shown. A frame that shows a new view (the first after a move or an edit) is finished
//! whatever arrives meanwhile, and the commands that arrived coalesce into the next one
//! (the latest pose wins), so a held key shows a new view every frame time instead of
//! none until it is released.
//!
//! On a cluster ([`Cluster`] resource on rank 0, [`serve_live`] on the other ranks)
//! every rank holds the same world: rank 0's thread sends each batch of camera moves and
//! [`LiveCommand::Shared`] edits to the others before the frame that shows them, every
//! rank applies them in the same order through the same ECS change detection, and the
//! frame's tiles are shared out; a frame given up on rank 0 is given up everywhere.

use crate::cluster::{Cluster, ClusterError, LiveStep};
use crate::picking::{MapPlant, Selected, map_plants};
use crate::profile::{FrameProfiler, ProfileLog};
use crate::progressive::{StopAt, refine};
use crate::{FrameCancel, RenderStats, TopLevelState, frame_schedule, shown_film};
use bevy_ecs::prelude::*;
use crossbeam_channel::{Receiver, RecvTimeoutError, Sender};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::thread::JoinHandle;
use std::time::Duration;
use sylva_engine::camera::Camera;
use sylva_engine::components::Transform;
use sylva_engine::discontinuity::FilteredImage;
use sylva_engine::film::Film;
use sylva_engine::sway::AnimationClock;
use sylva_engine::tlas::TopLevel;

/// A frame ready to be shown.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ShownImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Tone-mapped sRGB pixels as `0x00RRGGBB`, row by row from the top.
    pub pixels: Vec<u32>,
    /// Frames accumulated in it.
    pub frames: u32,
    /// Rendering time of the latest frame.
    pub frame_time: Duration,
    /// Rays per second of the latest frame.
    pub rays_per_second: f64,
    /// Sequence number of the last command applied before this frame was rendered (see
    /// [`LiveRender::send`]): a frame shows a command's effect when this has reached the
    /// command's number.
    pub applied: u64,
    /// The selected plant ([`Selected`]) when the frame was published.
    pub selected: Option<Entity>,
    /// Instances in the top level (plants and terrain).
    pub instances: usize,
    /// Time of the latest top-level rebuild and of the latest refit.
    pub top_level: (Duration, Duration),
    /// Time of the latest display filter (the interactive quality's discontinuity
    /// filter).
    pub filter: Duration,
    /// Time the render thread spent tone-mapping this frame for the window.
    pub tone_map: Duration,
    /// The plants as the editor's map draws them, as of this frame's top level (shared
    /// between frames until the plants change).
    pub map: Arc<Vec<MapPlant>>,
}

impl ShownImage {
    /// Tone-maps `film` (or its filtered image, when that is current) at `exposure`.
    pub fn of_film(film: &Film, filtered: Option<&FilteredImage>, exposure: f32) -> Self {
        let shown = shown_film(film, filtered);
        let bytes = shown.to_srgba8(exposure);
        let pixels = bytes
            .chunks_exact(4)
            .map(|p| (u32::from(p[0]) << 16) | (u32::from(p[1]) << 8) | u32::from(p[2]))
            .collect();
        Self {
            width: film.width(),
            height: film.height(),
            pixels,
            frames: film.frames(),
            ..Self::default()
        }
    }
}

/// What the render thread has done: each complete frame's rendering time, and the
/// frames it gave up.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FrameLog {
    /// Rendering time of every complete frame, in order.
    pub frame_times: Vec<Duration>,
    /// Frames given up half-way for a newer command.
    pub cancelled: u32,
}

impl FrameLog {
    /// Mean and 95th percentile (nearest rank) of the frame times; `None` before the
    /// first frame.
    pub fn mean_and_p95(&self) -> Option<(Duration, Duration)> {
        let n = self.frame_times.len();
        if n == 0 {
            return None;
        }
        let mean = self.frame_times.iter().sum::<Duration>() / n as u32;
        let mut sorted = self.frame_times.clone();
        sorted.sort();
        let rank = (n * 95).div_ceil(100).clamp(1, n);
        Some((mean, sorted[rank - 1]))
    }
}

/// What a window user feels, measured where the frames are shown: how many new images a
/// second reach the screen, and how old the newest input an image shows was when it
/// arrived (input-to-image latency).
#[derive(Clone, Debug, Default)]
pub struct Responsiveness {
    /// Commands sent and not yet seen in a shown image: sequence number and send time.
    pending: std::collections::VecDeque<(u64, std::time::Instant)>,
    /// When the images of the last second were shown.
    shown: std::collections::VecDeque<std::time::Instant>,
    /// The newest command an image has shown.
    applied: u64,
    /// The latency of the last image that showed a new command.
    latency: Option<Duration>,
}

impl Responsiveness {
    /// Notes that command `number` was sent at `at`.
    pub fn sent(&mut self, number: u64, at: std::time::Instant) {
        self.pending.push_back((number, at));
    }

    /// Notes that an image showing every command up to `applied` was shown at `at`.
    pub fn shown(&mut self, applied: u64, at: std::time::Instant) {
        self.shown.push_back(at);
        while self
            .shown
            .front()
            .is_some_and(|&t| at.duration_since(t) > Duration::from_secs(1))
        {
            self.shown.pop_front();
        }
        if applied > self.applied {
            // The newest command this image shows: its age is the image's latency.
            let newest = self.pending.iter().rev().find(|(n, _)| *n <= applied);
            if let Some(&(_, sent)) = newest {
                self.latency = Some(at.saturating_duration_since(sent));
            }
            self.applied = applied;
        }
        self.pending.retain(|&(n, _)| n > applied);
    }

    /// Images shown in the last second.
    pub fn shown_per_second(&self) -> usize {
        self.shown.len()
    }

    /// How old the newest input was when the last image that showed a new one appeared.
    pub fn latency(&self) -> Option<Duration> {
        self.latency
    }
}

/// What the window asks of the render thread.
#[derive(Clone)]
pub enum LiveCommand {
    /// Place the camera (restarts accumulation).
    Pose(Transform),
    /// Run a closure on the world between frames (edits, quality changes); changes it
    /// makes restart accumulation as any ECS change does. On a cluster it runs on rank 0
    /// only: what every rank must do alike is a [`Shared`](Self::Shared) edit.
    Edit(Arc<dyn Fn(&mut World) + Send + Sync>),
    /// An edit given as bytes, applied by the world's [`SharedEdits`] between frames on
    /// this process and, on a cluster, on every rank alike.
    Shared(Vec<u8>),
    /// Stop rendering and hand the world back.
    Quit,
}

/// The function that applies a [`LiveCommand::Shared`] edit from its bytes (the same on
/// every rank; an error says what could not be applied, and is the same on every rank).
pub type SharedEditFn = dyn Fn(&mut World, &[u8]) -> Result<(), String> + Send + Sync;

/// How this world applies [`LiveCommand::Shared`] edits: insert it before starting a
/// live render that is sent them.
#[derive(Resource, Clone)]
pub struct SharedEdits(pub Arc<SharedEditFn>);

/// Runs a live render's systems one after another on its own thread instead of on
/// bevy's task pool (tiles still render on the world's render pool). Ranks of a
/// cluster run as threads of one process need it: bevy's pool is one per process, and
/// ranks waiting for each other inside their frames could hold all of its threads.
#[derive(Resource, Clone, Copy, Debug, Default)]
pub struct SingleThreadedSystems;

/// The frame schedule, on the executor `world` asks for.
fn live_schedule(world: &World) -> Schedule {
    let mut schedule = frame_schedule();
    if world.contains_resource::<SingleThreadedSystems>() {
        schedule.set_executor(bevy_ecs::schedule::SingleThreadedExecutor::new());
    }
    schedule
}

/// The first byte of an edit on the wire: a camera pose.
const POSE_EDIT: u8 = 0;
/// The first byte of an edit on the wire: a [`LiveCommand::Shared`] edit.
const SHARED_EDIT: u8 = 1;

/// A pose as the bytes of its ten floats (bits, so every rank gets the same pose).
fn encode_pose(pose: &Transform) -> Vec<u8> {
    let floats = pose
        .translation
        .to_array()
        .into_iter()
        .chain(pose.rotation.to_array())
        .chain(pose.scale.to_array());
    std::iter::once(POSE_EDIT)
        .chain(floats.flat_map(|f| f.to_bits().to_le_bytes()))
        .collect()
}

fn decode_pose(bytes: &[u8]) -> Option<Transform> {
    let floats: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|c| f32::from_bits(u32::from_le_bytes(c.try_into().expect("four bytes"))))
        .collect();
    (bytes.len() == 40).then(|| Transform {
        translation: glam::Vec3::from_slice(&floats[0..3]),
        rotation: glam::Quat::from_slice(&floats[3..7]),
        scale: glam::Vec3::from_slice(&floats[7..10]),
    })
}

/// Places `camera` at `pose`, touching it only when it moves (an unchanged pose keeps
/// the film accumulating).
fn place_camera(world: &mut World, camera: Entity, pose: Transform) {
    if let Some(mut transform) = world.get_mut::<Transform>(camera)
        && *transform != pose
    {
        *transform = pose;
    }
}

/// Applies a shared edit's bytes with the world's [`SharedEdits`].
fn apply_shared(world: &mut World, bytes: &[u8]) {
    let outcome = match world.get_resource::<SharedEdits>().cloned() {
        Some(edits) => (edits.0)(world, bytes),
        None => Err("this world applies no shared edits (insert SharedEdits)".into()),
    };
    if let Err(error) = outcome {
        tracing::warn!(%error, "an edit was not applied");
    }
}

/// Applies an edit as it came over the wire (a pose or a shared edit).
fn apply_encoded(world: &mut World, camera: Entity, bytes: &[u8]) {
    match bytes.split_first() {
        Some((&POSE_EDIT, pose)) => match decode_pose(pose) {
            Some(pose) => place_camera(world, camera, pose),
            None => tracing::warn!(bytes = bytes.len(), "a camera pose could not be read"),
        },
        Some((&SHARED_EDIT, edit)) => apply_shared(world, edit),
        _ => tracing::warn!(bytes = bytes.len(), "an edit of an unknown kind"),
    }
}

/// What the render thread shares with the window about the frame in flight: whether a
/// new command may give it up, and the flag that does.
#[derive(Clone, Default)]
struct InFlight {
    /// Set: the frame is given up at its next tile.
    cancel: Arc<AtomicBool>,
    /// The frame shows a new view (or the thread is taking commands): commands wait for
    /// the next frame instead of giving this one up.
    keep: Arc<AtomicBool>,
}

impl InFlight {
    /// What a new command does to the frame in flight: gives it up unless it is kept.
    fn command_sent(&self) {
        if !self.keep.load(Ordering::SeqCst) {
            self.cancel.store(true, Ordering::SeqCst);
        }
    }

    /// Gives up the frame in flight whatever it is (quitting).
    fn give_up(&self) {
        self.cancel.store(true, Ordering::SeqCst);
    }
}

/// The render thread's handle: commands in, the latest frame out.
pub struct LiveRender {
    commands: Sender<(u64, LiveCommand)>,
    in_flight: InFlight,
    frame_log: Arc<Mutex<FrameLog>>,
    sent: u64,
    latest: Arc<Mutex<Option<ShownImage>>>,
    /// Why the render thread ended early: its panic's message.
    failure: Arc<Mutex<Option<String>>>,
    thread: Option<JoinHandle<Option<World>>>,
}

impl LiveRender {
    /// Starts rendering `camera` of `world` (set up as for [`refine`]) on a new thread;
    /// `frame_ready` is called from that thread after each frame is published (a
    /// window's wake-up). Accumulation stops at `max_frames` until the next command.
    pub fn start(
        world: World,
        camera: Entity,
        max_frames: u32,
        frame_ready: impl Fn() + Send + 'static,
    ) -> std::io::Result<Self> {
        Self::start_profiled(world, camera, max_frames, None, frame_ready)
    }

    /// [`start`](Self::start) that adds every shown frame to `profile` (its time to
    /// make the shown image as the frame's writing); the world's
    /// [`FrameProfiler`] must be enabled for stage times. Frames given up are left out.
    pub fn start_profiled(
        world: World,
        camera: Entity,
        max_frames: u32,
        profile: Option<Arc<Mutex<ProfileLog>>>,
        frame_ready: impl Fn() + Send + 'static,
    ) -> std::io::Result<Self> {
        let (commands, inbox) = crossbeam_channel::unbounded();
        let latest = Arc::new(Mutex::new(None));
        let in_flight = InFlight::default();
        let frame_log = Arc::new(Mutex::new(FrameLog::default()));
        let log = frame_log.clone();
        let mut world = world;
        world.insert_resource(FrameCancel(Some(in_flight.cancel.clone())));
        let flag = in_flight.clone();
        let published = latest.clone();
        let failure = Arc::new(Mutex::new(None));
        let failed = failure.clone();
        let thread = std::thread::Builder::new()
            .name("sylva-live".into())
            .spawn(move || {
                let rendered = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                    run(
                        world,
                        camera,
                        max_frames.max(1),
                        (inbox, &flag),
                        (&published, &log, profile),
                        &frame_ready,
                    )
                }));
                let message = match rendered {
                    Ok(Ok(world)) => return Some(world),
                    Ok(Err(error)) => error.to_string(),
                    Err(panic) => panic
                        .downcast_ref::<&str>()
                        .map(|s| s.to_string())
                        .or_else(|| panic.downcast_ref::<String>().cloned())
                        .unwrap_or_else(|| "a panic without a message".into()),
                };
                *failed.lock().unwrap_or_else(PoisonError::into_inner) = Some(message);
                // Wake the window: no frame will come, and it must not wait for one.
                frame_ready();
                None
            })?;
        Ok(Self {
            commands,
            in_flight,
            frame_log,
            sent: 0,
            latest,
            failure,
            thread: Some(thread),
        })
    }

    /// Sends a command and returns its sequence number (1, 2, …), or `None` when the
    /// render thread has ended.
    pub fn send(&mut self, command: LiveCommand) -> Option<u64> {
        self.sent += 1;
        self.commands.send((self.sent, command)).ok()?;
        // A frame that refines the view already shown would not show what the command
        // changes: it is given up at its next tile. One that shows a new view is kept.
        self.in_flight.command_sent();
        Some(self.sent)
    }

    /// The sequence number of the last command sent (0 before the first).
    pub fn last_sent(&self) -> u64 {
        self.sent
    }

    /// What the render thread has done so far.
    pub fn frame_log(&self) -> FrameLog {
        self.frame_log
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Why the render thread ended early, if it did: its panic's message, or its
    /// cluster's error (the window is woken when it does).
    pub fn failure(&self) -> Option<String> {
        self.failure
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// The newest frame not yet taken, if any.
    pub fn take_latest(&self) -> Option<ShownImage> {
        self.latest
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take()
    }

    /// Stops the thread after the frame in progress and returns the world; `None` when
    /// the thread failed ([`failure`](Self::failure)).
    pub fn stop(mut self) -> Option<World> {
        let _ = self.commands.send((u64::MAX, LiveCommand::Quit));
        self.in_flight.give_up();
        self.thread.take().and_then(|t| t.join().ok().flatten())
    }
}

impl Drop for LiveRender {
    fn drop(&mut self) {
        if let Some(thread) = self.thread.take() {
            let _ = self.commands.send((u64::MAX, LiveCommand::Quit));
            self.in_flight.give_up();
            let _ = thread.join();
        }
    }
}

/// What applying a command asks of the other ranks of a cluster.
enum Applied {
    /// Nothing: the command changed only this process's world, or nothing.
    Here,
    /// To apply these bytes alike.
    Everywhere(Vec<u8>),
    /// To quit.
    Quit,
}

/// Applies one command.
fn apply(world: &mut World, camera: Entity, command: LiveCommand) -> Applied {
    match command {
        LiveCommand::Pose(pose) => {
            place_camera(world, camera, pose);
            Applied::Everywhere(encode_pose(&pose))
        }
        LiveCommand::Edit(edit) => {
            edit(world);
            Applied::Here
        }
        LiveCommand::Shared(bytes) => {
            apply_shared(world, &bytes);
            Applied::Everywhere(std::iter::once(SHARED_EDIT).chain(bytes).collect())
        }
        LiveCommand::Quit => Applied::Quit,
    }
}

/// Rank 0 of a cluster tells the others what comes next (nothing without a cluster).
/// After a frame that was not given up the workers have gone on to the next one, as
/// when nothing changes (`workers_ahead`): unless this step is that frame with no edits
/// (then nothing is sent), they are stopped first.
fn announce(
    world: &mut World,
    edits: &[Vec<u8>],
    next: LiveStep,
    workers_ahead: &mut bool,
) -> Result<(), ClusterError> {
    let ahead = std::mem::take(workers_ahead);
    if ahead && edits.is_empty() && next == LiveStep::Render {
        return Ok(());
    }
    match world.get_resource_mut::<Cluster>() {
        Some(mut cluster) if cluster.leads() => {
            let announced = match ahead {
                true => cluster.finish(),
                false => Ok(()),
            }
            .and_then(|()| cluster.announce(edits, next));
            if let Err(error) = &announced {
                cluster.abandon(&error.to_string());
            }
            announced
        }
        _ => Ok(()),
    }
}

/// Renders one frame of `camera` (given up, or not); the cluster's failure if the frame
/// ended the run. `frames_follow`: another frame is expected after it (a cluster's
/// workers may start on it ahead of rank 0).
fn one_frame(
    world: &mut World,
    schedule: &mut Schedule,
    camera: Entity,
    frames_follow: bool,
) -> Result<crate::progressive::Progress, ClusterError> {
    let stop = StopAt {
        frames_follow,
        ..StopAt::default()
    };
    let (_, progress) = refine(world, schedule, camera, &stop, |_, _| {
        crate::progressive::Flow::Stop
    });
    match world.get_resource::<Cluster>().and_then(Cluster::failure) {
        Some(failure) => Err(failure.clone()),
        None => Ok(progress),
    }
}

/// A worker rank's side of a live render on a cluster (rank 0 runs [`LiveRender`] with
/// `cluster` in its world): applies rank 0's edits in its order and renders every frame
/// with it, until rank 0 quits (the world is returned) or the run fails. `world` is set
/// up as rank 0's, with the same [`SharedEdits`].
pub fn serve_live(
    mut world: World,
    camera: Entity,
    cluster: Cluster,
) -> Result<World, ClusterError> {
    world.insert_resource(cluster);
    let mut schedule = live_schedule(&world);
    // After a frame, the next one comes unless rank 0 stops it: start on it at once.
    let mut ahead = false;
    loop {
        if !ahead {
            let (edits, next) = world.resource_mut::<Cluster>().await_step()?;
            for edit in &edits {
                apply_encoded(&mut world, camera, edit);
            }
            match next {
                LiveStep::Idle => continue,
                LiveStep::Quit => return Ok(world),
                LiveStep::Render => {}
            }
        }
        let progress = one_frame(&mut world, &mut schedule, camera, true)?;
        // A frame rank 0 stopped (given up, or one it did not render after all) sends
        // this rank back to wait for its step.
        world.resource_mut::<Cluster>().resume();
        ahead = progress.cancelled == 0 && !animating(&world);
    }
}

/// True when every frame moves the world on (the wind blows): a frame started ahead of
/// rank 0 and then stopped would have moved this rank's world alone, so workers wait for
/// rank 0's step instead. Rank 0 decides the same from the same world.
fn animating(world: &World) -> bool {
    world
        .get_resource::<AnimationClock>()
        .is_some_and(|clock| clock.frame_seconds > 0.0)
}

/// A profile the render thread adds its frames to.
type SharedProfile = Option<Arc<Mutex<ProfileLog>>>;

/// The render thread: commands, one frame, publish; asleep at `max_frames`.
fn run(
    mut world: World,
    camera: Entity,
    max_frames: u32,
    (inbox, in_flight): (Receiver<(u64, LiveCommand)>, &InFlight),
    (published, log, mut profile): (&Mutex<Option<ShownImage>>, &Mutex<FrameLog>, SharedProfile),
    frame_ready: impl Fn(),
) -> Result<World, ClusterError> {
    let mut schedule = live_schedule(&world);
    let mut applied = 0;
    // Edits the other ranks of a cluster have not been sent yet.
    let mut unsent: Vec<Vec<u8>> = Vec::new();
    let mut given_up = false;
    // A cluster's workers have gone on to the next frame.
    let mut workers_ahead = false;
    // The map, and the top-level build and refit counts it was made at.
    let mut map: (Arc<Vec<MapPlant>>, Option<(u64, u64)>) = (Arc::default(), None);
    loop {
        // A frame given up is made again even without a new command: the command that
        // gave it up may have been taken before the frame started (it is sent before
        // the flag is raised), and the film it left may look converged.
        let converged =
            !given_up && world.get::<Film>(camera).map_or(0, Film::frames) >= max_frames;
        // Idle when converged: wait for a command (checking now and then that the
        // window is still there); otherwise take whatever has arrived.
        let first = if converged {
            match inbox.recv_timeout(Duration::from_millis(250)) {
                Ok(command) => Some(command),
                Err(RecvTimeoutError::Timeout) => {
                    // The other ranks wait for the next frame: a sign of life.
                    announce(&mut world, &[], LiveStep::Idle, &mut workers_ahead)?;
                    continue;
                }
                Err(RecvTimeoutError::Disconnected) => {
                    announce(&mut world, &unsent, LiveStep::Quit, &mut workers_ahead)?;
                    return Ok(world);
                }
            }
        } else {
            None
        };
        // Commands sent while they are taken wait for the frame; the flag is cleared
        // before they are taken, so none that is not taken gives up the coming frame.
        in_flight.keep.store(true, Ordering::SeqCst);
        in_flight.cancel.store(false, Ordering::SeqCst);
        let mut took = first.is_some();
        for (number, command) in first.into_iter().chain(inbox.try_iter()) {
            took = true;
            match apply(&mut world, camera, command) {
                Applied::Here => {}
                Applied::Everywhere(edit) => unsent.push(edit),
                Applied::Quit => {
                    announce(&mut world, &unsent, LiveStep::Quit, &mut workers_ahead)?;
                    return Ok(world);
                }
            }
            applied = number;
        }
        // A frame that shows a new view (after commands, after a frame given up, or the
        // first) is kept whatever comes meanwhile; one that only refines the shown view
        // is given up by the next command. A command that came after the inbox was
        // emptied and before that was said is taken first.
        let frames = world.get::<Film>(camera).map_or(0, Film::frames);
        let new_view = took || given_up || frames == 0 || animating(&world);
        if !new_view {
            in_flight.keep.store(false, Ordering::SeqCst);
            if !inbox.is_empty() {
                continue;
            }
        }
        announce(&mut world, &unsent, LiveStep::Render, &mut workers_ahead)?;
        unsent.clear();
        // One frame, whether or not it restarted the film; nothing to show when it was
        // given up.
        let progress = one_frame(
            &mut world,
            &mut schedule,
            camera,
            frames.saturating_add(1) < max_frames,
        )?;
        given_up = progress.cancelled > 0;
        workers_ahead = !given_up && !animating(&world);
        if given_up {
            log.lock().unwrap_or_else(PoisonError::into_inner).cancelled += 1;
            // The given-up frame's times are not a frame's.
            if let Some(profiler) = world.get_resource::<FrameProfiler>() {
                profiler.take();
            }
            continue;
        }
        if let Some(shared) = &profile {
            let recorded = shared
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .record(&world);
            if let Err(error) = recorded {
                tracing::warn!(%error, "the profile stops here");
                profile = None;
            }
        }
        let shown_start = std::time::Instant::now();
        let Some(film) = world.get::<Film>(camera) else {
            announce(&mut world, &[], LiveStep::Quit, &mut workers_ahead)?;
            return Ok(world);
        };
        let exposure = world.get::<Camera>(camera).map_or(0.0, |c| c.exposure);
        let tone_map_start = std::time::Instant::now();
        let mut image = ShownImage::of_film(film, world.get::<FilteredImage>(camera), exposure);
        image.tone_map = tone_map_start.elapsed();
        image.instances = world.get_resource::<TopLevel>().map_or(0, TopLevel::len);
        image.top_level = world
            .get_resource::<TopLevelState>()
            .map_or_else(Default::default, |t| (t.last_build, t.last_refit));
        let version = world
            .get_resource::<TopLevelState>()
            .map(|t| (t.rebuilds, t.refits));
        if map.1.is_none() || map.1 != version {
            map = (Arc::new(map_plants(&mut world)), version);
        }
        image.map = map.0.clone();
        let stats = world.resource::<RenderStats>();
        image.frame_time = stats.last_render;
        image.filter = stats.last_filter;
        log.lock()
            .unwrap_or_else(PoisonError::into_inner)
            .frame_times
            .push(stats.last_render);
        image.applied = applied;
        image.selected = world.get_resource::<Selected>().and_then(|s| s.0);
        image.rays_per_second =
            stats.last_frame.rays() as f64 / stats.last_render.as_secs_f64().max(1e-9);
        if let Some(shared) = &profile {
            shared
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .add_write(shown_start.elapsed());
        }
        *published.lock().unwrap_or_else(PoisonError::into_inner) = Some(image);
        frame_ready();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn latency_is_the_age_of_the_newest_input_an_image_shows() {
        let start = std::time::Instant::now();
        let at = |ms| start + Duration::from_millis(ms);
        let mut r = Responsiveness::default();
        assert_eq!(r.latency(), None);
        for n in 1..=5 {
            r.sent(n, at(n * 16));
        }
        // An image that shows the first three commands, 200 ms in: the third is 152 ms old.
        r.shown(3, at(200));
        assert_eq!(r.latency(), Some(Duration::from_millis(152)));
        // Refining the same view keeps the latency of the image that showed the input.
        r.shown(3, at(300));
        assert_eq!(r.latency(), Some(Duration::from_millis(152)));
        r.shown(5, at(400));
        assert_eq!(r.latency(), Some(Duration::from_millis(320)));
        assert_eq!(r.shown_per_second(), 3);
        r.shown(5, at(1350));
        assert_eq!(
            r.shown_per_second(),
            2,
            "images older than a second drop out"
        );
    }

    #[test]
    fn the_frame_log_gives_mean_and_nearest_rank_p95() {
        assert_eq!(FrameLog::default().mean_and_p95(), None);
        let log = FrameLog {
            frame_times: (1..=20).rev().map(Duration::from_millis).collect(),
            cancelled: 0,
        };
        let (mean, p95) = log.mean_and_p95().unwrap();
        assert_eq!(mean, Duration::from_micros(10_500));
        assert_eq!(p95, Duration::from_millis(19));
    }
}
