//! The device backend of the Newton loop (`[solver] newton = "gpu"`).
//!
//! The loop is the host's (module docs of [`crate::sim::integrator`]), with the state on
//! the device: positions, velocities, xⁿ, x̃, the element terms ([`GpuElements`]), the
//! assembled H and g ([`GpuAssembly`]), the constraint frames of every constraint set met
//! so far and the CG ([`DeviceCg`]), the loop's vector operations ([`NewtonOps`]). Per
//! Newton iteration only scalars cross the bus (energies, g·Δx, ‖Δx‖∞, the CCD bound and
//! the smallest distance, the CG's status) plus the positions of the moving nodes that
//! are still off their targets (their snapping and penalty decisions run on the host, with
//! the loop's own code, on those few entries). Once per step the positions, velocities
//! and the gradient come back for the output (steps.csv, frames, reactions).
//!
//! The multilevel preconditioner's levels are built and refreshed on the device from the
//! H it assembled ([`DeviceCg::set_multilevel_on_device`], src/gpu/pcg/mlsetup.rs): the host
//! partitions the mesh once per run and asks [`KeptLevels::plan`], the CPU loop's decision,
//! whether to build, keep or remask the levels of each system; no byte moves for them per
//! Newton iteration.
//!
//! The decisions are the CPU loop's; the arithmetic differs in summation order and in the
//! CG (the scene's preconditioner and coarse space on the device, against the scene's CPU
//! solver), so trajectories agree to the
//! solvers' tolerances, not bit for bit (tests/sim_gpu_newton.rs).

use super::backend::{Backend, EndState, SystemArrays};
use super::balance::ForceBalance;
use super::error::{InitError, StepError};
use super::forcing::Forcing;
use super::linear::LinearStats;
use super::report::GpuRunReport;
use super::state::{Contact, State, CCD_FRACTION, INVERSION_FRACTION};
use super::targets::MovingTargets;
use crate::gpu::pcg::{DeviceCg, DeviceCgParams, DeviceFrames, Tail};
use crate::gpu::{GpuContext, GpuError, GpuOptions, Phase, Precision, ReadRange, TrafficCount};
use crate::sim::device::assembly::GpuAssembly;
use crate::sim::device::checks::{BalanceFrames, NewtonChecks};
use crate::sim::device::elements::{GpuElements, TermKind};
use crate::sim::device::line_search::{LineScalars, LineSearchTail, TailInputs};
use crate::sim::device::newton_ops::conditions::{static_projections, MovingTerm};
use crate::sim::device::newton_ops::NewtonOps;
use crate::sim::energy::barrier::{Ccd, HalfSpace};
use crate::sim::energy::Law;
use crate::sim::energy::{InversionLimit, Inverted};
use crate::sim::phases::PhaseSpan;
use crate::sim::scene::Scene;
use crate::solve::multilevel::reuse::KeptLevels;
use crate::solve::multilevel::Hierarchy;
use crate::solve::options::Preconditioner;
use crate::solve::tolerance::ToleranceRule;
use std::collections::HashMap;
use std::time::Instant;

/// The device side of a scene: built once per run.
pub(super) struct DeviceLoop {
    ctx: GpuContext,
    elements: GpuElements,
    asm: GpuAssembly,
    cg: DeviceCg,
    ops: NewtonOps,
    /// The constraint frames per constraint set (the key of [`Stepper::frames`]).
    frames: HashMap<Vec<bool>, DeviceFrames>,
    params: DeviceCgParams,
    kinds: Vec<TermKind>,
    matrix_bytes: u64,
    /// The moving terms last uploaded (re-uploaded only when they change).
    moving: Option<Vec<MovingTerm>>,
    /// Host scratch of length n·d: only the entries of the nodes read back are meaningful.
    scratch: Vec<f64>,
    /// The velocities read with every position (kept to write the state back whole).
    scratch_v: Vec<f64>,
    /// The inversion bound and the force balance, reduced on the device.
    checks: NewtonChecks,
    /// The constraint frames of the force balance per constraint set (as `frames`).
    balance_frames: HashMap<Vec<bool>, BalanceFrames>,
    /// The line search's first trial, recorded with every chunk of the CG, and what it
    /// found for the last direction (until the iterate changes).
    tail: LineSearchTail,
    first_trial: Option<LineScalars>,
    /// The evaluation positions may hold a trial point rather than x ...
    at_trial: bool,
    /// ... and hold the first trial's, which the loop asked for.
    trial_is_first: bool,
    /// The multilevel preconditioner's clusters (H's pattern only: once per run), the
    /// decisions on its levels (built, kept or remasked per system, as the CPU loop's),
    /// and the host seconds and bytes of its setups so far.
    hierarchy: Option<std::sync::Arc<Hierarchy>>,
    levels: KeptLevels,
    multilevel_seconds: f64,
    multilevel_traffic: TrafficCount,
    dim: usize,
}

