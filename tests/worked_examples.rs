//! The two worked examples of docs/method.md ("Worked examples"), with answers worked
//! out by hand in the comments. Two nodes in 2D starting at the origin, so the
//! constraints on positions become constraints on Δx.

use stickslip::core::constraints::{Constraint, ConstraintKind, Frames};
use stickslip::core::elimination::{reactions, ConstrainedDiagonal, Eliminated};
use stickslip::core::sparse::BlockCsr;
use stickslip::solve::cg::{self, CgParams};
use stickslip::solve::oracle;

fn h_from_dense(d: &[[f64; 4]; 4]) -> BlockCsr {
    let mut t = Vec::new();
    for (r, row) in d.iter().enumerate() {
        for (c, &v) in row.iter().enumerate() {
            if v != 0.0 {
                t.push((r, c, v));
            }
        }
    }
    BlockCsr::from_triplets(2, 4, &t, false)
}

fn solve_both(h: &BlockCsr, g: &[f64], cs: &[Constraint]) -> (Vec<f64>, Vec<f64>) {
    let frames = Frames::build(2, 2, cs).unwrap();
    let e = Eliminated::new(h, g, &frames, ConstrainedDiagonal::Identity);
    let (y, _) = oracle::solve(&e).unwrap();
    let dx = e.recover(&y);
    let (ycg, _) = cg::solve(
        &e,
        &CgParams {
            tol: 1e-14,
            ..Default::default()
        },
    )
    .unwrap();
    let dxcg = e.recover(&ycg);
    for k in 0..4 {
        assert!((dx[k] - dxcg[k]).abs() < 1e-13);
    }
    (dx.clone(), reactions(h, g, &dx))
}

/// Worked example 1: fix the second node at (1, 2).
///
/// H is a unit spring between the nodes plus unit mass: [[2I, −I], [−I, 2I]], g = 0.
/// Δx_2 = (1, 2); the free node minimizes ½·2|Δx_1|² − Δx_1·Δx_2, so Δx_1 = Δx_2/2
/// = (0.5, 1). Reactions f = −(HΔx + g): f_1 = −(2·(0.5, 1) − (1, 2)) = 0 and
/// f_2 = −(−(0.5, 1) + 2·(1, 2)) = (−1.5, −3).
#[test]
fn worked_example_fixed_node_at_1_2() {
    let h = h_from_dense(&[
        [2.0, 0.0, -1.0, 0.0],
        [0.0, 2.0, 0.0, -1.0],
        [-1.0, 0.0, 2.0, 0.0],
        [0.0, -1.0, 0.0, 2.0],
    ]);
    let g = [0.0; 4];
    let cs = [Constraint {
        node: 1,
        kind: ConstraintKind::Sticky {
            displacement: Some(vec![1.0, 2.0]),
        },
        label: "fix".into(),
    }];
    let (dx, f) = solve_both(&h, &g, &cs);
    let want = [0.5, 1.0, 1.0, 2.0];
    let want_f = [0.0, 0.0, -1.5, -3.0];
    for k in 0..4 {
        assert!((dx[k] - want[k]).abs() < 1e-15, "dx[{k}] = {}", dx[k]);
        assert!((f[k] - want_f[k]).abs() < 1e-15, "f[{k}] = {}", f[k]);
    }
    // The same through the global form B Δx = p: rows [0 0 1 0; 0 0 0 1], p = (1, 2).
    let rows = [Constraint {
        node: 1,
        kind: ConstraintKind::Rows {
            rows: vec![vec![1.0, 0.0], vec![0.0, 1.0]],
            values: vec![1.0, 2.0],
        },
        label: "B".into(),
    }];
    let (dx2, _) = solve_both(&h, &g, &rows);
    for k in 0..4 {
        assert!((dx2[k] - want[k]).abs() < 1e-15);
    }
}

/// Worked example 2: the first node on the line 2x + 3y = 4.
///
/// H = I, g = (1, 0, 0, 0). Minimize ½|d|² + d_x subject to 2d_x + 3d_y = 4:
/// d = −g_1 + μ(2, 3) with 2(−1 + 2μ) + 9μ = 4, so μ = 6/13 and
/// Δx_1 = (−1/13, 18/13); the second node has no force, Δx_2 = 0. The reaction
/// f_1 = −(d + g_1) = −(6/13)(2, 3) lies along the normal.
#[test]
fn worked_example_node_on_line_2x_plus_3y_eq_4() {
    let h = h_from_dense(&[
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
    ]);
    let g = [1.0, 0.0, 0.0, 0.0];
    let cs = [Constraint {
        node: 0,
        kind: ConstraintKind::Plane {
            normal: vec![2.0, 3.0],
            offset: 4.0,
        },
        label: "line".into(),
    }];
    let (dx, f) = solve_both(&h, &g, &cs);
    let want = [-1.0 / 13.0, 18.0 / 13.0, 0.0, 0.0];
    let want_f = [-12.0 / 13.0, -18.0 / 13.0, 0.0, 0.0];
    // Tolerance: 4 ulps of values below 2 (the normal is normalized, the lift and the
    // rotation each round once, and f = −(HΔx + g) adds one more rounding).
    let tol = 4.0 * f64::EPSILON;
    for k in 0..4 {
        assert!((dx[k] - want[k]).abs() < tol, "dx[{k}] = {}", dx[k]);
        assert!((f[k] - want_f[k]).abs() < tol, "f[{k}] = {}", f[k]);
    }
    // The node lands on the line.
    // Evaluating the form rounds each term: a few ulps of Σ|terms|.
    let scale = (2.0 * dx[0]).abs() + (3.0 * dx[1]).abs() + 4.0;
    assert!((2.0 * dx[0] + 3.0 * dx[1] - 4.0).abs() <= 4.0 * f64::EPSILON * scale);
}
