//! What the subcommands share: the scene arguments and how a scene is built and lit,
//! tracing, output-path checks, durations, Ctrl-C, number formatting.

pub mod animate;
pub mod cluster;
pub mod compare;
pub mod converge;
pub mod info;
pub mod plot;
pub mod profile;
pub mod render;
#[cfg(feature = "view")]
pub mod view;

use anyhow::{Result, bail};
use clap::Args;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;
use sylva::engine::film::ImageKind;
use sylva::engine::tlas::TopLevel;
use sylva::prelude::*;
use sylva::scenes::SceneBuild;
use tracing_subscriber::prelude::*;

/// How a scene is lit: its own sun and sky, or an HDR map cut into virtual lights (the
/// flags of every subcommand that renders).
#[derive(clap::Args, Debug, Clone)]
pub(crate) struct LightingArgs {
    /// Light the scene with a latitude-longitude HDR environment map (.hdr or .exr)
    /// instead of the scene's sun and sky.
    #[arg(long, value_name = "FILE")]
    pub(crate) env: Option<PathBuf>,
    /// Virtual directional lights the environment map is discretised into (median cut).
    #[arg(long, default_value_t = 1024, allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(1..=65536))]
    pub(crate) lights: u32,
}

#[derive(Args, Clone, Debug)]
pub(crate) struct SceneArgs {
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

impl SceneArgs {
    /// These settings with the scene at `path` instead: a glTF file (`.gltf`, `.glb`),
    /// else a scene file or preset name.
    #[cfg(feature = "view")]
    fn opening(&self, path: &Path) -> Self {
        let gltf = path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| e.eq_ignore_ascii_case("gltf") || e.eq_ignore_ascii_case("glb"));
        Self {
            scene: if gltf {
                self.scene.clone()
            } else {
                path.to_string_lossy().into_owned()
            },
            gltf: gltf.then(|| path.to_owned()),
            camera: None,
            ..self.clone()
        }
    }
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

impl Preset {
    /// The library's quality of this preset.
    fn quality(self) -> Quality {
        match self {
            Preset::Interactive => Quality::interactive(),
            Preset::Still => Quality::still(),
        }
    }
}

/// Refuses an exposure that is not a finite number of stops.
fn check_exposure(exposure: f32) -> Result<()> {
    if !exposure.is_finite() {
        bail!("--exposure must be a finite number of stops, got {exposure}");
    }
    Ok(())
}

/// `on` or `off`.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
enum Switch {
    /// Enabled.
    On,
    /// Disabled.
    Off,
}

/// Logs warnings (or `RUST_LOG`) to stderr; with `trace`, every span to a Chrome trace.
fn init_tracing(trace: Option<&Path>) -> Option<tracing_chrome::FlushGuard> {
    init_tracing_filtered(trace, "warn")
}

/// [`init_tracing`] with another default filter (without `RUST_LOG`).
fn init_tracing_filtered(
    trace: Option<&Path>,
    default_filter: &str,
) -> Option<tracing_chrome::FlushGuard> {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default_filter));
    let fmt = tracing_subscriber::fmt::layer()
        .with_writer(std::io::stderr)
        .with_filter(filter);
    let registry = tracing_subscriber::registry().with(fmt);
    // Built with the `tracy` feature, every span also goes to a Tracy profiler that
    // connects while Sylva runs.
    #[cfg(feature = "tracy")]
    let registry = registry.with(tracing_tracy::TracyLayer::default());
    match trace {
        Some(path) => {
            let (chrome, guard) = tracing_chrome::ChromeLayerBuilder::new()
                .file(path)
                .include_args(true)
                .build();
            registry.with(chrome).init();
            Some(guard)
        }
        None => {
            registry.init();
            None
        }
    }
}

fn check_output_path(path: &Path) -> Result<()> {
    ImageKind::from_path(path)?;
    check_parent_dir(path)
}

/// Refuses a file to write whose directory does not exist, naming both.
fn check_parent_dir(path: &Path) -> Result<()> {
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

/// How a scene's camera is sized and exposed ([`size_camera`]).
struct Framing {
    /// Width (or `None`: from the height and the glTF camera's aspect) and height.
    size: (Option<u32>, u32),
    /// The widest image allowed.
    max_width: u32,
    /// Exposure in stops.
    exposure: f32,
}

/// [`build_lit`], then the camera sized and exposed as `framing` says; returns the
/// scene, its width and the environment light.
fn build_framed(
    world: &mut World,
    args: &SceneArgs,
    (env, lights): (Option<&Path>, u32),
    framing: &Framing,
) -> Result<(SceneBuild, u32, Option<EnvironmentLight>)> {
    let (mut scene, aspect, environment) = build_lit(world, args, env, lights)?;
    let width = size_camera(
        &mut scene,
        aspect,
        framing.size,
        framing.max_width,
        framing.exposure,
    );
    Ok((scene, width, environment))
}

/// Sizes the scene's camera: `width` when given, else `height` × `aspect` (a glTF
/// camera's aspect ratio, 4:3 without a usable one) up to `max_width`; sets its exposure.
/// Returns the width.
fn size_camera(
    scene: &mut SceneBuild,
    aspect: Option<f32>,
    (width, height): (Option<u32>, u32),
    max_width: u32,
    exposure: f32,
) -> u32 {
    let aspect = aspect
        .filter(|a| a.is_finite() && *a > 0.0)
        .unwrap_or(4.0 / 3.0);
    let width =
        width.unwrap_or_else(|| ((height as f32 * aspect).round() as u32).clamp(1, max_width));
    scene.camera.width = width;
    scene.camera.height = height;
    scene.camera.exposure = exposure;
    width
}

/// Name of what is being rendered, for messages.
fn scene_label(args: &SceneArgs) -> String {
    match &args.gltf {
        Some(path) => path.display().to_string(),
        None => args.scene.clone(),
    }
}

/// Adds what a scene's pixels depend on to `hash`: which scene, camera, seed and
/// translucency, and the lighting (the environment map, if any, and its light count).
fn hash_scene(hash: &mut Fingerprint, args: &SceneArgs, env: Option<&Path>, lights: u32) {
    hash.text(&scene_label(args))
        .text(args.camera.as_deref().unwrap_or(""))
        .u64(args.seed)
        .u32(u32::from(args.translucency == Switch::On))
        .text(&env.map_or(String::new(), |p| p.display().to_string()))
        .u32(lights);
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
    watch_interrupts(Arc::new(AtomicBool::new(false)))
}

/// [`interrupt_flag`] on a given flag (a cluster's stop flag, on rank 0).
fn watch_interrupts(flag: Arc<AtomicBool>) -> Arc<AtomicBool> {
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
