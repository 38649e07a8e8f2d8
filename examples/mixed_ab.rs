//! A/B of the precision kernels' f64 CG (mixed precision's fallback level; `solve --solver
//! gpu` runs f64 on the device PCG) against mixed precision on one generated 3D system,
//! alternating runs in one process (this machine is noisy):
//! `cargo run --release --example mixed_ab -- [nodes] [tol] [reps]`.

use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::gpu::{GpuContext, GpuOptions, GpuParams, GpuSolver, Precision};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let arg = |i: usize, d: f64| args.get(i).and_then(|s| s.parse().ok()).unwrap_or(d);
    let nodes = arg(1, 64_000.0) as usize;
    let tol = arg(2, 1e-9);
    let reps = arg(3, 3.0) as usize;
    let s = random_system(&SystemSpec::with_nodes(3, nodes, 1));
    let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
    let ctx = GpuContext::new(&GpuOptions::default())?;
    let mut solvers = Vec::new();
    for precision in [Precision::F64, Precision::Mixed] {
        let params = GpuParams {
            precision,
            tol,
            max_iters: 20_000,
            ..Default::default()
        };
        solvers.push(GpuSolver::new(&ctx, &e, &params)?);
    }
    println!(
        "{} nodes, {} dofs, tol {tol:e}, adapter {}",
        s.h.n,
        s.h.ndof(),
        ctx.adapter_name()
    );
    let mut best = [f64::INFINITY; 2];
    for rep in 0..reps {
        for (k, sol) in solvers.iter_mut().enumerate() {
            let info = sol.solve()?.info;
            best[k] = best[k].min(info.seconds.solve);
            println!(
                "rep {rep} {:>5}: {:>5} iterations, {:>3} outer, {:>3} readbacks, residual {:.2e}, solve {:.3} s ({:.2} ms/iteration)",
                info.precision.to_string(),
                info.iterations,
                info.outer_refinements,
                info.readbacks,
                info.relative_residual,
                info.seconds.solve,
                1e3 * info.seconds.solve / info.iterations.max(1) as f64
            );
        }
    }
    println!(
        "best of {reps}: f64 {:.3} s, mixed {:.3} s, f64/mixed {:.2}",
        best[0],
        best[1],
        best[0] / best[1]
    );
    Ok(())
}
