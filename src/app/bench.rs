//! `stickslip bench`: the CPU-versus-GPU comparison on the same generated systems, as
//! speed against error (BENCHMARKS.md).
//!
//! Per size of the ladder (2D and 3D, realistic constraint mix), in four steps: generate
//! the system; solve it for a reference (the Cholesky oracle, with symbolic, numeric and
//! solve timed apart, then a refactorization reusing the analysis; or a tight f64 CG where
//! the oracle does not fit, and the record says which); run every solver over a sweep of
//! tolerances, recording time, iterations, the f64 relative residual and the relative
//! error against the reference; derive the tables (which solver reaches a given error
//! first, time per iteration, the log-log scaling slope).

pub use crate::app::bench_report::{BenchReport, CholeskyRecord, RunRecord, ScalingFit, Winner};
use crate::cases::generate::{random_system, SystemSpec};
use crate::core::elimination::{ConstrainedDiagonal, Eliminated};
use crate::core::linalg::relative_error;
use crate::gpu::{GpuContext, GpuOptions, GpuParams, Precision};
use crate::solve::cg::{self, BuiltPreconditioner, CgParams, Preconditioner};
use crate::solve::coarse::CoarseSpace;
use crate::{LayoutKey, SolveDetails, SolveStats, Solver, SolverConfig, Step};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// What to run.
#[derive(Debug, Clone)]
pub struct BenchOptions {
    /// CI-sized ladder and sweep.
    pub quick: bool,
    /// Node counts (per dimension); None: the default ladder.
    pub sizes: Option<Vec<usize>>,
    pub dims: Vec<usize>,
    /// Skip the GPU solvers.
    pub no_gpu: bool,
    /// Largest node count at which the Cholesky oracle runs (memory); above it the
    /// reference is a CPU CG solve at tolerance 1e-12.
    pub oracle_max_nodes: usize,
    pub out: Option<PathBuf>,
    pub quiet: bool,
    pub seed: u64,
    /// Coarse correction of every CG (CPU and GPU alike).
    pub coarse: CoarseSpace,
    /// Fill-reducing ordering of the Cholesky oracle.
    pub ordering: crate::CholeskyOrdering,
}

impl Default for BenchOptions {
    fn default() -> Self {
        BenchOptions {
            quick: false,
            sizes: None,
            dims: vec![2, 3],
            no_gpu: false,
            oracle_max_nodes: 300_000,
            out: None,
            quiet: false,
            seed: 1,
            coarse: CoarseSpace::default(),
            ordering: crate::CholeskyOrdering::Auto,
        }
    }
}

/// Errors of the benchmark (I/O of the output, or a failed reference solve).
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error("{0}")]
    Io(String),
    #[error("{0}")]
    Solve(String),
}

fn ladder(opts: &BenchOptions, dim: usize) -> Vec<usize> {
    if let Some(s) = &opts.sizes {
        return s.clone();
    }
    match (opts.quick, dim) {
        (true, 2) => vec![1_000, 4_000],
        (true, _) => vec![1_000, 8_000],
        (false, 2) => vec![1_000, 10_000, 100_000, 250_000],
        (false, _) => vec![1_000, 8_000, 27_000, 64_000, 125_000, 216_000],
    }
}

fn tolerances(quick: bool) -> Vec<f64> {
    if quick {
        vec![1e-4, 1e-8]
    } else {
        vec![1e-2, 1e-4, 1e-6, 1e-8, 1e-10, 1e-12]
    }
}

/// Peak resident set size of this process (Linux VmHWM), 0 where unknown.
pub fn peak_rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

/// Host copy bandwidth: read + write bytes of a 256 MiB memcpy, best of 5.
pub fn cpu_copy_bandwidth() -> f64 {
    let n = 32 << 20; // f64 elements: 256 MiB
    let src = vec![1.0f64; n];
    let mut dst = vec![0.0f64; n];
    let mut best = f64::INFINITY;
    for _ in 0..5 {
        let t = Instant::now();
        dst.copy_from_slice(&src);
        std::hint::black_box(&mut dst);
        best = best.min(t.elapsed().as_secs_f64());
    }
    2.0 * (n * 8) as f64 / best / 1e9
}

