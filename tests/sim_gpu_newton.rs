//! The GPU Newton loop (`run --newton gpu`, f64) against the CPU loop (`--solver cg`) on
//! the built-in scenes that exercise every part of it: `twist` (neo-Hookean tetrahedra, a
//! moving sticky end), `compress` (triangles, gravity, static and moving plane slip),
//! `incline` (rotated plane-slip frames, gravity) and `drop` (a half-space obstacle: the
//! barrier, the CCD bound). Per step, the centre of mass and the summed reaction (the
//! steps.csv columns) must agree.
//!
//! Tolerances: both loops make the same decisions and stop Newton at ‖Δx‖∞/h < 1e-6·L/s;
//! their iterates differ by the CG's (relative residual 1e-10 on both sides, the same
//! preconditioner and coarse space) and by summation order, so positions agree to ~1e-10·L or better:
//! 1e-9·L is the bound. Reactions and contact forces are forces (newtons): they are
//! compared relative to the largest summed value of the run, at the same 1e-9; a position
//! difference δx moves them by k·δx with k the stiffness of the supported layer, and the
//! measured differences are ~1e-12 of the largest (the loops stop on nearly the same
//! iterates). The two CGs take the same iterations but for rounding that moves a stop:
//! within 5 % over the run.
//!
//! The comparisons above solve every Newton system to 1e-10 on both loops. With the
//! adaptive CG tolerance (inexact Newton, the default) the device loop is compared with the
//! CPU loop's Cholesky instead: the iterates then differ by the forcing sequence's
//! tolerances (1e-2 to 1e-6), but every step ends on a direction solved to 1e-6 that
//! passes the same Newton test, so the centre of mass agrees to 1e-7·L (twist) and 1e-6·L
//! (drop, whose barrier stiffens the contact layer), and Newton takes within 10 % of the
//! iterations.
//!
//! The multilevel preconditioner runs in both loops with the same levels (the device loop
//! builds them on the host from the H it reads back): there the two loops are compared
//! with the adaptive tolerance on both sides, to the same 1e-9.
//!
//! Also: `twist --size 4` moves less than 1 % of one assembled Hessian's bytes from host
//! to device per Newton iteration and none of the coarse space's E or E⁺ (formed on the
//! device), and the bad-input cases of the loop.

mod common;

use stickslip::sim::driver::{run, RunError, RunOptions, RunSummary};
use stickslip::sim::scene::{CgTolerance, NewtonLoop};

/// Every Newton system to this, on both loops, in the comparisons of the two loops.
const TIGHT: CgTolerance = CgTolerance::Fixed(1e-10);

fn run_scene(
    name: &str,
    newton: NewtonLoop,
    steps: usize,
    size: Option<f64>,
) -> Result<RunSummary, RunError> {
    run_with(name, newton, "cg", TIGHT, steps, size)
}

fn run_with(
    name: &str,
    newton: NewtonLoop,
    solver: &str,
    tol: CgTolerance,
    steps: usize,
    size: Option<f64>,
) -> Result<RunSummary, RunError> {
    // One folder per run: tests of the same scene run at the same time.
    let out = std::env::temp_dir().join(format!(
        "stickslip-gpu-newton-{}-{name}-{}-{solver}-{}-{steps}-{}",
        std::process::id(),
        newton.name(),
        tol.name(),
        size.unwrap_or(1.0)
    ));
    let opts = RunOptions {
        scene: Some(name.into()),
        out: Some(out.clone()),
        solver: Some(solver.parse().expect("a solver name")),
        newton: Some(newton),
        cg_tolerance: Some(tol),
        steps: Some(steps),
        size,
        quiet: true,
        ..RunOptions::default()
    };
    let r = run(&opts);
    let _ = std::fs::remove_dir_all(&out);
    r
}

/// The GPU run, or None (skipped loudly) when no adapter exists and CI does not demand one.
fn gpu_run(name: &str, steps: usize, size: Option<f64>) -> Option<RunSummary> {
    gpu_run_with(name, TIGHT, steps, size)
}

fn gpu_run_with(
    name: &str,
    tol: CgTolerance,
    steps: usize,
    size: Option<f64>,
) -> Option<RunSummary> {
    gpu_or_skip(
        name,
        run_with(name, NewtonLoop::Gpu, "cg", tol, steps, size),
    )
}

