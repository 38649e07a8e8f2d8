//! Errors. Bad input is an [`InputError`] that names the file, the entry and the fault;
//! the command line prints it on one line and exits with code 2. A GPU failure is a
//! [`GpuError`], kept typed through the facade's [`Error`].

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
        let problem = cut_tokens(&problem);
        if self.entry.is_empty() {
            write!(f, "{}: {}", self.file, problem)
        } else {
            let entry = cut_tokens(&self.entry);
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
    Cg(#[from] CgError),
    /// A GPU solve that ran and did not converge; on the command line also a device
    /// failure met while solving.
    #[error("{0}")]
    Gpu(GpuError),
    /// A Cholesky solve whose residual stayed above its bound after refinement, on a
    /// DĤD singular to working precision: no f64 answer can be trusted.
    #[error("the eliminated Hessian is singular to working precision: κ(DĤD) ≈ {condition_estimate:.1e} ≥ 1/(64ε) (D: Ĥ's diagonal to the −½), and the Cholesky solve's residual ‖D(b̂ − Ĥy)‖/‖Db̂‖ stayed at {scaled_residual:.3e} after {refinements} refinement steps")]
    Singular {
        condition_estimate: f64,
        scaled_residual: f64,
        refinements: usize,
    },
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
    /// system larger than the device allows ([`GpuError::does_not_fit`]), or a device
    /// failure.
    #[error(transparent)]
    Gpu(GpuError),
}

/// A GPU error where it belongs: a CG that ran and did not converge is the system's
/// fault ([`Error::Solve`]), an update that does not match the solver's system is the
/// caller's ([`Error::Input`]), the rest is the device's ([`Error::Gpu`]).
impl From<GpuError> for Error {
    fn from(e: GpuError) -> Self {
        match e {
            GpuError::Cg(_) | GpuError::InF32(_) => Error::Solve(SolveError::Gpu(e)),
            GpuError::Mismatch(_) => Error::Input(InputError::new("problem", "", e.to_string())),
            _ => Error::Gpu(e),
        }
    }
}

impl From<CgError> for Error {
    fn from(e: CgError) -> Self {
        Error::Solve(SolveError::Cg(e))
    }
}

// Why CG stopped: an error of every CG, on the CPU and on the GPU.

/// Why CG stopped without reaching its tolerance.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CgError {
    #[error("CG met non-positive curvature pᵀĤp = {curvature:e} at iteration {iteration}: the Hessian is not positive definite on the free subspace")]
    NonPositiveCurvature { iteration: usize, curvature: f64 },
    #[error("CG stagnated at iteration {iterations} with relative residual {relative_residual:e} (tolerance {tol:e})")]
    Stagnation {
        iterations: usize,
        relative_residual: f64,
        tol: f64,
    },
    #[error("CG reached the iteration limit {iterations} with relative residual {relative_residual:e} (tolerance {tol:e})")]
    MaxIterations {
        iterations: usize,
        relative_residual: f64,
        tol: f64,
    },
    #[error("CG broke down at iteration {iteration}: a non-finite value appeared")]
    Breakdown { iteration: usize },
    /// Found before any iteration (`solve::coarse::unpinned_translation`): Ĥ is
    /// singular, so a CG "solution" would carry an arbitrary rigid translation.
    #[error("the eliminated Hessian is not positive definite on the free subspace: {0}")]
    Unpinned(Unpinned),
}

impl CgError {
    /// The residual reached when the solver gave up (None for breakdowns).
    pub fn reached_residual(&self) -> Option<f64> {
        match self {
            CgError::Stagnation {
                relative_residual, ..
            }
            | CgError::MaxIterations {
                relative_residual, ..
            } => Some(*relative_residual),
            _ => None,
        }
    }
}

