//! File formats of the command line: Matrix Market for H, g, B, p, Δx and reactions
//! ([`mtx`]), and the per-node constraint JSON ([`bcjson`]); output safety (same-file
//! checks, atomic writes, owned output folders) in [`files`]. Every fault in a file is an
//! [`InputError`] naming the file, the entry and the problem.
//!
//! Input files are read through [`read_text`] (or [`read_bytes`] for binary formats),
//! which bound what a file can make us hold: a file larger than [`input_limit`] (the
//! smaller of [`MAX_INPUT_BYTES`] = 16 GiB and half the machine's memory) is refused
//! before it is read, and a stream with no size (a pipe, a device such as `/dev/zero`)
//! is read in chunks and refused as soon as it passes the limit. Text files are refused
//! at their first NUL byte (so `/dev/zero` fails on its first chunk). A leading UTF-8
//! byte-order mark is skipped by the parsers.

pub mod bcjson;
pub mod files;
pub mod mtx;

use crate::error::InputError;
pub use crate::error::{cut_tokens, one_line, BOM, MAX_TOKEN_CHARS};
use std::io::Read;

/// Largest input file read, whatever the machine (16 GiB). See [`input_limit`].
pub const MAX_INPUT_BYTES: u64 = 16 << 30;

/// Chunk size of [`read_limited`] for streams: how far a device is read before a check.
const CHUNK: u64 = 1 << 20;

/// Physical memory in bytes (`MemTotal` of /proc/meminfo), None where unknown.
pub fn memory_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = text.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kb.checked_mul(1024)
}

/// The input-file limit: [`MAX_INPUT_BYTES`], or half the physical memory when that is
/// smaller (a file is held whole while it is parsed, and its parsed form is as large).
pub fn input_limit() -> u64 {
    match memory_bytes() {
        Some(m) => MAX_INPUT_BYTES.min(m / 2).max(CHUNK),
        None => MAX_INPUT_BYTES,
    }
}

/// Bytes as a short human figure (`1.5 GiB`, `12 MiB`, `300 bytes`).
pub fn human_bytes(b: u64) -> String {
    const GIB: f64 = (1u64 << 30) as f64;
    const MIB: f64 = (1u64 << 20) as f64;
    let x = b as f64;
    if x >= GIB {
        format!("{:.1} GiB", x / GIB)
    } else if x >= MIB {
        format!("{:.1} MiB", x / MIB)
    } else {
        format!("{b} bytes")
    }
}

