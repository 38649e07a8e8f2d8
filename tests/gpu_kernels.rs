//! Every GPU kernel against its CPU reference. One shared device per test binary; GPU
//! tests are serialized (lavapipe is slow). Without an adapter they print a loud SKIP
//! line and return, unless STICKSLIP_REQUIRE_GPU=1 (CI), where a missing adapter fails.

use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::cases::springs::MassSpring;
use stickslip::core::constraints::{Constraint, ConstraintKind, Frames};
use stickslip::core::elimination::{rotate_blocks, ConstrainedDiagonal, Eliminated};
use stickslip::gpu::{DifferenceForm, GpuParams, GpuSolver, PcgSolver, Precision};
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

#[test]
fn matvec_rotation_and_preconditioners_match_cpu() {
    let Some((ctx, _g)) = gpu() else { return };
    for (dim, seed) in [(2, 1u64), (3, 2), (3, 5)] {
        let s = random_system(&SystemSpec::small(dim, seed));
        assert!(s.frames.has_rotation() && s.frames.has_constraints());
        for diag in [ConstrainedDiagonal::Identity, ConstrainedDiagonal::Hessian] {
            let e = Eliminated::new(&s.h, &s.g, &s.frames, diag);
            let n = e.ndof();
            let y = test_vector(n);
            let mut want = vec![0.0; n];
            let mut work = vec![0.0; 2 * n];
            e.apply(&y, &mut want, &mut work);
            let rot = rotate_blocks(&s.h, &s.frames);
            for (prec, tol, diff) in [
                (Precision::F64, 1e-13, false),
                (Precision::F32, 2e-6, false),
                (Precision::F32, 2e-6, true),
            ] {
                for pc in [Preconditioner::Jacobi, Preconditioner::BlockJacobi] {
                    let prm = GpuParams {
                        f32_difference: if diff {
                            DifferenceForm::On
                        } else {
                            DifferenceForm::Off
                        },
                        ..params(prec, pc)
                    };
                    // f32 blocks are read as u64 pairs where the device has SHADER_INT64
                    // and as vec4<f32> where it has not: both paths, same tolerance.
                    if prec == Precision::F32 {
                        let plain = ctx.without_int64();
                        let mut sol = GpuSolver::new(&plain, &e, &prm).expect("solver");
                        let got = sol.apply_operator(&y).expect("matvec");
                        let err = max_rel(&got, &want);
                        assert!(err <= tol, "vec4 matvec {dim}D {prec} seed {seed}: {err:e}");
                        assert!(sol.resources().kernels.iter().all(|k| !k.packed));
                    }
                    let mut sol = GpuSolver::new(ctx, &e, &prm).expect("solver");
                    let got = sol.apply_operator(&y).expect("matvec");
                    let err = max_rel(&got, &want);
                    assert!(err <= tol, "matvec {dim}D {prec} seed {seed}: {err:e}");
                    let packed = sol
                        .resources()
                        .kernels
                        .iter()
                        .any(|k| k.name == "matvec" && k.packed);
                    assert_eq!(packed, prec == Precision::F32 && ctx.has_int64());
                    let blocks = sol.rotated_blocks().expect("download").expect("assembled");
                    let err = max_rel(&blocks, &rot.values);
                    assert!(err <= tol, "rotate_blocks {dim}D {prec}: {err:e}");
                    let pre = sol.preconditioner_data().expect("download");
                    let cpu = BuiltPreconditioner::new(&e, pc);
                    let err = max_rel(&pre, cpu.data());
                    assert!(err <= 10.0 * tol, "precond {pc:?} {dim}D {prec}: {err:e}");
                    let r = sol.resources();
                    assert!(r.dispatches_of("rotate_blocks") >= 1);
                }
            }
        }
    }
}

