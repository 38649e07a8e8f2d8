//! SVG plots of the benchmark, drawn with plotters' SVG backend (text is written as SVG
//! `<text>`, so no system fonts are needed).

use crate::app::bench::record::BenchReport;
use plotters::prelude::*;
use std::path::Path;

const COLORS: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
];

/// Errors below this are drawn at it (the oracle's own error is 0 by definition).
const ERROR_FLOOR: f64 = 1e-16;

fn bounds(vals: impl Iterator<Item = f64>) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
    for v in vals.filter(|v| v.is_finite() && *v > 0.0) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() {
        return (1e-3, 1.0);
    }
    (lo / 2.0, hi * 2.0)
}

/// One log-log plot with a line and markers per series, legend in a box.
pub(crate) fn log_log_plot(
    path: &Path,
    caption: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[(String, Vec<(f64, f64)>)],
) -> Result<(), String> {
    // Drawn into memory, then written atomically (no half-written SVG under its name).
    let mut svg = String::new();
    draw(&mut svg, caption, x_desc, y_desc, series)?;
    crate::io::files::write_atomic_bytes(path, svg.as_bytes())
        .map_err(|e| format!("{}: {e}", path.display()))
}

fn draw(
    svg: &mut String,
    caption: &str,
    x_desc: &str,
    y_desc: &str,
    series: &[(String, Vec<(f64, f64)>)],
) -> Result<(), String> {
    let root = SVGBackend::with_string(svg, (720, 480)).into_drawing_area();
    root.fill(&WHITE).map_err(|e| e.to_string())?;
    let (x0, x1) = bounds(series.iter().flat_map(|s| s.1.iter().map(|p| p.0)));
    let (y0, y1) = bounds(series.iter().flat_map(|s| s.1.iter().map(|p| p.1)));
    let mut chart = ChartBuilder::on(&root)
        .caption(caption, ("sans-serif", 18))
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())
        .map_err(|e| e.to_string())?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(y_desc)
        .x_label_formatter(&|v| format!("{v:.0e}"))
        .y_label_formatter(&|v| format!("{v:.0e}"))
        .draw()
        .map_err(|e| e.to_string())?;
    for (k, (label, pts)) in series.iter().enumerate() {
        let c = COLORS[k % COLORS.len()];
        chart
            .draw_series(LineSeries::new(pts.clone(), c.stroke_width(2)))
            .map_err(|e| e.to_string())?
            .label(label.as_str())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], c.stroke_width(2)));
        chart
            .draw_series(pts.iter().map(|&p| Circle::new(p, 3, c.filled())))
            .map_err(|e| e.to_string())?;
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .draw()
        .map_err(|e| e.to_string())?;
    root.present().map_err(|e| e.to_string())
}

/// One plot per (dimension, size): total seconds against the relative error reached.
pub fn time_vs_error(report: &BenchReport, dir: &Path) -> Result<(), String> {
    let mut sizes: Vec<(usize, usize)> = report.runs.iter().map(|r| (r.dim, r.nodes)).collect();
    sizes.sort_unstable();
    sizes.dedup();
    for (dim, nodes) in sizes {
        let runs: Vec<_> = report
            .runs
            .iter()
            .filter(|r| r.dim == dim && r.nodes == nodes && r.converged)
            .collect();
        let mut solvers: Vec<String> = runs.iter().map(|r| r.solver.clone()).collect();
        solvers.sort();
        solvers.dedup();
        let series: Vec<(String, Vec<(f64, f64)>)> = solvers
            .into_iter()
            .map(|s| {
                let mut pts: Vec<(f64, f64)> = runs
                    .iter()
                    .filter(|r| r.solver == s)
                    .map(|r| (r.relative_error.max(ERROR_FLOOR), r.total_seconds))
                    .collect();
                pts.sort_by(|a, b| a.0.total_cmp(&b.0));
                (s, pts)
            })
            .collect();
        log_log_plot(
            &dir.join(format!("time_vs_error_{dim}d_{nodes}.svg")),
            &format!("{dim}D, {nodes} nodes: time to reach an error"),
            "relative error of Δx (vs oracle)",
            "seconds",
            &series,
        )?;
    }
    Ok(())
}

/// One plot per dimension: seconds per CG iteration against the node count.
pub fn time_vs_size(report: &BenchReport, dir: &Path) -> Result<(), String> {
    let mut dims: Vec<usize> = report.scaling.iter().map(|f| f.dim).collect();
    dims.sort_unstable();
    dims.dedup();
    for dim in dims {
        let series: Vec<(String, Vec<(f64, f64)>)> = report
            .scaling
            .iter()
            .filter(|f| f.dim == dim && f.quantity == "seconds_per_iteration")
            .map(|f| {
                (
                    format!("{} (slope {:.2})", f.solver, f.slope),
                    f.points.iter().map(|p| (p.0 as f64, p.1)).collect(),
                )
            })
            .collect();
        if series.is_empty() {
            continue;
        }
        log_log_plot(
            &dir.join(format!("time_vs_size_{dim}d.svg")),
            &format!("{dim}D: seconds per CG iteration"),
            "nodes",
            "seconds per iteration",
            &series,
        )?;
    }
    Ok(())
}
