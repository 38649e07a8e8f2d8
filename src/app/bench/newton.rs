//! `stickslip bench --newton`: one Newton iteration of the implicit-Euler incremental
//! potential (the integrator's `newton_direction` and `line_search`), phase by phase, on
//! the CPU and on the GPU, over a ladder of 3D box meshes of tetrahedra.
//!
//! The scene at every size: a neo-Hookean bar of 4k × k × k cells (6 tetrahedra each),
//! rotated 30° about z like the `incline` scene, its left end sticky and its bottom face
//! slipping on the tilted plane (rotated node frames), gravity on. The iterate x is the
//! rest shape under a smooth bend, shear and stretch that vanishes at the sticky end and
//! keeps the bottom face on its plane; x̃ = rest (a step from rest).
//!
//! The four phases of one iteration:
//! 1. assembly: ∇E and the PSD-projected ∇²E into the block matrix;
//! 2. elimination and preconditioner: b̂ = −P Vᵀ g and block-Jacobi on Ĥ;
//! 3. linear solve: CG to ‖b̂ − Ĥy‖/‖b̂‖ ≤ 1e-8, block-Jacobi, no coarse correction, then
//!    Δx = V y;
//! 4. line search: E(x + Δx) (one trial, α = 1) and gᵀΔx.
//!
//! CPU: f64 on every rayon worker (`--threads`): `Model`'s parallel assembly, `Eliminated`
//! and `BuiltPreconditioner`, the fused CPU CG, the model's energy. GPU (f64): phase 1 is
//! `GpuElements::evaluate` + `GpuAssembly::assemble`, waited for; phases 2–4 are the
//! device Newton loop's (`gpu::pcg`, `sim::device`): `DeviceCg::prepare` (b̂ and the
//! preconditioners from the assembled blocks), `DeviceCg::iterate` (PCG, true residual, Δx = V P y) and
//! `NewtonOps` (the trial point, an energy-only pass reduced per term, gᵀΔx). A phase that
//! fails to run is absent: null (JSON), an empty cell (CSV) and "n/a" (table).
//!
//! Every phase runs once as a warm-up, then `reps` times; a phase's time is the median of
//! those. A side's total is the sum of its four medians, absent when a phase is.

use crate::app::bench::measure::say;
use crate::app::bench::newton_report::{
    size_line, write_outputs, AssemblyDifference, CpuCheck, GpuCgRecord, Machine, NewtonReport,
    Phases, SideRecord, SizeRecord,
};
use crate::core::constraints::{Constraint, ConstraintKind, Frames};
use crate::core::elimination::{ConstrainedDiagonal, Eliminated};
use crate::core::sparse::BlockCsr;
use crate::error::InputError;
use crate::gpu::pcg::{DeviceCg, DeviceCgParams, DeviceFrames};
use crate::gpu::{GpuContext, GpuOptions, Phase, Precision};
use crate::sim::device::assembly::GpuAssembly;
use crate::sim::device::elements::GpuElements;
use crate::sim::device::newton_ops::NewtonOps;
use crate::sim::energy::{inertia, AssemblyWork};
use crate::sim::scene::{BcShape, Scene};
use crate::solve::cg::{self, BuiltPreconditioner, CgParams, Preconditioner};
use crate::solve::coarse::CoarseSpace;
use std::path::PathBuf;
use std::time::Instant;

/// CG tolerance of phase 3, both sides: ‖b̂ − Ĥy‖/‖b̂‖.
pub const CG_TOL: f64 = 1e-8;
/// CG iteration limit of phase 3.
pub const CG_MAX_ITERS: usize = 20_000;
/// Timed repetitions after the warm-up: default and `--quick`.
pub const REPS: usize = 5;
pub const QUICK_REPS: usize = 2;
/// The default ladder: k of the 4k × k × k cell grid, (4k+1)(k+1)² nodes, from 2,673 to
/// 1,036,288 nodes.
pub const LADDER: [usize; 5] = [8, 16, 25, 40, 63];
/// `--quick`: 425 and 2,673 nodes.
pub const QUICK_LADDER: [usize; 2] = [4, 8];

