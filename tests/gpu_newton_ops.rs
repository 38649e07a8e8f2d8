//! The device Newton loop's operations (`gpu::newton::ops`, shaders/newton_ops.wgsl)
//! against the CPU's computations on seeded random states of built-in scenes: `drop` (3D,
//! a ground half-space plus a tilted one, the scene's contact weights) and `default` (2D,
//! sticky, slip and moving sticky conditions, two half-spaces with random weights).
//!
//! Error measure of an array: max_k |gpu_k − cpu_k| / max_k |cpu_k| ("relative", as
//! tests/gpu_elements.rs). Of a sum: |gpu − cpu| / Σ_k |term_k|, so that a cancelling sum
//! is judged against its terms. Bounds, all in f64:
//! - 1e-12 for every sum (energy terms, g·Δx, moving energy): the device sums in a tree,
//!   the CPU in sequence, two orders whose difference is at most 2·n·ε·Σ|·| (≈ 1e-13 for
//!   the n ≤ 300 terms here); the energy terms add the element kernels' own differences
//!   from the CPU's, which tests/gpu_elements.rs bounds by 1e-12 per entry.
//! - 1e-14 for the vector updates (projection, x̃, trial, end of step) and the CCD bound:
//!   each entry is one to four roundings apart (a multiply-add the device may contract, a
//!   P x + c against the CPU's x − r), ≤ 4ε relative to the array's scale.
//! - exact for ‖Δx‖∞, node reads and writes, the limiting (node, plane) and the untouched
//!   entries of the moving-term update: a max, a copy or a comparison rounds nothing.
//!
//! Every test shares one device (tests/common/gpu.rs); the scenes are small for lavapipe.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use stickslip::gpu::{GpuContext, GpuError, Precision};
use stickslip::sim::device::assembly::GpuAssembly;
use stickslip::sim::device::elements::{GpuElements, TermKind};
use stickslip::sim::device::newton_ops::conditions::{static_projections, MovingTerm};
use stickslip::sim::device::newton_ops::NewtonOps;
use stickslip::sim::energy::barrier::{Barrier, HalfSpace};
use stickslip::sim::energy::{gravity, inertia, Model};
use stickslip::sim::integrator::{offset, projector};
use stickslip::sim::scene::{self, BcShape, Scene};

mod common;
use common::gpu::gpu;

const SUM_TOL: f64 = 1e-12;
const VEC_TOL: f64 = 1e-14;

fn rel(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let err = a
        .iter()
        .zip(b)
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
    if err == 0.0 {
        0.0
    } else {
        err / scale
    }
}

fn check_vec(what: &str, a: &[f64], b: &[f64], tol: f64) {
    let r = rel(a, b);
    eprintln!("{what}: relative error {r:.2e}");
    assert!(r <= tol, "{what}: relative error {r:e} above {tol:e}");
}

fn check_sum(what: &str, gpu: f64, cpu: f64, abs_sum: f64) {
    let r = if gpu == cpu {
        0.0
    } else {
        (gpu - cpu).abs() / abs_sum
    };
    eprintln!("{what}: device {gpu:e} CPU {cpu:e}, error {r:.2e} of Σ|·|");
    assert!(r <= SUM_TOL, "{what}: {gpu} vs {cpu}: {r:e} of Σ|·|");
}

/// The CPU's start-of-step projection (`Stepper::start_of_step`): single static
/// conditions x − r, nodes with several onto their joint target.
fn project_static(sc: &Scene, x: &mut [f64]) {
    let d = sc.dim;
    let joint = scene::joint_targets(d, &sc.x0, &sc.bcs, sc.characteristic_length)
        .expect("consistent conditions");
    let is_joint = |i: usize| joint.iter().any(|j| j.node == i);
    for b in sc
        .bcs
        .iter()
        .filter(|b| b.motion.is_none() && !is_joint(b.node))
    {
        let xi = &mut x[b.node * d..(b.node + 1) * d];
        let r = offset(d, &b.shape, xi);
        for a in 0..d {
            xi[a] -= r[a];
        }
    }
    for j in &joint {
        j.project(d, &mut x[j.node * d..(j.node + 1) * d]);
    }
}

