//! GPU solvers (wgpu) for the eliminated system Ĥ y = b̂ of docs/method.md ("The
//! eliminated system", "Solvers", "The GPU CG loop"): the device PCG in every precision
//! ([`pcg`], on any device block matrix: the Newton loop's assembly or an uploaded host H)
//! and the precision kernels of the matrix-free mass-spring operator ([`solver`], which
//! no solve of the product runs), over shared device plumbing (context, launches,
//! schedule, slot table, the scalar types of [`kernels::Real`]).

pub mod blocks;
pub mod context;
pub mod error;
pub mod kernels;
pub mod launch;
pub mod params;
pub mod pcg;
pub mod schedule;
pub mod solver;

pub use context::{
    adapter_name_mismatch, list_adapters, measure_copy_bandwidth, no_adapter_message,
    AdapterReport, GpuContext, GpuOptions, TrafficCount,
};
pub use solver::{
    BufferRecord, GpuSolveInfo, GpuSolver, KernelRecord, KernelTime, Resources, SolveOutcome,
    StageSeconds, DOES_NOT_FIT, MULTILEVEL_ON_CPU,
};

pub use error::GpuError;
pub use launch::{Launch, LaunchLimits, SegmentPolicy, SegmentWorkgroups};
pub use params::{DifferenceForm, GpuParams, MAX_WORKGROUPS};
pub use pcg::PcgSolver;

pub use crate::solve::options::{CoarseSpace, Precision, Preconditioner};
