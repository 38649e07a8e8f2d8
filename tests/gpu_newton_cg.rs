//! The device PCG (`gpu::pcg::DeviceCg`) on the device-assembled Newton system against the
//! CPU Cholesky solution of the same eliminated system, and against `solve --solver gpu`
//! (the facade in f64) on it.
//!
//! Systems: a box of tetrahedra (3D) and a rectangle of triangles (2D), deformed at random,
//! with neo-Hookean elements, inertia and gravity, assembled on the device in f64; sticky
//! nodes on one side, slip nodes on a slanted plane (rotated frames) on the bottom, and
//! slip nodes on an axis-aligned plane (masked, no rotation) on the other side. H and g
//! are read back from the device and eliminated on the CPU (`Eliminated`), so both sides
//! solve the very same system. A free-floating body (no constraints, masses 1/100 of the
//! others') is where the coarse correction on the translations matters: there Ĥ's
//! smallest eigenvalues are the translations' mass term.
//!
//! Bounds: CG stops on the true residual ‖b̂ − Ĥy‖ ≤ tol‖b̂‖ with tol = 1e-10, so the
//! error of y is at most κ(Ĥ)·tol relative; the tests print the difference from the
//! Cholesky Δx and require ≤ 1e-8 of ‖Δx‖, which these systems meet with room to spare
//! (the printed figures). The free-floating body is the exception without the coarse
//! correction: its small masses raise κ(Ĥ) (printed), and there Jacobi CG stopped at
//! tol is only bound to κ(Ĥ)·tol; with the correction the 1e-8 holds for it too.
//! Constrained components of Δx in the node frames are V_iᵀV_i P y
//! with V_i orthonormal to rounding: ≤ 1e-14·‖Δx‖. With the coarse correction, E = ZᵀĤZ
//! is reduced on the device in the row order of `translations_einv_from_blocks` (each
//! block row summed before it is added) and pseudo-inverted on the host by the same
//! function: the two E⁺ differ by the rounding of the sums over the rows (a few ulps of E
//! times κ(E), a d×d matrix), required ≤ 1e-12 relative (Frobenius). With the aggregates
//! the device sums E in the CPU's order (`galerkin_from_blocks`: per row and column
//! aggregate, then per aggregate pair in row order) and forms E⁺ from it by the CPU's
//! operations (shaders/coarse_factor.wgsl): E⁺ is the same up to a compiler's fused
//! multiply-adds (lavapipe gives the same bits), held to the same 1e-12.
//!
//! The multilevel preconditioner's levels are built on the device from the assembled H
//! (as the device loop builds them: tests/gpu_multilevel_setup.rs holds them to the
//! host's); its iterations are held within 10 % of the CPU CG's, and to those of `solve`'s
//! device PCG with levels built on the host.
//!
//! Every test shares one device (tests/common/gpu.rs); sizes are small for lavapipe.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use stickslip::core::constraints::{Constraint, Frames};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::gpu::pcg::DeviceCgParams;
use stickslip::gpu::{GpuContext, GpuError, Precision};
use stickslip::sim::device::assembly::GpuAssembly;
use stickslip::sim::device::elements::GpuElements;
use stickslip::sim::energy::{ElementSet, Law, Model, NeoHookean};
use stickslip::sim::mesh;
use stickslip::solve::cg::{CgError, Preconditioner};
use stickslip::solve::coarse::{
    aggregates_einv_from_blocks, translations_einv_from_blocks, Aggregation, CoarseSpace,
};
use stickslip::solve::multilevel::reuse::Levels;
use stickslip::solve::multilevel::{Hierarchy, Multilevel};
use stickslip::{LayoutKey, Solver, SolverConfig};

mod common;
use common::gpu::gpu;

/// h² of the step (h = 0.05).
const SCALE: f64 = 0.05 * 0.05;
const TOL: f64 = 1e-10;

struct Scene {
    model: Model,
    x: Vec<f64>,
    x_tilde: Vec<f64>,
    frames: Frames,
}

