//! The device Newton loop's checks (`sim::device::checks`, shaders/newton_checks.wgsl)
//! against the host's functions: the inversion bound (`Model::inversion_bound`) and the
//! force balance (`force_balance_of`), on small built-in scenes at seeded random states.
//!
//! Bounds, all in f64:
//! - Inversion bound: the same outcome (None, the same (set, element), or the same first
//!   inverted (set, element)), and α and J within [`ROOT_ULPS`] units in the last place.
//!   The device runs the host's operations in the host's order, so with IEEE arithmetic
//!   and no contraction of multiply-adds α and J are the host's bits (what lavapipe gives:
//!   the test prints the largest difference seen). A driver that contracts a multiply-add
//!   in det_polynomial or the Horner evaluation moves a coefficient by one rounding of its
//!   largest term; on these well-shaped elements (each root's condition number is below
//!   about 4, against the cancellations of c₀ … c₃) that is a few ulps of α.
//! - Force balance: the residual within [`RESIDUAL_TOL`] relative (the same ∇E and frames:
//!   d products per component and a norm, ≤ 2d + 2 roundings if a driver contracts them),
//!   its node the same, x_max exact (a maximum of absolute values rounds nothing), and the
//!   scale within [`SCALE_TOL`] relative: it sums the device's element gradients, which
//!   tests/gpu_elements.rs bounds by 1e-12 of the host's per entry, and the barrier's forces
//!   through the device's logarithm (a series accurate to a few ε).
//! - The same checks on element terms split into chunks (several reductions and sums per
//!   term) give exactly the unsplit results: every combine is exact and the sums continue
//!   in element order.
//!
//! Every test shares one device (tests/common/gpu.rs); the scenes are small for lavapipe.

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use stickslip::core::constraints::Frames;
use stickslip::gpu::{GpuContext, Precision};
use stickslip::sim::device::assembly::GpuAssembly;
use stickslip::sim::device::checks::NewtonChecks;
use stickslip::sim::device::elements::GpuElements;
use stickslip::sim::device::newton_ops::NewtonOps;
use stickslip::sim::energy::barrier::{Barrier, HalfSpace};
use stickslip::sim::energy::{AssemblyWork, InversionLimit, Inverted, Model};
use stickslip::sim::integrator::{force_balance_of, ForceBalance, INVERSION_FRACTION};
use stickslip::sim::scene::{self, BcShape, Scene};
use stickslip::Constraint;

mod common;
use common::gpu::gpu;

const ROOT_ULPS: f64 = 8.0;
const RESIDUAL_TOL: f64 = 1e-14;
const SCALE_TOL: f64 = 1e-12;

/// The device objects of one scene: element terms, assembly, a direction buffer (the
/// positions buffer of a second, barrier-free set of element terms: an f64 buffer of n·d
/// the test can write), the loop's operations and the checks.
struct Device {
    el: GpuElements,
    asm: GpuAssembly,
    holder: GpuElements,
    ops: NewtonOps,
    checks: NewtonChecks,
}

/// With `limit`, every per-item array of the element terms and the assembled values are
/// capped at that many bytes (terms split into chunks).
fn build(
    ctx: &GpuContext,
    m: &Model,
    contact: Option<(&Barrier, &[HalfSpace])>,
    limit: Option<u64>,
) -> Device {
    let el = GpuElements::new(ctx, m, contact, Precision::F64).expect("element terms");
    let (el, asm) = match limit {
        None => {
            let asm = GpuAssembly::new(&el, m).expect("assembly");
            (el, asm)
        }
        Some(l) => {
            let el = GpuElements::with_binding_limit(ctx, el.kernels(), m, contact, l)
                .expect("split element terms");
            let asm = GpuAssembly::with_binding_limit(&el, m, l).expect("split assembly");
            (el, asm)
        }
    };
    let holder = GpuElements::new(ctx, m, None, Precision::F64).expect("direction holder");
    let ops = NewtonOps::new(&el, &asm, holder.positions_buffer()).expect("newton ops");
    let checks = NewtonChecks::new(&el, &asm, &ops, m).expect("checks");
    Device {
        el,
        asm,
        holder,
        ops,
        checks,
    }
}

fn parse(name: &str, text: &str, size: f64) -> Scene {
    scene::parse(text, name, size).expect("scene parses")
}

fn builtin(name: &str, size: f64) -> Scene {
    parse(name, scene::builtin(name).expect("built-in scene"), size)
}

