//! `stickslip run`: simulates a scene and writes VTK frames, steps.csv and summary.json.
//!
//! The driver reads as numbered steps, like MFEM's examples:
//! 1. scene (file or built-in name) → mesh, materials, masses;
//! 2. boundary conditions (regions → per-node sticky / plane / line, moving or not);
//! 3. forms: inertia, gravity, elasticity, penalties ([`crate::sim::energy`]);
//! 4. time loop: each step projects, then runs Newton with the eliminated solve
//!    ([`crate::sim::integrator`]);
//! 5. recover: velocities, reaction forces, momentum, center of mass, energy;
//! 6. output: frames every k steps, one steps.csv row per step (written as it happens),
//!    summary.json after every step (`running`), and at the end (`complete`, `failed`
//!    or `interrupted`), a checkpoint every `[output] checkpoint_every` steps and at the
//!    end ([`crate::sim::checkpoint`]): `run --resume DIR` continues from it.

use crate::error::InputError;
use crate::gpu::Phase;
use crate::io::files::{Named, OutputDir};
use crate::sim::checkpoint::{self, Checkpoint, StartOptions, Tallies};
use crate::sim::integrator::{
    ContactCounters, InitError, NewtonSystem, StepError, Stepper, SystemSink,
};
use crate::sim::memory::SceneTooLarge;
use crate::sim::output::{write_vtk, StepRecord, StepsCsv};
use crate::sim::scene::{self, LinearKind, LoadError, MovingSpec, Scene};
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicI32, Ordering};
use std::time::Instant;

/// What `stickslip run` was asked.
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// A scene file path or a built-in scene name; None: the built-in `default`.
    pub scene: Option<String>,
    /// Output folder; None: `out/<scene name>`.
    pub out: Option<PathBuf>,
    /// Overrides the scene's linear solver: cholesky | cg | gpu.
    pub solver: Option<String>,
    /// Mesh resolution multiplier (default 1).
    pub size: Option<f64>,
    /// Overrides the number of steps.
    pub steps: Option<usize>,
    /// No progress bar.
    pub quiet: bool,
    /// Replace files in the output folder that look like a run's output but no previous
    /// run's manifest lists (otherwise such a folder is refused).
    pub overwrite: bool,
    /// Overrides the scene's Cholesky ordering.
    pub ordering: Option<crate::CholeskyOrdering>,
    /// Overrides where the Newton loop runs (`[solver] newton`).
    pub newton: Option<crate::sim::scene::NewtonLoop>,
    /// Overrides the CG tolerance policy of the Newton systems (`[solver] cg_tolerance`).
    pub cg_tolerance: Option<crate::sim::scene::CgTolerance>,
    /// Overrides the number of steps by the end time: round(T / h) steps.
    pub end_time: Option<f64>,
    /// Write every Newton system of these steps under `systems/step_S/iter_K/` in the
    /// output folder (`run --dump-systems`).
    pub dump_systems: Option<crate::sim::integrator::StepSelection>,
    /// Continue the run in this folder from its checkpoint (the scene and its options
    /// come from the checkpoint; `steps` or `end_time` may extend it).
    pub resume: Option<PathBuf>,
}