/// A one-line reason the device cannot hold the scene, as an input error on `newton`.
fn cannot_hold(problem: String) -> InitError {
    InitError::Input {
        entry: "solver.newton".into(),
        problem,
    }
}

fn device_error(e: GpuError) -> InitError {
    if e.does_not_fit() || matches!(e, GpuError::Unsupported(_)) {
        cannot_hold(format!("the GPU Newton loop cannot hold this scene: {e}"))
    } else {
        start_failed(e)
    }
}

/// Why the device loop cannot start, kept typed: the device's error under the loop's name.
fn start_failed(e: GpuError) -> InitError {
    InitError::Solver(crate::Error::Gpu(e.cannot_start("GPU Newton loop")))
}

/// Device bytes the loop allocates for `scene` (element outputs, assembly, CG and loop
/// vectors), counted from the same sizes the buffers get, before any of them exists.
pub fn device_bytes_needed(scene: &Scene) -> u64 {
    let d = scene.dim as u64;
    let n = scene.model.n_nodes as u64;
    let real = 8u64;
    let mut bytes = 0u64;
    let mut gathers = 0u64;
    for set in &scene.model.sets {
        let (count, arity) = (set.len() as u64, set.arity() as u64);
        let nl = arity * d;
        // Element indices and rest data, energy, gradient, Hessian.
        bytes += count * (4 * arity + real * (d * d + 4) + real * (1 + nl + nl * nl));
        gathers += count * (arity * arity + arity);
    }
    // Node terms (inertia, gravity, barrier): energy, gradient, Hessian, constants.
    bytes += 3 * n * real * (2 + d + d * d);
    let blocks = scene.model.pattern.nnz_blocks() as u64;
    // Values, column indices, gather lists (offsets and entries, blocks and nodes).
    bytes += blocks * (real * d * d + 4) + 4 * (2 * gathers + 2 * (blocks + n) + n);
    // Loop and CG vectors (x, xⁿ, v, x̃, trial, g, Δx, y, r, z, p, q and spares) and the
    // block-Jacobi inverse, masks and rotations.
    bytes += n * d * real * 16 + n * (real * d * d * 2 + 4);
    bytes
}

/// Whether an adapter can hold the loop for `scene`: it needs SHADER_F64 and, where the
/// backend reports its memory, [`device_bytes_needed`] of it. The error is one line naming
/// what is missing.
pub fn check_capacity(
    scene: &Scene,
    adapter: &str,
    has_f64: bool,
    memory: Option<u64>,
) -> Result<(), String> {
    if !has_f64 {
        return Err(format!(
            "the GPU Newton loop needs 64-bit floats in shaders (SHADER_F64), which adapter \
             '{adapter}' lacks"
        ));
    }
    let need = device_bytes_needed(scene);
    match memory {
        Some(have) if need > have => Err(format!(
            "the GPU Newton loop needs about {need} bytes of device memory for {} nodes, \
             adapter '{adapter}' has {have}",
            scene.model.n_nodes
        )),
        _ => Ok(()),
    }
}

/// The multilevel preconditioner's clusters of the assembled pattern (built once per run),
/// refused in one line before any Newton iteration when a buffer of the levels or of their
/// setup on the device exceeds the adapter's limits or they do not fit beside the loop's
/// buffers.
fn multilevel_hierarchy(
    ctx: &GpuContext,
    scene: &Scene,
    asm: &GpuAssembly,
) -> Result<std::sync::Arc<Hierarchy>, InitError> {
    let d = scene.dim;
    let (row_ptr, col_idx) = asm.pattern();
    let pattern = crate::core::sparse::BlockCsr {
        dim: d,
        n: row_ptr.len() - 1,
        row_ptr: row_ptr.to_vec(),
        col_idx: col_idx.to_vec(),
        values: Vec::new(),
    };
    let hierarchy = Hierarchy::new(&pattern);
    let chunks = asm.values_chunks().len();
    let bytes = crate::gpu::pcg::multilevel_bytes(ctx, &hierarchy.level_sizes(d), d, None)
        .and_then(|levels| {
            let setup = crate::gpu::pcg::multilevel_setup_bytes(ctx, &hierarchy, d, chunks, None)?;
            Ok(levels + setup)
        })
        .map_err(device_error)?;
    let need = device_bytes_needed(scene) + bytes;
    if let Some(have) = ctx.device_memory() {
        if need > have {
            return Err(cannot_hold(format!(
                "the GPU Newton loop needs about {need} bytes of device memory for {} nodes \
                 with the multilevel preconditioner ({bytes} for its levels and their setup), \
                 adapter '{}' has {have}",
                scene.model.n_nodes,
                ctx.adapter_name()
            )));
        }
    }
    Ok(std::sync::Arc::new(hierarchy))
}

