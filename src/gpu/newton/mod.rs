//! The Newton step on the device: the eliminated CG on the device-assembled system
//! (`cg`) and the loop's vector operations, reductions and per-node updates (`ops`).

pub mod cg;
pub mod ops;
