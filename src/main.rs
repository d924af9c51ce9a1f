//! The `sylva` command line: render a scene to PNG/EXR, or print its statistics.

use anyhow::{Result, bail};
use clap::{Args, Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use sylva::engine::discontinuity::{DiscontinuityFilter, FilteredImage};
use sylva::engine::film::{ImageKind, Tile};
use sylva::engine::tlas::TopLevel;
use sylva::prelude::*;
use sylva::scenes::SceneBuild;
use sylva::systems::shown_film;
use tracing_subscriber::prelude::*;

mod cli {
    pub mod converge;
}

/// Sylva: a ray tracer for dense plant ecosystems.
///
/// Examples:
///   sylva render --out meadow.png
///   sylva render --width 1280 --height 720 --spp 16 --out meadow.exr
///   sylva render --scene forest --out forest.png
///   sylva render --scene my_ecosystem.toml --out mine.png
///   sylva render --gltf model.glb --camera 0 --out model.png
///   sylva info --scene paper
#[derive(Parser, Debug)]
#[command(name = "sylva", version, verbatim_doc_comment)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Render a scene to an image (.png tone-mapped sRGB, or .exr linear radiance).
    Render(Box<RenderArgs>),
    /// Print a scene's statistics: species, triangles, instances, memory, build times.
    Info(SceneArgs),
    /// Measure error against wall time: render a converged reference (cached in the
    /// output directory), then run each sampling setting progressively and record RMSE
    /// and relMSE after every frame; writes error_vs_time.csv and error_vs_time.png and
    /// prints the time to reach relMSE 1e-2 and 1e-3 and the convergence slope.
    Converge(Box<ConvergeArgs>),
    /// Print the error of linear images (.exr or .hdr) against a reference: RMSE and
    /// relMSE (mean of (I−R)²/(R²+0.01) over pixels and channels).
    Compare(CompareArgs),
}

#[derive(Args, Debug)]
struct ConvergeArgs {
    #[command(flatten)]
    scene: SceneArgs,
    /// Image width in pixels.
    #[arg(long, default_value_t = 320, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=16384))]
    width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 240, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=16384))]
    height: u32,
    /// Render only the central FRACTION of the view (a crop, by narrowing the field of view).
    #[arg(long, default_value_t = 1.0, value_name = "FRACTION", allow_negative_numbers = true, value_parser = parse_fraction)]
    crop: f32,
    /// Light with a latitude-longitude HDR map instead of the scene's sun and sky.
    #[arg(long, value_name = "FILE")]
    env: Option<PathBuf>,
    /// Virtual lights the map is cut into.
    #[arg(long, default_value_t = 1024, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=65536))]
    lights: u32,
    /// Wall time each setting may refine for (e.g. 10s, 2m).
    #[arg(long, default_value = "10s", allow_hyphen_values = true, value_parser = parse_duration)]
    budget: Duration,
    /// Most frames per setting.
    #[arg(long, default_value_t = 100_000, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..))]
    max_frames: u32,
    /// Frames of the reference: still preset (4 camera and 4 light samples), exact
    /// transparency, a sampler seed of its own.
    #[arg(long, default_value_t = 64, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..))]
    reference_frames: u32,
    /// Settings to run, comma-separated [default: interactive, interactive-unfiltered,
    /// interactive-exact, interactive-exact-random, still, interactive-1-thread].
    #[arg(long, value_delimiter = ',', value_name = "NAMES")]
    configs: Vec<String>,
    /// Output directory (created if missing; holds the cached reference).
    #[arg(long, short)]
    out: PathBuf,
    /// No progress output.
    #[arg(long, short)]
    quiet: bool,
}

/// Parses a fraction in (0, 1].
fn parse_fraction(text: &str) -> Result<f32, String> {
    match text.parse::<f32>() {
        Ok(f) if f > 0.0 && f <= 1.0 => Ok(f),
        _ => Err(format!("'{text}' must be a number in (0, 1]")),
    }
}

#[derive(Args, Debug)]
struct CompareArgs {
    /// The reference image.
    #[arg(long, short, value_name = "FILE")]
    reference: PathBuf,
    /// Images to compare with it.
    #[arg(required = true, value_name = "IMAGE")]
    images: Vec<PathBuf>,
}

