//! System-level profiling: per frame, the wall time of each stage and of each of Sylva's
//! systems, each tile's render time, and the counters that explain them, logged as CSV
//! rows ([`ProfileLog`]) and summarised (mean, p50, p95, share of the frame).
//!
//! A [`FrameProfiler`] resource that is [enabled](FrameProfiler::enabled) makes the
//! systems time themselves (two clock reads each) and the schedule's stage boundaries
//! note the time; a disabled one (the default) costs a branch per system.

use crate::{RenderStats, TopLevelState};
use bevy_ecs::prelude::*;
use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::time::{Duration, Instant};
use sylva_engine::bvh::TraversalStats;
use sylva_engine::film::Tile;

/// The stages of a frame in order, as the profile names them (the `RenderSystems` sets).
pub const STAGES: [&str; 7] = [
    "animate",
    "prepare",
    "plan",
    "render",
    "accumulate",
    "display",
    "output",
];

/// Sylva's systems that time themselves, in schedule order.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ProfiledSystem {
    /// `animate`.
    Animate,
    /// `rebase_world_origin`.
    RebaseWorldOrigin,
    /// `rebuild_top_level` (a refit or a rebuild).
    RebuildTopLevel,
    /// `compile_shaders`.
    CompileShaders,
    /// `compile_lights`.
    CompileLights,
    /// `build_opacity_maps`.
    BuildOpacityMaps,
    /// `adaptive_transparency_lod`.
    AdaptiveTransparencyLod,
    /// `assign_light_subsets`.
    AssignLightSubsets,
    /// `render_tiles`.
    RenderTiles,
    /// `accumulate`.
    Accumulate,
    /// `filter_display`.
    FilterDisplay,
    /// `publish_frame_images`.
    PublishFrameImages,
}

impl ProfiledSystem {
    /// Every profiled system, in schedule order.
    pub const ALL: [ProfiledSystem; 12] = [
        Self::Animate,
        Self::RebaseWorldOrigin,
        Self::RebuildTopLevel,
        Self::CompileShaders,
        Self::CompileLights,
        Self::BuildOpacityMaps,
        Self::AdaptiveTransparencyLod,
        Self::AssignLightSubsets,
        Self::RenderTiles,
        Self::Accumulate,
        Self::FilterDisplay,
        Self::PublishFrameImages,
    ];

    /// The system's function name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Animate => "animate",
            Self::RebaseWorldOrigin => "rebase_world_origin",
            Self::RebuildTopLevel => "rebuild_top_level",
            Self::CompileShaders => "compile_shaders",
            Self::CompileLights => "compile_lights",
            Self::BuildOpacityMaps => "build_opacity_maps",
            Self::AdaptiveTransparencyLod => "adaptive_transparency_lod",
            Self::AssignLightSubsets => "assign_light_subsets",
            Self::RenderTiles => "render_tiles",
            Self::Accumulate => "accumulate",
            Self::FilterDisplay => "filter_display",
            Self::PublishFrameImages => "publish_frame_images",
        }
    }
}

const SYSTEMS: usize = ProfiledSystem::ALL.len();
const MARKS: usize = STAGES.len() + 1;

/// Collects one frame's times while the schedule runs; [`take`](Self::take) hands them
/// over and starts the next frame's.
#[derive(Resource, Debug)]
pub struct FrameProfiler {
    enabled: bool,
    epoch: Instant,
    /// Nanoseconds since `epoch` at each stage boundary, plus one (0: not reached).
    marks: [AtomicU64; MARKS],
    /// Nanoseconds each system ran this frame.
    systems: [AtomicU64; SYSTEMS],
    /// Bit `i`: system `i` ran this frame.
    ran: AtomicU32,
    tiles: Mutex<Vec<(Tile, Duration)>>,
}

impl Default for FrameProfiler {
    /// A disabled profiler: systems do not read the clock.
    fn default() -> Self {
        Self {
            enabled: false,
            epoch: Instant::now(),
            marks: Default::default(),
            systems: Default::default(),
            ran: AtomicU32::new(0),
            tiles: Mutex::default(),
        }
    }
}

