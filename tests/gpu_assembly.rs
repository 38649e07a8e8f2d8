//! Device assembly of the Newton system (shaders/assemble.wgsl through `gpu::assembly`)
//! against the CPU's block assembly of the same element arrays, in 2D (triangles) and 3D
//! (tetrahedra), f64 and f32, on meshes with two element sets sharing every node
//! (neo-Hookean and springs on the edges), inertia, gravity and a half-space barrier.
//!
//! The element arrays are the device's own (read back), so the comparison is of the
//! assembly alone. The CPU reference sums in the order the device does (inertia, the sets
//! in order with their elements in order, then gravity and barrier: the order of
//! `Model::add_potential_hessian` and the integrator).
//!
//! Bounds, per entry, with n the number of summands of the entry and Σ|·| the sum of their
//! absolute values: |device − reference| ≤ (n + 1)·ε·Σ|·|, the standard bound γ_{n+1} of a
//! recursive sum (each addition rounds once; a product scale·h rounds once more). In f64
//! the two sums are the same operations in the same order and differ only where the device
//! compiler contracts a multiply-add, so the bound is far from tight (the tests print the
//! largest error in units of ε·Σ|·|); in f32 the device rounds every partial sum to f32
//! while the reference sums the same f32 inputs in f64. Products: the assembled and the
//! matrix-free product of one row are two sums of the same exact terms in different
//! orders, so their difference is bounded by the sum of their two γ bounds times Σ|H||x|.
//!
//! Every test shares one device (tests/common/gpu.rs); sizes are small for lavapipe.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use stickslip::core::sparse::BlockCsr;
use stickslip::gpu::{GpuContext, GpuError, Precision};
use stickslip::sim::device::assembly::GpuAssembly;
use stickslip::sim::device::elements::{GpuElements, TermKind, TermValues};
use stickslip::sim::energy::barrier::{Barrier, HalfSpace};
use stickslip::sim::energy::{ElementSet, Law, Model, NeoHookean, Springs};
use stickslip::sim::mesh;

mod common;
use common::gpu::gpu;

/// h² of the reference time step (a non-power of two, so the scaling rounds).
const SCALE: f64 = 1.0 / 30.0 / 30.0;

struct Scene {
    model: Model,
    barrier: Barrier,
    planes: Vec<HalfSpace>,
    x: Vec<f64>,
    x_tilde: Vec<f64>,
}

/// A grid mesh (2D: 4×3 cells, 20 nodes; 3D: 3×2×2 cells, 36 nodes), deformed at random,
/// with neo-Hookean elements, springs on its edges, gravity, and two half-spaces that a
/// share of the weighted nodes is within d̂ of.
fn scene(d: usize, seed: u64) -> Scene {
    let mut rng = StdRng::seed_from_u64(seed);
    let m = if d == 2 {
        mesh::rectangle(2, [1.0, 0.7], [4, 3])
    } else {
        mesh::cuboid([1.0, 0.6, 0.5], [3, 2, 2])
    };
    let n = m.n_nodes();
    let x: Vec<f64> =
        m.x.iter()
            .map(|v| v + rng.random_range(-0.08..0.08))
            .collect();
    let nh = NeoHookean::new(&m, 1e5, 0.4, Law::StableNeoHookean).expect("valid rest elements");
    let springs = Springs::new(d, &m.x, m.edges(), 3e3).expect("valid springs");
    let mass: Vec<f64> = (0..n).map(|_| rng.random_range(0.5..2.0)).collect();
    let g = [0.0, -9.81, 1.5];
    let model = Model::new(
        d,
        mass,
        Some(g[..d].to_vec()),
        vec![ElementSet::NeoHookean(nh), ElementSet::Springs(springs)],
    );
    let weight: Vec<f64> = (0..n)
        .map(|_| {
            if rng.random_bool(0.7) {
                rng.random_range(0.01..1.0)
            } else {
                0.0
            }
        })
        .collect();
    let mut planes = Vec::new();
    for raw in [[0.0, 1.0, 0.0], [0.3, 0.9, -0.2]] {
        let len = raw[..d].iter().map(|v| v * v).sum::<f64>().sqrt();
        let mut normal = [0.0; 3];
        for a in 0..d {
            normal[a] = raw[a] / len;
        }
        let dist: Vec<f64> = x
            .chunks_exact(d)
            .map(|p| p.iter().zip(&normal).map(|(a, b)| a * b).sum())
            .collect();
        let lo = dist.iter().cloned().fold(f64::INFINITY, f64::min);
        let hi = dist.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        planes.push(HalfSpace {
            normal,
            offset: lo - 0.05 * (hi - lo),
            dhat: 0.4 * (hi - lo),
            kappa: 1e4,
        });
    }
    let x_tilde: Vec<f64> = x.iter().map(|v| v + rng.random_range(-0.1..0.1)).collect();
    Scene {
        model,
        barrier: Barrier::new(d, weight),
        planes,
        x,
        x_tilde,
    }
}

