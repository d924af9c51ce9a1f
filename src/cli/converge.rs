//! `sylva converge`: the reference (rendered once, cached as an exact checkpoint in the
//! output directory), one progressive run per setting, then the CSV, the plot and the
//! table.

use super::LightingArgs;
use super::cluster::{ClusterArgs, Node};
use super::plot::plot_error_vs_time;
use super::{SceneArgs, build_lit, hash_scene, init_tracing, parse_duration, scene_label};
use anyhow::{Context, Result};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Duration;
use sylva::prelude::{
    Entity, Film, Fingerprint, Quality, RenderSeed, Schedule, Vec3, World, frame_schedule, spawn,
};
use sylva::systems::cluster::Cluster;
use sylva::systems::converge::{
    ErrorSample, Setting, film_pixels, measure, render_reference, summarize, write_csv,
};
use sylva::systems::{Flow, StopAt, refine};

#[derive(Args, Debug)]
pub(crate) struct ConvergeArgs {
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
    #[command(flatten)]
    lighting: LightingArgs,
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
    #[command(flatten)]
    cluster: ClusterArgs,
}

/// Parses a fraction in (0, 1].
fn parse_fraction(text: &str) -> Result<f32, String> {
    match text.parse::<f32>() {
        Ok(f) if f > 0.0 && f <= 1.0 => Ok(f),
        _ => Err(format!("'{text}' must be a number in (0, 1]")),
    }
}

/// The reference's sampler seed differs from the runs' so their noise is independent.
const REFERENCE_SEED_OFFSET: u64 = 0x5eed_0f4e_f500;

pub fn run(args: ConvergeArgs) -> Result<()> {
    let _trace_guard = init_tracing(None);
    let settings = chosen_settings(&args.configs)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("{}: cannot create the directory", args.out.display()))?;
    let mut node = Node::join(&args.cluster)?;
    let result = converge(&args, settings, &mut node);
    node.end(result)
}

/// Builds the world for `converge`; returns it and its camera.
fn load(args: &ConvergeArgs) -> Result<(World, Entity)> {
    let mut world = World::new();
    let (mut scene, _, environment) = build_lit(
        &mut world,
        &args.scene,
        args.lighting.env.as_deref(),
        args.lighting.lights,
    )?;
    scene.camera.width = args.width;
    scene.camera.height = args.height;
    let half = (scene.camera.vertical_fov * 0.5).tan() * args.crop;
    scene.camera.vertical_fov = 2.0 * half.atan();
    let spawned = spawn(&mut world, scene);
    if let Some(environment) = environment {
        world.spawn(environment);
    }
    Ok((world, spawned.camera))
}

/// `sylva converge` on this node: alone, or one rank of an MPI run (rank 0 measures,
/// decides when each setting's run ends and writes; the others render with it).
fn converge(args: &ConvergeArgs, settings: Vec<Setting>, node: &mut Node) -> Result<()> {
    let ((mut world, camera), cluster, _interrupted) = node.agree(load(args))?;
    if let Some(cluster) = cluster {
        world.insert_resource(cluster);
    }
    let mut schedule = frame_schedule();

    let bounces = settings
        .iter()
        .map(|s| s.quality.bounces)
        .max()
        .unwrap_or(0);
    let reference = reference(args, bounces, &mut world, &mut schedule, camera)?;
    let mut runs: Vec<(Setting, Vec<ErrorSample>)> = Vec::new();
    for setting in settings {
        setting
            .apply(&mut world, camera)
            .map_err(|e| anyhow::anyhow!("could not start the worker threads: {e}"))?;
        world.insert_resource(RenderSeed(args.scene.seed));
        if world.get_resource::<Cluster>().is_some_and(|c| !c.leads()) {
            // Render with rank 0 until it has measured this setting.
            let stop = node.stop_at(StopAt::default(), &world);
            refine(&mut world, &mut schedule, camera, &stop, |_, _| {
                Flow::Continue
            });
            if let Some(failure) = world.resource::<Cluster>().failure() {
                node.fail_with(failure);
            }
            world.resource_mut::<Cluster>().resume();
            continue;
        }
        let bar = spinner(args.quiet, &setting.name);
        let samples = measure(
            &mut world,
            &mut schedule,
            camera,
            &reference,
            args.budget,
            args.max_frames,
            &mut |s| {
                bar.set_message(format!(
                    "{}: frame {}, {:.1} s, relMSE {:.2e}",
                    setting.name, s.frame, s.time_s, s.relmse
                ))
            },
        );
        bar.finish_and_clear();
        if let Some(failure) = node.end_frames(&mut world) {
            node.fail(&failure);
        }
        runs.push((setting, samples));
    }
    if !node.leads() {
        return Ok(());
    }

    let csv = args.out.join("error_vs_time.csv");
    write_csv(&csv, &runs).with_context(|| format!("{}: cannot write", csv.display()))?;
    let png = args.out.join("error_vs_time.png");
    let title = format!(
        "{} {}x{}: relMSE against wall time",
        scene_label(&args.scene),
        args.width,
        args.height
    );
    let curves: Vec<(String, Vec<ErrorSample>)> = runs
        .iter()
        .map(|(s, samples)| (s.name.clone(), samples.clone()))
        .collect();
    plot_error_vs_time(&png, &title, &curves, (720, 480))?;
    print!("{}", table(&runs));
    if !args.quiet {
        println!("wrote {} and {}", csv.display(), png.display());
    }
    Ok(())
}