/// Records a system's wall time when dropped.
pub struct SystemTimer<'a> {
    profiler: &'a FrameProfiler,
    system: ProfiledSystem,
    start: Instant,
}

impl Drop for SystemTimer<'_> {
    fn drop(&mut self) {
        let index = self.system as usize;
        let nanos = self.start.elapsed().as_nanos() as u64;
        self.profiler.systems[index].fetch_add(nanos, Ordering::Relaxed);
        self.profiler.ran.fetch_or(1 << index, Ordering::Relaxed);
    }
}

/// One frame's times as the profiler saw them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FrameTimes {
    /// Wall time of each stage ([`STAGES`]); `None` when its boundaries were not both
    /// reached (a schedule without the profiler's marks).
    pub stages: [Option<Duration>; 7],
    /// Wall time of each system ([`ProfiledSystem::ALL`]); `None` when it did not run.
    pub systems: [Option<Duration>; SYSTEMS],
    /// Each tile's render time, in the order the tiles finished.
    pub tiles: Vec<(Tile, Duration)>,
}

impl FrameTimes {
    /// The schedule's wall time: from the first stage's start to the last one's end.
    pub fn schedule(&self) -> Duration {
        self.stages.iter().flatten().sum()
    }
}

impl FrameProfiler {
    /// A profiler that times every frame.
    pub fn enabled() -> Self {
        Self {
            enabled: true,
            ..Self::default()
        }
    }

    /// True when systems time themselves.
    pub fn is_enabled(&self) -> bool {
        self.enabled
    }

    /// A guard that adds the time until it is dropped to `system`'s; `None` when
    /// disabled.
    #[inline]
    pub fn time(&self, system: ProfiledSystem) -> Option<SystemTimer<'_>> {
        self.enabled.then(|| SystemTimer {
            profiler: self,
            system,
            start: Instant::now(),
        })
    }

    /// Notes the time at stage boundary `boundary` (0: before the first stage, `k`:
    /// after stage `k − 1`).
    pub(crate) fn mark(&self, boundary: usize) {
        if self.enabled {
            let nanos = self.epoch.elapsed().as_nanos() as u64 + 1;
            self.marks[boundary].store(nanos, Ordering::Relaxed);
        }
    }

    /// Notes one tile's render time.
    pub(crate) fn tile(&self, tile: Tile, time: Duration) {
        if self.enabled
            && let Ok(mut tiles) = self.tiles.lock()
        {
            tiles.push((tile, time));
        }
    }

    /// The times collected since the last call, which start over.
    pub fn take(&self) -> FrameTimes {
        let marks = self.marks.each_ref().map(|m| m.swap(0, Ordering::Relaxed));
        let ran = self.ran.swap(0, Ordering::Relaxed);
        let mut times = FrameTimes::default();
        for (k, stage) in times.stages.iter_mut().enumerate() {
            if marks[k] > 0 && marks[k + 1] >= marks[k] {
                *stage = Some(Duration::from_nanos(marks[k + 1] - marks[k]));
            }
        }
        for (i, system) in times.systems.iter_mut().enumerate() {
            let nanos = self.systems[i].swap(0, Ordering::Relaxed);
            if ran & (1 << i) != 0 {
                *system = Some(Duration::from_nanos(nanos));
            }
        }
        if let Ok(mut tiles) = self.tiles.lock() {
            times.tiles = std::mem::take(&mut *tiles);
        }
        times
    }
}

/// The stage-boundary system `K` of the schedule (see `FrameProfiler::mark`).
pub fn mark_stage<const K: usize>(profiler: Res<FrameProfiler>) {
    profiler.mark(K);
}

/// Run condition of the stage marks.
pub fn profiling(profiler: Res<FrameProfiler>) -> bool {
    profiler.is_enabled()
}

/// What the top level did in a frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TopLevelAction {
    /// Nothing: no plant moved.
    Kept,
    /// Transforms moved and the tree was refitted.
    Refit,
    /// The tree was rebuilt.
    Rebuild,
}

impl TopLevelAction {
    fn name(self) -> &'static str {
        match self {
            Self::Kept => "kept",
            Self::Refit => "refit",
            Self::Rebuild => "rebuild",
        }
    }
}

