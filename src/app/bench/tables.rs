//! Step 5 of the ladder benchmark, the report: the tables derived from the runs (which
//! solver reaches each error first, the log-log scaling slopes), the plain-text summary,
//! and bench.json, bench.csv and the plots.

use crate::app::bench::record::{BenchReport, ScalingFit, Winner};
use std::path::Path;

/// Fills the winner and scaling tables from the runs.
pub fn derive_tables(report: &mut BenchReport) {
    let mut sizes: Vec<(usize, usize)> = report.runs.iter().map(|r| (r.dim, r.nodes)).collect();
    sizes.sort_unstable();
    sizes.dedup();
    for &(dim, nodes) in &sizes {
        for target in [1e-4, 1e-6, 1e-8, 1e-10] {
            let best = report
                .runs
                .iter()
                .filter(|r| {
                    r.dim == dim && r.nodes == nodes && r.converged && r.relative_error <= target
                })
                .min_by(|a, b| a.total_seconds.total_cmp(&b.total_seconds));
            if let Some(b) = best {
                report.winners.push(Winner {
                    dim,
                    nodes,
                    target_error: target,
                    solver: b.solver.clone(),
                    seconds: b.total_seconds,
                });
            }
        }
    }
    let mut solvers: Vec<(usize, String)> = report
        .runs
        .iter()
        .filter(|r| r.solver != "cholesky")
        .map(|r| (r.dim, r.solver.clone()))
        .collect();
    solvers.sort();
    solvers.dedup();
    for (dim, solver) in solvers {
        for quantity in ["seconds_per_iteration", "seconds_to_1e-6_error"] {
            let mut points = Vec::new();
            for &(d, nodes) in sizes.iter().filter(|s| s.0 == dim) {
                let runs = report.runs.iter().filter(|r| {
                    r.dim == d && r.nodes == nodes && r.solver == solver && r.converged
                });
                let v = if quantity == "seconds_per_iteration" {
                    runs.filter(|r| r.seconds_per_iteration > 0.0)
                        .map(|r| r.seconds_per_iteration)
                        .fold(f64::NAN, f64::min)
                } else {
                    runs.filter(|r| r.relative_error <= 1e-6)
                        .map(|r| r.total_seconds)
                        .fold(f64::NAN, f64::min)
                };
                if v.is_finite() && v > 0.0 {
                    points.push((nodes, v));
                }
            }
            if points.len() >= 2 {
                report.scaling.push(ScalingFit {
                    dim,
                    solver: solver.clone(),
                    quantity: quantity.to_string(),
                    slope: loglog_slope(&points),
                    points,
                });
            }
        }
    }
}

/// Least-squares slope of ln(y) against ln(x).
pub fn loglog_slope(points: &[(usize, f64)]) -> f64 {
    let n = points.len() as f64;
    let xs: Vec<f64> = points.iter().map(|p| (p.0 as f64).ln()).collect();
    let ys: Vec<f64> = points.iter().map(|p| p.1.ln()).collect();
    let mx = xs.iter().sum::<f64>() / n;
    let my = ys.iter().sum::<f64>() / n;
    let sxy: f64 = xs.iter().zip(&ys).map(|(x, y)| (x - mx) * (y - my)).sum();
    let sxx: f64 = xs.iter().map(|x| (x - mx) * (x - mx)).sum();
    sxy / sxx
}

/// The plain-text summary tables.
pub fn summary_text(report: &BenchReport) -> String {
    let mut s = String::new();
    s.push_str(&format!(
        "adapter: {}   CPU threads: {}   host copy bandwidth: {:.1} GB/s   GPU copy bandwidth: {}\n",
        report.adapter.as_deref().unwrap_or("none"),
        report.cpu_threads,
        report.cpu_copy_gb_per_s,
        report
            .gpu_copy_gb_per_s
            .map_or("-".to_string(), |b| format!("{b:.1} GB/s"))
    ));
    s.push_str("\nCholesky (faer): symbolic / numeric / solve / refactor with reused analysis\n");
    for c in &report.cholesky {
        s.push_str(&format!(
            "  {}D {:>8} nodes  {:>8.3} s  {:>8.3} s  {:>8.3} s  {:>8.3} s  nnz(L) {} ({})\n",
            c.dim,
            c.nodes,
            c.symbolic_seconds,
            c.numeric_seconds,
            c.solve_seconds,
            c.reused_numeric_seconds,
            c.factor_nnz,
            c.ordering
        ));
    }
    s.push_str("\nFirst to reach a relative error (total seconds)\n");
    for w in &report.winners {
        s.push_str(&format!(
            "  {}D {:>8} nodes  error ≤ {:.0e}: {:<16} {:.4} s\n",
            w.dim, w.nodes, w.target_error, w.solver, w.seconds
        ));
    }
    s.push_str("\nScaling (log-log slope against nodes)\n");
    for f in &report.scaling {
        s.push_str(&format!(
            "  {}D {:<16} {:<24} slope {:.2}\n",
            f.dim, f.solver, f.quantity, f.slope
        ));
    }
    s
}

/// bench.json, bench.csv and the SVG plots in `dir`.
pub fn write_outputs(report: &BenchReport, dir: &Path) -> std::io::Result<()> {
    std::fs::create_dir_all(dir)?;
    crate::io::files::write_atomic_bytes(
        dir.join("bench.json"),
        serde_json::to_string_pretty(report)
            .map_err(std::io::Error::other)?
            .as_bytes(),
    )?;
    let mut csv = String::from("dim,nodes,dofs,solver,precision,tol,converged,iterations,recorded_iterations,relative_residual,relative_error,error_reference,setup_seconds,solve_seconds,total_seconds,gpu_seconds,bytes_per_iteration,achieved_gb_per_s,seconds_per_iteration,bandwidth_floor_ratio,peak_rss_bytes\n");
    for r in &report.runs {
        csv.push_str(&format!(
            "{},{},{},{},{},{},{},{},{},{:e},{:e},{},{:e},{:e},{:e},{},{},{:e},{:e},{:e},{}\n",
            r.dim,
            r.nodes,
            r.dofs,
            r.solver,
            r.precision,
            r.tol.map_or(String::new(), |t| format!("{t:e}")),
            r.converged,
            r.iterations,
            r.recorded_iterations
                .map_or(String::new(), |v| v.to_string()),
            r.relative_residual,
            r.relative_error,
            r.error_reference,
            r.setup_seconds,
            r.solve_seconds,
            r.total_seconds,
            r.gpu_seconds.map_or(String::new(), |t| format!("{t:e}")),
            r.bytes_per_iteration,
            r.achieved_gb_per_s,
            r.seconds_per_iteration,
            r.bandwidth_floor_ratio,
            r.peak_rss_bytes
        ));
    }
    crate::io::files::write_atomic_bytes(dir.join("bench.csv"), csv.as_bytes())?;
    crate::app::bench::plots::time_vs_error(report, dir).map_err(std::io::Error::other)?;
    crate::app::bench::plots::time_vs_size(report, dir).map_err(std::io::Error::other)?;
    Ok(())
}
