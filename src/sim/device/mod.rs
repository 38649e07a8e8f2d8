//! The Newton step's device operators: element energies, gradients and projected
//! Hessians ([`elements`]), their assembly into block rows ([`assembly`]), the eliminated
//! CG on the device-assembled system ([`newton_cg`], with the index arrays of its aggregate
//! coarse space in [`newton_coarse`]) and the loop's vector operations,
//! reductions and per-node updates ([`newton_ops`]).

pub mod assembly;
pub mod elements;
pub mod newton_cg;
pub mod newton_coarse;
pub mod newton_ops;