thread_local! {
    /// Set while [`contain_panic`] runs a third-party parser on this thread.
    static CONTAINED: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Runs `f` (a third-party parser on user data), turning a panic inside it into `None`.
/// While it runs, [`panic_is_contained`] is true on this thread, so a panic hook can
/// stay silent about a panic that becomes an input error.
pub fn contain_panic<T>(f: impl FnOnce() -> T) -> Option<T> {
    CONTAINED.with(|c| c.set(true));
    let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    CONTAINED.with(|c| c.set(false));
    r.ok()
}

/// True inside [`contain_panic`] on this thread.
pub fn panic_is_contained() -> bool {
    CONTAINED.with(|c| c.get())
}

/// Text from a file quoted in a message: one line of at most `max_chars` characters
/// (then `…`), with control characters and every space other than ' ' written as
/// escapes (`\t`, `\u{a0}`), so an invisible fault stays visible.
pub fn escaped(text: &str, max_chars: usize) -> String {
    let mut out = String::new();
    for (k, ch) in text.chars().enumerate() {
        if k == max_chars {
            out.push('…');
            break;
        }
        match ch {
            ' ' => out.push(' '),
            '\t' => out.push_str("\\t"),
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            c if c.is_control() || c.is_whitespace() || c == BOM => {
                out.push_str(&format!("\\u{{{:x}}}", c as u32))
            }
            c => out.push(c),
        }
    }
    out
}

/// The input error for an allocation of `bytes` that failed while reading `file`.
pub fn out_of_memory(file: &str, what: &str, bytes: usize) -> InputError {
    InputError::new(
        file,
        "",
        format!(
            "cannot hold {what} in memory ({}): memory allocation failed (an address-space \
             limit such as `ulimit -v`, or too little memory for this input)",
            human_bytes(bytes as u64)
        ),
    )
}

/// Reads a file whole, at most `limit` bytes. `text`: refuse the first NUL byte (no text
/// file holds one). Regular files larger than the limit are refused before reading;
/// anything else (pipes, devices) is read in chunks and refused once past it.
/// The file is named as `path` displays. A `limit` other than [`input_limit`] is the
/// caller's (e.g. the size a header or another input fixes).
pub fn read_limited(
    path: impl AsRef<std::path::Path>,
    limit: u64,
    text: bool,
) -> Result<Vec<u8>, InputError> {
    let shown = path.as_ref().display().to_string();
    let path = path.as_ref();
    let cannot =
        |e: std::io::Error| InputError::new(&shown, "", format!("cannot read the file: {e}"));
    let why = if limit == input_limit() {
        " for input files (16 GiB, or half this machine's memory when that is less)"
    } else {
        " for this file"
    };
    let too_big = |what: String| {
        InputError::new(
            &shown,
            "",
            format!("{what}, more than the {} limit{why}", human_bytes(limit)),
        )
    };
    let mut f = std::fs::File::open(path).map_err(cannot)?;
    let meta = f.metadata().map_err(cannot)?;
    if meta.is_dir() {
        return Err(InputError::new(
            &shown,
            "",
            "cannot read the file: it is a directory",
        ));
    }
    let mut buf = Vec::new();
    // A regular file is read in one go (its size is known and checked); anything else
    // in chunks, each checked before the next is read.
    let chunk = if meta.is_file() {
        limit.saturating_add(1)
    } else {
        CHUNK
    };
    if meta.is_file() {
        if meta.len() > limit {
            return Err(too_big(format!("the file is {}", human_bytes(meta.len()))));
        }
        // A regular file can still grow while we read; the loop below bounds it anyway.
        let want = meta.len() as usize + 1;
        buf.try_reserve_exact(want)
            .map_err(|_| out_of_memory(&shown, "the file", want))?;
    }
    loop {
        let start = buf.len();
        let n = (&mut f).take(chunk).read_to_end(&mut buf).map_err(cannot)?;
        // `contains` on bytes is a memchr; the position is looked up only when found.
        if text && buf[start..].contains(&0) {
            if let Some(k) = buf[start..].iter().position(|&b| b == 0) {
                return Err(InputError::new(
                    &shown,
                    format!("byte {}", start + k),
                    "a NUL byte: this is not a text file",
                ));
            }
        }
        if buf.len() as u64 > limit {
            return Err(too_big(format!(
                "the stream holds more than {}",
                human_bytes(limit)
            )));
        }
        if n == 0 {
            return Ok(buf);
        }
    }
}

/// The first `max` bytes of a regular file (all of it when shorter), for a look at a
/// header ahead of the full read. Anything else (a pipe, a device) is refused: reading
/// ahead would consume what the full read needs.
pub fn read_limited_prefix(path: &str, max: u64) -> Result<Vec<u8>, InputError> {
    let cannot =
        |e: std::io::Error| InputError::new(path, "", format!("cannot read the file: {e}"));
    // Checked before opening: opening a FIFO for a look would take its writer's data (or
    // kill the writer with SIGPIPE when closed), leaving the full read to block forever.
    if !std::fs::metadata(path).map_err(cannot)?.is_file() {
        return Err(InputError::new(path, "", "not a regular file"));
    }
    let f = std::fs::File::open(path).map_err(cannot)?;
    let mut buf = Vec::new();
    f.take(max).read_to_end(&mut buf).map_err(cannot)?;
    if let Some(k) = buf.iter().position(|&b| b == 0) {
        return Err(InputError::new(
            path,
            format!("byte {k}"),
            "a NUL byte: this is not a text file",
        ));
    }
    Ok(buf)
}

/// Reads a whole text file (UTF-8), bounded by [`input_limit`]; a missing, unreadable,
/// oversized or non-text file is an input error.
pub fn read_text(path: &str) -> Result<String, InputError> {
    let bytes = read_limited(path, input_limit(), true)?;
    String::from_utf8(bytes).map_err(|e| {
        let at = e.utf8_error().valid_up_to();
        let bytes = e.as_bytes();
        let line = bytes[..at].iter().filter(|&&b| b == b'\n').count() + 1;
        InputError::new(
            path,
            format!("line {line}"),
            format!(
                "not UTF-8 text (invalid byte 0x{:02x} at byte {at})",
                bytes[at]
            ),
        )
    })
}

/// Reads a whole binary file, bounded by [`input_limit`] (for PETSc vectors, Gmsh meshes).
pub fn read_bytes(path: impl AsRef<std::path::Path>) -> Result<Vec<u8>, InputError> {
    read_limited(path, input_limit(), false)
}

/// `text` without a leading byte-order mark.
pub fn strip_bom(text: &str) -> &str {
    text.strip_prefix(BOM).unwrap_or(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_line_flattens_and_cuts() {
        assert_eq!(one_line("a\tb\n\n c\u{1b}[1m", 80), "a b c [1m");
        assert_eq!(one_line("abcdef", 3), "abc…");
        assert_eq!(one_line("ab  cdef", 3), "ab…");
        assert_eq!(one_line("ééé", 2), "éé…");
        assert_eq!(one_line("  x  ", 10), "x");
        assert_eq!(escaped("5\u{a0}\t\u{1b}x", 80), "5\\u{a0}\\t\\u{1b}x");
        assert_eq!(escaped("abcdef", 3), "abc…");
    }

    #[test]
    fn long_tokens_are_cut() {
        let n = "9".repeat(100_000);
        let msg = format!("entry: {n} is too large");
        let cut = cut_tokens(&msg);
        assert_eq!(cut, format!("entry: {}… is too large", "9".repeat(80)));
        assert_eq!(cut_tokens("short words stay"), "short words stay");
        let path = format!("/tmp/{}", "a".repeat(200));
        assert_eq!(cut_tokens(&path), path);
    }

    #[test]
    fn limits_devices_and_text() {
        let dir = std::env::temp_dir().join(format!("stickslip-io-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("t.txt");
        std::fs::write(&p, b"abc\xff").unwrap();
        let ps = p.to_str().unwrap();
        let e = read_text(ps).unwrap_err().to_string();
        assert!(
            e.ends_with("line 1: not UTF-8 text (invalid byte 0xff at byte 3)"),
            "{e}"
        );
        std::fs::write(&p, b"0123456789").unwrap();
        assert!(read_limited(ps, 10, true).is_ok());
        let e = read_limited(ps, 9, true).unwrap_err().to_string();
        assert!(
            e.contains("the file is 10 bytes, more than the 9 bytes limit"),
            "{e}"
        );
        if std::path::Path::new("/dev/zero").exists() {
            let e = read_text("/dev/zero").unwrap_err().to_string();
            assert_eq!(e, "/dev/zero: byte 0: a NUL byte: this is not a text file");
            let e = read_limited("/dev/zero", 3 << 20, false)
                .unwrap_err()
                .to_string();
            assert!(e.contains("the stream holds more than 3.0 MiB"), "{e}");
        }
        std::fs::remove_dir_all(&dir).ok();
    }
}