/// A 3D box (6×4×3 cells, 140 nodes) or a 2D rectangle (14×9 cells, 150 nodes), deformed
/// at random; sticky at x = 0, slip on a slanted plane at the bottom (y = 0, x > 0), slip
/// on the plane x = const at the far side. `gravity` off and `x_tilde` = x make the
/// gradient vanish when the potential's scale is 0.
fn scene(d: usize, seed: u64, gravity: bool) -> Scene {
    body(d, seed, gravity, false)
}

/// The same body free-floating: no constraint, masses 0.005 to 0.02.
fn free_scene(d: usize, seed: u64) -> Scene {
    body(d, seed, true, true)
}

fn body(d: usize, seed: u64, gravity: bool, free: bool) -> Scene {
    let mut rng = StdRng::seed_from_u64(seed);
    let (m, len) = if d == 2 {
        (mesh::rectangle(2, [1.4, 0.9], [14, 9]), 1.4)
    } else {
        (mesh::cuboid([1.2, 0.8, 0.6], [6, 4, 3]), 1.2)
    };
    let n = m.n_nodes();
    let x: Vec<f64> =
        m.x.iter()
            .map(|v| v + rng.random_range(-0.01..0.01))
            .collect();
    let nh = NeoHookean::new(&m, 1e5, 0.35, Law::StableNeoHookean).expect("valid rest elements");
    let mass_scale = if free { 0.01 } else { 1.0 };
    let mass: Vec<f64> = (0..n)
        .map(|_| mass_scale * rng.random_range(0.5..2.0))
        .collect();
    let g = [0.0, -9.81, 1.5];
    let model = Model::new(
        d,
        mass,
        gravity.then(|| g[..d].to_vec()),
        vec![ElementSet::NeoHookean(nh)],
    );
    let x_tilde: Vec<f64> = x
        .iter()
        .map(|v| v + rng.random_range(-0.05..0.05))
        .collect();
    let slanted: Vec<f64> = if d == 2 {
        vec![0.35, 1.0]
    } else {
        vec![0.3, 1.0, -0.25]
    };
    let axis: Vec<f64> = (0..d).map(|a| if a == 0 { 1.0 } else { 0.0 }).collect();
    let mut cs = Vec::new();
    if free {
        let frames = Frames::build(d, n, &cs).expect("no constraints");
        return Scene {
            model,
            x,
            x_tilde,
            frames,
        };
    }
    for i in 0..n {
        let p = &m.x[i * d..(i + 1) * d];
        if p[0] < 1e-9 {
            cs.push(Constraint::sticky(i));
        } else if p[1] < 1e-9 {
            cs.push(Constraint::plane(i, &slanted));
        } else if p[0] > len - 1e-9 {
            cs.push(Constraint::plane(i, &axis));
        }
    }
    let frames = Frames::build(d, n, &cs).expect("valid constraints");
    assert!(frames.has_rotation(), "some nodes carry a rotation");
    assert!(
        frames.mask.iter().enumerate().any(|(i, &mk)| mk != 0
            && frames.rot_index[i] == stickslip::core::constraints::NO_ROTATION
            && mk.count_ones() < d as u32),
        "some slip nodes are masked without a rotation"
    );
    Scene {
        model,
        x,
        x_tilde,
        frames,
    }
}

fn assembled(ctx: &GpuContext, s: &Scene, precision: Precision) -> (GpuElements, GpuAssembly) {
    let el = GpuElements::new(ctx, &s.model, None, precision).expect("element terms");
    el.set_positions(&s.x).expect("positions");
    el.set_inertia_target(&s.x_tilde).expect("target");
    el.evaluate(true).expect("evaluate");
    let asm = GpuAssembly::new(&el, &s.model).expect("assembly");
    asm.set_scale(SCALE);
    asm.assemble().expect("assemble");
    (el, asm)
}

