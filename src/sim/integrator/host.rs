//! The host backend: the iterate in arrays, ∇E and ∇²E assembled on the CPU, the
//! eliminated system solved by the library's [`crate::Solver`] (Cholesky, CPU CG or the
//! GPU CG, as the scene's `linear` says).

use super::backend::{Backend, EndState, SystemArrays};
use super::balance::{force_balance, ForceBalance};
use super::error::{InitError, StepError};
use super::forcing::Forcing;
use super::linear::{LinearSolver, LinearStats};
use super::report::GpuRunReport;
use super::state::{State, CCD_FRACTION};
use super::targets::{offset, projector, MovingTargets};
use crate::core::elimination::{ConstrainedDiagonal, Eliminated};
use crate::core::sparse::BlockCsr;
use crate::gpu::{Phase, Profile};
use crate::sim::energy::barrier::{Ccd, HalfSpace};
use crate::sim::energy::{inertia, AssemblyWork, InversionLimit, Inverted};
use crate::sim::memory::try_vec;
use crate::sim::phases::{HostPhases, PhaseSpan};
use crate::sim::scene::{BcShape, SolverSpec};
use crate::Precision;

pub(super) struct HostBackend {
    pub(super) linear: LinearSolver,
    hmat: BlockCsr,
    /// Element buffers of the gradient and Hessian assembly, kept across Newton iterations.
    assembly: AssemblyWork,
    /// The current iterate.
    x: Vec<f64>,
    /// xⁿ, the positions at the start of the step.
    xn: Vec<f64>,
    /// x̃ = xⁿ + h vⁿ.
    xt: Vec<f64>,
    /// ∇E at the current iterate.
    g: Vec<f64>,
    /// The line search's trial iterate (swapped with x when accepted).
    xtry: Vec<f64>,
    /// The last Newton direction.
    dx: Vec<f64>,
    /// Where the loop's seconds go (the assembly's buffers share it).
    pub(super) phases: HostPhases,
}

impl HostBackend {
    /// Fails with [`InitError::Solver`] when the linear solver cannot start and
    /// [`InitError::Memory`] when the system refuses the Hessian or the loop's vectors.
    pub(super) fn new(state: &State, linear: &SolverSpec) -> Result<Self, InitError> {
        let n = state.x.len();
        let linear = LinearSolver::new(linear).map_err(InitError::Solver)?;
        let vector = || try_vec(n, 0.0, "the Newton loop's vectors").map_err(InitError::Memory);
        let phases = HostPhases::default();
        Ok(HostBackend {
            linear,
            hmat: state
                .scene
                .model
                .try_zero_matrix()
                .map_err(InitError::Memory)?,
            assembly: AssemblyWork::timed(phases.clone()),
            x: vector()?,
            xn: vector()?,
            xt: vector()?,
            g: vector()?,
            xtry: vector()?,
            dx: vector()?,
            phases,
        })
    }

    /// The eliminated solve of the assembled ∇E and ∇²E for the constraint set of
    /// `moving`: Δx.
    fn solve(
        &mut self,
        state: &State,
        moving: &MovingTargets,
        iteration: usize,
        tolerance: &mut dyn FnMut(f64) -> f64,
    ) -> Result<LinearStats, StepError> {
        let snapped = &moving.snapped;
        let frames = &state.frames[snapped];
        let eliminating = self.phases.open(Phase::Elimination);
        let e = Eliminated::new(&self.hmat, &self.g, frames, ConstrainedDiagonal::Identity);
        drop(eliminating);
        let _solving = self.phases.open(Phase::LinearSolve);
        let (dx, stats) = self
            .linear
            .solve(snapped, &e, tolerance)
            .map_err(|cause| StepError::LinearSolve { iteration, cause })?;
        self.dx = dx;
        Ok(stats)
    }
}

impl Backend for HostBackend {
    fn begin_step(&mut self, state: &State) -> Result<(), StepError> {
        // A step's levels depend on its own systems only: a resume rebuilds them as here.
        self.linear.solver.new_newton_solve();
        let h = state.scene.time_step;
        self.xn.clone_from(&state.x);
        self.x.clone_from(&state.x);
        state.project_static(&mut self.x);
        for i in 0..self.x.len() {
            self.xt[i] = self.xn[i] + h * state.v[i];
        }
        Ok(())
    }

