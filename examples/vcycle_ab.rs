//! Seconds of one multilevel V-cycle against one product with Ĥ (the CG's own, and the
//! bulk of a Jacobi iteration) on captured Newton systems (`run --dump-systems`):
//! `cargo run --release --example vcycle_ab -- DIR [DIR ...]`. Each figure is the fastest
//! of `REPEATS` calls, which a machine shared with other work disturbs least (the levels'
//! build: of `BUILDS`); on stderr, each level's passes of the V-cycle, mean milliseconds
//! over `REPEATS` timed cycles. Used in
//! docs/lab/2026-11-28-multilevel-in-seconds.md.

use std::sync::Arc;
use std::time::Instant;
use stickslip::app::bench::systems;
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::solve::multilevel::{Hierarchy, Multilevel, CYCLE_PASSES};

const REPEATS: usize = 30;
/// Builds of the levels timed per system (each takes about a second).
const BUILDS: usize = 3;

/// CPU seconds of this process, all threads together.
fn cpu_seconds() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid timespec for the call to fill.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
    assert_eq!(rc, 0, "clock_gettime");
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

/// The fastest of `REPEATS` runs of `f`: wall seconds and CPU seconds (each its own
/// minimum).
fn fastest(mut f: impl FnMut()) -> (f64, f64) {
    (0..REPEATS)
        .map(|_| {
            let (t, c) = (Instant::now(), cpu_seconds());
            f();
            (t.elapsed().as_secs_f64(), cpu_seconds() - c)
        })
        .fold((f64::INFINITY, f64::INFINITY), |a, b| {
            (a.0.min(b.0), a.1.min(b.1))
        })
}

fn main() {
    println!(
        "| system | nodes | hierarchy s | levels s | refresh s | V-cycle ms | Ĥ product ms | V-cycle CPU ms | Ĥ product CPU ms |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|");
    for dir in std::env::args().skip(1) {
        let problem = match systems::read(std::path::Path::new(&dir)) {
            Ok(p) => p,
            Err(err) => {
                eprintln!("{err}");
                std::process::exit(2);
            }
        };
        let e = Eliminated::new(
            problem.hessian(),
            problem.gradient(),
            problem.frames(),
            ConstrainedDiagonal::Identity,
        );
        let t = Instant::now();
        let hier = Arc::new(Hierarchy::new(problem.hessian()));
        let hier_s = t.elapsed().as_secs_f64();
        let mut ml = Multilevel::new(&e, hier.clone());
        let mut levels_s = f64::INFINITY;
        for _ in 0..BUILDS {
            let t = Instant::now();
            ml = Multilevel::new(&e, hier.clone());
            levels_s = levels_s.min(t.elapsed().as_secs_f64());
        }
        let refresh_s = fastest(|| ml.refresh(&e)).0;
        let n = e.ndof();
        let r: Vec<f64> = (0..n).map(|k| ((k * 7919) % 23) as f64 - 11.0).collect();
        let mut z = vec![0.0; n];
        let mut work = ml.workspace();
        let vcycle = fastest(|| ml.apply_with(&r, &mut z, &mut work));
        let mut hz = vec![0.0; n];
        let mut scratch = vec![0.0; 2 * n];
        let product = fastest(|| e.apply(&r, &mut hz, &mut scratch));
        let counts = ml.hierarchy().cluster_counts();
        let mut seconds = vec![[0.0; 6]; counts.len()];
        for _ in 0..REPEATS {
            ml.apply_timed(&r, &mut z, &mut work, &mut seconds);
        }
        for (l, s) in seconds.iter().enumerate() {
            let passes: Vec<String> = CYCLE_PASSES
                .iter()
                .zip(s)
                .map(|(name, v)| format!("{name} {:.2}", v / REPEATS as f64 * 1e3))
                .collect();
            eprintln!(
                "{dir} level {l} ({} clusters), mean ms: {}",
                counts[l],
                passes.join(", ")
            );
        }
        println!(
            "| {dir} | {} | {hier_s:.3} | {levels_s:.3} | {refresh_s:.4} | {:.2} | {:.2} | {:.2} | {:.2} |",
            problem.n_nodes(),
            vcycle.0 * 1e3,
            product.0 * 1e3,
            vcycle.1 * 1e3,
            product.1 * 1e3
        );
    }
}
