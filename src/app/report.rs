//! The solve report (`--report report.json`) and the one-line human summary.

use serde::Serialize;

/// Wall-clock seconds of the stages of `stickslip solve`.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Seconds {
    /// Reading and validating H, g and the constraints.
    pub read: f64,
    /// Frames (per-node bases, ranks, lift) and the eliminated right-hand side; with the
    /// CPU CG's multilevel preconditioner also its clusters and levels.
    pub setup: f64,
    /// The solver call (for cholesky: symbolic + numeric + triangular solves).
    pub solve: f64,
    /// Recovery of Δx and the reactions.
    pub recover: f64,
    /// Writing the output files.
    pub write: f64,
    pub total: f64,
    /// Cholesky only: symbolic analysis, numeric factorization, triangular solves.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub symbolic: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub numeric: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub triangular: Option<f64>,
}

/// Cholesky details.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CholeskyReport {
    /// Stored entries of the lower triangle of Ĥ and of the factor L.
    pub matrix_nnz: usize,
    pub factor_nnz: usize,
    /// Whether the symbolic analysis was reused (always false for a one-shot solve).
    pub reused_symbolic: bool,
    /// Structural nonzeros of L for the ordering that ran (`factor_nnz` is faer's
    /// storage, which adds supernode padding).
    pub factor_nnz_exact: usize,
    /// The fill-reducing ordering that ran: "amd" or "nested-dissection".
    pub ordering: String,
    /// Seconds computing a nested-dissection ordering (0 for AMD, which faer's analysis
    /// runs inside `seconds.symbolic`).
    pub ordering_seconds: f64,
    /// ‖D(b̂ − Ĥy)‖/‖Db̂‖ with D Ĥ's diagonal to the −½ (powers of two): the residual the
    /// bound 1e-8 applies to, meaningful where the plain one cancels.
    pub scaled_residual: f64,
    /// Steps of iterative refinement on the factor (0 unless the first solve missed the
    /// bound).
    pub refinements: usize,
    /// κ(DĤD) estimated on the factor when the refined residual stayed above the bound
    /// (the answer is then as good as f64 allows for that κ); null otherwise.
    pub condition_estimate: Option<f64>,
}

/// CG details.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CgReport {
    pub preconditioner: String,
    /// The coarse correction added to it ("aggregates", "translations" or "none").
    pub coarse: String,
    pub tol: f64,
    pub max_iters: usize,
    pub restarts: usize,
    /// κ̃(M⁻¹Ĥ) from the CG's Lanczos coefficients (extreme Ritz values: a lower bound
    /// that tightens as CG runs); null when CG ran fewer than 2 iterations.
    pub condition_estimate: Option<f64>,
}

/// Everything report.json holds.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    pub solver: String,
    pub precision: String,
    /// The GPU adapter (null for the CPU solvers).
    pub adapter: Option<String>,
    /// Worker threads of the CPU solvers (`--threads`, else RAYON_NUM_THREADS, else every
    /// core).
    pub threads: usize,
    /// Solver iterations (null for cholesky, a direct method).
    pub iterations: Option<usize>,
    /// ‖b̂ − Ĥy‖/‖b̂‖ recomputed in f64.
    pub relative_residual: f64,
    pub seconds: Seconds,
    pub dim: usize,
    pub nodes: usize,
    pub free_dofs: usize,
    pub constrained_dofs: usize,
    /// Nodes whose frame is rotated (slip constraints off the coordinate axes).
    pub rotated_nodes: usize,
    /// Constraints as given (JSON entries or rows of B).
    pub constraints: usize,
    /// True when some prescribed value is nonzero (Δx_p ≠ 0).
    pub prescribed: bool,
    pub constrained_diagonal: String,
    /// max_i ‖B_i Δx_i − p_i‖ over the constraint rows (unit-normalized rows).
    pub constraint_violation: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cholesky: Option<CholeskyReport>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cg: Option<CgReport>,
    /// Whatever the GPU solver reports about itself.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gpu: Option<serde_json::Value>,
    pub files: Files,
}

/// The files the solve read and wrote.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Files {
    pub hessian: String,
    pub gradient: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub constraints: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub constraint_matrix: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub constraint_values: Option<String>,
    pub out: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reactions: Option<String>,
}

/// Above this κ̃·tol a CG's residual tolerance no longer bounds the error of Δx to a
/// useful size (‖y − y*‖/‖y*‖ ≤ κ·‖r‖/‖b̂‖): 1 % error.
pub const CONDITION_WARNING: f64 = 1e-2;

impl Report {
    /// κ̃(M⁻¹Ĥ) of an iterative solve: the CPU CG's, or the device CG's where it
    /// provides one and does not estimate the error itself.
    pub fn condition_estimate(&self) -> Option<f64> {
        match (&self.cg, &self.gpu) {
            (Some(cg), _) => cg.condition_estimate,
            // Mixed precision with refinement estimates the error itself.
            (None, Some(gpu)) if gpu.get("error_estimate").is_some_and(|e| !e.is_null()) => None,
            (None, Some(gpu)) => gpu.get("condition_estimate").and_then(|v| v.as_f64()),
            (None, None) => None,
        }
    }

    /// A line for stderr when κ̃·tol exceeds [`CONDITION_WARNING`]: the residual met the
    /// tolerance, but the answer may still be far from the solution.
    pub fn condition_warning(&self, tol: f64) -> Option<String> {
        let kappa = self.condition_estimate()?;
        let bound = kappa * tol;
        (bound > CONDITION_WARNING).then(|| {
            format!(
                "warning: the CG's condition estimate κ̃(M⁻¹Ĥ) ≈ {kappa:.1e} times --tol {tol:.1e} \
                 is {bound:.1e} > {CONDITION_WARNING:.0e}: the residual met the tolerance, but \
                 the relative error of Δx is bounded only by about that or more (κ̃ \
                 underestimates κ); check Δx against --solver cholesky, or rescale the system"
            )
        })
    }

    /// One line for stderr.
    pub fn summary(&self) -> String {
        let iters = match self.iterations {
            Some(k) => format!(", {k} iterations"),
            None => String::new(),
        };
        let adapter = match &self.adapter {
            Some(a) => format!(" on {a}"),
            None => String::new(),
        };
        // Mixed precision with extended-precision refinement claims an error bound.
        let est = self
            .gpu
            .as_ref()
            .and_then(|g| g.get("error_estimate"))
            .and_then(|v| v.as_f64())
            .map_or(String::new(), |e| {
                format!(", estimated relative error {e:.2e}")
            });
        // Cholesky's bound is on the scaled residual: shown where the two differ.
        let scaled = self
            .cholesky
            .as_ref()
            .filter(|c| {
                let (a, b) = (c.scaled_residual, self.relative_residual);
                (a - b).abs() > 0.5 * a.abs().max(b.abs())
            })
            .map_or(String::new(), |c| {
                format!(" (scaled {:.2e})", c.scaled_residual)
            });
        let kappa = self
            .cg
            .as_ref()
            .and_then(|c| c.condition_estimate)
            .map_or(String::new(), |k| format!(", condition estimate {k:.1e}"));
        format!(
            "stickslip: {} {}{adapter}: {} nodes, {} free + {} constrained dofs{iters}, relative residual {:.2e}{scaled}{est}{kappa}, solve {:.3} s, total {:.3} s",
            self.solver,
            self.precision,
            self.nodes,
            self.free_dofs,
            self.constrained_dofs,
            self.relative_residual,
            self.seconds.solve,
            self.seconds.total
        )
    }
}
