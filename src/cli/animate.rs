//! `sylva animate`: an image sequence of the scene with its plants swaying in the wind,
//! one image per 1/fps seconds, resumable after the last image written. The timing and
//! the per-image refinement are `sylva_systems::animation::Sequence`.

use super::cluster::{ClusterArgs, Node};
use super::profile::CliProfile;
use super::*;
use indicatif::{ProgressBar, ProgressStyle};
use sylva::engine::discontinuity::FilteredImage;
use sylva::scenes::editor;
use sylva::systems::NodeAnimationPlayer;
use sylva::systems::animation::Sequence;
use sylva::systems::cluster::Cluster;
use sylva::systems::shown_film;

#[derive(Args, Debug)]
pub(crate) struct AnimateArgs {
    #[command(flatten)]
    scene: SceneArgs,
    /// Seconds of animation [default: to the last key of the scene file's camera path or
    /// of the glTF file's animation].
    #[arg(long, value_parser = parse_seconds)]
    seconds: Option<f64>,
    /// Images per second of animation.
    #[arg(long, default_value_t = 30, value_parser = clap::value_parser!(u32).range(1..=1000))]
    fps: u32,
    /// Where image k goes: a path whose `%d` or `%0Nd` (e.g. frame_%04d.png) is replaced
    /// by k; .png (tone-mapped sRGB) or .exr (linear radiance). The directory is made
    /// when missing.
    #[arg(long, short, default_value = "frames/frame_%04d.png")]
    out: String,
    /// Also write the whole sequence as one animated PNG (APNG) that loops at --fps (its
    /// directory is made when missing).
    #[arg(long, value_name = "FILE.png")]
    preview: Option<PathBuf>,
    /// Skip the images already written (each is written whole or not at all) and render
    /// from the first one missing; the result is bit for bit an uninterrupted run's.
    #[arg(long)]
    resume: bool,
    /// Image width in pixels [default: height × 4/3, or × the glTF camera's aspect ratio].
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=16384))]
    width: Option<u32>,
    /// Image height in pixels.
    #[arg(long, default_value_t = 480, value_parser = clap::value_parser!(u32).range(1..=16384))]
    height: u32,
    /// Quality of each image's frames.
    #[arg(long, value_enum, default_value = "still")]
    preset: Preset,
    /// Camera samples per pixel per frame [default: the preset's].
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=65536))]
    spp: Option<u32>,
    /// Progressive frames accumulated into each image.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=100_000))]
    frames_per_image: u32,
    /// The wind that sways the plants (each on a damped spring sized by its height).
    #[arg(long, value_enum, value_name = "on|off", default_value = "on")]
    wind: Switch,
    #[command(flatten)]
    lighting: LightingArgs,
    /// Exposure in stops, applied before tone mapping (PNG only).
    #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
    exposure: f32,
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

/// What every rank builds before the images: the world, its camera and the sequence.
struct Loaded {
    world: World,
    camera: Entity,
    width: u32,
    quality: Quality,
    sequence: Sequence,
    /// Images in the sequence, and the first one to render.
    images: u32,
    first: u32,
}

/// A positive, finite number of seconds.
fn parse_seconds(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(s) if s.is_finite() && s > 0.0 => Ok(s),
        _ => Err(format!("'{text}' is not a positive number of seconds")),
    }
}

/// An output pattern split around its `%d` / `%0Nd`: prefix, digits, suffix.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct FramePattern {
    prefix: String,
    digits: usize,
    suffix: String,
}

impl FramePattern {
    /// Parses `frame_%04d.png`; errors say what is wrong with the pattern.
    pub(crate) fn parse(pattern: &str) -> Result<Self> {
        let Some(start) = pattern.find('%') else {
            bail!("--out {pattern}: the pattern needs %d or %0Nd where the image number goes");
        };
        let rest = &pattern[start + 1..];
        let Some(end) = rest.find('d') else {
            bail!("--out {pattern}: '%' must be followed by d or 0Nd (e.g. frame_%04d.png)");
        };
        let width = &rest[..end];
        let digits = if width.is_empty() {
            0
        } else {
            match width.strip_prefix('0').map(str::parse::<usize>) {
                Some(Ok(n)) if n <= 10 => n,
                _ => bail!("--out {pattern}: '%{width}d' is not %d or %0Nd with N up to 10"),
            }
        };
        let suffix = &rest[end + 1..];
        if suffix.contains('%') {
            bail!("--out {pattern}: only one image number placeholder is allowed");
        }
        let pattern = Self {
            prefix: pattern[..start].to_string(),
            digits,
            suffix: suffix.to_string(),
        };
        ImageKind::from_path(&pattern.path(0))?;
        Ok(pattern)
    }

    /// The path of image `index`.
    pub(crate) fn path(&self, index: u32) -> PathBuf {
        PathBuf::from(format!(
            "{}{index:0width$}{}",
            self.prefix,
            self.suffix,
            width = self.digits
        ))
    }
}

