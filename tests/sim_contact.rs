//! Contact with analytic obstacles (docs/method.md, "Contact with half-spaces": distance
//! barrier, CCD-filtered line search).
//!
//! - `drop` and `squash`: every Newton iterate of every step keeps every node at a positive
//!   distance from every obstacle (the per-step minimum over iterates, also in steps.csv);
//!   every line-searched Newton step is a descent direction (gᵀΔx < 0).
//! - `drop`: at rest the contact force carries the weight to 1e-2·M·|g|; momentum balance
//!   p_k − p_{k−1} = h (M g + f_k + c_k) holds every step to 1e-3 of h·M·|g|.
//! - The barrier's gradient and Hessian against finite differences; the Hessian is PSD.
//! - A scene without obstacles runs no contact code (counters stay 0).
//! - Every linear solver gives the same contact trajectory; slip, sticky and moving
//!   boundaries combine with a moving obstacle; a penetrating start is an input error.
//! - A mass-spring square squeezed between a moving and a fixed half-space until it turns
//!   inside out: every node (interior ones too) stays on the allowed side in every frame
//!   and iterate, `min_distance` is the minimum over all nodes, and the step where only the
//!   CCD bound holds an interior node fails with one line naming the node and obstacle.

mod common;

use stickslip::core::sparse::BlockCsr;
use stickslip::sim::driver::{run, RunError, RunOptions, RunSummary};
use stickslip::sim::energy::barrier::{Barrier, HalfSpace};

fn out_dir(name: &str) -> std::path::PathBuf {
    std::env::temp_dir().join(format!(
        "stickslip-sim-contact-{}-{name}",
        std::process::id()
    ))
}

fn run_opts(
    scene: &str,
    tag: &str,
    solver: Option<&str>,
    steps: Option<usize>,
) -> (Result<RunSummary, RunError>, String) {
    let out = out_dir(tag);
    let opts = RunOptions {
        scene: Some(scene.into()),
        out: Some(out.clone()),
        solver: solver.map(|s| s.parse().expect("a solver name")),
        steps,
        quiet: true,
        ..RunOptions::default()
    };
    let r = run(&opts);
    let csv = std::fs::read_to_string(out.join("steps.csv")).unwrap_or_default();
    let _ = std::fs::remove_dir_all(&out);
    (r, csv)
}

fn run_scene(scene: &str) -> (RunSummary, String) {
    let (r, csv) = run_opts(scene, scene, None, None);
    (r.unwrap_or_else(|e| panic!("{scene}: {e}")), csv)
}

/// Largest |Δp − h(Mg + f + c)| / (h M |g|) over the steps.
fn momentum_error(s: &RunSummary) -> f64 {
    let h = s.time_step;
    let m = s.total_mass;
    let gn = s.gravity.iter().map(|g| g * g).sum::<f64>().sqrt();
    let scale = h * m * gn;
    let mut worst = 0.0f64;
    for w in s.records.windows(2) {
        let (a, b) = (&w[0], &w[1]);
        for k in 0..s.dimension {
            let dp = b.momentum[k] - a.momentum[k];
            let pred = h * (m * s.gravity[k] + b.reaction[k] + b.contact[k]);
            worst = worst.max((dp - pred).abs() / scale);
        }
    }
    worst
}

