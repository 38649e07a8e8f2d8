//! Dispatch sizes under a forced per-dimension workgroup limit (`gpu::launch`): small
//! systems then take the two-dimensional and grid-stride launches of systems above
//! 65,535 workgroups, and every result must be the same bits as without the limit. The
//! per-item kernels compute each item by the same operations whatever invocation runs
//! it, and the reductions keep exactly their workgroups (laid out in two dimensions), so
//! the two runs differ in launch geometry only.

use stickslip::cases::generate::{random_system, SystemSpec};
use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
use stickslip::gpu::{GpuParams, PcgSolver, Precision};
use stickslip::solve::cg::Preconditioner;
use stickslip::solve::coarse::CoarseSpace;

mod common;
use common::gpu::gpu;

fn bits(v: &[f64]) -> Vec<u64> {
    v.iter().map(|x| x.to_bits()).collect()
}

/// `solve --solver gpu` in every precision (the device PCG; 2D and 3D; f64, f32, mixed
/// with its refinement kernels; block-Jacobi and Jacobi with the aggregate coarse space)
/// with at most 8 workgroups per dimension against the adapter's limit: the segmented
/// reductions, the per-row and per-DOF kernels run in two dimensions and grid-stride.
#[test]
fn a_forced_dispatch_limit_gives_the_same_bits_in_every_solver() {
    let Some((ctx, _g)) = gpu() else { return };
    let forced = ctx.with_dispatch_limit(Some(8));
    assert_eq!(forced.launch().per_dim, 8);
    let mut cases = 0;
    for dim in [3usize, 2] {
        let s = random_system(&SystemSpec::with_nodes(dim, 1000, 11));
        let e = Eliminated::new(&s.h, &s.g, &s.frames, ConstrainedDiagonal::Identity);
        let precisions: &[Precision] = if ctx.has_f64() {
            &[Precision::F64, Precision::F32, Precision::Mixed]
        } else {
            &[Precision::F32]
        };
        for &precision in precisions {
            for (preconditioner, coarse) in [
                (Preconditioner::BlockJacobi, CoarseSpace::None),
                (Preconditioner::Jacobi, CoarseSpace::Aggregates),
            ] {
                // f32 arithmetic stagnates near 1e-7 on these systems.
                let tol = if precision == Precision::F32 {
                    1e-5
                } else {
                    1e-8
                };
                let p = GpuParams {
                    precision,
                    tol,
                    max_iters: 5_000,
                    preconditioner,
                    coarse,
                    ..Default::default()
                };
                let what = format!("{dim}D {precision} coarse {}", coarse.name());
                let mut a = PcgSolver::new(ctx, &e, &p).expect("solver builds");
                let mut b = PcgSolver::new(&forced, &e, &p).expect("forced solver builds");
                let (ra, rb) = (a.solve().expect("solves"), b.solve().expect("solves"));
                assert!(ra.info.relative_residual <= tol, "{what}: {:?}", ra.info);
                assert_eq!(ra.info.iterations, rb.info.iterations, "{what}");
                assert!(bits(&ra.y) == bits(&rb.y), "{what}: y differs");
                assert!(bits(&ra.dx) == bits(&rb.dx), "{what}: Δx differs");
                eprintln!(
                    "{what}: {} iterations, rel. residual {:.3e}, bitwise equal",
                    ra.info.iterations, ra.info.relative_residual
                );
                cases += 1;
            }
        }
    }
    assert!(cases >= 4);
}

/// The device Newton loop (element terms, assembly, Newton operations, device CG) on a
/// 3D (`twist`, tetrahedra) and a 2D scene (`compress`, triangles, plane slip), run by the
/// command line with `STICKSLIP_MAX_WORKGROUPS_PER_DIM=2` and without: the step records
/// (but the seconds column) and every frame are the same bytes.
#[test]
fn the_device_newton_loop_gives_the_same_bytes_under_a_forced_limit() {
    if gpu().is_none() {
        return;
    }
    // A test binary carried to another machine (scripts/gpu-eval.sh) runs the binary
    // carried beside it, named by STICKSLIP_BIN; here, the one cargo built.
    let bin = std::env::var("STICKSLIP_BIN")
        .unwrap_or_else(|_| env!("CARGO_BIN_EXE_stickslip").to_string());
    let root = std::env::temp_dir().join(format!("stickslip-launch-{}", std::process::id()));
    for scene in ["twist", "compress"] {
        let run = |limit: Option<&str>| -> std::path::PathBuf {
            let out = root.join(format!("{scene}-{}", limit.unwrap_or("none")));
            let mut cmd = std::process::Command::new(&bin);
            cmd.args(["run", scene, "--steps", "1", "--newton", "gpu", "--quiet"])
                .args(["--overwrite", "--out"])
                .arg(&out);
            match limit {
                Some(l) => cmd.env("STICKSLIP_MAX_WORKGROUPS_PER_DIM", l),
                None => cmd.env_remove("STICKSLIP_MAX_WORKGROUPS_PER_DIM"),
            };
            let o = cmd.output().expect("runs");
            assert!(
                o.status.success(),
                "{scene} (limit {limit:?}): {}",
                String::from_utf8_lossy(&o.stderr)
            );
            out
        };
        let (a, b) = (run(None), run(Some("2")));
        // linear_seconds (column 5) is a timing.
        let steps = |d: &std::path::Path| -> Vec<String> {
            std::fs::read_to_string(d.join("steps.csv"))
                .expect("steps.csv")
                .lines()
                .map(|l| {
                    let mut f: Vec<&str> = l.split(',').collect();
                    f.remove(4);
                    f.join(",")
                })
                .collect()
        };
        let (sa, sb) = (steps(&a), steps(&b));
        assert!(sa.len() >= 2, "{scene}: {sa:?}");
        assert_eq!(sa, sb, "{scene}: step records differ");
        let mut frames = 0;
        for f in std::fs::read_dir(a.join("frames")).expect("frames") {
            let f = f.expect("entry").path();
            let name = f.file_name().expect("name");
            let other = std::fs::read(b.join("frames").join(name)).expect("same frame");
            assert!(
                std::fs::read(&f).expect("frame") == other,
                "{scene}: {name:?} differs"
            );
            frames += 1;
        }
        assert!(frames >= 2, "{scene}: {frames} frames");
    }
    let _ = std::fs::remove_dir_all(&root);
}
