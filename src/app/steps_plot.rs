//! steps.svg, the plot `stickslip run` keeps beside steps.csv: energy, Newton and CG
//! iterations and the CG tolerances per step, drawn with plotters' SVG backend (text as
//! SVG `<text>`, so no system fonts are needed). The run redraws it from the whole
//! steps.csv ([`crate::sim::driver::StepsPlot`]), so a resumed run's plot covers every step.

use crate::sim::driver::StepsPlot;
use plotters::coord::Shift;
use plotters::prelude::*;
use std::ops::Range;

const ENERGY: RGBColor = RGBColor(31, 119, 180);
const NEWTON: RGBColor = RGBColor(255, 127, 14);
const CG: RGBColor = RGBColor(44, 160, 44);
const LOOSEST: RGBColor = RGBColor(214, 39, 40);
const TIGHTEST: RGBColor = RGBColor(148, 103, 189);

/// Why steps.svg could not be drawn.
#[derive(Debug, thiserror::Error)]
pub enum StepsPlotError {
    #[error("steps.csv has no header")]
    NoHeader,
    #[error("steps.csv has no column `{0}`")]
    MissingColumn(&'static str),
    #[error("steps.csv line {line}: column `{column}` is `{value}`, not a number")]
    NotANumber {
        line: usize,
        column: &'static str,
        value: String,
    },
    #[error("drawing steps.svg: {0}")]
    Draw(String),
}

/// The columns of steps.csv that steps.svg shows, one entry per row.
#[derive(Debug, Default, PartialEq)]
pub struct StepColumns {
    pub step: Vec<f64>,
    pub energy: Vec<f64>,
    pub newton_iterations: Vec<f64>,
    pub linear_iterations: Vec<f64>,
    pub cg_tol_loosest: Vec<f64>,
    pub cg_tol_tightest: Vec<f64>,
}

const COLUMNS: [&str; 6] = [
    "step",
    "energy",
    "newton_iterations",
    "linear_iterations",
    "cg_tol_loosest",
    "cg_tol_tightest",
];

impl StepColumns {
    /// Reads steps.csv's text; a last line without its newline (a row being written)
    /// is left out.
    pub fn parse(text: &str) -> Result<StepColumns, StepsPlotError> {
        let mut lines = text.split_inclusive('\n');
        let header = lines.next().ok_or(StepsPlotError::NoHeader)?;
        let names: Vec<&str> = header.trim_end().split(',').collect();
        let mut at = [0usize; 6];
        for (k, c) in COLUMNS.iter().enumerate() {
            at[k] = names
                .iter()
                .position(|n| n == c)
                .ok_or(StepsPlotError::MissingColumn(c))?;
        }
        let mut out = StepColumns::default();
        for (i, line) in lines.enumerate() {
            if !line.ends_with('\n') {
                break;
            }
            let fields: Vec<&str> = line.trim_end().split(',').collect();
            let mut row = [0.0f64; 6];
            for (k, c) in COLUMNS.iter().enumerate() {
                let raw = fields.get(at[k]).copied().unwrap_or("");
                row[k] = raw.parse().map_err(|_| StepsPlotError::NotANumber {
                    line: i + 2,
                    column: c,
                    value: raw.to_string(),
                })?;
            }
            out.step.push(row[0]);
            out.energy.push(row[1]);
            out.newton_iterations.push(row[2]);
            out.linear_iterations.push(row[3]);
            out.cg_tol_loosest.push(row[4]);
            out.cg_tol_tightest.push(row[5]);
        }
        Ok(out)
    }
}

/// Draws steps.svg for `stickslip run`.
#[derive(Debug, Clone, Copy, Default)]
pub struct StepsSvg;

impl StepsPlot for StepsSvg {
    fn draw(&self, steps_csv: &str) -> Result<String, Box<dyn std::error::Error + Send + Sync>> {
        Ok(steps_svg(&StepColumns::parse(steps_csv)?)?)
    }
}

fn draw_err<E: std::error::Error + Send + Sync>(e: DrawingAreaErrorKind<E>) -> StepsPlotError {
    StepsPlotError::Draw(e.to_string())
}

/// (step, value) of the rows whose value is positive (a log axis shows no zero: row 0,
/// and the CG columns of direct solves).
fn positive(steps: &[f64], values: &[f64]) -> Vec<(f64, f64)> {
    steps
        .iter()
        .zip(values)
        .filter(|(_, v)| v.is_finite() && **v > 0.0)
        .map(|(s, v)| (*s, *v))
        .collect()
}

/// A log axis around the positive `values` (a decade when there are none).
fn log_range(values: impl Iterator<Item = f64>, empty: Range<f64>) -> Range<f64> {
    let (lo, hi) = values.fold((f64::INFINITY, 0.0f64), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    if lo.is_finite() {
        lo / 2.0..hi * 2.0
    } else {
        empty
    }
}

/// A linear axis around the finite `values`, with a margin (a unit span when flat).
fn linear_range(values: &[f64]) -> Range<f64> {
    let finite = values.iter().copied().filter(|v| v.is_finite());
    let (lo, hi) = finite.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    if !lo.is_finite() {
        return 0.0..1.0;
    }
    let pad = if hi > lo {
        0.05 * (hi - lo)
    } else {
        0.5 * lo.abs().max(1.0)
    };
    lo - pad..hi + pad
}

/// The SVG text of steps.svg: three panels over the step, energy (one marker per row),
/// Newton and CG iterations (log), the CG tolerances (log).
pub fn steps_svg(c: &StepColumns) -> Result<String, StepsPlotError> {
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (760, 900)).into_drawing_area();
        root.fill(&WHITE).map_err(draw_err)?;
        let last = c.step.iter().copied().fold(0.0f64, f64::max);
        let steps = 0.0..last.max(1.0);
        let panels = root.split_evenly((3, 1));
        energy_panel(&panels[0], c, steps.clone())?;
        let iterations = [
            ("Newton iterations", NEWTON, &c.newton_iterations[..]),
            ("CG iterations", CG, &c.linear_iterations[..]),
        ];
        log_panel(
            &panels[1],
            "iterations per step",
            &iterations,
            c,
            steps.clone(),
        )?;
        let tolerances = [
            ("cg_tol_loosest", LOOSEST, &c.cg_tol_loosest[..]),
            ("cg_tol_tightest", TIGHTEST, &c.cg_tol_tightest[..]),
        ];
        log_panel(&panels[2], "CG tolerances", &tolerances, c, steps)?;
        root.present().map_err(draw_err)?;
    }
    Ok(svg)
}

