//! Steps 5–7 of `stickslip run` ([`crate::sim::driver`]): the time loop (each step's
//! Newton solve), the recovered quantities of each step, and the outputs written as the
//! run goes: steps.csv rows, frames, dumped Newton systems, checkpoints, steps.svg and
//! summary.json.

use crate::error::InputError;
use crate::gpu::Phase;
use crate::io::files::OutputDir;
use crate::sim::checkpoint::{self, StartOptions, Tallies};
use crate::sim::integrator::{NewtonSystem, StepError, StepReport, Stepper, SystemSink};
use crate::sim::output::{write_pvd, write_vtk, StepRecord, StepsCsv, FRAMES_COLLECTION};
use crate::sim::run_error::RunError;
use crate::sim::run_options::{RunOptions, StepsPlot};
use crate::sim::scene::Scene;
use crate::sim::summary::{
    ContactSummary, MovingSummary, MultilevelLevels, PhaseSummary, RunSummary,
};
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicI32, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The plot of steps.csv that the run keeps beside it (see [`StepsPlot`]).
pub const STEPS_PLOT: &str = "steps.svg";

/// After a drawing of steps.svg that took d, the next one at a checkpoint waits at least
/// this many times d: redrawing a long run's whole history takes at most 5 % of its time.
const PLOT_WAIT_FACTOR: u32 = 19;

/// The first non-finite entry of a step's state or record, if any, as "what (value)".
fn non_finite(s: &Stepper, r: &StepRecord) -> Option<String> {
    let vectors: [(&str, &[f64]); 6] = [
        ("positions", &s.x),
        ("velocities", &s.v),
        ("reactions", &s.reactions),
        ("centre of mass", &r.com),
        ("momentum", &r.momentum),
        ("total reaction", &r.reaction),
    ];
    for (what, v) in vectors {
        if let Some(x) = v.iter().find(|x| !x.is_finite()) {
            return Some(format!("{what} ({x})"));
        }
    }
    (!r.energy.is_finite()).then(|| format!("mechanical energy ({})", r.energy))
}

/// The signal that asked the run to stop (0: none). Set by the command line's SIGINT and
/// SIGTERM handlers ([`request_interrupt`]); the time loop stops after the step it is in.
static INTERRUPT: AtomicI32 = AtomicI32::new(0);

/// Asks a running [`crate::sim::driver::run`] to stop after its current step, writing a checkpoint there
/// (async-signal-safe: one atomic store).
pub fn request_interrupt(signal: i32) {
    INTERRUPT.store(signal, Ordering::SeqCst);
}

/// What the time loop carries besides the stepper: the run's identity for its
/// checkpoints, and its tallies.
pub(crate) struct Run<'a> {
    pub scene: &'a Scene,
    pub fingerprint: String,
    pub run_id: String,
    pub start: StartOptions,
    /// What the run's earlier invocations and this one's steps so far add up to.
    pub tallies: Tallies,
    /// The run's frames on disk (file relative to the folder, simulated time), in the
    /// order written: what frames.pvd lists.
    pub frames: Vec<(String, f64)>,
    /// Start of this invocation.
    pub wall: Instant,
    /// Draws steps.svg; None: the run keeps no plot.
    pub plot: Option<Arc<dyn StepsPlot>>,
    /// The earliest time of the next drawing at a checkpoint (None: at the next one).
    pub plot_due: Option<Instant>,
}

