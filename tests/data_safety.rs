//! Output safety through the binary: no output destroys an input or another output,
//! outputs are checked before any input is read, result files are replaced by rename,
//! an output folder holds one run's files, and summary.json says how far a run got.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

mod common;
use common::cli::{assert_input_error, run, stderr, tmpdir, BIN};

/// A generated 2D system in `dir/sys`: (H, g, bc) paths.
fn system(dir: &Path, extra: &[&str]) -> (String, String, String) {
    let sys = dir.join("sys");
    let mut args = vec!["generate", "--dim", "2", "--nodes", "36", "-q", "--out-dir"];
    let s = sys.to_str().unwrap().to_string();
    args.push(&s);
    args.extend_from_slice(extra);
    let o = run(&args);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let p = |n: &str| sys.join(n).to_str().unwrap().to_string();
    (p("H.mtx"), p("g.mtx"), p("bc.json"))
}

fn s(p: &Path) -> String {
    p.to_str().unwrap().to_string()
}

/// Every file under `dir` (recursively) with its bytes, to show nothing changed.
fn snapshot(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            let t = std::fs::symlink_metadata(&p).unwrap().file_type();
            if t.is_dir() {
                stack.push(p);
            } else if t.is_file() {
                out.push((p.clone(), std::fs::read(&p).unwrap()));
            }
        }
    }
    out.sort();
    out
}

