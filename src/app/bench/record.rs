//! What `stickslip bench` records: one [`RunRecord`] per solver run, the Cholesky
//! reference runs, and the tables derived from them ([`BenchReport`]), as written to
//! bench.json and drawn by the plots.

use serde::Serialize;

/// One solver run at one tolerance.
#[derive(Debug, Clone, Serialize)]
pub struct RunRecord {
    pub dim: usize,
    pub nodes: usize,
    pub dofs: usize,
    /// cholesky | cg-jacobi | cg-block-jacobi | gpu-f32 | gpu-f64 | gpu-mixed
    pub solver: String,
    pub precision: String,
    pub tol: Option<f64>,
    pub converged: bool,
    pub iterations: usize,
    pub relative_residual: f64,
    pub relative_error: f64,
    /// "oracle" or "cg-1e-12" (when the oracle did not fit).
    pub error_reference: String,
    pub setup_seconds: f64,
    pub solve_seconds: f64,
    /// setup + solve (+ upload/download on the GPU).
    pub total_seconds: f64,
    pub gpu_seconds: Option<f64>,
    pub bytes_per_iteration: u64,
    pub achieved_gb_per_s: f64,
    pub seconds_per_iteration: f64,
    /// Iterations the device recorded (≥ iterations: chunks end past convergence).
    pub recorded_iterations: Option<usize>,
    /// GPU: dispatches per CG iteration, and the most invocations one of them launches.
    pub dispatches_per_iteration: Option<usize>,
    pub threads_per_dispatch: Option<u64>,
    /// Seconds per iteration over the bandwidth floor (bytes per iteration / copy
    /// bandwidth of the device that ran it): 1 is the physical limit.
    pub bandwidth_floor_ratio: f64,
    /// Peak resident memory of the process so far (VmHWM), bytes.
    pub peak_rss_bytes: u64,
    pub note: String,
}

/// Cholesky phases at one size.
#[derive(Debug, Clone, Serialize)]
pub struct CholeskyRecord {
    pub dim: usize,
    pub nodes: usize,
    pub symbolic_seconds: f64,
    pub numeric_seconds: f64,
    pub solve_seconds: f64,
    /// Numeric factorization + triangular solves again, with the analysis reused.
    pub reused_numeric_seconds: f64,
    pub factor_nnz: usize,
    /// Structural nonzeros of L (faer's `factor_nnz` adds supernode padding).
    pub factor_nnz_exact: usize,
    /// The ordering that ran: "amd" or "nested-dissection".
    pub ordering: String,
}

/// Which solver reaches a target error first at one size.
#[derive(Debug, Clone, Serialize)]
pub struct Winner {
    pub dim: usize,
    pub nodes: usize,
    pub target_error: f64,
    pub solver: String,
    pub seconds: f64,
}

/// Log-log fit of a per-solver quantity against the node count.
#[derive(Debug, Clone, Serialize)]
pub struct ScalingFit {
    pub dim: usize,
    pub solver: String,
    pub quantity: String,
    pub slope: f64,
    pub points: Vec<(usize, f64)>,
}

#[derive(Debug, Clone, Serialize)]
pub struct BenchReport {
    pub command: String,
    pub cpu_threads: usize,
    /// Worker threads the CPU solvers ran on (`--threads`, else RAYON_NUM_THREADS, else
    /// every core).
    pub threads: usize,
    pub adapter: Option<String>,
    /// Host memcpy bandwidth (read + write bytes per second), GB/s.
    pub cpu_copy_gb_per_s: f64,
    /// GPU buffer-to-buffer copy bandwidth (read + write), GB/s, timestamped.
    pub gpu_copy_gb_per_s: Option<f64>,
    pub runs: Vec<RunRecord>,
    pub cholesky: Vec<CholeskyRecord>,
    pub winners: Vec<Winner>,
    pub scaling: Vec<ScalingFit>,
}

/// Appends `record` as one JSON line to `OUT/records.jsonl` (`name`), so that a run
/// stopped at its time limit keeps every record finished before (bench.json and the
/// tables are written only at the end). Best effort: a failed write is reported by the
/// final write of the same folder.
pub fn append_record<T: Serialize>(out: Option<&std::path::Path>, name: &str, record: &T) {
    use std::io::Write;
    let Some(dir) = out else { return };
    let Ok(line) = serde_json::to_string(record) else {
        return;
    };
    let _ = std::fs::create_dir_all(dir);
    if let Ok(mut f) = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(dir.join(name))
    {
        let _ = writeln!(f, "{line}");
    }
}
