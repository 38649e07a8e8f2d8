//! The Newton loop of [`Stepper`] on the device (`[solver] newton = "gpu"`).
//!
//! Same algorithm as the CPU loop (module docs of [`crate::sim::integrator`]), with the state on
//! the device: positions, velocities, xⁿ, x̃, the element terms ([`GpuElements`]), the
//! assembled H and g ([`GpuAssembly`]), the constraint frames of every constraint set met
//! so far and the CG ([`DeviceCg`]), the loop's vector operations ([`NewtonOps`]). Per
//! Newton iteration only scalars cross the bus (energies, g·Δx, ‖Δx‖∞, the CCD bound and
//! the smallest distance, the CG's status) plus the positions of the moving nodes that
//! are still off their targets (their snapping and penalty decisions run on the host, with
//! the CPU loop's own code, on those few entries). Once per step the positions, velocities
//! and the gradient come back for the output (steps.csv, frames, reactions).
//!
//! The decisions are the CPU loop's; the arithmetic differs in summation order and in the
//! CG (the scene's Jacobi or block-Jacobi preconditioner with the translations as coarse
//! space on the device, against the scene's CPU solver), so trajectories agree to the
//! solvers' tolerances, not bit for bit (tests/sim_gpu_newton.rs).

use super::{
    Contact, InitError, MovingTargets, StepReport, Stepper, ARMIJO, CCD_FRACTION, MAX_HALVINGS,
};
use crate::gpu::{GpuContext, GpuError, GpuOptions, Precision};
use crate::sim::device::assembly::GpuAssembly;
use crate::sim::device::elements::{GpuElements, TermKind};
use crate::sim::device::newton_cg::{DeviceCg, DeviceCgParams, DeviceFrames};
use crate::sim::device::newton_ops::{static_projections, MovingTerm, NewtonOps};
use crate::sim::energy::barrier::Ccd;
use crate::sim::scene::{BcShape, Scene};
use std::collections::HashMap;
use std::time::Instant;

/// What a run with the GPU Newton loop moved and stored (summary.json `"gpu"`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct GpuRunReport {
    pub adapter: String,
    /// Arithmetic of every device computation.
    pub precision: String,
    /// Totals over the run, set-up included.
    pub host_to_device_bytes: u64,
    pub device_to_host_bytes: u64,
    /// Bytes of one assembled Hessian as stored on the device.
    pub matrix_bytes: u64,
    /// Newton iterations of the run (filled in by the driver, which counts them).
    pub newton_iterations: usize,
}

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
        bytes += count * (4 * arity + real * (d * d + 3) + real * (1 + nl + nl * nl));
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
        let cg = DeviceCg::new(&asm).map_err(device_error)?;
        let ops = NewtonOps::new(&elements, &asm, cg.dx_buffer()).map_err(device_error)?;
        let d = scene.dim;
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
                tol: scene.solver.cg_tolerance,
                max_iterations: scene.solver.cg_max_iterations,
                preconditioner: scene.solver.preconditioner,
                // The device CG's coarse space is the rigid translations: `aggregates`
                // (the default) has no device path, and gets the translations.
                coarse: match scene.solver.coarse {
                    crate::solve::coarse::CoarseSpace::None => {
                        crate::solve::coarse::CoarseSpace::None
                    }
                    _ => crate::solve::coarse::CoarseSpace::Translations,
                },
            },
            matrix_bytes,
            moving: None,
            scratch: vec![0.0; scene.model.n_nodes * d],
        })
    }

    pub(super) fn adapter_name(&self) -> &str {
        self.ctx.adapter_name()
    }

    /// The summary.json report so far.
    pub(super) fn report(&self) -> GpuRunReport {
        let t = self.ctx.traffic();
        GpuRunReport {
            adapter: self.ctx.adapter_name().to_string(),
            precision: "f64".into(),
            host_to_device_bytes: t.host_to_device_bytes,
            device_to_host_bytes: t.device_to_host_bytes,
            matrix_bytes: self.matrix_bytes,
            newton_iterations: 0,
        }
    }

    /// Reads the positions of `nodes` into the host scratch (entries of other nodes are
    /// stale) and returns it.
    fn read_nodes(&mut self, nodes: &[usize], d: usize) -> Result<&mut [f64], String> {
        let v = self.ops.read_nodes(nodes).map_err(gpu_msg)?;
        for (k, &i) in nodes.iter().enumerate() {
            self.scratch[i * d..(i + 1) * d].copy_from_slice(&v[k * d..(k + 1) * d]);
        }
        Ok(&mut self.scratch)
    }
}

