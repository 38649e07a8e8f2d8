//! The CPU solvers of the eliminated system: the faer sparse Cholesky oracle ([`oracle`])
//! with its fill-reducing orderings ([`ordering`]), f64 PCG ([`cg`], its fused threaded
//! passes in `cg_fused`), its point-wise preconditioners ([`precond`]), the coarse
//! corrections ([`coarse`]), the multilevel preconditioner ([`multilevel`]), the rule for
//! an iterative solve's tolerance ([`tolerance`]) and every solver option ([`options`]).
//! The [`crate::Solver`] that dispatches to them (and to the GPU) is in [`crate::engine`].

pub mod cg;
mod cg_fused;
pub mod coarse;
pub mod multilevel;
pub mod options;
pub mod oracle;
pub mod ordering;
pub mod precond;
pub mod tolerance;