/// Units in the last place of `b` between a and b (0 for equal bits, NaN included).
fn ulps(a: f64, b: f64) -> f64 {
    if a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()) {
        return 0.0;
    }
    let ulp = (b.abs() * f64::EPSILON).max(f64::MIN_POSITIVE);
    (a - b).abs() / ulp
}

type Bound = Result<Option<InversionLimit>, Inverted>;

/// Asserts the device's bound is the host's (see the module documentation); returns the
/// ulps between their α or J.
fn same_bound(what: &str, dev: Bound, host: Bound) -> f64 {
    let u = match (dev, host) {
        (Ok(None), Ok(None)) => 0.0,
        (Ok(Some(a)), Ok(Some(b))) if (a.set, a.element) == (b.set, b.element) => {
            ulps(a.alpha, b.alpha)
        }
        (Err(a), Err(b)) if (a.set, a.element) == (b.set, b.element) => ulps(a.j, b.j),
        other => panic!("{what}: device and host disagree: {other:?}"),
    };
    assert!(
        u <= ROOT_ULPS,
        "{what}: {u} ulps apart ({dev:?} vs {host:?})"
    );
    u
}

/// Outcomes met: (no root, a root, inverted).
#[derive(Default, Debug)]
struct Seen {
    none: usize,
    root: usize,
    inverted: usize,
    worst_ulps: f64,
}

impl Seen {
    fn note(&mut self, b: &Bound, u: f64) {
        match b {
            Ok(None) => self.none += 1,
            Ok(Some(_)) => self.root += 1,
            Err(_) => self.inverted += 1,
        }
        self.worst_ulps = self.worst_ulps.max(u);
    }
}

/// Seeded random states of `sc`: x within 1% of L of the rest shape, Δx of random
/// direction at sizes from 1e-3 L (no element inverts within `max`) to 0.5 L (many do),
/// then per set of `invert` an element of it inverted at x, and a NaN position on one of
/// its nodes. Every state on the unsplit and the split device objects.
fn inversion_cases(
    ctx: &GpuContext,
    sc: &Scene,
    seed: u64,
    trials: usize,
    invert: &[usize],
) -> Seen {
    let m = &sc.model;
    let n = m.n_nodes;
    let d = m.dim;
    let l = sc.characteristic_length;
    let whole = build(ctx, m, None, None);
    // Chunks of about a tenth of the largest element set.
    let nl = (d + 1) * d;
    let largest = m.sets.iter().map(|s| s.len()).max().unwrap_or(1);
    let split = build(
        ctx,
        m,
        None,
        Some((nl * nl * 8 * largest.div_ceil(10)) as u64),
    );
    let max = 1.0 / INVERSION_FRACTION;
    let mut rng = StdRng::seed_from_u64(seed);
    let mut seen = Seen::default();
    let mut run = |what: &str, x: &[f64], dx: &[f64]| {
        let host = m.inversion_bound(x, dx, max);
        for (dev_name, dev) in [("whole", &whole), ("split", &split)] {
            dev.ops.set_state(x, &vec![0.0; n * d]).expect("state");
            dev.holder.set_positions(dx).expect("direction");
            let got = dev.checks.inversion_bound(max).expect("device bound");
            let u = same_bound(&format!("{what} ({dev_name})"), got, host);
            if dev_name == "whole" {
                seen.note(&host, u);
            } else {
                assert_eq!(
                    format!("{got:?}"),
                    format!("{:?}", whole.checks.inversion_bound(max).expect("bound")),
                    "{what}: split and whole terms differ"
                );
            }
        }
    };
    let rest = sc.x0.clone();
    for t in 0..trials {
        let x: Vec<f64> = rest
            .iter()
            .map(|v| v + rng.random_range(-0.01 * l..0.01 * l))
            .collect();
        let size = l * 10f64.powf(rng.random_range(-3.0..-0.3));
        let dx: Vec<f64> = (0..n * d)
            .map(|_| size * rng.random_range(-1.0..1.0))
            .collect();
        run(&format!("trial {t}"), &x, &dx);
    }
    let dx: Vec<f64> = (0..n * d).map(|_| rng.random_range(-0.01..0.01)).collect();
    for &k in invert {
        // Node 1 of a middle element reflected through node 0 (its neighbours may invert
        // too; the first one counts).
        let el = m.sets[k].nodes(m.sets[k].len() / 2).to_vec();
        let mut x = rest.clone();
        for a in 0..d {
            x[el[1] * d + a] = 2.0 * x[el[0] * d + a] - x[el[1] * d + a];
        }
        run(&format!("inverted element of set {k}"), &x, &dx);
        // A NaN position: its elements are inverted (c₀ is NaN), J NaN.
        let mut x = rest.clone();
        x[el[2] * d] = f64::NAN;
        run(&format!("NaN position in set {k}"), &x, &dx);
    }
    seen
}

