//! What `stickslip run` is asked ([`RunOptions`]).

use crate::sim::scene::LinearKind;
use std::path::PathBuf;
use std::sync::Arc;

/// Draws steps.svg from steps.csv's whole text: supplied by the command line (whose
/// plotting library the simulation layer does not link); the run writes what it returns
/// atomically beside steps.csv.
pub trait StepsPlot: Send + Sync {
    /// The SVG text of the steps in `steps_csv` (steps.csv's header and rows).
    fn draw(&self, steps_csv: &str) -> Result<String, Box<dyn std::error::Error + Send + Sync>>;
}

impl std::fmt::Debug for dyn StepsPlot {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("StepsPlot")
    }
}

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
    /// Overrides the preconditioner of the CG solvers (`[solver] preconditioner`).
    pub preconditioner: Option<crate::sim::scene::PreconditionerChoice>,
    /// Overrides the number of steps by the end time: round(T / h) steps.
    pub end_time: Option<f64>,
    /// Write every Newton system of these steps under `systems/step_S/iter_K/` in the
    /// output folder (`run --dump-systems`).
    pub dump_systems: Option<crate::sim::integrator::StepSelection>,
    /// Continue the run in this folder from its checkpoint (the scene and its options
    /// come from the checkpoint; `steps` or `end_time` may extend it).
    pub resume: Option<PathBuf>,
    /// Draws steps.svg at the start, at checkpoints (at most a small share of the run's
    /// time), and when the run ends, is interrupted or fails; None: no steps.svg.
    pub steps_plot: Option<Arc<dyn StepsPlot>>,
}
