//! The input readers on crafted bad input, through the built binary: duplicate entries
//! that sum past f64, the file blamed for B and p, size lines declaring huge systems,
//! byte-order marks, devices and oversized files, repeated JSON keys, and file text
//! quoted in messages. Bad input exits 2 with one stderr line naming the file and the
//! entry; a BOM is skipped and the solve succeeds. No timing asserts (timings belong in
//! benchmarks): a regression to allocating a declared size aborts the process instead.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

mod common;
use common::cli::{assert_input_error, run, stderr, tmpdir, write};

use stickslip::io::mtx::{self, HessianBounds};

/// The 2D two-node spring of the worked examples (docs/method.md),
/// H = [[2I, −I], [−I, 2I]], lower triangle.
const H: &str = "%%MatrixMarket matrix coordinate real symmetric\n4 4 6\n1 1 2\n2 2 2\n3 1 -1\n3 3 2\n4 2 -1\n4 4 2\n";
const G: &str = "%%MatrixMarket matrix array real general\n4 1\n0\n0\n0\n0\n";
/// Node 1 sticky, moved by (1, 2): Δx = (0.5, 1, 1, 2).
const BC: &str =
    r#"{"dim": 2, "constraints": [{"node": 1, "kind": "sticky", "displacement": [1, 2]}]}"#;
/// The same constraint as B (rows on components 3 and 4) and p.
const B: &str = "%%MatrixMarket matrix coordinate real general\n2 4 2\n1 3 1\n2 4 1\n";
const P: &str = "%%MatrixMarket matrix array real general\n2 1\n1\n2\n";
const DX: [f64; 4] = [0.5, 1.0, 1.0, 2.0];

struct Case {
    dir: PathBuf,
    h: String,
    g: String,
    bc: String,
}

fn case(name: &str) -> Case {
    let dir = tmpdir(name);
    Case {
        h: write(&dir, "H.mtx", H),
        g: write(&dir, "g.mtx", G),
        bc: write(&dir, "bc.json", BC),
        dir,
    }
}

impl Case {
    fn out(&self) -> String {
        self.dir.join("dx.mtx").to_str().unwrap().to_string()
    }

    fn solve(&self, h: &str, g: &str, bc: &str) -> Output {
        run(&[
            "solve",
            "--hessian",
            h,
            "--gradient",
            g,
            "--constraints",
            bc,
            "--out",
            &self.out(),
            "--quiet",
        ])
    }

    fn solve_b(&self, b: &str, p: &str) -> Output {
        run(&[
            "solve",
            "--hessian",
            &self.h,
            "--gradient",
            &self.g,
            "--constraint-matrix",
            b,
            "--constraint-values",
            p,
            "--dim",
            "2",
            "--out",
            &self.out(),
            "--quiet",
        ])
    }

    fn dx(&self) -> Vec<f64> {
        let text = std::fs::read_to_string(self.out()).unwrap();
        let coo = mtx::parse("dx.mtx", &text).unwrap();
        coo.entries.iter().map(|e| e.2).collect()
    }
}

fn assert_dx(c: &Case, o: &Output) {
    assert_eq!(o.status.code(), Some(0), "{}", stderr(o));
    let dx = c.dx();
    assert_eq!(dx.len(), 4);
    for (a, b) in dx.iter().zip(DX) {
        assert!((a - b).abs() < 1e-12, "{dx:?}");
    }
}

// 1. Duplicate coordinate entries are summed; the sum must be finite too.

#[test]
fn duplicates_summing_past_f64_in_g() {
    let c = case("dup-g");
    for (v, sum) in [("1e308", "inf"), ("-1e308", "-inf")] {
        let g = write(
            &c.dir,
            "g_dup.mtx",
            &format!("%%MatrixMarket matrix coordinate real general\n4 1 2\n2 1 {v}\n2 1 {v}\n"),
        );
        let o = c.solve(&c.h, &g, &c.bc);
        assert_input_error(
            &o,
            &g,
            &["entry (2, 1)", &format!("sum to {sum}"), "not finite"],
        );
    }
    // A row vector names its column.
    let g = write(
        &c.dir,
        "g_row.mtx",
        "%%MatrixMarket matrix coordinate real general\n1 4 2\n1 3 1e308\n1 3 1e308\n",
    );
    assert_input_error(
        &c.solve(&c.h, &g, &c.bc),
        &g,
        &["entry (1, 3)", "not finite"],
    );
}

