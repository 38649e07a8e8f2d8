//! The library facade (`Problem`, `Solver`, `SolverConfig`) against the dense KKT solve,
//! with every solver and precision, value updates that reuse the analysis, and errors.
//!
//! Tolerances: the generated Hessians have κ of order 1e2–1e3 (tests/kkt.rs), so a
//! backward-stable f64 solve keeps ≥ 12 digits (oracle ≤ 1e-9 relative to the KKT
//! solution) and CG at a relative residual of 1e-12 keeps ≥ 8 (≤ 1e-8). f32 CG stopped
//! at 1e-6 is within κ·1e-6 ≤ 1e-3 in theory; f32 on these systems reaches ≤ 1e-4
//! (checked by tests/gpu_solver.rs on the same generator). The constraints must hold to
//! f64 rounding in every precision: Δx is recovered from the f64 frames.

mod common;

use common::kkt::{dense_kkt, global_b};
use nalgebra::DVector;
use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::{
    CgTuning, Constraint, Error, GpuTuning, Precision, Problem, SolveDetails, Solver, SolverConfig,
    SolverKind,
};

/// H's stored entries as triplets (both triangles).
fn triplets(h: &stickslip::core::sparse::BlockCsr) -> Vec<(usize, usize, f64)> {
    let d = h.dim;
    let mut t = Vec::new();
    for i in 0..h.n {
        for k in h.row_ptr[i]..h.row_ptr[i + 1] {
            let j = h.col_idx[k];
            for (a, &v) in h.block(k).iter().enumerate() {
                t.push((i * d + a / d, j * d + a % d, v));
            }
        }
    }
    t
}

fn rel(a: &[f64], b: &DVector<f64>) -> f64 {
    let d: f64 = a.iter().zip(b.iter()).map(|(x, y)| (x - y) * (x - y)).sum();
    d.sqrt() / b.norm().max(f64::MIN_POSITIVE)
}

/// The configurations to check, with the error bound each must meet; the GPU ones only
/// when a device is there.
fn configs(gpu: Option<&stickslip::gpu::GpuContext>) -> Vec<(SolverConfig, f64)> {
    let mut v = vec![
        (SolverConfig::cholesky(), 1e-9),
        (SolverConfig::cg().tol(1e-12), 1e-8),
    ];
    if let Some(ctx) = gpu {
        for (p, tol, bound) in [
            (Precision::F64, 1e-12, 1e-8),
            (Precision::Mixed, 1e-12, 1e-8),
            (Precision::F32, 1e-6, 1e-4),
        ] {
            v.push((
                SolverConfig::gpu(p).tol(tol).gpu_context(ctx.clone()),
                bound,
            ));
        }
    }
    v
}

#[test]
fn every_solver_matches_the_dense_kkt_solve() {
    let gpu = common::gpu::gpu();
    let ctx = gpu.as_ref().map(|(c, _)| *c);
    let mut solvers: Vec<(Solver, f64)> = configs(ctx)
        .into_iter()
        .map(|(c, b)| (Solver::new(c).expect("solver starts"), b))
        .collect();
    for case in 0..12u64 {
        let dim = 2 + (case % 2) as usize;
        let s = random_system(&SystemSpec::small(dim, 100 + case));
        let n = s.h.n;
        let problem = Problem::from_triplets(dim, n, &triplets(&s.h), &s.g, &s.constraints)
            .expect("a generated system is valid");
        let (b, p) = global_b(dim, n, &s.constraints);
        let kkt = dense_kkt(&s.h.to_dense(), &s.g, &b, &p);
        for (solver, bound) in solvers.iter_mut() {
            let name = format!(
                "case {case} {} {}",
                solver.config().kind,
                solver.config().precision
            );
            let sol = solver
                .solve(&problem)
                .unwrap_or_else(|e| panic!("{name}: {e}"));
            let err = rel(&sol.dx, &kkt.dx);
            assert!(err <= *bound, "{name}: relative error {err:e} > {bound:e}");
            // BΔx = p to f64 rounding whatever the solver's arithmetic.
            let dx = DVector::from_column_slice(&sol.dx);
            let miss = (&b * &dx - &p).norm() / dx.norm().max(1.0);
            assert!(miss <= 1e-12, "{name}: ‖BΔx − p‖/‖Δx‖ = {miss:e}");
            if solver.config().kind == SolverKind::Cholesky {
                let r = rel(&sol.reactions, &kkt.bt_lambda);
                assert!(r <= 1e-8, "{name}: reactions vs Bᵀλ {r:e}");
            }
            assert!(sol.stats.relative_residual.is_finite());
        }
    }
}