/// Every step's minimum distance over its iterates is positive; every line-searched Newton
/// step descends. Returns the smallest distance of the run.
fn check_iterates(name: &str, s: &RunSummary, csv: &str) -> f64 {
    let header = csv.lines().next().expect("steps.csv header");
    let axes = &["x", "y", "z"][..s.dimension];
    let want: String = std::iter::once(",min_distance".to_string())
        .chain(axes.iter().map(|a| format!(",c_{a}")))
        .collect();
    assert!(header.contains(&want), "{name}: header {header}");
    let col = header
        .split(',')
        .position(|c| c == "min_distance")
        .expect("min_distance column");
    let mut worst = f64::INFINITY;
    for (r, line) in s.records.iter().zip(csv.lines().skip(1)) {
        let d = r
            .min_distance
            .unwrap_or_else(|| panic!("{name}: step {} has no min_distance", r.step));
        assert!(
            d > 0.0,
            "{name}: step {}: an iterate reached distance {d:e}",
            r.step
        );
        let from_csv: f64 = line
            .split(',')
            .nth(col)
            .expect("column")
            .parse()
            .expect("number");
        assert_eq!(
            from_csv, d,
            "{name}: steps.csv min_distance at step {}",
            r.step
        );
        worst = worst.min(d);
        assert_eq!(
            r.ascent_directions, 0,
            "{name}: step {}: non-descent Newton step",
            r.step
        );
        if let Some(sl) = r.max_slope {
            assert!(sl < 0.0, "{name}: step {}: gᵀΔx = {sl:e}", r.step);
        }
    }
    let with_ls = s.records.iter().filter(|r| r.max_slope.is_some()).count();
    let slope = s
        .records
        .iter()
        .filter_map(|r| r.max_slope)
        .fold(f64::NEG_INFINITY, f64::max);
    eprintln!(
        "{name}: smallest node–obstacle distance over every Newton iterate {worst:.4e} m (d̂ = {:.4e} m); largest gᵀΔx over {} line-searched steps {slope:.3e}",
        s.contact.as_ref().expect("contact").dhat[0],
        s.newton_iterations,
    );
    assert!(with_ls > 0);
    worst
}

#[test]
fn drop_stays_apart_comes_to_rest_and_balances_momentum() {
    let (s, csv) = run_scene("drop");
    check_iterates("drop", &s, &csv);
    let c = s.contact.as_ref().expect("contact summary");
    assert!(c.ccd_limited_line_searches > 0, "the CCD bound never acted");
    let e = momentum_error(&s);
    eprintln!("drop: worst momentum error {e:.3e} of h·M·|g| (contact counted as external)");
    assert!(e <= 1e-3, "momentum error {e:e}");
    // At rest: speed tiny, the contact force carries the weight.
    let m = s.total_mass;
    let g = 9.81;
    let last = s.records.last().expect("records");
    let vmax = s
        .final_velocities
        .iter()
        .fold(0.0f64, |a, v| a.max(v.abs()));
    let mut imbalance = 0.0f64;
    for k in 0..3 {
        imbalance = imbalance.max((last.contact[k] + m * s.gravity[k]).abs());
    }
    eprintln!(
        "drop: at t = {} s max |v| = {vmax:.3e} m/s, contact force {:?} N vs weight {:.4} N, imbalance {:.3e} of M·|g|",
        last.time,
        last.contact,
        m * g,
        imbalance / (m * g)
    );
    assert!(vmax < 1e-3, "not at rest: max |v| = {vmax:e}");
    assert!(imbalance <= 1e-2 * m * g, "imbalance {imbalance:e} N");
    // The ground does the work: no Dirichlet reaction in this scene.
    assert!(last.reaction.iter().all(|&f| f == 0.0));
    // It actually landed: it fell, touched (inside d̂), and sits above the plane.
    assert!(c.min_distance < c.dhat[0]);
}

#[test]
fn squash_stays_apart_and_balances_momentum() {
    let (s, csv) = run_scene("squash");
    check_iterates("squash", &s, &csv);
    let e = momentum_error(&s);
    let last = s.records.last().expect("records");
    eprintln!(
        "squash: worst momentum error {e:.3e} of h·M·|g|; at the end contact {:?} N, reaction {:?} N",
        last.contact, last.reaction
    );
    assert!(e <= 1e-3, "momentum error {e:e}");
    // The ceiling pushes down, the ground pushes up.
    assert!(last.contact[1] > s.total_mass * 9.81 && last.reaction[1] < 0.0);
}

