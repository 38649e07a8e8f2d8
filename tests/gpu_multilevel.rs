//! The multilevel preconditioner on the device PCG (`solve --solver gpu`, f64) against the
//! CPU CG with the same preconditioner, on seeded random systems with sticky, slip
//! (rotated frames) and prescribed nodes, large enough for three or more levels (so
//! every V-cycle kernel runs: the smoothings, a coarse level's product, the restriction,
//! the prolongation and the coarsest solve).
//!
//! Both build the same levels on the host ([`Multilevel::new`]); the device applies
//! them with its own kernels and its own product at level 0 (H read in place), so the
//! sums run in other orders. Bounds:
//! - iterations within 10 % of the CPU CG's (the preconditioners are the same operator up
//!   to rounding; a stopping test that one side meets an iteration earlier is the
//!   difference expected);
//! - both stop on the true residual ≤ tol = 1e-10, so each Δx is within κ(Ĥ)·tol of the
//!   exact one; the two are required within 1e-8 of each other, which these systems meet
//!   with room to spare (the printed figures).
//!
//! Every test shares one device (tests/common/gpu.rs); sizes are small for lavapipe.

use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::gpu::pcg::multilevel_bytes;
use stickslip::gpu::{GpuError, GpuParams, PcgSolver, Precision};
use stickslip::solve::cg::Preconditioner;
use stickslip::solve::multilevel::Hierarchy;
use stickslip::{LayoutKey, Solver, SolverConfig};

mod common;
use common::gpu::gpu;

const TOL: f64 = 1e-10;

fn rel_diff(a: &[f64], b: &[f64]) -> f64 {
    let d: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum();
    let n: f64 = b.iter().map(|x| x * x).sum();
    (d / n).sqrt()
}

#[test]
fn the_device_v_cycle_takes_the_cpu_cgs_iterations() {
    let Some((ctx, _g)) = gpu() else { return };
    for (dim, nodes, seed) in [(3, 729, 5u64), (2, 900, 6)] {
        let mut spec = SystemSpec::with_nodes(dim, nodes, seed);
        spec.prescribed = true;
        let s = random_system(&spec);
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let levels = Hierarchy::new(&s.h).cluster_counts();
        assert!(levels.len() >= 3, "{dim}D: levels {levels:?}");
        let run = |config: SolverConfig| {
            let mut solver = Solver::new(
                config
                    .tol(TOL)
                    .max_iters(10_000)
                    .preconditioner(Preconditioner::Multilevel),
            )
            .expect("solver");
            solver
                .solve_eliminated(LayoutKey::fresh(), &e)
                .expect("converges")
        };
        let cpu = run(SolverConfig::cg());
        let dev = run(SolverConfig::gpu(Precision::F64).gpu_context(ctx.clone()));
        let (ic, id) = (
            cpu.stats.iterations.expect("CG iterations"),
            dev.stats.iterations.expect("GPU iterations"),
        );
        let gap = rel_diff(&dev.dx, &cpu.dx);
        eprintln!(
            "{dim}D, {} nodes, clusters per level {levels:?}: CPU CG {ic} iterations, device \
             PCG {id}; residuals {:.3e} / {:.3e}; ‖Δx_gpu − Δx_cpu‖/‖Δx_cpu‖ {gap:.3e}",
            s.h.n, cpu.stats.relative_residual, dev.stats.relative_residual
        );
        assert!(
            id.abs_diff(ic) * 10 <= ic,
            "{dim}D: device {id} iterations against the CPU's {ic}"
        );
        assert!(dev.stats.relative_residual <= TOL);
        assert!(gap <= 1e-8, "{dim}D: Δx differs by {gap:e}");
        // The multilevel preconditioner earns its keep here too: Jacobi takes more.
        let mut jacobi = Solver::new(
            SolverConfig::gpu(Precision::F64)
                .tol(TOL)
                .max_iters(10_000)
                .preconditioner(Preconditioner::Jacobi)
                .gpu_context(ctx.clone()),
        )
        .expect("solver");
        let j = jacobi
            .solve_eliminated(LayoutKey::fresh(), &e)
            .expect("converges");
        let ij = j.stats.iterations.expect("iterations");
        eprintln!("{dim}D: device PCG with Jacobi and the aggregates: {ij} iterations");
        assert!(id < ij, "{dim}D: multilevel {id} against Jacobi {ij}");
    }
}