/// Host memory per node, bytes: the scene (mesh, model with its gather maps and pattern)
/// and the CPU side's own buffers (element gradients and Hessians, 816 B per tetrahedron
/// at about 5.7 tetrahedra per node; H; the CG vectors). The peak resident memory of a
/// whole `--no-gpu` run was 8.9 kB per node at 68,276 nodes and 9.1 kB at 270,641, about
/// 6 kB of it the CPU side's by count; both are rounded up here.
const SCENE_BYTES_PER_NODE: u64 = 4_000;
const CPU_BYTES_PER_NODE: u64 = 7_000;

/// What to run.
#[derive(Debug, Clone)]
pub struct NewtonOptions {
    pub quick: bool,
    /// Approximate node counts instead of the ladder (each mapped to the nearest k).
    pub sizes: Option<Vec<usize>>,
    pub no_gpu: bool,
    /// Timed repetitions per phase (after one warm-up); None: [`REPS`] or [`QUICK_REPS`].
    pub reps: Option<usize>,
    pub out: Option<PathBuf>,
    pub quiet: bool,
}

/// Errors of the benchmark: no usable GPU (exit 1), or unwritable output.
#[derive(Debug, thiserror::Error)]
pub enum NewtonBenchError {
    #[error("{0}")]
    Gpu(String),
    #[error("{0}")]
    Io(String),
}

/// Nodes of the 4k × k × k box.
pub fn box_nodes(k: usize) -> usize {
    (4 * k + 1) * (k + 1) * (k + 1)
}

/// The k of each size to run: the ladder, or the nearest k (in log of the node count) to
/// each of `--sizes`, in the order given. Sizes that the scene cap refuses are input errors.
pub fn plan(opts: &NewtonOptions) -> Result<Vec<usize>, InputError> {
    let Some(sizes) = &opts.sizes else {
        return Ok(if opts.quick {
            QUICK_LADDER.to_vec()
        } else {
            LADDER.to_vec()
        });
    };
    let cap = crate::sim::mesh::MAX_SCENE_NODES_3D;
    let mut ks = Vec::new();
    for &n in sizes {
        if n == 0 || n > cap {
            return Err(InputError::new(
                "command line",
                "--sizes",
                format!("{n} nodes: each size must be in 1..={cap} (the 3D scene cap)"),
            ));
        }
        let target = (n as f64).ln();
        let dist = |k: usize| ((box_nodes(k) as f64).ln() - target).abs();
        let k = (1..)
            .take_while(|&k| box_nodes(k) <= cap)
            .min_by(|&a, &b| dist(a).total_cmp(&dist(b)))
            .unwrap_or(1);
        ks.push(k);
    }
    Ok(ks)
}

/// The bench scene at grid parameter k (see the module documentation). Its body follows
/// the stable neo-Hookean law, the one BENCHMARKS.md's figures were measured with.
pub fn scene_toml(k: usize) -> String {
    format!(
        r#"name = "newton-bench"
dimension = 3
time_step = 0.01
steps = 1
gravity = [0.0, -9.81, 0.0]

[[bodies]]
mesh = {{ kind = "box", size = [1.0, 0.25, 0.25], cells = [{cx}, {k}, {k}], rotate_degrees = 30.0 }}
material = {{ model = "stable-neo-hookean", young = 1e5, poisson = 0.4, density = 1000.0 }}

[[boundary]]
kind = "sticky"
region = {{ plane = {{ normal = [{c}, {s}, 0.0], offset = 0.0, tolerance = 1e-9 }} }}

[[boundary]]
kind = "plane"
normal = [-{s}, {c}, 0.0]
offset = 0.0
region = {{ plane = {{ normal = [-{s}, {c}, 0.0], offset = 0.0, tolerance = 1e-9 }} }}
"#,
        cx = 4 * k,
        c = AXIS[0],
        s = AXIS[1],
    )
}

/// The bar's axis after the 30° rotation: (cos 30°, sin 30°, 0); the slip plane's normal
/// is (−sin 30°, cos 30°, 0).
const AXIS: [f64; 3] = [0.866_025_403_784_438_6, 0.5, 0.0];
const NORMAL: [f64; 3] = [-0.5, 0.866_025_403_784_438_6, 0.0];

