//! Every GPU kernel against its CPU reference. One shared device per test binary; GPU
//! tests are serialized (lavapipe is slow). Without an adapter they print a loud SKIP
//! line and return, unless STICKSLIP_REQUIRE_GPU=1 (CI), where a missing adapter fails.

use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::core::constraints::Frames;
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::gpu::blocks::{row_sums, HostBlocks};
use stickslip::gpu::kernels::Real;
use stickslip::gpu::pcg::{DeviceCg, DeviceCgParams, Scalars, SegmentEnd, SegmentStart};
use stickslip::gpu::{DifferenceForm, GpuParams, PcgSolver, Precision};
use stickslip::solve::cg::{BuiltPreconditioner, Preconditioner};
use stickslip::solve::coarse::CoarseSpace;

mod common;
use common::gpu::gpu;

fn params(precision: Precision, pc: Preconditioner) -> GpuParams {
    GpuParams {
        precision,
        preconditioner: pc,
        ..Default::default()
    }
}

fn max_rel(a: &[f64], b: &[f64]) -> f64 {
    let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(1e-300);
    a.iter()
        .zip(b)
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
        / scale
}

fn test_vector(n: usize) -> Vec<f64> {
    (0..n)
        .map(|k| ((k * 7919) % 23) as f64 / 11.0 - 1.0)
        .collect()
}

/// The device PCG's product q = Ĥx (H read in place in the world frame, p rotated at
/// rotated nodes) and its preconditioners against the CPU's on random systems with slip
/// nodes, in f64, f32 and f32 in the difference form. The device puts D = I on the
/// constrained components whatever diagonal the system was eliminated with (b̂, and so r,
/// z and p, vanish there, so y does not depend on D): a system eliminated with
/// D = diag(VᵀHV) gives the product of D = I. Bounds: f64 to a few roundings of the row sums (1e-13 of max |Ĥx|);
/// f32 to ε_f32 = 6e-8 per rounding of H, x and the rotations, summed over a row's few
/// dozen terms of either sign (2e-6); the preconditioners (a d×d inverse more) to ten
/// times that.
#[test]
fn pcg_product_and_preconditioners_match_cpu_in_every_precision() {
    let Some((ctx, _g)) = gpu() else { return };
    for (dim, seed) in [(2, 1u64), (3, 2), (3, 5)] {
        let s = random_system(&SystemSpec::small(dim, seed));
        assert!(s.frames.has_rotation() && s.frames.has_constraints());
        let identity = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let x = test_vector(identity.ndof());
        let mut want = vec![0.0; x.len()];
        let mut work = vec![0.0; 2 * x.len()];
        identity.apply(&x, &mut want, &mut work);
        for diag in [ConstrainedDiagonal::Identity, ConstrainedDiagonal::Hessian] {
            let e = Eliminated::new(&s.h, &s.g, &s.frames, diag);
            for (prec, tol, diff) in [
                (Precision::F64, 1e-13, DifferenceForm::Off),
                (Precision::F32, 2e-6, DifferenceForm::Off),
                (Precision::F32, 2e-6, DifferenceForm::On),
            ] {
                for pc in [Preconditioner::Jacobi, Preconditioner::BlockJacobi] {
                    let what = format!("{dim}D seed {seed} {diag:?} {prec} {diff:?} {pc:?}");
                    let prm = GpuParams {
                        f32_difference: diff,
                        ..params(prec, pc)
                    };
                    let mut sol = PcgSolver::new(ctx, &e, &prm).expect("solver");
                    assert_eq!(sol.difference_form(), diff == DifferenceForm::On);
                    let err = max_rel(&sol.apply_operator(&x).expect("product"), &want);
                    eprintln!("{what}: product error {err:.2e}");
                    assert!(err <= tol, "{what}: product {err:e}");
                    let pre = sol.preconditioner_data().expect("download");
                    let err = max_rel(&pre, BuiltPreconditioner::new(&identity, pc).data());
                    assert!(err <= 10.0 * tol, "{what}: preconditioner {err:e}");
                }
            }
        }
    }
}

