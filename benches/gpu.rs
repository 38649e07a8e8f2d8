//! Benchmarks of the device PCG (criterion; what `solve --solver gpu` runs), on a
//! generated 3D system of 20k nodes with slip nodes (so the product rotates): the product
//! q = Ĥx, the preconditioner's download and a full solve, in f32 and (where the device
//! has SHADER_F64) f64. Wall times include the host transfers each call needs; device-only
//! kernel times come from `PcgSolver::profile_kernels` (examples/pcg_kernels.rs,
//! `stickslip bench`). Skips (with a message) when no adapter exists.

use criterion::{criterion_group, criterion_main, Criterion};
use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::gpu::{GpuContext, GpuOptions, GpuParams, PcgSolver, Precision};
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
    let y = vec![1.0; e.ndof()];
    let mut g = c.benchmark_group("gpu");
    g.sample_size(10);
    let precisions: &[Precision] = if ctx.has_f64() {
        &[Precision::F32, Precision::F64]
    } else {
        &[Precision::F32]
    };
    for &precision in precisions {
        let params = GpuParams {
            precision,
            tol: 1e-6,
            preconditioner: Preconditioner::Jacobi,
            ..Default::default()
        };
        let mut sol = match PcgSolver::new(&ctx, &e, &params) {
            Ok(s) => s,
            Err(err) => {
                eprintln!("SKIP gpu benchmarks in {precision}: {err}");
                continue;
            }
        };
        g.bench_function(format!("product_3d_20k_{precision}"), |b| {
            b.iter(|| sol.apply_operator(&y).map(|v| v.len()))
        });
        g.bench_function(format!("preconditioner_3d_20k_{precision}"), |b| {
            b.iter(|| sol.preconditioner_data().map(|v| v.len()))
        });
        g.bench_function(format!("solve_3d_20k_{precision}"), |b| {
            b.iter(|| sol.solve().map(|r| r.info.iterations))
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
