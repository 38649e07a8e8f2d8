//! Implicit Euler as an incremental potential (IPC style), with Dirichlet conditions
//! eliminated by the per-node change of basis and moving conditions as in docs/method.md
//! ("Time integration", "Moving boundary conditions").
//!
//! One step n → n+1 (h the time step, x̃ = xⁿ + h vⁿ):
//!
//! ```text
//! E(x) = ½ (x − x̃)ᵀ M (x − x̃) + h² Ψ(x) + Σ_{k unsatisfied} [½ k_M m_k ‖r_k(x)‖² − √m_k λ_kᵀ r_k(x)]
//! ```
//!
//! 1. Static conditions are projected at the start (sticky nodes snapped, slip nodes
//!    projected onto their plane or line; a node with several conditions onto their
//!    intersection, which must exist: see [`crate::sim::scene::joint_targets`]); they then hold
//!    through every Newton step because every step is homogeneous (Δx has no constrained
//!    component).
//! 2. Moving condition k has a target set at t^{n+1} (x̂_k for sticky, a moved plane or
//!    line for slip); r_k is the node's offset from it (slip: along the normal only). A node
//!    with ‖r_k‖/h < ε is snapped onto its target and eliminated; the others carry the
//!    penalty. When Newton converges with nodes still unsatisfied, k_M doubles (capped;
//!    with the augmented Lagrangian, λ is updated and k_M doubles only when the residual
//!    did not halve). k_M persists across steps. The step ends only when every moving node
//!    is eliminated and Newton has converged with elimination alone.
//! 3. Newton: eliminated linear solve (oracle / CG / GPU), Armijo backtracking, stop when
//!    ‖Δx‖∞/h < tol. Frames are built once per constraint set and cached, so are the
//!    oracle's symbolic analysis and the GPU solver (keyed by the set).
//! 4. v^{n+1} = (x^{n+1} − xⁿ)/h. Reactions f = +(constrained part of ∇E)/h² per node (the
//!    components along C_i): the force the supports exert on the body, in newtons, so that
//!    Σ m (v^{n+1} − vⁿ) = h (M g + Σ f) holds exactly when Newton has converged (a body
//!    resting on a floor gets an upward f). Sign: M(x − x̃) + h²∇Ψ = ∇E, and at the
//!    constrained minimum ∇E vanishes on free components and equals h² f on constrained
//!    ones. This is −1 times `elimination::reactions` (−(HΔx + g), the load on the
//!    support). Moving nodes are eliminated at the end of every step, so the force that
//!    drives them shows up as their reaction; no penalty force is left at the end of a step.
//!
//! Contact (only when the scene declares obstacles; docs/method.md, "Contact with
//! half-spaces"): E gains h² P_b(x), the distance
//! barrier of [`crate::sim::energy::barrier`] against every half-space at its end-of-step
//! position. Each line search starts from the CCD bound α_C (every node, interior nodes
//! included, covers at most [`CCD_FRACTION`] of its distance to every plane) and backtracks
//! from there, so every Newton iterate keeps every node on the allowed side; the smallest
//! distance over all nodes and iterates of a step is reported. Interior nodes of a solid
//! carry no barrier: when the bound is what stops one (the line search takes α_C and the
//! node sets it), the step fails naming the node and the obstacle, since Newton would only
//! creep towards the plane from there (the body has inverted). A moving half-space that
//! would overtake a node within one step pushes that (unconstrained) node's initial guess
//! ahead of it first (to half its gap at tⁿ): only the starting iterate changes, the
//! minimized energy does not. The contact force
//! c = −∇P_b (newtons) is an external force counted apart from the reactions:
//! Σ m (v^{n+1} − vⁿ) = h (M g + Σ f + Σ c). On a constrained node within d̂, the reaction
//! is taken net of the barrier (f = constrained part of ∇E/h², which includes h²∇P_b).

mod device;

pub use device::{device_bytes_needed, GpuRunReport};

use crate::core::constraints::{Constraint, ConstraintKind, Frames};
use crate::core::elimination::{ConstrainedDiagonal, Eliminated};
use crate::core::linalg::norm3;
use crate::core::sparse::BlockCsr;
use crate::sim::energy::barrier::{Barrier, Ccd, HalfSpace};
use crate::sim::energy::{inertia, AssemblyWork};
use crate::sim::scene::{
    check_solver_size, joint_targets, BcShape, JointTarget, LinearKind, NewtonLoop, Scene,
    SolverSpec,
};
use crate::{LayoutKey, Solver};
use std::cell::Cell;
use std::collections::HashMap;
use std::time::Instant;

/// Armijo sufficient-decrease constant.
const ARMIJO: f64 = 1e-4;
/// Backtracking halvings before the line search gives up.
const MAX_HALVINGS: usize = 40;
/// Largest relative residual ‖b̂ − Ĥy‖/‖b̂‖ accepted from a Cholesky solve inside Newton.
/// A factorization that succeeds on a nearly singular Ĥ can return a direction this far
/// off; the step then fails (naming the residual) instead of line-searching a wrong
/// direction, as the CG and GPU paths fail when they miss their tolerance.
pub const CHOLESKY_MAX_RESIDUAL: f64 = 1e-8;
/// CCD filter: a Newton step may cover at most this fraction of any node's distance to an
/// obstacle (IPC's 1 − s with s = 0.1).
pub const CCD_FRACTION: f64 = 0.9;