/// The f32 difference form keeps a free body's translations: on kappa-1e6 (a free spring
/// grid, Ĥt = m t exactly for a translation t, m = λ_max/(κ − 1)) the f32 operator in the
/// difference form maps t to m t within a few f32 roundings of m t itself, while plain f32
/// blocks miss it by ~κ·ε_f32 of m t (each row's blocks, of size λ_max, cancel to m).
#[test]
fn f32_difference_form_keeps_the_translations() {
    let Some((ctx, _g)) = gpu() else { return };
    let case = stickslip::app::hard::conditioned(stickslip::app::hard::Size::Ci, 1e6, false);
    let e = case.eliminated();
    let n = e.ndof();
    for axis in 0..3 {
        let t: Vec<f64> = (0..n).map(|k| f64::from(k % 3 == axis)).collect();
        let mut want = vec![0.0; n];
        let mut work = vec![0.0; 2 * n];
        e.apply(&t, &mut want, &mut work);
        let mut errs = [0.0; 2];
        for (k, diff) in [false, true].into_iter().enumerate() {
            let prm = GpuParams {
                f32_difference: if diff {
                    DifferenceForm::On
                } else {
                    DifferenceForm::Off
                },
                ..params(Precision::F32, Preconditioner::Jacobi)
            };
            let mut sol = GpuSolver::new(ctx, &e, &prm).expect("solver");
            errs[k] = max_rel(&sol.apply_operator(&t).expect("matvec"), &want);
        }
        // The row sum S_i = m I is rounded once to f32: ε_f32 = 6e-8 relative; 1e-6
        // leaves room for the 2^s-free upload and the f32 products.
        assert!(
            errs[1] <= 1e-6,
            "difference form, axis {axis}: {:e}",
            errs[1]
        );
        // κ·ε_f32 = 0.06 expected; 1e-3 is far below it and far above the form's error.
        assert!(
            errs[0] >= 1e-3,
            "plain f32 blocks, axis {axis}: {:e}",
            errs[0]
        );
    }
    // The default (Auto) turns it on here. On a body pinned by sticky nodes it is on
    // where the device sums the form's rows in f64 (it keeps the bending modes there), and
    // off on an f32-only device, whose f32 sums keep only the translations.
    let uses = |e: &Eliminated| {
        let sol = GpuSolver::new(ctx, e, &params(Precision::F32, Preconditioner::Jacobi))
            .expect("solver");
        sol.resources().has_buffer("rowsum_f32")
    };
    assert!(uses(&e));
    let pinned = stickslip::app::hard::stiffness_contrast(stickslip::app::hard::Size::Ci, 1e4);
    assert_eq!(uses(&pinned.eliminated()), ctx.has_f64());
}

/// The device PCG's product q = Ĥx (H read in place in the world frame, p rotated at
/// rotated nodes) against the CPU's Ĥx on random systems with slip nodes, in f64, f32 and
/// f32 in the difference form. Bounds: f64 to a few roundings of the row sums (1e-13 of
/// max |Ĥx|); f32 to ε_f32 = 6e-8 per rounding of H, x and the rotations, summed over a
/// row's few dozen terms of either sign (2e-6, as the precision kernels' bound).
#[test]
fn pcg_product_matches_cpu_in_every_precision() {
    let Some((ctx, _g)) = gpu() else { return };
    for (dim, seed) in [(2, 1u64), (3, 2), (3, 5)] {
        let s = random_system(&SystemSpec::small(dim, seed));
        assert!(s.frames.has_rotation() && s.frames.has_constraints());
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let x = test_vector(e.ndof());
        let mut want = vec![0.0; x.len()];
        let mut work = vec![0.0; 2 * x.len()];
        e.apply(&x, &mut want, &mut work);
        for (prec, tol, diff) in [
            (Precision::F64, 1e-13, DifferenceForm::Off),
            (Precision::F32, 2e-6, DifferenceForm::Off),
            (Precision::F32, 2e-6, DifferenceForm::On),
        ] {
            let prm = GpuParams {
                f32_difference: diff,
                ..params(prec, Preconditioner::Jacobi)
            };
            let mut sol = PcgSolver::new(ctx, &e, &prm).expect("solver");
            assert_eq!(sol.difference_form(), diff == DifferenceForm::On);
            let err = max_rel(&sol.apply_operator(&x).expect("product"), &want);
            eprintln!("{dim}D seed {seed} {prec} {diff:?}: max error {err:.2e}");
            assert!(err <= tol, "{dim}D seed {seed} {prec} {diff:?}: {err:e}");
        }
    }
}

/// The device PCG's f32 difference form keeps a free body's translations, as the
/// precision kernels' does (`f32_difference_form_keeps_the_translations`, same bounds):
/// on kappa-1e6, Ĥt = m t for a translation t; the form maps t to S t (S_i = m I rounded
/// once to f32), plain f32 blocks miss by ~κ·ε_f32 of m t. Auto turns it on where the
/// device has f64 sums, and on a free body everywhere.
#[test]
fn pcg_f32_difference_form_keeps_the_translations() {
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
        let mut sol = GpuSolver::new(ctx, &e, &params(Precision::F64, Preconditioner::Jacobi))
            .expect("solver");
        let got = sol.apply_operator(&y).expect("matvec");
        assert!(max_rel(&got, &want) <= 1e-13);
    }
}

/// k iterations of the same PCG recurrence on the CPU, in f64.
fn cpu_pcg(
    e: &Eliminated,
    pc: Preconditioner,
    coarse: CoarseSpace,
    k: usize,
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
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
    (x, r, p)
}

