//! `stickslip solve`: one constrained Newton system from files to Δx, the reactions and
//! report.json.

use crate::app::cli::args::{SolveArgs, SystemArgs};
use crate::app::cli::error::{solve_error, write_failed, CliError};
use crate::app::cli::info::check_adapter_name;
use crate::app::report::{CgReport, CholeskyReport, Files, Report, Seconds};
use crate::app::system_files::{read_system, LoadedSystem};
use crate::core::constraints::{node_rows, Constraint};
use crate::core::elimination::ConstrainedDiagonal;
use crate::error::InputError;
use crate::io::files::{self, Named};
use crate::io::mtx;
use crate::{Precision, Problem, SolveDetails, Solver, SolverConfig, SolverKind};
use std::time::Instant;

/// `solve`'s inputs and outputs, for [`files::check_outputs`].
fn solve_files(args: &SolveArgs) -> (Vec<Named<'_>>, Vec<Named<'_>>) {
    (
        system_inputs(&args.system),
        [
            ("--out", Some(&args.out)),
            ("--reactions", args.reactions.as_ref()),
            ("--report", args.report.as_ref()),
        ]
        .into_iter()
        .filter_map(|(o, p)| p.map(|p| Named::new(o, p)))
        .collect(),
    )
}

/// The input files of a system (H, g, the constraints).
pub fn system_inputs(sys: &SystemArgs) -> Vec<Named<'_>> {
    [
        ("--hessian", Some(&sys.hessian)),
        ("--gradient", Some(&sys.gradient)),
        ("--constraints", sys.constraints.as_ref()),
        ("--constraint-matrix", sys.constraint_matrix.as_ref()),
        ("--constraint-values", sys.constraint_values.as_ref()),
    ]
    .into_iter()
    .filter_map(|(o, p)| p.map(|p| Named::new(o, p)))
    .collect()
}

/// `stickslip solve`: read → constraints → frames → eliminate → solve → recover → write.
pub fn solve(args: &SolveArgs) -> Result<Report, CliError> {
    let t_start = Instant::now();
    // Before any work: no output may destroy an input or another output, and each can be
    // created.
    let (inputs, outputs) = solve_files(args);
    files::check_outputs(&inputs, &outputs)?;
    if args.solver == SolverKind::Gpu {
        check_adapter_name()?;
    }
    let (config, precision, max_iters) = solver_config(args)?;

    // 1–2. Read H, g and the constraints; build the per-node frames.
    let LoadedSystem {
        dim,
        h,
        g,
        constraints,
        frames,
        read_seconds: t_read,
        frames_seconds,
    } = read_system(&args.system.files())?;
    let n = h.n;
    let problem = Problem::from_checked_parts(h, g, constraints, frames);

    // 3–5. Eliminate, solve, recover Δx = Δx_p + V y and f = −(HΔx + g). Every GPU
    // failure (no adapter, no SHADER_F64, a device error) is a solve error: exit 1.
    let t = Instant::now();
    let mut solver = Solver::new(config).map_err(solve_error)?;
    let t_open = t.elapsed().as_secs_f64();
    let sol = solver.solve(&problem).map_err(solve_error)?;
    let st = &sol.stats;
    let (dx, f) = (&sol.dx, &sol.reactions);
    let constraints = problem.constraints();
    let frames = problem.frames();
    let violation = constraint_violation(dim, constraints, dx);
    let (mut seconds, chol, cgr, gpu) = details(args, max_iters, &st.details);
    let relative_residual = st.relative_residual;

    // 6. Write.
    let t = Instant::now();
    let solver = args.solver.name();
    let note =
        format!("stickslip solve --solver {solver}: relative residual {relative_residual:.3e}");
    mtx::write_vector(&args.out, dx, &format!("dx: {note}"))
        .map_err(|e| write_failed(&args.out, e))?;
    if let Some(path) = &args.reactions {
        mtx::write_vector(path, f, &format!("reactions f = -(H dx + g): {note}"))
            .map_err(|e| write_failed(path, e))?;
    }
    seconds.read = t_read;
    seconds.setup = frames_seconds + t_open + st.seconds.setup;
    seconds.solve = st.seconds.solve;
    seconds.recover = st.seconds.recover;
    seconds.write = t.elapsed().as_secs_f64();
    seconds.total = t_start.elapsed().as_secs_f64();
    let report = Report {
        threads: rayon::current_num_threads(),
        solver: solver.into(),
        precision: precision.to_string(),
        adapter: st.adapter.clone(),
        iterations: st.iterations,
        relative_residual,
        seconds,
        dim,
        nodes: n,
        free_dofs: frames.free_dofs(),
        constrained_dofs: frames.constrained_dofs(),
        rotated_nodes: frames.rot_nodes.len(),
        constraints: constraints.len(),
        prescribed: !frames.homogeneous,
        constrained_diagonal: match args.constrained_diagonal {
            ConstrainedDiagonal::Identity => "identity",
            ConstrainedDiagonal::Hessian => "hessian",
        }
        .into(),
        constraint_violation: violation,
        cholesky: chol,
        cg: cgr,
        gpu,
        files: Files {
            hessian: args.system.hessian.clone(),
            gradient: args.system.gradient.clone(),
            constraints: args.system.constraints.clone(),
            constraint_matrix: args.system.constraint_matrix.clone(),
            constraint_values: args.system.constraint_values.clone(),
            out: args.out.clone(),
            reactions: args.reactions.clone(),
        },
    };
    if let Some(path) = &args.report {
        let mut text =
            serde_json::to_string_pretty(&report).map_err(|e| CliError::Failed(e.to_string()))?;
        text.push('\n');
        files::write_atomic_bytes(path, text.as_bytes()).map_err(|e| write_failed(path, e))?;
    }
    Ok(report)
}