/// What one linear solve cost.
#[derive(Debug, Clone, Copy, Default)]
pub struct LinearStats {
    /// CG iterations; a direct (Cholesky) solve counts as one.
    pub iterations: usize,
    pub seconds: f64,
}

/// The linear solver behind every Newton step: the library [`Solver`], with one
/// [`LayoutKey`] per constraint set so that each set keeps its analysis or GPU buffers.
pub struct LinearSolver {
    kind: LinearKind,
    solver: Solver,
    layouts: HashMap<Vec<bool>, LayoutKey>,
    /// GPU adapter name, when the GPU runs.
    pub adapter: Option<String>,
}

impl LinearSolver {
    pub fn new(spec: &SolverSpec) -> Result<Self, String> {
        let solver = Solver::new(spec.config()).map_err(|e| e.to_string())?;
        Ok(LinearSolver {
            kind: spec.linear,
            adapter: solver.adapter().map(str::to_string),
            solver,
            layouts: HashMap::new(),
        })
    }

    /// Solves the eliminated system and recovers Δx. `key` names the constraint set.
    pub fn solve(
        &mut self,
        key: &[bool],
        e: &Eliminated,
    ) -> Result<(Vec<f64>, LinearStats), String> {
        let t = Instant::now();
        let layout = *self
            .layouts
            .entry(key.to_vec())
            .or_insert_with(LayoutKey::fresh);
        let step = self
            .solver
            .solve_eliminated(layout, e)
            .map_err(|err| err.to_string())?;
        if self.kind == LinearKind::Cholesky {
            check_cholesky_residual(step.stats.relative_residual)?;
        }
        Ok((
            step.dx,
            LinearStats {
                // A direct (Cholesky) solve counts as one.
                iterations: step.stats.iterations.unwrap_or(1),
                seconds: t.elapsed().as_secs_f64(),
            },
        ))
    }
}

/// Why a stepper could not start.
#[derive(Debug, Clone, PartialEq)]
pub enum InitError {
    /// The scene's conditions are inconsistent; `entry` names the scene entry.
    Input { entry: String, problem: String },
    /// The linear solver cannot start.
    Solver(String),
}

/// What one step did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct StepReport {
    pub step: usize,
    pub time: f64,
    pub newton_iterations: usize,
    pub linear_iterations: usize,
    pub linear_seconds: f64,
    /// k_M at the end of the step (meaningful when the scene has moving conditions).
    pub k_m: f64,
    /// k_M doublings in this step.
    pub k_m_doublings: usize,
    /// Newton iteration at which the last moving node was snapped and eliminated
    /// (0: all were satisfied at the start of the step); None without moving conditions.
    pub eliminated_at_iteration: Option<usize>,
    /// Largest ‖x_k − x̂_k‖ of a moving node at the end of the step (0 once snapped).
    pub moving_max_error: f64,
    /// Contact only: the smallest signed distance of any node to any obstacle over every
    /// Newton iterate of the step (including its starting iterate).
    pub min_distance: Option<f64>,
    /// Largest directional derivative gᵀΔx over the step's line-searched Newton iterates
    /// (negative: every Newton step was a descent direction); None when no line search ran.
    pub max_slope: Option<f64>,
    /// Line-searched iterates whose Newton step was not a descent direction (gᵀΔx ≥ 0).
    pub ascent_directions: usize,
    /// Line searches whose CCD bound α_C was below 1.
    pub ccd_limited: usize,
}

/// What the contact code did (all zero for a scene without obstacles).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct ContactCounters {
    /// Barrier energy, gradient or Hessian evaluations.
    pub barrier_evaluations: u64,
    /// CCD (α_C) computations.
    pub ccd_calls: u64,
    /// Initial guesses pushed ahead of a moving obstacle.
    pub pushed_nodes: u64,
}

/// The barrier and the obstacles' half-spaces for the current step.
struct Contact {
    barrier: Barrier,
    planes: Vec<HalfSpace>,
}

/// Time stepper state.
pub struct Stepper<'s> {
    pub scene: &'s Scene,
    pub x: Vec<f64>,
    pub v: Vec<f64>,
    pub t: f64,
    pub step: usize,
    pub k_m: f64,
    /// Per moving condition: the augmented-Lagrangian multiplier.
    lambda: Vec<[f64; 3]>,
    static_bcs: Vec<usize>,
    /// The static conditions projected one by one: those alone on their node.
    single_static_bcs: Vec<usize>,
    /// Nodes with several static conditions, projected onto their intersection.
    joint: Vec<JointTarget>,
    moving_bcs: Vec<usize>,
    frames: HashMap<Vec<bool>, Frames>,
    pub linear: LinearSolver,
    hmat: BlockCsr,
    /// Element buffers of the gradient and Hessian assembly, kept across Newton iterations.
    assembly: AssemblyWork,
    /// Reaction force per DOF at the end of the last step (newtons).
    pub reactions: Vec<f64>,
    /// Newton tolerance on ‖Δx‖∞/h (m/s).
    pub newton_tol: f64,
    /// ε of the moving conditions (m/s).
    pub moving_eps: f64,
    /// None for a scene without obstacles: no contact code runs at all.
    contact: Option<Contact>,
    barrier_evals: Cell<u64>,
    ccd_calls: u64,
    pushed_nodes: u64,
    /// Contact force per DOF at the end of the last step (newtons; empty without obstacles).
    pub contact_forces: Vec<f64>,
    /// Reused work vectors of [`Stepper::step`] (no allocation per Newton iteration).
    work: StepWork,
    /// The device side of the GPU Newton loop (`[solver] newton = "gpu"`); None: the CPU
    /// loop.
    device: Option<device::DeviceLoop>,
}

