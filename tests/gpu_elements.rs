//! Element energies, gradients and Hessians on the GPU (shaders/elements.wgsl through
//! `sim::device::elements`) against the CPU's (src/sim/energy), term by term, in 2D and 3D,
//! in f64 and f32, for well-shaped, nearly flat and inverted elements, elements with repeated
//! singular values, collapsed ones (F = 0 or nearly rank one), and, in f64, slivers that
//! are flat already at rest. Every projected neo-Hookean Hessian is also compared with the
//! numerical projection of ∂²Ψ/∂F² (SymmetricEigen), the reference where the CPU's analytic
//! one loses accuracy (collapsed 3D elements, printed).
//!
//! "Relative" error of an array: max_k |gpu_k − cpu_k| / max_k |cpu_k| over all its entries
//! (one array per term, category and quantity), so an entry near zero is judged against
//! the array's scale, as a solver sees it. Bounds:
//! - f64: 1e-12 (≈ 4500 ε). Each entry is a short sum whose rounding is a few tens of ε
//!   times the array scale (the SVD and Jacobi eigenvectors are backward stable, so errors
//!   are ε‖F‖ in σ and O(ε) in the assembled modes); the remaining factor covers the
//!   cancellation of the energy near rest (terms O(λ), energy O(λ·strain²)). Slivers at
//!   rest are compared with the CPU evaluated at element-local positions: at absolute
//!   positions the CPU's F = Σ_a x_a g_aᵀ itself moves by ε·|x|·‖Dm⁻¹‖ (≈ 1e-12, printed).
//! - f32: 1e-5 (≈ 80 ε_f32). Positions, rest data and parameters are rounded to f32
//!   (2⁻²⁴ relative) before any arithmetic; F = Ds Dm⁻¹ turns that into ~|x|/|Ds|·2⁻²⁴ in F
//!   (a few ×1e-7 for these elements, whose coordinates reach 5× their size), and the f32
//!   arithmetic adds tens of ε_f32. The largest errors are the inertia energy's (≈ 5e-6):
//!   x − x̃ is ~50× smaller than |x| here, so the f32 rounding of x and x̃ alone moves
//!   (x − x̃)² by 2·50·2⁻²⁴ ≈ 6e-6 relative. Slivers at rest are left out: their F loses
//!   ‖Dm⁻¹‖·|x|·2⁻²⁴ ≈ 1e-4 to the input rounding alone, whatever the kernel does.
//!
//! Every test shares one device (tests/common/gpu.rs); sizes are small for lavapipe.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use stickslip::gpu::{GpuContext, GpuError, Precision};
use stickslip::sim::device::elements::{ElementKernels, GpuElements, TermKind, TermValues};
use stickslip::sim::energy::barrier::{Barrier, HalfSpace};
use stickslip::sim::energy::{gravity, inertia, ElementSet, Law, Model, NeoHookean, Springs};
use stickslip::sim::mesh::{ElementKind, Mesh};

mod common;
use common::gpu::gpu;

const ELEMENTS_PER_CATEGORY: usize = 24;

#[derive(Debug, Clone, Copy, PartialEq)]
enum Category {
    WellShaped,
    Flat,
    /// The smallest σ in [0.02, 0.05]: J small and positive.
    NearlyInverted,
    Inverted,
    /// Ties in |σ|, where an SVD's vectors are not unique: pure rotations, two equal σ,
    /// and all |σ| equal with the last negative.
    RepeatedSigma,
    /// Collapsed elements: all nodes on one point (F = 0) or nearly on a line (σ = 1.2,
    /// 1e-6, 1e-7 in 3D; 1.2, 1e-7 in 2D).
    Collapsed,
    SliverAtRest,
}

/// A random rotation (d×d row-major, det +1).
fn rotation(d: usize, rng: &mut StdRng) -> Vec<f64> {
    let m = nalgebra::DMatrix::<f64>::from_fn(d, d, |_, _| rng.random_range(-1.0..1.0));
    let q = m.qr().q();
    let mut r: Vec<f64> = (0..d * d).map(|k| q[(k / d, k % d)]).collect();
    if nalgebra::DMatrix::from_row_slice(d, d, &r).determinant() < 0.0 {
        r.iter_mut().take(d).for_each(|v| *v = -*v);
    }
    r
}