#[derive(Args, Debug)]
struct SceneArgs {
    /// Built-in scene (meadow, forest, paper) or a TOML scene file (*.toml).
    #[arg(long, default_value = "meadow")]
    scene: String,
    /// Render or describe a glTF/GLB file instead of a scene.
    #[arg(long, conflicts_with = "scene", value_name = "FILE")]
    gltf: Option<PathBuf>,
    /// With --gltf: the camera to look through, by name or index (default: the file's
    /// first perspective camera, or a view framing the model).
    #[arg(long, requires = "gltf", value_name = "NAME|INDEX")]
    camera: Option<String>,
    /// Seed of the scene's generation and of the sampler: same seed, same image.
    #[arg(long, default_value_t = 0, allow_negative_numbers = true)]
    seed: u64,
    /// Worker threads for building and rendering (0 = one per core). The image does not
    /// depend on it.
    #[arg(long, default_value_t = 0, allow_negative_numbers = true, value_parser = clap::value_parser!(u16).range(0..=1024))]
    threads: u16,
    /// Leaf translucency: light from behind passes through thin leaves (the generated
    /// grass and broadleaves, glTF's KHR_materials_diffuse_transmission). Off makes them
    /// opaque with the same reflected light, and saves the shadow rays it costs.
    #[arg(long, value_enum, value_name = "on|off", default_value = "on")]
    translucency: Switch,
}

/// Quality presets of `--preset`.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
enum Preset {
    /// 1 camera sample and 1 light sample per hit, adaptive transparency and the
    /// discontinuity filter on: fast frames to refine progressively.
    Interactive,
    /// 4 camera samples and 4 light samples per hit, exact transparency.
    Still,
}

/// `on` or `off`.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
enum Switch {
    /// Enabled.
    On,
    /// Disabled.
    Off,
}

/// Parses `NEAR,FAR,DEPTH_NEAR,DEPTH_FAR[,WEIGHT]` into a checked transparency curve.
fn parse_transparency_curve(text: &str) -> Result<TransparencyCurve, String> {
    let parts: Vec<&str> = text.split(',').map(str::trim).collect();
    if !(4..=5).contains(&parts.len()) {
        return Err(format!(
            "'{text}': expected NEAR,FAR,DEPTH_NEAR,DEPTH_FAR[,WEIGHT], e.g. 5,40,4,1,0.75"
        ));
    }
    let number = |i: usize| -> Result<f32, String> {
        parts[i]
            .parse::<f32>()
            .map_err(|_| format!("'{}' is not a number", parts[i]))
    };
    let depth = |i: usize| -> Result<u32, String> {
        parts[i]
            .parse::<u32>()
            .map_err(|_| format!("'{}' is not a whole number of holes", parts[i]))
    };
    let curve = TransparencyCurve {
        near: number(0)?,
        far: number(1)?,
        depth_near: depth(2)?,
        depth_far: depth(3)?,
        weight: if parts.len() == 5 {
            number(4)?
        } else {
            TransparencyCurve::default().weight
        },
    };
    curve.validate()?;
    Ok(curve)
}