#[test]
fn duplicates_summing_past_f64_in_b() {
    let c = case("dup-b");
    let b = write(
        &c.dir,
        "B_dup.mtx",
        "%%MatrixMarket matrix coordinate real general\n2 4 3\n1 3 1e308\n1 3 1e308\n2 4 1\n",
    );
    let p = write(&c.dir, "p.mtx", P);
    assert_input_error(
        &c.solve_b(&b, &p),
        &b,
        &["row 1", "column 3", "sum to inf", "not finite"],
    );
}

// 2. A fault in p is blamed on p, not on B.

#[test]
fn duplicates_summing_past_f64_in_p_blame_p() {
    let c = case("dup-p");
    let b = write(&c.dir, "B.mtx", B);
    let p = write(
        &c.dir,
        "p_dup.mtx",
        "%%MatrixMarket matrix coordinate real general\n2 1 3\n1 1 1e308\n1 1 1e308\n2 1 2\n",
    );
    let e = assert_input_error(&c.solve_b(&b, &p), &p, &["entry (1, 1)", "not finite"]);
    assert!(!e.contains("B.mtx"), "{e}");
    // The valid pair solves.
    let p = write(&c.dir, "p.mtx", P);
    assert_dx(&c, &c.solve_b(&b, &p));
}

// 3. Size lines declaring systems far beyond the file.

#[test]
fn huge_declared_dimension_fails_at_once() {
    let c = case("huge");
    for rows in ["2147483646", "1000000000", "2000000"] {
        let h = write(
            &c.dir,
            "H_huge.mtx",
            &format!(
                "%%MatrixMarket matrix coordinate real symmetric\n{rows} {rows} 4\n1 1 2\n2 2 2\n3 3 2\n4 4 2\n"
            ),
        );
        let o = c.solve(&h, &c.g, &c.bc);
        assert_input_error(&o, &h, &["line 2", rows]);
        let b = write(&c.dir, "B.mtx", B);
        let p = write(&c.dir, "p.mtx", P);
        let o = run(&[
            "solve",
            "--hessian",
            &h,
            "--gradient",
            &c.g,
            "--constraint-matrix",
            &b,
            "--constraint-values",
            &p,
            "--dim",
            "2",
            "--out",
            &c.out(),
        ]);
        assert_input_error(&o, &h, &["line 2"]);
    }
    // Enough declared entries for the legacy ratio: refused by the machine's memory (64
    // bytes a row) where it has less than 119 GiB, else by the missing entries.
    let h = write(
        &c.dir,
        "H_mem.mtx",
        "%%MatrixMarket matrix coordinate real symmetric\n2000000000 2000000000 40000000\n1 1 2\n",
    );
    assert_input_error(&c.solve(&h, &c.g, &c.bc), &h, &["line 2"]);
    // Vectors are checked on their size line, before their entries.
    let g = write(
        &c.dir,
        "g_huge.mtx",
        "%%MatrixMarket matrix coordinate real general\n2000000000 1 1\n1 1 x\n",
    );
    assert_input_error(
        &c.solve(&c.h, &g, &c.bc),
        &g,
        &["line 2", "g has 2000000000 rows, expected 4 = 2 × 2 nodes"],
    );
}