/// U diag(s) Vᵀ.
fn compose(d: usize, u: &[f64], s: &[f64], v: &[f64]) -> Vec<f64> {
    let mut f = vec![0.0; d * d];
    for r in 0..d {
        for c in 0..d {
            f[r * d + c] = (0..d).map(|k| u[r * d + k] * s[k] * v[c * d + k]).sum();
        }
    }
    f
}

/// The deformation applied to one element of the category.
fn deformation(d: usize, cat: Category, rng: &mut StdRng) -> Vec<f64> {
    let (u, v) = (rotation(d, rng), rotation(d, rng));
    let mut s: Vec<f64> = (0..d).map(|_| rng.random_range(0.7..1.3)).collect();
    match cat {
        Category::WellShaped | Category::SliverAtRest => {
            return (0..d * d)
                .map(|k| if k % (d + 1) == 0 { 1.0 } else { 0.0 } + rng.random_range(-0.3..0.3))
                .collect();
        }
        Category::Flat => s[d - 1] = 1e-6 * rng.random_range(0.5..2.0),
        Category::NearlyInverted => s[d - 1] = rng.random_range(0.02..0.05),
        Category::Inverted => s[d - 1] = -rng.random_range(0.1..0.6),
        Category::RepeatedSigma => {
            let ties: [&[f64]; 3] = if d == 2 {
                [&[1.0, 1.0], &[1.3, 1.3], &[0.8, -0.8]]
            } else {
                [&[1.0, 1.0, 1.0], &[1.3, 1.3, 0.7], &[0.8, 0.8, -0.8]]
            };
            s.copy_from_slice(ties[rng.random_range(0..3)]);
        }
        Category::Collapsed => {
            if rng.random_bool(0.5) {
                return vec![0.0; d * d];
            }
            let line = [1.2, 1e-6, 1e-7];
            s.copy_from_slice(if d == 2 { &[1.2, 1e-7] } else { &line });
        }
    }
    compose(d, &u, &s, &v)
}

/// Disjoint random elements of one category: the rest mesh and deformed positions.
fn elements(d: usize, cat: Category, rng: &mut StdRng) -> (Mesh, Vec<f64>) {
    let nn = d + 1;
    let mut rest = Vec::new();
    let mut x = Vec::new();
    let mut els = Vec::new();
    for e in 0..ELEMENTS_PER_CATEGORY {
        // The unit simplex, jittered, scaled, rotated and moved away from the origin.
        let mut local = vec![0.0; nn * d];
        for a in 0..d {
            local[(a + 1) * d + a] = 1.0;
        }
        for v in local.iter_mut() {
            *v += rng.random_range(-0.15..0.15);
        }
        if cat == Category::SliverAtRest {
            // Squash the last axis to 1e-3 of the others: flat at rest, still far above
            // the degeneracy threshold.
            for a in 0..nn {
                local[a * d + d - 1] *= 1e-3;
            }
        }
        let scale = rng.random_range(0.1..1.0);
        let rot = rotation(d, rng);
        let shift: Vec<f64> = (0..d)
            .map(|_| rng.random_range(-5.0..5.0) * scale)
            .collect();
        let f = deformation(d, cat, rng);
        let moved: Vec<f64> = (0..d).map(|_| rng.random_range(-0.5..0.5)).collect();
        for a in 0..nn {
            let p: Vec<f64> = (0..d)
                .map(|i| {
                    scale
                        * (0..d)
                            .map(|j| rot[i * d + j] * local[a * d + j])
                            .sum::<f64>()
                        + shift[i]
                })
                .collect();
            rest.extend_from_slice(&p);
            for i in 0..d {
                x.push((0..d).map(|j| f[i * d + j] * p[j]).sum::<f64>() + moved[i]);
            }
        }
        els.push((e * nn..(e + 1) * nn).collect());
    }
    let kind = if d == 2 {
        ElementKind::Triangle
    } else {
        ElementKind::Tetrahedron
    };
    let mesh = Mesh {
        dim: d,
        x: rest,
        kind,
        elements: els,
    };
    (mesh, x)
}