#[derive(Args, Debug)]
struct RenderArgs {
    #[command(flatten)]
    scene: SceneArgs,
    /// Image width in pixels [default: height × 4/3 (640 at the default height), or × the
    /// glTF camera's aspect ratio].
    #[arg(long, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=16384))]
    width: Option<u32>,
    /// Image height in pixels.
    #[arg(long, default_value_t = 480, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=16384))]
    height: u32,
    /// Quality preset: interactive (1 camera sample, 1 light sample per hit, adaptive
    /// transparency, discontinuity filter) or still (4 and 4, exact, unfiltered). --spp,
    /// --light-samples, --adaptive-transparency and --filter override it.
    #[arg(long, value_enum)]
    preset: Option<Preset>,
    /// Treat alpha holes beyond a distance-dependent allowance as opaque (shaded with the
    /// leaf texture's mean colour × 0.75) [default: on with --preset interactive, else off].
    #[arg(long, value_enum, value_name = "on|off")]
    adaptive_transparency: Option<Switch>,
    /// The allowance: NEAR,FAR,DEPTH_NEAR,DEPTH_FAR[,WEIGHT] — up to NEAR metres a ray
    /// passes DEPTH_NEAR holes, beyond FAR only DEPTH_FAR, linear in between.
    #[arg(long, value_name = "CURVE", default_value = "5,40,4,1,0.75", allow_hyphen_values = true, value_parser = parse_transparency_curve)]
    transparency_curve: TransparencyCurve,
    /// Interleaved sampling of the virtual lights: pixels of an N×N tile draw from
    /// different light subsets, rotating every sample (1 = off, independent picks).
    #[arg(long, value_name = "N", default_value_t = 4, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=64))]
    interleave: u32,
    /// The discontinuity filter on the written image: each pixel averages the light
    /// (not the texture) of its N×N interleaving window over neighbours on the same
    /// surface; the accumulated film and checkpoints stay unfiltered [default: on with
    /// --preset interactive, else off].
    #[arg(long, value_enum, value_name = "on|off")]
    filter: Option<Switch>,
    /// Light subsets for --interleave [default: N²].
    #[arg(long, value_name = "S", allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=65536))]
    subsets: Option<u32>,
    /// Camera samples per pixel per frame [default: 4, or the preset's].
    #[arg(long, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=65536))]
    spp: Option<u32>,
    /// Diffuse bounces of indirect light after the first hit: continuation rays with
    /// direct light at every surface they reach (0 = direct light only).
    #[arg(long, default_value_t = 0, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(0..=16))]
    bounces: u32,
    /// Sky shadow rays per camera hit, or virtual lights sampled per hit with --env
    /// (0 = sun only) [default: 2, or the preset's].
    #[arg(long, visible_alias = "light-samples", allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(0..=1024))]
    sky_samples: Option<u32>,
    /// Progressive frames the image should hold (each with new random numbers) [default: 1].
    /// With --resume, the total including the checkpoint's frames.
    #[arg(long, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=10_000_000))]
    frames: Option<u32>,
    /// Refine until this much time is spent (e.g. 5s, 500ms, 2m); --frames then caps it.
    #[arg(long, allow_hyphen_values = true, value_parser = parse_duration)]
    time: Option<Duration>,
    /// Also write the image every K frames, as OUT.fNNNNNN.EXT.
    #[arg(long, value_name = "K", allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..))]
    snapshot_every: Option<u32>,
    /// Save the exact accumulation state at the end, to resume later with --resume.
    #[arg(long, value_name = "FILE")]
    checkpoint: Option<PathBuf>,
    /// Continue a checkpoint (same scene and settings): the result is bit for bit what
    /// one uninterrupted run would give.
    #[arg(long, value_name = "FILE")]
    resume: Option<PathBuf>,
    /// Light the scene with a latitude-longitude HDR environment map (.hdr or .exr)
    /// instead of the scene's sun and sky.
    #[arg(long, value_name = "FILE")]
    env: Option<PathBuf>,
    /// Virtual directional lights the environment map is discretised into (median cut).
    #[arg(long, default_value_t = 1024, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=65536))]
    lights: u32,
    /// Exposure in stops, applied before tone mapping (PNG only).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    exposure: f32,
    /// Output image: .png or .exr.
    #[arg(long, short, default_value = "sylva.png")]
    out: PathBuf,
    /// Write a Chrome trace (open in chrome://tracing or Perfetto) of every stage and tile.
    #[arg(long)]
    trace: Option<PathBuf>,
    /// No progress bar or summary.
    #[arg(long, short)]
    quiet: bool,
}

