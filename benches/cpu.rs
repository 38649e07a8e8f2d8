//! CPU paths on generated systems (no downloads): the block matvec, the matrix-free
//! eliminated operator, one PCG solve's iterations, and the Cholesky oracle with and
//! without symbolic reuse. `cargo bench --bench cpu`.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::solve::cg::{self, BuiltPreconditioner, CgParams, Preconditioner};
use stickslip::solve::oracle::CholeskyOracle;

fn systems() -> Vec<(String, stickslip::cases::generate::GeneratedSystem)> {
    [(2usize, 10_000usize), (3, 10_000), (3, 64_000)]
        .iter()
        .map(|&(d, n)| {
            (
                format!("{d}d-{n}"),
                random_system(&SystemSpec::with_nodes(d, n, 1)),
            )
        })
        .collect()
}

fn bench_operators(c: &mut Criterion) {
    let mut g = c.benchmark_group("cpu-operator");
    for (name, s) in systems() {
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let n = s.h.ndof();
        // Bytes one product must move: blocks + column indices + row pointers + x + y.
        let bytes =
            s.h.values.len() * 8 + s.h.col_idx.len() * 8 + s.h.row_ptr.len() * 8 + 2 * n * 8;
        g.throughput(Throughput::Bytes(bytes as u64));
        let x: Vec<f64> = (0..n).map(|k| (k % 7) as f64 - 3.0).collect();
        let mut y = vec![0.0; n];
        let mut w = vec![0.0; 2 * n];
        g.bench_function(BenchmarkId::new("block-matvec", &name), |b| {
            b.iter(|| s.h.matvec(&x, &mut y))
        });
        g.bench_function(BenchmarkId::new("eliminated-apply", &name), |b| {
            b.iter(|| e.apply(&x, &mut y, &mut w))
        });
    }
    g.finish();
}

fn bench_cg(c: &mut Criterion) {
    let mut g = c.benchmark_group("cpu-cg");
    g.sample_size(10);
    for (name, s) in systems() {
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        for pc in [Preconditioner::Jacobi, Preconditioner::BlockJacobi] {
            let pre = BuiltPreconditioner::new(&e, pc);
            // 50 iterations exactly: a tolerance it cannot reach, limit 50, error expected.
            let params = CgParams {
                tol: 1e-30,
                max_iters: 50,
                preconditioner: pc,
                ..Default::default()
            };
            g.bench_function(
                BenchmarkId::new(format!("50-iterations-{pc:?}"), &name),
                |b| b.iter(|| cg::solve_with(&e, &pre, None, &params).err()),
            );
        }
    }
    g.finish();
}

fn bench_cholesky(c: &mut Criterion) {
    let mut g = c.benchmark_group("cpu-cholesky");
    g.sample_size(10);
    for (name, s) in systems().into_iter().take(2) {
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        g.bench_function(BenchmarkId::new("analyze+factor+solve", &name), |b| {
            b.iter(|| {
                stickslip::solve::oracle::solve(&e)
                    .map(|r| r.1.relative_residual)
                    .ok()
            })
        });
        let mut oracle = CholeskyOracle::analyze(&e).expect("analysis");
        g.bench_function(
            BenchmarkId::new("factor+solve (symbolic reused)", &name),
            |b| b.iter(|| oracle.solve(&e).map(|r| r.1.relative_residual).ok()),
        );
    }
    g.finish();
}

criterion_group!(benches, bench_operators, bench_cg, bench_cholesky);
criterion_main!(benches);
