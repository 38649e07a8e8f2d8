//! Element terms split into chunks because their arrays exceed one storage binding
//! (`GpuElements::with_binding_limit` forces a small limit on small meshes) against the
//! same terms unsplit, on a 3D box of tetrahedra and a 2D rectangle of triangles, each
//! with springs on its edges, inertia, gravity and a half-space barrier.
//!
//! Two limits per mesh: one that splits every element set into at least three chunks
//! (node terms whole), and one that splits the inertia and barrier into at least three
//! chunks too (the element sets then into many). A chunk computes each of its items as
//! the unsplit term does, and the assembly continues each entry's sum chunk after chunk in
//! element order, so everything but the device's energy reductions must be the same bits:
//! - per-item energies, gradients, Hessians and barrier flags (`GpuElements::read`, the
//!   chunks of a term concatenated), and their per-term sums taken on the host in item
//!   order;
//! - the assembled H and g, and the matrix-free and assembled products with one vector.
//!
//! The device's per-term energy sums (`NewtonOps::energy_terms`) reduce each chunk by a
//! tree and the chunks' sums are added in order, a different order of the same n terms
//! than the unsplit tree: each sum is within γ_n·Σ|e| of the exact one, so the two differ
//! by at most 2·n·ε·Σ|e| (the tests print the difference in units of ε·Σ|e|).
//!
//! Every test shares one device (tests/common/gpu.rs); sizes are small for lavapipe.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use stickslip::gpu::{GpuContext, GpuError, Precision};
use stickslip::sim::device::assembly::GpuAssembly;
use stickslip::sim::device::elements::{ElementKernels, GpuElements, TermKind};
use stickslip::sim::device::newton_ops::NewtonOps;
use stickslip::sim::energy::barrier::{Barrier, HalfSpace};
use stickslip::sim::energy::{ElementSet, Law, Model, NeoHookean, Springs};
use stickslip::sim::mesh;

mod common;
use common::gpu::gpu;

/// h² of a time step (not a power of two, so the scaling rounds).
const SCALE: f64 = 1.0 / 30.0 / 30.0;

struct Case {
    model: Model,
    barrier: Barrier,
    planes: Vec<HalfSpace>,
    x: Vec<f64>,
    x_tilde: Vec<f64>,
}

/// A grid mesh (2D: 8×6 cells, 96 triangles, 63 nodes; 3D: 4×4×3 cells, 288 tetrahedra,
/// 100 nodes) deformed at random, with neo-Hookean elements, springs on its edges,
/// random masses, gravity, and two half-spaces that a share of the weighted nodes is
/// within d̂ of (none touches one: every barrier energy is finite).
fn case(d: usize, seed: u64) -> Case {
    let mut rng = StdRng::seed_from_u64(seed);
    let m = if d == 2 {
        mesh::rectangle(2, [1.0, 0.7], [8, 6])
    } else {
        mesh::cuboid([1.0, 0.8, 0.6], [4, 4, 3])
    };
    let n = m.n_nodes();
    let x: Vec<f64> =
        m.x.iter()
            .map(|v| v + rng.random_range(-0.03..0.03))
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
    Case {
        model,
        barrier: Barrier::new(d, weight),
        planes,
        x,
        x_tilde,
    }
}

/// One term of the scene (an element set or node term) with its chunks' outputs
/// concatenated in item order.
struct Term {
    kind: TermKind,
    chunks: usize,
    energy: Vec<f64>,
    gradient: Vec<f64>,
    hessian: Vec<f64>,
    flags: Vec<u32>,
    /// The device's energy reductions of the chunks, added in chunk order.
    device_energy: f64,
}

/// Everything the comparison reads back from one build.
struct Outcome {
    terms: Vec<Term>,
    h: Vec<f64>,
    g: Vec<f64>,
    y_assembled: Vec<f64>,
    y_matrix_free: Vec<f64>,
}

