//! The `stickslip` command line ([`cli`]) and what only it uses: the benchmarks and the
//! hard-case suite ([`bench`]), the system files a command reads ([`system_files`]), the
//! PETSc/Matrix Market export ([`export`]) and the solve report.

pub mod bench;
pub mod cli;
pub mod export;
mod report;
pub mod system_files;

pub use bench::hard;
