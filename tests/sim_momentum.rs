//! Momentum balance per step: p_k − p_{k−1} = h·(M·g + f_k), f_k the summed reaction force,
//! to a relative error ≤ 1e-3 of h·M·|g| (docs/method.md, "Checks that keep the math
//! honest"). Incline: the reaction has no component along the slope and the center of
//! mass gains h·g·sin 30° of speed along it.

use stickslip::sim::driver::{run, RunOptions, RunSummary};

fn out_dir(name: &str) -> std::path::PathBuf {
    std::env::temp_dir().join(format!(
        "stickslip-sim-momentum-{}-{name}",
        std::process::id()
    ))
}

fn run_scene(name: &str) -> RunSummary {
    let opts = RunOptions {
        scene: Some(name.into()),
        out: Some(out_dir(name)),
        quiet: true,
        ..RunOptions::default()
    };
    run(&opts).unwrap_or_else(|e| panic!("{name}: {e}"))
}

/// Largest |Δp − h(Mg + f)| / (h M |g|) over the steps.
fn momentum_error(s: &RunSummary) -> f64 {
    let h = s.time_step;
    let m = s.total_mass;
    let gn = s.gravity.iter().map(|g| g * g).sum::<f64>().sqrt();
    let scale = h * m * gn;
    let mut worst = 0.0f64;
    for w in s.records.windows(2) {
        let (a, b) = (&w[0], &w[1]);
        for k in 0..s.dimension {
            let dp = b.momentum[k] - a.momentum[k];
            let pred = h * (m * s.gravity[k] + b.reaction[k]);
            worst = worst.max((dp - pred).abs() / scale);
        }
    }
    worst
}

#[test]
fn hanging_balances_momentum_every_step() {
    let s = run_scene("hanging");
    let e = momentum_error(&s);
    eprintln!(
        "hanging: {} steps, worst momentum error {e:.3e} of h·M·|g|",
        s.steps
    );
    assert!(e <= 1e-3, "momentum error {e:e}");
    // The pins carry the weight plus the swing: the reaction is not trivially zero.
    let last = s.records.last().expect("records");
    assert!(last.reaction[1] > 0.0);
}

#[test]
fn bead_balances_momentum_every_step() {
    let s = run_scene("bead");
    let e = momentum_error(&s);
    eprintln!(
        "bead: {} steps, worst momentum error {e:.3e} of h·M·|g|",
        s.steps
    );
    assert!(e <= 1e-3, "momentum error {e:e}");
    // Along the wire t the reaction vanishes, so p·t gains h M (g·t) per step.
    let t = [1.0, -0.5, 0.3];
    let tn = (t.iter().map(|v| v * v).sum::<f64>()).sqrt();
    let t: Vec<f64> = t.iter().map(|v| v / tn).collect();
    let gt: f64 = s.gravity.iter().zip(&t).map(|(g, t)| g * t).sum();
    let scale = s.time_step * s.total_mass * 9.81;
    for w in s.records.windows(2) {
        let dpt: f64 = (0..3)
            .map(|k| (w[1].momentum[k] - w[0].momentum[k]) * t[k])
            .sum();
        let err = (dpt - s.time_step * s.total_mass * gt).abs() / scale;
        assert!(
            err <= 1e-3,
            "step {}: along-wire momentum error {err:e}",
            w[1].step
        );
        let ft: f64 = (0..3).map(|k| w[1].reaction[k] * t[k]).sum();
        assert!(
            ft.abs() <= 1e-9 * s.total_mass * 9.81,
            "reaction along the wire {ft:e}"
        );
    }
}

#[test]
fn incline_slides_with_g_sin_theta() {
    let s = run_scene("incline");
    let e = momentum_error(&s);
    eprintln!(
        "incline: {} steps, worst momentum error {e:.3e} of h·M·|g|",
        s.steps
    );
    assert!(e <= 1e-3, "momentum error {e:e}");
    let (sin, cos) = (30f64.to_radians().sin(), 30f64.to_radians().cos());
    let t = [cos, sin, 0.0]; // up the slope
    let n = [-sin, cos, 0.0];
    let h = s.time_step;
    let g = 9.81;
    let m = s.total_mass;
    let mut worst_speed = 0.0f64;
    for w in s.records.windows(2) {
        let (a, b) = (&w[0], &w[1]);
        // No reaction along the slope (nor along z).
        let ft: f64 = (0..3).map(|k| b.reaction[k] * t[k]).sum();
        assert!(
            ft.abs() <= 1e-9 * m * g,
            "step {}: reaction along the slope {ft:e}",
            b.step
        );
        assert!(b.reaction[2].abs() <= 1e-9 * m * g);
        // Center-of-mass speed down the slope grows by h g sin 30° per step.
        let va: f64 = (0..3).map(|k| a.momentum[k] * t[k]).sum::<f64>() / m;
        let vb: f64 = (0..3).map(|k| b.momentum[k] * t[k]).sum::<f64>() / m;
        let err = ((va - vb) - h * g * sin).abs() / (h * g);
        worst_speed = worst_speed.max(err);
        // The normal reaction balances the normal part of gravity on average: positive.
        let fnrm: f64 = (0..3).map(|k| b.reaction[k] * n[k]).sum();
        assert!(fnrm > 0.0, "step {}: normal reaction {fnrm}", b.step);
    }
    eprintln!("incline: worst along-slope speed-gain error {worst_speed:.3e} of h·g");
    assert!(worst_speed <= 1e-3);
    // COM position along the slope: x_com·t decreases like ½ g sin θ t² (implicit Euler:
    // exactly Σ_k k h² g sin θ).
    let n_steps = s.steps as f64;
    let expect = -h * h * g * sin * n_steps * (n_steps + 1.0) / 2.0;
    let c0: f64 = (0..3).map(|k| s.records[0].com[k] * t[k]).sum();
    let c1: f64 = (0..3)
        .map(|k| s.records.last().expect("records").com[k] * t[k])
        .sum();
    assert!(
        ((c1 - c0) - expect).abs() <= 1e-3 * expect.abs(),
        "COM moved {} expected {expect}",
        c1 - c0
    );
}