/// The CPU's assembly of the device's element arrays: H (and |H| from the absolute values
/// of every summand, and the summand count per entry) and g (with Σ|·| and counts).
struct Reference {
    h: BlockCsr,
    h_abs: BlockCsr,
    h_count: Vec<usize>,
    g: Vec<f64>,
    g_abs: Vec<f64>,
    g_count: Vec<usize>,
}

fn reference(model: &Model, terms: &[TermValues], scale: f64) -> Reference {
    let d = model.dim;
    let dd = d * d;
    let n = model.n_nodes;
    let mut h = model.zero_matrix();
    let mut h_abs = model.zero_matrix();
    let mut h_count = vec![0usize; h.values.len()];
    let mut g = vec![0.0; n * d];
    let mut g_abs = vec![0.0; n * d];
    let mut g_count = vec![0usize; n * d];
    let mut add_h = |h: &mut BlockCsr, k: usize, t: usize, v: f64| {
        h.values[k * dd + t] += v;
        h_abs.values[k * dd + t] += v.abs();
        h_count[k * dd + t] += 1;
    };
    let mut add_g = |g: &mut [f64], i: usize, v: f64| {
        g[i] += v;
        g_abs[i] += v.abs();
        g_count[i] += 1;
    };
    let order = |k: &TermKind| match k {
        TermKind::Inertia => 0,
        TermKind::NeoHookean | TermKind::Springs => 1,
        TermKind::Gravity => 2,
        TermKind::Barrier => 3,
    };
    let mut sorted: Vec<(usize, &TermValues)> = terms.iter().enumerate().collect();
    sorted.sort_by_key(|(t, v)| (order(&v.kind), *t));
    let mut set = 0;
    for (_, tv) in sorted {
        match tv.kind {
            TermKind::NeoHookean | TermKind::Springs => {
                let s = &model.sets[set];
                set += 1;
                let ar = s.arity();
                let nl = ar * d;
                for e in 0..s.len() {
                    let nodes = s.nodes(e);
                    let m = &tv.hessian[e * nl * nl..(e + 1) * nl * nl];
                    for a in 0..ar {
                        for b in 0..ar {
                            let k = h.find(nodes[a], nodes[b]).expect("pattern");
                            for r in 0..d {
                                for c in 0..d {
                                    add_h(
                                        &mut h,
                                        k,
                                        r * d + c,
                                        scale * m[(a * d + r) * nl + b * d + c],
                                    );
                                }
                            }
                        }
                        for c in 0..d {
                            add_g(
                                &mut g,
                                nodes[a] * d + c,
                                scale * tv.gradient[e * nl + a * d + c],
                            );
                        }
                    }
                }
            }
            kind => {
                let f = if kind == TermKind::Inertia {
                    1.0
                } else {
                    scale
                };
                for i in 0..n {
                    if !tv.hessian.is_empty() {
                        let k = h.diag_index(i).expect("diagonal block");
                        for t in 0..dd {
                            add_h(&mut h, k, t, f * tv.hessian[i * dd + t]);
                        }
                    }
                    for c in 0..d {
                        add_g(&mut g, i * d + c, f * tv.gradient[i * d + c]);
                    }
                }
            }
        }
    }
    Reference {
        h,
        h_abs,
        h_count,
        g,
        g_abs,
        g_count,
    }
}

/// Largest |a − b| / ((n + 1)·ε·mag) over the entries; fails above 1.
fn check(what: &str, a: &[f64], b: &[f64], mag: &[f64], count: &[usize], eps: f64) -> f64 {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    let mut worst = 0.0f64;
    let mut exact = 0;
    for k in 0..a.len() {
        let bound = (count[k] + 1) as f64 * eps * mag[k];
        let err = (a[k] - b[k]).abs();
        if err == 0.0 {
            exact += 1;
            continue;
        }
        assert!(
            err <= bound,
            "{what}: entry {k}: device {} reference {} (error {err:e}, bound {bound:e})",
            a[k],
            b[k]
        );
        worst = worst.max(err / (eps * mag[k]));
    }
    eprintln!(
        "{what}: {exact} of {} entries bitwise equal, largest error {worst:.3} ε·Σ|·|",
        a.len()
    );
    worst
}

