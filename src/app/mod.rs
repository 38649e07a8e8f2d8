//! The `stickslip` command line ([`cli`]) and what only it uses: the benchmarks and the
//! hard-case suite ([`bench`]), the system files a command reads ([`system_files`]), the
//! PETSc/Matrix Market export ([`export`]), the solve report and the plot a run keeps
//! beside its steps.csv ([`steps_plot`]).

pub mod bench;
pub mod cli;
pub mod export;
mod report;
pub mod steps_plot;
pub mod system_files;

pub use bench::hard;