/// A device-loop run's summary, or None (skipped loudly) when it could not start for want
/// of an adapter and CI does not demand one.
fn gpu_or_skip(name: &str, run: Result<RunSummary, RunError>) -> Option<RunSummary> {
    match run {
        Ok(s) => Some(s),
        Err(RunError::Solve { step: 0, cause, .. }) if cause.contains("cannot start") => {
            if std::env::var_os("STICKSLIP_REQUIRE_GPU").is_some() {
                panic!("{name}: STICKSLIP_REQUIRE_GPU is set but the GPU Newton loop cannot start: {cause}");
            }
            common::skip(&format!(
                "SKIP {name}: GPU Newton loop NOT RUN (no adapter): {cause}"
            ));
            None
        }
        Err(e) => panic!("{name} with the GPU Newton loop: {e}"),
    }
}

fn compare(name: &str, steps: usize) {
    let Some(gpu) = gpu_run(name, steps, None) else {
        return;
    };
    let cpu = run_scene(name, NewtonLoop::Cpu, steps, None)
        .unwrap_or_else(|e| panic!("{name} with the CPU loop: {e}"));
    assert_eq!(gpu.records.len(), cpu.records.len(), "{name}: steps");
    let l = cpu.characteristic_length;
    let largest = |v: &mut dyn Iterator<Item = &f64>| v.fold(0.0f64, |m, x| m.max(x.abs()));
    let f_scale = largest(&mut cpu.records.iter().flat_map(|r| r.reaction.iter()));
    let c_scale = largest(&mut cpu.records.iter().flat_map(|r| r.contact.iter()));
    let (mut com_worst, mut reaction_worst, mut contact_worst) = (0.0f64, 0.0f64, 0.0f64);
    for (g, c) in gpu.records.iter().zip(&cpu.records) {
        assert_eq!(g.step, c.step);
        for (a, b) in g.com.iter().zip(&c.com) {
            com_worst = com_worst.max((a - b).abs() / l);
        }
        for (a, b) in g.reaction.iter().zip(&c.reaction) {
            if f_scale > 0.0 {
                reaction_worst = reaction_worst.max((a - b).abs() / f_scale);
            }
        }
        assert_eq!(g.contact.len(), c.contact.len());
        for (a, b) in g.contact.iter().zip(&c.contact) {
            if c_scale > 0.0 {
                contact_worst = contact_worst.max((a - b).abs() / c_scale);
            }
        }
    }
    let gr = gpu.gpu.as_ref().expect("a GPU run reports its traffic");
    eprintln!(
        "{name}: {} steps on {}: centre of mass max |Δ|/L = {com_worst:.3e}, reactions max |Δ|/max|R| = {reaction_worst:.3e} (max |R| = {f_scale:.3e} N), contact max |Δ|/max|C| = {contact_worst:.3e} (max |C| = {c_scale:.3e} N); Newton {} (gpu) vs {} (cpu); h2d {} B, d2h {} B, matrix {} B",
        gpu.records.len() - 1,
        gr.adapter,
        gpu.newton_iterations,
        cpu.newton_iterations,
        gr.host_to_device_bytes,
        gr.device_to_host_bytes,
        gr.matrix_bytes
    );
    assert!(
        com_worst <= 1e-9,
        "{name}: centre of mass differs by {com_worst:e}·L"
    );
    assert!(
        reaction_worst <= 1e-9,
        "{name}: reactions differ by {reaction_worst:e} of the largest"
    );
    assert!(
        contact_worst <= 1e-9,
        "{name}: contact forces differ by {contact_worst:e} of the largest"
    );
    // Both CGs: the scene's preconditioner and coarse space (the aggregates by default),
    // the same algorithm summed in another order, so rounding may move a stop by an
    // iteration here and there: within 5 % over the run.
    let (gi, ci) = (gpu.linear_iterations as f64, cpu.linear_iterations as f64);
    eprintln!(
        "{name}: CG iterations {} (gpu) vs {} (cpu)",
        gpu.linear_iterations, cpu.linear_iterations
    );
    assert!(
        (gi - ci).abs() <= 0.05 * ci,
        "{name}: {gi} CG iterations on the device loop against the CPU loop's {ci}"
    );
}

#[test]
fn twist_same_trajectory_on_the_gpu_loop() {
    compare("twist", 20);
}

#[test]
fn compress_same_trajectory_on_the_gpu_loop() {
    compare("compress", 20);
}