/// The bounded reader refuses a size line the other inputs contradict before it stores
/// an entry, and still accepts a valid H whose fully constrained nodes have empty rows.
#[test]
fn bounded_hessian_reader() {
    let dir = tmpdir("bounded");
    // 4 nodes in 2D; nodes 1-3 sticky with empty rows in H.
    let h = write(
        &dir,
        "H_sticky.mtx",
        "%%MatrixMarket matrix coordinate real symmetric\n8 8 2\n1 1 2\n2 2 2\n",
    );
    let ok = HessianBounds {
        max_rows: Some((8, "the 8 rows of g")),
        constrained_nodes: Some(3),
    };
    let m = mtx::read_hessian_bounded(&h, 2, &ok).unwrap();
    assert_eq!((m.n, m.get(0, 0), m.get(7, 7)), (4, 2.0, 0.0));
    // One constraint fewer and node 3 would have a free direction and no entry.
    let few = HessianBounds {
        constrained_nodes: Some(1),
        ..ok
    };
    let e = mtx::read_hessian_bounded(&h, 2, &few)
        .unwrap_err()
        .to_string();
    assert_eq!(
        e,
        format!("{h}: line 2: H declares 8 rows (4 nodes) but stores only 2 entries and the constraints fix at most 1 nodes; every node that is not fully constrained needs an entry in its diagonal block")
    );
    // More rows than g declares (g's header read ahead of its entries).
    let g = write(
        &dir,
        "g.mtx",
        "%%MatrixMarket matrix array real general\n% a comment\n6 1\n0\n0\n0\n0\n0\n0\n",
    );
    let gh = mtx::read_header(&g).unwrap();
    assert_eq!((gh.vector_len(), gh.size_line), (Some(6), 3));
    let what = format!("the 6 rows of g ({g})");
    let by_g = HessianBounds {
        max_rows: Some((6, &what)),
        constrained_nodes: None,
    };
    let e = mtx::read_hessian_bounded(&h, 2, &by_g)
        .unwrap_err()
        .to_string();
    assert_eq!(
        e,
        format!("{h}: line 2: H declares 8 rows, more than the 6 rows of g ({g})")
    );
    // The amplification case: 20,000 stored diagonal entries, 1.28M declared rows (the
    // legacy ratio of 64 rows per entry lets it through); with the constraints known it
    // fails on the size line, before anything is stored.
    let mut text =
        String::from("%%MatrixMarket matrix coordinate real symmetric\n1280000 1280000 20000\n");
    for k in 1..=20000 {
        text.push_str(&format!("{k} {k} 1\n"));
    }
    let amp = write(&dir, "H_amp.mtx", &text);
    let e = mtx::read_hessian_bounded(
        &amp,
        2,
        &HessianBounds {
            max_rows: None,
            constrained_nodes: Some(10),
        },
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("line 2: H declares 1280000 rows (640000 nodes) but stores only 20000 entries"),
        "{e}"
    );
    // A machine cannot hold more rows than its memory at 64 bytes a row.
    assert_eq!(mtx::max_rows_for_memory(64 << 30), 1 << 30);
    assert_eq!(mtx::max_rows_for_memory(u64::MAX), mtx::MAX_DIMENSION);
    std::fs::remove_dir_all(&dir).ok();
}

// 4. A UTF-8 byte-order mark is skipped.

#[test]
fn byte_order_marks_are_skipped() {
    let c = case("bom");
    let h = write(&c.dir, "H_bom.mtx", &format!("\u{feff}{H}"));
    let g = write(&c.dir, "g_bom.mtx", &format!("\u{feff}{G}"));
    let bc = write(&c.dir, "bc_bom.json", &format!("\u{feff}{BC}"));
    assert_dx(&c, &c.solve(&h, &g, &bc));
    let b = write(&c.dir, "B_bom.mtx", &format!("\u{feff}{B}"));
    let p = write(&c.dir, "p_bom.mtx", &format!("\u{feff}{P}"));
    assert_dx(&c, &c.solve_b(&b, &p));
    // Only one mark, only at the start.
    let h2 = write(&c.dir, "H_bom2.mtx", &format!("\u{feff}\u{feff}{H}"));
    assert_input_error(&c.solve(&h2, &c.g, &c.bc), &h2, &["line 1"]);
}

// 6. Devices, non-text and oversized files.

#[test]
fn devices_and_non_text_files() {
    let c = case("dev");
    if Path::new("/dev/zero").exists() {
        for o in [
            c.solve("/dev/zero", &c.g, &c.bc),
            c.solve(&c.h, "/dev/zero", &c.bc),
            c.solve(&c.h, &c.g, "/dev/zero"),
        ] {
            assert_input_error(&o, "/dev/zero", &["byte 0", "NUL", "not a text file"]);
        }
    }
    let bin = c.dir.join("bin.mtx");
    std::fs::write(
        &bin,
        b"%%MatrixMarket matrix coordinate real general\n\x00\x01",
    )
    .unwrap();
    let bin = bin.to_str().unwrap();
    assert_input_error(&c.solve(bin, &c.g, &c.bc), bin, &["byte 46", "NUL"]);
    let latin = c.dir.join("latin1.json");
    std::fs::write(&latin, b"{\"dim\": 2,\n \"constraints\": [], \"\xe9\": 1}").unwrap();
    let latin = latin.to_str().unwrap();
    assert_input_error(
        &c.solve(&c.h, &c.g, latin),
        latin,
        &["line 2", "not UTF-8 text (invalid byte 0xe9 at byte 32)"],
    );
}

