//! `sylva view`: a window onto a scene. Walk through it with the keyboard and mouse
//! while it renders at interactive quality on the render thread and refines when the
//! camera rests; or fly a scripted walkthrough (`--script`) for tests and benchmarks.
//! Only window glue lives here: the camera control, the scripts and the render thread
//! are `sylva_systems::walkthrough` and `sylva_systems::live`.

use super::cluster::{ClusterArgs, Node};
use super::profile::{finish_profile, open_profile};
use super::*;
use std::collections::HashSet;
use std::num::NonZeroU32;
use std::rc::Rc;
use std::sync::{Mutex, PoisonError};
use std::time::Instant;
use sylva::scenes::editor;
use sylva::scenes::editor::EditorAction;
use sylva::systems::cluster::Cluster;
use sylva::systems::live::{LiveCommand, LiveRender, SharedEdits, ShownImage, serve_live};
use sylva::systems::profile::{FrameProfiler, ProfileLog};
use sylva::systems::walkthrough::{
    FlyCamera, FlyInput, ScriptRecorder, ScriptStep, WalkthroughScript, overview_pose,
};
use winit::application::ApplicationHandler;
use winit::dpi::{PhysicalPosition, PhysicalSize};
use winit::event::{ElementState, Modifiers, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::{ActiveEventLoop, ControlFlow, EventLoop};
use winit::keyboard::{KeyCode, PhysicalKey};
use winit::window::{Window, WindowId};

#[derive(Args, Debug)]
pub(crate) struct ViewArgs {
    #[command(flatten)]
    scene: SceneArgs,
    /// Image width in pixels [default: height × 4/3, or × the glTF camera's aspect ratio].
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=8192))]
    width: Option<u32>,
    /// Image height in pixels.
    #[arg(long, default_value_t = 480, value_parser = clap::value_parser!(u32).range(1..=8192))]
    height: u32,
    /// Light the scene with a latitude-longitude HDR environment map (.hdr or .exr).
    #[arg(long, value_name = "FILE")]
    env: Option<PathBuf>,
    /// Virtual directional lights the environment map is discretised into.
    #[arg(long, default_value_t = 1024, value_parser = clap::value_parser!(u32).range(1..=65536))]
    lights: u32,
    /// Exposure in stops, applied before tone mapping.
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    exposure: f32,
    /// Frames accumulated while the camera rests, after which rendering pauses.
    #[arg(long, default_value_t = 64, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    max_frames: u32,
    /// Start with the top-down map panel shown (Tab toggles it).
    #[arg(long)]
    map: bool,
    /// Where Ctrl+S saves the edited ecosystem (a scene file with every plant where it
    /// stands) [default: NAME-edited.toml in the current directory].
    #[arg(long, value_name = "FILE")]
    save: Option<PathBuf>,
    /// Fly a scripted walkthrough: TOML `[[step]]` tables with `position`, `look_at` or
    /// `rotation`, edits (`select`, `insert`, `move`, `map_select`, `delete`, `undo`, …),
    /// `frames` (wait for that many accumulated frames), `save`, `screenshot` and `quit`.
    #[arg(long, value_name = "FILE")]
    script: Option<PathBuf>,
    /// Write what happens in the window as a script `--script` replays: each camera rest
    /// (exact pose, frames watched), edit, save, screenshot and the quit.
    #[arg(long, value_name = "FILE")]
    record: Option<PathBuf>,
    /// Save every frame the window shows as DIR/frame_NNNNN.png (with its metadata).
    #[arg(long, value_name = "DIR")]
    frames_out: Option<PathBuf>,
    /// Write per shown frame the time of every stage and system and the counters that
    /// explain it to FILE.csv (and the last frame's tile times to FILE.tiles.csv), and
    /// print a summary table at the end; plot it with `sylva profile`.
    #[arg(long, value_name = "FILE.csv")]
    profile: Option<PathBuf>,
    /// Under mpirun (a build with the `mpi` feature): the window on rank 0 and every
    /// rank rendering each frame's tiles; camera moves and edits reach every rank.
    #[arg(long)]
    cluster: bool,
    #[command(flatten)]
    cluster_args: ClusterArgs,
}

/// Sent by the render thread when a frame is ready.
#[derive(Debug)]
struct FrameReady;

/// Runs `sylva view`: the window, or under mpirun with `--cluster` the window on rank
/// 0 and a renderer on every other rank.
pub(crate) fn run(args: ViewArgs) -> Result<()> {
    let mut node = Node::join(&args.cluster_args)?;
    match (args.cluster, node.launched_by_mpi()) {
        (true, false) if cfg!(feature = "mpi") => bail!(
            "--cluster renders on the ranks of an MPI run: start it as `mpirun -np N sylva \
             view --cluster …`"
        ),
        (true, false) => bail!(
            "--cluster needs a sylva built with MPI: `cargo build --release --features mpi`, \
             then `mpirun -np N target/release/sylva view --cluster …`"
        ),
        (false, true) => bail!(
            "under mpirun, `sylva view` needs --cluster (one window on rank 0, every rank \
             rendering); without it each rank would open a window of its own"
        ),
        _ => {}
    }
    let result = match node.leads() {
        true => show(args, &mut node),
        false => serve(&args, &mut node),
    };
    node.end(result)
}

/// A worker rank of `sylva view --cluster`: the scene as rank 0 builds it, rendered
/// with rank 0 frame by frame, its edits applied alike, until the window closes.
fn serve(args: &ViewArgs, node: &mut Node) -> Result<()> {
    check_exposure(args.exposure)?;
    let settings = ViewSettings {
        env: args.env.clone(),
        lights: args.lights,
        exposure: args.exposure,
        max_frames: args.max_frames,
        save: args.save.clone(),
        wake: None,
        profile: None,
    };
    let built = build_scene(&settings, &args.scene, (args.width, args.height));
    let (mut built, cluster) = node.agree_loaded(built)?;
    let Some(cluster) = cluster else {
        bail!("a rank other than 0 outside an MPI run");
    };
    // Only rank 0 shows the image: the display filter is its business.
    built
        .world
        .entity_mut(built.facts.camera)
        .remove::<sylva::engine::discontinuity::DiscontinuityFilter>();
    if let Err(error) = serve_live(built.world, built.facts.camera, cluster) {
        node.fail_with(&error);
    }
    Ok(())
}

