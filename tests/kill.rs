//! SIGKILL, many times: a `run` killed after a few steps and a `solve` killed while it
//! writes leave only complete files. Every result file present parses whole, steps.csv
//! holds every step whose frame exists (and no partial row), the checkpoint is whole, and
//! summary.json says "running" (or "failed"), never "complete".

#![cfg(unix)]

use std::path::{Path, PathBuf};
use std::process::Child;
use std::time::{Duration, Instant};

mod common;
use common::cli::{run, stderr, tmpdir, Rng};

fn s(p: &Path) -> String {
    p.to_str().unwrap().to_string()
}

fn spawn(args: &[&str]) -> Child {
    common::cli::spawn(args, false)
}

/// SIGKILL (Child::kill on Unix) and reap.
fn kill(mut c: Child) {
    let _ = c.kill();
    let _ = c.wait();
}

/// A Matrix Market array vector, whole: the header, the size line and exactly that many
/// numbers, the file ending with a newline. Err says what is wrong.
fn check_vector(path: &Path) -> Result<usize, String> {
    let text = std::fs::read_to_string(path).map_err(|e| e.to_string())?;
    if !text.ends_with('\n') {
        return Err("does not end with a newline".into());
    }
    let mut lines = text.lines();
    if lines.next() != Some("%%MatrixMarket matrix array real general") {
        return Err("no header".into());
    }
    let mut data = lines.filter(|l| !l.starts_with('%'));
    let size: Vec<usize> = data
        .next()
        .ok_or("no size line")?
        .split_whitespace()
        .map(|t| t.parse().map_err(|_| format!("size token {t}")))
        .collect::<Result<_, _>>()?;
    if size.len() != 2 || size[1] != 1 {
        return Err(format!("size line {size:?}"));
    }
    let mut n = 0;
    for l in data {
        let v: f64 = l.trim().parse().map_err(|_| format!("value '{l}'"))?;
        if !v.is_finite() {
            return Err(format!("value {v}"));
        }
        n += 1;
    }
    if n != size[0] {
        return Err(format!("{n} values, the size line says {}", size[0]));
    }
    Ok(n)
}

/// A legacy VTK frame as `write_vtk` writes it, whole: every section's count matches.
fn check_vtk(path: &Path) -> Result<(), String> {
    let text = std::fs::read_to_string(path).map_err(|e| e.to_string())?;
    if !text.ends_with('\n') {
        return Err("does not end with a newline".into());
    }
    let lines: Vec<&str> = text.lines().collect();
    let mut k = 4;
    if lines.len() < 5 || lines[2] != "ASCII" || lines[3] != "DATASET UNSTRUCTURED_GRID" {
        return Err("no header".into());
    }
    let count = |line: &str, head: &str| -> Result<usize, String> {
        let rest = line
            .strip_prefix(head)
            .ok_or(format!("expected '{head}', found '{line}'"))?;
        rest.split_whitespace()
            .next()
            .and_then(|t| t.parse().ok())
            .ok_or(format!("no count in '{line}'"))
    };
    let numbers = |l: &str, want: usize| -> Result<(), String> {
        let v: Vec<f64> = l
            .split_whitespace()
            .map(|t| t.parse::<f64>().map_err(|_| format!("'{t}'")))
            .collect::<Result<_, _>>()?;
        (v.len() == want)
            .then_some(())
            .ok_or(format!("'{l}' is not {want} numbers"))
    };
    let n = count(lines[k], "POINTS ")?;
    k += 1;
    for _ in 0..n {
        numbers(lines.get(k).ok_or("points cut short")?, 3)?;
        k += 1;
    }
    let c = count(lines.get(k).ok_or("no CELLS")?, "CELLS ")?;
    k += 1 + c;
    let ct = count(lines.get(k).ok_or("no CELL_TYPES")?, "CELL_TYPES ")?;
    if ct != c {
        return Err("cell counts differ".into());
    }
    k += 1 + ct;
    if count(lines.get(k).ok_or("no POINT_DATA")?, "POINT_DATA ")? != n {
        return Err("POINT_DATA count".into());
    }
    k += 1;
    for name in ["velocity", "reaction_force"] {
        if lines.get(k) != Some(&format!("VECTORS {name} double").as_str()) {
            return Err(format!("no {name} section"));
        }
        k += 1;
        for _ in 0..n {
            numbers(lines.get(k).ok_or(format!("{name} cut short"))?, 3)?;
            k += 1;
        }
    }
    (k == lines.len())
        .then_some(())
        .ok_or(format!("{} lines after the last section", lines.len() - k))
}

