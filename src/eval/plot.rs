//! The paper's per-phase figures: the training curve (from the policy's `metrics.csv`) beside a
//! representative evaluation rollout (payload height and tilt over time), and the monolithic
//! baseline's reward and entropy curves beside the phase policies'.

use std::path::Path;

use anyhow::{bail, Context, Result};
use moonhaul_core::input::{read_capped_text, MAX_RUN_LOG_BYTES};
use moonhaul_core::plot_font::FAMILY;
use plotters::coord::Shift;
use plotters::prelude::*;

use super::episode::EpisodeRow;

/// One training iteration as a figure needs it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CurvePoint {
    pub env_steps: f64,
    pub mean_return: Option<f64>,
    pub eval_return: Option<f64>,
    pub entropy: f64,
}

/// Reads the columns a figure needs from a trainer's `metrics.csv` (by header name, so the
/// file's other columns may change); errors name the file and line.
pub fn read_curve(path: &Path) -> Result<Vec<CurvePoint>> {
    let text = read_capped_text(path, MAX_RUN_LOG_BYTES)?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines
        .next()
        .with_context(|| format!("{}: empty", path.display()))?
        .split(',')
        .collect();
    let column = |name: &str| {
        header
            .iter()
            .position(|h| *h == name)
            .with_context(|| format!("{}: no column {name}", path.display()))
    };
    let (steps, mean, eval, entropy) = (
        column("env_steps")?,
        column("mean_return")?,
        column("eval_return")?,
        column("entropy")?,
    );
    let mut points = Vec::new();
    for (k, line) in lines.enumerate() {
        let fields: Vec<&str> = line.split(',').collect();
        let field = |i: usize| -> Result<Option<f64>> {
            let text = fields.get(i).copied().unwrap_or("");
            if text.is_empty() {
                return Ok(None);
            }
            let v: f64 = text.parse().with_context(|| {
                format!(
                    "{}: line {}, column {}: {text:?}",
                    path.display(),
                    k + 2,
                    header[i]
                )
            })?;
            if !v.is_finite() {
                bail!(
                    "{}: line {}, column {}: not finite",
                    path.display(),
                    k + 2,
                    header[i]
                );
            }
            Ok(Some(v))
        };
        let required = |i: usize| {
            field(i)?.with_context(|| {
                format!(
                    "{}: line {}, column {}: empty",
                    path.display(),
                    k + 2,
                    header[i]
                )
            })
        };
        points.push(CurvePoint {
            env_steps: required(steps)?,
            mean_return: field(mean)?,
            eval_return: field(eval)?,
            entropy: required(entropy)?,
        });
    }
    Ok(points)
}

fn range(values: impl Iterator<Item = f64>, min_span: f64) -> (f64, f64) {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    if !lo.is_finite() {
        return (0.0, min_span);
    }
    let hi = hi.max(lo + min_span);
    let pad = 0.05 * (hi - lo);
    (lo - pad, hi + pad)
}

type Series<'a> = (&'a str, Vec<(f64, f64)>, RGBColor);

/// One line chart with a legend.
fn chart(
    area: &DrawingArea<BitMapBackend, Shift>,
    title: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[Series],
    min_span: f64,
) -> Result<()> {
    let x = range(series.iter().flat_map(|s| s.1.iter().map(|p| p.0)), 1.0);
    let y = range(
        series.iter().flat_map(|s| s.1.iter().map(|p| p.1)),
        min_span,
    );
    let mut chart = ChartBuilder::on(area)
        .caption(title, (FAMILY, 20))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(80)
        .build_cartesian_2d(x.0.max(0.0)..x.1, y.0..y.1)?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(y_desc)
        .label_style((FAMILY, 14))
        .axis_desc_style((FAMILY, 15))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()?;
    for (name, points, color) in series {
        let color = *color;
        chart
            .draw_series(LineSeries::new(
                points.iter().copied(),
                color.stroke_width(2),
            ))?
            .label(*name)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
            });
    }
    chart
        .configure_series_labels()
        .label_font((FAMILY, 14))
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()?;
    Ok(())
}

const COLORS: [RGBColor; 4] = [BLUE, RED, RGBColor(0, 140, 0), RGBColor(150, 0, 150)];

