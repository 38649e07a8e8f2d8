//! Running the built `stickslip` binary on files in a fresh temp directory, and checking
//! the one-line input-error contract (exit 2, `error: FILE: ...`).

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::atomic::{AtomicUsize, Ordering};

pub const BIN: &str = env!("CARGO_BIN_EXE_stickslip");

/// A fresh directory under the system temp dir, unique per test binary, process and call.
pub fn tmpdir(name: &str) -> PathBuf {
    static COUNT: AtomicUsize = AtomicUsize::new(0);
    let d = std::env::temp_dir().join(format!(
        "stickslip-{}-{}-{}-{name}",
        env!("CARGO_CRATE_NAME"),
        std::process::id(),
        COUNT.fetch_add(1, Ordering::Relaxed)
    ));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Writes `text` to `dir/name`; returns the path.
pub fn write(dir: &Path, name: &str, text: &str) -> String {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p.to_str().unwrap().to_string()
}

pub fn run(args: &[&str]) -> Output {
    Command::new(BIN)
        .args(args)
        .output()
        .expect("run stickslip")
}

pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Exit 2, one stderr line that starts with `error: FILE: ` (the file blamed is `file`,
/// not merely mentioned) and contains every `want`. Returns the line.
pub fn assert_input_error(o: &Output, file: &str, want: &[&str]) -> String {
    let e = stderr(o);
    assert_eq!(o.status.code(), Some(2), "stderr: {e}");
    assert_eq!(e.lines().count(), 1, "not one line: {e:?}");
    assert!(
        e.starts_with(&format!("error: {file}: ")),
        "file {file} not blamed first: {e}"
    );
    for w in want {
        assert!(e.contains(w), "missing {w:?} in: {e}");
    }
    assert!(!e.contains("panicked") && !e.contains("backtrace"), "{e}");
    e
}

/// A small deterministic generator (xorshift64*), for seeded kill delays.
pub struct Rng(pub u64);

impl Rng {
    /// The next value in 0..n (0 for n = 0).
    pub fn below(&mut self, n: u64) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545F4914F6CDD1D) >> 11) % n.max(1)
    }
}

/// Starts the binary with `args`, stdout discarded and stderr kept (or discarded).
pub fn spawn(args: &[&str], keep_stderr: bool) -> std::process::Child {
    use std::process::Stdio;
    Command::new(BIN)
        .args(args)
        .stdout(Stdio::null())
        .stderr(if keep_stderr {
            Stdio::piped()
        } else {
            Stdio::null()
        })
        .spawn()
        .expect("spawn stickslip")
}

/// A run folder's summary.json.
pub fn summary(dir: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join("summary.json")).expect("summary"))
        .expect("summary.json parses")
}

/// A run folder's steps.csv without its timing column (linear_seconds, the fifth).
pub fn steps_without_timing(dir: &Path) -> Vec<String> {
    std::fs::read_to_string(dir.join("steps.csv"))
        .expect("steps.csv")
        .lines()
        .map(|l| {
            let mut f: Vec<&str> = l.split(',').collect();
            f.remove(4);
            f.join(",")
        })
        .collect()
}