fn main() {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Render(args) => render(*args),
        Command::Info(args) => info(args),
        Command::Compare(args) => compare(args),
        Command::Converge(args) => cli::converge::run(*args),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

/// Logs warnings (or `RUST_LOG`) to stderr; with `trace`, every span to a Chrome trace.
fn init_tracing(trace: Option<&Path>) -> Option<tracing_chrome::FlushGuard> {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    let fmt = tracing_subscriber::fmt::layer()
        .with_writer(std::io::stderr)
        .with_filter(filter);
    match trace {
        Some(path) => {
            let (chrome, guard) = tracing_chrome::ChromeLayerBuilder::new()
                .file(path)
                .include_args(true)
                .build();
            tracing_subscriber::registry().with(fmt).with(chrome).init();
            Some(guard)
        }
        None => {
            tracing_subscriber::registry().with(fmt).init();
            None
        }
    }
}

fn check_output_path(path: &Path) -> Result<()> {
    ImageKind::from_path(path)?;
    let dir = path
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    if !dir.is_dir() {
        bail!(
            "{}: the directory {} does not exist",
            path.display(),
            dir.display()
        );
    }
    Ok(())
}

/// A built scene and, for glTF files, the chosen camera's aspect ratio.
fn build(world: &mut World, args: &SceneArgs) -> Result<(SceneBuild, Option<f32>)> {
    init_render_world(world, args.threads as usize)
        .map_err(|e| anyhow::anyhow!("could not start the worker threads: {e}"))?;
    world.insert_resource(RenderSeed(args.seed));
    let pool = world.resource::<RenderPool>().clone();
    let (mut scene, aspect) = match &args.gltf {
        Some(path) => import_gltf(&pool, path, args.camera.as_deref())?,
        None => (pool.install(|| build_scene(&args.scene, args.seed))?, None),
    };
    if args.translucency == Switch::Off {
        scene.without_translucency();
    }
    Ok((scene, aspect))
}

#[cfg(feature = "gltf")]
fn import_gltf(
    pool: &RenderPool,
    path: &Path,
    camera: Option<&str>,
) -> Result<(SceneBuild, Option<f32>)> {
    use sylva::scenes::gltf::{CameraChoice, import};
    let imported = import(path)?;
    let choice = camera.map_or(CameraChoice::First, CameraChoice::parse);
    let aspect = imported.camera(&choice)?.and_then(|c| c.aspect_ratio);
    let scene = pool.install(|| imported.into_scene(&choice))?;
    Ok((scene, aspect))
}

#[cfg(not(feature = "gltf"))]
fn import_gltf(
    _pool: &RenderPool,
    path: &Path,
    _camera: Option<&str>,
) -> Result<(SceneBuild, Option<f32>)> {
    bail!(
        "{}: reading glTF needs the 'gltf' cargo feature, which this build left out",
        path.display()
    )
}

/// Builds the scene and, with `env`, the environment light that replaces its sun and sky.
fn build_lit(
    world: &mut World,
    args: &SceneArgs,
    env: Option<&Path>,
    lights: u32,
) -> Result<(SceneBuild, Option<f32>, Option<EnvironmentLight>)> {
    let environment = match env {
        Some(path) => Some(EnvironmentLight::new(
            load_linear_image(path)?,
            lights as usize,
        )),
        None => None,
    };
    let (mut scene, aspect) = build(world, args)?;
    if environment.is_some() {
        // The map carries the sun and the sky: keeping the scene's would count them twice.
        scene.sun = None;
        scene.sky = None;
        scene.environment = None;
    }
    Ok((scene, aspect, environment))
}

/// Name of what is being rendered, for messages.
fn scene_label(args: &SceneArgs) -> String {
    match &args.gltf {
        Some(path) => path.display().to_string(),
        None => args.scene.clone(),
    }
}

/// Peak resident memory of this process (Linux `VmHWM`), when known.
fn peak_memory_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// `5s`, `500ms`, `2m`, `1.5s` → a duration.
fn parse_duration(text: &str) -> Result<Duration, String> {
    let text = text.trim();
    let (number, unit) = text
        .find(|c: char| c.is_ascii_alphabetic())
        .map_or((text, "s"), |i| text.split_at(i));
    let value: f64 = number
        .trim()
        .parse()
        .map_err(|_| format!("'{text}' is not a duration (examples: 5s, 500ms, 2m)"))?;
    let seconds = match unit {
        "ms" => value / 1e3,
        "s" => value,
        "m" | "min" => value * 60.0,
        "h" => value * 3600.0,
        _ => {
            return Err(format!(
                "unknown unit '{unit}' in '{text}' (use ms, s, m or h)"
            ));
        }
    };
    if !(seconds.is_finite() && seconds > 0.0 && seconds < 1e7) {
        return Err(format!("'{text}' must be a positive duration"));
    }
    Ok(Duration::from_secs_f64(seconds))
}

/// Set by the first Ctrl-C (SIGINT/SIGTERM): the render loop then stops after the frame
/// in progress and writes what has accumulated. A second Ctrl-C exits at once (130).
fn interrupt_flag() -> Arc<AtomicBool> {
    let flag = Arc::new(AtomicBool::new(false));
    let handler_flag = flag.clone();
    let installed = ctrlc::set_handler(move || {
        if handler_flag.swap(true, Ordering::SeqCst) {
            std::process::exit(130);
        }
    });
    if let Err(e) = installed {
        eprintln!("warning: Ctrl-C will not save the image: {e}");
    }
    flag
}

/// What an output image records about how it was made (PNG tEXt / EXR attributes).
fn image_metadata(
    args: &RenderArgs,
    film: &Film,
    width: u32,
    quality: &Quality,
) -> Vec<(String, String)> {
    let (spp, interleave) = (quality.samples_per_pixel, quality.interleave);
    let curve = quality.transparency.map_or("off".to_string(), |c| {
        format!(
            "{},{},{},{},{}",
            c.near, c.far, c.depth_near, c.depth_far, c.weight
        )
    });
    [
        ("Software", format!("sylva {}", env!("CARGO_PKG_VERSION"))),
        ("sylva.scene", scene_label(&args.scene)),
        ("sylva.seed", args.scene.seed.to_string()),
        ("sylva.size", format!("{width}x{}", args.height)),
        ("sylva.frames", film.frames().to_string()),
        (
            "sylva.spp",
            (u64::from(film.frames()) * u64::from(spp)).to_string(),
        ),
        ("sylva.spp_per_frame", spp.to_string()),
        ("sylva.light_samples", quality.light_samples.to_string()),
        ("sylva.adaptive_transparency", curve),
        (
            "sylva.filter",
            quality.filter.map_or("off".to_string(), |f| {
                format!("discontinuity {0}x{0}", f.window)
            }),
        ),
        (
            "sylva.interleave",
            format!(
                "{} ({} subsets)",
                interleave.pattern,
                interleave.subset_count()
            ),
        ),
        (
            "sylva.environment",
            args.env
                .as_ref()
                .map_or("scene sun and sky".to_string(), |p| {
                    format!("{} ({} lights)", p.display(), args.lights)
                }),
        ),
        ("sylva.exposure", args.exposure.to_string()),
        (
            "sylva.rejected_samples",
            film.rejected_samples().to_string(),
        ),
        ("sylva.fireflies", film.fireflies().to_string()),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), v))
    .collect()
}

