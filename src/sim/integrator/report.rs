//! What a step did ([`StepReport`]), what the contact code did over a run
//! ([`ContactCounters`]) and what the GPU moved and stored ([`GpuRunReport`]).

use crate::gpu::profile::phase_map;
use crate::gpu::Phase;

/// What one step did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct StepReport {
    pub step: usize,
    pub time: f64,
    pub newton_iterations: usize,
    pub linear_iterations: usize,
    pub linear_seconds: f64,
    /// The loosest and the tightest relative residual tolerance the step's iterative
    /// solves were given (None: direct solves only).
    pub cg_tol_loosest: Option<f64>,
    pub cg_tol_tightest: Option<f64>,
    /// Systems solved again to the convergence tolerance because their loosely solved
    /// direction passed the Newton test (inexact Newton).
    pub linear_resolves: usize,
    /// Newton systems of the step whose multilevel levels were built, and that kept
    /// earlier ones (`[solver] multilevel_setup`; zero without the multilevel
    /// preconditioner).
    pub multilevel_built: usize,
    pub multilevel_kept: usize,
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
    /// Line searches that started at the inversion bound (below 1 and the CCD bound).
    pub inversion_limited: usize,
    /// The smallest element volume ratio J of the step's end state over the neo-Hookean
    /// elements; None without them.
    pub min_j: Option<f64>,
    /// The neo-Hookean laws with an element inverted (J ≤ 0) at the end of the step.
    pub inverted: Vec<crate::sim::energy::Law>,
    /// The last iterate's largest unbalanced free force over the step's force scale
    /// (the stationarity test, `[solver] force_tolerance`).
    pub force_residual: Option<f64>,
}

impl StepReport {
    /// Counts one linear solve.
    pub(super) fn add_solve(&mut self, stats: &super::linear::LinearStats) {
        self.linear_iterations += stats.iterations;
        self.linear_seconds += stats.seconds;
        if let Some(t) = stats.tolerance {
            self.cg_tol_loosest = Some(self.cg_tol_loosest.map_or(t, |m| m.max(t)));
            self.cg_tol_tightest = Some(self.cg_tol_tightest.map_or(t, |m| m.min(t)));
        }
    }
}

/// What the contact code did (all zero for a scene without obstacles).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct ContactCounters {
    /// Barrier energy, gradient or Hessian evaluations.
    pub barrier_evaluations: u64,
    /// CCD (α_C) computations.
    pub ccd_calls: u64,
    /// Initial guesses pushed ahead of a moving obstacle.
    pub pushed_nodes: u64,
}

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
    /// Of the totals, the device loop's coarse matrix: E = ZᵀĤZ of the aggregates read
    /// back and E⁺ written, (D·aggregates)² f64 each way per Newton iteration, at most
    /// (3·128)² whatever the mesh (0 for the CPU loop and other coarse spaces).
    pub coarse_host_to_device_bytes: u64,
    pub coarse_device_to_host_bytes: u64,
    /// Host seconds the device loop spent on the multilevel preconditioner's setup (the
    /// decision and the recording of the device's setup kernels, once per Newton
    /// iteration; part of the linear seconds; 0 without it and for the CPU loop).
    pub multilevel_setup_seconds: f64,
    /// Every wait of the host on the device (read-backs and explicit waits), set-up
    /// included.
    pub host_syncs: u64,
    /// Compute dispatches recorded (gated and no-op ones included).
    pub dispatches: u64,
    /// Of the totals, what moved during the Newton iterations: outside the set-up, the
    /// pipelines' creation and the per-step reads and writes of the state (the steps'
    /// output; `gpu::profile::Profile::iteration_bytes`); 0 for the CPU loop.
    pub iteration_host_to_device_bytes: u64,
    pub iteration_device_to_host_bytes: u64,
    /// Wall seconds per phase of the device loop (`gpu::profile`), summing to the run's
    /// wall time (empty for the CPU loop).
    #[serde(serialize_with = "phase_map")]
    pub phases: Vec<(Phase, f64)>,
    /// Device seconds per phase from timestamp queries (empty where the adapter has
    /// none).
    #[serde(serialize_with = "phase_map")]
    pub device_seconds: Vec<(Phase, f64)>,
    /// Bytes [host to device, device to host] moved while each phase was open.
    #[serde(serialize_with = "phase_map")]
    pub phase_bytes: Vec<(Phase, [u64; 2])>,
    /// Of the totals, the multilevel preconditioner's setup: the levels' index words and
    /// the setup's dispatch parameters once per run, nothing per Newton iteration (0
    /// without it and for the CPU loop).
    pub multilevel_host_to_device_bytes: u64,
    pub multilevel_device_to_host_bytes: u64,
    /// Newton iterations of the run (filled in by the driver, which counts them).
    pub newton_iterations: usize,
}
