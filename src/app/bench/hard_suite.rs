//! `stickslip bench --hard`: the hard-case suite ([`crate::app::bench::hard`]) as the
//! STABILITY.md table, then GPU f64 against mixed precision on the larger cases.

use crate::app::bench::hard::{
    condition_number, conditioned, incompressible, near_axis_normals, reference, relative_error,
    stiffness_contrast, suite, time_step, HardCase, Size,
};
use crate::app::bench::ladder::BenchError;
use crate::core::elimination::Eliminated;
use crate::gpu::{GpuContext, GpuOptions};
use crate::solve::coarse::CoarseSpace;
use std::path::Path;

/// `stickslip bench --hard`: the hard-case table (src/app/bench/hard.rs) for STABILITY.md, and GPU
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
    let rows = table(Size::Ci, ctx.as_ref(), 3000).map_err(BenchError::Solve)?;
    for r in &rows {
        crate::app::bench::record::append_record(out, "records.jsonl", r);
    }
    let mut md = format!(
        "adapter: {}\n\n{}",
        ctx.as_ref()
            .map_or("none".to_string(), |c| c.adapter_name().to_string()),
        table_markdown(&rows)
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
            let mut done = |r: &SpeedRow| {
                // Kept as each case finishes: a run stopped at its time limit keeps them.
                crate::app::bench::record::append_record(out, "records.jsonl", r);
                let s = |v: Option<f64>| v.map_or("failed".to_string(), |x| format!("{x:.3} s"));
                say(&format!(
                    "  {} ({} DOFs): f64 {}, mixed {}",
                    r.case,
                    r.dofs,
                    s(r.f64_seconds),
                    s(r.mixed_seconds)
                ));
            };
            let rows = mixed_speed(Size::Scale(scale), c, 1e-10, cs, k == 0, &mut done)
                .map_err(BenchError::Solve)?;
            md.push_str(&format!(
                "\nGPU f64 CG against mixed precision, both Jacobi with coarse correction \
                 `{}`, to residual tol 1e-10, best of {} solves after a warm-up, grid scale \
                 {scale}:\n",
                cs.name(),
                SPEED_REPS
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

/// One row of the `stickslip bench --hard` table.
#[derive(Debug, Clone, serde::Serialize)]
pub struct TableRow {
    pub case: String,
    pub dofs: usize,
    /// κ of the free block of Ĥ (dense eigen solve; None when too large for it).
    pub kappa: Option<f64>,
    pub solver: String,
    pub tol: f64,
    /// Whether the solver reported success.
    pub claimed: bool,
    /// Relative error against the reference (of the iterate reached, also on failure
    /// where the solver returns one; None otherwise).
    pub error: Option<f64>,
    pub iterations: Option<usize>,
    pub seconds: f64,
    pub note: String,
}

/// Runs every solver on every case of `suite(size)` and returns the rows. GPU rows need
/// `gpu` (a context); κ is computed for cases with at most `dense_max` free DOFs.
pub fn table(
    size: Size,
    gpu: Option<&crate::gpu::GpuContext>,
    dense_max: usize,
) -> Result<Vec<TableRow>, String> {
    let mut rows = Vec::new();
    for case in suite(size) {
        // 1. The case, its κ and its extended-precision reference.
        let e = case.eliminated();
        let kappa = (case.frames.free_dofs() <= dense_max).then(|| condition_number(&e));
        let r = reference(&e).map_err(|err| format!("{}: reference: {err}", case.name))?;
        let rows_of = CaseRows {
            case: &case,
            kappa,
            reference: &r.y,
        };
        // 2.–4. Every solver, timed, its answer checked against the reference.
        cpu_rows(&rows_of, &e, &mut rows);
        if let Some(ctx) = gpu {
            gpu_rows(&rows_of, ctx, &e, &mut rows);
        }
    }
    Ok(rows)
}

/// What every row of one case shares.
struct CaseRows<'a> {
    case: &'a HardCase,
    kappa: Option<f64>,
    reference: &'a [f64],
}

impl CaseRows<'_> {
    /// A row of this case: `y` the answer (None where the solver gave none).
    #[allow(clippy::too_many_arguments)]
    fn row(
        &self,
        solver: &str,
        tol: f64,
        claimed: bool,
        y: Option<&[f64]>,
        it: Option<usize>,
        s: f64,
        note: String,
    ) -> TableRow {
        TableRow {
            case: self.case.name.clone(),
            dofs: self.case.ndof(),
            kappa: self.kappa,
            solver: solver.into(),
            tol,
            claimed,
            error: y.map(|y| relative_error(y, self.reference)),
            iterations: it,
            seconds: s,
            note,
        }
    }
}

/// Cholesky, then the CPU CG with each preconditioner and coarse correction, to 1e-10.
fn cpu_rows(c: &CaseRows, e: &Eliminated, rows: &mut Vec<TableRow>) {
    use crate::solve::cg::{Preconditioner, Scaling};
    use crate::solve::coarse::CoarseSpace;
    use crate::{CgTuning, SolveDetails, SolverConfig, Step};
    use std::time::Instant;
    let t = Instant::now();
    match solve_once(SolverConfig::cholesky(), e) {
        Ok(Step { y, .. }) => rows.push(c.row(
            "cholesky",
            0.0,
            true,
            Some(&y),
            None,
            t.elapsed().as_secs_f64(),
            String::new(),
        )),
        Err(err) => rows.push(c.row(
            "cholesky",
            0.0,
            false,
            None,
            None,
            t.elapsed().as_secs_f64(),
            err.to_string(),
        )),
    }
    // Default coarse correction (aggregates) unless the name says otherwise.
    for (name, pc, scaling, coarse) in [
        (
            "cg jacobi",
            Preconditioner::Jacobi,
            Scaling::None,
            CoarseSpace::Aggregates,
        ),
        (
            "cg jacobi translations",
            Preconditioner::Jacobi,
            Scaling::None,
            CoarseSpace::Translations,
        ),
        (
            "cg jacobi no coarse",
            Preconditioner::Jacobi,
            Scaling::None,
            CoarseSpace::None,
        ),
        (
            "cg block-jacobi",
            Preconditioner::BlockJacobi,
            Scaling::None,
            CoarseSpace::Aggregates,
        ),
        (
            "cg none",
            Preconditioner::None,
            Scaling::None,
            CoarseSpace::Aggregates,
        ),
        (
            "cg none+scaling",
            Preconditioner::None,
            Scaling::NodeDiagonal,
            CoarseSpace::Aggregates,
        ),
    ] {
        let tol = 1e-10;
        let config = SolverConfig::cg()
            .tol(tol)
            .max_iters(20_000)
            .preconditioner(pc)
            .coarse(coarse)
            .cg_tuning(CgTuning {
                scaling,
                ..CgTuning::default()
            });
        let t = Instant::now();
        match solve_once(config, e) {
            Ok(Step { y, stats, .. }) => rows.push(
                c.row(
                    name,
                    tol,
                    true,
                    Some(&y),
                    stats.iterations,
                    t.elapsed().as_secs_f64(),
                    match stats.details {
                        SolveDetails::Cg(info) => info
                            .condition_estimate
                            .map_or(String::new(), |k| format!("κ̃(M⁻¹Ĥ) {k:.1e}")),
                        _ => String::new(),
                    },
                ),
            ),
            Err(err) => rows.push(c.row(
                name,
                tol,
                false,
                None,
                None,
                t.elapsed().as_secs_f64(),
                err.to_string(),
            )),
        }
    }
}

/// The GPU CG in each precision (mixed also with each coarse correction and with
/// extended-precision refinement).
fn gpu_rows(c: &CaseRows, ctx: &crate::gpu::GpuContext, e: &Eliminated, rows: &mut Vec<TableRow>) {
    use crate::gpu::Precision;
    use crate::solve::coarse::CoarseSpace;
    use crate::{SolveDetails, SolverConfig};
    use std::time::Instant;
    for (precision, tol, error_tol, coarse) in [
        (Precision::F32, 1e-5, None, CoarseSpace::Aggregates),
        (Precision::F64, 1e-10, None, CoarseSpace::Aggregates),
        (Precision::Mixed, 1e-10, None, CoarseSpace::Aggregates),
        (Precision::Mixed, 1e-10, None, CoarseSpace::Translations),
        (Precision::Mixed, 1e-10, None, CoarseSpace::None),
        (
            Precision::Mixed,
            1e-10,
            Some(1e-10),
            CoarseSpace::Aggregates,
        ),
    ] {
        let suffix = match coarse {
            CoarseSpace::None => " no coarse",
            CoarseSpace::Translations => " translations",
            CoarseSpace::Aggregates => "",
        };
        let name = match error_tol {
            Some(et) => format!("gpu {precision} error_tol {et:.0e}{suffix}"),
            None => format!("gpu {precision}{suffix}"),
        };
        let t = Instant::now();
        let mut config = SolverConfig::gpu(precision)
            .tol(tol)
            .max_iters(20_000)
            .coarse(coarse)
            .gpu_context(ctx.clone());
        config.error_tol = error_tol;
        let res = solve_once(config, e).and_then(|step| match step.stats.details {
            SolveDetails::Gpu(info) => Ok((step.y, *info)),
            _ => Err(crate::Error::Gpu(crate::gpu::GpuError::Internal(
                "not a GPU solve".into(),
            ))),
        });
        match res {
            Ok((y, info)) => rows.push(
                c.row(
                    &name,
                    tol,
                    true,
                    Some(&y),
                    Some(info.iterations),
                    info.seconds.solve,
                    info.error_estimate
                        .map(|est| format!("error estimate {est:.1e}"))
                        .into_iter()
                        .chain(info.fallback.map(|f| format!("fell back to f64: {f}")))
                        .chain(info.notes.into_iter().filter(|n| n.starts_with("mixed: Ĥ")))
                        .collect::<Vec<_>>()
                        .join("; "),
                ),
            ),
            Err(err) => rows.push(c.row(
                &name,
                tol,
                false,
                None,
                None,
                t.elapsed().as_secs_f64(),
                err.to_string(),
            )),
        }
    }
}

/// One solve of `e` with a fresh solver of `config`.
fn solve_once(config: crate::SolverConfig, e: &Eliminated) -> Result<crate::Step, crate::Error> {
    crate::Solver::new(config)?.solve_eliminated(crate::LayoutKey::fresh(), e)
}

/// The rows as a Markdown table.
pub fn table_markdown(rows: &[TableRow]) -> String {
    let mut s = String::from(
        "| case | DOFs | κ(Ĥ_free) | solver | tol | claimed | rel. error | iterations | seconds | note |\n|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        let note: String = r.note.replace('|', "/").chars().take(90).collect();
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {:.4} | {} |\n",
            r.case,
            r.dofs,
            r.kappa.map_or("—".into(), |k| format!("{k:.1e}")),
            r.solver,
            if r.tol == 0.0 {
                "—".into()
            } else {
                format!("{:.0e}", r.tol)
            },
            if r.claimed { "yes" } else { "**no**" },
            r.error.map_or("—".into(), |e| format!("{e:.1e}")),
            r.iterations.map_or("—".into(), |i| i.to_string()),
            r.seconds,
            note
        ));
    }
    s
}

