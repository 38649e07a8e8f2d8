//! Where a step's iterate lives: [`Backend`] is what the one Newton loop
//! (`stepper.rs`) asks of it. The host backend keeps x, xⁿ, x̃, ∇E and Δx in arrays and
//! solves with the library's [`crate::Solver`]; the device backend keeps them in device
//! buffers and reads back only scalars and the few node positions the loop's decisions
//! need. Both evaluate the same energy, so the loop's decisions (Armijo, snapping, the
//! penalty update, the CCD bound, convergence) are made once, here, for both.

use super::balance::ForceBalance;
use super::error::StepError;
use super::forcing::Forcing;
use super::linear::LinearStats;
use super::report::GpuRunReport;
use super::state::State;
use super::targets::MovingTargets;
use crate::gpu::{Phase, Profile};
use crate::sim::energy::barrier::{Ccd, HalfSpace};
use crate::sim::energy::{InversionLimit, Inverted};
use crate::sim::phases::PhaseSpan;

/// The state at the end of a step, read back from wherever it lived.
pub(super) struct EndState {
    /// Positions x^{n+1}.
    pub(super) x: Vec<f64>,
    /// Velocities v^{n+1} = (x^{n+1} − xⁿ)/h.
    pub(super) v: Vec<f64>,
    /// ∇E at x^{n+1} (for the reactions).
    pub(super) g: Vec<f64>,
}

/// A Newton system as [`Backend::system`] reads it back.
pub(super) struct SystemArrays {
    pub(super) h: crate::core::sparse::BlockCsr,
    pub(super) g: Vec<f64>,
    pub(super) x: Vec<f64>,
    pub(super) dx: Vec<f64>,
}

/// The operations of one step on the iterate, wherever it lives.
pub(super) trait Backend {
    /// Start of step: xⁿ from the state, x̃ = xⁿ + h vⁿ, and the starting iterate: xⁿ
    /// projected onto the static constraint sets.
    fn begin_step(&mut self, state: &State) -> Result<(), StepError>;

    /// The current iterate's positions, node-major, as a whole-length array of which at
    /// least `nodes` (every node for None) are current; changes are kept only where
    /// [`Backend::write_positions`] follows.
    fn positions(&mut self, nodes: Option<&[usize]>) -> Result<&mut [f64], StepError>;

    /// Stores the positions of `nodes` (every node for None) from the array
    /// [`Backend::positions`] handed out.
    fn write_positions(&mut self, nodes: Option<&[usize]>) -> Result<(), StepError>;

    /// The obstacles' half-spaces for this step changed.
    fn set_planes(&mut self, planes: &[HalfSpace]) -> Result<(), StepError>;

    /// The smallest signed distance of any node of the current iterate to any obstacle,
    /// with the node and the obstacle (call only with obstacles).
    fn min_distance(&mut self, state: &State) -> Result<(f64, usize, usize), StepError>;

    /// ∇E, ∇²E and the eliminated solve for the constraint set of `moving` (its frames
    /// are built) at the current iterate: Δx is kept for the line search. `iteration`
    /// (from 1) names it in errors; `forcing` gives the iterative solver's relative
    /// residual tolerance as a rule of ‖b̂‖ and remembers the system solved.
    fn direction(
        &mut self,
        state: &State,
        moving: &MovingTargets,
        iteration: usize,
        forcing: &mut Forcing,
    ) -> Result<LinearStats, StepError>;

    /// Solves the system of the last [`Backend::direction`] again to the relative
    /// residual `tol` (the same ∇E and ∇²E): Δx is replaced.
    fn resolve(
        &mut self,
        state: &State,
        moving: &MovingTargets,
        iteration: usize,
        tol: f64,
    ) -> Result<LinearStats, StepError>;

    /// The system of the last [`Backend::direction`] (or [`Backend::resolve`]): ∇²E, ∇E,
    /// the iterate it was taken at and the Δx it gave, read back for `run --dump-systems`.
    fn system(&mut self) -> Result<SystemArrays, StepError>;

    /// ‖Δx‖∞.
    fn max_abs_dx(&mut self) -> Result<f64, StepError>;

    /// The force balance of the current iterate, with ∇E of the last
    /// [`Backend::direction`] (taken there) and every moving node of `snapped` eliminated.
    fn force_balance(&mut self, state: &State, snapped: &[bool])
        -> Result<ForceBalance, StepError>;

    /// E at the current iterate (`trial` false) or at the trial iterate of the last
    /// [`Backend::set_trial`].
    fn energy(
        &mut self,
        state: &State,
        moving: &MovingTargets,
        trial: bool,
    ) -> Result<f64, StepError>;

    /// The directional derivative ∇E·Δx at the current iterate.
    fn slope(&mut self) -> Result<f64, StepError>;

    /// The CCD bound α_C of Δx from the current iterate (call only with obstacles).
    fn ccd(&mut self, state: &State) -> Result<Ccd, StepError>;

    /// The largest step along Δx from the current iterate before an element of the
    /// classical neo-Hookean law inverts: the smallest root α ∈ (0, `max`] of
    /// det F(x + αΔx) = 0 over those elements (`Model::inversion_bound`), None when none
    /// inverts there; the inner Err names an element already inverted at x. Both backends
    /// compute it with the same host function on the same x and Δx.
    fn inversion_bound(
        &mut self,
        state: &State,
        max: f64,
    ) -> Result<Result<Option<InversionLimit>, Inverted>, StepError>;

    /// The trial iterate x + α Δx.
    fn set_trial(&mut self, alpha: f64) -> Result<(), StepError>;

    /// The trial iterate becomes the current one.
    fn accept(&mut self) -> Result<(), StepError>;

    /// End of step: x^{n+1}, v^{n+1} and ∇E there.
    fn end_step(&mut self, state: &State) -> Result<EndState, StepError>;

    /// The state was restored from a snapshot: take its positions and velocities.
    fn restore(&mut self, state: &State) -> Result<(), StepError>;

    /// The GPU adapter this loop uses, if any.
    fn adapter(&self) -> Option<&str>;

    /// Opens `phase` of the loop's profile until the span drops (`None`: no profile).
    fn phase(&self, _phase: Phase) -> Option<PhaseSpan> {
        None
    }

    /// The CPU loop's profile so far (None for the device loop, whose profile is in its
    /// [`GpuRunReport`]).
    fn host_profile(&self) -> Option<Profile> {
        None
    }

    /// The run began at `run_start`: the time before the device existed is its set-up.
    fn started_at(&self, _run_start: std::time::Instant) {}

    /// Systems so far whose multilevel levels were built, and systems that kept them
    /// (both zero without the multilevel preconditioner).
    fn multilevel_levels(&self) -> (usize, usize);

    /// What the GPU moved and stored so far; None without a GPU.
    fn gpu_report(&self, state: &State) -> Option<GpuRunReport>;
}