/// Everything one scene can hold, around the deformed elements: neo-Hookean, springs on
/// the element edges, inertia, gravity and two half-spaces that a share of the weighted
/// nodes is within d̂ of.
struct Scene {
    model: Model,
    barrier: Barrier,
    planes: Vec<HalfSpace>,
    x: Vec<f64>,
    x_tilde: Vec<f64>,
    category: Category,
    /// Slivers at rest: each element's positions relative to its first node, where the
    /// CPU's neo-Hookean reference is taken (see [`compare`]).
    local_x: Option<Vec<f64>>,
}

fn scene(d: usize, cat: Category, seed: u64) -> Scene {
    scene_of(d, cat, seed, Law::StableNeoHookean)
}

/// [`scene`] with its neo-Hookean elements of `law`.
fn scene_of(d: usize, cat: Category, seed: u64, law: Law) -> Scene {
    let mut rng = StdRng::seed_from_u64(seed);
    let (mesh, x) = elements(d, cat, &mut rng);
    let n = mesh.x.len() / d;
    let nh = NeoHookean::new(&mesh, 1e5, 0.45, law).expect("valid rest elements");
    let springs = Springs::new(d, &mesh.x, mesh.edges(), 3e3).expect("valid springs");
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
    let barrier = Barrier::new(d, weight);
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
    let local_x = (cat == Category::SliverAtRest).then(|| {
        let nn = d + 1;
        let mut l = x.clone();
        for e in 0..ELEMENTS_PER_CATEGORY {
            for a in 0..nn {
                for i in 0..d {
                    l[(e * nn + a) * d + i] = x[(e * nn + a) * d + i] - x[e * nn * d + i];
                }
            }
        }
        l
    });
    Scene {
        model,
        barrier,
        planes,
        x,
        x_tilde,
        category: cat,
        local_x,
    }
}

/// The CPU's values of one term, in the GPU's per-item layout.
fn cpu_values(s: &Scene, kind: TermKind, set: usize, project: bool) -> TermValues {
    cpu_values_at(s, &s.x, kind, set, project)
}

/// [`cpu_values`] with the element sets evaluated at `xe` (the node terms at the scene's x).
fn cpu_values_at(s: &Scene, xe: &[f64], kind: TermKind, set: usize, project: bool) -> TermValues {
    let m = &s.model;
    let d = m.dim;
    let n = m.n_nodes;
    let mut out = TermValues {
        kind,
        energy: Vec::new(),
        gradient: Vec::new(),
        hessian: Vec::new(),
        flags: Vec::new(),
    };
    let node = |v: &[f64], i: usize| v[i * d..(i + 1) * d].to_vec();
    match kind {
        TermKind::NeoHookean | TermKind::Springs => {
            let es = &m.sets[set];
            let nl = es.arity() * d;
            let flagged = matches!(es, ElementSet::NeoHookean(nh) if nh.law == Law::NeoHookean);
            for e in 0..es.len() {
                out.energy.push(es.energy(xe, e));
                if flagged {
                    // Classical neo-Hookean: J ≤ 0 is flagged (energy +∞).
                    out.flags.push(u32::from(es.energy(xe, e).is_infinite()));
                }
                let mut g = vec![0.0; nl];
                es.gradient(xe, e, &mut g);
                out.gradient.extend_from_slice(&g);
                let mut h = vec![0.0; nl * nl];
                es.hessian(xe, e, project, &mut h);
                out.hessian.extend_from_slice(&h);
            }
        }
        TermKind::Inertia => {
            let mut h = m.zero_matrix();
            m.add_mass(&mut h);
            for i in 0..n {
                let (xi, ti) = (node(&s.x, i), node(&s.x_tilde, i));
                out.energy
                    .push(inertia::energy(&m.mass[i..=i], d, &xi, &ti));
                let mut g = vec![0.0; d];
                inertia::add_gradient(&m.mass[i..=i], d, &xi, &ti, &mut g);
                out.gradient.extend_from_slice(&g);
                let k = h.diag_index(i).expect("diagonal block");
                out.hessian
                    .extend_from_slice(&h.values[k * d * d..(k + 1) * d * d]);
            }
        }
        TermKind::Gravity => {
            let g = m.gravity.as_ref().expect("gravity");
            for i in 0..n {
                let xi = node(&s.x, i);
                out.energy.push(gravity::energy(&m.mass[i..=i], d, g, &xi));
                let mut gr = vec![0.0; d];
                gravity::add_gradient(&m.mass[i..=i], d, g, 1.0, &mut gr);
                out.gradient.extend_from_slice(&gr);
            }
        }
        TermKind::Barrier => {
            let mut grad = vec![0.0; n * d];
            s.barrier.add_gradient(&s.x, &s.planes, 1.0, &mut grad);
            let mut h = m.zero_matrix();
            s.barrier.add_hessian(&s.x, &s.planes, 1.0, &mut h);
            for i in 0..n {
                // The node's own energy: the barrier with only its weight.
                let mut w = vec![0.0; n];
                w[i] = s.barrier.weight[i];
                let e = Barrier::new(d, w).energy(&s.x, &s.planes);
                out.flags.push(u32::from(e.is_infinite()));
                out.energy.push(e);
                out.gradient.extend_from_slice(&grad[i * d..(i + 1) * d]);
                let k = h.diag_index(i).expect("diagonal block");
                out.hessian
                    .extend_from_slice(&h.values[k * d * d..(k + 1) * d * d]);
            }
        }
    }
    out
}