impl DeviceLoop {
    pub(super) fn new(scene: &Scene, contact: Option<&Contact>) -> Result<Self, InitError> {
        if scene.solver.precision == Precision::F32 {
            return Err(cannot_hold(
                "the GPU Newton loop runs in f64; precision = \"f32\" applies to the linear \
                 solve of the CPU loop (newton = \"cpu\", linear = \"gpu\")"
                    .into(),
            ));
        }
        let ctx = GpuContext::new(&GpuOptions::default()).map_err(start_failed)?;
        let _setup = ctx.phase(Phase::Setup);
        check_capacity(
            scene,
            ctx.adapter_name(),
            ctx.has_f64(),
            ctx.device_memory(),
        )
        .map_err(cannot_hold)?;
        let barrier = contact.map(|c| (&c.barrier, &c.planes[..]));
        let elements =
            GpuElements::new(&ctx, &scene.model, barrier, Precision::F64).map_err(device_error)?;
        let asm = GpuAssembly::new(&elements, &scene.model).map_err(device_error)?;
        let h = scene.time_step;
        asm.set_scale(h * h);
        let cg = asm.device_cg().map_err(device_error)?;
        let ops = NewtonOps::new(&elements, &asm, cg.dx_buffer()).map_err(device_error)?;
        let checks =
            NewtonChecks::new(&elements, &asm, &ops, &scene.model).map_err(device_error)?;
        let tail = LineSearchTail::new(&ctx, cg.state_buffer()).map_err(device_error)?;
        let d = scene.dim;
        let setup = scene.solver.multilevel_setup;
        let hierarchy = if scene.solver.preconditioner == Preconditioner::Multilevel {
            Some(multilevel_hierarchy(&ctx, scene, &asm)?)
        } else {
            None
        };
        let levels = match &hierarchy {
            Some(h) => KeptLevels::with_hierarchy(setup, h.clone()),
            None => KeptLevels::new(setup),
        };
        let matrix_bytes = (asm.pattern().1.len() * d * d * 8) as u64;
        Ok(DeviceLoop {
            kinds: elements.kinds(),
            ctx,
            elements,
            asm,
            cg,
            ops,
            frames: HashMap::new(),
            params: DeviceCgParams {
                tol: scene.solver.cg_tolerance.loosest(),
                max_iterations: scene.solver.cg_max_iterations,
                preconditioner: scene.solver.preconditioner,
                coarse: scene.solver.coarse,
                stagnation_window: crate::solve::cg::STAGNATION_WINDOW,
            },
            matrix_bytes,
            moving: None,
            scratch: vec![0.0; scene.model.n_nodes * d],
            scratch_v: Vec::new(),
            checks,
            balance_frames: HashMap::new(),
            tail,
            first_trial: None,
            at_trial: false,
            trial_is_first: false,
            hierarchy,
            levels,
            multilevel_seconds: 0.0,
            multilevel_traffic: TrafficCount::default(),
            dim: d,
        })
    }

    pub(super) fn adapter_name(&self) -> &str {
        self.ctx.adapter_name()
    }