fn norm(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

fn rel_diff(a: &[f64], b: &[f64]) -> f64 {
    let diff: Vec<f64> = a.iter().zip(b).map(|(x, y)| x - y).collect();
    norm(&diff) / norm(b)
}

/// κ(Ĥ) from its dense eigenvalues (small systems only).
fn condition_number(e: &Eliminated) -> f64 {
    let nd = e.ndof();
    let mut dense = nalgebra::DMatrix::<f64>::zeros(nd, nd);
    let mut unit = vec![0.0; nd];
    let mut col = vec![0.0; nd];
    let mut work = vec![0.0; 2 * nd];
    for j in 0..nd {
        unit[j] = 1.0;
        e.apply(&unit, &mut col, &mut work);
        unit[j] = 0.0;
        dense.set_column(j, &nalgebra::DVector::from_column_slice(&col));
    }
    let ev = nalgebra::SymmetricEigen::new(dense).eigenvalues;
    let (lo, hi) = ev.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &v| {
        (lo.min(v), hi.max(v))
    });
    assert!(lo > 0.0, "Ĥ is positive definite");
    hi / lo
}

/// How far the device Δx may be from the Cholesky Δx without the coarse correction.
#[derive(Clone, Copy, PartialEq)]
enum Bound {
    /// 1e-8 relative (the constrained systems).
    Fixed,
    /// κ(Ĥ)·tol: the bound of a solution whose residual is tol relative.
    Kappa,
}

