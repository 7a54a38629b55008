//! PNG learning curves (return and entropy against environment steps, the paper's training
//! figure), redrawn from `metrics.csv`'s rows after each evaluation.
//!
//! Text uses the bundled font of [`moonhaul_core::plot_font`].

use std::path::Path;

use plotters::prelude::*;

use crate::metrics::MetricsRow;
use crate::LearnError;

const SIZE_PX: (u32, u32) = (900, 540);

/// One curve: its legend, colour, and points; `markers` draws dots (sparse series).
struct Series {
    label: &'static str,
    color: RGBColor,
    points: Vec<(f64, f64)>,
    markers: bool,
}

/// Writes `return.png` and `entropy.png` into `dir`, as one group
/// ([`moonhaul_core::atomic_file::Group`]): a reader never sees a new plot beside an old one.
pub fn plot_curves(dir: &Path, rows: &[MetricsRow]) -> Result<(), LearnError> {
    let x = |r: &MetricsRow| r.env_steps as f64;
    let returns = vec![
        Series {
            label: "mean training return (stochastic policy)",
            color: RGBColor(31, 119, 180),
            points: rows
                .iter()
                .filter_map(|r| r.mean_return.map(|v| (x(r), v)))
                .collect(),
            markers: false,
        },
        Series {
            label: "evaluation return (deterministic policy)",
            color: RGBColor(214, 39, 40),
            points: rows
                .iter()
                .filter_map(|r| r.eval_return.map(|v| (x(r), v)))
                .collect(),
            markers: true,
        },
    ];
    let entropy = vec![Series {
        label: "policy entropy",
        color: RGBColor(44, 160, 44),
        points: rows.iter().map(|r| (x(r), r.entropy)).collect(),
        markers: false,
    }];
    let mut plots = moonhaul_core::atomic_file::Group::new(|path: &Path, e: std::io::Error| {
        LearnError::io(path)(e)
    });
    let return_png = dir.join("return.png");
    plots.stage(&return_png, |temp| {
        draw(&return_png, temp, "Episode return", "return", &returns)
    })?;
    let entropy_png = dir.join("entropy.png");
    plots.stage(&entropy_png, |temp| {
        draw(
            &entropy_png,
            temp,
            "Policy entropy",
            "entropy (nats)",
            &entropy,
        )
    })?;
    plots.publish()
}

/// Draws `series` into the file `temp`, which stands in for `path` (the name errors give).
fn draw(
    path: &Path,
    temp: &Path,
    title: &str,
    y_desc: &str,
    series: &[Series],
) -> Result<(), LearnError> {
    let fail = |reason: String| LearnError::Plot {
        path: path.to_path_buf(),
        reason,
    };
    moonhaul_core::plot_font::register().map_err(|e| fail(e.into()))?;
    let all = series.iter().flat_map(|s| s.points.iter());
    let (mut x_max, mut y_min, mut y_max) = (1.0f64, f64::INFINITY, f64::NEG_INFINITY);
    for &(x, y) in all {
        x_max = x_max.max(x);
        y_min = y_min.min(y);
        y_max = y_max.max(y);
    }
    if !(y_min.is_finite() && y_max.is_finite()) {
        (y_min, y_max) = (-1.0, 1.0);
    }
    let pad = ((y_max - y_min) * 0.05).max(1e-3);
    // plotters picks the image format from the extension, which the temporary keeps.
    let root = BitMapBackend::new(temp, SIZE_PX).into_drawing_area();
    let e = |e: DrawingAreaErrorKind<_>| fail(e.to_string());
    root.fill(&WHITE).map_err(e)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, (moonhaul_core::plot_font::FAMILY, 26))
        .margin(16)
        .x_label_area_size(50)
        .y_label_area_size(80)
        .build_cartesian_2d(0.0..x_max, (y_min - pad)..(y_max + pad))
        .map_err(e)?;
    chart
        .configure_mesh()
        .x_desc("environment steps")
        .y_desc(y_desc)
        .label_style((moonhaul_core::plot_font::FAMILY, 15))
        .draw()
        .map_err(e)?;
    for s in series {
        let color = s.color;
        chart
            .draw_series(LineSeries::new(
                s.points.iter().copied(),
                color.stroke_width(2),
            ))
            .map_err(e)?
            .label(s.label)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
            });
        if s.markers {
            let dots = s.points.iter().map(|&p| Circle::new(p, 3, color.filled()));
            chart.draw_series(dots).map_err(e)?;
        }
    }
    chart
        .configure_series_labels()
        .label_font((moonhaul_core::plot_font::FAMILY, 15))
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(SeriesLabelPosition::LowerRight)
        .draw()
        .map_err(e)?;
    root.present().map_err(e)
}