/// Timed solves per solver in [`mixed_speed`] (after one warm-up solve).
pub const SPEED_REPS: usize = 5;

/// One case of [`mixed_speed`]: best solve seconds, iterations and relative error of GPU
/// f64 CG and of mixed precision (None for a failed solve).
#[derive(Debug, Clone, serde::Serialize)]
pub struct SpeedRow {
    pub case: String,
    pub dofs: usize,
    /// The coarse correction both solvers used.
    pub coarse: String,
    pub f64_seconds: Option<f64>,
    pub mixed_seconds: Option<f64>,
    pub f64_iterations: Option<usize>,
    pub mixed_iterations: Option<usize>,
    pub f64_error: Option<f64>,
    pub mixed_error: Option<f64>,
    /// Why mixed left f32, when it did.
    pub mixed_fallback: Option<String>,
}

/// GPU f64 CG against mixed precision on larger cases, both Jacobi with the coarse
/// correction `coarse`, at tolerance `tol`, best of [`SPEED_REPS`] after a warm-up. The
/// cantilever cases (`neohookean-nu0.49`, `dt-1e2`) run at `size`, and with
/// `cantilevers_twice` at twice its scale too. `progress` sees each row when it is done.
pub fn mixed_speed(
    size: Size,
    ctx: &crate::gpu::GpuContext,
    tol: f64,
    coarse: crate::solve::coarse::CoarseSpace,
    cantilevers_twice: bool,
    progress: &mut dyn FnMut(&SpeedRow),
) -> Result<Vec<SpeedRow>, String> {
    use crate::gpu::Precision;
    use crate::{LayoutKey, SolveDetails, Solver, SolverConfig};
    // The two cantilever cases have a sixth of the others' DOFs at one grid scale, so they
    // run at twice the scale too: every case then has an instance of 81k–107k DOFs at
    // scale 5 ("the larger cases"), and the smaller ones show where mixed stops paying.
    let twice = Size::Scale(2 * size.k());
    let mut cases = vec![stiffness_contrast(size, 1e4), incompressible(size, 0.49)];
    if cantilevers_twice {
        cases.push(incompressible(twice, 0.49));
    }
    cases.push(time_step(size, 1e2));
    if cantilevers_twice {
        cases.push(time_step(twice, 1e2));
    }
    cases.extend([
        near_axis_normals(size),
        conditioned(size, 1e6, false),
        conditioned(size, 1e8, true),
    ]);
    let mut out = Vec::new();
    for case in cases {
        let e = case.eliminated();
        let r = reference(&e).map_err(|err| format!("{}: reference: {err}", case.name))?;
        // (best seconds, iterations, error, fallback) per solver.
        type Best = Option<(f64, usize, f64, Option<String>)>;
        let mut res: [Best; 2] = [None, None];
        // Both solvers built first, then solved alternately, best of SPEED_REPS after one
        // warm-up solve each: the ratio of one run on a shared 2-core machine is noise.
        let layout = LayoutKey::fresh();
        let mut solvers: Vec<Option<Solver>> = [Precision::F64, Precision::Mixed]
            .into_iter()
            .map(|precision| {
                let config = SolverConfig::gpu(precision)
                    .tol(tol)
                    .max_iters(50_000)
                    .coarse(coarse)
                    .gpu_context(ctx.clone());
                // The warm-up solve (rep 0) builds the device buffers; later reps reuse them.
                Solver::new(config).ok()
            })
            .collect();
        for rep in 0..=SPEED_REPS {
            for (k, sol) in solvers.iter_mut().enumerate() {
                let Some(sol) = sol else { continue };
                let solved =
                    sol.solve_eliminated(layout, &e)
                        .map(|step| match step.stats.details {
                            SolveDetails::Gpu(info) => Some((step.y, *info)),
                            _ => None,
                        });
                if let Ok(Some((y, info))) = solved {
                    if rep > 0 {
                        let best = res[k]
                            .as_ref()
                            .map_or(info.seconds.solve, |b| b.0.min(info.seconds.solve));
                        res[k] = Some((
                            best,
                            info.iterations,
                            relative_error(&y, &r.y),
                            info.fallback.clone(),
                        ));
                    }
                }
            }
        }
        let [a, b] = res;
        out.push(SpeedRow {
            case: case.name.clone(),
            dofs: case.ndof(),
            coarse: coarse.name().into(),
            f64_seconds: a.as_ref().map(|v| v.0),
            mixed_seconds: b.as_ref().map(|v| v.0),
            f64_iterations: a.as_ref().map(|v| v.1),
            mixed_iterations: b.as_ref().map(|v| v.1),
            f64_error: a.as_ref().map(|v| v.2),
            mixed_error: b.as_ref().map(|v| v.2),
            mixed_fallback: b.and_then(|v| v.3),
        });
        if let Some(row) = out.last() {
            progress(row);
        }
    }
    Ok(out)
}