#[test]
fn incline_same_trajectory_on_the_gpu_loop() {
    compare("incline", 20);
}

#[test]
fn drop_same_trajectory_on_the_gpu_loop() {
    compare("drop", 40);
}

/// The device loop with the adaptive tolerance against the CPU loop's Cholesky: the
/// centre of mass in every step within `bound`·L, Newton iterations within 10 %.
fn adaptive_against_cholesky(name: &str, steps: usize, bound: f64) {
    let Some(gpu) = gpu_run_with(name, CgTolerance::Adaptive, steps, None) else {
        return;
    };
    let chol = run_with(name, NewtonLoop::Cpu, "cholesky", TIGHT, steps, None)
        .unwrap_or_else(|e| panic!("{name} with Cholesky: {e}"));
    assert_eq!(gpu.records.len(), chol.records.len(), "{name}: steps");
    let l = chol.characteristic_length;
    let mut worst = 0.0f64;
    for (g, c) in gpu.records.iter().zip(&chol.records) {
        for (a, b) in g.com.iter().zip(&c.com) {
            worst = worst.max((a - b).abs() / l);
        }
    }
    let ratio = gpu.newton_iterations as f64 / chol.newton_iterations as f64;
    eprintln!(
        "{name}: {steps} steps, device loop (adaptive CG tolerance, {} CG iterations, {} re-solves) vs Cholesky: centre of mass max |Δ|/L = {worst:.3e}; Newton {} vs {} ({ratio:.3})",
        gpu.linear_iterations, gpu.linear_resolves, gpu.newton_iterations, chol.newton_iterations
    );
    assert!(
        worst <= bound,
        "{name}: centre of mass differs by {worst:e}·L"
    );
    assert!(
        (ratio - 1.0).abs() <= 0.1,
        "{name}: {} Newton iterations against Cholesky's {}",
        gpu.newton_iterations,
        chol.newton_iterations
    );
}

#[test]
fn twist_adaptive_device_loop_matches_cholesky() {
    adaptive_against_cholesky("twist", 20, 1e-7);
}

#[test]
fn drop_adaptive_device_loop_matches_cholesky() {
    adaptive_against_cholesky("drop", 40, 1e-6);
}

