//! The `sylva` command line: render a scene to PNG/EXR, print its statistics, measure
//! error against time, compare images. One module per subcommand under `cli/`; the
//! work itself lives in the library crates.

use clap::{Parser, Subcommand};

mod cli;

use cli::SceneArgs;
use cli::compare::CompareArgs;
use cli::converge::ConvergeArgs;
use cli::render::RenderArgs;

/// Sylva: a ray tracer for dense plant ecosystems.
///
/// Examples:
///   sylva render --out meadow.png
///   sylva render --width 1280 --height 720 --spp 16 --out meadow.exr
///   sylva render --scene forest --out forest.png
///   sylva render --scene my_ecosystem.toml --out mine.png
///   sylva render --gltf model.glb --camera 0 --out model.png
///   sylva animate --scene meadow --seconds 2 --fps 30 --out frames/frame_%04d.png
///   sylva render --scene forest --frames 8 --profile forest.csv
///   sylva profile forest.csv --out forest_profile.png
///   sylva info --scene paper
///   sylva view --scene forest
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
    /// Render an image sequence of the scene with its plants swaying in the wind (one
    /// image per 1/fps seconds, frame_%04d.png or .exr), resumable with --resume.
    Animate(Box<cli::animate::AnimateArgs>),
    /// Print a scene's statistics: species, triangles, instances, memory, build times.
    Info(SceneArgs),
    /// Measure error against wall time: render a converged reference (cached in the
    /// output directory), then run each sampling setting progressively and record RMSE
    /// and relMSE after every frame; writes error_vs_time.csv and error_vs_time.png and
    /// prints the time to reach relMSE 1e-2 and 1e-3 and the convergence slope.
    Converge(Box<ConvergeArgs>),
    /// Plot a profile written with --profile: stage times stacked over the frames, and a
    /// heat map of the last frame's tile render times.
    Profile(cli::profile::ProfileArgs),
    /// Print the error of linear images (.exr or .hdr) against a reference: RMSE and
    /// relMSE (mean of (I−R)²/(R²+0.01) over pixels and channels).
    Compare(CompareArgs),
    /// Open a window onto a scene: walk through it (WASD/arrows, drag to look, scroll for
    /// speed) at interactive quality, refining while the camera rests; --script flies a
    /// scripted walkthrough and saves screenshots.
    #[cfg(feature = "view")]
    View(Box<cli::view::ViewArgs>),
}

fn main() {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Render(args) => cli::render::run(*args),
        Command::Animate(args) => cli::animate::run(*args),
        Command::Info(args) => cli::info::run(args),
        Command::Compare(args) => cli::compare::run(args),
        Command::Profile(args) => cli::profile::run(args),
        Command::Converge(args) => cli::converge::run(*args),
        #[cfg(feature = "view")]
        Command::View(args) => cli::view::run(*args),
    };
    if let Err(e) = result {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
