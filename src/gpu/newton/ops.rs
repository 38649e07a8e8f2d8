//! The device Newton loop's vector operations, reductions and per-node updates.
