//! The constrained Newton system: per-node constraints and their frames V_i
//! ([`constraints`]), the eliminated system Ĥ y = b̂ ([`elimination`]), block-sparse
//! matrices ([`sparse`]), the checked [`problem::Problem`], and small dense helpers
//! ([`linalg`]).

pub mod constraints;
pub mod elimination;
pub mod linalg;
pub mod problem;
pub mod sparse;
