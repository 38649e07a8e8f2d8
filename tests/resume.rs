//! Long runs survive: a `run` killed (SIGKILL) at seeded points, or stopped by SIGINT or
//! SIGTERM, resumes with `run --resume` to the bits of a run that was never stopped
//! (every non-timing column of steps.csv and every frame file, byte for byte), on the CPU
//! loop and on the device loop; and a checkpoint that does not fit is refused in one line
//! with exit 2 and the folder unchanged.

#![cfg(unix)]

use std::path::{Path, PathBuf};
use std::process::{Child, Output};
use std::time::{Duration, Instant, SystemTime};

mod common;
use common::cli::{assert_input_error, run, stderr, steps_without_timing, summary, tmpdir, Rng};

fn s(p: &Path) -> String {
    p.to_str().expect("utf-8 path").to_string()
}

fn spawn(args: &[&str]) -> Child {
    common::cli::spawn(args, true)
}

fn ok(o: &Output, what: &str) {
    assert!(o.status.success(), "{what}: {}", stderr(o));
}

/// Every frame, by name.
fn frames(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir.join("frames"))
        .map(|rd| {
            rd.flatten()
                .map(|e| {
                    (
                        e.file_name().to_string_lossy().into_owned(),
                        std::fs::read(e.path()).expect("frame"),
                    )
                })
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

fn assert_same_run(reference: &Path, resumed: &Path, what: &str) {
    let (a, b) = (
        steps_without_timing(reference),
        steps_without_timing(resumed),
    );
    assert_eq!(a.len(), b.len(), "{what}: steps.csv rows");
    for (k, (x, y)) in a.iter().zip(&b).enumerate() {
        assert_eq!(x, y, "{what}: steps.csv line {k}");
    }
    let (fa, fb) = (frames(reference), frames(resumed));
    let names = |f: &[(String, Vec<u8>)]| f.iter().map(|x| x.0.clone()).collect::<Vec<_>>();
    assert_eq!(names(&fa), names(&fb), "{what}: frame files");
    for ((n, x), (_, y)) in fa.iter().zip(&fb) {
        assert!(x == y, "{what}: frame {n} differs");
    }
}

/// frames.pvd lists exactly the frames on disk, in step order, each with the simulated
/// time its title line gives (the same f64).
fn assert_collection_lists_frames(dir: &Path, what: &str) {
    let text = std::fs::read_to_string(dir.join("frames.pvd")).expect("frames.pvd");
    assert!(
        text.starts_with("<?xml") && text.trim_end().ends_with("</VTKFile>"),
        "{what}: {text}"
    );
    let attr = |line: &str, name: &str| -> String {
        let key = format!("{name}=\"");
        let at = line.find(&key).expect("attribute") + key.len();
        line[at..].split('"').next().expect("value").to_string()
    };
    let listed: Vec<(String, f64)> = text
        .lines()
        .filter(|l| l.contains("<DataSet"))
        .map(|l| {
            let t = attr(l, "timestep").parse().expect("a time");
            (attr(l, "file"), t)
        })
        .collect();
    let on_disk: Vec<(String, f64)> = frames(dir)
        .iter()
        .map(|(name, bytes)| {
            let title = String::from_utf8_lossy(bytes)
                .lines()
                .nth(1)
                .expect("title")
                .to_string();
            let t = title
                .rsplit_once(" t = ")
                .expect("time")
                .1
                .parse()
                .expect("t");
            (format!("frames/{name}"), t)
        })
        .collect();
    assert_eq!(
        listed.len(),
        on_disk.len(),
        "{what}: {listed:?} vs {on_disk:?}"
    );
    for (a, b) in listed.iter().zip(&on_disk) {
        assert!(
            a.0 == b.0 && a.1.to_bits() == b.1.to_bits(),
            "{what}: {a:?} vs {b:?}"
        );
    }
}

/// Waits until the run has written its first checkpoint (or has ended).
fn wait_for_checkpoint(c: &mut Child, dir: &Path) {
    let t = Instant::now();
    while !dir.join("checkpoint.bin").exists() && c.try_wait().expect("wait").is_none() {
        assert!(
            t.elapsed() < Duration::from_secs(120),
            "no checkpoint after 2 min"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
}

/// Kills `args` (writing to `dir`) with SIGKILL once steps.csv holds `rows` steps, plus
/// `extra_ms`, resumes it until it completes, and compares it with `reference`. Returns
/// the step the resume started from (the last one when the run had ended before the kill).
fn kill_and_resume(
    args: &[&str],
    dir: &Path,
    reference: &Path,
    rows: usize,
    extra_ms: u64,
    what: &str,
) -> Option<u64> {
    let mut a: Vec<&str> = args.to_vec();
    let d = s(dir);
    a.extend(["--out", &d, "-q"]);
    let mut c = spawn(&a);
    wait_for_checkpoint(&mut c, dir);
    let t = Instant::now();
    loop {
        let done = std::fs::read_to_string(dir.join("steps.csv"))
            .map(|text| text.lines().count().saturating_sub(2))
            .unwrap_or(0);
        if done >= rows || c.try_wait().expect("wait").is_some() {
            break;
        }
        assert!(
            t.elapsed() < Duration::from_secs(120),
            "{what}: no progress"
        );
        std::thread::sleep(Duration::from_millis(2));
    }
    std::thread::sleep(Duration::from_millis(extra_ms));
    let _ = c.kill();
    let _ = c.wait();
    let o = run(&["run", "--resume", &d, "-q"]);
    // A run killed after its last checkpoint has every step done: the resume finishes it.
    ok(&o, what);
    let sm = summary(dir);
    assert_eq!(sm["status"], "complete", "{what}");
    let from = sm["resumed_from_step"].as_u64();
    assert!(from.is_some(), "{what}: {sm}");
    eprintln!("{what}: resumed from step {from:?}");
    assert_same_run(reference, dir, what);
    assert_collection_lists_frames(reference, what);
    assert_collection_lists_frames(dir, what);
    from
}

fn reference_run(args: &[&str], name: &str) -> (PathBuf, f64) {
    let dir = tmpdir(name).join("reference");
    let mut a: Vec<&str> = args.to_vec();
    let d = s(&dir);
    a.extend(["--out", &d, "-q"]);
    let t = Instant::now();
    ok(&run(&a), name);
    (dir, t.elapsed().as_secs_f64())
}

/// The CPU loop killed at seeded points, on 1 and 2 threads (the CPU solvers give the
/// same bits on any count).
#[test]
fn killed_cpu_runs_resume_to_the_same_bits() {
    let args = [
        "run", "twist", "--size", "2", "--steps", "24", "--solver", "cg",
    ];
    let (reference, _) = reference_run(&args, "twist-ref");
    let mut rng = Rng(0x5eed_0001);
    let mut resumed = 0;
    for k in 0..3 {
        let dir = tmpdir("twist-kill").join("run");
        let (rows, extra) = (1 + rng.below(21) as usize, rng.below(20));
        let threads = if k % 2 == 0 { "1" } else { "2" };
        let mut a = args.to_vec();
        a.extend(["--threads", threads]);
        eprintln!("twist --size 2: SIGKILL after {rows} steps and {extra} ms ({threads} threads)");
        let what = format!("twist kill {k}");
        let from = kill_and_resume(&a, &dir, &reference, rows, extra, &what);
        resumed += from.is_some_and(|s| s < 24) as usize;
    }
    assert!(resumed >= 1, "no kill landed inside the run");
}

/// The device loop (f64 on the GPU) killed at seeded points.
#[test]
fn killed_device_loop_runs_resume_to_the_same_bits() {
    let args = ["run", "drop", "--steps", "12", "--newton", "gpu"];
    let dir = tmpdir("drop-ref").join("reference");
    let d = s(&dir);
    let mut a = args.to_vec();
    a.extend(["--out", &d, "-q"]);
    let t = Instant::now();
    let o = run(&a);
    if !o.status.success() {
        let e = stderr(&o);
        if e.contains("cannot start") && std::env::var_os("STICKSLIP_REQUIRE_GPU").is_none() {
            common::skip(&format!("SKIP killed_device_loop_runs_resume_to_the_same_bits: GPU Newton loop NOT RUN (no adapter): {e}"));
            return;
        }
        panic!("drop with the device loop: {e}");
    }
    eprintln!(
        "drop --newton gpu: reference in {:.1} s",
        t.elapsed().as_secs_f64()
    );
    let mut rng = Rng(0x5eed_0002);
    let mut resumed = 0;
    for k in 0..2 {
        let run_dir = tmpdir("drop-kill").join("run");
        let (rows, extra) = (1 + rng.below(9) as usize, rng.below(20));
        eprintln!("drop --newton gpu: SIGKILL after {rows} steps and {extra} ms");
        let from = kill_and_resume(
            &args,
            &run_dir,
            &dir,
            rows,
            extra,
            &format!("drop kill {k}"),
        );
        resumed += from.is_some_and(|s| s < 12) as usize;
    }
    assert!(resumed >= 1, "no kill landed inside the run");
}

/// Every dumped Newton system under `dir/systems` (relative path, bytes), sorted.
fn systems(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let root = dir.join("systems");
    let mut out = Vec::new();
    let mut stack = vec![root.clone()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).expect("systems").flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let rel = p.strip_prefix(&root).expect("inside").display().to_string();
                out.push((rel, std::fs::read(&p).expect("system file")));
            }
        }
    }
    out.sort();
    out
}

/// A run that dumps its Newton systems, killed at seeded points (inside a step's dump,
/// when the kill lands there), resumes to the same steps.csv, frames and dumped systems.
#[test]
fn killed_runs_dumping_systems_resume_to_the_same_bits() {
    let args = [
        "run",
        "twist",
        "--steps",
        "12",
        "--solver",
        "cg",
        "--dump-systems",
        "all",
    ];
    let (reference, _) = reference_run(&args, "dump-ref");
    let want = systems(&reference);
    assert!(!want.is_empty(), "the reference dumped no system");
    let mut rng = Rng(0x5eed_0003);
    let mut resumed = 0;
    for k in 0..2 {
        let dir = tmpdir("dump-kill").join("run");
        let (rows, extra) = (1 + rng.below(9) as usize, rng.below(20));
        eprintln!("twist --dump-systems all: SIGKILL after {rows} steps and {extra} ms");
        let what = format!("dump kill {k}");
        let from = kill_and_resume(&args, &dir, &reference, rows, extra, &what);
        resumed += from.is_some_and(|s| s < 12) as usize;
        let got = systems(&dir);
        let names = |v: &[(String, Vec<u8>)]| v.iter().map(|f| f.0.clone()).collect::<Vec<_>>();
        assert_eq!(names(&got), names(&want), "{what}: dumped files");
        assert!(got == want, "{what}: dumped systems differ");
    }
    assert!(resumed >= 1, "no kill landed inside the run");
}

/// The device loop's host↔device byte totals in summary.json cover every invocation of
/// a resumed run: at least the first part's totals plus what the steps after the resume
/// move in an uninterrupted run (the traffic of steps 3–4 is the difference of a 4-step
/// and a 2-step run: the steps are the same bits, so the same transfers).
#[test]
fn device_traffic_totals_cover_every_invocation() {
    let base = ["run", "drop", "--newton", "gpu", "--steps"];
    let bytes = |dir: &Path| {
        let sm = summary(dir);
        let g = &sm["gpu"];
        (
            g["host_to_device_bytes"]
                .as_u64()
                .expect("host_to_device_bytes"),
            g["device_to_host_bytes"]
                .as_u64()
                .expect("device_to_host_bytes"),
        )
    };
    let root = tmpdir("traffic");
    let mut totals = Vec::new();
    for steps in ["2", "4"] {
        let dir = root.join(format!("steps-{steps}"));
        let mut a = base.to_vec();
        let d = s(&dir);
        a.extend([steps, "--out", &d, "-q"]);
        let o = run(&a);
        if !o.status.success() {
            let e = stderr(&o);
            if e.contains("cannot start") && std::env::var_os("STICKSLIP_REQUIRE_GPU").is_none() {
                common::skip(&format!("SKIP device_traffic_totals_cover_every_invocation: GPU Newton loop NOT RUN (no adapter): {e}"));
                return;
            }
            panic!("drop with the device loop: {e}");
        }
        totals.push(bytes(&dir));
    }
    let (two, four) = (totals[0], totals[1]);
    let dir = root.join("steps-2");
    let d = s(&dir);
    ok(
        &run(&["run", "--resume", &d, "--steps", "4", "-q"]),
        "resume to 4",
    );
    let resumed = bytes(&dir);
    assert!(
        resumed.0 >= two.0 + (four.0 - two.0) && resumed.1 >= two.1 + (four.1 - two.1),
        "resumed totals {resumed:?}, first part {two:?}, uninterrupted 4 steps {four:?}"
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// A run resumed from its last step with a larger --steps equals the longer run.
#[test]
fn a_finished_run_goes_further_with_more_steps() {
    let (reference, _) = reference_run(&["run", "twist", "--steps", "9"], "longer-ref");
    let dir = tmpdir("longer").join("run");
    let d = s(&dir);
    ok(
        &run(&["run", "twist", "--steps", "6", "--out", &d, "-q"]),
        "6 steps",
    );
    let o = run(&["run", "--resume", &d, "--steps", "9", "-q"]);
    ok(&o, "resume to 9");
    assert_eq!(summary(&dir)["resumed_from_step"], 6);
    assert_same_run(&reference, &dir, "6 then 9 steps");
    // --end-time: 12 steps of 0.01 s.
    let (reference, _) = reference_run(&["run", "twist", "--steps", "12"], "end-time-ref");
    let o = run(&["run", "--resume", &d, "--end-time", "0.12", "-q"]);
    ok(&o, "resume to t = 0.12");
    assert_same_run(&reference, &dir, "9 then 12 steps");
}

/// SIGINT and SIGTERM end the run after the step it is in: summary.json says
/// "interrupted" with the steps steps.csv holds, and the run resumes to the same bits.
#[test]
fn interrupted_runs_say_so_and_resume() {
    let args = [
        "run", "twist", "--size", "2", "--steps", "24", "--solver", "cg",
    ];
    let (reference, _) = reference_run(&args, "signal-ref");
    for (sig, name) in [(libc::SIGINT, "SIGINT"), (libc::SIGTERM, "SIGTERM")] {
        let dir = tmpdir("signal").join("run");
        let d = s(&dir);
        let mut a = args.to_vec();
        a.extend(["--out", &d, "-q"]);
        let mut c = spawn(&a);
        wait_for_checkpoint(&mut c, &dir);
        std::thread::sleep(Duration::from_millis(300));
        // SAFETY: sends a signal to the child this test spawned.
        unsafe {
            libc::kill(c.id() as libc::pid_t, sig);
        }
        let o = c.wait_with_output().expect("wait");
        let sm = summary(&dir);
        if sm["status"] == "complete" {
            eprintln!("{name}: the run ended before the signal arrived");
            assert!(o.status.success());
        } else {
            assert_eq!(o.status.code(), Some(128 + sig), "{name}: {}", stderr(&o));
            let e = stderr(&o);
            assert_eq!(e.lines().count(), 1, "{e}");
            assert!(e.contains("interrupted") && e.contains("--resume"), "{e}");
            assert_eq!(sm["status"], "interrupted", "{name}");
            let rows = steps_without_timing(&dir).len() as u64 - 2;
            assert_eq!(sm["steps_completed"].as_u64(), Some(rows), "{name}: {sm}");
            ok(&run(&["run", "--resume", &d, "-q"]), name);
        }
        assert_same_run(&reference, &dir, name);
    }
}

/// Every file under `dir` with its size and modification time.
fn listing(dir: &Path) -> Vec<(String, u64, SystemTime)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).expect("dir").flatten() {
            let m = e.metadata().expect("metadata");
            if m.is_dir() {
                stack.push(e.path());
            } else {
                out.push((
                    s(&e.path()),
                    m.len(),
                    m.modified().expect("modification time"),
                ));
            }
        }
    }
    out.sort();
    out
}