    fn positions(&mut self, _nodes: Option<&[usize]>) -> Result<&mut [f64], StepError> {
        Ok(&mut self.x)
    }

    fn write_positions(&mut self, _nodes: Option<&[usize]>) -> Result<(), StepError> {
        Ok(())
    }

    fn set_planes(&mut self, _planes: &[HalfSpace]) -> Result<(), StepError> {
        Ok(())
    }

    fn min_distance(&mut self, state: &State) -> Result<(f64, usize, usize), StepError> {
        Ok(state
            .min_distance(&self.x)
            .expect("min_distance is asked only with obstacles"))
    }

    fn direction(
        &mut self,
        state: &State,
        moving: &MovingTargets,
        iteration: usize,
        forcing: &mut Forcing,
    ) -> Result<LinearStats, StepError> {
        let p = &self.phases;
        gradient(
            state,
            &self.x,
            &self.xt,
            moving,
            &mut self.g,
            &mut self.assembly,
            p,
        );
        hessian(
            state,
            &self.x,
            moving,
            &mut self.hmat,
            &mut self.assembly,
            p,
        );
        let checking = self.phases.open(Phase::Checks);
        // Positions far beyond the scene (a moving target running off at 1e300 m/s) overflow the element
        // terms; say so here rather than as a failed factorization of a non-finite H.
        for (what, v) in [
            ("gradient", &self.g[..]),
            ("Hessian", &self.hmat.values[..]),
        ] {
            if let Some(value) = first_non_finite(v) {
                return Err(StepError::SystemNotFinite {
                    what,
                    value,
                    iteration,
                });
            }
        }
        drop(checking);
        self.solve(state, moving, iteration, &mut |n| forcing.tolerance(n))
    }

    fn resolve(
        &mut self,
        state: &State,
        moving: &MovingTargets,
        iteration: usize,
        tol: f64,
    ) -> Result<LinearStats, StepError> {
        self.solve(state, moving, iteration, &mut |_| tol)
    }

    fn system(&mut self) -> Result<SystemArrays, StepError> {
        Ok(SystemArrays {
            h: self.hmat.clone(),
            g: self.g.clone(),
            x: self.x.clone(),
            dx: self.dx.clone(),
        })
    }

    fn max_abs_dx(&mut self) -> Result<f64, StepError> {
        Ok(self.dx.iter().fold(0.0f64, |m, v| m.max(v.abs())))
    }

    fn force_balance(
        &mut self,
        state: &State,
        snapped: &[bool],
    ) -> Result<ForceBalance, StepError> {
        // The force scale's element passes are the check's, not the assembly's.
        let timed = self.assembly.phases.take();
        let b = force_balance(
            state,
            &self.x,
            &self.xt,
            &self.g,
            &state.frames[snapped],
            &mut self.assembly,
        );
        self.assembly.phases = timed;
        Ok(b)
    }

    fn energy(
        &mut self,
        state: &State,
        moving: &MovingTargets,
        trial: bool,
    ) -> Result<f64, StepError> {
        let x = if trial { &self.xtry } else { &self.x };
        let (shapes, snapped) = (&moving.shapes, &moving.snapped);
        Ok(energy(state, x, &self.xt, shapes, snapped, &self.phases))
    }

    fn slope(&mut self) -> Result<f64, StepError> {
        Ok(self.g.iter().zip(&self.dx).map(|(a, b)| a * b).sum())
    }

    fn ccd(&mut self, state: &State) -> Result<Ccd, StepError> {
        let c = state
            .contact
            .as_ref()
            .expect("the CCD bound is asked only with obstacles");
        Ok(c.barrier.ccd(&self.x, &self.dx, &c.planes, CCD_FRACTION))
    }

    fn inversion_bound(
        &mut self,
        state: &State,
        max: f64,
    ) -> Result<Result<Option<InversionLimit>, Inverted>, StepError> {
        Ok(state.scene.model.inversion_bound(&self.x, &self.dx, max))
    }

    fn set_trial(&mut self, alpha: f64) -> Result<(), StepError> {
        for i in 0..self.x.len() {
            self.xtry[i] = self.x[i] + alpha * self.dx[i];
        }
        Ok(())
    }

    fn accept(&mut self) -> Result<(), StepError> {
        std::mem::swap(&mut self.x, &mut self.xtry);
        Ok(())
    }