/// The steps of a steps.csv whose every row is whole (as many fields as the header, each
/// a number), consecutive from 0.
fn check_csv(path: &Path) -> Result<Vec<usize>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| e.to_string())?;
    if !text.is_empty() && !text.ends_with('\n') {
        return Err("a partial row".into());
    }
    let mut lines = text.lines();
    let header = lines.next().ok_or("no header")?;
    let fields = header.split(',').count();
    let mut steps = Vec::new();
    for (k, l) in lines.enumerate() {
        let f: Vec<&str> = l.split(',').collect();
        if f.len() != fields {
            return Err(format!("row {k} has {} fields of {fields}", f.len()));
        }
        for t in &f {
            t.parse::<f64>()
                .map_err(|_| format!("row {k}: '{t}' is not a number"))?;
        }
        let step: usize = f[0].parse().map_err(|_| format!("row {k}: step"))?;
        if step != k {
            return Err(format!("row {k} holds step {step}"));
        }
        steps.push(step);
    }
    Ok(steps)
}

/// Result files in `dir` (recursively), skipping dot files (the lock, the manifest and
/// the temporary files, none of which is a result).
fn results(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') {
                continue;
            }
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push(p);
            }
        }
    }
    out
}

#[test]
fn killed_runs_leave_complete_files_and_say_so() {
    let dir = tmpdir("kill-run");
    let text = stickslip::sim::scene::builtin("hanging")
        .unwrap()
        .replace("every = 5", "every = 1")
        .replace("cells = [10, 5]", "cells = [24, 12]");
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, text).unwrap();
    // One folder for every run: each killed run's files are cleared by the next one.
    let out = dir.join("out");
    let mut rng = Rng(0x9e3779b97f4a7c15);
    let kills = 16;
    let mut rows_seen = Vec::new();
    for k in 0..kills {
        // Each run asks for a different step count, so its summary.json (written once the
        // folder is cleared) tells it apart from the killed run's before it.
        let steps = 100_000 + k;
        let steps_arg = steps.to_string();
        let child = spawn(&[
            "run",
            &s(&scene),
            "--out",
            &s(&out),
            "-q",
            "--steps",
            &steps_arg,
        ]);
        // Wait for a few completed steps of this run, then a little more, at random.
        let want_rows = 3 + rng.below(4) as usize;
        let t = Instant::now();
        loop {
            let fresh = std::fs::read_to_string(out.join("summary.json"))
                .ok()
                .and_then(|j| serde_json::from_str::<serde_json::Value>(&j).ok())
                .is_some_and(|v| v["steps"] == steps);
            let rows = std::fs::read_to_string(out.join("steps.csv"))
                .map(|c| c.lines().count().saturating_sub(1))
                .unwrap_or(0);
            if fresh && rows >= want_rows {
                break;
            }
            assert!(
                t.elapsed() < Duration::from_secs(120),
                "kill {k}: no progress"
            );
            std::thread::sleep(Duration::from_millis(1));
        }
        std::thread::sleep(Duration::from_micros(rng.below(20_000)));
        kill(child);

        let summary: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap())
                .unwrap_or_else(|e| panic!("kill {k}: summary.json: {e}"));
        let status = summary["status"].as_str().unwrap_or_default();
        assert!(
            status == "running" || status == "failed",
            "kill {k}: status {status}"
        );
        let steps = check_csv(&out.join("steps.csv"))
            .unwrap_or_else(|e| panic!("kill {k}: steps.csv: {e}"));
        let last = *steps.last().expect("the initial row");
        rows_seen.push(steps.len());
        for f in results(&out) {
            let name = f.file_name().unwrap().to_string_lossy().into_owned();
            if name.ends_with(".vtk") {
                check_vtk(&f).unwrap_or_else(|e| panic!("kill {k}: {name}: {e}"));
                let step: usize = name
                    .trim_end_matches(".vtk")
                    .rsplit('_')
                    .next()
                    .unwrap()
                    .parse()
                    .unwrap();
                // A frame is written after its step's row: the row is there.
                assert!(
                    step <= last,
                    "kill {k}: frame of step {step}, csv ends at {last}"
                );
            } else if name == "checkpoint.bin" {
                // Replaced by rename: whole, its header first (tests/resume.rs resumes
                // from such files).
                let b = std::fs::read(&f).expect("checkpoint");
                assert!(
                    b.starts_with(b"stickslip-checkpoint\n"),
                    "kill {k}: checkpoint"
                );
            } else if name == "frames.pvd" {
                // Replaced by rename: whole, and it lists no frame that is not there.
                let text = std::fs::read_to_string(&f).expect("frames.pvd");
                assert!(
                    text.trim_end().ends_with("</VTKFile>"),
                    "kill {k}: frames.pvd"
                );
                for listed in text.split("file=\"").skip(1) {
                    let rel = listed.split('"').next().expect("file");
                    assert!(out.join(rel).is_file(), "kill {k}: {rel} listed, absent");
                }
            } else if name == "steps.svg" {
                // Replaced by rename: whole (tests/steps_plot.rs parses it).
                let text = std::fs::read_to_string(&f).expect("steps.svg");
                assert!(
                    text.starts_with("<svg") && text.trim_end().ends_with("</svg>"),
                    "kill {k}: steps.svg"
                );
            } else {
                assert!(
                    name == "steps.csv" || name == "summary.json",
                    "kill {k}: unexpected {name}"
                );
            }
        }
    }
    eprintln!("{kills} runs killed; steps.csv rows at the kill: {rows_seen:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn killed_solves_leave_no_partial_result() {
    let dir = tmpdir("kill-solve");
    let sys = dir.join("sys");
    let o = run(&[
        "generate",
        "--dim",
        "2",
        "--nodes",
        "40000",
        "-q",
        "--out-dir",
        &s(&sys),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let p = |n: &str| s(&sys.join(n));
    let (h, g, bc) = (p("H.mtx"), p("g.mtx"), p("bc.json"));
    let (dx, f, rep) = (
        dir.join("dx.mtx"),
        dir.join("f.mtx"),
        dir.join("report.json"),
    );
    let args = [
        "solve",
        "--hessian",
        &h,
        "--gradient",
        &g,
        "--constraints",
        &bc,
        "--out",
        &s(&dx),
        "--reactions",
        &s(&f),
        "--report",
        &s(&rep),
        "-q",
    ];
    // One whole solve: the sizes every complete file must have, and how long writing takes.
    let o = run(&args);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let n = check_vector(&dx).unwrap();
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&rep).unwrap()).unwrap();
    let write_us = (r["seconds"]["write"].as_f64().unwrap() * 1e6) as u64;
    let mut rng = Rng(0x2545f4914f6cdd1d);
    let kills = 16;
    let mut outcomes = Vec::new();
    for k in 0..kills {
        for p in [&dx, &f, &rep] {
            let _ = std::fs::remove_file(p);
        }
        let names = || -> Vec<String> {
            std::fs::read_dir(&dir)
                .unwrap()
                .flatten()
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        };
        // Temporary files an earlier kill left behind.
        let before = names();
        let child = spawn(&args);
        // Kill while the results are being written: from the moment the first of them
        // (or its temporary file) appears, within twice the time writing takes.
        let t = Instant::now();
        loop {
            let started = names()
                .iter()
                .any(|n| n.contains("dx.mtx") && !before.contains(n));
            if started {
                break;
            }
            assert!(
                t.elapsed() < Duration::from_secs(300),
                "kill {k}: never wrote"
            );
            std::thread::sleep(Duration::from_micros(200));
        }
        std::thread::sleep(Duration::from_micros(rng.below(2 * write_us + 1)));
        kill(child);
        let mut present = Vec::new();
        for p in [&dx, &f] {
            if p.exists() {
                let len = check_vector(p).unwrap_or_else(|e| panic!("kill {k}: {p:?}: {e}"));
                assert_eq!(len, n, "kill {k}: {p:?}");
                present.push(p.file_name().unwrap().to_string_lossy().into_owned());
            }
        }
        if rep.exists() {
            let text = std::fs::read_to_string(&rep).unwrap();
            serde_json::from_str::<serde_json::Value>(&text)
                .unwrap_or_else(|e| panic!("kill {k}: report.json: {e}"));
            present.push("report.json".into());
        }
        outcomes.push(present.join("+"));
        // Whatever is left besides the results is a hidden temporary file.
        for e in std::fs::read_dir(&dir).unwrap().flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            assert!(
                ["sys", "dx.mtx", "f.mtx", "report.json"].contains(&name.as_str())
                    || (name.starts_with('.') && name.contains(".stickslip-tmp-")),
                "kill {k}: {name}"
            );
        }
    }
    eprintln!(
        "{kills} solves killed while writing ({} µs of writing); files present after each: {outcomes:?}",
        write_us
    );
    let _ = std::fs::remove_dir_all(&dir);
}
