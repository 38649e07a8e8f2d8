//! The device-assembled Newton matrix split into several buffers of consecutive block rows
//! (`GpuAssembly::with_binding_limit` forces a small limit on small meshes) against the
//! same matrix in one buffer, on a 3D box of tetrahedra and a 2D rectangle of triangles:
//! neo-Hookean elements, inertia, gravity and a half-space barrier, sticky nodes, slip
//! nodes on a slanted plane (rotated frames) and on an axis-aligned plane (masked), and
//! moving-penalty terms on free nodes.
//!
//! Every block receives the same additions in the same order whatever the split, the CG's
//! product sums each row as one buffer does, and its reductions carry each thread's
//! running sum across the chunks' dispatches, so everything compared is required to be the
//! same bits:
//! - the assembled H and g, and the assembled product with one vector;
//! - H and g after `NewtonOps::add_moving`;
//! - `DeviceCg`'s Δx and iteration count, for Jacobi and block Jacobi, without and with
//!   the coarse correction on the translations (whose E is reduced per chunk too).
//!   With the aggregates, the rows' E sums are written per chunk and summed after.
//!
//! A second build also splits the element terms (`GpuElements::with_binding_limit`), so
//! that node terms' chunks and values chunks cut the nodes at different places.
//!
//! Every test shares one device (tests/common/gpu.rs); sizes are small for lavapipe.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use stickslip::core::constraints::{Constraint, Frames};
use stickslip::gpu::pcg::DeviceCgParams;
use stickslip::gpu::{GpuContext, GpuError, Precision};
use stickslip::sim::device::assembly::GpuAssembly;
use stickslip::sim::device::elements::{ElementKernels, GpuElements, TermKind};
use stickslip::sim::device::newton_ops::conditions::MovingTerm;
use stickslip::sim::device::newton_ops::NewtonOps;
use stickslip::sim::energy::barrier::{Barrier, HalfSpace};
use stickslip::sim::energy::{ElementSet, Law, Model, NeoHookean};
use stickslip::sim::mesh;
use stickslip::sim::scene::BcShape;
use stickslip::solve::cg::Preconditioner;
use stickslip::solve::coarse::CoarseSpace;

mod common;
use common::gpu::gpu;

/// h² of a time step (not a power of two, so the scaling rounds).
const SCALE: f64 = 1.0 / 30.0 / 30.0;
const TOL: f64 = 1e-10;

struct Case {
    model: Model,
    barrier: Barrier,
    planes: Vec<HalfSpace>,
    x: Vec<f64>,
    x_tilde: Vec<f64>,
    frames: Frames,
    moving: Vec<MovingTerm>,
}

/// A 3D box (4×4×3 cells, 100 nodes) or a 2D rectangle (8×6 cells, 63 nodes; `large`:
/// 130×128 cells, 16,899 nodes, more than the CG's 256 workgroups of 64 threads, so that
/// threads sum rows of several chunks) deformed at random; sticky at x = 0, slip on a slanted plane at the bottom, slip on the plane
/// x = const at the far side; a half-space near the bottom; moving penalties (a sticky
/// anchor and a plane) on two free nodes.
fn case(d: usize, seed: u64, large: bool) -> Case {
    let mut rng = StdRng::seed_from_u64(seed);
    let (m, len) = if d == 2 {
        let cells = if large { [130, 128] } else { [8, 6] };
        (mesh::rectangle(2, [1.0, 0.7], cells), 1.0)
    } else {
        (mesh::cuboid([1.0, 0.8, 0.6], [4, 4, 3]), 1.0)
    };
    let n = m.n_nodes();
    let x: Vec<f64> =
        m.x.iter()
            .map(|v| v + rng.random_range(-0.01..0.01))
            .collect();
    let nh = NeoHookean::new(&m, 1e5, 0.35, Law::StableNeoHookean).expect("valid rest elements");
    let mass: Vec<f64> = (0..n).map(|_| rng.random_range(0.5..2.0)).collect();
    let g = [0.0, -9.81, 1.5];
    let model = Model::new(
        d,
        mass,
        Some(g[..d].to_vec()),
        vec![ElementSet::NeoHookean(nh)],
    );
    let weight: Vec<f64> = (0..n).map(|_| rng.random_range(0.01..1.0)).collect();
    let mut normal = [0.0; 3];
    normal[1] = 1.0;
    let planes = vec![HalfSpace {
        normal,
        offset: -0.05,
        dhat: 0.2,
        kappa: 1e4,
    }];
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
    let mut free = Vec::new();
    for i in 0..n {
        let p = &m.x[i * d..(i + 1) * d];
        if p[0] < 1e-9 {
            cs.push(Constraint::sticky(i));
        } else if p[1] < 1e-9 {
            cs.push(Constraint::plane(i, &slanted));
        } else if p[0] > len - 1e-9 {
            cs.push(Constraint::plane(i, &axis));
        } else {
            free.push(i);
        }
    }
    let frames = Frames::build(d, n, &cs).expect("valid constraints");
    assert!(frames.has_rotation(), "some nodes carry a rotation");
    // Two free nodes far apart in the numbering, so that they lie in different chunks.
    let nodes = [free[1], free[free.len() - 2]];
    let mut pos = |i: usize| {
        let mut a = [0.0; 3];
        for c in 0..d {
            a[c] = x[i * d + c] + rng.random_range(-0.02..0.02);
        }
        a
    };
    let shapes = [
        BcShape::Sticky {
            anchor: pos(nodes[0]),
        },
        BcShape::Plane {
            normal: {
                let mut v = [0.0; 3];
                v[0] = 0.6;
                v[1] = 0.8;
                v
            },
            offset: 0.1,
        },
    ];
    let moving = nodes
        .iter()
        .zip(shapes)
        .map(|(&node, shape)| {
            let m = model.mass[node];
            let mut lam = [0.0; 3];
            (0..d).for_each(|a| lam[a] = rng.random_range(-5.0..5.0));
            MovingTerm {
                node,
                shape,
                coef: 1e3 * rng.random_range(0.5..2.0) * m,
                sqrt_m_lambda: lam.map(|l| m.sqrt() * l),
            }
        })
        .collect();
    Case {
        model,
        barrier: Barrier::new(d, weight),
        planes,
        x,
        x_tilde,
        frames,
        moving,
    }
}