/// ½ k m ‖r‖² − √m λ·r of one term, as `Stepper::energy` (coef = k m, w = √m λ).
fn moving_energy(d: usize, t: &MovingTerm, x: &[f64]) -> f64 {
    let r = offset(d, &t.shape, &x[t.node * d..(t.node + 1) * d]);
    let rr: f64 = r.iter().map(|v| v * v).sum();
    let lr: f64 = (0..3).map(|a| t.sqrt_m_lambda[a] * r[a]).sum();
    0.5 * t.coef * rr - lr
}

struct Fixture {
    scene: Scene,
    barrier: Barrier,
    planes: Vec<HalfSpace>,
}

/// `drop` (3D, 64 nodes) with its ground and a tilted half-space; `default` (2D) at a
/// quarter of its resolution with two half-spaces and random contact weights. Both
/// planes are placed so that a share of the nodes is within d̂.
fn fixture(d: usize, seed: u64) -> Fixture {
    let mut rng = StdRng::seed_from_u64(seed);
    let (name, size) = if d == 3 {
        ("drop", 1.0)
    } else {
        ("default", 0.25)
    };
    let sc = scene::parse(scene::builtin(name).expect("built-in scene"), name, size)
        .expect("scene parses");
    let mut sc = sc;
    let n = sc.model.n_nodes;
    if d == 3 {
        // `drop` has no boundary conditions: one of each kind, and a node on two planes
        // (projected onto their intersection line), each through or near its node.
        let unit = |r: [f64; 3]| {
            let l = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]).sqrt();
            r.map(|v| v / l)
        };
        let at = |i: usize| [sc.x0[3 * i], sc.x0[3 * i + 1], sc.x0[3 * i + 2]];
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let (n1, n2, n3) = (
            unit([0.2, 1.0, -0.4]),
            unit([1.0, 0.1, 0.3]),
            unit([-0.3, 0.4, 1.0]),
        );
        let shapes = [
            (
                n - 1,
                BcShape::Sticky {
                    anchor: at(n - 1).map(|v| v + 0.003),
                },
            ),
            (
                n - 2,
                BcShape::Plane {
                    normal: n1,
                    offset: dot(n1, at(n - 2)) + 0.002,
                },
            ),
            (
                n - 3,
                BcShape::Line {
                    point: at(n - 3).map(|v| v - 0.004),
                    direction: n3,
                },
            ),
            (
                n - 4,
                BcShape::Plane {
                    normal: n1,
                    offset: dot(n1, at(n - 4)),
                },
            ),
            (
                n - 4,
                BcShape::Plane {
                    normal: n2,
                    offset: dot(n2, at(n - 4)),
                },
            ),
        ];
        for (k, (node, shape)) in shapes.into_iter().enumerate() {
            sc.bcs.push(scene::NodeBc {
                node,
                shape,
                motion: None,
                label: format!("boundary[{k}]"),
            });
        }
    }
    let weight = if sc.contact_weight.is_empty() {
        (0..n)
            .map(|_| {
                if rng.random_bool(0.7) {
                    rng.random_range(0.01..0.2)
                } else {
                    0.0
                }
            })
            .collect()
    } else {
        sc.contact_weight.clone()
    };
    let mut planes = Vec::new();
    for raw in [[0.0, 1.0, 0.0], [0.3, 0.9, -0.2]] {
        let len = raw[..d].iter().map(|v| v * v).sum::<f64>().sqrt();
        let mut normal = [0.0; 3];
        for a in 0..d {
            normal[a] = raw[a] / len;
        }
        let dist: Vec<f64> = sc
            .x0
            .chunks_exact(d)
            .map(|p| p.iter().zip(&normal).map(|(a, b)| a * b).sum())
            .collect();
        let lo = dist.iter().cloned().fold(f64::INFINITY, f64::min);
        let hi = dist.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        planes.push(HalfSpace {
            normal,
            offset: lo - 0.3 * (hi - lo),
            dhat: 0.4 * (hi - lo),
            kappa: 1e4,
        });
    }
    Fixture {
        barrier: Barrier::new(d, weight),
        scene: sc,
        planes,
    }
}