/// DeviceCg's Δx against the Cholesky Δx of the same H and g, for both preconditioners,
/// without and with the coarse correction on the translations (whose E⁺ is checked against
/// the CPU's); returns the iterations per (preconditioner, coarse space). With the
/// correction Δx is always required within 1e-8; without it, within `bound`. `solve`'s
/// GPU CG on the same eliminated system must stop after the same number of iterations.
fn compare(ctx: &GpuContext, s: &Scene, bound: Bound) -> Vec<(Preconditioner, CoarseSpace, usize)> {
    let d = s.frames.dim;
    let (_el, asm) = assembled(ctx, s, Precision::F64);
    let h = asm.read_matrix().expect("read H");
    let g = asm.read_gradient().expect("read g");
    let e = Eliminated::new(&h, &g, &s.frames, ConstrainedDiagonal::Identity);
    let (y_ref, _) = stickslip::solve::oracle::solve(&e).expect("Cholesky");
    let dx_ref = e.recover(&y_ref);
    let ref_norm = norm(&dx_ref);
    assert!(ref_norm > 0.0, "a non-trivial step");
    let kappa = (bound == Bound::Kappa).then(|| condition_number(&e));
    if let Some(k) = kappa {
        eprintln!("{d}D: κ(Ĥ) = {k:.3e}, κ(Ĥ)·tol = {:.3e}", k * TOL);
    }

    let einv_cpu = translations_einv_from_blocks(&h, &s.frames).expect("free translations");
    let agg = Aggregation::build(&h);
    let agg_einv_cpu =
        aggregates_einv_from_blocks(&h, &s.frames, &agg).expect("free aggregate translations");
    let mut cg = asm.device_cg().expect("device CG");
    let frames = cg
        .frames(&s.frames, CoarseSpace::Aggregates)
        .expect("device frames");
    let n = s.model.n_nodes;
    eprintln!(
        "{d}D: {n} nodes, {} constrained components, {} rotated nodes",
        s.frames.constrained_dofs(),
        s.frames.rot_nodes.len()
    );
    let mut iterations = Vec::new();
    for (pre, coarse) in [
        (Preconditioner::Jacobi, CoarseSpace::None),
        (Preconditioner::Jacobi, CoarseSpace::Translations),
        (Preconditioner::Jacobi, CoarseSpace::Aggregates),
        (Preconditioner::BlockJacobi, CoarseSpace::None),
        (Preconditioner::BlockJacobi, CoarseSpace::Translations),
        (Preconditioner::BlockJacobi, CoarseSpace::Aggregates),
        (Preconditioner::Multilevel, CoarseSpace::None),
    ] {
        let before = ctx.traffic();
        let params = DeviceCgParams {
            tol: TOL,
            max_iterations: 10_000,
            preconditioner: pre,
            coarse,
            stagnation_window: stickslip::solve::cg::STAGNATION_WINDOW,
        };
        // The multilevel levels built on the device from the assembled H, as the device
        // Newton loop builds them.
        cg.prepare(&frames).expect("prepare");
        if pre == Preconditioner::Multilevel {
            let hier = std::sync::Arc::new(Hierarchy::new(&h));
            cg.set_multilevel_on_device(&hier, &frames, Levels::Built, None)
                .expect("multilevel levels");
        }
        let info = cg.iterate(&frames, &params).expect("device CG converges");
        let after = ctx.traffic();
        let dx = cg.read_dx().expect("read dx");
        let diff: Vec<f64> = dx.iter().zip(&dx_ref).map(|(a, b)| a - b).collect();
        let rel = norm(&diff) / ref_norm;
        // Constrained components in the node frames.
        let mut yf = vec![0.0; dx.len()];
        s.frames.to_frame(&dx, &mut yf);
        let mut worst_fixed = 0.0f64;
        for i in 0..n {
            for a in 0..d {
                if !s.frames.is_free(i, a) {
                    worst_fixed = worst_fixed.max(yf[i * d + a].abs());
                }
            }
        }
        // The CPU's residual of the device's y (its free components).
        let mut y = yf.clone();
        s.frames.apply_mask(&mut y);
        let cpu_res = e.relative_residual(&y);
        let b_norm = norm(&e.rhs);
        if coarse == CoarseSpace::Translations {
            let (e_dev, einv_dev) = cg.coarse_matrix().expect("E read back");
            let einv_dev = einv_dev.expect("E⁺ on the device");
            let de = rel_diff(einv_dev, &einv_cpu);
            let e_dev: Vec<String> = e_dev.iter().map(|v| format!("{v:.6e}")).collect();
            eprintln!(
                "{d}D: E from the device [{}]; ‖E⁺ − E⁺_cpu‖/‖E⁺_cpu‖ {de:.3e}",
                e_dev.join(", ")
            );
            assert!(de <= 1e-12, "{d}D: E⁺ differs by {de:e}");
        } else if coarse == CoarseSpace::Aggregates {
            let einv_dev = cg
                .aggregate_einv(&frames)
                .expect("read E⁺")
                .expect("aggregates on the device");
            let de = rel_diff(&einv_dev, &agg_einv_cpu);
            eprintln!(
                "{d}D: {} aggregates; ‖E⁺ − E⁺_cpu‖/‖E⁺_cpu‖ {de:.3e}",
                agg.count
            );
            assert!(de <= 1e-12, "{d}D: the aggregates' E⁺ differs by {de:e}");
        } else {
            // Read for every solve: the check for a translation pinned by nothing uses it.
            assert!(cg.coarse_matrix().is_some(), "E read back");
        }
        iterations.push((pre, coarse, info.iterations));
        eprintln!(
            "{d}D {pre:?} coarse {}: {} iterations, device true residual {:.3e}, CPU \
             residual of the device y {:.3e}, ‖b̂‖ {:.6e} (CPU {:.6e}), \
             ‖Δx − Δx_chol‖/‖Δx‖ {:.3e}, constrained |Δx| {:.3e}·‖Δx‖; device→host {} B, \
             host→device {} B",
            coarse.name(),
            info.iterations,
            info.relative_residual,
            cpu_res,
            info.rhs_norm,
            b_norm,
            rel,
            worst_fixed / ref_norm,
            after.device_to_host_bytes - before.device_to_host_bytes,
            after.host_to_device_bytes - before.host_to_device_bytes,
        );
        assert!(info.iterations > 0);
        assert!(
            info.relative_residual <= TOL,
            "reported residual {:e}",
            info.relative_residual
        );
        // ‖b̂‖ is the same f64 sum of squares in another order: a few ulps.
        assert!(
            (info.rhs_norm - b_norm).abs() <= 1e-13 * b_norm,
            "‖b̂‖ {} vs {}",
            info.rhs_norm,
            b_norm
        );
        let limit = match kappa {
            Some(k) if coarse == CoarseSpace::None => k * TOL,
            _ => 1e-8,
        };
        assert!(
            rel <= limit,
            "{d}D {pre:?} coarse {}: relative difference {rel:e} > {limit:e}",
            coarse.name()
        );
        assert!(
            worst_fixed <= 1e-14 * ref_norm,
            "{d}D {pre:?}: constrained component {worst_fixed:e}"
        );
        // `solve --solver gpu` (the facade's engine, f64) on the same eliminated system,
        // with the same preconditioner, coarse space and tolerance. It runs the same device
        // PCG on H uploaded into the assembly's block layout, with b̂ formed on the host
        // and the multilevel levels built there (the same f64 operations in another order:
        // a few ulps): the same stopping iteration, and Δx within 1e-12 relative (κ·ulps
        // of b̂ and of the preconditioner, far below it here).
        let mut solver = Solver::new(
            SolverConfig::gpu(Precision::F64)
                .tol(TOL)
                .preconditioner(pre)
                .coarse(coarse)
                .gpu_context(ctx.clone()),
        )
        .expect("solve's GPU solver");
        let other = solver
            .solve_eliminated(LayoutKey::fresh(), &e)
            .expect("solve's GPU CG");
        let gap = rel_diff(&other.dx, &dx);
        eprintln!(
            "{d}D {pre:?} coarse {}: solve's GPU CG {:?} iterations, ‖Δx − Δx_loop‖/‖Δx_loop‖ {gap:.3e}",
            coarse.name(),
            other.stats.iterations
        );
        assert_eq!(
            other.stats.iterations,
            Some(info.iterations),
            "{d}D {pre:?} coarse {}: solve's GPU CG against the device loop's",
            coarse.name()
        );
        assert!(
            gap <= 1e-12,
            "{d}D {pre:?} coarse {}: {gap:e}",
            coarse.name()
        );
        if pre == Preconditioner::Multilevel {
            // The CPU CG with the same levels: the same operator up to the order of its
            // sums, so the iterations agree within 10 %.
            let mut cpu =
                Solver::new(SolverConfig::cg().tol(TOL).preconditioner(pre)).expect("the CPU CG");
            let c = cpu
                .solve_eliminated(LayoutKey::fresh(), &e)
                .expect("the CPU CG converges");
            let ic = c.stats.iterations.expect("iterations");
            eprintln!("{d}D multilevel: the CPU CG {ic} iterations");
            assert!(
                info.iterations.abs_diff(ic) * 10 <= ic,
                "{d}D multilevel: device {} iterations, CPU {ic}",
                info.iterations
            );
        }
    }
    iterations
}