/// One profiled frame.
#[derive(Clone, Debug)]
pub struct ProfileRow {
    /// Frame number within the run, from 0.
    pub frame: u64,
    /// Stage and system times.
    pub times: FrameTimes,
    /// Time the program spent on the frame's results after the schedule (writing
    /// images), if it said.
    pub write: Duration,
    /// The frame's traversal counters.
    pub counters: TraversalStats,
    /// What the top level did.
    pub top_level: TopLevelAction,
}

impl ProfileRow {
    /// The frame's wall time: the schedule's and the program's writing.
    pub fn wall(&self) -> Duration {
        self.times.schedule() + self.write
    }
}

/// A run's profile: one row per frame, written to a CSV file as it goes (a killed run
/// keeps every finished frame), and a summary at the end.
pub struct ProfileLog {
    rows: Vec<ProfileRow>,
    /// Rows already in the file (the last row stays open for [`add_write`](Self::add_write)
    /// until the next frame or [`finish`](Self::finish)).
    written: usize,
    writer: Option<(PathBuf, std::io::BufWriter<std::fs::File>)>,
    top_level_seen: (u64, u64),
    last_tiles: Vec<(Tile, Duration)>,
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// The CSV file's columns, in order.
pub fn csv_header() -> String {
    let mut header = String::from("frame,wall_ms");
    for stage in STAGES {
        let _ = write!(header, ",stage_{stage}_ms");
    }
    header.push_str(",write_ms");
    for system in ProfiledSystem::ALL {
        let _ = write!(header, ",{}_ms", system.name());
    }
    header.push_str(
        ",top_level,camera_rays,shadow_rays,nodes_per_ray,primitives_per_ray,alpha_tests,texture_alpha_tests,holes_passed,holes_made_opaque",
    );
    header
}

impl ProfileLog {
    /// A profile kept in memory only.
    pub fn in_memory() -> Self {
        Self {
            rows: Vec::new(),
            written: 0,
            writer: None,
            top_level_seen: (0, 0),
            last_tiles: Vec::new(),
        }
    }

    /// A profile written to the CSV file `path` (its header first).
    pub fn create(path: &Path) -> std::io::Result<Self> {
        let file = std::fs::File::create(path)?;
        let mut writer = std::io::BufWriter::new(file);
        writeln!(writer, "{}", csv_header())?;
        writer.flush()?;
        Ok(Self {
            writer: Some((path.to_owned(), writer)),
            ..Self::in_memory()
        })
    }

    /// The rows so far.
    pub fn rows(&self) -> &[ProfileRow] {
        &self.rows
    }

    /// Each tile's render time in the last frame that rendered tiles.
    pub fn last_tiles(&self) -> &[(Tile, Duration)] {
        &self.last_tiles
    }

    /// Adds the frame the schedule has just run in `world` (its [`FrameProfiler`]'s
    /// times, the render counters and what the top level did) and writes the frame before
    /// it to the file. The new row stays open for [`add_write`](Self::add_write).
    pub fn record(&mut self, world: &World) -> std::io::Result<()> {
        let times = world
            .get_resource::<FrameProfiler>()
            .map(FrameProfiler::take)
            .unwrap_or_default();
        let rendered = times.systems[ProfiledSystem::RenderTiles as usize].is_some();
        let counters = match world.get_resource::<RenderStats>() {
            Some(stats) if rendered => stats.last_frame,
            _ => TraversalStats::default(),
        };
        let top_level = match world.get_resource::<TopLevelState>() {
            Some(state) => {
                let (rebuilds, refits) = self.top_level_seen;
                self.top_level_seen = (state.rebuilds, state.refits);
                if state.rebuilds > rebuilds {
                    TopLevelAction::Rebuild
                } else if state.refits > refits {
                    TopLevelAction::Refit
                } else {
                    TopLevelAction::Kept
                }
            }
            None => TopLevelAction::Kept,
        };
        if !times.tiles.is_empty() {
            self.last_tiles.clone_from(&times.tiles);
        }
        let row = ProfileRow {
            frame: self.rows.len() as u64,
            times,
            write: Duration::ZERO,
            counters,
            top_level,
        };
        self.write_rows()?;
        self.rows.push(row);
        Ok(())
    }