    fn end_step(&mut self, state: &State) -> Result<EndState, StepError> {
        let h = state.scene.time_step;
        let v = (0..self.x.len())
            .map(|i| (self.x[i] - self.xn[i]) / h)
            .collect();
        Ok(EndState {
            x: self.x.clone(),
            v,
            g: self.g.clone(),
        })
    }

    fn restore(&mut self, _state: &State) -> Result<(), StepError> {
        // The host loop reads xⁿ and vⁿ from the state at the start of every step.
        Ok(())
    }

    fn adapter(&self) -> Option<&str> {
        self.linear.adapter.as_deref()
    }

    fn phase(&self, phase: Phase) -> Option<PhaseSpan> {
        Some(self.phases.open(phase))
    }

    fn host_profile(&self) -> Option<Profile> {
        Some(self.phases.profile())
    }

    fn started_at(&self, run_start: std::time::Instant) {
        // The time before the loop existed: the scene, the mesh, the model's tables.
        let profiled = self.phases.profile().wall_seconds;
        let before = run_start.elapsed().as_secs_f64() - profiled;
        self.phases.add(Phase::Setup, before.max(0.0));
    }

    fn multilevel_levels(&self) -> (usize, usize) {
        self.linear.solver.multilevel_levels()
    }

    fn gpu_report(&self, state: &State) -> Option<GpuRunReport> {
        let t = self.linear.solver.gpu_traffic()?;
        let sc = state.scene;
        let precision = sc.solver.precision;
        // The CG's operator: f64 blocks for f64, f32 blocks for f32 and mixed.
        let real = if precision == Precision::F64 { 8 } else { 4 };
        Some(GpuRunReport {
            adapter: self.linear.adapter.clone().unwrap_or_default(),
            precision: precision.to_string(),
            host_to_device_bytes: t.host_to_device_bytes,
            device_to_host_bytes: t.device_to_host_bytes,
            matrix_bytes: (sc.model.pattern.nnz_blocks() * sc.dim * sc.dim * real) as u64,
            coarse_host_to_device_bytes: 0,
            coarse_device_to_host_bytes: 0,
            multilevel_setup_seconds: 0.0,
            host_syncs: t.host_syncs,
            dispatches: 0,
            iteration_host_to_device_bytes: 0,
            iteration_device_to_host_bytes: 0,
            phases: Vec::new(),
            device_seconds: Vec::new(),
            phase_bytes: Vec::new(),
            multilevel_host_to_device_bytes: 0,
            multilevel_device_to_host_bytes: 0,
            newton_iterations: 0,
        })
    }
}

/// E(x) for the current step.
fn energy(
    state: &State,
    x: &[f64],
    xt: &[f64],
    targets: &[BcShape],
    snapped: &[bool],
    phases: &HostPhases,
) -> f64 {
    let sc = state.scene;
    let h = sc.time_step;
    let d = sc.dim;
    let mut e = inertia::energy(&sc.model.mass, d, x, xt) + h * h * sc.model.potential(x);
    let moving = phases.open(Phase::MovingBoundary);
    for (j, &k) in state.moving_bcs.iter().enumerate() {
        if snapped[j] {
            continue;
        }
        let b = &sc.bcs[k];
        let m = sc.model.mass[b.node];
        let r = offset(d, &targets[j], &x[b.node * d..(b.node + 1) * d]);
        let rr: f64 = r.iter().map(|v| v * v).sum();
        let lr: f64 = (0..3).map(|a| state.lambda[j][a] * r[a]).sum();
        e += 0.5 * state.k_m * m * rr - m.sqrt() * lr;
    }
    drop(moving);
    if let Some(c) = &state.contact {
        let _contact = phases.open(Phase::Contact);
        state.count_barrier(1);
        e += h * h * c.barrier.energy(x, &c.planes);
    }
    e
}

