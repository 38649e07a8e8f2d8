//! Why a GPU solve could not run or did not converge: [`GpuError`], defined beside the
//! facade's [`crate::Error`] that holds it, and the messages of the GPU's refusals.

pub use crate::error::{GpuError, DOES_NOT_FIT};

/// Why f32 and mixed precision refuse the multilevel preconditioner.
pub const MULTILEVEL_ON_CPU: &str =
    "the multilevel preconditioner runs in f64 only (the CPU CG and the f64 device PCG); f32 and mixed take none, jacobi or block-jacobi";