    /// Adds `time`, spent by the program on the last frame's results (writing images),
    /// to that frame.
    pub fn add_write(&mut self, time: Duration) {
        if let Some(row) = self.rows.last_mut() {
            row.write += time;
        }
    }

    /// Writes the rows not yet in the file.
    fn write_rows(&mut self) -> std::io::Result<()> {
        if let Some((_, writer)) = &mut self.writer {
            for row in &self.rows[self.written..] {
                writeln!(writer, "{}", csv_row(row))?;
            }
            writer.flush()?;
        }
        self.written = self.rows.len();
        Ok(())
    }

    /// Writes the last row and the last frame's tile times (see
    /// [`write_tiles`](Self::write_tiles)); returns the tile file's path.
    pub fn finish(&mut self) -> std::io::Result<Option<PathBuf>> {
        self.write_rows()?;
        self.write_tiles()
    }

    /// Writes the last frame's tile times next to the CSV file (`NAME.tiles.csv`:
    /// x, y, width, height, ms) and returns its path; `None` in memory or without tiles.
    pub fn write_tiles(&self) -> std::io::Result<Option<PathBuf>> {
        let Some((path, _)) = &self.writer else {
            return Ok(None);
        };
        if self.last_tiles.is_empty() {
            return Ok(None);
        }
        let tiles_path = tiles_path(path);
        let mut text = String::from("x,y,width,height,ms\n");
        for (tile, time) in &self.last_tiles {
            let _ = writeln!(
                text,
                "{},{},{},{},{:.4}",
                tile.x,
                tile.y,
                tile.width,
                tile.height,
                ms(*time)
            );
        }
        std::fs::write(&tiles_path, text)?;
        Ok(Some(tiles_path))
    }

    /// The summary table: per stage, the program's writing and the whole frame, the
    /// mean, median and 95th percentile over the frames in ms, and the share of the
    /// mean frame.
    pub fn summary(&self) -> String {
        let frames = self.rows.len();
        let mut out = format!(
            "profile of {frames} frames (ms)\n{:<28} {:>9} {:>9} {:>9} {:>7}\n",
            "stage", "mean", "p50", "p95", "share"
        );
        if frames == 0 {
            return out;
        }
        let wall: Vec<f64> = self.rows.iter().map(|r| ms(r.wall())).collect();
        let wall_mean = mean(&wall);
        let mut line = |name: &str, values: Vec<f64>| {
            let (m, p50, p95) = (
                mean(&values),
                percentile(&values, 0.5),
                percentile(&values, 0.95),
            );
            let share = if wall_mean > 0.0 {
                m / wall_mean * 100.0
            } else {
                0.0
            };
            let _ = writeln!(
                out,
                "{name:<28} {m:>9.2} {p50:>9.2} {p95:>9.2} {share:>6.1}%"
            );
        };
        for (k, stage) in STAGES.iter().enumerate() {
            line(
                stage,
                self.rows
                    .iter()
                    .map(|r| r.times.stages[k].map_or(0.0, ms))
                    .collect(),
            );
            // The systems of the stage, indented under it, when any of them ran.
            for system in systems_of_stage(k) {
                let i = *system as usize;
                if self.rows.iter().any(|r| r.times.systems[i].is_some()) {
                    let values = self
                        .rows
                        .iter()
                        .map(|r| r.times.systems[i].map_or(0.0, ms))
                        .collect();
                    line(&format!("  {}", system.name()), values);
                }
            }
        }
        line(
            "write (program)",
            self.rows.iter().map(|r| ms(r.write)).collect(),
        );
        line("frame", wall);
        let refits = self
            .rows
            .iter()
            .filter(|r| r.top_level == TopLevelAction::Refit)
            .count();
        let rebuilds = self
            .rows
            .iter()
            .filter(|r| r.top_level == TopLevelAction::Rebuild)
            .count();
        let _ = writeln!(
            out,
            "top level: {rebuilds} rebuilds, {refits} refits, {} kept",
            frames - refits - rebuilds
        );
        out
    }
}

/// The systems in stage `k` of [`STAGES`].
fn systems_of_stage(k: usize) -> &'static [ProfiledSystem] {
    use ProfiledSystem::*;
    match k {
        0 => &[Animate],
        1 => &[
            RebaseWorldOrigin,
            RebuildTopLevel,
            CompileShaders,
            CompileLights,
        ],
        2 => &[
            BuildOpacityMaps,
            AdaptiveTransparencyLod,
            AssignLightSubsets,
        ],
        3 => &[RenderTiles],
        4 => &[Accumulate],
        5 => &[FilterDisplay],
        _ => &[PublishFrameImages],
    }
}

