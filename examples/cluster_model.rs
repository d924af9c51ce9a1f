//! The cluster scaling model (`sylva::systems::cluster::model`) on the frame costs
//! measured here: frames per second of the `paper` scene on N nodes of c cores over
//! gigabit, 10-gigabit and InfiniBand networks, as a table and a plot beside the seed
//! paper's cluster figures.
//!
//! `cargo run --release --example cluster_model -- COSTS.csv PLOT.png`, where COSTS.csv
//! holds one row per quality preset: `preset,tile_work_s,serial_s,frame_bytes,
//! node_efficiency,tiles,message_wait_s` (benches/README.md says how each figure was
//! measured), and optionally rows `check,PRESET,RANKS,CORES,MEASURED_S` of runs on this
//! machine to hold the model against.

use plotters::prelude::*;
use std::path::Path;
use sylva::systems::cluster::model::{FrameCosts, Network};

/// The seed paper's measured cluster rates: (CPUs, frames per second, what).
const SEED: [(usize, f64, &str); 3] = [
    (32, 1.0, "seed: still, 32 CPUs"),
    (32, 6.0, "seed: interactive, 32 CPUs"),
    (48, 1.47, "seed: still, 48 CPUs"),
];

const NETWORKS: [(&str, Network); 3] = [
    ("1 GbE", Network::GIGABIT),
    ("10 GbE", Network::TEN_GIGABIT),
    ("InfiniBand", Network::INFINIBAND),
];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [costs_path, plot_path] = args.as_slice() else {
        return Err("usage: cluster_model COSTS.csv PLOT.png".into());
    };
    let (presets, checks) = read_costs(Path::new(costs_path))?;
    println!(
        "| preset | ranks × threads here | measured s/frame | model s/frame | model / measured |"
    );
    println!("|---|---|---|---|---|");
    for check in &checks {
        let costs = presets
            .iter()
            .find(|(name, _)| *name == check.preset)
            .ok_or_else(|| format!("no costs for preset {}", check.preset))?
            .1;
        let model = costs
            .estimate_on_one_node(check.ranks, check.cores)
            .seconds();
        println!(
            "| {} | {} × {} | {:.3} | {:.3} | {:.2} |",
            check.preset,
            check.ranks,
            check.cores / check.ranks.min(check.cores),
            check.measured,
            model,
            model / check.measured
        );
    }
    println!();
    for (name, costs) in &presets {
        println!("{name}: {costs:?}");
        println!("| nodes × cores | cores | 1 GbE fps | 10 GbE fps | InfiniBand fps |");
        println!("|---|---|---|---|---|");
        for (nodes, cores) in [
            (1, 2),
            (2, 2),
            (4, 2),
            (16, 2),
            (24, 2),
            (8, 8),
            (4, 16),
            (16, 16),
            (8, 64),
            (32, 64),
        ] {
            let fps: Vec<String> = NETWORKS
                .iter()
                .map(|(_, net)| format!("{:.2}", costs.estimate(nodes, cores, net).fps()))
                .collect();
            println!(
                "| {nodes} × {cores} | {} | {} |",
                nodes * cores,
                fps.join(" | ")
            );
        }
        println!();
    }
    plot(Path::new(plot_path), &presets)?;
    println!("wrote {plot_path}");
    Ok(())
}

/// A run on this machine to hold the model against.
struct Check {
    preset: String,
    ranks: usize,
    cores: usize,
    measured: f64,
}

/// Presets and their costs, and the checks.
type Costs = (Vec<(String, FrameCosts)>, Vec<Check>);

fn read_costs(path: &Path) -> Result<Costs, Box<dyn std::error::Error>> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let (mut presets, mut checks) = (Vec::new(), Vec::new());
    for (line_number, line) in text.lines().enumerate().skip(1) {
        if line.trim().is_empty() {
            continue;
        }
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        let number = |i: usize| -> Result<f64, String> {
            fields
                .get(i)
                .and_then(|f| f.parse::<f64>().ok())
                .ok_or_else(|| {
                    format!(
                        "{}:{}: field {} is not a number",
                        path.display(),
                        line_number + 1,
                        i + 1
                    )
                })
        };
        if fields[0] == "check" {
            checks.push(Check {
                preset: fields.get(1).copied().unwrap_or_default().to_owned(),
                ranks: number(2)? as usize,
                cores: number(3)? as usize,
                measured: number(4)?,
            });
            continue;
        }
        presets.push((
            fields[0].to_owned(),
            FrameCosts {
                tile_work: number(1)?,
                serial: number(2)?,
                frame_bytes: number(3)?,
                node_efficiency: number(4)?,
                tiles: number(5)? as usize,
                message_wait: number(6)?,
                run_tiles: 4,
            },
        ));
    }
    Ok((presets, checks))
}

fn plot(path: &Path, presets: &[(String, FrameCosts)]) -> Result<(), Box<dyn std::error::Error>> {
    const FONT: &str = "sans-serif";
    let _ = plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular());
    let (width, height) = (900u32, 560u32);
    let mut buffer = vec![0u8; width as usize * height as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (width, height)).into_drawing_area();
        root.fill(&WHITE)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(
                "paper scene, 640×480: modelled frame rate on N nodes of 2 cores",
                (FONT, 18),
            )
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(56)
            .build_cartesian_2d((2f64..256f64).log_scale(), (0.1f64..40f64).log_scale())?;
        chart
            .configure_mesh()
            .x_desc("cores (2 per node)")
            .y_desc("frames per second")
            .label_style((FONT, 13))
            .x_label_formatter(&|v| format!("{v:.0}"))
            .y_label_formatter(&|v| format!("{v}"))
            .draw()?;
        let colours = [
            RGBColor(0, 114, 178),
            RGBColor(213, 94, 0),
            RGBColor(0, 158, 115),
            RGBColor(204, 121, 167),
            RGBColor(230, 159, 0),
            RGBColor(86, 180, 233),
        ];
        let mut colour = colours.iter().cycle();
        for (name, costs) in presets {
            for (network, net) in NETWORKS.iter().take(2) {
                let c = *colour.next().expect("the palette cycles");
                let points = (1..=128).map(|nodes| {
                    let fps = costs.estimate(nodes, 2, net).fps();
                    ((2 * nodes) as f64, fps)
                });
                chart
                    .draw_series(LineSeries::new(points, c.stroke_width(2)))?
                    .label(format!("Sylva {name}, {network}"))
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 18, y)], c.stroke_width(2))
                    });
            }
        }
        for (cpus, fps, what) in SEED {
            let c = RGBColor(0, 0, 0);
            chart
                .draw_series(std::iter::once(Cross::new(
                    (cpus as f64, fps),
                    7,
                    c.stroke_width(2),
                )))?
                .label(what)
                .legend(move |(x, y)| Cross::new((x + 9, y), 5, c.stroke_width(2)));
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .label_font((FONT, 13))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()?;
        root.present()?;
    }
    image::RgbImage::from_raw(width, height, buffer)
        .expect("the buffer holds width × height RGB pixels")
        .save(path)?;
    Ok(())
}