fn gpu_msg(e: GpuError) -> String {
    format!("GPU Newton loop: {e}")
}

impl Stepper<'_> {
    /// Builds the device loop (after the constraint sets have been validated).
    pub(super) fn start_device(&mut self) -> Result<(), InitError> {
        let sc = self.scene;
        let mut dl = DeviceLoop::new(sc, self.contact.as_ref())?;
        let projections = static_projections(sc).map_err(|problem| InitError::Input {
            entry: "boundary".into(),
            problem,
        })?;
        let init = |e: GpuError| InitError::Solver(format!("the GPU Newton loop: {e}"));
        dl.ops.set_static_projections(&projections).map_err(init)?;
        dl.ops.set_state(&self.x, &self.v).map_err(init)?;
        self.linear.adapter = Some(dl.adapter_name().to_string());
        self.device = Some(dl);
        Ok(())
    }

    /// What the GPU did so far: the device loop's report, or for the CPU loop with
    /// `linear = "gpu"` the linear solver's traffic and operator size; None for a run
    /// without a GPU. `newton_iterations` is left for the caller, who counts them.
    pub fn gpu_report(&self) -> Option<GpuRunReport> {
        if let Some(dl) = &self.device {
            return Some(dl.report());
        }
        let t = self.linear.solver.gpu_traffic()?;
        let sc = self.scene;
        let precision = sc.solver.precision;
        // The CG's operator: f64 blocks for f64, f32 blocks for f32 and mixed.
        let real = if precision == Precision::F64 { 8 } else { 4 };
        Some(GpuRunReport {
            adapter: self.linear.adapter.clone().unwrap_or_default(),
            precision: precision.to_string(),
            host_to_device_bytes: t.host_to_device_bytes,
            device_to_host_bytes: t.device_to_host_bytes,
            matrix_bytes: (sc.model.pattern.nnz_blocks() * sc.dim * sc.dim * real) as u64,
            newton_iterations: 0,
        })
    }

    /// [`Stepper::step`] with the device loop.
    pub(super) fn step_device(&mut self) -> Result<StepReport, String> {
        let Some(mut dl) = self.device.take() else {
            return Err("the GPU Newton loop was not started".into());
        };
        let r = self.step_on(&mut dl);
        self.device = Some(dl);
        r
    }

    fn step_on(&mut self, dl: &mut DeviceLoop) -> Result<StepReport, String> {
        let sc = self.scene;
        let h = sc.time_step;
        let t1 = self.t + h;
        let mut rep = StepReport {
            step: self.step + 1,
            time: t1,
            k_m: self.k_m,
            ..StepReport::default()
        };
        // 1. Static projection, xⁿ and x̃ on the device; obstacles at t^{n+1}.
        dl.ops.begin_step(h).map_err(gpu_msg)?;
        if self.contact.is_some() {
            self.advance_obstacles_device(dl, t1)?;
            rep.min_distance = self.check_distance_device(dl, "at the start of the step")?;
        }
        // 2. Moving targets at t^{n+1}; nodes already within ε are snapped now.
        let mut moving = MovingTargets {
            shapes: self
                .moving_bcs
                .iter()
                .map(|&k| sc.bcs[k].shape_at(t1))
                .collect(),
            snapped: vec![false; self.moving_bcs.len()],
        };
        self.snap_device(dl, &mut moving)?;
        // 3. Newton.
        self.newton_device(dl, &mut moving, &mut rep)?;
        // 4–5. Velocity, state and forces at the converged iterate.
        dl.ops.end_step(h).map_err(gpu_msg)?;
        let (x, v) = dl.ops.read_state().map_err(gpu_msg)?;
        let g = dl.ops.read_gradient().map_err(gpu_msg)?;
        let mut w = self.take_work();
        w.g.copy_from_slice(&g);
        self.recover_forces(&x, &moving.snapped, &mut w);
        self.finish_device_step(x, v, w, t1)?;
        Ok(rep)
    }

    /// Moves the obstacles to t1 on the host and on the device. A moving obstacle may push
    /// starting guesses ahead of it: the positions then make a round trip.
    fn advance_obstacles_device(&mut self, dl: &mut DeviceLoop, t1: f64) -> Result<(), String> {
        let moves = self.scene.obstacles.iter().any(|o| o.motion.is_some());
        if moves {
            let (mut x, v) = dl.ops.read_state().map_err(gpu_msg)?;
            let pushed = self.pushed_nodes;
            self.advance_obstacles(t1, &mut x);
            if self.pushed_nodes != pushed {
                dl.ops.set_state(&x, &v).map_err(gpu_msg)?;
            }
        } else {
            let mut none = [];
            self.advance_obstacles(t1, &mut none);
        }
        if let Some(c) = &self.contact {
            dl.elements.set_planes(&c.planes).map_err(gpu_msg)?;
        }
        Ok(())
    }

    /// [`Stepper::check_distance`] with the smallest distance taken on the device.
    fn check_distance_device(
        &self,
        dl: &mut DeviceLoop,
        when: &str,
    ) -> Result<Option<f64>, String> {
        let Some(c) = &self.contact else {
            return Ok(None);
        };
        let (dist, node, j) = dl.ops.min_distance(&c.planes).map_err(gpu_msg)?;
        if dist.is_nan() || dist <= 0.0 {
            return Err(format!(
                "node {node} is at signed distance {dist:e} m from {} {when}: the configuration must stay penetration-free",
                self.scene.obstacles[j].label
            ));
        }
        Ok(Some(dist))
    }

    /// [`Stepper::snap_satisfied`] on the moving nodes still off target, read from the
    /// device; the snapped ones are written back.
    fn snap_device(&self, dl: &mut DeviceLoop, moving: &mut MovingTargets) -> Result<(), String> {
        let d = self.scene.dim;
        let nodes = self.unsnapped_nodes(&moving.snapped);
        if nodes.is_empty() {
            return Ok(());
        }
        let before = moving.snapped.clone();
        let x = dl.read_nodes(&nodes, d)?;
        self.snap_satisfied(x, &moving.shapes, &mut moving.snapped);
        let newly: Vec<usize> = (0..before.len())
            .filter(|&j| moving.snapped[j] && !before[j])
            .map(|j| self.scene.bcs[self.moving_bcs[j]].node)
            .collect();
        if !newly.is_empty() {
            let vals: Vec<f64> = newly
                .iter()
                .flat_map(|&i| dl.scratch[i * d..(i + 1) * d].iter().copied())
                .collect();
            dl.ops.write_nodes(&newly, &vals).map_err(gpu_msg)?;
        }
        Ok(())
    }

    fn unsnapped_nodes(&self, snapped: &[bool]) -> Vec<usize> {
        self.moving_bcs
            .iter()
            .zip(snapped)
            .filter(|(_, &s)| !s)
            .map(|(&k, _)| self.scene.bcs[k].node)
            .collect()
    }

    /// The penalty terms of the unsnapped moving nodes, for the device.
    fn moving_terms(&self, targets: &[BcShape], snapped: &[bool]) -> Vec<MovingTerm> {
        let sc = self.scene;
        let mut out = Vec::new();
        for (j, &k) in self.moving_bcs.iter().enumerate() {
            if snapped[j] {
                continue;
            }
            let node = sc.bcs[k].node;
            let m = sc.model.mass[node];
            out.push(MovingTerm {
                node,
                shape: targets[j].clone(),
                coef: self.k_m * m,
                sqrt_m_lambda: self.lambda[j].map(|l| m.sqrt() * l),
            });
        }
        out
    }

    /// Newton on the device (see [`Stepper::newton`]).
    fn newton_device(
        &mut self,
        dl: &mut DeviceLoop,
        moving: &mut MovingTargets,
        rep: &mut StepReport,
    ) -> Result<(), String> {
        let sc = self.scene;
        let h = sc.time_step;
        let d = sc.dim;
        let mut all_snapped_at = None;
        let mut residual_at_update = f64::INFINITY;
        let mut iter = 0usize;
        loop {
            if iter >= sc.solver.max_newton_iterations {
                return Err(format!(
                    "Newton did not converge in {} iterations (k_M = {:e}, unsatisfied moving nodes: {})",
                    iter,
                    self.k_m,
                    moving.snapped.iter().filter(|s| !**s).count()
                ));
            }
            if !moving.snapped.is_empty()
                && moving.snapped.iter().all(|&s| s)
                && all_snapped_at.is_none()
            {
                all_snapped_at = Some(iter);
            }
            self.direction_device(dl, moving, iter, rep)?;
            iter += 1;
            let dmax = dl.ops.max_abs_dx().map_err(gpu_msg)?;
            if !dmax.is_finite() {
                return Err(format!(
                    "the Newton direction is not finite at iteration {iter}"
                ));
            }
            if dmax / h < self.newton_tol {
                if moving.snapped.iter().all(|&s| s) {
                    break;
                }
                let nodes = self.unsnapped_nodes(&moving.snapped);
                let x = dl.read_nodes(&nodes, d)?;
                self.update_moving_penalty(x, moving, &mut residual_at_update, rep)?;
                continue;
            }
            self.line_search_device(dl, dmax, iter, rep)?;
            self.snap_device(dl, moving)?;
            if self.contact.is_some() {
                let when = format!("after Newton iteration {iter}");
                let dist = self.check_distance_device(dl, &when)?;
                rep.min_distance = match (rep.min_distance, dist) {
                    (Some(a), Some(b)) => Some(a.min(b)),
                    (a, b) => a.or(b),
                };
            }
        }
        rep.newton_iterations = iter;
        rep.eliminated_at_iteration = all_snapped_at;
        rep.k_m = self.k_m;
        Ok(())
    }

    /// Element terms, assembly, the moving penalty and the eliminated CG at the current
    /// iterate (the evaluation positions hold it); Δx is left on the device.
    fn direction_device(
        &mut self,
        dl: &mut DeviceLoop,
        moving: &MovingTargets,
        iter: usize,
        rep: &mut StepReport,
    ) -> Result<(), String> {
        let t = Instant::now();
        let snapped = &moving.snapped;
        self.frames_for(snapped)?;
        dl.elements.evaluate(true).map_err(gpu_msg)?;
        dl.asm.assemble().map_err(gpu_msg)?;
        let terms = self.moving_terms(&moving.shapes, snapped);
        if dl.moving.as_ref() != Some(&terms) {
            dl.ops.set_moving(&terms).map_err(gpu_msg)?;
            dl.moving = Some(terms);
        }
        dl.ops.add_moving().map_err(gpu_msg)?;
        if self.contact.is_some() {
            // Gradient and Hessian, as the CPU loop counts them.
            self.barrier_evals.set(self.barrier_evals.get() + 2);
        }
        if !dl.frames.contains_key(snapped) {
            let f = dl.cg.frames(&self.frames[snapped]).map_err(gpu_msg)?;
            dl.frames.insert(snapped.to_vec(), f);
        }
        let frames = &dl.frames[snapped];
        let info = dl
            .cg
            .solve(frames, &dl.params)
            .map_err(|e| format!("linear solve failed at Newton iteration {}: {e}", iter + 1))?;
        rep.linear_iterations += info.iterations;
        rep.linear_seconds += t.elapsed().as_secs_f64();
        Ok(())
    }

    /// E at the evaluation positions, from the per-term sums on the device, combined as
    /// the CPU's [`Stepper::energy`] combines its terms.
    fn energy_device(&self, dl: &mut DeviceLoop) -> Result<f64, String> {
        let h2 = self.scene.time_step * self.scene.time_step;
        dl.elements.evaluate_energy().map_err(gpu_msg)?;
        let terms = dl.ops.energy_terms().map_err(gpu_msg)?;
        let mut inertia = 0.0;
        let mut potential = 0.0;
        let mut barrier = 0.0;
        for (kind, e) in dl.kinds.iter().zip(&terms) {
            match kind {
                TermKind::Inertia => inertia += e,
                TermKind::Barrier => barrier += e,
                TermKind::NeoHookean | TermKind::Springs | TermKind::Gravity => potential += e,
            }
        }
        let mut e = inertia + h2 * potential;
        if dl.moving.as_ref().is_some_and(|m| !m.is_empty()) {
            e += dl.ops.moving_energy().map_err(gpu_msg)?;
        }
        if self.contact.is_some() {
            self.barrier_evals.set(self.barrier_evals.get() + 1);
            e += h2 * barrier;
        }
        Ok(e)
    }

    /// Armijo backtracking on the device (see [`Stepper::line_search`]).
    fn line_search_device(
        &mut self,
        dl: &mut DeviceLoop,
        dmax: f64,
        iter: usize,
        rep: &mut StepReport,
    ) -> Result<(), String> {
        let h = self.scene.time_step;
        let d = self.scene.dim;
        let e0 = self.energy_device(dl)?;
        if !e0.is_finite() {
            return Err(format!(
                "the energy is not finite (E = {e0:e}) at Newton iteration {iter}: the positions or velocities have overflowed"
            ));
        }
        let slope = dl.ops.dot_gradient_dx().map_err(gpu_msg)?;
        rep.max_slope = Some(rep.max_slope.map_or(slope, |m| m.max(slope)));
        if slope.is_nan() || slope >= 0.0 {
            rep.ascent_directions += 1;
        }
        let ccd = match &self.contact {
            Some(c) => {
                self.ccd_calls += 1;
                dl.ops.ccd(&c.planes, CCD_FRACTION).map_err(gpu_msg)?
            }
            None => Ccd {
                alpha: 1.0,
                limit: None,
            },
        };
        let alpha_c = ccd.alpha;
        if alpha_c < 1.0 {
            rep.ccd_limited += 1;
        }
        let mut alpha = alpha_c;
        let mut accepted = false;
        for _ in 0..MAX_HALVINGS {
            dl.ops.set_trial(alpha).map_err(gpu_msg)?;
            let e1 = self.energy_device(dl)?;
            if e1 <= e0 + ARMIJO * alpha * slope.min(0.0) {
                accepted = true;
                break;
            }
            alpha *= 0.5;
        }
        if !accepted {
            if dmax / h < 1e3 * self.newton_tol {
                alpha = alpha_c;
                dl.ops.set_trial(alpha_c).map_err(gpu_msg)?;
            } else {
                return Err(format!(
                    "the line search found no decrease at Newton iteration {iter} (‖Δx‖∞/h = {:e} m/s)",
                    dmax / h
                ));
            }
        }
        if alpha == alpha_c {
            if let Some((node, _)) = ccd.limit {
                let x = dl.read_nodes(&[node], d)?;
                self.check_unbarriered_limit(x, &ccd, iter)?;
            }
        }
        dl.ops.accept().map_err(gpu_msg)?;
        Ok(())
    }

    /// [`Stepper::finish_step`] for the state read back from the device.
    fn finish_device_step(
        &mut self,
        x: Vec<f64>,
        v: Vec<f64>,
        w: super::StepWork,
        t1: f64,
    ) -> Result<(), String> {
        let sc = self.scene;
        let d = sc.dim;
        let ke: f64 = v
            .iter()
            .enumerate()
            .map(|(i, vi)| sc.model.mass[i / d] * vi * vi)
            .sum();
        if !ke.is_finite() {
            return Err(format!(
                "the velocities overflow (2·kinetic energy = {ke:e}): a node was moved by about {:e} m in one step",
                (0..x.len())
                    .map(|i| (x[i] - self.x[i]).abs())
                    .fold(0.0f64, f64::max)
            ));
        }
        self.v = v;
        self.x = x;
        self.work = w;
        self.t = t1;
        self.step += 1;
        Ok(())
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
