//! `run --resume DIR`: which options a resume takes, the checks that a checkpoint belongs
//! to the folder's run and fits the scene rebuilt from it (all before anything in the
//! folder changes), and the folder brought back to the checkpoint's step.

use crate::error::InputError;
use crate::io::files::OutputDir;
use crate::sim::checkpoint::{self, Checkpoint, Tallies};
use crate::sim::run_error::RunError;
use crate::sim::run_options::RunOptions;
use crate::sim::scene::Scene;
use std::path::Path;

/// What `--resume` takes besides the folder; the scene and every other option come from
/// the checkpoint.
pub const ACCEPTED: &str = "--steps or --end-time (to go further), --dump-systems (the \
                            steps dumped from the resume on), --threads and --quiet";

/// The options that cannot change on a resume (the checkpoint holds them).
pub fn refuse_options(opts: &RunOptions) -> Result<(), RunError> {
    let fixed = [
        ("a scene", opts.scene.is_some()),
        ("--out", opts.out.is_some()),
        ("--solver", opts.solver.is_some()),
        ("--size", opts.size.is_some()),
        ("--ordering", opts.ordering.is_some()),
        ("--newton", opts.newton.is_some()),
        ("--cg-tolerance", opts.cg_tolerance.is_some()),
        ("--preconditioner", opts.preconditioner.is_some()),
        ("--overwrite", opts.overwrite),
    ];
    for (what, given) in fixed {
        if given {
            return Err(InputError::new(
                "--resume",
                "",
                format!(
                    "takes its scene and options from the checkpoint: {what} cannot be given \
                     with it (only {ACCEPTED})"
                ),
            )
            .into());
        }
    }
    Ok(())
}

/// Checks a checkpoint against the folder and the scene rebuilt from it, before anything
/// in the folder changes: the same fingerprint, the folder's run (summary.json's run id
/// and steps.csv up to the checkpoint's step, by digest), and no more steps done than the
/// run is asked for. Returns steps.csv's header and rows up to the checkpoint's step.
pub fn check(ck: &Checkpoint, scene: &Scene, dir: &Path) -> Result<String, RunError> {
    let file = dir.join(checkpoint::FILE_NAME).display().to_string();
    let fail = |problem: String| RunError::from(InputError::new(&file, "", problem));
    let fp = checkpoint::fingerprint(scene);
    if fp != ck.fingerprint {
        return Err(fail(format!(
            "was written for another scene (fingerprint {} here, {fp} for {} now): the scene \
             file or what it reads changed since the run started",
            ck.fingerprint, ck.options.scene
        )));
    }
    let step = ck.snapshot.step;
    if scene.steps < step {
        return Err(fail(format!(
            "the run has done {step} of {} steps; give --steps or --end-time at or beyond step \
             {step}",
            scene.steps
        )));
    }
    let foreign = |why: String| {
        fail(format!(
            "belongs to another run: {why}; a checkpoint resumes only the run whose folder \
             wrote it"
        ))
    };
    let summary = dir.join("summary.json");
    let run_id = std::fs::read_to_string(&summary)
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .and_then(|v| v.get("run_id")?.as_str().map(str::to_string));
    match run_id {
        Some(id) if id == ck.identity.run_id => {}
        Some(id) => {
            return Err(foreign(format!(
                "this folder's summary.json names run {id}, the checkpoint run {}",
                ck.identity.run_id
            )))
        }
        None => return Err(foreign(format!("{} names no run id", summary.display()))),
    }
    let csv = dir.join("steps.csv");
    let text = std::fs::read_to_string(&csv)
        .map_err(|e| foreign(format!("{} cannot be read: {e}", csv.display())))?;
    let kept = crate::sim::output::rows_up_to(&text, step)
        .filter(|k| crate::sim::output::steps_digest(k) == ck.identity.steps_digest)
        .ok_or_else(|| {
            foreign(format!(
                "{} up to step {step} is not the one the checkpoint was written with",
                csv.display()
            ))
        })?;
    Ok(kept)
}

/// A resumed run's folder: the manifest continues; a killed run's temporary files go;
/// steps.csv keeps `kept` (its header and the rows up to the checkpoint's step); the
/// frames after the step go, with the step's own frame when it was written only because
/// that step was the last one and the run now goes further (and `tallies` stops counting
/// it); the dumped systems of the steps after it go (a dump the run was killed in is
/// partial; the resumed run dumps those steps again). Returns the frames kept (file
/// relative to the folder, simulated time from its title), by step, and frames.pvd lists
/// them.
pub fn prepare(
    dir: &mut OutputDir,
    scene: &Scene,
    step: usize,
    kept: &str,
    tallies: &mut Tallies,
) -> Result<Vec<(String, f64)>, RunError> {
    let out_err = |path: &Path, cause: String| RunError::Output {
        path: path.display().to_string(),
        cause,
    };
    dir.resume()
        .map_err(|e| out_err(dir.path(), e.to_string()))?;
    dir.remove_temporaries();
    let csv = dir.path().join("steps.csv");
    if std::fs::read_to_string(&csv).ok().as_deref() != Some(kept) {
        crate::io::files::write_atomic_bytes(&csv, kept.as_bytes())
            .map_err(|e| out_err(&csv, e.to_string()))?;
    }
    let numbered = |folder: &Path, prefix: &str, suffix: &str| {
        let mut found = Vec::new();
        for e in std::fs::read_dir(folder).into_iter().flatten().flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            if let Some(n) = name
                .strip_prefix(prefix)
                .and_then(|r| r.strip_suffix(suffix))
                .and_then(|r| r.parse::<usize>().ok())
            {
                found.push((n, e.path()));
            }
        }
        found
    };
    let every = scene.output.every;
    let goes_further = scene.steps > step;
    let frames = dir.path().join("frames");
    let mut on_disk = numbered(&frames, &format!("{}_", scene.name), ".vtk");
    on_disk.sort();
    let (mut listed, mut removed) = (Vec::new(), Vec::new());
    for (n, path) in on_disk {
        let last_only = n == step && n % every != 0 && n != 0 && goes_further;
        if n > step || last_only {
            removed.push(path);
            if last_only {
                tallies.frames = tallies.frames.saturating_sub(1);
            }
        } else if let Some(t) = crate::sim::output::frame_time(&path) {
            listed.push((format!("frames/{}_{n:05}.vtk", scene.name), t));
        }
    }
    // frames.pvd first: killed here, it lists no frame that is gone.
    if scene.output.vtk {
        crate::sim::time_loop::write_collection(dir, &listed)?;
    }
    for path in removed {
        std::fs::remove_file(&path).map_err(|e| out_err(&path, e.to_string()))?;
    }
    let systems = dir.path().join("systems");
    for (n, path) in numbered(&systems, "step_", "") {
        if n > step {
            std::fs::remove_dir_all(&path).map_err(|e| out_err(&path, e.to_string()))?;
        }
    }
    Ok(listed)
}
