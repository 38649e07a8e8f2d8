//! Device time per kernel of one f64 CG iteration: the device PCG (`gpu::pcg`, what
//! `solve --solver gpu --precision f64` and the device Newton loop run) against the
//! precision kernels' f64 level (`gpu::GpuSolver`), on one generated 3D system with the
//! realistic constraint mix, without and with the aggregates; then the device PCG with the
//! multilevel preconditioner (its V-cycle's kernels by level, the levels built on the
//! host).
//!
//!     cargo run --release --example pcg_kernels -- [NODES] [REPS]
//!
//! Prints the fastest of REPS timestamped iterations per kernel (default 27,000 nodes, 5
//! reps). Needs an adapter with SHADER_F64 and TIMESTAMP_QUERY.

use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::gpu::{GpuContext, GpuOptions, GpuParams, GpuSolver, KernelTime, PcgSolver};
use stickslip::solve::cg::Preconditioner;
use stickslip::solve::coarse::CoarseSpace;
use stickslip::Precision;

fn print(what: &str, times: Option<Vec<KernelTime>>) {
    let Some(times) = times else {
        println!("{what}: no TIMESTAMP_QUERY on this adapter");
        return;
    };
    let total: f64 = times.iter().map(|k| k.best_s).sum();
    println!("{what}: {:.2} ms per iteration", total * 1e3);
    for k in &times {
        println!("  {:16} {:8.3} ms", k.name, k.best_s * 1e3);
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let nodes: usize = args.next().map_or(Ok(27_000), |a| a.parse())?;
    let reps: usize = args.next().map_or(Ok(5), |a| a.parse())?;
    let ctx = GpuContext::new(&GpuOptions::default())?;
    let s = random_system(&SystemSpec::with_nodes(3, nodes, 1));
    let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
    println!("{} nodes on {}", nodes, ctx.adapter_name());
    for coarse in [CoarseSpace::None, CoarseSpace::Aggregates] {
        let p = GpuParams {
            precision: Precision::F64,
            tol: 1e-8,
            coarse,
            ..Default::default()
        };
        let mut pcg = PcgSolver::new(&ctx, &e, &p)?;
        print(
            &format!("device PCG, coarse {}", coarse.name()),
            pcg.profile_kernels(reps)?,
        );
        let mut kernels = GpuSolver::new(&ctx, &e, &p)?;
        print(
            &format!("precision kernels f64, coarse {}", coarse.name()),
            kernels.profile_kernels(reps)?,
        );
    }
    let p = GpuParams {
        precision: Precision::F64,
        tol: 1e-8,
        preconditioner: Preconditioner::Multilevel,
        ..Default::default()
    };
    let mut pcg = PcgSolver::new(&ctx, &e, &p)?;
    print("device PCG, multilevel", pcg.profile_kernels(reps)?);
    Ok(())
}