/// Why a run failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RunError {
    /// Bad scene or options (exit code 2).
    #[error("{0}")]
    Input(#[from] InputError),
    /// A step failed (exit code 1).
    #[error("step {step} (t = {} s) failed: {cause}", show_time(.time))]
    Solve {
        step: usize,
        time: f64,
        cause: String,
    },
    /// Output could not be written (exit code 1).
    #[error("cannot write {path}: {cause}")]
    Output { path: String, cause: String },
    /// The scene does not fit in the memory the process may allocate (exit code 1).
    #[error("{0}")]
    Memory(#[from] SceneTooLarge),
    /// SIGINT or SIGTERM: the run stopped after a completed step and wrote its checkpoint
    /// (exit code 128 + the signal).
    #[error("interrupted by signal {signal} after step {step}; `stickslip run --resume {dir}` continues the run")]
    Interrupted {
        signal: i32,
        step: usize,
        dir: String,
    },
}

/// A time for a message: fixed-point when it reads well, else scientific (a time step of
/// 1e300 must not print 300 digits, nor 1e-300 print 0.000000).
fn show_time(t: &f64) -> String {
    if *t == 0.0 || (1e-3..1e6).contains(&t.abs()) {
        format!("{t:.6}")
    } else {
        format!("{t:.6e}")
    }
}

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

impl RunError {
    /// The process exit code for this error: 2 for bad input ([`RunError::Input`]: the
    /// scene, its entries or the command-line options), 1 for everything else (a failed
    /// step, output that could not be written). The command line exits with it.
    pub fn exit_code(&self) -> i32 {
        match self {
            RunError::Input(_) => 2,
            RunError::Interrupted { signal, .. } => 128 + signal,
            _ => 1,
        }
    }
}

/// Moving-boundary history of a run.
#[derive(Debug, Clone, serde::Serialize)]
pub struct MovingSummary {
    pub settings: MovingSpec,
    pub moving_nodes: usize,
    pub k_m_start: f64,
    pub k_m_final: f64,
    pub k_m_doublings: usize,
    /// (step, k_M) at every step where k_M changed.
    pub k_m_history: Vec<(usize, f64)>,
    /// Per step: the Newton iteration at which every moving node was eliminated.
    pub eliminated_at_iteration: Vec<usize>,
    /// First step at which the moving nodes were all satisfied at the start of the step
    /// (pure elimination, no penalty iteration), if any.
    pub first_step_eliminated_at_start: Option<usize>,
    /// Every step ended with every moving node on its target and eliminated.
    pub all_eliminated_every_step: bool,
}

/// Contact history of a run (scenes with obstacles).
#[derive(Debug, Clone, serde::Serialize)]
pub struct ContactSummary {
    pub obstacles: usize,
    /// Per obstacle: d̂ (m) and κ (Pa) as resolved (defaults filled in).
    pub dhat: Vec<f64>,
    pub kappa: Vec<f64>,
    /// Smallest node–obstacle signed distance over every Newton iterate of the run.
    pub min_distance: f64,
    /// Line searches cut by the CCD bound (α_C < 1).
    pub ccd_limited_line_searches: usize,
    /// Summed contact force at the end (newtons).
    pub final_contact_force: Vec<f64>,
}

/// How far a run got, as summary.json says it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum RunStatus {
    Running,
    Complete,
    Failed,
    /// Stopped by SIGINT or SIGTERM after a completed step, with a checkpoint there.
    Interrupted,
}