/// The window (rank 0 of a cluster run, or the only process).
fn show(args: ViewArgs, node: &mut Node) -> Result<()> {
    check_exposure(args.exposure)?;
    let script = match &args.script {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
            let script = WalkthroughScript::parse(&text)
                .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
            for step in &script.steps {
                if let Some(shot) = &step.screenshot {
                    check_output_path(shot)?;
                }
            }
            Some(script)
        }
        None => None,
    };
    if let Some(record) = &args.record {
        check_parent_dir(record)?;
    }
    if let Some(dir) = &args.frames_out {
        std::fs::create_dir_all(dir)
            .map_err(|e| anyhow::anyhow!("{}: cannot create the directory: {e}", dir.display()))?;
    }
    let profile = match &args.profile {
        Some(path) => Some(Arc::new(Mutex::new(open_profile(path)?))),
        None => None,
    };
    if cfg!(target_os = "linux") && std::env::var_os("DISPLAY").is_none_or(|d| d.is_empty()) {
        bail!(
            "no display: `sylva view` opens an X11 window and DISPLAY is not set (run it in a \
             desktop session or under Xvfb, or render to a file with `sylva render`)"
        );
    }
    let event_loop = EventLoop::<FrameReady>::with_user_event()
        .build()
        .map_err(|e| anyhow::anyhow!("cannot open the display: {e} (try `sylva render`)"))?;
    // winit warns about what virtual X servers report (a display of 0 mm): not the user's
    // business.
    let _trace_guard = init_tracing_filtered(None, "warn,winit=error");

    let proxy = event_loop.create_proxy();
    let settings = Arc::new(ViewSettings {
        env: args.env.clone(),
        lights: args.lights,
        exposure: args.exposure,
        max_frames: args.max_frames,
        save: args.save.clone(),
        wake: Some(proxy),
        profile: profile.clone(),
    });
    let built = build_scene(&settings, &args.scene, (args.width, args.height));
    let (built, cluster) = node.agree_loaded(built)?;
    let clustered = cluster.is_some();
    let loaded = start_scene(&settings, built, cluster)?;
    let font = ab_glyph::FontRef::try_from_slice(dejavu::sans::regular())
        .map_err(|e| anyhow::anyhow!("the HUD font does not load: {e}"))?;
    let mut app = App {
        live: loaded.live,
        saving: Arc::new(loaded.facts.saving),
        hud: Some(Hud {
            font,
            triangles: loaded.facts.triangles,
        }),
        hud_hidden: false,
        wind: false,
        map_shown: args.map,
        camera: loaded.facts.camera,
        modifiers: Modifiers::default(),
        press: None,
        label: loaded.facts.label,
        size: (loaded.facts.width, args.height),
        window: None,
        surface: None,
        shown: None,
        fly: FlyCamera::from_transform(&loaded.facts.start_pose, loaded.facts.speed),
        held: HashSet::new(),
        look: glam::Vec2::ZERO,
        scroll: 0.0,
        dragging: false,
        cursor: None,
        last_step: Instant::now(),
        script: script.map(|s| ScriptRun {
            steps: s.steps,
            next: 0,
            waiting: None,
            started: Instant::now(),
            finished: Vec::new(),
        }),
        screenshots: 0,
        error: None,
        pose: loaded.facts.start_pose,
        views: [loaded.facts.start_pose, loaded.facts.overview],
        scene: args.scene.clone(),
        settings,
        status: None,
        view: 0,
        brush: None,
        moving: false,
        recorder: args
            .record
            .clone()
            .map(|path| (path, ScriptRecorder::default())),
        frames_out: args.frames_out.clone().map(FrameWriter::start),
        clustered,
    };
    event_loop.run_app(&mut app)?;
    let written = app.frames_out.take().map(FrameWriter::finish).transpose();
    if let Some((path, recorder)) = &app.recorder {
        let script = recorder.script(app.shown.as_ref().map_or(1, |s| s.frames));
        sylva::engine::film::write_atomically(path, |tmp| {
            std::fs::write(tmp, script.to_toml()).map_err(|e| e.to_string())
        })?;
        eprintln!(
            "recorded {} steps to {}",
            script.steps.len(),
            path.display()
        );
    }
    if let Some(error) = app.error.take() {
        return Err(error);
    }
    if let Some(frames) = written? {
        eprintln!("saved {frames} frames");
    }
    if let Some(script) = &app.script {
        println!(
            "{}",
            walkthrough_summary(&app.label, &app.live.frame_log(), &script.finished)
        );
    }
    if let (Some(profile), Some(path)) = (&profile, &args.profile) {
        let mut log = profile.lock().unwrap_or_else(PoisonError::into_inner);
        finish_profile(&mut log, path, false);
    }
    if node.is_cluster() {
        // The other ranks are told to quit as the render thread stops.
        let failure = app.live.failure();
        match app.live.stop() {
            Some(world) => {
                if let Some(line) = node.summary(&world) {
                    println!("{line}");
                }
            }
            None => bail!(
                "the render thread failed: {}",
                failure.unwrap_or_else(|| "no reason given".into())
            ),
        }
    }
    Ok(())
}

/// The walkthrough benchmark's lines: frame times over the run, how long a move took to
/// show (steps that waited for one frame), and each longer wait's time to its frames.
fn walkthrough_summary(
    label: &str,
    log: &sylva::systems::live::FrameLog,
    steps: &[(u32, Duration)],
) -> String {
    use sylva::systems::live::FrameLog;
    let ms = |d: Duration| d.as_secs_f64() * 1e3;
    let spread = |times: Vec<Duration>| {
        let log = FrameLog {
            frame_times: times,
            cancelled: 0,
        };
        log.mean_and_p95()
            .map_or("none".to_string(), |(mean, p95)| {
                format!("mean {:.0} ms, p95 {:.0} ms", ms(mean), ms(p95))
            })
    };
    // The first step waits for the scene's first frame, not for a move.
    let moves: Vec<Duration> = steps
        .iter()
        .skip(1)
        .filter(|s| s.0 == 1)
        .map(|s| s.1)
        .collect();
    let rests: Vec<String> = steps
        .iter()
        .enumerate()
        .filter(|(_, s)| s.0 > 1)
        .map(|(i, (frames, took))| {
            format!("step {}: {frames} frames after {:.0} ms", i + 1, ms(*took))
        })
        .collect();
    format!(
        "walkthrough of {label}: {} frames, frame time {}, {} given up for newer input\n  {} one-frame steps (moves, edits) shown after {}{}{}",
        log.frame_times.len(),
        spread(log.frame_times.clone()),
        log.cancelled,
        moves.len(),
        spread(moves.clone()),
        if rests.is_empty() { "" } else { "; " },
        rests.join(", ")
    )
}

/// What every scene the window loads is set up with.
struct ViewSettings {
    env: Option<PathBuf>,
    lights: u32,
    exposure: f32,
    max_frames: u32,
    save: Option<PathBuf>,
    /// Wakes the event loop when the render thread has a frame (none on the ranks that
    /// only render).
    wake: Option<winit::event_loop::EventLoopProxy<FrameReady>>,
    /// `--profile`: every shown frame of every scene opened is added to it.
    profile: Option<Arc<Mutex<ProfileLog>>>,
}

/// What the window needs to know of the scene it shows.
struct SceneFacts {
    camera: Entity,
    start_pose: Transform,
    overview: Transform,
    triangles: u64,
    width: u32,
    /// A walking pace for the scene's size.
    speed: f32,
    saving: Saving,
    label: String,
}

/// A scene built into a world, its render thread not yet started.
struct BuiltScene {
    world: World,
    facts: SceneFacts,
}

/// A scene loaded into a world with its render thread running.
struct LoadedScene {
    live: LiveRender,
    facts: SceneFacts,
}

/// Builds `scene` lit as `settings` say, sized `(width, height)`, and starts its render
/// thread.
fn load_scene(
    settings: &ViewSettings,
    scene_args: &SceneArgs,
    size: (Option<u32>, u32),
) -> Result<LoadedScene> {
    start_scene(settings, build_scene(settings, scene_args, size)?, None)
}

