//! Measures the device PCG (what `solve --solver gpu` runs) against the CPU CG on a large
//! 3D system:
//! `cargo run --release --example gpu_measure -- [nodes] [precision] [tol]`.

use std::time::Instant;
use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::gpu::{
    measure_copy_bandwidth, GpuContext, GpuOptions, GpuParams, PcgSolver, Precision, SolveOutcome,
};
use stickslip::solve::cg::{self, CgParams, Preconditioner};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let nodes: usize = args
        .get(1)
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(200_000);
    let precision: Precision = args
        .get(2)
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(Precision::F32);
    let tol: f64 = args.get(3).map(|s| s.parse()).transpose()?.unwrap_or(1e-6);
    let t = Instant::now();
    let mut s = random_system(&SystemSpec::with_nodes(3, nodes, 1));
    if std::env::var("UNCONSTRAINED").is_ok() {
        s.frames = stickslip::core::constraints::Frames::unconstrained(3, s.h.n);
    }
    let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
    println!(
        "system: {} nodes, {} dofs, {} blocks, {} rotated nodes, {} constrained dofs (generated in {:.2} s)",
        s.h.n,
        s.h.ndof(),
        s.h.nnz_blocks(),
        s.frames.rot_nodes.len(),
        s.frames.constrained_dofs(),
        t.elapsed().as_secs_f64()
    );
    let ctx = GpuContext::new(&GpuOptions::default())?;
    let params = GpuParams {
        precision,
        tol,
        max_iters: 20_000,
        preconditioner: Preconditioner::Jacobi,
        ..Default::default()
    };
    let t = Instant::now();
    let mut sol = PcgSolver::new(&ctx, &e, &params)?;
    let build = t.elapsed().as_secs_f64();
    if std::env::var("MEASURE_MATVEC").is_ok() {
        // Operator kernel alone (upload of p and download of q included, ~2·dofs·4 bytes).
        let y = vec![1.0; e.ndof()];
        sol.apply_operator(&y)?;
        let t = Instant::now();
        for _ in 0..5 {
            sol.apply_operator(&y)?;
        }
        println!("matvec alone: {:.1} ms", t.elapsed().as_secs_f64() * 200.0);
    }
    let reps: usize = std::env::var("PROFILE_REPS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(10);
    let copy_gbs = measure_copy_bandwidth(&ctx)?;
    println!("adapter: {}; copy bandwidth (128 MiB copy_buffer_to_buffer, read+write) {copy_gbs:.2} GB/s", ctx.adapter_name());
    if let Some(prof) = sol.profile_kernels(reps)? {
        let line: Vec<String> = prof
            .iter()
            .map(|k| {
                format!(
                    "{} {:.2} (mean {:.2}) ms",
                    k.name,
                    k.best_s * 1e3,
                    k.mean_s * 1e3
                )
            })
            .collect();
        println!(
            "per-kernel device time (best of {reps}): {}; sum {:.2} ms",
            line.join(", "),
            prof.iter().map(|k| k.best_s).sum::<f64>() * 1e3
        );
    }
    if std::env::var("PROFILE_ONLY").is_ok() {
        return Ok(());
    }
    let SolveOutcome { dx, info, .. } = sol.solve()?;
    println!(
        "gpu: {} iterations ({} recorded, {:.1}% over), {} dispatches/iteration, {} readbacks, {:.1} MB/iteration, {:.2} GB/s wall ({:.2} of copy), {} GB/s timestamps ({} of copy)",
        info.iterations,
        info.recorded_iterations,
        100.0 * (info.recorded_iterations as f64 / info.iterations.max(1) as f64 - 1.0),
        info.dispatches_per_iteration,
        info.readbacks,
        info.bytes_per_iteration as f64 / 1e6,
        info.achieved_gb_per_s,
        info.achieved_gb_per_s / copy_gbs,
        info.achieved_gb_per_s_gpu.map(|g| format!("{g:.2}")).unwrap_or("-".into()),
        info.achieved_gb_per_s_gpu.map(|g| format!("{:.2}", g / copy_gbs)).unwrap_or("-".into()),
    );
    println!("gpu: {}", serde_json::to_string_pretty(&info)?);
    println!("gpu: solver build (pipelines, buffers, upload, setup) {build:.3} s");
    println!(
        "gpu: {:.1} MiB of device memory",
        PcgSolver::memory_needed(&ctx, &e, &params)? as f64 / (1 << 20) as f64
    );
    if std::env::var("SKIP_CPU").is_ok() {
        return Ok(());
    }
    let t = Instant::now();
    let (y_cpu, cinfo) = cg::solve(
        &e,
        &CgParams {
            tol,
            max_iters: 20_000,
            preconditioner: Preconditioner::Jacobi,
            ..Default::default()
        },
    )?;
    let cpu_s = t.elapsed().as_secs_f64();
    let dx_cpu = e.recover(&y_cpu);
    let diff: f64 = dx
        .iter()
        .zip(&dx_cpu)
        .map(|(a, b)| (a - b).powi(2))
        .sum::<f64>()
        .sqrt();
    let nrm: f64 = dx_cpu.iter().map(|a| a * a).sum::<f64>().sqrt();
    // f64 blocks, usize indices and ~18 vector passes per CPU iteration.
    let cpu_bytes = stickslip::app::bench::cpu_cg_bytes_per_iteration(&e) as f64;
    println!(
        "cpu cg (f64, 1 thread): {} iterations, {:.3} s, {:.2} ms/iteration, {:.1} MB/iteration, ~{:.2} GB/s, residual {:.2e}",
        cinfo.iterations,
        cpu_s,
        1e3 * cpu_s / cinfo.iterations.max(1) as f64,
        cpu_bytes / 1e6,
        cpu_bytes * cinfo.iterations as f64 / cpu_s / 1e9,
        cinfo.relative_residual
    );
    println!(
        "gpu: {} iterations, {:.3} s solve, {:.2} ms/iteration; ‖Δx_gpu − Δx_cpu‖/‖Δx_cpu‖ = {:.2e}",
        info.iterations,
        info.seconds.solve,
        1e3 * info.seconds.solve / info.iterations.max(1) as f64,
        diff / nrm
    );
    Ok(())
}
