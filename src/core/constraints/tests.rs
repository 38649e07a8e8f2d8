//! The constraint frames: orthonormal and spanning each constraint, planes combining into
//! lines and sticky nodes, redundant rows adding nothing and contradictions refused, bad
//! vectors rejected, the row reduction and the rotation round trip.

use super::*;
use rand::{Rng, SeedableRng};

fn c(node: usize, kind: ConstraintKind) -> Constraint {
    Constraint {
        node,
        kind,
        label: format!("c{node}"),
    }
}

fn check_orthonormal(f: &Frames, i: usize) {
    let d = f.dim;
    let v = f.rotation(i).unwrap();
    for a in 0..d {
        for b in 0..d {
            let s: f64 = (0..d).map(|k| v[k * d + a] * v[k * d + b]).sum();
            let e = if a == b { 1.0 } else { 0.0 };
            assert!((s - e).abs() < 1e-14, "VᵀV[{a}][{b}] = {s}");
        }
    }
}

#[test]
fn plane_frames_are_orthonormal_and_span_the_normal_even_near_e_x() {
    let mut rng = rand::rngs::StdRng::seed_from_u64(7);
    for trial in 0..200 {
        let n: Vec<f64> = if trial % 2 == 0 {
            // Within 1e-8 of e_x.
            vec![
                1.0,
                rng.random_range(-1e-8..1e-8),
                rng.random_range(-1e-8..1e-8),
            ]
        } else {
            (0..3).map(|_| rng.random_range(-1.0..1.0)).collect()
        };
        let f = Frames::build(
            3,
            1,
            &[c(
                0,
                ConstraintKind::Plane {
                    normal: n.clone(),
                    offset: 0.0,
                },
            )],
        )
        .unwrap();
        if f.rotation(0).is_none() {
            continue; // exactly axis-aligned: masked without rotation
        }
        check_orthonormal(&f, 0);
        let v = f.rotation(0).unwrap();
        let nn = unit(&n);
        // First column is n; the others are orthogonal to n.
        for k in 0..3 {
            assert!((v[k * 3] - nn[k]).abs() < 1e-15);
        }
        for col in 1..3 {
            let s: f64 = (0..3).map(|k| v[k * 3 + col] * nn[k]).sum();
            assert!(s.abs() < 1e-14);
        }
        assert_eq!(f.mask[0], 0b001);
    }
}

#[test]
fn axis_aligned_slip_masks_without_rotation() {
    let f = Frames::build(
        3,
        2,
        &[
            c(
                0,
                ConstraintKind::Plane {
                    normal: vec![0.0, 2.0, 0.0],
                    offset: 0.0,
                },
            ),
            c(
                1,
                ConstraintKind::Line {
                    direction: vec![0.0, 0.0, -3.0],
                    offset: None,
                },
            ),
        ],
    )
    .unwrap();
    assert!(!f.has_rotation());
    assert_eq!(f.mask, vec![0b010, 0b011]);
}

#[test]
fn two_planes_make_a_line_three_make_sticky() {
    let p = |n: Vec<f64>| ConstraintKind::Plane {
        normal: n,
        offset: 0.0,
    };
    let f = Frames::build(
        3,
        1,
        &[c(0, p(vec![1.0, 1.0, 0.0])), c(0, p(vec![0.0, 1.0, 1.0]))],
    )
    .unwrap();
    assert_eq!(f.mask[0].count_ones(), 2);
    check_orthonormal(&f, 0);
    // The free direction is orthogonal to both normals.
    let v = f.rotation(0).unwrap();
    let t = [v[2], v[5], v[8]];
    assert!(dot(&t, &[1.0, 1.0, 0.0]).abs() < 1e-14);
    assert!(dot(&t, &[0.0, 1.0, 1.0]).abs() < 1e-14);
    let f = Frames::build(
        3,
        1,
        &[
            c(0, p(vec![1.0, 1.0, 0.0])),
            c(0, p(vec![0.0, 1.0, 1.0])),
            c(0, p(vec![1.0, 0.0, 1.0])),
        ],
    )
    .unwrap();
    assert_eq!(f.mask[0], 0b111);
    assert!(!f.has_rotation());
}

#[test]
fn nearly_redundant_rows_add_nothing_and_contradictions_are_errors() {
    let a = 1e-10;
    let rows = ConstraintKind::Rows {
        rows: vec![vec![1.0, 2.0, 0.5], vec![1.0 + a, 2.0, 0.5]],
        values: vec![0.3, 0.3],
    };
    let f = Frames::build(3, 1, &[c(0, rows)]).unwrap();
    assert_eq!(f.mask[0].count_ones(), 1);
    let bad = ConstraintKind::Rows {
        rows: vec![vec![1.0, 2.0, 0.5], vec![2.0, 4.0, 1.0]],
        values: vec![0.3, 0.3],
    };
    let e = Frames::build(3, 1, &[c(0, bad)]).unwrap_err();
    assert!(e.problem.contains("contradictory"), "{e}");
}

