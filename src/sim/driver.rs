//! `stickslip run`: simulates a scene and writes VTK frames, steps.csv and summary.json.
//!
//! The driver reads as numbered steps, like MFEM's examples, each in the module that
//! holds it:
//! 1. scene (file or built-in name), 2. mesh, materials and masses, 3. boundary conditions
//!    (regions → per-node sticky / plane / line, moving or not), 4. forms: inertia,
//!    gravity, elasticity, penalties ([`crate::sim::energy`]): read, resolved and checked
//!    in `sim::scene_setup`;
//! 5. solve loop: each step projects, then runs Newton with the eliminated solve
//!    ([`crate::sim::integrator`]), 6. recover: velocities, reaction forces, momentum,
//!    center of mass, energy, and 7. output: frames every k steps, one steps.csv row per
//!    step (written as it happens), summary.json after every step (`running`), a
//!    checkpoint every `[output] checkpoint_every` steps and at the end
//!    ([`crate::sim::checkpoint`]) and, given a [`StepsPlot`], steps.svg redrawn from
//!    steps.csv: in `sim::time_loop`;
//!
//! and this module runs them: the options, the output folder (taken once every check has
//! passed), the stepper, and summary.json at the end (`complete`, `failed` or
//! `interrupted`). `run --resume DIR` continues a run from its checkpoint
//! (`sim::resume`).

use crate::error::InputError;
use crate::gpu::Phase;
use crate::io::files::{Named, OutputDir};
use crate::sim::checkpoint::{self, Checkpoint, StartOptions, Tallies};
use crate::sim::integrator::{ContactCounters, InitError, Stepper};
use crate::sim::memory::SceneTooLarge;
pub use crate::sim::run_error::RunError;
pub use crate::sim::run_options::{RunOptions, StepsPlot};
use crate::sim::scene::Scene;
use crate::sim::scene_setup::build_scene;
pub use crate::sim::scene_setup::{load_scene, open_scene, MAX_SYSTEM_ENTRY};
pub use crate::sim::summary::{
    largest_phases, ContactSummary, MovingSummary, MultilevelLevels, PhaseSummary, RunStatus,
    RunSummary, CPU_PHASES,
};
pub use crate::sim::time_loop::{request_interrupt, STEPS_PLOT, SYSTEM_FILES};
use crate::sim::time_loop::{simulate, write_summary, Run};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// What `run` writes in its output folder (what the folder's previous run of `run` wrote
/// is removed before a new run writes).
pub const OUTPUT_NAMES: [&str; 6] = [
    "steps.csv",
    STEPS_PLOT,
    "summary.json",
    checkpoint::FILE_NAME,
    "frames/*.vtk",
    crate::sim::output::FRAMES_COLLECTION,
];

/// Takes the output folder for this run (see [`crate::io::files::OutputDir`]); with
/// `check_only`, checks it without creating or changing anything (and returns None).
fn open_out(
    dir: &Path,
    scene: Option<&str>,
    option: &str,
    overwrite: bool,
    check_only: bool,
) -> Result<Option<OutputDir>, RunError> {
    let scene_file = scene.filter(|s| Path::new(s).is_file());
    let inputs: Vec<Named> = scene_file
        .iter()
        .map(|s| Named::new("scene", Path::new(*s)))
        .collect();
    let names = &OUTPUT_NAMES[..];
    if check_only {
        OutputDir::check(dir, option, "run", names, &inputs, overwrite)?;
        return Ok(None);
    }
    let d = OutputDir::open(dir, option, "run", names, &inputs, overwrite)?;
    Ok(Some(d))
}