/// What a run did (summary.json holds everything but the per-step records and state).
#[derive(Debug, Clone, serde::Serialize)]
pub struct RunSummary {
    /// `running` while the run goes (rewritten after every step), then `complete`,
    /// `failed` or `interrupted`.
    pub status: RunStatus,
    /// Why the run failed (the command's error line), for `failed`.
    pub message: Option<String>,
    pub scene: String,
    pub file: String,
    pub dimension: usize,
    pub nodes: usize,
    pub elements: usize,
    pub total_mass: f64,
    pub time_step: f64,
    pub gravity: Vec<f64>,
    /// Steps asked for.
    pub steps: usize,
    /// Steps finished (equal to `steps` when complete).
    pub steps_completed: usize,
    pub end_time: f64,
    pub wall_seconds: f64,
    pub solver: String,
    /// Why `[solver] linear = "auto"` chose `solver` (None for an explicit choice).
    pub linear_choice: Option<String>,
    pub adapter: Option<String>,
    pub characteristic_length: f64,
    /// Newton stops when ‖Δx‖∞/h is below this (m/s).
    pub newton_tolerance: f64,
    pub newton_iterations: usize,
    pub linear_iterations: usize,
    pub linear_seconds: f64,
    /// The CG tolerance policy of the Newton systems: "adaptive" or the fixed number.
    pub cg_tolerance: crate::sim::scene::CgTolerance,
    /// Systems solved again to the convergence tolerance because their loosely solved
    /// direction passed the Newton test (adaptive tolerance only).
    pub linear_resolves: usize,
    /// With the multilevel preconditioner: how its levels were set up over the run's
    /// Newton systems (absent otherwise).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub multilevel_levels: Option<MultilevelLevels>,
    pub frames: usize,
    pub out_dir: String,
    /// The step this invocation resumed from (`run --resume`); None for a run started
    /// from step 0.
    pub resumed_from_step: Option<usize>,
    /// Checkpoints are written every this many steps (and at the last step).
    pub checkpoint_every: usize,
    /// Wall time spent writing checkpoints, over every invocation of the run.
    pub checkpoint_seconds: f64,
    pub moving_boundary: Option<MovingSummary>,
    /// Per neo-Hookean law of the scene (by its scene name, e.g. "stable-neo-hookean"):
    /// the steps that ended with an inverted element (J ≤ 0). The classical law's line
    /// search keeps its elements' J positive, so its count stays 0.
    pub inverted_steps: std::collections::BTreeMap<String, usize>,
    /// What the contact code did: all zero for a scene without obstacles.
    pub contact_counters: ContactCounters,
    /// Contact history; None for a scene without obstacles.
    pub contact: Option<ContactSummary>,
    /// The GPU Newton loop's adapter, precision and host↔device traffic (totals over the
    /// run); absent for a run with the CPU loop.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub gpu: Option<crate::sim::integrator::GpuRunReport>,
    #[serde(skip)]
    pub records: Vec<StepRecord>,
    #[serde(skip)]
    pub final_positions: Vec<f64>,
    #[serde(skip)]
    pub final_velocities: Vec<f64>,
}

/// Loads a scene by path or built-in name, applying the size option.
pub fn load_scene(name_or_path: &str, size: f64) -> Result<Scene, InputError> {
    open_scene(name_or_path, size).map_err(|e| match e {
        LoadError::Input(e) => e,
        LoadError::Memory(m) => InputError::new(name_or_path, "", m.to_string()),
    })
}

/// [`load_scene`], telling a scene too large for memory ([`LoadError::Memory`]) apart.
pub fn open_scene(name_or_path: &str, size: f64) -> Result<Scene, LoadError> {
    let p = Path::new(name_or_path);
    // A path that exists is a file to read, never a name to look up: a folder (or a
    // device) says so instead of "no such scene".
    if let Ok(m) = std::fs::metadata(p) {
        if m.is_dir() {
            return Err(
                InputError::new(name_or_path, "", "is a folder, not a scene file (TOML)").into(),
            );
        }
        let text = crate::io::read_text(name_or_path).map_err(LoadError::Input)?;
        return scene::load(crate::io::strip_bom(&text), name_or_path, size);
    }
    if p.is_file() {
        let text = crate::io::read_text(name_or_path).map_err(LoadError::Input)?;
        return scene::load(crate::io::strip_bom(&text), name_or_path, size);
    }
    if let Some(text) = scene::builtin(name_or_path) {
        return scene::load(text, &format!("scenes/{name_or_path}.toml"), size);
    }
    let names: Vec<&str> = scene::BUILTIN.iter().map(|(n, _)| *n).collect();
    Err(InputError::new(
        name_or_path,
        "",
        format!(
            "no such scene file or built-in scene (built-ins: {})",
            names.join(", ")
        ),
    )
    .into())
}

/// The largest entry a Newton system may hold, about √(f64::MAX): the solvers square
/// entries (dot products, Cholesky pivots), and past it those squares overflow.
pub const MAX_SYSTEM_ENTRY: f64 = 1.3e154;