/// Work vectors of one step, kept between steps so the Newton loop does not allocate them.
/// Every entry is overwritten before it is read; they carry no state between steps.
#[derive(Default)]
struct StepWork {
    /// xⁿ, the positions at the start of the step.
    xn: Vec<f64>,
    /// x̃ = xⁿ + h vⁿ.
    xt: Vec<f64>,
    /// ∇E at the current iterate.
    g: Vec<f64>,
    /// The line search's trial iterate (swapped with x when accepted).
    xtry: Vec<f64>,
    /// The gradient in the nodes' frames (reactions).
    gy: Vec<f64>,
}

/// The moving conditions within one step.
struct MovingTargets {
    /// Per moving condition, its target set at t^{n+1}.
    shapes: Vec<BcShape>,
    /// Per moving condition, whether its node has been snapped onto the target and
    /// eliminated (the key of the constraint set).
    snapped: Vec<bool>,
}

/// One Newton direction, for the line search.
struct NewtonStep {
    dx: Vec<f64>,
    /// ‖Δx‖∞.
    dmax: f64,
    /// The iteration it was computed at (counting from 1), for messages.
    iter: usize,
}

impl<'s> Stepper<'s> {
    /// Fails with [`InitError::Input`] when the scene's conditions are inconsistent (for
    /// example contradictory conditions on one node, see [`joint_targets`]) or the scene
    /// is too big for its linear solver ([`check_solver_size`]: the solver may have been
    /// overridden after parsing), and [`InitError::Solver`] when the linear solver cannot
    /// start (no GPU adapter).
    pub fn new(scene: &'s Scene) -> Result<Self, InitError> {
        let on_device = scene.solver.newton == NewtonLoop::Gpu;
        // The GPU loop has its own CG; the CPU one is never called (a CG costs nothing to
        // build, a second GPU device would).
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
        let mut s = Stepper {
            scene,
            x: scene.x0.clone(),
            v: scene.v0.clone(),
            t: 0.0,
            step: 0,
            k_m: scene.moving.penalty_start,
            lambda: vec![[0.0; 3]; moving_bcs.len()],
            static_bcs,
            single_static_bcs,
            joint,
            moving_bcs,
            frames: HashMap::new(),
            linear: LinearSolver::new(&linear).map_err(InitError::Solver)?,
            hmat: scene.model.zero_matrix(),
            assembly: AssemblyWork::default(),
            reactions: vec![0.0; scene.x0.len()],
            newton_tol: scene.solver.newton_tolerance * scene.characteristic_length,
            moving_eps: scene.moving.tolerance * scene.characteristic_length,
            contact: scene.has_obstacles().then(|| Contact {
                barrier: Barrier::new(scene.dim, scene.contact_weight.clone()),
                planes: scene.obstacles.iter().map(|o| o.at(0.0)).collect(),
            }),
            barrier_evals: Cell::new(0),
            ccd_calls: 0,
            pushed_nodes: 0,
            contact_forces: if scene.has_obstacles() {
                vec![0.0; scene.x0.len()]
            } else {
                Vec::new()
            },
            work: StepWork::default(),
            device: None,
        };
        // Build (and validate) the static constraint set up front: bad conditions fail
        // before the first step.
        let key = vec![false; s.moving_bcs.len()];
        if let Err(e) = s.build_frames(&key) {
            return Err(InitError::Input {
                entry: e.label,
                problem: e.problem,
            });
        }
        // Every moving node eliminated at once: the largest set a step can reach.
        let all = vec![true; s.moving_bcs.len()];
        if let Err(e) = s.build_frames(&all) {
            return Err(InitError::Input {
                entry: e.label,
                problem: e.problem,
            });
        }
        if on_device {
            s.start_device()?;
        }
        Ok(s)
    }

    pub fn has_moving(&self) -> bool {
        !self.moving_bcs.is_empty()
    }

    pub fn has_contact(&self) -> bool {
        self.contact.is_some()
    }

    /// What the contact code has done so far.
    pub fn contact_counters(&self) -> ContactCounters {
        ContactCounters {
            barrier_evaluations: self.barrier_evals.get(),
            ccd_calls: self.ccd_calls,
            pushed_nodes: self.pushed_nodes,
        }
    }

    /// Smallest signed distance of any node to any obstacle at its current (end-of-step)
    /// position, with the node and the obstacle's index; None without obstacles.
    pub fn min_distance(&self, x: &[f64]) -> Option<(f64, usize, usize)> {
        self.contact
            .as_ref()
            .map(|c| c.barrier.min_distance(x, &c.planes))
    }

    /// Fails naming the node and the obstacle when an iterate touches or crosses one.
    fn check_distance(&self, x: &[f64], when: &str) -> Result<Option<f64>, String> {
        match self.min_distance(x) {
            Some((d, node, j)) if d.is_nan() || d <= 0.0 => Err(format!(
                "node {node} is at signed distance {d:e} m from {} {when}: the configuration must stay penetration-free",
                self.scene.obstacles[j].label
            )),
            Some((d, _, _)) => Ok(Some(d)),
            None => Ok(None),
        }
    }

