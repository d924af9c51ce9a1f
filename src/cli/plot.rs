//! Log–log error-against-time plots as PNG: plotters on an in-memory bitmap, text in the
//! embedded DejaVu Sans (no system font libraries), encoded with the image crate.

use plotters::prelude::*;
use std::path::Path;
use std::sync::Once;
use sylva::systems::converge::ErrorSample;

/// Why a plot could not be written.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// Drawing failed.
    #[error("{path}: could not draw the plot: {message}")]
    Draw {
        /// The plot's path.
        path: String,
        /// What plotters said.
        message: String,
    },
    /// Encoding or writing the PNG failed.
    #[error("{path}: {source}")]
    Write {
        /// The plot's path.
        path: String,
        /// The encoder's error.
        source: image::ImageError,
    },
}

/// The font family name the plots use.
pub(crate) const FONT: &str = "sans-serif";

pub(crate) fn register_font() {
    static REGISTER: Once = Once::new();
    REGISTER.call_once(|| {
        // The bytes are a valid TrueType font shipped in the dejavu crate.
        let _ = plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular());
    });
}

/// Distinct colours for up to eight curves (Okabe–Ito, readable by colour-blind viewers).
pub(crate) const PALETTE: [RGBColor; 8] = [
    RGBColor(0, 114, 178),
    RGBColor(213, 94, 0),
    RGBColor(0, 158, 115),
    RGBColor(204, 121, 167),
    RGBColor(230, 159, 0),
    RGBColor(86, 180, 233),
    RGBColor(0, 0, 0),
    RGBColor(240, 228, 66),
];

/// A short tick label: `0.02`, `0.5`, `3`, `40`.
fn compact(v: f64) -> String {
    if v >= 10.0 {
        format!("{v:.0}")
    } else {
        let text = format!("{v:.3}");
        text.trim_end_matches('0').trim_end_matches('.').to_string()
    }
}

/// Writes a `width × height` PNG plotting relMSE against time on log–log axes, one curve
/// per `(name, samples)`.
pub fn plot_error_vs_time(
    path: &Path,
    title: &str,
    curves: &[(String, Vec<ErrorSample>)],
    (width, height): (u32, u32),
) -> Result<(), PlotError> {
    register_font();
    let label = path.display().to_string();
    let draw_error = |e: &dyn std::fmt::Display| PlotError::Draw {
        path: label.clone(),
        message: e.to_string(),
    };
    let points: Vec<(f64, f64)> = curves
        .iter()
        .flat_map(|(_, s)| s.iter())
        .filter(|s| s.time_s > 0.0 && s.relmse > 0.0 && s.relmse.is_finite())
        .map(|s| (s.time_s, s.relmse))
        .collect();
    let range = |values: &mut dyn Iterator<Item = f64>| {
        let (lo, hi) = values.fold((f64::INFINITY, 0f64), |(lo, hi), v| (lo.min(v), hi.max(v)));
        if lo.is_finite() && hi > lo {
            (lo / 1.5, hi * 1.5)
        } else {
            (1e-3, 1.0)
        }
    };
    let (t0, t1) = range(&mut points.iter().map(|p| p.0));
    let (e0, e1) = range(&mut points.iter().map(|p| p.1));

    let mut buffer = vec![0u8; width as usize * height as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| draw_error(&e))?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, (FONT, 18))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(64)
            .build_cartesian_2d((t0..t1).log_scale(), (e0..e1).log_scale())
            .map_err(|e| draw_error(&e))?;
        chart
            .configure_mesh()
            .x_desc("wall time (s)")
            .y_desc("relMSE")
            .label_style((FONT, 13))
            .x_labels(6)
            .y_labels(8)
            .x_label_formatter(&|v| compact(*v))
            .y_label_formatter(&|v| format!("{v:.0e}"))
            .draw()
            .map_err(|e| draw_error(&e))?;
        for (i, (name, samples)) in curves.iter().enumerate() {
            let colour = PALETTE[i % PALETTE.len()];
            let series = samples
                .iter()
                .filter(|s| s.time_s > 0.0 && s.relmse > 0.0 && s.relmse.is_finite())
                .map(|s| (s.time_s, s.relmse));
            chart
                .draw_series(LineSeries::new(series, colour.stroke_width(2)))
                .map_err(|e| draw_error(&e))?
                .label(name)
                .legend(move |(x, y)| {
                    PathElement::new(vec![(x, y), (x + 18, y)], colour.stroke_width(2))
                });
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .label_font((FONT, 13))
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()
            .map_err(|e| draw_error(&e))?;
        root.present().map_err(|e| draw_error(&e))?;
    }
    let image = image::RgbImage::from_raw(width, height, buffer)
        .expect("the buffer holds width × height RGB pixels");
    image.save(path).map_err(|source| PlotError::Write {
        path: path.display().to_string(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_plot_has_curves_and_text_in_their_colours() {
        let dir = std::env::temp_dir().join(format!("sylva-plot-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("p.png");
        let curve = |scale: f64| -> Vec<ErrorSample> {
            (1..=20)
                .map(|i| ErrorSample {
                    frame: i,
                    time_s: i as f64 * 0.2,
                    spp: u64::from(i),
                    rmse: 0.0,
                    relmse: scale / i as f64,
                })
                .collect()
        };
        let curves = vec![
            ("a".to_string(), curve(0.1)),
            ("b".to_string(), curve(0.01)),
        ];
        plot_error_vs_time(&path, "test", &curves, (480, 320)).unwrap();
        let image = image::open(&path).unwrap().to_rgb8();
        assert_eq!(image.dimensions(), (480, 320));
        let count = |c: RGBColor| image.pixels().filter(|p| p.0 == [c.0, c.1, c.2]).count();
        assert!(count(PALETTE[0]) > 200 && count(PALETTE[1]) > 200);
        // The title was drawn: dark pixels in the top rows, above the chart's frame.
        let dark = (0..480)
            .flat_map(|x| (0..28).map(move |y| (x, y)))
            .filter(|&(x, y)| image.get_pixel(x, y).0.iter().all(|&v| v < 100))
            .count();
        assert!(dark > 40, "{dark} dark title pixels");
        std::fs::remove_dir_all(dir).ok();
    }
}
