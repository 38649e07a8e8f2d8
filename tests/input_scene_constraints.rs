//! Bad input in constraints and scenes, end to end through the built binary: each exits 2
//! with one stderr line naming the file and the entry, never a panic, an abort or a
//! silently wrong answer. Covers many rows on one node (reduced by QR, not a k×k SVD),
//! lifts that overflow, contradictory scene conditions on one node, overlong scene names
//! and the scene node caps; plus library checks of the many-rows frames. No timing
//! asserts (timings belong in benchmarks): the 100,000-row case needed 80 GB before.

use std::path::Path;
use std::process::Output;

mod common;
use common::cli::{assert_input_error, run, stderr, tmpdir, write};

use stickslip::core::constraints::{Constraint, ConstraintKind, Frames};
use stickslip::sim::integrator::Stepper;

/// A 3D system of `n` nodes: H = tridiagonal-ish SPD (4 on the diagonal, −1 between
/// neighbours' matching components), g = a fixed pattern. Returns (H path, g path).
fn system_3d(dir: &Path, n: usize) -> (String, String) {
    let nd = 3 * n;
    let mut e = Vec::new();
    for i in 0..nd {
        e.push(format!("{} {} 4", i + 1, i + 1));
        if i + 3 < nd {
            e.push(format!("{} {} -1", i + 4, i + 1));
        }
    }
    let h = format!(
        "%%MatrixMarket matrix coordinate real symmetric\n{nd} {nd} {}\n{}\n",
        e.len(),
        e.join("\n")
    );
    let g: Vec<String> = (0..nd)
        .map(|k| format!("{}", (k % 5) as f64 - 2.0))
        .collect();
    let g = format!(
        "%%MatrixMarket matrix array real general\n{nd} 1\n{}\n",
        g.join("\n")
    );
    (write(dir, "H.mtx", &h), write(dir, "g.mtx", &g))
}

fn solve(h: &str, g: &str, extra: &[&str], out: &Path) -> Output {
    let mut a = vec![
        "solve",
        "--hessian",
        h,
        "--gradient",
        g,
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ];
    a.extend_from_slice(extra);
    run(&a)
}

fn read_vec(path: &Path) -> Vec<f64> {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines().filter(|l| !l.starts_with('%'));
    lines.next().unwrap();
    lines.map(|l| l.trim().parse().unwrap()).collect()
}