/// Builds the device objects: element terms, assembly, a direction buffer (the positions
/// buffer of a second, barrier-free set of element terms: an f64 buffer of n·d that the
/// test can write) and the operations.
fn build(ctx: &GpuContext, f: &Fixture) -> (GpuElements, GpuAssembly, GpuElements, NewtonOps) {
    let m = &f.scene.model;
    let el = GpuElements::new(
        ctx,
        m,
        Some((&f.barrier, f.planes.as_slice())),
        Precision::F64,
    )
    .expect("element terms");
    let asm = GpuAssembly::new(&el, m).expect("assembly");
    let holder = GpuElements::new(ctx, m, None, Precision::F64).expect("direction holder");
    let ops = NewtonOps::new(&el, &asm, holder.positions_buffer()).expect("newton ops");
    (el, asm, holder, ops)
}

/// The CPU's per-term energies of `kinds` at x (unscaled), with Σ|·| of each.
fn cpu_terms(m: &Model, kinds: &[TermKind], f: &Fixture, x: &[f64], xt: &[f64]) -> Vec<(f64, f64)> {
    let d = m.dim;
    let mut set = 0;
    kinds
        .iter()
        .map(|k| match k {
            TermKind::NeoHookean | TermKind::Springs => {
                let s = &m.sets[set];
                set += 1;
                let e: Vec<f64> = (0..s.len()).map(|e| s.energy(x, e)).collect();
                (e.iter().sum(), e.iter().map(|v| v.abs()).sum())
            }
            TermKind::Inertia => {
                let e = inertia::energy(&m.mass, d, x, xt);
                (e, e.abs())
            }
            TermKind::Gravity => {
                let g = m.gravity.as_ref().expect("gravity");
                let abs: f64 = (0..x.len())
                    .map(|k| (m.mass[k / d] * g[k % d] * x[k]).abs())
                    .sum();
                (gravity::energy(&m.mass, d, g, x), abs)
            }
            TermKind::Barrier => {
                let e = f.barrier.energy(x, &f.planes);
                (e, e.abs())
            }
        })
        .collect()
}

fn check_energies(
    what: &str,
    ops: &NewtonOps,
    el: &GpuElements,
    f: &Fixture,
    x: &[f64],
    xt: &[f64],
) {
    el.evaluate_energy().expect("energy-only evaluation");
    let gpu = ops.energy_terms().expect("energy terms");
    let kinds = ops.kinds().to_vec();
    let cpu = cpu_terms(&f.scene.model, &kinds, f, x, xt);
    for ((k, g), (c, abs)) in kinds.iter().zip(&gpu).zip(&cpu) {
        check_sum(&format!("{what} {k:?} energy"), *g, *c, *abs);
    }
    // Model::potential is the element sets plus gravity.
    let pot: f64 = kinds
        .iter()
        .zip(&gpu)
        .filter(|(k, _)| !matches!(k, TermKind::Inertia | TermKind::Barrier))
        .map(|(_, v)| v)
        .sum();
    let abs: f64 = kinds
        .iter()
        .zip(&cpu)
        .filter(|(k, _)| !matches!(k, TermKind::Inertia | TermKind::Barrier))
        .map(|(_, v)| v.1)
        .sum();
    check_sum(
        &format!("{what} potential"),
        pot,
        f.scene.model.potential(x),
        abs,
    );
}

