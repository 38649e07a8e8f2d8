//! Moving boundary conditions (docs/method.md, "Moving boundary conditions"): in `twist`
//! and `compress` every moving node reaches its target within ε·h and is then eliminated,
//! every step; k_M history and the Newton iteration at which elimination took over are
//! recorded.

use stickslip::sim::driver::{load_scene, run, RunOptions, RunSummary};
use stickslip::sim::scene::BcShape;

fn run_scene(name: &str) -> RunSummary {
    let out = std::env::temp_dir().join(format!(
        "stickslip-sim-moving-{}-{name}",
        std::process::id()
    ));
    let opts = RunOptions {
        scene: Some(name.into()),
        out: Some(out.clone()),
        quiet: true,
        ..RunOptions::default()
    };
    let s = run(&opts).unwrap_or_else(|e| panic!("{name}: {e}"));
    let csv = std::fs::read_to_string(out.join("steps.csv")).expect("steps.csv");
    let header = csv.lines().next().expect("header");
    assert!(
        header.contains(",k_m,eliminated_at_iteration,"),
        "{name}: {header}"
    );
    let _ = std::fs::remove_dir_all(&out);
    s
}

fn check(name: &str) {
    let s = run_scene(name);
    let scene = load_scene(name, 1.0).expect("scene");
    let m = s.moving_boundary.as_ref().expect("moving summary");
    eprintln!(
        "{name}: {} moving nodes, k_M {:e} → {:e} ({} doublings), history {:?}",
        m.moving_nodes, m.k_m_start, m.k_m_final, m.k_m_doublings, m.k_m_history
    );
    eprintln!(
        "{name}: elimination took over at Newton iteration (per step) {:?}",
        m.eliminated_at_iteration
    );
    eprintln!(
        "{name}: first step eliminated at its start: {:?}",
        m.first_step_eliminated_at_start
    );
    assert!(m.all_eliminated_every_step);
    assert_eq!(m.eliminated_at_iteration.len(), s.steps);
    // At the end, every moving node sits on its target set at t_end (it was snapped, then
    // eliminated, so it cannot drift): offset within round-off, far inside ε·h.
    let d = scene.dim;
    let eps_h = scene.moving.tolerance * scene.characteristic_length * scene.time_step;
    let mut worst = 0.0f64;
    for b in scene.bcs.iter().filter(|b| b.motion.is_some()) {
        let x = &s.final_positions[b.node * d..(b.node + 1) * d];
        let off = match b.shape_at(s.end_time) {
            BcShape::Sticky { anchor } => (0..d)
                .map(|a| (x[a] - anchor[a]).powi(2))
                .sum::<f64>()
                .sqrt(),
            BcShape::Plane { normal, offset } => {
                ((0..d).map(|a| normal[a] * x[a]).sum::<f64>() - offset).abs()
            }
            BcShape::Line { .. } => unreachable!("no line in these scenes"),
        };
        worst = worst.max(off);
    }
    eprintln!("{name}: largest final offset of a moving node from its target {worst:e} m (ε·h = {eps_h:e} m)");
    assert!(
        worst <= 1e-9 * scene.characteristic_length,
        "offset {worst:e}"
    );
}

#[test]
fn twist_moving_end_reaches_target_then_is_eliminated() {
    check("twist");
}

#[test]
fn compress_ceiling_reaches_target_then_is_eliminated() {
    check("compress");
}

#[test]
fn augmented_lagrangian_variant_reaches_targets_too() {
    let text = stickslip::sim::scene::builtin("twist")
        .expect("builtin")
        .replace(
            "tolerance = 1e-3",
            "tolerance = 1e-3\naugmented_lagrangian = true",
        );
    let dir = std::env::temp_dir().join(format!("stickslip-sim-moving-al-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("tmp");
    let path = dir.join("twist-al.toml");
    std::fs::write(&path, text).expect("write");
    let opts = RunOptions {
        scene: Some(path.display().to_string()),
        out: Some(dir.join("out")),
        steps: Some(20),
        quiet: true,
        ..RunOptions::default()
    };
    let s = run(&opts).unwrap_or_else(|e| panic!("twist-al: {e}"));
    let m = s.moving_boundary.as_ref().expect("moving");
    eprintln!(
        "twist (augmented Lagrangian): k_M history {:?}, elimination iterations {:?}",
        m.k_m_history, m.eliminated_at_iteration
    );
    assert!(m.settings.augmented_lagrangian && m.all_eliminated_every_step);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn slip_line_node_stays_on_2x_plus_3y_eq_4() {
    let out = std::env::temp_dir().join(format!("stickslip-sim-slip-line-{}", std::process::id()));
    let opts = RunOptions {
        scene: Some("slip-line".into()),
        out: Some(out.clone()),
        quiet: true,
        ..RunOptions::default()
    };
    let s = run(&opts).unwrap_or_else(|e| panic!("slip-line: {e}"));
    let scene = load_scene("slip-line", 1.0).expect("scene");
    let node = scene.bcs[0].node;
    let x = &s.final_positions[2 * node..2 * node + 2];
    let r = 2.0 * x[0] + 3.0 * x[1] - 4.0;
    eprintln!(
        "slip-line: node {node} ends at ({}, {}), 2x + 3y − 4 = {r:e}",
        x[0], x[1]
    );
    assert!(r.abs() <= 1e-12);
    // It slid: the line is free along (3, −2)/√13.
    let x0 = &scene.x0[2 * node..2 * node + 2];
    assert!((x[0] - x0[0]).abs() > 1e-3);
    let _ = std::fs::remove_dir_all(&out);
}