/// The multilevel preconditioner in both loops (the scene's `[solver] preconditioner =
/// "multilevel"`, adaptive tolerance on both): the device loop builds the levels on the
/// host from the H it reads back, with the CPU loop's code, so both loops precondition
/// with the same operator and make the same decisions. Bounds as in [`compare`]: centre
/// of mass and reactions within 1e-9 (the solves differ by rounding, then by the
/// tolerance each meets, 1e-2 to 1e-6 relative, on nearly the same iterates), Newton
/// iterations equal within 10 %, CG iterations within 5 % over the run.
fn multilevel_on_both_loops(name: &str, steps: usize) {
    let text = stickslip::sim::scene::builtin(name).expect("a built-in scene");
    let file = std::env::temp_dir().join(format!(
        "stickslip-multilevel-{}-{name}.toml",
        std::process::id()
    ));
    std::fs::write(
        &file,
        format!("{text}\n[solver]\npreconditioner = \"multilevel\"\ncoarse = \"none\"\n"),
    )
    .expect("scene file");
    let scene = file.display().to_string();
    let run_loop = |newton: NewtonLoop| {
        let out = std::env::temp_dir().join(format!(
            "stickslip-multilevel-{}-{name}-{}",
            std::process::id(),
            newton.name()
        ));
        let opts = RunOptions {
            scene: Some(scene.clone()),
            out: Some(out.clone()),
            solver: Some(stickslip::SolverKind::Cg),
            newton: Some(newton),
            cg_tolerance: Some(CgTolerance::Adaptive),
            steps: Some(steps),
            quiet: true,
            ..RunOptions::default()
        };
        let r = run(&opts);
        let _ = std::fs::remove_dir_all(&out);
        r
    };
    let Some(gpu) = gpu_or_skip(name, run_loop(NewtonLoop::Gpu)) else {
        let _ = std::fs::remove_file(&file);
        return;
    };
    let cpu =
        run_loop(NewtonLoop::Cpu).unwrap_or_else(|e| panic!("{name}, multilevel, CPU loop: {e}"));
    let _ = std::fs::remove_file(&file);
    assert_eq!(gpu.records.len(), cpu.records.len(), "{name}: steps");
    let l = cpu.characteristic_length;
    let f_scale = cpu
        .records
        .iter()
        .flat_map(|r| r.reaction.iter())
        .fold(0.0f64, |m, x| m.max(x.abs()));
    let (mut com, mut reaction) = (0.0f64, 0.0f64);
    for (g, c) in gpu.records.iter().zip(&cpu.records) {
        for (a, b) in g.com.iter().zip(&c.com) {
            com = com.max((a - b).abs() / l);
        }
        for (a, b) in g.reaction.iter().zip(&c.reaction) {
            if f_scale > 0.0 {
                reaction = reaction.max((a - b).abs() / f_scale);
            }
        }
    }
    eprintln!(
        "{name}, multilevel: {steps} steps: Newton {} (device) vs {} (CPU), CG {} vs {}; centre of mass max |Δ|/L = {com:.3e}, reactions max |Δ|/max|R| = {reaction:.3e}",
        gpu.newton_iterations, cpu.newton_iterations, gpu.linear_iterations, cpu.linear_iterations
    );
    assert!(com <= 1e-9, "{name}: centre of mass differs by {com:e}·L");
    assert!(reaction <= 1e-9, "{name}: reactions differ by {reaction:e}");
    let ratio = gpu.newton_iterations as f64 / cpu.newton_iterations as f64;
    assert!((ratio - 1.0).abs() <= 0.1, "{name}: Newton {ratio}");
    let (gi, ci) = (gpu.linear_iterations as f64, cpu.linear_iterations as f64);
    assert!(
        (gi - ci).abs() <= 0.05 * ci,
        "{name}: {gi} CG iterations on the device loop against the CPU loop's {ci}"
    );
    // The scenes keep the levels across Newton systems, and both loops decide alike.
    let levels = |s: &RunSummary| {
        let l = s.multilevel_levels.as_ref().expect("multilevel_levels");
        (l.built, l.kept)
    };
    let (gl, cl) = (levels(&gpu), levels(&cpu));
    eprintln!("{name}: levels (built, kept): device loop {gl:?}, CPU loop {cl:?}");
    assert!(cl.0 > 0 && cl.1 > 0, "{name}: levels {cl:?}");
    assert_eq!(
        gl, cl,
        "{name}: the loops keep and rebuild the levels alike"
    );
}

#[test]
fn twist_multilevel_on_both_loops() {
    multilevel_on_both_loops("twist", 10);
}

#[test]
fn drop_multilevel_on_both_loops() {
    multilevel_on_both_loops("drop", 20);
}

/// The device loop builds the multilevel levels on the device: their setup moves nothing
/// per Newton iteration. Over 1 and over 4 steps of twist with the multilevel
/// preconditioner nothing of it comes back, and what goes to the device (the levels'
/// index arrays and the setup's dispatch parameters, once per run) is the same number of
/// bytes however many systems were built or kept.
#[test]
fn multilevel_setup_moves_nothing_per_newton_iteration() {
    let text = stickslip::sim::scene::builtin("twist").expect("a built-in scene");
    let file = std::env::temp_dir().join(format!(
        "stickslip-multilevel-traffic-{}.toml",
        std::process::id()
    ));
    std::fs::write(
        &file,
        format!("{text}\n[solver]\npreconditioner = \"multilevel\"\ncoarse = \"none\"\n"),
    )
    .expect("scene file");
    let run_steps = |steps: usize| {
        let out = std::env::temp_dir().join(format!(
            "stickslip-multilevel-traffic-{}-{steps}",
            std::process::id()
        ));
        let opts = RunOptions {
            scene: Some(file.display().to_string()),
            out: Some(out.clone()),
            solver: Some(stickslip::SolverKind::Cg),
            newton: Some(NewtonLoop::Gpu),
            steps: Some(steps),
            quiet: true,
            ..RunOptions::default()
        };
        let r = run(&opts);
        let _ = std::fs::remove_dir_all(&out);
        gpu_or_skip("twist", r)
    };
    let (Some(one), Some(four)) = (run_steps(1), run_steps(4)) else {
        let _ = std::fs::remove_file(&file);
        return;
    };
    let _ = std::fs::remove_file(&file);
    let systems = |s: &RunSummary| {
        let l = s.multilevel_levels.as_ref().expect("multilevel_levels");
        l.built + l.kept
    };
    let (g1, g4) = (
        one.gpu.clone().expect("gpu report"),
        four.gpu.clone().expect("gpu report"),
    );
    eprintln!(
        "twist, multilevel setup: 1 step: {} systems, {} B to the device, {} B back; 4 steps: \
         {} systems, {} B, {} B (of {} B and {} B in all)",
        systems(&one),
        g1.multilevel_host_to_device_bytes,
        g1.multilevel_device_to_host_bytes,
        systems(&four),
        g4.multilevel_host_to_device_bytes,
        g4.multilevel_device_to_host_bytes,
        g4.host_to_device_bytes,
        g4.device_to_host_bytes
    );
    assert!(systems(&four) > systems(&one));
    assert_eq!(g1.multilevel_device_to_host_bytes, 0);
    assert_eq!(g4.multilevel_device_to_host_bytes, 0);
    assert!(g1.multilevel_host_to_device_bytes > 0);
    assert_eq!(
        g4.multilevel_host_to_device_bytes,
        g1.multilevel_host_to_device_bytes
    );
}

