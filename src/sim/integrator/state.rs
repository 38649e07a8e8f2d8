//! What the stepper holds whichever loop runs it: time, velocities and positions at the
//! last completed step, the moving-boundary state (k_M, λ), the constraint sets' frames,
//! the obstacles at the current step, the recovered forces, and the step logic that
//! works on node positions handed to it (snapping, the penalty update, the distance and
//! CCD checks, the obstacles' advance, the force recovery).

use super::error::StepError;
use super::report::ContactCounters;
use super::targets::{offset, project, MovingTargets};
use crate::core::constraints::{Constraint, ConstraintError, ConstraintKind, Frames};
use crate::core::linalg::{norm2, norm3};
use crate::sim::energy::barrier::{Barrier, Ccd, HalfSpace};
use crate::sim::energy::ElementSet;
use crate::sim::scene::{BcShape, JointTarget, Scene};
use std::cell::Cell;
use std::collections::HashMap;

/// Armijo sufficient-decrease constant.
pub(super) const ARMIJO: f64 = 1e-4;
/// A decrease of E below this many ε of |E| is rounding: the line search takes the bounded
/// step without judging it.
pub(super) const ENERGY_ULPS: f64 = 64.0;
/// Backtracking halvings before the line search gives up.
pub(super) const MAX_HALVINGS: usize = 40;
/// CCD filter: a Newton step may cover at most this fraction of any node's distance to an
/// obstacle (IPC's 1 − s with s = 0.1).
pub const CCD_FRACTION: f64 = 0.9;
/// Inversion filter: the line search of a scene with classical neo-Hookean elements starts
/// at most at this fraction of the first step size that would invert an element (the
/// smallest positive root of det F(x + αΔx) = 0).
pub const INVERSION_FRACTION: f64 = 0.9;
/// A static condition holds its node where it starts: the start-of-step projection of the
/// initial positions may move a node by at most this fraction of the characteristic
/// length L (round-off, and meshes written with a few digits, are far below it; a node
/// meant to move takes a moving condition).
pub const STATIC_PROJECTION_FRACTION: f64 = 1e-3;

/// The barrier and the obstacles' half-spaces for the current step.
pub(super) struct Contact {
    pub(super) barrier: Barrier,
    pub(super) planes: Vec<HalfSpace>,
}

/// Everything the next step depends on, taken after a completed step
/// ([`crate::sim::integrator::Stepper::snapshot`]) and given back to a stepper of the same
/// scene ([`crate::sim::integrator::Stepper::restore`]): the stepper then continues with
/// the same bits as one that was never stopped. The frames of the constraint sets, the
/// linear solver's analysis and the device buffers are rebuilt from the scene; the
/// obstacles' positions follow from `t`.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Snapshot {
    pub step: usize,
    pub t: f64,
    pub x: Vec<f64>,
    pub v: Vec<f64>,
    /// k_M of the moving conditions (it persists across steps).
    pub k_m: f64,
    /// Per moving condition, the augmented-Lagrangian multiplier.
    pub lambda: Vec<[f64; 3]>,
    pub reactions: Vec<f64>,
    pub contact_forces: Vec<f64>,
    pub counters: ContactCounters,
    /// The inexact Newton sequence's memory across steps: ‖Δx‖∞ of the last sequence's
    /// first direction (see `forcing.rs`).
    #[serde(default)]
    pub forcing_first_step: Option<f64>,
}

/// The stepper's state and the step logic shared by both loops.
pub struct State<'s> {
    pub scene: &'s Scene,
    /// Positions at the last completed step.
    pub x: Vec<f64>,
    /// Velocities at the last completed step.
    pub v: Vec<f64>,
    pub t: f64,
    pub step: usize,
    pub k_m: f64,
    /// Per moving condition: the augmented-Lagrangian multiplier.
    pub(super) lambda: Vec<[f64; 3]>,
    pub(super) static_bcs: Vec<usize>,
    /// The static conditions projected one by one: those alone on their node.
    pub(super) single_static_bcs: Vec<usize>,
    /// Nodes with several static conditions, projected onto their intersection.
    pub(super) joint: Vec<JointTarget>,
    pub(super) moving_bcs: Vec<usize>,
    /// The frames of every constraint set met so far, keyed by which moving nodes are
    /// snapped.
    pub(super) frames: HashMap<Vec<bool>, Frames>,
    /// Reaction force per DOF at the end of the last step (newtons).
    pub reactions: Vec<f64>,
    /// Newton tolerance on ‖Δx‖∞/h (m/s).
    pub newton_tol: f64,
    /// ε of the moving conditions (m/s).
    pub moving_eps: f64,
    /// None for a scene without obstacles: no contact code runs at all.
    pub(super) contact: Option<Contact>,
    pub(super) barrier_evals: Cell<u64>,
    pub(super) ccd_calls: u64,
    pub(super) pushed_nodes: u64,
    /// Contact force per DOF at the end of the last step (newtons; empty without obstacles).
    pub contact_forces: Vec<f64>,
    /// The gradient in the nodes' frames (reactions), kept between steps.
    gy: Vec<f64>,
}

