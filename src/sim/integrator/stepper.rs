//! [`Stepper`]: the time step and its Newton loop, written once over a [`Backend`] that
//! holds the iterate (host arrays, or device buffers with scalars read back).

use super::backend::Backend;
use super::balance::ForceBalance;
use super::device::DeviceLoop;
use super::dump::{NewtonSystem, SystemSink};
use super::error::{InitError, StepError, Unbalanced};
use super::forcing::Forcing;
use super::host::HostBackend;
use super::report::{GpuRunReport, StepReport};
use super::state::{Snapshot, State, ARMIJO, ENERGY_ULPS, INVERSION_FRACTION, MAX_HALVINGS};
use super::targets::MovingTargets;
use crate::gpu::{Phase, Profile};
use crate::sim::energy::barrier::Ccd;
use crate::sim::energy::Law;
use crate::sim::phases::PhaseSpan;
use crate::sim::scene::InversionPolicy;
use crate::sim::scene::{check_solver_size, joint_targets, LinearKind, NewtonLoop, Scene};

/// Time stepper: the [`State`] (read through this type) and the backend its Newton loop
/// runs on.
pub struct Stepper<'s> {
    state: State<'s>,
    backend: Box<dyn Backend + 's>,
    /// The CG tolerance of each Newton system (restarted at every step).
    forcing: Forcing,
}

impl<'s> std::ops::Deref for Stepper<'s> {
    type Target = State<'s>;
    fn deref(&self) -> &State<'s> {
        &self.state
    }
}

impl<'s> std::ops::DerefMut for Stepper<'s> {
    fn deref_mut(&mut self) -> &mut State<'s> {
        &mut self.state
    }
}