#[test]
fn matches_cholesky_3d() {
    let Some((ctx, _g)) = gpu() else { return };
    compare(ctx, &scene(3, 11, true), Bound::Fixed);
}

#[test]
fn matches_cholesky_2d() {
    let Some((ctx, _g)) = gpu() else { return };
    compare(ctx, &scene(2, 12, true), Bound::Fixed);
}

/// A free-floating body with small masses: the translations carry Ĥ's smallest
/// eigenvalues, and the coarse correction on them cuts the iterations with either
/// preconditioner.
#[test]
fn free_body_matches_cholesky_with_the_coarse_correction() {
    let Some((ctx, _g)) = gpu() else { return };
    for (d, seed) in [(3, 17), (2, 18)] {
        let its = compare(ctx, &free_scene(d, seed), Bound::Kappa);
        eprintln!("{d}D free body, iterations: {its:?}");
        for pre in [Preconditioner::Jacobi, Preconditioner::BlockJacobi] {
            let of = |c: CoarseSpace| {
                its.iter()
                    .find(|(p, cs, _)| *p == pre && *cs == c)
                    .map(|t| t.2)
                    .expect("both runs")
            };
            let (none, with) = (of(CoarseSpace::None), of(CoarseSpace::Translations));
            assert!(
                with < none,
                "{d}D {pre:?}: {with} iterations with the translations, {none} without"
            );
        }
    }
}

/// The aggregates need frames built for them: others are refused with a one-line error.
#[test]
fn aggregates_need_frames_built_for_them() {
    let Some((ctx, _g)) = gpu() else { return };
    let s = scene(2, 19, true);
    let (_el, asm) = assembled(ctx, &s, Precision::F64);
    let mut cg = asm.device_cg().expect("device CG");
    let frames = cg
        .frames(&s.frames, CoarseSpace::Translations)
        .expect("device frames");
    let params = DeviceCgParams {
        tol: TOL,
        max_iterations: 100,
        preconditioner: Preconditioner::Jacobi,
        coarse: CoarseSpace::Aggregates,
        stagnation_window: stickslip::solve::cg::STAGNATION_WINDOW,
    };
    match cg.solve(&frames, &params) {
        Err(GpuError::Mismatch(m)) => {
            assert!(m.contains("aggregates") && !m.contains('\n'), "{m}")
        }
        other => panic!("aggregates: {other:?}"),
    }
}

