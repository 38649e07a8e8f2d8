//! Why a command failed, and the exit code that says so: 0 success; 1 a solve failed
//! (H not positive definite on the free subspace, CG did not converge, GPU failure) or a
//! subcommand is not available; 2 bad input or usage.

use crate::error::{Error, InputError, SolveError};

/// Why a command failed; decides the exit code.
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    /// Bad input data or options: exit 2.
    #[error("{0}")]
    Input(#[from] InputError),
    /// The system could not be solved as posed: exit 1.
    #[error("{0}")]
    Solve(#[from] SolveError),
    /// Anything else (unwritable output, a feature not in this build): exit 1.
    #[error("{0}")]
    Failed(String),
    /// A run stopped by SIGINT or SIGTERM after a completed step: exit 128 + the signal.
    #[error("{message}")]
    Interrupted { message: String, code: u8 },
}

impl CliError {
    pub fn exit_code(&self) -> u8 {
        match self {
            CliError::Input(_) => 2,
            CliError::Interrupted { code, .. } => *code,
            _ => 1,
        }
    }
}

/// An output that could not be written (exit 1), naming it.
pub fn write_failed(path: &str, e: std::io::Error) -> CliError {
    CliError::Failed(format!("cannot write {path}: {e}"))
}

/// A solve error (exit 1) when `v` holds a NaN or an infinity.
pub fn all_finite(what: &str, v: &[f64]) -> Result<(), CliError> {
    crate::engine::solver::all_finite(what, v).map_err(solve_error)
}

/// The facade's errors as the command line reports them: bad input exits 2, everything
/// else (unsolvable system, GPU failure) exits 1.
pub fn solve_error(e: Error) -> CliError {
    match e {
        Error::Input(e) => CliError::Input(e),
        Error::Solve(e) => CliError::Solve(e),
        // A system too large for the device: the input must change, not the device.
        Error::Gpu(e) if e.does_not_fit() => {
            CliError::Input(InputError::new("--solver gpu", "", e.to_string()))
        }
        Error::Gpu(e) => CliError::Solve(SolveError::Gpu(e)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A system too large for the device is an input fault (exit 2); other device
    /// failures exit 1.
    #[test]
    fn a_system_too_large_for_the_device_exits_2() {
        let big = Error::Gpu(crate::gpu::GpuError::DoesNotFit {
            need: 9,
            limit: 8,
            adapter: "a".into(),
        });
        assert_eq!(solve_error(big).exit_code(), 2);
        let lost = Error::Gpu(crate::gpu::GpuError::Lost {
            what: "solving".into(),
            cause: "device lost".into(),
        });
        assert_eq!(solve_error(lost).exit_code(), 1);
    }
}