fn energy_panel(
    area: &DrawingArea<SVGBackend, Shift>,
    c: &StepColumns,
    steps: Range<f64>,
) -> Result<(), StepsPlotError> {
    let mut chart = ChartBuilder::on(area)
        .caption("mechanical energy", ("sans-serif", 16))
        .margin(10)
        .x_label_area_size(30)
        .y_label_area_size(80)
        .build_cartesian_2d(steps, linear_range(&c.energy))
        .map_err(draw_err)?;
    chart
        .configure_mesh()
        .x_desc("step")
        .y_desc("J")
        .y_label_formatter(&|v| format!("{v:.3e}"))
        .draw()
        .map_err(draw_err)?;
    let pts: Vec<(f64, f64)> = c
        .step
        .iter()
        .copied()
        .zip(c.energy.iter().copied())
        .collect();
    chart
        .draw_series(LineSeries::new(pts.clone(), ENERGY.stroke_width(1)))
        .map_err(draw_err)?;
    chart
        .draw_series(pts.into_iter().map(|p| Circle::new(p, 2, ENERGY.filled())))
        .map_err(draw_err)?;
    Ok(())
}

/// A series of a log panel: its label, colour and (step, value) points.
type Series<'a> = (&'a str, RGBColor, Vec<(f64, f64)>);

/// A panel of positive per-step series on a log axis, lines only (the energy panel's
/// markers are the plot's one point per row).
fn log_panel(
    area: &DrawingArea<SVGBackend, Shift>,
    caption: &str,
    series: &[(&str, RGBColor, &[f64])],
    c: &StepColumns,
    steps: Range<f64>,
) -> Result<(), StepsPlotError> {
    let pts: Vec<Series> = series
        .iter()
        .map(|(name, color, v)| (*name, *color, positive(&c.step, v)))
        .collect();
    let y = log_range(pts.iter().flat_map(|s| s.2.iter().map(|p| p.1)), 0.1..10.0);
    let empty = pts.iter().all(|s| s.2.is_empty());
    let caption = if empty {
        format!("{caption} (none: no CG solve)")
    } else {
        caption.to_string()
    };
    let mut chart = ChartBuilder::on(area)
        .caption(caption, ("sans-serif", 16))
        .margin(10)
        .x_label_area_size(30)
        .y_label_area_size(80)
        .build_cartesian_2d(steps, y.log_scale())
        .map_err(draw_err)?;
    chart
        .configure_mesh()
        .x_desc("step")
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .draw()
        .map_err(draw_err)?;
    for (name, color, p) in pts.into_iter().filter(|s| !s.2.is_empty()) {
        chart
            .draw_series(LineSeries::new(p, color.stroke_width(2)))
            .map_err(draw_err)?
            .label(name)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2))
            });
    }
    if !empty {
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(draw_err)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    const CSV: &str =
        "step,time,newton_iterations,linear_iterations,energy,cg_tol_loosest,cg_tol_tightest\n\
        0,0,0,0,1.5,0,0\n\
        1,0.01,3,40,1.25,1e-2,1e-6\n\
        2,0.02,2,30,1.0,1e-3,1e-5\n\
        3,0.03,2,2";

    #[test]
    fn reads_the_plotted_columns_and_leaves_out_a_partial_row() {
        let c = StepColumns::parse(CSV).expect("parses");
        assert_eq!(c.step, vec![0.0, 1.0, 2.0]);
        assert_eq!(c.energy, vec![1.5, 1.25, 1.0]);
        assert_eq!(c.linear_iterations, vec![0.0, 40.0, 30.0]);
        assert_eq!(c.cg_tol_tightest, vec![0.0, 1e-6, 1e-5]);
    }

    #[test]
    fn a_missing_column_or_a_bad_number_is_named() {
        let e = StepColumns::parse("step,energy\n0,1\n").unwrap_err();
        assert!(matches!(
            e,
            StepsPlotError::MissingColumn("newton_iterations")
        ));
        let bad = CSV.replace("1,0.01,3,40", "1,0.01,x,40");
        let e = StepColumns::parse(&bad).unwrap_err().to_string();
        assert!(
            e.contains("line 3") && e.contains("newton_iterations"),
            "{e}"
        );
    }

    #[test]
    fn one_marker_per_row() {
        let svg = steps_svg(&StepColumns::parse(CSV).expect("parses")).expect("draws");
        assert_eq!(svg.matches("<circle").count(), 3);
        assert!(svg.trim_end().ends_with("</svg>"));
    }
}