/// The multilevel preconditioner needs its levels for the system just prepared: without
/// them, and again after the next `prepare`, iterating is a one-line error; with them
/// (built on the host or on the device) it converges.
#[test]
fn multilevel_needs_its_levels_after_every_prepare() {
    let Some((ctx, _g)) = gpu() else { return };
    let s = scene(2, 20, true);
    let (_el, asm) = assembled(ctx, &s, Precision::F64);
    let mut cg = asm.device_cg().expect("device CG");
    let frames = cg
        .frames(&s.frames, CoarseSpace::None)
        .expect("device frames");
    let params = DeviceCgParams {
        tol: TOL,
        max_iterations: 1_000,
        preconditioner: Preconditioner::Multilevel,
        coarse: CoarseSpace::None,
        stagnation_window: stickslip::solve::cg::STAGNATION_WINDOW,
    };
    let refused = |r: Result<stickslip::gpu::pcg::DeviceCgInfo, GpuError>| match r {
        Err(GpuError::Mismatch(m)) => {
            assert!(m.contains("set_multilevel") && !m.contains('\n'), "{m}")
        }
        other => panic!("multilevel without its levels: {other:?}"),
    };
    cg.prepare(&frames).expect("prepare");
    refused(cg.iterate(&frames, &params));
    let h = asm.read_matrix().expect("read H");
    let g = asm.read_gradient().expect("read g");
    let e = Eliminated::new(&h, &g, &s.frames, ConstrainedDiagonal::Identity);
    let ml = Multilevel::new(&e, std::sync::Arc::new(Hierarchy::new(&h)));
    cg.set_multilevel(&ml, &s.frames, None).expect("levels");
    let info = cg
        .iterate(&frames, &params)
        .expect("converges with its levels");
    assert!(info.relative_residual <= TOL);
    cg.prepare(&frames).expect("prepare again");
    refused(cg.iterate(&frames, &params));
    // The same with the levels built on the device.
    let hier = std::sync::Arc::new(Hierarchy::new(&h));
    cg.set_multilevel_on_device(&hier, &frames, Levels::Built, None)
        .expect("levels on the device");
    let info = cg
        .iterate(&frames, &params)
        .expect("converges with its levels");
    assert!(info.relative_residual <= TOL);
    cg.prepare(&frames).expect("prepare again");
    refused(cg.iterate(&frames, &params));
}

/// A vanishing gradient gives Δx = 0 in 0 iterations, even after a non-zero step left
/// something in the Δx buffer.
#[test]
fn zero_gradient_gives_zero_step() {
    let Some((ctx, _g)) = gpu() else { return };
    let mut s = scene(3, 13, false);
    let (el, asm) = assembled(ctx, &s, Precision::F64);
    let mut cg = asm.device_cg().expect("device CG");
    let frames = cg
        .frames(&s.frames, CoarseSpace::Translations)
        .expect("device frames");
    let params = DeviceCgParams {
        tol: TOL,
        max_iterations: 1000,
        preconditioner: Preconditioner::BlockJacobi,
        coarse: CoarseSpace::Translations,
        stagnation_window: stickslip::solve::cg::STAGNATION_WINDOW,
    };
    let first = cg.solve(&frames, &params).expect("non-zero step");
    assert!(first.iterations > 0 && first.rhs_norm > 0.0);
    assert!(cg.read_dx().expect("dx").iter().any(|&v| v != 0.0));
    // x̃ = x and the potential scaled by 0: g = M(x − x̃) + 0·(…) = 0 exactly.
    s.x_tilde = s.x.clone();
    el.set_inertia_target(&s.x_tilde).expect("target");
    el.evaluate(true).expect("evaluate");
    asm.set_scale(0.0);
    asm.assemble().expect("assemble");
    assert!(asm.read_gradient().expect("g").iter().all(|&v| v == 0.0));
    let info = cg.solve(&frames, &params).expect("zero step");
    eprintln!("zero gradient: {info:?}");
    assert_eq!(info.iterations, 0);
    assert_eq!(info.rhs_norm, 0.0);
    assert_eq!(info.relative_residual, 0.0);
    assert!(cg.read_dx().expect("dx").iter().all(|&v| v == 0.0));
}