#[test]
fn a_reused_solver_gives_the_answers_of_fresh_solvers() {
    let gpu = common::gpu::gpu();
    let ctx = gpu.as_ref().map(|(c, _)| *c);
    let s = random_system(&SystemSpec::small(3, 7));
    let base = triplets(&s.h);
    let mut problem = Problem::from_triplets(3, s.h.n, &base, &s.g, &s.constraints).expect("valid");
    let key = problem.layout();
    let mut kept: Vec<(Solver, f64)> = configs(ctx)
        .into_iter()
        .map(|(c, b)| (Solver::new(c).expect("solver starts"), b))
        .collect();
    for it in 0..5 {
        // A Newton-like update: values change, the pattern and constraints do not.
        let scale = 1.0 + 0.3 * it as f64;
        let t: Vec<_> = base.iter().map(|&(r, c, v)| (r, c, v * scale)).collect();
        let g: Vec<f64> =
            s.g.iter()
                .enumerate()
                .map(|(k, v)| v + 0.01 * (k as f64 + it as f64).sin())
                .collect();
        problem.update_values(&t, &g).expect("same pattern");
        assert_eq!(problem.layout(), key);
        for (solver, bound) in kept.iter_mut() {
            let reused = solver.solve(&problem).expect("solves");
            let mut fresh = Solver::new(solver.config().clone()).expect("starts");
            let again = fresh.solve(&problem).expect("solves");
            let name = format!(
                "update {it} {} {}",
                solver.config().kind,
                solver.config().precision
            );
            // Reuse is reported from the second solve on by the solvers that keep state.
            if solver.config().kind != SolverKind::Cg {
                assert_eq!(reused.stats.reused, it > 0, "{name}");
            }
            let diff = rel(&reused.dx, &DVector::from_column_slice(&again.dx));
            assert!(diff <= *bound, "{name}: reused vs fresh {diff:e}");
        }
    }
}

#[test]
fn stats_carry_each_solvers_own_report() {
    let s = random_system(&SystemSpec::small(2, 3));
    let problem =
        Problem::from_triplets(2, s.h.n, &triplets(&s.h), &s.g, &s.constraints).expect("valid");
    let sol = Solver::new(SolverConfig::cholesky())
        .and_then(|mut s| s.solve(&problem))
        .expect("solves");
    assert!(matches!(sol.stats.details, SolveDetails::Cholesky(ref i) if i.factor_nnz > 0));
    assert_eq!(sol.stats.iterations, None);
    let sol = Solver::new(SolverConfig::cg())
        .and_then(|mut s| s.solve(&problem))
        .expect("solves");
    assert!(matches!(sol.stats.details, SolveDetails::Cg(_)));
    assert!(sol.stats.iterations.is_some_and(|i| i > 0));
    assert!(sol.stats.relative_residual <= 1e-8);
}

