//! Why a GPU solve could not run or did not converge ([`GpuError`]). It sits with the
//! facade's [`crate::Error`], which holds it typed ([`crate::Error::Gpu`]), so that a
//! caller tells "does not fit" from "device lost" by its variant, never by its text.

use super::CgError;

/// What a refusal for want of device memory says (the command line exits 2 on it: the
/// input, not the device, is what must change).
pub const DOES_NOT_FIT: &str = "does not fit on the GPU";

/// Why the GPU solver could not run or did not converge.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GpuError {
    /// No adapter matches: none at all, or `WGPU_ADAPTER_NAME` names none (the message
    /// lists the adapters there are).
    #[error("{0}")]
    NoAdapter(String),
    /// The adapter refused to open a device.
    #[error("GPU device error: {0}")]
    RequestDevice(String),
    /// A solver could not open its device: `what` names the solver ("GPU solver", "GPU
    /// Newton loop"), `cause` is why (no adapter, no device, a bad setting).
    #[error("the {what} cannot start: {cause}")]
    CannotStart {
        what: &'static str,
        cause: Box<GpuError>,
    },
    /// A device setting from the environment is malformed.
    #[error("GPU device error: {var}={value}: expected a whole number of at least {min}")]
    BadSetting {
        var: &'static str,
        value: String,
        min: u32,
    },
    /// f64 or mixed precision on an adapter without SHADER_F64.
    #[error("precision {precision} needs SHADER_F64, which adapter '{adapter}' does not offer (use --precision f32)")]
    NoF64 {
        adapter: String,
        precision: &'static str,
    },
    /// One buffer larger than the adapter allows per buffer or per storage binding.
    #[error("GPU buffer '{label}' needs {bytes} bytes but adapter '{adapter}' allows at most {limit} bytes per {what}: the system {}", DOES_NOT_FIT)]
    BufferTooLarge {
        label: String,
        bytes: u64,
        limit: u64,
        what: &'static str,
        adapter: String,
    },
    /// The system's buffers together need more device memory than the device has (or
    /// than `GpuParams::memory_limit` allows).
    #[error("the system {}: it needs {need} bytes of device memory and adapter '{adapter}' has {limit} bytes", DOES_NOT_FIT)]
    DoesNotFit {
        need: u64,
        limit: u64,
        adapter: String,
    },
    /// The device reported an error (a validation error, out of memory) during `what`.
    #[error("GPU device error: {what}: {message}")]
    Validation { what: String, message: String },
    /// Waiting for the device failed during `what`: the device was lost or timed out.
    #[error("GPU device error: {what}: waiting for the GPU: {cause}")]
    Lost { what: String, cause: String },
    /// A read-back buffer could not be mapped or read.
    #[error("GPU device error: {what}: {cause}")]
    ReadBack { what: &'static str, cause: String },
    /// A lock shared with the device's callbacks or another thread was poisoned by a
    /// panic there; `lock` names what it guards.
    #[error("GPU device error: {lock} was poisoned by a panic in another thread")]
    Poisoned { lock: &'static str },
    /// The device's results break an invariant of the code that reads them (a bug in
    /// the solver, not a fault of the input).
    #[error("GPU device error: {0}")]
    Internal(String),
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

impl GpuError {
    /// Whether the system is too large for the device (one buffer, or all of them): the
    /// input must change, not the device.
    pub fn does_not_fit(&self) -> bool {
        match self {
            GpuError::BufferTooLarge { .. } | GpuError::DoesNotFit { .. } => true,
            GpuError::CannotStart { cause, .. } => cause.does_not_fit(),
            _ => false,
        }
    }

    /// `self` as the reason the solver `what` cannot start.
    pub fn cannot_start(self, what: &'static str) -> GpuError {
        GpuError::CannotStart {
            what,
            cause: Box::new(self),
        }
    }
}
