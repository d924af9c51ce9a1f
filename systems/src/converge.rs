//! The error-against-time harness behind `sylva converge`: sampling settings to compare,
//! progressive runs that record wall time, samples per pixel, RMSE and relMSE against a
//! reference after every frame, and the summary a user chooses settings by (time to reach
//! a relMSE, fitted convergence slope).

use crate::{Flow, Quality, RenderPool, RenderSeed, StopAt, refine};
use bevy_ecs::prelude::*;
use glam::Vec3;
use std::io::Write;
use std::path::Path;
use std::time::Duration;
use sylva_engine::Camera;
use sylva_engine::discontinuity::FilteredImage;
use sylva_engine::film::Film;
use sylva_engine::interleave::LightInterleave;
use sylva_engine::metrics::image_error;

/// One sampling setting under test.
#[derive(Clone, Debug, PartialEq)]
pub struct Setting {
    /// Short name, used in the CSV and the plot legend.
    pub name: String,
    /// How the camera samples and shows its frames.
    pub quality: Quality,
    /// Worker threads (0 = one per core).
    pub threads: usize,
}

impl Setting {
    /// `quality` on every core, named `name`.
    pub fn new(name: &str, quality: Quality) -> Self {
        Self {
            name: name.into(),
            quality,
            threads: 0,
        }
    }

    /// The interactive preset ([`Quality::interactive`]) on every core.
    pub fn interactive() -> Self {
        Self::new("interactive", Quality::interactive())
    }

    /// The still preset ([`Quality::still`]) on every core.
    pub fn still() -> Self {
        Self::new("still", Quality::still())
    }

    /// The comparisons `sylva converge` runs by default: the interactive preset with and
    /// without its display filter, interleaved vs independent light picks (both exact,
    /// unfiltered), adaptive transparency on vs off, interactive vs still, and the
    /// interactive preset on 1 thread.
    pub fn standard() -> Vec<Setting> {
        let interactive = Quality::interactive();
        let exact = Quality {
            transparency: None,
            filter: None,
            ..interactive
        };
        vec![
            Self::interactive(),
            Self::new(
                "interactive-unfiltered",
                Quality {
                    filter: None,
                    ..interactive
                },
            ),
            Self::new("interactive-exact", exact),
            Self::new(
                "interactive-exact-random",
                Quality {
                    interleave: LightInterleave {
                        pattern: 1,
                        subsets: 0,
                    },
                    ..exact
                },
            ),
            Self::still(),
            Setting {
                threads: 1,
                ..Self::new("interactive-1-thread", interactive)
            },
        ]
    }

    /// Every setting `--configs` may name: the standard ones, and `bounces1` (the still
    /// preset with one bounce of indirect light; naming it makes the reference carry
    /// one bounce too, so the direct-light settings show the light they leave out).
    pub fn available() -> Vec<Setting> {
        let mut all = Self::standard();
        all.push(Self::new(
            "bounces1",
            Quality {
                bounces: 1,
                ..Quality::still()
            },
        ));
        all
    }

    /// Puts this setting's quality on `camera` (which restarts its accumulation) and
    /// sizes the render pool.
    pub fn apply(
        &self,
        world: &mut World,
        camera: Entity,
    ) -> Result<(), rayon::ThreadPoolBuildError> {
        world.insert_resource(RenderPool::new(self.threads)?);
        self.quality.apply(world, camera);
        Ok(())
    }
}

/// The error of one progressive frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ErrorSample {
    /// Frames accumulated.
    pub frame: u32,
    /// Wall time since the setting's first frame started, seconds.
    pub time_s: f64,
    /// Camera samples per pixel accumulated.
    pub spp: u64,
    /// RMSE against the reference.
    pub rmse: f64,
    /// relMSE against the reference.
    pub relmse: f64,
}

/// Mean radiance of a camera's film, row-major.
pub fn film_pixels(world: &World, camera: Entity) -> Vec<Vec3> {
    world
        .get::<Film>(camera)
        .map(|film| film.mean_rgb().into_iter().map(Vec3::from).collect())
        .unwrap_or_default()
}

/// What `camera` shows: its filtered image when it has one of the film's current frame
/// count, else the film's means.
pub fn shown_pixels(world: &World, camera: Entity) -> Vec<Vec3> {
    let frames = world.get::<Film>(camera).map_or(0, Film::frames);
    match world.get::<FilteredImage>(camera) {
        Some(image) if image.frames == frames => image.pixels.clone(),
        _ => film_pixels(world, camera),
    }
}

/// Renders `frames` progressive frames of `camera` with the current settings and a
/// sampler seed of its own, calling `on_frame` after each.
pub fn render_reference(
    world: &mut World,
    schedule: &mut Schedule,
    camera: Entity,
    frames: u32,
    seed: u64,
    on_frame: &mut dyn FnMut(u32),
) -> Vec<Vec3> {
    world.insert_resource(RenderSeed(seed));
    let stop = StopAt {
        frames: Some(frames),
        ..StopAt::default()
    };
    refine(world, schedule, camera, &stop, |_, progress| {
        on_frame(progress.rendered);
        Flow::Continue
    });
    film_pixels(world, camera)
}

