//! Device time per kernel of one CG iteration of the device PCG (`gpu::pcg`, what
//! `solve --solver gpu` and the device Newton loop run), on one generated 3D system with
//! the realistic constraint mix, without and with the aggregates; in f64 then with the
//! multilevel preconditioner (its V-cycle's kernels by level, the levels built on the
//! host); in f32 with and without the difference form.
//!
//!     cargo run --release --example pcg_kernels -- [NODES] [REPS] [f64|f32]
//!
//! Prints the fastest of REPS timestamped iterations per kernel (default 27,000 nodes, 5
//! reps, f64). Needs an adapter with SHADER_F64 and TIMESTAMP_QUERY.

use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::gpu::{DifferenceForm, GpuContext, GpuOptions, GpuParams, KernelTime, PcgSolver};
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
    let precision: Precision = args.next().map_or(Ok(Precision::F64), |a| a.parse())?;
    let ctx = GpuContext::new(&GpuOptions::default())?;
    let s = random_system(&SystemSpec::with_nodes(3, nodes, 1));
    let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
    println!("{} nodes on {}", nodes, ctx.adapter_name());
    let forms: &[DifferenceForm] = match precision {
        Precision::F32 => &[DifferenceForm::On, DifferenceForm::Off],
        _ => &[DifferenceForm::Off],
    };
    for coarse in [CoarseSpace::None, CoarseSpace::Aggregates] {
        for &f32_difference in forms {
            let p = GpuParams {
                precision,
                tol: 1e-8,
                coarse,
                f32_difference,
                ..Default::default()
            };
            let what = format!(
                "{precision}, coarse {}, difference form {f32_difference:?}",
                coarse.name()
            );
            let mut pcg = PcgSolver::new(&ctx, &e, &p)?;
            print(&format!("device PCG {what}"), pcg.profile_kernels(reps)?);
        }
    }
    if precision != Precision::F64 {
        return Ok(());
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
