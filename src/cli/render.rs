//! `sylva render`: a scene's frames refined progressively into a PNG or EXR, with
//! snapshots, checkpoints and the summary of what was traced.

use super::cluster::{ClusterArgs, Node};
use super::profile::CliProfile;
use super::*;
use indicatif::{ProgressBar, ProgressStyle};
use std::time::Instant;
use sylva::engine::discontinuity::{DiscontinuityFilter, FilteredImage};
use sylva::engine::film::Tile;
use sylva::scenes::SceneStats;
use sylva::systems::cluster::Cluster;
use sylva::systems::shown_film;

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
pub(crate) struct RenderArgs {
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
    /// Light samples per camera hit: shadow rays toward the sky, or toward virtual
    /// lights picked from the --env map (0 = sun only) [default: 2, or the preset's].
    #[arg(long, visible_alias = "sky-samples", allow_negative_numbers = true, value_parser = clap::value_parser!(u32).range(0..=1024))]
    light_samples: Option<u32>,
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
    /// Also write the image and the checkpoint (--checkpoint, or OUT.checkpoint) every
    /// DURATION while refining, so a crash loses at most that much work [default: 30s
    /// under mpirun, where a rank that dies ends the whole run; else off].
    #[arg(long, value_name = "DURATION", allow_hyphen_values = true, value_parser = parse_duration)]
    checkpoint_every: Option<Duration>,
    /// Continue a checkpoint (same scene and settings): the result is bit for bit what
    /// one uninterrupted run would give.
    #[arg(long, value_name = "FILE")]
    resume: Option<PathBuf>,
    #[command(flatten)]
    lighting: LightingArgs,
    /// Exposure in stops, applied before tone mapping (PNG only).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    exposure: f32,
    /// Output image: .png or .exr.
    #[arg(long, short, default_value = "sylva.png")]
    out: PathBuf,
    /// Write a Chrome trace (open in chrome://tracing or Perfetto) of every stage and tile.
    #[arg(long)]
    trace: Option<PathBuf>,
    /// Write per frame the time of every stage and system and the counters that explain
    /// it to FILE.csv (and the last frame's tile times to FILE.tiles.csv), and print a
    /// summary table; plot it with `sylva profile`.
    #[arg(long, value_name = "FILE.csv")]
    profile: Option<PathBuf>,
    /// No progress bar or summary.
    #[arg(long, short)]
    quiet: bool,
    #[command(flatten)]
    cluster: ClusterArgs,
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
            args.lighting
                .env
                .as_ref()
                .map_or("scene sun and sky".to_string(), |p| {
                    format!("{} ({} lights)", p.display(), args.lighting.lights)
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
    let preset = args.preset.map_or_else(Quality::default, Preset::quality);
    let on =
        |switch: Option<Switch>, preset_on: bool| switch.map_or(preset_on, |s| s == Switch::On);
    Quality {
        samples_per_pixel: args.spp.unwrap_or(preset.samples_per_pixel),
        light_samples: args.light_samples.unwrap_or(preset.light_samples),
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

/// Identifies everything a checkpoint's pixels depend on: the scene, the image size,
/// the environment and the quality (not the exposure or the display filter, which only
/// change the written image).
fn checkpoint_fingerprint(args: &RenderArgs, width: u32, quality: &Quality) -> u64 {
    let mut hash = Fingerprint::new("sylva checkpoint v2");
    hash_scene(
        &mut hash,
        &args.scene,
        args.lighting.env.as_deref(),
        args.lighting.lights,
    );
    hash.u32(width).u32(args.height).u64(quality.fingerprint());
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

/// What every rank builds before rendering: the world with its camera and film, and
/// what the summary and the checkpoint need.
struct Loaded {
    world: World,
    camera: Entity,
    width: u32,
    quality: Quality,
    built: Built,
    fingerprint: u64,
    resumed_frames: u32,
}

/// Builds the scene, sizes and sets up the camera, and loads the checkpoint to resume.
fn load(args: &RenderArgs) -> Result<Loaded> {
    let mut world = World::new();
    let (scene, width, environment) = build_framed(
        &mut world,
        &args.scene,
        (args.lighting.env.as_deref(), args.lighting.lights),
        &Framing {
            size: (args.width, args.height),
            max_width: 16384,
            exposure: args.exposure,
        },
    )?;
    let quality = quality(args);
    let built = Built {
        stats: scene.stats(),
        generate_time: scene.generate_time,
        blas_time: scene.blas_time,
    };
    let spawned = spawn(&mut world, scene);
    if let Some(environment) = environment {
        world.spawn(environment);
    }
    quality.apply(&mut world, spawned.camera);
    let fingerprint = checkpoint_fingerprint(args, width, &quality);
    if let Some(path) = &args.resume {
        let film = Film::read_checkpoint(path, fingerprint)?;
        world.entity_mut(spawned.camera).insert(film);
    }
    let resumed_frames = world.get::<Film>(spawned.camera).map_or(0, Film::frames);
    if args.time.is_none() && args.frames.unwrap_or(1) <= resumed_frames {
        bail!("the checkpoint already holds {resumed_frames} frames; ask for more with --frames");
    }
    Ok(Loaded {
        world,
        camera: spawned.camera,
        width,
        quality,
        built,
        fingerprint,
        resumed_frames,
    })
}

/// Runs `sylva render`: alone, or as one rank of an MPI run (rank 0 writes).
pub(crate) fn run(args: RenderArgs) -> Result<()> {
    check_output_path(&args.out)?;
    check_exposure(args.exposure)?;
    let mut node = Node::join(&args.cluster)?;
    let result = render(&args, &mut node);
    node.end(result)
}

/// `sylva render` on this node.
fn render(args: &RenderArgs, node: &mut Node) -> Result<()> {
    let _trace_guard = init_tracing(node.trace_path(args.trace.as_deref()).as_deref());
    let (loaded, cluster, interrupted) = node.agree(load(args))?;
    let Loaded {
        mut world,
        camera,
        width,
        quality,
        built,
        fingerprint,
        resumed_frames,
    } = loaded;
    if let Some(cluster) = cluster {
        world.insert_resource(cluster);
    }
    let leads = node.leads();
    if !leads {
        // A worker's film holds only its own tiles and is never shown: filtering it
        // would only keep the worker from the next frame.
        world
            .entity_mut(camera)
            .remove::<(DiscontinuityFilter, FilteredImage)>();
    }
    let spp = quality.samples_per_pixel;
    let target_frames = args.frames.unwrap_or(1);

    let mut profile = if leads {
        CliProfile::start(&mut world, args.profile.as_deref())?
    } else {
        None
    };
    let bar = progress_bar(
        args,
        width,
        target_frames.saturating_sub(resumed_frames),
        !leads,
    );
    let tick = bar.clone();
    world.insert_resource(TileProgress(Some(Arc::new(move |_| tick.inc(1)))));

    let start = Instant::now();
    let mut schedule = frame_schedule();
    let stop = node.stop_at(
        StopAt {
            frames: if args.time.is_some() {
                args.frames
            } else {
                Some(target_frames)
            },
            budget: args.time,
            interrupt: Some(interrupted.clone()),
            frames_follow: false,
        },
        &world,
    );
    let mut snapshot_failure = None;
    let checkpoint_path = args
        .checkpoint
        .clone()
        .unwrap_or_else(|| args.out.with_extension("checkpoint"));
    let checkpoint_every = args
        .checkpoint_every
        .or(node.is_cluster().then_some(Duration::from_secs(30)));
    let mut last_save = Instant::now();
    let (stopped, _) = refine(
        &mut world,
        &mut schedule,
        camera,
        &stop,
        |world, progress| {
            if !leads {
                return Flow::Continue;
            }
            if let Some(every) = checkpoint_every
                && last_save.elapsed() >= every
            {
                last_save = Instant::now();
                let film = world.get::<Film>(camera).expect("cameras have films");
                let metadata = image_metadata(args, film, width, &quality);
                let saved = shown_film(film, world.get::<FilteredImage>(camera))
                    .write_with(&args.out, args.exposure, &metadata)
                    .and_then(|()| film.write_checkpoint(&checkpoint_path, fingerprint));
                if let Err(error) = saved {
                    snapshot_failure = Some(error);
                    return Flow::Stop;
                }
            }
            if let Some(profile) = &mut profile {
                profile.record(world);
            }
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
                let film = world.get::<Film>(camera).expect("cameras have films");
                let metadata = image_metadata(args, film, width, &quality);
                let writing = Instant::now();
                let written = shown_film(film, world.get::<FilteredImage>(camera)).write_with(
                    &snapshot_path(&args.out, frames),
                    args.exposure,
                    &metadata,
                );
                if let Some(profile) = &mut profile {
                    profile.add_write(writing.elapsed());
                }
                if let Err(error) = written {
                    snapshot_failure = Some(error);
                    return Flow::Stop;
                }
            }
            Flow::Continue
        },
    );
    if !leads {
        // A worker's film holds only its own tiles: rank 0 writes the image.
        return match world.get_resource::<Cluster>().and_then(Cluster::failure) {
            Some(failure) => node.fail_with(failure),
            None => Ok(()),
        };
    }
    if let Some(error) = snapshot_failure {
        if node.is_cluster() {
            if let Some(mut cluster) = world.get_resource_mut::<Cluster>() {
                cluster.abandon(&error.to_string());
            }
            node.fail(&error.to_string());
        }
        return Err(error.into());
    }
    let cluster_failure = node.end_frames(&mut world);
    if stopped == Stopped::Interrupted && cluster_failure.is_none() {
        bar.finish_and_clear();
        let frames = world.get::<Film>(camera).map_or(0, Film::frames);
        eprintln!(
            "interrupted: writing the {frames} frames accumulated so far (Ctrl-C again to quit without writing)"
        );
    }
    let wall = start.elapsed();
    bar.finish_and_clear();

    let film = world
        .get::<Film>(camera)
        .ok_or_else(|| anyhow::anyhow!("the camera has no film"))?;
    if let Some(failure) = &cluster_failure
        && film.frames() == 0
    {
        node.fail(&format!(
            "{failure} (no frame was complete: nothing written)"
        ));
    }
    let metadata = image_metadata(args, film, width, &quality);
    let writing = Instant::now();
    shown_film(film, world.get::<FilteredImage>(camera)).write_with(
        &args.out,
        args.exposure,
        &metadata,
    )?;
    if let Some(profile) = &mut profile {
        profile.add_write(writing.elapsed());
    }
    let interrupted = interrupted.load(Ordering::SeqCst);
    // A cluster run cut short keeps a checkpoint even when none was asked for: a signal
    // there is Ctrl-C or mpirun ending the run because a rank died.
    let checkpoint = args.checkpoint.clone().or_else(|| {
        (node.is_cluster() && (interrupted || cluster_failure.is_some()))
            .then(|| checkpoint_path.clone())
    });
    if let Some(path) = &checkpoint {
        film.write_checkpoint(path, fingerprint)?;
    }
    if let Some(failure) = cluster_failure {
        eprintln!(
            "wrote the {} frames rendered before the failure to {} and {} (continue with --resume)",
            film.frames(),
            args.out.display(),
            checkpoint.as_deref().unwrap_or(Path::new("")).display()
        );
        node.fail(&failure);
    }
    if interrupted {
        match (&checkpoint, node.is_cluster()) {
            (Some(path), true) => eprintln!(
                "wrote {} and {} (a rank that died is named by mpirun; continue with --resume)",
                args.out.display(),
                path.display()
            ),
            _ => eprintln!("wrote {}", args.out.display()),
        }
        if let Some(profile) = profile.take() {
            profile.finish(true);
        }
        // Without MPI_Finalize: it would wait for ranks that may be gone.
        std::process::exit(130);
    }
    if film.rejected_samples() > 0 {
        eprintln!(
            "warning: {} NaN/Inf samples were dropped",
            film.rejected_samples()
        );
    }
    if !args.quiet {
        println!("{}", summary(args, width, spp, film, &world, &built, wall));
        if let Some(line) = node.summary(&world) {
            println!("{line}");
        }
    }
    if let Some(profile) = profile {
        profile.finish(args.quiet);
    }
    Ok(())
}

/// What building the scene took and made, for the summary.
struct Built {
    stats: SceneStats,
    generate_time: Duration,
    blas_time: Duration,
}

/// The summary lines printed after a render: the image, the scene, the time and what
/// the rays did.
fn summary(
    args: &RenderArgs,
    width: u32,
    spp: u32,
    film: &Film,
    world: &World,
    built: &Built,
    wall: Duration,
) -> String {
    let render_stats = world.resource::<RenderStats>();
    let tlas = world.resource::<TopLevelState>();
    let render_s = render_stats.total_render.as_secs_f64();
    let rays = render_stats.total.rays();
    let rendered = render_stats.frames;
    format!(
        "{}: {}x{}, {} frames at {} spp ({} spp in all) -> {}\n  {} instances, {} instanced triangles ({} unique), BLAS build {:.2} s, TLAS build {:.1} ms, scene generation {:.2} s\n  render {:.2} s ({:.3} s per frame), {:.2} M rays/s ({} camera + {} shadow rays), {:.2} transparency segments per camera ray ({:.2} holes tested), {} holes made opaque, {}, total {:.2} s\n  per ray: {:.1} nodes visited, {:.1} primitive tests (instances and triangles), {:.2} alpha tests ({:.2} sampled the texture); {:.1} % of shadow rays stopped by a recent occluder without a walk",
        scene_label(&args.scene),
        width,
        args.height,
        film.frames(),
        spp,
        film.frames() as u64 * spp as u64,
        args.out.display(),
        group(built.stats.instances as u64),
        group(built.stats.instanced_triangles),
        group(built.stats.unique_triangles as u64),
        built.blas_time.as_secs_f64(),
        tlas.last_build.as_secs_f64() * 1e3,
        built.generate_time.as_secs_f64(),
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
        100.0 * render_stats.total.cached_occlusions as f64
            / render_stats.total.any_rays.max(1) as f64,
    )
}

/// A bar over the tiles of `frames` frames, or a spinner for a time budget; hidden with
/// --quiet.
fn progress_bar(args: &RenderArgs, width: u32, frames: u32, hidden: bool) -> ProgressBar {
    let tiles = Tile::grid(
        width,
        args.height,
        sylva::engine::RenderParams::default().tile_size,
    )
    .len() as u64;
    let bar = if args.quiet || hidden {
        ProgressBar::hidden()
    } else if args.time.is_some() {
        ProgressBar::new_spinner()
    } else {
        ProgressBar::new(tiles * u64::from(frames))
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
    bar
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