#[test]
fn bad_configurations_and_unsolvable_systems_are_errors() {
    let input = |r: Result<Solver, Error>| match r {
        Err(Error::Input(e)) => e.to_string(),
        Err(e) => panic!("not an input error: {e}"),
        Ok(_) => panic!("accepted"),
    };
    assert!(input(Solver::new(SolverConfig::cg().tol(0.0))).contains("tol"));
    assert!(input(Solver::new(SolverConfig::cg().tol(f64::NAN))).contains("tol"));
    assert!(input(Solver::new(SolverConfig::cg().max_iters(0))).contains("max_iters"));
    assert!(input(Solver::new(SolverConfig::cg().error_tol(1e-10))).contains("error_tol"));
    let mut f32_cpu = SolverConfig::cholesky();
    f32_cpu.precision = Precision::F32;
    assert!(input(Solver::new(f32_cpu)).contains("precision"));

    // An indefinite H: −1 on the diagonal of a free node.
    let mut t = Vec::new();
    for i in 0..6 {
        t.push((i, i, if i == 4 { -1.0 } else { 2.0 }));
    }
    let problem =
        Problem::from_triplets(3, 2, &t, &[0.1; 6], &[Constraint::sticky(0)]).expect("well-formed");
    match Solver::new(SolverConfig::cholesky()).and_then(|mut s| s.solve(&problem)) {
        Err(Error::Solve(e)) => assert!(e.to_string().contains("not positive definite"), "{e}"),
        other => panic!("expected a solve error, got {other:?}"),
    }
    match Solver::new(SolverConfig::cg()).and_then(|mut s| s.solve(&problem)) {
        Err(Error::Solve(_)) => {}
        other => panic!("expected a solve error, got {other:?}"),
    }
}

/// A system larger than the device memory in force is refused through the facade as the
/// typed [`GpuError::DoesNotFit`], carrying the bytes the solve needs (what the device
/// PCG's memory plan counts) and the bytes in force; with exactly that many bytes the
/// same solve runs.
#[test]
fn a_system_over_the_device_memory_is_a_typed_does_not_fit() {
    use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
    use stickslip::gpu::{GpuError, PcgSolver};
    let Some((ctx, _g)) = common::gpu::gpu() else {
        return;
    };
    let s = random_system(&SystemSpec::small(3, 5));
    let problem = Problem::from_triplets(3, s.h.n, &triplets(&s.h), &s.g, &s.constraints)
        .expect("a generated system is valid");
    // f32 resolves a relative residual of 1e-6, not the default 1e-8.
    let config = |limit| {
        SolverConfig::gpu(Precision::F32)
            .tol(1e-6)
            .gpu_tuning(GpuTuning {
                memory_limit: Some(limit),
                ..GpuTuning::default()
            })
            .gpu_context(ctx.clone())
    };
    let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
    let planned =
        PcgSolver::memory_needed(ctx, &e, &config(u64::MAX).gpu_params()).expect("a plan");
    let mut small = Solver::new(config(planned - 1)).expect("the solver starts");
    match small.solve(&problem) {
        Err(Error::Gpu(GpuError::DoesNotFit { need, limit, .. })) => {
            assert_eq!((need, limit), (planned, planned - 1));
        }
        other => panic!("expected DoesNotFit, got {other:?}"),
    }
    let mut exact = Solver::new(config(planned)).expect("the solver starts");
    assert!(exact.solve(&problem).is_ok());
}

/// The CPU CG's iterations, relative residual and whether it ran equilibrated.
fn cg_run(config: SolverConfig, problem: &Problem) -> Result<(usize, f64, bool), Error> {
    let sol = Solver::new(config)?.solve(problem)?;
    match sol.stats.details {
        SolveDetails::Cg(info) => Ok((info.iterations, info.relative_residual, info.scaled)),
        other => panic!("expected a CPU CG report, got {other:?}"),
    }
}

