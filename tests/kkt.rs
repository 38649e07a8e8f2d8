//! The elimination against the constrained problem itself (docs/method.md, "The
//! constrained Newton step" and "Checks that keep the math honest").
//!
//! For 200 seeded random systems (2D and 3D, mesh-like block sparsity, every constraint
//! kind mixed, normals within 1e-8 of e_x, redundant rows, prescribed values) the dense
//! KKT system [H Bᵀ; B 0][Δx; λ] = [−g; p] is solved by an SVD pseudo-inverse (it is
//! singular where rows are redundant; Δx and Bᵀλ are still unique) and compared with:
//! the oracle's Δx (≤ 1e-9 relative), BΔx = p (≤ 1e-12·‖Δx‖), the reactions f = Bᵀλ
//! (≤ 1e-8 relative), and the CPU CG at tolerance 1e-12 (≤ 1e-8 relative).
//!
//! Why these tolerances hold: the generated Hessians have condition numbers of order
//! 1e2–1e3, so a backward-stable solve loses about 3 digits of the 16 available.

use nalgebra::{DMatrix, DVector};
use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::core::constraints::Frames;
use stickslip::core::elimination::{norm2, reactions, ConstrainedDiagonal, Eliminated};
use stickslip::solve::cg::{self, CgParams, Preconditioner};
use stickslip::solve::oracle;

mod common;
use common::kkt::{dense_kkt, global_b};

fn rel(a: &[f64], b: &DVector<f64>) -> f64 {
    let num: f64 = a
        .iter()
        .zip(b.iter())
        .map(|(x, y)| (x - y) * (x - y))
        .sum::<f64>()
        .sqrt();
    num / b.norm()
}

#[test]
fn oracle_and_cg_match_the_dense_kkt_solve_on_200_random_systems() {
    let mut worst = [0.0f64; 4];
    let mut rotated_nodes = 0;
    let mut constrained = 0;
    for case in 0..200u64 {
        let dim = if case % 2 == 0 { 2 } else { 3 };
        let spec = SystemSpec::small(dim, 1000 + case);
        let s = random_system(&spec);
        let n = s.h.n;
        rotated_nodes += s.frames.rot_nodes.len();
        constrained += s.frames.constrained_dofs();
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let (y, info) = oracle::solve(&e).expect("oracle");
        assert!(
            info.relative_residual < 1e-12,
            "case {case}: residual {}",
            info.relative_residual
        );
        let dx = e.recover(&y);
        let (b, p) = global_b(dim, n, &s.constraints);
        let kkt = dense_kkt(&s.h.to_dense(), &s.g, &b, &p);

        let err = rel(&dx, &kkt.dx);
        assert!(
            err <= 1e-9,
            "case {case} (dim {dim}): oracle vs KKT {err:e}"
        );

        let bdx = &b * DVector::from_column_slice(&dx) - &p;
        let dxn = DVector::from_column_slice(&dx).norm();
        let cons = bdx.norm() / dxn;
        assert!(cons <= 1e-12, "case {case}: ‖BΔx − p‖/‖Δx‖ = {cons:e}");

        let f = reactions(&s.h, &s.g, &dx);
        let rerr = rel(&f, &kkt.bt_lambda);
        assert!(rerr <= 1e-8, "case {case}: reactions vs Bᵀλ {rerr:e}");

        let params = CgParams {
            tol: 1e-12,
            preconditioner: if case % 3 == 0 {
                Preconditioner::BlockJacobi
            } else {
                Preconditioner::Jacobi
            },
            ..Default::default()
        };
        let (ycg, cginfo) = cg::solve(&e, &params).expect("cg");
        assert!(cginfo.relative_residual <= 1e-12);
        let cgerr = rel(&e.recover(&ycg), &kkt.dx);
        assert!(cgerr <= 1e-8, "case {case}: CG vs KKT {cgerr:e}");

        for (w, v) in worst.iter_mut().zip([err, cons, rerr, cgerr]) {
            *w = w.max(v);
        }
    }
    // The mix must really exercise rotations and constraints.
    assert!(rotated_nodes > 500, "only {rotated_nodes} rotated nodes");
    assert!(constrained > 1000);
    println!(
        "worst over 200 systems: oracle {:.2e}, constraints {:.2e}, reactions {:.2e}, CG {:.2e}",
        worst[0], worst[1], worst[2], worst[3]
    );
}