/// The iterate: rest positions displaced by u(s, t, w) (s along the bar from the sticky
/// end, t the height above the slip plane, w along z): a sideways bend, an axial stretch
/// and shears, zero at s = 0 and with no normal part at t = 0, so both conditions hold.
pub fn iterate(x0: &[f64]) -> Vec<f64> {
    let mut x = x0.to_vec();
    for p in x.chunks_exact_mut(3) {
        let s = p[0] * AXIS[0] + p[1] * AXIS[1];
        let t = p[0] * NORMAL[0] + p[1] * NORMAL[1];
        let w = p[2];
        let ua = 0.02 * (std::f64::consts::PI * s).sin() + 0.05 * s * (w - 0.125);
        let un = 0.2 * s * t;
        let uz = 0.05 * s * s + 0.1 * s * t;
        for a in 0..3 {
            p[a] += ua * AXIS[a] + un * NORMAL[a];
        }
        p[2] += uz;
    }
    x
}

/// The static conditions of the scene as constraints (homogeneous: Δx has no constrained
/// component, as in every Newton step of the integrator).
fn frames(scene: &Scene) -> Result<Frames, String> {
    let cs: Vec<Constraint> = scene
        .bcs
        .iter()
        .map(|b| Constraint {
            node: b.node,
            kind: match &b.shape {
                BcShape::Sticky { .. } => ConstraintKind::Sticky { displacement: None },
                BcShape::Plane { normal, .. } => ConstraintKind::Plane {
                    normal: normal.to_vec(),
                    offset: 0.0,
                },
                BcShape::Line { direction, .. } => ConstraintKind::Line {
                    direction: direction.to_vec(),
                    offset: None,
                },
            },
            label: b.label.clone(),
        })
        .collect();
    Frames::build(3, scene.model.n_nodes, &cs).map_err(|e| e.to_string())
}

/// MemAvailable from /proc/meminfo, bytes; 0 where unknown.
fn memory_available() -> u64 {
    std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("MemAvailable:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

fn gib(b: u64) -> f64 {
    b as f64 / (1u64 << 30) as f64
}

/// Median of the samples (mean of the middle two for an even count).
pub fn median(v: &[f64]) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let m = s.len() / 2;
    Some(if s.len() % 2 == 1 {
        s[m]
    } else {
        0.5 * (s[m - 1] + s[m])
    })
}

/// Per-phase samples over the repetitions; a phase that reports itself absent has none.
#[derive(Default)]
struct Samples([Vec<f64>; 4]);

impl Samples {
    fn phases(&self) -> Phases {
        Phases {
            assembly: median(&self.0[0]),
            elimination: median(&self.0[1]),
            solve: median(&self.0[2]),
            line_search: median(&self.0[3]),
        }
    }
}

/// The CPU side's state at one size: the model's assembly buffers and the iterate.
struct CpuSide<'s> {
    scene: &'s Scene,
    frames: &'s Frames,
    x: &'s [f64],
    xt: &'s [f64],
    h: BlockCsr,
    g: Vec<f64>,
    work: AssemblyWork,
    xtry: Vec<f64>,
}

impl<'s> CpuSide<'s> {
    fn new(scene: &'s Scene, frames: &'s Frames, x: &'s [f64], xt: &'s [f64]) -> Self {
        CpuSide {
            scene,
            frames,
            x,
            xt,
            h: scene.model.zero_matrix(),
            g: vec![0.0; x.len()],
            work: AssemblyWork::default(),
            xtry: vec![0.0; x.len()],
        }
    }

    fn h2(&self) -> f64 {
        self.scene.time_step * self.scene.time_step
    }

    /// Phase 1: g = M(x − x̃) + h²∇Ψ and H = M + h² proj ∇²Ψ (the integrator's order).
    fn assemble(&mut self) {
        let m = &self.scene.model;
        let h2 = self.h2();
        self.g.iter_mut().for_each(|v| *v = 0.0);
        inertia::add_gradient(&m.mass, 3, self.x, self.xt, &mut self.g);
        m.add_potential_gradient_with(self.x, h2, &mut self.g, &mut self.work);
        self.h.values.iter_mut().for_each(|v| *v = 0.0);
        m.add_mass(&mut self.h);
        m.add_potential_hessian_with(self.x, h2, true, &mut self.h, &mut self.work);
    }

    /// E(x) for the step (inertia + h²Ψ).
    fn energy(&self, x: &[f64]) -> f64 {
        let m = &self.scene.model;
        inertia::energy(&m.mass, 3, x, self.xt) + self.h2() * m.potential(x)
    }
}