/// Gradient and Hessian of P_b against central differences, 2D and 3D, two planes, nodes
/// inside and outside d̂; the Hessian is PSD.
#[test]
fn barrier_gradient_and_hessian_match_finite_differences() {
    for dim in [2usize, 3] {
        let n = 5;
        let planes = [
            HalfSpace {
                normal: [0.0, 1.0, 0.0],
                offset: 0.0,
                dhat: 0.01,
                kappa: 1e5,
            },
            HalfSpace {
                normal: if dim == 3 {
                    [0.6, 0.0, 0.8]
                } else {
                    [0.6, 0.8, 0.0]
                },
                offset: -0.02,
                dhat: 0.02,
                kappa: 3e4,
            },
        ];
        let weight = vec![0.1, 0.2, 0.0, 0.05, 0.3];
        let bar = Barrier::new(dim, weight);
        // Points near both planes, one interior node (w = 0), one far away.
        let pts: [[f64; 3]; 5] = [
            [0.01, 0.004, 0.0],
            [0.002, 0.0005, 0.001],
            [0.0, 0.001, 0.0],
            [1.0, 1.0, 1.0],
            [-0.02, 0.008, 0.0],
        ];
        let mut x = Vec::new();
        for p in &pts {
            x.extend_from_slice(&p[..dim]);
        }
        let (dmin, _, _) = bar.min_distance(&x, &planes);
        assert!(dmin > 0.0);
        let mut g = vec![0.0; n * dim];
        let active = bar.add_gradient(&x, &planes, 1.0, &mut g);
        assert!(active >= 3, "{dim}D: only {active} active pairs");
        let rows: Vec<Vec<usize>> = (0..n).map(|i| vec![i]).collect();
        let mut hm = BlockCsr::from_pattern(dim, &rows);
        bar.add_hessian(&x, &planes, 1.0, &mut hm);
        let mut worst_g = 0.0f64;
        let mut worst_h = 0.0f64;
        let gscale = g.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        let hscale = hm.values.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        for k in 0..n * dim {
            let eps = 1e-8;
            let mut xp = x.clone();
            let mut xm = x.clone();
            xp[k] += eps;
            xm[k] -= eps;
            let fd = (bar.energy(&xp, &planes) - bar.energy(&xm, &planes)) / (2.0 * eps);
            worst_g = worst_g.max((fd - g[k]).abs() / gscale);
            let mut gp = vec![0.0; n * dim];
            let mut gm = vec![0.0; n * dim];
            bar.add_gradient(&xp, &planes, 1.0, &mut gp);
            bar.add_gradient(&xm, &planes, 1.0, &mut gm);
            for r in 0..n * dim {
                let fdh = (gp[r] - gm[r]) / (2.0 * eps);
                // Only node-diagonal blocks exist: off-diagonal node pairs must be 0.
                let exact = if r / dim == k / dim {
                    let kb = hm.diag_index(r / dim).expect("diag");
                    hm.values[kb * dim * dim + (r % dim) * dim + k % dim]
                } else {
                    0.0
                };
                worst_h = worst_h.max((fdh - exact).abs() / hscale);
            }
        }
        eprintln!(
            "barrier {dim}D: relative FD error gradient {worst_g:.2e}, Hessian {worst_h:.2e}"
        );
        assert!(worst_g < 1e-6, "{dim}D gradient FD error {worst_g:e}");
        assert!(worst_h < 1e-6, "{dim}D Hessian FD error {worst_h:e}");
        // PSD: every diagonal block w b'' n nᵀ summed over planes.
        for i in 0..n {
            let kb = hm.diag_index(i).expect("diag");
            let blk = &hm.values[kb * dim * dim..(kb + 1) * dim * dim];
            let m = nalgebra::DMatrix::from_row_slice(dim, dim, blk);
            let eig = m.symmetric_eigen();
            let lo = eig.eigenvalues.iter().fold(f64::INFINITY, |a, &v| a.min(v));
            let hi = eig.eigenvalues.iter().fold(0.0f64, |a, &v| a.max(v));
            assert!(
                lo >= -1e-12 * hi.max(1.0),
                "{dim}D node {i}: eigenvalue {lo:e}"
            );
        }
    }
}

