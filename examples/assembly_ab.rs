//! Time of the simulation's element loops outside the linear solver on a built-in scene
//! (energy, gradient, projected Hessian, each assembled into the model's fixed pattern),
//! on 1 and 2 threads, and whether the results are bitwise equal across thread counts:
//! `cargo run --release --example assembly_ab -- [scene] [size] [repeats]`. Wall seconds
//! are the best of the repeats; CPU seconds (all threads, Unix only) their mean, which a
//! loaded machine disturbs less; the Hessian's element passes and gathers are the means of
//! the assembly's own phase timers. The inversion bound (`Model::inversion_bound`) runs
//! along a fixed pseudo-random step of about a tenth of the node spacing, which inverts
//! some elements before α = 1.

use std::time::Instant;
use stickslip::gpu::Phase;
use stickslip::sim::driver::load_scene;
use stickslip::sim::energy::AssemblyWork;
use stickslip::sim::phases::HostPhases;

/// CPU seconds of this process so far (all threads); 0 where unavailable.
fn cpu_seconds() -> f64 {
    #[cfg(unix)]
    {
        let mut t = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        // SAFETY: clock_gettime writes one timespec into `t`.
        if unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut t) } == 0 {
            return t.tv_sec as f64 + 1e-9 * t.tv_nsec as f64;
        }
    }
    0.0
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let name = args.get(1).map_or("twist", String::as_str);
    let size: f64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(10.0);
    let reps: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(5);
    let scene = match load_scene(name, size) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("{e}");
            std::process::exit(2);
        }
    };
    let m = &scene.model;
    let d = m.dim;
    // A twisted configuration: every element deformed, some strongly (the projection works).
    let mut x = scene.x0.clone();
    for i in 0..m.n_nodes {
        let p = &mut x[i * d..(i + 1) * d];
        let a = 0.8 * p[0];
        if d == 3 {
            let (y, z) = (p[1] - 0.1, p[2] - 0.1);
            p[1] = 0.1 + y * a.cos() - z * a.sin();
            p[2] = 0.1 + y * a.sin() + z * a.cos();
        } else {
            p[1] *= 1.0 + 0.3 * a;
        }
    }
    let elements: usize = m.sets.iter().map(|s| s.len()).sum();
    // The step: per coordinate a SplitMix64 value in [-1, 1), times a tenth of the node
    // spacing (the bounding box's volume per node, to the power 1/d).
    let (lo, hi) = (0..d).fold(
        (vec![f64::MAX; d], vec![f64::MIN; d]),
        |(mut lo, mut hi), c| {
            for i in 0..m.n_nodes {
                lo[c] = lo[c].min(scene.x0[i * d + c]);
                hi[c] = hi[c].max(scene.x0[i * d + c]);
            }
            (lo, hi)
        },
    );
    let extent: f64 = (0..d).map(|c| hi[c] - lo[c]).product();
    let spacing = (extent / m.n_nodes as f64).powf(1.0 / d as f64);
    let dx: Vec<f64> = (0..x.len() as u64)
        .map(|k| {
            let mut z = k.wrapping_add(1).wrapping_mul(0x9e37_79b9_7f4a_7c15);
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^= z >> 31;
            let unit = (z >> 11) as f64 / (1u64 << 53) as f64;
            spacing / 10.0 * (2.0 * unit - 1.0)
        })
        .collect();
    println!(
        "{name} size {size}: {} nodes, {elements} elements, best of {reps}",
        m.n_nodes
    );
    println!("| threads | energy s | gradient s | Hessian s | gradient's element terms s | gradient's gather s | Hessian's element terms s | Hessian's gather s | inversion bound s | energy CPU s | gradient CPU s | Hessian CPU s |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    let mut results = Vec::new();
    for threads in [1, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("thread pool");
        let r = pool.install(|| {
            let mut work = AssemblyWork::default();
            let mut h = m.zero_matrix();
            let mut g = vec![0.0; x.len()];
            let (mut te, mut tg, mut th) = (f64::MAX, f64::MAX, f64::MAX);
            let mut cpu = [0.0f64; 3];
            // The passes' own timers: element terms and gathers, best of the repeats.
            let seconds = |p: &HostPhases, want: Phase| -> f64 {
                let profile = p.profile();
                profile.phases.iter().filter(|(q, _)| *q == want).map(|(_, s)| s).sum()
            };
            let mut split = [f64::MAX; 4];
            let mut e = 0.0;
            let mut ti = f64::MAX;
            let mut bound = None;
            for _ in 0..reps {
                let (t, c) = (Instant::now(), cpu_seconds());
                e = m.potential(&x);
                te = te.min(t.elapsed().as_secs_f64());
                cpu[0] += cpu_seconds() - c;
                g.iter_mut().for_each(|v| *v = 0.0);
                let timers = HostPhases::default();
                work.phases = Some(timers.clone());
                let (t, c) = (Instant::now(), cpu_seconds());
                m.add_potential_gradient_with(&x, 1.0, &mut g, &mut work);
                tg = tg.min(t.elapsed().as_secs_f64());
                cpu[1] += cpu_seconds() - c;
                split[0] = split[0].min(seconds(&timers, Phase::ElementTerms));
                split[1] = split[1].min(seconds(&timers, Phase::Assembly));
                h.values.iter_mut().for_each(|v| *v = 0.0);
                let timers = HostPhases::default();
                work.phases = Some(timers.clone());
                let (t, c) = (Instant::now(), cpu_seconds());
                m.add_potential_hessian_with(&x, 1.0, true, &mut h, &mut work);
                th = th.min(t.elapsed().as_secs_f64());
                cpu[2] += cpu_seconds() - c;
                split[2] = split[2].min(seconds(&timers, Phase::ElementTerms));
                split[3] = split[3].min(seconds(&timers, Phase::Assembly));
                work.phases = None;
                let t = Instant::now();
                bound = Some(m.inversion_bound(&x, &dx, 1.0));
                ti = ti.min(t.elapsed().as_secs_f64());
            }
            let [gelements, ggather, elements, gather] = split;
            let n = reps as f64;
            println!(
                "| {threads} | {te:.4} | {tg:.4} | {th:.4} | {gelements:.4} | {ggather:.4} | {elements:.4} | {gather:.4} | {ti:.4} | {:.4} | {:.4} | {:.4} |",
                cpu[0] / n,
                cpu[1] / n,
                cpu[2] / n
            );
            let bound = match bound {
                Some(Ok(Some(b))) => format!("α = {:e} at set {} element {}", b.alpha, b.set, b.element),
                Some(Ok(None)) => "none".to_string(),
                Some(Err(i)) => format!("inverted: set {} element {}", i.set, i.element),
                None => "not run".to_string(),
            };
            (e.to_bits(), g, h.values, bound)
        });
        results.push(r);
    }
    let same = results[0].0 == results[1].0
        && results[0]
            .1
            .iter()
            .zip(&results[1].1)
            .all(|(a, b)| a.to_bits() == b.to_bits())
        && results[0]
            .2
            .iter()
            .zip(&results[1].2)
            .all(|(a, b)| a.to_bits() == b.to_bits());
    let same = same && results[0].3 == results[1].3;
    println!("inversion bound: {}", results[0].3);
    // Fingerprints of the bits, to compare builds: the energy's, and a fold of the
    // gradient's and the Hessian's values (FNV-1a over their 8-byte words).
    let fold = |v: &[f64]| {
        v.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, x| {
            (h ^ x.to_bits()).wrapping_mul(0x100_0000_01b3)
        })
    };
    println!(
        "bits: energy {:016x}, gradient {:016x}, Hessian {:016x}",
        results[0].0,
        fold(&results[0].1),
        fold(&results[0].2)
    );
    println!("bitwise equal on 1 and 2 threads: {same}");
}
