//! The aggregates' E⁺ formed on the device by `prepare` (shaders/coarse_factor.wgsl)
//! against the host's specification (`aggregates_einv_from_galerkin`) and the CPU CG's
//! E⁺, bit for bit, and against an independent reference: nalgebra's eigen
//! pseudo-inverse of sym(E) restricted to range(W) (P sym(E) P, P the projector onto the
//! range of each aggregate's Gram matrix, from an SVD). And the fallback: a system whose
//! Ĥ is indefinite on the coarse space makes the device flag its factorization, and the
//! first start then takes E⁺ from the host, once.
//!
//! Systems: generated grids (`random_system`, the realistic mix: a sticky face, a
//! prescribed face, a tilted slip plane (rotated frames) and line slips), and the same
//! grids with every free node on one tilted plane (every aggregate loses a translation:
//! W narrower than E); several aggregates each; sizes small for lavapipe, one with 168
//! columns of W (the factorization's loops then run many rows per invocation).

use stickslip::cases::generate::{random_system, GeneratedSystem, SystemSpec};
use stickslip::core::constraints::{Constraint, Frames};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::core::sparse::BlockCsr;
use stickslip::gpu::blocks::HostBlocks;
use stickslip::gpu::kernels::Real;
use stickslip::gpu::pcg::{DeviceCg, DeviceCgParams, DeviceFrames};
use stickslip::gpu::{GpuContext, GpuError};
use stickslip::solve::cg::{CgError, Preconditioner};
use stickslip::solve::coarse::{
    aggregate_projections, aggregates_einv_from_blocks, aggregates_einv_from_galerkin,
    aggregates_einv_with_basis, pseudo_inverse, AggregateBasis, Aggregation, CoarseSpace,
};

mod common;
use common::gpu::gpu;

