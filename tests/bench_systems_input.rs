//! `bench --systems DIR` on the files `solve` reads: a malformed system is an input error
//! found before any timing, and `--quiet` keeps the result table on stdout.

mod common;

use common::cli::{assert_input_error, run, tmpdir};
use std::path::Path;

/// A small seeded system (27 nodes, 3D) written by `generate` into `dir`.
fn generate(dir: &Path) {
    let o = run(&[
        "generate",
        "--nodes",
        "27",
        "--quiet",
        "--out-dir",
        dir.to_str().expect("utf-8 temp path"),
    ]);
    assert!(o.status.success(), "{}", common::cli::stderr(&o));
}

#[test]
fn a_malformed_system_exits_2_naming_its_file_before_any_timing() {
    let dir = tmpdir("bench-malformed");
    let systems = dir.join("systems");
    // The good system sorts first, so a bench that reads lazily would time it before
    // meeting the bad one.
    let good = systems.join("a_good");
    let bad = systems.join("b_bad");
    generate(&good);
    generate(&bad);
    let h = bad.join("H.mtx");
    let text = std::fs::read_to_string(&h).expect("H.mtx");
    // An entry whose value is not a number.
    let broken = text.replacen("\n1 1 ", "\n1 1 x", 1);
    assert_ne!(broken, text, "the first diagonal entry was found");
    std::fs::write(&h, broken).expect("write H.mtx");
    let out = dir.join("out");
    let o = run(&[
        "bench",
        "--systems",
        systems.to_str().expect("utf-8"),
        "--no-gpu",
        "--out",
        out.to_str().expect("utf-8"),
    ]);
    // One line (no progress line before it: nothing was timed), exit 2, the file first.
    let line = assert_input_error(&o, h.to_str().expect("utf-8"), &[]);
    // `solve` on the same files says the same.
    let s = |f: &str| bad.join(f).to_str().expect("utf-8").to_string();
    let solved = run(&[
        "solve",
        "--hessian",
        &s("H.mtx"),
        "--gradient",
        &s("g.mtx"),
        "--constraints",
        &s("bc.json"),
        "--out",
        dir.join("dx.mtx").to_str().expect("utf-8"),
    ]);
    assert_eq!(assert_input_error(&solved, &s("H.mtx"), &[]), line);
    assert!(
        !out.join("bench.json").exists(),
        "bench.json written for a failed bench"
    );
    assert!(o.stdout.is_empty(), "a table was printed");
}

#[test]
fn quiet_keeps_the_result_table_and_silences_progress() {
    let dir = tmpdir("bench-quiet");
    generate(&dir.join("systems").join("only"));
    let o = run(&[
        "bench",
        "--systems",
        dir.join("systems").to_str().expect("utf-8"),
        "--no-gpu",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", common::cli::stderr(&o));
    assert!(o.stderr.is_empty(), "{}", common::cli::stderr(&o));
    let table = String::from_utf8_lossy(&o.stdout);
    assert!(table.starts_with("| system | nodes | solver |"), "{table}");
    // One row per solver: Cholesky, six CG preconditioner and coarse pairs, multilevel.
    let rows: Vec<&str> = table
        .lines()
        .filter(|l| l.starts_with("| only |"))
        .collect();
    assert_eq!(rows.len(), 8, "{table}");
}