/// Per Newton iteration, what goes to the device is scalars and a few nodes: over the
/// whole run (set-up included) at most 1 % of one assembled Hessian per iteration. The
/// coarse space's E⁺ is formed on the device from the E reduced there, so neither crosses
/// the bus in either direction (the host forms E⁺ only where the device's factorization
/// meets a pivot that is not positive, which these SPD systems never give: any byte of it
/// here is a fallback or a regression).
#[test]
fn twist_size_4_moves_scalars_not_matrices() {
    let steps = 50;
    let Some(gpu) = gpu_run("twist", steps, Some(4.0)) else {
        return;
    };
    let g = gpu.gpu.expect("gpu report");
    assert_eq!(g.precision, "f64");
    let its = g.newton_iterations as f64;
    let per_iter = g.host_to_device_bytes as f64 / its;
    let ratio = per_iter / g.matrix_bytes as f64;
    eprintln!(
        "twist --size 4: {} nodes, {} Newton iterations; host→device {} B ({per_iter:.0} B per iteration), device→host {} B ({:.0} B per iteration); coarse E⁺ up {} B, E down {} B; matrix {} B; ratio {ratio:.4}",
        gpu.nodes,
        g.newton_iterations,
        g.host_to_device_bytes,
        g.device_to_host_bytes,
        g.device_to_host_bytes as f64 / its,
        g.coarse_host_to_device_bytes,
        g.coarse_device_to_host_bytes,
        g.matrix_bytes
    );
    assert!(
        ratio <= 0.01,
        "host→device per Newton iteration is {ratio} of the matrix"
    );
    let state = (steps * 5 * gpu.nodes * 3 * 8) as u64;
    let back = (g.device_to_host_bytes - g.coarse_device_to_host_bytes - state) as f64 / its;
    eprintln!(
        "twist --size 4: device→host besides E and the state once per step: {back:.0} B per \
         iteration ({:.4} of the matrix)",
        back / g.matrix_bytes as f64
    );
    assert!(
        back <= 0.01 * g.matrix_bytes as f64,
        "device→host per Newton iteration is {back} B besides E and the per-step state"
    );
    assert_eq!(
        (g.coarse_host_to_device_bytes, g.coarse_device_to_host_bytes),
        (0, 0),
        "the coarse space's E⁺ and E per run (0 per Newton iteration)"
    );
}

/// `run SCENE --size 2 --steps 3 --newton gpu` with the scene's own settings (`extra`
/// appended to its text when given), or None (skipped loudly) without an adapter.
fn loop_run(name: &str, extra: Option<&str>) -> Option<RunSummary> {
    let tag = if extra.is_some() { "extra" } else { "plain" };
    let dir = std::env::temp_dir().join(format!(
        "stickslip-gpu-traffic-{}-{name}-{tag}",
        std::process::id()
    ));
    std::fs::create_dir_all(&dir).expect("temp folder");
    let scene = match extra {
        Some(extra) => {
            let text = stickslip::sim::scene::builtin(name).expect("a built-in scene");
            let file = dir.join(format!("{name}.toml"));
            std::fs::write(&file, format!("{text}\n{extra}\n")).expect("scene file");
            file.display().to_string()
        }
        None => name.to_string(),
    };
    let opts = RunOptions {
        scene: Some(scene),
        out: Some(dir.join("out")),
        newton: Some(NewtonLoop::Gpu),
        steps: Some(3),
        size: Some(2.0),
        quiet: true,
        ..RunOptions::default()
    };
    let r = run(&opts);
    let _ = std::fs::remove_dir_all(&dir);
    gpu_or_skip(name, r)
}

