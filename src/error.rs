//! Errors. Bad input is an [`InputError`] that names the file, the entry and the fault;
//! the command line prints it on one line and exits with code 2.

use std::fmt;

/// A fault in user-supplied data.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub struct InputError {
    /// The file (or command-line option) the fault is in.
    pub file: String,
    /// The entry: a JSON path, a matrix entry, a row, a key.
    pub entry: String,
    /// What is wrong.
    pub problem: String,
}

impl InputError {
    pub fn new(
        file: impl Into<String>,
        entry: impl Into<String>,
        problem: impl Into<String>,
    ) -> Self {
        InputError {
            file: file.into(),
            entry: entry.into(),
            problem: problem.into(),
        }
    }
}

impl fmt::Display for InputError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        // One line, always: newlines in nested messages are flattened, and a token echoed
        // from a file (a 100,000-digit number, a megabyte key) is cut.
        let problem = self.problem.replace('\n', " ");
        let problem = crate::io::cut_tokens(&problem);
        if self.entry.is_empty() {
            write!(f, "{}: {}", self.file, problem)
        } else {
            let entry = crate::io::cut_tokens(&self.entry);
            write!(f, "{}: {}: {}", self.file, entry, problem)
        }
    }
}

/// Faults found while solving (the data was well-formed but the problem is not solvable
/// as posed, or a solver did not reach its tolerance).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SolveError {
    /// Cholesky met a non-positive pivot: H is not positive definite on the free subspace.
    #[error("the eliminated Hessian is not positive definite on the free subspace (Cholesky pivot at node {node}, component {component} in the node's frame)")]
    NotPositiveDefinite { node: usize, component: usize },
    /// A CG solver failed; the message says how.
    #[error("{0}")]
    Cg(#[from] crate::cg::CgError),
    /// A GPU failure (no adapter, out of memory, a device error).
    #[error("{0}")]
    Gpu(String),
    /// Anything else from the factorization library.
    #[error("sparse factorization failed: {0}")]
    Factorization(String),
    /// Finite data whose solve or recovery overflowed f64; the message says where.
    #[error("{0}")]
    NotFinite(String),
    /// A given solution does not solve the system it claims to (`recover`).
    #[error("{0}")]
    NotSolved(String),
}

/// The one error of the library facade ([`crate::Problem`], [`crate::Solver`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Error {
    /// The caller's data or configuration is malformed: the message names the entry
    /// (`H`, `g`, `constraints[k]`, a configuration field) and what is wrong with it.
    #[error(transparent)]
    Input(#[from] InputError),
    /// The data is well-formed but the system cannot be solved as posed (H not positive
    /// definite on the free subspace, CG not reaching its tolerance, overflow).
    #[error(transparent)]
    Solve(#[from] SolveError),
    /// The GPU cannot run this solve: no adapter, no SHADER_F64 for f64 or mixed, a
    /// system larger than the device allows, or a device failure.
    #[error("{0}")]
    Device(String),
}

impl From<crate::gpu::GpuError> for Error {
    fn from(e: crate::gpu::GpuError) -> Self {
        use crate::gpu::GpuError as G;
        match e {
            // CG ran and did not converge: the system, not the device, is at fault.
            G::Cg(_) | G::InF32(_) => Error::Solve(SolveError::Gpu(e.to_string())),
            G::Mismatch(_) => Error::Input(InputError::new("problem", "", e.to_string())),
            _ => Error::Device(e.to_string()),
        }
    }
}

impl From<crate::cg::CgError> for Error {
    fn from(e: crate::cg::CgError) -> Self {
        Error::Solve(SolveError::Cg(e))
    }
}
