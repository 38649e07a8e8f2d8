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

/// Says that a test, or part of one, did not run. The line goes straight to the process's
/// stderr, past the test harness's capture (which takes `eprintln!`), so `cargo test`
/// shows it beside the test's "ok" without `--nocapture`.
#[allow(dead_code)]
pub fn skip(line: &str) {
    use std::io::Write;
    let _ = writeln!(std::io::stderr().lock(), "{line}");
}
