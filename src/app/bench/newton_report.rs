//! What the Newton benchmark ([`crate::app::bench::newton`]) records, per size and
//! phase, and its report (step 5): the summary table, bench.json, bench.csv and
//! newton_phases.svg.

use serde::Serialize;
use std::path::Path;

/// Seconds per phase (median of the repetitions); None: the phase did not run.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct Phases {
    pub assembly: Option<f64>,
    pub elimination: Option<f64>,
    pub solve: Option<f64>,
    pub line_search: Option<f64>,
}

impl Phases {
    pub fn list(&self) -> [(&'static str, Option<f64>); 4] {
        [
            ("assembly", self.assembly),
            ("elimination", self.elimination),
            ("solve", self.solve),
            ("line_search", self.line_search),
        ]
    }

    /// Sum of the four phases; None when one is absent.
    pub fn total(&self) -> Option<f64> {
        self.list()
            .iter()
            .try_fold(0.0, |acc, (_, v)| v.map(|s| acc + s))
    }
}

/// One side (CPU or GPU) at one size.
#[derive(Debug, Clone, Default, Serialize)]
pub struct SideRecord {
    /// Whether this side ran at this size.
    pub ran: bool,
    pub seconds: Phases,
    pub total_seconds: Option<f64>,
    /// Why it did not run, or which phases are absent.
    pub note: String,
}

/// What the CPU's iteration computed (the same work every repetition).
#[derive(Debug, Clone, Default, Serialize)]
pub struct CpuCheck {
    pub cg_iterations: usize,
    /// ‖b̂ − Ĥy‖/‖b̂‖, recomputed by the CG at the end.
    pub relative_residual: f64,
    /// gᵀΔx (negative: a descent direction).
    pub slope: f64,
    /// E(x + Δx) − E(x).
    pub energy_change: f64,
}

/// The device CG's iteration (f64): what it launched and the bytes it must move, beside
/// the time per iteration (the median solve over its iterations). Dispatches, threads and
/// bytes do not depend on the machine; the bandwidth is those bytes over that time.
#[derive(Debug, Clone, Serialize)]
pub struct GpuCgRecord {
    pub iterations: usize,
    pub seconds_per_iteration: f64,
    pub bytes_per_iteration: u64,
    /// bytes_per_iteration / seconds_per_iteration, GB/s.
    pub gb_per_second: f64,
    pub dispatches_per_iteration: Vec<crate::gpu::pcg::DispatchRecord>,
}

/// The device's assembled system against the CPU's at the same iterate, as
/// max|device − CPU| / max|CPU| over the entries (both f64).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct AssemblyDifference {
    pub hessian: f64,
    pub gradient: f64,
}

/// One size of the ladder.
#[derive(Debug, Clone, Serialize)]
pub struct SizeRecord {
    /// k of the 4k × k × k cells.
    pub k: usize,
    pub nodes: usize,
    pub dofs: usize,
    pub tetrahedra: usize,
    /// Nodes with a sticky or slip condition, and free DOFs after elimination.
    pub constrained_nodes: usize,
    pub free_dofs: usize,
    pub cpu: SideRecord,
    pub gpu: SideRecord,
    /// GPU seconds / CPU seconds per phase (None when either is absent).
    pub ratio: Phases,
    pub ratio_total: Option<f64>,
    pub cpu_check: Option<CpuCheck>,
    pub gpu_cg: Option<GpuCgRecord>,
    pub gpu_assembly_difference: Option<AssemblyDifference>,
    /// The device side's profile over its warm-up and repetitions: wall seconds per phase
    /// (the device loop's phases, `gpu::profile`), device seconds from timestamps, host
    /// waits, passes and dispatches.
    pub gpu_profile: Option<crate::gpu::Profile>,
    /// Peak resident memory of the process after this size (VmHWM), bytes.
    pub peak_rss_bytes: u64,
}

