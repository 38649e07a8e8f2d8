//! Element Hessians of the neo-Hookean laws (classical and stable, 2D and 3D) on a
//! deformed mesh, per element and thread: the per-element reference
//! (`NeoHookean::element_hessian`, a full matrix then split into the assembly's upper
//! node blocks) beside the fixed-size kernel that writes the blocks directly
//! (`NeoHookean::element_hessian_blocks`) and the assembly's kernel, which runs twelve 3D
//! elements side by side, every stage lane-innermost (`NeoHookean::element_hessian_blocks_run`),
//! in one run so that their ratios are measured under the same load. `cargo bench --bench elements`.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use stickslip::sim::energy::kernels::upper_blocks_of;
use stickslip::sim::energy::{Law, NeoHookean};
use stickslip::sim::mesh;

/// A mesh of `d` dimensions stretched by 1.2, twisted a little and jittered by a fixed
/// pattern, so that the projection clamps some modes as it does in a Newton step.
fn deformed(d: usize) -> (mesh::Mesh, Vec<f64>) {
    let m = if d == 2 {
        mesh::rectangle(2, [1.0, 1.0], [60, 60])
    } else {
        mesh::cuboid([1.0, 1.0, 1.0], [12, 12, 12])
    };
    let x =
        m.x.iter()
            .enumerate()
            .map(|(k, v)| {
                let jitter = ((k * 7919) % 101) as f64 / 101.0 - 0.5;
                1.2 * v + 0.02 * jitter
            })
            .collect();
    (m, x)
}

fn bench_hessians(c: &mut Criterion) {
    let mut g = c.benchmark_group("element-hessian");
    for d in [2usize, 3] {
        let (m, x) = deformed(d);
        for law in [Law::NeoHookean, Law::StableNeoHookean] {
            let nh = NeoHookean::new(&m, 1e5, 0.45, law).expect("valid mesh");
            let n = nh.len();
            let nl = (d + 1) * d;
            let np = (d + 1) * (d + 2) / 2;
            let mut full = vec![0.0; nl * nl];
            let mut blocks = vec![0.0; n * np * d * d];
            g.throughput(Throughput::Elements(n as u64));
            let name = format!("{d}d-{}", law.name());
            g.bench_function(BenchmarkId::new("reference", &name), |b| {
                b.iter(|| {
                    for (e, out) in blocks.chunks_exact_mut(np * d * d).enumerate() {
                        nh.element_hessian(&x, e, true, &mut full);
                        upper_blocks_of(d, d + 1, &full, out);
                    }
                })
            });
            g.bench_function(BenchmarkId::new("fixed-size", &name), |b| {
                b.iter(|| {
                    for (e, out) in blocks.chunks_exact_mut(np * d * d).enumerate() {
                        nh.element_hessian_blocks(&x, e, true, out);
                    }
                })
            });
            g.bench_function(BenchmarkId::new("batched", &name), |b| {
                b.iter(|| nh.element_hessian_blocks_run(&x, 0, true, &mut blocks))
            });
        }
    }
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).warm_up_time(std::time::Duration::from_millis(500)).measurement_time(std::time::Duration::from_secs(2));
    targets = bench_hessians
}
criterion_main!(benches);