/// `profile.csv` → `profile.tiles.csv`.
pub fn tiles_path(csv: &Path) -> PathBuf {
    let stem = csv.file_stem().map_or_else(
        || "profile".to_owned(),
        |s| s.to_string_lossy().into_owned(),
    );
    csv.with_file_name(format!("{stem}.tiles.csv"))
}

fn csv_row(row: &ProfileRow) -> String {
    let mut line = format!("{},{:.4}", row.frame, ms(row.wall()));
    let optional = |d: Option<Duration>| d.map_or(String::new(), |d| format!("{:.4}", ms(d)));
    for stage in &row.times.stages {
        let _ = write!(line, ",{}", optional(*stage));
    }
    let _ = write!(line, ",{:.4}", ms(row.write));
    for system in &row.times.systems {
        let _ = write!(line, ",{}", optional(*system));
    }
    let c = &row.counters;
    let rays = c.rays().max(1) as f64;
    let _ = write!(
        line,
        ",{},{},{},{:.3},{:.3},{},{},{},{}",
        row.top_level.name(),
        c.closest_rays,
        c.any_rays,
        c.nodes_visited as f64 / rays,
        c.primitive_tests as f64 / rays,
        c.filter_tests,
        c.texture_alpha_tests,
        c.holes_passed,
        c.opaque_holes
    );
    line
}

fn mean(values: &[f64]) -> f64 {
    values.iter().sum::<f64>() / values.len().max(1) as f64
}

/// The `q` quantile of `values` (nearest rank).
fn percentile(values: &[f64], q: f64) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    sorted[rank - 1]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_are_nearest_rank() {
        let v: Vec<f64> = (1..=20).map(f64::from).collect();
        assert_eq!(percentile(&v, 0.5), 10.0);
        assert_eq!(percentile(&v, 0.95), 19.0);
        assert_eq!(percentile(&[3.0], 0.95), 3.0);
        assert_eq!(mean(&v), 10.5);
    }

    #[test]
    fn a_disabled_profiler_records_nothing_and_an_enabled_one_hands_over_once() {
        let off = FrameProfiler::default();
        assert!(off.time(ProfiledSystem::Accumulate).is_none());
        off.mark(0);
        assert_eq!(off.take(), FrameTimes::default());

        let on = FrameProfiler::enabled();
        for k in 0..MARKS {
            on.mark(k);
        }
        drop(on.time(ProfiledSystem::RenderTiles));
        on.tile(
            Tile {
                x: 0,
                y: 0,
                width: 4,
                height: 4,
            },
            Duration::from_millis(2),
        );
        let times = on.take();
        assert!(times.stages.iter().all(Option::is_some));
        assert!(times.systems[ProfiledSystem::RenderTiles as usize].is_some());
        assert!(times.systems[ProfiledSystem::Animate as usize].is_none());
        assert_eq!(times.tiles.len(), 1);
        assert_eq!(on.take(), FrameTimes::default(), "taken times start over");
    }

    #[test]
    fn the_csv_rows_have_the_headers_columns() {
        let columns = csv_header().split(',').count();
        let row = ProfileRow {
            frame: 3,
            times: FrameTimes::default(),
            write: Duration::from_millis(1),
            counters: TraversalStats::default(),
            top_level: TopLevelAction::Refit,
        };
        let line = csv_row(&row);
        assert_eq!(line.split(',').count(), columns, "{line}");
        assert!(line.contains(",refit,"));
        assert_eq!(
            tiles_path(Path::new("out/run.csv")),
            Path::new("out/run.tiles.csv")
        );
    }
}
