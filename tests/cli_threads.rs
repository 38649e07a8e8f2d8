//! `--threads`: the CPU CG writes the same Δx, bit for bit, on one and on two worker
//! threads, and report.json says how many ran; a thread count of 0 is a usage error.

mod common;
use common::cli::{run, stderr, tmpdir};

#[test]
fn cg_on_one_and_two_threads_writes_the_same_bits() {
    let dir = tmpdir("cli-threads");
    let d = dir.to_str().unwrap();
    // 8,000 nodes: many row chunks, rotated slip nodes in the realistic mix.
    let o = run(&[
        "generate",
        "--dim",
        "3",
        "--nodes",
        "8000",
        "--seed",
        "4",
        "--out-dir",
        d,
        "--quiet",
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let mut dx = Vec::new();
    for t in ["1", "2"] {
        let out = format!("{d}/dx{t}.mtx");
        let rep = format!("{d}/report{t}.json");
        let o = run(&[
            "solve",
            "--hessian",
            &format!("{d}/H.mtx"),
            "--gradient",
            &format!("{d}/g.mtx"),
            "--constraints",
            &format!("{d}/bc.json"),
            "--solver",
            "cg",
            "--threads",
            t,
            "--out",
            &out,
            "--report",
            &rep,
            "--quiet",
        ]);
        assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
        let r: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&rep).unwrap()).unwrap();
        assert_eq!(r["threads"].as_u64(), Some(t.parse().unwrap()));
        assert!(r["relative_residual"].as_f64().unwrap() <= 1e-8);
        assert!(r["rotated_nodes"].as_u64().unwrap() > 0);
        dx.push(std::fs::read_to_string(&out).unwrap());
    }
    // The files carry 17 significant digits: equal text is equal bits.
    assert_eq!(dx[0], dx[1]);
    let o = run(&[
        "solve",
        "--hessian",
        &format!("{d}/H.mtx"),
        "--gradient",
        &format!("{d}/g.mtx"),
        "--constraints",
        &format!("{d}/bc.json"),
        "--solver",
        "cg",
        "--threads",
        "0",
        "--out",
        &format!("{d}/dx0.mtx"),
    ]);
    assert_eq!(o.status.code(), Some(2));
    let e = stderr(&o);
    assert_eq!(e.trim().lines().count(), 1, "{e}");
    assert!(e.contains("--threads"), "{e}");
}

/// A thread count past the stated limit (1024) is a usage error on every command that
/// takes one, before any work: one line naming `--threads`, exit 2.
#[test]
fn thread_counts_past_the_limit_are_refused() {
    for args in [
        &["run", "hanging", "--steps", "1", "--threads", "4000", "-q"][..],
        &["solve", "--threads", "100000", "--hessian", "H.mtx"][..],
        &["bench", "--quick", "--threads", "1025"][..],
    ] {
        let o = run(args);
        let e = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {e}");
        assert_eq!(e.lines().count(), 1, "{e}");
        assert!(e.contains("--threads") && e.contains("1024"), "{e}");
    }
}