/// Phase 2 on the CPU: the eliminated system and its block-Jacobi preconditioner.
fn cpu_eliminate<'a>(
    h: &'a BlockCsr,
    g: &[f64],
    frames: &'a Frames,
) -> (Eliminated<'a>, BuiltPreconditioner) {
    let e = Eliminated::new(h, g, frames, ConstrainedDiagonal::Identity);
    let pre = BuiltPreconditioner::new(&e, Preconditioner::BlockJacobi);
    (e, pre)
}

fn cg_params() -> CgParams {
    CgParams {
        tol: CG_TOL,
        max_iters: CG_MAX_ITERS,
        preconditioner: Preconditioner::BlockJacobi,
        coarse: CoarseSpace::None,
        ..CgParams::default()
    }
}

/// Phase 3 on the CPU: the fused CG, then Δx = V y.
fn cpu_solve(e: &Eliminated, pre: &BuiltPreconditioner) -> Result<(Vec<f64>, cg::CgInfo), String> {
    let (y, info) = cg::solve_with(e, pre, None, &cg_params()).map_err(|err| err.to_string())?;
    Ok((e.recover(&y), info))
}

/// Phase 4 on the CPU: E(x + Δx) and gᵀΔx.
fn cpu_line_search(side: &mut CpuSide, dx: &[f64]) -> (f64, f64) {
    let mut xtry = std::mem::take(&mut side.xtry);
    for ((t, x), d) in xtry.iter_mut().zip(side.x).zip(dx) {
        *t = x + d;
    }
    let e1 = side.energy(&xtry);
    side.xtry = xtry;
    let slope: f64 = side.g.iter().zip(dx).map(|(a, b)| a * b).sum();
    (e1, slope)
}

/// Runs the CPU side: a warm-up and `reps` timed repetitions of the four phases.
fn run_cpu(side: &mut CpuSide, reps: usize) -> Result<(Phases, CpuCheck), String> {
    let mut s = Samples::default();
    let mut check = CpuCheck::default();
    for rep in 0..=reps {
        let timed = rep > 0;
        let t = Instant::now();
        side.assemble();
        let t1 = t.elapsed().as_secs_f64();
        // Positions far from rest could overflow the element terms; a non-finite system
        // would make every later number meaningless.
        if let Some(bad) = side.h.values.iter().chain(&side.g).find(|v| !v.is_finite()) {
            return Err(format!("the assembled system holds {bad}"));
        }
        let t = Instant::now();
        let (e, pre) = cpu_eliminate(&side.h, &side.g, side.frames);
        let t2 = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let (dx, info) = cpu_solve(&e, &pre)?;
        let t3 = t.elapsed().as_secs_f64();
        drop((e, pre));
        let t = Instant::now();
        let (e1, slope) = cpu_line_search(side, &dx);
        let t4 = t.elapsed().as_secs_f64();
        if timed {
            for (k, v) in [t1, t2, t3, t4].into_iter().enumerate() {
                s.0[k].push(v);
            }
        } else {
            check = CpuCheck {
                cg_iterations: info.iterations,
                relative_residual: info.relative_residual,
                slope,
                energy_change: e1 - side.energy(side.x),
            };
        }
    }
    Ok((s.phases(), check))
}

/// The device side at one size: the element terms and the assembly (phase 1) now; the
/// device CG and the loop's operations (phases 2–4) plug in at `GpuSide::eliminate`,
/// `GpuSide::solve` and `GpuSide::line_search`.
/// The device CG of phase 3.
const GPU_CG: DeviceCgParams = DeviceCgParams {
    tol: CG_TOL,
    max_iterations: 100_000,
    preconditioner: Preconditioner::BlockJacobi,
    coarse: crate::solve::coarse::CoarseSpace::None,
    stagnation_window: crate::solve::cg::STAGNATION_WINDOW,
};

struct GpuSide {
    /// CG iterations of the last solve.
    cg_iterations: usize,
    elements: GpuElements,
    assembly: GpuAssembly,
    cg: DeviceCg,
    frames: DeviceFrames,
    ops: NewtonOps,
    /// h², the factor of the potential terms in E.
    h2: f64,
}

