//! `--profile FILE.csv` on `render`, `animate` and `view` (a [`CliProfile`] around the
//! library's `ProfileLog`), and `sylva profile`: the picture of a profile — stage times
//! stacked over the frames, and a heat map of the last frame's tile render times.

use super::check_parent_dir;
use super::plot::{FONT, PALETTE, register_font};
use anyhow::{Context, Result, bail};
use bevy_ecs::world::World;
use clap::Args;
use plotters::prelude::*;
use std::path::{Path, PathBuf};
use std::time::Duration;
use sylva::systems::profile::{FrameProfiler, ProfileLog, STAGES, tiles_path};

/// A run's profile as the CLI keeps it: a write failure is reported once and ends the
/// profile, never the render.
pub(crate) struct CliProfile {
    log: Option<ProfileLog>,
    path: PathBuf,
}

/// Opens the profile `path` (a `.csv` in an existing directory), errors naming it.
pub(crate) fn open_profile(path: &Path) -> Result<ProfileLog> {
    if !path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("csv"))
    {
        bail!(
            "--profile {}: the profile is written as CSV; name it FILE.csv",
            path.display()
        );
    }
    check_parent_dir(path)?;
    ProfileLog::create(path)
        .with_context(|| format!("{}: cannot write the profile", path.display()))
}

/// Writes the last rows and the tile times of `log` (written to `path`), and prints the
/// summary table unless `quiet`; a failure is a warning.
pub(crate) fn finish_profile(log: &mut ProfileLog, path: &Path, quiet: bool) {
    match log.finish() {
        Ok(tiles) => {
            if !quiet {
                print!("{}", log.summary());
                let tiles = tiles.map_or(String::new(), |t| format!(", tiles {}", t.display()));
                println!(
                    "profile: {}{tiles} (plot it with `sylva profile {}`)",
                    path.display(),
                    path.display()
                );
            }
        }
        Err(e) => eprintln!(
            "warning: {}: {e}; the profile is incomplete",
            path.display()
        ),
    }
}

impl CliProfile {
    /// Turns profiling on in `world` and opens `path` when given.
    pub(crate) fn start(world: &mut World, path: Option<&Path>) -> Result<Option<Self>> {
        let Some(path) = path else {
            return Ok(None);
        };
        let log = open_profile(path)?;
        world.insert_resource(FrameProfiler::enabled());
        Ok(Some(Self {
            log: Some(log),
            path: path.to_owned(),
        }))
    }

    /// Adds the frame the schedule has just run.
    pub(crate) fn record(&mut self, world: &World) {
        if let Some(log) = &mut self.log
            && let Err(e) = log.record(world)
        {
            eprintln!(
                "warning: {}: {e}; the profile stops here (the render goes on)",
                self.path.display()
            );
            self.log = None;
        }
    }

    /// Adds time spent writing the last frame's results.
    pub(crate) fn add_write(&mut self, time: Duration) {
        if let Some(log) = &mut self.log {
            log.add_write(time);
        }
    }

    /// Writes the last rows and the tile times, and prints the summary table unless
    /// `quiet`.
    pub(crate) fn finish(mut self, quiet: bool) {
        if let Some(log) = &mut self.log {
            finish_profile(log, &self.path, quiet);
        }
    }
}

/// `sylva profile`: plot a profile written with `--profile`.
#[derive(Args, Debug)]
pub(crate) struct ProfileArgs {
    /// The profile (CSV from `--profile`); its tile times are read from NAME.tiles.csv
    /// beside it when present.
    csv: PathBuf,
    /// The plot to write (PNG).
    #[arg(long, short, default_value = "profile.png")]
    out: PathBuf,
}

/// One frame's stage times (ms), as read back from the CSV.
struct StageRow {
    stages: Vec<f64>,
}

