//! GPU solver (wgpu): device-resident PCG on the eliminated system Ĥ y = b̂ of
//! docs/method.md ("The eliminated system", "Solvers", "The GPU CG loop"), with WGSL
//! kernels for the per-node rotations, the masked block-sparse (or matrix-free mass-spring)
//! Hessian product, Jacobi / block-Jacobi preconditioners and the CG updates with
//! deterministic two-pass reductions.

#[cfg(feature = "sim")]
pub mod assembly;
pub mod context;
#[cfg(feature = "sim")]
pub mod elements;
pub mod kernels;
pub mod newton;
pub mod solver;

pub use context::{
    adapter_name_mismatch, list_adapters, measure_copy_bandwidth, AdapterReport, GpuContext,
    GpuOptions, TrafficCount,
};
pub use solver::{
    BufferRecord, GpuSolveInfo, GpuSolver, KernelRecord, KernelTime, Resources, SolveOutcome,
    StageSeconds, DOES_NOT_FIT,
};

use crate::cg::{CgError, Preconditioner};
pub use crate::coarse::CoarseSpace;

/// Why the GPU solver could not run or did not converge.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GpuError {
    #[error("{0}")]
    NoAdapter(String),
    #[error("GPU device error: {0}")]
    Device(String),
    #[error("precision {precision} needs SHADER_F64, which adapter '{adapter}' does not offer (use --precision f32)")]
    NoF64 {
        adapter: String,
        precision: Precision,
    },
    #[error("GPU buffer '{label}' needs {bytes} bytes but adapter '{adapter}' allows at most {limit} bytes per {what}: the system {}", solver::DOES_NOT_FIT)]
    BufferTooLarge {
        label: String,
        bytes: u64,
        limit: u64,
        what: &'static str,
        adapter: String,
    },
    #[error("the GPU solver does not support this system: {0}")]
    Unsupported(String),
    #[error("update does not match the solver's system: {0}")]
    Mismatch(String),
    #[error(transparent)]
    Cg(#[from] CgError),
    /// A CG failure in f32 arithmetic: on an ill-conditioned system rounding alone can
    /// produce non-positive curvature or stagnation, so the message says so.
    #[error("{0} — in f32 arithmetic, where rounding on an ill-conditioned system can cause this; --precision mixed or f64 tells the two apart")]
    InF32(CgError),
}

/// Arithmetic of the GPU CG.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// f32 throughout (reductions in f64 where the device has SHADER_F64).
    #[default]
    F32,
    /// f64 throughout; needs SHADER_F64.
    F64,
    /// f32 CG inside f64 iterative refinement; stops on the f64 residual.
    Mixed,
}

impl std::fmt::Display for Precision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Precision::F32 => "f32",
            Precision::F64 => "f64",
            Precision::Mixed => "mixed",
        })
    }
}

impl std::str::FromStr for Precision {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "f32" => Ok(Precision::F32),
            "f64" => Ok(Precision::F64),
            "mixed" => Ok(Precision::Mixed),
            _ => Err(format!(
                "unknown precision '{s}' (expected f32, f64 or mixed)"
            )),
        }
    }
}

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

/// Upper bound of the workgroups of the grid-stride CG kernels (`GpuParams::workgroups`),
/// and so of the partial sums one reduction leaves: the partial-sum buffers hold this many.
pub const MAX_WORKGROUPS: u32 = 256;

/// Parameters of a GPU solve.
#[derive(Debug, Clone, PartialEq)]
pub struct GpuParams {
    pub precision: Precision,
    /// Stop when the true f64 relative residual ‖b̂ − Ĥy‖/‖b̂‖ ≤ tol.
    pub tol: f64,
    /// Limit on CG iterations (all restarts and, for mixed, all inner solves together).
    pub max_iters: usize,
    pub preconditioner: Preconditioner,
    /// Stagnation: the recurrence residual has not improved for this many iterations.
    pub stagnation_window: usize,
    /// Restarts from the current iterate when the true residual misses the tolerance.
    pub max_restarts: usize,
    /// Iterations recorded in the first submit; later chunks follow the predicted
    /// iterations left to the tolerance (at most doubling each time, at least
    /// `first_chunk / 4`, rounded up).
    pub first_chunk: usize,
    /// Cap of the iterations per submit (and per status read-back).
    pub max_chunk: usize,
    /// Workgroup size (power of two, 32..=256).
    pub workgroup_size: u32,
    /// Workgroups of the grid-stride CG kernels (matvec, update_xrz, update_p), which is
    /// also the number of partial sums each reduction leaves; fewer when the system has
    /// fewer workgroups' worth of nodes; 1..=[`MAX_WORKGROUPS`]. None: 256 on a GPU; on a
    /// CPU adapter (lavapipe)
    /// 8 per hardware thread. Why fewer there: every workgroup of the update
    /// kernels re-reduces all partials through barrier trees, and llvmpipe runs barriers
    /// as coroutine switches, about 4 µs per workgroup and kernel; with 256 workgroups
    /// that was 40% of an f64 CG iteration at 27k nodes on a 2-core machine.
    pub workgroups: Option<u32>,
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
    /// [`crate::coarse`]); the same choice as [`crate::cg::CgParams::coarse`].
    pub coarse: CoarseSpace,
    /// Whether f32 operators of an assembled Ĥ use the difference form
    /// (`shaders/matvec.wgsl` `DIFF`: node row sums summed in f64), which keeps the
    /// eigenvalues of the rigid translations that plain f32 rounding perturbs by
    /// ε_f32·‖Ĥ‖. See [`DifferenceForm`]; f64 operators never use it.
    pub f32_difference: DifferenceForm,
    /// Caps the storage binding size the solver assumes (bytes; None: the adapter's
    /// `max_storage_buffer_binding_size`). Per-block arrays larger than the limit are bound
    /// in row-chunk pieces; a lower cap makes small systems take that path (tests).
    #[doc(hidden)]
    pub binding_limit: Option<u64>,
    /// Caps the device memory the solver assumes (bytes; None: the device's). A system
    /// whose buffers exceed it is refused before anything is allocated (tests).
    #[doc(hidden)]
    pub memory_limit: Option<u64>,
}

impl Default for GpuParams {
    fn default() -> Self {
        GpuParams {
            precision: Precision::F32,
            tol: 1e-6,
            max_iters: 10_000,
            preconditioner: Preconditioner::Jacobi,
            stagnation_window: 1_000,
            max_restarts: 3,
            first_chunk: 8,
            max_chunk: 256,
            workgroup_size: 64,
            workgroups: None,
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