    /// The summary.json report so far.
    pub(super) fn report(&self) -> GpuRunReport {
        let t = self.ctx.traffic();
        let c = self.cg.coarse_traffic();
        let prof = self.ctx.profile();
        GpuRunReport {
            adapter: self.ctx.adapter_name().to_string(),
            precision: "f64".into(),
            host_to_device_bytes: t.host_to_device_bytes,
            device_to_host_bytes: t.device_to_host_bytes,
            matrix_bytes: self.matrix_bytes,
            coarse_host_to_device_bytes: c.host_to_device_bytes,
            coarse_device_to_host_bytes: c.device_to_host_bytes,
            multilevel_setup_seconds: self.multilevel_seconds,
            host_syncs: prof.host_syncs,
            dispatches: prof.dispatches,
            iteration_host_to_device_bytes: prof.iteration_bytes()[0],
            iteration_device_to_host_bytes: prof.iteration_bytes()[1],
            phases: prof.phases,
            device_seconds: prof.device_seconds,
            phase_bytes: prof.bytes.clone(),
            multilevel_host_to_device_bytes: self.multilevel_traffic.host_to_device_bytes,
            multilevel_device_to_host_bytes: self.multilevel_traffic.device_to_host_bytes,
            newton_iterations: 0,
        }
    }

    /// Reads the positions of `nodes` into the host scratch (entries of other nodes are
    /// stale) and returns it.
    fn read_nodes(&mut self, nodes: &[usize], d: usize) -> Result<&mut [f64], StepError> {
        let v = self.ops.read_nodes(nodes)?;
        for (k, &i) in nodes.iter().enumerate() {
            self.scratch[i * d..(i + 1) * d].copy_from_slice(&v[k * d..(k + 1) * d]);
        }
        Ok(&mut self.scratch)
    }
}

impl DeviceLoop {
    /// The multilevel preconditioner of the system just assembled and prepared with the
    /// constraint set `snapped`: [`KeptLevels::plan`] decides as the CPU loop does, the
    /// device builds, keeps or remasks the levels from its own H. Its host seconds and
    /// the context's bytes moved meanwhile are counted for the report.
    fn set_multilevel(&mut self, state: &State, snapped: &[bool]) -> Result<(), GpuError> {
        let t = Instant::now();
        let before = self.ctx.traffic();
        let hierarchy = self.hierarchy.clone().ok_or_else(|| {
            GpuError::Mismatch("the multilevel preconditioner has no hierarchy".into())
        })?;
        let how = self.levels.plan(&hierarchy, &state.frames[snapped]);
        let frames = &self.frames[snapped];
        self.cg
            .set_multilevel_on_device(&hierarchy, frames, how, None)?;
        let after = self.ctx.traffic();
        let m = &mut self.multilevel_traffic;
        m.host_to_device_bytes += after.host_to_device_bytes - before.host_to_device_bytes;
        m.device_to_host_bytes += after.device_to_host_bytes - before.device_to_host_bytes;
        self.multilevel_seconds += t.elapsed().as_secs_f64();
        Ok(())
    }

    /// The evaluation positions back at x where a trial left them elsewhere; whether they
    /// were.
    fn at_x(&mut self) -> Result<bool, GpuError> {
        let moved = self.at_trial;
        if moved {
            self.ops.reset_trial()?;
        }
        self.at_trial = false;
        self.trial_is_first = false;
        Ok(moved)
    }

    /// The force balance's binding of the constraint set `snapped`, made once: on the
    /// PCG's frame buffers where that set has them, else uploaded.
    fn bind_balance_frames(&mut self, state: &State, snapped: &[bool]) -> Result<(), GpuError> {
        if self.balance_frames.contains_key(snapped) {
            return Ok(());
        }
        let f = match self.frames.get(snapped) {
            Some(pcg) => {
                let (frame, rotations) = pcg.buffers();
                self.checks.frames_from(frame, rotations)?
            }
            None => self.checks.frames(&state.frames[snapped])?,
        };
        self.balance_frames.insert(snapped.to_vec(), f);
        Ok(())
    }

