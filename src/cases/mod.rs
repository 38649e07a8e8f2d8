//! Systems to solve that no file supplies: seeded random Newton systems with mesh-like
//! block sparsity ([`generate`]) and the mass-spring incremental potential that the GPU's
//! matrix-free product is checked against ([`springs`]).

pub mod generate;
pub mod springs;