/// Builds `scene` lit as `settings` say, sized `(width, height)`, at interactive quality;
/// its editor actions arrive as shared edits.
fn build_scene(
    settings: &ViewSettings,
    scene_args: &SceneArgs,
    (width, height): (Option<u32>, u32),
) -> Result<BuiltScene> {
    let mut world = World::new();
    let (scene, width, environment) = build_framed(
        &mut world,
        scene_args,
        (settings.env.as_deref(), settings.lights),
        &Framing {
            size: (width, height),
            max_width: 8192,
            exposure: settings.exposure,
        },
    )?;
    let start_pose = scene.camera_transform;
    let overview = {
        use glam::Vec3Swizzles;
        let (mut min, mut max, mut ground) = (
            glam::Vec2::splat(f32::MAX),
            glam::Vec2::splat(f32::MIN),
            0.0f64,
        );
        for plant in &scene.plants {
            let t = plant.transform.translation;
            (min, max) = (min.min(t.xz()), max.max(t.xz()));
            ground += f64::from(t.y);
        }
        if scene.plants.is_empty() {
            (min, max) = (start_pose.translation.xz(), start_pose.translation.xz());
        }
        let ground = (ground / scene.plants.len().max(1) as f64) as f32;
        let aspect = width as f32 / height as f32;
        overview_pose(min, max, ground, scene.camera.vertical_fov, aspect)
    };
    let triangles = scene.stats().instanced_triangles;
    // A pace for the scene's size: a twentieth of the plants' spread per second.
    let extent = scene.plants.iter().fold(1.0f32, |m, p| {
        m.max(p.transform.translation.x.abs())
            .max(p.transform.translation.z.abs())
    });
    let spawned = spawn(&mut world, scene);
    if let Some(environment) = environment {
        world.spawn(environment);
    }
    Quality::interactive().apply(&mut world, spawned.camera);
    if settings.profile.is_some() {
        world.insert_resource(FrameProfiler::enabled());
    }
    let camera = spawned.camera;
    world.insert_resource(SharedEdits(Arc::new(
        move |world: &mut World, bytes: &[u8]| {
            editor::EditorAction::from_bytes(bytes)?.apply(world, camera);
            Ok(())
        },
    )));
    let saving = Saving {
        source: match (&scene_args.gltf, scene_args.scene.as_str()) {
            (Some(_), _) => None,
            (None, name) if name.ends_with(".toml") => {
                Some(editor::SceneSource::File(PathBuf::from(name)))
            }
            (None, name) => Some(editor::SceneSource::Preset(name.to_string())),
        },
        seed: scene_args.seed,
        path: settings.save.clone().unwrap_or_else(|| {
            let stem = Path::new(&scene_args.scene)
                .file_stem()
                .map_or("scene".into(), |s| s.to_string_lossy().into_owned());
            PathBuf::from(format!("{stem}-edited.toml"))
        }),
    };
    Ok(BuiltScene {
        world,
        facts: SceneFacts {
            camera,
            start_pose,
            overview,
            triangles,
            width,
            speed: (extent * 0.05).clamp(1.0, 200.0),
            saving,
            label: scene_label(scene_args),
        },
    })
}

/// Starts the render thread of a built scene; on rank 0 of a cluster run with its
/// `cluster`, which every frame is then shared out over.
fn start_scene(
    settings: &ViewSettings,
    mut built: BuiltScene,
    cluster: Option<Cluster>,
) -> Result<LoadedScene> {
    if let Some(cluster) = cluster {
        built.world.insert_resource(cluster);
    }
    let wake = settings.wake.clone();
    let live = LiveRender::start_profiled(
        built.world,
        built.facts.camera,
        settings.max_frames,
        settings.profile.clone(),
        move || {
            if let Some(wake) = &wake {
                let _ = wake.send_event(FrameReady);
            }
        },
    )?;
    Ok(LoadedScene {
        live,
        facts: built.facts,
    })
}

/// A script in progress: the next step to start, and the step waiting for its frames.
struct ScriptRun {
    steps: Vec<sylva::systems::walkthrough::ScriptStep>,
    next: usize,
    /// The running step's index, the sequence number of its camera command and the
    /// frames it waits for.
    waiting: Option<(usize, u64, u32)>,
    /// When the running step sent its commands.
    started: Instant,
    /// Each finished step: its frames and the time they took to show.
    finished: Vec<(u32, Duration)>,
}

/// What saving the edited ecosystem needs: where the scene came from, its seed and
/// where Ctrl+S writes.
struct Saving {
    source: Option<editor::SceneSource>,
    seed: u64,
    path: PathBuf,
}

impl Saving {
    /// The command that saves on the render thread to `path` (the default when `None`),
    /// reporting on standard error.
    fn command(self: &Arc<Self>, path: Option<PathBuf>) -> LiveCommand {
        let saving = self.clone();
        LiveCommand::Edit(Arc::new(move |world: &mut World| {
            let path = path.clone().unwrap_or_else(|| saving.path.clone());
            let Some(source) = &saving.source else {
                eprintln!("error: saving needs a built-in scene or a .toml scene file, not glTF");
                return;
            };
            match editor::save_ecosystem(world, source, saving.seed, &path) {
                Ok(plants) => eprintln!("saved {plants} plants to {}", path.display()),
                Err(e) => eprintln!("error: {e}"),
            }
        }))
    }
}

struct App {
    live: LiveRender,
    saving: Arc<Saving>,
    /// The heads-up display (H toggles it).
    hud: Option<Hud>,
    hud_hidden: bool,
    /// The wind is blowing (G toggles it).
    wind: bool,
    /// The top-down map panel is shown (Tab toggles it).
    map_shown: bool,
    /// The camera entity (for picking on the render thread).
    camera: Entity,
    modifiers: Modifiers,
    /// Where the left button went down: a release nearby is a click, not a drag.
    press: Option<PhysicalPosition<f64>>,
    label: String,
    size: (u32, u32),
    window: Option<Rc<Window>>,
    surface: Option<softbuffer::Surface<Rc<Window>, Rc<Window>>>,
    shown: Option<ShownImage>,
    fly: FlyCamera,
    held: HashSet<KeyCode>,
    look: glam::Vec2,
    scroll: f32,
    dragging: bool,
    cursor: Option<PhysicalPosition<f64>>,
    last_step: Instant,
    script: Option<ScriptRun>,
    screenshots: u32,
    error: Option<anyhow::Error>,
    /// The camera pose last sent to the renderer.
    pose: Transform,
    /// The scene shown (F5 loads it again; a script's `open` another).
    scene: SceneArgs,
    settings: Arc<ViewSettings>,
    /// The last load's failure, shown on the HUD and in the title until the next load.
    status: Option<String>,
    /// The scene's camera and the overview, which V switches between.
    views: [Transform; 2],
    /// The one shown last.
    view: usize,
    /// I is held down (painting plants): where the cursor was at the last insert.
    brush: Option<PhysicalPosition<f64>>,
    /// The camera moved at the last step (its coming to rest is recorded).
    moving: bool,
    /// `--record`: where the walkthrough goes, and what it holds so far.
    recorder: Option<(PathBuf, ScriptRecorder)>,
    /// `--frames-out`: the writer of every shown frame.
    frames_out: Option<FrameWriter>,
    /// Every rank of an MPI run renders (`--cluster`): the scene cannot be switched.
    clustered: bool,
}

