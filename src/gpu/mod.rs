//! GPU solver (wgpu): device-resident PCG on the eliminated system Ĥ y = b̂ of
//! docs/method.md ("The eliminated system", "Solvers", "The GPU CG loop"), with WGSL
//! kernels for the per-node rotations, the masked block-sparse (or matrix-free mass-spring)
//! Hessian product, Jacobi / block-Jacobi preconditioners and the CG updates with
//! deterministic two-pass reductions.

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