    /// Fails when the step the line search took is the CCD bound α_C < 1 and the node that
    /// sets the bound has no barrier weight (an interior node of a solid). Nothing in E holds
    /// such a node off the obstacle, so Newton would keep heading for the plane, each step
    /// cut to 0.9 of the gap, and stall. At α_C/[`CCD_FRACTION`] that node touches the
    /// plane before any other node has reached it (barring an exact tie): the body's
    /// interior crosses its own boundary, so the body has (or is about to have) inverted.
    fn check_unbarriered_limit(&self, x: &[f64], ccd: &Ccd, iter: usize) -> Result<(), String> {
        let (Some(c), Some((node, j))) = (&self.contact, ccd.limit) else {
            return Ok(());
        };
        if ccd.alpha >= 1.0 || c.barrier.weight[node] > 0.0 {
            return Ok(());
        }
        let d = self.scene.dim;
        let gap = c.planes[j].distance(&x[node * d..(node + 1) * d]);
        Err(format!(
            "interior node {node} (no contact barrier) is held off {} only by the CCD bound at Newton iteration {iter} (it was {gap:e} m away, the step covers {CCD_FRACTION} of that): the body has likely inverted; use a stiffer material, a smaller time step or a finer mesh",
            self.scene.obstacles[j].label
        ))
    }

    fn frames_for(&mut self, key: &[bool]) -> Result<(), String> {
        self.build_frames(key).map_err(|e| e.to_string())
    }

    fn build_frames(
        &mut self,
        key: &[bool],
    ) -> Result<(), crate::core::constraints::ConstraintError> {
        if self.frames.contains_key(key) {
            return Ok(());
        }
        let d = self.scene.dim;
        let mut cs = Vec::new();
        let active = self.static_bcs.iter().copied().chain(
            self.moving_bcs
                .iter()
                .zip(key)
                .filter(|(_, &on)| on)
                .map(|(&k, _)| k),
        );
        for k in active {
            let b = &self.scene.bcs[k];
            let kind = match &b.shape {
                BcShape::Sticky { .. } => ConstraintKind::Sticky { displacement: None },
                BcShape::Plane { normal, .. } => ConstraintKind::Plane {
                    normal: normal[..d].to_vec(),
                    offset: 0.0,
                },
                BcShape::Line { direction, .. } => ConstraintKind::Line {
                    direction: direction[..d].to_vec(),
                    offset: None,
                },
            };
            cs.push(Constraint {
                node: b.node,
                kind,
                label: b.label.clone(),
            });
        }
        let f = if cs.is_empty() {
            Frames::unconstrained(d, self.scene.model.n_nodes)
        } else {
            Frames::build(d, self.scene.model.n_nodes, &cs)?
        };
        self.frames.insert(key.to_vec(), f);
        Ok(())
    }

    /// E(x) for the current step.
    fn energy(&self, x: &[f64], xt: &[f64], targets: &[BcShape], snapped: &[bool]) -> f64 {
        let sc = self.scene;
        let h = sc.time_step;
        let d = sc.dim;
        let mut e = inertia::energy(&sc.model.mass, d, x, xt) + h * h * sc.model.potential(x);
        for (j, &k) in self.moving_bcs.iter().enumerate() {
            if snapped[j] {
                continue;
            }
            let b = &sc.bcs[k];
            let m = sc.model.mass[b.node];
            let r = offset(d, &targets[j], &x[b.node * d..(b.node + 1) * d]);
            let rr: f64 = r.iter().map(|v| v * v).sum();
            let lr: f64 = (0..3).map(|a| self.lambda[j][a] * r[a]).sum();
            e += 0.5 * self.k_m * m * rr - m.sqrt() * lr;
        }
        if let Some(c) = &self.contact {
            self.barrier_evals.set(self.barrier_evals.get() + 1);
            e += h * h * c.barrier.energy(x, &c.planes);
        }
        e
    }

    /// Advances one step: the start-of-step projection, Newton (with the moving-boundary
    /// updates and the CCD-bounded line search), then the end-of-step recovery of forces,
    /// velocities and state.
    pub fn step(&mut self) -> Result<StepReport, String> {
        if self.device.is_some() {
            return self.step_device();
        }
        let t1 = self.t + self.scene.time_step;
        let mut rep = StepReport {
            step: self.step + 1,
            time: t1,
            k_m: self.k_m,
            ..StepReport::default()
        };
        // Work vectors, taken from the stepper and put back at the end of the step (an
        // error path drops them; the next step reallocates).
        let mut w = self.take_work();
        // 1. Static projection, x̃, obstacles at t^{n+1}.
        let mut x = self.start_of_step(t1, &mut w, &mut rep)?;
        // 2. Moving targets at t^{n+1}; nodes already within ε are snapped now.
        let mut moving = MovingTargets {
            shapes: self
                .moving_bcs
                .iter()
                .map(|&k| self.scene.bcs[k].shape_at(t1))
                .collect(),
            snapped: vec![false; self.moving_bcs.len()],
        };
        self.snap_satisfied(&mut x, &moving.shapes, &mut moving.snapped);
        // 3. Newton.
        self.newton(&mut x, &mut moving, &mut w, &mut rep)?;
        // 4. Reactions and contact forces at the converged iterate.
        self.recover_forces(&x, &moving.snapped, &mut w);
        // 5. Velocity and state.
        self.finish_step(x, w, t1)?;
        Ok(rep)
    }

    /// The work vectors, sized for this scene.
    fn take_work(&mut self) -> StepWork {
        let mut w = std::mem::take(&mut self.work);
        let n = self.x.len();
        for v in [&mut w.xt, &mut w.g, &mut w.xtry, &mut w.gy] {
            v.clear();
            v.resize(n, 0.0);
        }
        w
    }

