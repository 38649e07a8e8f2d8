//! Step 3 of every benchmark, timing: what a run is measured against (the host's copy
//! bandwidth, the bytes a CPU CG iteration moves) and the process's peak memory.

use crate::core::elimination::Eliminated;
use std::time::Instant;

/// Peak resident set size of this process (Linux VmHWM), 0 where unknown.
pub fn peak_rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse::<u64>().ok())
        })
        .map_or(0, |kb| kb * 1024)
}

/// Host copy bandwidth: read + write bytes of a 256 MiB memcpy, best of 5.
pub fn cpu_copy_bandwidth() -> f64 {
    let n = 32 << 20; // f64 elements: 256 MiB
    let src = vec![1.0f64; n];
    let mut dst = vec![0.0f64; n];
    let mut best = f64::INFINITY;
    for _ in 0..5 {
        let t = Instant::now();
        dst.copy_from_slice(&src);
        std::hint::black_box(&mut dst);
        best = best.min(t.elapsed().as_secs_f64());
    }
    2.0 * (n * 8) as f64 / best / 1e9
}

/// Bytes one CPU CG iteration moves: the blocks, the column indices and row pointers
/// (usize), and about 18 passes over f64 vectors (matvec in/out, two dot products, the
/// x, r, z and p updates).
pub fn cpu_cg_bytes_per_iteration(e: &Eliminated) -> u64 {
    let h = e.h;
    let idx = std::mem::size_of::<usize>() as u64;
    let matrix =
        h.values.len() as u64 * 8 + h.col_idx.len() as u64 * idx + h.row_ptr.len() as u64 * idx;
    matrix + 18 * h.ndof() as u64 * 8
}

/// One line per finished run: above the progress bar on a terminal, plain on stderr
/// otherwise (indicatif hides its bar, and its println, when stderr is not a terminal).
pub(super) fn say(bar: &indicatif::ProgressBar, quiet: bool, text: &str) {
    if quiet {
        return;
    }
    if bar.is_hidden() {
        eprintln!("{text}");
    } else {
        bar.println(text);
    }
}