fn set_kind(m: &Model, set: usize) -> TermKind {
    match m.sets[set] {
        ElementSet::NeoHookean(_) => TermKind::NeoHookean,
        ElementSet::Springs(_) => TermKind::Springs,
    }
}

/// The neo-Hookean element Hessians with ∂²Ψ/∂F² projected numerically (nalgebra
/// SymmetricEigen, negative eigenvalues dropped: `energy::project_psd`) instead of through
/// the analytic eigensystem. The PSD projection is 1-Lipschitz and the symmetric
/// eigensolver backward stable, so this is accurate to ~ε‖∂²Ψ/∂F²‖ even where singular
/// vectors are ill-determined (nearly equal tiny σ).
fn numeric_projection(s: &Scene, xe: &[f64]) -> Vec<f64> {
    let ElementSet::NeoHookean(nh) = &s.model.sets[0] else {
        panic!("set 0 is neo-Hookean")
    };
    let d = nh.dim;
    let (dd, nl) = (d * d, (d + 1) * d);
    let mut out = Vec::new();
    for e in 0..nh.len() {
        let mut f = [0.0; 9];
        nh.deformation_gradient(xe, e, &mut f);
        let mut h = vec![0.0; dd * dd];
        nh.stress_derivative(&f, &mut h);
        stickslip::sim::energy::project_psd(dd, &mut h);
        let g = nh.grads(e);
        for a in 0..=d {
            for c in 0..d {
                for b in 0..=d {
                    for k in 0..d {
                        let mut v = 0.0;
                        for j in 0..d {
                            for l in 0..d {
                                v += h[(c * d + j) * dd + k * d + l] * g[a * d + j] * g[b * d + l];
                            }
                        }
                        out.push(nh.volume[e] * v);
                    }
                }
            }
        }
        debug_assert_eq!(out.len(), (e + 1) * nl * nl);
    }
    out
}

/// Every GPU element (or node) Hessian is exactly symmetric, and with `project` PSD: its
/// smallest eigenvalue is ≥ −tol times the array's largest entry (the comparison's bound:
/// clamped modes are left out of the sum exactly, so what remains is the rounding of at
/// most nine PSD rank-one terms, ~12 ε of their scale).
fn check_symmetric_and_psd(t: &TermValues, d: usize, project: bool, tol: f64, what: &str) {
    if t.hessian.is_empty() {
        return;
    }
    let n = t.hessian.len() / t.energy.len();
    let nl = (n as f64).sqrt() as usize;
    assert_eq!(nl * nl, n);
    assert_eq!(nl % d, 0);
    let scale = t.hessian.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    for (e, h) in t.hessian.chunks_exact(n).enumerate() {
        for r in 0..nl {
            for c in 0..r {
                assert_eq!(h[r * nl + c], h[c * nl + r], "{what} {:?} {e}", t.kind);
            }
        }
        if project {
            let m = nalgebra::DMatrix::from_row_slice(nl, nl, h);
            let min = nalgebra::SymmetricEigen::new(m).eigenvalues.min();
            assert!(min >= -tol * scale, "{what} {:?} {e}: {min:e}", t.kind);
        }
    }
}