/// The quality `render` asks for: the preset's, with the flags that override it.
fn quality(args: &RenderArgs) -> Quality {
    let preset = match args.preset {
        Some(Preset::Interactive) => Quality::interactive(),
        Some(Preset::Still) => Quality::still(),
        None => Quality::default(),
    };
    let on =
        |switch: Option<Switch>, preset_on: bool| switch.map_or(preset_on, |s| s == Switch::On);
    Quality {
        samples_per_pixel: args.spp.unwrap_or(preset.samples_per_pixel),
        light_samples: args.sky_samples.unwrap_or(preset.light_samples),
        bounces: args.bounces,
        transparency: on(args.adaptive_transparency, preset.transparency.is_some())
            .then_some(args.transparency_curve),
        interleave: LightInterleave {
            pattern: args.interleave,
            subsets: args.subsets.unwrap_or(0),
        },
        filter: on(args.filter, preset.filter.is_some())
            .then(|| DiscontinuityFilter::for_pattern(args.interleave)),
    }
}

/// Adds what a scene's pixels depend on (which scene, camera, seed and translucency)
/// to `hash`.
fn hash_scene(hash: &mut Fingerprint, args: &SceneArgs) {
    hash.text(&scene_label(args))
        .text(args.camera.as_deref().unwrap_or(""))
        .u64(args.seed)
        .u32(u32::from(args.translucency == Switch::On));
}

/// Identifies everything a checkpoint's pixels depend on: the scene, the image size,
/// the environment and the quality (not the exposure or the display filter, which only
/// change the written image).
fn checkpoint_fingerprint(args: &RenderArgs, width: u32, quality: &Quality) -> u64 {
    let mut hash = Fingerprint::new("sylva checkpoint v2");
    hash_scene(&mut hash, &args.scene);
    hash.u32(width)
        .u32(args.height)
        .text(
            &args
                .env
                .as_ref()
                .map_or(String::new(), |p| p.display().to_string()),
        )
        .u32(args.lights)
        .u64(quality.fingerprint());
    hash.finish()
}

/// `out.png` → `out.f000016.png`.
fn snapshot_path(out: &Path, frames: u32) -> PathBuf {
    let stem = out
        .file_stem()
        .map_or("sylva".into(), |s| s.to_string_lossy().into_owned());
    let extension = out
        .extension()
        .map_or("png".into(), |e| e.to_string_lossy().into_owned());
    out.with_file_name(format!("{stem}.f{frames:06}.{extension}"))
}