/// Magnitudes that each look valid but together overflow the Newton system H = M + h²K
/// (+ h²·barrier): found here, named on the key that causes them, instead of failing a
/// step later as "not positive definite" or "overflowed".
fn check_magnitudes(scene: &Scene) -> Result<(), RunError> {
    let h = scene.time_step;
    let h2 = h * h;
    let mut k = scene.model.try_zero_matrix().map_err(|e| SceneTooLarge {
        scene: scene.name.clone(),
        error: e.with_nodes(scene.model.n_nodes),
    })?;
    scene
        .model
        .add_potential_hessian(&scene.x0, 1.0, true, &mut k);
    let kmax = k.max_abs();
    // A non-finite stiffness is the material's fault, reported where it is used.
    let scaled = h2 * kmax;
    if kmax.is_finite() && (scaled.is_nan() || scaled > MAX_SYSTEM_ENTRY) {
        return Err(InputError::new(
            scene.file.clone(),
            "time_step",
            format!(
                "h = {h:.3e} s scales the stiffness (largest entry {kmax:.3e} at the initial \
                 state) to h²K = {:.3e}, past the {MAX_SYSTEM_ENTRY:.1e} (≈ √f64::MAX) the \
                 solvers can square; take a smaller time step",
                scaled
            ),
        )
        .into());
    }
    for (j, o) in scene.obstacles.iter().enumerate() {
        let (dhat, kappa) = (o.plane.dhat, o.plane.kappa);
        let scale = h2 * kappa * dhat * dhat;
        if scale.is_nan() || scale > MAX_SYSTEM_ENTRY {
            return Err(InputError::new(
                scene.file.clone(),
                format!("obstacle[{j}].dhat"),
                format!(
                    "d̂ = {dhat:.3e} m makes the barrier's energy scale h²κd̂² = {scale:.3e} \
                     overflow the {MAX_SYSTEM_ENTRY:.1e} (≈ √f64::MAX) the solvers can square; \
                     d̂ is an activation distance, a small fraction of the scene's size \
                     (L = {:.3e} m)",
                    scene.characteristic_length
                ),
            )
            .into());
        }
    }
    Ok(())
}

/// What `run` writes in its output folder (what the folder's previous run of `run` wrote
/// is removed before a new run writes).
pub const OUTPUT_NAMES: [&str; 4] = [
    "steps.csv",
    "summary.json",
    checkpoint::FILE_NAME,
    "frames/*.vtk",
];

/// The signal that asked the run to stop (0: none). Set by the command line's SIGINT and
/// SIGTERM handlers ([`request_interrupt`]); the time loop stops after the step it is in.
static INTERRUPT: AtomicI32 = AtomicI32::new(0);

/// Asks a running [`run`] to stop after its current step, writing a checkpoint there
/// (async-signal-safe: one atomic store).
pub fn request_interrupt(signal: i32) {
    INTERRUPT.store(signal, Ordering::SeqCst);
}

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