/// Builds the element terms (with `limit`, or unsplit), their assembly and the Newton
/// operations, evaluates at the case's state and reads everything back.
fn evaluate(
    ctx: &GpuContext,
    kernels: &ElementKernels,
    c: &Case,
    limit: Option<u64>,
) -> Result<Outcome, GpuError> {
    let m = &c.model;
    let barrier = Some((&c.barrier, c.planes.as_slice()));
    let el = match limit {
        Some(l) => GpuElements::with_binding_limit(ctx, kernels, m, barrier, l)?,
        None => GpuElements::with_kernels(ctx, kernels, m, barrier)?,
    };
    let asm = GpuAssembly::new(&el, m)?;
    asm.set_scale(SCALE);
    // The operations need a direction buffer of n·d reals: the positions of a second,
    // barrier-free set of terms (never written here).
    let holder = GpuElements::with_kernels(ctx, kernels, m, None)?;
    let ops = NewtonOps::new(&el, &asm, holder.positions_buffer())?;
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
    asm.matvec_matrix_free()?;
    let (y_assembled, y_matrix_free) = asm.read_products()?;
    let h = asm.read_matrix()?.values;
    let g = asm.read_gradient()?;
    let values = el.read()?;
    let sums = ops.energy_terms()?;
    let mut terms: Vec<Term> = Vec::new();
    for (t, (tv, e)) in values.into_iter().zip(sums).enumerate() {
        let r = el.term_range(t).expect("term range");
        if r.start == 0 {
            terms.push(Term {
                kind: tv.kind,
                chunks: 0,
                energy: Vec::new(),
                gradient: Vec::new(),
                hessian: Vec::new(),
                flags: Vec::new(),
                device_energy: 0.0,
            });
        }
        let term = terms.last_mut().expect("a chunk after its term's first");
        assert_eq!(
            term.kind, tv.kind,
            "chunk {t} of another kind than its term"
        );
        assert_eq!(
            term.energy.len(),
            r.start,
            "chunk {t} does not follow the one before"
        );
        assert_eq!(tv.energy.len(), r.len());
        term.chunks += 1;
        term.energy.extend(tv.energy);
        term.gradient.extend(tv.gradient);
        term.hessian.extend(tv.hessian);
        term.flags.extend(tv.flags);
        term.device_energy += e;
    }
    Ok(Outcome {
        terms,
        h,
        g,
        y_assembled,
        y_matrix_free,
    })
}

/// Asserts that two arrays are the same bits.
fn same_bits(what: &str, a: &[f64], b: &[f64]) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    let diff: Vec<usize> = (0..a.len())
        .filter(|&k| a[k].to_bits() != b[k].to_bits())
        .collect();
    assert!(
        diff.is_empty(),
        "{what}: {} of {} entries differ, first at {}: {:e} vs {:e}",
        diff.len(),
        a.len(),
        diff[0],
        a[diff[0]],
        b[diff[0]]
    );
}

/// The largest per-element Hessian of the model's sets, in bytes (f64).
fn element_hessian_bytes(m: &Model) -> Vec<u64> {
    m.sets
        .iter()
        .map(|s| ((s.arity() * m.dim).pow(2) * 8) as u64)
        .collect()
}

