//! Why a run of `stickslip run` failed ([`RunError`]), and its exit code.

use crate::error::InputError;
use crate::sim::memory::SceneTooLarge;

/// Why a run failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RunError {
    /// Bad scene or options (exit code 2).
    #[error("{0}")]
    Input(#[from] InputError),
    /// A step failed (exit code 1).
    #[error("step {step} (t = {} s) failed: {cause}", show_time(.time))]
    Solve {
        step: usize,
        time: f64,
        cause: String,
    },
    /// Output could not be written (exit code 1).
    #[error("cannot write {path}: {cause}")]
    Output { path: String, cause: String },
    /// The scene does not fit in the memory the process may allocate (exit code 1).
    #[error("{0}")]
    Memory(#[from] SceneTooLarge),
    /// SIGINT or SIGTERM: the run stopped after a completed step and wrote its checkpoint
    /// (exit code 128 + the signal).
    #[error("interrupted by signal {signal} after step {step}; `stickslip run --resume {dir}` continues the run")]
    Interrupted {
        signal: i32,
        step: usize,
        dir: String,
    },
}

/// A time for a message: fixed-point when it reads well, else scientific (a time step of
/// 1e300 must not print 300 digits, nor 1e-300 print 0.000000).
fn show_time(t: &f64) -> String {
    if *t == 0.0 || (1e-3..1e6).contains(&t.abs()) {
        format!("{t:.6}")
    } else {
        format!("{t:.6e}")
    }
}

impl RunError {
    /// The process exit code for this error: 2 for bad input ([`RunError::Input`]: the
    /// scene, its entries or the command-line options), 1 for everything else (a failed
    /// step, output that could not be written). The command line exits with it.
    pub fn exit_code(&self) -> i32 {
        match self {
            RunError::Input(_) => 2,
            RunError::Interrupted { signal, .. } => 128 + signal,
            _ => 1,
        }
    }
}