fn fnv(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// Refusals: one line, exit 2, and nothing in the folder changed.
#[test]
fn checkpoints_that_do_not_fit_are_refused_and_change_nothing() {
    let root = tmpdir("refusals");
    // A scene file of our own, so that it can change under the run.
    let scene = root.join("bar.toml");
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/twist.toml"))
        .expect("twist.toml");
    std::fs::write(&scene, &text).expect("scene");
    let dir = root.join("run");
    let d = s(&dir);
    ok(
        &run(&["run", &s(&scene), "--steps", "4", "--out", &d, "-q"]),
        "the run",
    );
    let ckpt = dir.join("checkpoint.bin");
    let ckpt_s = s(&ckpt);
    let refuse = |want: &[&str], blamed: &str| {
        let before = listing(&dir);
        let o = run(&["run", "--resume", &d, "--steps", "8", "-q"]);
        assert_input_error(&o, blamed, want);
        assert_eq!(listing(&dir), before, "the folder changed");
    };
    // Another scene: the material changed since the run started.
    let changed = text.replacen("young = 1e5", "young = 2e5", 1);
    assert_ne!(changed, text);
    std::fs::write(&scene, &changed).expect("scene");
    refuse(&["written for another scene"], &ckpt_s);
    std::fs::write(&scene, &text).expect("scene");
    let good = std::fs::read(&ckpt).expect("checkpoint");
    // Truncated, and one flipped bit.
    std::fs::write(&ckpt, &good[..good.len() / 3]).expect("write");
    refuse(&["truncated or corrupt"], &ckpt_s);
    let mut flipped = good.clone();
    let k = flipped.len() - 40;
    flipped[k] ^= 0x10;
    std::fs::write(&ckpt, &flipped).expect("write");
    refuse(&["truncated or corrupt"], &ckpt_s);
    // Another format version, its checksum valid.
    let mut other = good.clone();
    let key = format!("\"format\":{}", stickslip::sim::checkpoint::FORMAT_VERSION);
    let key = key.as_bytes();
    let at = other
        .windows(key.len())
        .position(|w| w == key)
        .expect("format in the header");
    other[at + key.len() - 1] = b'7';
    let n = other.len() - 8;
    let sum = fnv(&other[..n]).to_le_bytes();
    other[n..].copy_from_slice(&sum);
    std::fs::write(&ckpt, &other).expect("write");
    refuse(&["checkpoint format 7"], &ckpt_s);
    // No checkpoint at all.
    std::fs::remove_file(&ckpt).expect("remove");
    refuse(&["no checkpoint here"], &ckpt_s);
    // Options that the checkpoint fixes.
    std::fs::write(&ckpt, &good).expect("write");
    let o = run(&["run", "--resume", &d, "--solver", "cholesky"]);
    assert_input_error(&o, "--resume", &["--solver cannot be given"]);
    // Fewer steps than the run has done.
    let o = run(&["run", "--resume", &d, "--steps", "2", "-q"]);
    assert_input_error(&o, &ckpt_s, &["done 4 of 2 steps", "at or beyond step 4"]);
}

/// Two resumes of one folder at once: the second refuses (the folder's lock).
#[test]
fn a_second_resume_of_a_running_folder_is_refused() {
    let dir = tmpdir("two-resumes").join("run");
    let d = s(&dir);
    ok(
        &run(&[
            "run", "twist", "--size", "2", "--steps", "2", "--out", &d, "-q",
        ]),
        "start",
    );
    let mut first = spawn(&["run", "--resume", &d, "--steps", "400", "-q"]);
    // The first resume holds the lock once it has rewritten steps.csv.
    let t = Instant::now();
    while summary(&dir)["steps"] != 400 {
        assert!(
            first.try_wait().expect("wait").is_none(),
            "the first resume ended"
        );
        assert!(t.elapsed() < Duration::from_secs(60));
        std::thread::sleep(Duration::from_millis(10));
    }
    let before = listing(&dir)
        .into_iter()
        .filter(|(p, ..)| p.ends_with("checkpoint.bin"))
        .collect::<Vec<_>>();
    let o = run(&["run", "--resume", &d, "--steps", "400", "-q"]);
    let e = stderr(&o);
    let _ = first.kill();
    let _ = first.wait();
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert_eq!(e.lines().count(), 1, "{e}");
    assert!(e.contains("another stickslip process"), "{e}");
    assert!(!before.is_empty());
}

/// The library side: a stepper restored from another's snapshot continues with the same
/// bits, moving boundaries (k_M, snapping) included; a snapshot of another scene is
/// refused and changes nothing.
#[test]
fn a_restored_stepper_continues_with_the_same_bits() {
    use stickslip::sim::integrator::Stepper;
    let text = stickslip::sim::scene::builtin("twist").expect("twist");
    let scene = stickslip::sim::scene::parse(text, "twist", 1.0).expect("scene");
    let mut a = Stepper::new(&scene).expect("stepper");
    for _ in 0..3 {
        a.step().expect("step");
    }
    let snap = a.snapshot();
    let mut b = Stepper::new(&scene).expect("stepper");
    b.restore(&snap).expect("restore");
    assert_eq!(b.snapshot(), snap);
    for _ in 0..4 {
        let (ra, rb) = (a.step().expect("a"), b.step().expect("b"));
        assert_eq!(ra.newton_iterations, rb.newton_iterations);
        assert_eq!(ra.linear_iterations, rb.linear_iterations);
    }
    let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&a.x), bits(&b.x));
    assert_eq!(bits(&a.v), bits(&b.v));
    assert_eq!(bits(&a.reactions), bits(&b.reactions));
    assert_eq!(a.k_m.to_bits(), b.k_m.to_bits());
    // Another scene's snapshot: refused, and the stepper is unchanged.
    let other = stickslip::sim::scene::parse(
        stickslip::sim::scene::builtin("drop").expect("drop"),
        "drop",
        1.0,
    )
    .expect("scene");
    let mut c = Stepper::new(&other).expect("stepper");
    let before = c.snapshot();
    let e = c.restore(&snap).expect_err("another scene");
    assert!(e.to_string().contains("entries"), "{e}");
    assert_eq!(c.snapshot(), before);
}

