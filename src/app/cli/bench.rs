//! `stickslip bench`: the checks made before a long run, then the benchmark chosen (the
//! ladder, `--hard`, `--newton` or `--systems`).

use crate::app::cli::args::BenchArgs;
use crate::app::cli::error::{write_failed, CliError};
use crate::app::cli::info::check_adapter_name;
use crate::error::InputError;
use crate::solve::coarse::CoarseSpace;
use std::path::Path;

/// `stickslip bench`: see [`crate::app::bench`].
pub fn bench(a: &BenchArgs, quiet: bool) -> Result<(), CliError> {
    if !a.no_gpu {
        check_adapter_name()?;
    }
    // Fail before a long run, not after it, when the output folder cannot be written.
    if let Some(out) = &a.out {
        let shown = out.display().to_string();
        if std::fs::metadata(out).is_ok_and(|m| !m.is_dir()) {
            return Err(InputError::new(&shown, "--out", "is a file, not a folder").into());
        }
        std::fs::create_dir_all(out).map_err(|e| write_failed(&shown, e))?;
        let probe = out.join(".stickslip-write-probe");
        std::fs::write(&probe, b"").map_err(|e| write_failed(&shown, e))?;
        let _ = std::fs::remove_file(&probe);
        // records.jsonl holds this run's records (appended as each one finishes): an
        // earlier run's go first.
        match std::fs::remove_file(out.join("records.jsonl")) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(write_failed(&shown, e));
            }
            _ => {}
        }
    }
    if a.newton {
        return bench_newton(a, quiet);
    }
    if let Some(dir) = &a.systems {
        return bench_systems(dir, a, quiet);
    }
    if a.hard {
        let coarse = match a.coarse {
            Some(c) => vec![c],
            None => vec![CoarseSpace::Aggregates, CoarseSpace::Translations],
        };
        let md = crate::app::bench::hard_suite::run_hard(
            a.out.as_deref(),
            a.no_gpu,
            a.hard_scale,
            &coarse,
            quiet,
        )
        .map_err(|e| CliError::Failed(format!("bench --hard: {e}")))?;
        if !quiet {
            println!("{md}");
        }
        return Ok(());
    }
    if let Some(d) = a.dims.iter().find(|&&d| d != 2 && d != 3) {
        return Err(InputError::new(
            "command line",
            "--dims",
            format!("dimension {d} is not 2 or 3"),
        )
        .into());
    }
    if a.sizes.as_ref().is_some_and(|s| s.iter().any(|&n| n < 4)) {
        return Err(InputError::new(
            "command line",
            "--sizes",
            "every size must be at least 4 nodes",
        )
        .into());
    }
    let opts = crate::app::bench::ladder::BenchOptions {
        quick: a.quick,
        sizes: a.sizes.clone(),
        dims: a.dims.clone(),
        no_gpu: a.no_gpu,
        oracle_max_nodes: a.oracle_max_nodes,
        out: a.out.clone(),
        quiet,
        seed: a.seed,
        coarse: a.coarse.unwrap_or_default(),
        ordering: a.ordering,
    };
    let command: Vec<String> = std::env::args().collect();
    let report =
        crate::app::bench::ladder::run(&opts, &command.join(" ")).map_err(|e| match e {
            crate::app::bench::ladder::BenchError::Io(m) => CliError::Failed(m),
            crate::app::bench::ladder::BenchError::Solve(m) => {
                CliError::Failed(format!("bench: {m}"))
            }
        })?;
    if !quiet {
        println!("{}", crate::app::bench::tables::summary_text(&report));
    }
    Ok(())
}

/// `stickslip bench --systems DIR`: see [`crate::app::bench::systems`].
fn bench_systems(dir: &Path, a: &BenchArgs, quiet: bool) -> Result<(), CliError> {
    use crate::app::bench::systems as bs;
    let shown = dir.display().to_string();
    if !dir.is_dir() {
        return Err(InputError::new(&shown, "--systems", "is not a folder").into());
    }
    let found =
        bs::find_systems(dir).map_err(|e| CliError::Failed(format!("cannot read {shown}: {e}")))?;
    if found.is_empty() {
        return Err(InputError::new(
            &shown,
            "--systems",
            "holds no system (a folder with H.mtx, g.mtx and bc.json; `run --dump-systems` writes them)",
        )
        .into());
    }
    let mut progress = |r: &bs::SystemRecord| {
        if !quiet {
            eprintln!(
                "{} {}: {}",
                r.system,
                r.solver,
                match (&r.error, r.iterations, r.solve_s) {
                    (Some(e), _, _) => format!("failed: {e}"),
                    (None, k, Some(t)) => format!(
                        "{:.4} s setup, {t:.4} s solve, {} iterations",
                        r.setup_s.unwrap_or(0.0),
                        k.map_or("–".into(), |k| k.to_string())
                    ),
                    _ => String::new(),
                }
            );
        }
    };
    bs::check_all(&found)?;
    let records = bs::run(dir, &found, a.no_gpu, &mut progress)?;
    if let Some(out) = &a.out {
        let json = serde_json::json!({
            "command": std::env::args().collect::<Vec<_>>().join(" "),
            "tolerance": bs::TOL,
            "records": records,
        });
        let path = out.join("bench.json");
        crate::io::files::write_atomic_bytes(&path, json.to_string().as_bytes())
            .map_err(|e| write_failed(&path.display().to_string(), e))?;
    }
    // The table is the result, on stdout: --quiet silences only the progress lines.
    print!("{}", bs::table(&records));
    Ok(())
}

/// `stickslip bench --newton`: see [`crate::app::bench::newton`].
fn bench_newton(a: &BenchArgs, quiet: bool) -> Result<(), CliError> {
    let opts = crate::app::bench::newton::NewtonOptions {
        quick: a.quick,
        sizes: a.sizes.clone(),
        no_gpu: a.no_gpu,
        reps: a.reps,
        out: a.out.clone(),
        quiet,
    };
    crate::app::bench::newton::plan(&opts)?;
    let command: Vec<String> = std::env::args().collect();
    let report =
        crate::app::bench::newton::run(&opts, &command.join(" ")).map_err(|e| match e {
            crate::app::bench::newton::NewtonBenchError::Gpu(m) => CliError::Failed(m),
            crate::app::bench::newton::NewtonBenchError::Io(m) => CliError::Failed(m),
        })?;
    if !quiet {
        print!(
            "{}",
            crate::app::bench::newton_report::summary_text(&report)
        );
    }
    Ok(())
}