fn render(args: RenderArgs) -> Result<()> {
    check_output_path(&args.out)?;
    if !args.exposure.is_finite() {
        bail!(
            "--exposure must be a finite number of stops, got {}",
            args.exposure
        );
    }
    let _trace_guard = init_tracing(args.trace.as_deref());
    let mut world = World::new();
    let (mut scene, aspect, environment) =
        build_lit(&mut world, &args.scene, args.env.as_deref(), args.lights)?;
    let aspect = aspect
        .filter(|a| a.is_finite() && *a > 0.0)
        .unwrap_or(4.0 / 3.0);
    let width = args
        .width
        .unwrap_or_else(|| ((args.height as f32 * aspect).round() as u32).clamp(1, 16384));
    let quality = quality(&args);
    scene.camera.width = width;
    scene.camera.height = args.height;
    scene.camera.exposure = args.exposure;
    let stats = scene.stats();
    let (generate_time, blas_time) = (scene.generate_time, scene.blas_time);
    let spawned = spawn(&mut world, scene);
    if let Some(environment) = environment {
        world.spawn(environment);
    }
    quality.apply(&mut world, spawned.camera);
    let spp = quality.samples_per_pixel;
    let fingerprint = checkpoint_fingerprint(&args, width, &quality);
    if let Some(path) = &args.resume {
        let film = Film::read_checkpoint(path, fingerprint)?;
        world.entity_mut(spawned.camera).insert(film);
    }
    let resumed_frames = world.get::<Film>(spawned.camera).map_or(0, Film::frames);
    let target_frames = args.frames.unwrap_or(1);
    if args.time.is_none() && target_frames <= resumed_frames {
        bail!("the checkpoint already holds {resumed_frames} frames; ask for more with --frames");
    }

    let tiles = Tile::grid(
        width,
        args.height,
        sylva::engine::RenderParams::default().tile_size,
    )
    .len() as u64;
    let bar = if args.quiet {
        ProgressBar::hidden()
    } else if args.time.is_some() {
        ProgressBar::new_spinner()
    } else {
        ProgressBar::new(tiles * (target_frames - resumed_frames) as u64)
    };
    bar.set_style(
        ProgressStyle::with_template(if args.time.is_some() {
            "{spinner} refining: {msg}, {elapsed_precise}"
        } else {
            "{spinner} rendering [{bar:40}] {pos}/{len} tiles, {elapsed_precise} (eta {eta})"
        })
        .expect("the template is valid")
        .progress_chars("=> "),
    );
    let tick = bar.clone();
    world.insert_resource(TileProgress(Some(Arc::new(move |_| tick.inc(1)))));

    let start = Instant::now();
    let mut schedule = frame_schedule();
    let interrupted = interrupt_flag();
    let stop = StopAt {
        frames: if args.time.is_some() {
            args.frames
        } else {
            Some(target_frames)
        },
        budget: args.time,
        interrupt: Some(interrupted.clone()),
    };
    let mut snapshot_failure = None;
    let (stopped, _) = refine(
        &mut world,
        &mut schedule,
        spawned.camera,
        &stop,
        |world, progress| {
            let frames = progress.frames;
            if args.time.is_some() {
                bar.set_message(format!(
                    "{frames} frames, {} spp",
                    u64::from(frames) * u64::from(spp)
                ));
            }
            if let Some(every) = args.snapshot_every
                && frames.is_multiple_of(every)
            {
                let film = world
                    .get::<Film>(spawned.camera)
                    .expect("cameras have films");
                let metadata = image_metadata(&args, film, width, &quality);
                let written = shown_film(film, world.get::<FilteredImage>(spawned.camera))
                    .write_with(&snapshot_path(&args.out, frames), args.exposure, &metadata);
                if let Err(error) = written {
                    snapshot_failure = Some(error);
                    return Flow::Stop;
                }
            }
            Flow::Continue
        },
    );
    if let Some(error) = snapshot_failure {
        return Err(error.into());
    }
    if stopped == Stopped::Interrupted {
        bar.finish_and_clear();
        let frames = world.get::<Film>(spawned.camera).map_or(0, Film::frames);
        eprintln!(
            "interrupted: writing the {frames} frames accumulated so far (Ctrl-C again to quit without writing)"
        );
    }
    let wall = start.elapsed();
    bar.finish_and_clear();

    let film = world
        .get::<Film>(spawned.camera)
        .ok_or_else(|| anyhow::anyhow!("the camera has no film"))?;
    let metadata = image_metadata(&args, film, width, &quality);
    shown_film(film, world.get::<FilteredImage>(spawned.camera)).write_with(
        &args.out,
        args.exposure,
        &metadata,
    )?;
    if let Some(path) = &args.checkpoint {
        film.write_checkpoint(path, fingerprint)?;
    }
    if interrupted.load(Ordering::SeqCst) {
        eprintln!("wrote {}", args.out.display());
        std::process::exit(130);
    }
    let render_stats = world.resource::<RenderStats>();
    let tlas = world.resource::<TopLevelState>();
    let render_s = render_stats.total_render.as_secs_f64();
    let rays = render_stats.total.rays();
    if film.rejected_samples() > 0 {
        eprintln!(
            "warning: {} NaN/Inf samples were dropped",
            film.rejected_samples()
        );
    }
    if !args.quiet {
        let rendered = render_stats.frames;
        println!(
            "{}: {}x{}, {} frames at {} spp ({} spp in all) -> {}\n  {} instances, {} instanced triangles ({} unique), BLAS build {:.2} s, TLAS build {:.1} ms, scene generation {:.2} s\n  render {:.2} s ({:.3} s per frame), {:.2} M rays/s ({} camera + {} shadow rays), {:.2} transparency segments per camera ray ({:.2} holes tested), {} holes made opaque, {}, total {:.2} s\n  per ray: {:.1} nodes visited, {:.1} primitive tests (instances and triangles), {:.2} alpha tests ({:.2} sampled the texture)",
            scene_label(&args.scene),
            width,
            args.height,
            film.frames(),
            spp,
            film.frames() as u64 * spp as u64,
            args.out.display(),
            group(stats.instances as u64),
            group(stats.instanced_triangles),
            group(stats.unique_triangles as u64),
            blas_time.as_secs_f64(),
            tlas.last_build.as_secs_f64() * 1e3,
            generate_time.as_secs_f64(),
            render_s,
            render_s / rendered.max(1) as f64,
            rays as f64 / render_s.max(1e-9) / 1e6,
            group(render_stats.total.closest_rays),
            group(render_stats.total.any_rays),
            render_stats.total.segments_per_closest_ray(),
            render_stats.total.hole_tests_per_closest_ray(),
            group(render_stats.total.opaque_holes),
            fireflies_summary(film),
            wall.as_secs_f64(),
            render_stats.total.nodes_visited as f64 / rays.max(1) as f64,
            render_stats.total.primitive_tests as f64 / rays.max(1) as f64,
            render_stats.total.filter_tests as f64 / rays.max(1) as f64,
            render_stats.total.texture_alpha_tests as f64 / rays.max(1) as f64,
        );
    }
    Ok(())
}

