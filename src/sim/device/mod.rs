//! The Newton step's device operators: element energies, gradients and projected
//! Hessians ([`elements`]), their assembly into block rows ([`assembly`], which the device PCG of
//! [`crate::gpu::pcg`] reads in place), the loop's vector operations, reductions and
//! per-node updates ([`newton_ops`]) and its checks reduced to scalars: the inversion bound
//! and the force balance ([`checks`]); the line search's first trial recorded with the CG
//! ([`line_search`]).

pub mod assembly;
pub mod checks;
pub mod elements;
pub mod line_search;
pub mod newton_ops;
