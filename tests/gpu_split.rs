//! H's values larger than the storage binding limit are split into row chunks, one buffer
//! each, and every kernel that reads them runs once per chunk. `GpuParams::binding_limit`
//! lowers the limit so that ~1,000-node systems take that path on any adapter; the
//! chunked solve must equal the one-chunk solve bit for bit: every row is computed by the
//! same operations on the same values, and a reduction segment cut by a chunk's end
//! carries each invocation's running sum to the next chunk's dispatch, so the two differ
//! in addresses only. A system over the device memory is refused before anything is
//! allocated.

use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::gpu::{DifferenceForm, GpuError, GpuParams, PcgSolver, Precision, SolveOutcome};
use stickslip::solve::cg::Preconditioner;
use stickslip::solve::coarse::CoarseSpace;

mod common;
use common::gpu::gpu;

/// The solution and the values chunks (the solver's level, mixed's f64 level).
fn solve(
    ctx: &stickslip::gpu::GpuContext,
    e: &Eliminated,
    p: &GpuParams,
) -> (SolveOutcome, (usize, Option<usize>)) {
    let mut s = PcgSolver::new(ctx, e, p).expect("solver builds");
    let out = s.solve().expect("solve converges");
    (out, s.values_chunks())
}

fn bits(v: &[f64]) -> Vec<u64> {
    v.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn chunked_operators_give_the_one_chunk_solution_bit_for_bit() {
    let Some((ctx, _g)) = gpu() else { return };
    let mut cases = 0;
    for dim in [3usize, 2] {
        // The realistic mix has sticky, moved and tilted-plane slip nodes: masking, the
        // block rotation and the preconditioner build all run per chunk.
        let s = random_system(&SystemSpec::with_nodes(dim, 1000, 7));
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        assert!(s.frames.has_rotation() && s.frames.has_constraints());
        // f32 values (4d² bytes a block) in at least three pieces, f64 in more.
        let limit = s.h.nnz_blocks() as u64 * (4 * dim * dim) as u64 / 3 / 16 * 16;
        let precisions: &[Precision] = if ctx.has_f64() {
            &[Precision::F64, Precision::F32, Precision::Mixed]
        } else {
            &[Precision::F32]
        };
        for &precision in precisions {
            for (k, coarse) in [CoarseSpace::None, CoarseSpace::Aggregates]
                .into_iter()
                .enumerate()
            {
                // f32 arithmetic stagnates near 1e-7 on these systems.
                let tol = if precision == Precision::F32 {
                    1e-5
                } else {
                    1e-8
                };
                let base = GpuParams {
                    precision,
                    tol,
                    max_iters: 5_000,
                    coarse,
                    preconditioner: if k == 0 {
                        Preconditioner::BlockJacobi
                    } else {
                        Preconditioner::Jacobi
                    },
                    ..Default::default()
                };
                let split = GpuParams {
                    binding_limit: Some(limit),
                    ..base.clone()
                };
                let (a, ra) = solve(ctx, &e, &base);
                let (b, rb) = solve(ctx, &e, &split);
                let what = format!("{dim}D {precision} coarse {}", coarse.name());
                assert_eq!(ra.0, 1, "{what}: one chunk without the cap");
                assert!(ra.1.is_none_or(|c| c == 1), "{what}: {ra:?}");
                assert!(rb.0 >= 3, "{what}: {} chunks under the cap", rb.0);
                if precision == Precision::Mixed {
                    // The f64 level of the outer residual is split too.
                    assert!(rb.1.is_some_and(|c| c >= 3), "{what}: f64 level {rb:?}");
                }
                assert!(a.info.relative_residual <= tol, "{what}: {a:?}");
                assert_eq!(a.info.iterations, b.info.iterations, "{what}");
                assert_eq!(a.info.outer_refinements, b.info.outer_refinements, "{what}");
                assert!(bits(&a.y) == bits(&b.y), "{what}: y differs");
                assert!(bits(&a.dx) == bits(&b.dx), "{what}: Δx differs");
                eprintln!(
                    "{what}: {} iterations, rel. residual {:.3e}, {} chunks, bitwise equal",
                    a.info.iterations, a.info.relative_residual, rb.0
                );
                cases += 1;
            }
        }
    }
    assert!(cases >= 4);
}

/// The device memory a solver needs is computed before anything is allocated
/// ([`PcgSolver::memory_needed`]): with `memory_limit` at it the solver builds; one byte
/// below, f64 and f32 are refused with one line naming both numbers, and mixed builds
/// without its f64 level (its residual then formed on the host).
#[test]
fn a_system_larger_than_device_memory_is_refused_with_the_exact_need() {
    let Some((ctx, _g)) = gpu() else { return };
    let s = random_system(&SystemSpec::with_nodes(3, 1000, 7));
    let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
    let split = s.h.nnz_blocks() as u64 * 36 / 3 / 16 * 16;
    let precisions: &[Precision] = if ctx.has_f64() {
        &[Precision::F64, Precision::F32, Precision::Mixed]
    } else {
        &[Precision::F32]
    };
    for &precision in precisions {
        for (coarse, pc, limit) in [
            (CoarseSpace::Aggregates, Preconditioner::BlockJacobi, None),
            (
                CoarseSpace::Translations,
                Preconditioner::Jacobi,
                Some(split),
            ),
            (CoarseSpace::None, Preconditioner::None, None),
        ] {
            let p = GpuParams {
                precision,
                coarse,
                preconditioner: pc,
                binding_limit: limit,
                ..Default::default()
            };
            let what = format!("{precision} {} {pc:?} cap {limit:?}", coarse.name());
            let total = PcgSolver::memory_needed(ctx, &e, &p).expect("a plan");
            let tight = GpuParams {
                memory_limit: Some(total),
                ..p.clone()
            };
            let built = PcgSolver::new(ctx, &e, &tight).expect("builds at its need");
            if precision == Precision::Mixed {
                assert!(built.has_f64_level(), "{what}");
            }
            drop(built);
            let short = GpuParams {
                memory_limit: Some(total - 1),
                ..p.clone()
            };
            match PcgSolver::new(ctx, &e, &short) {
                Ok(s) if precision == Precision::Mixed => {
                    assert!(
                        !s.has_f64_level(),
                        "{what}: the f64 level in {} bytes",
                        total - 1
                    )
                }
                Err(e @ GpuError::DoesNotFit { need, limit, .. })
                    if precision != Precision::Mixed =>
                {
                    assert_eq!((need, limit), (total, total - 1), "{what}: {e}");
                    let m = e.to_string();
                    assert!(m.contains(stickslip::gpu::DOES_NOT_FIT), "{what}: {m}");
                    assert!(!m.contains('\n'));
                    // The facade's error: the device's, still telling its numbers.
                    let f: stickslip::Error = e.into();
                    assert!(
                        matches!(
                            f,
                            stickslip::Error::Gpu(GpuError::DoesNotFit { need, limit, .. })
                                if need == total && limit == total - 1
                        ),
                        "{what}: {f:?}"
                    );
                }
                Err(other) => panic!("{what}: {other}"),
                Ok(_) => panic!("{what}: accepted {total} bytes in {}", total - 1),
            }
        }
    }
}

/// The device PCG (what `solve --solver gpu` runs in f64 and f32) refuses a system over
/// the device memory in force before it allocates anything, in one line naming what it
/// needs: more than H's values alone (8 or 4 bytes per entry).
#[test]
fn the_device_pcg_refuses_a_system_over_device_memory() {
    let Some((ctx, _g)) = gpu() else { return };
    let s = random_system(&SystemSpec::with_nodes(3, 1000, 7));
    let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
    for (precision, entry) in [(Precision::F64, 8u64), (Precision::F32, 4)] {
        if precision == Precision::F64 && !ctx.has_f64() {
            eprintln!("SKIP the device PCG in f64: no SHADER_F64");
            continue;
        }
        let h_bytes = entry * s.h.values.len() as u64;
        let p = GpuParams {
            precision,
            ..Default::default()
        };
        assert!(PcgSolver::new(ctx, &e, &p).is_ok());
        let short = GpuParams {
            memory_limit: Some(h_bytes),
            ..p
        };
        match PcgSolver::new(ctx, &e, &short) {
            Err(e @ GpuError::DoesNotFit { need, limit, .. }) => {
                let m = e.to_string();
                assert!(m.contains(stickslip::gpu::DOES_NOT_FIT), "{m}");
                assert!(!m.contains('\n'));
                eprintln!("{precision}: {m}");
                assert_eq!(limit, h_bytes, "{m}");
                assert!(need > h_bytes, "{precision}: {need} ≤ {h_bytes}");
            }
            Err(other) => panic!("{precision}: {other}"),
            Ok(_) => panic!("{precision}: accepted a system in {h_bytes} bytes"),
        }
    }
}

/// The device PCG's memory plan is what it allocates, to the byte: the bytes every buffer
/// of [`PcgSolver::new`] takes (`GpuContext::allocated_bytes`) equal
/// [`PcgSolver::memory_needed`], in f64 and in f32 with and without the difference form,
/// with H in one buffer and split over several, with the translations' coarse space and
/// with the multilevel levels.
#[test]
fn the_device_pcgs_memory_plan_is_what_it_allocates() {
    let Some((ctx, _g)) = gpu() else { return };
    let s = random_system(&SystemSpec::with_nodes(3, 1000, 7));
    let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
    let base = GpuParams {
        coarse: CoarseSpace::Translations,
        ..Default::default()
    };
    let mut cases = vec![
        GpuParams {
            precision: Precision::F32,
            f32_difference: DifferenceForm::Off,
            ..base.clone()
        },
        GpuParams {
            precision: Precision::F32,
            f32_difference: DifferenceForm::On,
            binding_limit: Some(64 * 1024),
            ..base.clone()
        },
    ];
    if ctx.has_f64() {
        cases.push(GpuParams {
            precision: Precision::F64,
            ..base.clone()
        });
        cases.push(GpuParams {
            precision: Precision::F64,
            binding_limit: Some(64 * 1024),
            coarse: CoarseSpace::None,
            preconditioner: Preconditioner::Multilevel,
            ..base.clone()
        });
    }
    for p in &cases {
        let plan = PcgSolver::memory_needed(ctx, &e, p).expect("a plan");
        let before = ctx.allocated_bytes();
        let solver = PcgSolver::new(ctx, &e, p).expect("solver");
        let allocated = ctx.allocated_bytes() - before;
        eprintln!(
            "{} {:?} binding limit {:?} {:?}: plan {plan} B, allocated {allocated} B",
            p.precision, p.f32_difference, p.binding_limit, p.preconditioner
        );
        assert_eq!(allocated, plan);
        drop(solver);
    }
}