/// Where and how it ran.
#[derive(Debug, Clone, Serialize)]
pub struct Machine {
    pub command: String,
    pub adapter: Option<String>,
    /// Cores the machine has.
    pub cpu_cores: usize,
    /// Worker threads of the CPU side (`--threads`, else RAYON_NUM_THREADS, else every core).
    pub threads: usize,
    /// MemAvailable at the start, bytes (0 where unknown).
    pub memory_available_bytes: u64,
}

#[derive(Debug, Clone, Serialize)]
pub struct NewtonReport {
    pub machine: Machine,
    /// Timed repetitions per phase after one warm-up; phase times are their medians.
    pub reps: usize,
    pub cg_tol: f64,
    pub preconditioner: String,
    pub precision: String,
    pub sizes: Vec<SizeRecord>,
}

fn fmt_s(v: Option<f64>) -> String {
    v.map_or("n/a".to_string(), |s| format!("{s:.3e}"))
}

fn fmt_ratio(v: Option<f64>) -> String {
    v.map_or("n/a".to_string(), |s| format!("{s:.3}"))
}

/// One line per size: each side's phase seconds, or why it did not run.
pub fn size_line(r: &SizeRecord) -> String {
    let side = |s: &SideRecord| {
        if s.ran {
            format!(
                "{} {} {} {}",
                fmt_s(s.seconds.assembly),
                fmt_s(s.seconds.elimination),
                fmt_s(s.seconds.solve),
                fmt_s(s.seconds.line_search)
            )
        } else {
            s.note.clone()
        }
    };
    format!(
        "{:>9} nodes  CPU s: {}  GPU s: {}",
        r.nodes,
        side(&r.cpu),
        side(&r.gpu)
    )
}

/// The summary table: one row per size and phase, then the totals.
pub fn summary_text(report: &NewtonReport) -> String {
    let m = &report.machine;
    let mut s = format!(
        "one Newton iteration, f64, CG to {:.0e} ({}); median of {} after a warm-up\nadapter: {}   CPU threads: {} of {} cores\n\n",
        report.cg_tol,
        report.preconditioner,
        report.reps,
        m.adapter.as_deref().unwrap_or("none (--no-gpu)"),
        m.threads,
        m.cpu_cores,
    );
    s.push_str(&format!(
        "{:>9} {:>9}  {:<12} {:>10} {:>10} {:>8}\n",
        "nodes", "dofs", "phase", "CPU s", "GPU s", "GPU/CPU"
    ));
    for r in &report.sizes {
        let rows = r
            .cpu
            .seconds
            .list()
            .into_iter()
            .zip(r.gpu.seconds.list())
            .zip(r.ratio.list())
            .map(|(((name, c), (_, g)), (_, q))| (name, c, g, q))
            .chain(std::iter::once((
                "total",
                r.cpu.total_seconds,
                r.gpu.total_seconds,
                r.ratio_total,
            )));
        for (i, (name, c, g, q)) in rows.enumerate() {
            let (n, d) = if i == 0 {
                (r.nodes.to_string(), r.dofs.to_string())
            } else {
                (String::new(), String::new())
            };
            s.push_str(&format!(
                "{n:>9} {d:>9}  {name:<12} {:>10} {:>10} {:>8}\n",
                fmt_s(c),
                fmt_s(g),
                fmt_ratio(q)
            ));
        }
        if let Some(c) = &r.cpu_check {
            s.push_str(&format!(
                "{:>21}CG {} it, residual {:.2e}, gᵀΔx {:.3e}, E(x+Δx) − E(x) {:.3e}\n",
                "", c.cg_iterations, c.relative_residual, c.slope, c.energy_change
            ));
        }
        if let Some(c) = &r.gpu_cg {
            let threads: Vec<String> = c
                .dispatches_per_iteration
                .iter()
                .map(|d| format!("{} {}", d.kernel, d.threads))
                .collect();
            s.push_str(&format!(
                "{:>21}GPU CG {} it, {:.3e} s/it, {} B/it ({:.1} GB/s); threads per dispatch: {}\n",
                "",
                c.iterations,
                c.seconds_per_iteration,
                c.bytes_per_iteration,
                c.gb_per_second,
                threads.join(", ")
            ));
        }
        if let Some(d) = &r.gpu_assembly_difference {
            s.push_str(&format!(
                "{:>21}GPU assembly vs CPU: H {:.1e}, g {:.1e} (max |Δ| / max |CPU|)\n",
                "", d.hessian, d.gradient
            ));
        }
        if let Some(p) = &r.gpu_profile {
            let largest: Vec<String> = p
                .largest(3)
                .iter()
                .map(|(ph, secs)| format!("{} {secs:.3e} s", ph.name().replace('_', " ")))
                .collect();
            s.push_str(&format!(
                "{:>21}GPU phases: {}; {} host waits, {} dispatches\n",
                "",
                largest.join(", "),
                p.host_syncs,
                p.dispatches
            ));
        }
        for (side, rec) in [("CPU", &r.cpu), ("GPU", &r.gpu)] {
            if !rec.note.is_empty() {
                s.push_str(&format!("{:>21}{side}: {}\n", "", rec.note));
            }
        }
    }
    s
}

