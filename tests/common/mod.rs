//! Helpers shared by the integration-test binaries (each includes this with `mod common;`
//! and uses the part it needs, hence the `dead_code` allowances).

#[allow(dead_code)]
pub mod cli;
#[allow(dead_code)]
pub mod gpu;
#[allow(dead_code)]
pub mod kkt;
#[allow(dead_code)]
pub mod readers;
