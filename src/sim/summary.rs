//! summary.json: what a run of `stickslip run` did, rewritten after every step (`running`)
//! and at the end (`complete`, `failed` or `interrupted`).

use crate::gpu::{Phase, Profile};
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
    /// The CG's preconditioner (None for Cholesky).
    pub preconditioner: Option<String>,
    /// Why `[solver] preconditioner = "auto"` chose `preconditioner` (None for an
    /// explicit choice or Cholesky).
    pub preconditioner_choice: Option<String>,
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
    /// Where the CPU Newton loop's seconds went, by phase (this invocation); absent for
    /// the device loop, whose phases are in `gpu`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub phases: Option<PhaseSummary>,
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

/// summary.json's `phases`: the CPU loop's wall seconds of this invocation by phase
/// ([`crate::sim::phases`]), the linear solve apart.
#[derive(Debug, Clone, serde::Serialize)]
pub struct PhaseSummary {
    /// Wall seconds from the invocation's start to this summary.
    pub wall_seconds: f64,
    /// Of them, in the linear solve (`linear_seconds` of this invocation, as the
    /// profile times it).
    pub linear_solve_seconds: f64,
    /// `wall_seconds − linear_solve_seconds`.
    pub outside_solve_seconds: f64,
    /// The seconds outside the solve by phase; they sum to `outside_solve_seconds`.
    #[serde(serialize_with = "crate::gpu::profile::phase_map")]
    pub seconds: Vec<(Phase, f64)>,
    /// The share of `outside_solve_seconds` in a named phase (every one but
    /// `host_decisions`, the loop's own logic and whatever no phase covers).
    pub accounted_fraction: f64,
}

/// The phases a CPU run reports outside the linear solve, in summary.json's order.
pub const CPU_PHASES: [Phase; 11] = [
    Phase::Setup,
    Phase::ElementTerms,
    Phase::Assembly,
    Phase::Elimination,
    Phase::Contact,
    Phase::MovingBoundary,
    Phase::InversionBound,
    Phase::LineSearch,
    Phase::Checks,
    Phase::Output,
    Phase::HostDecisions,
];

impl PhaseSummary {
    /// The summary of a CPU loop's profile. Phases the CPU loop never opens (the
    /// device's) count as `host_decisions`.
    pub fn of(p: &Profile) -> Self {
        let linear = p.seconds(Phase::LinearSolve);
        let outside = p.wall_seconds - linear;
        let mut seconds: Vec<(Phase, f64)> =
            CPU_PHASES.iter().map(|&q| (q, p.seconds(q))).collect();
        let elsewhere: f64 = p
            .phases
            .iter()
            .filter(|(q, _)| *q != Phase::LinearSolve && !CPU_PHASES.contains(q))
            .map(|(_, s)| s)
            .sum();
        if let Some(last) = seconds.last_mut() {
            last.1 += elsewhere;
        }
        let named: f64 = seconds
            .iter()
            .filter(|(q, _)| *q != Phase::HostDecisions)
            .map(|(_, s)| s)
            .sum();
        PhaseSummary {
            wall_seconds: p.wall_seconds,
            linear_solve_seconds: linear,
            outside_solve_seconds: outside,
            accounted_fraction: if outside > 0.0 { named / outside } else { 1.0 },
            seconds,
        }
    }

    /// One line: the seconds outside the solve and the three largest phases.
    pub fn line(&self) -> String {
        format!(
            "outside the linear solve: {:.2} s of {:.2} s; {}",
            self.outside_solve_seconds,
            self.wall_seconds,
            largest_phases(&self.seconds, self.outside_solve_seconds)
        )
    }
}

/// The three phases with the most seconds, each with its share of `total`, in one line.
pub fn largest_phases(phases: &[(Phase, f64)], total: f64) -> String {
    let mut v = phases.to_vec();
    v.sort_by(|a, b| b.1.total_cmp(&a.1));
    let parts: Vec<String> = v
        .iter()
        .take(3)
        .map(|(p, s)| {
            let share = if total > 0.0 { 100.0 * s / total } else { 0.0 };
            format!("{} {s:.2} s ({share:.0} %)", p.name().replace('_', " "))
        })
        .collect();
    format!("largest phases: {}", parts.join(", "))
}
