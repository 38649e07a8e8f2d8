//! Why a stepper could not start ([`InitError`]) and why a step failed ([`StepError`]).
//! Both loops, on the host and on the device, fail with the same errors.

use crate::core::constraints::ConstraintError;
use crate::gpu::GpuError;
use crate::sim::memory::AllocError;

/// Why a stepper could not start.
#[derive(Debug, Clone, PartialEq)]
pub enum InitError {
    /// The scene's conditions are inconsistent; `entry` names the scene entry.
    Input { entry: String, problem: String },
    /// The linear solver or the device loop cannot start (no adapter, no SHADER_F64, a
    /// device failure); the error keeps its kind ([`crate::Error::Gpu`] for the device).
    Solver(crate::Error),
    /// The system refused an allocation of the scene's size.
    Memory(AllocError),
}

/// Why a step failed. Iterations count from 1, on both loops.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StepError {
    #[error("Newton did not converge in {iterations} iterations{}{}", moving_state(.moving), unbalanced_state(.unbalanced))]
    NewtonLimit {
        iterations: usize,
        /// k_M and the moving nodes still off target; None for a scene without moving
        /// boundaries.
        moving: Option<(f64, usize)>,
        /// When the last iterate passed ‖Δx‖∞/h < tol but did not balance its forces.
        unbalanced: Option<Unbalanced>,
    },
    #[error("the Newton direction is not finite at iteration {iteration}")]
    DirectionNotFinite { iteration: usize },
    #[error("the {what} holds {value} at Newton iteration {iteration}: the positions or velocities have overflowed f64")]
    SystemNotFinite {
        what: &'static str,
        value: f64,
        iteration: usize,
    },
    #[error("the energy is not finite (E = {energy:e}) at Newton iteration {iteration}: the positions or velocities have overflowed")]
    EnergyNotFinite { energy: f64, iteration: usize },
    #[error("linear solve failed at Newton iteration {iteration}: {cause}")]
    LinearSolve { iteration: usize, cause: String },
    #[error("the line search found no decrease at Newton iteration {iteration} (‖Δx‖∞/h = {rate:e} m/s)")]
    NoDecrease { iteration: usize, rate: f64 },
    #[error("node {node} is at signed distance {distance:e} m from {obstacle} {when}: the configuration must stay penetration-free")]
    Penetration {
        node: usize,
        distance: f64,
        obstacle: String,
        when: String,
    },
    #[error("interior node {node} (no contact barrier) is held off {obstacle} only by the CCD bound at Newton iteration {iteration} (it was {gap:e} m away, the step covers {fraction} of that): the body has likely inverted; use a stiffer material, a smaller time step or a finer mesh")]
    Unbarriered {
        node: usize,
        obstacle: String,
        iteration: usize,
        gap: f64,
        fraction: f64,
    },
    #[error("{unsatisfied} moving node(s) did not reach their targets (largest offset {worst:e} m, ε·h = {eps_h:e} m) with k_M at its cap {cap:e}")]
    PenaltyCap {
        unsatisfied: usize,
        worst: f64,
        eps_h: f64,
        cap: f64,
    },
    #[error("the velocities overflow (2·kinetic energy = {kinetic:e}): a node was moved by about {moved:e} m in one step")]
    VelocityOverflow { kinetic: f64, moved: f64 },
    #[error("element {element} of body {body} ({law}) is inverted {} (J = {j:e}): the classical neo-Hookean energy is not defined for J ≤ 0; the state must be inversion-free", inverted_when(*.iteration))]
    InvertedStart {
        body: usize,
        element: usize,
        j: f64,
        law: &'static str,
        /// The Newton iteration; 0: the step's starting state (after the static projection
        /// and the obstacles' pushes), the scene's fault rather than the solver's.
        iteration: usize,
    },
    #[error("element {element} of body {body} ({law}) ended the step inverted (J = {j:e}) and [solver] inversion = \"fail\"")]
    InvertedEnd {
        body: usize,
        element: usize,
        j: f64,
        law: &'static str,
    },
    #[error("{0}")]
    Constraints(#[from] ConstraintError),
    #[error("cannot restore the stepper: {0}")]
    Snapshot(String),
    #[error("GPU Newton loop: {0}")]
    Device(#[from] GpuError),
    #[error("cannot write the Newton system of iteration {iteration}: {cause}")]
    Dump { iteration: usize, cause: String },
}

fn inverted_when(iteration: usize) -> String {
    if iteration == 0 {
        "at the start of the step".into()
    } else {
        format!("at Newton iteration {iteration}")
    }
}

/// The forces a Newton iterate left unbalanced although its steps were short.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Unbalanced {
    /// The node with the largest unbalanced force on its free components.
    pub node: usize,
    /// That force (N).
    pub force: f64,
    /// That force over the step's force scale.
    pub ratio: f64,
    /// The scene's force tolerance on `ratio`.
    pub tol: f64,
}

fn unbalanced_state(unbalanced: &Option<Unbalanced>) -> String {
    match unbalanced {
        Some(Unbalanced {
            node,
            force,
            ratio,
            tol,
        }) => format!(
            "; its steps there are short but the forces do not balance: {force:.3e} N on \
             node {node}'s free components, {ratio:.1e} of the step's force scale \
             (force_tolerance {tol:e})"
        ),
        None => String::new(),
    }
}

fn moving_state(moving: &Option<(f64, usize)>) -> String {
    match moving {
        Some((k_m, unsatisfied)) => {
            format!(" (k_M = {k_m:e}, unsatisfied moving nodes: {unsatisfied})")
        }
        None => String::new(),
    }
}
