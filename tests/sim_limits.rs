//! Run limits: huge meshes and step counts, unsafe scene names and bad options are input
//! errors (exit code 2) raised before anything is written; other failures exit with 1.

use std::path::PathBuf;
use stickslip::error::InputError;
use stickslip::sim::driver::{run, RunError, RunOptions};
use stickslip::sim::scene::MAX_STEPS;

fn tmp(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("stickslip-sim-limits-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

fn input_error(opts: &RunOptions) -> InputError {
    match run(opts) {
        Err(e @ RunError::Input(_)) => {
            assert_eq!(e.exit_code(), 2);
            match e {
                RunError::Input(i) => i,
                _ => unreachable!(),
            }
        }
        other => panic!("expected an input error, got {other:?}"),
    }
}

#[test]
fn huge_size_on_a_box_is_an_input_error() {
    let dir = tmp("size");
    let out = dir.join("out");
    let e = input_error(&RunOptions {
        scene: Some("drop".into()),
        out: Some(out.clone()),
        size: Some(1e7),
        quiet: true,
        ..RunOptions::default()
    });
    assert!(e.entry.ends_with(".mesh.cells"), "{e}");
    assert!(e.problem.contains("--size"), "{e}");
    assert!(!out.exists(), "nothing is written for a rejected scene");
    for size in [0.0, -2.0, f64::NAN] {
        let e = input_error(&RunOptions {
            scene: Some("drop".into()),
            out: Some(out.clone()),
            size: Some(size),
            quiet: true,
            ..RunOptions::default()
        });
        assert_eq!(e.file, "--size", "{e}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn step_counts_are_capped() {
    let e = input_error(&RunOptions {
        scene: Some("hanging".into()),
        steps: Some(MAX_STEPS + 1),
        quiet: true,
        ..RunOptions::default()
    });
    assert_eq!(e.file, "--steps", "{e}");
    let dir = tmp("steps");
    let path = dir.join("long.toml");
    let text = stickslip::sim::scene::builtin("hanging").expect("built-in");
    let steps_line = text
        .lines()
        .find(|l| l.starts_with("steps"))
        .expect("hanging gives steps");
    std::fs::write(&path, text.replace(steps_line, "end_time = 1e300")).expect("write");
    let e = input_error(&RunOptions {
        scene: Some(path.display().to_string()),
        out: Some(dir.join("out")),
        quiet: true,
        ..RunOptions::default()
    });
    assert_eq!(e.entry, "end_time", "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn scene_names_cannot_escape_the_output_folder() {
    let dir = tmp("name");
    let text = stickslip::sim::scene::builtin("hanging").expect("built-in");
    let name_line = text
        .lines()
        .find(|l| l.starts_with("name"))
        .expect("hanging has a name");
    for bad in ["", "../escape", "a/b", "..", "a\\\\b"] {
        let path = dir.join("bad.toml");
        std::fs::write(&path, text.replace(name_line, &format!("name = \"{bad}\"")))
            .expect("write");
        let e = input_error(&RunOptions {
            scene: Some(path.display().to_string()),
            out: Some(dir.join("out")),
            quiet: true,
            ..RunOptions::default()
        });
        assert_eq!(e.entry, "name", "{bad:?}: {e}");
        assert!(!dir.join("out").exists());
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn exit_codes() {
    let input = RunError::Input(InputError::new("f.toml", "steps", "bad"));
    assert_eq!(input.exit_code(), 2);
    let solve = RunError::Solve {
        step: 3,
        time: 0.03,
        cause: "the Cholesky solve has relative residual 1e-3".into(),
    };
    assert_eq!(solve.exit_code(), 1);
    assert!(solve.to_string().starts_with("step 3 "), "{solve}");
    let output = RunError::Output {
        path: "out".into(),
        cause: "denied".into(),
    };
    assert_eq!(output.exit_code(), 1);
}

/// A scene without moving boundaries that runs out of Newton iterations says so without
/// a k_M or a count of moving nodes it does not have; with moving boundaries it names both.
#[test]
fn newton_limit_messages_name_only_what_the_scene_has() {
    let hanging = stickslip::sim::scene::builtin("hanging").expect("hanging");
    let capped = format!("{hanging}\n[solver]\nmax_newton_iterations = 1\n");
    let dir = tmp("newton-limit");
    let file = dir.join("hanging.toml");
    std::fs::write(&file, &capped).expect("scene");
    let opts = RunOptions {
        scene: Some(file.to_str().expect("utf-8").to_string()),
        out: Some(dir.join("out")),
        quiet: true,
        ..RunOptions::default()
    };
    let e = stickslip::sim::driver::run(&opts).expect_err("one Newton iteration is too few");
    let msg = e.to_string();
    assert!(
        msg.contains("Newton did not converge in 1 iterations"),
        "{msg}"
    );
    assert!(!msg.contains("k_M") && !msg.contains("moving"), "{msg}");
    let twist = stickslip::sim::scene::builtin("twist").expect("twist");
    let capped = twist.replace(
        "[moving]",
        "[solver]\nmax_newton_iterations = 1\n\n[moving]",
    );
    let file = dir.join("twist.toml");
    std::fs::write(&file, &capped).expect("scene");
    let opts = RunOptions {
        scene: Some(file.to_str().expect("utf-8").to_string()),
        out: Some(dir.join("out2")),
        quiet: true,
        ..RunOptions::default()
    };
    let msg = stickslip::sim::driver::run(&opts)
        .expect_err("one Newton iteration is too few")
        .to_string();
    assert!(
        msg.contains("k_M = ") && msg.contains("unsatisfied moving nodes"),
        "{msg}"
    );
}
