//! A scene that fails a check, or a run whose resources are missing, leaves the output
//! folder of an earlier run byte for byte: every input and resource check (scene keys and
//! values, mesh file, static conditions, GPU adapter) completes before anything in the
//! folder changes.

#![cfg(unix)]

use std::path::{Path, PathBuf};
use std::process::Command;

mod common;
use common::cli::{stderr, tmpdir, BIN};

fn s(p: &Path) -> String {
    p.to_str().expect("utf-8 path").to_string()
}

/// Every entry under `dir` (relative path, bytes; folders with no bytes), sorted.
fn tree(dir: &Path) -> Vec<(PathBuf, Option<Vec<u8>>)> {
    fn walk(root: &Path, d: &Path, out: &mut Vec<(PathBuf, Option<Vec<u8>>)>) {
        for e in std::fs::read_dir(d).expect("folder").flatten() {
            let p = e.path();
            let rel = p.strip_prefix(root).expect("inside").to_path_buf();
            if p.is_dir() {
                out.push((rel, None));
                walk(root, &p, out);
            } else {
                out.push((rel, Some(std::fs::read(&p).expect("file"))));
            }
        }
    }
    let mut v = Vec::new();
    walk(dir, dir, &mut v);
    v.sort();
    v
}

/// What a case is, its scene, its extra options, its environment and its exit code.
type Case = (&'static str, String, &'static [&'static str], Env, i32);
type Env = &'static [(&'static str, &'static str)];

#[test]
fn bad_scenes_and_missing_adapters_leave_the_folder_as_it_was() {
    let dir = tmpdir("keep");
    let base = stickslip::sim::scene::builtin("hanging")
        .expect("built-in hanging")
        .replace("cells = [10, 5]", "cells = [4, 2]");
    let good = dir.join("good.toml");
    std::fs::write(&good, &base).expect("scene");
    let out = dir.join("out");
    let o = Command::new(BIN)
        .args(["run", &s(&good), "--out", &s(&out), "--steps", "5", "-q"])
        .output()
        .expect("run");
    assert!(o.status.success(), "{}", stderr(&o));
    let before = tree(&out);
    assert!(
        before
            .iter()
            .any(|(p, _)| p.starts_with("frames") && p.extension().is_some()),
        "the earlier run wrote frames"
    );

    let far = "\n[[boundary]]\nkind = \"plane\"\nnormal = [0.0, 1.0]\noffset = -1.0\n\
               region = { box = { min = [-0.1, -0.01], max = [1.1, 0.01] } }\n";
    let cases: [Case; 5] = [
        (
            "unknown key",
            base.replace("time_step = 0.01", "time_step = 0.01\nwobble = 3"),
            &[],
            &[],
            2,
        ),
        (
            "bad value",
            base.replace("time_step = 0.01", "time_step = -0.01"),
            &[],
            &[],
            2,
        ),
        (
            "missing mesh file",
            base.replace(
                "mesh = { kind = \"sheet\", size = [1.0, 0.5], cells = [4, 2] }",
                "mesh = { kind = \"gmsh\", file = \"missing.msh\" }",
            ),
            &[],
            &[],
            2,
        ),
        ("obstacle too far", format!("{base}{far}"), &[], &[], 2),
        (
            "no adapter",
            base.clone(),
            &["--newton", "gpu"],
            // Names no backend: wgpu sees no adapter, whatever the machine has.
            &[("WGPU_BACKEND", "none")],
            1,
        ),
    ];
    for (what, text, extra, env, code) in cases {
        let (extra, env): (&[&str], &[(&str, &str)]) = (extra, env);
        let sc = dir.join("bad.toml");
        std::fs::write(&sc, &text).expect("scene");
        let mut c = Command::new(BIN);
        c.args(["run", &s(&sc), "--out", &s(&out), "--steps", "5", "-q"])
            .args(extra);
        for (k, v) in env {
            c.env(k, v);
        }
        let o = c.output().expect("run");
        assert_eq!(o.status.code(), Some(code), "{what}: {}", stderr(&o));
        assert_eq!(stderr(&o).lines().count(), 1, "{what}: {}", stderr(&o));
        let after = tree(&out);
        let names =
            |t: &[(PathBuf, Option<Vec<u8>>)]| t.iter().map(|f| f.0.clone()).collect::<Vec<_>>();
        assert_eq!(names(&before), names(&after), "{what}: entries");
        assert!(before == after, "{what}: the folder's bytes changed");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