/// Writes summary.json atomically: a reader sees the previous state or the new one.
fn write_summary(dir: &mut OutputDir, summary: &RunSummary) -> Result<(), RunError> {
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

/// 1–3: the scene of `start` with the run's overrides, checked.
fn build_scene(
    start: &StartOptions,
    steps: Option<usize>,
    end_time: Option<f64>,
) -> Result<Scene, RunError> {
    // `--size` is checked (once) by the scene parser, which names `--size`.
    let mut scene = open_scene(&start.scene, start.size).map_err(|e| match e {
        LoadError::Input(e) => RunError::Input(e),
        LoadError::Memory(m) => RunError::Memory(m),
    })?;
    if let Some(s) = &start.solver {
        scene.solver.linear = s
            .parse::<LinearKind>()
            .map_err(|e| InputError::new("--solver", "", e))?;
        scene.solver.linear_choice = crate::sim::scene::LinearChoice::of(scene.solver.linear);
    }
    if let Some(o) = start.ordering {
        scene.solver.ordering = o;
    }
    if let Some(n) = start.newton {
        scene.solver.newton = n;
    }
    if let Some(t) = start.cg_tolerance {
        scene.solver.cg_tolerance = t;
    }
    if steps.is_some() && end_time.is_some() {
        return Err(InputError::new("--end-time", "", "give either --steps or --end-time").into());
    }
    if let Some(t) = end_time {
        let n = t / scene.time_step;
        if !(t.is_finite() && t > 0.0) || n.round() > scene::MAX_STEPS as f64 {
            return Err(InputError::new(
                "--end-time",
                "",
                format!(
                    "must be positive and reach at most {} steps of {} s, got {t}",
                    scene::MAX_STEPS,
                    scene.time_step
                ),
            )
            .into());
        }
        scene.steps = (n.round() as usize).max(1);
    }
    if let Some(n) = steps {
        if n == 0 {
            return Err(InputError::new("--steps", "", "must be at least 1").into());
        }
        if n > scene::MAX_STEPS {
            return Err(InputError::new(
                "--steps",
                "",
                format!("{n} is more than the cap of {}", scene::MAX_STEPS),
            )
            .into());
        }
        scene.steps = n;
    }
    // The inertia term m/h² must be a finite, nonzero f64 for every node: a time step so
    // small (or a mass so large) that it overflows is the scene's fault, not a step's.
    let h2 = scene.time_step * scene.time_step;
    if let Some(m) = scene
        .model
        .mass
        .iter()
        .find(|&&m| m > 0.0 && !(h2 > 0.0 && (m / h2).is_finite()))
    {
        return Err(InputError::new(
            scene.file.clone(),
            "time_step",
            format!(
                "h = {:.3e} s gives an inertia term m/h² = {:.3e}/{h2:.3e} that is not a finite f64",
                scene.time_step, m
            ),
        )
        .into());
    }
    check_magnitudes(&scene)?;
    // The device Newton loop and the GPU solver in f64 run the device PCG, which has
    // the multilevel preconditioner; f32 and mixed precision do not.
    if scene.solver.preconditioner == crate::solve::options::Preconditioner::Multilevel
        && scene.solver.linear == LinearKind::Gpu
        && scene.solver.newton != crate::sim::scene::NewtonLoop::Gpu
        && scene.solver.precision != crate::gpu::Precision::F64
    {
        return Err(InputError::new(
            scene.file.clone(),
            "solver.preconditioner",
            format!(
                "{}; this scene's linear = \"gpu\" runs in {} (set [solver] precision = \"f64\")",
                crate::gpu::MULTILEVEL_ON_CPU,
                scene.solver.precision
            ),
        )
        .into());
    }
    if scene.solver.linear == LinearKind::Gpu
        || scene.solver.newton == crate::sim::scene::NewtonLoop::Gpu
    {
        if let Some(problem) = crate::gpu::adapter_name_mismatch(&crate::gpu::GpuOptions::default())
        {
            return Err(InputError::new("WGPU_ADAPTER_NAME", "", problem).into());
        }
    }
    Ok(scene)
}

/// The options that cannot change on a resume (the checkpoint holds them).
fn refuse_with_resume(opts: &RunOptions) -> Result<(), RunError> {
    let fixed = [
        ("a scene", opts.scene.is_some()),
        ("--out", opts.out.is_some()),
        ("--solver", opts.solver.is_some()),
        ("--size", opts.size.is_some()),
        ("--ordering", opts.ordering.is_some()),
        ("--newton", opts.newton.is_some()),
        ("--cg-tolerance", opts.cg_tolerance.is_some()),
        ("--overwrite", opts.overwrite),
    ];
    for (what, given) in fixed {
        if given {
            return Err(InputError::new(
                "--resume",
                "",
                format!(
                    "takes its scene and options from the checkpoint: {what} cannot be given \
                     with it (only --steps or --end-time)"
                ),
            )
            .into());
        }
    }
    Ok(())
}

/// Checks a checkpoint against the scene rebuilt from it, before anything in the folder
/// changes: the same fingerprint, and steps beyond the checkpoint's.
fn check_resume(ck: &Checkpoint, scene: &Scene, dir: &Path) -> Result<(), RunError> {
    let file = dir.join(checkpoint::FILE_NAME).display().to_string();
    let fp = checkpoint::fingerprint(scene);
    if fp != ck.fingerprint {
        return Err(InputError::new(
            &file,
            "",
            format!(
                "was written for another scene (fingerprint {} here, {fp} for {} now): the \
                 scene file or what it reads changed since the run started",
                ck.fingerprint, ck.options.scene
            ),
        )
        .into());
    }
    if scene.steps <= ck.snapshot.step {
        return Err(InputError::new(
            &file,
            "",
            format!(
                "the run has done {} of {} steps; give --steps or --end-time beyond step {}",
                ck.snapshot.step, scene.steps, ck.snapshot.step
            ),
        )
        .into());
    }
    Ok(())
}

/// Runs a scene to the end, or resumes one. One call: parse, simulate, write.
///
/// The output folder is checked before the scene is read when `out` is given; it is
/// created, locked and cleared of what its previous run wrote once the scene has been
/// read and checked. summary.json is written at the start and after every step with
/// `"status": "running"`, and at the end with `"complete"`, `"interrupted"`, or
/// `"failed"` and the message. With `resume`, every refusal (no checkpoint, another
/// scene, a corrupt file, a folder another process holds) comes before anything in the
/// folder changes; then steps.csv rows and frames after the checkpoint are removed and
/// the run goes on, appending.
pub fn run(opts: &RunOptions) -> Result<RunSummary, RunError> {
    let wall = Instant::now();
    let resumed = match &opts.resume {
        Some(dir) => {
            refuse_with_resume(opts)?;
            Some(checkpoint::read(dir)?)
        }
        None => None,
    };
    let start = match &resumed {
        Some(ck) => ck.options.clone(),
        None => StartOptions {
            scene: opts.scene.clone().unwrap_or_else(|| "default".into()),
            size: opts.size.unwrap_or(1.0),
            solver: opts.solver.clone(),
            ordering: opts.ordering,
            newton: opts.newton,
            cg_tolerance: opts.cg_tolerance,
        },
    };
    // An output folder that cannot be used fails before the scene is read; it is
    // created (and taken) once the scene has passed its checks.
    if let (Some(d), None) = (&opts.out, &resumed) {
        open_out(d, Some(&start.scene), "--out", opts.overwrite, true)?;
    }
    // 1–3. Scene, boundary conditions and forms.
    let steps = opts.steps.or(resumed.as_ref().map(|c| c.steps));
    let steps = if opts.end_time.is_some() {
        opts.steps
    } else {
        steps
    };
    let scene = build_scene(&start, steps, opts.end_time)?;
    if let Some(sel) = &opts.dump_systems {
        sel.check(scene.steps)
            .map_err(|p| InputError::new("--dump-systems", "", p))?;
    }
    if let (Some(ck), Some(dir)) = (&resumed, &opts.resume) {
        check_resume(ck, &scene, dir)?;
    }
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

    let stepper = Stepper::new(&scene).map_err(|e| match e {
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
    });
    // From here on the folder is this run's: the previous run's files go (or, resuming,
    // what came after the checkpoint), and summary.json always says how far the run got.
    let prepared = match &resumed {
        Some(ck) => prepare_resume(&mut dir, &scene, ck),
        None => dir.clean().map_err(|e| RunError::Output {
            path: out.display().to_string(),
            cause: format!("cannot clear the previous run's files: {e}"),
        }),
    };
    prepared?;
    let tallies = resumed
        .as_ref()
        .map(|c| c.tallies.clone())
        .unwrap_or(Tallies {
            all_eliminated_every_step: true,
            ..Tallies::default()
        });
    let mut summary = RunSummary {
        status: RunStatus::Running,
        message: None,
        scene: scene.name.clone(),
        file: scene.file.clone(),
        dimension: scene.dim,
        nodes: scene.model.n_nodes,
        elements: scene.cells.iter().map(|b| b.cells.len()).sum(),
        total_mass: scene.model.total_mass(),
        time_step: scene.time_step,
        gravity: scene.gravity.clone(),
        steps: scene.steps,
        steps_completed: 0,
        end_time: 0.0,
        wall_seconds: 0.0,
        solver: match scene.solver.newton {
            crate::sim::scene::NewtonLoop::Gpu => "newton-gpu".to_string(),
            crate::sim::scene::NewtonLoop::Cpu => scene.solver.linear.to_string(),
        },
        linear_choice: match scene.solver.newton {
            crate::sim::scene::NewtonLoop::Gpu => None,
            crate::sim::scene::NewtonLoop::Cpu => scene
                .solver
                .linear_choice
                .reason(scene.dim, scene.model.n_nodes),
        },
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
        resumed_from_step: resumed.as_ref().map(|c| c.snapshot.step),
        checkpoint_every: scene.output.checkpoint_every.unwrap_or(scene.output.every),
        checkpoint_seconds: 0.0,
        moving_boundary: None,
        inverted_steps: Default::default(),
        contact_counters: ContactCounters::default(),
        contact: None,
        gpu: None,
        records: Vec::new(),
        final_positions: Vec::new(),
        final_velocities: Vec::new(),
    };
    let mut this_run = Run {
        scene: &scene,
        fingerprint: checkpoint::fingerprint(&scene),
        start,
        tallies,
        wall,
    };
    let result = match stepper {
        Ok(mut stepper) => {
            stepper.started_at(wall);
            summary.adapter = stepper.adapter().map(str::to_string);
            summary.newton_tolerance = stepper.newton_tol;
            let r = match &resumed {
                Some(ck) => stepper.restore(&ck.snapshot).map_err(|e| RunError::Solve {
                    step: ck.snapshot.step,
                    time: ck.snapshot.t,
                    cause: e.to_string(),
                }),
                None => Ok(()),
            };
            summary.end_time = stepper.t;
            summary.steps_completed = stepper.step;
            let r = r
                .and_then(|_| write_summary(&mut dir, &summary))
                .and_then(|_| simulate(&mut this_run, opts, &mut stepper, &mut dir, &mut summary));
            summary.contact_counters = stepper.contact_counters();
            summary.gpu = stepper.gpu_report().map(|mut g| {
                g.newton_iterations = summary.newton_iterations;
                g
            });
            summary.final_positions = stepper.x.clone();
            summary.final_velocities = stepper.v.clone();
            r
        }
        Err(e) => Err(e),
    };
    summary.wall_seconds = this_run.tallies.wall_seconds + wall.elapsed().as_secs_f64();
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
            let _ = write_summary(&mut dir, &summary);
            Err(e)
        }
    }
}

