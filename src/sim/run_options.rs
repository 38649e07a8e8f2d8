//! What `stickslip run` is asked ([`RunOptions`]).

use crate::sim::scene::LinearKind;
use std::path::PathBuf;

/// What `stickslip run` was asked.
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// A scene file path or a built-in scene name; None: the built-in `default`.
    pub scene: Option<String>,
    /// Output folder; None: `out/<scene name>`.
    pub out: Option<PathBuf>,
    /// Overrides the scene's linear solver.
    pub solver: Option<LinearKind>,
    /// Mesh resolution multiplier (default 1).
    pub size: Option<f64>,
    /// Overrides the number of steps.
    pub steps: Option<usize>,
    /// No progress bar.
    pub quiet: bool,
    /// Replace files in the output folder that look like a run's output but no previous
    /// run's manifest lists (otherwise such a folder is refused).
    pub overwrite: bool,
    /// Overrides the scene's Cholesky ordering.
    pub ordering: Option<crate::CholeskyOrdering>,
    /// Overrides where the Newton loop runs (`[solver] newton`).
    pub newton: Option<crate::sim::scene::NewtonLoop>,
    /// Overrides the CG tolerance policy of the Newton systems (`[solver] cg_tolerance`).
    pub cg_tolerance: Option<crate::sim::scene::CgTolerance>,
    /// Overrides the number of steps by the end time: round(T / h) steps.
    pub end_time: Option<f64>,
    /// Write every Newton system of these steps under `systems/step_S/iter_K/` in the
    /// output folder (`run --dump-systems`).
    pub dump_systems: Option<crate::sim::integrator::StepSelection>,
    /// Continue the run in this folder from its checkpoint (the scene and its options
    /// come from the checkpoint; `steps` or `end_time` may extend it).
    pub resume: Option<PathBuf>,
}