/// Per Newton iteration nothing of size n crosses the bus: with the classical neo-Hookean
/// law (the inversion bound), moving boundaries (twist, compress), the barrier and CCD
/// (drop) and the multilevel preconditioner (twist), the bytes each way while the Newton
/// iterations run (the run's set-up, the pipelines' creation and the per-step reads and
/// writes of the state aside: `gpu.iteration_*_bytes`, counted by the context through
/// which every transfer passes, tests/layers.rs) stay within 2 KiB + 8·d bytes per moving
/// node per Newton iteration. The loop waits on the device at most once per 16 CG
/// iterations on twist, and its profile accounts for its wall time: the phases sum to
/// `wall_seconds` within 5 % (the time before the first phase opens and after the last
/// snapshot is all that is left out).
#[test]
fn newton_iterations_move_scalars_and_the_phases_account_for_the_wall_time() {
    let cases: [(&str, Option<&str>); 4] = [
        ("twist", None),
        ("compress", None),
        ("drop", None),
        (
            "twist",
            Some("[solver]\npreconditioner = \"multilevel\"\ncoarse = \"none\""),
        ),
    ];
    for (name, extra) in cases {
        let Some(s) = loop_run(name, extra) else {
            return;
        };
        let g = s.gpu.as_ref().expect("gpu report");
        let its = g.newton_iterations as f64;
        let moving = s.moving_boundary.as_ref().map_or(0, |m| m.moving_nodes);
        let allowance = 2048.0 + 8.0 * (s.dimension * moving) as f64;
        let up = g.iteration_host_to_device_bytes as f64 / its;
        let down = g.iteration_device_to_host_bytes as f64 / its;
        let phases: f64 = g.phases.iter().map(|(_, v)| v).sum();
        let per_sync = s.linear_iterations as f64 / g.host_syncs as f64;
        eprintln!(
            "{name}{}: {} Newton, {} CG iterations; per Newton iteration {up:.0} B up, \
             {down:.0} B down (allowance {allowance:.0} B, {moving} moving nodes); {} host \
             waits ({per_sync:.1} CG iterations each); phases {phases:.3} s of {:.3} s",
            if extra.is_some() { " (multilevel)" } else { "" },
            g.newton_iterations,
            s.linear_iterations,
            g.host_syncs,
            s.wall_seconds
        );
        assert!(
            up <= allowance,
            "{name}: {up} B per Newton iteration to the device"
        );
        assert!(
            down <= allowance,
            "{name}: {down} B per Newton iteration back"
        );
        assert!(
            (phases - s.wall_seconds).abs() <= 0.05 * s.wall_seconds,
            "{name}: phases {phases} s, wall {} s",
            s.wall_seconds
        );
        if name == "twist" && extra.is_none() {
            assert!(
                16 * g.host_syncs as usize <= s.linear_iterations,
                "twist: {} waits for {} CG iterations",
                g.host_syncs,
                s.linear_iterations
            );
        }
    }
}

/// The device loop runs in f64 only: a scene asking for it in f32 is refused before any
/// device work, as an input error on `solver.newton` (exit 2), in one line. Needs no GPU.
#[test]
fn f32_device_loop_is_refused_in_one_line() {
    let dir = std::env::temp_dir().join(format!("stickslip-gpu-newton-f32-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp folder");
    let scene = dir.join("f32.toml");
    let twist = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/twist.toml"),
    )
    .expect("scenes/twist.toml");
    std::fs::write(
        &scene,
        format!("{twist}\n[solver]\nnewton = \"gpu\"\nprecision = \"f32\"\n"),
    )
    .expect("scene file");
    let opts = RunOptions {
        scene: Some(scene.display().to_string()),
        out: Some(dir.join("out")),
        steps: Some(1),
        quiet: true,
        ..RunOptions::default()
    };
    let e = run(&opts).expect_err("f32 device loop must be refused");
    let msg = e.to_string();
    assert_eq!(e.exit_code(), 2, "{msg}");
    assert!(
        msg.contains("solver.newton") && msg.contains("f64") && !msg.contains('\n'),
        "{msg}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
