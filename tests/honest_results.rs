//! Honest results through the binary: a singular system is refused by every solver, and
//! messages name the real cause.

use std::path::Path;

mod common;
use common::cli::{run, stderr, tmpdir, write};

fn s(p: &Path) -> String {
    p.to_str().unwrap().to_string()
}

/// Does `stickslip info` list an adapter? Without one the GPU parts are skipped (loudly),
/// unless STICKSLIP_REQUIRE_GPU=1, where that fails.
fn have_gpu(test: &str) -> bool {
    let info = run(&["info"]);
    if String::from_utf8_lossy(&info.stdout).contains("adapter 0:") {
        return true;
    }
    assert!(
        std::env::var("STICKSLIP_REQUIRE_GPU").map_or(true, |v| v != "1"),
        "STICKSLIP_REQUIRE_GPU=1 but `stickslip info` lists no adapter"
    );
    common::skip(&format!("SKIP the GPU part of {test}: no GPU adapter"));
    false
}

/// A floating 2D spring chain (Laplacian ⊗ I₂, no constraints, no mass term) with a
/// consistent g = H·x: every solver exits 1 with the Cholesky-like message, and writes
/// nothing.
#[test]
fn a_floating_body_is_refused_by_every_solver() {
    let dir = tmpdir("floating");
    let n = 40;
    let mut entries = Vec::new();
    for i in 0..n - 1 {
        for a in 0..2 {
            let (p, q) = (2 * i + a + 1, 2 * (i + 1) + a + 1);
            entries.push(format!("{p} {p} 1"));
            entries.push(format!("{q} {q} 1"));
            entries.push(format!("{q} {p} -1"));
        }
    }
    // Duplicates sum (the inner nodes' diagonals get 2).
    let h = write(
        &dir,
        "H.mtx",
        &format!(
            "%%MatrixMarket matrix coordinate real symmetric\n{} {} {}\n{}\n",
            2 * n,
            2 * n,
            entries.len(),
            entries.join("\n")
        ),
    );
    // g = H x for x_i = (sin i, cos 2i): in H's range, so a CG would "converge".
    let x: Vec<f64> = (0..n)
        .flat_map(|i| [(i as f64).sin(), (2.0 * i as f64).cos()])
        .collect();
    let mut g = vec![0.0; 2 * n];
    for i in 0..n - 1 {
        for a in 0..2 {
            let (p, q) = (2 * i + a, 2 * (i + 1) + a);
            let f = x[p] - x[q];
            g[p] += f;
            g[q] -= f;
        }
    }
    let body: Vec<String> = g.iter().map(|v| format!("{v:e}")).collect();
    let g = write(
        &dir,
        "g.mtx",
        &format!(
            "%%MatrixMarket matrix array real general\n{} 1\n{}\n",
            2 * n,
            body.join("\n")
        ),
    );
    let bc = write(&dir, "bc.json", r#"{"dim": 2, "constraints": []}"#);
    let out = dir.join("dx.mtx");
    let mut cases: Vec<Vec<&str>> = vec![vec!["cholesky"], vec!["cg"]];
    if have_gpu("a_floating_body_is_refused_by_every_solver") {
        for p in ["f64", "f32", "mixed"] {
            cases.push(vec!["gpu", "--precision", p]);
        }
    }
    for solver in cases {
        let mut args = vec![
            "solve",
            "--hessian",
            &h,
            "--gradient",
            &g,
            "--constraints",
            &bc,
            "--solver",
        ];
        args.extend(&solver);
        let o_s = s(&out);
        args.extend(["--out", &o_s]);
        let o = run(&args);
        // The Vulkan loader may complain about the environment on its own lines.
        let e: String = stderr(&o)
            .lines()
            .filter(|l| !l.contains("XDG_RUNTIME_DIR"))
            .map(|l| format!("{l}\n"))
            .collect();
        assert_eq!(o.status.code(), Some(1), "{solver:?}: {e}");
        assert_eq!(e.lines().count(), 1, "{e}");
        assert!(
            e.contains("the eliminated Hessian is not positive definite on the free subspace"),
            "{solver:?}: {e}"
        );
        if solver[0] != "cholesky" {
            assert!(
                e.contains("rigid translation") && e.contains("40 free nodes connected to node 0"),
                "{e}"
            );
        }
        assert!(!out.exists(), "{solver:?} wrote a result");
    }
    // One sticky node makes it solvable by each of them.
    let bc = write(
        &dir,
        "bc1.json",
        r#"{"dim": 2, "constraints": [{"node": 7, "kind": "sticky"}]}"#,
    );
    for solver in ["cholesky", "cg"] {
        let o = run(&[
            "solve",
            "--hessian",
            &h,
            "--gradient",
            &g,
            "--constraints",
            &bc,
            "--solver",
            solver,
            "--out",
            &s(&out),
            "-q",
        ]);
        assert_eq!(o.status.code(), Some(0), "{solver}: {}", stderr(&o));
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Positions of the unit square's nodes by tag (four corners and the centre), and its
/// four triangles by tag.
const SQUARE: [(u64, [f64; 2]); 5] = [
    (1, [0.0, 0.0]),
    (2, [1.0, 0.0]),
    (3, [1.0, 1.0]),
    (4, [0.0, 1.0]),
    (5, [0.5, 0.5]),
];
const TRIANGLES: [[u64; 3]; 4] = [[1, 2, 5], [2, 3, 5], [3, 4, 5], [4, 1, 5]];

/// The square as ASCII MSH 4.1 with its nodes in `blocks` (tags, in file order).
fn square_ascii(blocks: &[&[u64]]) -> Vec<u8> {
    let pos = |t: u64| SQUARE.iter().find(|(k, _)| *k == t).unwrap().1;
    let mut s = String::from("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n");
    s += &format!("{} 5 1 5\n", blocks.len());
    for b in blocks {
        s += &format!("2 1 0 {}\n", b.len());
        for t in *b {
            s += &format!("{t}\n");
        }
        for t in *b {
            let p = pos(*t);
            s += &format!("{} {} 0\n", p[0], p[1]);
        }
    }
    s += "$EndNodes\n$Elements\n1 4 1 4\n2 1 2 4\n";
    for (k, e) in TRIANGLES.iter().enumerate() {
        s += &format!("{} {} {} {}\n", k + 1, e[0], e[1], e[2]);
    }
    s += "$EndElements\n";
    s.into_bytes()
}

/// The same as binary MSH 4.1 (little-endian, 8-byte size_t).
fn square_binary(blocks: &[&[u64]]) -> Vec<u8> {
    let pos = |t: u64| SQUARE.iter().find(|(k, _)| *k == t).unwrap().1;
    let mut b: Vec<u8> = b"$MeshFormat\n4.1 1 8\n".to_vec();
    b.extend(1i32.to_le_bytes());
    b.extend(b"\n$EndMeshFormat\n$Nodes\n");
    for v in [blocks.len() as u64, 5, 1, 5] {
        b.extend(v.to_le_bytes());
    }
    for blk in blocks {
        for v in [2i32, 1, 0] {
            b.extend(v.to_le_bytes());
        }
        b.extend((blk.len() as u64).to_le_bytes());
        for t in *blk {
            b.extend(t.to_le_bytes());
        }
        for t in *blk {
            let p = pos(*t);
            for v in [p[0], p[1], 0.0] {
                b.extend(v.to_le_bytes());
            }
        }
    }
    b.extend(b"\n$EndNodes\n$Elements\n");
    for v in [1u64, 4, 1, 4] {
        b.extend(v.to_le_bytes());
    }
    for v in [2i32, 1, 2] {
        b.extend(v.to_le_bytes());
    }
    b.extend(4u64.to_le_bytes());
    for (k, e) in TRIANGLES.iter().enumerate() {
        b.extend((k as u64 + 1).to_le_bytes());
        for t in e {
            b.extend(t.to_le_bytes());
        }
    }
    b.extend(b"\n$EndElements\n");
    b
}

/// Gmsh node tags in any order (a contiguous range, which mshio does not keep) load the
/// geometry the file describes: every node where its tag says, the square's area 1, and
/// through `run` a total mass of density × area = 100.
#[test]
fn gmsh_node_tags_out_of_file_order_keep_the_geometry() {
    let dir = tmpdir("gmsh-tags");
    let orders: [&[&[u64]]; 5] = [
        &[&[1, 2, 3, 4, 5]],
        &[&[5, 4, 3, 2, 1]],
        &[&[2, 1, 3, 4, 5]],
        &[&[4, 5], &[1, 2, 3]],
        &[&[3, 1], &[5], &[2, 4]],
    ];
    for (k, blocks) in orders.iter().enumerate() {
        for (kind, bytes) in [
            ("ascii", square_ascii(blocks)),
            ("binary", square_binary(blocks)),
        ] {
            let what = format!("{kind} {blocks:?}");
            let m = stickslip::sim::mesh::gmsh(2, &bytes).unwrap_or_else(|e| panic!("{what}: {e}"));
            assert_eq!(m.n_nodes(), 5, "{what}");
            // Exact: each triangle's area is 1/4 in binary fractions.
            let area: f64 = (0..4).map(|e| m.measure(e)).sum();
            assert_eq!(area, 1.0, "{what}");
            for e in 0..4 {
                assert_eq!(m.measure(e), 0.25, "{what}: element {e}");
            }
            // Nodes keep their $Nodes order: node k sits at the k-th listed tag's position.
            let listed: Vec<u64> = blocks.iter().flat_map(|b| b.iter().copied()).collect();
            for (k, &t) in listed.iter().enumerate() {
                let p = SQUARE.iter().find(|(tag, _)| *tag == t).unwrap().1;
                assert_eq!(
                    [m.x[2 * k], m.x[2 * k + 1]],
                    [p[0], p[1]],
                    "{what}: node {k}"
                );
            }
            // Element 1 is (1, 2, 5): its nodes sit at the tags' positions.
            let at = |i: usize| [m.x[2 * i], m.x[2 * i + 1]];
            let mut got: Vec<[f64; 2]> = m.elements[0].iter().map(|&i| at(i)).collect();
            got.sort_by(|a, b| a.partial_cmp(b).unwrap());
            assert_eq!(got, vec![[0.0, 0.0], [0.5, 0.5], [1.0, 0.0]], "{what}");
            let msh = dir.join(format!("sq{k}-{kind}.msh"));
            std::fs::write(&msh, &bytes).unwrap();
            let scene = format!(
                "dimension = 2\ntime_step = 0.01\nsteps = 1\n[output]\nvtk = false\n[[bodies]]\nmesh = {{ kind = \"gmsh\", file = \"{}\" }}\nmaterial = {{ model = \"neo-hookean\", young = 1e4, poisson = 0.3, density = 100.0 }}\n[[boundary]]\nkind = \"sticky\"\nregion = {{ nodes = [0] }}\n",
                msh.file_name().unwrap().to_str().unwrap()
            );
            let sc = dir.join(format!("sq{k}-{kind}.toml"));
            std::fs::write(&sc, scene).unwrap();
            let out = dir.join(format!("out{k}-{kind}"));
            let o = run(&["run", &s(&sc), "--out", &s(&out), "-q"]);
            assert_eq!(o.status.code(), Some(0), "{what}: {}", stderr(&o));
            let sm: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap())
                    .unwrap();
            let mass = sm["total_mass"].as_f64().unwrap();
            // Lumped masses sum the four element masses of 25 each (rounding only).
            assert!((mass - 100.0).abs() <= 1e-12 * 100.0, "{what}: mass {mass}");
        }
    }
    // A tag given twice is an error that says so.
    let e = stickslip::sim::mesh::gmsh(2, &square_ascii(&[&[1, 2, 3, 3, 5]])).unwrap_err();
    assert!(e.contains("node tag 3 is given to two nodes"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// stderr without the lines the Vulkan loader may print about the environment.
fn our_stderr(o: &std::process::Output) -> String {
    stderr(o)
        .lines()
        .filter(|l| !l.contains("XDG_RUNTIME_DIR"))
        .map(|l| format!("{l}\n"))
        .collect()
}

/// A generated 2D system in `dir/sys`: (H, g, bc) paths.
fn system(dir: &Path, seed: &str) -> (String, String, String) {
    let sys = dir.join(format!("sys{seed}"));
    let o = run(&[
        "generate",
        "--dim",
        "2",
        "--nodes",
        "36",
        "--seed",
        seed,
        "-q",
        "--out-dir",
        &s(&sys),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let p = |n: &str| s(&sys.join(n));
    (p("H.mtx"), p("g.mtx"), p("bc.json"))
}

/// WGPU_ADAPTER_NAME that names no adapter: exit 2 with the adapters listed, for `solve`
/// and for a `run` with the GPU solver or the device Newton loop; never a silent run on
/// another adapter.
#[test]
fn an_adapter_name_that_matches_nothing_is_refused() {
    let dir = tmpdir("adapter-name");
    let (h, g, bc) = system(&dir, "1");
    let out = s(&dir.join("dx.mtx"));
    let o = std::process::Command::new(common::cli::BIN)
        .args([
            "solve",
            "--hessian",
            &h,
            "--gradient",
            &g,
            "--constraints",
            &bc,
            "--solver",
            "gpu",
            "--out",
            &out,
        ])
        .env("WGPU_ADAPTER_NAME", "no-such-adapter-anywhere")
        .output()
        .unwrap();
    let e = our_stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert_eq!(e.lines().count(), 1, "{e}");
    assert!(
        e.starts_with("error: WGPU_ADAPTER_NAME: 'no-such-adapter-anywhere' names no GPU adapter; the adapters are: "),
        "{e}"
    );
    assert!(!Path::new(&out).exists());
    // `run` with the GPU solver, and with the device Newton loop (an input error, not a
    // failed step 0).
    for (option, folder) in [("--solver", "run"), ("--newton", "run-device")] {
        let o = std::process::Command::new(common::cli::BIN)
            .args([
                "run", "hanging", option, "gpu", "--steps", "1", "-q", "--out",
            ])
            .arg(dir.join(folder))
            .env("WGPU_ADAPTER_NAME", "no-such-adapter-anywhere")
            .output()
            .unwrap();
        let e = our_stderr(&o);
        assert_eq!(o.status.code(), Some(2), "{option}: {e}");
        assert_eq!(e.lines().count(), 1, "{option}: {e}");
        assert!(e.starts_with("error: WGPU_ADAPTER_NAME: "), "{option}: {e}");
        assert!(e.contains("names no GPU adapter"), "{option}: {e}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// `recover` refuses a y that does not solve the exported system (zero, another
/// system's) with exit 1 and writes nothing; the exact solution passes; a layout whose
/// lift, masks or rotations were changed after export is refused (exit 2).
#[test]
fn recover_checks_the_solution_and_the_layout() {
    use stickslip::core::elimination::{ConstrainedDiagonal, Eliminated};
    let dir = tmpdir("recover");
    let (h, g, bc) = system(&dir, "1");
    let ex = dir.join("ex");
    let o = run(&[
        "export",
        "--hessian",
        &h,
        "--gradient",
        &g,
        "--constraints",
        &bc,
        "-q",
        "--out-dir",
        &s(&ex),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let layout = s(&ex.join("layout.json"));
    // The exact y, solved here through the library from the same files.
    let hm = stickslip::io::mtx::read_hessian(&h, 2).unwrap();
    let gv = stickslip::io::mtx::read_vector(&g, "g", None).unwrap();
    let cs = stickslip::io::bcjson::read(&bc, Some(2)).unwrap();
    let frames = stickslip::core::constraints::Frames::build(2, hm.n, &cs.constraints).unwrap();
    let e = Eliminated::new(&hm, &gv, &frames, ConstrainedDiagonal::Identity);
    let (y, _) = stickslip::solve::oracle::solve(&e).unwrap();
    let write_y = |name: &str, v: &[f64]| {
        let p = dir.join(name);
        stickslip::io::mtx::write_vector(&p, v, "y").unwrap();
        s(&p)
    };
    let exact = write_y("y.mtx", &y);
    let zero = write_y("y0.mtx", &vec![0.0; y.len()]);
    // Another system of the same size, solved exactly: the wrong y for this one.
    let (h2, g2, bc2) = system(&dir, "2");
    let hm2 = stickslip::io::mtx::read_hessian(&h2, 2).unwrap();
    let gv2 = stickslip::io::mtx::read_vector(&g2, "g", None).unwrap();
    let cs2 = stickslip::io::bcjson::read(&bc2, Some(2)).unwrap();
    let f2 = stickslip::core::constraints::Frames::build(2, hm2.n, &cs2.constraints).unwrap();
    let e2 = Eliminated::new(&hm2, &gv2, &f2, ConstrainedDiagonal::Identity);
    let (y2, _) = stickslip::solve::oracle::solve(&e2).unwrap();
    let other = write_y("y2.mtx", &y2);
    let dx = dir.join("dx.mtx");
    let recover = |layout: &str, y: &str, extra: &[&str]| {
        let mut a = vec![
            "recover",
            "--layout",
            layout,
            "--solution",
            y,
            "--hessian",
            &h,
            "--gradient",
            &g,
            "-q",
        ];
        let dxs = s(&dx);
        a.extend(["--out", &dxs]);
        a.extend_from_slice(extra);
        run(&a)
    };
    for y in [&zero, &other] {
        let o = recover(&layout, y, &[]);
        let e = stderr(&o);
        assert_eq!(o.status.code(), Some(1), "{e}");
        assert_eq!(e.lines().count(), 1, "{e}");
        assert!(
            e.contains("y does not solve the exported system") && e.contains("--max-residual"),
            "{e}"
        );
        assert!(!dx.exists());
    }
    let o = recover(&layout, &exact, &[]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!(dx.exists());
    // A y off by 1e-4 of its size: refused by default, accepted under a looser bound.
    let norm = y.iter().map(|v| v * v).sum::<f64>().sqrt();
    let off: Vec<f64> = y
        .iter()
        .enumerate()
        .map(|(k, v)| {
            v + 1e-4 * norm * if k % 2 == 0 { 1.0 } else { -1.0 } / (y.len() as f64).sqrt()
        })
        .collect();
    let off = write_y("y-off.mtx", &off);
    std::fs::remove_file(&dx).unwrap();
    let o = recover(&layout, &off, &[]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(!dx.exists());
    let o = recover(&layout, &off, &["--max-residual", "0.1"]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    // Layouts changed after export.
    let text = std::fs::read_to_string(&layout).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    let mut cases = Vec::new();
    if v["lift"].is_array() {
        let mut t = v.clone();
        let x = t["lift"][0].as_f64().unwrap();
        t["lift"][0] = serde_json::json!(x + 1e-3);
        cases.push(("lift", t));
    }
    let mut t = v.clone();
    let k = (0..t["mask"].as_array().unwrap().len())
        .find(|&k| t["mask"][k] == 0)
        .unwrap();
    t["mask"][k] = serde_json::json!(3);
    t["free_dofs"] = serde_json::json!(t["free_dofs"].as_u64().unwrap() - 2);
    t["constrained_dofs"] = serde_json::json!(t["constrained_dofs"].as_u64().unwrap() + 2);
    cases.push(("mask", t));
    if v["rotations"].as_array().is_some_and(|r| r.len() >= 4) {
        // A 2D rotation turned by a further angle stays orthonormal.
        let mut t = v.clone();
        let r: Vec<f64> = (0..4)
            .map(|i| t["rotations"][i].as_f64().unwrap())
            .collect();
        let (c, sn) = (0.1f64.cos(), 0.1f64.sin());
        let turned = [
            c * r[0] - sn * r[2],
            c * r[1] - sn * r[3],
            sn * r[0] + c * r[2],
            sn * r[1] + c * r[3],
        ];
        for (i, x) in turned.iter().enumerate() {
            t["rotations"][i] = serde_json::json!(x);
        }
        cases.push(("rotations", t));
    }
    assert!(
        cases.len() >= 2,
        "the generated system has a lift or rotations"
    );
    for (what, t) in cases {
        let p = dir.join(format!("layout-{what}.json"));
        std::fs::write(&p, serde_json::to_string(&t).unwrap()).unwrap();
        let o = recover(&s(&p), &exact, &[]);
        common::cli::assert_input_error(
            &o,
            &s(&p),
            &["frames_fingerprint", "changed after export"],
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Magnitudes that pass one by one but overflow together, and a scene path that is a
/// folder: exit 2 at validation, naming the key that causes it.
#[test]
fn scene_faults_name_the_real_cause() {
    let dir = tmpdir("causes");
    let scene = |name: &str, text: String| {
        let p = dir.join(format!("{name}.toml"));
        std::fs::write(&p, text).unwrap();
        s(&p)
    };
    let builtin = |n: &str| stickslip::sim::scene::builtin(n).unwrap().to_string();
    let cases = [
        (
            scene(
                "dt",
                builtin("drop").replace("time_step = 0.01", "time_step = 1e152"),
            ),
            vec!["time_step", "smaller time step"],
        ),
        (
            scene(
                "dhat",
                builtin("drop").replace(
                    "normal = [0.0, 1.0, 0.0]",
                    "normal = [0.0, 1.0, 0.0]\ndhat = 1e300",
                ),
            ),
            vec!["obstacle[0].dhat", "activation distance"],
        ),
        (
            scene(
                "thin",
                builtin("drop").replace("size = [0.2, 0.2, 0.2]", "size = [0.2, 0.2, 1e-300]"),
            ),
            vec!["bodies[0].mesh", "degenerate at rest"],
        ),
    ];
    for (path, want) in &cases {
        let o = run(&["run", path, "--out", &s(&dir.join("out")), "-q"]);
        common::cli::assert_input_error(&o, path, want);
    }
    let folder = dir.join("a-folder");
    std::fs::create_dir_all(&folder).unwrap();
    let o = run(&["run", &s(&folder), "--out", &s(&dir.join("out")), "-q"]);
    common::cli::assert_input_error(&o, &s(&folder), &["is a folder, not a scene file"]);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A 100,000-digit JSON number and a million-character TOML key: the error line echoes
/// at most 80 characters of either.
#[test]
fn error_lines_are_bounded() {
    let dir = tmpdir("bounded");
    let (h, g, _) = system(&dir, "1");
    let digits = "1".repeat(100_000);
    let bc = write(
        &dir,
        "big.json",
        &format!(
            r#"{{"dim": 2, "constraints": [{{"node": 1, "kind": "sticky", "displacement": [{digits}, 0]}}]}}"#
        ),
    );
    let o = run(&[
        "solve",
        "--hessian",
        &h,
        "--gradient",
        &g,
        "--constraints",
        &bc,
        "--out",
        &s(&dir.join("dx.mtx")),
    ]);
    let e = common::cli::assert_input_error(&o, &bc, &["…"]);
    assert!(
        e.len() < 400,
        "{} bytes: {}",
        e.len(),
        &e[..400.min(e.len())]
    );
    assert!(e.contains(&format!("{}…", "1".repeat(80))), "{e}");
    let key = "k".repeat(1_000_000);
    let sc = write(&dir, "key.toml", &format!("name = \"t\"\n{key} = 1\n"));
    let o = run(&["run", &sc, "--out", &s(&dir.join("out")), "-q"]);
    let e = common::cli::assert_input_error(&o, &sc, &["…"]);
    assert!(e.len() < 600, "{} bytes", e.len());
    let _ = std::fs::remove_dir_all(&dir);
}

/// A Matrix Market number cut short (`4.`, as a write that stopped mid-way leaves it) is
/// refused, in H and in g.
#[test]
fn a_number_cut_short_is_refused() {
    let dir = tmpdir("cut-number");
    let h = write(
        &dir,
        "H.mtx",
        "%%MatrixMarket matrix coordinate real symmetric\n6 6 6\n1 1 4\n2 2 4\n3 3 4\n4 4 4\n5 5 4\n6 6 4.",
    );
    let g = write(
        &dir,
        "g.mtx",
        "%%MatrixMarket matrix array real general\n6 1\n1\n2\n3\n4\n5\n6\n",
    );
    let bc = write(
        &dir,
        "bc.json",
        r#"{"dim": 2, "constraints": [{"node": 0, "kind": "sticky"}]}"#,
    );
    let args = |h: &str, g: &str| {
        run(&[
            "solve",
            "--hessian",
            h,
            "--gradient",
            g,
            "--constraints",
            &bc,
            "--out",
            &s(&dir.join("dx.mtx")),
        ])
    };
    common::cli::assert_input_error(
        &args(&h, &g),
        &h,
        &["line 8", "'4.' is not a complete number"],
    );
    let g2 = write(
        &dir,
        "g2.mtx",
        "%%MatrixMarket matrix array real general\n6 1\n1\n2\n3\n4\n5\n6.",
    );
    let h2 = write(
        &dir,
        "H2.mtx",
        "%%MatrixMarket matrix coordinate real symmetric\n6 6 6\n1 1 4\n2 2 4\n3 3 4\n4 4 4\n5 5 4\n6 6 4.5",
    );
    common::cli::assert_input_error(&args(&h2, &g2), &g2, &["'6.' is not a complete number"]);
    // The complete numbers solve.
    let o = args(&h2, &g);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let _ = std::fs::remove_dir_all(&dir);
}

/// Under an address-space limit (`ulimit -v`) a large input fails with one line naming
/// the file (exit 2), not an abort. The limit is the smallest that runs a tiny solve,
/// plus room for part of the large input.
#[cfg(target_os = "linux")]
#[test]
fn a_large_input_under_an_address_space_limit_is_an_input_error() {
    let dir = tmpdir("ulimit");
    let (h, g, bc) = system(&dir, "1");
    let limited = |kb: usize, args: &[&str]| {
        let mut cmd = format!("ulimit -v {kb} && exec '{}'", common::cli::BIN);
        for a in args {
            cmd.push_str(&format!(" '{a}'"));
        }
        std::process::Command::new("sh")
            .args(["-c", &cmd])
            .output()
            .unwrap()
    };
    let dx = s(&dir.join("dx.mtx"));
    let small = [
        "solve",
        "--hessian",
        &h,
        "--gradient",
        &g,
        "--constraints",
        &bc,
        "--out",
        &dx,
        "-q",
    ];
    let Some(base) = (4..=64)
        .map(|k| k * 8 * 1024)
        .find(|&kb| limited(kb, &small).status.code() == Some(0))
    else {
        panic!("a tiny solve does not run under 512 MiB of address space");
    };
    // A 3D H of 900,000 rows (about 30 MB of text, 20 MB of entries, 150 MB of blocks).
    let n = 300_000;
    let mut text = format!(
        "%%MatrixMarket matrix coordinate real symmetric\n{} {} {}\n",
        3 * n,
        3 * n,
        3 * n
    );
    for i in 1..=3 * n {
        text.push_str(&format!("{i} {i} 2.0000000000000000\n"));
    }
    let big_h = write(&dir, "bigH.mtx", &text);
    let big_g = write(
        &dir,
        "bigg.mtx",
        &format!(
            "%%MatrixMarket matrix array real general\n{} 1\n{}",
            3 * n,
            "1\n".repeat(3 * n)
        ),
    );
    let bc3 = write(
        &dir,
        "bc3.json",
        r#"{"dim": 3, "constraints": [{"node": 0, "kind": "sticky"}]}"#,
    );
    let big = [
        "solve",
        "--hessian",
        &big_h,
        "--gradient",
        &big_g,
        "--constraints",
        &bc3,
        "--out",
        &dx,
    ];
    // Room for the text but not for what is built from it, and less.
    for extra_mb in [8, 40, 80] {
        let o = limited(base + extra_mb * 1024, &big);
        let e = stderr(&o);
        assert_eq!(o.status.code(), Some(2), "+{extra_mb} MiB: {e}");
        assert!(
            e.starts_with(&format!("error: {big_h}: cannot hold"))
                && e.contains("memory allocation failed"),
            "+{extra_mb} MiB: {e}"
        );
        assert_eq!(e.lines().count(), 1, "{e}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// An unsupported body with a mass term 1e-25 of its stiffness (density 1e-16, Young's
/// modulus 1e12) under gravity: Ĥ is singular to working precision along a rigid
/// translation. Both Newton loops, with the CPU's CG and the device's, refuse the first
/// step with the same one-line verdict (exit 1); the CPU loop's Cholesky meets the zero
/// pivot. The same body with a density of 1e3 runs.
#[test]
fn a_weightless_stiff_body_fails_on_both_newton_loops() {
    let dir = tmpdir("weightless");
    let scene = |density: &str| {
        let text = format!(
            "name = \"weightless\"\ndimension = 2\ntime_step = 0.01\nsteps = 2\n\
             gravity = [0.0, -9.81]\n\n[[bodies]]\n\
             mesh = {{ kind = \"rectangle\", size = [1.0, 0.5], cells = [4, 2] }}\n\
             material = {{ model = \"stable-neo-hookean\", young = 1e12, poisson = 0.3, \
             density = {density} }}\n"
        );
        write(&dir, &format!("weightless_{density}.toml"), &text)
    };
    let singular = scene("1e-16");
    let mut runs = vec![
        (vec!["--solver", "cholesky"], "not positive definite"),
        (
            vec!["--solver", "cg"],
            "meets no constraint and no mass term",
        ),
    ];
    let gpu = have_gpu("a_weightless_stiff_body_fails_on_both_newton_loops");
    if gpu {
        runs.push((
            vec!["--newton", "gpu"],
            "meets no constraint and no mass term",
        ));
    }
    for (k, (args, want)) in runs.iter().enumerate() {
        let out = s(&dir.join(format!("out{k}")));
        let mut a = vec!["run", singular.as_str(), "--out", &out, "-q"];
        a.extend(args.iter().copied());
        let o = run(&a);
        let e = our_stderr(&o);
        assert_eq!(o.status.code(), Some(1), "{args:?}: {e}");
        assert_eq!(e.lines().count(), 1, "{args:?}: {e:?}");
        assert!(
            e.contains("step 1") && e.contains("Newton iteration 1") && e.contains(want),
            "{args:?}: {e}"
        );
    }
    if gpu {
        let heavy = scene("1e3");
        let out = s(&dir.join("heavy"));
        let o = run(&["run", &heavy, "--out", &out, "-q", "--newton", "gpu"]);
        assert!(o.status.success(), "{}", our_stderr(&o));
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// steps.csv as (header, rows of numbers).
fn steps_csv(dir: &Path) -> (Vec<String>, Vec<Vec<f64>>) {
    let text = std::fs::read_to_string(dir.join("steps.csv")).expect("steps.csv");
    let mut lines = text.lines();
    let header = lines
        .next()
        .expect("header")
        .split(',')
        .map(String::from)
        .collect();
    let rows = lines
        .map(|l| {
            l.split(',')
                .map(|v| v.parse().unwrap_or(f64::NAN))
                .collect()
        })
        .collect();
    (header, rows)
}

/// Column `name` of steps.csv.
fn column(csv: &(Vec<String>, Vec<Vec<f64>>), name: &str) -> Vec<f64> {
    let k = csv.0.iter().position(|h| h == name).expect(name);
    csv.1.iter().map(|r| r[k]).collect()
}

/// The Newton loops (`--newton cpu`, and `gpu` with an adapter) on `scene`: their
/// steps.csv, in that order.
fn both_loops(dir: &Path, scene: &str, test: &str) -> Vec<(Vec<String>, Vec<Vec<f64>>)> {
    let mut loops = vec!["cpu"];
    if have_gpu(test) {
        loops.push("gpu");
    }
    loops
        .iter()
        .map(|l| {
            let out = dir.join(format!("out_{l}"));
            let o = run(&["run", scene, "--out", &s(&out), "-q", "--newton", l]);
            assert!(o.status.success(), "{l}: {}", our_stderr(&o));
            steps_csv(&out)
        })
        .collect()
}

/// A clamped beam (10 kg) under gravity with a time step of 1e6 s: every Newton step is
/// short against ‖Δx‖∞/h < tol, so only the force balance ends the step. Both loops reach
/// the equilibrium in step 1 (the supports carry the weight to the force tolerance, and
/// the next steps start there and stay); with 3 Newton iterations allowed the step fails
/// in one line naming the node whose forces do not balance.
#[test]
fn a_huge_time_step_ends_at_the_equilibrium() {
    let dir = tmpdir("huge_step");
    let text = "name = \"beam\"\ndimension = 2\ntime_step = 1e6\nsteps = 3\n\
                gravity = [0.0, -9.81]\n\n[[bodies]]\n\
                mesh = { kind = \"rectangle\", size = [1.0, 0.1], cells = [10, 2] }\n\
                material = { model = \"stable-neo-hookean\", young = 1e5, poisson = 0.3, \
                density = 100.0 }\n\n[[boundary]]\nkind = \"sticky\"\n\
                region = { box = { min = [-0.001, -1.0], max = [0.001, 1.0] } }\n";
    let scene = write(&dir, "beam.toml", text);
    let weight = 10.0 * 9.81;
    let runs = both_loops(&dir, &scene, "a_huge_time_step_ends_at_the_equilibrium");
    for csv in &runs {
        let newton = column(csv, "newton_iterations");
        let f_y = column(csv, "f_y");
        let com_y = column(csv, "com_y");
        let balance = column(csv, "force_residual");
        assert!(
            newton[1] > 3.0,
            "step 1 took {} Newton iterations",
            newton[1]
        );
        for k in 1..=3 {
            assert!(
                balance[k] <= 1e-4,
                "step {k}: force residual {}",
                balance[k]
            );
            // p = 0 at rest: the supports carry the weight, to the force tolerance
            // summed over the 33 nodes.
            assert!(
                (f_y[k] - weight).abs() <= 33.0 * 1e-4 * weight,
                "step {k}: f_y {} against the weight {weight}",
                f_y[k]
            );
        }
        // The beam sags (its centre of mass was at 0.05) and stays.
        assert!(com_y[1] < 0.0, "com_y {}", com_y[1]);
        assert!((com_y[3] - com_y[1]).abs() <= 1e-6, "{com_y:?}");
    }
    if let [cpu, gpu] = &runs[..] {
        let (a, b) = (column(cpu, "com_y"), column(gpu, "com_y"));
        // Both stop within the force tolerance of the same equilibrium: 1e-4 of its sag.
        assert!((a[3] - b[3]).abs() <= 1e-4 * a[3].abs(), "{a:?} {b:?}");
    }
    let limited = write(
        &dir,
        "beam3.toml",
        &format!("{text}\n[solver]\nmax_newton_iterations = 3\n"),
    );
    let o = run(&["run", &limited, "--out", &s(&dir.join("out3")), "-q"]);
    let e = our_stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert_eq!(e.lines().count(), 1, "{e:?}");
    assert!(
        e.contains("step 1") && e.contains("do not balance") && e.contains(" N on node "),
        "{e}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// A 4 kg square released 1e-12 m above a half-space: the barrier's force is ~1e12 times
/// the weight and every Newton step ~1e-12 m. Both loops climb out of the barrier in step 1
/// to the same state (1e-9·L), and momentum balances in every step,
/// p_k − p_{k−1} = h·(M·g + c_k), to the force tolerance (1e-4) of the step's impulse
/// (the step that stopped at 1e-12 m missed it by 12 orders).
#[test]
fn a_body_deep_in_the_barrier_balances_its_forces() {
    let dir = tmpdir("deep_barrier");
    let text = "name = \"rest\"\ndimension = 2\ntime_step = 0.01\nsteps = 3\n\
                gravity = [0.0, -9.81]\n\n[[bodies]]\n\
                mesh = { kind = \"rectangle\", size = [0.2, 0.2], cells = [2, 2], \
                origin = [0.0, 1e-12] }\n\
                material = { model = \"stable-neo-hookean\", young = 1e5, poisson = 0.3, \
                density = 100.0 }\n\n[[obstacle]]\nkind = \"half-space\"\n\
                point = [0.0, 0.0]\nnormal = [0.0, 1.0]\n";
    let scene = write(&dir, "rest.toml", text);
    let (h, m, g) = (0.01, 4.0, -9.81);
    let runs = both_loops(
        &dir,
        &scene,
        "a_body_deep_in_the_barrier_balances_its_forces",
    );
    for csv in &runs {
        let p = column(csv, "p_y");
        let c = column(csv, "c_y");
        let d = column(csv, "min_distance");
        let balance = column(csv, "force_residual");
        for k in 1..=3 {
            let impulse = h * (m * g + c[k]);
            assert!(
                (p[k] - p[k - 1] - impulse).abs() <= 1e-4 * impulse.abs().max(h * m * g.abs()),
                "step {k}: Δp {} against h(Mg + c) {impulse}",
                p[k] - p[k - 1]
            );
            assert!(
                balance[k] <= 1e-4,
                "step {k}: force residual {}",
                balance[k]
            );
        }
        // Out of the barrier's stiff core: the body left 1e-12 m behind.
        assert!(d[2] > 1e-4, "min_distance {d:?}");
    }
    if let [cpu, gpu] = &runs[..] {
        let (a, b) = (column(cpu, "com_y"), column(gpu, "com_y"));
        let l = (0.2f64 * 0.2 * 2.0).sqrt();
        for k in 1..=3 {
            assert!(
                (a[k] - b[k]).abs() <= 1e-9 * l,
                "step {k}: {} vs {}",
                a[k],
                b[k]
            );
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Extreme scenes on which the Newton loops once parted ways, each run on both: the same
/// exit code, and, when they complete, the same end state (centre of mass to 1e-8·L).
/// A 10 m activation distance under a 0.2 m box (the barrier launches it; the CPU loop's
/// line search stalled on energy differences below rounding), and an edge of a strip
/// dragged through its clamp at 100 m/s.
#[test]
fn extreme_scenes_reach_the_same_verdict_on_both_loops() {
    let test = "extreme_scenes_reach_the_same_verdict_on_both_loops";
    if !have_gpu(test) {
        return;
    }
    let dir = tmpdir("same_verdict");
    let drop = stickslip::sim::scene::builtin("drop")
        .unwrap()
        .replace("steps = 100", "steps = 3")
        .replace(
            "normal = [0.0, 1.0, 0.0]",
            "normal = [0.0, 1.0, 0.0]\ndhat = 10.0",
        );
    let drag = "name = \"drag\"\ndimension = 2\ntime_step = 0.01\nsteps = 5\n\
                gravity = [0.0, -9.81]\n\n[[bodies]]\n\
                mesh = { kind = \"rectangle\", size = [1.0, 0.2], cells = [10, 2] }\n\
                material = { model = \"stable-neo-hookean\", young = 1e4, poisson = 0.3, \
                density = 100.0 }\n\n[[boundary]]\nkind = \"sticky\"\n\
                region = { box = { min = [-0.001, -1.0], max = [0.001, 1.0] } }\n\n\
                [[boundary]]\nkind = \"sticky\"\n\
                region = { box = { min = [0.999, -1.0], max = [1.001, 1.0] } }\n\
                motion = { velocity = [-100.0, 0.0], end = 0.4 }\n";
    for (name, text, l) in [
        ("dhat", drop, 0.2 * 3f64.sqrt()),
        ("drag", drag.to_string(), 1.02),
    ] {
        let scene = write(&dir, &format!("{name}.toml"), &text);
        let mut ends = Vec::new();
        for lp in ["cpu", "gpu"] {
            let out = dir.join(format!("{name}_{lp}"));
            let o = run(&["run", &scene, "--out", &s(&out), "-q", "--newton", lp]);
            let com = o.status.success().then(|| {
                let csv = steps_csv(&out);
                ["com_x", "com_y"].map(|c| *column(&csv, c).last().unwrap())
            });
            ends.push((o.status.code(), com, our_stderr(&o)));
        }
        let (cpu, gpu) = (&ends[0], &ends[1]);
        assert_eq!(cpu.0, gpu.0, "{name}: cpu {} / gpu {}", cpu.2, gpu.2);
        assert_eq!(cpu.0, Some(0), "{name}: {}", cpu.2);
        let (a, b) = (cpu.1.unwrap(), gpu.1.unwrap());
        for k in 0..2 {
            assert!(
                (a[k] - b[k]).abs() <= 1e-8 * l,
                "{name}: com {a:?} vs {b:?}"
            );
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}
