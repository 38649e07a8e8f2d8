//! The engine behind the crate's facade: [`solver`] holds [`crate::Solver`], its
//! [`crate::SolverConfig`] and the [`crate::Solution`] it returns, and dispatches a
//! [`crate::Problem`] to the Cholesky oracle, the CPU CG or the GPU CG.

pub mod solver;