/// Seed eq. 10: remove the constrained DOFs (in the node frames) and solve H_UU Δx_U =
/// −g_U − H_UB Δx_B densely; the in-place masked system must give the same Δx.
#[test]
fn reduced_system_equals_in_place_masked_system() {
    let mut worst = 0.0f64;
    for case in 0..40u64 {
        let dim = 2 + (case % 2) as usize;
        let s = random_system(&SystemSpec::small(dim, 5000 + case));
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let (y, _) = oracle::solve(&e).expect("oracle");
        let dx = e.recover(&y);

        // Reduced system in frame coordinates: H̃ = VᵀHV, x̃_B = VᵀΔx_p.
        let nd = s.h.ndof();
        let vthv = stickslip::core::elimination::rotate_blocks(&s.h, &s.frames).to_dense();
        let mut gt = vec![0.0; nd];
        s.frames.to_frame(&s.g, &mut gt);
        let mut lift_t = vec![0.0; nd];
        s.frames.to_frame(&s.frames.lift, &mut lift_t);
        let free: Vec<usize> = (0..nd)
            .filter(|&k| s.frames.is_free(k / dim, k % dim))
            .collect();
        let bound: Vec<usize> = (0..nd)
            .filter(|&k| !s.frames.is_free(k / dim, k % dim))
            .collect();
        let huu = DMatrix::from_fn(free.len(), free.len(), |r, c| vthv[(free[r], free[c])]);
        let mut rhs = DVector::from_fn(free.len(), |r, _| -gt[free[r]]);
        for (r, &u) in free.iter().enumerate() {
            for &bdof in &bound {
                rhs[r] -= vthv[(u, bdof)] * lift_t[bdof];
            }
        }
        let yu = huu.cholesky().expect("H_UU is SPD").solve(&rhs);
        let mut yt = lift_t.clone();
        for (r, &u) in free.iter().enumerate() {
            yt[u] = yu[r];
        }
        let mut dx_reduced = vec![0.0; nd];
        s.frames.from_frame(&yt, &mut dx_reduced);
        let err = rel(&dx, &DVector::from_column_slice(&dx_reduced));
        worst = worst.max(err);
        assert!(err <= 1e-12, "case {case}: reduced vs masked {err:e}");
    }
    println!("worst reduced-vs-masked relative difference over 40 systems: {worst:.2e}");
}

/// Constrained components come out exactly as prescribed: the rotation is exact where
/// docs/method.md says it is (sticky nodes and axis-aligned slips carry no rotation at
/// all).
#[test]
fn constrained_components_are_exact() {
    for case in 0..20u64 {
        let dim = 2 + (case % 2) as usize;
        let s = random_system(&SystemSpec::small(dim, 9000 + case));
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let (y, _) = oracle::solve(&e).expect("oracle");
        for i in 0..s.h.n {
            for a in 0..dim {
                if !s.frames.is_free(i, a) {
                    assert_eq!(y[i * dim + a], 0.0, "case {case} node {i} comp {a}");
                }
            }
            if s.frames.mask[i] == (1 << dim) - 1 {
                // Sticky: Δx is the prescribed displacement to the bit.
                let dx = e.recover(&y);
                for a in 0..dim {
                    assert_eq!(dx[i * dim + a], s.frames.lift[i * dim + a]);
                }
            }
        }
    }
}

#[test]
fn frames_of_a_generated_system_need_no_rotation_without_slip() {
    let mut spec = SystemSpec::with_nodes(3, 1000, 3);
    spec.mix = stickslip::cases::generate::ConstraintMix::None;
    let s = random_system(&spec);
    assert!(!s.frames.has_rotation());
    assert!(!s.frames.has_constraints());
    let f = Frames::unconstrained(3, s.h.n);
    assert_eq!(f, s.frames);
}

/// The matrix-free product with Ĥ equals the product with the assembled Ĥ (to 1e-13 of
/// the result's norm: both sum the same few products per entry in different orders).
#[test]
fn matrix_free_apply_equals_assembled_product() {
    for (dim, seed) in [(2, 1u64), (3, 2), (3, 3)] {
        let s = random_system(&SystemSpec::small(dim, seed));
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let a = e.assemble();
        let n = s.h.ndof();
        let y: Vec<f64> = (0..n).map(|k| ((k * 7919) % 13) as f64 - 6.0).collect();
        let mut o1 = vec![0.0; n];
        let mut o2 = vec![0.0; n];
        let mut w = vec![0.0; 2 * n];
        e.apply(&y, &mut o1, &mut w);
        a.matvec(&y, &mut o2);
        let scale = norm2(&o1);
        for k in 0..n {
            assert!(
                (o1[k] - o2[k]).abs() <= 1e-13 * scale,
                "{k}: {} vs {}",
                o1[k],
                o2[k]
            );
        }
        assert!(a.check_symmetric().is_ok());
    }
}