fn run(ctx: &GpuContext, d: usize, seed: u64) {
    let f = fixture(d, seed);
    let sc = &f.scene;
    let h = sc.time_step;
    let n = sc.model.n_nodes;
    let nd = n * d;
    let mut rng = StdRng::seed_from_u64(seed + 10);
    let (el, asm, holder, mut ops) = build(ctx, &f);
    let cell = sc.characteristic_length * 0.005;
    let x: Vec<f64> = sc
        .x0
        .iter()
        .map(|v| v + rng.random_range(-cell..cell))
        .collect();
    let v: Vec<f64> = (0..nd).map(|_| rng.random_range(-1.0..1.0)).collect();
    ops.set_state(&x, &v).expect("set state");
    let (rx, rv) = ops.read_state().expect("read state");
    assert_eq!((rx.as_slice(), rv.as_slice()), (x.as_slice(), v.as_slice()));

    // Start of step.
    let proj = static_projections(sc).expect("projections");
    assert!(!proj.is_empty(), "the scene has static conditions");
    ops.set_static_projections(&proj).expect("projections");
    ops.begin_step(h).expect("begin step");
    let xt: Vec<f64> = (0..nd).map(|k| x[k] + h * v[k]).collect();
    let mut xp = x.clone();
    project_static(sc, &mut xp);
    let (gx, _) = ops.read_state().expect("read state");
    check_vec(&format!("{d}D projected x"), &gx, &xp, VEC_TOL);
    // x̃ through the inertia gradient m(x − x̃) the element terms compute from it.
    el.evaluate(true).expect("evaluate");
    let terms = el.read().expect("read terms");
    let inertia = terms
        .iter()
        .find(|t| t.kind == TermKind::Inertia)
        .expect("inertia term");
    let want: Vec<f64> = (0..nd)
        .map(|k| sc.model.mass[k / d] * (gx[k] - xt[k]))
        .collect();
    check_vec(&format!("{d}D m(x − x̃)"), &inertia.gradient, &want, 1e-12);
    assert!(
        terms
            .iter()
            .any(|t| t.kind == TermKind::Barrier && t.energy.iter().any(|&e| e > 0.0)),
        "a weighted node is within d̂"
    );
    check_energies(&format!("{d}D at x"), &ops, &el, &f, &gx, &xt);

    // Gradient, direction, slope, max.
    asm.set_scale(h * h);
    el.evaluate(true).expect("evaluate");
    asm.assemble().expect("assemble");
    let g = asm.read_gradient().expect("gradient");
    assert_eq!(ops.read_gradient().expect("gradient"), g);
    let dx: Vec<f64> = (0..nd).map(|_| rng.random_range(-0.05..0.05)).collect();
    holder.set_positions(&dx).expect("dx");
    let slope: f64 = g.iter().zip(&dx).map(|(a, b)| a * b).sum();
    let slope_abs: f64 = g.iter().zip(&dx).map(|(a, b)| (a * b).abs()).sum();
    let before = ctx.traffic();
    let gs = ops.dot_gradient_dx().expect("g·dx");
    let after = ctx.traffic();
    eprintln!(
        "{d}D g·dx read back {} bytes, wrote {} bytes",
        after.device_to_host_bytes - before.device_to_host_bytes,
        after.host_to_device_bytes - before.host_to_device_bytes
    );
    check_sum(&format!("{d}D g·dx"), gs, slope, slope_abs);
    let dmax = dx.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert_eq!(ops.max_abs_dx().expect("max"), dmax);

    // CCD and distances at x along dx: scale dx so that nodes approach the planes.
    let gx_cpu = gx.clone();
    let ccd_cpu = f.barrier.ccd(&gx_cpu, &dx, &f.planes, 0.9);
    let ccd = ops.ccd(&f.planes, 0.9).expect("ccd");
    eprintln!("{d}D ccd: device {ccd:?} CPU {ccd_cpu:?}");
    assert_eq!(ccd.limit, ccd_cpu.limit);
    check_vec(
        &format!("{d}D ccd α"),
        &[ccd.alpha],
        &[ccd_cpu.alpha],
        VEC_TOL,
    );
    // A step that sends everything towards the ground: a bound below 1.
    let down: Vec<f64> = (0..nd)
        .map(|k| {
            if k % d == 1 {
                -1.0 - 0.1 * (k / d) as f64 % 0.7
            } else {
                0.0
            }
        })
        .collect();
    holder.set_positions(&down).expect("dx");
    let ccd_cpu = f.barrier.ccd(&gx_cpu, &down, &f.planes, 0.9);
    let ccd = ops.ccd(&f.planes, 0.9).expect("ccd");
    eprintln!("{d}D ccd downwards: device {ccd:?} CPU {ccd_cpu:?}");
    assert!(ccd_cpu.alpha < 1.0 && ccd_cpu.limit.is_some());
    assert_eq!(ccd.limit, ccd_cpu.limit);
    check_vec(
        &format!("{d}D ccd α down"),
        &[ccd.alpha],
        &[ccd_cpu.alpha],
        VEC_TOL,
    );
    holder.set_positions(&dx).expect("dx");
    let md = ops.min_distance(&f.planes).expect("min distance");
    let md_cpu = f.barrier.min_distance(&gx_cpu, &f.planes);
    eprintln!("{d}D min distance: device {md:?} CPU {md_cpu:?}");
    assert_eq!((md.1, md.2), (md_cpu.1, md_cpu.2));
    check_vec(&format!("{d}D min distance"), &[md.0], &[md_cpu.0], VEC_TOL);

    // Node reads and writes; a node past a plane and a NaN node.
    let pick = [n - 1, 0, n / 2];
    let got = ops.read_nodes(&pick).expect("read nodes");
    let want: Vec<f64> = pick
        .iter()
        .flat_map(|&i| gx[i * d..(i + 1) * d].to_vec())
        .collect();
    assert_eq!(got, want);
    let k = n / 3;
    let mut past = gx[k * d..(k + 1) * d].to_vec();
    past[1] = f.planes[0].offset - 0.01;
    ops.write_nodes(&[k], &past).expect("write node");
    assert_eq!(ops.read_nodes(&[k]).expect("read node"), past);
    let mut xpast = gx.clone();
    xpast[k * d..(k + 1) * d].copy_from_slice(&past);
    let md = ops.min_distance(&f.planes).expect("min distance");
    let md_cpu = f.barrier.min_distance(&xpast, &f.planes);
    eprintln!("{d}D min distance, node {k} past the ground: device {md:?} CPU {md_cpu:?}");
    assert!(md_cpu.0 < 0.0);
    assert_eq!((md.1, md.2), (md_cpu.1, md_cpu.2));
    check_vec("min distance past", &[md.0], &[md_cpu.0], VEC_TOL);
    let ccd_cpu = f.barrier.ccd(&xpast, &dx, &f.planes, 0.9);
    let ccd = ops.ccd(&f.planes, 0.9).expect("ccd");
    eprintln!("{d}D ccd, node {k} past the ground: device {ccd:?} CPU {ccd_cpu:?}");
    assert_eq!(ccd.limit, ccd_cpu.limit);
    assert_eq!(ccd.alpha, ccd_cpu.alpha);
    let mut nan = past.clone();
    nan[0] = f64::NAN;
    let k2 = n / 4;
    ops.write_nodes(&[k2], &nan).expect("write node");
    let mut xnan = xpast.clone();
    xnan[k2 * d..(k2 + 1) * d].copy_from_slice(&nan);
    let md = ops.min_distance(&f.planes).expect("min distance");
    let md_cpu = f.barrier.min_distance(&xnan, &f.planes);
    eprintln!("{d}D min distance with node {k2} NaN: device {md:?} CPU {md_cpu:?}");
    assert!(md.0.is_nan() && md_cpu.0.is_nan());
    assert_eq!((md.1, md.2), (md_cpu.1, md_cpu.2));
    // Back to the projected state.
    ops.write_nodes(
        &[k, k2],
        &[&gx[k * d..(k + 1) * d], &gx[k2 * d..(k2 + 1) * d]].concat(),
    )
    .expect("restore");
    assert_eq!(ops.read_state().expect("state").0, gx);

    // Trial, accept, energies at the trial point.
    let alpha = 0.37;
    ops.set_trial(alpha).expect("trial");
    let xtry: Vec<f64> = (0..nd).map(|k| gx[k] + alpha * dx[k]).collect();
    check_energies(
        &format!("{d}D at the trial point"),
        &ops,
        &el,
        &f,
        &xtry,
        &xt,
    );
    assert_eq!(
        ops.read_state().expect("state").0,
        gx,
        "x kept until accept"
    );
    ops.accept().expect("accept");
    let (ax, _) = ops.read_state().expect("state");
    check_vec(&format!("{d}D accepted trial"), &ax, &xtry, VEC_TOL);

    // Moving terms: the scene's moving nodes (sticky) plus a plane and a line term.
    let mut terms = Vec::new();
    for b in sc.bcs.iter().filter(|b| b.motion.is_some()) {
        terms.push((b.node, b.shape_at(h)));
    }
    let used: Vec<usize> = sc.bcs.iter().map(|b| b.node).collect();
    let mut free = (0..n).filter(|i| !used.contains(i));
    let unit = |raw: [f64; 3]| {
        let l = raw[..d].iter().map(|v| v * v).sum::<f64>().sqrt();
        let mut u = [0.0; 3];
        (0..d).for_each(|a| u[a] = raw[a] / l);
        u
    };
    let pad = |p: &[f64]| {
        let mut q = [0.0; 3];
        q[..d].copy_from_slice(p);
        q
    };
    let i = free.next().expect("a free node");
    terms.push((
        i,
        BcShape::Plane {
            normal: unit([0.6, -0.8, 0.3]),
            offset: 0.05,
        },
    ));
    let i = free.next().expect("a free node");
    terms.push((
        i,
        BcShape::Line {
            point: pad(&xtry[i * d..(i + 1) * d]).map(|v| v + 0.03),
            direction: unit([0.2, 0.5, -0.7]),
        },
    ));
    let i = free.next().expect("a free node");
    terms.push((
        i,
        BcShape::Sticky {
            anchor: pad(&xtry[i * d..(i + 1) * d]).map(|v| v - 0.02),
        },
    ));
    let terms: Vec<MovingTerm> = terms
        .into_iter()
        .map(|(node, shape)| {
            let m = sc.model.mass[node];
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
    ops.set_moving(&terms).expect("moving terms");
    let me_cpu: Vec<f64> = terms.iter().map(|t| moving_energy(d, t, &ax)).collect();
    let me = ops.moving_energy().expect("moving energy");
    check_sum(
        &format!("{d}D moving energy"),
        me,
        me_cpu.iter().sum(),
        me_cpu.iter().map(|v| v.abs()).sum(),
    );
    el.evaluate(true).expect("evaluate");
    asm.assemble().expect("assemble");
    let g0 = asm.read_gradient().expect("gradient");
    let h0 = asm.read_matrix().expect("matrix");
    ops.add_moving().expect("add moving");
    let g1 = asm.read_gradient().expect("gradient");
    let h1 = asm.read_matrix().expect("matrix");
    let is_moving = |i: usize| terms.iter().any(|t| t.node == i);
    for i in (0..n).filter(|&i| !is_moving(i)) {
        assert_eq!(g1[i * d..(i + 1) * d], g0[i * d..(i + 1) * d], "node {i}");
    }
    let dd = d * d;
    for row in 0..n {
        for k in h0.row_ptr[row]..h0.row_ptr[row + 1] {
            if !(h0.col_idx[k] == row && is_moving(row)) {
                assert_eq!(
                    h1.values[k * dd..(k + 1) * dd],
                    h0.values[k * dd..(k + 1) * dd]
                );
            }
        }
    }
    let mut worst_g = 0.0f64;
    let mut worst_fd = 0.0f64;
    let mut worst_h = 0.0f64;
    for t in &terms {
        let i = t.node;
        let xi = &ax[i * d..(i + 1) * d];
        let r = offset(d, &t.shape, xi);
        let p = projector(d, &t.shape);
        // The CPU's gradient k m r − √m P λ and Hessian block k m P.
        let want: Vec<f64> = (0..d)
            .map(|a| {
                let pl: f64 = (0..d).map(|c| p[a * 3 + c] * t.sqrt_m_lambda[c]).sum();
                t.coef * r[a] - pl
            })
            .collect();
        let got: Vec<f64> = (0..d).map(|a| g1[i * d + a] - g0[i * d + a]).collect();
        let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()))
            + g0[i * d..(i + 1) * d]
                .iter()
                .fold(0.0f64, |m, v| m.max(v.abs()));
        for a in 0..d {
            worst_g = worst_g.max((got[a] - want[a]).abs() / scale);
        }
        // Central differences of the moving energy (quadratic in x: exact up to rounding,
        // ≈ ε·E/δ, δ = 1e-6 m).
        let delta = 1e-6;
        for a in 0..d {
            let (mut xp, mut xm) = (ax.clone(), ax.clone());
            xp[i * d + a] += delta;
            xm[i * d + a] -= delta;
            let fd = (moving_energy(d, t, &xp) - moving_energy(d, t, &xm)) / (2.0 * delta);
            worst_fd = worst_fd.max((fd - got[a]).abs() / scale);
        }
        let kb = h0.diag_index(i).expect("diagonal");
        for a in 0..d {
            for c in 0..d {
                let got = h1.values[kb * dd + a * d + c] - h0.values[kb * dd + a * d + c];
                let want = t.coef * p[a * 3 + c];
                let s = h0.values[kb * dd..(kb + 1) * dd]
                    .iter()
                    .fold(t.coef, |m, v| m.max(v.abs()));
                worst_h = worst_h.max((got - want).abs() / s);
            }
        }
    }
    eprintln!(
        "{d}D moving terms: gradient {worst_g:.2e}, finite difference {worst_fd:.2e}, Hessian {worst_h:.2e} (relative to the node's entries)"
    );
    // g1 − g0 and H1 − H0 subtract the assembled entries back out: one rounding of
    // their scale each, hence VEC_TOL relative to it.
    assert!(worst_g <= VEC_TOL, "moving gradient {worst_g:e}");
    assert!(worst_h <= VEC_TOL, "moving Hessian {worst_h:e}");
    assert!(worst_fd <= 1e-6, "finite difference {worst_fd:e}");
    // Dropping the terms: no moving energy.
    ops.set_moving(&[]).expect("no moving terms");
    assert_eq!(ops.moving_energy().expect("moving energy"), 0.0);

    // End of step: v = (x − xⁿ)/h, xⁿ the unprojected start.
    ops.end_step(h).expect("end step");
    let (_, gv) = ops.read_state().expect("state");
    let want: Vec<f64> = (0..nd).map(|k| (ax[k] - x[k]) / h).collect();
    check_vec(&format!("{d}D end-of-step v"), &gv, &want, VEC_TOL);
}

