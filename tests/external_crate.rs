//! A crate outside stickslip (tests/external-crate) depends on it by path with
//! `default-features = false`, uses only the names at the crate root, and checks every
//! solver against the others. It builds in release into this build's target folder, so
//! the dependencies compiled for the tests are reused (cargo releases its lock before it
//! runs the test binaries).

use std::process::Command;

#[test]
fn an_external_crate_embeds_the_solver_without_default_features() {
    let root = env!("CARGO_MANIFEST_DIR");
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args(["run", "--release", "--quiet", "--manifest-path"])
        .arg(format!("{root}/tests/external-crate/Cargo.toml"))
        .env("CARGO_TARGET_DIR", format!("{root}/target"))
        .output()
        .expect("cargo runs");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    print!("{stdout}");
    assert!(
        out.status.success(),
        "external crate failed:\n{stdout}\n{stderr}"
    );
    assert!(
        stdout.contains("external crate: all solvers agree"),
        "{stdout}"
    );
    // Without a GPU it says so loudly; with STICKSLIP_REQUIRE_GPU=1 it fails instead.
    assert!(stdout.contains("round 1 cholesky"), "{stdout}");
}

#[test]
fn the_solver_library_alone_pulls_in_none_of_the_command_lines_crates() {
    let root = env!("CARGO_MANIFEST_DIR");
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let out = Command::new(cargo)
        .args([
            "tree",
            "-e",
            "normal",
            "--no-default-features",
            "--prefix",
            "none",
            "--manifest-path",
        ])
        .arg(format!("{root}/Cargo.toml"))
        .output()
        .expect("cargo runs");
    let tree = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(tree.lines().any(|l| l.starts_with("wgpu ")), "{tree}");
    for name in ["clap", "indicatif", "plotters", "toml", "mshio"] {
        let hit = tree.lines().find(|l| l.starts_with(&format!("{name} ")));
        assert!(hit.is_none(), "{name} is a dependency of the core: {hit:?}");
    }
}