/// Progressive frames of `camera` until `budget` is spent or `max_frames` are done, with
/// the error against `reference` after each frame. The error computation is not timed.
pub fn measure(
    world: &mut World,
    schedule: &mut Schedule,
    camera: Entity,
    reference: &[Vec3],
    budget: Duration,
    max_frames: u32,
    on_frame: &mut dyn FnMut(&ErrorSample),
) -> Vec<ErrorSample> {
    let spp = u64::from(
        world
            .get::<Camera>(camera)
            .map_or(1, |c| c.samples_per_pixel),
    );
    let mut samples = Vec::new();
    let stop = StopAt {
        frames: Some(max_frames),
        budget: Some(budget),
        ..StopAt::default()
    };
    refine(world, schedule, camera, &stop, |world, progress| {
        let error = image_error(reference, &shown_pixels(world, camera)).unwrap_or_default();
        let sample = ErrorSample {
            frame: progress.rendered,
            time_s: progress.rendering.as_secs_f64(),
            spp: spp * u64::from(progress.rendered),
            rmse: error.rmse,
            relmse: error.relmse,
        };
        on_frame(&sample);
        samples.push(sample);
        Flow::Continue
    });
    samples
}

/// What the table reports per setting.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Summary {
    /// Seconds until relMSE first fell to 10⁻², if it did.
    pub time_to_1e2: Option<f64>,
    /// Seconds until relMSE first fell to 10⁻³, if it did.
    pub time_to_1e3: Option<f64>,
    /// Least-squares slope of log relMSE against log time (−1 for unbiased Monte Carlo;
    /// near 0 once a bias floor dominates); `None` with fewer than 3 usable frames.
    pub slope: Option<f64>,
    /// relMSE at the last frame.
    pub final_relmse: f64,
}

/// Summarises one setting's samples.
pub fn summarize(samples: &[ErrorSample]) -> Summary {
    let first_below = |threshold: f64| {
        samples
            .iter()
            .find(|s| s.relmse <= threshold)
            .map(|s| s.time_s)
    };
    Summary {
        time_to_1e2: first_below(1e-2),
        time_to_1e3: first_below(1e-3),
        slope: log_log_slope(samples),
        final_relmse: samples.last().map_or(f64::NAN, |s| s.relmse),
    }
}

/// Slope of the least-squares line through (ln time, ln relMSE), skipping the first frame
/// (start-up) and non-positive values.
fn log_log_slope(samples: &[ErrorSample]) -> Option<f64> {
    let points: Vec<(f64, f64)> = samples
        .iter()
        .skip(1)
        .filter(|s| s.time_s > 0.0 && s.relmse > 0.0 && s.relmse.is_finite())
        .map(|s| (s.time_s.ln(), s.relmse.ln()))
        .collect();
    if points.len() < 3 {
        return None;
    }
    let n = points.len() as f64;
    let (mx, my) = points
        .iter()
        .fold((0.0, 0.0), |(x, y), p| (x + p.0 / n, y + p.1 / n));
    let (sxy, sxx) = points.iter().fold((0.0, 0.0), |(sxy, sxx), p| {
        (sxy + (p.0 - mx) * (p.1 - my), sxx + (p.0 - mx) * (p.0 - mx))
    });
    (sxx > 0.0).then(|| sxy / sxx)
}

/// Writes `DIR/error_vs_time.csv`: `config,frame,time_s,spp,rmse,relmse`.
pub fn write_csv(path: &Path, runs: &[(Setting, Vec<ErrorSample>)]) -> std::io::Result<()> {
    let mut out = std::io::BufWriter::new(std::fs::File::create(path)?);
    writeln!(out, "config,frame,time_s,spp,rmse,relmse")?;
    for (setting, samples) in runs {
        for s in samples {
            writeln!(
                out,
                "{},{},{:.6},{},{:.8e},{:.8e}",
                setting.name, s.frame, s.time_s, s.spp, s.rmse, s.relmse
            )?;
        }
    }
    out.flush()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn samples(f: impl Fn(f64) -> f64) -> Vec<ErrorSample> {
        (1..=50)
            .map(|i| {
                let t = i as f64 * 0.1;
                ErrorSample {
                    frame: i,
                    time_s: t,
                    spp: u64::from(i),
                    rmse: f(t).sqrt(),
                    relmse: f(t),
                }
            })
            .collect()
    }

    #[test]
    fn the_summary_finds_thresholds_and_the_convergence_slope() {
        let unbiased = summarize(&samples(|t| 2e-3 / t));
        assert!((unbiased.slope.unwrap() + 1.0).abs() < 1e-9);
        // 2e-3 / t ≤ 1e-2 from t = 0.2 on, ≤ 1e-3 from t = 2.
        assert!((unbiased.time_to_1e2.unwrap() - 0.2).abs() < 1e-9);
        assert!((unbiased.time_to_1e3.unwrap() - 2.0).abs() < 1e-9);
        let floored = summarize(&samples(|t| 5e-3 + 1e-4 / t));
        assert!(floored.slope.unwrap() > -0.2, "{floored:?}");
        assert_eq!(floored.time_to_1e3, None);
        assert_eq!(summarize(&[]).slope, None);
    }

    #[test]
    fn the_csv_has_one_row_per_frame_after_its_header() {
        let dir = std::env::temp_dir().join(format!("sylva-csv-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("e.csv");
        let runs = vec![
            (Setting::interactive(), samples(|t| 1.0 / t)),
            (Setting::still(), samples(|t| 0.5 / t)),
        ];
        write_csv(&path, &runs).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "config,frame,time_s,spp,rmse,relmse");
        assert_eq!(lines.len(), 101);
        assert!(lines[51].starts_with("still,1,0.100000,1,"));
        std::fs::remove_dir_all(dir).ok();
    }
}