impl GpuSide {
    /// Uploads the mesh, the iterate x, x̃ and the scale h² (f64 throughout).
    fn new(
        ctx: &GpuContext,
        scene: &Scene,
        x: &[f64],
        xt: &[f64],
        frames: &Frames,
    ) -> Result<Self, String> {
        let elements =
            GpuElements::new(ctx, &scene.model, None, Precision::F64).map_err(|e| e.to_string())?;
        elements.set_positions(x).map_err(|e| e.to_string())?;
        elements.set_inertia_target(xt).map_err(|e| e.to_string())?;
        let assembly = GpuAssembly::new(&elements, &scene.model).map_err(|e| e.to_string())?;
        assembly.set_scale(scene.time_step * scene.time_step);
        let cg = assembly.device_cg().map_err(|e| e.to_string())?;
        let frames = cg
            .frames(frames, GPU_CG.coarse)
            .map_err(|e| e.to_string())?;
        let ops =
            NewtonOps::new(&elements, &assembly, cg.dx_buffer()).map_err(|e| e.to_string())?;
        ops.set_state(x, &vec![0.0; x.len()])
            .map_err(|e| e.to_string())?;
        Ok(GpuSide {
            cg_iterations: 0,
            elements,
            assembly,
            cg,
            frames,
            ops,
            h2: scene.time_step * scene.time_step,
        })
    }

    /// Phase 1: the element terms (PSD-projected) and the assembly of H and g, waited for.
    fn assemble(&mut self) -> Result<Option<()>, String> {
        let ctx = self.elements.context().clone();
        let terms = ctx.phase(Phase::ElementTerms);
        self.elements.evaluate(true).map_err(|e| e.to_string())?;
        drop(terms);
        let _assembly = ctx.phase(Phase::Assembly);
        self.assembly.assemble().map_err(|e| e.to_string())?;
        self.assembly.wait().map_err(|e| e.to_string())?;
        Ok(Some(()))
    }

    /// Phase 2: b̂ and the preconditioners on the device, from the assembled H and g
    /// and the node frames (uploaded once, as the loop keeps them per constraint set),
    /// waited for.
    fn eliminate(&mut self) -> Result<Option<()>, String> {
        let _phase = self.elements.context().phase(Phase::Elimination);
        self.cg.prepare(&self.frames).map_err(|e| e.to_string())?;
        self.assembly.wait().map_err(|e| e.to_string())?;
        Ok(Some(()))
    }

    /// Phase 3: the device CG to [`CG_TOL`] (block-Jacobi), the true residual and
    /// Δx = V P y (its last status read waits for the device).
    fn solve(&mut self) -> Result<Option<()>, String> {
        let _phase = self.elements.context().phase(Phase::Cg);
        let info = self
            .cg
            .iterate(&self.frames, &GPU_CG)
            .map_err(|e| e.to_string())?;
        self.cg_iterations = info.iterations;
        Ok(Some(()))
    }

    /// The CG's iteration record, its solve having taken `seconds`.
    fn cg_record(&self, seconds: f64) -> Result<GpuCgRecord, String> {
        let profile = self
            .cg
            .iteration_profile(&self.frames, &GPU_CG)
            .map_err(|e| e.to_string())?;
        let per_it = seconds / self.cg_iterations.max(1) as f64;
        Ok(GpuCgRecord {
            iterations: self.cg_iterations,
            seconds_per_iteration: per_it,
            bytes_per_iteration: profile.bytes,
            gb_per_second: profile.bytes as f64 / per_it / 1e9,
            dispatches_per_iteration: profile.dispatches,
        })
    }

    /// Phase 4: the trial x + Δx, E there (an energy-only pass, one sum per term) and
    /// gᵀΔx on the device, then the evaluation positions back to x (as the loop's accept
    /// copies them the other way), so that the next repetition assembles at x again.
    fn line_search(&mut self) -> Result<Option<()>, String> {
        let err = |e: crate::gpu::GpuError| e.to_string();
        let _phase = self.elements.context().phase(Phase::LineSearch);
        self.ops.set_trial(1.0).map_err(err)?;
        self.elements.evaluate_energy().map_err(err)?;
        let terms = self.ops.energy_terms().map_err(err)?;
        let slope = self.ops.dot_gradient_dx().map_err(err)?;
        self.ops.set_trial(0.0).map_err(err)?;
        let (mut inertia, mut rest) = (0.0, 0.0);
        for (k, e) in self.ops.kinds().iter().zip(&terms) {
            match k {
                crate::sim::device::elements::TermKind::Inertia => inertia += e,
                _ => rest += e,
            }
        }
        let e = inertia + self.h2 * rest;
        if !e.is_finite() || !slope.is_finite() {
            return Err(format!(
                "the device line search gave E = {e:e}, gᵀΔx = {slope:e}"
            ));
        }
        Ok(Some(()))
    }