/// A setting given once reaches the CPU CG that runs, in whatever order the builder gets
/// it beside a custom [`CgTuning`]: the tolerance (a loose one stops earlier than a tight
/// one, each met), the iteration limit (a limit of 2 stops the solve there) and the tuning
/// itself (equilibration, which the report shows).
#[test]
fn shared_settings_and_the_cg_tuning_both_reach_the_cpu_cg() {
    use stickslip::solve::cg::Scaling;
    let s = random_system(&SystemSpec::small(3, 21));
    let problem = Problem::from_triplets(3, s.h.n, &triplets(&s.h), &s.g, &s.constraints)
        .expect("a generated system is valid");
    let tuning = CgTuning {
        scaling: Scaling::NodeDiagonal,
        check_every: 8,
        ..CgTuning::default()
    };
    let (loose_its, loose_res, loose_scaled) =
        cg_run(SolverConfig::cg().tol(1e-3).cg_tuning(tuning), &problem).expect("solves");
    let (tight_its, tight_res, tight_scaled) =
        cg_run(SolverConfig::cg().cg_tuning(tuning).tol(1e-12), &problem).expect("solves");
    assert!(
        loose_scaled && tight_scaled,
        "the tuning's equilibration ran"
    );
    assert!(loose_res <= 1e-3, "loose: residual {loose_res:e} > 1e-3");
    assert!(tight_res <= 1e-12, "tight: residual {tight_res:e} > 1e-12");
    assert!(
        loose_its < tight_its,
        "tol 1e-3 took {loose_its} iterations, tol 1e-12 {tight_its}"
    );
    let limited = cg_run(
        SolverConfig::cg().cg_tuning(tuning).tol(1e-12).max_iters(2),
        &problem,
    );
    match limited {
        Err(e) => assert!(e.to_string().contains("iteration limit 2"), "{e}"),
        Ok((its, res, _)) => panic!("max_iters 2 was not in force: {its} iterations, {res:e}"),
    }
    // The tolerance a running solver is given replaces the configured one.
    let mut solver = Solver::new(SolverConfig::cg().tol(1e-3).cg_tuning(tuning)).expect("starts");
    solver.set_tol(1e-12).expect("a valid tolerance");
    let sol = solver.solve(&problem).expect("solves");
    assert!(sol.stats.relative_residual <= 1e-12);
    assert_eq!(sol.stats.iterations, Some(tight_its));
}

/// A setting given once reaches the GPU CG that runs beside a custom [`GpuTuning`]: the
/// tolerance (met, and a loose one stops earlier) and the tuning's f32 difference form,
/// which the report shows in both settings.
#[test]
fn shared_settings_and_the_gpu_tuning_both_reach_the_gpu_cg() {
    use stickslip::gpu::DifferenceForm;
    let Some((ctx, _g)) = common::gpu::gpu() else {
        return;
    };
    let s = random_system(&SystemSpec::small(3, 21));
    let problem = Problem::from_triplets(3, s.h.n, &triplets(&s.h), &s.g, &s.constraints)
        .expect("a generated system is valid");
    let run = |config: SolverConfig| {
        let sol = Solver::new(config.gpu_context(ctx.clone()))
            .and_then(|mut s| s.solve(&problem))
            .expect("solves");
        match sol.stats.details {
            SolveDetails::Gpu(info) => *info,
            other => panic!("expected a GPU report, got {other:?}"),
        }
    };
    for (form, on) in [(DifferenceForm::On, true), (DifferenceForm::Off, false)] {
        let tuning = GpuTuning {
            f32_difference: form,
            ..GpuTuning::default()
        };
        let loose = run(SolverConfig::gpu(Precision::F32)
            .tol(1e-2)
            .gpu_tuning(tuning));
        let tight = run(SolverConfig::gpu(Precision::F32)
            .gpu_tuning(tuning)
            .tol(1e-5));
        for (info, tol) in [(&loose, 1e-2), (&tight, 1e-5)] {
            assert_eq!(info.f32_difference, on, "{form:?} at tol {tol:e}");
            assert!(
                info.relative_residual <= tol,
                "{form:?}: residual {:e} > {tol:e}",
                info.relative_residual
            );
        }
        assert!(
            loose.iterations < tight.iterations,
            "{form:?}: tol 1e-2 took {} iterations, tol 1e-5 {}",
            loose.iterations,
            tight.iterations
        );
    }
}
