//! `sylva view`: a window onto a scene. Walk through it with the keyboard and mouse
//! while it renders at interactive quality on the render thread and refines when the
//! camera rests; or fly a scripted walkthrough (`--script`) for tests and benchmarks.
//! The window's glue only: the camera control, the scripts and the render thread are
//! `sylva_systems::walkthrough` and `sylva_systems::live`. Here: the arguments and the
//! run (`mod.rs`), the scene a window shows (`scene`), its state and actions (`app`),
//! winit's events (`events`), the HUD (`hud`), the map panel (`map`) and the frame writer
//! (`frames`).

mod app;
mod events;
mod frames;
mod hud;
mod map;
mod scene;
#[cfg(test)]
mod tests;

use super::cluster::{ClusterArgs, Node};
use super::profile::{finish_profile, open_profile};
use super::*;
use app::{App, HeldKeys, ScriptRun};
use frames::FrameWriter;
use hud::Hud;
use scene::{ViewSettings, build_scene, start_scene};
use std::collections::HashSet;
use std::num::NonZeroU32;
use std::rc::Rc;
use std::sync::{Mutex, PoisonError};
use std::time::Instant;
use sylva::scenes::editor;
use sylva::scenes::editor::EditorAction;
use sylva::systems::cluster::Cluster;
use sylva::systems::live::{
    LiveCommand, LiveRender, Responsiveness, SharedEdits, ShownImage, serve_live,
};
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
    #[command(flatten)]
    lighting: LightingArgs,
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
        env: args.lighting.env.clone(),
        lights: args.lighting.lights,
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
        env: args.lighting.env.clone(),
        lights: args.lighting.lights,
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
        responsiveness: Responsiveness::default(),
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
            holding: None,
            held: HeldKeys::default(),
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
        if script.held.seconds > 0.0 {
            println!("{}", held_keys_summary(&script.held));
        }
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

/// The walkthrough benchmark's line for held keys: frames shown while a key was held,
/// their rate, and the input-to-image latency of those that showed new input.
fn held_keys_summary(held: &HeldKeys) -> String {
    use sylva::systems::live::FrameLog;
    let latency = FrameLog {
        frame_times: held.latencies.clone(),
        cancelled: 0,
    }
    .mean_and_p95()
    .map_or("none".to_string(), |(mean, p95)| {
        format!(
            "mean {:.0} ms, p95 {:.0} ms",
            mean.as_secs_f64() * 1e3,
            p95.as_secs_f64() * 1e3
        )
    });
    format!(
        "  held keys: {} frames shown in {:.1} s ({:.1} a second), input to image {latency}",
        held.frames,
        held.seconds,
        f64::from(held.frames) / held.seconds
    )
}