    /// The assembled H and g, read back, against the CPU's.
    fn difference(&self, h: &BlockCsr, g: &[f64]) -> Result<AssemblyDifference, String> {
        let hd = self.assembly.read_matrix().map_err(|e| e.to_string())?;
        let gd = self.assembly.read_gradient().map_err(|e| e.to_string())?;
        if hd.col_idx != h.col_idx || hd.row_ptr != h.row_ptr {
            return Err("the device's block pattern is not the CPU's".into());
        }
        let rel = |a: &[f64], b: &[f64]| {
            let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let diff = a
                .iter()
                .zip(b)
                .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
            diff / scale
        };
        Ok(AssemblyDifference {
            hessian: rel(&hd.values, &h.values),
            gradient: rel(&gd, g),
        })
    }
}

/// Runs the GPU side: a warm-up and `reps` timed repetitions of each phase that exists.
fn run_gpu(side: &mut GpuSide, reps: usize) -> Result<Phases, String> {
    let mut s = Samples::default();
    for rep in 0..=reps {
        let mut time =
            |k: usize, r: Result<Option<()>, String>, t: Instant| -> Result<(), String> {
                let secs = t.elapsed().as_secs_f64();
                if r?.is_some() && rep > 0 {
                    s.0[k].push(secs);
                }
                Ok(())
            };
        let t = Instant::now();
        time(0, side.assemble(), t)?;
        let t = Instant::now();
        time(1, side.eliminate(), t)?;
        let t = Instant::now();
        time(2, side.solve(), t)?;
        let t = Instant::now();
        time(3, side.line_search(), t)?;
    }
    Ok(s.phases())
}

fn ratio(gpu: Option<f64>, cpu: Option<f64>) -> Option<f64> {
    match (gpu, cpu) {
        (Some(g), Some(c)) if c > 0.0 => Some(g / c),
        _ => None,
    }
}