#[test]
fn outputs_never_overwrite_inputs_or_each_other() {
    let dir = tmpdir("same-file");
    let (h, g, bc) = system(&dir, &[]);
    let dx = s(&dir.join("dx.mtx"));
    let base = [
        "solve",
        "--hessian",
        &h,
        "--gradient",
        &g,
        "--constraints",
        &bc,
    ];
    #[cfg(unix)]
    let soft = {
        let p = dir.join("soft.mtx");
        std::os::unix::fs::symlink(&g, &p).unwrap();
        s(&p)
    };
    let hard = s(&dir.join("hard.mtx"));
    std::fs::hard_link(&h, &hard).unwrap();
    let mut cases: Vec<(Vec<&str>, &str, &str)> = vec![
        (vec!["--out", &g], &g, "the input --gradient"),
        (vec!["--out", &h], &h, "the input --hessian"),
        (
            vec!["--out", &dx, "--reactions", &bc],
            &bc,
            "the input --constraints",
        ),
        (
            vec!["--out", &dx, "--report", &h],
            &h,
            "the input --hessian",
        ),
        (vec!["--out", &hard], &hard, "the input --hessian"),
        (
            vec!["--out", &dx, "--reactions", &dx],
            &dx,
            "the output --out",
        ),
    ];
    #[cfg(unix)]
    cases.push((vec!["--out", &soft], &soft, "the input --gradient"));
    let before = snapshot(&dir);
    for (extra, blamed, want) in &cases {
        let mut args = base.to_vec();
        args.extend_from_slice(extra);
        let o = run(&args);
        assert_input_error(&o, blamed, &["is the same file as", want]);
        assert_eq!(snapshot(&dir), before, "{extra:?} changed a file");
    }

    // export into a folder that holds one of its inputs under an output name.
    let x = dir.join("x");
    std::fs::create_dir_all(&x).unwrap();
    let hhat = s(&x.join("hhat.mtx"));
    std::fs::copy(&h, &hhat).unwrap();
    let before = snapshot(&dir);
    let o = run(&[
        "export",
        "--hessian",
        &hhat,
        "--gradient",
        &g,
        "--constraints",
        &bc,
        "--out-dir",
        &s(&x),
        "-q",
    ]);
    assert_input_error(&o, &s(&x), &["hhat.mtx", "the input --hessian"]);
    assert_eq!(snapshot(&dir), before);

    // recover onto each of its inputs.
    let e = dir.join("e");
    let o = run(&[
        "export",
        "--hessian",
        &h,
        "--gradient",
        &g,
        "--constraints",
        &bc,
        "--out-dir",
        &s(&e),
        "-q",
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let layout = s(&e.join("layout.json"));
    let y = s(&e.join("bhat.mtx"));
    let before = snapshot(&dir);
    for (out, want) in [
        (&layout, "--layout"),
        (&y, "--solution"),
        (&h, "--hessian"),
        (&g, "--gradient"),
    ] {
        for extra in [
            vec!["--out", out.as_str()],
            vec!["--out", &dx, "--reactions", out],
        ] {
            let mut args = vec![
                "recover",
                "--layout",
                &layout,
                "--solution",
                &y,
                "--hessian",
                &h,
                "--gradient",
                &g,
            ];
            args.extend_from_slice(&extra);
            let o = run(&args);
            assert_input_error(&o, out, &[&format!("the input {want}")]);
            assert_eq!(snapshot(&dir), before);
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn outputs_are_checked_before_any_input_is_read() {
    let dir = tmpdir("outputs-first");
    // The inputs do not exist: an error about the output proves it came first.
    let nowhere = s(&dir.join("no-such-H.mtx"));
    let missing = s(&dir.join("missing-dir/dx.mtx"));
    let o = run(&[
        "solve",
        "--hessian",
        &nowhere,
        "--gradient",
        &nowhere,
        "--constraints",
        &nowhere,
        "--out",
        &missing,
    ]);
    assert_input_error(&o, &missing, &["--out", "does not exist"]);
    let o = run(&[
        "solve",
        "--hessian",
        &nowhere,
        "--gradient",
        &nowhere,
        "--constraints",
        &nowhere,
        "--out",
        &s(&dir),
    ]);
    assert_input_error(&o, &s(&dir), &["--out", "is a folder"]);
    let o = run(&[
        "recover",
        "--layout",
        &nowhere,
        "--solution",
        &nowhere,
        "--hessian",
        &nowhere,
        "--gradient",
        &nowhere,
        "--out",
        &s(&dir.join("dx.mtx")),
        "--reactions",
        &missing,
    ]);
    assert_input_error(&o, &missing, &["--reactions", "does not exist"]);
    // A folder that cannot be created under a file.
    let file = dir.join("a-file");
    std::fs::write(&file, "x").unwrap();
    let under = s(&file.join("out"));
    let o = run(&[
        "export",
        "--hessian",
        &nowhere,
        "--gradient",
        &nowhere,
        "--constraints",
        &nowhere,
        "--out-dir",
        &under,
    ]);
    assert_input_error(&o, &under, &["--out-dir", "a-file is a file"]);
    let o = run(&["run", &nowhere, "--out", &under, "-q"]);
    assert_input_error(&o, &under, &["--out", "a-file is a file"]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[cfg(unix)]
#[test]
fn result_files_are_replaced_by_rename() {
    let dir = tmpdir("rename");
    let (h, g, bc) = system(&dir, &[]);
    let dx = dir.join("dx.mtx");
    std::fs::write(&dx, "old").unwrap();
    // A hard link to the old file keeps the old bytes: the result was renamed into place,
    // not written through the old file.
    let old = dir.join("old.mtx");
    std::fs::hard_link(&dx, &old).unwrap();
    // A symbolic link as an output stays a link, to the new file.
    let target = dir.join("f-target.mtx");
    std::fs::write(&target, "old").unwrap();
    let link = dir.join("f.mtx");
    std::os::unix::fs::symlink("f-target.mtx", &link).unwrap();
    let o = run(&[
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
        &s(&link),
        "-q",
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert_eq!(std::fs::read_to_string(&old).unwrap(), "old");
    let new = std::fs::read_to_string(&dx).unwrap();
    assert!(new.starts_with("%%MatrixMarket"), "{new}");
    assert!(std::fs::symlink_metadata(&link)
        .unwrap()
        .file_type()
        .is_symlink());
    assert!(std::fs::read_to_string(&target)
        .unwrap()
        .starts_with("%%MatrixMarket"));
    // No temporary file is left behind.
    let leftovers: Vec<String> = std::fs::read_dir(&dir)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.contains("stickslip-tmp"))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The `hanging` scene with a frame every step (and `extra` TOML appended).
fn scene(dir: &Path, cells: &str, extra: &str) -> String {
    let text = stickslip::sim::scene::builtin("hanging")
        .unwrap()
        .replace("every = 5", "every = 1")
        .replace("cells = [10, 5]", cells);
    let p = dir.join("scene.toml");
    std::fs::write(&p, format!("{text}\n{extra}")).unwrap();
    s(&p)
}

fn frame_steps(out: &Path) -> Vec<usize> {
    let mut steps: Vec<usize> = std::fs::read_dir(out.join("frames"))
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| !n.starts_with('.'))
        .map(|n| {
            n.trim_end_matches(".vtk")
                .rsplit('_')
                .next()
                .unwrap()
                .parse()
                .unwrap()
        })
        .collect();
    steps.sort();
    steps
}

fn summary(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap()
}

#[test]
fn a_reused_folder_holds_one_run() {
    let dir = tmpdir("reuse");
    let sc = scene(&dir, "cells = [10, 5]", "");
    let out = dir.join("out");
    for steps in ["5", "2"] {
        let o = run(&["run", &sc, "--out", &s(&out), "--steps", steps, "-q"]);
        assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    }
    assert_eq!(frame_steps(&out), vec![0, 1, 2]);
    let sm = summary(&out);
    assert_eq!(sm["frames"], 3);
    assert_eq!(sm["status"], "complete");
    let csv = std::fs::read_to_string(out.join("steps.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + 3);

    // export --no-mtx after an export with the Matrix Market copies.
    let (h, g, bc) = system(&dir, &[]);
    let e = dir.join("e");
    for extra in [None, Some("--no-mtx")] {
        let mut args = vec![
            "export",
            "--hessian",
            &h,
            "--gradient",
            &g,
            "--constraints",
            &bc,
            "-q",
            "--out-dir",
        ];
        let es = s(&e);
        args.push(&es);
        args.extend(extra);
        let o = run(&args);
        assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    }
    assert!(e.join("hhat.petsc").exists());
    assert!(!e.join("hhat.mtx").exists() && !e.join("bhat.mtx").exists());

    // generate without --matrix-form after one with it: B.mtx and p.mtx go, so a solve
    // can no longer pick up the old system's constraints.
    let (h, g, _) = system(&dir, &["--matrix-form"]);
    let b = dir.join("sys/B.mtx");
    assert!(b.exists());
    system(&dir, &[]);
    assert!(!b.exists() && !dir.join("sys/p.mtx").exists());
    let o = run(&[
        "solve",
        "--hessian",
        &h,
        "--gradient",
        &g,
        "--constraint-matrix",
        &s(&b),
        "--dim",
        "2",
        "--out",
        &s(&dir.join("dx.mtx")),
    ]);
    assert_input_error(&o, &s(&b), &["cannot read"]);

    // A folder holding files with run's output names that no run wrote is refused, and
    // taken with --overwrite, which leaves other files alone.
    let hand = dir.join("hand");
    std::fs::create_dir_all(hand.join("frames")).unwrap();
    std::fs::write(hand.join("steps.csv"), "mine").unwrap();
    std::fs::write(hand.join("frames/old_00009.vtk"), "mine").unwrap();
    std::fs::write(hand.join("notes.txt"), "mine").unwrap();
    let o = run(&["run", &sc, "--out", &s(&hand), "--steps", "1", "-q"]);
    assert_input_error(&o, &s(&hand), &["steps.csv", "--overwrite"]);
    assert_eq!(
        std::fs::read_to_string(hand.join("steps.csv")).unwrap(),
        "mine"
    );
    let o = run(&[
        "run",
        &sc,
        "--out",
        &s(&hand),
        "--steps",
        "1",
        "-q",
        "--overwrite",
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert_eq!(frame_steps(&hand), vec![0, 1]);
    assert_eq!(
        std::fs::read_to_string(hand.join("notes.txt")).unwrap(),
        "mine"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_second_concurrent_run_into_a_folder_refuses() {
    let dir = tmpdir("lock");
    let sc = scene(&dir, "cells = [20, 10]", "");
    let out = dir.join("out");
    let mut first = Command::new(BIN)
        .args(["run", &sc, "--out", &s(&out), "--steps", "100000", "-q"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // Wait until the first run has taken the folder (its summary says running).
    let t = std::time::Instant::now();
    while !out.join("summary.json").exists() {
        assert!(t.elapsed().as_secs() < 120, "the first run never started");
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    let o = run(&["run", &sc, "--out", &s(&out), "--steps", "1", "-q"]);
    // Another command's output file in that folder is refused too (nothing replaced).
    let sys = dir.join("sys");
    let g = run(&[
        "generate",
        "--dim",
        "2",
        "--nodes",
        "50",
        "-q",
        "--out-dir",
        &s(&sys),
    ]);
    assert_eq!(g.status.code(), Some(0), "{}", stderr(&g));
    let steps = out.join("steps.csv");
    let before = std::fs::read(&steps).ok();
    let solve = run(&[
        "solve",
        "--hessian",
        &s(&sys.join("H.mtx")),
        "--gradient",
        &s(&sys.join("g.mtx")),
        "--constraints",
        &s(&sys.join("bc.json")),
        "--out",
        &s(&steps),
    ]);
    first.kill().unwrap();
    first.wait().unwrap();
    assert_input_error(&o, &s(&out), &["another stickslip process", "writing into"]);
    assert_input_error(
        &solve,
        &s(&steps),
        &["another stickslip process", "writing into the folder"],
    );
    if let Some(before) = before {
        assert!(
            std::fs::read(&steps).unwrap().starts_with(&before),
            "solve replaced the running run's steps.csv"
        );
    }
    assert_eq!(summary(&out)["status"], "running");
    // Once the first has ended (killed), the folder can be taken again.
    let o = run(&["run", &sc, "--out", &s(&out), "--steps", "1", "-q"]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    assert_eq!(summary(&out)["status"], "complete");
    assert_eq!(frame_steps(&out), vec![0, 1]);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn summary_says_failed_with_the_message() {
    let dir = tmpdir("failed");
    // One Newton iteration per step is too few: step 1 fails.
    let sc = scene(
        &dir,
        "cells = [10, 5]",
        "[solver]\nmax_newton_iterations = 1\n",
    );
    let out = dir.join("out");
    let o = run(&["run", &sc, "--out", &s(&out), "-q"]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    let sm = summary(&out);
    assert_eq!(sm["status"], "failed");
    let line = stderr(&o);
    assert_eq!(
        format!("error: {}", sm["message"].as_str().unwrap()),
        line.trim_end()
    );
    assert_eq!(sm["steps_completed"], 0);
    // steps.csv holds the initial state, written before the failure.
    let csv = std::fs::read_to_string(out.join("steps.csv")).unwrap();
    assert_eq!(csv.lines().count(), 2, "{csv}");
    // A complete run says so, with every step done.
    let sc = scene(&dir, "cells = [10, 5]", "");
    let o = run(&["run", &sc, "--out", &s(&out), "--steps", "3", "-q"]);
    assert_eq!(o.status.code(), Some(0), "{}", stderr(&o));
    let sm = summary(&out);
    assert_eq!(sm["status"], "complete");
    assert_eq!(sm["steps_completed"], 3);
    assert!(sm["message"].is_null());
    let _ = std::fs::remove_dir_all(&dir);
}