/// A rigid translation that no constraint and no mass term pins: Ĥ is singular.
#[derive(Debug, Clone, PartialEq)]
pub struct Unpinned {
    /// The first node of the connected group of free nodes.
    pub node: usize,
    /// The group's node count.
    pub nodes: usize,
    /// The direction of the translation (unit, world axes).
    pub direction: Vec<f64>,
    /// tᵀĤt/tᵀt of the translation.
    pub stiffness: f64,
    /// The group's absolute row sums of Ĥ along the translation, per node it moves (what
    /// the stiffness is measured against).
    pub row_scale: f64,
}

impl std::fmt::Display for Unpinned {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let dir: Vec<String> = self
            .direction
            .iter()
            .map(|v| format!("{:.3}", if v.abs() < 5e-4 { 0.0 } else { *v }))
            .collect();
        write!(
            f,
            "the rigid translation along ({}) of the {} free node{} connected to node {} \
             meets no constraint and no mass term (tᵀĤt/tᵀt = {:.3e}, rows of size {:.3e})",
            dir.join(", "),
            self.nodes,
            if self.nodes == 1 { "" } else { "s" },
            self.node,
            self.stiffness,
            self.row_scale
        )
    }
}

// Why a GPU solve could not run or did not converge. It sits with the facade's Error,
// which holds it typed, so that a caller tells "does not fit" from "device lost" by its
// variant, never by its text.

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

// One-line messages: what every error line is made of, whatever text it echoes.

/// The byte-order mark some editors put at the start of a UTF-8 file.
pub const BOM: char = '\u{feff}';

/// A message from another library (or text from a file) made fit for our one-line
/// errors: control characters (tabs, newlines, escapes) become spaces, runs of spaces
/// collapse, and the result is cut at `max_chars` characters with `…`.
pub fn one_line(msg: &str, max_chars: usize) -> String {
    let mut out = String::with_capacity(msg.len().min(max_chars * 4 + 4));
    let mut chars = 0usize;
    let mut space = false;
    for ch in msg.trim().chars() {
        let ch = if ch.is_control() || ch.is_whitespace() || ch == BOM {
            ' '
        } else {
            ch
        };
        if ch == ' ' {
            if space {
                continue;
            }
            space = true;
        } else {
            space = false;
        }
        if chars == max_chars {
            out.truncate(out.trim_end().len());
            out.push('…');
            return out;
        }
        out.push(ch);
        chars += 1;
    }
    out.truncate(out.trim_end().len());
    out
}

/// Longest run of non-space characters an error line echoes whole (a number, a key,
/// a token from a file); longer runs are cut there with `…`.
pub const MAX_TOKEN_CHARS: usize = 80;

/// A path is kept whole up to this many characters (the longest path Linux resolves).
const MAX_PATH_CHARS: usize = 4096;

/// `msg` with every run of non-whitespace characters longer than [`MAX_TOKEN_CHARS`] cut
/// to that many with `…` (a path, a token holding `/`, is kept up to 4096 characters), so
/// an error line stays readable whatever a file holds.
pub fn cut_tokens(msg: &str) -> std::borrow::Cow<'_, str> {
    let long = |t: &str| {
        let limit = if t.contains('/') {
            MAX_PATH_CHARS
        } else {
            MAX_TOKEN_CHARS
        };
        t.chars().nth(limit).is_some().then_some(limit)
    };
    if !msg.split_whitespace().any(|t| long(t).is_some()) {
        return std::borrow::Cow::Borrowed(msg);
    }
    let mut out = String::with_capacity(msg.len().min(4096));
    let mut rest = msg;
    while !rest.is_empty() {
        let ws = rest.len() - rest.trim_start().len();
        out.push_str(&rest[..ws]);
        rest = &rest[ws..];
        let end = rest.find(char::is_whitespace).unwrap_or(rest.len());
        let tok = &rest[..end];
        match long(tok) {
            Some(limit) => {
                out.extend(tok.chars().take(limit));
                out.push('…');
            }
            None => out.push_str(tok),
        }
        rest = &rest[end..];
    }
    std::borrow::Cow::Owned(out)
}
