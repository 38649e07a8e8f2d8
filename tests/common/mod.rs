//! Helpers shared by the integration-test binaries (each includes this with `mod common;`).

pub mod gpu;
