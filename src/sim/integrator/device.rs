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
use super::balance::{force_balance, ForceBalance};
use super::error::{InitError, StepError};
use super::linear::LinearStats;
use super::report::GpuRunReport;
use super::state::{Contact, State, CCD_FRACTION};
use super::targets::MovingTargets;
use crate::gpu::pcg::{DeviceCg, DeviceCgParams, DeviceFrames};
use crate::gpu::{GpuContext, GpuError, GpuOptions, Precision, TrafficCount};
use crate::sim::device::assembly::GpuAssembly;
use crate::sim::device::elements::{GpuElements, TermKind};
use crate::sim::device::newton_ops::{static_projections, MovingTerm, NewtonOps};
use crate::sim::energy::barrier::{Ccd, HalfSpace};
use crate::sim::energy::{AssemblyWork, InversionLimit, Inverted};
use crate::sim::scene::Scene;
use crate::solve::multilevel::reuse::KeptLevels;
use crate::solve::multilevel::Hierarchy;
use crate::solve::options::Preconditioner;
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
    /// The host's element buffer of the force balance, kept between steps.
    assembly: AssemblyWork,
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
    match e {
        GpuError::BufferTooLarge { .. } | GpuError::Unsupported(_) => {
            cannot_hold(format!("the GPU Newton loop cannot hold this scene: {e}"))
        }
        other => InitError::Solver(format!("the GPU Newton loop cannot start: {other}")),
    }
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
        let ctx = GpuContext::new(&GpuOptions::default())
            .map_err(|e| InitError::Solver(format!("the GPU Newton loop cannot start: {e}")))?;
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
            assembly: AssemblyWork::default(),
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
        GpuRunReport {
            adapter: self.ctx.adapter_name().to_string(),
            precision: "f64".into(),
            host_to_device_bytes: t.host_to_device_bytes,
            device_to_host_bytes: t.device_to_host_bytes,
            matrix_bytes: self.matrix_bytes,
            coarse_host_to_device_bytes: c.host_to_device_bytes,
            coarse_device_to_host_bytes: c.device_to_host_bytes,
            multilevel_setup_seconds: self.multilevel_seconds,
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
        let projections = static_projections(sc).map_err(|problem| InitError::Input {
            entry: "boundary".into(),
            problem,
        })?;
        let init = |e: GpuError| InitError::Solver(format!("the GPU Newton loop: {e}"));
        dl.ops.set_static_projections(&projections).map_err(init)?;
        dl.ops.set_state(&state.x, &state.v).map_err(init)?;
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
        self.ops.begin_step(state.scene.time_step)?;
        Ok(())
    }

    fn positions(&mut self, nodes: Option<&[usize]>) -> Result<&mut [f64], StepError> {
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
        self.elements.set_planes(planes)?;
        Ok(())
    }

    fn min_distance(&mut self, state: &State) -> Result<(f64, usize, usize), StepError> {
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
        tolerance: &mut dyn FnMut(f64) -> f64,
    ) -> Result<LinearStats, StepError> {
        let t = Instant::now();
        let snapped = &moving.snapped;
        self.elements.evaluate(true)?;
        self.asm.assemble()?;
        let terms = Self::moving_terms(state, moving);
        if self.moving.as_ref() != Some(&terms) {
            self.ops.set_moving(&terms)?;
            self.moving = Some(terms);
        }
        self.ops.add_moving()?;
        // Gradient and Hessian, as the host loop counts them.
        state.count_barrier(2);
        if !self.frames.contains_key(snapped) {
            let f = self.cg.frames(&state.frames[snapped], self.params.coarse)?;
            self.frames.insert(snapped.to_vec(), f);
        }
        let cg_error = |e: GpuError| StepError::LinearSolve {
            iteration,
            cause: e.to_string(),
        };
        let multilevel = self.params.preconditioner == Preconditioner::Multilevel;
        // The forcing sequence gives one tolerance per system, also to a second try.
        let mut eta = None;
        let mut once = |n: f64| *eta.get_or_insert_with(|| tolerance(n));
        let info = loop {
            let frames = &self.frames[snapped];
            self.cg.prepare(frames).map_err(cg_error)?;
            if multilevel {
                self.set_multilevel(state, snapped).map_err(cg_error)?;
            }
            let frames = &self.frames[snapped];
            match self.cg.iterate_to(frames, &self.params, &mut once) {
                Ok(info) => break info,
                // Kept multilevel levels get one more try on levels built for this system.
                Err(_) if multilevel && self.levels.failed() => {}
                Err(e) => return Err(cg_error(e)),
            }
        };
        if multilevel {
            self.levels.solved(info.iterations, info.tolerance);
        }
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
        let cg_error = |e: GpuError| StepError::LinearSolve {
            iteration,
            cause: e.to_string(),
        };
        let multilevel = self.params.preconditioner == Preconditioner::Multilevel;
        if multilevel {
            if self.levels.rebuild_due() {
                self.set_multilevel(state, &moving.snapped)
                    .map_err(cg_error)?;
            } else {
                self.levels.again();
            }
        }
        let frames = &self.frames[&moving.snapped];
        let params = DeviceCgParams { tol, ..self.params };
        let info = self.cg.iterate(frames, &params).map_err(cg_error)?;
        if multilevel {
            self.levels.solved(info.iterations, info.tolerance);
        }
        Ok(Self::stats(&info, t))
    }

    /// Read back whole: for `run --dump-systems`, not the loop.
    fn system(&mut self) -> Result<SystemArrays, StepError> {
        let h = self.asm.read_matrix()?;
        let g = self.asm.read_gradient()?;
        let dx = self.cg.read_dx()?;
        let x = self.positions(None)?.to_vec();
        Ok(SystemArrays { h, g, x, dx })
    }

    fn max_abs_dx(&mut self) -> Result<f64, StepError> {
        Ok(self.ops.max_abs_dx()?)
    }

    /// Reads back x and ∇E and asks the host's test, on x̃ = xⁿ + h vⁿ as the device
    /// formed it.
    fn force_balance(
        &mut self,
        state: &State,
        snapped: &[bool],
    ) -> Result<ForceBalance, StepError> {
        let h = state.scene.time_step;
        let (x, _) = self.ops.read_state()?;
        let g = self.ops.read_gradient()?;
        let xt: Vec<f64> = state
            .x
            .iter()
            .zip(&state.v)
            .map(|(x, v)| x + h * v)
            .collect();
        Ok(force_balance(
            state,
            &x,
            &xt,
            &g,
            &state.frames[snapped],
            &mut self.assembly,
        ))
    }

    /// E at the evaluation positions (the current iterate, or the trial one after
    /// [`Backend::set_trial`]), from the per-term sums on the device, combined as the host
    /// backend combines its terms.
    fn energy(
        &mut self,
        state: &State,
        _moving: &MovingTargets,
        _trial: bool,
    ) -> Result<f64, StepError> {
        let h2 = state.scene.time_step * state.scene.time_step;
        self.elements.evaluate_energy()?;
        let terms = self.ops.energy_terms()?;
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
            e += self.ops.moving_energy()?;
        }
        if state.contact.is_some() {
            state.count_barrier(1);
            e += h2 * barrier;
        }
        Ok(e)
    }

    fn slope(&mut self) -> Result<f64, StepError> {
        Ok(self.ops.dot_gradient_dx()?)
    }

    fn ccd(&mut self, state: &State) -> Result<Ccd, StepError> {
        let c = state
            .contact
            .as_ref()
            .expect("the CCD bound is asked only with obstacles");
        Ok(self.ops.ccd(&c.planes, CCD_FRACTION)?)
    }

    /// x and Δx are read back whole (2·n·d f64) and the bound computed on the host with
    /// the host backend's function: exact, and the same numbers on both loops; one
    /// download per line search of a scene with classical neo-Hookean elements.
    fn inversion_bound(
        &mut self,
        state: &State,
        max: f64,
    ) -> Result<Result<Option<InversionLimit>, Inverted>, StepError> {
        let (x, dx) = self.ops.read_positions_and_direction()?;
        Ok(state.scene.model.inversion_bound(&x, &dx, max))
    }

    fn set_trial(&mut self, alpha: f64) -> Result<(), StepError> {
        self.ops.set_trial(alpha)?;
        Ok(())
    }

    fn accept(&mut self) -> Result<(), StepError> {
        self.ops.accept()?;
        Ok(())
    }

    fn end_step(&mut self, state: &State) -> Result<EndState, StepError> {
        self.ops.end_step(state.scene.time_step)?;
        let (x, v) = self.ops.read_state()?;
        let g = self.ops.read_gradient()?;
        Ok(EndState { x, v, g })
    }

    fn restore(&mut self, state: &State) -> Result<(), StepError> {
        self.ops.set_state(&state.x, &state.v)?;
        Ok(())
    }

    fn adapter(&self) -> Option<&str> {
        Some(self.adapter_name())
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
