//! The public report types: what a solve did (`GpuSolveInfo`, `StageSeconds`) and kernel
//! timings (`KernelTime`).

use crate::gpu::Precision;

/// Device time of one kernel (see [`crate::gpu::PcgSolver::profile_kernels`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct KernelTime {
    pub name: String,
    pub best_s: f64,
    pub mean_s: f64,
}

/// Wall-clock split of a solve.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct StageSeconds {
    pub upload: f64,
    pub setup: f64,
    pub solve: f64,
    pub download: f64,
}

/// What a successful GPU solve returns.
#[derive(Debug, Clone, PartialEq)]
pub struct SolveOutcome {
    /// The solution of Ĥ y = b̂ in frame coordinates.
    pub y: Vec<f64>,
    /// Δx = Δx_p + V y, recovered in f64 with the f64 frames in every precision.
    pub dx: Vec<f64>,
    pub info: GpuSolveInfo,
}

/// What a successful GPU solve did.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct GpuSolveInfo {
    pub adapter: String,
    pub precision: Precision,
    /// The coarse correction added to the preconditioner ("aggregates (count)",
    /// "translations" or "none", with a remark when every translation is constrained and
    /// the correction adds nothing).
    pub coarse: String,
    /// Whether the f32 operator ran in difference form (f32 and mixed).
    pub f32_difference: bool,
    /// CG iterations, all restarts and inner solves together.
    pub iterations: usize,
    /// Iterations recorded into command buffers (the chunks); those past convergence are
    /// no-ops on the device but still cost their dispatches. ≥ `iterations`.
    pub recorded_iterations: usize,
    /// Mixed precision: f32 segments, each ended by a reliable update (the true residual
    /// recomputed in f64 and put in place of the f32 one); 0 otherwise.
    pub outer_refinements: usize,
    pub restarts: usize,
    /// ‖b̂ − Ĥy‖/‖b̂‖ recomputed in f64 on the host from the downloaded y.
    pub relative_residual: f64,
    pub seconds: StageSeconds,
    /// Device time of the CG chunks from timestamp queries, where the adapter has them.
    pub gpu_seconds: Option<f64>,
    /// Bytes one CG iteration must move: matrix (or element) data, indices, vectors.
    pub bytes_per_iteration: u64,
    /// bytes_per_iteration · iterations / seconds.solve.
    pub achieved_gb_per_s: f64,
    /// The same over gpu_seconds.
    pub achieved_gb_per_s_gpu: Option<f64>,
    pub dispatches_per_iteration: usize,
    /// The most workgroups of one dispatch of a CG iteration (the device's launch policy,
    /// [`crate::gpu::launch`]).
    pub workgroups: u32,
    /// The most invocations of one dispatch of a CG iteration.
    pub threads_per_dispatch: u64,
    /// Status and result read-backs of this solve.
    pub readbacks: usize,
    /// Mixed: why the solve fell back to f64 CG and where that ran (None: it did not).
    pub fallback: Option<String>,
    /// Mixed, when extended-precision refinement ran (f64 CG stagnated above `tol`, or
    /// `error_tol` was set): its estimate of the relative error ‖y − y*‖/‖y*‖, y* the exact
    /// solution of Ĥ as assembled in f64 on the host (the device's product rounds
    /// differently: the two solutions differ by about κε). After a
    /// stagnation, success was claimed on this estimate being ≤ min(tol, error_tol),
    /// because the f64 residual cannot resolve `tol` (its rounding floor ε‖Ĥ‖‖y‖/‖b̂‖ is
    /// above it), so `relative_residual` may exceed `tol`. It is an estimate from the
    /// contraction of consecutive corrections (as LAPACK's refinement error bounds), not
    /// a proof. None: success means relative_residual ≤ tol.
    pub error_estimate: Option<f64>,
    /// κ̃(M⁻¹Ĥ), M the preconditioner, from the Lanczos coefficients of the CG runs (the
    /// largest over uninterrupted runs; an underestimate that tightens as CG runs; the
    /// f32 runs of mixed see the f32 operator). None when no run had 2 iterations.
    pub condition_estimate: Option<f64>,
    pub notes: Vec<String>,
}