/// The number of bytes a refusal says the system needs.
fn needed(ctx: &stickslip::gpu::GpuContext, e: &Eliminated, p: &GpuParams) -> u64 {
    let tiny = GpuParams {
        memory_limit: Some(16),
        ..p.clone()
    };
    match PcgSolver::new(ctx, e, &tiny) {
        Err(e @ GpuError::DoesNotFit { need, limit, .. }) => {
            assert!(!e.to_string().contains('\n'), "{e}");
            assert_eq!(limit, 16, "{e}");
            need
        }
        Err(other) => panic!("{other}"),
        Ok(_) => panic!("accepted a system in 16 bytes"),
    }
}

/// The multilevel levels count in the device PCG's memory check before anything is
/// allocated: with memory for everything else but not for them, Jacobi builds and the
/// multilevel solver is refused in one line, and the difference between the two needs is
/// exactly the levels' bytes ([`multilevel_bytes`], the sizes the upload checks it packs).
#[test]
fn the_multilevel_levels_count_in_the_memory_check() {
    let Some((ctx, _g)) = gpu() else { return };
    let s = random_system(&SystemSpec::with_nodes(3, 729, 9));
    let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
    let jacobi = GpuParams {
        precision: Precision::F64,
        ..Default::default()
    };
    let multilevel = GpuParams {
        preconditioner: Preconditioner::Multilevel,
        ..jacobi.clone()
    };
    let (nj, nm) = (needed(ctx, &e, &jacobi), needed(ctx, &e, &multilevel));
    let levels =
        multilevel_bytes(ctx, &Hierarchy::new(&s.h).level_sizes(3), 3, None).expect("fits");
    eprintln!("needs: Jacobi {nj} bytes, multilevel {nm} ({levels} for the levels)");
    assert_eq!(nm - nj, levels);
    let between = GpuParams {
        memory_limit: Some(nj),
        ..multilevel.clone()
    };
    assert!(PcgSolver::new(
        ctx,
        &e,
        &GpuParams {
            memory_limit: Some(nj),
            ..jacobi
        }
    )
    .is_ok());
    match PcgSolver::new(ctx, &e, &between) {
        Err(e @ GpuError::DoesNotFit { .. }) => eprintln!("{e}"),
        Err(other) => panic!("{other}"),
        Ok(_) => panic!("the levels were not counted"),
    }
    // And with room for them it builds and solves.
    let mut ok = PcgSolver::new(
        ctx,
        &e,
        &GpuParams {
            memory_limit: Some(nm),
            ..multilevel
        },
    )
    .expect("fits in what it said it needs");
    assert!(ok.solve().is_ok());
}

/// Cluster inverses over the binding limit go in several buffers of consecutive clusters,
/// each smoothed by its own dispatch with the same sums: the same iterations and the same
/// Δx, bit for bit, as one buffer.
#[test]
fn split_inverses_give_the_same_bits() {
    let Some((ctx, _g)) = gpu() else { return };
    let s = random_system(&SystemSpec::with_nodes(3, 729, 10));
    let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
    let whole = GpuParams {
        precision: Precision::F64,
        preconditioner: Preconditioner::Multilevel,
        tol: TOL,
        ..Default::default()
    };
    let mut one = PcgSolver::new(ctx, &e, &whole).expect("one buffer per level");
    let a = one.solve().expect("converges");
    let levels = one.multilevel_inverse_buffers();
    assert!(levels.iter().all(|&b| b == 1));
    // An iteration's dispatches: the PCG's product, its two updates and the r·z partials
    // (4), then the V-cycle: level 0's two smoothings, restriction, prolongation and two
    // products of two dispatches each (`world_z`, `matvec`: 8), six per level between it
    // and the coarsest, and the coarsest's solve (1).
    assert!(levels.len() >= 3, "{levels:?}");
    assert_eq!(
        a.info.dispatches_per_iteration,
        4 + 8 + 6 * (levels.len() - 2) + 1,
        "levels {levels:?}"
    );
    // About a third of level 0's inverses per buffer (and H split too).
    let level0: usize = Hierarchy::new(&s.h).level_sizes(3)[0].inverses.iter().sum();
    let split = GpuParams {
        binding_limit: Some((8 * level0 as u64 / 3).max(8 * 48 * 48)),
        ..whole
    };
    let mut many = PcgSolver::new(ctx, &e, &split).expect("split inverses");
    let b = many.solve().expect("converges");
    let buffers = many.multilevel_inverse_buffers();
    eprintln!(
        "inverse buffers per level {buffers:?}: {} and {} iterations; {}",
        a.info.iterations, b.info.iterations, b.info.coarse
    );
    assert!(buffers[0] >= 3, "{buffers:?}");
    assert_eq!(a.info.iterations, b.info.iterations);
    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&a.dx), bits(&b.dx));
}

