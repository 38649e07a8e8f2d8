//! A simulator's own Newton loop calling stickslip: a 3D mass-spring chain pinned at one
//! end, whose last node slides on the tilted plane x + z = const, falls under gravity with
//! backward Euler (the incremental potential E(x) = ½‖x − x̃‖²_M / h² + springs − Mg·x).
//! Each Newton iteration hands the Hessian and gradient to the solver; the constraints and
//! the sparsity pattern never change, so the solver's analysis is reused throughout.
//!
//!     cargo run --release --example embed [cholesky|cg|gpu]

use stickslip::{Constraint, Error, Precision, Problem, Solver, SolverConfig};

const N: usize = 20; // nodes
const H: f64 = 0.01; // time step (s)
const MASS: f64 = 0.05; // per node (kg)
const K: f64 = 2.0e3; // spring stiffness (N/m)
const REST: f64 = 0.05; // rest length (m)
const GRAVITY: [f64; 3] = [0.0, -9.81, 0.0];

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn run() -> Result<(), Error> {
    let config = match std::env::args().nth(1).as_deref() {
        Some("cg") => SolverConfig::cg().tol(1e-10),
        Some("gpu") => SolverConfig::gpu(Precision::Mixed).tol(1e-10),
        _ => SolverConfig::cholesky(),
    };
    let mut solver = Solver::new(config)?;

    // The chain starts straight along x; node 0 is pinned, the last node keeps to its plane.
    let mut x: Vec<f64> = (0..N).flat_map(|i| [i as f64 * REST, 0.0, 0.0]).collect();
    let mut v = vec![0.0; 3 * N];
    let constraints = [
        Constraint::sticky(0),
        Constraint::plane(N - 1, &[1.0, 0.0, 1.0]),
    ];

    let (t0, g0) = incremental_potential(&x, &x);
    let mut problem = Problem::from_triplets(3, N, &t0, &g0, &constraints)?;
    for step in 0..50 {
        let xt: Vec<f64> = x.iter().zip(&v).map(|(x, v)| x + H * v).collect();
        let x_start = x.clone();
        let mut iterations = 0;
        loop {
            let (triplets, g) = incremental_potential(&x, &xt);
            problem.update_values(&triplets, &g)?;
            let sol = solver.solve(&problem)?;
            // Full Newton steps suffice for this mild problem (a simulator would line-search).
            for (xi, d) in x.iter_mut().zip(&sol.dx) {
                *xi += d;
            }
            iterations += 1;
            let step_norm = sol.dx.iter().fold(0.0f64, |m, d| m.max(d.abs()));
            if step_norm / H < 1e-6 || iterations == 50 {
                break;
            }
        }
        for k in 0..3 * N {
            v[k] = (x[k] - x_start[k]) / H;
        }
        if step % 10 == 9 {
            let tip = &x[3 * (N - 1)..];
            println!(
                "step {:3}: {iterations} Newton iterations, tip at ({:+.4}, {:+.4}, {:+.4}), x + z = {:+.3e}",
                step + 1,
                tip[0],
                tip[1],
                tip[2],
                tip[0] + tip[2] - (N - 1) as f64 * REST
            );
        }
    }
    println!("solver: {:?}", solver.config().kind);
    Ok(())
}

/// The Hessian (triplets, both triangles, springs projected to PSD) and the gradient of
/// E(x) = ½‖x − x̃‖²_M / h² + Σ ½K(|x_j − x_i| − L)² − Σ m g·x_i, scaled by h².
fn incremental_potential(x: &[f64], xt: &[f64]) -> (Vec<(usize, usize, f64)>, Vec<f64>) {
    let h2 = H * H;
    let mut t = Vec::new();
    let mut g = vec![0.0; 3 * N];
    for i in 0..3 * N {
        t.push((i, i, MASS));
        g[i] = MASS * (x[i] - xt[i]) - h2 * MASS * GRAVITY[i % 3];
    }
    for i in 0..N - 1 {
        let j = i + 1;
        let d: Vec<f64> = (0..3).map(|a| x[3 * j + a] - x[3 * i + a]).collect();
        let l = d.iter().map(|v| v * v).sum::<f64>().sqrt();
        for a in 0..3 {
            let f = h2 * K * (l - REST) * d[a] / l;
            g[3 * j + a] += f;
            g[3 * i + a] -= f;
        }
        // K(ddᵀ/l² + max(0, 1 − L/l)(I − ddᵀ/l²)): the compressed spring's negative
        // transverse stiffness is dropped, which keeps the Hessian positive semi-definite.
        let s = (1.0 - REST / l).max(0.0);
        for a in 0..3 {
            for b in 0..3 {
                let ddt = d[a] * d[b] / (l * l);
                let eye = if a == b { 1.0 } else { 0.0 };
                let kab = h2 * K * (ddt + s * (eye - ddt));
                t.push((3 * i + a, 3 * i + b, kab));
                t.push((3 * j + a, 3 * j + b, kab));
                t.push((3 * i + a, 3 * j + b, -kab));
                t.push((3 * j + a, 3 * i + b, -kab));
            }
        }
    }
    (t, g)
}