/// Writes shown frames as numbered PNGs on a thread of its own, so the window does not
/// wait on the encoder; a bounded queue makes the window wait rather than drop a frame.
struct FrameWriter {
    queue: Option<std::sync::mpsc::SyncSender<ShownImage>>,
    writer: std::thread::JoinHandle<Result<u32>>,
}

impl FrameWriter {
    fn start(dir: PathBuf) -> Self {
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
    fn push(&self, image: &ShownImage) -> bool {
        self.queue
            .as_ref()
            .is_some_and(|queue| queue.send(image.clone()).is_ok())
    }

    /// Waits for the queued frames to be written; how many were.
    fn finish(mut self) -> Result<u32> {
        self.queue.take();
        self.writer
            .join()
            .map_err(|_| anyhow::anyhow!("the frame writer panicked"))?
    }
}

/// Pixels the cursor moves between two of the brush's inserts.
const BRUSH_STEP: f64 = 8.0;

/// Radians of turn per pixel of mouse drag.
const LOOK_PER_PIXEL: f32 = 0.004;

/// The heads-up display: the frame's figures as text over its top-left corner.
struct Hud {
    font: ab_glyph::FontRef<'static>,
    /// Instanced triangles of the scene as built.
    triangles: u64,
}

/// Text height of the HUD in pixels.
const HUD_TEXT: f32 = 14.0;

impl Hud {
    /// What the HUD says about `shown`.
    fn lines(&self, shown: &ShownImage, speed: f32) -> Vec<String> {
        let ms = |d: Duration| d.as_secs_f64() * 1e3;
        let fps = 1.0 / shown.frame_time.as_secs_f64().max(1e-6);
        let memory =
            current_memory_bytes().map_or("?".to_string(), |b| format!("{:.0} MB", b as f64 / 1e6));
        vec![
            format!(
                "{:.1} fps  {} spp  {:.2} M rays/s",
                fps,
                shown.frames,
                shown.rays_per_second / 1e6
            ),
            format!(
                "render {:.0} ms  filter {:.1} ms  top level {:.1} ms (refit {:.1})  tone map {:.1} ms",
                ms(shown.frame_time),
                ms(shown.filter),
                ms(shown.top_level.0),
                ms(shown.top_level.1),
                ms(shown.tone_map)
            ),
            format!(
                "{} instances  {} instanced triangles (as built)  memory {memory}",
                group(shown.instances as u64),
                group(self.triangles)
            ),
            format!(
                "{:.1} m/s  {}  H hides this",
                speed,
                shown
                    .selected
                    .map_or("nothing selected".to_string(), |e| format!(
                        "plant {e} selected"
                    ))
            ),
        ]
    }

    /// Draws `lines` in white on a darkened band at the top left of `buffer`.
    fn draw(&self, buffer: &mut [u32], width: usize, height: usize, lines: &[String]) {
        use ab_glyph::{Font, ScaleFont, point};
        let scaled = self.font.as_scaled(HUD_TEXT);
        let line_height = scaled.height().ceil() as usize + 2;
        let band = (line_height * lines.len() + 6).min(height);
        let text_width = lines
            .iter()
            .map(|l| {
                l.chars()
                    .map(|c| scaled.h_advance(self.font.glyph_id(c)))
                    .sum::<f32>()
            })
            .fold(0.0f32, f32::max);
        let band_width = ((text_width.ceil() as usize) + 12).min(width);
        for row in buffer.chunks_exact_mut(width).take(band) {
            for pixel in &mut row[..band_width] {
                // Halve each channel: the image stays visible under the text.
                *pixel = (*pixel >> 1) & 0x007f_7f7f;
            }
        }
        for (i, line) in lines.iter().enumerate() {
            let mut x = 6.0;
            let baseline = 3.0 + scaled.ascent() + (i * line_height) as f32;
            for c in line.chars() {
                let glyph = self
                    .font
                    .glyph_id(c)
                    .with_scale_and_position(HUD_TEXT, point(x, baseline));
                x += scaled.h_advance(glyph.id);
                let Some(outline) = self.font.outline_glyph(glyph) else {
                    continue;
                };
                let bounds = outline.px_bounds();
                outline.draw(|gx, gy, coverage| {
                    let px = bounds.min.x as i64 + i64::from(gx);
                    let py = bounds.min.y as i64 + i64::from(gy);
                    if px < 0 || py < 0 || px as usize >= width || py as usize >= height {
                        return;
                    }
                    let pixel = &mut buffer[py as usize * width + px as usize];
                    let blend = |shift: u32| {
                        let under = ((*pixel >> shift) & 0xff) as f32;
                        ((under + (255.0 - under) * coverage.clamp(0.0, 1.0)) as u32) << shift
                    };
                    *pixel = blend(16) | blend(8) | blend(0);
                });
            }
        }
    }
}

/// The editor's top-down map: a square panel at the bottom right of the window with
/// every plant as a circle coloured by species and sized by its crown.
#[derive(Clone, Copy, Debug, PartialEq)]
struct MapView {
    /// Panel's top-left pixel and side.
    left: f32,
    top: f32,
    side: f32,
    /// World (x, z) at the panel's top-left, and pixels per metre.
    origin: glam::Vec2,
    scale: f32,
}

impl MapView {
    /// The panel for a `width × height` window showing `plants` (their spread, padded).
    fn new(width: u32, height: u32, plants: &[sylva::systems::picking::MapPlant]) -> Self {
        let side = (width.min(height) as f32 * 0.45).floor();
        let (lo, hi) = plants.iter().fold(
            (
                glam::Vec2::splat(f32::INFINITY),
                glam::Vec2::splat(f32::NEG_INFINITY),
            ),
            |(lo, hi), p| (lo.min(p.position), hi.max(p.position)),
        );
        let (lo, hi) = if lo.x <= hi.x {
            (lo, hi)
        } else {
            (glam::Vec2::ZERO, glam::Vec2::ONE)
        };
        let extent = (hi - lo).max_element().max(1.0) * 1.04;
        let centre = (lo + hi) * 0.5;
        Self {
            left: width as f32 - side - 6.0,
            top: height as f32 - side - 6.0,
            side,
            origin: centre - glam::Vec2::splat(extent * 0.5),
            scale: side / extent,
        }
    }

    fn contains(self, x: f32, y: f32) -> bool {
        x >= self.left && y >= self.top && x < self.left + self.side && y < self.top + self.side
    }

    fn to_panel(self, world: glam::Vec2) -> glam::Vec2 {
        glam::Vec2::new(self.left, self.top) + (world - self.origin) * self.scale
    }

    fn to_world(self, x: f32, y: f32) -> glam::Vec2 {
        self.origin + (glam::Vec2::new(x, y) - glam::Vec2::new(self.left, self.top)) / self.scale
    }

    /// The plant drawn under panel pixel `(x, y)`: the nearest whose circle (at least
    /// three pixels wide) holds it.
    fn plant_at(
        &self,
        plants: &[sylva::systems::picking::MapPlant],
        x: f32,
        y: f32,
    ) -> Option<Entity> {
        let at = self.to_world(x, y);
        plants
            .iter()
            .map(|p| (p, p.position.distance(at)))
            .filter(|(p, d)| *d <= p.radius.max(3.0 / self.scale))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(p, _)| p.entity)
    }