impl<'s> State<'s> {
    pub(super) fn new(
        scene: &'s Scene,
        static_bcs: Vec<usize>,
        single_static_bcs: Vec<usize>,
        joint: Vec<JointTarget>,
        moving_bcs: Vec<usize>,
    ) -> Self {
        State {
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
            gy: vec![0.0; scene.x0.len()],
        }
    }

    /// The state after the last completed step.
    pub fn snapshot(&self) -> Snapshot {
        Snapshot {
            step: self.step,
            t: self.t,
            x: self.x.clone(),
            v: self.v.clone(),
            k_m: self.k_m,
            lambda: self.lambda.clone(),
            reactions: self.reactions.clone(),
            contact_forces: self.contact_forces.clone(),
            counters: self.contact_counters(),
            // Filled in by the stepper, which holds the forcing sequence.
            forcing_first_step: None,
        }
    }

    /// Takes the state of `snap` (checked against this scene's sizes); the obstacles move
    /// to their position at `snap.t`.
    pub(super) fn restore(&mut self, snap: &Snapshot) -> Result<(), String> {
        let n = self.x.len();
        let sizes = [
            ("x", snap.x.len(), n),
            ("v", snap.v.len(), n),
            ("reactions", snap.reactions.len(), n),
            (
                "contact_forces",
                snap.contact_forces.len(),
                self.contact_forces.len(),
            ),
            ("lambda", snap.lambda.len(), self.lambda.len()),
        ];
        for (what, got, want) in sizes {
            if got != want {
                return Err(format!(
                    "the snapshot's {what} has {got} entries, this scene needs {want}"
                ));
            }
        }
        self.step = snap.step;
        self.t = snap.t;
        self.x.clone_from(&snap.x);
        self.v.clone_from(&snap.v);
        self.k_m = snap.k_m;
        self.lambda.clone_from(&snap.lambda);
        self.reactions.clone_from(&snap.reactions);
        self.contact_forces.clone_from(&snap.contact_forces);
        self.barrier_evals.set(snap.counters.barrier_evaluations);
        self.ccd_calls = snap.counters.ccd_calls;
        self.pushed_nodes = snap.counters.pushed_nodes;
        if let Some(c) = self.contact.as_mut() {
            for (p, o) in c.planes.iter_mut().zip(&self.scene.obstacles) {
                *p = o.at(snap.t);
            }
        }
        Ok(())
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

    /// Counts barrier evaluations (energy, gradient or Hessian), as both loops report them.
    pub(super) fn count_barrier(&self, evaluations: u64) {
        if self.contact.is_some() {
            self.barrier_evals
                .set(self.barrier_evals.get() + evaluations);
        }
    }

    /// Smallest signed distance of any node to any obstacle at its current (end-of-step)
    /// position, with the node and the obstacle's index; None without obstacles.
    pub fn min_distance(&self, x: &[f64]) -> Option<(f64, usize, usize)> {
        self.contact
            .as_ref()
            .map(|c| c.barrier.min_distance(x, &c.planes))
    }

    /// The smallest distance, or the error naming the node and the obstacle when an
    /// iterate touches or crosses one.
    pub(super) fn check_distance(
        &self,
        nearest: (f64, usize, usize),
        when: &str,
    ) -> Result<f64, StepError> {
        let (distance, node, j) = nearest;
        if distance.is_nan() || distance <= 0.0 {
            return Err(StepError::Penetration {
                node,
                distance,
                obstacle: self.scene.obstacles[j].label.clone(),
                when: when.to_string(),
            });
        }
        Ok(distance)
    }

    /// Fails when the step the line search took is the CCD bound α_C < 1 and the node that
    /// sets the bound has no barrier weight (an interior node of a solid). Nothing in E holds
    /// such a node off the obstacle, so Newton would keep heading for the plane, each step
    /// cut to 0.9 of the gap, and stall. At α_C/[`CCD_FRACTION`] that node touches the
    /// plane before any other node has reached it (barring an exact tie): the body's
    /// interior crosses its own boundary, so the body has (or is about to have) inverted.
    /// `x` holds at least the limiting node's position.
    pub(super) fn check_unbarriered_limit(
        &self,
        x: &[f64],
        ccd: &Ccd,
        iteration: usize,
    ) -> Result<(), StepError> {
        let (Some(c), Some((node, j))) = (&self.contact, ccd.limit) else {
            return Ok(());
        };
        if ccd.alpha >= 1.0 || c.barrier.weight[node] > 0.0 {
            return Ok(());
        }
        let d = self.scene.dim;
        let gap = c.planes[j].distance(&x[node * d..(node + 1) * d]);
        Err(StepError::Unbarriered {
            node,
            obstacle: self.scene.obstacles[j].label.clone(),
            iteration,
            gap,
            fraction: CCD_FRACTION,
        })
    }

    /// The frames of the constraint set `key` (the static conditions and the snapped moving
    /// nodes), built on first use and cached.
    pub(super) fn build_frames(&mut self, key: &[bool]) -> Result<&Frames, ConstraintError> {
        if !self.frames.contains_key(key) {
            let f = self.frames_of(key)?;
            self.frames.insert(key.to_vec(), f);
        }
        Ok(&self.frames[key])
    }

    fn frames_of(&self, key: &[bool]) -> Result<Frames, ConstraintError> {
        let d = self.scene.dim;
        let cs = self.constraints_of(key);
        if cs.is_empty() {
            Ok(Frames::unconstrained(d, self.scene.model.n_nodes))
        } else {
            Frames::build(d, self.scene.model.n_nodes, &cs)
        }
    }

    /// The homogeneous constraints of a Newton step for the constraint set `key` (which
    /// moving conditions are snapped and eliminated): every static condition and the
    /// snapped moving ones, with zero prescribed displacement.
    pub(super) fn constraints_of(&self, key: &[bool]) -> Vec<Constraint> {
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
        cs
    }

    /// Projects the start-of-step positions onto the static constraint sets (a node with
    /// several conditions onto their intersection, not onto each in turn).
    pub(super) fn project_static(&self, x: &mut [f64]) {
        let d = self.scene.dim;
        for &k in &self.single_static_bcs {
            let b = &self.scene.bcs[k];
            project(d, &b.shape, &mut x[b.node * d..(b.node + 1) * d]);
        }
        for j in &self.joint {
            j.project(d, &mut x[j.node * d..(j.node + 1) * d]);
        }
    }

    /// Checks the start-of-step projection of the initial positions (the static conditions
    /// are known when the scene is loaded, and later steps start on their sets): it may
    /// neither invert an element (J > 0 before, J ≤ 0 after, either neo-Hookean law) nor
    /// move a node farther than [`STATIC_PROJECTION_FRACTION`]·L. Err((entry, problem))
    /// names the condition's entry, the node, the distance and the limit (and the element).
    pub(super) fn check_static_projection(&self) -> Result<(), (String, String)> {
        let sc = self.scene;
        let d = sc.dim;
        let mut x = sc.x0.clone();
        self.project_static(&mut x);
        let moved = |i: usize| -> f64 {
            let mut r = [0.0; 3];
            for a in 0..d {
                r[a] = x[i * d + a] - sc.x0[i * d + a];
            }
            // Scaled: a move of 1e300 m is said as such, not as ∞.
            let n = norm2(&r[..d]);
            // An overflowed offset is as far as it gets.
            if n.is_nan() {
                f64::INFINITY
            } else {
                n
            }
        };
        // The entry of a projected node: its one condition, or all of them (a joint node).
        let entry = |i: usize| -> String {
            let labels: Vec<&str> = self
                .static_bcs
                .iter()
                .map(|&k| &sc.bcs[k])
                .filter(|b| b.node == i)
                .map(|b| b.label.as_str())
                .collect();
            if labels.len() == 1 {
                labels[0].to_string()
            } else {
                format!("node {i} ({})", labels.join(", "))
            }
        };
        let nodes: Vec<usize> = self
            .single_static_bcs
            .iter()
            .map(|&k| sc.bcs[k].node)
            .chain(self.joint.iter().map(|j| j.node))
            .collect();
        let limit = STATIC_PROJECTION_FRACTION * sc.characteristic_length;
        let said_limit = format!(
            "a static condition may move its node by at most {STATIC_PROJECTION_FRACTION:e}·L = \
             {limit:.3e} m at the start of a step (L = {:.3e} m); give a node that is to move a \
             moving condition (motion)",
            sc.characteristic_length
        );
        if let Some(m) = sc.model.first_inverted_by(&sc.x0, &x) {
            let ElementSet::NeoHookean(nh) = &sc.model.sets[m.set] else {
                unreachable!("first_inverted_by names neo-Hookean elements")
            };
            let node = nh
                .nodes(m.element)
                .iter()
                .copied()
                .max_by(|&a, &b| moved(a).total_cmp(&moved(b)))
                .expect("an element has nodes");
            return Err((
                entry(node),
                format!(
                    "projecting node {node} onto its static conditions moves it by {:.3e} m \
                     and inverts element {} of bodies[{}] (J = {:.3e}); {said_limit}",
                    moved(node),
                    m.element,
                    m.set,
                    m.j
                ),
            ));
        }
        let far = nodes
            .iter()
            .copied()
            .map(|i| (i, moved(i)))
            .max_by(|a, b| a.1.total_cmp(&b.1));
        if let Some((node, dist)) = far.filter(|&(_, dist)| dist > limit) {
            return Err((
                entry(node),
                format!(
                    "node {node} lies {dist:.3e} m from the set its static conditions hold it \
                     on; {said_limit}"
                ),
            ));
        }
        Ok(())
    }

    /// The nodes of the moving conditions not yet snapped.
    pub(super) fn unsnapped_nodes(&self, snapped: &[bool]) -> Vec<usize> {
        self.moving_bcs
            .iter()
            .zip(snapped)
            .filter(|(_, &s)| !s)
            .map(|(&k, _)| self.scene.bcs[k].node)
            .collect()
    }

    /// Snaps every unsnapped moving node within ε·h of its target. `x` holds at least the
    /// unsnapped nodes' positions.
    pub(super) fn snap_satisfied(&self, x: &mut [f64], targets: &[BcShape], snapped: &mut [bool]) {
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

    /// Moving-boundary update, when Newton has converged with moving nodes still off their
    /// targets: with the augmented Lagrangian, λ_k −= k_M √m_k r_k and k_M doubles only
    /// when the largest offset did not halve since the last update; without it, k_M
    /// doubles. Fails when k_M would have to pass its cap. `x` holds at least the unsnapped
    /// nodes' positions; returns whether k_M doubled.
    pub(super) fn update_moving_penalty(
        &mut self,
        x: &[f64],
        moving: &MovingTargets,
        residual_at_update: &mut f64,
    ) -> Result<bool, StepError> {
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
                return Err(StepError::PenaltyCap {
                    unsatisfied: unsat.len(),
                    worst,
                    eps_h: self.moving_eps * h,
                    cap: sc.moving.penalty_max,
                });
            }
            self.k_m = (2.0 * self.k_m).min(sc.moving.penalty_max);
        }
        Ok(double)
    }