/// max |a − b| / max |b| (0 when both are empty or both all zero).
fn rel(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let diff = a
        .iter()
        .zip(b)
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
    if scale == 0.0 {
        assert_eq!(diff, 0.0, "a nonzero array where the CPU's is zero");
        return 0.0;
    }
    diff / scale
}

/// Evaluates the scene on the GPU and returns the worst relative error per term over
/// energy, gradient and Hessian, checking each against `tol`.
fn compare(ctx: &GpuContext, kernels: &ElementKernels, s: &Scene, tol: f64, what: &str) {
    let dev = GpuElements::with_kernels(ctx, kernels, &s.model, Some((&s.barrier, &s.planes)))
        .expect("element data");
    assert_eq!(
        dev.kinds(),
        [
            TermKind::NeoHookean,
            TermKind::Springs,
            TermKind::Inertia,
            TermKind::Gravity,
            TermKind::Barrier
        ]
    );
    dev.set_positions(&s.x).expect("positions");
    dev.set_inertia_target(&s.x_tilde).expect("target");
    for project in [true, false] {
        dev.evaluate(project).expect("evaluate");
        let got = dev.read().expect("read back");
        for (set, g) in got.iter().enumerate() {
            // Slivers at rest: the CPU forms F = Σ_a x_a g_aᵀ from absolute positions, which
            // loses ε·|x|·‖Dm⁻¹‖ (≈ 1e-12 of F here), the GPU F = Ds Dm⁻¹ from edge vectors,
            // which does not. Ψ is invariant under translation, so the CPU is evaluated at
            // each element moved to its first node (where both forms agree) and its own
            // translation variance is printed beside.
            let want = match (&s.local_x, g.kind) {
                (Some(l), TermKind::NeoHookean) => {
                    let raw = cpu_values(s, g.kind, set, project);
                    let local = cpu_values_at(s, l, g.kind, set, project);
                    println!(
                        "{what} CPU at absolute vs element-local positions: energy {:.1e} \
                         gradient {:.1e} hessian {:.1e}",
                        rel(&raw.energy, &local.energy),
                        rel(&raw.gradient, &local.gradient),
                        rel(&raw.hessian, &local.hessian)
                    );
                    local
                }
                _ => cpu_values(s, g.kind, set, project),
            };
            let mut want = want;
            if g.kind == TermKind::NeoHookean && project {
                // Every projected neo-Hookean Hessian also against the numerical projection.
                let num = numeric_projection(s, s.local_x.as_deref().unwrap_or(&s.x));
                let (gpu_err, cpu_err) = (rel(&g.hessian, &num), rel(&want.hessian, &num));
                println!(
                    "{what} against the numerical projection: GPU {gpu_err:.1e} CPU {cpu_err:.1e}"
                );
                assert!(
                    gpu_err <= tol,
                    "{what}: {gpu_err:e} from the numerical projection"
                );
                if s.category == Category::Collapsed {
                    // Two tiny σ (3D): the CPU's analytic projection is itself ~3e-11 off
                    // the numerical one here (its nalgebra SVD reconstructs such F only to
                    // ~1e-10·‖F‖), the GPU's is not; the numerical projection is the
                    // reference.
                    want.hessian = num;
                }
            }
            let errs = [
                rel(&g.energy, &want.energy),
                rel(&g.gradient, &want.gradient),
                rel(&g.hessian, &want.hessian),
            ];
            println!(
                "{what} {:?} project {project}: energy {:.1e} gradient {:.1e} hessian {:.1e}",
                g.kind, errs[0], errs[1], errs[2]
            );
            for (q, e) in ["energy", "gradient", "hessian"].iter().zip(errs) {
                assert!(
                    e <= tol,
                    "{what} {:?} project {project} {q}: {e:e} > {tol:e}",
                    g.kind
                );
            }
            assert_eq!(g.flags, want.flags, "{what} barrier flags");
            check_symmetric_and_psd(g, s.model.dim, project, tol, what);
        }
    }
}

