//! The command line, end to end through the built binary: bad input exits 2 with one
//! stderr line naming the file and the entry; an indefinite H exits 1; the seed
//! examples and generated systems give the right answers through the files.

use std::path::{Path, PathBuf};
use std::process::Output;

mod common;
use common::cli::{run, stderr, tmpdir, write};

/// Reads a Matrix Market array vector written by the CLI.
fn read_vec(path: &str) -> Vec<f64> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines().filter(|l| !l.starts_with('%'));
    let n: usize = lines
        .next()
        .unwrap()
        .split_whitespace()
        .next()
        .unwrap()
        .parse()
        .unwrap();
    let v: Vec<f64> = lines.map(|l| l.trim().parse().unwrap()).collect();
    assert_eq!(v.len(), n);
    v
}

/// Dense symmetric H as a general coordinate file.
fn h_general(d: &[&[f64]]) -> String {
    let mut e = Vec::new();
    for (r, row) in d.iter().enumerate() {
        for (c, &v) in row.iter().enumerate() {
            if v != 0.0 {
                e.push(format!("{} {} {v}", r + 1, c + 1));
            }
        }
    }
    format!(
        "%%MatrixMarket matrix coordinate real general\n{} {} {}\n{}\n",
        d.len(),
        d.len(),
        e.len(),
        e.join("\n")
    )
}

fn g_array(v: &[f64]) -> String {
    let body: Vec<String> = v.iter().map(|x| x.to_string()).collect();
    format!(
        "%%MatrixMarket matrix array real general\n{} 1\n{}\n",
        v.len(),
        body.join("\n")
    )
}

/// The 2D two-node spring of the worked examples (docs/method.md): [[2I, −I], [−I, 2I]].
const SPRING: [&[f64]; 4] = [
    &[2.0, 0.0, -1.0, 0.0],
    &[0.0, 2.0, 0.0, -1.0],
    &[-1.0, 0.0, 2.0, 0.0],
    &[0.0, -1.0, 0.0, 2.0],
];

struct Case {
    dir: PathBuf,
    h: String,
    g: String,
    bc: String,
}

/// A valid 2D two-node case whose files the bad-input tests then spoil one at a time.
fn case(name: &str) -> Case {
    let dir = tmpdir(name);
    let h = write(&dir, "H.mtx", &h_general(&SPRING));
    let g = write(&dir, "g.mtx", &g_array(&[0.0, 0.0, 0.0, 0.0]));
    let bc = write(
        &dir,
        "bc.json",
        r#"{"dim": 2, "constraints": [{"node": 1, "kind": "sticky", "displacement": [1, 2]}]}"#,
    );
    Case { dir, h, g, bc }
}

impl Case {
    /// `solve` with another H file.
    fn solve_with_h(&self, h: &str) -> Output {
        let out = self.dir.join("dx.mtx");
        run(&[
            "solve",
            "--hessian",
            h,
            "--gradient",
            &self.g,
            "--constraints",
            &self.bc,
            "--out",
            out.to_str().unwrap(),
        ])
    }

    fn solve(&self, extra: &[&str]) -> Output {
        let out = self.dir.join("dx.mtx");
        let mut a = vec![
            "solve",
            "--hessian",
            &self.h,
            "--gradient",
            &self.g,
            "--out",
            out.to_str().unwrap(),
        ];
        if !extra.contains(&"--constraint-matrix") {
            a.extend(["--constraints", &self.bc]);
        }
        a.extend_from_slice(extra);
        run(&a)
    }
}

/// Exit code 2, exactly one stderr line, naming the file and containing every `want`.
fn assert_input_error(o: &Output, file: &str, want: &[&str]) {
    let e = stderr(o);
    assert_eq!(o.status.code(), Some(2), "stderr: {e}");
    assert_eq!(e.lines().count(), 1, "not one line: {e:?}");
    assert!(e.starts_with("error: "), "{e}");
    assert!(e.contains(file), "file {file} not named: {e}");
    for w in want {
        assert!(e.contains(w), "missing {w:?} in: {e}");
    }
    assert!(!e.contains("panicked") && !e.contains("backtrace"), "{e}");
}

fn bad_bc(name: &str, json: &str, want: &[&str]) {
    let c = case(name);
    let bc = write(&c.dir, "bc.json", json);
    assert_input_error(&c.solve(&[]), &bc, want);
}

#[test]
fn zero_normal() {
    bad_bc(
        "zero-normal",
        r#"{"dim": 2, "constraints": [{"node": 0, "kind": "plane", "normal": [0, 0]}]}"#,
        &["constraints[0].normal", "zero"],
    );
}

#[test]
fn non_finite_normal() {
    bad_bc(
        "inf-normal",
        r#"{"dim": 2, "constraints": [{"node": 0, "kind": "plane", "normal": [1e999, 1]}]}"#,
        &["constraints[0].normal[0]", "not a finite number"],
    );
}

#[test]
fn nan_in_h() {
    let c = case("nan-h");
    let h = write(
        &c.dir,
        "H.mtx",
        "%%MatrixMarket matrix coordinate real symmetric\n4 4 4\n1 1 2\n2 2 NaN\n3 3 2\n4 4 2\n",
    );
    assert_input_error(&c.solve(&[]), &h, &["entry (2, 2)", "NaN", "not finite"]);
}

#[test]
fn inf_in_g() {
    let c = case("inf-g");
    let g = write(
        &c.dir,
        "g.mtx",
        "%%MatrixMarket matrix array real general\n4 1\n0\n0\ninf\n0\n",
    );
    assert_input_error(&c.solve(&[]), &g, &["entry (3, 1)", "not finite"]);
}

#[test]
fn node_out_of_range() {
    bad_bc(
        "node-range",
        r#"{"dim": 2, "constraints": [{"node": 0, "kind": "sticky"}, {"node": 2, "kind": "sticky"}]}"#,
        &["constraints[1]", "node 2 is out of range"],
    );
}

#[test]
fn wrong_g_length() {
    let c = case("g-len");
    let g = write(&c.dir, "g.mtx", &g_array(&[0.0; 5]));
    assert_input_error(
        &c.solve(&[]),
        &g,
        &["line 2", "g has 5 rows, expected 4 = 2 × 2 nodes"],
    );
}

#[test]
fn direction_of_wrong_dimension() {
    bad_bc(
        "dir-dim",
        r#"{"dim": 2, "constraints": [{"node": 0, "kind": "line", "direction": [1, 0, 0]}]}"#,
        &["constraints[0].direction", "has 3 components, expected 2"],
    );
}

#[test]
fn unknown_kind() {
    bad_bc(
        "kind",
        r#"{"dim": 2, "constraints": [{"node": 0, "kind": "sticky"}, {"node": 1, "kind": "hinge"}]}"#,
        &["constraints[1].kind", "unknown kind 'hinge'"],
    );
}

#[test]
fn unknown_key() {
    bad_bc(
        "key",
        r#"{"dim": 2, "constraints": [{"node": 0, "kind": "plane", "normal": [1, 0], "offest": 1}]}"#,
        &["constraints[0].offest", "unknown key"],
    );
}

#[test]
fn malformed_json() {
    bad_bc(
        "json",
        "{\"dim\": 2, \"constraints\": [\n  {\"node\": 0 \"kind\": \"sticky\"}]}",
        &["line 2, column", "malformed JSON"],
    );
}