/// Reads the stage columns and the program's write time of every frame.
fn read_stage_rows(path: &Path) -> Result<(Vec<String>, Vec<StageRow>)> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read", path.display()))?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines
        .next()
        .with_context(|| format!("{}: empty file", path.display()))?
        .split(',')
        .collect();
    let mut names: Vec<String> = STAGES.iter().map(|s| s.to_string()).collect();
    names.push("write".to_owned());
    let columns: Vec<usize> = names
        .iter()
        .enumerate()
        .map(|(k, name)| {
            let column = if k < STAGES.len() {
                format!("stage_{name}_ms")
            } else {
                format!("{name}_ms")
            };
            header.iter().position(|h| *h == column).with_context(|| {
                format!(
                    "{}: no column {column}: not a profile written by --profile",
                    path.display()
                )
            })
        })
        .collect::<Result<_>>()?;
    let mut rows = Vec::new();
    for (number, line) in lines.enumerate() {
        let fields: Vec<&str> = line.split(',').collect();
        if fields.len() != header.len() {
            bail!(
                "{}:{}: {} fields where the header has {}",
                path.display(),
                number + 2,
                fields.len(),
                header.len()
            );
        }
        let stages = columns
            .iter()
            .map(|&c| {
                let field = fields[c];
                if field.is_empty() {
                    return Ok(0.0);
                }
                field
                    .parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite() && *v >= 0.0)
                    .with_context(|| {
                        format!(
                            "{}:{}: {}: '{field}' is not a time in ms",
                            path.display(),
                            number + 2,
                            header[c]
                        )
                    })
            })
            .collect::<Result<_>>()?;
        rows.push(StageRow { stages });
    }
    if rows.is_empty() {
        bail!("{}: the profile has no frames", path.display());
    }
    Ok((names, rows))
}

/// One tile's place and render time.
struct TileTime {
    x: u32,
    y: u32,
    width: u32,
    height: u32,
    ms: f64,
}

fn read_tiles(path: &Path) -> Result<Vec<TileTime>> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read", path.display()))?;
    text.lines()
        .enumerate()
        .skip(1)
        .map(|(number, line)| {
            let f: Vec<&str> = line.split(',').collect();
            let bad = || format!("{}:{}: not x,y,width,height,ms", path.display(), number + 1);
            if f.len() != 5 {
                bail!(bad());
            }
            let int = |s: &str| s.parse::<u32>().ok();
            match (
                int(f[0]),
                int(f[1]),
                int(f[2]),
                int(f[3]),
                f[4].parse::<f64>().ok(),
            ) {
                (Some(x), Some(y), Some(width), Some(height), Some(ms))
                    if ms.is_finite() && ms >= 0.0 && width > 0 && height > 0 =>
                {
                    Ok(TileTime {
                        x,
                        y,
                        width,
                        height,
                        ms,
                    })
                }
                _ => bail!(bad()),
            }
        })
        .collect()
}

/// A perceptual dark-blue → yellow ramp for `t` in [0, 1] (viridis-like, five stops).
fn heat(t: f64) -> RGBColor {
    const STOPS: [(f64, f64, f64); 5] = [
        (68.0, 1.0, 84.0),
        (59.0, 82.0, 139.0),
        (33.0, 145.0, 140.0),
        (94.0, 201.0, 98.0),
        (253.0, 231.0, 37.0),
    ];
    let t = t.clamp(0.0, 1.0) * 4.0;
    let i = (t.floor() as usize).min(3);
    let f = t - i as f64;
    let (a, b) = (STOPS[i], STOPS[i + 1]);
    let mix = |p: f64, q: f64| (p + (q - p) * f).round() as u8;
    RGBColor(mix(a.0, b.0), mix(a.1, b.1), mix(a.2, b.2))
}

/// Runs `sylva profile`.
pub(crate) fn run(args: ProfileArgs) -> Result<()> {
    if !args
        .out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("png"))
    {
        bail!(
            "--out {}: the plot is a PNG; name it FILE.png",
            args.out.display()
        );
    }
    check_parent_dir(&args.out)?;
    let (names, rows) = read_stage_rows(&args.csv)?;
    let tiles_file = tiles_path(&args.csv);
    let tiles = if tiles_file.exists() {
        read_tiles(&tiles_file)?
    } else {
        Vec::new()
    };
    plot_profile(&args.out, &names, &rows, &tiles)
        .with_context(|| format!("{}: could not draw the plot", args.out.display()))?;
    println!(
        "wrote {} ({} frames{})",
        args.out.display(),
        rows.len(),
        if tiles.is_empty() {
            String::new()
        } else {
            format!(", {} tiles of the last frame", tiles.len())
        }
    );
    Ok(())
}

