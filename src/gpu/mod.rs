//! The GPU solver (wgpu) for the eliminated system Ĥ y = b̂ of docs/method.md ("The
//! eliminated system", "Solvers", "The GPU CG loop"): the device PCG in every precision
//! ([`pcg`], on any device block matrix: the Newton loop's assembly or an uploaded host H)
//! over shared device plumbing (context, launches, schedule, slot table, the scalar types
//! of [`kernels::Real`]) and the report of a solve ([`info`]).

pub mod blocks;
pub mod context;
pub mod error;
pub mod gate;
pub mod info;
pub mod kernels;
pub mod launch;
pub mod params;
pub mod pcg;
pub mod profile;
pub mod schedule;

pub use context::{
    adapter_name_mismatch, list_adapters, measure_copy_bandwidth, no_adapter_message,
    AdapterReport, GpuContext, GpuOptions, PhaseGuard, ReadRange, TrafficCount,
};
pub use info::{GpuSolveInfo, KernelTime, SolveOutcome, StageSeconds};
pub use profile::{Phase, Profile};

pub use error::{GpuError, DOES_NOT_FIT, MULTILEVEL_ON_CPU};
pub use launch::{Launch, LaunchLimits, SegmentPolicy, SegmentWorkgroups};
pub use params::{DifferenceForm, GpuParams};
pub use pcg::PcgSolver;

pub use crate::solve::options::{CoarseSpace, Precision, Preconditioner};
