//! The GPU CG's parameters ([`GpuParams`]) and the kernel-size bounds they refer to.

use crate::solve::options::{CoarseSpace, MultilevelSetup, Precision, Preconditioner};

/// The f32 difference form of the operator (`GpuParams::f32_difference`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum DifferenceForm {
    Off,
    /// On wherever the device has SHADER_F64, where the form sums each row in f64 (the
    /// products of two f32 are exact there), so it keeps every smooth mode, not only the
    /// translations, and costs the f32 matvec about 5% on lavapipe: on dt-1e2 with the
    /// aggregate coarse space mixed needs 273 iterations with it against f64's 265, and
    /// 331 without it (STABILITY.md). On an f32-only device, whose form sums in f32 and
    /// keeps only the translations, it is on where plain f32 blocks would move the softest
    /// rigid translation's eigenvalue by more than 0.1%: ε_f32·max diag(Ĥ) > 1e-3·λ_Z,
    /// λ_Z its Rayleigh quotient (`coarse::softest_translation`).
    #[default]
    Auto,
    On,
}

/// Relative move of the softest translation's eigenvalue above which
/// [`DifferenceForm::Auto`] turns the difference form on for f32 sums.
const DIFF_AUTO_THRESHOLD: f64 = 1e-3;

impl DifferenceForm {
    /// Whether an f32 operator of `h` under `frames` takes the difference form, with f64
    /// sums (`acc_f64`) or f32 ones; `diag_max` gives the largest |diagonal entry| of H
    /// (asked for only with f32 sums and `Auto`).
    pub fn wanted(
        self,
        acc_f64: bool,
        h: &crate::core::sparse::BlockCsr,
        frames: &crate::core::constraints::Frames,
        diag_max: impl FnOnce() -> f64,
    ) -> bool {
        match self {
            DifferenceForm::Off => false,
            DifferenceForm::On => true,
            DifferenceForm::Auto if acc_f64 => true,
            DifferenceForm::Auto => crate::solve::coarse::softest_translation(h, frames)
                .is_some_and(|lz| f64::from(f32::EPSILON) * diag_max() > DIFF_AUTO_THRESHOLD * lz),
        }
    }
}

/// Parameters of a solve on the device PCG ([`crate::gpu::PcgSolver`], which the facade
/// runs in every precision). Its workgroups and chunk lengths follow the device's own
/// policy (`gpu::launch`, `gpu::schedule`), not parameters.
#[derive(Debug, Clone, PartialEq)]
pub struct GpuParams {
    pub precision: Precision,
    /// Stop when the true f64 relative residual ‖b̂ − Ĥy‖/‖b̂‖ ≤ tol.
    pub tol: f64,
    /// Limit on CG iterations (all restarts and, for mixed, all inner solves together).
    pub max_iters: usize,
    pub preconditioner: Preconditioner,
    /// f64 with the multilevel preconditioner: when its levels are rebuilt (for every
    /// system, or kept across the systems of a Newton solve).
    pub multilevel_setup: MultilevelSetup,
    /// Stagnation: the recurrence residual has not improved for this many iterations.
    pub stagnation_window: usize,
    /// Restarts from the current iterate when the true residual misses the tolerance.
    pub max_restarts: usize,
    /// Mixed: reliable-update factor δ. The f32 CG's recurrence residual is replaced by
    /// the true residual, recomputed in f64, each time it has dropped by δ (CG then goes on
    /// with its search direction kept). Smaller δ means fewer f64 products but more drift
    /// between the f32 recurrence and the truth: before the difference form and the
    /// coarse correction, δ = 1e-3 cost 5–30× more iterations on the sliver and κ = 1e6
    /// hard cases. With them, δ = 1e-2 (the default) takes as few iterations as δ = 0.1 or
    /// fewer on every timed hard case (dt-1e2 at 107k DOFs: 469 against 515; f64 CG 462)
    /// with half the reliable updates; slivers +3% (STABILITY.md).
    pub inner_tol: f64,
    /// Mixed: limit on outer steps (reliable updates).
    pub max_outer: usize,
    /// Mixed: once the residual criterion is met, go on with extended-precision refinement
    /// (double-double residuals on the host, f64 CG corrections on the GPU) until the
    /// estimated relative error ‖y − y*‖/‖y*‖ is ≤ error_tol (y* the exact solution of the
    /// f64 Ĥ; the estimate comes from the contraction of consecutive corrections). A small
    /// residual bounds the error only by κ·tol; this targets the error directly. The
    /// estimate is in `GpuSolveInfo::error_estimate`. Needs an assembled Hessian and the
    /// f64 operator on the device. None: residual criterion only.
    pub error_tol: Option<f64>,
    /// Coarse correction added to the preconditioner, in every level (see
    /// [`crate::solve::coarse`]); the same choice as [`crate::solve::cg::CgParams::coarse`].
    pub coarse: CoarseSpace,
    /// Whether f32 operators use the difference form (`DIFF` in shaders/pcg_common.wgsl, in the
    /// world frame, with row sums summed in f64 on the host), which keeps the eigenvalues of the rigid translations that plain f32 rounding
    /// perturbs by ε_f32·‖Ĥ‖. See [`DifferenceForm`]; f64 operators never use it.
    pub f32_difference: DifferenceForm,
    /// Caps the storage binding size the solver assumes (bytes; None: the adapter's
    /// `max_storage_buffer_binding_size`). H's values are split into row chunks that each
    /// fit it; a lower cap makes small systems take that path (tests).
    #[doc(hidden)]
    pub binding_limit: Option<u64>,
    /// Caps the device memory the solver assumes (bytes; None: the device's). A system
    /// whose buffers exceed it is refused before anything is allocated (tests).
    #[doc(hidden)]
    pub memory_limit: Option<u64>,
}

/// A CG tolerance a solver accepts: in (0, 1) (NaN refused too).
pub(crate) fn checked_tol(tol: f64) -> Result<f64, super::GpuError> {
    if tol > 0.0 && tol < 1.0 {
        Ok(tol)
    } else {
        Err(super::GpuError::Unsupported(format!(
            "the CG tolerance must lie in (0, 1), not {tol}"
        )))
    }
}

impl Default for GpuParams {
    fn default() -> Self {
        GpuParams {
            precision: Precision::F32,
            tol: 1e-6,
            max_iters: 10_000,
            preconditioner: Preconditioner::Jacobi,
            multilevel_setup: MultilevelSetup::default(),
            stagnation_window: crate::solve::cg::STAGNATION_WINDOW,
            max_restarts: 3,
            inner_tol: 0.01,
            max_outer: 200,
            error_tol: None,
            coarse: CoarseSpace::default(),
            f32_difference: DifferenceForm::default(),
            binding_limit: None,
            memory_limit: None,
        }
    }
}
