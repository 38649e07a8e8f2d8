use stickslip::gpu::{GpuContext, GpuOptions, GpuParams, GpuSolver, Precision};
use stickslip::hard::{self, Size};
fn main() {
    let ctx = GpuContext::new(&GpuOptions::default()).expect("ctx");
    let cases = vec![
        hard::conditioned(Size::Ci, 1e10, false),
        hard::conditioned(Size::Ci, 1e8, true),
        hard::conditioned(Size::Ci, 1e10, true),
        hard::scaled(Size::Ci, 1e30, 1e-30),
    ];
    for c in cases {
        let e = c.eliminated();
        let yr = hard::reference(&e).expect("ref").y;
        let kappa = hard::condition_number(&e);
        for (prec, tol) in [(Precision::Mixed, 1e-11), (Precision::F64, 1e-11)] {
            let p = GpuParams { precision: prec, tol, max_iters: 20_000, ..Default::default() };
            let mut s = GpuSolver::new(&ctx, &e, &p).expect("solver");
            match s.solve() {
                Ok((y, _, info)) => {
                    let n: f64 = yr.iter().map(|v| v * v).sum::<f64>().sqrt();
                    let d: f64 = y.iter().zip(&yr).map(|(a, b)| (a - b) * (a - b)).sum::<f64>().sqrt();
                    println!("{:<22} κ {:.3e} {prec} claimed yes err {:.2e} it {} outer {} res {:.1e} t {:.4}s fallback {:?}",
                        c.name, kappa, d / n, info.iterations, info.outer_refinements, info.relative_residual, info.seconds.solve, info.fallback);
                }
                Err(err) => println!("{:<22} κ {:.3e} {prec} claimed no: {err} fallback {:?}", c.name, kappa, s.last_fallback()),
            }
        }
    }
}
