//! Runs one hard case (src/hard.rs) at a grid scale on the GPU in f64 and mixed precision:
//! `cargo run --release --example hard_case -- NAME [scale] [tol] [inner_tol]`.

use stickslip::gpu::{GpuContext, GpuOptions, GpuParams, GpuSolver, Precision};
use stickslip::hard::{self, Size};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let name = args.get(1).cloned().unwrap_or_else(|| "kappa-1e6".into());
    let scale: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1);
    let tol: f64 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(1e-10);
    let inner_tol: f64 = args
        .get(4)
        .and_then(|s| s.parse().ok())
        .unwrap_or(GpuParams::default().inner_tol);
    let size = if scale <= 1 {
        Size::Ci
    } else {
        Size::Scale(scale)
    };
    let case = hard::suite(size)
        .into_iter()
        .find(|c| c.name == name)
        .ok_or_else(|| format!("no hard case named {name}"))?;
    let e = case.eliminated();
    let ctx = GpuContext::new(&GpuOptions::default())?;
    for precision in [Precision::F64, Precision::Mixed] {
        let params = GpuParams {
            precision,
            tol,
            max_iters: 50_000,
            inner_tol,
            ..Default::default()
        };
        let mut sol = GpuSolver::new(&ctx, &e, &params)?;
        let (_, _, info) = sol.solve()?;
        println!(
            "{name} ({} dofs) {precision}: {} iterations, {} segments, solve {:.3} s, residual {:.2e}, κ̃ {:?}, fallback {:?}",
            case.ndof(),
            info.iterations,
            info.outer_refinements,
            info.seconds.solve,
            info.relative_residual,
            info.condition_estimate.map(|k| format!("{k:.2e}")),
            info.fallback
        );
    }
    Ok(())
}
