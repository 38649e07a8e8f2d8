//! The CPU CG on 1, 2 (and every, where more) threads of its own rayon pool: 50
//! iterations of Jacobi PCG without coarse space (time per iteration = time / 50), and a
//! whole solve to 1e-8 with the default aggregates coarse space, on a generated 3D system
//! of 64,000 nodes. The iterates are the same bits on every thread count (the reductions
//! are summed per fixed chunk). `cargo bench --bench cg_threads`.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use stickslip::cases::generate::{random_system, Stencil, SystemSpec};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::solve::cg::{self, BuiltPreconditioner, CgParams, Preconditioner};
use stickslip::solve::coarse::CoarseSpace;

fn thread_counts() -> Vec<usize> {
    let all = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut t = vec![1, 2];
    if all > 2 {
        t.push(all);
    }
    t
}

fn bench_threads(c: &mut Criterion) {
    let mut g = c.benchmark_group("cg-threads");
    g.sample_size(10);
    for (label, stencil) in [("mesh", Stencil::Mesh), ("face", Stencil::Face)] {
        let mut spec = SystemSpec::with_nodes(3, 64_000, 1);
        spec.stencil = stencil;
        let s = random_system(&spec);
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let pre = BuiltPreconditioner::new(&e, Preconditioner::Jacobi);
        // 50 iterations exactly: a tolerance it cannot reach, limit 50, error expected.
        let fifty = CgParams {
            tol: 1e-30,
            max_iters: 50,
            coarse: CoarseSpace::None,
            ..Default::default()
        };
        let solve = CgParams {
            tol: 1e-8,
            ..Default::default()
        };
        for threads in thread_counts() {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("thread pool");
            g.bench_function(
                BenchmarkId::new(format!("50-iterations-jacobi-{label}"), threads),
                |b| {
                    b.iter(|| {
                        pool.install(|| {
                            let r = cg::solve_with(&e, &pre, None, &fifty);
                            assert!(matches!(r, Err(cg::CgError::MaxIterations { .. })));
                        })
                    })
                },
            );
            g.bench_function(
                BenchmarkId::new(format!("solve-1e-8-aggregates-{label}"), threads),
                |b| {
                    b.iter(|| {
                        pool.install(|| {
                            let (_, info) = cg::solve(&e, &solve).expect("converges");
                            assert!(info.relative_residual <= 1e-8);
                        })
                    })
                },
            );
        }
    }
    g.finish();
}

criterion_group!(benches, bench_threads);
criterion_main!(benches);