/// Three rows, the third an exact combination of the first two, with consistent
/// values: nalgebra 0.34's SVD factored this block with an error of 5e-2 and made it
/// look contradictory; the frame must be a line with an exact lift.
#[test]
fn dependent_rows_with_consistent_values_form_a_line() {
    let rows = vec![
        vec![
            -0.8903906045381308,
            0.44743133743890545,
            -0.08372436698986958,
        ],
        vec![0.1787047698398585, -0.7666862336085959, -0.6166496772329882],
        vec![
            -0.5121120358653778,
            -0.4637409631693257,
            -0.7229699729591847,
        ],
    ];
    let values = vec![
        -0.04979598171710053,
        0.13127464870145872,
        0.10055917227601849,
    ];
    let f = Frames::build(
        3,
        1,
        &[c(
            0,
            ConstraintKind::Rows {
                rows: rows.clone(),
                values: values.clone(),
            },
        )],
    )
    .unwrap();
    assert_eq!(f.mask[0].count_ones(), 2);
    check_orthonormal(&f, 0);
    for (r, v) in rows.iter().zip(&values) {
        assert!((dot(r, &f.lift[..3]) - v).abs() < 1e-15);
    }
}

#[test]
fn bad_vectors_are_rejected() {
    for (kind, want) in [
        (
            ConstraintKind::Plane {
                normal: vec![0.0, 0.0, 0.0],
                offset: 0.0,
            },
            "zero",
        ),
        (
            ConstraintKind::Plane {
                normal: vec![f64::NAN, 0.0, 1.0],
                offset: 0.0,
            },
            "not finite",
        ),
        (
            ConstraintKind::Line {
                direction: vec![1.0, 0.0],
                offset: None,
            },
            "expected 3",
        ),
    ] {
        let e = Frames::build(3, 1, &[c(0, kind)]).unwrap_err();
        assert!(e.problem.contains(want), "{e}");
    }
    let e =
        Frames::build(3, 1, &[c(5, ConstraintKind::Sticky { displacement: None })]).unwrap_err();
    assert!(e.problem.contains("out of range"));
}

/// The QR reduction keeps what the SVD needs: RᵀR = AᵀA and Rᵀc = Aᵀvals (so A and R
/// share singular values and right singular vectors, and the lift is the same).
#[test]
fn householder_reduction_preserves_the_normal_matrix_and_values() {
    let mut rng = rand::rngs::StdRng::seed_from_u64(11);
    for (dim, k) in [(3, 4), (3, 50), (2, 3), (2, 200)] {
        let rows: Vec<[f64; 3]> = (0..k)
            .map(|_| {
                let mut r = [0.0; 3];
                for x in r.iter_mut().take(dim) {
                    *x = rng.random_range(-1.0..1.0);
                }
                r
            })
            .collect();
        let vals: Vec<f64> = (0..k).map(|_| rng.random_range(-1.0..1.0)).collect();
        let (r, c) = householder_reduce(dim, &rows, &vals);
        for a in 0..dim {
            for b in 0..dim {
                let ata: f64 = rows.iter().map(|x| x[a] * x[b]).sum();
                let rtr: f64 = (0..dim).map(|i| r[i][a] * r[i][b]).sum();
                assert!(
                    (ata - rtr).abs() < 1e-12 * k as f64,
                    "{dim} {k}: {ata} {rtr}"
                );
            }
            let atv: f64 = rows.iter().zip(&vals).map(|(x, v)| x[a] * v).sum();
            let rtc: f64 = (0..dim).map(|i| r[i][a] * c[i]).sum();
            assert!(
                (atv - rtc).abs() < 1e-12 * k as f64,
                "{dim} {k}: {atv} {rtc}"
            );
            // Upper triangular.
            for row in r.iter().take(dim).skip(a + 1) {
                assert_eq!(row[a], 0.0);
            }
        }
    }
}

#[test]
fn rotation_round_trip_is_identity() {
    let f = Frames::build(
        3,
        2,
        &[c(
            1,
            ConstraintKind::Plane {
                normal: vec![0.3, -0.4, 0.8],
                offset: 0.0,
            },
        )],
    )
    .unwrap();
    let x = [1.0, 2.0, 3.0, -1.0, 0.5, 0.25];
    let mut y = [0.0; 6];
    let mut z = [0.0; 6];
    f.to_frame(&x, &mut y);
    f.from_frame(&y, &mut z);
    for k in 0..6 {
        assert!((x[k] - z[k]).abs() < 1e-15);
    }
}