fn csv_cell(v: Option<f64>) -> String {
    v.map_or(String::new(), |s| format!("{s:e}"))
}

/// bench.json, bench.csv and newton_phases.svg in `dir`.
pub fn write_outputs(report: &NewtonReport, dir: &Path) -> std::io::Result<()> {
    std::fs::create_dir_all(dir)?;
    crate::io::files::write_atomic_bytes(
        dir.join("bench.json"),
        serde_json::to_string_pretty(report)
            .map_err(std::io::Error::other)?
            .as_bytes(),
    )?;
    let phases = ["assembly", "elimination", "solve", "line_search", "total"];
    let mut csv = String::from("k,nodes,dofs,tetrahedra,free_dofs");
    for side in ["cpu", "gpu", "ratio"] {
        for p in phases {
            csv.push_str(&format!(
                ",{side}_{p}{}",
                if side == "ratio" { "" } else { "_s" }
            ));
        }
    }
    csv.push_str(",cg_iterations,relative_residual,peak_rss_bytes\n");
    for r in &report.sizes {
        let mut row = format!(
            "{},{},{},{},{}",
            r.k, r.nodes, r.dofs, r.tetrahedra, r.free_dofs
        );
        for (p, total) in [
            (r.cpu.seconds, r.cpu.total_seconds),
            (r.gpu.seconds, r.gpu.total_seconds),
            (r.ratio, r.ratio_total),
        ] {
            for (_, v) in p.list() {
                row.push_str(&format!(",{}", csv_cell(v)));
            }
            row.push_str(&format!(",{}", csv_cell(total)));
        }
        let (it, res) = r
            .cpu_check
            .as_ref()
            .map_or((String::new(), String::new()), |c| {
                (
                    c.cg_iterations.to_string(),
                    format!("{:e}", c.relative_residual),
                )
            });
        row.push_str(&format!(",{it},{res},{}\n", r.peak_rss_bytes));
        csv.push_str(&row);
    }
    crate::io::files::write_atomic_bytes(dir.join("bench.csv"), csv.as_bytes())?;
    let mut series = Vec::new();
    for side in ["CPU", "GPU"] {
        for (p, name) in phases[..4].iter().enumerate() {
            let pts: Vec<(f64, f64)> = report
                .sizes
                .iter()
                .filter_map(|r| {
                    let rec = if side == "CPU" { &r.cpu } else { &r.gpu };
                    rec.seconds.list()[p].1.map(|s| (r.nodes as f64, s))
                })
                .collect();
            if !pts.is_empty() {
                series.push((format!("{side} {}", name.replace('_', " ")), pts));
            }
        }
    }
    crate::app::bench::plots::log_log_plot(
        &dir.join("newton_phases.svg"),
        "one Newton iteration: seconds per phase",
        "nodes",
        "seconds (median)",
        &series,
    )
    .map_err(std::io::Error::other)
}