    /// The CG on the system prepared for the constraint set `snapped`, to the tolerance of
    /// `rule`, with the line search's first trial recorded after every chunk; what that
    /// found is kept where the solve ended in a chunk whose verification ran it.
    fn solve_with_first_trial(
        &mut self,
        state: &State,
        snapped: &[bool],
        params: DeviceCgParams,
        rule: ToleranceRule,
    ) -> Result<crate::gpu::pcg::DeviceCgInfo, GpuError> {
        self.bind_balance_frames(state, snapped)?;
        let sc = state.scene;
        let inp = TailInputs {
            ops: &self.ops,
            checks: &self.checks,
            elements: &self.elements,
            ccd: state
                .contact
                .as_ref()
                .map(|c| (&c.planes[..], CCD_FRACTION)),
            inversion: sc
                .model
                .has_law(Law::NeoHookean)
                .then_some((1.0 / INVERSION_FRACTION, INVERSION_FRACTION)),
            balance: Some((&self.balance_frames[snapped], sc.time_step)),
        };
        let tail = &self.tail;
        let record = |enc: &mut wgpu::CommandEncoder| tail.record(enc, &inp);
        let result = self.ops.result_buffer();
        let (at_x, at_x_bytes) = self.ops.energy_at_x_buffer();
        let read = [
            ReadRange {
                buffer: result,
                offset: 0,
                bytes: 32 * self.ops.result_slots() as u64,
            },
            ReadRange {
                buffer: at_x,
                offset: 0,
                bytes: at_x_bytes,
            },
        ];
        let frames = &self.frames[snapped];
        // The trial may run in any chunk whose verification met the tolerance.
        self.at_trial = true;
        let (info, bytes) = self.cg.iterate_with(
            frames,
            &params,
            rule,
            Some(&Tail {
                record: &record,
                read: &read,
            }),
        )?;
        if let Some([result, at_x]) = bytes.as_deref() {
            let (result, at_x) = (
                NewtonOps::result_values(result),
                NewtonOps::result_values(at_x),
            );
            self.first_trial = Some(LineSearchTail::decode(&inp, &result, &at_x)?);
        }
        Ok(info)
    }

    /// What a device CG solve cost, as the host loop reports its solves.
    fn stats(info: &crate::gpu::pcg::DeviceCgInfo, t: Instant) -> LinearStats {
        LinearStats {
            iterations: info.iterations,
            seconds: t.elapsed().as_secs_f64(),
            rhs_norm: info.rhs_norm,
            tolerance: Some(info.tolerance),
        }
    }

    /// Builds the device loop for `state`'s scene and uploads its static projections and
    /// its state (after the constraint sets have been validated).
    pub(super) fn start(state: &State) -> Result<Self, InitError> {
        let sc = state.scene;
        let mut dl = DeviceLoop::new(sc, state.contact.as_ref())?;
        let _setup = dl.ctx.phase(Phase::Setup);
        let projections = static_projections(sc).map_err(|problem| InitError::Input {
            entry: "boundary".into(),
            problem,
        })?;
        dl.ops
            .set_static_projections(&projections)
            .map_err(start_failed)?;
        dl.ops.set_state(&state.x, &state.v).map_err(start_failed)?;
        Ok(dl)
    }

    /// The penalty terms of the unsnapped moving nodes, for the device.
    fn moving_terms(state: &State, moving: &MovingTargets) -> Vec<MovingTerm> {
        let sc = state.scene;
        let mut out = Vec::new();
        for (j, &k) in state.moving_bcs.iter().enumerate() {
            if moving.snapped[j] {
                continue;
            }
            let node = sc.bcs[k].node;
            let m = sc.model.mass[node];
            out.push(MovingTerm {
                node,
                shape: moving.shapes[j].clone(),
                coef: state.k_m * m,
                sqrt_m_lambda: state.lambda[j].map(|l| m.sqrt() * l),
            });
        }
        out
    }
}

impl Backend for DeviceLoop {
    fn multilevel_levels(&self) -> (usize, usize) {
        self.levels.counts()
    }

    fn begin_step(&mut self, state: &State) -> Result<(), StepError> {
        self.first_trial = None;
        self.at_trial = false;
        self.trial_is_first = false;
        // A step's levels depend on its own systems only: a resume rebuilds them as here.
        self.levels.new_newton_solve();
        let _phase = self.ctx.phase(Phase::HostDecisions);
        self.ops.begin_step(state.scene.time_step)?;
        Ok(())
    }

    fn positions(&mut self, nodes: Option<&[usize]>) -> Result<&mut [f64], StepError> {
        // A few nodes are the loop's decisions; the whole state is a step's own read.
        let _phase = self.ctx.phase(match nodes {
            Some(_) => Phase::HostDecisions,
            None => Phase::Output,
        });
        match nodes {
            Some(nodes) => {
                let d = self.dim;
                self.read_nodes(nodes, d)
            }
            None => {
                let (x, v) = self.ops.read_state()?;
                self.scratch = x;
                self.scratch_v = v;
                Ok(&mut self.scratch)
            }
        }
    }