/// ∇E at x into `g`.
fn gradient(
    state: &State,
    x: &[f64],
    xt: &[f64],
    moving: &MovingTargets,
    g: &mut [f64],
    assembly: &mut AssemblyWork,
    phases: &HostPhases,
) {
    let sc = state.scene;
    let d = sc.dim;
    let h = sc.time_step;
    let assembling = phases.open(Phase::Assembly);
    g.iter_mut().for_each(|v| *v = 0.0);
    inertia::add_gradient(&sc.model.mass, d, x, xt, g);
    sc.model.add_potential_gradient_with(x, h * h, g, assembly);
    drop(assembling);
    let moving_terms = phases.open(Phase::MovingBoundary);
    for (j, &k) in state.moving_bcs.iter().enumerate() {
        if moving.snapped[j] {
            continue;
        }
        let node = sc.bcs[k].node;
        let m = sc.model.mass[node];
        let r = offset(d, &moving.shapes[j], &x[node * d..(node + 1) * d]);
        let p = projector(d, &moving.shapes[j]);
        for a in 0..d {
            // ∇[½ k m ‖r‖² − √m λᵀr] = k m r − √m P λ (P the projector with r = P(x − ·)).
            let pl: f64 = (0..d).map(|c| p[a * 3 + c] * state.lambda[j][c]).sum();
            g[node * d + a] += state.k_m * m * r[a] - m.sqrt() * pl;
        }
    }
    drop(moving_terms);
    if let Some(c) = &state.contact {
        let _contact = phases.open(Phase::Contact);
        state.count_barrier(1);
        c.barrier.add_gradient(x, &c.planes, h * h, g);
    }
}

/// ∇²E at x into `hmat` (the element terms PSD-projected).
fn hessian(
    state: &State,
    x: &[f64],
    moving: &MovingTargets,
    hmat: &mut BlockCsr,
    assembly: &mut AssemblyWork,
    phases: &HostPhases,
) {
    let sc = state.scene;
    let d = sc.dim;
    let h = sc.time_step;
    let assembling = phases.open(Phase::Assembly);
    sc.model
        .mass_and_potential_hessian_with(x, h * h, true, hmat, assembly);
    drop(assembling);
    let moving_terms = phases.open(Phase::MovingBoundary);
    for (j, &k) in state.moving_bcs.iter().enumerate() {
        if moving.snapped[j] {
            continue;
        }
        let node = sc.bcs[k].node;
        let m = sc.model.mass[node];
        let p = projector(d, &moving.shapes[j]);
        let kb = hmat.diag_index(node).expect("diagonal block");
        for a in 0..d {
            for c in 0..d {
                hmat.values[kb * d * d + a * d + c] += state.k_m * m * p[a * 3 + c];
            }
        }
    }
    drop(moving_terms);
    if let Some(c) = &state.contact {
        let _contact = phases.open(Phase::Contact);
        state.count_barrier(1);
        c.barrier.add_hessian(x, &c.planes, h * h, hmat);
    }
}

/// The first value of `v` (in order) that is NaN or infinite. Fixed chunks in parallel,
/// each tested at memory speed (`a·0` is 0 for a finite `a` and NaN otherwise, summed
/// lane-wise so the loop vectorises) and searched only when it holds one.
fn first_non_finite(v: &[f64]) -> Option<f64> {
    use rayon::prelude::*;
    const CHUNK: usize = 1 << 14;
    const LANES: usize = 8;
    let all_finite = |c: &[f64]| {
        let mut acc = [0.0f64; LANES];
        let lanes = c.chunks_exact(LANES);
        let tail = lanes.remainder();
        for w in lanes {
            for l in 0..LANES {
                acc[l] += w[l] * 0.0;
            }
        }
        acc.iter().all(|a| *a == 0.0) && tail.iter().all(|a| a.is_finite())
    };
    let k = v.par_chunks(CHUNK).position_first(|c| !all_finite(c))?;
    v[k * CHUNK..].iter().copied().find(|a| !a.is_finite())
}

#[cfg(test)]
mod tests {
    use super::first_non_finite;

    #[test]
    fn first_non_finite_finds_the_first_in_order() {
        let mut v = vec![1.5f64; 100_000];
        assert_eq!(first_non_finite(&v), None);
        v[99_999] = f64::NEG_INFINITY;
        assert_eq!(first_non_finite(&v), Some(f64::NEG_INFINITY));
        v[70_001] = f64::INFINITY;
        assert_eq!(first_non_finite(&v), Some(f64::INFINITY));
        v[40_003] = f64::NAN;
        assert!(first_non_finite(&v).is_some_and(f64::is_nan));
        // Huge finite values (their sum would overflow) are finite.
        let w = vec![f64::MAX; 1_000];
        assert_eq!(first_non_finite(&w), None);
    }
}
