//! The benchmarks of `stickslip bench` and the hard-case suite. Every benchmark is a
//! driver in the same five steps:
//!
//! 1. read or generate the systems ([`ladder`]: seeded systems over a ladder of sizes;
//!    [`newton`]: a neo-Hookean bar at a ladder of grids; [`systems`]: the Newton systems a
//!    simulation captured; [`hard`]: the hard cases);
//! 2. build the solvers (each driver's list of configurations);
//! 3. time them ([`measure`]: peak memory, copy bandwidth, bytes per CG iteration);
//! 4. check the answers against an oracle (the Cholesky solve, or an extended-precision
//!    reference for the hard cases);
//! 5. report and plot ([`record`]: what a run records; [`tables`]: the derived tables,
//!    the summary and the files of the ladder; `plots`: the SVG plots; [`hard_suite`]:
//!    hard.md and hard.json).

pub mod hard;
pub mod hard_suite;
pub mod ladder;
pub mod measure;
pub mod newton;
pub mod newton_report;
mod plots;
pub mod record;
pub mod systems;
pub mod tables;

pub use measure::{cpu_cg_bytes_per_iteration, cpu_copy_bandwidth, peak_rss_bytes};