    fn write_positions(&mut self, nodes: Option<&[usize]>) -> Result<(), StepError> {
        let _phase = self.ctx.phase(match nodes {
            Some(_) => Phase::HostDecisions,
            None => Phase::Output,
        });
        match nodes {
            Some(nodes) => {
                let d = self.dim;
                let vals: Vec<f64> = nodes
                    .iter()
                    .flat_map(|&i| self.scratch[i * d..(i + 1) * d].iter().copied())
                    .collect();
                self.ops.write_nodes(nodes, &vals)?;
            }
            None => self.ops.set_state(&self.scratch, &self.scratch_v)?,
        }
        Ok(())
    }

    fn set_planes(&mut self, planes: &[HalfSpace]) -> Result<(), StepError> {
        let _phase = self.ctx.phase(Phase::Uploads);
        self.elements.set_planes(planes)?;
        Ok(())
    }

    fn min_distance(&mut self, state: &State) -> Result<(f64, usize, usize), StepError> {
        let _phase = self.ctx.phase(Phase::LineSearch);
        let c = state
            .contact
            .as_ref()
            .expect("min_distance is asked only with obstacles");
        Ok(self.ops.min_distance(&c.planes)?)
    }

    /// Element terms, assembly, the moving penalty and the eliminated CG at the current
    /// iterate (the evaluation positions hold it); Δx is left on the device.
    fn direction(
        &mut self,
        state: &State,
        moving: &MovingTargets,
        iteration: usize,
        forcing: &mut Forcing,
    ) -> Result<LinearStats, StepError> {
        let t = Instant::now();
        let snapped = &moving.snapped;
        self.at_x()?;
        self.first_trial = None;
        {
            let _phase = self.ctx.phase(Phase::ElementTerms);
            self.elements.evaluate(true)?;
        }
        let assembling = self.ctx.phase(Phase::Assembly);
        self.asm.assemble()?;
        let terms = Self::moving_terms(state, moving);
        if self.moving.as_ref() != Some(&terms) {
            self.ops.set_moving(&terms)?;
            self.moving = Some(terms);
        }
        self.ops.add_moving()?;
        drop(assembling);
        let _eliminating = self.ctx.phase(Phase::Elimination);
        // Gradient and Hessian, as the host loop counts them.
        state.count_barrier(2);
        if !self.frames.contains_key(snapped) {
            // The first constraint set also uploads the mesh's aggregate index: set-up.
            let first = self.frames.is_empty();
            let _phase = first.then(|| self.ctx.phase(Phase::Setup));
            let f = self.cg.frames(&state.frames[snapped], self.params.coarse)?;
            self.frames.insert(snapped.to_vec(), f);
        }
        let cg_error = |e: GpuError| StepError::LinearSolve {
            iteration,
            cause: e.to_string(),
        };
        let multilevel = self.params.preconditioner == Preconditioner::Multilevel;
        // The forcing sequence's rule, evaluated on the device where ‖b̂‖ is formed; a
        // second try keeps the tolerance of the first.
        let mut rule = forcing.rule();
        let info = loop {
            let frames = &self.frames[snapped];
            self.cg.prepare(frames).map_err(cg_error)?;
            if multilevel {
                // The first build also uploads the hierarchy's index arrays: set-up.
                let first = self.levels.counts() == (0, 0);
                let phase = if first {
                    Phase::Setup
                } else {
                    Phase::PreconditionerSetup
                };
                let _phase = self.ctx.phase(phase);
                self.set_multilevel(state, snapped).map_err(cg_error)?;
            }
            let _solving = self.ctx.phase(Phase::Cg);
            match self.solve_with_first_trial(state, snapped, self.params, rule) {
                Ok(info) => break info,
                // Kept multilevel levels get one more try on levels built for this system.
                Err(_) if multilevel && self.levels.failed() => {
                    if let Some(eta) = self.cg.last_tolerance() {
                        rule = ToleranceRule::Fixed(eta);
                    }
                }
                Err(e) => return Err(cg_error(e)),
            }
        };
        if multilevel {
            self.levels.solved(info.iterations, info.tolerance);
        }
        forcing.record(info.rhs_norm, info.tolerance);
        Ok(Self::stats(&info, t))
    }

