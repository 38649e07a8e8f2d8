//! Device time per CG kernel (timestamp queries, best of `reps`) of the precision kernels
//! (`GpuSolver`: mixed precision's f32 and f64 levels; the device PCG that `solve --solver
//! gpu` runs in f32 and f64 is examples/pcg_kernels.rs) on one generated 3D system in f64
//! and f32, with and without the coarse correction and the f32 difference form: what each
//! option costs per iteration on this adapter.
//! `cargo run --release --example kernel_ab -- [nodes] [reps] [realistic|none]` (the
//! constraint mix: slip nodes with rotations, or no constraints at all), or
//! `kernel_ab -- NAME:SCALE [reps]` for a hard case of src/app/hard.rs at a grid scale.
//! `STICKSLIP_WORKGROUPS=n` sets the workgroups of the CG kernels (`GpuParams::workgroups`).

use stickslip::app::hard::{self, Size};
use stickslip::cases::generate::{random_system, ConstraintMix, SystemSpec};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::gpu::{DifferenceForm, GpuContext, GpuOptions, GpuParams, GpuSolver, Precision};
use stickslip::solve::coarse::CoarseSpace;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let reps: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(20);
    let hard_case = args
        .get(1)
        .and_then(|a| a.split_once(':'))
        .map(|(name, scale)| (name.to_string(), scale.parse::<usize>().unwrap_or(1)));
    // Either a hard case or a generated system; the eliminated system borrows from it.
    let mut case = None;
    let mut generated = None;
    if let Some((name, scale)) = hard_case {
        let size = Size::from_scale(scale);
        let c = hard::named(size, &name).ok_or_else(|| format!("no hard case named {name}"))?;
        println!("hard case {name}, grid scale {scale}, {} DOFs", c.ndof());
        case = Some(c);
    } else {
        let nodes: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(64_000);
        let mut spec = SystemSpec::with_nodes(3, nodes, 1);
        if args.get(3).is_some_and(|m| m == "none") {
            spec.mix = ConstraintMix::None;
        }
        generated = Some(random_system(&spec));
    }
    let (e, n, rotated) = match (&case, &generated) {
        (Some(c), _) => (c.eliminated(), c.h.n, c.frames.rot_nodes.len()),
        (None, Some(s)) => (
            Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity),
            s.h.n,
            s.frames.rot_nodes.len(),
        ),
        (None, None) => unreachable!("one of the two is built above"),
    };
    let ctx = GpuContext::new(&GpuOptions::default())?;
    let workgroups: Option<u32> = std::env::var("STICKSLIP_WORKGROUPS")
        .ok()
        .and_then(|s| s.parse().ok());
    println!(
        "{n} nodes, {rotated} rotated, {} free DOFs, adapter {}, {} workgroups, best of {reps} per kernel (ms)",
        e.ndof(),
        ctx.adapter_name(),
        ctx.workgroups(workgroups)
    );
    println!("| precision | coarse | f32 difference form | matvec | update_xrz | update_p | coarse_restrict + coarse_solve | sum |");
    println!("|---|---|---|---|---|---|---|---|");
    let configs = [
        (Precision::F64, CoarseSpace::None, false),
        (Precision::F64, CoarseSpace::Translations, false),
        (Precision::F64, CoarseSpace::Aggregates, false),
        (Precision::F32, CoarseSpace::None, false),
        (Precision::F32, CoarseSpace::None, true),
        (Precision::F32, CoarseSpace::Translations, true),
        (Precision::F32, CoarseSpace::Aggregates, false),
        (Precision::F32, CoarseSpace::Aggregates, true),
    ];
    for (precision, coarse, diff) in configs {
        let params = GpuParams {
            precision,
            coarse,
            f32_difference: if diff {
                DifferenceForm::On
            } else {
                DifferenceForm::Off
            },
            workgroups,
            ..Default::default()
        };
        let mut sol = GpuSolver::new(&ctx, &e, &params)?;
        let Some(times) = sol.profile_kernels(reps)? else {
            println!("no timestamp queries on this adapter");
            return Ok(());
        };
        let t = |name: &str| {
            times
                .iter()
                .find(|k| k.name == name)
                .map_or(0.0, |k| 1e3 * k.best_s)
        };
        let (m, x, p) = (t("matvec"), t("update_xrz"), t("update_p"));
        let c = t("coarse_restrict") + t("coarse_solve");
        if c > 0.0 {
            eprintln!(
                "restrict {:.2} ms, solve {:.2} ms",
                t("coarse_restrict"),
                t("coarse_solve")
            );
        }
        println!(
            "| {precision} | {} | {} | {m:.2} | {x:.2} | {p:.2} | {c:.2} | {:.2} |",
            coarse.name(),
            if precision == Precision::F64 {
                "—"
            } else if diff {
                "on"
            } else {
                "off"
            },
            m + x + p + c
        );
    }
    Ok(())
}