impl Run<'_> {
    /// Writes the checkpoint of the stepper's last completed step; `steps_digest`: of
    /// steps.csv up to it.
    fn checkpoint(
        &mut self,
        dir: &mut OutputDir,
        stepper: &Stepper,
        steps_digest: String,
        summary: &mut RunSummary,
    ) -> Result<(), RunError> {
        let _output = stepper.phase(Phase::Output);
        let t = Instant::now();
        let path = dir
            .record(checkpoint::FILE_NAME)
            .map_err(|e| RunError::Output {
                path: dir.path().display().to_string(),
                cause: e.to_string(),
            })?;
        let mut tallies = self.tallies.clone();
        tallies.wall_seconds += self.wall.elapsed().as_secs_f64();
        if let Some(g) = stepper.gpu_report() {
            tallies.host_to_device_bytes += g.host_to_device_bytes;
            tallies.device_to_host_bytes += g.device_to_host_bytes;
        }
        let identity = checkpoint::RunIdentity {
            run_id: self.run_id.clone(),
            steps_digest,
        };
        checkpoint::write(
            dir.path(),
            &self.fingerprint,
            &identity,
            &self.start,
            self.scene.steps,
            &stepper.snapshot(),
            &tallies,
        )
        .map_err(|e| RunError::Output {
            path: path.display().to_string(),
            cause: e.to_string(),
        })?;
        let spent = t.elapsed().as_secs_f64();
        self.tallies.checkpoint_seconds += spent;
        summary.checkpoint_seconds = self.tallies.checkpoint_seconds;
        Ok(())
    }

    /// Redraws steps.svg from the whole of steps.csv and writes it atomically (when the
    /// run has a plot); `always`: whatever the time since the last drawing (the start,
    /// the end, an interruption, a failure), otherwise only once it is due.
    pub(crate) fn draw_plot(
        &mut self,
        dir: &mut OutputDir,
        stepper: &Stepper,
        always: bool,
    ) -> Result<(), RunError> {
        let Some(plot) = self.plot.clone() else {
            return Ok(());
        };
        let now = Instant::now();
        if !always && self.plot_due.is_some_and(|due| now < due) {
            return Ok(());
        }
        let _output = stepper.phase(Phase::Output);
        let csv_path = dir.path().join("steps.csv");
        let text = std::fs::read_to_string(&csv_path).map_err(|e| RunError::Output {
            path: csv_path.display().to_string(),
            cause: e.to_string(),
        })?;
        let svg_path = dir.path().join(STEPS_PLOT);
        let fail = |cause: String| RunError::Output {
            path: svg_path.display().to_string(),
            cause,
        };
        let svg = plot.draw(&text).map_err(|e| fail(e.to_string()))?;
        dir.write(STEPS_PLOT, |w| w.write_all(svg.as_bytes()))
            .map_err(|e| fail(e.to_string()))?;
        let spent = now.elapsed().max(Duration::from_micros(1));
        self.plot_due = Some(Instant::now() + spent * PLOT_WAIT_FACTOR);
        Ok(())
    }
}

/// Writes one VTK frame (when the scene asks for frames).
fn write_frame(run: &mut Run, dir: &mut OutputDir, s: &Stepper) -> Result<(), RunError> {
    let scene = run.scene;
    let _output = s.phase(Phase::Output);
    if !scene.output.vtk {
        return Ok(());
    }
    let rel = format!("frames/{}_{:05}.vtk", scene.name, s.step);
    let path = dir.record(&rel).map_err(|e| RunError::Output {
        path: dir.path().display().to_string(),
        cause: e.to_string(),
    })?;
    let title = format!("stickslip {} step {} t = {}", scene.name, s.step, s.t);
    let c = s.has_contact().then_some(&s.contact_forces[..]);
    write_vtk(&path, scene, &title, &s.x, &s.v, &s.reactions, c).map_err(|e| RunError::Output {
        path: path.display().to_string(),
        cause: e.to_string(),
    })?;
    run.tallies.frames += 1;
    run.frames.push((rel, s.t));
    write_collection(dir, &run.frames)
}

/// Writes frames.pvd, the ParaView collection of `frames` (file, simulated time),
/// atomically.
pub(crate) fn write_collection(
    dir: &mut OutputDir,
    frames: &[(String, f64)],
) -> Result<(), RunError> {
    let path = dir.path().join(FRAMES_COLLECTION);
    dir.write(FRAMES_COLLECTION, |w| write_pvd(w, frames))
        .map_err(|e| RunError::Output {
            path: path.display().to_string(),
            cause: e.to_string(),
        })?;
    Ok(())
}

/// Files of one dumped Newton system, in `systems/step_S/iter_K/`.
pub const SYSTEM_FILES: [&str; 6] = [
    "H.mtx",
    "g.mtx",
    "bc.json",
    "x.mtx",
    "dx.mtx",
    "system.json",
];

