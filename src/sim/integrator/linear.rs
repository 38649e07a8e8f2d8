//! The linear solver behind every Newton step of the host loop: the library's
//! [`crate::Solver`], with one [`LayoutKey`] per constraint set, and the residual check
//! that a direct solve must pass.

use crate::core::elimination::Eliminated;
use crate::sim::scene::{LinearKind, SolverSpec};
use crate::{LayoutKey, Solver};
use std::collections::HashMap;
use std::time::Instant;

/// Largest relative residual ‖b̂ − Ĥy‖/‖b̂‖ accepted from a Cholesky solve inside Newton.
/// A factorization that succeeds on a nearly singular Ĥ can return a direction this far
/// off; the step then fails (naming the residual) instead of line-searching a wrong
/// direction, as the CG and GPU paths fail when they miss their tolerance.
pub const CHOLESKY_MAX_RESIDUAL: f64 = 1e-8;
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
    pub fn new(spec: &SolverSpec) -> Result<Self, String> {
        let solver = Solver::new(spec.config()).map_err(|e| e.to_string())?;
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
        if self.kind == LinearKind::Cholesky {
            check_cholesky_residual(step.stats.relative_residual)?;
        }
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