/// The solver configuration of the command line, with its precision and iteration
/// limit; checked before any file is read (f32 on the CPU, --error-tol without mixed):
/// one line naming the option.
fn solver_config(args: &SolveArgs) -> Result<(SolverConfig, Precision, usize), CliError> {
    let precision = args.precision.unwrap_or(Precision::F64);
    let max_iters = args
        .max_iters
        .unwrap_or(crate::engine::solver::DEFAULT_MAX_ITERS);
    let mut config = match args.solver {
        SolverKind::Cholesky => SolverConfig::cholesky(),
        SolverKind::Cg => SolverConfig::cg(),
        SolverKind::Gpu => SolverConfig::gpu(precision),
    }
    .tol(args.tol)
    .max_iters(max_iters)
    .preconditioner(args.preconditioner)
    .coarse(args.coarse)
    .constrained_diagonal(args.constrained_diagonal)
    .ordering(args.ordering);
    config.precision = precision;
    config.error_tol = args.error_tol;
    if args.solver != SolverKind::Gpu && precision != Precision::F64 {
        return Err(InputError::new(
            "command line",
            "--precision",
            format!("{precision} needs --solver gpu (cholesky and cg compute in f64)"),
        )
        .into());
    }
    if args.error_tol.is_some() && (args.solver != SolverKind::Gpu || precision != Precision::Mixed)
    {
        return Err(InputError::new(
            "command line",
            "--error-tol",
            "needs --solver gpu --precision mixed (extended-precision refinement)",
        )
        .into());
    }
    Ok((config, precision, max_iters))
}

/// The solver's own report (Cholesky, CPU CG or GPU) and the seconds of its phases.
fn details(
    args: &SolveArgs,
    max_iters: usize,
    details: &SolveDetails,
) -> (
    Seconds,
    Option<CholeskyReport>,
    Option<CgReport>,
    Option<serde_json::Value>,
) {
    let mut seconds = Seconds::default();
    let mut chol = None;
    let mut cgr = None;
    let mut gpu = None;
    match details {
        SolveDetails::Cholesky(info) => {
            seconds.symbolic = Some(info.symbolic_seconds);
            seconds.numeric = Some(info.numeric_seconds);
            seconds.triangular = Some(info.solve_seconds);
            chol = Some(CholeskyReport {
                matrix_nnz: info.matrix_nnz,
                factor_nnz: info.factor_nnz,
                reused_symbolic: info.reused_symbolic,
                factor_nnz_exact: info.factor_nnz_exact,
                ordering: info.ordering.name().into(),
                ordering_seconds: info.ordering_seconds,
                scaled_residual: info.scaled_residual,
                refinements: info.refinements,
                condition_estimate: info.condition_estimate,
            });
        }
        SolveDetails::Cg(info) => {
            cgr = Some(CgReport {
                preconditioner: args.preconditioner.name().into(),
                coarse: args.coarse.name().into(),
                tol: args.tol,
                max_iters,
                restarts: info.restarts,
                condition_estimate: info.condition_estimate,
            });
        }
        SolveDetails::Gpu(info) => {
            gpu = Some(serde_json::to_value(info).unwrap_or(serde_json::Value::Null));
        }
    }
    (seconds, chol, cgr, gpu)
}

/// max over constraint rows of |aᵀΔx_i − c| / ‖a‖: how well Δx meets B Δx = p.
fn constraint_violation(dim: usize, cs: &[Constraint], dx: &[f64]) -> f64 {
    let mut worst = 0.0f64;
    for c in cs {
        let (rows, vals) = node_rows(dim, c);
        let xi = &dx[c.node * dim..c.node * dim + dim];
        for (r, v) in rows.iter().zip(vals) {
            // Scaled norm: rows near 1e±200 are accepted and must not turn into 0 or ∞.
            let len = crate::core::elimination::norm2(r);
            let s: f64 = r.iter().zip(xi).map(|(a, b)| a * b).sum();
            let miss = (s - v).abs() / len;
            if !miss.is_finite() {
                return f64::NAN;
            }
            worst = worst.max(miss);
        }
    }
    worst
}
