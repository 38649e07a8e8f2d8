//! Hard scenes run to the end or stop with a clear message: `twist` with a
//! nearly incompressible, very stiff material (ν = 0.499, E = 1e9) and `incline` with a
//! tiny (1e-5 s) and a huge (0.1 s) time step. CI-sized: fewer steps than the scene files.
//!
//! "Clear message" means: the run either finishes every requested step, or fails with
//! `RunError::Solve` whose text names the step and the cause. A panic, a NaN in the final
//! state or a silent early stop is a failure of this test.

use stickslip::sim::driver::{run, RunError, RunOptions, RunSummary};

/// Writes a modified copy of a built-in scene and runs it with the given solver.
fn run_modified(
    name: &str,
    tag: &str,
    edits: &[(&str, &str)],
    solver: &str,
    steps: usize,
) -> Result<RunSummary, RunError> {
    let mut text = stickslip::sim::scene::builtin(name)
        .unwrap_or_else(|| panic!("no built-in scene {name}"))
        .to_string();
    for (from, to) in edits {
        assert!(text.contains(from), "scene {name} has no '{from}' to edit");
        text = text.replacen(from, to, 1);
    }
    let dir = std::env::temp_dir().join(format!(
        "stickslip-sim-stability-{}-{name}-{tag}-{solver}",
        std::process::id()
    ));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let file = dir.join(format!("{name}-{tag}.toml"));
    std::fs::write(&file, text).expect("write scene");
    let opts = RunOptions {
        scene: Some(file.display().to_string()),
        out: Some(dir.join("out")),
        solver: Some(solver.parse().expect("a solver name")),
        steps: Some(steps),
        quiet: true,
        ..RunOptions::default()
    };
    let r = run(&opts);
    let _ = std::fs::remove_dir_all(&dir);
    r
}

/// Either every step ran with a finite state, or the error names the step and a cause.
fn check(label: &str, r: Result<RunSummary, RunError>, steps: usize) {
    match r {
        Ok(s) => {
            eprintln!(
                "{label}: ran {} steps, newton {}, linear iterations {}, {:.2} s",
                s.steps, s.newton_iterations, s.linear_iterations, s.wall_seconds
            );
            assert_eq!(s.steps, steps, "{label}: stopped early without an error");
            assert!(
                s.final_positions.iter().all(|v| v.is_finite()),
                "{label}: non-finite final positions"
            );
            assert!(
                s.final_velocities.iter().all(|v| v.is_finite()),
                "{label}: non-finite final velocities"
            );
        }
        Err(e @ RunError::Solve { .. }) => {
            let msg = e.to_string();
            eprintln!("{label}: stopped with: {msg}");
            assert!(
                msg.starts_with("step "),
                "{label}: message does not name the step: {msg}"
            );
            if let RunError::Solve { cause, .. } = &e {
                assert!(!cause.trim().is_empty(), "{label}: empty cause");
            }
        }
        Err(e) => panic!("{label}: unexpected error: {e}"),
    }
}

#[test]
fn twist_nearly_incompressible_and_stiff() {
    let steps = 50;
    for solver in ["cholesky", "cg"] {
        let r = run_modified(
            "twist",
            "nu0499-e1e9",
            &[
                ("young = 1e5", "young = 1e9"),
                ("poisson = 0.4", "poisson = 0.499"),
            ],
            solver,
            steps,
        );
        check(&format!("twist ν=0.499 E=1e9 ({solver})"), r, steps);
    }
}

#[test]
fn incline_tiny_time_step() {
    let steps = 40;
    for solver in ["cholesky", "cg"] {
        let r = run_modified(
            "incline",
            "dt1e-5",
            &[("time_step = 0.01", "time_step = 1e-5")],
            solver,
            steps,
        );
        check(&format!("incline dt=1e-5 ({solver})"), r, steps);
    }
}

#[test]
fn incline_huge_time_step() {
    let steps = 40;
    for solver in ["cholesky", "cg"] {
        let r = run_modified(
            "incline",
            "dt0.1",
            &[("time_step = 0.01", "time_step = 0.1")],
            solver,
            steps,
        );
        check(&format!("incline dt=0.1 ({solver})"), r, steps);
    }
}