/// Runs a scene to the end, or resumes one. One call: parse, simulate, write.
///
/// Every input and resource check comes before anything in the output folder changes:
/// the folder itself (when `out` is given, before the scene is read), the scene and the
/// options, the stepper's own checks (static conditions, the GPU adapter and its
/// capacity) and, with `resume`, the checkpoint (readable, of this scene, of the folder's
/// run). Then the folder is created, locked and cleared of what its previous run wrote
/// (resuming: brought back to the checkpoint's step). summary.json is written at the
/// start and after every step with `"status": "running"`, and at the end with
/// `"complete"`, `"interrupted"`, or `"failed"` and the message. A resume of a run whose
/// steps are all done finishes it.
pub fn run(opts: &RunOptions) -> Result<RunSummary, RunError> {
    let wall = Instant::now();
    let resumed = match &opts.resume {
        Some(dir) => {
            crate::sim::resume::refuse_options(opts)?;
            Some(checkpoint::read(dir)?)
        }
        None => None,
    };
    let start = start_options(opts, resumed.as_ref());
    // An output folder that cannot be used fails before the scene is read; it is
    // created (and taken) once every check has passed.
    if let (Some(d), None) = (&opts.out, &resumed) {
        open_out(d, Some(&start.scene), "--out", opts.overwrite, true)?;
    }
    // 1–4. Scene, mesh, boundary conditions and forms.
    let steps = match opts.end_time {
        Some(_) => opts.steps,
        None => opts.steps.or(resumed.as_ref().map(|c| c.steps)),
    };
    let scene = build_scene(&start, steps, opts.end_time)?;
    if let Some(sel) = &start.dump_systems {
        sel.check(scene.steps)
            .map_err(|p| InputError::new("--dump-systems", "", p))?;
    }
    let kept_rows = match (&resumed, &opts.resume) {
        (Some(ck), Some(dir)) => Some(crate::sim::resume::check(ck, &scene, dir)?),
        _ => None,
    };
    let mut stepper = open_stepper(&scene, resumed.as_ref(), wall)?;
    // The folder, the fingerprint and a resume's preparation are the run's set-up.
    let setup = stepper.phase(Phase::Setup);
    let (out, option) = match &opts.resume {
        Some(d) => (d.clone(), "--resume"),
        None => (
            opts.out
                .clone()
                .unwrap_or_else(|| PathBuf::from("out").join(&scene.name)),
            "--out",
        ),
    };
    let Some(mut dir) = open_out(&out, Some(&start.scene), option, opts.overwrite, false)? else {
        unreachable!("open_out returns the folder unless check_only")
    };
    let fingerprint = checkpoint::fingerprint(&scene);
    let mut tallies = Tallies {
        all_eliminated_every_step: true,
        ..Tallies::default()
    };
    let mut frames = Vec::new();
    let run_id = match (&resumed, &kept_rows) {
        (Some(ck), Some(kept)) => {
            tallies = ck.tallies.clone();
            let step = ck.snapshot.step;
            frames = crate::sim::resume::prepare(&mut dir, &scene, step, kept, &mut tallies)?;
            ck.identity.run_id.clone()
        }
        _ => {
            dir.clean().map_err(|e| RunError::Output {
                path: out.display().to_string(),
                cause: format!("cannot clear the previous run's files: {e}"),
            })?;
            checkpoint::new_run_id(&fingerprint)
        }
    };
    // From here on summary.json always says how far the run got.
    let mut summary = new_summary(&scene, &out, run_id.clone());
    summary.resumed_from_step = resumed.as_ref().map(|c| c.snapshot.step);
    summary.adapter = stepper.adapter().map(str::to_string);
    summary.newton_tolerance = stepper.newton_tol;
    summary.end_time = stepper.t;
    summary.steps_completed = stepper.step;
    let mut this_run = Run {
        scene: &scene,
        fingerprint,
        run_id,
        start: StartOptions {
            scene: stored_scene(&start.scene),
            ..start
        },
        tallies,
        frames,
        wall,
        plot: opts.steps_plot.clone(),
        plot_due: None,
    };
    drop(setup);
    let result = write_summary(&mut dir, &summary)
        .and_then(|_| simulate(&mut this_run, opts, &mut stepper, &mut dir, &mut summary));
    summary.contact_counters = stepper.contact_counters();
    summary.gpu = stepper.gpu_report().map(|mut g| {
        g.newton_iterations = summary.newton_iterations;
        g.host_to_device_bytes += this_run.tallies.host_to_device_bytes;
        g.device_to_host_bytes += this_run.tallies.device_to_host_bytes;
        g
    });
    summary.final_positions = stepper.x.clone();
    summary.final_velocities = stepper.v.clone();
    summary.wall_seconds = this_run.tallies.wall_seconds + wall.elapsed().as_secs_f64();
    summary.phases = stepper.host_profile().map(|p| PhaseSummary::of(&p));
    match result {
        Ok(()) => {
            summary.status = RunStatus::Complete;
            write_summary(&mut dir, &summary)?;
            Ok(summary)
        }
        Err(e) => {
            summary.status = match e {
                RunError::Interrupted { .. } => RunStatus::Interrupted,
                _ => RunStatus::Failed,
            };
            summary.message = Some(e.to_string());
            // The run's own error is the one to report; a failure to record it is not.
            // An interrupted run drew its plot with its last checkpoint.
            if !matches!(e, RunError::Interrupted { .. }) {
                let _ = this_run.draw_plot(&mut dir, &stepper, true);
            }
            let _ = write_summary(&mut dir, &summary);
            Err(e)
        }
    }
}