    /// The CG again on the assembly and preconditioner of the last `direction` (the
    /// multilevel levels rebuilt first when the CPU loop's solver would rebuild them).
    fn resolve(
        &mut self,
        state: &State,
        moving: &MovingTargets,
        iteration: usize,
        tol: f64,
    ) -> Result<LinearStats, StepError> {
        let t = Instant::now();
        let _phase = self.ctx.phase(Phase::Cg);
        let cg_error = |e: GpuError| StepError::LinearSolve {
            iteration,
            cause: e.to_string(),
        };
        let multilevel = self.params.preconditioner == Preconditioner::Multilevel;
        if multilevel {
            if self.levels.rebuild_due() {
                let _setup = self.ctx.phase(Phase::PreconditionerSetup);
                self.set_multilevel(state, &moving.snapped)
                    .map_err(cg_error)?;
            } else {
                self.levels.again();
            }
        }
        // The first trial sums E at x from the element energies: bring them back to x.
        if self.at_x()? {
            self.elements.evaluate_energy()?;
        }
        self.first_trial = None;
        let params = DeviceCgParams { tol, ..self.params };
        let info = self
            .solve_with_first_trial(state, &moving.snapped, params, ToleranceRule::Fixed(tol))
            .map_err(cg_error)?;
        if multilevel {
            self.levels.solved(info.iterations, info.tolerance);
        }
        Ok(Self::stats(&info, t))
    }

    /// Read back whole: for `run --dump-systems`, not the loop.
    fn system(&mut self) -> Result<SystemArrays, StepError> {
        let _phase = self.ctx.phase(Phase::Output);
        let h = self.asm.read_matrix()?;
        let g = self.asm.read_gradient()?;
        let dx = self.cg.read_dx()?;
        let x = self.positions(None)?.to_vec();
        Ok(SystemArrays { h, g, x, dx })
    }

    fn max_abs_dx(&mut self) -> Result<f64, StepError> {
        if let Some(f) = &self.first_trial {
            return Ok(f.dmax);
        }
        let _phase = self.ctx.phase(Phase::LineSearch);
        Ok(self.ops.max_abs_dx()?)
    }

    /// The force balance of x under the constraint set `snapped`, reduced on the device
    /// ([`NewtonChecks::force_balance`]: 32 bytes read back) from the ∇E and element
    /// gradients of the last `direction`, at x, and x̃ = xⁿ + h vⁿ as the device formed it.
    fn force_balance(
        &mut self,
        state: &State,
        snapped: &[bool],
    ) -> Result<ForceBalance, StepError> {
        if let Some(b) = self.first_trial.as_ref().and_then(|f| f.balance) {
            return Ok(b);
        }
        let _phase = self.ctx.phase(Phase::HostDecisions);
        self.bind_balance_frames(state, snapped)?;
        let frames = &self.balance_frames[snapped];
        Ok(self.checks.force_balance(frames, state.scene.time_step)?)
    }

    /// E at the evaluation positions (the current iterate, or the trial one after
    /// [`Backend::set_trial`]), from the per-term sums on the device, combined as the host
    /// backend combines its terms.
    fn energy(
        &mut self,
        state: &State,
        _moving: &MovingTargets,
        trial: bool,
    ) -> Result<f64, StepError> {
        let _phase = self.ctx.phase(Phase::LineSearch);
        let h2 = state.scene.time_step * state.scene.time_step;
        let known = match (&self.first_trial, trial) {
            (Some(f), false) => Some((f.terms_at_x.clone(), f.moving_at_x)),
            (Some(f), true) if self.trial_is_first => {
                Some((f.terms_at_trial.clone(), f.moving_at_trial))
            }
            _ => None,
        };
        let (terms, moving_energy) = match known {
            Some(k) => k,
            None => {
                if !trial {
                    self.at_x()?;
                }
                self.elements.evaluate_energy()?;
                let terms = self.ops.energy_terms()?;
                let m = if self.moving.as_ref().is_some_and(|m| !m.is_empty()) {
                    self.ops.moving_energy()?
                } else {
                    0.0
                };
                (terms, m)
            }
        };
        let mut inertia = 0.0;
        let mut potential = 0.0;
        let mut barrier = 0.0;
        for (kind, e) in self.kinds.iter().zip(&terms) {
            match kind {
                TermKind::Inertia => inertia += e,
                TermKind::Barrier => barrier += e,
                TermKind::NeoHookean | TermKind::Springs | TermKind::Gravity => potential += e,
            }
        }
        let mut e = inertia + h2 * potential;
        if self.moving.as_ref().is_some_and(|m| !m.is_empty()) {
            e += moving_energy;
        }
        if state.contact.is_some() {
            state.count_barrier(1);
            e += h2 * barrier;
        }
        Ok(e)
    }

    fn slope(&mut self) -> Result<f64, StepError> {
        if let Some(f) = &self.first_trial {
            return Ok(f.slope);
        }
        let _phase = self.ctx.phase(Phase::LineSearch);
        Ok(self.ops.dot_gradient_dx()?)
    }