fn categories(precision: Precision) -> Vec<Category> {
    let mut c = vec![
        Category::WellShaped,
        Category::Flat,
        Category::Inverted,
        Category::RepeatedSigma,
        Category::Collapsed,
    ];
    if precision == Precision::F64 {
        c.push(Category::SliverAtRest);
    }
    c
}

fn run(precision: Precision, tol: f64) {
    let Some((ctx, _g)) = gpu() else { return };
    if precision == Precision::F64 && !ctx.has_f64() {
        common::skip(&format!(
            "SKIP: adapter '{}' has no SHADER_F64",
            ctx.adapter_name()
        ));
        return;
    }
    for d in [2, 3] {
        // Compiled once, shared by every scene of this dimension.
        let kernels = ElementKernels::new(ctx, d, precision).expect("element kernels");
        for (k, cat) in categories(precision).into_iter().enumerate() {
            let s = scene(d, cat, 100 * d as u64 + k as u64);
            compare(ctx, &kernels, &s, tol, &format!("{precision} {d}D {cat:?}"));
        }
    }
}

/// The classical neo-Hookean law's elements (defined for J > 0 only: well-shaped, flat and
/// nearly inverted ones) against the CPU and the numerical projection.
fn run_classical(precision: Precision, tol: f64, cats: &[Category]) {
    let Some((ctx, _g)) = gpu() else { return };
    if precision == Precision::F64 && !ctx.has_f64() {
        common::skip(&format!(
            "SKIP: adapter '{}' has no SHADER_F64",
            ctx.adapter_name()
        ));
        return;
    }
    for d in [2, 3] {
        let kernels = ElementKernels::new(ctx, d, precision).expect("element kernels");
        for (k, &cat) in cats.iter().enumerate() {
            let s = scene_of(d, cat, 700 + 100 * d as u64 + k as u64, Law::NeoHookean);
            // Flat elements (σ = 1e-6): J formed from O(1) entries is known only to ε/J
            // ≈ 2e-10 of itself, whether as det F or as the SVD's Πσ, and the classical
            // law's gradient and Hessian go as 1/J and 1/J², so any two correct
            // evaluations (CPU, GPU, the numerical projection) differ by ~ε/J: 1e-9.
            let tol = if cat == Category::Flat && precision == Precision::F64 {
                1e-9
            } else {
                tol
            };
            compare(
                ctx,
                &kernels,
                &s,
                tol,
                &format!("classical {precision} {d}D {cat:?}"),
            );
        }
    }
}

#[test]
fn f64_classical_element_terms_match_the_cpu() {
    run_classical(
        Precision::F64,
        1e-12,
        &[
            Category::WellShaped,
            Category::Flat,
            Category::NearlyInverted,
            Category::SliverAtRest,
        ],
    );
}

/// f32: F carries the input rounding ~|x|/|Ds|·2⁻²⁴ (a few ×1e-7), and the classical
/// Hessian's terms go as 1/σ², so flat elements (σ = 1e-6) are left out: their f32 F is
/// ~10% off before any arithmetic.
#[test]
fn f32_classical_element_terms_match_the_cpu() {
    run_classical(
        Precision::F32,
        1e-5,
        &[Category::WellShaped, Category::NearlyInverted],
    );
}

#[test]
fn f64_element_terms_match_the_cpu() {
    run(Precision::F64, 1e-12);
}

#[test]
fn f32_element_terms_match_the_cpu() {
    run(Precision::F32, 1e-5);
}