/// Runs the unsplit and two split builds of a case and compares them.
fn split_matches_unsplit(d: usize, seed: u64) {
    let Some((ctx, _lock)) = gpu() else { return };
    let c = case(d, seed);
    let m = &c.model;
    let n = m.n_nodes;
    let kernels = ElementKernels::new(ctx, d, Precision::F64).expect("element kernels");
    let whole = evaluate(ctx, &kernels, &c, None).expect("unsplit build");
    assert!(whole.terms.iter().all(|t| t.chunks == 1));
    assert!(
        whole
            .terms
            .iter()
            .any(|t| t.kind == TermKind::Barrier && t.hessian.iter().any(|&v| v != 0.0)),
        "no node within d̂: the barrier would be tested on zeros only"
    );
    let hb = element_hessian_bytes(m);
    // A limit of a third of the smallest set's Hessian array splits every set at least
    // three ways; one of a third of the inertia's Hessian array (d² per node) splits the
    // node terms with Hessians too.
    let sets_limit = m
        .sets
        .iter()
        .zip(&hb)
        .map(|(s, b)| s.len() as u64 * b / 3 / 16 * 16)
        .min()
        .expect("two sets");
    let nodes_limit = (n * d * d * 8) as u64 / 3 / 16 * 16;
    assert!(nodes_limit >= hb.iter().copied().max().unwrap_or(0));
    for (name, limit) in [("sets", sets_limit), ("nodes", nodes_limit)] {
        let split = evaluate(ctx, &kernels, &c, Some(limit)).expect("split build");
        assert_eq!(split.terms.len(), whole.terms.len(), "{name}: terms");
        let chunks: Vec<String> = split
            .terms
            .iter()
            .map(|t| format!("{:?}×{}", t.kind, t.chunks))
            .collect();
        eprintln!(
            "{d}D, limit {limit} B ({name}): chunks {}",
            chunks.join(", ")
        );
        for (s, w) in split.terms.iter().zip(&whole.terms) {
            assert_eq!(s.kind, w.kind, "{name}: term order");
            let what = format!("{d}D {name} {:?}", s.kind);
            let expect_split = match s.kind {
                TermKind::NeoHookean | TermKind::Springs => true,
                TermKind::Inertia | TermKind::Barrier => name == "nodes",
                TermKind::Gravity => false,
            };
            if expect_split {
                assert!(s.chunks >= 3, "{what}: {} chunks", s.chunks);
            }
            same_bits(&format!("{what} energies"), &s.energy, &w.energy);
            same_bits(&format!("{what} gradients"), &s.gradient, &w.gradient);
            same_bits(&format!("{what} Hessians"), &s.hessian, &w.hessian);
            assert_eq!(s.flags, w.flags, "{what} flags");
            let host = |t: &Term| t.energy.iter().fold(0.0, |a, e| a + e);
            assert_eq!(
                host(s).to_bits(),
                host(w).to_bits(),
                "{what}: host sum of the energies"
            );
            // The device sums: two orders of the same terms.
            let abs: f64 = w.energy.iter().map(|e| e.abs()).sum();
            let diff = (s.device_energy - w.device_energy).abs();
            let bound = 2.0 * w.energy.len() as f64 * f64::EPSILON * abs;
            eprintln!(
                "  {what}: {} items, device energy {:.17e} vs unsplit {:.17e}: {:.2} ε·Σ|e| apart",
                w.energy.len(),
                s.device_energy,
                w.device_energy,
                if abs > 0.0 {
                    diff / (f64::EPSILON * abs)
                } else {
                    0.0
                }
            );
            assert!(
                diff <= bound,
                "{what}: device energy {:e} vs {:e}, bound {bound:e}",
                s.device_energy,
                w.device_energy
            );
        }
        same_bits(&format!("{d}D {name} assembled H"), &split.h, &whole.h);
        same_bits(&format!("{d}D {name} assembled g"), &split.g, &whole.g);
        same_bits(
            &format!("{d}D {name} assembled product"),
            &split.y_assembled,
            &whole.y_assembled,
        );
        same_bits(
            &format!("{d}D {name} matrix-free product"),
            &split.y_matrix_free,
            &whole.y_matrix_free,
        );
        eprintln!(
            "  {d}D {name}: H ({} entries), g ({}), both products: same bits",
            split.h.len(),
            split.g.len()
        );
    }
}

/// Tetrahedra, springs, inertia, gravity and a barrier in 3D.
#[test]
fn box_3d_split_terms_match_the_unsplit_bits() {
    split_matches_unsplit(3, 31);
}

/// Triangles, springs, inertia, gravity and a barrier in 2D.
#[test]
fn rectangle_2d_split_terms_match_the_unsplit_bits() {
    split_matches_unsplit(2, 32);
}

/// A limit below one element's Hessian cannot be met by splitting: refused, naming the
/// set, not a device fault.
#[test]
fn an_element_over_the_limit_is_refused() {
    let Some((ctx, _lock)) = gpu() else { return };
    let c = case(3, 33);
    let kernels = ElementKernels::new(ctx, 3, Precision::F64).expect("element kernels");
    let one_tet = element_hessian_bytes(&c.model)[0];
    let barrier = Some((&c.barrier, c.planes.as_slice()));
    match GpuElements::with_binding_limit(ctx, &kernels, &c.model, barrier, one_tet - 16) {
        Err(GpuError::BufferTooLarge {
            label,
            bytes,
            limit,
            ..
        }) => {
            assert_eq!(label, "elements set 0 (one item)");
            assert_eq!((bytes, limit), (one_tet, one_tet - 16));
        }
        Err(e) => panic!("another error: {e}"),
        Ok(_) => panic!("a limit below one tetrahedron's Hessian was accepted"),
    }
    // At exactly one element per chunk it builds.
    let el = GpuElements::with_binding_limit(ctx, &kernels, &c.model, barrier, one_tet)
        .expect("one element per chunk");
    let tets = el
        .kinds()
        .iter()
        .filter(|k| **k == TermKind::NeoHookean)
        .count();
    assert_eq!(tets, c.model.sets[0].len());
}