/// The settings named in `--configs`, or all standard ones.
fn chosen_settings(names: &[String]) -> Result<Vec<Setting>> {
    if names.is_empty() {
        return Ok(Setting::standard());
    }
    let all = Setting::available();
    names
        .iter()
        .map(|name| {
            all.iter()
                .find(|s| &s.name == name)
                .cloned()
                .ok_or_else(|| {
                    let known: Vec<&str> = all.iter().map(|s| s.name.as_str()).collect();
                    anyhow::anyhow!("unknown setting '{name}' (available: {})", known.join(", "))
                })
        })
        .collect()
}

fn spinner(quiet: bool, what: &str) -> ProgressBar {
    if quiet {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new_spinner();
    bar.set_style(
        ProgressStyle::with_template("{spinner} {msg}, {elapsed_precise}")
            .expect("the template is valid"),
    );
    bar.set_message(what.to_string());
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    bar
}

/// The reference pixels: loaded from `OUT/reference.film` when it was made for this
/// scene, view and reference length, rendered (and cached) otherwise.
fn reference(
    args: &ConvergeArgs,
    bounces: u32,
    world: &mut World,
    schedule: &mut Schedule,
    camera: Entity,
) -> Result<Vec<Vec3>> {
    let quality = Quality {
        bounces,
        ..Quality::still()
    };
    let mut hash = Fingerprint::new("sylva converge reference v2");
    hash_scene(
        &mut hash,
        &args.scene,
        args.lighting.env.as_deref(),
        args.lighting.lights,
    );
    hash.u32(args.width)
        .u32(args.height)
        .f32(args.crop)
        .u32(args.reference_frames)
        .u64(quality.fingerprint());
    let key = hash.finish();
    let cache = args.out.join("reference.film");
    // Rank 0 reads the cache and says whether every rank renders the reference.
    let leads = world.get_resource::<Cluster>().is_none_or(Cluster::leads);
    let cached = if leads {
        Film::read_checkpoint(&cache, key).ok()
    } else {
        None
    };
    let use_cache = match world.get_resource_mut::<Cluster>() {
        Some(mut cluster) => cluster.share(u64::from(cached.is_some()))? == 1,
        None => cached.is_some(),
    };
    if use_cache && !leads {
        return Ok(Vec::new());
    }
    if let Some(film) = cached.filter(|_| use_cache) {
        if !args.quiet {
            println!(
                "reference: cached {} ({} frames, {} spp)",
                cache.display(),
                film.frames(),
                film.frames() * 4
            );
        }
        return Ok(film.mean_rgb().into_iter().map(Vec3::from).collect());
    }
    Setting::new("reference", quality)
        .apply(world, camera)
        .map_err(|e| anyhow::anyhow!("could not start the worker threads: {e}"))?;
    let bar = if args.quiet || !leads {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(u64::from(args.reference_frames))
    };
    bar.set_style(
        ProgressStyle::with_template("reference [{bar:40}] {pos}/{len} frames, eta {eta}")
            .expect("the template is valid")
            .progress_chars("=> "),
    );
    let pixels = render_reference(
        world,
        schedule,
        camera,
        args.reference_frames,
        args.scene.seed ^ REFERENCE_SEED_OFFSET,
        &mut |frame| bar.set_position(u64::from(frame)),
    );
    bar.finish_and_clear();
    if !leads {
        return Ok(Vec::new());
    }
    let film = world
        .get::<Film>(camera)
        .context("the camera has no film")?;
    film.write_checkpoint(&cache, key)?;
    #[cfg(feature = "exr")]
    film.write(&args.out.join("reference.exr"), 0.0)?;
    if !args.quiet {
        println!(
            "reference: {} frames, {} spp -> {}",
            args.reference_frames,
            args.reference_frames * 4,
            cache.display()
        );
    }
    debug_assert_eq!(pixels, film_pixels(world, camera));
    Ok(pixels)
}

/// The summary table, one row per setting.
fn table(runs: &[(Setting, Vec<ErrorSample>)]) -> String {
    let seconds = |t: Option<f64>| t.map_or("—".to_string(), |t| format!("{t:.2}"));
    let mut out = String::new();
    let _ = writeln!(
        out,
        "{:<26} {:>7} {:>8} {:>9} {:>12} {:>11} {:>11} {:>7}",
        "setting", "frames", "spp", "time s", "final relMSE", "t(1e-2) s", "t(1e-3) s", "slope"
    );
    for (setting, samples) in runs {
        let summary = summarize(samples);
        let last = samples.last();
        let _ = writeln!(
            out,
            "{:<26} {:>7} {:>8} {:>9.2} {:>12.3e} {:>11} {:>11} {:>7}",
            setting.name,
            last.map_or(0, |s| s.frame),
            last.map_or(0, |s| s.spp),
            last.map_or(0.0, |s| s.time_s),
            summary.final_relmse,
            seconds(summary.time_to_1e2),
            seconds(summary.time_to_1e3),
            summary.slope.map_or("—".to_string(), |s| format!("{s:.2}")),
        );
    }
    out
}