/// A resumed run's folder: the manifest continues, steps.csv keeps its header and the
/// rows up to the checkpoint's step (a partial last row is dropped), and the frames after
/// it go, with the checkpoint step's own frame when it was written only because that step
/// was the last one.
fn prepare_resume(dir: &mut OutputDir, scene: &Scene, ck: &Checkpoint) -> Result<(), RunError> {
    let step = ck.snapshot.step;
    let out_err = |path: &Path, cause: String| RunError::Output {
        path: path.display().to_string(),
        cause,
    };
    dir.resume()
        .map_err(|e| out_err(dir.path(), e.to_string()))?;
    let csv = dir.path().join("steps.csv");
    let text = std::fs::read_to_string(&csv).map_err(|e| out_err(&csv, e.to_string()))?;
    let kept = crate::sim::output::rows_up_to(&text, step).ok_or_else(|| {
        out_err(
            &csv,
            format!("holds fewer rows than the checkpoint's {step} steps"),
        )
    })?;
    crate::io::files::write_atomic_bytes(&csv, kept.as_bytes())
        .map_err(|e| out_err(&csv, e.to_string()))?;
    let frames = dir.path().join("frames");
    let every = scene.output.every;
    let prefix = format!("{}_", scene.name);
    if let Ok(entries) = std::fs::read_dir(&frames) {
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let Some(n) = name
                .strip_prefix(&prefix)
                .and_then(|r| r.strip_suffix(".vtk"))
                .and_then(|r| r.parse::<usize>().ok())
            else {
                continue;
            };
            let last_only = n == step && n % every != 0 && n != 0;
            if n > step || last_only {
                std::fs::remove_file(e.path())
                    .map_err(|err| out_err(&e.path(), err.to_string()))?;
            }
        }
    }
    Ok(())
}