/// Everything compared from one build.
#[derive(Debug, PartialEq)]
struct Outcome {
    h: Vec<f64>,
    g: Vec<f64>,
    y_assembled: Vec<f64>,
    h_moving: Vec<f64>,
    g_moving: Vec<f64>,
    /// Per (preconditioner, coarse space): iterations and Δx.
    solves: Vec<(usize, Vec<f64>)>,
}

/// Builds the terms (element arrays capped at `element_limit`, values at `values_limit`),
/// assembles, multiplies, adds the moving terms and solves; returns what it read back and
/// the number of values chunks.
fn evaluate(
    ctx: &GpuContext,
    c: &Case,
    element_limit: Option<u64>,
    values_limit: Option<u64>,
) -> Result<(Outcome, usize, usize), GpuError> {
    let m = &c.model;
    let kernels = ElementKernels::new(ctx, m.dim, Precision::F64)?;
    let barrier = Some((&c.barrier, c.planes.as_slice()));
    let el = match element_limit {
        Some(l) => GpuElements::with_binding_limit(ctx, &kernels, m, barrier, l)?,
        None => GpuElements::with_kernels(ctx, &kernels, m, barrier)?,
    };
    let asm = match values_limit {
        Some(l) => GpuAssembly::with_binding_limit(&el, m, l)?,
        None => GpuAssembly::new(&el, m)?,
    };
    asm.set_scale(SCALE);
    // The operations need a direction buffer of n·d reals: the positions of a second,
    // barrier-free set of terms (never written here).
    let holder = GpuElements::with_kernels(ctx, &kernels, m, None)?;
    let mut ops = NewtonOps::new(&el, &asm, holder.positions_buffer())?;
    el.set_positions(&c.x)?;
    el.set_inertia_target(&c.x_tilde)?;
    el.evaluate(true)?;
    asm.assemble()?;
    let mut rng = StdRng::seed_from_u64(7);
    let v: Vec<f64> = (0..c.x.len())
        .map(|_| rng.random_range(-1.0..1.0))
        .collect();
    asm.set_x(&v)?;
    asm.matvec_assembled()?;
    let (y_assembled, _) = asm.read_products()?;
    let h = asm.read_matrix()?.values;
    let g = asm.read_gradient()?;
    ops.set_moving(&c.moving)?;
    ops.add_moving()?;
    let h_moving = asm.read_matrix()?.values;
    let g_moving = asm.read_gradient()?;
    let mut cg = asm.device_cg()?;
    let frames = cg.frames(&c.frames, CoarseSpace::Aggregates)?;
    let mut solves = Vec::new();
    for (preconditioner, coarse) in [
        (Preconditioner::Jacobi, CoarseSpace::None),
        (Preconditioner::Jacobi, CoarseSpace::Translations),
        (Preconditioner::BlockJacobi, CoarseSpace::None),
        (Preconditioner::BlockJacobi, CoarseSpace::Translations),
        (Preconditioner::BlockJacobi, CoarseSpace::Aggregates),
    ] {
        let info = cg.solve(
            &frames,
            &DeviceCgParams {
                tol: TOL,
                max_iterations: 10_000,
                preconditioner,
                coarse,
                stagnation_window: stickslip::solve::cg::STAGNATION_WINDOW,
            },
        )?;
        solves.push((info.iterations, cg.read_dx()?));
    }
    let outcome = Outcome {
        h,
        g,
        y_assembled,
        h_moving,
        g_moving,
        solves,
    };
    let node_chunks = el
        .kinds()
        .iter()
        .filter(|k| matches!(k, TermKind::Inertia | TermKind::Barrier))
        .count();
    Ok((outcome, asm.values_chunks().len(), node_chunks))
}