impl<'s> Stepper<'s> {
    /// Fails with [`InitError::Input`] when the scene's conditions are inconsistent (for
    /// example contradictory conditions on one node, see [`joint_targets`]), when the static
    /// conditions' projection of the initial positions inverts an element or moves a node
    /// farther than [`STATIC_PROJECTION_FRACTION`](super::STATIC_PROJECTION_FRACTION)·L, or the scene
    /// is too big for its linear solver ([`check_solver_size`]: the solver may have been
    /// overridden after parsing), and [`InitError::Solver`] when the linear solver cannot
    /// start (no GPU adapter).
    pub fn new(scene: &'s Scene) -> Result<Self, InitError> {
        let on_device = scene.solver.newton == NewtonLoop::Gpu;
        // The device loop has its own CG: the size limit of the scene's linear solver does
        // not apply to it.
        let mut linear = scene.solver.clone();
        if on_device {
            linear.linear = LinearKind::Cg;
        }
        // The solver may have been overridden after the scene was parsed (`--solver`).
        check_solver_size(scene.dim, scene.model.n_nodes, linear.linear).map_err(|p| {
            InitError::Input {
                entry: "solver.linear".into(),
                problem: format!("{p} (or --solver)"),
            }
        })?;
        let mut static_bcs = Vec::new();
        let mut moving_bcs = Vec::new();
        for (k, b) in scene.bcs.iter().enumerate() {
            if b.motion.is_some() {
                moving_bcs.push(k);
            } else {
                static_bcs.push(k);
            }
        }
        // Nodes with several static conditions: they must agree (checked again here for
        // scenes built without the parser) and are projected onto their intersection.
        let joint = joint_targets(
            scene.dim,
            &scene.x0,
            &scene.bcs,
            scene.characteristic_length,
        )
        .map_err(|e| InitError::Input {
            entry: e.label,
            problem: e.problem,
        })?;
        let mut is_joint = vec![false; scene.model.n_nodes];
        for j in &joint {
            is_joint[j.node] = true;
        }
        let single_static_bcs = static_bcs
            .iter()
            .copied()
            .filter(|&k| !is_joint[scene.bcs[k].node])
            .collect();
        // The classical law is not defined for an inverted element: a scene that starts
        // with one is bad input.
        let inverted = scene
            .model
            .min_volume_ratio(&scene.x0)
            .into_iter()
            .find(|m| m.law == Law::NeoHookean && (m.j.is_nan() || m.j <= 0.0));
        if let Some(m) = inverted {
            return Err(InitError::Input {
                entry: format!("bodies[{}]", m.set),
                problem: format!(
                    "element {} is inverted in the initial state (J = {:e}); the neo-Hookean \
                     law needs J > 0",
                    m.element, m.j
                ),
            });
        }
        let mut state = State::new(scene, static_bcs, single_static_bcs, joint, moving_bcs);
        // Every step starts with the static projection; the first one moves the initial
        // positions, later ones only round-off. It may not carry a node far or through
        // the body (whichever loop runs the steps).
        state
            .check_static_projection()
            .map_err(|(entry, problem)| InitError::Input { entry, problem })?;
        // The host loop's linear solver starts first (a missing GPU adapter for `linear =
        // "gpu"` is said before anything else).
        let host = if on_device {
            None
        } else {
            Some(HostBackend::new(&state, &linear)?)
        };
        let _setup = host.as_ref().map(|h| h.phases.open(Phase::Setup));
        // Build (and validate) the static constraint set up front: bad conditions fail
        // before the first step; then every moving node eliminated at once, the largest
        // set a step can reach.
        let n_moving = state.moving_bcs.len();
        for key in [vec![false; n_moving], vec![true; n_moving]] {
            if let Err(e) = state.build_frames(&key) {
                return Err(InitError::Input {
                    entry: e.label,
                    problem: e.problem,
                });
            }
        }
        let backend: Box<dyn Backend + 's> = match host {
            Some(h) => Box::new(h),
            None => Box::new(DeviceLoop::start(&state)?),
        };
        let forcing = Forcing::new(
            scene.solver.cg_tolerance,
            state.newton_tol * scene.time_step,
        );
        Ok(Stepper {
            state,
            backend,
            forcing,
        })
    }

    /// Everything the next step depends on (see [`Snapshot`]).
    pub fn snapshot(&self) -> Snapshot {
        Snapshot {
            forcing_first_step: self.forcing.carried(),
            ..self.state.snapshot()
        }
    }

    /// Continues from `snap`, taken from a stepper of the same scene: the next
    /// [`Stepper::step`] gives the same bits as the stepper it was taken from would have.
    /// Fails (and changes nothing) when the snapshot's sizes do not fit this scene.
    pub fn restore(&mut self, snap: &Snapshot) -> Result<(), StepError> {
        self.state.restore(snap).map_err(StepError::Snapshot)?;
        self.forcing.resume(snap.forcing_first_step);
        self.backend.restore(&self.state)
    }

    /// The GPU adapter the run uses (the device loop's, or the GPU linear solver's).
    pub fn adapter(&self) -> Option<&str> {
        self.backend.adapter()
    }

    /// Opens `phase` of the loop's profile until the span drops (`None` without one).
    pub fn phase(&self, phase: Phase) -> Option<PhaseSpan> {
        self.backend.phase(phase)
    }

    /// The CPU loop's profile so far: every second since the run began, by phase (None
    /// for the device loop, whose profile is in [`Stepper::gpu_report`]).
    pub fn host_profile(&self) -> Option<Profile> {
        self.backend.host_profile()
    }

    /// The run began at `run_start` (its set-up before the device existed is profiled).
    pub fn started_at(&self, run_start: std::time::Instant) {
        self.backend.started_at(run_start);
    }

    /// What the GPU did so far: the device loop's report, or for the host loop with
    /// `linear = "gpu"` the linear solver's traffic and operator size; None for a run
    /// without a GPU. `newton_iterations` is left for the caller, who counts them.
    pub fn gpu_report(&self) -> Option<GpuRunReport> {
        self.backend.gpu_report(&self.state)
    }

    /// Advances one step: the start-of-step projection, Newton (with the moving-boundary
    /// updates and the CCD-bounded line search), then the end-of-step recovery of forces,
    /// velocities and state.
    pub fn step(&mut self) -> Result<StepReport, StepError> {
        self.step_with(None)
    }

    /// [`Stepper::step`], handing every Newton system of the step (after its solve) to
    /// `dump` when given (`run --dump-systems`).
    pub fn step_with(&mut self, mut dump: Option<SystemSink>) -> Result<StepReport, StepError> {
        let sc = self.state.scene;
        let t1 = self.state.t + sc.time_step;
        let mut rep = StepReport {
            step: self.state.step + 1,
            time: t1,
            k_m: self.state.k_m,
            ..StepReport::default()
        };
        // 1. Static projection, xⁿ and x̃; obstacles at t^{n+1}.
        self.backend.begin_step(&self.state)?;
        if self.state.contact.is_some() {
            let _contact = self.backend.phase(Phase::Contact);
            self.advance_obstacles(t1)?;
            rep.min_distance = Some(self.check_distance("at the start of the step")?);
        }
        // The classical neo-Hookean law needs every element's J > 0 in the starting state.
        if sc.model.has_law(Law::NeoHookean) {
            let _checks = self.backend.phase(Phase::Checks);
            let x = self.backend.positions(None)?;
            let inverted = sc
                .model
                .min_volume_ratio(x)
                .into_iter()
                .find(|m| m.law == Law::NeoHookean && (m.j.is_nan() || m.j <= 0.0));
            if let Some(m) = inverted {
                return Err(StepError::InvertedStart {
                    body: m.set,
                    element: m.element,
                    j: m.j,
                    law: m.law.name(),
                    iteration: 0,
                });
            }
        }
        // 2. Moving targets at t^{n+1}; nodes already within ε are snapped now.
        let moving_terms = self.backend.phase(Phase::MovingBoundary);
        let mut moving = MovingTargets {
            shapes: self
                .state
                .moving_bcs
                .iter()
                .map(|&k| sc.bcs[k].shape_at(t1))
                .collect(),
            snapped: vec![false; self.state.moving_bcs.len()],
        };
        self.snap(&mut moving)?;
        drop(moving_terms);
        // 3. Newton.
        let levels = self.backend.multilevel_levels();
        self.newton(&mut moving, &mut rep, &mut dump)?;
        let (built, kept) = self.backend.multilevel_levels();
        (rep.multilevel_built, rep.multilevel_kept) = (built - levels.0, kept - levels.1);
        // 4. Reactions and contact forces at the converged iterate.
        let end = self.backend.end_step(&self.state)?;
        let checks = self.backend.phase(Phase::Checks);
        self.check_inversion(&end.x, &mut rep)?;
        self.state.recover_forces(&end.x, &end.g, &moving.snapped);
        drop(checks);
        // 5. Velocity and state.
        self.state.finish_step(end.x, end.v, t1)?;
        Ok(rep)
    }

    /// The end state's smallest element volume ratio and the laws with an inverted
    /// element, into `rep`; with `[solver] inversion = "fail"` an inverted element fails
    /// the step, naming it.
    fn check_inversion(&self, x: &[f64], rep: &mut StepReport) -> Result<(), StepError> {
        let sc = self.state.scene;
        let per_law = sc.model.min_volume_ratio(x);
        rep.min_j = per_law
            .iter()
            .map(|m| m.j)
            .reduce(|a, b| if b < a || b.is_nan() { b } else { a });
        for m in per_law.iter().filter(|m| m.j.is_nan() || m.j <= 0.0) {
            rep.inverted.push(m.law);
            if sc.solver.inversion == InversionPolicy::Fail {
                return Err(StepError::InvertedEnd {
                    body: m.set,
                    element: m.element,
                    j: m.j,
                    law: m.law.name(),
                });
            }
        }
        Ok(())
    }

    /// Moves the obstacles to t1 on the host (and the backend's planes); a moving obstacle
    /// may push starting guesses ahead of it, which the backend then stores.
    fn advance_obstacles(&mut self, t1: f64) -> Result<(), StepError> {
        let moves = self
            .state
            .scene
            .obstacles
            .iter()
            .any(|o| o.motion.is_some());
        if moves {
            let x = self.backend.positions(None)?;
            if self.state.advance_obstacles(t1, x) {
                self.backend.write_positions(None)?;
            }
        } else {
            self.state.advance_obstacles(t1, &mut []);
        }
        if let Some(c) = &self.state.contact {
            self.backend.set_planes(&c.planes)?;
        }
        Ok(())
    }

    /// The smallest distance of the current iterate to the obstacles, or the error naming
    /// the node when it touches or crosses one (call only with obstacles).
    fn check_distance(&mut self, when: &str) -> Result<f64, StepError> {
        let nearest = self.backend.min_distance(&self.state)?;
        self.state.check_distance(nearest, when)
    }

    /// Snaps the unsnapped moving nodes within ε·h of their targets, on the backend's
    /// positions; true when a node snapped (the iterate and E changed).
    fn snap(&mut self, moving: &mut MovingTargets) -> Result<bool, StepError> {
        let _moving = self.backend.phase(Phase::MovingBoundary);
        let nodes = self.state.unsnapped_nodes(&moving.snapped);
        if nodes.is_empty() {
            return Ok(false);
        }
        let before = moving.snapped.clone();
        let x = self.backend.positions(Some(&nodes))?;
        self.state
            .snap_satisfied(x, &moving.shapes, &mut moving.snapped);
        let newly: Vec<usize> = (0..before.len())
            .filter(|&j| moving.snapped[j] && !before[j])
            .map(|j| self.state.scene.bcs[self.state.moving_bcs[j]].node)
            .collect();
        if !newly.is_empty() {
            self.backend.write_positions(Some(&newly))?;
        }
        Ok(!newly.is_empty())
    }

    /// Newton on E from the starting iterate: per iteration the eliminated solve; when it
    /// has converged with moving nodes still off target, the moving-boundary update;
    /// otherwise the CCD-bounded line search. The step is done when ‖Δx‖∞/h < tol with
    /// every moving node snapped and eliminated, at an iterate whose forces balance
    /// (`balance.rs`).
    fn newton(
        &mut self,
        moving: &mut MovingTargets,
        rep: &mut StepReport,
        dump: &mut Option<SystemSink>,
    ) -> Result<(), StepError> {
        let sc = self.state.scene;
        let h = sc.time_step;
        let mut all_snapped_at = None;
        let mut residual_at_update = f64::INFINITY;
        let mut iter = 0usize;
        // Taken for the step (the loop borrows self), put back at its end.
        let mut forcing = self.forcing.clone();
        forcing.restart();
        let mut sequence_of = moving.snapped.clone();
        // The last iterate that passed the ‖Δx‖∞ test without balancing its forces.
        let mut unbalanced: Option<ForceBalance> = None;
        // E at the current iterate when the last line search evaluated it there (its
        // accepted trial) and nothing has changed E or the iterate since: a snap moves
        // nodes and drops their penalty terms, a moving-boundary update changes k_M.
        let mut energy_here: Option<f64> = None;
        loop {
            if iter >= sc.solver.max_newton_iterations {
                return Err(StepError::NewtonLimit {
                    iterations: iter,
                    moving: self.state.has_moving().then(|| {
                        (
                            self.state.k_m,
                            moving.snapped.iter().filter(|s| !**s).count(),
                        )
                    }),
                    unbalanced: unbalanced.map(|b| Unbalanced {
                        node: b.node,
                        force: b.residual / (h * h),
                        ratio: b.residual / b.scale,
                        tol: sc.solver.force_tolerance,
                    }),
                });
            }
            if !moving.snapped.is_empty()
                && moving.snapped.iter().all(|&s| s)
                && all_snapped_at.is_none()
            {
                all_snapped_at = Some(iter);
            }
            iter += 1;
            // A node snapped and eliminated: another system, another forcing sequence.
            if moving.snapped != sequence_of {
                forcing.restart();
                sequence_of.clone_from(&moving.snapped);
            }
            let frames = self.backend.phase(Phase::Elimination);
            self.state.build_frames(&moving.snapped)?;
            drop(frames);
            let stats = self
                .backend
                .direction(&self.state, moving, iter, &mut forcing)?;
            rep.add_solve(&stats);
            let mut last = stats;
            let mut dmax = self.max_abs_dx(iter)?;
            let tight = forcing.converged_tolerance();
            if dmax / h < self.state.newton_tol && stats.tolerance.is_some_and(|t| t > tight) {
                // The test passed on a loosely solved direction: it is judged on the same
                // system solved to the convergence tolerance, whatever the sequence did.
                let stats = self.backend.resolve(&self.state, moving, iter, tight)?;
                rep.add_solve(&stats);
                last = stats;
                rep.linear_resolves += 1;
                dmax = self.max_abs_dx(iter)?;
            }
            forcing.step_taken(dmax);
            if let Some(sink) = dump.as_mut() {
                let _output = self.backend.phase(Phase::Output);
                let a = self.backend.system()?;
                sink(NewtonSystem {
                    step: rep.step,
                    iteration: iter,
                    dim: sc.dim,
                    h: a.h,
                    g: a.g,
                    x: a.x,
                    dx: a.dx,
                    constraints: self.state.constraints_of(&moving.snapped),
                    tolerance: last.tolerance,
                    iterations: last.iterations,
                })
                .map_err(|cause| StepError::Dump {
                    iteration: iter,
                    cause,
                })?;
            }
            if dmax / h < self.state.newton_tol {
                if moving.snapped.iter().all(|&s| s) {
                    // Short steps are not enough: the forces must balance too (a huge h
                    // or a stiff barrier makes every step short).
                    let _checks = self.backend.phase(Phase::Checks);
                    let b = self.backend.force_balance(&self.state, &moving.snapped)?;
                    rep.force_residual = Some(b.residual / b.scale);
                    if b.stationary(dmax, sc.solver.force_tolerance) {
                        break;
                    }
                    unbalanced = Some(b);
                } else {
                    // Converged with the penalty but nodes still off target.
                    let _moving = self.backend.phase(Phase::MovingBoundary);
                    let nodes = self.state.unsnapped_nodes(&moving.snapped);
                    let x = self.backend.positions(Some(&nodes))?;
                    if self
                        .state
                        .update_moving_penalty(x, moving, &mut residual_at_update)?
                    {
                        rep.k_m_doublings += 1;
                    }
                    // The penalty changed the energy: a new forcing sequence.
                    forcing.restart();
                    energy_here = None;
                    continue;
                }
            }
            self.line_search(moving, dmax, iter, rep, &mut energy_here)?;
            if self.snap(moving)? {
                energy_here = None;
            }
            if self.state.contact.is_some() {
                let _contact = self.backend.phase(Phase::Contact);
                let d = self.check_distance(&format!("after Newton iteration {iter}"))?;
                rep.min_distance = Some(rep.min_distance.map_or(d, |m| m.min(d)));
            }
        }
        self.forcing = forcing;
        rep.newton_iterations = iter;
        rep.eliminated_at_iteration = all_snapped_at;
        rep.k_m = self.state.k_m;
        Ok(())
    }

    /// ‖Δx‖∞ of the last direction; an error when it is not finite.
    fn max_abs_dx(&mut self, iter: usize) -> Result<f64, StepError> {
        let dmax = self.backend.max_abs_dx()?;
        if !dmax.is_finite() {
            return Err(StepError::DirectionNotFinite { iteration: iter });
        }
        Ok(dmax)
    }

    /// Armijo backtracking on E along Δx, from the CCD bound α_C when there is contact (1
    /// without), lowered to [`INVERSION_FRACTION`] of the first step that inverts an
    /// element of the classical neo-Hookean law (an element already inverted fails the
    /// step, naming it); the accepted iterate becomes the current one. When no step decreases E,
    /// the bounded step is taken if the energy is flat to round-off near the minimum and
    /// the step fails otherwise. A bounded step taken whole is checked by
    /// [`State::check_unbarriered_limit`]. `energy_here` is E at the current iterate when
    /// known (the same function at the same positions, so the same bits as evaluating it
    /// again); it leaves as E at the accepted iterate when the search evaluated it there.
    fn line_search(
        &mut self,
        moving: &MovingTargets,
        dmax: f64,
        iter: usize,
        rep: &mut StepReport,
        energy_here: &mut Option<f64>,
    ) -> Result<(), StepError> {
        let h = self.state.scene.time_step;
        let _line_search = self.backend.phase(Phase::LineSearch);
        let e0 = match energy_here.take() {
            Some(e) => e,
            None => self.backend.energy(&self.state, moving, false)?,
        };
        if !e0.is_finite() {
            // Positions far beyond the scene (a moving target running off at 1e300 m/s) overflow the
            // energy; line-searching NaN would "converge" and write NaN results.
            return Err(StepError::EnergyNotFinite {
                energy: e0,
                iteration: iter,
            });
        }
        let slope = self.backend.slope()?;
        rep.max_slope = Some(rep.max_slope.map_or(slope, |m| m.max(slope)));
        if slope.is_nan() || slope >= 0.0 {
            rep.ascent_directions += 1;
        }
        let ccd = if self.state.contact.is_some() {
            let _contact = self.backend.phase(Phase::Contact);
            self.state.ccd_calls += 1;
            self.backend.ccd(&self.state)?
        } else {
            Ccd {
                alpha: 1.0,
                limit: None,
            }
        };
        let mut alpha_c = ccd.alpha;
        if alpha_c < 1.0 {
            rep.ccd_limited += 1;
        }
        // Classical neo-Hookean elements: start below the first step size that inverts one.
        if self.state.scene.model.has_law(Law::NeoHookean) {
            let bound = {
                let _bound = self.backend.phase(Phase::InversionBound);
                self.backend
                    .inversion_bound(&self.state, 1.0 / INVERSION_FRACTION)?
            };
            match bound {
                Ok(Some(b)) if INVERSION_FRACTION * b.alpha < alpha_c => {
                    alpha_c = INVERSION_FRACTION * b.alpha;
                    rep.inversion_limited += 1;
                }
                Ok(_) => {}
                Err(inv) => {
                    return Err(StepError::InvertedStart {
                        body: inv.set,
                        element: inv.element,
                        j: inv.j,
                        law: Law::NeoHookean.name(),
                        iteration: iter,
                    })
                }
            }
        }
        let mut alpha = alpha_c;
        let mut accepted = false;
        // Near the minimum, a decrease below the energy's rounding cannot be judged:
        // Armijo would compare noise, and a tiny step that happens to pass it stalls
        // Newton. When even the whole bounded step predicts less than ENERGY_ULPS·ε·|E|,
        // it is taken, as the flat case below takes it.
        let near = dmax / h < 1e3 * self.state.newton_tol;
        let flat =
            near && slope <= 0.0 && -alpha_c * slope <= ENERGY_ULPS * f64::EPSILON * e0.abs();
        if flat {
            self.backend.set_trial(alpha_c)?;
            accepted = true;
        }
        for _ in 0..MAX_HALVINGS {
            if accepted {
                break;
            }
            self.backend.set_trial(alpha)?;
            let e1 = self.backend.energy(&self.state, moving, true)?;
            if e1 <= e0 + ARMIJO * alpha * slope.min(0.0) {
                accepted = true;
                *energy_here = Some(e1);
                break;
            }
            alpha *= 0.5;
        }
        if !accepted {
            // Energy flat to round-off near the minimum: take the full (CCD-bounded) step.
            if near {
                alpha = alpha_c;
                self.backend.set_trial(alpha_c)?;
            } else {
                return Err(StepError::NoDecrease {
                    iteration: iter,
                    rate: dmax / h,
                });
            }
        }
        if alpha == ccd.alpha {
            if let Some((node, _)) = ccd.limit {
                let _contact = self.backend.phase(Phase::Contact);
                let x = self.backend.positions(Some(&[node]))?;
                self.state.check_unbarriered_limit(x, &ccd, iter)?;
            }
        }
        self.backend.accept()
    }
}