/// A device PCG on `h` (uploaded in f64) with aggregate frames, prepared with b̂ of the
/// system.
fn prepared(
    ctx: &GpuContext,
    s: &GeneratedSystem,
    h: &BlockCsr,
) -> (HostBlocks, DeviceCg, DeviceFrames) {
    let blocks = HostBlocks::upload(ctx, h, Real::F64, None).expect("upload H");
    let mut cg = DeviceCg::new(ctx, blocks.matrix(), None, false, false).expect("device PCG");
    let frames = cg
        .frames(&s.frames, CoarseSpace::Aggregates)
        .expect("aggregate frames");
    let e = Eliminated::new(h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
    cg.prepare_with_rhs(&frames, &e.rhs).expect("prepare");
    (blocks, cg, frames)
}

/// `s` with every node that is not fully constrained on one tilted plane (2D: line):
/// every aggregate's Gram matrix loses a rank, so W has d − 1 columns per aggregate.
fn planar(mut s: GeneratedSystem) -> GeneratedSystem {
    let d = s.frames.dim;
    let full = (1u8 << d) - 1;
    let normal = [0.3, 1.0, -0.25];
    let cs: Vec<Constraint> = (0..s.frames.n_nodes)
        .map(|i| {
            if s.frames.mask[i] == full {
                Constraint::sticky(i)
            } else {
                Constraint::plane(i, &normal[..d])
            }
        })
        .collect();
    s.frames = Frames::build(d, s.frames.n_nodes, &cs).expect("valid constraints");
    s.constraints = cs;
    s
}

/// Entries whose bits differ.
fn differing_bits(a: &[f64], b: &[f64]) -> usize {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .filter(|(x, y)| x.to_bits() != y.to_bits())
        .count()
}

/// The reference: the eigen pseudo-inverse of P sym(E) P, P = blockdiag(P_a) with P_a
/// the projector onto the singular vectors of G_a above 1e-12 of its largest (the
/// threshold of W); and κ of sym(E) on that range.
fn reference(d: usize, count: usize, e: &[f64], gram: &[f64]) -> (Vec<f64>, f64) {
    let k = d * count;
    let mut p = nalgebra::DMatrix::<f64>::zeros(k, k);
    for a in 0..count {
        let ga = nalgebra::DMatrix::from_row_slice(d, d, &gram[a * d * d..(a + 1) * d * d]);
        let svd = ga.svd(true, false);
        let u = svd.u.expect("U");
        let smax = svd.singular_values.max();
        for (j, &sv) in svd.singular_values.iter().enumerate() {
            if sv > 1e-12 * smax {
                let c = u.column(j);
                let block = c * c.transpose();
                let mut v = p.view_mut((a * d, a * d), (d, d));
                v += block;
            }
        }
    }
    let mut es = nalgebra::DMatrix::from_row_slice(k, k, e);
    es = (&es + es.transpose()) * 0.5;
    let pep = &p * es * &p;
    let flat: Vec<f64> = (0..k * k).map(|t| pep[(t / k, t % k)]).collect();
    let ev = nalgebra::SymmetricEigen::new(pep).eigenvalues;
    let lmax = ev.max();
    let lmin = ev
        .iter()
        .copied()
        .filter(|&l| l > 1e-12 * lmax)
        .fold(f64::INFINITY, f64::min);
    (pseudo_inverse(k, &flat).expect("modes"), lmax / lmin)
}

/// Device E⁺ after `prepare` = the host routine on the device's E, bit for bit; = the CPU
/// CG's E⁺ (E reduced on the host) bit for bit where E matches; the reference within
/// 16·m·κ·ε of its largest entry (m columns of W: a Cholesky inverse and an eigen
/// pseudo-inverse, both backward stable, each off by O(m·κ·ε) relative). A CG with it
/// moves no coarse matrix.
#[test]
fn device_einv_is_the_host_specification_bit_for_bit() {
    let Some((ctx, _g)) = gpu() else { return };
    let cases = [
        (3, 4096, 11u64, false),
        (2, 900, 3, false),
        (3, 512, 4, false),
        (3, 729, 7, false),
    ]
    .into_iter()
    .chain([(2, 400, 8, true), (3, 343, 9, true)]);
    for (dim, nodes, seed, on_plane) in cases {
        let s = random_system(&SystemSpec::with_nodes(dim, nodes, seed));
        let s = if on_plane { planar(s) } else { s };
        let full = (1u8 << dim) - 1;
        let fixed = s.frames.mask.iter().filter(|&&m| m == full).count();
        assert!(
            fixed > 0 && s.frames.has_rotation(),
            "{dim}D: sticky and rotated nodes"
        );
        let agg = Aggregation::build(&s.h);
        assert!(agg.count >= 4, "{dim}D: {} aggregates", agg.count);
        let (_b, mut cg, frames) = prepared(ctx, &s, &s.h);
        let e_dev = cg
            .aggregate_galerkin(&frames)
            .expect("read E")
            .expect("aggregates");
        let einv_dev = cg
            .aggregate_einv(&frames)
            .expect("read E⁺")
            .expect("aggregates");
        let gram = aggregate_projections(&s.frames, &agg);
        let w = AggregateBasis::new(dim, agg.count, &gram).expect("W");
        let k = dim * agg.count;
        assert!(
            aggregates_einv_with_basis(k, &e_dev, &w).is_ok(),
            "{dim}D: Er is SPD"
        );
        let host =
            aggregates_einv_from_galerkin(dim, agg.count, e_dev.clone(), &gram).expect("host E⁺");
        let cpu = aggregates_einv_from_blocks(&s.h, &s.frames, &agg).expect("CPU E⁺");
        let (want, kappa) = reference(dim, agg.count, &e_dev, &gram);
        let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let worst = einv_dev
            .iter()
            .zip(&want)
            .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
        let m = w.columns();
        if on_plane {
            assert_eq!(
                m,
                (dim - 1) * agg.count,
                "{dim}D: W drops the plane's normal"
            );
        }
        let bound = 16.0 * m as f64 * kappa * f64::EPSILON * scale;
        eprintln!(
            "{dim}D seed {seed}: {} nodes, {fixed} fully constrained, {} rotated, {} aggregates, \
             W {m} columns, κ(Er) {kappa:.3e}; entries whose bits differ: device vs host \
             routine {}, device vs CPU CG {} (of {}); max |E⁺ − reference| {worst:.3e} = \
             {:.3e} of max|E⁺| (bound {:.3e})",
            s.frames.n_nodes,
            s.frames.rot_nodes.len(),
            agg.count,
            differing_bits(&einv_dev, &host),
            differing_bits(&einv_dev, &cpu),
            k * k,
            worst / scale,
            bound / scale,
        );
        assert_eq!(
            differing_bits(&einv_dev, &host),
            0,
            "{dim}D: device vs host"
        );
        assert_eq!(
            differing_bits(&einv_dev, &cpu),
            0,
            "{dim}D: device vs CPU CG"
        );
        assert!(worst <= bound, "{dim}D: {worst:e} > {bound:e}");
        // A solve with it: no coarse matrix crosses the bus.
        let params = DeviceCgParams {
            tol: 1e-8,
            max_iterations: 5000,
            preconditioner: Preconditioner::Jacobi,
            coarse: CoarseSpace::Aggregates,
            stagnation_window: stickslip::solve::cg::STAGNATION_WINDOW,
        };
        let info = cg.iterate(&frames, &params).expect("CG converges");
        let t = cg.coarse_traffic();
        eprintln!(
            "{dim}D: {} iterations; coarse traffic {} B up, {} B down",
            info.iterations, t.host_to_device_bytes, t.device_to_host_bytes
        );
        assert_eq!((t.host_to_device_bytes, t.device_to_host_bytes), (0, 0));
    }
}

/// H − σI on the diagonal blocks: Ĥ − σI on the free components, so E − σG on the
/// coarse space.
fn shifted(h: &BlockCsr, sigma: f64) -> BlockCsr {
    let d = h.dim;
    let mut out = h.clone();
    for i in 0..h.n {
        let kb = (h.row_ptr[i]..h.row_ptr[i + 1])
            .find(|&kb| h.col_idx[kb] == i)
            .expect("diagonal block");
        for a in 0..d {
            out.values[kb * d * d + a * d + a] -= sigma;
        }
    }
    out
}

/// σ midway between the extreme eigenvalues of Er v = μ (WᵀGW) v: E − σG is then
/// indefinite on range(W) and keeps a positive part.
fn indefinite_shift(d: usize, count: usize, e: &[f64], gram: &[f64]) -> f64 {
    let k = d * count;
    let w = AggregateBasis::new(d, count, gram).expect("W");
    let m = w.columns();
    let wm = nalgebra::DMatrix::from_fn(k, m, |r, p| {
        if w.of[p] == r / d {
            w.values[p * d + r % d]
        } else {
            0.0
        }
    });
    let mut g = nalgebra::DMatrix::<f64>::zeros(k, k);
    for a in 0..count {
        for x in 0..d {
            for y in 0..d {
                g[(a * d + x, a * d + y)] = gram[a * d * d + x * d + y];
            }
        }
    }
    let es = nalgebra::DMatrix::from_row_slice(k, k, e);
    let es = (&es + es.transpose()) * 0.5;
    let er = wm.transpose() * es * &wm;
    // WᵀGW is diagonal (W holds G_a's eigenvectors) and positive.
    let dg = wm.transpose() * g * &wm;
    let s = nalgebra::DMatrix::from_fn(m, m, |p, q| er[(p, q)] / (dg[(p, p)] * dg[(q, q)]).sqrt());
    let mu = nalgebra::SymmetricEigen::new(s).eigenvalues;
    0.5 * (mu.min() + mu.max())
}

/// Ĥ indefinite on the coarse space: the device's factorization flags it (E⁺ left zero
/// after `prepare`), the first start reads the flag with its status and E⁺ comes from the
/// host routine (whose Cholesky fails too: the eigen pseudo-inverse of sym(E)), bit for
/// bit; E went down and E⁺ up once (K² f64 each), and a second run of the same prepare
/// moves nothing more (the flag is cleared). Whatever CG then makes of the indefinite
/// system (non-positive curvature, or a solution) is its own report.
#[test]
fn indefinite_coarse_matrix_falls_back_to_the_host_once() {
    let Some((ctx, _g)) = gpu() else { return };
    for (dim, nodes, seed) in [(2, 400, 5u64), (3, 343, 6)] {
        let s = random_system(&SystemSpec::with_nodes(dim, nodes, seed));
        let agg = Aggregation::build(&s.h);
        let gram = aggregate_projections(&s.frames, &agg);
        let k = dim * agg.count;
        let e_cpu = {
            // E of the unshifted system, from the device.
            let (_b, cg, frames) = prepared(ctx, &s, &s.h);
            cg.aggregate_galerkin(&frames)
                .expect("E")
                .expect("aggregates")
        };
        let sigma = indefinite_shift(dim, agg.count, &e_cpu, &gram);
        let h2 = shifted(&s.h, sigma);
        let (_b, mut cg, frames) = prepared(ctx, &s, &h2);
        let e_dev = cg
            .aggregate_galerkin(&frames)
            .expect("E")
            .expect("aggregates");
        let w = AggregateBasis::new(dim, agg.count, &gram).expect("W");
        let pivot = aggregates_einv_with_basis(k, &e_dev, &w).expect_err("indefinite");
        let before = cg.aggregate_einv(&frames).expect("E⁺").expect("aggregates");
        assert!(
            before.iter().all(|v| *v == 0.0),
            "{dim}D: the failed factorization leaves E⁺ zero"
        );
        let params = DeviceCgParams {
            tol: 1e-8,
            max_iterations: 200,
            preconditioner: Preconditioner::Jacobi,
            coarse: CoarseSpace::Aggregates,
            stagnation_window: stickslip::solve::cg::STAGNATION_WINDOW,
        };
        let outcome = |r: Result<_, GpuError>| match r {
            Ok(info) => format!("converged ({info:?})"),
            Err(GpuError::Cg(e @ CgError::NonPositiveCurvature { .. }))
            | Err(GpuError::Cg(e @ CgError::MaxIterations { .. }))
            | Err(GpuError::Cg(e @ CgError::Stagnation { .. })) => e.to_string(),
            Err(e) => panic!("{dim}D: {e}"),
        };
        let first = outcome(cg.iterate(&frames, &params));
        let t = cg.coarse_traffic();
        let einv = cg.aggregate_einv(&frames).expect("E⁺").expect("aggregates");
        let mut es = e_dev.clone();
        for r in 0..k {
            for c in 0..r {
                let m = 0.5 * (es[r * k + c] + es[c * k + r]);
                es[r * k + c] = m;
                es[c * k + r] = m;
            }
        }
        let want = pseudo_inverse(k, &es).expect("a positive part");
        eprintln!(
            "{dim}D: σ {sigma:.4e}, pivot {pivot:?}; {first}; coarse traffic {} B up, {} B down; \
             E⁺ bits differing from the host's {}",
            t.host_to_device_bytes,
            t.device_to_host_bytes,
            differing_bits(&einv, &want)
        );
        let kk = 8 * (k * k) as u64;
        assert_eq!((t.host_to_device_bytes, t.device_to_host_bytes), (kk, kk));
        assert_eq!(differing_bits(&einv, &want), 0, "{dim}D");
        let second = outcome(cg.iterate(&frames, &params));
        let t2 = cg.coarse_traffic();
        eprintln!("{dim}D: again without prepare: {second}");
        assert_eq!(
            (t2.host_to_device_bytes, t2.device_to_host_bytes),
            (kk, kk),
            "{dim}D: one fallback per prepare"
        );
    }
}