/// The firefly count for the summary line, or why there is none yet.
fn fireflies_summary(film: &Film) -> String {
    use sylva::engine::film::{FIREFLY_MIN_FRAMES, FIREFLY_RATIO};
    if film.frames() <= FIREFLY_MIN_FRAMES {
        format!("fireflies judged from frame {}", FIREFLY_MIN_FRAMES + 1)
    } else {
        format!(
            "{} fireflies (pixel-frames over {FIREFLY_RATIO}x their pixel's mean)",
            group(film.fireflies())
        )
    }
}

/// A linear image (.hdr or .exr: an environment map, or a render to compare), with
/// NaN, infinite and negative values read as zero and counted in a warning.
fn load_linear_image(path: &Path) -> Result<EnvironmentMap> {
    let loaded = sylva::scenes::environment::load_environment(path)?;
    if loaded.repaired_texels > 0 {
        eprintln!(
            "warning: {}: {} NaN, infinite or negative texels set to zero",
            path.display(),
            loaded.repaired_texels
        );
    }
    Ok(loaded.map)
}

/// The pixels of a linear image, row-major.
fn pixels(map: &EnvironmentMap) -> Vec<Vec3> {
    (0..map.height())
        .flat_map(|y| (0..map.width()).map(move |x| map.texel(x, y)))
        .collect()
}

