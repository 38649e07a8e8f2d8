//! Systems to solve that no file supplies: seeded random Newton systems with mesh-like
//! block sparsity ([`generate`]).

pub mod generate;