/// Deterministic pseudo-random numbers in [-1, 1) (no RNG crate needed).
fn lcg(state: &mut u64) -> f64 {
    *state = state
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    ((*state >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
}

/// `k` rows on one 3D node, each a random combination of the normals n1 = (1, 1, 0) and
/// n2 = (0, 1, 1) (rank 2: the node slides on the line along n1 × n2), with values
/// consistent with the point p.
fn rank2_rows(k: usize, p: [f64; 3]) -> (Vec<Vec<f64>>, Vec<f64>) {
    let mut s = 7u64;
    let (n1, n2) = ([1.0, 1.0, 0.0], [0.0, 1.0, 1.0]);
    let mut rows = Vec::with_capacity(k);
    let mut vals = Vec::with_capacity(k);
    for _ in 0..k {
        let (a, b) = (lcg(&mut s), lcg(&mut s));
        let r: Vec<f64> = (0..3).map(|i| a * n1[i] + b * n2[i]).collect();
        vals.push((0..3).map(|i| r[i] * p[i]).sum());
        rows.push(r);
    }
    (rows, vals)
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

// ---------------------------------------------------------------------------------------
// 1. Many rows on one node: O(k·d) memory, the right frame, contradictions still caught.

#[test]
fn many_consistent_rows_on_one_node_give_the_right_frame_quickly() {
    let p = [0.3, -0.2, 0.5];
    let (rows, values) = rank2_rows(5000, p);
    let cs = vec![Constraint {
        node: 1,
        kind: ConstraintKind::Rows {
            rows: rows.clone(),
            values: values.clone(),
        },
        label: "constraints[0]".into(),
    }];
    let f = Frames::build(3, 2, &cs).expect("consistent rows");
    assert_eq!(
        f.mask[1].count_ones(),
        2,
        "two planes' worth of rows is a line"
    );
    assert_eq!(f.mask[0], 0);
    // The free direction is along n1 × n2 = (1, −1, 1)/√3.
    let v = f.rotation(1).expect("an off-axis line rotates");
    let free = [v[2], v[5], v[8]];
    assert!(dot(&free, &[1.0, 1.0, 0.0]).abs() < 1e-13, "{free:?}");
    assert!(dot(&free, &[0.0, 1.0, 1.0]).abs() < 1e-13, "{free:?}");
    // The lift meets every row, and is the minimum-norm point: orthogonal to the line.
    let lift = &f.lift[3..6];
    for (r, val) in rows.iter().zip(&values) {
        assert!((dot(r, lift) - val).abs() < 1e-12 * (1.0 + val.abs()));
    }
    assert!(dot(lift, &free).abs() < 1e-13);

    // 100,000 rows: linear time and memory (the full SVD needed a k×k matrix: 80 GB).
    let (rows, values) = rank2_rows(100_000, p);
    let cs = vec![Constraint {
        node: 0,
        kind: ConstraintKind::Rows { rows, values },
        label: "constraints[0]".into(),
    }];
    let f = Frames::build(3, 1, &cs).expect("consistent rows");
    assert_eq!(f.mask[0].count_ones(), 2);
}

#[test]
fn many_rows_with_one_contradiction_are_rejected() {
    let p = [0.3, -0.2, 0.5];
    let (rows, mut values) = rank2_rows(5000, p);
    values[4321] += 1e-3;
    let cs = vec![Constraint {
        node: 0,
        kind: ConstraintKind::Rows { rows, values },
        label: "constraints[0]".into(),
    }];
    let e = Frames::build(3, 1, &cs).expect_err("one row disagrees");
    assert_eq!(e.label, "constraints[0]");
    assert!(e.problem.contains("contradictory"), "{e}");
    assert_eq!(e.node, Some(0));
}

/// Many copies of two planes 1e-10 rad apart (numerically one plane) with consistent
/// values: the QR reduction keeps the conditioning (normal equations would square it), so
/// the rank is 1 and the values are consistent, as with two rows.
#[test]
fn many_nearly_redundant_rows_stay_rank_one() {
    let th = 1e-10f64;
    let n1 = [1.0, 0.0, 0.0];
    let n2 = [th.cos(), th.sin(), 0.0];
    let mut rows = Vec::new();
    for k in 0..3000 {
        rows.push(if k % 2 == 0 { n1.to_vec() } else { n2.to_vec() });
    }
    let values = vec![0.0; rows.len()];
    let cs = vec![Constraint {
        node: 0,
        kind: ConstraintKind::Rows { rows, values },
        label: "c".into(),
    }];
    let f = Frames::build(3, 1, &cs).expect("redundant, not contradictory");
    assert_eq!(f.mask[0].count_ones(), 1);
}

#[test]
fn many_rows_through_the_binary() {
    let dir = tmpdir("rows");
    let (h, g) = system_3d(&dir, 3);
    // bc.json: one `rows` constraint with 20,000 consistent rows on node 1.
    let p = [0.3, -0.2, 0.5];
    let (rows, values) = rank2_rows(20_000, p);
    let json = serde_json::json!({"dim": 3, "constraints": [
        {"node": 1, "kind": "rows", "rows": rows, "values": values}]});
    let bc = write(&dir, "bc.json", &json.to_string());
    let out = dir.join("dx.mtx");
    let o = solve(&h, &g, &["--constraints", &bc], &out);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let dx = read_vec(&out);
    for (r, v) in rows.iter().zip(&values).step_by(97) {
        assert!((dot(r, &dx[3..6]) - v).abs() < 1e-12);
    }

    // B.mtx: 3000 rows on node 0, row 3000's value contradicts the others.
    let m = 3000;
    let mut b = format!("%%MatrixMarket matrix coordinate real general\n{m} 9 {m}\n");
    let mut pv = format!("%%MatrixMarket matrix array real general\n{m} 1\n");
    for r in 0..m {
        b.push_str(&format!("{} 1 2.0\n", r + 1));
        pv.push_str(if r + 1 == m { "1.5\n" } else { "1.0\n" });
    }
    let bf = write(&dir, "B.mtx", &b);
    let pf = write(&dir, "p.mtx", &pv);
    let o = solve(
        &h,
        &g,
        &[
            "--constraint-matrix",
            &bf,
            "--constraint-values",
            &pf,
            "--dim",
            "3",
        ],
        &out,
    );
    let e = assert_input_error(
        &o,
        &bf,
        &[
            "node 0 (row 1, row 2,",
            "and 2992 more",
            "contradictory",
            "a row of row 3000 misses",
        ],
    );
    assert!(e.len() < 400, "the message lists every row: {e}");
    // The same rows, all consistent, solve.
    let pv_ok = pv.replace("1.5\n", "1.0\n");
    let pf = write(&dir, "p_ok.mtx", &pv_ok);
    let o = solve(
        &h,
        &g,
        &[
            "--constraint-matrix",
            &bf,
            "--constraint-values",
            &pf,
            "--dim",
            "3",
        ],
        &out,
    );
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!((read_vec(&out)[0] - 0.5).abs() < 1e-14);
}

// ---------------------------------------------------------------------------------------
// 2. Lifts that overflow, and normals too short to normalize.

#[test]
fn overflowing_lifts_and_subnormal_normals_are_input_errors() {
    let dir = tmpdir("lift");
    let (h, g) = system_3d(&dir, 2);
    let out = dir.join("dx.mtx");
    for (name, c, want) in [
        (
            "tiny",
            r#"{"node": 1, "kind": "plane", "normal": [1e-320, 1e-320, 0], "offset": 1}"#,
            &["constraints[0]", "normal has length", "too short"][..],
        ),
        (
            "huge-offset",
            r#"{"node": 1, "kind": "plane", "normal": [1e-300, 0, 0], "offset": 1e300}"#,
            &["constraints[0]", "offset / |normal|", "overflows"][..],
        ),
        (
            "rows",
            r#"{"node": 0, "kind": "rows", "rows": [[1e-300, 0, 0], [0, 1, 0]], "values": [1e300, 0]}"#,
            &["constraints[0]", "values[0] / |rows[0]|", "overflows"][..],
        ),
        (
            "line",
            r#"{"node": 0, "kind": "line", "direction": [1, 1, 1], "offset": [1.7e308, 1.7e308, 1.7e308]}"#,
            &["constraints[0]", "not finite"][..],
        ),
        (
            "short-direction",
            r#"{"node": 0, "kind": "line", "direction": [0, 4e-324, 0]}"#,
            &["constraints[0]", "direction has length", "too short"][..],
        ),
    ] {
        let bc = write(
            &dir,
            &format!("{name}.json"),
            &format!(r#"{{"dim": 3, "constraints": [{c}]}}"#),
        );
        let o = solve(&h, &g, &["--constraints", &bc], &out);
        assert_input_error(&o, &bc, want);
    }
    // Two constraints on one node, one of whose values overflows: named inside the node.
    let bc = write(
        &dir,
        "pair.json",
        r#"{"dim": 3, "constraints": [{"node": 1, "kind": "plane", "normal": [0, 1, 0]},
            {"node": 1, "kind": "plane", "normal": [1e-300, 0, 0], "offset": 1e300}]}"#,
    );
    let o = solve(&h, &g, &["--constraints", &bc], &out);
    assert_input_error(
        &o,
        &bc,
        &[
            "node 1 (constraints[0], constraints[1])",
            "constraints[1]: offset / |normal|",
        ],
    );
    // B.mtx with p: the row's value over its length overflows.
    let b = write(
        &dir,
        "B.mtx",
        "%%MatrixMarket matrix coordinate real general\n1 6 1\n1 1 1e-300\n",
    );
    let p = write(
        &dir,
        "p.mtx",
        "%%MatrixMarket matrix array real general\n1 1\n1e300\n",
    );
    let o = solve(
        &h,
        &g,
        &[
            "--constraint-matrix",
            &b,
            "--constraint-values",
            &p,
            "--dim",
            "3",
        ],
        &out,
    );
    assert_input_error(&o, &b, &["row 1", "overflows"]);
    // A small but normal-range normal still works, and the lift is right.
    let bc = write(
        &dir,
        "small.json",
        r#"{"dim": 3, "constraints": [{"node": 1, "kind": "plane", "normal": [1e-300, 0, 0], "offset": 2e-301}]}"#,
    );
    let o = solve(&h, &g, &["--constraints", &bc], &out);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert!((read_vec(&out)[3] - 0.2).abs() < 1e-15);
}

// ---------------------------------------------------------------------------------------
// 3. Several scene conditions on one node must agree.

const SCENE_2D: &str = r#"name = "t"
dimension = 2
time_step = 0.01
steps = 2
gravity = [0.0, -9.81]

[output]
vtk = false

[[bodies]]
mesh = { kind = "rectangle", size = [1.0, 0.5], cells = [4, 2] }
material = { model = "neo-hookean", young = 1e4, poisson = 0.3, density = 100.0 }
"#;

fn run_scene(dir: &Path, name: &str, text: &str) -> (String, Output) {
    let path = write(dir, &format!("{name}.toml"), text);
    let o = run(&[
        "run",
        &path,
        "--out",
        dir.join(format!("out-{name}")).to_str().unwrap(),
        "--quiet",
    ]);
    (path, o)
}

#[test]
fn contradictory_scene_conditions_on_one_node_are_input_errors() {
    let dir = tmpdir("contra");
    // Sticky at x = 0 and the plane x = 0.5 on the same nodes.
    let text = format!(
        r#"{SCENE_2D}
[[boundary]]
kind = "sticky"
region = {{ box = {{ min = [-0.001, -1.0], max = [0.001, 1.0] }} }}

[[boundary]]
kind = "plane"
normal = [1.0, 0.0]
offset = 0.5
region = {{ box = {{ min = [-0.001, -1.0], max = [0.001, 1.0] }} }}
"#
    );
    let (path, o) = run_scene(&dir, "sticky-plane", &text);
    assert_input_error(
        &o,
        &path,
        &[
            "node 0 (boundary[0], boundary[1])",
            "contradictory",
            "initial position",
        ],
    );
    // Two parallel planes x = 0 and x = 0.5 on node 0.
    let text = format!(
        r#"{SCENE_2D}
[[boundary]]
kind = "plane"
normal = [1.0, 0.0]
offset = 0.0
region = {{ nodes = [0] }}

[[boundary]]
kind = "plane"
normal = [2.0, 0.0]
offset = 1.0
region = {{ nodes = [0] }}
"#
    );
    let (path, o) = run_scene(&dir, "two-planes", &text);
    assert_input_error(
        &o,
        &path,
        &["node 0 (boundary[0], boundary[1])", "contradictory"],
    );
    // The parser says it too (library users get the same error).
    let e = stickslip::sim::scene::parse(&text, "s.toml", 1.0).expect_err("contradictory");
    assert_eq!(e.entry, "node 0 (boundary[0], boundary[1])");
}

#[test]
fn consistent_scene_conditions_on_one_node_still_run() {
    let dir = tmpdir("consistent");
    // Sticky plus a plane through the nodes, two planes through node 0 (nearly parallel),
    // and a plane whose offset / |normal| = 0.075 / 0.1 = 0.7499999999999999 misses node 3
    // at x = 0.75 by rounding only.
    let text = format!(
        r#"{SCENE_2D}
[[boundary]]
kind = "sticky"
region = {{ box = {{ min = [-0.001, -1.0], max = [0.001, 1.0] }} }}

[[boundary]]
kind = "plane"
normal = [1.0, 0.0]
region = {{ box = {{ min = [-0.001, -1.0], max = [0.001, 1.0] }} }}

[[boundary]]
kind = "plane"
normal = [1.0, 1e-9]
region = {{ nodes = [0] }}

[[boundary]]
kind = "sticky"
region = {{ nodes = [3] }}

[[boundary]]
kind = "plane"
normal = [0.1, 0.0]
offset = 0.075
region = {{ nodes = [3] }}
"#
    );
    let (_, o) = run_scene(&dir, "ok", &text);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
}

/// Two non-orthogonal planes with explicit offsets hold node 0 at their intersection
/// (1e-4, 4e-4), within the 1e-3·L a static condition may move a node; projecting onto
/// one plane and then the other would leave it off the first.
#[test]
fn several_planes_on_a_node_project_onto_their_intersection() {
    let text = format!(
        r#"{SCENE_2D}
[[boundary]]
kind = "plane"
normal = [1.0, 0.0]
offset = 1e-4
region = {{ nodes = [0] }}

[[boundary]]
kind = "plane"
normal = [1.0, 1.0]
offset = 5e-4
region = {{ nodes = [0] }}

[[boundary]]
kind = "sticky"
region = {{ box = {{ min = [0.999, -1.0], max = [1.001, 1.0] }} }}
"#
    );
    let scene = stickslip::sim::scene::parse(&text, "s.toml", 1.0).expect("consistent");
    let mut st = Stepper::new(&scene).expect("stepper");
    st.step().expect("step");
    st.step().expect("step");
    assert!((st.x[0] - 1e-4).abs() < 1e-14, "{:?}", &st.x[..2]);
    assert!((st.x[1] - 4e-4).abs() < 1e-14, "{:?}", &st.x[..2]);
}

/// The scene side of finding 2: normals are normalized with a scaled length (no underflow
/// of the squares), subnormal lengths and overflowing offset / |normal| are input errors,
/// and a plane near the end of the f64 range fails the step (exit 1, stable law) instead of
/// writing NaN, or is refused as an inverted start (exit 2, classical law).
#[test]
fn scene_plane_offsets_and_tiny_normals() {
    let dir = tmpdir("scene-planes");
    let plane = |normal: &str, offset: &str| {
        format!(
            "{SCENE_2D}\n[[boundary]]\nkind = \"plane\"\nnormal = {normal}\noffset = {offset}\nregion = {{ nodes = [0] }}\n"
        )
    };
    let (path, o) = run_scene(&dir, "overflow", &plane("[1e-300, 0.0]", "1e10"));
    assert_input_error(&o, &path, &["boundary[0].offset", "overflows"]);
    let (path, o) = run_scene(&dir, "subnormal", &plane("[1e-320, 0.0]", "0.0"));
    assert_input_error(&o, &path, &["boundary[0].normal", "got length 1e-320"]);
    // Small (normal-range) and huge normals are fine: x = 0 through node 0.
    for (name, n, off) in [
        ("small", "[1e-160, 0.0]", "0.0"),
        ("huge", "[1e300, 1e300]", "0.0"),
    ] {
        let (_, o) = run_scene(&dir, name, &plane(n, off));
        assert_eq!(o.status.code(), Some(0), "{name}: {}", stderr(&o));
    }
    // A plane near the end of the f64 range is refused before the first step on either
    // law: its projection would carry node 0 1e300 m.
    let stable = plane("[1.0, 0.0]", "1e300")
        .replace("model = \"neo-hookean\"", "model = \"stable-neo-hookean\"");
    let (path, o) = run_scene(&dir, "far", &stable);
    assert_input_error(&o, &path, &["boundary[0]", "node 0", "1.000e300 m"]);
    let (path, o) = run_scene(&dir, "far-classical", &plane("[1.0, 0.0]", "1e300"));
    assert_input_error(&o, &path, &["boundary[0]", "node 0", "1.000e300 m"]);
}

// ---------------------------------------------------------------------------------------
// 4. Scene names are capped.

fn no_name() -> String {
    SCENE_2D.replacen("name = \"t\"\n", "", 1)
}

#[test]
fn overlong_scene_names_are_input_errors() {
    let dir = tmpdir("name");
    let text = format!("name = \"{}\"\n{}", "x".repeat(5000), &no_name());
    let (path, o) = run_scene(&dir, "long", &text);
    assert_input_error(&o, &path, &[": name: ", "5000 bytes", "cap of 100 bytes"]);
    // A name taken from a long file name is checked too.
    let stem = "y".repeat(150);
    let (path, o) = run_scene(&dir, &stem, &no_name());
    assert_input_error(
        &o,
        &path,
        &[": name: ", "taken from the file name", "150 bytes"],
    );
    // 100 bytes is fine.
    let text = format!("name = \"{}\"\n{}", "z".repeat(100), &no_name());
    let (_, o) = run_scene(&dir, "max", &text);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
}

// ---------------------------------------------------------------------------------------
// 5. Node caps: per scene over all bodies, checked before any mesh is allocated.

#[test]
fn scenes_over_the_node_caps_are_input_errors() {
    use stickslip::sim::mesh::{MAX_CHOLESKY_NODES_3D, MAX_SCENE_NODES_2D, MAX_SCENE_NODES_3D};
    let dir = tmpdir("caps");
    let big = SCENE_2D.replace("cells = [4, 2]", "cells = [7000, 7000]");
    let (path, o) = run_scene(&dir, "rect", &big);
    assert_input_error(
        &o,
        &path,
        &[
            "bodies[0].mesh.cells",
            "49014001 nodes",
            &format!("{MAX_SCENE_NODES_2D}"),
            "MAX_SCENE_NODES_2D",
        ],
    );
    // --size takes the scene over the cap: named.
    let path = write(&dir, "small.toml", SCENE_2D);
    let o = run(&[
        "run",
        &path,
        "--size",
        "1700",
        "--out",
        dir.join("out-size").to_str().unwrap(),
        "--quiet",
    ]);
    assert_input_error(&o, &path, &["bodies[0].mesh.cells", "--size 1700", "cap"]);
    // Three bodies each under the cap, over it together: the third is named, and nothing
    // is generated first (this would take ~20 GB otherwise).
    let body = "\n[[bodies]]\nmesh = { kind = \"rectangle\", size = [1.0, 1.0], cells = [2500, 2500] }\nmaterial = { model = \"neo-hookean\", young = 1e4, poisson = 0.3, density = 100.0 }\n";
    let three = format!(
        "{}{body}{body}{body}",
        SCENE_2D.replace("cells = [4, 2]", "cells = [1, 1]")
    );
    let (path, o) = run_scene(&dir, "three", &three);
    assert_input_error(
        &o,
        &path,
        &[
            "bodies[3].mesh.cells",
            "bodies before it",
            "all bodies together",
        ],
    );
    // 3D: a 200³ box and a rod.
    let box3 = r#"name = "b"
dimension = 3
time_step = 0.01
steps = 1
[solver]
linear = "cg"
[[bodies]]
mesh = { kind = "box", size = [1.0, 1.0, 1.0], cells = [200, 200, 200] }
material = { model = "neo-hookean", young = 1e4, poisson = 0.3, density = 100.0 }
"#;
    let (path, o) = run_scene(&dir, "box", box3);
    assert_input_error(
        &o,
        &path,
        &[
            "bodies[0].mesh.cells",
            &format!("{MAX_SCENE_NODES_3D}"),
            "MAX_SCENE_NODES_3D",
        ],
    );
    let rod = box3.replace(
        r#"mesh = { kind = "box", size = [1.0, 1.0, 1.0], cells = [200, 200, 200] }
material = { model = "neo-hookean", young = 1e4, poisson = 0.3, density = 100.0 }"#,
        r#"mesh = { kind = "rod", length = 1.0, cells = [49000000] }
material = { model = "mass-spring", stiffness = 1e4, density = 100.0 }"#,
    );
    let (path, o) = run_scene(&dir, "rod", &rod);
    assert_input_error(&o, &path, &["bodies[0].mesh.cells", "49000001 nodes"]);
    // The Cholesky solver has its own, smaller cap in 3D.
    let chol = box3
        .replace("linear = \"cg\"", "linear = \"cholesky\"")
        .replace("[200, 200, 200]", "[80, 80, 80]");
    let (path, o) = run_scene(&dir, "chol", &chol);
    assert_input_error(
        &o,
        &path,
        &[
            "solver.linear",
            &format!("{MAX_CHOLESKY_NODES_3D}"),
            "531441",
        ],
    );
}

/// The Cholesky cap belongs to the solver that runs: a scene that names Cholesky parses
/// at any size, and its run starts once `--solver cg` or the device loop replaces it.
#[test]
fn the_cholesky_cap_follows_the_solver_that_runs() {
    use stickslip::sim::integrator::{InitError, Stepper};
    use stickslip::sim::mesh::MAX_CHOLESKY_NODES_3D;
    use stickslip::sim::scene::LinearKind;
    let cells = MAX_CHOLESKY_NODES_3D; // cells + 1 nodes: one over the cap
    let text = format!(
        r#"name = "long-rod"
dimension = 3
time_step = 0.01
steps = 1
[solver]
linear = "cholesky"
[[bodies]]
mesh = {{ kind = "rod", length = 1.0, cells = [{cells}] }}
material = {{ model = "mass-spring", stiffness = 1e4, density = 100.0 }}
[[boundary]]
kind = "sticky"
region = {{ nodes = [0] }}
"#
    );
    let mut scene = stickslip::sim::scene::parse(&text, "rod.toml", 1.0).expect("parses");
    match Stepper::new(&scene) {
        Err(InitError::Input { entry, problem }) => {
            assert_eq!(entry, "solver.linear");
            assert!(
                problem.contains(&format!("{MAX_CHOLESKY_NODES_3D}")),
                "{problem}"
            );
        }
        Err(e) => panic!("expected the cap, got {e:?}"),
        Ok(_) => panic!("expected the cap"),
    }
    scene.solver.linear = LinearKind::Cg;
    assert!(Stepper::new(&scene).is_ok(), "CG has no cap of its own");
}

/// Values near f64's top on more rows than dimensions: the QR reduction scales them, so a
/// finite lift of 5e307 is kept (unscaled, the reflections' sums overflowed to NaN).
#[test]
fn many_rows_with_huge_finite_values_keep_their_lift() {
    for (k, v) in [(4usize, 5e307), (1000, 1e306)] {
        let cs = vec![Constraint {
            node: 0,
            kind: ConstraintKind::Rows {
                rows: vec![vec![1.0, 0.0, 0.0]; k],
                values: vec![v; k],
            },
            label: "constraints[0]".into(),
        }];
        let f = Frames::build(3, 1, &cs).expect("consistent, finite rows");
        assert_eq!(f.mask[0], 1, "x fixed");
        // One reduction of k equal rows: a few roundings relative to v.
        assert!(
            (f.lift[0] / v - 1.0).abs() < 1e-13,
            "{} for {v:e}",
            f.lift[0]
        );
        assert_eq!(&f.lift[1..3], &[0.0, 0.0]);
    }
}

/// The multilevel preconditioner runs in f64 (the CPU CG, the device PCG): a scene that
/// asks for it with the GPU linear solver in f32 or mixed precision is refused before any
/// work.
#[test]
fn multilevel_with_a_gpu_solver_below_f64_is_an_input_error() {
    let dir = tmpdir("multilevel-gpu");
    for (name, solver) in [
        (
            "f32",
            "linear = \"gpu\"\nprecision = \"f32\"\npreconditioner = \"multilevel\"",
        ),
        (
            "mixed",
            "linear = \"gpu\"\nprecision = \"mixed\"\npreconditioner = \"multilevel\"",
        ),
    ] {
        let text = format!("{SCENE_2D}\n[solver]\n{solver}\n");
        let (path, o) = run_scene(&dir, name, &text);
        assert_input_error(&o, &path, &["solver.preconditioner", "multilevel"]);
    }
}
