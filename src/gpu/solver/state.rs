//! The solver's state between chunks and between solves: the CG driver's (status
//! scalars, the Lanczos history, the chunk schedule's hints), how a run of chunks ended,
//! and mixed precision's (the f32 operator's scale, the fallback taken).

use super::levels::SCAL_LEN;
use super::policy::{inner_scale, MixedPolicy};
use crate::core::sparse::BlockCsr;

/// The CG driver's state between status reads and runs.
pub(super) struct RunState {
    /// The scalars and coefficient history of the last status read.
    pub(super) last_scal: Vec<f64>,
    /// The Lanczos coefficients of the current uninterrupted CG sequence.
    pub(super) lz_alphas: Vec<f64>,
    pub(super) lz_betas: Vec<f64>,
    /// The next run continues the sequence (set by a reliable update).
    pub(super) lz_resumed: bool,
    /// Largest κ̃(M⁻¹Ĥ) of the closed sequences of this solve.
    pub(super) kappa_est: Option<f64>,
    /// ρ_prev at the last status read: what a reliable update rescales.
    pub(super) last_rho_prev: f64,
    /// Size of the first chunk of the next `run_cg` (mixed: the length the previous
    /// segment's late rate predicts).
    pub(super) chunk_hint: Option<usize>,
    /// The fall of ln r·r per iteration over the later half of the last converged run
    /// (mixed: predicts the next segment's length).
    pub(super) last_rate: Option<f64>,
    /// r·r where the next `run_cg` starts, when known (mixed: 1, the unit right-hand side
    /// with x = 0): the first point of its rate history, so the chunk after the first is
    /// predicted instead of doubled.
    pub(super) start_rr: Option<f64>,
    /// Mixed, during an f32 segment: the policy and outer step whose condition verdict
    /// `run_cg` checks at every status read.
    pub(super) kappa_watch: Option<(MixedPolicy, usize)>,
}

impl RunState {
    pub(super) fn new() -> Self {
        RunState {
            last_scal: vec![0.0; SCAL_LEN],
            lz_alphas: Vec::new(),
            lz_betas: Vec::new(),
            lz_resumed: false,
            kappa_est: None,
            last_rho_prev: 1.0,
            chunk_hint: None,
            last_rate: None,
            start_rr: None,
            kappa_watch: None,
        }
    }

    /// Forgets the condition estimate of the previous solve.
    pub(super) fn start_solve(&mut self) {
        self.lz_alphas.clear();
        self.lz_betas.clear();
        self.lz_resumed = false;
        self.kappa_est = None;
    }
}

/// Result of one CG run (until convergence of the recurrence, the budget or stagnation).
pub(super) enum Outcome {
    Converged,
    MaxIters,
    Stagnated,
    /// Mixed: the condition estimate says f32 CG costs more than it saves (the reason).
    LeaveF32(String),
}

/// Mixed precision's state across and within solves.
pub(super) struct MixedState {
    /// The f32 operator holds 2^s·Ĥ (this factor; 1 unless Ĥ's diagonal is extreme).
    pub(super) inner_scale: f64,
    /// Run the fallback on the CPU even where an f64 GPU level could be built.
    pub(super) force_cpu_fallback: bool,
    /// Why and where the last solve fell back to f64.
    pub(super) last_fallback: Option<String>,
    /// The error estimate of the extended-precision refinement of the last solve.
    pub(super) last_error_estimate: Option<f64>,
    /// The assembled Ĥ for the double-double residuals (built on first use).
    pub(super) assembled: Option<BlockCsr>,
}

impl MixedState {
    /// `mixed`: whether the solve is in mixed precision; `diag_max` H's largest diagonal
    /// entry, which sets the f32 operator's scale.
    pub(super) fn new(mixed: bool, diag_max: f64) -> Self {
        MixedState {
            inner_scale: if mixed { inner_scale(diag_max) } else { 1.0 },
            force_cpu_fallback: false,
            last_fallback: None,
            last_error_estimate: None,
            assembled: None,
        }
    }

    pub(super) fn start_solve(&mut self) {
        self.last_fallback = None;
        self.last_error_estimate = None;
    }
}
