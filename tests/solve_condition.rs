//! The CG's own condition estimate: κ̃(M⁻¹Ĥ) from its Lanczos coefficients, in `solve`'s
//! report and summary, with a warning where the residual tolerance does not bound the
//! error (κ̃·tol > 1e-2).

mod common;

use common::cli::{run, stderr, tmpdir};
use stickslip::cases::generate::{random_system, ConstraintMix, SystemSpec};
use stickslip::core::sparse::BlockCsr;
use stickslip::io::mtx;
use stickslip::{Preconditioner, Problem, SolveDetails, Solver, SolverConfig};

/// A dense SPD matrix Q diag(λ) Qᵀ (Q a product of Givens rotations) with the spectrum
/// λ_j = 10^(4 j/(n−1)): κ = 1e4 exactly, n = 12 distinct eigenvalues.
fn known_spectrum(n: usize) -> (Vec<f64>, f64) {
    let lambda: Vec<f64> = (0..n)
        .map(|j| 10f64.powf(4.0 * j as f64 / (n - 1) as f64))
        .collect();
    let mut q = vec![0.0; n * n];
    for i in 0..n {
        q[i * n + i] = 1.0;
    }
    // Rotations in every plane (i, i+1) and (i, i+2), by angles that mix all rows.
    for (step, i) in (0..n - 1).flat_map(|i| [(1, i), (2, i)]) {
        let j = i + step;
        if j >= n {
            continue;
        }
        let t = 0.3 + 0.17 * (i + step) as f64;
        let (c, s) = (t.cos(), t.sin());
        for r in 0..n {
            let (a, b) = (q[r * n + i], q[r * n + j]);
            q[r * n + i] = c * a - s * b;
            q[r * n + j] = s * a + c * b;
        }
    }
    let mut a = vec![0.0; n * n];
    for r in 0..n {
        for c in 0..n {
            a[r * n + c] = (0..n)
                .map(|k| q[r * n + k] * lambda[k] * q[c * n + k])
                .sum();
        }
    }
    (a, lambda[n - 1] / lambda[0])
}

/// Lanczos' extreme Ritz values lie inside [λ_min, λ_max] and converge to them from
/// inside; once the Krylov space holds the extreme eigenvectors (n = 12 dimensions here,
/// which CG to 1e-12 at κ = 1e4 fills) they are the extreme eigenvalues up to rounding.
/// So the estimate is at most κ (up to rounding: 1e-9 relative, far above what a
/// tridiagonal of a few dozen rows rounds to at κ = 1e4) and close to it from below:
/// 1e-6 relative leaves room for the loss of orthogonality of an f64 Lanczos run, which
/// repeats eigenvalues but does not move the extreme ones past it.
#[test]
fn the_cg_estimate_matches_the_condition_number_of_a_known_spectrum() {
    let n = 12;
    let (a, kappa) = known_spectrum(n);
    // Symmetrize exactly: the reader-free path still checks symmetry.
    let triplets: Vec<(usize, usize, f64)> = (0..n)
        .flat_map(|r| (0..n).map(move |c| (r, c)))
        .map(|(r, c)| (r, c, 0.5 * (a[r * n + c] + a[c * n + r])))
        .collect();
    let h = BlockCsr::from_triplets(2, n, &triplets, false);
    let g: Vec<f64> = (0..n).map(|i| 1.0 + 0.1 * i as f64).collect();
    let problem = Problem::from_blocks(h, g, &[]).expect("an SPD system");
    let config = SolverConfig::cg()
        .preconditioner(Preconditioner::None)
        .coarse(stickslip::CoarseSpace::None)
        .tol(1e-12)
        .max_iters(50 * n);
    let sol = Solver::new(config)
        .expect("a CPU solver")
        .solve(&problem)
        .expect("CG converges");
    let info = match &sol.stats.details {
        SolveDetails::Cg(info) => info.clone(),
        other => panic!("not a CG solve: {other:?}"),
    };
    let est = info
        .condition_estimate
        .expect("an estimate after n iterations");
    assert!(
        est <= kappa * (1.0 + 1e-9) && est >= kappa * (1.0 - 1e-6),
        "estimate {est:e} against κ = {kappa:e} after {} iterations",
        sol.stats.iterations.unwrap_or(0)
    );
}