#[test]
fn scene_without_obstacles_runs_no_contact_code() {
    let (r, csv) = run_opts("compress", "no-contact", None, Some(5));
    let s = r.unwrap_or_else(|e| panic!("compress: {e}"));
    eprintln!("compress: contact counters {:?}", s.contact_counters);
    assert_eq!(s.contact_counters.barrier_evaluations, 0);
    assert_eq!(s.contact_counters.ccd_calls, 0);
    assert_eq!(s.contact_counters.pushed_nodes, 0);
    assert!(s.contact.is_none());
    assert!(s
        .records
        .iter()
        .all(|r| r.min_distance.is_none() && r.contact.is_empty()));
    let header = csv.lines().next().expect("header");
    assert!(
        !header.contains("min_distance") && !header.contains("c_x"),
        "{header}"
    );
    // And a scene with obstacles does count.
    let (r, _) = run_opts("squash", "contact-counted", None, Some(2));
    let s = r.unwrap_or_else(|e| panic!("squash: {e}"));
    assert!(s.contact_counters.barrier_evaluations > 0 && s.contact_counters.ccd_calls > 0);
}

fn max_diff(a: &RunSummary, b: &RunSummary) -> f64 {
    let mut worst = a
        .final_positions
        .iter()
        .zip(&b.final_positions)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f64, f64::max);
    for (ra, rb) in a.records.iter().zip(&b.records) {
        for (x, y) in ra.com.iter().zip(&rb.com) {
            worst = worst.max((x - y).abs());
        }
    }
    worst / a.characteristic_length
}

#[test]
fn drop_same_trajectory_with_every_linear_solver() {
    let steps = Some(40);
    let (chol, _) = run_opts("drop", "drop-chol", Some("cholesky"), steps);
    let chol = chol.unwrap_or_else(|e| panic!("drop cholesky: {e}"));
    let (cg, csv) = run_opts("drop", "drop-cg", Some("cg"), steps);
    let cg = cg.unwrap_or_else(|e| panic!("drop cg: {e}"));
    check_iterates("drop (cg)", &cg, &csv);
    let d = max_diff(&chol, &cg);
    eprintln!("drop: cholesky vs cg: max |Δx|/L = {d:.3e}");
    assert!(d <= 1e-6, "cholesky and cg differ by {d:e} L");
    match run_opts("drop", "drop-gpu", Some("gpu"), steps) {
        (Ok(gpu), csv) => {
            check_iterates("drop (gpu)", &gpu, &csv);
            let d = max_diff(&chol, &gpu);
            eprintln!(
                "drop: cholesky vs gpu ({:?}): max |Δx|/L = {d:.3e}",
                gpu.adapter
            );
            assert!(d <= 1e-6, "cholesky and gpu differ by {d:e} L");
        }
        (Err(RunError::Solve { step: 0, cause, .. }), _) if cause.contains("cannot start") => {
            if std::env::var_os("STICKSLIP_REQUIRE_GPU").is_some() {
                panic!("STICKSLIP_REQUIRE_GPU is set but the GPU solver cannot start: {cause}");
            }
            common::skip(&format!(
                "SKIP drop: GPU comparison NOT RUN (no adapter): {cause}"
            ));
        }
        (Err(e), _) => panic!("drop gpu: {e}"),
    }
}

/// A scene file variant written to a temporary folder.
fn variant(tag: &str, text: &str) -> std::path::PathBuf {
    let dir = out_dir(&format!("{tag}-scene"));
    std::fs::create_dir_all(&dir).expect("tmp");
    let path = dir.join(format!("{tag}.toml"));
    std::fs::write(&path, text).expect("write");
    path
}