    /// Moves the obstacles to t1 (their position for the whole step). A node (interior
    /// nodes included) that a moving half-space would overtake by more than half its gap at
    /// tⁿ starts the step at half that gap instead (a new initial guess; the push is monotone
    /// in the gap, so it keeps the nodes' order along the normal). Nodes with a boundary
    /// condition are left alone and fail the distance check that follows when they
    /// penetrate. `x` holds every position when an obstacle moves (it may be empty
    /// otherwise); returns whether any node was pushed.
    pub(super) fn advance_obstacles(&mut self, t1: f64, x: &mut [f64]) -> bool {
        let sc = self.scene;
        let d = sc.dim;
        let Some(c) = self.contact.as_mut() else {
            return false;
        };
        let mut constrained = vec![false; sc.model.n_nodes];
        for b in &sc.bcs {
            constrained[b.node] = true;
        }
        let before = self.pushed_nodes;
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
        self.pushed_nodes != before
    }

    /// End-of-step recovery of the forces at the converged x. Reactions: the constrained
    /// components of ∇E / h², per node, in newtons (`g` = ∇E at x). Contact forces:
    /// c = −∇P_b.
    pub(super) fn recover_forces(&mut self, x: &[f64], g: &[f64], snapped: &[bool]) {
        let d = self.scene.dim;
        let h = self.scene.time_step;
        let frames = &self.frames[snapped];
        frames.to_frame(g, &mut self.gy);
        for (i, &m) in frames.mask.iter().enumerate() {
            for a in 0..d {
                if m & (1 << a) == 0 {
                    self.gy[i * d + a] = 0.0;
                }
            }
        }
        frames.from_frame(&self.gy, &mut self.reactions);
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

    /// End of step: x and v become the state at t1. A kinetic energy that overflows (a
    /// moving condition whose target runs off near the end of the f64 range drags its node
    /// there in one step) fails the step instead of writing NaN energies.
    pub(super) fn finish_step(
        &mut self,
        x: Vec<f64>,
        v: Vec<f64>,
        t1: f64,
    ) -> Result<(), StepError> {
        let d = self.scene.dim;
        let kinetic: f64 = v
            .iter()
            .enumerate()
            .map(|(i, vi)| self.scene.model.mass[i / d] * vi * vi)
            .sum();
        if !kinetic.is_finite() {
            return Err(StepError::VelocityOverflow {
                kinetic,
                moved: (0..x.len())
                    .map(|i| (x[i] - self.x[i]).abs())
                    .fold(0.0f64, f64::max),
            });
        }
        self.v = v;
        self.x = x;
        self.t = t1;
        self.step += 1;
        Ok(())
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