/// A seeded 2D mesh system (400 nodes, one sticky node) rescaled as S H S, S b with S's
/// entries spread so that H's diagonal spans about 1e-16 to 1e19, written to `dir`.
fn badly_scaled(dir: &std::path::Path) {
    let mut spec = SystemSpec::with_nodes(2, 400, 1);
    spec.mix = ConstraintMix::None;
    let mut s = random_system(&spec);
    let (d, nd) = (s.h.dim, s.h.ndof());
    let scale: Vec<f64> = (0..nd)
        .map(|i| 10f64.powf(0.5 * (-16.0 + 35.0 * i as f64 / (nd - 1) as f64)))
        .collect();
    for i in 0..s.h.n {
        for k in s.h.row_ptr[i]..s.h.row_ptr[i + 1] {
            let j = s.h.col_idx[k];
            for r in 0..d {
                for c in 0..d {
                    s.h.values[k * d * d + r * d + c] *= scale[i * d + r] * scale[j * d + c];
                }
            }
        }
    }
    let g: Vec<f64> = s.g.iter().zip(&scale).map(|(g, s)| g * s).collect();
    mtx::write_hessian(dir.join("H.mtx"), &s.h, "badly scaled").expect("write H.mtx");
    mtx::write_vector(dir.join("g.mtx"), &g, "badly scaled").expect("write g.mtx");
    std::fs::write(
        dir.join("bc.json"),
        r#"{"dim": 2, "constraints": [{"kind": "sticky", "node": 0}]}"#,
    )
    .expect("write bc.json");
}

fn read_dx(path: &std::path::Path) -> Vec<f64> {
    mtx::read_vector(path.to_str().expect("utf-8"), "dx", None).expect("dx.mtx")
}

fn relative_error(a: &[f64], b: &[f64]) -> f64 {
    let d: f64 = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum();
    let n: f64 = b.iter().map(|y| y * y).sum();
    (d / n).sqrt()
}

/// The multilevel CG meets its residual tolerance on the badly scaled system with an
/// answer far from the Cholesky one; `solve` says so on stderr and in report.json. The
/// Jacobi CG, whose preconditioned operator does not see the scaling, gets the answer
/// and gives no warning.
#[test]
fn a_badly_scaled_system_makes_solve_warn_that_the_residual_does_not_bound_the_error() {
    let dir = tmpdir("badly-scaled");
    badly_scaled(&dir);
    let f = |name: &str| dir.join(name).to_str().expect("utf-8").to_string();
    let system = [
        "solve",
        "--hessian",
        &f("H.mtx"),
        "--gradient",
        &f("g.mtx"),
        "--constraints",
        &f("bc.json"),
    ];
    let solve = |extra: &[&str]| {
        let args: Vec<&str> = system.iter().chain(extra).copied().collect();
        let o = run(&args);
        assert!(o.status.success(), "{}", stderr(&o));
        stderr(&o)
    };
    solve(&["--out", &f("ref.mtx")]);
    let reference = read_dx(&dir.join("ref.mtx"));
    for (pre, wrong) in [("multilevel", true), ("jacobi", false)] {
        let dx = f(&format!("dx-{pre}.mtx"));
        let report = f(&format!("report-{pre}.json"));
        let err = solve(&[
            "--solver",
            "cg",
            "--preconditioner",
            pre,
            "--out",
            &dx,
            "--report",
            &report,
        ]);
        let json: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&report).expect("report")).expect("JSON");
        let kappa = json["cg"]["condition_estimate"]
            .as_f64()
            .unwrap_or_else(|| panic!("{pre}: no cg.condition_estimate in {json}"));
        assert!(
            err.contains(&format!("condition estimate {kappa:.1e}")),
            "{pre}: summary lacks the estimate: {err}"
        );
        let error = relative_error(&read_dx(std::path::Path::new(&dx)), &reference);
        let warned = err.lines().any(|l| {
            l.starts_with("warning: ") && l.contains("the relative error of Δx is bounded only by")
        });
        // The answers' difference: far above 1e-3 for the wrong one, the CG tolerance's
        // order for the right one (Cholesky's own error is far below both).
        if wrong {
            assert!(error > 1e-3, "{pre}: error {error:e}");
            assert!(kappa * 1e-8 > 1e-2, "{pre}: κ̃ {kappa:e}");
            assert!(warned, "{pre}: no warning: {err}");
        } else {
            assert!(error < 1e-6, "{pre}: error {error:e}");
            assert!(!warned, "{pre}: a warning at κ̃ {kappa:e}: {err}");
        }
    }
}