/// Writes one Newton system as `solve`'s input files (H.mtx, g.mtx, bc.json) with the
/// iterate (x.mtx), the direction the run used (dx.mtx) and how it was solved
/// (system.json), into `systems/step_S/iter_K/`: written in a temporary folder beside it
/// and renamed, so the folder is whole or absent.
fn write_system(dir: &mut OutputDir, sys: &NewtonSystem) -> Result<(), String> {
    let rel = PathBuf::from("systems")
        .join(format!("step_{}", sys.step))
        .join(format!("iter_{}", sys.iteration));
    let fail = |e: std::io::Error| format!("{}: {e}", rel.display());
    let final_dir = dir.path().join(&rel);
    let tmp = dir
        .path()
        .join(rel.with_file_name(format!(".iter_{}.partial", sys.iteration)));
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(fail)?;
    }
    std::fs::create_dir_all(&tmp).map_err(fail)?;
    for f in SYSTEM_FILES {
        dir.record(rel.join(f)).map_err(fail)?;
    }
    let comment = format!(
        "stickslip run --dump-systems: step {}, Newton iteration {}",
        sys.step, sys.iteration
    );
    crate::io::mtx::write_hessian(tmp.join("H.mtx"), &sys.h, &comment).map_err(fail)?;
    crate::io::mtx::write_vector(tmp.join("g.mtx"), &sys.g, &comment).map_err(fail)?;
    crate::io::bcjson::write(tmp.join("bc.json"), sys.dim, &sys.constraints).map_err(fail)?;
    crate::io::mtx::write_vector(tmp.join("x.mtx"), &sys.x, &comment).map_err(fail)?;
    crate::io::mtx::write_vector(tmp.join("dx.mtx"), &sys.dx, &comment).map_err(fail)?;
    let info = serde_json::json!({
        "step": sys.step,
        "iteration": sys.iteration,
        "dim": sys.dim,
        "nodes": sys.h.n,
        "tolerance": sys.tolerance,
        "linear_iterations": sys.iterations,
    });
    crate::io::files::write_atomic_bytes(tmp.join("system.json"), info.to_string().as_bytes())
        .map_err(fail)?;
    if final_dir.exists() {
        std::fs::remove_dir_all(&final_dir).map_err(fail)?;
    }
    std::fs::rename(&tmp, &final_dir).map_err(fail)
}

/// The summary's counts and histories from the tallies.
fn fill_summary(run: &Run, stepper: &Stepper, summary: &mut RunSummary) {
    let (scene, t) = (run.scene, &run.tallies);
    summary.newton_iterations = t.newton_iterations;
    summary.linear_iterations = t.linear_iterations;
    summary.linear_seconds = t.linear_seconds;
    summary.linear_resolves = t.linear_resolves;
    if scene.solver.preconditioner == crate::solve::options::Preconditioner::Multilevel {
        summary.multilevel_levels = Some(MultilevelLevels {
            setup: scene.solver.multilevel_setup,
            built: t.multilevel_built,
            kept: t.multilevel_kept,
        });
    }
    summary.frames = t.frames;
    summary.steps_completed = stepper.step;
    summary.end_time = stepper.t;
    summary.checkpoint_seconds = t.checkpoint_seconds;
    // Every neo-Hookean law of the scene, with zero when no step ended inverted.
    summary.inverted_steps = scene
        .model
        .solid_laws()
        .iter()
        .map(|law| {
            let name = law.name().to_string();
            let n = t.inverted_steps.get(&name).copied().unwrap_or(0);
            (name, n)
        })
        .collect();
    summary.moving_boundary = stepper.has_moving().then(|| MovingSummary {
        settings: scene.moving.clone(),
        moving_nodes: scene.bcs.iter().filter(|b| b.motion.is_some()).count(),
        k_m_start: scene.moving.penalty_start,
        k_m_final: stepper.k_m,
        k_m_doublings: t.k_m_doublings,
        k_m_history: t.k_m_history.clone(),
        eliminated_at_iteration: t.eliminated_at_iteration.clone(),
        first_step_eliminated_at_start: t.first_step_eliminated_at_start,
        all_eliminated_every_step: t.all_eliminated_every_step,
    });
    summary.contact = stepper.has_contact().then(|| ContactSummary {
        obstacles: scene.obstacles.len(),
        dhat: scene.obstacles.iter().map(|o| o.plane.dhat).collect(),
        kappa: scene.obstacles.iter().map(|o| o.plane.kappa).collect(),
        min_distance: t.min_distance.unwrap_or(f64::INFINITY),
        ccd_limited_line_searches: t.ccd_limited,
        final_contact_force: stepper.total_contact().unwrap_or_default(),
    });
}