/// The scenes exercise what the comparison is about: the projection changes the
/// neo-Hookean and spring Hessians of the flat and inverted elements (so the GPU's clamp
/// is compared, not only its eigensystem), the barrier has active and inactive weighted
/// nodes, and a weighted node past a plane is flagged (energy +∞ on the CPU) while a
/// weightless one is not.
#[test]
fn scenes_exercise_projection_barrier_and_crossing() {
    for d in [2, 3] {
        for (k, cat) in [Category::Flat, Category::Inverted].into_iter().enumerate() {
            let s = scene(d, cat, 1000 + 10 * d as u64 + k as u64);
            for set in 0..2 {
                let p = cpu_values(&s, set_kind(&s.model, set), set, true);
                let u = cpu_values(&s, set_kind(&s.model, set), set, false);
                assert!(rel(&p.hessian, &u.hessian) > 1e-3, "{d}D {cat:?} set {set}");
            }
            let b = cpu_values(&s, TermKind::Barrier, 0, true);
            let active = b.energy.iter().filter(|&&e| e != 0.0).count();
            assert!(
                active > 0 && active < s.model.n_nodes,
                "{d}D {cat:?}: {active}"
            );
        }
    }
    let Some((ctx, _g)) = gpu() else { return };
    let precision = if ctx.has_f64() {
        Precision::F64
    } else {
        Precision::F32
    };
    for d in [2, 3] {
        let mut s = scene(d, Category::WellShaped, 7 + d as u64);
        let weighted = (0..s.model.n_nodes)
            .find(|&i| s.barrier.weight[i] > 0.0)
            .expect("a weighted node");
        let weightless = (0..s.model.n_nodes)
            .find(|&i| s.barrier.weight[i] == 0.0)
            .expect("a weightless node");
        // Both nodes 0.01 past the first plane.
        for i in [weighted, weightless] {
            let p = &s.planes[0];
            let dist: f64 = (0..d).map(|a| s.x[i * d + a] * p.normal[a]).sum::<f64>() - p.offset;
            for a in 0..d {
                s.x[i * d + a] -= (dist + 0.01) * p.normal[a];
            }
        }
        let want = cpu_values(&s, TermKind::Barrier, 0, true);
        assert_eq!(want.energy[weighted], f64::INFINITY);
        assert_eq!(want.flags[weightless], 0);
        let dev = GpuElements::new(ctx, &s.model, Some((&s.barrier, &s.planes)), precision)
            .expect("element kernels");
        dev.set_positions(&s.x).expect("positions");
        dev.set_inertia_target(&s.x_tilde).expect("target");
        dev.evaluate(true).expect("evaluate");
        let got = dev.read().expect("read back");
        let b = got
            .iter()
            .find(|t| t.kind == TermKind::Barrier)
            .expect("barrier term");
        assert_eq!(b.flags, want.flags, "{d}D");
        assert_eq!(b.flags[weighted], 1);
    }
}

/// Requests the kernels cannot serve are errors, never panics: mixed precision, a
/// dimension other than 2 or 3, kernels of another dimension than the model's, positions
/// of the wrong length, more half-spaces than the barrier was built with.
#[test]
fn bad_requests_are_errors() {
    let Some((ctx, _g)) = gpu() else { return };
    let s = scene(2, Category::WellShaped, 3);
    assert!(matches!(
        ElementKernels::new(ctx, 2, Precision::Mixed),
        Err(GpuError::Unsupported(_))
    ));
    assert!(matches!(
        ElementKernels::new(ctx, 4, Precision::F32),
        Err(GpuError::Unsupported(_))
    ));
    let k3 = ElementKernels::new(ctx, 3, Precision::F32).expect("3D kernels");
    assert!(matches!(
        GpuElements::with_kernels(ctx, &k3, &s.model, None),
        Err(GpuError::Mismatch(_))
    ));
    let dev = GpuElements::new(ctx, &s.model, None, Precision::F32).expect("element data");
    assert_eq!(
        dev.kinds(),
        [
            TermKind::NeoHookean,
            TermKind::Springs,
            TermKind::Inertia,
            TermKind::Gravity
        ]
    );
    assert!(matches!(
        dev.set_positions(&s.x[1..]),
        Err(GpuError::Mismatch(_))
    ));
    assert!(matches!(
        dev.set_planes(&s.planes),
        Err(GpuError::Mismatch(_))
    ));
}