    /// Start of step: xⁿ and x̃ = xⁿ + h vⁿ into `w`, and the starting iterate, returned:
    /// the positions projected onto the static constraint sets (a node with several
    /// conditions onto their intersection, not onto each in turn). With obstacles, moves
    /// them to t1 (pushing overtaken starting guesses ahead) and records the starting
    /// distance, which must be positive.
    fn start_of_step(
        &mut self,
        t1: f64,
        w: &mut StepWork,
        rep: &mut StepReport,
    ) -> Result<Vec<f64>, String> {
        let sc = self.scene;
        let d = sc.dim;
        let h = sc.time_step;
        w.xn.clone_from(&self.x);
        let mut x = self.x.clone();
        for &k in &self.single_static_bcs {
            let b = &sc.bcs[k];
            project(d, &b.shape, &mut x[b.node * d..(b.node + 1) * d]);
        }
        for j in &self.joint {
            j.project(d, &mut x[j.node * d..(j.node + 1) * d]);
        }
        for i in 0..x.len() {
            w.xt[i] = w.xn[i] + h * self.v[i];
        }
        if self.contact.is_some() {
            self.advance_obstacles(t1, &mut x);
            rep.min_distance = self.check_distance(&x, "at the start of the step")?;
        }
        Ok(x)
    }