/// The GPU's PCG updates (with and without the coarse correction on the translations,
/// whose Z_i = P_i V_iᵀ the kernels compute from the mask and the rotations of these
/// systems' slip nodes) follow the CPU recurrence to 1e-11: six f64 iterations on a
/// well-conditioned system lose a few hundred ulps at most.
#[test]
fn cg_update_kernels_and_reductions_match_cpu_recurrence() {
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
        let (x, r, p) = cpu_pcg(&e, pc, coarse, k);
        let prm = GpuParams {
            coarse,
            ..params(Precision::F64, pc)
        };
        let mut sol = GpuSolver::new(ctx, &e, &prm).expect("solver");
        let (gx, gr, gp) = sol.iterate(k).expect("iterate");
        for (name, a, b) in [("x", &gx, &x), ("r", &gr, &r), ("p", &gp, &p)] {
            let err = max_rel(a, b);
            assert!(
                err <= 1e-11,
                "{name} after {k} iterations ({dim}D, {pc:?}, coarse {coarse:?}): {err:e}"
            );
        }
        let res = sol.resources();
        // One chunk: 3 dispatches per iteration, plus the start (matvec, init, update_p).
        assert_eq!(res.dispatches_of("update_xrz"), k as u64);
        assert_eq!(res.dispatches_of("update_p"), k as u64 + 1);
        assert_eq!(res.dispatches_of("matvec"), k as u64 + 1);
        // Mixed: the inner f32 CG follows the same recurrence to f32 round-off.
        // (Also with the difference form of the f32 operator, on by default.)
        let prm = GpuParams {
            precision: Precision::Mixed,
            ..prm
        };
        let mut sol = GpuSolver::new(ctx, &e, &prm).expect("solver");
        let (gx, _, _) = sol.iterate(k).expect("iterate");
        let err = max_rel(&gx, &x);
        assert!(
            err <= 1e-4,
            "f32 inner x after {k} iterations (coarse {coarse:?}): {err:e}"
        );
    }
}

fn spring_frames(ms: &MassSpring) -> Frames {
    let d = ms.dim;
    let n = ms.n_nodes();
    let mut cs = Vec::new();
    let mut push = |node: usize, kind: ConstraintKind| {
        let label = format!("c{}", cs.len());
        cs.push(Constraint { node, kind, label });
    };
    push(
        0,
        ConstraintKind::Sticky {
            displacement: Some(vec![0.01; d]),
        },
    );
    let mut nrm = vec![1.0, 2.0];
    let mut dir = vec![1.0, -1.0];
    if d == 3 {
        nrm.push(-0.5);
        dir.push(0.3);
    }
    push(
        1,
        ConstraintKind::Plane {
            normal: nrm,
            offset: 0.02,
        },
    );
    push(
        n - 1,
        ConstraintKind::Line {
            direction: dir,
            offset: None,
        },
    );
    let mut ax = vec![0.0; d];
    ax[1] = 2.0;
    push(
        n / 2,
        ConstraintKind::Plane {
            normal: ax,
            offset: 0.0,
        },
    );
    Frames::build(d, n, &cs).expect("valid constraints")
}

#[test]
fn spring_kernel_matches_assembled_operator() {
    let Some((ctx, _g)) = gpu() else { return };
    for dim in [2, 3] {
        let ms = MassSpring::random_grid(dim, [4, 4, 3], 11 + dim as u64);
        let h = ms.assemble();
        let frames = spring_frames(&ms);
        assert!(frames.has_rotation());
        let xt: Vec<f64> = ms.positions.iter().map(|v| v + 0.05).collect();
        let g = ms.gradient(&xt);
        let e = Eliminated::new(&h, &g, &frames, ConstrainedDiagonal::Identity);
        let y = test_vector(e.ndof());
        let mut want = vec![0.0; y.len()];
        let mut work = vec![0.0; 2 * y.len()];
        e.apply(&y, &mut want, &mut work);
        for (prec, tol) in [(Precision::F64, 1e-13), (Precision::F32, 2e-6)] {
            for pc in [Preconditioner::Jacobi, Preconditioner::BlockJacobi] {
                let mut sol = GpuSolver::new_mass_spring(ctx, &ms, &g, &frames, &params(prec, pc))
                    .expect("solver");
                let got = sol.apply_operator(&y).expect("spring matvec");
                let err = max_rel(&got, &want);
                assert!(err <= tol, "spring matvec {dim}D {prec}: {err:e}");
                let pre = sol.preconditioner_data().expect("download");
                let err = max_rel(&pre, BuiltPreconditioner::new(&e, pc).data());
                assert!(
                    err <= 10.0 * tol,
                    "spring precond {dim}D {prec} {pc:?}: {err:e}"
                );
                let r = sol.resources();
                assert!(
                    !r.buffers.iter().any(|b| b.label.starts_with("blocks")),
                    "matrix-free assembles nothing"
                );
                assert_eq!(r.dispatches_of("rotate_blocks"), 0);
            }
        }
    }
}

/// The one block-Jacobi specification on blocks that are not SPD: the device PCG and the
/// precision kernels build, in f64 and f32, what the CPU's `block_jacobi_inverse` and
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
            let kernels = |prec| -> Vec<f64> {
                GpuSolver::new(ctx, &e, &params(prec, pc))
                    .expect("solver")
                    .preconditioner_data()
                    .expect("download")
            };
            for (&(prec, ulps), solver, got) in precisions.iter().flat_map(|p| {
                [
                    (p, "device PCG", device_pcg(p.0)),
                    (p, "precision kernels", kernels(p.0)),
                ]
            }) {
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