/// 5–7: the time loop, writing steps.csv row by row, the frames and the checkpoints;
/// `summary` follows the run (counts, end time, moving and contact histories) whether it
/// ends or fails.
pub(crate) fn simulate(
    run: &mut Run,
    opts: &RunOptions,
    stepper: &mut Stepper,
    dir: &mut OutputDir,
    summary: &mut RunSummary,
) -> Result<(), RunError> {
    let scene = run.scene;
    let out_err = |path: &Path, e: std::io::Error| RunError::Output {
        path: path.display().to_string(),
        cause: e.to_string(),
    };
    let output = stepper.phase(Phase::Output);
    let frames_dir = dir.path().join("frames");
    std::fs::create_dir_all(&frames_dir).map_err(|e| out_err(&frames_dir, e))?;
    let csv_path = dir
        .record("steps.csv")
        .map_err(|e| out_err(dir.path(), e))?;
    let resuming = summary.resumed_from_step.is_some();
    let (dim, moving, contact) = (scene.dim, stepper.has_moving(), stepper.has_contact());
    let solid = !scene.model.solid_laws().is_empty();
    let mut csv = if resuming {
        StepsCsv::append(&csv_path, moving, contact, solid)
    } else {
        StepsCsv::create(&csv_path, dim, moving, contact, solid)
    }
    .map_err(|e| out_err(&csv_path, e))?;

    let record = |s: &Stepper, rep: Option<&StepReport>| step_record(scene, s, rep);
    let checkpoint_every = summary.checkpoint_every;

    if !resuming {
        let first = record(stepper, None);
        if let Some(what) = non_finite(stepper, &first) {
            // Finite entries whose products overflow (sizes near 1e300, ...): the scene's
            // fault.
            return Err(InputError::new(
                scene.file.clone(),
                "scene",
                format!(
                    "the initial state is not finite: {what}; the scene's magnitudes (mesh \
                     size, density, offsets, time step) overflow f64"
                ),
            )
            .into());
        }
        csv.row(&first).map_err(|e| out_err(&csv_path, e))?;
        fold_min(&mut run.tallies, &first);
        summary.records.push(first);
        write_frame(run, dir, stepper)?;
        run.tallies.k_m_history = vec![(0, stepper.k_m)];
        fill_summary(run, stepper, summary);
        // A run killed before its first periodic checkpoint resumes from step 0.
        run.checkpoint(dir, stepper, csv.digest(), summary)?;
    }
    // A resumed run's plot is redrawn from the steps.csv it continues.
    run.draw_plot(dir, stepper, true)?;
    fill_summary(run, stepper, summary);
    drop(output);
    let bar = if opts.quiet {
        indicatif::ProgressBar::hidden()
    } else {
        let b = indicatif::ProgressBar::new(scene.steps as u64);
        if let Ok(style) = indicatif::ProgressStyle::with_template(
            "{prefix} [{bar:30}] {pos}/{len} steps {msg} ({elapsed})",
        ) {
            b.set_style(style.progress_chars("=> "));
        }
        b.set_prefix(scene.name.clone());
        b.set_position(stepper.step as u64);
        b
    };

    // 5–7. Time loop: step, recover, output.
    while stepper.step < scene.steps {
        let next = stepper.step + 1;
        let mut sink = |sys: NewtonSystem| write_system(dir, &sys);
        let dump: Option<SystemSink> = run
            .start
            .dump_systems
            .as_ref()
            .filter(|sel| sel.contains(next))
            .map(|_| &mut sink as SystemSink);
        let rep = stepper.step_with(dump).map_err(|cause| match cause {
            // The step's starting iterate (after its static projection) has an inverted
            // classical neo-Hookean element: bad input, naming the body and element.
            StepError::InvertedStart {
                body, iteration: 0, ..
            } => RunError::Input(InputError::new(
                scene.file.clone(),
                format!("bodies[{body}]"),
                format!("step {}: {cause}", stepper.step + 1),
            )),
            cause => RunError::Solve {
                step: stepper.step + 1,
                time: stepper.t + scene.time_step,
                cause: cause.to_string(),
            },
        })?;
        add_step(&mut run.tallies, &rep, stepper.has_moving());
        let output = stepper.phase(Phase::Output);
        let r = record(stepper, Some(&rep));
        if let Some(what) = non_finite(stepper, &r) {
            return Err(RunError::Solve {
                step: stepper.step,
                time: stepper.t,
                cause: format!(
                    "the state is not finite after the step: {what} (f64 overflow or \
                     underflow; check the scene's magnitudes and time step)"
                ),
            });
        }
        csv.row(&r).map_err(|e| out_err(&csv_path, e))?;
        fold_min(&mut run.tallies, &r);
        summary.records.push(r);
        drop(output);
        if stepper.step % scene.output.every == 0 || stepper.step == scene.steps {
            write_frame(run, dir, stepper)?;
        }
        let signal = INTERRUPT.load(Ordering::SeqCst);
        let last = stepper.step == scene.steps;
        if stepper.step % checkpoint_every == 0 || last || signal != 0 {
            run.checkpoint(dir, stepper, csv.digest(), summary)?;
            run.draw_plot(dir, stepper, last || signal != 0)?;
        }
        let output = stepper.phase(Phase::Output);
        fill_summary(run, stepper, summary);
        summary.wall_seconds = run.tallies.wall_seconds + run.wall.elapsed().as_secs_f64();
        summary.phases = stepper.host_profile().map(|p| PhaseSummary::of(&p));
        write_summary(dir, summary)?;
        drop(output);
        if signal != 0 {
            bar.abandon();
            return Err(RunError::Interrupted {
                signal,
                step: stepper.step,
                dir: dir.path().display().to_string(),
            });
        }
        bar.set_message(format!(
            "newton {} linear {}",
            rep.newton_iterations, rep.linear_iterations
        ));
        bar.inc(1);
    }
    bar.finish_and_clear();
    let _output = stepper.phase(Phase::Output);
    csv.finish().map_err(|e| out_err(&csv_path, e))?;
    Ok(())
}

