//! The Newton step's device operators: element energies, gradients and projected
//! Hessians ([`elements`]), their assembly into block rows ([`assembly`], which the device PCG of
//! [`crate::gpu::pcg`] reads in place) and the loop's vector operations, reductions and
//! per-node updates ([`newton_ops`]).

pub mod assembly;
pub mod elements;
pub mod newton_ops;