fn plot_profile(out: &Path, names: &[String], rows: &[StageRow], tiles: &[TileTime]) -> Result<()> {
    register_font();
    let (width, height) = (960u32, if tiles.is_empty() { 420 } else { 840 });
    let mut buffer = vec![0u8; width as usize * height as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| anyhow::anyhow!("{e}"))?;
        let (top, bottom) = if tiles.is_empty() {
            (root.clone(), None)
        } else {
            let (a, b) = root.split_vertically(420);
            (a, Some(b))
        };
        // Stacked: the band of stage k lies between the sums of stages < k and ≤ k.
        let cumulative: Vec<Vec<f64>> = rows
            .iter()
            .map(|r| {
                r.stages
                    .iter()
                    .scan(0.0, |sum, v| {
                        *sum += v;
                        Some(*sum)
                    })
                    .collect()
            })
            .collect();
        let peak = cumulative
            .iter()
            .filter_map(|c| c.last().copied())
            .fold(0.0f64, f64::max)
            .max(1e-3);
        let frames = rows.len();
        let mut chart = ChartBuilder::on(&top)
            .caption("stage times per frame (stacked)", (FONT, 18))
            .margin(12)
            .x_label_area_size(36)
            .y_label_area_size(60)
            .build_cartesian_2d(0f64..(frames.max(2) - 1) as f64, 0f64..peak * 1.1)
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        chart
            .configure_mesh()
            .x_labels(frames.clamp(2, 11))
            .x_label_formatter(&|v| format!("{v:.0}"))
            .x_desc("frame")
            .y_desc("ms")
            .label_style((FONT, 13))
            .draw()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        for k in (0..names.len()).rev() {
            let colour = PALETTE[k % PALETTE.len()];
            let upper: Vec<(f64, f64)> = cumulative
                .iter()
                .enumerate()
                .map(|(i, c)| (i as f64, c[k]))
                .collect();
            let mut band = upper.clone();
            band.extend(
                cumulative
                    .iter()
                    .enumerate()
                    .rev()
                    .map(|(i, c)| (i as f64, if k == 0 { 0.0 } else { c[k - 1] })),
            );
            if frames == 1 {
                // One frame: a bar instead of a band of no width.
                let (lo, hi) = (band[1].1, upper[0].1);
                band = vec![(0.0, lo), (0.0, hi), (1.0, hi), (1.0, lo)];
            }
            chart
                .draw_series(std::iter::once(Polygon::new(band, colour.filled())))
                .map_err(|e| anyhow::anyhow!("{e}"))?
                .label(names[k].as_str())
                .legend(move |(x, y)| {
                    Rectangle::new([(x, y - 5), (x + 14, y + 5)], colour.filled())
                });
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .label_font((FONT, 13))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()
            .map_err(|e| anyhow::anyhow!("{e}"))?;

        if let Some(bottom) = bottom {
            let image_w = tiles.iter().map(|t| t.x + t.width).max().unwrap_or(1);
            let image_h = tiles.iter().map(|t| t.y + t.height).max().unwrap_or(1);
            let slowest = tiles.iter().map(|t| t.ms).fold(0.0f64, f64::max).max(1e-6);
            let fastest = tiles.iter().map(|t| t.ms).fold(f64::INFINITY, f64::min);
            let caption = format!(
                "tile render time, last frame: {fastest:.2} ms (dark) to {slowest:.2} ms (yellow)"
            );
            // The image's aspect ratio kept: the map centred in the panel below a caption.
            let (panel_w, panel_h) = bottom.dim_in_pixel();
            let (room_w, room_h) = (f64::from(panel_w) - 24.0, f64::from(panel_h) - 48.0);
            let scale = (room_w / f64::from(image_w)).min(room_h / f64::from(image_h));
            let (map_w, map_h) = (f64::from(image_w) * scale, f64::from(image_h) * scale);
            let side = ((f64::from(panel_w) - map_w) / 2.0).max(0.0) as u32;
            let below = (f64::from(panel_h) - 36.0 - map_h).max(0.0) as u32;
            let area = bottom.margin(0, below, side, side);
            let mut map = ChartBuilder::on(&area)
                .caption(caption, (FONT, 16))
                .build_cartesian_2d(0u32..image_w, image_h..0u32)
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            map.draw_series(tiles.iter().map(|t| {
                Rectangle::new(
                    [(t.x, t.y), (t.x + t.width, t.y + t.height)],
                    heat(t.ms / slowest).filled(),
                )
            }))
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        }
        root.present().map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    let image = image::RgbImage::from_raw(width, height, buffer)
        .expect("the buffer holds width × height RGB pixels");
    image.save(out)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_heat_ramp_runs_from_dark_blue_to_yellow() {
        assert_eq!(heat(0.0), RGBColor(68, 1, 84));
        assert_eq!(heat(1.0), RGBColor(253, 231, 37));
        assert_eq!(heat(2.0), heat(1.0));
        let brightness = |c: RGBColor| u32::from(c.0) + u32::from(c.1) + u32::from(c.2);
        assert!(
            (0..10).all(
                |i| brightness(heat(i as f64 / 10.0)) < brightness(heat((i + 1) as f64 / 10.0))
            )
        );
    }
}
