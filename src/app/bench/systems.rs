//! `stickslip bench --systems DIR`: every solver and preconditioner on the Newton systems a
//! simulation captured (`run --dump-systems`), to one relative residual, timed.
//!
//! A system is a folder holding H.mtx, g.mtx and bc.json (found at any depth under DIR).
//! Each is solved by Cholesky, by the CPU CG with Jacobi and block Jacobi, each with no
//! coarse space, the rigid translations and the aggregates, by the CPU CG with the
//! multilevel preconditioner, and (unless `--no-gpu`) by the GPU CG in f64 with Jacobi and
//! aggregates and with the multilevel preconditioner; setup (analysis or upload, and the
//! multilevel levels) and solve are timed
//! apart, with the iterations and the true relative residual beside them.

use crate::app::system_files::{read_system, SystemFiles};
use crate::core::problem::Problem;
use crate::engine::solver::{Solver, SolverConfig};
use crate::error::InputError;
use crate::solve::options::{CoarseSpace, Precision, Preconditioner};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The relative residual every iterative solver is run to.
pub const TOL: f64 = 1e-6;

/// One solver on one system.
#[derive(Debug, Clone, serde::Serialize)]
pub struct SystemRecord {
    /// The system's folder, relative to DIR.
    pub system: String,
    pub nodes: usize,
    pub solver: String,
    /// Analysis (Cholesky) or device upload and build (GPU) of a fresh solver, and the
    /// solve; None where the solver failed.
    pub setup_s: Option<f64>,
    pub solve_s: Option<f64>,
    pub iterations: Option<usize>,
    pub relative_residual: Option<f64>,
    /// Why the solver failed on this system.
    pub error: Option<String>,
}

/// The folders under `dir` that hold a system, sorted.
pub fn find_systems(dir: &Path) -> std::io::Result<Vec<PathBuf>> {
    let mut found = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        if ["H.mtx", "g.mtx", "bc.json"]
            .iter()
            .all(|f| d.join(f).is_file())
        {
            found.push(d.clone());
        }
        for e in std::fs::read_dir(&d)?.flatten() {
            if e.file_type().is_ok_and(|t| t.is_dir()) {
                stack.push(e.path());
            }
        }
    }
    found.sort_by_key(|p| natural_key(p));
    Ok(found)
}

/// Sorts `step_10` after `step_9`: the path's runs of digits compare as numbers.
fn natural_key(p: &Path) -> Vec<(String, u64)> {
    let s = p.display().to_string();
    let mut out = Vec::new();
    let mut text = String::new();
    let mut num: Option<u64> = None;
    for c in s.chars() {
        match c.to_digit(10) {
            Some(d) => num = Some(num.unwrap_or(0).saturating_mul(10).saturating_add(d as u64)),
            None => {
                if let Some(n) = num.take() {
                    out.push((std::mem::take(&mut text), n));
                }
                text.push(c);
            }
        }
    }
    out.push((text, num.unwrap_or(0)));
    out
}

/// The solvers compared: (name, configuration).
fn solvers(no_gpu: bool) -> Vec<(String, SolverConfig)> {
    let mut v = vec![("cholesky".to_string(), SolverConfig::cholesky())];
    for p in [Preconditioner::Jacobi, Preconditioner::BlockJacobi] {
        for c in [
            CoarseSpace::None,
            CoarseSpace::Translations,
            CoarseSpace::Aggregates,
        ] {
            v.push((
                format!("cg {} {}", p.name(), c.name()),
                SolverConfig::cg().preconditioner(p).coarse(c),
            ));
        }
    }
    v.push((
        "cg multilevel".to_string(),
        SolverConfig::cg().preconditioner(Preconditioner::Multilevel),
    ));
    if !no_gpu {
        v.push((
            "gpu f64 jacobi aggregates".into(),
            SolverConfig::gpu(Precision::F64)
                .preconditioner(Preconditioner::Jacobi)
                .coarse(CoarseSpace::Aggregates),
        ));
        v.push((
            "gpu f64 multilevel".into(),
            SolverConfig::gpu(Precision::F64).preconditioner(Preconditioner::Multilevel),
        ));
    }
    v.into_iter()
        .map(|(n, c)| (n, c.tol(TOL).max_iters(100_000)))
        .collect()
}

/// Reads one captured system with `solve`'s reader and checks: the same one-line input
/// error (exit 2, naming the file) on a malformed one.
pub fn read(dir: &Path) -> Result<Problem, InputError> {
    let s = |f: &str| dir.join(f).display().to_string();
    let files = SystemFiles {
        hessian: s("H.mtx"),
        gradient: s("g.mtx"),
        constraints: Some(s("bc.json")),
        constraint_matrix: None,
        constraint_values: None,
        dim: None,
    };
    let sys = read_system(&files)?;
    Ok(Problem::from_checked_parts(
        sys.h,
        sys.g,
        sys.constraints,
        sys.frames,
    ))
}

/// Reads every system before any is timed, so that a malformed one fails the bench at
/// once rather than after the others' timings.
pub fn check_all(systems: &[PathBuf]) -> Result<(), InputError> {
    for sys in systems {
        read(sys)?;
    }
    Ok(())
}

/// Runs every solver on every system of `systems` (found by [`find_systems`] under
/// `dir`, checked by [`check_all`]); `progress` sees each record as it finishes.
pub fn run(
    dir: &Path,
    systems: &[PathBuf],
    no_gpu: bool,
    progress: &mut dyn FnMut(&SystemRecord),
) -> Result<Vec<SystemRecord>, InputError> {
    let mut out = Vec::new();
    for sys in systems {
        let problem = read(sys)?;
        let name = match sys.strip_prefix(dir) {
            Ok(rel) if !rel.as_os_str().is_empty() => rel.display().to_string(),
            _ => sys.display().to_string(),
        };
        for (solver, config) in solvers(no_gpu) {
            let mut rec = SystemRecord {
                system: name.clone(),
                nodes: problem.n_nodes(),
                solver,
                setup_s: None,
                solve_s: None,
                iterations: None,
                relative_residual: None,
                error: None,
            };
            // A fresh solver per record: the setup is part of what is compared.
            let t = Instant::now();
            match Solver::new(config).and_then(|mut s| s.solve(&problem)) {
                Ok(sol) => {
                    let total = t.elapsed().as_secs_f64();
                    let setup = sol.stats.seconds.setup;
                    rec.setup_s = Some(setup);
                    rec.solve_s = Some((total - setup).max(0.0));
                    rec.iterations = sol.stats.iterations;
                    rec.relative_residual = Some(sol.stats.relative_residual);
                }
                Err(e) => rec.error = Some(e.to_string()),
            }
            progress(&rec);
            out.push(rec);
        }
    }
    Ok(out)
}

/// A Markdown table of the records, one row each.
pub fn table(records: &[SystemRecord]) -> String {
    let mut s = String::from(
        "| system | nodes | solver | setup s | solve s | iterations | relative residual |\n|---|---:|---|---:|---:|---:|---:|\n",
    );
    let f = |v: Option<f64>| v.map_or("–".to_string(), |x| format!("{x:.4}"));
    for r in records {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {} | {} | {} | {} |",
            r.system,
            r.nodes,
            r.solver,
            f(r.setup_s),
            f(r.solve_s),
            r.iterations.map_or("–".into(), |k| k.to_string()),
            match (&r.error, r.relative_residual) {
                (Some(e), _) => format!("failed: {e}"),
                (None, Some(x)) => format!("{x:.2e}"),
                (None, None) => "–".into(),
            }
        );
    }
    s
}
