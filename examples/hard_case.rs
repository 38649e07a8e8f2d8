//! Runs one hard case (src/app/bench/hard.rs) at a grid scale on the device PCG in f64 and in
//! mixed precision, each without and with a coarse correction, solved alternately
//! (best of `reps` after a warm-up, so machine noise hits every configuration alike):
//! `cargo run --release --example hard_case -- NAME [scale] [tol] [reps]`.
//! `STICKSLIP_NO_DIFF=1` turns the f32 difference form off (`GpuParams::f32_difference`),
//! `STICKSLIP_DIFF=1` on for every f32 operator;
//! `STICKSLIP_INNER_TOL=δ` sets mixed precision's reliable-update factor;
//! `STICKSLIP_COARSE=aggregates` the coarse space of the second pair (default translations),
//! `STICKSLIP_ONLY_COARSE=1` runs that pair only.

use stickslip::app::hard::{self, Size};
use stickslip::gpu::{DifferenceForm, GpuContext, GpuOptions, GpuParams, PcgSolver, Precision};
use stickslip::solve::coarse::CoarseSpace;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let name = args.get(1).cloned().unwrap_or_else(|| "kappa-1e6".into());
    let scale: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1);
    let tol: f64 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(1e-10);
    let reps: usize = args.get(4).and_then(|s| s.parse().ok()).unwrap_or(1);
    let diff_choice = if std::env::var_os("STICKSLIP_NO_DIFF").is_some() {
        DifferenceForm::Off
    } else if std::env::var_os("STICKSLIP_DIFF").is_some() {
        DifferenceForm::On
    } else {
        DifferenceForm::Auto
    };
    let inner_tol = std::env::var("STICKSLIP_INNER_TOL")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(GpuParams::default().inner_tol);
    let size = Size::from_scale(scale);
    let case = hard::named(size, &name).ok_or_else(|| format!("no hard case named {name}"))?;
    let e = case.eliminated();
    let ctx = GpuContext::new(&GpuOptions::default())?;
    let coarse: CoarseSpace = std::env::var("STICKSLIP_COARSE")
        .ok()
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(CoarseSpace::Translations);
    let configs = [
        (Precision::F64, CoarseSpace::None),
        (Precision::Mixed, CoarseSpace::None),
        (Precision::F64, coarse),
        (Precision::Mixed, coarse),
    ];
    // STICKSLIP_ONLY_COARSE=1: the pair with the coarse space only.
    let only = std::env::var_os("STICKSLIP_ONLY_COARSE").is_some();
    let configs: Vec<_> = configs
        .into_iter()
        .filter(|(_, c)| !only || *c == coarse)
        .collect();
    let mut solvers = Vec::new();
    for &(precision, coarse) in &configs {
        let params = GpuParams {
            precision,
            tol,
            max_iters: 50_000,
            coarse,
            f32_difference: diff_choice,
            inner_tol,
            ..Default::default()
        };
        solvers.push(PcgSolver::new(&ctx, &e, &params)?);
    }
    let mut best = vec![f64::INFINITY; configs.len()];
    let mut last = vec![None; configs.len()];
    for rep in 0..=reps {
        for (k, sol) in solvers.iter_mut().enumerate() {
            let info = sol.solve()?.info;
            if rep > 0 {
                best[k] = best[k].min(info.seconds.solve);
            }
            last[k] = Some(info);
        }
    }
    println!(
        "{name}: {} DOFs, tol {tol:e}, best of {reps}, f32 difference form {}",
        case.ndof(),
        format!("{diff_choice:?}").to_lowercase()
    );
    for (k, (precision, coarse)) in configs.iter().enumerate() {
        let Some(info) = &last[k] else { continue };
        println!(
            "  {precision:<5} coarse {:<12} {:>6} iterations ({:>2} segments, {} recorded, {} read-backs)  {:>8.3} s  {:>6.2} ms/iteration (device {})  residual {:.2e}  κ̃ {}  fallback {:?} diff {}",
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
            info.fallback, info.f32_difference
        );
    }
    for pair in best.chunks_exact(2).zip(configs.chunks_exact(2)) {
        let (b, c) = pair;
        println!("  f64/mixed, coarse {}: {:.2}", c[0].1.name(), b[0] / b[1]);
    }
    Ok(())
}