/// The ground rises under the square at 1 m/s for 0.1 s (a moving obstacle) while the left edge slips on the
/// wall x = 0 and the top is a moving sticky boundary: all three together with contact.
#[test]
fn moving_obstacle_with_slip_and_moving_sticky_boundaries() {
    let text = stickslip::sim::scene::builtin("squash")
        .expect("builtin")
        .replace(
            "normal = [0.0, 1.0]\n",
            "normal = [0.0, 1.0]\nmotion = { velocity = [0.0, 1.0], end = 0.1 }\n",
        )
        + "\n[[boundary]]\nkind = \"plane\"\nnormal = [1.0, 0.0]\nregion = { box = { min = [-0.001, 0.1], max = [0.001, 0.9] } }\n";
    let path = variant("squash-moving-ground", &text);
    let (r, csv) = run_opts(
        &path.display().to_string(),
        "squash-moving-ground",
        None,
        Some(40),
    );
    let s = r.unwrap_or_else(|e| panic!("squash with a moving ground: {e}"));
    check_iterates("squash (rising ground, slip wall)", &s, &csv);
    let e = momentum_error(&s);
    eprintln!(
        "squash (rising ground): momentum error {e:.3e}, pushed initial guesses {}",
        s.contact_counters.pushed_nodes
    );
    assert!(e <= 1e-3, "momentum error {e:e}");
    // The ground moves 1 cm per step, faster than the gap closes: it overtook nodes'
    // starting guesses, which were pushed ahead of it.
    assert!(s.contact_counters.pushed_nodes > 0);
    let _ = std::fs::remove_dir_all(path.parent().expect("dir"));
}

#[test]
fn penetrating_start_names_the_node_and_the_obstacle() {
    let text = stickslip::sim::scene::builtin("squash")
        .expect("builtin")
        .replace("point = [0.0, 0.0]", "point = [0.0, 0.5]");
    let err = stickslip::sim::scene::parse(&text, "pen.toml", 1.0).expect_err("must fail");
    eprintln!("{err}");
    assert_eq!(err.entry, "obstacle[0]");
    assert!(err.problem.contains("node 0 ") && err.problem.contains("penetration-free"));
    let bad = stickslip::sim::scene::builtin("drop")
        .expect("builtin")
        .replace(
            "normal = [0.0, 1.0, 0.0]",
            "normal = [0.0, 1.0, 0.0]\ndhatt = 1.0",
        );
    let err = stickslip::sim::scene::parse(&bad, "typo.toml", 1.0).expect_err("must fail");
    assert!(err.entry.starts_with("obstacle[0]"), "{err}");
    let bad = stickslip::sim::scene::builtin("drop")
        .expect("builtin")
        .replace(
            "normal = [0.0, 1.0, 0.0]",
            "normal = [0.0, 1.0, 0.0]\ndhat = -1.0",
        );
    let err = stickslip::sim::scene::parse(&bad, "neg.toml", 1.0).expect_err("must fail");
    assert_eq!(err.entry, "obstacle[0].dhat");
}

/// A unit square of four triangles around a center node (one given clockwise), a boundary
/// line block that must be skipped, and an unused node that must be dropped.
const SQUARE_MSH: &str = "$MeshFormat
4.1 0 8
$EndMeshFormat
$Nodes
1 6 1 6
2 1 0 6
1
2
3
4
5
6
0 0 0
1 0 0
1 1 0
0 1 0
0.5 0.5 0
7 7 0
$EndNodes
$Elements
2 5 1 5
1 1 1 1
5 1 2
2 1 2 4
1 1 2 5
2 3 2 5
3 3 4 5
4 4 1 5
$EndElements
";

