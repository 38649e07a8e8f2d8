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
    eprintln!("SKIP the GPU part of {test}: no GPU adapter");
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
            let m = stickslip::mesh::gmsh(2, &bytes).unwrap_or_else(|e| panic!("{what}: {e}"));
            assert_eq!(m.n_nodes(), 5, "{what}");
            // Exact: each triangle's area is 1/4 in binary fractions.
            let area: f64 = (0..4).map(|e| m.measure(e)).sum();
            assert_eq!(area, 1.0, "{what}");
            for e in 0..4 {
                assert_eq!(m.measure(e), 0.25, "{what}: element {e}");
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
    let e = stickslip::mesh::gmsh(2, &square_ascii(&[&[1, 2, 3, 3, 5]])).unwrap_err();
    assert!(e.contains("node tag 3 is given to two nodes"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}