#[test]
fn inversion_bound_3d_twist() {
    let Some((ctx, _g)) = gpu() else { return };
    let sc = builtin("twist", 1.0);
    let seen = inversion_cases(ctx, &sc, 11, 24, &[0]);
    eprintln!("twist (3D, {} elements): {seen:?}", sc.model.sets[0].len());
    assert!(
        seen.none > 0 && seen.root > 0 && seen.inverted >= 2,
        "{seen:?}"
    );
}

/// Two bodies, the first of the stable law (never bounded) and the second classical: the
/// element indices of the second set are global, and the stable set's elements never count,
/// even inverted.
#[test]
fn inversion_bound_2d_two_bodies() {
    let Some((ctx, _g)) = gpu() else { return };
    let text = r#"
name = "two"
dimension = 2
time_step = 0.01
steps = 1
gravity = [0.0, -9.81]
[[bodies]]
mesh = { kind = "rectangle", size = [1.0, 0.5], cells = [6, 3] }
material = { model = "stable-neo-hookean", young = 1e4, poisson = 0.4, density = 100.0 }
[[bodies]]
mesh = { kind = "rectangle", size = [1.0, 0.5], cells = [8, 4], origin = [0.0, 1.0] }
material = { model = "neo-hookean", young = 1e4, poisson = 0.4, density = 100.0 }
"#;
    let sc = parse("two", text, 1.0);
    assert_eq!(sc.model.sets.len(), 2);
    let seen = inversion_cases(ctx, &sc, 12, 24, &[0, 1]);
    eprintln!("two bodies (2D): {seen:?}");
    // Only the two cases of set 1 are inverted: set 0's elements do not count.
    assert!(
        seen.none > 0 && seen.root > 0 && seen.inverted == 2,
        "{seen:?}"
    );
}

#[test]
fn inversion_bound_2d_default() {
    let Some((ctx, _g)) = gpu() else { return };
    let sc = builtin("default", 0.25);
    let seen = inversion_cases(ctx, &sc, 13, 24, &[0]);
    eprintln!(
        "default (2D, {} elements): {seen:?}",
        sc.model.sets[0].len()
    );
    assert!(
        seen.none > 0 && seen.root > 0 && seen.inverted >= 2,
        "{seen:?}"
    );
}

/// The homogeneous constraints of every boundary condition of `sc` (moving ones snapped).
fn frames(sc: &Scene) -> Frames {
    let d = sc.dim;
    let cs: Vec<Constraint> = sc
        .bcs
        .iter()
        .map(|b| match &b.shape {
            BcShape::Sticky { .. } => Constraint::sticky(b.node),
            BcShape::Plane { normal, .. } => Constraint::plane(b.node, &normal[..d]),
            BcShape::Line { direction, .. } => Constraint::line(b.node, &direction[..d]),
        })
        .collect();
    Frames::build(d, sc.model.n_nodes, &cs).expect("consistent constraints")
}

fn rel(a: f64, b: f64) -> f64 {
    if a == b {
        0.0
    } else {
        (a - b).abs() / b.abs()
    }
}

/// Compares one state's force balance; returns (residual, scale) relative errors.
fn same_balance(what: &str, dev: ForceBalance, host: ForceBalance) -> (f64, f64) {
    let (r, s) = (rel(dev.residual, host.residual), rel(dev.scale, host.scale));
    eprintln!(
        "{what}: residual {:e} at node {} (error {r:.1e}), scale {:e} (error {s:.1e}), x_max {:e}",
        host.residual, host.node, host.scale, host.x_max
    );
    assert!(r <= RESIDUAL_TOL, "{what}: residual {dev:?} vs {host:?}");
    assert_eq!(dev.node, host.node, "{what}: {dev:?} vs {host:?}");
    assert!(s <= SCALE_TOL, "{what}: scale {dev:?} vs {host:?}");
    assert_eq!(dev.x_max, host.x_max, "{what}");
    (r, s)
}

