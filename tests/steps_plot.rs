//! steps.svg beside a run's steps.csv: a well-formed SVG with one energy marker per row
//! of steps.csv, there while the run goes (a killed run keeps the plot of its last
//! checkpoint) and covering every step once the run is resumed to its end.

#![cfg(unix)]

use std::path::Path;
use std::time::{Duration, Instant};

mod common;
use common::cli::{run, stderr, tmpdir};

fn s(p: &Path) -> String {
    p.to_str().expect("utf-8 path").to_string()
}

/// What a parse of steps.svg finds: its root element, the markers' x coordinates and
/// its text.
struct Svg {
    root: String,
    circles_x: Vec<f64>,
    text: String,
}

/// Parses `path` as XML (any malformed or truncated file fails here).
fn parse_svg(path: &Path) -> Svg {
    use xml::reader::{EventReader, XmlEvent};
    let file = std::fs::File::open(path).expect("steps.svg");
    let mut svg = Svg {
        root: String::new(),
        circles_x: Vec::new(),
        text: String::new(),
    };
    for event in EventReader::new(std::io::BufReader::new(file)) {
        match event.unwrap_or_else(|e| panic!("{}: not well-formed: {e}", path.display())) {
            XmlEvent::StartElement {
                name, attributes, ..
            } => {
                if svg.root.is_empty() {
                    svg.root = name.local_name.clone();
                }
                if name.local_name == "circle" {
                    let cx = attributes
                        .iter()
                        .find(|a| a.name.local_name == "cx")
                        .and_then(|a| a.value.parse().ok())
                        .expect("a circle's cx");
                    svg.circles_x.push(cx);
                }
            }
            XmlEvent::Characters(t) => {
                svg.text.push_str(&t);
                svg.text.push('\n');
            }
            _ => {}
        }
    }
    svg
}

/// The step numbers of steps.csv's rows.
fn csv_steps(dir: &Path) -> Vec<usize> {
    std::fs::read_to_string(dir.join("steps.csv"))
        .expect("steps.csv")
        .lines()
        .skip(1)
        .map(|l| {
            l.split(',')
                .next()
                .and_then(|v| v.parse().ok())
                .expect("step")
        })
        .collect()
}

/// One marker per row, placed along the step axis: the markers of rows 0..=N sit at
/// evenly spaced x positions. Plotters rounds each position to a whole pixel, so each
/// may be off the exact spacing by half a pixel, and the spacing itself (from the two
/// end markers) by one: 1 px.
fn assert_one_marker_per_row(svg: &Svg, rows: usize, what: &str) {
    assert_eq!(svg.root, "svg", "{what}");
    let x = &svg.circles_x;
    assert_eq!(x.len(), rows, "{what}: markers vs steps.csv rows");
    let n = (rows - 1) as f64;
    let (first, last) = (x[0], x[rows - 1]);
    assert!(last - first > 300.0, "{what}: markers span {first}..{last}");
    for (i, cx) in x.iter().enumerate() {
        let want = first + (last - first) * i as f64 / n;
        assert!(
            (cx - want).abs() <= 1.0,
            "{what}: marker {i} at x = {cx}, expected {want}"
        );
    }
}

#[test]
fn a_run_draws_one_point_per_step() {
    let dir = tmpdir("steps-plot").join("run");
    let o = run(&[
        "run",
        "hanging",
        "--steps",
        "6",
        "--solver",
        "cg",
        "--out",
        &s(&dir),
        "-q",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let steps = csv_steps(&dir);
    assert_eq!(steps, (0..=6).collect::<Vec<_>>());
    let svg = parse_svg(&dir.join("steps.svg"));
    assert_one_marker_per_row(&svg, steps.len(), "6 steps");
    // CG solved the steps' systems, so the tolerance panel has its two series.
    for label in [
        "mechanical energy",
        "Newton iterations",
        "CG iterations",
        "cg_tol_loosest",
        "cg_tol_tightest",
    ] {
        assert!(svg.text.contains(label), "no `{label}` in steps.svg");
    }
    // No temporary file of the atomic write is left.
    let leftovers: Vec<String> = std::fs::read_dir(&dir)
        .expect("folder")
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(".steps.svg"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
}

#[test]
fn a_killed_run_resumed_plots_every_step() {
    let base = tmpdir("steps-plot-kill");
    let text = stickslip::sim::scene::builtin("hanging")
        .expect("built-in scene")
        .replace("every = 5", "every = 2")
        .replace("cells = [10, 5]", "cells = [24, 12]");
    let scene = base.join("scene.toml");
    std::fs::write(&scene, text).expect("scene");
    let dir = base.join("run");
    let steps = 600;
    let mut child = common::cli::spawn(
        &[
            "run",
            &s(&scene),
            "--steps",
            &steps.to_string(),
            "--out",
            &s(&dir),
            "-q",
        ],
        false,
    );
    // SIGKILL once a few steps are done.
    let t = Instant::now();
    loop {
        let rows = std::fs::read_to_string(dir.join("steps.csv"))
            .map(|c| c.lines().count().saturating_sub(1))
            .unwrap_or(0);
        if rows >= 5 || child.try_wait().expect("wait").is_some() {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(120), "no progress");
        std::thread::sleep(Duration::from_millis(2));
    }
    let _ = child.kill();
    let _ = child.wait();
    // The killed run's plot is whole: drawn at its start and at checkpoints, each time
    // written to a temporary name and renamed.
    let killed = parse_svg(&dir.join("steps.svg"));
    assert_eq!(killed.root, "svg");
    assert!(
        !killed.circles_x.is_empty() && killed.circles_x.len() <= csv_steps(&dir).len(),
        "the killed run's plot has {} markers",
        killed.circles_x.len()
    );
    let o = run(&["run", "--resume", &s(&dir), "-q"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let summary: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.join("summary.json")).expect("summary.json"),
    )
    .expect("summary.json parses");
    let from = summary["resumed_from_step"].as_u64().expect("resumed");
    assert!(from < steps as u64, "the kill came after the run ended");
    let rows = csv_steps(&dir);
    assert_eq!(rows, (0..=steps).collect::<Vec<_>>());
    let svg = parse_svg(&dir.join("steps.svg"));
    assert_one_marker_per_row(&svg, rows.len(), "resumed");
    let _ = std::fs::remove_dir_all(&base);
}