#[test]
fn newton_ops_3d_drop() {
    let Some((ctx, _g)) = gpu() else { return };
    run(ctx, 3, 11);
}

#[test]
fn newton_ops_2d_default() {
    let Some((ctx, _g)) = gpu() else { return };
    run(ctx, 2, 12);
}

/// The reductions are deterministic: the same inputs give the same bits twice.
#[test]
fn reductions_repeat_bitwise() {
    let Some((ctx, _g)) = gpu() else { return };
    let f = fixture(3, 13);
    let (el, asm, holder, ops) = build(ctx, &f);
    let sc = &f.scene;
    ops.set_state(&sc.x0, &vec![0.1; sc.x0.len()])
        .expect("state");
    ops.begin_step(sc.time_step).expect("begin");
    el.evaluate(true).expect("evaluate");
    asm.assemble().expect("assemble");
    let dx: Vec<f64> = (0..sc.x0.len())
        .map(|k| ((k * 37) % 11) as f64 - 5.0)
        .collect();
    holder.set_positions(&dx).expect("dx");
    let once = (
        ops.energy_terms().expect("energies"),
        ops.dot_gradient_dx().expect("dot"),
    );
    let twice = (
        ops.energy_terms().expect("energies"),
        ops.dot_gradient_dx().expect("dot"),
    );
    // Ties: the mesh at rest moving straight down, so every node of the bottom face
    // reaches the ground at the same α and lies at the same distance from it; the CPU
    // keeps the first (smallest node, then plane), and so must the device.
    let down: Vec<f64> = (0..sc.x0.len())
        .map(|k| if k % 3 == 1 { -1.0 } else { 0.0 })
        .collect();
    holder.set_positions(&down).expect("dx");
    let ccd = ops.ccd(&f.planes, 0.9).expect("ccd");
    let ccd_cpu = f.barrier.ccd(&sc.x0, &down, &f.planes, 0.9);
    let md = ops.min_distance(&f.planes).expect("min distance");
    let md_cpu = f.barrier.min_distance(&sc.x0, &f.planes);
    eprintln!(
        "ties: ccd device {ccd:?} CPU {ccd_cpu:?}; min distance device {md:?} CPU {md_cpu:?}"
    );
    let y0 = f.planes[0].distance(&sc.x0[..3]);
    let tied = sc
        .x0
        .chunks_exact(3)
        .filter(|p| f.planes[0].distance(p) == y0)
        .count();
    assert!(tied > 1, "several nodes tie");
    assert_eq!(ccd, ccd_cpu);
    assert_eq!(md, md_cpu);
    assert_eq!(
        (
            once.0.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            once.1.to_bits()
        ),
        (
            twice.0.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            twice.1.to_bits()
        )
    );
}

/// f32 element terms are refused with one line.
#[test]
fn f32_is_refused() {
    let Some((ctx, _g)) = gpu() else { return };
    let f = fixture(2, 14);
    let m = &f.scene.model;
    let el = GpuElements::new(ctx, m, None, Precision::F32).expect("element terms");
    let asm = GpuAssembly::new(&el, m).expect("assembly");
    let holder = GpuElements::new(ctx, m, None, Precision::F64).expect("holder");
    match NewtonOps::new(&el, &asm, holder.positions_buffer()) {
        Err(GpuError::Unsupported(msg)) => {
            assert!(msg.contains("f64") && !msg.contains('\n'), "{msg}")
        }
        Err(e) => panic!("unexpected error {e}"),
        Ok(_) => panic!("f32 element terms were accepted"),
    }
}