/// The f32 difference form keeps a free body's translations: on kappa-1e6 (a free spring
/// grid, Ĥt = m t exactly for a translation t, m = λ_max/(κ − 1)) the form maps t to S t
/// (S_i = m I rounded once to f32: ε_f32 = 6e-8 relative, 1e-6 leaves room for the f32
/// products), while plain f32 blocks miss it by ~κ·ε_f32 = 0.06 of m t (each row's
/// blocks, of size λ_max, cancel to m; 1e-3 is far below that and far above the form's
/// error). Auto turns it on where the device has f64 sums, and on a free body everywhere.
#[test]
fn f32_difference_form_keeps_the_translations() {
    let Some((ctx, _g)) = gpu() else { return };
    let case = stickslip::app::hard::conditioned(stickslip::app::hard::Size::Ci, 1e6, false);
    let e = case.eliminated();
    let n = e.ndof();
    let mut solvers = [DifferenceForm::Off, DifferenceForm::On].map(|diff| {
        let prm = GpuParams {
            f32_difference: diff,
            ..params(Precision::F32, Preconditioner::Jacobi)
        };
        PcgSolver::new(ctx, &e, &prm).expect("solver")
    });
    for axis in 0..3 {
        let t: Vec<f64> = (0..n).map(|k| f64::from(k % 3 == axis)).collect();
        let mut want = vec![0.0; n];
        let mut work = vec![0.0; 2 * n];
        e.apply(&t, &mut want, &mut work);
        let errs = solvers
            .each_mut()
            .map(|s| max_rel(&s.apply_operator(&t).expect("product"), &want));
        eprintln!(
            "axis {axis}: plain f32 {:.2e}, difference form {:.2e}",
            errs[0], errs[1]
        );
        assert!(
            errs[1] <= 1e-6,
            "difference form, axis {axis}: {:e}",
            errs[1]
        );
        assert!(
            errs[0] >= 1e-3,
            "plain f32 blocks, axis {axis}: {:e}",
            errs[0]
        );
    }
    let auto = |e: &Eliminated| {
        PcgSolver::new(ctx, e, &params(Precision::F32, Preconditioner::Jacobi))
            .expect("solver")
            .difference_form()
    };
    assert!(auto(&e));
    let pinned = stickslip::app::hard::stiffness_contrast(stickslip::app::hard::Size::Ci, 1e4);
    assert_eq!(auto(&pinned.eliminated()), ctx.has_f64());
}

#[test]
fn unmasked_matvec_matches_cpu() {
    let Some((ctx, _g)) = gpu() else { return };
    for dim in [2, 3] {
        let s = random_system(&SystemSpec::small(dim, 9));
        let f = Frames::unconstrained(dim, s.h.n);
        let e = Eliminated::new(&s.h, &s.g, &f, ConstrainedDiagonal::Identity);
        let y = test_vector(e.ndof());
        let mut want = vec![0.0; y.len()];
        s.h.matvec(&y, &mut want);
        let mut sol = PcgSolver::new(ctx, &e, &params(Precision::F64, Preconditioner::Jacobi))
            .expect("solver");
        let got = sol.apply_operator(&y).expect("matvec");
        assert!(max_rel(&got, &want) <= 1e-13);
    }
}