    /// Draws the panel into `buffer` (`width` pixels a row).
    fn draw(
        &self,
        buffer: &mut [u32],
        width: usize,
        plants: &[sylva::systems::picking::MapPlant],
        selected: Option<Entity>,
    ) {
        let height = buffer.len() / width.max(1);
        let (x0, y0, side) = (self.left as usize, self.top as usize, self.side as usize);
        for row in y0..(y0 + side).min(height) {
            for pixel in
                &mut buffer[row * width + x0..(row * width + x0 + side).min((row + 1) * width)]
            {
                *pixel = 0x0020_2820;
            }
        }
        let mut disc = |centre: glam::Vec2, radius: f32, colour: u32| {
            let r = radius.max(0.7);
            let (lo, hi) = (centre - r, centre + r);
            for y in lo.y.floor().max(self.top) as usize
                ..=hi.y.ceil().min(self.top + self.side - 1.0) as usize
            {
                for x in lo.x.floor().max(self.left) as usize
                    ..=hi.x.ceil().min(self.left + self.side - 1.0) as usize
                {
                    let d = glam::Vec2::new(x as f32 + 0.5, y as f32 + 0.5) - centre;
                    if (d.length() <= r || r < 1.0) && y < height && x < width {
                        buffer[y * width + x] = colour;
                    }
                }
            }
        };
        // Larger plants first, so the small ones under them stay visible.
        let mut order: Vec<&sylva::systems::picking::MapPlant> = plants.iter().collect();
        order.sort_by(|a, b| b.radius.total_cmp(&a.radius));
        for plant in order {
            disc(
                self.to_panel(plant.position),
                plant.radius * self.scale,
                species_colour(plant.species),
            );
        }
        if let Some(p) = plants.iter().find(|p| Some(p.entity) == selected) {
            let centre = self.to_panel(p.position);
            disc(centre, (p.radius * self.scale).max(3.0) + 2.0, 0x00ff_ffff);
            disc(
                centre,
                (p.radius * self.scale).max(3.0),
                species_colour(p.species),
            );
        }
    }
}

/// A bright, stable colour per species.
fn species_colour(species: u32) -> u32 {
    let h = sylva::engine::sampling::mix64(u64::from(species) + 17);
    let channel = |shift: u32| 0x40 + ((h >> shift) & 0xff) as u32 * 3 / 4;
    (channel(0) << 16) | (channel(8) << 8) | channel(16)
}

/// Resident memory of this process now (Linux `VmRSS`), when known.
fn current_memory_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

impl App {
    /// Sends an editor action the user made (recorded with `--record`); its sequence
    /// number.
    fn edit(&mut self, action: EditorAction) -> Option<u64> {
        let step = match action {
            EditorAction::Select(x, y) => ScriptStep {
                select: Some([x, y]),
                ..ScriptStep::default()
            },
            EditorAction::Insert(x, y) => ScriptStep {
                insert: Some([x, y]),
                ..ScriptStep::default()
            },
            EditorAction::Move(x, y) => ScriptStep {
                move_to: Some([x, y]),
                ..ScriptStep::default()
            },
            EditorAction::Delete => ScriptStep {
                delete: true,
                ..ScriptStep::default()
            },
            EditorAction::Undo => ScriptStep {
                undo: true,
                ..ScriptStep::default()
            },
            EditorAction::Redo => ScriptStep {
                redo: true,
                ..ScriptStep::default()
            },
            EditorAction::Wind(on) => ScriptStep {
                wind: Some(on),
                ..ScriptStep::default()
            },
            EditorAction::SelectAtGround(x, z) => ScriptStep {
                map_select: Some([x, z]),
                ..ScriptStep::default()
            },
            EditorAction::SelectPlant(plant) => ScriptStep {
                map_select: self
                    .shown
                    .as_ref()
                    .and_then(|s| s.map.iter().find(|p| p.entity == plant))
                    .map(|p| p.position.to_array()),
                ..ScriptStep::default()
            },
            EditorAction::InsertAtGround(x, z) => ScriptStep {
                map_insert: Some([x, z]),
                ..ScriptStep::default()
            },
            EditorAction::MoveToGround(x, z) => ScriptStep {
                map_move: Some([x, z]),
                ..ScriptStep::default()
            },
        };
        self.record(step);
        self.live.send(LiveCommand::Shared(action.to_bytes()))
    }

    /// Records `step` with `--record`, at the pose last sent.
    fn record(&mut self, step: ScriptStep) {
        let shown_frames = self.shown.as_ref().map_or(1, |s| s.frames);
        if let Some((_, recorder)) = &mut self.recorder {
            recorder.record(&self.pose, shown_frames, step);
        }
    }

    /// Loads `scene` in place of the one shown, keeping the camera where it is; a scene
    /// that fails to load leaves the shown one running and its error on the HUD.
    /// Returns the sequence number a step waits for.
    fn switch_scene(&mut self, scene: SceneArgs) -> u64 {
        if self.clustered {
            let message = format!(
                "{}: switching scenes is not available with --cluster (kept {})",
                scene_label(&scene),
                self.label
            );
            eprintln!("error: {message}");
            self.status = Some(message);
            self.update_title();
            return self.live.last_sent();
        }
        let loaded = match load_scene(&self.settings, &scene, (Some(self.size.0), self.size.1)) {
            Ok(loaded) => loaded,
            Err(e) => {
                let message = format!("{}: {e:#} (kept {})", scene_label(&scene), self.label);
                eprintln!("error: {message}");
                self.status = Some(message);
                self.update_title();
                return self.live.last_sent();
            }
        };
        self.live = loaded.live;
        self.camera = loaded.facts.camera;
        self.views = [loaded.facts.start_pose, loaded.facts.overview];
        self.saving = Arc::new(loaded.facts.saving);
        self.label = loaded.facts.label;
        if let Some(hud) = &mut self.hud {
            hud.triangles = loaded.facts.triangles;
        }
        self.scene = scene;
        self.status = None;
        self.wind = false;
        // The image shown came from the last render thread: the next frames must come
        // from this one before a script step counts them.
        if let Some(shown) = &mut self.shown {
            (shown.applied, shown.frames) = (0, 0);
        }
        eprintln!("loaded {}", self.label);
        self.send_pose(self.pose).unwrap_or(0)
    }

    /// Plants one of the selected plant's species where the cursor points, on the map or
    /// in the view (refused by the render thread where the layer's spacing forbids it).
    fn insert_at_cursor(&mut self) {
        if let Some(at) = self.cursor_on_map() {
            self.edit(EditorAction::InsertAtGround(at.x, at.y));
        } else if let Some((x, y)) = self.cursor_pixel() {
            self.edit(EditorAction::Insert(x, y));
        }
    }

    /// Records the end of the walkthrough (a script's own quit step is recorded with it).
    fn record_quit(&mut self) {
        self.record(ScriptStep {
            quit: true,
            ..ScriptStep::default()
        });
    }

    /// Sends a camera pose; its sequence number.
    fn send_pose(&mut self, pose: Transform) -> Option<u64> {
        self.pose = pose;
        self.live.send(LiveCommand::Pose(pose))
    }

    /// The map panel as drawn now, when it is shown.
    fn map_view(&self) -> Option<MapView> {
        let shown = self.shown.as_ref().filter(|_| self.map_shown)?;
        Some(MapView::new(self.size.0, self.size.1, &shown.map))
    }