#[test]
fn malformed_matrix_market() {
    let c = case("mm");
    let h = write(
        &c.dir,
        "H.mtx",
        "%%MatrixMarket matrix coordinate real general\n4 4 4\n1 1 2\n2 2\n3 3 2\n4 4 2\n",
    );
    assert_input_error(&c.solve(&[]), &h, &["line 4", "malformed entry"]);
    let h = write(&c.dir, "H.mtx", "4 4 4\n1 1 2\n");
    assert_input_error(&c.solve(&[]), &h, &["line 1", "not a Matrix Market file"]);
}

#[test]
fn non_symmetric_h() {
    let c = case("nonsym");
    let mut d: Vec<Vec<f64>> = SPRING.iter().map(|r| r.to_vec()).collect();
    d[2][0] = -0.5;
    let rows: Vec<&[f64]> = d.iter().map(|r| r.as_slice()).collect();
    let h = write(&c.dir, "H.mtx", &h_general(&rows));
    assert_input_error(
        &c.solve(&[]),
        &h,
        &["entry (", "not symmetric", "relative tolerance"],
    );
}

#[test]
fn h_not_a_multiple_of_dim() {
    let c = case("h-dim");
    let h = write(
        &c.dir,
        "H.mtx",
        "%%MatrixMarket matrix coordinate real symmetric\n3 3 3\n1 1 1\n2 2 1\n3 3 1\n",
    );
    assert_input_error(
        &c.solve(&[]),
        &h,
        &["line 2", "not a multiple of the dimension 2"],
    );
}

#[test]
fn contradictory_constraints_on_a_node() {
    bad_bc(
        "contra",
        r#"{"dim": 2, "constraints": [
            {"node": 0, "kind": "plane", "normal": [1, 0], "offset": 1},
            {"node": 0, "kind": "rows", "rows": [[2, 0]], "values": [3]}]}"#,
        &["node 0 (constraints[0], constraints[1])", "contradictory"],
    );
}

#[test]
fn b_row_coupling_two_nodes() {
    let c = case("b-couple");
    let b = write(
        &c.dir,
        "B.mtx",
        "%%MatrixMarket matrix coordinate real general\n2 4 3\n1 3 1\n2 1 1\n2 4 1\n",
    );
    let o = c.solve(&["--constraint-matrix", &b, "--dim", "2"]);
    assert_input_error(&o, &b, &["row 2", "couples node 0 and node 1"]);
}

