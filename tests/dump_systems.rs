//! `run --dump-systems`: every Newton system of the chosen steps lands in
//! `systems/step_S/iter_K/` as `solve`'s input files, and replays to the direction the run
//! used: exactly (≤ 1e-12 relative) when the run used Cholesky, and within the CG
//! tolerance the run recorded otherwise (the direction's true relative residual
//! ‖P Vᵀ(HΔx + g)‖/‖P Vᵀ g‖ on the dumped files, which is what that tolerance bounds).
//! A bad value is one line, exit 2, before any work.

mod common;

use common::cli::{run as run_cli, stderr, tmpdir};
use std::path::{Path, PathBuf};
use stickslip::core::constraints::Frames;
use stickslip::core::linalg::norm2;
use stickslip::io::{bcjson, mtx};
use stickslip::sim::driver::{run, RunError, RunOptions, RunSummary};
use stickslip::sim::integrator::StepSelection;
use stickslip::sim::scene::NewtonLoop;

fn dump_run(
    scene: &str,
    solver: &str,
    newton: NewtonLoop,
    steps: usize,
    dump: &str,
) -> (PathBuf, Result<RunSummary, RunError>) {
    let out = tmpdir(&format!("dump-{scene}-{solver}-{}", newton.name())).join("out");
    let opts = RunOptions {
        scene: Some(scene.into()),
        out: Some(out.clone()),
        solver: Some(solver.parse().expect("a solver name")),
        newton: Some(newton),
        steps: Some(steps),
        dump_systems: Some(dump.parse::<StepSelection>().expect("selection")),
        quiet: true,
        ..RunOptions::default()
    };
    let r = run(&opts);
    (out, r)
}

/// The iteration folders of one dumped step, in iteration order.
fn iterations(out: &Path, step: usize) -> Vec<PathBuf> {
    let dir = out.join("systems").join(format!("step_{step}"));
    let mut v: Vec<(usize, PathBuf)> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .flatten()
        .map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let k = name
                .strip_prefix("iter_")
                .and_then(|k| k.parse().ok())
                .unwrap_or_else(|| panic!("unexpected entry {name} in {}", dir.display()));
            (k, e.path())
        })
        .collect();
    v.sort();
    assert_eq!(
        v.iter().map(|x| x.0).collect::<Vec<_>>(),
        (1..=v.len()).collect::<Vec<_>>(),
        "iterations of step {step}"
    );
    v.into_iter().map(|x| x.1).collect()
}

fn s(p: &Path) -> String {
    p.display().to_string()
}

fn vector(p: &Path) -> Vec<f64> {
    mtx::read_vector(&s(p), "vector", None).expect("vector")
}

/// ‖P Vᵀ(HΔx + g)‖ / ‖P Vᵀ g‖ of the dumped direction, and its recorded tolerance.
fn dumped_residual(it: &Path) -> (f64, Option<f64>) {
    let info: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(it.join("system.json")).expect("json"))
            .expect("system.json");
    let dim = info["dim"].as_u64().expect("dim") as usize;
    let h = mtx::read_hessian(&s(&it.join("H.mtx")), dim).expect("H");
    let g = vector(&it.join("g.mtx"));
    let dx = vector(&it.join("dx.mtx"));
    let cs = bcjson::read(&s(&it.join("bc.json")), None).expect("bc.json");
    let frames = Frames::build(dim, h.n, &cs.constraints).expect("frames");
    let mut r = vec![0.0; g.len()];
    h.matvec(&dx, &mut r);
    for (ri, gi) in r.iter_mut().zip(&g) {
        *ri += gi;
    }
    let free = |v: &[f64]| {
        let mut y = vec![0.0; v.len()];
        frames.to_frame(v, &mut y);
        frames.apply_mask(&mut y);
        norm2(&y)
    };
    (free(&r) / free(&g), info["tolerance"].as_f64())
}

/// Every dumped direction of `step` meets the CG tolerance recorded beside it.
fn meet_their_tolerance(out: &Path, step: usize) {
    for it in iterations(out, step) {
        let (res, tol) = dumped_residual(&it);
        let tol = tol.expect("a CG solve records its tolerance");
        eprintln!(
            "{}: relative residual {res:.3e}, tolerance {tol:.1e}",
            it.display()
        );
        // The run met tol on the same arrays; the files hold them to 17 digits.
        assert!(
            res <= tol * (1.0 + 1e-6),
            "{}: {res:e} > {tol:e}",
            it.display()
        );
    }
}

