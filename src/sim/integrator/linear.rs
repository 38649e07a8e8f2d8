//! The linear solver behind every Newton step of the host loop: the library's
//! [`crate::Solver`], with one [`LayoutKey`] per constraint set, and the residual check
//! that a direct solve must pass.

use crate::core::elimination::Eliminated;
use crate::sim::scene::{LinearKind, SolverSpec};
use crate::{LayoutKey, Solver};
use std::collections::HashMap;
use std::time::Instant;

/// The residual a Cholesky solve aims for (the oracle refines above it, and fails on an Ĥ
/// singular to working precision): such an Ĥ fails the step, naming its condition,
/// instead of line-searching a wrong direction.
pub use crate::solve::oracle::CHOLESKY_MAX_RESIDUAL;
/// What one linear solve cost.
#[derive(Debug, Clone, Copy, Default)]
pub struct LinearStats {
    /// CG iterations; a direct (Cholesky) solve counts as one.
    pub iterations: usize,
    pub seconds: f64,
    /// ‖b̂‖ of the system (the eliminated gradient's norm).
    pub rhs_norm: f64,
    /// The relative residual tolerance the solve was asked for; None for a direct solve.
    pub tolerance: Option<f64>,
}

/// The linear solver behind every Newton step: the library [`Solver`], with one
/// [`LayoutKey`] per constraint set so that each set keeps its analysis or GPU buffers.
pub struct LinearSolver {
    kind: LinearKind,
    pub(super) solver: Solver,
    layouts: HashMap<Vec<bool>, LayoutKey>,
    /// GPU adapter name, when the GPU runs.
    pub adapter: Option<String>,
}

impl LinearSolver {
    pub fn new(spec: &SolverSpec) -> Result<Self, crate::Error> {
        let solver = Solver::new(spec.config())?;
        Ok(LinearSolver {
            kind: spec.linear,
            adapter: solver.adapter().map(str::to_string),
            solver,
            layouts: HashMap::new(),
        })
    }

    /// Solves the eliminated system and recovers Δx. `key` names the constraint set;
    /// `tolerance` maps ‖b̂‖ to the iterative solvers' relative residual tolerance.
    pub fn solve(
        &mut self,
        key: &[bool],
        e: &Eliminated,
        tolerance: &mut dyn FnMut(f64) -> f64,
    ) -> Result<(Vec<f64>, LinearStats), String> {
        let t = Instant::now();
        let rhs_norm = crate::core::linalg::norm2(&e.rhs);
        let tol = match self.kind {
            LinearKind::Cholesky => None,
            LinearKind::Cg | LinearKind::Gpu => {
                let tol = tolerance(rhs_norm);
                self.solver.set_tol(tol).map_err(|err| err.to_string())?;
                Some(tol)
            }
        };
        let layout = *self
            .layouts
            .entry(key.to_vec())
            .or_insert_with(LayoutKey::fresh);
        let step = self
            .solver
            .solve_eliminated(layout, e)
            .map_err(|err| err.to_string())?;
        Ok((
            step.dx,
            LinearStats {
                // A direct (Cholesky) solve counts as one.
                iterations: step.stats.iterations.unwrap_or(1),
                seconds: t.elapsed().as_secs_f64(),
                rhs_norm,
                tolerance: tol,
            },
        ))
    }
}
