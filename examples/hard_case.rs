//! Runs one hard case (src/hard.rs) at a grid scale on the GPU: f64 CG and mixed precision,
//! each without and with the coarse correction on the translations, solved alternately
//! (best of `reps` after a warm-up, so machine noise hits every configuration alike):
//! `cargo run --release --example hard_case -- NAME [scale] [tol] [reps]`.
//! `STICKSLIP_NO_DIFF=1` turns the f32 difference form off (`GpuParams::f32_difference`);
//! `STICKSLIP_INNER_TOL=δ` sets mixed precision's reliable-update factor;
//! `STICKSLIP_WORKGROUPS=n` the workgroups of the CG kernels (`GpuParams::workgroups`).

use stickslip::coarse::CoarseSpace;
use stickslip::gpu::{DifferenceForm, GpuContext, GpuOptions, GpuParams, GpuSolver, Precision};
use stickslip::hard::{self, Size};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let name = args.get(1).cloned().unwrap_or_else(|| "kappa-1e6".into());
    let scale: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1);
    let tol: f64 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(1e-10);
    let reps: usize = args.get(4).and_then(|s| s.parse().ok()).unwrap_or(1);
    let diff = std::env::var_os("STICKSLIP_NO_DIFF").is_none();
    let inner_tol = std::env::var("STICKSLIP_INNER_TOL")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(GpuParams::default().inner_tol);
    let workgroups = std::env::var("STICKSLIP_WORKGROUPS")
        .ok()
        .and_then(|s| s.parse().ok());
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
    let configs = [
        (Precision::F64, CoarseSpace::None),
        (Precision::Mixed, CoarseSpace::None),
        (Precision::F64, CoarseSpace::Translations),
        (Precision::Mixed, CoarseSpace::Translations),
    ];
    let mut solvers = Vec::new();
    for (precision, coarse) in configs {
        let params = GpuParams {
            precision,
            tol,
            max_iters: 50_000,
            coarse,
            f32_difference: if diff {
                DifferenceForm::Auto
            } else {
                DifferenceForm::Off
            },
            inner_tol,
            workgroups,
            ..Default::default()
        };
        solvers.push(GpuSolver::new(&ctx, &e, &params)?);
    }
    let mut best = vec![f64::INFINITY; configs.len()];
    let mut last = vec![None; configs.len()];
    for rep in 0..=reps {
        for (k, sol) in solvers.iter_mut().enumerate() {
            let (_, _, info) = sol.solve()?;
            if rep > 0 {
                best[k] = best[k].min(info.seconds.solve);
            }
            last[k] = Some(info);
        }
    }
    println!(
        "{name}: {} DOFs, tol {tol:e}, best of {reps}, f32 difference form {}",
        case.ndof(),
        if diff { "auto" } else { "off" }
    );
    for (k, (precision, coarse)) in configs.iter().enumerate() {
        let Some(info) = &last[k] else { continue };
        println!(
            "  {precision:<5} coarse {:<12} {:>6} iterations ({:>2} segments, {} recorded, {} read-backs)  {:>8.3} s  {:>6.2} ms/iteration (device {})  residual {:.2e}  κ̃ {}  fallback {:?}",
            coarse.name(),
            info.iterations,
            info.outer_refinements,
            info.recorded_iterations,
            info.readbacks,
            best[k],
            1e3 * best[k] / info.iterations.max(1) as f64,
            info.gpu_seconds.map_or("—".to_string(), |s| format!(
                "{:.2} ms/iteration",
                1e3 * s / info.iterations.max(1) as f64
            )),
            info.relative_residual,
            info.condition_estimate
                .map_or("—".to_string(), |k| format!("{k:.2e}")),
            info.fallback
        );
    }
    for (f, m, label) in [(0, 1, "none"), (2, 3, "translations")] {
        println!("  f64/mixed, coarse {label}: {:.2}", best[f] / best[m]);
    }
    Ok(())
}
