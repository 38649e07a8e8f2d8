//! A/B of mixed precision on the device PCG against the device PCG in f64, on one
//! generated 3D system, alternating runs in one process (this machine is noisy):
//! `cargo run --release --example mixed_ab -- [nodes] [tol] [reps]`.

use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::gpu::{
    GpuContext, GpuError, GpuOptions, GpuParams, GpuSolveInfo, PcgSolver, Precision,
};

type Run<'a> = Box<dyn FnMut() -> Result<GpuSolveInfo, GpuError> + 'a>;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let arg = |i: usize, d: f64| args.get(i).and_then(|s| s.parse().ok()).unwrap_or(d);
    let nodes = arg(1, 64_000.0) as usize;
    let tol = arg(2, 1e-9);
    let reps = arg(3, 3.0) as usize;
    let s = random_system(&SystemSpec::with_nodes(3, nodes, 1));
    let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
    let ctx = GpuContext::new(&GpuOptions::default())?;
    let params = |precision| GpuParams {
        precision,
        tol,
        max_iters: 20_000,
        ..Default::default()
    };
    let mut f64_pcg = PcgSolver::new(&ctx, &e, &params(Precision::F64))?;
    let mut mixed_pcg = PcgSolver::new(&ctx, &e, &params(Precision::Mixed))?;
    let mut runs: Vec<(&str, Run)> = vec![
        ("PCG f64", Box::new(|| f64_pcg.solve().map(|o| o.info))),
        ("PCG mixed", Box::new(|| mixed_pcg.solve().map(|o| o.info))),
    ];
    println!(
        "{} nodes, {} dofs, tol {tol:e}, adapter {}",
        s.h.n,
        s.h.ndof(),
        ctx.adapter_name()
    );
    let mut best = vec![f64::INFINITY; runs.len()];
    for rep in 0..reps {
        for (k, (name, run)) in runs.iter_mut().enumerate() {
            let info = run()?;
            best[k] = best[k].min(info.seconds.solve);
            println!(
                "rep {rep} {name:>13}: {:>5} iterations ({:>5} recorded), {:>3} outer, {:>3} readbacks, residual {:.2e}, solve {:.3} s ({:.2} ms/iteration)",
                info.iterations,
                info.recorded_iterations,
                info.outer_refinements,
                info.readbacks,
                info.relative_residual,
                info.seconds.solve,
                1e3 * info.seconds.solve / info.iterations.max(1) as f64
            );
        }
    }
    let names: Vec<&str> = runs.iter().map(|(n, _)| *n).collect();
    println!("best of {reps} (solve s):");
    for (name, b) in names.iter().zip(&best) {
        println!("  {name:>13}: {b:.3} ({:.2}× PCG f64)", b / best[0]);
    }
    Ok(())
}