/// Runs `sylva animate`.
pub(crate) fn run(args: AnimateArgs) -> Result<()> {
    let pattern = FramePattern::parse(&args.out)?;
    if let Some(preview) = &args.preview
        && ImageKind::from_path(preview)? != ImageKind::Png
    {
        bail!(
            "--preview {}: an animated preview is a .png file",
            preview.display()
        );
    }
    let outputs = [Some(pattern.path(0)), args.preview.clone()];
    for dir in outputs.iter().flatten().filter_map(|p| p.parent()) {
        if !dir.as_os_str().is_empty() {
            std::fs::create_dir_all(dir).map_err(|e| {
                anyhow::anyhow!("{}: cannot create the directory: {e}", dir.display())
            })?;
        }
    }
    check_exposure(args.exposure)?;
    let mut node = Node::join(&args.cluster)?;
    let result = animate(&args, &pattern, &mut node);
    node.end(result)
}

/// Builds the world and the sequence, and finds the first image to render.
fn load(args: &AnimateArgs, pattern: &FramePattern) -> Result<Loaded> {
    let mut world = World::new();
    let (mut scene, width, environment) = build_framed(
        &mut world,
        &args.scene,
        (args.lighting.env.as_deref(), args.lighting.lights),
        &Framing {
            size: (args.width, args.height),
            max_width: 16384,
            exposure: args.exposure,
        },
    )?;
    let preset = args.preset.quality();
    let quality = Quality {
        samples_per_pixel: args.spp.unwrap_or(preset.samples_per_pixel),
        ..preset
    };
    // The scene file's camera flight: the camera follows it from image 0.
    let camera_path = scene.camera_path.take();
    // A glTF file's node animation plays on the plants it moves.
    let node_animation = scene.node_animation.take();
    let last_key = camera_path
        .as_ref()
        .map(|p| p.keys()[p.keys().len() - 1].time)
        .into_iter()
        .chain(
            node_animation
                .as_ref()
                .map(|(a, _)| f64::from(a.duration())),
        )
        .fold(0.0, f64::max);
    let seconds = match args.seconds {
        Some(seconds) => seconds,
        None if last_key > 0.0 => last_key,
        None => bail!(
            "give --seconds: how long the animation runs (the scene has no camera path or \
             animation to take it from)"
        ),
    };
    let spawned = spawn(&mut world, scene);
    if let Some((animation, bound)) = node_animation {
        let instances = bound
            .into_iter()
            .filter_map(|(plant, node, local)| {
                spawned
                    .plants
                    .get(plant)
                    .map(|&entity| (entity, node, local))
            })
            .collect();
        world.insert_resource(NodeAnimationPlayer {
            animation,
            instances,
        });
    }
    if let Some(environment) = environment {
        world.spawn(environment);
    }
    if let Some(path) = camera_path {
        world.entity_mut(spawned.camera).insert(path);
    }
    quality.apply(&mut world, spawned.camera);
    let sequence = Sequence {
        fps: f64::from(args.fps),
        frames_per_image: args.frames_per_image,
        seed: args.scene.seed,
    };
    if args.wind == Switch::On {
        editor::set_wind(&mut world, true, 1.0 / sequence.fps);
    }
    let images = sequence.images(seconds);
    let first = if args.resume {
        (0..images)
            .find(|&k| !pattern.path(k).exists())
            .unwrap_or(images)
    } else {
        0
    };
    Ok(Loaded {
        world,
        camera: spawned.camera,
        width,
        quality,
        sequence,
        images,
        first,
    })
}

