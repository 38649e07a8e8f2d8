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

use crate::app::bench::measure::{
    cpu_cg_bytes_per_iteration, cpu_copy_bandwidth, peak_rss_bytes, say,
};
pub use crate::app::bench::record::{BenchReport, CholeskyRecord, RunRecord, ScalingFit, Winner};
use crate::app::bench::tables::{derive_tables, write_outputs};
use crate::cases::generate::{random_system, SystemSpec};
use crate::core::elimination::{ConstrainedDiagonal, Eliminated};
use crate::core::linalg::relative_error;
use crate::gpu::{GpuContext, GpuOptions, Precision};
use crate::solve::cg::{self, BuiltPreconditioner, CgParams, Preconditioner};
use crate::solve::coarse::CoarseSpace;
use crate::{LayoutKey, SolveDetails, SolveStats, Solver, SolverConfig, Step};
use std::path::PathBuf;
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

/// One size of the ladder: where its runs are recorded and the fields they share.
struct Size<'a> {
    opts: &'a BenchOptions,
    bar: &'a indicatif::ProgressBar,
    dim: usize,
    n: usize,
    dofs: usize,
}

impl Size<'_> {
    /// A record of this size for `solver` in `precision`, nothing measured yet.
    fn base(&self, solver: &str, precision: &str) -> RunRecord {
        let (dim, n, dofs) = (self.dim, self.n, self.dofs);
        RunRecord {
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
        }
    }

    /// Prints a finished run, appends it to records.jsonl and keeps it in the report.
    fn record(&self, report: &mut BenchReport, r: RunRecord) {
        say(self.bar, self.opts.quiet, &line(&r));
        crate::app::bench::record::append_record(self.opts.out.as_deref(), "records.jsonl", &r);
        report.runs.push(r);
    }
}

/// One size of the ladder, in steps: 1. generate the system; 2. its reference solution
/// (the oracle, itself timed); 3.–4. every CPU and GPU solver over the sweep of
/// tolerances, timed and checked against the reference.
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
    let size = Size {
        opts,
        bar,
        dim,
        n: s.h.n,
        dofs: s.h.ndof(),
    };
    // 2. The reference.
    let (reference, ref_name) = reference(&size, &e, report)?;
    // 3. CPU CG over the tolerance sweep.
    time_cpu_cg(&size, &e, (&reference, &ref_name), tols, report);
    // 4. GPU CG in each precision over the sweep.
    if let Some(ctx) = ctx {
        time_gpu_cg(&size, ctx, &e, (&reference, &ref_name), tols, report);
    }
    Ok(())
}

/// The reference Δx and its name: the Cholesky oracle (recorded as a run, with a
/// refactorization that reuses the analysis) up to `oracle_max_nodes`, else CPU CG at 1e-12.
fn reference(
    size: &Size,
    e: &Eliminated,
    report: &mut BenchReport,
) -> Result<(Vec<f64>, String), BenchError> {
    let dim = size.dim;
    let n = size.n;
    let (reference, ref_name) = if n <= size.opts.oracle_max_nodes {
        let t = Instant::now();
        let layout = LayoutKey::fresh();
        let mut oracle = Solver::new(SolverConfig::cholesky().ordering(size.opts.ordering))
            .map_err(|err| BenchError::Solve(err.to_string()))?;
        let mut factor = || match oracle.solve_eliminated(layout, e) {
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
        let mut r = size.base("cholesky", "f64");
        r.converged = true;
        r.relative_residual = info.relative_residual;
        r.relative_error = 0.0;
        r.error_reference = "oracle (itself)".into();
        r.setup_seconds = info.symbolic_seconds;
        r.solve_seconds = info.numeric_seconds + info.solve_seconds;
        r.total_seconds = total;
        r.peak_rss_bytes = peak_rss_bytes();
        r.note = format!("refactor with reused analysis: {reused:.3} s");
        size.record(report, r);
        (dx, "oracle".to_string())
    } else {
        let (y, _) = cg::solve(
            e,
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
    Ok((reference, ref_name))
}

/// The CPU CG with Jacobi and block Jacobi over the tolerance sweep.
fn time_cpu_cg(
    size: &Size,
    e: &Eliminated,
    (reference, ref_name): (&[f64], &str),
    tols: &[f64],
    report: &mut BenchReport,
) {
    let cpu_bytes = cpu_cg_bytes_per_iteration(e);
    for pc in [Preconditioner::Jacobi, Preconditioner::BlockJacobi] {
        let name = match pc {
            Preconditioner::BlockJacobi => "cg-block-jacobi",
            _ => "cg-jacobi",
        };
        let t = Instant::now();
        let pre = BuiltPreconditioner::new(e, pc).with_coarse(e, size.opts.coarse, None);
        let setup = t.elapsed().as_secs_f64();
        for &tol in tols {
            let mut r = size.base(name, "f64");
            r.tol = Some(tol);
            r.error_reference = ref_name.to_string();
            r.setup_seconds = setup;
            let params = CgParams {
                tol,
                max_iters: 50_000,
                preconditioner: pc,
                coarse: size.opts.coarse,
                ..Default::default()
            };
            let t = Instant::now();
            match cg::solve_with(e, &pre, None, &params) {
                Ok((y, info)) => {
                    r.solve_seconds = t.elapsed().as_secs_f64();
                    r.converged = true;
                    r.iterations = info.iterations;
                    r.relative_residual = info.relative_residual;
                    r.relative_error = relative_error(&e.recover(&y), reference);
                }
                Err(err) => {
                    r.solve_seconds = t.elapsed().as_secs_f64();
                    r.relative_residual = err.reached_residual().unwrap_or(f64::NAN);
                    r.note = err.to_string();
                }
            }
            finish_record(&mut r, cpu_bytes, report.cpu_copy_gb_per_s);
            size.record(report, r);
        }
    }
}

/// The GPU CG in f32, f64 and mixed precision over the tolerance sweep (f32 down to
/// 1e-7, its unit round-off).
fn time_gpu_cg(
    size: &Size,
    ctx: &GpuContext,
    e: &Eliminated,
    (reference, ref_name): (&[f64], &str),
    tols: &[f64],
    report: &mut BenchReport,
) {
    for precision in [Precision::F32, Precision::F64, Precision::Mixed] {
        let name = format!("gpu-{precision}");
        for &tol in tols {
            let mut r = size.base(&name, &precision.to_string());
            r.tol = Some(tol);
            r.error_reference = ref_name.to_string();
            if precision == Precision::F32 && tol < 1e-7 {
                // f32 cannot resolve a residual below its unit round-off.
                continue;
            }
            let config = SolverConfig::gpu(precision)
                .tol(tol)
                .max_iters(50_000)
                .preconditioner(Preconditioner::Jacobi)
                .coarse(size.opts.coarse)
                .gpu_context(ctx.clone());
            let solved =
                Solver::new(config).and_then(|mut s| s.solve_eliminated(LayoutKey::fresh(), e));
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
                    size.record(report, r);
                    break;
                }
                Err(err) => (Vec::new(), Err(err)),
            };
            match info {
                Ok(info) => {
                    r.converged = true;
                    r.iterations = info.iterations;
                    r.relative_residual = info.relative_residual;
                    r.relative_error = relative_error(&dx, reference);
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
            size.record(report, r);
        }
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
