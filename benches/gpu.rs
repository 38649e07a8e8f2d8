//! Benchmarks of the precision kernels (criterion; `GpuSolver`, mixed precision's levels:
//! `solve --solver gpu` runs f32 and f64 on the device PCG), on a generated 3D system of
//! 20k nodes with slip nodes (so the rotation kernels run): the masked operator, the
//! rotation on recovery (V y), the preconditioner build, CG iterations (matvec + fused
//! updates + the two-pass reductions) and a full f32 solve of those kernels. Wall times include the host transfers each call
//! needs; device-only kernel times come from `GpuSolver::profile_kernels` (examples/
//! gpu_measure.rs, `stickslip bench`). Skips (with a message) when no adapter exists.

use criterion::{criterion_group, criterion_main, Criterion};
use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::gpu::{GpuContext, GpuOptions, GpuParams, GpuSolver, Precision};
use stickslip::solve::cg::Preconditioner;

fn bench(c: &mut Criterion) {
    let ctx = match GpuContext::new(&GpuOptions::default()) {
        Ok(c) => c,
        Err(e) => {
            eprintln!("SKIP gpu benchmarks: {e}");
            return;
        }
    };
    let s = random_system(&SystemSpec::with_nodes(3, 20_000, 1));
    let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
    let params = GpuParams {
        precision: Precision::F32,
        tol: 1e-6,
        preconditioner: Preconditioner::Jacobi,
        ..Default::default()
    };
    let Ok(mut sol) = GpuSolver::new(&ctx, &e, &params) else {
        eprintln!("SKIP gpu benchmarks: solver could not be built");
        return;
    };
    let y = vec![1.0; e.ndof()];
    let mut g = c.benchmark_group("gpu");
    g.sample_size(10);
    g.bench_function("matvec_3d_20k_f32", |b| {
        b.iter(|| sol.apply_operator(&y).map(|v| v.len()))
    });
    g.bench_function("preconditioner_build_3d_20k_f32", |b| {
        b.iter(|| sol.preconditioner_data().map(|v| v.len()))
    });
    g.bench_function("cg_iterations_1_3d_20k_f32", |b| {
        b.iter(|| sol.iterate(1).map(|r| r.0.len()))
    });
    g.bench_function("cg_iterations_16_3d_20k_f32", |b| {
        b.iter(|| sol.iterate(16).map(|r| r.0.len()))
    });
    g.bench_function("solve_3d_20k_f32", |b| {
        b.iter(|| sol.solve().map(|r| r.info.iterations))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