/// Bits of a vector, so that equality is bitwise (−0 ≠ 0, NaN = NaN of the same bits).
fn bits(v: &[f64]) -> Vec<u64> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn same(what: &str, a: &[f64], b: &[f64]) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    let differ = bits(a)
        .iter()
        .zip(bits(b))
        .filter(|(x, y)| **x != *y)
        .count();
    assert_eq!(differ, 0, "{what}: {differ} of {} entries differ", a.len());
}

/// The unsplit build against the values split (and, unless `large`, the values and the
/// element terms split).
fn run(d: usize, seed: u64, large: bool) {
    let Some((ctx, _guard)) = gpu() else {
        return;
    };
    let c = case(d, seed, large);
    let (whole, chunks, terms) = evaluate(ctx, &c, None, None).expect("unsplit build");
    assert_eq!(chunks, 1, "{d}D: the values fit one binding unforced");
    let nnz = whole.h.len() / (d * d);
    let bytes = (whole.h.len() * 8) as u64;
    // A quarter of the values (rounded to 16 bytes): at least four chunks.
    let limit = (bytes / 4).div_ceil(16) * 16;
    // Element arrays capped so that the node terms split into about three chunks too.
    let element_limit = (c.model.n_nodes as u64 * (d * d) as u64 * 8 / 3).div_ceil(16) * 16;
    let builds = [
        ("values split", None),
        ("values and elements split", Some(element_limit)),
    ];
    for &(label, el_limit) in &builds[..if large { 1 } else { 2 }] {
        let (split, chunks, split_terms) =
            evaluate(ctx, &c, el_limit, Some(limit)).expect("split build");
        eprintln!(
            "{d}D {label}: {} nodes, {nnz} blocks, limit {limit} B → {chunks} values chunks, \
             {split_terms} inertia and barrier chunks ({terms} unsplit); iterations {:?}",
            c.model.n_nodes,
            split.solves.iter().map(|s| s.0).collect::<Vec<_>>()
        );
        assert!(chunks >= 3, "{d}D {label}: {chunks} chunks");
        // The node terms in three or more chunks each.
        if el_limit.is_some() {
            assert!(
                split_terms >= 6,
                "{d}D {label}: {split_terms} node-term chunks"
            );
        }
        same(&format!("{d}D {label}: H"), &split.h, &whole.h);
        same(&format!("{d}D {label}: g"), &split.g, &whole.g);
        same(
            &format!("{d}D {label}: H v"),
            &split.y_assembled,
            &whole.y_assembled,
        );
        same(
            &format!("{d}D {label}: H with moving terms"),
            &split.h_moving,
            &whole.h_moving,
        );
        same(
            &format!("{d}D {label}: g with moving terms"),
            &split.g_moving,
            &whole.g_moving,
        );
        assert_ne!(
            bits(&whole.h_moving),
            bits(&whole.h),
            "{d}D: the moving terms change H"
        );
        for (k, ((it_s, dx_s), (it_w, dx_w))) in split.solves.iter().zip(&whole.solves).enumerate()
        {
            assert_eq!(it_s, it_w, "{d}D {label}: solve {k} iterations");
            assert!(*it_w > 0, "{d}D: solve {k} iterates");
            same(&format!("{d}D {label}: solve {k} Δx"), dx_s, dx_w);
        }
    }
}

#[test]
fn split_matrix_3d_is_bitwise_the_unsplit() {
    run(3, 11, false);
}

#[test]
fn split_matrix_2d_is_bitwise_the_unsplit() {
    run(2, 12, false);
}

/// More rows than CG threads: a thread's rows lie in several chunks, and its running sums
/// carry from one chunk's dispatch to the next.
#[test]
fn split_matrix_2d_with_several_rows_per_thread_is_bitwise_the_unsplit() {
    run(2, 14, true);
}

/// A limit below one row's blocks is refused, naming the row.
#[test]
fn a_row_larger_than_the_limit_is_refused() {
    let Some((ctx, _guard)) = gpu() else {
        return;
    };
    let c = case(2, 13, false);
    let el = GpuElements::new(ctx, &c.model, None, Precision::F64).expect("element terms");
    match GpuAssembly::with_binding_limit(&el, &c.model, 64) {
        Err(GpuError::BufferTooLarge { label, .. }) => {
            assert!(label.contains("row 0"), "{label}")
        }
        Err(e) => panic!("another error: {e}"),
        Ok(_) => panic!("a row of 2D blocks over 64 bytes was accepted"),
    }
}
