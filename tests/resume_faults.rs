//! `run --resume` continues only the folder's own run, with every option that shapes its
//! outputs, and leaves the folder as an uninterrupted run would: a checkpoint copied from
//! another run is refused with the folder unchanged; `--dump-systems` goes on after the
//! resume and a partial step dump is redone; a run whose steps are all done is finished;
//! the scene file is found from any working directory; a killed run's temporary files go;
//! summary.json's frame count is the frames on disk.

#![cfg(unix)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

mod common;
use common::cli::{assert_input_error, run, stderr, steps_without_timing, summary, tmpdir, BIN};

fn s(p: &Path) -> String {
    p.to_str().expect("utf-8 path").to_string()
}

fn ok(o: &Output, what: &str) {
    assert!(o.status.success(), "{what}: {}", stderr(o));
}

/// The `hanging` scene with `cells`, a frame every `every` steps and a checkpoint every
/// `checkpoint` steps, written to `dir/name`.
fn scene(dir: &Path, name: &str, cells: &str, every: usize, checkpoint: usize) -> PathBuf {
    let text = stickslip::sim::scene::builtin("hanging")
        .expect("built-in hanging")
        .replace(
            "every = 5",
            &format!("every = {every}\ncheckpoint_every = {checkpoint}"),
        )
        .replace("cells = [10, 5]", cells);
    let p = dir.join(name);
    std::fs::write(&p, text).expect("scene");
    p
}

/// Every file under `dir` (relative path, bytes), sorted.
fn tree(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    fn walk(root: &Path, d: &Path, out: &mut Vec<(PathBuf, Vec<u8>)>) {
        for e in std::fs::read_dir(d).expect("folder").flatten() {
            let p = e.path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                let rel = p.strip_prefix(root).expect("inside").to_path_buf();
                out.push((rel, std::fs::read(&p).expect("file")));
            }
        }
    }
    let mut v = Vec::new();
    walk(dir, dir, &mut v);
    v.sort();
    v
}