/// Kept levels (`MultilevelSetup::Reuse`) on the device PCG through the facade: a Newton
/// sequence on one layout (Ĥ scaled ×4 as a penalty doubling twice grows it: the kept
/// levels refreshed, only the smoothing weights uploaded) and then a constraint set with
/// one more sticky node (the levels masked: their values uploaded again) takes the CPU
/// CG's iterations with the same kept levels, system by system, within the same bounds
/// as above; with `Every` it takes no fewer iterations than with levels kept.
#[test]
fn kept_levels_on_the_device_take_the_cpu_cgs_iterations() {
    use stickslip::MultilevelSetup;
    let Some((ctx, _g)) = gpu() else { return };
    let mut spec = SystemSpec::with_nodes(3, 729, 7);
    spec.prescribed = true;
    let s = random_system(&spec);
    let mut h4 = s.h.clone();
    h4.values.iter_mut().for_each(|v| *v *= 4.0);
    let node = (0..s.frames.n_nodes)
        .find(|&i| s.frames.mask[i] == 0 && s.frames.rotation(i).is_none())
        .expect("a free node");
    let mut more = s.frames.clone();
    more.mask[node] = 0b111;
    let systems = [
        (&s.h, &s.frames),
        (&h4, &s.frames),
        (&s.h, &s.frames),
        (&h4, &more),
    ];
    let (same, other) = (LayoutKey::fresh(), LayoutKey::fresh());
    let run = |config: SolverConfig, setup: MultilevelSetup| {
        let mut solver = Solver::new(
            config
                .tol(TOL)
                .max_iters(10_000)
                .preconditioner(Preconditioner::Multilevel)
                .multilevel_setup(setup),
        )
        .expect("solver");
        systems
            .iter()
            .enumerate()
            .map(|(k, (h, f))| {
                let e = Eliminated::new(h, &s.g, f, ConstrainedDiagonal::Identity);
                let layout = if k < 3 { same } else { other };
                solver.solve_eliminated(layout, &e).expect("converges")
            })
            .collect::<Vec<_>>()
    };
    let gpu_config = || SolverConfig::gpu(Precision::F64).gpu_context(ctx.clone());
    let cpu = run(SolverConfig::cg(), MultilevelSetup::Reuse);
    let dev = run(gpu_config(), MultilevelSetup::Reuse);
    let every = run(gpu_config(), MultilevelSetup::Every);
    for (k, ((c, d), f)) in cpu.iter().zip(&dev).zip(&every).enumerate() {
        let (ic, id, ie) = (
            c.stats.iterations.expect("CG iterations"),
            d.stats.iterations.expect("GPU iterations"),
            f.stats.iterations.expect("GPU iterations"),
        );
        let gap = rel_diff(&d.dx, &c.dx);
        eprintln!(
            "system {k}: kept levels: CPU CG {ic} iterations, device PCG {id}, \
             ‖Δx_gpu − Δx_cpu‖/‖Δx_cpu‖ {gap:.3e}; levels for every system: {ie}"
        );
        assert!(id.abs_diff(ic) * 10 <= ic, "system {k}: {id} against {ic}");
        assert!(d.stats.relative_residual <= TOL);
        assert!(gap <= 1e-8, "system {k}: Δx differs by {gap:e}");
        assert!(ie <= id + id / 10, "system {k}: every {ie}, kept {id}");
    }
}