/// x after k iterations of the same PCG recurrence on the CPU, in f64.
fn cpu_pcg(e: &Eliminated, pc: Preconditioner, coarse: CoarseSpace, k: usize) -> Vec<f64> {
    let n = e.ndof();
    let pre = BuiltPreconditioner::new(e, pc).with_coarse(e, coarse, None);
    let mut x = vec![0.0; n];
    let mut r = e.rhs.clone();
    let mut z = vec![0.0; n];
    pre.apply(&r, &mut z);
    let mut p = z.clone();
    let mut rz: f64 = r.iter().zip(&z).map(|(a, b)| a * b).sum();
    let mut q = vec![0.0; n];
    let mut work = vec![0.0; 2 * n];
    for _ in 0..k {
        e.apply(&p, &mut q, &mut work);
        let pq: f64 = p.iter().zip(&q).map(|(a, b)| a * b).sum();
        let alpha = rz / pq;
        for i in 0..n {
            x[i] += alpha * p[i];
            r[i] -= alpha * q[i];
        }
        pre.apply(&r, &mut z);
        let rz_new: f64 = r.iter().zip(&z).map(|(a, b)| a * b).sum();
        let beta = rz_new / rz;
        rz = rz_new;
        for i in 0..n {
            p[i] = z[i] + beta * p[i];
        }
    }
    x
}

/// The device PCG's updates (with and without the coarse correction on the translations,
/// whose Z_i = P_i V_iᵀ the kernels compute from the mask and the rotations of these
/// systems' slip nodes) follow the CPU recurrence: after six f64 iterations on a
/// well-conditioned system y is the CPU's x to 1e-11 (a few hundred ulps at most); the
/// f32 PCG (difference form) follows it to f32 round-off (1e-4).
#[test]
fn cg_updates_and_reductions_match_cpu_recurrence() {
    let Some((ctx, _g)) = gpu() else { return };
    for (dim, seed, pc, coarse) in [
        (2, 3u64, Preconditioner::Jacobi, CoarseSpace::None),
        (3, 4, Preconditioner::BlockJacobi, CoarseSpace::None),
        (3, 6, Preconditioner::None, CoarseSpace::None),
        (2, 3, Preconditioner::Jacobi, CoarseSpace::Translations),
        (3, 4, Preconditioner::BlockJacobi, CoarseSpace::Translations),
        (3, 6, Preconditioner::None, CoarseSpace::Translations),
        (3, 7, Preconditioner::Jacobi, CoarseSpace::Translations),
    ] {
        let s = random_system(&SystemSpec::small(dim, seed));
        assert!(s.frames.has_rotation(), "the systems have slip nodes");
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let k = 6;
        let x = cpu_pcg(&e, pc, coarse, k);
        let reals: &[(Real, f64)] = if ctx.has_f64() {
            &[(Real::F64, 1e-11), (Real::F32, 1e-4)]
        } else {
            &[(Real::F32, 1e-4)]
        };
        for &(real, tol) in reals {
            let ty = Scalars::on(ctx, real, real == Real::F32).expect("scalars");
            let blocks = HostBlocks::upload(ctx, e.h, ty.real, None).expect("upload");
            let mut cg =
                DeviceCg::new(ctx, blocks.matrix(), None, false, ty.difference).expect("pcg");
            if ty.difference {
                cg.write_row_sums(&row_sums(e.h)).expect("row sums");
            }
            let frames = cg.frames(e.frames, coarse).expect("frames");
            cg.prepare_with_rhs(&frames, &e.rhs).expect("prepare");
            let prm = DeviceCgParams {
                tol: 1e-30,
                max_iterations: k,
                preconditioner: pc,
                coarse,
                stagnation_window: 1000,
            };
            let info = cg
                .segment(&frames, &prm, SegmentStart::Fresh, None)
                .expect("segment");
            assert_eq!((info.end, info.iterations), (SegmentEnd::MaxIterations, k));
            let err = max_rel(&cg.read_y().expect("y"), &x);
            assert!(
                err <= tol,
                "{} y after {k} iterations ({dim}D, {pc:?}, coarse {coarse:?}): {err:e}",
                real.name()
            );
        }
    }
}

