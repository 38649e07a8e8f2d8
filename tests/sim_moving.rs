//! Moving boundary conditions (design.md §5): in `twist` and `compress` every moving node
//! reaches its target within ε·h and is then eliminated, every step; k_M history and the
//! Newton iteration at which elimination took over are recorded.

use stickslip::driver::{load_scene, run, RunOptions, RunSummary};
use stickslip::scene::BcShape;

fn run_scene(name: &str) -> RunSummary {
    let out = std::env::temp_dir().join(format!("stickslip-sim-moving-{}-{name}", std::process::id()));
    let opts = RunOptions {
        scene: Some(name.into()),
        out: Some(out.clone()),
        quiet: true,
        ..RunOptions::default()
    };
    let s = run(&opts).unwrap_or_else(|e| panic!("{name}: {e}"));
    let csv = std::fs::read_to_string(out.join("steps.csv")).expect("steps.csv");
    assert!(csv.lines().next().expect("header").ends_with(",k_m,eliminated_at_iteration"));
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
    eprintln!("{name}: elimination took over at Newton iteration (per step) {:?}", m.eliminated_at_iteration);
    eprintln!("{name}: first step eliminated at its start: {:?}", m.first_step_eliminated_at_start);
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
            BcShape::Sticky { anchor } => (0..d).map(|a| (x[a] - anchor[a]).powi(2)).sum::<f64>().sqrt(),
            BcShape::Plane { normal, offset } => ((0..d).map(|a| normal[a] * x[a]).sum::<f64>() - offset).abs(),
            BcShape::Line { .. } => unreachable!("no line in these scenes"),
        };
        worst = worst.max(off);
    }
    eprintln!("{name}: largest final offset of a moving node from its target {worst:e} m (ε·h = {eps_h:e} m)");
    assert!(worst <= 1e-9 * scene.characteristic_length, "offset {worst:e}");
}

#[test]
fn twist_moving_end_reaches_target_then_is_eliminated() {
    check("twist");
}

#[test]
fn compress_ceiling_reaches_target_then_is_eliminated() {
    check("compress");
}