fn compare(args: CompareArgs) -> Result<()> {
    let reference = load_linear_image(&args.reference)?;
    let (width, height) = (reference.width(), reference.height());
    let reference = pixels(&reference);
    println!("{:<40} {:>12} {:>12}", "image", "rmse", "relmse");
    for path in &args.images {
        let image = load_linear_image(path)?;
        let (w, h) = (image.width(), image.height());
        let image = pixels(&image);
        if (w, h) != (width, height) {
            bail!(
                "{}: the image is {w}x{h} but the reference {} is {width}x{height}",
                path.display(),
                args.reference.display()
            );
        }
        let error = sylva::engine::metrics::image_error(&reference, &image)
            .expect("sizes were checked and are non-zero");
        println!(
            "{:<40} {:>12.6} {:>12.6}",
            path.display(),
            error.rmse,
            error.relmse
        );
    }
    Ok(())
}

fn info(args: SceneArgs) -> Result<()> {
    let _guard = init_tracing(None);
    let command_start = Instant::now();
    let mut world = World::new();
    let (scene, _) = build(&mut world, &args)?;
    let stats = scene.stats();
    let pool = world.resource::<RenderPool>().clone();
    let descs = scene.instance_descs();
    let start = Instant::now();
    let tlas = pool.install(|| {
        TopLevel::build(
            &scene.library,
            &descs,
            sylva::systems::BuildSettings::default().top_level,
        )
    });
    let tlas_time = start.elapsed();
    let start = Instant::now();
    let shaders = sylva::engine::ShaderTable::new(scene.shaders.clone());
    let opacity = pool.install(|| sylva::engine::OpacityMaps::build(&scene.library, &shaders));
    let opacity_time = start.elapsed();
    let total_time = command_start.elapsed();
    println!("scene            {} (seed {})", scene.name, args.seed);
    println!("species          {}", stats.species);
    for s in &scene.species {
        let count = scene
            .plants
            .iter()
            .filter(|p| p.geometry == s.geometry)
            .count();
        let tris = scene
            .library
            .get(s.geometry)
            .map_or(0, |g| g.mesh.triangle_count());
        println!(
            "  {:<22} {:>9} triangles  {:>9} instances",
            s.name,
            group(tris as u64),
            group(count as u64)
        );
    }
    if let Some(t) = scene.terrain.and_then(|t| scene.library.get(t)) {
        println!(
            "terrain          {} triangles",
            group(t.mesh.triangle_count() as u64)
        );
    }
    println!("layers           {}", scene.layers.len());
    for (i, name) in scene.layers.iter().enumerate() {
        let count = scene.plants.iter().filter(|p| p.layer == i as u32).count();
        println!("  {name:<22} {:>9} plants", group(count as u64));
    }
    println!("plants           {}", group(scene.plants.len() as u64));
    println!("unique triangles {}", group(stats.unique_triangles as u64));
    println!(
        "instances        {} (plants{})",
        group(stats.instances as u64),
        if scene.terrain.is_some() {
            " + terrain"
        } else {
            ""
        }
    );
    println!("instanced tris   {}", group(stats.instanced_triangles));
    println!(
        "memory           {:.1} MB (geometry + BLAS {:.1} MB, TLAS {:.1} MB, opacity maps {:.1} MB)",
        (scene.library.memory_bytes() + tlas.memory_bytes() + opacity.memory_bytes()) as f64 / 1e6,
        scene.library.memory_bytes() as f64 / 1e6,
        tlas.memory_bytes() as f64 / 1e6,
        opacity.memory_bytes() as f64 / 1e6
    );
    println!(
        "build times      generation {:.2} s, BLAS {:.2} s, TLAS {:.1} ms, opacity maps {:.1} ms ({} maps) ({} threads)",
        scene.generate_time.as_secs_f64(),
        scene.blas_time.as_secs_f64(),
        tlas_time.as_secs_f64() * 1e3,
        opacity_time.as_secs_f64() * 1e3,
        group(opacity.map_count() as u64),
        pool.threads()
    );
    println!(
        "total            {:.2} s to generate and build everything, peak memory {}",
        total_time.as_secs_f64(),
        peak_memory_bytes().map_or("unknown".into(), |b| format!("{:.0} MB", b as f64 / 1e6))
    );
    Ok(())
}

/// `1234567` → `1,234,567`.
fn group(n: u64) -> String {
    let s = n.to_string();
    let mut out = String::new();
    for (i, c) in s.chars().enumerate() {
        if i > 0 && (s.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}