/// `path`: the training curve of `phase` (left; empty when `curve` is) beside the rollout's
/// payload height with its goal (top right) and tilt (bottom right).
pub fn phase_figure(
    path: &Path,
    phase: &str,
    curve: &[CurvePoint],
    rollout: &[EpisodeRow],
) -> Result<()> {
    moonhaul_core::plot_font::register().map_err(anyhow::Error::msg)?;
    let root = BitMapBackend::new(path, (1500, 700)).into_drawing_area();
    root.fill(&WHITE)?;
    let (left, right) = root.split_horizontally(700);
    let returns: Vec<Series> = vec![
        (
            "mean training return",
            curve
                .iter()
                .filter_map(|p| p.mean_return.map(|r| (p.env_steps, r)))
                .collect(),
            COLORS[0],
        ),
        (
            "deterministic evaluation return",
            curve
                .iter()
                .filter_map(|p| p.eval_return.map(|r| (p.env_steps, r)))
                .collect(),
            COLORS[1],
        ),
    ];
    chart(
        &left,
        &format!("{phase}: PPO training"),
        "environment steps (unit rows)",
        "return",
        &returns,
        1.0,
    )?;
    let (top, bottom) = right.split_vertically(350);
    let height: Vec<Series> = vec![
        (
            "payload height",
            rollout
                .iter()
                .map(|r| (r.t_s, r.payload_height_m))
                .collect(),
            COLORS[0],
        ),
        (
            "goal height",
            rollout.iter().map(|r| (r.t_s, r.goal_height_m)).collect(),
            COLORS[2],
        ),
    ];
    chart(
        &top,
        &format!("{phase}: representative rollout"),
        "time (s)",
        "height (m)",
        &height,
        0.1,
    )?;
    let tilt: Vec<Series> = vec![(
        "payload tilt",
        rollout
            .iter()
            .map(|r| (r.t_s, r.payload_tilt_deg))
            .collect(),
        COLORS[1],
    )];
    chart(&bottom, "", "time (s)", "tilt (deg)", &tilt, 1.0)?;
    root.present()?;
    Ok(())
}

/// `path`: mean training return (left) and policy entropy (right) over environment steps for
/// every named run, e.g. the three phase policies and the monolithic baseline.
pub fn comparison_figure(path: &Path, runs: &[(&str, Vec<CurvePoint>)]) -> Result<()> {
    moonhaul_core::plot_font::register().map_err(anyhow::Error::msg)?;
    let root = BitMapBackend::new(path, (1500, 600)).into_drawing_area();
    root.fill(&WHITE)?;
    let (left, right) = root.split_horizontally(750);
    let pick = |f: fn(&CurvePoint) -> Option<f64>| -> Vec<Series> {
        runs.iter()
            .zip(COLORS.iter().cycle())
            .map(|((name, points), color)| {
                (
                    *name,
                    points
                        .iter()
                        .filter_map(|p| f(p).map(|v| (p.env_steps, v)))
                        .collect(),
                    *color,
                )
            })
            .collect()
    };
    chart(
        &left,
        "mean training return",
        "environment steps (unit rows)",
        "return",
        &pick(|p| p.mean_return),
        1.0,
    )?;
    chart(
        &right,
        "policy entropy",
        "environment steps (unit rows)",
        "entropy (nats)",
        &pick(|p| Some(p.entropy)),
        1.0,
    )?;
    root.present()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn curves_read_by_column_name_and_bad_lines_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.csv");
        std::fs::write(
            &path,
            "iteration,env_steps,mean_return,eval_return,entropy\n1,10,,,-3\n2,20,-5,-4,-2.5\n",
        )
        .unwrap();
        let curve = read_curve(&path).unwrap();
        assert_eq!(curve.len(), 2);
        assert_eq!(curve[0].mean_return, None);
        assert_eq!(
            (curve[1].env_steps, curve[1].eval_return),
            (20.0, Some(-4.0))
        );
        std::fs::write(&path, "env_steps,mean_return,eval_return,entropy\n1,x,,0\n").unwrap();
        let err = format!("{:#}", read_curve(&path).unwrap_err());
        assert!(
            err.contains("line 2") && err.contains("mean_return"),
            "{err}"
        );
        std::fs::write(&path, "env_steps,eval_return,entropy\n").unwrap();
        let err = format!("{:#}", read_curve(&path).unwrap_err());
        assert!(err.contains("no column mean_return"), "{err}");
        let png = dir.path().join("f.png");
        phase_figure(&png, "lift", &curve, &[]).unwrap();
        comparison_figure(&png, &[("lift", curve)]).unwrap();
        assert!(std::fs::metadata(&png).unwrap().len() > 1000);
    }
}