/// What the time loop carries besides the stepper: the run's identity for its
/// checkpoints, and its tallies.
struct Run<'a> {
    scene: &'a Scene,
    fingerprint: String,
    start: StartOptions,
    tallies: Tallies,
    /// Start of this invocation.
    wall: Instant,
}

impl Run<'_> {
    /// Writes the checkpoint of the stepper's last completed step.
    fn checkpoint(
        &mut self,
        dir: &mut OutputDir,
        stepper: &Stepper,
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
        checkpoint::write(
            dir.path(),
            &self.fingerprint,
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
}

/// Writes one VTK frame (when the scene asks for frames).
fn write_frame(
    scene: &Scene,
    dir: &mut OutputDir,
    s: &Stepper,
    tallies: &mut Tallies,
) -> Result<(), RunError> {
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
    tallies.frames += 1;
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

/// summary.json's `multilevel_levels`: the scene's `multilevel_setup` and the Newton
/// systems (directions and re-solves) whose levels were built or kept.
#[derive(Debug, Clone, serde::Serialize)]
pub struct MultilevelLevels {
    pub setup: crate::solve::options::MultilevelSetup,
    pub built: usize,
    pub kept: usize,
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
        .min_volume_ratio(&scene.x0)
        .iter()
        .map(|m| {
            let name = m.law.name().to_string();
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

/// 4–6: the time loop, writing steps.csv row by row, the frames and the checkpoints;
/// `summary` follows the run (counts, end time, moving and contact histories) whether it
/// ends or fails.
fn simulate(
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
    let frames_dir = dir.path().join("frames");
    std::fs::create_dir_all(&frames_dir).map_err(|e| out_err(&frames_dir, e))?;
    let csv_path = dir
        .record("steps.csv")
        .map_err(|e| out_err(dir.path(), e))?;
    let resuming = summary.resumed_from_step.is_some();
    let (dim, moving, contact) = (scene.dim, stepper.has_moving(), stepper.has_contact());
    let solid = !scene.model.min_volume_ratio(&scene.x0).is_empty();
    let mut csv = if resuming {
        StepsCsv::append(&csv_path, moving, contact, solid)
    } else {
        StepsCsv::create(&csv_path, dim, moving, contact, solid)
    }
    .map_err(|e| out_err(&csv_path, e))?;

    let record = |s: &Stepper, rep: Option<&crate::sim::integrator::StepReport>| StepRecord {
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
    };
    let fold_min = |t: &mut Tallies, r: &StepRecord| {
        if let Some(d) = r.min_distance {
            t.min_distance = Some(t.min_distance.map_or(d, |m: f64| m.min(d)));
        }
    };
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
        write_frame(scene, dir, stepper, &mut run.tallies)?;
        run.tallies.k_m_history = vec![(0, stepper.k_m)];
        fill_summary(run, stepper, summary);
        // A run killed before its first periodic checkpoint resumes from step 0.
        run.checkpoint(dir, stepper, summary)?;
    }
    fill_summary(run, stepper, summary);

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

    // 4–6. Time loop: step, recover, output.
    while stepper.step < scene.steps {
        let next = stepper.step + 1;
        let mut sink = |sys: NewtonSystem| write_system(dir, &sys);
        let dump: Option<SystemSink> = opts
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
        let t = &mut run.tallies;
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
        if stepper.has_moving() {
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
        let output = stepper.phase(Phase::Output);
        csv.row(&r).map_err(|e| out_err(&csv_path, e))?;
        fold_min(t, &r);
        summary.records.push(r);
        drop(output);
        if stepper.step % scene.output.every == 0 || stepper.step == scene.steps {
            write_frame(scene, dir, stepper, &mut run.tallies)?;
        }
        let signal = INTERRUPT.load(Ordering::SeqCst);
        if stepper.step % checkpoint_every == 0 || stepper.step == scene.steps || signal != 0 {
            run.checkpoint(dir, stepper, summary)?;
        }
        let output = stepper.phase(Phase::Output);
        fill_summary(run, stepper, summary);
        summary.wall_seconds = run.tallies.wall_seconds + run.wall.elapsed().as_secs_f64();
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
    csv.finish().map_err(|e| out_err(&csv_path, e))?;
    Ok(())
}
