//! Why a GPU solve could not run or did not converge ([`GpuError`]), and how that
//! becomes the facade's [`crate::Error`].

use crate::error::{CgError, Error, InputError, SolveError};
use crate::solve::options::Precision;

/// What a refusal for want of device memory says (the command line exits 2 on it: the
/// input, not the device, is what must change; tests look for it).
pub const DOES_NOT_FIT: &str = "does not fit on the GPU";

/// Why f32 and mixed precision refuse the multilevel preconditioner.
pub const MULTILEVEL_ON_CPU: &str =
    "the multilevel preconditioner runs in f64 only (the CPU CG and the f64 device PCG); f32 and mixed take none, jacobi or block-jacobi";

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
    #[error("GPU buffer '{label}' needs {bytes} bytes but adapter '{adapter}' allows at most {limit} bytes per {what}: the system {}", DOES_NOT_FIT)]
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

impl From<GpuError> for Error {
    fn from(e: GpuError) -> Self {
        use GpuError as G;
        match e {
            // CG ran and did not converge: the system, not the device, is at fault.
            G::Cg(_) | G::InF32(_) => Error::Solve(SolveError::Gpu(e.to_string())),
            G::Mismatch(_) => Error::Input(InputError::new("problem", "", e.to_string())),
            _ => Error::Device(e.to_string()),
        }
    }
}