/// With the multilevel preconditioner keeping its levels across Newton systems
/// (`multilevel_setup = "reuse"`), a run stopped at step 4 and resumed to step 10 gives
/// the bits of the run that went to step 10 at once, and so does one killed at a seeded
/// point: on the CPU CG and on the device loop.
#[test]
fn runs_keeping_multilevel_levels_resume_to_the_same_bits() {
    let root = tmpdir("multilevel-reuse");
    let scene = root.join("hanging.toml");
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/scenes/hanging.toml"))
        .expect("hanging.toml");
    assert!(
        !text.contains("[solver]"),
        "hanging.toml has its own [solver]"
    );
    let solver = "[solver]\npreconditioner = \"multilevel\"\nmultilevel_setup = \"reuse\"\n";
    std::fs::write(&scene, format!("{text}\n{solver}")).expect("write the scene");
    let sc = s(&scene);
    let mut rng = Rng(0x5eed_0004);
    let mut inside = 0;
    for (newton, extra) in [("cpu", ["--solver", "cg"]), ("gpu", ["--newton", "gpu"])] {
        let reference = root.join(format!("reference-{newton}"));
        let r = s(&reference);
        let mut a = vec!["run", &sc, "--steps", "10", "--out", &r, "-q"];
        a.extend(extra);
        let o = run(&a);
        if !o.status.success() {
            let e = stderr(&o);
            if newton == "gpu"
                && e.contains("cannot start")
                && std::env::var_os("STICKSLIP_REQUIRE_GPU").is_none()
            {
                common::skip(&format!("SKIP runs_keeping_multilevel_levels_resume_to_the_same_bits: GPU Newton loop NOT RUN (no adapter): {e}"));
                return;
            }
            panic!("hanging with --newton {newton}: {e}");
        }
        let levels = &summary(&reference)["multilevel_levels"];
        assert!(
            levels["kept"].as_u64().is_some_and(|k| k > 0),
            "--newton {newton}: no levels were kept: {levels}"
        );
        let dir = root.join(format!("resumed-{newton}"));
        let d = s(&dir);
        let mut a = vec!["run", &sc, "--steps", "4", "--out", &d, "-q"];
        a.extend(extra);
        ok(&run(&a), "4 steps");
        ok(
            &run(&["run", "--resume", &d, "--steps", "10", "-q"]),
            "resume",
        );
        assert_eq!(summary(&dir)["resumed_from_step"], 4);
        assert_same_run(
            &reference,
            &dir,
            &format!("multilevel reuse, --newton {newton}"),
        );
        // Killed at a seeded point rather than stopped at a step.
        let (rows, wait) = (1 + rng.below(6) as usize, rng.below(20));
        let mut a = vec!["run", &sc, "--steps", "10"];
        a.extend(extra);
        let what = format!("multilevel reuse, --newton {newton}, SIGKILL after {rows} steps");
        let killed = root.join(format!("killed-{newton}"));
        let from = kill_and_resume(&a, &killed, &reference, rows, wait, &what);
        inside += from.is_some_and(|s| s < 10) as usize;
    }
    assert!(inside >= 1, "no kill landed inside a run");
}