fn frame_names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir.join("frames"))
        .expect("frames")
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// A checkpoint copied from another run (another scene, fewer steps) into a run's folder
/// is refused, exit 2, naming the checkpoint, and the folder stays byte for byte.
#[test]
fn a_checkpoint_from_another_run_is_refused() {
    let dir = tmpdir("foreign");
    let a_scene = scene(&dir, "a.toml", "cells = [4, 2]", 2, 2);
    let b_scene = scene(&dir, "b.toml", "cells = [6, 3]", 2, 2);
    let (a, b) = (dir.join("a"), dir.join("b"));
    ok(
        &run(&["run", &s(&a_scene), "--out", &s(&a), "--steps", "4", "-q"]),
        "run a",
    );
    ok(
        &run(&["run", &s(&b_scene), "--out", &s(&b), "--steps", "10", "-q"]),
        "run b",
    );
    std::fs::copy(a.join("checkpoint.bin"), b.join("checkpoint.bin")).expect("copy");
    let before = tree(&b);
    let o = run(&["run", "--resume", &s(&b), "--steps", "12", "-q"]);
    let shown = s(&b.join("checkpoint.bin"));
    assert_input_error(&o, &shown, &["another run"]);
    assert!(tree(&b) == before, "the folder changed");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A run started with `--dump-systems` dumps after a resume too; a step whose dump a
/// killed run left partial is dumped whole; the systems are those of a run never stopped.
/// The refusal of `--resume` names the options it takes.
#[test]
fn a_resumed_run_keeps_dumping_systems() {
    let dir = tmpdir("dump");
    let sc = s(&scene(&dir, "s.toml", "cells = [4, 2]", 2, 2));
    let (reference, resumed) = (dir.join("reference"), dir.join("resumed"));
    let dump = ["--dump-systems", "all", "-q"];
    let mut args = vec!["run", &sc, "--steps", "4"];
    args.extend(dump);
    let r = s(&reference);
    let mut a = args.clone();
    a.extend(["--out", &r]);
    ok(&run(&a), "reference");
    let d = s(&resumed);
    let mut a = vec!["run", &sc, "--steps", "2", "--out", &d];
    a.extend(dump);
    ok(&run(&a), "first part");
    // What a kill in step 3's dump leaves: a whole iteration, a partial one.
    let step3 = resumed.join("systems/step_3");
    std::fs::create_dir_all(step3.join(".iter_1.partial")).expect("partial");
    std::fs::write(step3.join(".iter_1.partial/H.mtx"), "%%Matrix").expect("partial");
    std::fs::create_dir_all(step3.join("iter_7")).expect("stale");
    std::fs::write(step3.join("iter_7/H.mtx"), "%%Matrix").expect("stale");
    ok(
        &run(&["run", "--resume", &d, "--steps", "4", "-q"]),
        "resume",
    );
    let systems = |root: &Path| tree(&root.join("systems"));
    let (x, y) = (systems(&reference), systems(&resumed));
    let names = |t: &[(PathBuf, Vec<u8>)]| t.iter().map(|f| f.0.clone()).collect::<Vec<_>>();
    assert_eq!(names(&x), names(&y), "dumped files");
    assert!(x == y, "dumped systems differ");
    assert_eq!(
        steps_without_timing(&reference),
        steps_without_timing(&resumed)
    );

    let o = run(&["run", "--resume", &d, "--size", "2", "-q"]);
    let line = assert_input_error(&o, "--resume", &["--size"]);
    for accepted in ["--steps", "--end-time", "--threads", "--dump-systems"] {
        assert!(line.contains(accepted), "{accepted} not named: {line}");
    }
    let help = Command::new(BIN)
        .args(["run", "--help"])
        .output()
        .expect("help");
    let help = String::from_utf8_lossy(&help.stdout).into_owned();
    let at = help.find("--resume <DIR>").expect("--resume documented");
    let text = &help[at..];
    for accepted in ["--threads", "--dump-systems"] {
        assert!(text.contains(accepted), "help of --resume omits {accepted}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// A run killed after its last checkpoint, or that could not write its final summary,
/// says `running` with every step done: `--resume` finishes it (exit 0, `complete`) and
/// leaves steps.csv and the frames as they were.
#[test]
fn a_resume_finishes_a_run_whose_steps_are_done() {
    let dir = tmpdir("done");
    let sc = s(&scene(&dir, "s.toml", "cells = [4, 2]", 2, 2));
    let out = dir.join("out");
    let d = s(&out);
    ok(
        &run(&["run", &sc, "--out", &d, "--steps", "3", "-q"]),
        "run",
    );
    let csv = std::fs::read(out.join("steps.csv")).expect("csv");
    let frames = frame_names(&out);
    let text = std::fs::read_to_string(out.join("summary.json")).expect("summary");
    let running = text.replace("\"complete\"", "\"running\"");
    assert_ne!(text, running, "summary.json names its status");
    std::fs::write(out.join("summary.json"), running).expect("summary");
    let o = run(&["run", "--resume", &d, "-q"]);
    ok(&o, "resume of a done run");
    let sm = summary(&out);
    assert_eq!(sm["status"], "complete", "{sm}");
    assert_eq!(sm["steps_completed"], 3, "{sm}");
    assert_eq!(sm["frames"].as_u64(), Some(frames.len() as u64), "{sm}");
    assert_eq!(std::fs::read(out.join("steps.csv")).expect("csv"), csv);
    assert_eq!(frame_names(&out), frames);
    let _ = std::fs::remove_dir_all(&dir);
}

/// A run started with a relative scene path resumes from another working directory.
#[test]
fn a_resume_does_not_depend_on_the_working_directory() {
    let dir = tmpdir("cwd");
    scene(&dir, "s.toml", "cells = [4, 2]", 2, 2);
    let out = dir.join("out");
    let first = Command::new(BIN)
        .current_dir(&dir)
        .args(["run", "s.toml", "--out", "out", "--steps", "2", "-q"])
        .output()
        .expect("run");
    ok(&first, "first part");
    let elsewhere = dir.join("elsewhere");
    std::fs::create_dir_all(&elsewhere).expect("folder");
    let o = Command::new(BIN)
        .current_dir(&elsewhere)
        .args(["run", "--resume", &s(&out), "--steps", "4", "-q"])
        .output()
        .expect("resume");
    ok(&o, "resume from another folder");
    assert_eq!(summary(&out)["steps_completed"], 4);
    let _ = std::fs::remove_dir_all(&dir);
}

/// The temporary files a killed run left (an atomic write cut short) are gone after a
/// resume, and summary.json counts the frames on disk: a frame the resume removed (the
/// last step's, off the frame interval) is not counted.
#[test]
fn a_resume_leaves_no_temporary_files_and_counts_its_frames() {
    let dir = tmpdir("tmp");
    let sc = s(&scene(&dir, "s.toml", "cells = [4, 2]", 2, 2));
    let (out, reference) = (dir.join("out"), dir.join("reference"));
    let d = s(&out);
    ok(
        &run(&["run", &sc, "--out", &s(&reference), "--steps", "5", "-q"]),
        "reference",
    );
    ok(
        &run(&["run", &sc, "--out", &d, "--steps", "3", "-q"]),
        "first part",
    );
    let leftovers = [
        out.join("frames/.hanging_00004.vtk.stickslip-tmp-4194303-0"),
        out.join(".summary.json.stickslip-tmp-4194303-1"),
        out.join(".checkpoint.bin.stickslip-tmp-4194303-2"),
    ];
    for p in &leftovers {
        std::fs::write(p, "partial").expect("leftover");
    }
    ok(
        &run(&["run", "--resume", &d, "--steps", "5", "-q"]),
        "resume",
    );
    for p in &leftovers {
        assert!(!p.exists(), "{} left", p.display());
    }
    assert_eq!(frame_names(&out), frame_names(&reference));
    let (sm, rm) = (summary(&out), summary(&reference));
    assert_eq!(sm["frames"].as_u64(), Some(frame_names(&out).len() as u64));
    assert_eq!(sm["frames"], rm["frames"]);
    let _ = std::fs::remove_dir_all(&dir);
}