/// The one block-Jacobi specification on blocks that are not SPD: the device PCG builds,
/// in f64 and f32, what the CPU's `block_jacobi_inverse` and
/// `jacobi_inverse` give: B⁻¹ where
/// every Cholesky pivot is positive and finite, else the Jacobi diagonal (1/B_aa where
/// B_aa is positive, else 1). The fallback is a decision, so its pattern must match
/// exactly; the values agree to a few ulps of the precision (f64: the same operations,
/// in the same order, on the same inputs).
#[test]
fn block_jacobi_follows_one_specification_on_blocks_that_are_not_spd() {
    use stickslip::solve::precond::{block_jacobi_inverse, jacobi_inverse};
    let Some((ctx, _g)) = gpu() else { return };
    let special: [[f64; 9]; 6] = [
        // SPD.
        [4.0, 1.0, 0.0, 1.0, 3.0, 1.0, 0.0, 1.0, 2.0],
        // Positive diagonal, indefinite: the second pivot is −3.
        [1.0, 2.0, 0.0, 2.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        // A negative diagonal entry.
        [-2.0, 0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 0.0, 1.0],
        // Zero.
        [0.0; 9],
        // SPD, badly scaled.
        [1e6, 1.0, 0.0, 1.0, 1e-3, 0.0, 0.0, 0.0, 5.0],
        // An infinite pivot: not finite, so the fallback (all ones).
        [f64::INFINITY, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
    ];
    for dim in [2usize, 3] {
        let mut s = random_system(&SystemSpec::small(dim, 9));
        let n = s.frames.n_nodes;
        let dd = dim * dim;
        for (t, b) in special.iter().enumerate() {
            let k = s.h.diag_index(t).expect("diagonal block");
            for r in 0..dim {
                for c in 0..dim {
                    s.h.values[k * dd + r * dim + c] = b[r * 3 + c];
                }
            }
        }
        let frames = Frames::unconstrained(dim, n);
        let e = Eliminated::new(&s.h, &s.g, &frames, ConstrainedDiagonal::Identity);
        for pc in [Preconditioner::Jacobi, Preconditioner::BlockJacobi] {
            let want: Vec<f64> = (0..n)
                .flat_map(|i| {
                    let k = s.h.diag_index(i).expect("diagonal block");
                    let b = &s.h.values[k * dd..(k + 1) * dd];
                    match pc {
                        Preconditioner::Jacobi => {
                            (0..dim).map(|a| jacobi_inverse(b[a * dim + a])).collect()
                        }
                        _ => block_jacobi_inverse(dim, b)[..dd].to_vec(),
                    }
                })
                .collect();
            assert_eq!(
                BuiltPreconditioner::new(&e, pc).data(),
                &want[..],
                "{dim}D {pc:?}: the CPU CG's preconditioner"
            );
            let precisions: &[(Precision, f64)] = if ctx.has_f64() {
                &[(Precision::F64, 4.0 * f64::EPSILON), (Precision::F32, 4e-7)]
            } else {
                &[(Precision::F32, 4e-7)]
            };
            let device_pcg = |prec| -> Vec<f64> {
                PcgSolver::new(ctx, &e, &params(prec, pc))
                    .expect("solver")
                    .preconditioner_data()
                    .expect("download")
            };
            for (&(prec, ulps), solver, got) in precisions
                .iter()
                .map(|p| (p, "device PCG", device_pcg(p.0)))
            {
                assert_eq!(got.len(), want.len(), "{solver}");
                let per = want.len() / n;
                for (i, (g, w)) in got.chunks(per).zip(want.chunks(per)).enumerate() {
                    let what =
                        format!("{solver} {dim}D {pc:?} {prec}: node {i}: {g:?} against {w:?}");
                    // The fallback's pattern: zero where the CPU has zero.
                    let zeros = |v: &[f64]| v.iter().map(|x| *x == 0.0).collect::<Vec<_>>();
                    assert_eq!(zeros(g), zeros(w), "{what}");
                    // A few roundings of the node's own values (f32: of its values rounded
                    // to f32), relative to the largest entry of its inverse.
                    let scale = w.iter().fold(0.0f64, |m, x| m.max(x.abs()));
                    let err = g
                        .iter()
                        .zip(w)
                        .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
                    assert!(err <= 8.0 * ulps * scale, "{what}: {err:e} of {scale:e}");
                }
            }
        }
    }
}
