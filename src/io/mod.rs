//! File formats of the command line: Matrix Market for H, g, B, p, Δx and reactions
//! ([`mtx`]), and the per-node constraint JSON ([`bcjson`]). Every fault in a file is an
//! [`InputError`](crate::error::InputError) naming the file, the entry and the problem.

pub mod bcjson;
pub mod mtx;

use crate::error::InputError;

/// Reads a whole text file; a missing or unreadable file is an input error.
pub fn read_text(path: &str) -> Result<String, InputError> {
    std::fs::read_to_string(path)
        .map_err(|e| InputError::new(path, "", format!("cannot read the file: {e}")))
}