    fn ccd(&mut self, state: &State) -> Result<Ccd, StepError> {
        if let Some(c) = self.first_trial.as_ref().and_then(|f| f.ccd) {
            return Ok(c);
        }
        let _phase = self.ctx.phase(Phase::LineSearch);
        let c = state
            .contact
            .as_ref()
            .expect("the CCD bound is asked only with obstacles");
        Ok(self.ops.ccd(&c.planes, CCD_FRACTION)?)
    }

    /// The bound of the step Δx from x, reduced on the device with the host's root search
    /// element by element ([`NewtonChecks::inversion_bound`]: 32 bytes read back): the host
    /// backend's numbers wherever the driver rounds as written (lavapipe: bit for bit).
    fn inversion_bound(
        &mut self,
        _state: &State,
        max: f64,
    ) -> Result<Result<Option<InversionLimit>, Inverted>, StepError> {
        if let Some(b) = self.first_trial.as_ref().and_then(|f| f.inversion) {
            return Ok(b);
        }
        let _phase = self.ctx.phase(Phase::InversionBound);
        Ok(self.checks.inversion_bound(max)?)
    }

    fn set_trial(&mut self, alpha: f64) -> Result<(), StepError> {
        // The first trial's point is where the device left the positions.
        self.trial_is_first = self
            .first_trial
            .as_ref()
            .is_some_and(|f| f.alpha.to_bits() == alpha.to_bits());
        if !self.trial_is_first {
            let _phase = self.ctx.phase(Phase::LineSearch);
            self.ops.set_trial(alpha)?;
        }
        self.at_trial = true;
        Ok(())
    }

    fn accept(&mut self) -> Result<(), StepError> {
        let _phase = self.ctx.phase(Phase::LineSearch);
        self.ops.accept()?;
        self.first_trial = None;
        self.at_trial = false;
        self.trial_is_first = false;
        Ok(())
    }

    fn end_step(&mut self, state: &State) -> Result<EndState, StepError> {
        self.first_trial = None;
        self.at_trial = false;
        self.trial_is_first = false;
        let _phase = self.ctx.phase(Phase::Output);
        self.ops.end_step(state.scene.time_step)?;
        let [x, v, g] = self.ops.read_state_and_gradient()?;
        Ok(EndState { x, v, g })
    }

    fn restore(&mut self, state: &State) -> Result<(), StepError> {
        self.first_trial = None;
        self.at_trial = false;
        self.trial_is_first = false;
        let _phase = self.ctx.phase(Phase::Setup);
        self.ops.set_state(&state.x, &state.v)?;
        Ok(())
    }

    fn adapter(&self) -> Option<&str> {
        Some(self.adapter_name())
    }

    fn phase(&self, phase: Phase) -> Option<PhaseSpan> {
        Some(self.ctx.phase(phase).into())
    }

    fn started_at(&self, run_start: Instant) {
        // The time before the device existed: the scene, the mesh, the host's set-up.
        let profiled = self.ctx.profile().wall_seconds;
        let before = run_start.elapsed().as_secs_f64() - profiled;
        self.ctx.add_phase_seconds(Phase::Setup, before.max(0.0));
    }

    fn gpu_report(&self, _state: &State) -> Option<GpuRunReport> {
        Some(self.report())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Without SHADER_F64, or with less memory than the loop needs, the refusal is one
    /// line naming what is missing; with enough, none.
    #[test]
    fn capacity_refusals_name_what_is_missing() {
        let text = crate::sim::scene::builtin("twist").expect("built-in scene");
        let scene = crate::sim::scene::parse(text, "twist", 1.0).expect("built-in scene");
        let need = device_bytes_needed(&scene);
        assert!(need > 0);
        let e = check_capacity(&scene, "Test GPU", false, None).expect_err("no f64");
        assert!(
            e.contains("SHADER_F64") && e.contains("Test GPU") && !e.contains('\n'),
            "{e}"
        );
        let e = check_capacity(&scene, "Test GPU", true, Some(need - 1)).expect_err("memory");
        assert!(
            e.contains(&need.to_string())
                && e.contains(&(need - 1).to_string())
                && !e.contains('\n'),
            "{e}"
        );
        assert!(check_capacity(&scene, "Test GPU", true, Some(need)).is_ok());
        assert!(check_capacity(&scene, "Test GPU", true, None).is_ok());
    }
}