#[test]
fn gmsh_meshes_load_and_run_with_contact() {
    let m = stickslip::sim::mesh::gmsh(2, SQUARE_MSH.as_bytes()).expect("2D msh");
    assert_eq!(m.n_nodes(), 5, "the unused node is dropped");
    assert_eq!(m.elements.len(), 4);
    let area: f64 = (0..4).map(|e| m.measure(e)).sum();
    assert!((area - 1.0).abs() < 1e-12);
    for e in &m.elements {
        let p = |k: usize| [m.x[e[k] * 2], m.x[e[k] * 2 + 1]];
        let (a, b, c) = (p(0), p(1), p(2));
        assert!((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]) > 0.0);
    }
    // 3D: one tetrahedron given with negative orientation.
    let tet = "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\n1 4 1 4\n3 1 0 4\n1\n2\n3\n4\n0 0 0\n0 1 0\n1 0 0\n0 0 1\n$EndNodes\n$Elements\n1 1 1 1\n3 1 4 1\n1 1 2 3 4\n$EndElements\n";
    let m3 = stickslip::sim::mesh::gmsh(3, tet.as_bytes()).expect("3D msh");
    assert_eq!(m3.elements.len(), 1);
    assert!((m3.measure(0) - 1.0 / 6.0).abs() < 1e-12);

    // A scene that drops the square onto the ground.
    let dir = out_dir("gmsh-scene");
    std::fs::create_dir_all(&dir).expect("tmp");
    std::fs::write(dir.join("square.msh"), SQUARE_MSH).expect("write msh");
    let scene = "dimension = 2\ntime_step = 0.01\nsteps = 20\ngravity = [0.0, -9.81]\n[output]\nvtk = false\n[[bodies]]\nmesh = { kind = \"gmsh\", file = \"square.msh\", origin = [0.0, 0.02] }\nmaterial = { model = \"neo-hookean\", young = 1e4, poisson = 0.3, density = 100.0 }\n[[obstacle]]\nkind = \"half-space\"\npoint = [0.0, 0.0]\nnormal = [0.0, 1.0]\n";
    let path = dir.join("gmsh.toml");
    std::fs::write(&path, scene).expect("write scene");
    let (r, csv) = run_opts(&path.display().to_string(), "gmsh-run", None, None);
    let s = r.unwrap_or_else(|e| panic!("gmsh scene: {e}"));
    assert_eq!(s.nodes, 5);
    check_iterates("gmsh square", &s, &csv);
    // Errors name the scene file, the key and the .msh file with the problem.
    std::fs::write(dir.join("bad.msh"), "$MeshFormat\n9 9 9\n").expect("write");
    for (file, want) in [
        ("missing.msh", "cannot read"),
        ("bad.msh", "not a readable"),
    ] {
        let text = scene.replace("square.msh", file);
        let p = dir.join(format!("{file}.toml"));
        std::fs::write(&p, &text).expect("write");
        let err = stickslip::sim::driver::load_scene(&p.display().to_string(), 1.0)
            .expect_err("must fail");
        eprintln!("{err}");
        assert_eq!(err.entry, "bodies[0].mesh.file");
        assert!(
            err.problem.contains(file) && err.problem.contains(want),
            "{err}"
        );
        assert!(!err.to_string().contains('\n'));
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// A 2D mass-spring square of 5 × 5 nodes squeezed by a ceiling half-space that moves down
/// onto the ground half-space by 60 % of the square's height (0.5 m/s for 1.24 s from a
/// 4 cm gap) and then holds. The spring network has no resistance to inversion, so it
/// turns inside out under the load and its interior nodes (which carry no barrier) head
/// for the ground.
const SQUEEZE: &str = "name = \"squeeze\"
dimension = 2
time_step = 0.01
steps = 160
gravity = [0.0, -9.81]

[output]
every = 1

[[bodies]]
mesh = { kind = \"rectangle\", size = [1.0, 1.0], cells = [4, 4], origin = [0.0, 0.02] }
material = { model = \"mass-spring\", stiffness = 1e3, density = 100.0 }

[[obstacle]]
kind = \"half-space\"
point = [0.0, 0.0]
normal = [0.0, 1.0]

[[obstacle]]
kind = \"half-space\"
point = [0.0, 1.04]
normal = [0.0, -1.0]
motion = { velocity = [0.0, -0.5], end = 1.24 }
";

/// Node positions of a legacy VTK frame written by `run` (`{:e}`: exact round trip).
fn vtk_points(path: &std::path::Path, dim: usize) -> Vec<f64> {
    let text = std::fs::read_to_string(path).expect("frame");
    let mut lines = text.lines().skip_while(|l| !l.starts_with("POINTS"));
    let n: usize = lines
        .next()
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .expect("POINTS n");
    let mut x = Vec::with_capacity(n * dim);
    for l in lines.take(n) {
        let p: Vec<f64> = l
            .split_whitespace()
            .map(|v| v.parse().expect("coordinate"))
            .collect();
        x.extend_from_slice(&p[..dim]);
    }
    assert_eq!(x.len(), n * dim);
    x
}

/// Smallest signed distance of any node (every node, interior ones included) to any
/// obstacle of `scene` at time t, with the node.
fn true_min_distance(scene: &stickslip::sim::scene::Scene, x: &[f64], t: f64) -> (f64, usize) {
    let d = scene.dim;
    let mut best = (f64::INFINITY, usize::MAX);
    for o in &scene.obstacles {
        let plane = o.at(t);
        for (i, p) in x.chunks_exact(d).enumerate() {
            let dist = plane.distance(p);
            assert!(!dist.is_nan(), "node {i}: NaN distance at t = {t}");
            if dist < best.0 {
                best = (dist, i);
            }
        }
    }
    best
}

/// The failure line of an interior node stopped only by the CCD bound names the node,
/// the obstacle and the likely cause.
fn assert_inverted_message(e: &str) {
    for want in [
        "interior node ",
        "obstacle[",
        "only by the CCD bound",
        "inverted",
        "stiffer material",
        "smaller time step",
        "finer mesh",
    ] {
        assert!(e.contains(want), "missing {want:?} in: {e}");
    }
}

/// Through the binary: the squeezed square either keeps every node of every frame on the
/// allowed side of both half-spaces to the end, or the run stops with exit 1 and one line
/// naming the step, the node, the obstacle and the cause, with steps.csv holding exactly the
/// completed steps. Either way every steps.csv `min_distance` (every node, every Newton
/// iterate) is positive and no larger than the smallest distance over all nodes of the
/// frame written after that step; at t = 0 it equals it.
#[test]
fn squeezed_mass_spring_square_keeps_every_node_out_or_fails_naming_it() {
    let dir = out_dir("squeeze");
    std::fs::create_dir_all(&dir).expect("tmp");
    let path = dir.join("squeeze.toml");
    std::fs::write(&path, SQUEEZE).expect("write scene");
    let scene = stickslip::sim::scene::parse(SQUEEZE, "squeeze.toml", 1.0).expect("scene");
    assert_eq!(scene.model.n_nodes, 25);
    let out = dir.join("out");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_stickslip"))
        .args([
            "run",
            path.to_str().expect("utf-8 path"),
            "--quiet",
            "--out",
        ])
        .arg(&out)
        .output()
        .expect("run stickslip");
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    eprintln!("squeeze: exit {:?}, stderr {err}", o.status.code());
    let csv = std::fs::read_to_string(out.join("steps.csv")).expect("steps.csv");
    let header = csv.lines().next().expect("header");
    let cols: Vec<&str> = header.split(',').collect();
    let col = |name: &str| cols.iter().position(|c| *c == name).expect(name);
    let (c_step, c_time, c_min) = (col("step"), col("time"), col("min_distance"));
    let rows: Vec<Vec<f64>> = csv
        .lines()
        .skip(1)
        .map(|l| {
            l.split(',')
                .map(|v| v.parse().unwrap_or(f64::NAN))
                .collect()
        })
        .collect();
    let mut smallest = f64::INFINITY;
    for (k, r) in rows.iter().enumerate() {
        assert_eq!(r[c_step], k as f64, "steps.csv rows are the steps in order");
        let (t, dmin) = (r[c_time], r[c_min]);
        assert!(dmin > 0.0, "step {k}: an iterate reached distance {dmin:e}");
        let frame = out.join("frames").join(format!("squeeze_{k:05}.vtk"));
        let x = vtk_points(&frame, 2);
        let (truth, node) = true_min_distance(&scene, &x, t);
        // Same positions, same plane, same arithmetic: exact comparisons.
        assert!(truth > 0.0, "step {k}: node {node} at {truth:e} m");
        if k == 0 {
            assert_eq!(
                dmin, truth,
                "t = 0: min_distance is the minimum over all nodes"
            );
        } else {
            assert!(
                dmin <= truth,
                "step {k}: min_distance {dmin:e} above node {node}'s {truth:e} at the end of the step"
            );
        }
        smallest = smallest.min(truth);
    }
    eprintln!(
        "squeeze: {} steps written, smallest node–obstacle distance over every frame {smallest:.4e} m",
        rows.len() - 1
    );
    match o.status.code() {
        Some(0) => {
            assert_eq!(
                rows.len(),
                scene.steps + 1,
                "a complete run writes every step"
            );
        }
        Some(1) => {
            assert_eq!(err.lines().count(), 1, "not one line: {err:?}");
            assert_inverted_message(&err);
            // "step N (t = ...) failed": steps.csv holds rows 0..N−1.
            let step: usize = err
                .split("step ")
                .nth(1)
                .and_then(|s| s.split_whitespace().next())
                .and_then(|s| s.parse().ok())
                .unwrap_or_else(|| panic!("no step number in: {err}"));
            assert_eq!(
                rows.len(),
                step,
                "steps.csv holds the steps before step {step}"
            );
            // The run got well into the squeeze before the network turned inside out.
            assert!(step > 10, "failed at step {step}");
            let summary = out.join("summary.json");
            let s: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(&summary).expect("summary.json"))
                    .expect("summary.json parses");
            assert_eq!(s["status"], "failed", "summary.json: {s}");
        }
        c => panic!("exit {c:?}: {err}"),
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Through the library: after every step of the squeezed square, the stepper's
/// `min_distance` is the minimum over every node (interior nodes included), and a step's
/// `min_distance` over its iterates is no larger; a failed step says why in one line.
#[test]
fn squeezed_square_min_distance_covers_every_node() {
    let scene = stickslip::sim::scene::parse(SQUEEZE, "squeeze.toml", 1.0).expect("scene");
    let mut s = stickslip::sim::integrator::Stepper::new(&scene).expect("stepper");
    let mut interior_nearest = 0usize;
    for _ in 0..scene.steps {
        let rep = match s.step() {
            Ok(r) => r,
            Err(err) => {
                assert!(
                    matches!(
                        err,
                        stickslip::sim::integrator::StepError::Unbarriered { .. }
                    ),
                    "{err:?}"
                );
                let e = err.to_string();
                eprintln!("squeeze (library): step {} failed: {e}", s.step + 1);
                assert!(!e.contains('\n'), "{e:?}");
                assert_inverted_message(&e);
                break;
            }
        };
        let (truth, node) = true_min_distance(&scene, &s.x, s.t);
        let (d, n, j) = s.min_distance(&s.x).expect("scene has obstacles");
        // Same positions and planes: exact. (Nodes at equal distance may be named either way.)
        assert_eq!(d, truth, "step {}", s.step);
        assert_eq!(
            scene.obstacles[j].at(s.t).distance(&s.x[2 * n..2 * n + 2]),
            d
        );
        assert!(truth > 0.0, "step {}: node {node} at {truth:e}", s.step);
        let over_iterates = rep.min_distance.expect("min_distance");
        assert!(over_iterates <= truth, "step {}", s.step);
        if scene.contact_weight[node] == 0.0 {
            interior_nearest += 1;
        }
    }
    eprintln!(
        "squeeze (library): {} steps, {interior_nearest} of them ended with an interior node nearest an obstacle",
        s.step
    );
}