/// Runs the ladder; progress on stderr, one line per size.
pub fn run(opts: &NewtonOptions, command: &str) -> Result<NewtonReport, NewtonBenchError> {
    let ks = plan(opts).map_err(|e| NewtonBenchError::Io(e.to_string()))?;
    let reps = opts
        .reps
        .unwrap_or(if opts.quick { QUICK_REPS } else { REPS });
    let ctx = if opts.no_gpu {
        None
    } else {
        let c = GpuContext::new(&GpuOptions::default()).map_err(|e| {
            NewtonBenchError::Gpu(format!(
                "bench --newton: no GPU adapter ({e}); --no-gpu runs the CPU side only"
            ))
        })?;
        if !c.has_f64() {
            return Err(NewtonBenchError::Gpu(format!(
                "bench --newton: the GPU side runs in f64 and adapter '{}' has no SHADER_F64; --no-gpu runs the CPU side only",
                c.adapter_name()
            )));
        }
        Some(c)
    };
    let mut report = NewtonReport {
        machine: Machine {
            command: command.to_string(),
            adapter: ctx.as_ref().map(|c| c.adapter_name().to_string()),
            cpu_cores: std::thread::available_parallelism().map_or(1, |n| n.get()),
            threads: rayon::current_num_threads(),
            memory_available_bytes: memory_available(),
        },
        reps,
        cg_tol: CG_TOL,
        preconditioner: "block-jacobi (no coarse correction)".into(),
        precision: "f64".into(),
        sizes: Vec::new(),
    };
    let bar = if opts.quiet {
        indicatif::ProgressBar::hidden()
    } else {
        let b = indicatif::ProgressBar::new(ks.len() as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template("{bar:30} {pos}/{len} sizes {msg}")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        b
    };
    for &k in &ks {
        bar.set_message(format!("{} nodes", box_nodes(k)));
        let rec = bench_size(k, reps, ctx.as_ref(), &bar, opts.quiet);
        say(&bar, opts.quiet, &size_line(&rec));
        crate::app::bench::record::append_record(opts.out.as_deref(), "records.jsonl", &rec);
        report.sizes.push(rec);
        bar.inc(1);
    }
    bar.finish_and_clear();
    if let Some(dir) = &opts.out {
        write_outputs(&report, dir)
            .map_err(|e| NewtonBenchError::Io(format!("{}: {e}", dir.display())))?;
    }
    Ok(report)
}

fn bench_size(
    k: usize,
    reps: usize,
    ctx: Option<&GpuContext>,
    bar: &indicatif::ProgressBar,
    quiet: bool,
) -> SizeRecord {
    let nodes = box_nodes(k);
    let mut rec = SizeRecord {
        k,
        nodes,
        dofs: 3 * nodes,
        tetrahedra: 0,
        constrained_nodes: 0,
        free_dofs: 0,
        cpu: SideRecord::default(),
        gpu: SideRecord::default(),
        ratio: Phases::default(),
        ratio_total: None,
        cpu_check: None,
        gpu_cg: None,
        gpu_assembly_difference: None,
        gpu_profile: None,
        peak_rss_bytes: 0,
    };
    let not_run = |r: &mut SizeRecord, why: String| {
        r.cpu.note = why.clone();
        if ctx.is_some() {
            r.gpu.note = why;
        } else {
            r.gpu.note = "not run: --no-gpu".into();
        }
        r.peak_rss_bytes = crate::app::bench::measure::peak_rss_bytes();
    };
    // Memory: the scene first (both sides need it), then the CPU side's own buffers.
    let avail = memory_available();
    let scene_bytes = SCENE_BYTES_PER_NODE * nodes as u64;
    let cpu_bytes = CPU_BYTES_PER_NODE * nodes as u64;
    if avail > 0 && scene_bytes > avail {
        not_run(
            &mut rec,
            format!(
                "not run: the scene needs about {:.1} GiB of host memory and {:.1} GiB is available",
                gib(scene_bytes),
                gib(avail)
            ),
        );
        return rec;
    }
    let scene = match crate::sim::scene::parse(&scene_toml(k), "newton-bench", 1.0) {
        Ok(s) => s,
        Err(e) => {
            not_run(&mut rec, format!("not run: {e}"));
            return rec;
        }
    };
    let frames = match frames(&scene) {
        Ok(f) => f,
        Err(e) => {
            not_run(&mut rec, format!("not run: {e}"));
            return rec;
        }
    };
    rec.tetrahedra = scene.model.sets.iter().map(|s| s.len()).sum();
    rec.constrained_nodes = frames.mask.iter().filter(|&&m| m != 0).count();
    rec.free_dofs = frames.free_dofs();
    let x = iterate(&scene.x0);
    let xt = scene.x0.clone();
    // CPU side, unless memory is short.
    let avail = memory_available();
    let mut cpu_system = None;
    if avail > 0 && cpu_bytes > avail {
        rec.cpu.note = format!(
            "not run: the CPU side needs about {:.1} GiB more host memory and {:.1} GiB is available",
            gib(cpu_bytes),
            gib(avail)
        );
    } else {
        bar.set_message(format!("{nodes} nodes: CPU"));
        let mut side = CpuSide::new(&scene, &frames, &x, &xt);
        match run_cpu(&mut side, reps) {
            Ok((phases, check)) => {
                rec.cpu.ran = true;
                rec.cpu.seconds = phases;
                rec.cpu.total_seconds = phases.total();
                rec.cpu_check = Some(check);
                cpu_system = Some((side.h, side.g));
            }
            Err(e) => rec.cpu.note = format!("failed: {e}"),
        }
    }
    // GPU side.
    match ctx {
        None => rec.gpu.note = "not run: --no-gpu".into(),
        Some(ctx) => {
            bar.set_message(format!("{nodes} nodes: GPU"));
            let before = ctx.profile();
            let run = GpuSide::new(ctx, &scene, &x, &xt, &frames).and_then(|mut side| {
                let phases = run_gpu(&mut side, reps)?;
                let diff = match &cpu_system {
                    Some((h, g)) => Some(side.difference(h, g)?),
                    None => None,
                };
                let cg = phases.solve.map(|secs| side.cg_record(secs)).transpose()?;
                Ok((phases, diff, cg))
            });
            rec.gpu_profile = Some(ctx.profile().since(&before));
            match run {
                Ok((phases, diff, cg)) => {
                    rec.gpu.ran = true;
                    rec.gpu.seconds = phases;
                    rec.gpu.total_seconds = phases.total();
                    rec.gpu_assembly_difference = diff;
                    rec.gpu_cg = cg;
                    let absent: Vec<&str> = phases
                        .list()
                        .iter()
                        .filter(|(_, v)| v.is_none())
                        .map(|(n, _)| *n)
                        .collect();
                    if !absent.is_empty() {
                        rec.gpu.note = format!("absent: {}", absent.join(", "));
                    }
                }
                Err(e) => {
                    rec.gpu.note = format!("failed: {e}");
                    say(bar, quiet, &format!("{nodes} nodes: GPU side failed: {e}"));
                }
            }
        }
    }
    let (c, g) = (rec.cpu.seconds, rec.gpu.seconds);
    rec.ratio = Phases {
        assembly: ratio(g.assembly, c.assembly),
        elimination: ratio(g.elimination, c.elimination),
        solve: ratio(g.solve, c.solve),
        line_search: ratio(g.line_search, c.line_search),
    };
    rec.ratio_total = ratio(rec.gpu.total_seconds, rec.cpu.total_seconds);
    rec.peak_rss_bytes = crate::app::bench::measure::peak_rss_bytes();
    rec
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_of_odd_and_even_counts() {
        assert_eq!(median(&[]), None);
        assert_eq!(median(&[3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0]), Some(2.5));
    }

    #[test]
    fn a_total_needs_every_phase() {
        let mut p = Phases {
            assembly: Some(1.0),
            elimination: Some(2.0),
            solve: Some(3.0),
            line_search: Some(4.0),
        };
        assert_eq!(p.total(), Some(10.0));
        p.solve = None;
        assert_eq!(p.total(), None);
    }

    #[test]
    fn sizes_map_to_the_nearest_grid() {
        let opts = |sizes: Vec<usize>| NewtonOptions {
            quick: false,
            sizes: Some(sizes),
            no_gpu: true,
            reps: None,
            out: None,
            quiet: true,
        };
        // 425 and 2,673 nodes are k = 4 and 8 exactly; 1 node is the smallest grid.
        assert_eq!(
            plan(&opts(vec![425, 2673, 1])).expect("valid"),
            vec![4, 8, 1]
        );
        assert_eq!(plan(&opts(vec![1_000_000])).expect("valid"), vec![62]);
        assert!(plan(&opts(vec![0])).is_err());
        assert!(plan(&opts(vec![100_000_000])).is_err());
    }

    /// The iterate keeps the sticky end at rest and the slip face on its plane, and the
    /// scene's conditions are the ones the module describes.
    #[test]
    fn the_iterate_meets_the_conditions() {
        let scene = crate::sim::scene::parse(&scene_toml(3), "newton-bench", 1.0).expect("scene");
        let x = iterate(&scene.x0);
        let (mut sticky, mut plane) = (0, 0);
        for b in &scene.bcs {
            let p = &x[3 * b.node..3 * b.node + 3];
            let p0 = &scene.x0[3 * b.node..3 * b.node + 3];
            match &b.shape {
                BcShape::Sticky { .. } => {
                    sticky += 1;
                    // u vanishes at s = 0 exactly up to the rounding of s (|s| ≤ 1e-16).
                    assert!((0..3).all(|a| (p[a] - p0[a]).abs() <= 1e-15), "{p:?}");
                }
                BcShape::Plane { normal, offset } => {
                    plane += 1;
                    let d: f64 = (0..3).map(|a| normal[a] * p[a]).sum::<f64>() - offset;
                    // The rest node is on the plane to 1e-9 (the region tolerance) and u
                    // adds no normal part there beyond rounding.
                    assert!(d.abs() <= 1e-9, "{d}");
                }
                BcShape::Line { .. } => panic!("no line conditions in the bench scene"),
            }
        }
        // k = 3: the left end has 4×4 nodes, the bottom face 13×4.
        assert_eq!(sticky, 16);
        assert_eq!(plane, 52);
        assert!(x.iter().zip(&scene.x0).any(|(a, b)| (a - b).abs() > 1e-3));
    }
}