#[test]
fn dim_is_required_somewhere() {
    let c = case("no-dim");
    let bc = write(&c.dir, "bc.json", r#"{"constraints": []}"#);
    let out = c.dir.join("dx.mtx");
    let o = run(&[
        "solve",
        "--hessian",
        &c.h,
        "--gradient",
        &c.g,
        "--constraints",
        &bc,
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_input_error(&o, &bc, &["dim"]);
}

#[test]
fn f32_needs_the_gpu_solver() {
    let c = case("prec");
    assert_input_error(
        &c.solve(&["--precision", "f32"]),
        "--precision",
        &["--solver gpu"],
    );
}

#[test]
fn error_tol_needs_gpu_mixed() {
    let c = case("etol");
    for extra in [
        &["--error-tol", "1e-10"][..],
        &[
            "--solver",
            "gpu",
            "--precision",
            "f64",
            "--error-tol",
            "1e-10",
        ][..],
    ] {
        assert_input_error(&c.solve(extra), "--error-tol", &["--precision mixed"]);
    }
}

#[test]
fn missing_file() {
    let c = case("missing");
    let h = c.dir.join("nope.mtx");
    let o = run(&[
        "solve",
        "--hessian",
        h.to_str().unwrap(),
        "--gradient",
        &c.g,
        "--constraints",
        &c.bc,
        "--out",
        "x.mtx",
    ]);
    assert_input_error(&o, "nope.mtx", &["cannot read"]);
}

/// H indefinite on the free subspace: exit 1, one line, for cholesky and for cg.
#[test]
fn indefinite_h_exits_1() {
    let c = case("indef");
    // Node 1 is fixed at (1, 2) and H_00 = diag(−2, 2): with g_0 = (2, 2) the
    // eliminated right-hand side is b̂_0 = −(g_0 + H_01 Δx_1) = (−1, 0), along the
    // negative-curvature axis, so unpreconditioned CG meets pᵀĤp = −2 at once.
    write(
        &c.dir,
        "H.mtx",
        &h_general(&[
            &[-2.0, 0.0, -1.0, 0.0],
            &[0.0, 2.0, 0.0, -1.0],
            &[-1.0, 0.0, 2.0, 0.0],
            &[0.0, -1.0, 0.0, 2.0],
        ]),
    );
    write(&c.dir, "g.mtx", &g_array(&[2.0, 2.0, 0.0, 0.0]));
    for (solver, want) in [
        ("cholesky", "not positive definite"),
        ("cg", "non-positive curvature"),
    ] {
        let o = c.solve(&["--solver", solver, "--preconditioner", "none"]);
        let e = stderr(&o);
        assert_eq!(o.status.code(), Some(1), "{solver}: {e}");
        assert_eq!(e.lines().count(), 1, "{e:?}");
        assert!(e.contains(want), "{solver}: {e}");
    }
}

#[test]
fn help_lists_every_subcommand() {
    let o = run(&["--help"]);
    let help = String::from_utf8_lossy(&o.stdout);
    for sub in [
        "solve", "generate", "info", "run", "bench", "export", "recover",
    ] {
        assert!(help.contains(sub), "{help}");
    }
    // info: 0 with an adapter, else 1 with one line.
    let o = run(&["info"]);
    let one_line_error = o.status.code() == Some(1) && stderr(&o).lines().count() == 1;
    assert!(
        o.status.code() == Some(0) || one_line_error,
        "{}",
        stderr(&o)
    );
    // Usage errors: exit 2, one line like every other error.
    let o = run(&["solve", "--bogus"]);
    assert_eq!(o.status.code(), Some(2));
    assert_eq!(stderr(&o).lines().count(), 1, "{}", stderr(&o));
    assert!(stderr(&o).contains("--bogus"));
}

/// Worked example 1 of docs/method.md through the CLI: node 1 fixed at (1, 2) (sticky
/// with a displacement from the origin), H = [[2I, −I], [−I, 2I]], g = 0. The free node
/// minimizes |Δx_0|² − Δx_0·Δx_1, so Δx_0 = (0.5, 1); f_0 = 0, f_1 = −(−Δx_0 + 2Δx_1)
/// = (−1.5, −3). The same through B = [0 0 1 0; 0 0 0 1], p = (1, 2).
#[test]
fn worked_example_fixed_node() {
    let c = case("worked1");
    let want = [0.5, 1.0, 1.0, 2.0];
    let want_f = [0.0, 0.0, -1.5, -3.0];
    let b = write(
        &c.dir,
        "B.mtx",
        "%%MatrixMarket matrix coordinate real general\n2 4 2\n1 3 1\n2 4 1\n",
    );
    let p = write(&c.dir, "p.mtx", &g_array(&[1.0, 2.0]));
    let f = c.dir.join("f.mtx");
    let f = f.to_str().unwrap();
    for solver in ["cholesky", "cg"] {
        for form in [
            vec![],
            vec![
                "--constraint-matrix",
                &b,
                "--constraint-values",
                &p,
                "--dim",
                "2",
            ],
        ] {
            let mut a = vec![
                "--solver",
                solver,
                "--tol",
                "1e-14",
                "--reactions",
                f,
                "--quiet",
            ];
            a.extend(form.iter());
            let o = c.solve(&a);
            assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
            assert!(o.stderr.is_empty(), "--quiet: {}", stderr(&o));
            let dx = read_vec(c.dir.join("dx.mtx").to_str().unwrap());
            let fv = read_vec(f);
            for k in 0..4 {
                assert!(
                    (dx[k] - want[k]).abs() < 1e-14,
                    "{solver} dx[{k}] = {}",
                    dx[k]
                );
                assert!(
                    (fv[k] - want_f[k]).abs() < 1e-14,
                    "{solver} f[{k}] = {}",
                    fv[k]
                );
            }
        }
    }
}

/// Worked example 2 of docs/method.md through the CLI: node 0 on the line 2x + 3y = 4
/// (a plane with normal [2, 3], offset 4), H = I, g = (1, 0, 0, 0). Δx_0 = −g_0 +
/// μ(2, 3) with 2(−1 + 2μ) + 9μ = 4, μ = 6/13: Δx_0 = (−1/13, 18/13), Δx_1 = 0; the
/// reaction f_0 = −(Δx_0 + g_0) = −(6/13)(2, 3) is along the normal.
#[test]
fn worked_example_node_on_a_line() {
    let c = case("worked2");
    let i4: [&[f64]; 4] = [
        &[1.0, 0.0, 0.0, 0.0],
        &[0.0, 1.0, 0.0, 0.0],
        &[0.0, 0.0, 1.0, 0.0],
        &[0.0, 0.0, 0.0, 1.0],
    ];
    write(&c.dir, "H.mtx", &h_general(&i4));
    write(&c.dir, "g.mtx", &g_array(&[1.0, 0.0, 0.0, 0.0]));
    write(
        &c.dir,
        "bc.json",
        r#"{"dim": 2, "constraints": [{"node": 0, "kind": "plane", "normal": [2, 3], "offset": 4}]}"#,
    );
    let f = c.dir.join("f.mtx");
    let rep = c.dir.join("report.json");
    let o = c.solve(&[
        "--reactions",
        f.to_str().unwrap(),
        "--report",
        rep.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    // The human summary: one line on stderr.
    assert_eq!(stderr(&o).lines().count(), 1, "{}", stderr(&o));
    let dx = read_vec(c.dir.join("dx.mtx").to_str().unwrap());
    let fv = read_vec(f.to_str().unwrap());
    let want = [-1.0 / 13.0, 18.0 / 13.0, 0.0, 0.0];
    let want_f = [-12.0 / 13.0, -18.0 / 13.0, 0.0, 0.0];
    for k in 0..4 {
        assert!((dx[k] - want[k]).abs() < 1e-15, "dx[{k}] = {}", dx[k]);
        assert!((fv[k] - want_f[k]).abs() < 1e-15, "f[{k}] = {}", fv[k]);
    }
    assert!((2.0 * dx[0] + 3.0 * dx[1] - 4.0).abs() < 1e-14);
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&rep).unwrap()).unwrap();
    assert_eq!(r["free_dofs"], 3);
    assert_eq!(r["constrained_dofs"], 1);
    assert_eq!(r["rotated_nodes"], 1);
}

fn generate(dir: &Path, dim: &str, nodes: &str, mix: &str) {
    let o = run(&[
        "generate",
        "--dim",
        dim,
        "--nodes",
        nodes,
        "--seed",
        "3",
        "--mix",
        mix,
        "--matrix-form",
        "--out-dir",
        dir.to_str().unwrap(),
        "--quiet",
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
}

/// A generated system through cholesky and cg, per-node JSON and global B/p: all four
/// Δx agree to 1e-9 relative, and the report holds its fields.
#[test]
fn generated_system_all_solvers_and_forms_agree() {
    for (dim, nodes, mix) in [("3", "300", "random"), ("2", "200", "realistic")] {
        let dir = tmpdir("gen");
        generate(&dir, dim, nodes, mix);
        let s = |n: &str| dir.join(n).to_str().unwrap().to_string();
        let mut results = Vec::new();
        for solver in ["cholesky", "cg"] {
            for form in ["json", "matrix"] {
                let out = s(&format!("dx-{solver}-{form}.mtx"));
                let rep = s(&format!("report-{solver}-{form}.json"));
                let (h, g, bc, b, p) =
                    (s("H.mtx"), s("g.mtx"), s("bc.json"), s("B.mtx"), s("p.mtx"));
                let mut a = vec![
                    "solve",
                    "--hessian",
                    &h,
                    "--gradient",
                    &g,
                    "--solver",
                    solver,
                    "--tol",
                    "1e-13",
                    "--max-iters",
                    "100000",
                    "--out",
                    &out,
                    "--report",
                    &rep,
                    "--quiet",
                ];
                if form == "json" {
                    a.extend(["--constraints", bc.as_str()]);
                } else {
                    a.extend([
                        "--constraint-matrix",
                        &b,
                        "--constraint-values",
                        &p,
                        "--dim",
                        dim,
                    ]);
                }
                let o = run(&a);
                assert_eq!(o.status.code(), Some(0), "{solver}/{form}: {}", stderr(&o));
                let r: serde_json::Value =
                    serde_json::from_str(&std::fs::read_to_string(&rep).unwrap()).unwrap();
                for key in [
                    "solver",
                    "precision",
                    "adapter",
                    "iterations",
                    "relative_residual",
                    "seconds",
                    "free_dofs",
                    "constrained_dofs",
                    "nodes",
                    "dim",
                    "rotated_nodes",
                ] {
                    assert!(r.get(key).is_some(), "report lacks {key}: {r}");
                }
                for key in ["read", "setup", "solve", "total"] {
                    assert!(r["seconds"][key].as_f64().unwrap() >= 0.0);
                }
                assert_eq!(r["solver"], solver);
                assert_eq!(r["precision"], "f64");
                assert!(r["relative_residual"].as_f64().unwrap() < 1e-12);
                assert!(r["constraint_violation"].as_f64().unwrap() < 1e-12, "{r}");
                if solver == "cholesky" {
                    assert!(r["cholesky"]["factor_nnz"].as_u64().unwrap() > 0);
                    assert_eq!(r["cholesky"]["reused_symbolic"], false);
                    assert!(r["seconds"]["numeric"].as_f64().is_some());
                } else {
                    assert!(r["iterations"].as_u64().unwrap() > 0);
                }
                results.push((format!("{solver}/{form}"), read_vec(&out)));
            }
        }
        let (_, base) = &results[0];
        let scale = base.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(scale > 0.0);
        for (name, v) in &results[1..] {
            let diff = v
                .iter()
                .zip(base)
                .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
            assert!(
                diff <= 1e-9 * scale,
                "{name} differs from cholesky/json by {diff:e} (scale {scale:e})"
            );
        }
        std::fs::remove_dir_all(&dir).ok();
    }
}

/// `--solver gpu` through the CLI (f64 and mixed) against cholesky. Without an adapter
/// a loud skip, unless STICKSLIP_REQUIRE_GPU=1 (CI), where it fails.
#[test]
fn gpu_solver_through_the_cli() {
    let info = run(&["info"]);
    if !String::from_utf8_lossy(&info.stdout).contains("adapter 0:") {
        assert!(
            std::env::var("STICKSLIP_REQUIRE_GPU").map_or(true, |v| v != "1"),
            "STICKSLIP_REQUIRE_GPU=1 but `stickslip info` lists no adapter"
        );
        common::skip("SKIP gpu_solver_through_the_cli: no GPU adapter");
        return;
    }
    let dir = tmpdir("gpu");
    generate(&dir, "3", "300", "random");
    let s = |n: &str| dir.join(n).to_str().unwrap().to_string();
    let (h, g, bc) = (s("H.mtx"), s("g.mtx"), s("bc.json"));
    let solve = |extra: &[&str], out: &str| {
        let mut a = vec![
            "solve",
            "--hessian",
            &h,
            "--gradient",
            &g,
            "--constraints",
            &bc,
        ];
        a.extend(["--out", out, "--quiet"]);
        a.extend_from_slice(extra);
        let o = run(&a);
        assert_eq!(o.status.code(), Some(0), "{extra:?}: {}", stderr(&o));
        read_vec(out)
    };
    let base = solve(&[], &s("dx-chol.mtx"));
    let scale = base.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    for (p, error_tol) in [("f64", None), ("mixed", None), ("mixed", Some("1e-12"))] {
        let rep = s(&format!("rep-{p}-{}.json", error_tol.is_some()));
        let mut args = vec![
            "--solver",
            "gpu",
            "--precision",
            p,
            "--tol",
            "1e-10",
            "--report",
            &rep,
        ];
        if let Some(et) = error_tol {
            args.extend(["--error-tol", et]);
        }
        let dx = solve(&args, &s(&format!("dx-{p}.mtx")));
        let diff = dx
            .iter()
            .zip(&base)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(diff <= 1e-7 * scale, "gpu {p}: differs by {diff:e}");
        let r: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&rep).unwrap()).unwrap();
        assert_eq!(r["solver"], "gpu");
        assert_eq!(r["precision"], p);
        assert!(r["adapter"].is_string() && r["gpu"].is_object(), "{r}");
        // --error-tol: the report carries the certified estimate, ≤ the request.
        let est = r["gpu"]["error_estimate"].as_f64();
        match error_tol {
            Some(et) => assert!(
                est.is_some_and(|e| e <= et.parse::<f64>().unwrap()),
                "error estimate {est:?} for --error-tol {et}"
            ),
            None => assert!(est.is_none(), "{r}"),
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

/// `export` and `recover` through the CLI: export a generated system, solve the exported
/// Ĥ y = b̂ as a plain unconstrained system (H = Ĥ, g = −b̂), recover, and compare with a
/// direct solve; then the malformed and mismatched recovery inputs exit 2 with one line.
#[test]
fn export_recover_round_trip_and_bad_recovery_inputs() {
    let dir = tmpdir("export");
    generate(&dir, "3", "300", "random");
    let s = |n: &str| dir.join(n).to_str().unwrap().to_string();
    let ex = s("ex");
    let o = run(&[
        "export",
        "--hessian",
        &s("H.mtx"),
        "--gradient",
        &s("g.mtx"),
        "--constraints",
        &s("bc.json"),
        "--out-dir",
        &ex,
        "--quiet",
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    for f in [
        "hhat.petsc",
        "hhat.petsc.info",
        "bhat.petsc",
        "hhat.mtx",
        "bhat.mtx",
        "layout.json",
    ] {
        assert!(dir.join("ex").join(f).exists(), "{f} missing");
    }
    // g for the unconstrained solve is −b̂.
    let bhat = read_vec(&format!("{ex}/bhat.mtx"));
    let neg: Vec<f64> = bhat.iter().map(|v| -v).collect();
    let gneg = write(&dir, "gneg.mtx", &g_array(&neg));
    let free = write(&dir, "free.json", r#"{"dim": 3, "constraints": []}"#);
    let o = run(&[
        "solve",
        "--hessian",
        &format!("{ex}/hhat.mtx"),
        "--gradient",
        &gneg,
        "--constraints",
        &free,
        "--out",
        &s("y.mtx"),
        "--quiet",
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let o = run(&[
        "recover",
        "--layout",
        &format!("{ex}/layout.json"),
        "--solution",
        &s("y.mtx"),
        "--hessian",
        &s("H.mtx"),
        "--gradient",
        &s("g.mtx"),
        "--out",
        &s("dx_rec.mtx"),
        "--reactions",
        &s("f_rec.mtx"),
        "--quiet",
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let o = run(&[
        "solve",
        "--hessian",
        &s("H.mtx"),
        "--gradient",
        &s("g.mtx"),
        "--constraints",
        &s("bc.json"),
        "--out",
        &s("dx.mtx"),
        "--reactions",
        &s("f.mtx"),
        "--quiet",
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let rel = |a: &[f64], b: &[f64]| {
        let n: f64 = a
            .iter()
            .zip(b)
            .map(|(x, y)| (x - y) * (x - y))
            .sum::<f64>()
            .sqrt();
        n / b.iter().map(|x| x * x).sum::<f64>().sqrt()
    };
    // Both are Cholesky solves of the same SPD system in f64 (condition ~1e2): 1e-12.
    assert!(rel(&read_vec(&s("dx_rec.mtx")), &read_vec(&s("dx.mtx"))) < 1e-12);
    assert!(rel(&read_vec(&s("f_rec.mtx")), &read_vec(&s("f.mtx"))) < 1e-10);

    // Wrong length.
    let short = write(&dir, "short.mtx", &g_array(&bhat[1..]));
    let o = run(&[
        "recover",
        "--layout",
        &format!("{ex}/layout.json"),
        "--solution",
        &short,
        "--hessian",
        &s("H.mtx"),
        "--gradient",
        &s("g.mtx"),
        "--out",
        &s("x.mtx"),
    ]);
    assert_input_error(&o, &short, &["rows", "expected"]);
    // A layout from another system of the same size.
    let other = tmpdir("export-other");
    let o = run(&[
        "generate",
        "--dim",
        "3",
        "--nodes",
        "300",
        "--seed",
        "4",
        "--mix",
        "random",
        "--out-dir",
        other.to_str().unwrap(),
        "--quiet",
    ]);
    assert_eq!(o.status.code(), Some(0));
    let ex2 = other.join("ex").to_str().unwrap().to_string();
    let o2 = |n: &str| other.join(n).to_str().unwrap().to_string();
    let o = run(&[
        "export",
        "--hessian",
        &o2("H.mtx"),
        "--gradient",
        &o2("g.mtx"),
        "--constraints",
        &o2("bc.json"),
        "--out-dir",
        &ex2,
        "--quiet",
        "--no-mtx",
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let o = run(&[
        "recover",
        "--layout",
        &format!("{ex2}/layout.json"),
        "--solution",
        &s("y.mtx"),
        "--hessian",
        &s("H.mtx"),
        "--gradient",
        &s("g.mtx"),
        "--out",
        &s("x.mtx"),
    ]);
    assert_input_error(&o, &format!("{ex2}/layout.json"), &["another system"]);
    // A malformed layout.
    let bad = write(
        &dir,
        "bad_layout.json",
        r#"{"format": "stickslip-eliminated-v1", "dim": 3"#,
    );
    let o = run(&[
        "recover",
        "--layout",
        &bad,
        "--solution",
        &s("y.mtx"),
        "--hessian",
        &s("H.mtx"),
        "--gradient",
        &s("g.mtx"),
        "--out",
        &s("x.mtx"),
    ]);
    assert_input_error(&o, &bad, &["line"]);
}

/// Bad scene files: exit 2 and one stderr line naming the file and the key.
#[test]
fn bad_scene_files_name_the_key() {
    let dir = tmpdir("scene");
    let base = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/default.toml"))
        .unwrap();
    for (name, from, to, want) in [
        ("poisson", "poisson = 0.35", "poisson = 0.7", "poisson"),
        ("young", "young = 2e5", "young = -1.0", "young"),
        (
            "unknown",
            "time_step = 0.01",
            "time_step = 0.01\ntimestep = 0.02",
            "timestep",
        ),
        ("kind", "kind = \"plane\"", "kind = \"hinge\"", "kind"),
        ("dt", "time_step = 0.01", "time_step = 0.0", "time_step"),
    ] {
        let text = base.replacen(from, to, 1);
        assert_ne!(text, base, "{name}: edit did not apply");
        let path = write(&dir, &format!("{name}.toml"), &text);
        let o = run(&[
            "run",
            &path,
            "--out",
            dir.join("out").to_str().unwrap(),
            "--quiet",
        ]);
        assert_input_error(&o, &path, &[want]);
    }
    let o = run(&["run", "no-such-scene", "--quiet"]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert_eq!(stderr(&o).lines().count(), 1);
}

/// Corrupt size lines and tampered layouts are input errors, never panics or aborts.
#[test]
fn corrupt_sizes_and_tampered_layouts_exit_2() {
    let c = case("sizes");
    // An H whose size line declares far more rows than it holds.
    let h = write(
        &c.dir,
        "huge.mtx",
        "%%MatrixMarket matrix coordinate real general\n18446744073709551614 18446744073709551614 0\n",
    );
    let o = c.solve_with_h(&h);
    assert_input_error(&o, &h, &["line 2"]);
    let h = write(
        &c.dir,
        "big.mtx",
        "%%MatrixMarket matrix coordinate real general\n2000000 2000000 1\n1 1 1.0\n",
    );
    let o = c.solve_with_h(&h);
    assert_input_error(&o, &h, &["line 2", "entries"]);

    // A layout with a duplicated rotated node or stray mask bits.
    let dir = tmpdir("layout");
    generate(&dir, "3", "300", "random");
    let s = |n: &str| dir.join(n).to_str().unwrap().to_string();
    let ex = s("ex");
    let o = run(&[
        "export",
        "--hessian",
        &s("H.mtx"),
        "--gradient",
        &s("g.mtx"),
        "--constraints",
        &s("bc.json"),
        "--out-dir",
        &ex,
        "--quiet",
        "--no-mtx",
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let text = std::fs::read_to_string(format!("{ex}/layout.json")).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v["mask"][0] = serde_json::json!(255);
    let bad = write(&dir, "bad_mask.json", &v.to_string());
    let y = write(&dir, "y.mtx", &g_array(&vec![0.0; 900]));
    let o = run(&[
        "recover",
        "--layout",
        &bad,
        "--solution",
        &y,
        "--hessian",
        &s("H.mtx"),
        "--gradient",
        &s("g.mtx"),
        "--out",
        &s("x.mtx"),
    ]);
    assert_input_error(&o, &bad, &["mask[0]"]);
}

#[test]
fn missing_required_option_is_named() {
    let c = case("missing-out");
    let o = run(&[
        "solve",
        "--hessian",
        &c.h,
        "--gradient",
        &c.g,
        "--constraints",
        &c.bc,
    ]);
    let e = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert_eq!(e.lines().count(), 1, "{e:?}");
    assert!(e.contains("--out"), "the missing option is not named: {e}");
}

#[test]
fn option_values_out_of_range_exit_2() {
    let c = case("ranges");
    for (extra, want) in [
        (&["--solver", "cg", "--max-iters", "0"][..], "--max-iters"),
        (&["--solver", "cg", "--tol", "10"][..], "--tol"),
        (&["--solver", "cg", "--tol", "1"][..], "--tol"),
    ] {
        assert_input_error(&c.solve(extra), "command line", &[want]);
    }
    let gen = c.dir.join("gen");
    let o = run(&[
        "generate",
        "--nodes",
        "1000000000000",
        "--out-dir",
        gen.to_str().unwrap(),
    ]);
    assert_input_error(&o, "command line", &["--nodes", "cap"]);
    assert!(!gen.exists(), "nothing is written for a rejected size");
    for args in [
        &["bench", "--sizes", "18446744073709551615", "--no-gpu"][..],
        &["bench", "--hard", "--hard-scale", "0"][..],
        &["bench", "--hard", "--hard-scale", "1000000000"][..],
    ] {
        assert_input_error(&run(args), "command line", &[args[2]]);
    }
}

/// Finite data whose solve overflows f64 (g = 1e308 everywhere, or a lift of 1e308 through
/// H·Δx_p) must fail with exit 1, not write NaN with exit 0; every solver.
#[test]
fn overflowing_data_fails_instead_of_writing_nan() {
    let c = case("overflow");
    // y = Ĥ⁻¹b̂ ≈ 1e308 / 1e-10: beyond f64.
    let soft: Vec<Vec<f64>> = SPRING
        .iter()
        .map(|r| r.iter().map(|v| v * 1e-10).collect())
        .collect();
    let soft: Vec<&[f64]> = soft.iter().map(|r| &r[..]).collect();
    let soft_h = write(&c.dir, "H_soft.mtx", &h_general(&soft));
    let big_g = write(&c.dir, "g_big.mtx", &g_array(&[1e308; 4]));
    let big_lift = write(
        &c.dir,
        "bc_big.json",
        r#"{"dim": 2, "constraints": [{"node": 1, "kind": "sticky", "displacement": [1e308, 1e308]}]}"#,
    );
    for solver in ["cholesky", "cg"] {
        for (h, g, bc) in [(&soft_h, &big_g, &c.bc), (&c.h, &c.g, &big_lift)] {
            let out = c.dir.join(format!("dx-{solver}.mtx"));
            let o = run(&[
                "solve",
                "--hessian",
                h,
                "--gradient",
                g,
                "--constraints",
                bc,
                "--solver",
                solver,
                "--out",
                out.to_str().unwrap(),
            ]);
            let e = stderr(&o);
            assert_eq!(o.status.code(), Some(1), "{solver}: {e}");
            assert_eq!(e.lines().count(), 1, "{e:?}");
            assert!(!e.contains("panicked"), "{e}");
            if let Ok(text) = std::fs::read_to_string(&out) {
                assert!(
                    !text.contains("NaN") && !text.contains("inf"),
                    "{solver} wrote {text}"
                );
            }
        }
    }
}

/// `solve --solver SOLVER` on dense H and g with no constraints (2D), the files named
/// after `name` in `dir`; returns the run and the Δx path.
fn solve_free(dir: &Path, name: &str, h: &[&[f64]], g: &[f64], solver: &str) -> (Output, PathBuf) {
    let hf = write(dir, &format!("H_{name}.mtx"), &h_general(h));
    let gf = write(dir, &format!("g_{name}.mtx"), &g_array(g));
    let bc = write(dir, "bc_free.json", r#"{"dim": 2, "constraints": []}"#);
    let out = dir.join(format!("dx-{name}-{solver}.mtx"));
    let o = run(&[
        "solve",
        "--hessian",
        &hf,
        "--gradient",
        &gf,
        "--constraints",
        &bc,
        "--solver",
        solver,
        "--out",
        out.to_str().unwrap(),
    ]);
    (o, out)
}

/// A well-conditioned system (κ ≈ 2.6) whose gradient is 1e-170, 1e-160 or 1e155: CG
/// solves it (rᵀr would under- or overflow unscaled) and agrees with Cholesky.
#[test]
fn cg_solves_well_conditioned_systems_at_any_scale_of_g() {
    let c = case("cg-scales");
    let h = [
        [3.0, -1.0, 0.0, 0.0],
        [-1.0, 3.0, -1.0, 0.0],
        [0.0, -1.0, 3.0, -1.0],
        [0.0, 0.0, -1.0, 3.0],
    ];
    let rows: Vec<&[f64]> = h.iter().map(|r| &r[..]).collect();
    for scale in [1e-170, 1e-160, 1e155] {
        let g: Vec<f64> = [1.0, -0.5, 0.25, 2.0].iter().map(|v| v * scale).collect();
        let mut dx = Vec::new();
        for solver in ["cholesky", "cg"] {
            let (o, out) = solve_free(&c.dir, &format!("tri-{scale:e}"), &rows, &g, solver);
            assert!(o.status.success(), "{solver} at {scale:e}: {}", stderr(&o));
            dx.push(read_vec(out.to_str().unwrap()));
        }
        // CG's tolerance 1e-8 on the residual, κ < 3: the error is below 3e-8.
        for (a, b) in dx[1].iter().zip(&dx[0]) {
            assert!((a - b).abs() <= 3e-8 * b.abs(), "{scale:e}: {a:e} vs {b:e}");
        }
    }
}

/// A Cholesky solve on a Ĥ singular to working precision (κ ≈ 2e15: the f64 answer is off
/// by about 10 %, its residual 3e-2) fails with exit 1 in one line and writes nothing.
#[test]
fn a_hessian_singular_to_working_precision_fails_cholesky() {
    let c = case("cholesky-inaccurate");
    let mut h = [[0.0f64; 4]; 4];
    for (i, row) in h.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    h[0][2] = 1.0 - 1e-15;
    h[2][0] = h[0][2];
    let rows: Vec<&[f64]> = h.iter().map(|r| &r[..]).collect();
    let (o, out) = solve_free(&c.dir, "ill", &rows, &[1.0, 0.3, -0.7, 0.2], "cholesky");
    let e = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert_eq!(e.lines().count(), 1, "{e:?}");
    assert!(e.contains("singular to working precision"), "{e}");
    assert!(!out.exists());
}

/// H = S T S with T tridiagonal (4, −1) and S = 2^k from 2^-480 to 2^480: the plain
/// residual cancels beyond f64 (Ĥy's terms reach 1e280 where b̂ is 1), the scaled one does
/// not, and Δx is S⁻¹z with T z = −S⁻¹g (powers of two scale exactly).
#[test]
fn cholesky_solves_a_system_whose_diagonal_spans_the_f64_range() {
    let c = case("cholesky-scaled");
    let n = 10;
    let s: Vec<f64> = (0..n)
        .map(|i| (-480.0 + 960.0 * i as f64 / (n - 1) as f64).round().exp2())
        .collect();
    let mut h = vec![vec![0.0f64; n]; n];
    for i in 0..n {
        h[i][i] = 4.0 * s[i] * s[i];
        if i + 1 < n {
            h[i][i + 1] = -s[i] * s[i + 1];
            h[i + 1][i] = h[i][i + 1];
        }
    }
    let rows: Vec<&[f64]> = h.iter().map(|r| &r[..]).collect();
    let (o, out) = solve_free(&c.dir, "scaled", &rows, &vec![1.0; n], "cholesky");
    assert!(o.status.success(), "{}", stderr(&o));
    let dx = read_vec(out.to_str().unwrap());
    // T z = −S⁻¹g by the Thomas algorithm (T is diagonally dominant: stable in f64).
    let mut diag = vec![4.0f64; n];
    let mut rhs: Vec<f64> = s.iter().map(|si| -1.0 / si).collect();
    // Sub- and super-diagonal −1: the multiplier is −1/diag[i−1].
    for i in 1..n {
        let m = -1.0 / diag[i - 1];
        diag[i] += m;
        rhs[i] -= m * rhs[i - 1];
    }
    let mut z = vec![0.0; n];
    z[n - 1] = rhs[n - 1] / diag[n - 1];
    for i in (0..n - 1).rev() {
        z[i] = (rhs[i] + z[i + 1]) / diag[i];
    }
    for i in 0..n {
        let want = z[i] / s[i];
        // Both are backward-stable solves of T to rounding: a few ε apart.
        assert!(
            (dx[i] - want).abs() <= 1e-14 * want.abs(),
            "{i}: {} vs {want}",
            dx[i]
        );
    }
}

/// A scene whose magnitudes overflow: a time step of 1e-300 (m/h² = ∞) is the scene's
/// fault (exit 2, naming time_step), and no NaN row is written to steps.csv.
#[test]
fn run_stops_on_a_non_finite_state() {
    let (scene, o) = run_rectangle_scene(
        "tiny_dt",
        "1e-300",
        "stable-neo-hookean",
        r#"kind = "sticky""#,
        LEFT_EDGE,
        &[],
    );
    assert_input_error(&o, &scene, &["time_step", "not a finite f64"]);
}

/// A scene on the 1 × 0.5 rectangle of 4 × 2 cells (L = 1.118 m) with one boundary
/// condition on the nodes of `region`, run with `args` at h = 0.01 s.
fn run_boundary_scene(
    name: &str,
    law: &str,
    boundary: &str,
    region: &str,
    args: &[&str],
) -> (String, Output) {
    run_rectangle_scene(name, "0.01", law, boundary, region, args)
}

/// [`run_boundary_scene`] with the time step `time_step`; whatever the outcome, steps.csv
/// must hold no NaN or ∞ row. Returns the scene file and the run's output.
fn run_rectangle_scene(
    name: &str,
    time_step: &str,
    law: &str,
    boundary: &str,
    region: &str,
    args: &[&str],
) -> (String, Output) {
    let dir = tmpdir(name);
    let scene = write(
        &dir,
        &format!("{name}.toml"),
        &format!(
            r#"name = "{name}"
dimension = 2
time_step = {time_step}
steps = 2
gravity = [0.0, -9.81]

[output]
vtk = false

[[bodies]]
mesh = {{ kind = "rectangle", size = [1.0, 0.5], cells = [4, 2] }}
material = {{ model = "{law}", young = 1e4, poisson = 0.3, density = 100.0 }}

[[boundary]]
{boundary}
region = {region}
"#
        ),
    );
    let out = dir.join("out");
    let mut all = vec![
        "run",
        scene.as_str(),
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ];
    all.extend_from_slice(args);
    let o = run(&all);
    if let Ok(csv) = std::fs::read_to_string(out.join("steps.csv")) {
        assert!(!csv.contains("NaN") && !csv.contains("inf"), "{csv}");
    }
    (scene, o)
}

/// The left edge x = 0.
const LEFT_EDGE: &str = "{ box = { min = [-0.001, -1.0], max = [0.001, 1.0] } }";

/// A static plane far from its nodes is refused when the scene is loaded (exit 2, one line
/// naming the condition, the node, the distance and the limit 1e-3·L), on either law and
/// before the Newton loop is chosen: `--newton gpu` says the same without a GPU.
#[test]
fn run_refuses_a_static_plane_far_from_its_nodes() {
    let plane = "kind = \"plane\"\nnormal = [1.0, 0.0]";
    for (name, law, offset, args, distance) in [
        ("plane_99m", "neo-hookean", "-99.0", &[][..], "9.900e1 m"),
        (
            "plane_99m_stable",
            "stable-neo-hookean",
            "-99.0",
            &[][..],
            "9.900e1 m",
        ),
        (
            "plane_99m_gpu",
            "neo-hookean",
            "-99.0",
            &["--newton", "gpu"][..],
            "9.900e1 m",
        ),
        (
            "plane_1e300",
            "stable-neo-hookean",
            "-1e300",
            &[][..],
            "1.000e300 m",
        ),
    ] {
        let (scene, o) = run_boundary_scene(
            name,
            law,
            &format!("{plane}\noffset = {offset}"),
            LEFT_EDGE,
            args,
        );
        assert_input_error(
            &o,
            &scene,
            &[
                "boundary[0]: node ",
                &format!("lies {distance} from"),
                "1e-3·L = 1.118e-3 m",
            ],
        );
    }
}

/// A static plane through the body: its projection puts the left edge beyond the nodes
/// of the next column, inverting elements; refused naming the element (exit 2, one line).
#[test]
fn run_refuses_a_static_plane_through_the_body() {
    for law in ["neo-hookean", "stable-neo-hookean"] {
        let (scene, o) = run_boundary_scene(
            &format!("plane_through_{law}"),
            law,
            "kind = \"plane\"\nnormal = [1.0, 0.0]\noffset = 0.6",
            LEFT_EDGE,
            &[],
        );
        assert_input_error(
            &o,
            &scene,
            &[
                "boundary[0]: projecting node ",
                "moves it by 6.000e-1 m",
                "inverts element ",
                "of bodies[0]",
            ],
        );
    }
}

/// Nodes on their static plane up to round-off run: the column x = 0.75 on the plane
/// 0.1·x = 0.075, whose offset / |normal| is 0.7499999999999999; and the left edge on a
/// plane 1e-6·L from it.
#[test]
fn run_accepts_a_static_plane_off_its_nodes_by_round_off() {
    for (name, boundary, region) in [
        (
            "plane_roundoff",
            "kind = \"plane\"\nnormal = [0.1, 0.0]\noffset = 0.075",
            "{ box = { min = [0.749, -1.0], max = [0.751, 1.0] } }",
        ),
        (
            "plane_near",
            "kind = \"plane\"\nnormal = [1.0, 0.0]\noffset = 1.1e-6",
            LEFT_EDGE,
        ),
    ] {
        let (_, o) = run_boundary_scene(name, "neo-hookean", boundary, region, &[]);
        assert_eq!(o.status.code(), Some(0), "{name}: {}", stderr(&o));
    }
}

/// A moving boundary whose target runs off at 1e300 m/s: every input is finite, but the
/// first step's energy overflows. The step fails (exit 1, one line naming step 1 and the
/// overflow) and steps.csv holds no NaN row.
#[test]
fn run_step_that_overflows_fails_cleanly() {
    for law in ["neo-hookean", "stable-neo-hookean"] {
        let (_, o) = run_boundary_scene(
            &format!("runaway_{law}"),
            law,
            "kind = \"sticky\"\nmotion = { velocity = [1e300, 0.0] }",
            LEFT_EDGE,
            &[],
        );
        let e = stderr(&o);
        assert_eq!(o.status.code(), Some(1), "{e}");
        assert_eq!(e.lines().count(), 1, "{e:?}");
        assert!(e.contains("step 1") && e.contains("overflow"), "{e}");
        assert!(!e.contains("panicked"), "{e}");
    }
}

/// A scene too large for the address space the process may use (`ulimit -v` of 1 GB;
/// `twist --size 40` has 2.6 million nodes) is refused before any of its meshes is built:
/// exit 1 (a resource limit, not bad input), one line naming the scene, the bytes and
/// the nodes, no panic or backtrace, at once.
#[cfg(target_os = "linux")]
#[test]
fn run_refuses_a_scene_too_large_for_the_address_space() {
    let dir = tmpdir("too_large");
    let out = dir.join("out");
    let start = std::time::Instant::now();
    let o = std::process::Command::new("sh")
        .arg("-c")
        .arg("ulimit -v 1000000 && exec \"$0\" run twist --size 40 --steps 1 --threads 1 --quiet --out \"$1\"")
        .arg(common::cli::BIN)
        .arg(&out)
        .output()
        .expect("run sh");
    let e = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert_eq!(e.lines().count(), 1, "not one line: {e:?}");
    assert!(
        e.starts_with("error: scene \"twist\" needs ")
            && e.contains(" bytes) for ")
            && e.contains("(2,630,961 nodes); the allocation failed"),
        "{e}"
    );
    assert!(!e.contains("panicked") && !e.contains("backtrace"), "{e}");
    assert!(start.elapsed().as_secs() < 30, "{:?}", start.elapsed());
    let _ = std::fs::remove_dir_all(&dir);
}

/// `solve --ordering`: each ordering is reported as the one that ran, with the factor's
/// structural nnz; AMD and nested dissection give the same Δx to 1e-9 relative (both
/// backward-stable factorizations of one SPD system); an unknown name exits 2.
#[test]
fn cholesky_ordering_option() {
    let dir = tmpdir("ordering");
    generate(&dir, "3", "2744", "random");
    let s = |n: &str| dir.join(n).to_str().unwrap().to_string();
    let (h, g, bc) = (s("H.mtx"), s("g.mtx"), s("bc.json"));
    let mut results = Vec::new();
    for ordering in ["amd", "nested-dissection", "auto"] {
        let (out, rep) = (
            s(&format!("dx-{ordering}.mtx")),
            s(&format!("r-{ordering}.json")),
        );
        let o = run(&[
            "solve",
            "--hessian",
            &h,
            "--gradient",
            &g,
            "--constraints",
            &bc,
            "--ordering",
            ordering,
            "--out",
            &out,
            "--report",
            &rep,
            "--quiet",
        ]);
        assert_eq!(o.status.code(), Some(0), "{ordering}: {}", stderr(&o));
        let r: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&rep).unwrap()).unwrap();
        let c = &r["cholesky"];
        let ran = c["ordering"].as_str().unwrap().to_string();
        if ordering == "auto" {
            assert!(ran == "amd" || ran == "nested-dissection", "{r}");
        } else {
            assert_eq!(ran, ordering, "{r}");
        }
        let exact = c["factor_nnz_exact"].as_u64().unwrap();
        assert!(
            exact > 0 && exact <= c["factor_nnz"].as_u64().unwrap(),
            "{r}"
        );
        assert!(c["ordering_seconds"].as_f64().unwrap() >= 0.0);
        assert!(r["relative_residual"].as_f64().unwrap() < 1e-12);
        results.push(read_vec(&out));
    }
    let scale = results[0].iter().fold(0.0f64, |m, v| m.max(v.abs()));
    for v in &results[1..] {
        let diff = v
            .iter()
            .zip(&results[0])
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(diff <= 1e-9 * scale, "differs from amd by {diff:e}");
    }
    let o = run(&[
        "solve",
        "--hessian",
        &h,
        "--gradient",
        &g,
        "--constraints",
        &bc,
        "--ordering",
        "metis",
        "--out",
        &s("dx-bad.mtx"),
    ]);
    assert_eq!(o.status.code(), Some(2));
    assert_eq!(stderr(&o).trim().lines().count(), 1, "{}", stderr(&o));
    assert!(stderr(&o).contains("--ordering"), "{}", stderr(&o));
    std::fs::remove_dir_all(&dir).ok();
}

/// Help texts are written for the terminal: no rustdoc link syntax in any command's help;
/// the numbers they state in words are the current ones.
#[test]
fn help_texts_carry_no_rustdoc_links() {
    assert_eq!(stickslip::solve::ordering::AUTO_MIN_NODES, 2_000);
    assert_eq!(stickslip::solve::coarse::AGGREGATE_NODES, 64);
    assert_eq!(stickslip::solve::coarse::MAX_AGGREGATES, 128);
    for cmd in [
        "solve", "generate", "info", "run", "bench", "export", "recover",
    ] {
        let o = run(&[cmd, "--help"]);
        assert_eq!(o.status.code(), Some(0), "{cmd} --help");
        let text = String::from_utf8_lossy(&o.stdout);
        assert!(
            !text.contains("[`") && !text.contains("`]"),
            "{cmd} --help shows link syntax:\n{text}"
        );
    }
}

/// With no adapter on the backends named, `info` and a GPU benchmark fail in one line each,
/// naming the backends tried and the environment read; nothing runs on the CPU instead.
#[test]
fn no_adapter_is_one_line_and_a_failure() {
    let out = tmpdir("no-adapter");
    let no_gpu = |args: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_stickslip"))
            .args(args)
            .env("WGPU_BACKEND", "nonsense")
            .output()
            .expect("run stickslip")
    };
    let o = no_gpu(&["info"]);
    let e = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert_eq!(e.lines().count(), 1, "{e}");
    assert!(
        e.contains("no GPU adapter") && e.contains("WGPU_BACKEND=nonsense"),
        "{e}"
    );
    assert!(e.contains("VK_ICD_FILENAMES"), "{e}");
    // A backend name that names none: the remedy is the variable, not a driver install.
    assert!(
        e.contains("set WGPU_BACKEND to vulkan") && !e.contains("install"),
        "{e}"
    );
    let dest = out.join("bench");
    let o = no_gpu(&[
        "bench",
        "--quick",
        "--sizes",
        "1000",
        "--dims",
        "2",
        "--out",
        dest.to_str().unwrap(),
    ]);
    let e = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert_eq!(e.lines().count(), 1, "{e}");
    assert!(
        e.contains("no GPU adapter") && e.contains("--no-gpu"),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&out);
}

/// `bench --out` naming an existing file is bad input (exit 2, one line naming the file),
/// checked before any benchmark runs.
#[test]
fn bench_out_naming_a_file_is_an_input_error() {
    let dir = tmpdir("bench-out-file");
    let file = write(&dir, "taken.txt", "not a folder\n");
    let o = run(&["bench", "--quick", "--no-gpu", "--out", &file]);
    common::cli::assert_input_error(&o, &file, &["--out", "is a file, not a folder"]);
    assert_eq!(
        std::fs::read_to_string(&file).expect("file"),
        "not a folder\n",
        "the file is untouched"
    );
}

/// A skipped test says so past the test harness's capture: this test runs itself in a
/// child (without --nocapture) as the probe, and the child's SKIP line must be in what it
/// printed (an `eprintln!` there would be captured and lost for a passing test).
#[test]
fn skip_lines_are_visible_without_nocapture() {
    if std::env::var_os("STICKSLIP_SKIP_PROBE").is_some() {
        common::skip("SKIP probe: shown past the capture");
        return;
    }
    let exe = std::env::current_exe().expect("this test binary");
    let o = std::process::Command::new(exe)
        .args(["--exact", "skip_lines_are_visible_without_nocapture"])
        .env("STICKSLIP_SKIP_PROBE", "1")
        .output()
        .expect("run the probe");
    let all = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(o.status.success(), "{all}");
    assert!(all.contains("1 passed"), "{all}");
    assert!(all.contains("SKIP probe: shown past the capture"), "{all}");
}

/// bench appends a record per finished solve to OUT/records.jsonl as it goes; a second
/// bench into the same folder starts the file anew instead of adding to the first's.
#[test]
fn bench_records_are_this_runs_own() {
    let dir = tmpdir("bench-records");
    let out = dir.join("b");
    let o_s = out.to_str().expect("utf-8");
    let args = [
        "bench", "--quick", "--no-gpu", "--sizes", "64", "--dims", "2", "--out", o_s, "-q",
    ];
    let lines = || {
        std::fs::read_to_string(out.join("records.jsonl"))
            .expect("records.jsonl")
            .lines()
            .inspect(|l| {
                serde_json::from_str::<serde_json::Value>(l).expect("a JSON record per line");
            })
            .count()
    };
    let o = run(&args);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let first = lines();
    assert!(first >= 2, "{first} records");
    let o = run(&args);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert_eq!(lines(), first);
}

/// The multilevel preconditioner solves the worked case on the CPU CG to the oracle's
/// Δx, and the GPU solver in f32 asked for it is refused before any work: one line, exit 2
/// (the f64 device PCG takes it: tests/gpu_multilevel.rs).
#[test]
fn multilevel_runs_on_the_cpu_cg_and_the_f32_gpu_refuses_it() {
    let c = case("multilevel");
    let o = c.solve(&["--solver", "cg", "--preconditioner", "multilevel"]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let cg = read_vec(c.dir.join("dx.mtx").to_str().unwrap());
    let o = c.solve(&["--solver", "cholesky"]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let oracle = read_vec(c.dir.join("dx.mtx").to_str().unwrap());
    // CG stops at its default relative residual; on this 2-node system it is exact to a
    // few ulps of the largest entry (2).
    for (a, b) in cg.iter().zip(&oracle) {
        assert!((a - b).abs() <= 1e-12, "{cg:?} vs {oracle:?}");
    }
    let o = c.solve(&[
        "--solver",
        "gpu",
        "--precision",
        "f32",
        "--preconditioner",
        "multilevel",
    ]);
    let e = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert_eq!(e.lines().count(), 1, "{e:?}");
    assert!(e.contains("multilevel"), "{e}");
}
