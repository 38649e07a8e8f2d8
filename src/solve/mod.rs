//! The CPU solvers of the eliminated system and the engine behind the crate's facade:
//! the faer sparse Cholesky oracle ([`oracle`]) with its fill-reducing orderings
//! ([`ordering`]), f64 PCG ([`cg`], its fused threaded passes in `cg_fused`), the coarse
//! corrections ([`coarse`]), and the [`crate::Solver`] facade's engine.

pub mod cg;
mod cg_fused;
pub mod coarse;
pub mod multilevel;
pub mod options;
pub mod oracle;
pub mod ordering;
pub mod precond;
pub mod tolerance;
