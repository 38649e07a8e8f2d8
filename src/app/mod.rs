//! The `stickslip` command line ([`cli`]) and what only it uses: the benchmarks
//! ([`bench`], [`bench_newton`]), the hard-case suite ([`hard`]), the PETSc/Matrix Market
//! export ([`export`]), the solve report and the benchmark's plots.

pub mod bench;
pub mod bench_newton;
pub mod bench_report;
pub mod bench_systems;
pub mod cli;
pub mod export;
pub mod hard;
mod plots;
mod report;
pub mod system_files;