/// The options the run starts from: a new run's, or the checkpoint's (with the steps to
/// dump replaced when `--dump-systems` is given with `--resume`).
fn start_options(opts: &RunOptions, resumed: Option<&Checkpoint>) -> StartOptions {
    match resumed {
        Some(ck) => StartOptions {
            dump_systems: opts
                .dump_systems
                .clone()
                .or_else(|| ck.options.dump_systems.clone()),
            ..ck.options.clone()
        },
        None => StartOptions {
            scene: opts.scene.clone().unwrap_or_else(|| "default".into()),
            size: opts.size.unwrap_or(1.0),
            solver: opts.solver,
            ordering: opts.ordering,
            newton: opts.newton,
            cg_tolerance: opts.cg_tolerance,
            preconditioner: opts.preconditioner,
            dump_systems: opts.dump_systems.clone(),
        },
    }
}

/// The scene as the checkpoint keeps it: a file by its absolute path (a resume may run
/// in another working directory), a built-in scene by its name.
fn stored_scene(scene: &str) -> String {
    let p = Path::new(scene);
    if p.is_file() {
        if let Ok(abs) = std::path::absolute(p) {
            return abs.display().to_string();
        }
    }
    scene.to_string()
}

/// The stepper of `scene` (its checks: static conditions, the GPU adapter and its
/// capacity), restored to the checkpoint's state when resuming.
fn open_stepper<'s>(
    scene: &'s Scene,
    resumed: Option<&Checkpoint>,
    wall: Instant,
) -> Result<Stepper<'s>, RunError> {
    let mut stepper = Stepper::new(scene).map_err(|e| match e {
        InitError::Input { entry, problem } => {
            RunError::Input(InputError::new(scene.file.clone(), entry, problem))
        }
        InitError::Solver(cause) => RunError::Solve {
            step: 0,
            time: 0.0,
            cause: cause.to_string(),
        },
        InitError::Memory(e) => RunError::Memory(SceneTooLarge {
            scene: scene.name.clone(),
            error: e.with_nodes(scene.model.n_nodes),
        }),
    })?;
    stepper.started_at(wall);
    let _setup = stepper.phase(Phase::Setup);
    if let Some(ck) = resumed {
        stepper.restore(&ck.snapshot).map_err(|e| RunError::Solve {
            step: ck.snapshot.step,
            time: ck.snapshot.t,
            cause: e.to_string(),
        })?;
    }
    Ok(stepper)
}

/// summary.json at the start of a run (status `running`, nothing done yet).
fn new_summary(scene: &Scene, out: &Path, run_id: String) -> RunSummary {
    use crate::sim::scene::NewtonLoop;
    RunSummary {
        status: RunStatus::Running,
        message: None,
        run_id,
        scene: scene.name.clone(),
        file: scene.file.clone(),
        dimension: scene.dim,
        nodes: scene.model.n_nodes,
        elements: scene.cells.iter().map(|b| b.len()).sum(),
        total_mass: scene.model.total_mass(),
        time_step: scene.time_step,
        gravity: scene.gravity.clone(),
        steps: scene.steps,
        steps_completed: 0,
        end_time: 0.0,
        wall_seconds: 0.0,
        solver: match scene.solver.newton {
            NewtonLoop::Gpu => "newton-gpu".to_string(),
            NewtonLoop::Cpu => scene.solver.linear.to_string(),
        },
        linear_choice: match scene.solver.newton {
            NewtonLoop::Gpu => None,
            NewtonLoop::Cpu => scene
                .solver
                .linear_choice
                .reason(scene.dim, scene.model.n_nodes),
        },
        preconditioner: (scene.solver.newton == NewtonLoop::Gpu
            || scene.solver.linear != crate::sim::scene::LinearKind::Cholesky)
            .then(|| scene.solver.preconditioner.name().to_string()),
        preconditioner_choice: scene
            .solver
            .preconditioner_reason(scene.dim, scene.model.n_nodes),
        adapter: None,
        characteristic_length: scene.characteristic_length,
        newton_tolerance: 0.0,
        newton_iterations: 0,
        linear_iterations: 0,
        linear_seconds: 0.0,
        cg_tolerance: scene.solver.cg_tolerance,
        linear_resolves: 0,
        multilevel_levels: None,
        frames: 0,
        out_dir: out.display().to_string(),
        resumed_from_step: None,
        checkpoint_every: scene.output.checkpoint_every.unwrap_or(scene.output.every),
        checkpoint_seconds: 0.0,
        moving_boundary: None,
        inverted_steps: Default::default(),
        contact_counters: ContactCounters::default(),
        contact: None,
        phases: None,
        gpu: None,
        records: Vec::new(),
        final_positions: Vec::new(),
        final_velocities: Vec::new(),
    }
}