/// `sylva animate` on this node: alone, or one rank of an MPI run (rank 0 writes).
fn animate(args: &AnimateArgs, pattern: &FramePattern, node: &mut Node) -> Result<()> {
    let (loaded, cluster, interrupted) = node.agree(load(args, pattern))?;
    let Loaded {
        mut world,
        camera,
        width,
        quality,
        sequence,
        images,
        first,
    } = loaded;
    let leads = node.leads();
    if let Some(cluster) = cluster {
        world.insert_resource(cluster);
    }
    if first == images {
        if leads {
            eprintln!("all {images} images are there already");
        }
        return Ok(());
    }
    if !leads {
        world.entity_mut(camera).remove::<(
            sylva::engine::discontinuity::DiscontinuityFilter,
            FilteredImage,
        )>();
    }
    sequence.skip(&mut world, 0, first.saturating_sub(1));
    // The preview's frames: those already written are read back (PNG only: EXR images
    // would need tone mapping again), the new ones kept as they are written.
    let mut preview_frames = Vec::new();
    if args.preview.is_some() && leads {
        for index in 0..first {
            let path = pattern.path(index);
            if ImageKind::from_path(&path)? != ImageKind::Png {
                bail!(
                    "--preview with --resume reads the images already written back, and {} is \
                     not a PNG: render the sequence as PNG or make the preview in a full run",
                    path.display()
                );
            }
            preview_frames.push(sylva::engine::film::read_rgba8_png(&path)?.1);
        }
    }

    let bar = if args.quiet || !leads {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(u64::from(images))
    };
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} animating [{bar:40}] {pos}/{len} images, {elapsed_precise} (eta {eta})",
        )
        .expect("the template is valid"),
    );
    bar.set_position(u64::from(first));
    let stop = StopAt {
        interrupt: Some(match world.get_resource::<Cluster>() {
            Some(cluster) => cluster.stop_flag(),
            None => interrupted,
        }),
        ..StopAt::default()
    };
    let mut schedule = frame_schedule();
    let mut profile = if leads {
        CliProfile::start(&mut world, args.profile.as_deref())?
    } else {
        None
    };
    let start = std::time::Instant::now();
    for index in first..images {
        let stopped = sequence.render_image(
            &mut world,
            &mut schedule,
            camera,
            index,
            &StopAt {
                frames_follow: index + 1 < images,
                ..stop.clone()
            },
            |world, _| {
                if let Some(profile) = &mut profile {
                    profile.record(world);
                }
                Flow::Continue
            },
        );
        if stopped == Stopped::Interrupted && !leads {
            return match world.get_resource::<Cluster>().and_then(Cluster::failure) {
                Some(failure) => node.fail_with(failure),
                None => Ok(()),
            };
        }
        if stopped == Stopped::Interrupted {
            if let Some(failure) = node.end_frames(&mut world) {
                node.fail(&format!(
                    "{failure} (images 0 to {} are written; --resume continues with image {index})",
                    index.saturating_sub(1)
                ));
            }
            bar.finish_and_clear();
            eprintln!(
                "interrupted: images 0 to {} are written; --resume continues with image {index}",
                index.saturating_sub(1)
            );
            if let Some(profile) = profile.take() {
                profile.finish(true);
            }
            std::process::exit(130);
        }
        if !leads {
            continue;
        }
        let film = world
            .get::<Film>(camera)
            .ok_or_else(|| anyhow::anyhow!("the camera has no film"))?;
        let metadata: Vec<(String, String)> = [
            (
                "Software",
                format!("sylva {} animate", env!("CARGO_PKG_VERSION")),
            ),
            ("sylva.scene", scene_label(&args.scene)),
            ("sylva.seed", args.scene.seed.to_string()),
            ("sylva.size", format!("{width}x{}", args.height)),
            ("sylva.image", index.to_string()),
            ("sylva.time", format!("{}", f64::from(index) / sequence.fps)),
            ("sylva.frames", film.frames().to_string()),
            ("sylva.spp_per_frame", quality.samples_per_pixel.to_string()),
            ("sylva.wind", format!("{:?}", args.wind).to_lowercase()),
        ]
        .map(|(k, v)| (k.to_string(), v))
        .into();
        let writing = std::time::Instant::now();
        let shown = shown_film(film, world.get::<FilteredImage>(camera));
        shown.write_with(&pattern.path(index), args.exposure, &metadata)?;
        if args.preview.is_some() {
            preview_frames.push(shown.to_srgba8(args.exposure));
        }
        if let Some(profile) = &mut profile {
            profile.add_write(writing.elapsed());
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    if !leads {
        return Ok(());
    }
    if let Some(failure) = node.end_frames(&mut world) {
        node.fail(&failure);
    }
    if let Some(preview) = &args.preview {
        let fps = u16::try_from(args.fps).unwrap_or(u16::MAX);
        sylva::engine::film::write_apng(
            preview,
            (width, args.height),
            &preview_frames,
            fps,
            &[(
                "Software".to_string(),
                format!("sylva {} animate", env!("CARGO_PKG_VERSION")),
            )],
        )?;
    }
    if !args.quiet {
        let rendered = images - first;
        println!(
            "{rendered} images of {} ({}x{}, {} fps, {} frames each) in {:.1} s ({:.2} s per image): {} … {}",
            scene_label(&args.scene),
            width,
            args.height,
            args.fps,
            args.frames_per_image,
            start.elapsed().as_secs_f64(),
            start.elapsed().as_secs_f64() / f64::from(rendered),
            pattern.path(first).display(),
            pattern.path(images - 1).display(),
        );
    }
    if let Some(profile) = profile {
        profile.finish(args.quiet);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_patterns_number_their_images_and_bad_ones_say_why() {
        let p = FramePattern::parse("out/frame_%04d.png").unwrap();
        assert_eq!(p.path(7), PathBuf::from("out/frame_0007.png"));
        assert_eq!(p.path(12345), PathBuf::from("out/frame_12345.png"));
        let plain = FramePattern::parse("f%d.exr").unwrap();
        assert_eq!(plain.path(3), PathBuf::from("f3.exr"));
        for (bad, says) in [
            ("frame.png", "needs %d"),
            ("frame_%4x.png", "0Nd"),
            ("frame_%4d.png", "%0Nd"),
            ("frame_%04d_%d.png", "only one"),
            ("frame_%04d.jpg", "jpg"),
        ] {
            let error = FramePattern::parse(bad).unwrap_err().to_string();
            assert!(error.contains(says), "{bad}: {error}");
        }
    }
}
