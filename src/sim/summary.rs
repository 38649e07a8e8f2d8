//! summary.json: what a run of `stickslip run` did, rewritten after every step (`running`)
//! and at the end (`complete`, `failed` or `interrupted`).

use crate::sim::integrator::ContactCounters;
use crate::sim::output::StepRecord;
use crate::sim::scene::MovingSpec;

/// Moving-boundary history of a run.
#[derive(Debug, Clone, serde::Serialize)]
pub struct MovingSummary {
    pub settings: MovingSpec,
    pub moving_nodes: usize,
    pub k_m_start: f64,
    pub k_m_final: f64,
    pub k_m_doublings: usize,
    /// (step, k_M) at every step where k_M changed.
    pub k_m_history: Vec<(usize, f64)>,
    /// Per step: the Newton iteration at which every moving node was eliminated.
    pub eliminated_at_iteration: Vec<usize>,
    /// First step at which the moving nodes were all satisfied at the start of the step
    /// (pure elimination, no penalty iteration), if any.
    pub first_step_eliminated_at_start: Option<usize>,
    /// Every step ended with every moving node on its target and eliminated.
    pub all_eliminated_every_step: bool,
}

/// Contact history of a run (scenes with obstacles).
#[derive(Debug, Clone, serde::Serialize)]
pub struct ContactSummary {
    pub obstacles: usize,
    /// Per obstacle: d̂ (m) and κ (Pa) as resolved (defaults filled in).
    pub dhat: Vec<f64>,
    pub kappa: Vec<f64>,
    /// Smallest node–obstacle signed distance over every Newton iterate of the run.
    pub min_distance: f64,
    /// Line searches cut by the CCD bound (α_C < 1).
    pub ccd_limited_line_searches: usize,
    /// Summed contact force at the end (newtons).
    pub final_contact_force: Vec<f64>,
}

/// How far a run got, as summary.json says it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum RunStatus {
    Running,
    Complete,
    Failed,
    /// Stopped by SIGINT or SIGTERM after a completed step, with a checkpoint there.
    Interrupted,
}

/// What a run did (summary.json holds everything but the per-step records and state).
#[derive(Debug, Clone, serde::Serialize)]
pub struct RunSummary {
    /// `running` while the run goes (rewritten after every step), then `complete`,
    /// `failed` or `interrupted`.
    pub status: RunStatus,
    /// Why the run failed (the command's error line), for `failed`.
    pub message: Option<String>,
    /// The run's id, the same in every invocation of the run (`run --resume`) and in its
    /// checkpoint: a checkpoint from another run is refused.
    pub run_id: String,
    pub scene: String,
    pub file: String,
    pub dimension: usize,
    pub nodes: usize,
    pub elements: usize,
    pub total_mass: f64,
    pub time_step: f64,
    pub gravity: Vec<f64>,
    /// Steps asked for.
    pub steps: usize,
    /// Steps finished (equal to `steps` when complete).
    pub steps_completed: usize,
    pub end_time: f64,
    pub wall_seconds: f64,
    pub solver: String,
    /// Why `[solver] linear = "auto"` chose `solver` (None for an explicit choice).
    pub linear_choice: Option<String>,
    pub adapter: Option<String>,
    pub characteristic_length: f64,
    /// Newton stops when ‖Δx‖∞/h is below this (m/s).
    pub newton_tolerance: f64,
    pub newton_iterations: usize,
    pub linear_iterations: usize,
    pub linear_seconds: f64,
    /// The CG tolerance policy of the Newton systems: "adaptive" or the fixed number.
    pub cg_tolerance: crate::sim::scene::CgTolerance,
    /// Systems solved again to the convergence tolerance because their loosely solved
    /// direction passed the Newton test (adaptive tolerance only).
    pub linear_resolves: usize,
    /// With the multilevel preconditioner: how its levels were set up over the run's
    /// Newton systems (absent otherwise).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub multilevel_levels: Option<MultilevelLevels>,
    pub frames: usize,
    pub out_dir: String,
    /// The step this invocation resumed from (`run --resume`); None for a run started
    /// from step 0.
    pub resumed_from_step: Option<usize>,
    /// Checkpoints are written every this many steps (and at the last step).
    pub checkpoint_every: usize,
    /// Wall time spent writing checkpoints, over every invocation of the run.
    pub checkpoint_seconds: f64,
    pub moving_boundary: Option<MovingSummary>,
    /// Per neo-Hookean law of the scene (by its scene name, e.g. "stable-neo-hookean"):
    /// the steps that ended with an inverted element (J ≤ 0). The classical law's line
    /// search keeps its elements' J positive, so its count stays 0.
    pub inverted_steps: std::collections::BTreeMap<String, usize>,
    /// What the contact code did: all zero for a scene without obstacles.
    pub contact_counters: ContactCounters,
    /// Contact history; None for a scene without obstacles.
    pub contact: Option<ContactSummary>,
    /// The GPU Newton loop's adapter, precision and host↔device traffic (totals over the
    /// run); absent for a run with the CPU loop.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gpu: Option<crate::sim::integrator::GpuRunReport>,
    #[serde(skip)]
    pub records: Vec<StepRecord>,
    #[serde(skip)]
    pub final_positions: Vec<f64>,
    #[serde(skip)]
    pub final_velocities: Vec<f64>,
}

/// summary.json's `multilevel_levels`: the scene's `multilevel_setup` and the Newton
/// systems (directions and re-solves) whose levels were built or kept.
#[derive(Debug, Clone, serde::Serialize)]
pub struct MultilevelLevels {
    pub setup: crate::solve::options::MultilevelSetup,
    pub built: usize,
    pub kept: usize,
}