#[test]
fn cholesky_systems_replay_exactly_with_solve() {
    let (out, r) = dump_run("twist", "cholesky", NewtonLoop::Cpu, 2, "2");
    let summary = r.expect("twist with --dump-systems");
    let iters = iterations(&out, 2);
    assert_eq!(
        iters.len(),
        summary.records[2].newton_iterations,
        "one folder per Newton iteration of step 2"
    );
    assert!(!out.join("systems").join("step_1").exists());
    for it in &iters {
        for f in stickslip::sim::driver::SYSTEM_FILES {
            assert!(it.join(f).is_file(), "{}: no {f}", it.display());
        }
    }
    // The command line's Cholesky on the dumped files gives the run's Δx.
    let it = &iters[0];
    let replay = it.join("replay.mtx");
    let o = run_cli(&[
        "solve",
        "--hessian",
        &s(&it.join("H.mtx")),
        "--gradient",
        &s(&it.join("g.mtx")),
        "--constraints",
        &s(&it.join("bc.json")),
        "--solver",
        "cholesky",
        "--out",
        &s(&replay),
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (a, b) = (vector(&it.join("dx.mtx")), vector(&replay));
    let diff: Vec<f64> = a.iter().zip(&b).map(|(x, y)| x - y).collect();
    let rel = norm2(&diff) / norm2(&a);
    eprintln!("twist step 2 iteration 1: |Δx_solve − Δx_run| / |Δx_run| = {rel:.3e}");
    assert!(rel <= 1e-12, "{rel:e}");
    let _ = std::fs::remove_dir_all(out.parent().expect("parent"));
}

/// `bench --systems` runs every CPU solver on every dumped system to 1e-6.
#[test]
fn bench_times_every_solver_on_the_dumped_systems() {
    let (out, r) = dump_run("incline", "cholesky", NewtonLoop::Cpu, 1, "1");
    let summary = r.expect("incline with --dump-systems");
    let systems = summary.records[1].newton_iterations;
    let bench_out = out.with_file_name("bench");
    let o = run_cli(&[
        "bench",
        "--systems",
        &s(&out.join("systems")),
        "--no-gpu",
        "--quiet",
        "--out",
        &s(&bench_out),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let json: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(bench_out.join("bench.json")).expect("bench.json"),
    )
    .expect("json");
    let records = json["records"].as_array().expect("records");
    // Cholesky, 2 preconditioners × 3 coarse spaces and the multilevel CG per system.
    assert_eq!(records.len(), 8 * systems, "{json}");
    assert_eq!(
        records
            .iter()
            .filter(|r| r["solver"] == "cg multilevel")
            .count(),
        systems,
        "{json}"
    );
    for r in records {
        assert!(r["error"].is_null(), "{r}");
        let res = r["relative_residual"].as_f64().expect("residual");
        assert!(res <= 1e-6, "{r}");
    }
    let o = run_cli(&["bench", "--systems", &s(&bench_out), "--no-gpu"]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("holds no system"), "{}", stderr(&o));
    let _ = std::fs::remove_dir_all(out.parent().expect("parent"));
}

#[test]
fn cg_systems_meet_the_recorded_tolerance() {
    let (out, r) = dump_run("twist", "cg", NewtonLoop::Cpu, 1, "all");
    r.expect("twist with cg");
    meet_their_tolerance(&out, 1);
    let _ = std::fs::remove_dir_all(out.parent().expect("parent"));
}

#[test]
fn device_loop_systems_meet_the_recorded_tolerance() {
    let (out, r) = dump_run("drop", "cg", NewtonLoop::Gpu, 2, "2");
    match r {
        Ok(_) => {}
        Err(RunError::Solve { step: 0, cause, .. }) if cause.contains("cannot start") => {
            if std::env::var_os("STICKSLIP_REQUIRE_GPU").is_some() {
                panic!(
                    "STICKSLIP_REQUIRE_GPU is set but the GPU Newton loop cannot start: {cause}"
                );
            }
            common::skip(&format!(
                "SKIP device-loop dump NOT RUN (no adapter): {cause}"
            ));
            return;
        }
        Err(e) => panic!("drop on the device loop: {e}"),
    }
    meet_their_tolerance(&out, 2);
    let _ = std::fs::remove_dir_all(out.parent().expect("parent"));
}

#[test]
fn bad_selections_fail_in_one_line_before_any_work() {
    let dir = tmpdir("dump-bad");
    for (value, steps, want) in [
        ("0", "3", "step numbers"),
        ("1,x", "3", "\"x\""),
        ("5", "3", "step 5 is past the run's last step (3)"),
    ] {
        let out = dir.join(format!("out-{value}"));
        let o = run_cli(&[
            "run",
            "twist",
            "--steps",
            steps,
            "--dump-systems",
            value,
            "--out",
            &s(&out),
            "--quiet",
        ]);
        let e = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{value}: {e}");
        assert_eq!(e.lines().count(), 1, "{value}: {e:?}");
        assert!(
            e.contains("--dump-systems") && e.contains(want),
            "{value}: {e}"
        );
        assert!(!out.exists(), "{value}: the output folder was created");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