/// steps.csv's row of the stepper's state after a step (`rep`: the step's report; None
/// for row 0, the initial state).
fn step_record(scene: &Scene, s: &Stepper, rep: Option<&StepReport>) -> StepRecord {
    StepRecord {
        step: s.step,
        time: s.t,
        newton_iterations: rep.map_or(0, |r| r.newton_iterations),
        linear_iterations: rep.map_or(0, |r| r.linear_iterations),
        linear_seconds: rep.map_or(0.0, |r| r.linear_seconds),
        cg_tol_loosest: rep.and_then(|r| r.cg_tol_loosest),
        cg_tol_tightest: rep.and_then(|r| r.cg_tol_tightest),
        linear_resolves: rep.map_or(0, |r| r.linear_resolves),
        force_residual: rep.and_then(|r| r.force_residual),
        energy: s.mechanical_energy(),
        com: s.center_of_mass(),
        momentum: s.momentum(),
        reaction: s.total_reaction(),
        k_m: s.k_m,
        eliminated_at_iteration: rep.and_then(|r| r.eliminated_at_iteration),
        min_distance: match rep {
            Some(r) => r.min_distance,
            None => s.min_distance(&s.x).map(|m| m.0),
        },
        contact: s.total_contact().unwrap_or_default(),
        max_slope: rep.and_then(|r| r.max_slope),
        ascent_directions: rep.map_or(0, |r| r.ascent_directions),
        min_j: match rep {
            Some(r) => r.min_j,
            None => scene
                .model
                .min_volume_ratio(&s.x)
                .iter()
                .map(|m| m.j)
                .reduce(f64::min),
        },
    }
}

/// Folds a row's smallest obstacle distance into the run's.
fn fold_min(t: &mut Tallies, r: &StepRecord) {
    if let Some(d) = r.min_distance {
        t.min_distance = Some(t.min_distance.map_or(d, |m: f64| m.min(d)));
    }
}

/// Adds a step's report to the run's tallies (`moving`: the scene has moving conditions).
fn add_step(t: &mut Tallies, rep: &StepReport, moving: bool) {
    t.newton_iterations += rep.newton_iterations;
    t.linear_iterations += rep.linear_iterations;
    t.linear_seconds += rep.linear_seconds;
    t.linear_resolves += rep.linear_resolves;
    t.multilevel_built += rep.multilevel_built;
    t.multilevel_kept += rep.multilevel_kept;
    t.ccd_limited += rep.ccd_limited;
    for law in &rep.inverted {
        *t.inverted_steps.entry(law.name().to_string()).or_default() += 1;
    }
    if moving {
        t.k_m_doublings += rep.k_m_doublings;
        if t.k_m_history.last().is_none_or(|&(_, k)| k != rep.k_m) {
            t.k_m_history.push((rep.step, rep.k_m));
        }
        match rep.eliminated_at_iteration {
            Some(k) => {
                t.eliminated_at_iteration.push(k);
                if k == 0 && t.first_step_eliminated_at_start.is_none() {
                    t.first_step_eliminated_at_start = Some(rep.step);
                }
            }
            None => t.all_eliminated_every_step = false,
        }
    }
}

/// Writes summary.json atomically: a reader sees the previous state or the new one.
pub(crate) fn write_summary(dir: &mut OutputDir, summary: &RunSummary) -> Result<(), RunError> {
    let path = dir.path().join("summary.json");
    let json = serde_json::to_string_pretty(summary).map_err(|e| RunError::Output {
        path: path.display().to_string(),
        cause: e.to_string(),
    })?;
    dir.write("summary.json", |w| w.write_all(json.as_bytes()))
        .map_err(|e| RunError::Output {
            path: path.display().to_string(),
            cause: e.to_string(),
        })?;
    Ok(())
}