    /// Newton on E from `x`, which ends at the converged iterate: per iteration the
    /// eliminated solve; when it has converged with moving nodes still off target, the
    /// moving-boundary update; otherwise the CCD-bounded line search. The step is done when
    /// ‖Δx‖∞/h < tol with every moving node snapped and eliminated.
    fn newton(
        &mut self,
        x: &mut Vec<f64>,
        moving: &mut MovingTargets,
        w: &mut StepWork,
        rep: &mut StepReport,
    ) -> Result<(), String> {
        let sc = self.scene;
        let h = sc.time_step;
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
            let snapped = &moving.snapped;
            if !snapped.is_empty() && snapped.iter().all(|&s| s) && all_snapped_at.is_none() {
                all_snapped_at = Some(iter);
            }
            let dx = self.newton_direction(x, moving, w, iter, rep)?;
            iter += 1;
            let dmax = dx.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            if !dmax.is_finite() {
                return Err(format!(
                    "the Newton direction is not finite at iteration {iter}"
                ));
            }
            if dmax / h < self.newton_tol {
                if moving.snapped.iter().all(|&s| s) {
                    break;
                }
                // Converged with the penalty but nodes still off target.
                self.update_moving_penalty(x, moving, &mut residual_at_update, rep)?;
                continue;
            }
            let step = NewtonStep { dx, dmax, iter };
            self.line_search(x, &step, moving, w, rep)?;
            self.snap_satisfied(x, &moving.shapes, &mut moving.snapped);
            if self.contact.is_some() {
                let d = self.check_distance(x, &format!("after Newton iteration {iter}"))?;
                rep.min_distance = match (rep.min_distance, d) {
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

    /// The Newton direction Δx at `x`: ∇E (left in `w.g` for the line search and the
    /// reactions), ∇²E, and the eliminated solve for the current constraint set (the
    /// static conditions and the snapped moving nodes). `iter` names the iteration in errors.
    fn newton_direction(
        &mut self,
        x: &[f64],
        moving: &MovingTargets,
        w: &mut StepWork,
        iter: usize,
        rep: &mut StepReport,
    ) -> Result<Vec<f64>, String> {
        let snapped = &moving.snapped;
        self.frames_for(snapped)?;
        self.gradient(x, &w.xt, &moving.shapes, snapped, &mut w.g);
        self.hessian(x, &moving.shapes, snapped);
        // Positions far beyond the scene (a plane offset near 1e300) overflow the element
        // terms; say so here rather than as a failed factorization of a non-finite H.
        for (what, v) in [("gradient", &w.g[..]), ("Hessian", &self.hmat.values[..])] {
            if let Some(bad) = v.iter().find(|v| !v.is_finite()) {
                return Err(format!(
                    "the {what} holds {bad} at Newton iteration {iter}: the positions or \
                     velocities have overflowed f64"
                ));
            }
        }
        let frames = &self.frames[snapped];
        let e = Eliminated::new(&self.hmat, &w.g, frames, ConstrainedDiagonal::Identity);
        let (dx, stats) = self
            .linear
            .solve(snapped, &e)
            .map_err(|err| format!("linear solve failed at Newton iteration {iter}: {err}"))?;
        rep.linear_iterations += stats.iterations;
        rep.linear_seconds += stats.seconds;
        Ok(dx)
    }

    /// Moving-boundary update, when Newton has converged with moving nodes still off their
    /// targets: with the augmented Lagrangian, λ_k −= k_M √m_k r_k and k_M doubles only
    /// when the largest offset did not halve since the last update; without it, k_M
    /// doubles. Fails when k_M would have to pass its cap.
    fn update_moving_penalty(
        &mut self,
        x: &[f64],
        moving: &MovingTargets,
        residual_at_update: &mut f64,
        rep: &mut StepReport,
    ) -> Result<(), String> {
        let sc = self.scene;
        let d = sc.dim;
        let h = sc.time_step;
        let targets = &moving.shapes;
        let unsat: Vec<usize> = (0..moving.snapped.len())
            .filter(|&j| !moving.snapped[j])
            .collect();
        let worst = unsat
            .iter()
            .map(|&j| {
                let b = &sc.bcs[self.moving_bcs[j]];
                norm3(&offset(d, &targets[j], &x[b.node * d..(b.node + 1) * d]))
            })
            .fold(0.0f64, f64::max);
        let mut double = true;
        if sc.moving.augmented_lagrangian {
            for &j in &unsat {
                let b = &sc.bcs[self.moving_bcs[j]];
                let m = sc.model.mass[b.node];
                let r = offset(d, &targets[j], &x[b.node * d..(b.node + 1) * d]);
                for (l, ra) in self.lambda[j].iter_mut().zip(r) {
                    *l -= self.k_m * m.sqrt() * ra;
                }
            }
            double = worst > 0.5 * *residual_at_update;
            *residual_at_update = worst;
        }
        if double {
            if self.k_m >= sc.moving.penalty_max {
                return Err(format!(
                    "{} moving node(s) did not reach their targets (largest offset {worst:e} m, ε·h = {:e} m) with k_M at its cap {:e}",
                    unsat.len(),
                    self.moving_eps * h,
                    sc.moving.penalty_max
                ));
            }
            self.k_m = (2.0 * self.k_m).min(sc.moving.penalty_max);
            rep.k_m_doublings += 1;
        }
        Ok(())
    }

    /// Armijo backtracking on E along Δx, from the CCD bound α_C when there is contact (1
    /// without); the accepted iterate replaces `x` (the old one is left in `w.xtry`). When
    /// no step decreases E, the bounded step is taken if the energy is flat to round-off
    /// near the minimum and the step fails otherwise. A bounded step taken whole is checked
    /// by [`Stepper::check_unbarriered_limit`].
    fn line_search(
        &mut self,
        x: &mut Vec<f64>,
        step: &NewtonStep,
        moving: &MovingTargets,
        w: &mut StepWork,
        rep: &mut StepReport,
    ) -> Result<(), String> {
        let h = self.scene.time_step;
        let (dx, iter) = (&step.dx, step.iter);
        let (targets, snapped) = (&moving.shapes, &moving.snapped);
        let e0 = self.energy(x, &w.xt, targets, snapped);
        if !e0.is_finite() {
            // Positions far beyond the scene (a plane offset near 1e300) overflow the
            // energy; line-searching NaN would "converge" and write NaN results.
            return Err(format!(
                "the energy is not finite (E = {e0:e}) at Newton iteration {iter}: the positions or velocities have overflowed"
            ));
        }
        let slope: f64 = w.g.iter().zip(dx).map(|(a, b)| a * b).sum();
        rep.max_slope = Some(rep.max_slope.map_or(slope, |m| m.max(slope)));
        if slope.is_nan() || slope >= 0.0 {
            rep.ascent_directions += 1;
        }
        let ccd = self.ccd_bound(x, dx);
        let alpha_c = ccd.alpha;
        if alpha_c < 1.0 {
            rep.ccd_limited += 1;
        }
        let xtry = &mut w.xtry;
        let mut alpha = alpha_c;
        let mut accepted = false;
        for _ in 0..MAX_HALVINGS {
            for i in 0..x.len() {
                xtry[i] = x[i] + alpha * dx[i];
            }
            let e1 = self.energy(xtry, &w.xt, targets, snapped);
            if e1 <= e0 + ARMIJO * alpha * slope.min(0.0) {
                accepted = true;
                break;
            }
            alpha *= 0.5;
        }
        if !accepted {
            // Energy flat to round-off near the minimum: take the full (CCD-bounded) step.
            if step.dmax / h < 1e3 * self.newton_tol {
                alpha = alpha_c;
                for i in 0..x.len() {
                    xtry[i] = x[i] + alpha_c * dx[i];
                }
            } else {
                return Err(format!(
                    "the line search found no decrease at Newton iteration {iter} (‖Δx‖∞/h = {:e} m/s)",
                    step.dmax / h
                ));
            }
        }
        if alpha == alpha_c {
            self.check_unbarriered_limit(x, &ccd, iter)?;
        }
        std::mem::swap(x, xtry);
        Ok(())
    }

    /// The CCD bound α_C of the step Δx from x over every node and obstacle (1, bounded by
    /// nothing, without obstacles).
    fn ccd_bound(&mut self, x: &[f64], dx: &[f64]) -> Ccd {
        match &self.contact {
            Some(c) => {
                self.ccd_calls += 1;
                c.barrier.ccd(x, dx, &c.planes, CCD_FRACTION)
            }
            None => Ccd {
                alpha: 1.0,
                limit: None,
            },
        }
    }

    /// End-of-step recovery of the forces at the converged x. Reactions: the constrained
    /// components of ∇E / h², per node, in newtons (`w.g` holds ∇E at x). Contact forces:
    /// c = −∇P_b.
    fn recover_forces(&mut self, x: &[f64], snapped: &[bool], w: &mut StepWork) {
        let d = self.scene.dim;
        let h = self.scene.time_step;
        let frames = &self.frames[snapped];
        frames.to_frame(&w.g, &mut w.gy);
        for (i, &m) in frames.mask.iter().enumerate() {
            for a in 0..d {
                if m & (1 << a) == 0 {
                    w.gy[i * d + a] = 0.0;
                }
            }
        }
        frames.from_frame(&w.gy, &mut self.reactions);
        for r in self.reactions.iter_mut() {
            *r /= h * h;
        }
        if let Some(c) = &self.contact {
            self.barrier_evals.set(self.barrier_evals.get() + 1);
            self.contact_forces.iter_mut().for_each(|v| *v = 0.0);
            c.barrier
                .add_gradient(x, &c.planes, -1.0, &mut self.contact_forces);
        }
    }

    /// End of step: v^{n+1} = (x − xⁿ)/h, x becomes the state at t1 and the work vectors go
    /// back to the stepper. A kinetic energy that overflows (a static condition whose
    /// target lies near the end of the f64 range pulls its node there in one step) fails
    /// the step instead of writing NaN energies.
    fn finish_step(&mut self, x: Vec<f64>, mut w: StepWork, t1: f64) -> Result<(), String> {
        let sc = self.scene;
        let d = sc.dim;
        let h = sc.time_step;
        let xn = &w.xn;
        let ke: f64 = (0..x.len())
            .map(|i| {
                let v = (x[i] - xn[i]) / h;
                sc.model.mass[i / d] * v * v
            })
            .sum();
        if !ke.is_finite() {
            return Err(format!(
                "the velocities overflow (2·kinetic energy = {ke:e}): a node was moved by about {:e} m in one step",
                (0..x.len()).map(|i| (x[i] - xn[i]).abs()).fold(0.0f64, f64::max)
            ));
        }
        for i in 0..x.len() {
            self.v[i] = (x[i] - xn[i]) / h;
        }
        // The old positions' buffer becomes next step's xⁿ work vector.
        w.xn = std::mem::replace(&mut self.x, x);
        self.work = w;
        self.t = t1;
        self.step += 1;
        Ok(())
    }

    /// Snaps every unsnapped moving node within ε·h of its target.
    fn snap_satisfied(&self, x: &mut [f64], targets: &[BcShape], snapped: &mut [bool]) {
        let d = self.scene.dim;
        let h = self.scene.time_step;
        for (j, &k) in self.moving_bcs.iter().enumerate() {
            if snapped[j] {
                continue;
            }
            let node = self.scene.bcs[k].node;
            let xi = &mut x[node * d..(node + 1) * d];
            if norm3(&offset(d, &targets[j], xi)) / h < self.moving_eps {
                project(d, &targets[j], xi);
                snapped[j] = true;
            }
        }
    }

    fn gradient(
        &mut self,
        x: &[f64],
        xt: &[f64],
        targets: &[BcShape],
        snapped: &[bool],
        g: &mut [f64],
    ) {
        let sc = self.scene;
        let d = sc.dim;
        let h = sc.time_step;
        g.iter_mut().for_each(|v| *v = 0.0);
        inertia::add_gradient(&sc.model.mass, d, x, xt, g);
        sc.model
            .add_potential_gradient_with(x, h * h, g, &mut self.assembly);
        for (j, &k) in self.moving_bcs.iter().enumerate() {
            if snapped[j] {
                continue;
            }
            let node = sc.bcs[k].node;
            let m = sc.model.mass[node];
            let r = offset(d, &targets[j], &x[node * d..(node + 1) * d]);
            let p = projector(d, &targets[j]);
            for a in 0..d {
                // ∇[½ k m ‖r‖² − √m λᵀr] = k m r − √m P λ (P the projector with r = P(x − ·)).
                let pl: f64 = (0..d).map(|c| p[a * 3 + c] * self.lambda[j][c]).sum();
                g[node * d + a] += self.k_m * m * r[a] - m.sqrt() * pl;
            }
        }
        if let Some(c) = &self.contact {
            self.barrier_evals.set(self.barrier_evals.get() + 1);
            c.barrier.add_gradient(x, &c.planes, h * h, g);
        }
    }

    fn hessian(&mut self, x: &[f64], targets: &[BcShape], snapped: &[bool]) {
        let sc = self.scene;
        let d = sc.dim;
        let h = sc.time_step;
        self.hmat.values.iter_mut().for_each(|v| *v = 0.0);
        sc.model.add_mass(&mut self.hmat);
        sc.model
            .add_potential_hessian_with(x, h * h, true, &mut self.hmat, &mut self.assembly);
        for (j, &k) in self.moving_bcs.iter().enumerate() {
            if snapped[j] {
                continue;
            }
            let node = sc.bcs[k].node;
            let m = sc.model.mass[node];
            let p = projector(d, &targets[j]);
            let kb = self.hmat.diag_index(node).expect("diagonal block");
            for a in 0..d {
                for c in 0..d {
                    self.hmat.values[kb * d * d + a * d + c] += self.k_m * m * p[a * 3 + c];
                }
            }
        }
        if let Some(c) = &self.contact {
            self.barrier_evals.set(self.barrier_evals.get() + 1);
            c.barrier.add_hessian(x, &c.planes, h * h, &mut self.hmat);
        }
    }

    /// Moves the obstacles to t1 (their position for the whole step). A node (interior
    /// nodes included) that a moving half-space would overtake by more than half its gap at
    /// tⁿ starts the step at half that gap instead (a new initial guess; the push is monotone
    /// in the gap, so it keeps the nodes' order along the normal). Nodes with a boundary
    /// condition are left alone and fail the distance check that follows when they
    /// penetrate.
    fn advance_obstacles(&mut self, t1: f64, x: &mut [f64]) {
        let sc = self.scene;
        let d = sc.dim;
        let Some(c) = self.contact.as_mut() else {
            return;
        };
        let mut constrained = vec![false; sc.model.n_nodes];
        for b in &sc.bcs {
            constrained[b.node] = true;
        }
        for (j, o) in sc.obstacles.iter().enumerate() {
            let old = c.planes[j];
            let new = o.at(t1);
            c.planes[j] = new;
            if o.motion.is_none() {
                continue;
            }
            for i in 0..sc.model.n_nodes {
                let p = &mut x[i * d..(i + 1) * d];
                let (d_old, d_new) = (old.distance(p), new.distance(p));
                if d_new < 0.5 * d_old && !constrained[i] {
                    for (pa, na) in p.iter_mut().zip(new.normal) {
                        *pa += (0.5 * d_old - d_new) * na;
                    }
                    self.pushed_nodes += 1;
                }
            }
        }
    }

    /// Σ m v.
    pub fn momentum(&self) -> Vec<f64> {
        let d = self.scene.dim;
        let mut p = vec![0.0; d];
        for (k, v) in self.v.iter().enumerate() {
            p[k % d] += self.scene.model.mass[k / d] * v;
        }
        p
    }

    /// Center of mass.
    pub fn center_of_mass(&self) -> Vec<f64> {
        let d = self.scene.dim;
        let mut c = vec![0.0; d];
        for (k, x) in self.x.iter().enumerate() {
            c[k % d] += self.scene.model.mass[k / d] * x;
        }
        let m = self.scene.model.total_mass();
        c.iter().map(|v| v / m).collect()
    }

    /// Σ contact forces (newtons); None without obstacles.
    pub fn total_contact(&self) -> Option<Vec<f64>> {
        self.contact.as_ref()?;
        let d = self.scene.dim;
        let mut f = vec![0.0; d];
        for (k, c) in self.contact_forces.iter().enumerate() {
            f[k % d] += c;
        }
        Some(f)
    }

    /// Σ reactions (newtons).
    pub fn total_reaction(&self) -> Vec<f64> {
        let d = self.scene.dim;
        let mut f = vec![0.0; d];
        for (k, r) in self.reactions.iter().enumerate() {
            f[k % d] += r;
        }
        f
    }

    /// Kinetic + elastic + gravitational energy (joules).
    pub fn mechanical_energy(&self) -> f64 {
        let d = self.scene.dim;
        let kin: f64 = self
            .v
            .iter()
            .enumerate()
            .map(|(k, v)| 0.5 * self.scene.model.mass[k / d] * v * v)
            .sum();
        kin + self.scene.model.potential(&self.x)
    }
}

/// Fails (saying the residual) when a Cholesky solve's relative residual is above
/// [`CHOLESKY_MAX_RESIDUAL`] or NaN.
fn check_cholesky_residual(r: f64) -> Result<(), String> {
    if !r.is_finite() {
        // NaN or ∞ is overflow in the system (g, H·Δx_p), not ill-conditioning.
        return Err(format!(
            "the Cholesky solve's relative residual is {r}: the Newton system overflows f64 \
             (check the scene's magnitudes: sizes, offsets, time step)"
        ));
    }
    if r > CHOLESKY_MAX_RESIDUAL {
        return Err(format!(
            "the Cholesky solve has relative residual {r:e}, above the limit {CHOLESKY_MAX_RESIDUAL:e} (the eliminated Hessian is too ill-conditioned)"
        ));
    }
    Ok(())
}

/// r: the node's offset from its target set (slip: along the normal directions only).
fn offset(d: usize, s: &BcShape, xi: &[f64]) -> [f64; 3] {
    let mut p = [0.0; 3];
    p[..d].copy_from_slice(&xi[..d]);
    match s {
        BcShape::Sticky { anchor } => [p[0] - anchor[0], p[1] - anchor[1], p[2] - anchor[2]],
        BcShape::Plane { normal, offset } => {
            let dist = (0..3).map(|a| normal[a] * p[a]).sum::<f64>() - offset;
            [dist * normal[0], dist * normal[1], dist * normal[2]]
        }
        BcShape::Line { point, direction } => {
            let q = [p[0] - point[0], p[1] - point[1], p[2] - point[2]];
            let s: f64 = (0..3).map(|a| q[a] * direction[a]).sum();
            [
                q[0] - s * direction[0],
                q[1] - s * direction[1],
                q[2] - s * direction[2],
            ]
        }
    }
}

/// The projector P onto the constrained directions (row-major 3×3): I, nnᵀ or I − ttᵀ.
fn projector(d: usize, s: &BcShape) -> [f64; 9] {
    let mut p = [0.0; 9];
    match s {
        BcShape::Sticky { .. } => {
            for a in 0..d {
                p[a * 3 + a] = 1.0;
            }
        }
        BcShape::Plane { normal, .. } => {
            for a in 0..3 {
                for c in 0..3 {
                    p[a * 3 + c] = normal[a] * normal[c];
                }
            }
        }
        BcShape::Line { direction, .. } => {
            for a in 0..3 {
                for c in 0..3 {
                    p[a * 3 + c] = if a == c { 1.0 } else { 0.0 } - direction[a] * direction[c];
                }
            }
        }
    }
    p
}

/// Moves a node onto its constraint set (closest point).
fn project(d: usize, s: &BcShape, xi: &mut [f64]) {
    let r = offset(d, s, xi);
    for a in 0..d {
        xi[a] -= r[a];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cholesky_residual_above_the_limit_fails_the_solve() {
        assert!(check_cholesky_residual(0.0).is_ok());
        assert!(check_cholesky_residual(1e-12).is_ok());
        assert!(check_cholesky_residual(CHOLESKY_MAX_RESIDUAL).is_ok());
        for r in [2e-8, 1e-3, f64::INFINITY, f64::NAN] {
            let e = check_cholesky_residual(r).expect_err("must fail");
            assert!(
                e.contains("relative residual") && e.contains(&format!("{r:e}")),
                "{e}"
            );
        }
    }
}
