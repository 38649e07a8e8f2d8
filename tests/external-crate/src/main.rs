//! Solves one 3D system with sticky, plane and line constraints with every solver the
//! library offers, reuses each solver after `update_values`, and checks the answers
//! against each other. Exits 1 on any disagreement; prints one line per solve.
//!
//! Agreement bound: the system below has κ ≈ 10 (diagonal 4 against off-diagonal −1 on a
//! chain), so every f64 solve (Cholesky, CG and GPU f64/mixed at tol 1e-12) agrees with
//! Cholesky to ≤ 1e-9 relative, and GPU f32 at tol 1e-6 to ≤ 1e-5.

use stickslip::{Constraint, Error, Precision, Problem, Solver, SolverConfig};

const N: usize = 30;

fn system(scale: f64) -> (Vec<(usize, usize, f64)>, Vec<f64>) {
    let mut t = Vec::new();
    for k in 0..3 * N {
        t.push((k, k, 4.0 * scale));
    }
    for i in 0..N - 1 {
        for a in 0..3 {
            let (p, q) = (3 * i + a, 3 * (i + 1) + a);
            t.push((p, q, -scale));
            t.push((q, p, -scale));
        }
    }
    let g = (0..3 * N).map(|k| ((k * 7 % 11) as f64 - 5.0) * 0.1 * scale).collect();
    (t, g)
}

fn rel(a: &[f64], b: &[f64]) -> f64 {
    let d: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum();
    let n: f64 = b.iter().map(|y| y * y).sum();
    (d / n).sqrt()
}

fn main() {
    match run() {
        Ok(()) => println!("external crate: all solvers agree"),
        Err(e) => {
            eprintln!("external crate: {e}");
            std::process::exit(1);
        }
    }
}

fn run() -> Result<(), String> {
    let constraints = vec![
        Constraint::sticky(0),
        Constraint::sticky(5).displacement(&[0.0, 0.01, 0.0]),
        Constraint::plane(10, &[0.3, 1.0, 0.2]).offset(0.002),
        Constraint::line(20, &[1.0, 1.0, 0.0]),
        Constraint::rows(25, &[&[1.0, 0.0, 0.0]], &[0.0]),
    ];
    let (t, g) = system(1.0);
    let mut problem =
        Problem::from_triplets(3, N, &t, &g, &constraints).map_err(|e| e.to_string())?;

    let mut configs = vec![
        ("cholesky", SolverConfig::cholesky(), 0.0),
        ("cg", SolverConfig::cg().tol(1e-12), 1e-9),
    ];
    let gpu_ok = match Solver::new(SolverConfig::gpu(Precision::F64)) {
        Ok(_) => true,
        Err(Error::Gpu(why)) => {
            if std::env::var("STICKSLIP_REQUIRE_GPU").is_ok_and(|v| v == "1") {
                return Err(format!("STICKSLIP_REQUIRE_GPU=1 but the GPU solver cannot start: {why}"));
            }
            println!("!!!!!!!! SKIP: no GPU ({why}); the GPU solvers did not run !!!!!!!!");
            false
        }
        Err(e) => return Err(e.to_string()),
    };
    if gpu_ok {
        configs.push(("gpu f64", SolverConfig::gpu(Precision::F64).tol(1e-12), 1e-9));
        configs.push(("gpu mixed", SolverConfig::gpu(Precision::Mixed).tol(1e-12), 1e-9));
        configs.push(("gpu f32", SolverConfig::gpu(Precision::F32).tol(1e-6), 1e-5));
    }
    let mut solvers: Vec<(&str, Solver, f64)> = Vec::new();
    for (name, config, bound) in configs {
        solvers.push((name, Solver::new(config).map_err(|e| format!("{name}: {e}"))?, bound));
    }

    for round in 0..2 {
        if round == 1 {
            // Same pattern, new values: every solver reuses what it built.
            let (t, g) = system(2.5);
            problem.update_values(&t, &g).map_err(|e| e.to_string())?;
        }
        let mut reference: Option<Vec<f64>> = None;
        for (name, solver, bound) in solvers.iter_mut() {
            let sol = solver.solve(&problem).map_err(|e| format!("{name}: {e}"))?;
            let dx = &sol.dx;
            // The constraints hold in every precision.
            let ok = dx[0..3].iter().all(|&v| v == 0.0)
                && (dx[16] - 0.01).abs() < 1e-15
                && (0.3 * dx[30] + dx[31] + 0.2 * dx[32] - 0.002).abs() < 1e-14
                && (dx[60] - dx[61]).abs() < 1e-14
                && dx[62].abs() < 1e-14
                && dx[75].abs() < 1e-14;
            if !ok {
                return Err(format!("{name}: a constraint is not met"));
            }
            let err = match &reference {
                None => {
                    reference = Some(dx.clone());
                    0.0
                }
                Some(r) => rel(dx, r),
            };
            if err > *bound {
                return Err(format!("{name}: differs from cholesky by {err:e} > {bound:e}"));
            }
            if round == 1 && *name != "cg" && !sol.stats.reused {
                return Err(format!("{name}: did not reuse its analysis after update_values"));
            }
            println!(
                "round {round} {name}: relative difference from cholesky {err:.1e}, residual {:.1e}, reused {}",
                sol.stats.relative_residual, sol.stats.reused
            );
        }
    }
    Ok(())
}