    /// The ground position (x, z) under the cursor when it is over the map panel.
    fn cursor_on_map(&self) -> Option<glam::Vec2> {
        let (map, cursor) = self.map_view().zip(self.cursor)?;
        let (x, y) = (cursor.x as f32, cursor.y as f32);
        map.contains(x, y).then(|| map.to_world(x, y))
    }

    /// The image pixel under the cursor, if it is over the image.
    fn cursor_pixel(&self) -> Option<(u32, u32)> {
        let cursor = self.cursor?;
        let (x, y) = (cursor.x.floor(), cursor.y.floor());
        (x >= 0.0 && y >= 0.0 && (x as u32) < self.size.0 && (y as u32) < self.size.1)
            .then_some((x as u32, y as u32))
    }

    fn fail(&mut self, event_loop: &ActiveEventLoop, error: anyhow::Error) {
        self.error = Some(error);
        event_loop.exit();
    }

    /// What the held keys ask for.
    fn input(&self) -> FlyInput {
        let axis = |plus: &[KeyCode], minus: &[KeyCode]| {
            let on = |keys: &[KeyCode]| keys.iter().any(|k| self.held.contains(k));
            f32::from(u8::from(on(plus))) - f32::from(u8::from(on(minus)))
        };
        FlyInput {
            forward: axis(
                &[KeyCode::KeyW, KeyCode::ArrowUp],
                &[KeyCode::KeyS, KeyCode::ArrowDown],
            ),
            right: axis(
                &[KeyCode::KeyD, KeyCode::ArrowRight],
                &[KeyCode::KeyA, KeyCode::ArrowLeft],
            ),
            up: axis(
                &[KeyCode::KeyE, KeyCode::Space],
                &[KeyCode::KeyQ, KeyCode::KeyC],
            ),
            look: self.look,
            speed_steps: self.scroll,
        }
    }

    /// The window title as a heads-up line: frames, frame time, rays/s, speed, keys.
    fn update_title(&self) {
        let (Some(window), Some(shown)) = (&self.window, &self.shown) else {
            return;
        };
        if let Some(status) = &self.status {
            window.set_title(&format!("sylva view: load failed: {status}"));
            return;
        }
        window.set_title(&format!(
            "sylva view: {}, {} frames, {:.0} ms/frame, {:.2} M rays/s, {:.1} m/s, {} (WASD/arrows move, Q/E down/up, drag to look, scroll speed, click select, I insert (hold and move to paint), M move, Del delete, Ctrl+Z/Y undo/redo, G wind, V overview/camera, F5 reload, Tab map, H HUD, P screenshot, Esc quit)",
            self.label,
            shown.frames,
            shown.frame_time.as_secs_f64() * 1e3,
            shown.rays_per_second / 1e6,
            self.fly.speed,
            shown
                .selected
                .map_or("nothing selected".to_string(), |e| format!("plant {e} selected")),
        ));
    }

