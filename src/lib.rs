//! stickslip solves the Newton systems of implicit, optimization-based simulation
//! (incremental potential) with Dirichlet boundary conditions (sticky nodes, slip on
//! planes and lines of any orientation, general per-node rows, prescribed displacements)
//! eliminated by a per-node change of basis. It solves the eliminated SPD system with a
//! sparse Cholesky (faer), conjugate gradients on the CPU, or conjugate gradients on the
//! GPU (wgpu, f32 / f64 / mixed precision), then recovers the step Δx and the reaction
//! forces the constraints exert.
//!
//! # One way in
//!
//! A [`Problem`] holds H (as triplets, both triangles, duplicates summed), the gradient g
//! and the per-node [`Constraint`]s; a [`Solver`] built from a [`SolverConfig`] solves it
//! and hands back a [`Solution`]. Keep the solver and call
//! [`Problem::update_values`] for the next Newton iteration: while the sparsity pattern and
//! the constraints stay the same, the Cholesky analysis and the GPU's device buffers are
//! reused.
//!
//! ```
//! use stickslip::{Constraint, Error, Precision, Problem, Solver, SolverConfig};
//!
//! # fn main() -> Result<(), Error> {
//! // A 3D chain of 10 nodes joined by unit springs, with a small mass term on the
//! // diagonal (H is then SPD, as an incremental potential's Hessian is).
//! let n = 10;
//! let mut triplets = Vec::new();
//! for i in 0..n {
//!     for a in 0..3 {
//!         triplets.push((3 * i + a, 3 * i + a, 0.1));
//!     }
//! }
//! for i in 0..n - 1 {
//!     for a in 0..3 {
//!         let (p, q) = (3 * i + a, 3 * (i + 1) + a);
//!         triplets.extend([(p, p, 1.0), (q, q, 1.0), (p, q, -1.0), (q, p, -1.0)]);
//!     }
//! }
//! let g: Vec<f64> = (0..3 * n).map(|k| -0.01 * (k as f64).sin()).collect();
//! let constraints = vec![
//!     Constraint::sticky(0),
//!     Constraint::plane(4, &[0.0, 1.0, 0.0]).offset(0.01),
//!     Constraint::line(7, &[1.0, 1.0, 0.0]),
//!     Constraint::rows(9, &[&[1.0, 0.0, 0.0]], &[0.0]),
//! ];
//! let mut problem = Problem::from_triplets(3, n, &triplets, &g, &constraints)?;
//!
//! // The GPU in mixed precision where a GPU with SHADER_F64 exists, CPU CG otherwise.
//! let mut solver = match Solver::new(SolverConfig::gpu(Precision::Mixed).tol(1e-8)) {
//!     Ok(s) => s,
//!     Err(Error::Gpu(why)) => {
//!         eprintln!("no GPU ({why}); solving on the CPU");
//!         Solver::new(SolverConfig::cg().tol(1e-8))?
//!     }
//!     Err(e) => return Err(e),
//! };
//! let sol = solver.solve(&problem)?;
//! assert!(sol.dx[0..3].iter().all(|&v| v == 0.0)); // the sticky node stays
//! assert!((sol.dx[3 * 4 + 1] - 0.01).abs() < 1e-12); // node 4 meets its plane
//! assert!(sol.stats.relative_residual <= 1e-8);
//!
//! // The next Newton iteration: same pattern, new values; the solver reuses its analysis.
//! let g2: Vec<f64> = g.iter().map(|v| 2.0 * v).collect();
//! problem.update_values(&triplets, &g2)?;
//! let sol2 = solver.solve(&problem)?;
//! assert!(sol2.stats.reused);
//! # Ok(())
//! # }
//! ```
//!
//! [`SolverConfig`] lists every default in one table. Errors are one [`Error`]: bad input
//! (naming the entry), a system that cannot be solved as posed, or a device failure.
//!
//! # Layers
//!
//! The facade is built from folders by layer, each importing only from the layers below
//! it (`tests/layers.rs` checks this, and that no two modules import each other):
//!
//! | layer | folder | what it holds |
//! |---|---|---|
//! | 0 | [`error`] | the error types (a leaf) |
//! | 1 | [`core`] | constraints → per-node frames V_i, masks and the lift Δx_p; the eliminated system Ĥ y = b̂; block-sparse H; the constrained [`Problem`] |
//! | 1 | [`io`], [`cases`] | Matrix Market and bc.json readers and writers; seeded random systems and mass-spring operators |
//! | 2 | [`solve`] | the sparse Cholesky oracle and its orderings, f64 PCG, its preconditioners, coarse spaces and the multilevel preconditioner, every option enum |
//! | 3 | [`gpu`] | device plumbing and the device PCG in every precision, with its coarse spaces and multilevel levels (no simulation types) |
//! | 4 | [`engine`] | the [`Solver`] behind this facade, dispatching to the oracle, the CPU CG or the GPU CG |
//! | 5 | `sim` | meshes, energies, scenes, the Newton loop and its device operators, the `run` driver, its output files and checkpoints (feature `sim`, on by default) |
//! | 6 | `app` | the `stickslip` command line, benchmarks, hard cases, plots, reports (feature `cli`) |
//!
//! docs/method.md gives the method; docs/architecture.md, "Layers of the crate", the layers.

pub mod error;

pub mod cases;
pub mod core;
pub mod io;

pub mod solve;

pub mod gpu;

pub mod engine;

// Scenes, meshes, energies and the time stepper.
#[cfg(feature = "sim")]
pub mod sim;

// The command line and what only it uses. Public for the binary and its tests, not an
// API: embed the solver through the names at the crate root.
#[cfg(feature = "cli")]
#[doc(hidden)]
pub mod app;

pub use crate::core::constraints::Constraint;
pub use crate::core::elimination::ConstrainedDiagonal;
pub use crate::core::problem::Problem;
pub use engine::solver::{
    CgTuning, GpuTuning, LayoutKey, Solution, SolveDetails, SolveSeconds, SolveStats, Solver,
    SolverConfig, Step,
};
pub use error::{Error, InputError, SolveError};
pub use solve::options::{
    CholeskyOrdering, CoarseSpace, MultilevelSetup, Precision, Preconditioner, SolverKind,
};