fn run(ctx: &GpuContext, d: usize, precision: Precision, seed: u64) {
    let s = scene(d, seed);
    let el = GpuElements::new(
        ctx,
        &s.model,
        Some((&s.barrier, s.planes.as_slice())),
        precision,
    )
    .expect("element terms");
    el.set_positions(&s.x).expect("positions");
    el.set_inertia_target(&s.x_tilde).expect("target");
    el.evaluate(true).expect("evaluate");
    let terms = el.read().expect("read terms");
    assert!(
        terms
            .iter()
            .any(|t| t.kind == TermKind::Barrier && t.hessian.iter().any(|&v| v != 0.0)),
        "the barrier is active somewhere"
    );
    let asm = GpuAssembly::new(&el, &s.model).expect("assembly");
    // The scale as the device holds it, so both sides multiply by the same number.
    let (eps, scale) = match precision {
        Precision::F64 => (f64::EPSILON, SCALE),
        _ => (f32::EPSILON as f64, SCALE as f32 as f64),
    };
    asm.set_scale(SCALE);
    asm.assemble().expect("assemble");
    let r = reference(&s.model, &terms, scale);
    let h = asm.read_matrix().expect("read H");
    assert_eq!(h.row_ptr, r.h.row_ptr);
    assert_eq!(h.col_idx, r.h.col_idx);
    let tag = format!("{d}D {precision}");
    check(
        &format!("{tag} H"),
        &h.values,
        &r.h.values,
        &r.h_abs.values,
        &r.h_count,
        eps,
    );
    let g = asm.read_gradient().expect("read g");
    check(&format!("{tag} g"), &g, &r.g, &r.g_abs, &r.g_count, eps);

    // Products with a random vector: device assembled vs the CPU product of the device's
    // blocks, and matrix-free vs assembled.
    let mut rng = StdRng::seed_from_u64(seed + 100);
    let nd = s.model.ndof();
    let x: Vec<f64> = (0..nd)
        .map(|_| {
            let v: f64 = rng.random_range(-1.0..1.0);
            if precision == Precision::F64 {
                v
            } else {
                v as f32 as f64
            }
        })
        .collect();
    asm.set_x(&x).expect("x");
    asm.matvec_assembled().expect("assembled product");
    asm.matvec_matrix_free().expect("matrix-free product");
    let (y_as, y_mf) = asm.read_products().expect("read products");
    let mut y_cpu = vec![0.0; nd];
    h.matvec(&x, &mut y_cpu);
    // Σ|H||x| per row: of the device blocks (assembled product) and of every summand of
    // the blocks (matrix-free, whose terms are the summands times x).
    let abs_x: Vec<f64> = x.iter().map(|v| v.abs()).collect();
    let abs_h = BlockCsr {
        values: h.values.iter().map(|v| v.abs()).collect(),
        ..h.clone()
    };
    let mut mag_as = vec![0.0; nd];
    abs_h.matvec(&abs_x, &mut mag_as);
    let mut mag_all = vec![0.0; nd];
    r.h_abs.matvec(&abs_x, &mut mag_all);
    // Summands per row: each block row of the assembled product has blocks·d; the
    // matrix-free one, per entry of H its summands times d, plus the assembly's own.
    let dd = d * d;
    let mut n_as = vec![0usize; nd];
    let mut n_both = vec![0usize; nd];
    for i in 0..s.model.n_nodes {
        let blocks = h.row_ptr[i + 1] - h.row_ptr[i];
        let summands: usize = (h.row_ptr[i]..h.row_ptr[i + 1])
            .map(|k| {
                r.h_count[k * dd..(k + 1) * dd]
                    .iter()
                    .max()
                    .copied()
                    .unwrap_or(0)
            })
            .sum();
        for c in 0..d {
            n_as[i * d + c] = blocks * d;
            n_both[i * d + c] = 2 * (blocks * d + summands * d) + 2;
        }
    }
    check(
        &format!("{tag} assembled Hx"),
        &y_as,
        &y_cpu,
        &mag_as,
        &n_as,
        eps,
    );
    check(
        &format!("{tag} matrix-free Hx"),
        &y_mf,
        &y_as,
        &mag_all,
        &n_both,
        eps,
    );
}

#[test]
fn assembly_2d_f64() {
    let Some((ctx, _g)) = gpu() else { return };
    run(ctx, 2, Precision::F64, 1);
}

#[test]
fn assembly_3d_f64() {
    let Some((ctx, _g)) = gpu() else { return };
    run(ctx, 3, Precision::F64, 2);
}

#[test]
fn assembly_2d_f32() {
    let Some((ctx, _g)) = gpu() else { return };
    run(ctx, 2, Precision::F32, 3);
}

#[test]
fn assembly_3d_f32() {
    let Some((ctx, _g)) = gpu() else { return };
    run(ctx, 3, Precision::F32, 4);
}

/// Element terms of another mesh are refused, not assembled.
#[test]
fn mismatched_model_is_an_error() {
    let Some((ctx, _g)) = gpu() else { return };
    let a = scene(3, 5);
    let b = scene(2, 6);
    let el = GpuElements::new(ctx, &a.model, None, Precision::F32).expect("element terms");
    match GpuAssembly::new(&el, &b.model) {
        Err(GpuError::Mismatch(m)) => assert!(m.contains("3D"), "{m}"),
        Err(e) => panic!("unexpected error {e}"),
        Ok(_) => panic!("a 2D model was accepted for 3D element terms"),
    }
}
