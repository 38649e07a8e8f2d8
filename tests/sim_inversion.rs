//! Inversion-free steps of the classical neo-Hookean law (`model = "neo-hookean"`) and the
//! inversion report of the stable one.
//!
//! - `crush` (the simulation book's inversion-free example: a 4×4 square crushed between the
//!   ground and a ceiling driven down to y = −0.6): every step ends with min_j > 0, and the
//!   GPU Newton loop follows the CPU loop's centre of mass to 1e-9·L every step.
//! - `crush --size 2` (8×8): min_j > 0 every step with the classical law; with the stable
//!   law and `inversion = "fail"` the run fails with one line naming the step and element,
//!   and with `inversion = "allow"` it completes and summary.json counts the inverted steps.
//! - A step whose first Newton direction inverts elements (free nodes thrown through the
//!   fixed ones) is cut back to a step that keeps every J positive, on both loops.
//! - A scene whose initial state, or whose step's starting state after the static
//!   projection, has an inverted classical element is an input error naming the element.
//! - Command line: steps.csv has a `min_j` column for solid scenes only, summary.json's
//!   `inverted_steps` has one entry per neo-Hookean law of the scene, and a bad
//!   `[solver] inversion` is a one-line input error (exit 2).
//!
//! GPU parts skip loudly without an adapter unless STICKSLIP_REQUIRE_GPU=1.

mod common;

use stickslip::sim::driver::{run, RunError, RunOptions, RunSummary};
use stickslip::sim::integrator::Stepper;
use stickslip::sim::scene::{self, NewtonLoop};