/// Too few iterations allowed: an error naming the iterations and the residual.
#[test]
fn iteration_limit_is_an_error() {
    let Some((ctx, _g)) = gpu() else { return };
    let s = scene(3, 14, true);
    let (_el, asm) = assembled(ctx, &s, Precision::F64);
    let mut cg = asm.device_cg().expect("device CG");
    let frames = cg
        .frames(&s.frames, CoarseSpace::Translations)
        .expect("device frames");
    for max in [0, 3] {
        let r = cg.solve(
            &frames,
            &DeviceCgParams {
                tol: TOL,
                max_iterations: max,
                preconditioner: Preconditioner::Jacobi,
                coarse: CoarseSpace::Translations,
                stagnation_window: stickslip::solve::cg::STAGNATION_WINDOW,
            },
        );
        match r {
            Err(GpuError::Cg(CgError::MaxIterations {
                iterations,
                relative_residual,
                tol,
            })) => {
                let msg = r.unwrap_err().to_string();
                eprintln!("max_iterations {max}: {msg}");
                assert_eq!(iterations, max);
                assert!(relative_residual > TOL && relative_residual.is_finite());
                assert_eq!(tol, TOL);
                assert!(msg.contains(&max.to_string()), "{msg}");
            }
            other => panic!("max_iterations {max}: {other:?}"),
        }
    }
}

/// A tolerance below f64's reach ends in stagnation, an error that carries the true
/// residual reached, not in a claim of convergence and not at the iteration limit.
#[test]
fn a_tolerance_below_rounding_stagnates() {
    let Some((ctx, _g)) = gpu() else { return };
    let s = scene(2, 15, true);
    let (_el, asm) = assembled(ctx, &s, Precision::F64);
    let mut cg = asm.device_cg().expect("device CG");
    let frames = cg
        .frames(&s.frames, CoarseSpace::None)
        .expect("device frames");
    let (tol, max) = (1e-30, 20_000);
    let r = cg.solve(
        &frames,
        &DeviceCgParams {
            tol,
            max_iterations: max,
            preconditioner: Preconditioner::Jacobi,
            coarse: CoarseSpace::None,
            stagnation_window: 40,
        },
    );
    match r {
        Err(GpuError::Cg(CgError::Stagnation {
            iterations,
            relative_residual,
            ..
        })) => {
            eprintln!("stagnated after {iterations} iterations at {relative_residual:e}");
            assert!(iterations < max);
            // The rounding floor of f64 CG on this system: far above tol, far below 1e-10.
            assert!(relative_residual > tol && relative_residual < 1e-10);
        }
        other => panic!("{other:?}"),
    }
}