/// Bytes one CPU CG iteration moves: the blocks, the column indices and row pointers
/// (usize), and about 18 passes over f64 vectors (matvec in/out, two dot products, the
/// x, r, z and p updates).
pub fn cpu_cg_bytes_per_iteration(e: &Eliminated) -> u64 {
    let h = e.h;
    let idx = std::mem::size_of::<usize>() as u64;
    let matrix =
        h.values.len() as u64 * 8 + h.col_idx.len() as u64 * idx + h.row_ptr.len() as u64 * idx;
    matrix + 18 * h.ndof() as u64 * 8
}

/// Runs the whole benchmark; `progress` receives one line per finished run.
pub fn run(opts: &BenchOptions, command: &str) -> Result<BenchReport, BenchError> {
    let ctx =
        if opts.no_gpu {
            None
        } else {
            // No silent CPU-only run: without an adapter the GPU benchmark fails (--no-gpu
            // asks for the CPU solvers only).
            Some(GpuContext::new(&GpuOptions::default()).map_err(|e| {
                BenchError::Solve(format!("{e} (--no-gpu runs the CPU solvers only)"))
            })?)
        };
    let mut report = BenchReport {
        command: command.to_string(),
        cpu_threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
        threads: rayon::current_num_threads(),
        adapter: ctx.as_ref().map(|c| c.adapter_name().to_string()),
        cpu_copy_gb_per_s: cpu_copy_bandwidth(),
        gpu_copy_gb_per_s: ctx
            .as_ref()
            .and_then(|c| crate::gpu::measure_copy_bandwidth(c).ok()),
        runs: Vec::new(),
        cholesky: Vec::new(),
        winners: Vec::new(),
        scaling: Vec::new(),
    };
    let tols = tolerances(opts.quick);
    let mut jobs = Vec::new();
    for &dim in &opts.dims {
        for nodes in ladder(opts, dim) {
            jobs.push((dim, nodes));
        }
    }
    let bar = if opts.quiet {
        indicatif::ProgressBar::hidden()
    } else {
        let b = indicatif::ProgressBar::new(jobs.len() as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} sizes {msg}")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        b
    };
    for (dim, nodes) in jobs {
        bar.set_message(format!("{dim}D {nodes} nodes"));
        bench_one(opts, ctx.as_ref(), dim, nodes, &tols, &mut report, &bar)?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    derive_tables(&mut report);
    if let Some(dir) = &opts.out {
        write_outputs(&report, dir)
            .map_err(|e| BenchError::Io(format!("{}: {e}", dir.display())))?;
    }
    Ok(report)
}

fn bench_one(
    opts: &BenchOptions,
    ctx: Option<&GpuContext>,
    dim: usize,
    nodes: usize,
    tols: &[f64],
    report: &mut BenchReport,
    bar: &indicatif::ProgressBar,
) -> Result<(), BenchError> {
    // 1. The system.
    let s = random_system(&SystemSpec::with_nodes(dim, nodes, opts.seed));
    let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
    let n = s.h.n;
    let dofs = s.h.ndof();
    let base = |solver: &str, precision: &str| RunRecord {
        dim,
        nodes: n,
        dofs,
        solver: solver.to_string(),
        precision: precision.to_string(),
        tol: None,
        converged: false,
        iterations: 0,
        relative_residual: f64::NAN,
        relative_error: f64::NAN,
        error_reference: String::new(),
        setup_seconds: 0.0,
        solve_seconds: 0.0,
        total_seconds: 0.0,
        gpu_seconds: None,
        bytes_per_iteration: 0,
        achieved_gb_per_s: 0.0,
        seconds_per_iteration: 0.0,
        recorded_iterations: None,
        dispatches_per_iteration: None,
        threads_per_dispatch: None,
        bandwidth_floor_ratio: f64::NAN,
        peak_rss_bytes: 0,
        note: String::new(),
    };
    // 2. Reference.
    let (reference, ref_name) = if n <= opts.oracle_max_nodes {
        let t = Instant::now();
        let layout = LayoutKey::fresh();
        let mut oracle = Solver::new(SolverConfig::cholesky().ordering(opts.ordering))
            .map_err(|err| BenchError::Solve(err.to_string()))?;
        let mut factor = || match oracle.solve_eliminated(layout, &e) {
            Ok(Step {
                y,
                stats:
                    SolveStats {
                        details: SolveDetails::Cholesky(info),
                        ..
                    },
                ..
            }) => Ok((y, info)),
            Ok(_) => Err(BenchError::Solve("not a Cholesky solve".into())),
            Err(err) => Err(BenchError::Solve(err.to_string())),
        };
        let (y, info) = factor()?;
        let total = t.elapsed().as_secs_f64();
        let (_, info2) = factor()?;
        // Same phases as the first factorization, analysis skipped.
        let reused = info2.numeric_seconds + info2.solve_seconds;
        debug_assert!(info2.reused_symbolic);
        report.cholesky.push(CholeskyRecord {
            dim,
            nodes: n,
            symbolic_seconds: info.symbolic_seconds,
            numeric_seconds: info.numeric_seconds,
            solve_seconds: info.solve_seconds,
            reused_numeric_seconds: reused,
            factor_nnz: info.factor_nnz,
            factor_nnz_exact: info.factor_nnz_exact,
            ordering: info.ordering.name().into(),
        });
        let dx = e.recover(&y);
        let mut r = base("cholesky", "f64");
        r.converged = true;
        r.relative_residual = info.relative_residual;
        r.relative_error = 0.0;
        r.error_reference = "oracle (itself)".into();
        r.setup_seconds = info.symbolic_seconds;
        r.solve_seconds = info.numeric_seconds + info.solve_seconds;
        r.total_seconds = total;
        r.peak_rss_bytes = peak_rss_bytes();
        r.note = format!("refactor with reused analysis: {reused:.3} s");
        say(bar, opts.quiet, &line(&r));
        crate::app::bench_report::append_record(opts.out.as_deref(), "records.jsonl", &r);
        report.runs.push(r);
        (dx, "oracle".to_string())
    } else {
        let (y, _) = cg::solve(
            &e,
            &CgParams {
                tol: 1e-12,
                max_iters: 100_000,
                preconditioner: Preconditioner::BlockJacobi,
                ..Default::default()
            },
        )
        .map_err(|err| BenchError::Solve(format!("reference CG: {err}")))?;
        (e.recover(&y), "cg-1e-12".to_string())
    };
    // 3. CPU CG over the tolerance sweep.
    let cpu_bytes = cpu_cg_bytes_per_iteration(&e);
    for pc in [Preconditioner::Jacobi, Preconditioner::BlockJacobi] {
        let name = match pc {
            Preconditioner::BlockJacobi => "cg-block-jacobi",
            _ => "cg-jacobi",
        };
        let t = Instant::now();
        let pre = BuiltPreconditioner::new(&e, pc).with_coarse(&e, opts.coarse, None);
        let setup = t.elapsed().as_secs_f64();
        for &tol in tols {
            let mut r = base(name, "f64");
            r.tol = Some(tol);
            r.error_reference = ref_name.clone();
            r.setup_seconds = setup;
            let params = CgParams {
                tol,
                max_iters: 50_000,
                preconditioner: pc,
                coarse: opts.coarse,
                ..Default::default()
            };
            let t = Instant::now();
            match cg::solve_with(&e, &pre, None, &params) {
                Ok((y, info)) => {
                    r.solve_seconds = t.elapsed().as_secs_f64();
                    r.converged = true;
                    r.iterations = info.iterations;
                    r.relative_residual = info.relative_residual;
                    r.relative_error = relative_error(&e.recover(&y), &reference);
                }
                Err(err) => {
                    r.solve_seconds = t.elapsed().as_secs_f64();
                    r.relative_residual = err.reached_residual().unwrap_or(f64::NAN);
                    r.note = err.to_string();
                }
            }
            finish_record(&mut r, cpu_bytes, report.cpu_copy_gb_per_s);
            say(bar, opts.quiet, &line(&r));
            crate::app::bench_report::append_record(opts.out.as_deref(), "records.jsonl", &r);
            report.runs.push(r);
        }
    }
    // 4. GPU CG in each precision over the sweep.
    if let Some(ctx) = ctx {
        for precision in [Precision::F32, Precision::F64, Precision::Mixed] {
            let name = format!("gpu-{precision}");
            for &tol in tols {
                let mut r = base(&name, &precision.to_string());
                r.tol = Some(tol);
                r.error_reference = ref_name.clone();
                if precision == Precision::F32 && tol < 1e-7 {
                    // f32 cannot resolve a residual below its unit round-off.
                    continue;
                }
                let params = GpuParams {
                    precision,
                    tol,
                    max_iters: 50_000,
                    preconditioner: Preconditioner::Jacobi,
                    coarse: opts.coarse,
                    ..Default::default()
                };
                let config = SolverConfig::gpu(precision)
                    .gpu_params(params)
                    .gpu_context(ctx.clone());
                let solved = Solver::new(config)
                    .and_then(|mut s| s.solve_eliminated(LayoutKey::fresh(), &e));
                let (dx, info) = match solved {
                    Ok(Step {
                        dx,
                        stats:
                            SolveStats {
                                details: SolveDetails::Gpu(info),
                                seconds,
                                ..
                            },
                        ..
                    }) => {
                        r.setup_seconds = seconds.setup;
                        (dx, Ok(*info))
                    }
                    Ok(_) => continue,
                    // The device could not take this system or precision: no further tolerance will run.
                    Err(crate::Error::Gpu(err)) => {
                        r.note = format!("not run: {err}");
                        say(bar, opts.quiet, &line(&r));
                        crate::app::bench_report::append_record(
                            opts.out.as_deref(),
                            "records.jsonl",
                            &r,
                        );
                        report.runs.push(r);
                        break;
                    }
                    Err(err) => (Vec::new(), Err(err)),
                };
                match info {
                    Ok(info) => {
                        r.converged = true;
                        r.iterations = info.iterations;
                        r.relative_residual = info.relative_residual;
                        r.relative_error = relative_error(&dx, &reference);
                        r.solve_seconds = info.seconds.solve;
                        r.total_seconds = r.setup_seconds
                            + info.seconds.upload
                            + info.seconds.solve
                            + info.seconds.download;
                        r.gpu_seconds = info.gpu_seconds;
                        r.bytes_per_iteration = info.bytes_per_iteration;
                        r.recorded_iterations = Some(info.recorded_iterations);
                        r.dispatches_per_iteration = Some(info.dispatches_per_iteration);
                        r.threads_per_dispatch = Some(info.threads_per_dispatch);
                        r.note = info.notes.join("; ");
                    }
                    Err(err) => {
                        r.note = err.to_string();
                    }
                }
                let bytes = r.bytes_per_iteration;
                finish_record(&mut r, bytes, report.gpu_copy_gb_per_s.unwrap_or(f64::NAN));
                say(bar, opts.quiet, &line(&r));
                crate::app::bench_report::append_record(opts.out.as_deref(), "records.jsonl", &r);
                report.runs.push(r);
            }
        }
    }
    Ok(())
}

/// One line per finished run: above the progress bar on a terminal, plain on stderr
/// otherwise (indicatif hides its bar, and its println, when stderr is not a terminal).
fn say(bar: &indicatif::ProgressBar, quiet: bool, text: &str) {
    if quiet {
        return;
    }
    if bar.is_hidden() {
        eprintln!("{text}");
    } else {
        bar.println(text);
    }
}

fn finish_record(r: &mut RunRecord, bytes_per_iteration: u64, copy_gb_per_s: f64) {
    if r.total_seconds == 0.0 {
        r.total_seconds = r.setup_seconds + r.solve_seconds;
    }
    r.bytes_per_iteration = bytes_per_iteration;
    if r.iterations > 0 && r.solve_seconds > 0.0 {
        r.seconds_per_iteration = r.solve_seconds / r.iterations as f64;
        r.achieved_gb_per_s =
            bytes_per_iteration as f64 * r.iterations as f64 / r.solve_seconds / 1e9;
        let floor = bytes_per_iteration as f64 / (copy_gb_per_s * 1e9);
        r.bandwidth_floor_ratio = r.seconds_per_iteration / floor;
    }
    r.peak_rss_bytes = peak_rss_bytes();
}

fn line(r: &RunRecord) -> String {
    format!(
        "{}D {:>8} nodes  {:<16} tol {:>7}  {:>6} it  res {:>9.2e}  err {:>9.2e}  {:>9.4} s  {:>6.2} GB/s{}",
        r.dim,
        r.nodes,
        r.solver,
        r.tol.map_or("-".to_string(), |t| format!("{t:.0e}")),
        r.iterations,
        r.relative_residual,
        r.relative_error,
        r.total_seconds,
        r.achieved_gb_per_s,
        if r.converged { String::new() } else { format!("  NOT CONVERGED: {}", r.note) }
    )
}

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

fn write_outputs(report: &BenchReport, dir: &Path) -> std::io::Result<()> {
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
    crate::app::plots::time_vs_error(report, dir).map_err(std::io::Error::other)?;
    crate::app::plots::time_vs_size(report, dir).map_err(std::io::Error::other)?;
    Ok(())
}

/// `stickslip bench --hard`: the hard-case table (src/app/hard.rs) for STABILITY.md, and GPU
/// f64 against mixed precision on larger hard cases. Writes hard.md and hard.json to `out`.
pub fn run_hard(
    out: Option<&Path>,
    no_gpu: bool,
    scale: usize,
    coarse: &[CoarseSpace],
    quiet: bool,
) -> Result<String, BenchError> {
    let ctx =
        if no_gpu {
            None
        } else {
            Some(GpuContext::new(&GpuOptions::default()).map_err(|e| {
                BenchError::Solve(format!("{e} (--no-gpu runs the CPU solvers only)"))
            })?)
        };
    // A line per stage and per timed case: the whole run takes minutes (16 at scale 5).
    let say = |text: &str| {
        if !quiet {
            eprintln!("bench --hard: {text}");
        }
    };
    say("the CI-size table, every case, solver and precision");
    let rows = crate::app::hard::table(crate::app::hard::Size::Ci, ctx.as_ref(), 3000)
        .map_err(BenchError::Solve)?;
    for r in &rows {
        crate::app::bench_report::append_record(out, "records.jsonl", r);
    }
    let mut md = format!(
        "adapter: {}\n\n{}",
        ctx.as_ref()
            .map_or("none".to_string(), |c| c.adapter_name().to_string()),
        crate::app::hard::table_markdown(&rows)
    );
    let mut speed = Vec::new();
    if let Some(c) = ctx.as_ref() {
        let f = |v: Option<f64>, p: usize| {
            v.map_or("failed".to_string(), |x| format!("{x:.prec$e}", prec = p))
        };
        for (k, &cs) in coarse.iter().enumerate() {
            // The cantilevers at twice the scale for the first coarse space only: with the
            // translations, neohookean at 107k DOFs takes minutes per solve.
            say(&format!(
                "GPU f64 CG against mixed, coarse {}, grid scale {scale}",
                cs.name()
            ));
            let mut done = |r: &crate::app::hard::SpeedRow| {
                // Kept as each case finishes: a run stopped at its time limit keeps them.
                crate::app::bench_report::append_record(out, "records.jsonl", r);
                let s = |v: Option<f64>| v.map_or("failed".to_string(), |x| format!("{x:.3} s"));
                say(&format!(
                    "  {} ({} DOFs): f64 {}, mixed {}",
                    r.case,
                    r.dofs,
                    s(r.f64_seconds),
                    s(r.mixed_seconds)
                ));
            };
            let rows = crate::app::hard::mixed_speed(
                crate::app::hard::Size::Scale(scale),
                c,
                1e-10,
                cs,
                k == 0,
                &mut done,
            )
            .map_err(BenchError::Solve)?;
            md.push_str(&format!(
                "\nGPU f64 CG against mixed precision, both Jacobi with coarse correction \
                 `{}`, to residual tol 1e-10, best of {} solves after a warm-up, grid scale \
                 {scale}:\n",
                cs.name(),
                crate::app::hard::SPEED_REPS
            ));
            md.push_str("\n| case | DOFs | f64 CG s (its) | mixed s (its) | f64/mixed | f64 error | mixed error |\n|---|---|---|---|---|---|---|\n");
            for r in &rows {
                let ratio = match (r.f64_seconds, r.mixed_seconds) {
                    (Some(a), Some(b)) if b > 0.0 => format!("{:.2}", a / b),
                    _ => "—".into(),
                };
                let it = |v: Option<usize>| v.map_or("—".to_string(), |i| i.to_string());
                md.push_str(&format!(
                    "| {} | {} | {} ({}) | {} ({}) | {ratio} | {} | {} |\n",
                    r.case,
                    r.dofs,
                    f(r.f64_seconds, 2),
                    it(r.f64_iterations),
                    f(r.mixed_seconds, 2),
                    it(r.mixed_iterations),
                    f(r.f64_error, 1),
                    f(r.mixed_error, 1)
                ));
            }
            speed.extend(rows);
        }
    }
    if let Some(dir) = out {
        std::fs::create_dir_all(dir)
            .map_err(|e| BenchError::Io(format!("{}: {e}", dir.display())))?;
        let json = serde_json::json!({ "rows": rows, "mixed_speed": speed });
        crate::io::files::write_atomic_bytes(dir.join("hard.md"), md.as_bytes())
            .and_then(|_| {
                crate::io::files::write_atomic_bytes(
                    dir.join("hard.json"),
                    json.to_string().as_bytes(),
                )
            })
            .map_err(|e| BenchError::Io(format!("{}: {e}", dir.display())))?;
    }
    Ok(md)
}