/// Seeded random states of `sc` (x within `amp`·L of `x0`, v random): the device's force
/// balance against the host's on the gradient the device assembled, on the unsplit and
/// the split element terms.
fn balance_cases(
    ctx: &GpuContext,
    sc: &Scene,
    planes: &[HalfSpace],
    (x0, amp): (&[f64], f64),
    seed: u64,
) {
    let m = &sc.model;
    let (n, d) = (m.n_nodes, m.dim);
    let h = sc.time_step;
    let l = sc.characteristic_length;
    let barrier = Barrier::new(d, sc.contact_weight.clone());
    let contact = (!planes.is_empty()).then_some((&barrier, planes));
    let f = frames(sc);
    let whole = build(ctx, m, contact, None);
    let largest = m.sets.iter().map(|s| s.len()).max().unwrap_or(1);
    let nl = (d + 1) * d;
    let split = build(
        ctx,
        m,
        contact,
        Some((nl * nl * 8 * largest.div_ceil(4)) as u64),
    );
    let mut rng = StdRng::seed_from_u64(seed);
    let mut work = AssemblyWork::default();
    for t in 0..3 {
        let x: Vec<f64> = x0
            .iter()
            .map(|v| v + rng.random_range(-amp * l..amp * l))
            .collect();
        let v: Vec<f64> = (0..n * d).map(|_| rng.random_range(-1.0..1.0)).collect();
        let xt: Vec<f64> = (0..n * d).map(|k| x[k] + h * v[k]).collect();
        let mut results = Vec::new();
        for (name, dev) in [("whole", &whole), ("split", &split)] {
            dev.ops.set_state(&x, &v).expect("state");
            dev.el.set_inertia_target(&xt).expect("inertia target");
            dev.el.evaluate(true).expect("element terms");
            dev.asm.assemble().expect("assembly");
            let g = dev.asm.read_gradient().expect("gradient");
            let host = force_balance_of(m, contact, h, &x, &xt, &g, &f, &mut work);
            let bf = dev.checks.frames(&f).expect("frames");
            let got = dev.checks.force_balance(&bf, h).expect("device balance");
            same_balance(&format!("{} state {t} ({name})", sc.name), got, host);
            results.push(got);
        }
        assert_eq!(results[0], results[1], "split and whole terms differ");
    }
}

/// `incline` (3D): slip nodes on a plane tilted by 30°, rotated frames; gravity.
#[test]
fn force_balance_3d_incline() {
    let Some((ctx, _g)) = gpu() else { return };
    let sc = builtin("incline", 1.0);
    let f = frames(&sc);
    assert!(f.has_rotation(), "incline has rotated slip frames");
    balance_cases(ctx, &sc, &[], (&sc.x0, 0.005), 21);
}

/// `compress` (2D): slip nodes on two planes (masks, no rotation: the normals are axes),
/// one of them moving (snapped here); gravity.
#[test]
fn force_balance_2d_compress() {
    let Some((ctx, _g)) = gpu() else { return };
    let sc = builtin("compress", 0.5);
    assert!(
        frames(&sc).has_constraints(),
        "compress has slip conditions"
    );
    balance_cases(ctx, &sc, &[], (&sc.x0, 0.005), 22);
}

/// `drop` (3D) lowered into its ground's d̂ (0.01 L), with a tilted wall within d̂ of one
/// corner: nodes within d̂ of one plane and of both, none touching (x within 0.001 L).
#[test]
fn force_balance_3d_drop_barrier() {
    let Some((ctx, _g)) = gpu() else { return };
    let sc = builtin("drop", 1.0);
    let ground = sc.obstacles[0].at(0.0);
    let d = sc.dim;
    let lowest = (0..sc.model.n_nodes)
        .map(|i| sc.x0[i * d + 1])
        .fold(f64::INFINITY, f64::min);
    let drop = lowest - ground.offset - 0.4 * ground.dhat;
    let x0: Vec<f64> = (0..sc.x0.len())
        .map(|k| sc.x0[k] - if k % d == 1 { drop } else { 0.0 })
        .collect();
    let s = std::f64::consts::FRAC_1_SQRT_2;
    let normal = [s, 0.0, s];
    let corner = (0..sc.model.n_nodes)
        .map(|i| normal[0] * x0[i * d] + normal[2] * x0[i * d + 2])
        .fold(f64::INFINITY, f64::min);
    let wall = HalfSpace {
        normal,
        offset: corner - 0.5 * ground.dhat,
        ..ground
    };
    let planes = [ground, wall];
    let near = |p: &HalfSpace| {
        (0..sc.model.n_nodes)
            .filter(|&i| p.distance(&x0[i * d..(i + 1) * d]) < 0.9 * p.dhat)
            .count()
    };
    assert!(near(&ground) > 0 && near(&wall) > 0, "nodes within d̂");
    balance_cases(ctx, &sc, &planes, (&x0, 0.001), 23);
}