    /// Saves the shown frame as a PNG (atomically) with what it shows in its metadata.
    fn screenshot(&mut self, path: &Path) -> Result<()> {
        let shown = self
            .shown
            .as_ref()
            .ok_or_else(|| anyhow::anyhow!("no frame to save yet"))?;
        let rgba: Vec<u8> = shown
            .pixels
            .iter()
            .flat_map(|p| [(p >> 16) as u8, (p >> 8) as u8, *p as u8, 255])
            .collect();
        let pose = self.fly.transform();
        let forward = pose.rotation * -glam::Vec3::Z;
        let metadata: Vec<(String, String)> = [
            (
                "Software",
                format!("sylva {} view", env!("CARGO_PKG_VERSION")),
            ),
            ("sylva.scene", self.label.clone()),
            ("sylva.size", format!("{}x{}", shown.width, shown.height)),
            ("sylva.frames", shown.frames.to_string()),
            ("sylva.quality", "interactive".to_string()),
            (
                "sylva.camera.position",
                format!("{:?}", pose.translation.to_array()),
            ),
            ("sylva.camera.forward", format!("{:?}", forward.to_array())),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        sylva::engine::film::write_rgba8_png(path, (shown.width, shown.height), &rgba, &metadata)?;
        eprintln!("saved {}", path.display());
        Ok(())
    }

    /// Starts the script's next step, or finishes a step whose frames are shown.
    fn advance_script(&mut self, event_loop: &ActiveEventLoop) {
        loop {
            let Some(script) = &mut self.script else {
                return;
            };
            match script.waiting {
                Some((index, command, frames)) => {
                    let Some(shown) = &self.shown else { return };
                    if shown.applied < command || shown.frames < frames {
                        return;
                    }
                    let step = script.steps[index].clone();
                    script.waiting = None;
                    script.finished.push((frames, script.started.elapsed()));
                    if let Some(path) = &step.screenshot
                        && let Err(e) = self.screenshot(path)
                    {
                        return self.fail(event_loop, e);
                    }
                    if step.quit {
                        event_loop.exit();
                        return;
                    }
                }
                None => {
                    let Some(step) = script.steps.get(script.next).cloned() else {
                        return;
                    };
                    let index = script.next;
                    script.next += 1;
                    let opened = match (&step.open, step.reload) {
                        (Some(path), _) => {
                            let scene = self.scene.opening(path);
                            Some(self.switch_scene(scene))
                        }
                        (None, true) => Some(self.switch_scene(self.scene.clone())),
                        (None, false) => None,
                    };
                    // A step that stays where the camera is sends nothing: a pose that
                    // differs in the last bit would restart the accumulation.
                    let command = if WalkthroughScript::moves(&step) {
                        let from = match step.overview {
                            Some(overview) => {
                                self.view = usize::from(overview);
                                self.views[self.view]
                            }
                            None => self.pose,
                        };
                        let pose = WalkthroughScript::pose(&step, &from);
                        self.fly = FlyCamera::from_transform(&pose, self.fly.speed);
                        let Some(command) = self.send_pose(pose) else {
                            return self.fail(event_loop, anyhow::anyhow!("the renderer stopped"));
                        };
                        command
                    } else {
                        opened.unwrap_or_else(|| self.live.last_sent())
                    };
                    self.record(step.clone());
                    let actions = [
                        step.select.map(|[x, y]| EditorAction::Select(x, y)),
                        step.map_select
                            .map(|[x, z]| EditorAction::SelectAtGround(x, z)),
                        step.insert.map(|[x, y]| EditorAction::Insert(x, y)),
                        step.map_insert
                            .map(|[x, z]| EditorAction::InsertAtGround(x, z)),
                        step.move_to.map(|[x, y]| EditorAction::Move(x, y)),
                        step.map_move.map(|[x, z]| EditorAction::MoveToGround(x, z)),
                        step.delete.then_some(EditorAction::Delete),
                        step.undo.then_some(EditorAction::Undo),
                        step.redo.then_some(EditorAction::Redo),
                        step.wind.map(EditorAction::Wind),
                    ];
                    let mut command = command;
                    for action in actions.into_iter().flatten() {
                        let Some(number) = self.live.send(LiveCommand::Shared(action.to_bytes()))
                        else {
                            return self.fail(event_loop, anyhow::anyhow!("the renderer stopped"));
                        };
                        command = number;
                    }
                    if let Some(path) = &step.save {
                        let Some(number) = self.live.send(self.saving.command(Some(path.clone())))
                        else {
                            return self.fail(event_loop, anyhow::anyhow!("the renderer stopped"));
                        };
                        command = number;
                    }
                    if let Some(script) = &mut self.script {
                        script.waiting = Some((index, command, step.frames.unwrap_or(1)));
                        script.started = Instant::now();
                    }
                }
            }
        }
    }
}

impl ApplicationHandler<FrameReady> for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.window.is_some() {
            return;
        }
        let attributes = Window::default_attributes()
            .with_title(format!("sylva view: {}", self.label))
            .with_inner_size(PhysicalSize::new(self.size.0, self.size.1))
            .with_resizable(false);
        let window = match event_loop.create_window(attributes) {
            Ok(window) => Rc::new(window),
            Err(e) => return self.fail(event_loop, anyhow::anyhow!("cannot open a window: {e}")),
        };
        let surface = softbuffer::Context::new(window.clone())
            .and_then(|context| softbuffer::Surface::new(&context, window.clone()));
        match surface {
            Ok(surface) => self.surface = Some(surface),
            Err(e) => {
                return self.fail(
                    event_loop,
                    anyhow::anyhow!("cannot draw to the window: {e}"),
                );
            }
        }
        self.window = Some(window);
    }

    fn user_event(&mut self, event_loop: &ActiveEventLoop, _: FrameReady) {
        if let Some(failure) = self.live.failure() {
            return self.fail(
                event_loop,
                anyhow::anyhow!("the render thread failed: {failure}"),
            );
        }
        if let Some(image) = self.live.take_latest() {
            if let Some(writer) = &self.frames_out
                && !writer.push(&image)
            {
                self.frames_out.take();
                return self.fail(
                    event_loop,
                    anyhow::anyhow!("saving the shown frames failed"),
                );
            }
            self.shown = Some(image);
            self.update_title();
            if let Some(window) = &self.window {
                window.request_redraw();
            }
            self.advance_script(event_loop);
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => {
                self.record_quit();
                event_loop.exit();
            }
            WindowEvent::KeyboardInput { event, .. } => {
                let PhysicalKey::Code(code) = event.physical_key else {
                    return;
                };
                match (code, event.state) {
                    (KeyCode::Escape, ElementState::Pressed) => {
                        self.record_quit();
                        event_loop.exit();
                    }
                    (KeyCode::Delete | KeyCode::Backspace, ElementState::Pressed)
                        if !event.repeat =>
                    {
                        self.edit(EditorAction::Delete);
                    }
                    (KeyCode::KeyI, ElementState::Pressed) if !event.repeat => {
                        self.brush = self.cursor;
                        self.insert_at_cursor();
                    }
                    (KeyCode::KeyI, ElementState::Released) => self.brush = None,
                    (KeyCode::KeyM, ElementState::Pressed) if !event.repeat => {
                        if let Some((x, y)) = self.cursor_pixel() {
                            self.edit(EditorAction::Move(x, y));
                        }
                    }
                    (KeyCode::KeyS, ElementState::Pressed)
                        if self.modifiers.state().control_key() && !event.repeat =>
                    {
                        self.held.remove(&KeyCode::KeyS);
                        self.record(ScriptStep {
                            save: Some(self.saving.path.clone()),
                            ..ScriptStep::default()
                        });
                        self.live.send(self.saving.command(None));
                    }
                    (KeyCode::KeyZ | KeyCode::KeyY, ElementState::Pressed)
                        if self.modifiers.state().control_key() =>
                    {
                        let redo = code == KeyCode::KeyY || self.modifiers.state().shift_key();
                        self.edit(if redo {
                            EditorAction::Redo
                        } else {
                            EditorAction::Undo
                        });
                    }
                    (KeyCode::Tab, ElementState::Pressed) if !event.repeat => {
                        self.map_shown = !self.map_shown;
                        if let Some(window) = &self.window {
                            window.request_redraw();
                        }
                    }
                    (KeyCode::KeyG, ElementState::Pressed) if !event.repeat => {
                        self.wind = !self.wind;
                        self.edit(EditorAction::Wind(self.wind));
                    }
                    (KeyCode::F5, ElementState::Pressed) if !event.repeat => {
                        self.switch_scene(self.scene.clone());
                        self.record(ScriptStep {
                            reload: true,
                            ..ScriptStep::default()
                        });
                    }
                    (KeyCode::KeyV, ElementState::Pressed) if !event.repeat => {
                        self.view = (self.view + 1) % self.views.len();
                        let pose = self.views[self.view];
                        self.fly = FlyCamera::from_transform(&pose, self.fly.speed);
                        if self.send_pose(pose).is_none() {
                            return self.fail(event_loop, anyhow::anyhow!("the renderer stopped"));
                        }
                        self.record(ScriptStep::default());
                    }
                    (KeyCode::KeyH, ElementState::Pressed) if !event.repeat => {
                        self.hud_hidden = !self.hud_hidden;
                        if let Some(window) = &self.window {
                            window.request_redraw();
                        }
                    }
                    (KeyCode::KeyP, ElementState::Pressed) if !event.repeat => {
                        self.screenshots += 1;
                        let path = PathBuf::from(format!("sylva-view-{:03}.png", self.screenshots));
                        if let Err(e) = self.screenshot(&path) {
                            eprintln!("warning: {e:#}");
                        } else {
                            self.record(ScriptStep {
                                screenshot: Some(path),
                                ..ScriptStep::default()
                            });
                        }
                    }
                    (code, ElementState::Pressed) => {
                        self.held.insert(code);
                    }
                    (code, ElementState::Released) => {
                        self.held.remove(&code);
                    }
                }
            }
            WindowEvent::Focused(false) => {
                self.held.clear();
                self.brush = None;
            }
            WindowEvent::ModifiersChanged(modifiers) => self.modifiers = modifiers,
            WindowEvent::MouseInput {
                state,
                button: MouseButton::Left,
                ..
            } => {
                self.dragging = state == ElementState::Pressed;
                match state {
                    ElementState::Pressed => self.press = self.cursor,
                    ElementState::Released => {
                        // A click (the cursor barely moved) selects what it points at.
                        let press = self.press.take();
                        let clicked = press
                            .zip(self.cursor)
                            .is_some_and(|(a, b)| (a.x - b.x).abs() + (a.y - b.y).abs() < 4.0);
                        let on_map = self
                            .map_view()
                            .zip(press)
                            .filter(|(map, p)| map.contains(p.x as f32, p.y as f32));
                        if let (Some((map, _)), Some(cursor)) = (on_map, self.cursor) {
                            // On the map a click selects and a drag moves the selection.
                            let (x, y) = (cursor.x as f32, cursor.y as f32);
                            if clicked {
                                let plants = self
                                    .shown
                                    .as_ref()
                                    .map(|s| s.map.clone())
                                    .unwrap_or_default();
                                if let Some(plant) = map.plant_at(&plants, x, y) {
                                    self.edit(EditorAction::SelectPlant(plant));
                                }
                            } else if map.contains(x, y) {
                                let to = map.to_world(x, y);
                                self.edit(EditorAction::MoveToGround(to.x, to.y));
                            }
                        } else if clicked && let Some((x, y)) = self.cursor_pixel() {
                            self.edit(EditorAction::Select(x, y));
                        }
                    }
                }
            }
            WindowEvent::CursorMoved { position, .. } => {
                let on_map = self
                    .map_view()
                    .zip(self.press)
                    .is_some_and(|(map, p)| map.contains(p.x as f32, p.y as f32));
                if self.dragging
                    && !on_map
                    && let Some(last) = self.cursor
                {
                    self.look += glam::Vec2::new(
                        (position.x - last.x) as f32,
                        -(position.y - last.y) as f32,
                    ) * LOOK_PER_PIXEL;
                }
                self.cursor = Some(position);
                // I held down paints: a plant wherever the cursor has moved on a few
                // pixels, where the layer's spacing allows one.
                if let Some(last) = self.brush
                    && (position.x - last.x).abs() + (position.y - last.y).abs() >= BRUSH_STEP
                {
                    self.brush = Some(position);
                    self.insert_at_cursor();
                }
            }
            WindowEvent::MouseWheel { delta, .. } => {
                self.scroll += match delta {
                    MouseScrollDelta::LineDelta(_, y) => y,
                    MouseScrollDelta::PixelDelta(p) => (p.y / 40.0) as f32,
                };
            }
            WindowEvent::RedrawRequested => {
                if let Err(e) = self.present() {
                    self.fail(event_loop, e);
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, event_loop: &ActiveEventLoop) {
        let now = Instant::now();
        let seconds = now.duration_since(self.last_step).as_secs_f32().min(0.1);
        self.last_step = now;
        let input = self.input();
        (self.look, self.scroll) = (glam::Vec2::ZERO, 0.0);
        let scrolled = input.speed_steps != 0.0;
        if self.fly.step(&input, seconds) {
            self.moving = true;
            let pose = self.fly.transform();
            if self.send_pose(pose).is_none() {
                return self.fail(event_loop, anyhow::anyhow!("the renderer stopped"));
            }
        } else if std::mem::take(&mut self.moving) {
            // Come to rest: a stop of the recorded walkthrough.
            self.record(ScriptStep::default());
        }
        if scrolled {
            self.update_title();
        }
        // Keys held: keep stepping at about 60 Hz; otherwise sleep until an event.
        event_loop.set_control_flow(if self.held.is_empty() {
            ControlFlow::Wait
        } else {
            ControlFlow::WaitUntil(now + Duration::from_millis(16))
        });
    }
}

impl App {
    /// Copies the latest frame into the window (black where the window is larger).
    fn present(&mut self) -> Result<()> {
        let map = self.map_view();
        let (Some(window), Some(surface)) = (&self.window, &mut self.surface) else {
            return Ok(());
        };
        let size = window.inner_size();
        let (Some(w), Some(h)) = (NonZeroU32::new(size.width), NonZeroU32::new(size.height)) else {
            return Ok(());
        };
        surface
            .resize(w, h)
            .map_err(|e| anyhow::anyhow!("cannot size the window's buffer: {e}"))?;
        let mut buffer = surface
            .buffer_mut()
            .map_err(|e| anyhow::anyhow!("cannot draw to the window: {e}"))?;
        buffer.fill(0);
        if let Some(shown) = &self.shown {
            let columns = (shown.width as usize).min(size.width as usize);
            for row in 0..(shown.height as usize).min(size.height as usize) {
                let src = row * shown.width as usize;
                let dst = row * size.width as usize;
                buffer[dst..dst + columns].copy_from_slice(&shown.pixels[src..src + columns]);
            }
            if let Some(map) = map {
                map.draw(&mut buffer, size.width as usize, &shown.map, shown.selected);
            }
            if let Some(hud) = self.hud.as_ref().filter(|_| !self.hud_hidden) {
                let mut lines = hud.lines(shown, self.fly.speed);
                if let Some(status) = &self.status {
                    lines.push(format!("load failed: {status}"));
                }
                hud.draw(
                    &mut buffer,
                    size.width as usize,
                    size.height as usize,
                    &lines,
                );
            }
        }
        buffer
            .present()
            .map_err(|e| anyhow::anyhow!("cannot show the frame: {e}"))?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_map_panel_maps_ground_to_pixels_and_back_and_finds_the_plant_under_a_click() {
        use sylva::systems::picking::MapPlant;
        let mut world = World::new();
        let (a, b) = (world.spawn_empty().id(), world.spawn_empty().id());
        let plants = [
            MapPlant {
                entity: a,
                position: glam::Vec2::new(-50.0, -50.0),
                radius: 4.0,
                species: 1,
            },
            MapPlant {
                entity: b,
                position: glam::Vec2::new(50.0, 50.0),
                radius: 0.5,
                species: 2,
            },
        ];
        let map = MapView::new(640, 480, &plants);
        assert_eq!(map.side, 216.0);
        let ground = glam::Vec2::new(12.5, -7.0);
        let p = map.to_panel(ground);
        assert!(map.contains(p.x, p.y));
        assert!((map.to_world(p.x, p.y) - ground).length() < 1e-3);
        let at_a = map.to_panel(plants[0].position);
        assert_eq!(map.plant_at(&plants, at_a.x + 1.0, at_a.y), Some(a));
        let at_b = map.to_panel(plants[1].position);
        // A small plant is still hit within three pixels.
        assert_eq!(map.plant_at(&plants, at_b.x + 2.0, at_b.y), Some(b));
        assert_eq!(map.plant_at(&plants, p.x, p.y), None);
        let mut buffer = vec![0u32; 640 * 480];
        map.draw(&mut buffer, 640, &plants, Some(b));
        let outside = buffer[..640 * 200].iter().all(|&p| p == 0);
        assert!(outside, "the panel drew above itself");
        let (ax, ay) = (at_a.x as usize, at_a.y as usize);
        assert_eq!(buffer[ay * 640 + ax], species_colour(1));
        let (bx, by) = (at_b.x as usize, at_b.y as usize);
        assert_eq!(buffer[by * 640 + bx], species_colour(2));
        assert_eq!(buffer[by * 640 + bx + 4], 0x00ff_ffff, "the selection ring");
    }

    #[test]
    fn the_hud_writes_its_lines_on_a_darkened_band_and_leaves_the_rest() {
        let hud = Hud {
            font: ab_glyph::FontRef::try_from_slice(dejavu::sans::regular()).unwrap(),
            triangles: 1_234_567,
        };
        let shown = ShownImage {
            width: 320,
            height: 200,
            frames: 7,
            frame_time: Duration::from_millis(250),
            instances: 42,
            ..ShownImage::default()
        };
        let lines = hud.lines(&shown, 2.5);
        assert!(lines[0].starts_with("4.0 fps  7 spp"), "{lines:?}");
        assert!(lines[2].contains("42 instances") && lines[2].contains("1,234,567"));
        let grey = 0x0080_8080;
        let mut buffer = vec![grey; 320 * 200];
        hud.draw(&mut buffer, 320, 200, &lines);
        let band_rows = (0..200)
            .filter(|&y| buffer[y * 320..y * 320 + 4].iter().all(|&p| p != grey))
            .count();
        assert!((60..100).contains(&band_rows), "{band_rows} rows darkened");
        let bright = buffer.iter().filter(|&&p| p & 0xff > 0xc0).count();
        assert!(bright > 200, "only {bright} text pixels");
        assert!(
            buffer[150 * 320..].iter().all(|&p| p == grey),
            "below the band"
        );
    }
}