/// An f32 assembly gets the PCG in f32 (f64 sums where the device has them): its y meets
/// the tolerance against the f32 H it read, by the host's f64 residual. Why a 2× margin
/// over the device's own f32-vector residual: r = b̂ − Ĥy is stored in f32, which adds at
/// most a few ε_f32 (1.2e-7) of ‖b̂‖ + ‖Ĥy‖ ≈ 2‖b̂‖, far below tol = 1e-4. Another mesh's
/// frames and iterating before `prepare` are refused with one-line errors.
#[test]
fn an_f32_assembly_runs_in_f32_and_foreign_frames_are_refused() {
    let Some((ctx, _g)) = gpu() else { return };
    let s = scene(2, 15, true);
    let (_el, asm) = assembled(ctx, &s, Precision::F32);
    let mut cg32 = asm.device_cg().expect("an f32 device CG");
    assert_eq!(cg32.scalars().real, stickslip::gpu::kernels::Real::F32);
    let h32 = asm.read_matrix().expect("read the f32 H");
    let g32 = asm.read_gradient().expect("read the f32 g");
    let e32 = Eliminated::new(&h32, &g32, &s.frames, ConstrainedDiagonal::Identity);
    let frames32 = cg32
        .frames(&s.frames, CoarseSpace::Aggregates)
        .expect("device frames");
    cg32.prepare(&frames32).expect("prepare");
    let tol32 = 1e-4;
    let info = cg32
        .iterate(
            &frames32,
            &DeviceCgParams {
                tol: tol32,
                max_iterations: 10_000,
                preconditioner: Preconditioner::Jacobi,
                coarse: CoarseSpace::Aggregates,
                stagnation_window: stickslip::solve::cg::STAGNATION_WINDOW,
            },
        )
        .expect("the f32 PCG converges");
    let y = cg32.read_y().expect("read y");
    let host = e32.relative_residual(&y);
    eprintln!(
        "f32 assembly: {} iterations, device residual {:.3e}, host f64 residual {host:.3e}",
        info.iterations, info.relative_residual
    );
    assert!(info.iterations > 0 && host <= 2.0 * tol32, "{host:e}");
    let (_el64, asm64) = assembled(ctx, &s, Precision::F64);
    let mut cg = asm64.device_cg().expect("device CG");
    // Iterating before b̂ and the preconditioner exist for these frames.
    let frames = cg
        .frames(&s.frames, CoarseSpace::Translations)
        .expect("device frames");
    let params = DeviceCgParams {
        tol: TOL,
        max_iterations: 100,
        preconditioner: Preconditioner::Jacobi,
        coarse: CoarseSpace::None,
        stagnation_window: stickslip::solve::cg::STAGNATION_WINDOW,
    };
    match cg.iterate(&frames, &params) {
        Err(GpuError::Mismatch(m)) => assert!(m.contains("prepare"), "{m}"),
        other => panic!("iterate before prepare: {other:?}"),
    }
    let other = scene(3, 16, true);
    match cg.frames(&other.frames, CoarseSpace::None) {
        Err(GpuError::Mismatch(m)) => assert!(m.contains("3D"), "{m}"),
        Err(e) => panic!("unexpected error {e}"),
        Ok(_) => panic!("3D frames were accepted for a 2D mesh"),
    }
}

/// The reductions are segmented (src/gpu/launch.rs, `SegmentPolicy`): their partials and
/// the order in which they are summed depend on the segment length only, so the device CG
/// gives the same iterations and Δx bit for bit whether its reductions run on 1, 7, 256 or
/// 4,096 workgroups (idle ones included) or on the adapter's own count.
#[test]
fn reductions_give_the_same_bits_on_any_workgroup_count() {
    let Some((ctx, _g)) = gpu() else { return };
    let s = scene(3, 21, true);
    let run = |ctx: &GpuContext, coarse: CoarseSpace| {
        let (_el, asm) = assembled(ctx, &s, Precision::F64);
        let mut cg = asm.device_cg().expect("device CG");
        let frames = cg.frames(&s.frames, coarse).expect("device frames");
        let params = DeviceCgParams {
            tol: TOL,
            max_iterations: 10_000,
            preconditioner: Preconditioner::BlockJacobi,
            coarse,
            stagnation_window: stickslip::solve::cg::STAGNATION_WINDOW,
        };
        let info = cg.solve(&frames, &params).expect("device CG converges");
        let dx: Vec<u64> = cg
            .read_dx()
            .expect("read dx")
            .iter()
            .map(|v| v.to_bits())
            .collect();
        (info.iterations, info.rhs_norm.to_bits(), dx)
    };
    for coarse in [CoarseSpace::Translations, CoarseSpace::Aggregates] {
        let own = run(ctx, coarse);
        for w in [1u64, 7, 256, 4096] {
            let forced = ctx.with_reduction_workgroups(Some(w));
            let got = run(&forced, coarse);
            eprintln!(
                "coarse {}: {} iterations on the adapter's workgroups, {} on {w}",
                coarse.name(),
                own.0,
                got.0
            );
            assert_eq!(got.0, own.0, "{} at {w} workgroups", coarse.name());
            assert_eq!(got.1, own.1, "‖b̂‖ at {w} workgroups");
            assert!(
                got.2 == own.2,
                "{}: Δx differs at {w} workgroups",
                coarse.name()
            );
        }
    }
}
