//! A run on one thread and on two gives bitwise the same steps.csv (every column but
//! linear_seconds, a timing) and the same final positions and velocities: the element
//! loops run in fixed chunks and reduce in a fixed order. Scenes large enough for several
//! chunks of elements: a twisted 3D bar (moving conditions, neo-Hookean tetrahedra) and a
//! 2D one (the default scene, triangles), both with the CPU CG.

use stickslip::sim::driver::{run, RunOptions};

/// steps.csv without its linear_seconds column, plus the final state's bits.
fn run_on(threads: usize, scene: &str, size: f64, steps: usize) -> (Vec<String>, Vec<u64>) {
    let out = std::env::temp_dir().join(format!(
        "stickslip-sim-threads-{}-{scene}-{threads}",
        std::process::id()
    ));
    let opts = RunOptions {
        scene: Some(scene.into()),
        out: Some(out.clone()),
        solver: Some(stickslip::SolverKind::Cg),
        size: Some(size),
        steps: Some(steps),
        quiet: true,
        ..RunOptions::default()
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    let summary = pool
        .install(|| run(&opts))
        .unwrap_or_else(|e| panic!("{scene} on {threads} thread(s): {e}"));
    let csv = std::fs::read_to_string(out.join("steps.csv")).expect("steps.csv");
    let _ = std::fs::remove_dir_all(&out);
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().expect("header").split(',').collect();
    let skip = header
        .iter()
        .position(|h| *h == "linear_seconds")
        .expect("linear_seconds column");
    let rows: Vec<String> = std::iter::once(header.join(","))
        .chain(lines.map(|l| {
            l.split(',')
                .enumerate()
                .filter(|(k, _)| *k != skip)
                .map(|(_, v)| v)
                .collect::<Vec<_>>()
                .join(",")
        }))
        .collect();
    assert_eq!(
        rows.len(),
        steps + 2,
        "{scene}: header, step 0 and {steps} steps"
    );
    let state = summary
        .final_positions
        .iter()
        .chain(&summary.final_velocities)
        .map(|v| v.to_bits())
        .collect();
    (rows, state)
}

fn same_on_one_and_two_threads(scene: &str, size: f64, steps: usize) {
    let (csv1, x1) = run_on(1, scene, size, steps);
    let (csv2, x2) = run_on(2, scene, size, steps);
    for (a, b) in csv1.iter().zip(&csv2) {
        assert_eq!(a, b, "{scene}: steps.csv differs between 1 and 2 threads");
    }
    assert_eq!(csv1.len(), csv2.len());
    assert!(
        x1 == x2,
        "{scene}: final state differs between 1 and 2 threads"
    );
}

#[test]
fn twist_is_bitwise_the_same_on_one_and_two_threads() {
    // 6,480 tetrahedra: several chunks of the parallel element loops.
    same_on_one_and_two_threads("twist", 3.0, 3);
}

#[test]
fn default_scene_is_bitwise_the_same_on_one_and_two_threads() {
    // 2D, 3,840 triangles.
    same_on_one_and_two_threads("default", 2.0, 3);
}
