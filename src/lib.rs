//! stickslip: Newton systems of implicit, optimization-based simulation (incremental
//! potential) with Dirichlet boundary conditions eliminated by a per-node change of basis,
//! solved by a sparse Cholesky oracle and CG on the CPU, and by CG on the GPU (wgpu).
//!
//! The pipeline, in the order a solve runs:
//! 1. [`constraints`]: per-node constraints → frames V_i, masks and the lift Δx_p.
//! 2. [`elimination`]: the eliminated SPD system Ĥ y = b̂ (matrix-free or assembled).
//! 3. [`oracle`] (faer sparse Cholesky) or [`cg`] (f64 PCG) solve it.
//! 4. Recovery Δx = Δx_p + V y and reactions f = −(HΔx + g).

pub mod bench;
pub mod cg;
pub mod cli;
pub mod coarse;
pub mod constraints;
pub mod driver;
pub mod elimination;
pub mod energy;
pub mod error;
pub mod export;
pub mod generate;
pub mod gpu;
pub mod hard;
pub mod integrator;
pub mod io;
pub mod linalg;
pub mod mesh;
pub mod oracle;
pub mod output;
pub mod plots;
pub mod report;
pub mod scene;
pub mod sparse;
pub mod springs;