fn scene_file(tag: &str, text: &str) -> std::path::PathBuf {
    let dir =
        std::env::temp_dir().join(format!("stickslip-inversion-{}-{tag}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let p = dir.join(format!("{tag}.toml"));
    std::fs::write(&p, text).expect("scene file");
    p
}

fn run_scene(
    scene: &str,
    tag: &str,
    newton: NewtonLoop,
    size: Option<f64>,
    steps: Option<usize>,
) -> Result<RunSummary, RunError> {
    let out = std::env::temp_dir().join(format!(
        "stickslip-inversion-{}-{tag}-{}",
        std::process::id(),
        newton.name()
    ));
    let opts = RunOptions {
        scene: Some(scene.into()),
        out: Some(out.clone()),
        solver: Some(stickslip::SolverKind::Cg),
        newton: Some(newton),
        size,
        steps,
        quiet: true,
        ..RunOptions::default()
    };
    let r = run(&opts);
    let _ = std::fs::remove_dir_all(&out);
    r
}

/// The GPU run, or None (skipped loudly) without an adapter unless CI demands one.
fn gpu_run(r: Result<RunSummary, RunError>, what: &str) -> Option<RunSummary> {
    match r {
        Ok(s) => Some(s),
        Err(RunError::Solve { step: 0, cause, .. }) if cause.contains("cannot start") => {
            if std::env::var_os("STICKSLIP_REQUIRE_GPU").is_some() {
                panic!(
                    "{what}: STICKSLIP_REQUIRE_GPU is set but the GPU loop cannot start: {cause}"
                );
            }
            common::skip(&format!(
                "SKIP {what}: GPU Newton loop NOT RUN (no adapter): {cause}"
            ));
            None
        }
        Err(e) => panic!("{what} on the GPU loop: {e}"),
    }
}

/// Every row's min_j (row 0 included) is positive; returns the smallest.
fn min_j_positive(what: &str, s: &RunSummary) -> f64 {
    let mut least = f64::INFINITY;
    for r in &s.records {
        let j = r
            .min_j
            .unwrap_or_else(|| panic!("{what}: step {} has no min_j", r.step));
        assert!(j > 0.0, "{what}: step {} ends with min_j = {j:e}", r.step);
        least = least.min(j);
    }
    assert_eq!(
        s.inverted_steps.get("neo-hookean"),
        Some(&0),
        "{what}: {:?}",
        s.inverted_steps
    );
    least
}

#[test]
fn crush_keeps_every_element_uninverted_on_both_loops() {
    let cpu = run_scene("crush", "crush4", NewtonLoop::Cpu, None, None)
        .unwrap_or_else(|e| panic!("crush: {e}"));
    assert_eq!(cpu.steps_completed, 240);
    let least = min_j_positive("crush 4×4 (CPU loop)", &cpu);
    eprintln!("crush 4×4, CPU loop: smallest min_j {least:.4e}");
    let Some(gpu) = gpu_run(
        run_scene("crush", "crush4", NewtonLoop::Gpu, None, None),
        "crush 4×4",
    ) else {
        return;
    };
    let least_gpu = min_j_positive("crush 4×4 (GPU loop)", &gpu);
    let l = cpu.characteristic_length;
    let mut worst = 0.0f64;
    for (g, c) in gpu.records.iter().zip(&cpu.records) {
        for (a, b) in g.com.iter().zip(&c.com) {
            worst = worst.max((a - b).abs() / l);
        }
    }
    eprintln!(
        "crush 4×4, GPU loop: smallest min_j {least_gpu:.4e}; centre of mass max |Δ|/L = {worst:.3e} over {} steps",
        gpu.records.len() - 1
    );
    assert_eq!(gpu.records.len(), cpu.records.len());
    assert!(worst <= 1e-9, "the loops differ by {worst:e}·L");
}

#[test]
fn crush_8x8_classical_stays_uninverted_and_stable_inverts() {
    let classical = run_scene("crush", "crush8", NewtonLoop::Cpu, Some(2.0), None)
        .unwrap_or_else(|e| panic!("crush --size 2: {e}"));
    let least = min_j_positive("crush 8×8", &classical);
    eprintln!("crush 8×8, classical law: smallest min_j {least:.4e}");
    let text = scene::builtin("crush")
        .expect("built-in")
        .replace("model = \"neo-hookean\"", "model = \"stable-neo-hookean\"");
    assert!(text.contains("stable-neo-hookean"));
    let allow = scene_file("crush-stable", &text);
    let s = run_scene(
        &allow.display().to_string(),
        "crush8-stable",
        NewtonLoop::Cpu,
        Some(2.0),
        None,
    )
    .unwrap_or_else(|e| panic!("crush 8×8, stable law: {e}"));
    let inverted = s
        .inverted_steps
        .get("stable-neo-hookean")
        .copied()
        .unwrap_or(0);
    let first = s
        .records
        .iter()
        .find(|r| r.min_j.is_some_and(|j| j <= 0.0))
        .map(|r| r.step)
        .expect("the stable law inverts an element of the 8×8 square");
    eprintln!(
        "crush 8×8, stable law: {inverted} of {} steps end inverted, the first is step {first}",
        s.steps_completed
    );
    assert!(inverted > 0);
    let fail = scene_file(
        "crush-stable-fail",
        &text.replace(
            "newton_tolerance = 1e-6",
            "newton_tolerance = 1e-6\ninversion = \"fail\"",
        ),
    );
    let err = run_scene(
        &fail.display().to_string(),
        "crush8-stable-fail",
        NewtonLoop::Cpu,
        Some(2.0),
        None,
    )
    .expect_err("inversion = \"fail\" fails the step");
    let line = err.to_string();
    eprintln!("{line}");
    assert!(!line.contains('\n'), "one line: {line}");
    assert!(
        line.starts_with(&format!("step {first} "))
            && line.contains("element ")
            && line.contains("inverted"),
        "{line}"
    );
    for p in [allow, fail] {
        let _ = std::fs::remove_dir_all(p.parent().expect("dir"));
    }
}

/// A 1 m square of two triangles, its bottom edge sticky, thrown down at 150 m/s: x̃ puts
/// the top nodes 0.5 m below the fixed ones, so the first Newton direction (from xⁿ, nearly
/// x̃ − xⁿ for these heavy, soft elements) would turn both triangles inside out. Newton
/// runs to ‖Δx‖∞/h < 1e-9·L/s, so the two loops' end states can be compared at 1e-9·L.
const THROWN: &str = r#"
name = "thrown"
dimension = 2
time_step = 0.01
steps = 1
[output]
vtk = false
[[bodies]]
mesh = { kind = "rectangle", size = [1.0, 1.0], cells = [1, 1] }
material = { model = "neo-hookean", young = 1e3, poisson = 0.3, density = 1000.0 }
velocity = [0.0, -150.0]
[[boundary]]
kind = "sticky"
region = { plane = { normal = [0.0, 1.0], offset = 0.0 } }
"#;

#[test]
fn a_direction_that_inverts_is_cut_back_on_both_loops() {
    let mut results = Vec::new();
    for newton in [NewtonLoop::Cpu, NewtonLoop::Gpu] {
        let text = if newton == NewtonLoop::Gpu {
            THROWN.replace(
                "steps = 1\n",
                "steps = 1\n[solver]\nnewton = \"gpu\"\ncg_tolerance = 1e-12\nnewton_tolerance = 1e-9\n",
            )
        } else {
            THROWN.replace(
                "steps = 1\n",
                "steps = 1\n[solver]\nlinear = \"cholesky\"\nnewton_tolerance = 1e-9\n",
            )
        };
        let sc = scene::parse(&text, "thrown.toml", 1.0).expect("scene");
        let mut st = match Stepper::new(&sc) {
            Ok(s) => s,
            Err(e) if newton == NewtonLoop::Gpu => {
                if std::env::var_os("STICKSLIP_REQUIRE_GPU").is_some() {
                    panic!("STICKSLIP_REQUIRE_GPU is set but the GPU loop cannot start: {e:?}");
                }
                common::skip(&format!(
                    "SKIP thrown square: GPU Newton loop NOT RUN: {e:?}"
                ));
                continue;
            }
            Err(e) => panic!("{e:?}"),
        };
        let rep = st
            .step()
            .unwrap_or_else(|e| panic!("{}: {e}", newton.name()));
        let j = rep.min_j.expect("solid");
        eprintln!(
            "thrown square, {} loop: {} Newton iterations, {} line searches started at the inversion bound, min_j {j:.4e}",
            newton.name(),
            rep.newton_iterations,
            rep.inversion_limited
        );
        assert!(
            rep.inversion_limited >= 1,
            "{}: never cut back",
            newton.name()
        );
        assert!(
            j > 0.0 && rep.inverted.is_empty(),
            "{}: min_j {j:e}",
            newton.name()
        );
        results.push(st.x.clone());
    }
    if let [cpu, gpu] = &results[..] {
        let worst = cpu
            .iter()
            .zip(gpu)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        eprintln!("thrown square: loops differ by {worst:.3e} m");
        assert!(worst <= 1e-9 * 2f64.sqrt(), "{worst:e}");
    }
}

#[test]
fn an_inverted_classical_element_at_the_start_is_an_input_error() {
    // The classical law refuses a state with J ≤ 0; the scene parser builds x0 from the
    // rest mesh, so the inverted state is made by hand.
    let mut sc = scene::parse(THROWN, "thrown.toml", 1.0).expect("scene");
    // Node 3 is (1, 1) in the 2×2-node rectangle: moved below the bottom edge.
    let d = sc.dim;
    let top_right = (0..sc.model.n_nodes)
        .find(|&i| sc.x0[i * d] == 1.0 && sc.x0[i * d + 1] == 1.0)
        .expect("top right node");
    sc.x0[top_right * d + 1] = -1.0;
    let err = match Stepper::new(&sc) {
        Err(e) => format!("{e:?}"),
        Ok(_) => panic!("an inverted start must be refused"),
    };
    eprintln!("{err}");
    assert!(
        err.contains("bodies[0]") && err.contains("element ") && err.contains("inverted"),
        "{err}"
    );
}

/// Through the command line: steps.csv of a solid scene ends with `min_j` and its summary
/// counts inverted steps per law; a mass-spring scene has neither; a bad `inversion` value
/// is an input error naming the key (exit 2, one line).
#[test]
fn command_line_reports_min_j_and_rejects_a_bad_policy() {
    use common::cli;
    let dir = cli::tmpdir("inversion-cli");
    for (scene, solid) in [("crush", true), ("hanging", false)] {
        let out = dir.join(scene);
        let o = cli::run(&[
            "run",
            scene,
            "--steps",
            "2",
            "--quiet",
            "--out",
            out.to_str().expect("utf-8"),
        ]);
        assert_eq!(o.status.code(), Some(0), "{scene}: {}", cli::stderr(&o));
        let csv = std::fs::read_to_string(out.join("steps.csv")).expect("steps.csv");
        let header = csv.lines().next().expect("header");
        let columns: Vec<&str> = header.split(',').collect();
        assert_eq!(columns.contains(&"min_j"), solid, "{scene}: {header}");
        let summary: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(out.join("summary.json")).expect("summary.json"),
        )
        .expect("json");
        let want = if solid {
            serde_json::json!({"neo-hookean": 0})
        } else {
            serde_json::json!({})
        };
        assert_eq!(summary["inverted_steps"], want, "{scene}");
    }
    let text = scene::builtin("crush").expect("built-in").replace(
        "newton_tolerance = 1e-6",
        "newton_tolerance = 1e-6\ninversion = \"sometimes\"",
    );
    let path = cli::write(&dir, "bad.toml", &text);
    let o = cli::run(&[
        "run",
        &path,
        "--quiet",
        "--out",
        dir.join("bad").to_str().expect("utf-8"),
    ]);
    let e = cli::stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert_eq!(e.trim_end().lines().count(), 1, "{e}");
    assert!(e.contains("solver.inversion"), "{e}");
    // A plane condition whose start-of-step projection puts the top edge below the fixed
    // bottom one inverts the elements between: an input error naming the condition, the
    // node, the body and the element.
    let text = THROWN.replace("velocity = [0.0, -150.0]\n", "")
        + "[[boundary]]\nkind = \"plane\"\nnormal = [0.0, 1.0]\noffset = -1.0\n\
           region = { plane = { normal = [0.0, 1.0], offset = 1.0 } }\n";
    let path = cli::write(&dir, "projected.toml", &text);
    let o = cli::run(&[
        "run",
        &path,
        "--quiet",
        "--out",
        dir.join("projected").to_str().expect("utf-8"),
    ]);
    let e = cli::stderr(&o);
    eprintln!("{e}");
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert_eq!(e.trim_end().lines().count(), 1, "{e}");
    assert!(
        e.contains("boundary[1]: projecting node ")
            && e.contains("inverts element ")
            && e.contains("of bodies[0]"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