#[test]
fn oversized_files_are_refused_unread() {
    let c = case("big");
    let p = c.dir.join("H_sparse.mtx");
    // A sparse file: its size costs no disk. Skip where the file system cannot.
    let f = std::fs::File::create(&p).unwrap();
    if f.set_len(17 << 30).is_err() {
        common::skip("SKIP: cannot create a sparse 17 GiB file here");
        return;
    }
    drop(f);
    let h = p.to_str().unwrap();
    assert_input_error(
        &c.solve(h, &c.g, &c.bc),
        h,
        &[
            "the file is 17.0 GiB, more than the",
            "limit for input files",
        ],
    );
    std::fs::remove_file(&p).ok();
}

// 7. Repeated JSON keys.

#[test]
fn repeated_json_keys() {
    let c = case("dupkey");
    let cases = [
        (r#"{"dim": 3, "dim": 2, "constraints": []}"#, "dim"),
        (
            r#"{"dim": 2, "constraints": [{"node": 1, "kind": "sticky"}, {"node": 0, "node": 1, "kind": "sticky"}]}"#,
            "constraints[1].node",
        ),
        (
            r#"{"dim": 2, "constraints": [{"node": 0, "kind": "rows", "rows": [[1, 0]], "values": [0], "values": [1]}]}"#,
            "constraints[0].values",
        ),
    ];
    for (json, path) in cases {
        let bc = write(&c.dir, "bc_dup.json", json);
        assert_input_error(
            &c.solve(&c.h, &c.g, &bc),
            &bc,
            &[&format!(": {path}: duplicate key")],
        );
    }
}

// 5 (for our own messages): text from the file is quoted on one short line.

#[test]
fn quoted_file_text_stays_one_short_line() {
    let c = case("quote");
    let junk = format!("1 2\t{}\x1b[31m 4", "9".repeat(5000));
    let h = write(
        &c.dir,
        "H_junk.mtx",
        &format!("%%MatrixMarket matrix coordinate real general\n4 4 1\n{junk}\n"),
    );
    let e = assert_input_error(
        &c.solve(&h, &c.g, &c.bc),
        &h,
        &["line 3", "malformed entry"],
    );
    assert!(
        e.len() < 400 && !e.contains('\x1b') && !e.contains('\t'),
        "{e}"
    );
    let bc = write(
        &c.dir,
        "bc_key.json",
        &format!(
            r#"{{"dim": 2, "constraints": [{{"node": 1, "kind": "sticky", "a\nb\u0007{}": 1}}]}}"#,
            "k".repeat(3000)
        ),
    );
    let e = assert_input_error(
        &c.solve(&c.h, &c.g, &bc),
        &bc,
        &["unknown key for kind sticky"],
    );
    assert!(e.len() < 400 && !e.contains('\x07'), "{e}");
    let bc = write(
        &c.dir,
        "bc_kind.json",
        &format!(
            r#"{{"dim": 2, "constraints": [{{"node": 1, "kind": {{"x": "{}"}}}}]}}"#,
            "y".repeat(3000)
        ),
    );
    let e = assert_input_error(&c.solve(&c.h, &c.g, &bc), &bc, &["constraints[0].kind"]);
    assert!(e.len() < 400, "{e}");
}

/// g given as a named pipe: the look-ahead at g's size line must not open it (a writer
/// whose reader went away dies, and the full read then blocks forever).
#[cfg(unix)]
#[test]
fn gradient_through_a_named_pipe() {
    let c = case("fifo");
    let fifo = c.dir.join("g.fifo");
    let made = Command::new("mkfifo").arg(&fifo).status();
    if !made.is_ok_and(|s| s.success()) {
        common::skip("SKIP: mkfifo is not available");
        return;
    }
    let fifo_s = fifo.to_str().unwrap().to_string();
    let writer = std::thread::spawn(move || std::fs::write(&fifo_s, G));
    let o = c.solve(&c.h, fifo.to_str().unwrap(), &c.bc);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    writer
        .join()
        .unwrap()
        .expect("the writer got its data read");
    assert_dx(&c, &o);
}
