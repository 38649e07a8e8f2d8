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
//!    summary.json at the start (`running`) and at the end (`complete` or `failed`).

use crate::error::InputError;
use crate::io::files::{Named, OutputDir};
use crate::sim::integrator::{ContactCounters, InitError, Stepper};
use crate::sim::output::{write_vtk, StepRecord, StepsCsv};
use crate::sim::scene::{self, LinearKind, MovingSpec, Scene};
use std::io::Write as _;
use std::path::{Path, PathBuf};
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
}

/// What a run did (summary.json holds everything but the per-step records and state).
#[derive(Debug, Clone, serde::Serialize)]
pub struct RunSummary {
    /// `running` while the run goes (written at its start), then `complete` or `failed`.
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
    pub adapter: Option<String>,
    pub characteristic_length: f64,
    /// Newton stops when ‖Δx‖∞/h is below this (m/s).
    pub newton_tolerance: f64,
    pub newton_iterations: usize,
    pub linear_iterations: usize,
    pub linear_seconds: f64,
    pub frames: usize,
    pub out_dir: String,
    pub moving_boundary: Option<MovingSummary>,
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
    let p = Path::new(name_or_path);
    // A path that exists is a file to read, never a name to look up: a folder (or a
    // device) says so instead of "no such scene".
    if let Ok(m) = std::fs::metadata(p) {
        if m.is_dir() {
            return Err(InputError::new(
                name_or_path,
                "",
                "is a folder, not a scene file (TOML)",
            ));
        }
        let text = crate::io::read_text(name_or_path)?;
        return scene::parse(crate::io::strip_bom(&text), name_or_path, size);
    }
    if p.is_file() {
        let text = crate::io::read_text(name_or_path)?;
        return scene::parse(crate::io::strip_bom(&text), name_or_path, size);
    }
    if let Some(text) = scene::builtin(name_or_path) {
        return scene::parse(text, &format!("scenes/{name_or_path}.toml"), size);
    }
    let names: Vec<&str> = scene::BUILTIN.iter().map(|(n, _)| *n).collect();
    Err(InputError::new(
        name_or_path,
        "",
        format!(
            "no such scene file or built-in scene (built-ins: {})",
            names.join(", ")
        ),
    ))
}

/// The largest entry a Newton system may hold, about √(f64::MAX): the solvers square
/// entries (dot products, Cholesky pivots), and past it those squares overflow.
pub const MAX_SYSTEM_ENTRY: f64 = 1.3e154;

/// Magnitudes that each look valid but together overflow the Newton system H = M + h²K
/// (+ h²·barrier): found here, named on the key that causes them, instead of failing a
/// step later as "not positive definite" or "overflowed".
fn check_magnitudes(scene: &Scene) -> Result<(), InputError> {
    let h = scene.time_step;
    let h2 = h * h;
    let mut k = scene.model.zero_matrix();
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
        ));
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
            ));
        }
    }
    Ok(())
}

/// What `run` writes in its output folder (what the folder's previous run of `run` wrote
/// is removed before a new run writes).
pub const OUTPUT_NAMES: [&str; 3] = ["steps.csv", "summary.json", "frames/*.vtk"];

/// Takes the output folder for this run (see [`crate::io::files::OutputDir`]); with
/// `check_only`, checks it without creating or changing anything (and returns None).
fn open_out(
    dir: &Path,
    opts: &RunOptions,
    check_only: bool,
) -> Result<Option<OutputDir>, RunError> {
    let scene_file = opts.scene.as_deref().filter(|s| Path::new(s).is_file());
    let inputs: Vec<Named> = scene_file
        .iter()
        .map(|s| Named::new("scene", Path::new(*s)))
        .collect();
    let (opt, names) = ("--out", &OUTPUT_NAMES[..]);
    if check_only {
        OutputDir::check(dir, opt, "run", names, &inputs, opts.overwrite)?;
        return Ok(None);
    }
    let d = OutputDir::open(dir, opt, "run", names, &inputs, opts.overwrite)?;
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

/// Runs a scene to the end. One call: parse, simulate, write.
///
/// The output folder is checked before the scene is read when `out` is given; it is
/// created, locked and cleared of what its previous run wrote once the scene has been
/// read and checked. summary.json is written at the start with `"status": "running"`, and at
/// the end with `"complete"`, or `"failed"` and the message.
pub fn run(opts: &RunOptions) -> Result<RunSummary, RunError> {
    let wall = Instant::now();
    // An output folder that cannot be used fails before the scene is read; it is
    // created (and taken) once the scene has passed its checks.
    if let Some(d) = &opts.out {
        open_out(d, opts, true)?;
    }
    // 1–3. Scene, boundary conditions and forms.
    // `--size` is checked (once) by the scene parser, which names `--size`.
    let size = opts.size.unwrap_or(1.0);
    let mut scene = load_scene(opts.scene.as_deref().unwrap_or("default"), size)?;
    if let Some(s) = &opts.solver {
        scene.solver.linear = s
            .parse::<LinearKind>()
            .map_err(|e| InputError::new("--solver", "", e))?;
    }
    if let Some(o) = opts.ordering {
        scene.solver.ordering = o;
    }
    if let Some(n) = opts.newton {
        scene.solver.newton = n;
    }
    if let Some(n) = opts.steps {
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
    if scene.solver.linear == LinearKind::Gpu {
        if let Some(problem) = crate::gpu::adapter_name_mismatch(&crate::gpu::GpuOptions::default())
        {
            return Err(InputError::new("WGPU_ADAPTER_NAME", "", problem).into());
        }
    }
    let out = opts
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("out").join(&scene.name));
    let Some(mut dir) = open_out(&out, opts, false)? else {
        unreachable!("open_out returns the folder unless check_only")
    };

    let stepper = Stepper::new(&scene).map_err(|e| match e {
        InitError::Input { entry, problem } => {
            RunError::Input(InputError::new(scene.file.clone(), entry, problem))
        }
        InitError::Solver(cause) => RunError::Solve {
            step: 0,
            time: 0.0,
            cause,
        },
    });
    // From here on the folder is this run's: the previous run's files go, and
    // summary.json always says how far this run got.
    dir.clean().map_err(|e| RunError::Output {
        path: out.display().to_string(),
        cause: format!("cannot clear the previous run's files: {e}"),
    })?;
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
        adapter: None,
        characteristic_length: scene.characteristic_length,
        newton_tolerance: 0.0,
        newton_iterations: 0,
        linear_iterations: 0,
        linear_seconds: 0.0,
        frames: 0,
        out_dir: out.display().to_string(),
        moving_boundary: None,
        contact_counters: ContactCounters::default(),
        contact: None,
        gpu: None,
        records: Vec::new(),
        final_positions: Vec::new(),
        final_velocities: Vec::new(),
    };
    let result = match stepper {
        Ok(mut stepper) => {
            summary.adapter = stepper.adapter().map(str::to_string);
            summary.newton_tolerance = stepper.newton_tol;
            summary.end_time = stepper.t;
            let r = write_summary(&mut dir, &summary)
                .and_then(|_| simulate(&scene, opts, &mut stepper, &mut dir, &mut summary));
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
    summary.wall_seconds = wall.elapsed().as_secs_f64();
    match result {
        Ok(()) => {
            summary.status = RunStatus::Complete;
            write_summary(&mut dir, &summary)?;
            Ok(summary)
        }
        Err(e) => {
            summary.status = RunStatus::Failed;
            summary.message = Some(e.to_string());
            // The run's own error is the one to report; a failure to record it is not.
            let _ = write_summary(&mut dir, &summary);
            Err(e)
        }
    }
}

/// Writes one VTK frame (when the scene asks for frames).
fn write_frame(
    scene: &Scene,
    dir: &mut OutputDir,
    s: &Stepper,
    summary: &mut RunSummary,
) -> Result<(), RunError> {
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
    summary.frames += 1;
    Ok(())
}

/// 4–6: the time loop, writing steps.csv row by row and the frames; `summary` follows
/// the run (counts, end time, moving and contact histories) whether it ends or fails.
fn simulate(
    scene: &Scene,
    opts: &RunOptions,
    stepper: &mut Stepper,
    dir: &mut OutputDir,
    summary: &mut RunSummary,
) -> Result<(), RunError> {
    let out_err = |path: &Path, e: std::io::Error| RunError::Output {
        path: path.display().to_string(),
        cause: e.to_string(),
    };
    let frames_dir = dir.path().join("frames");
    std::fs::create_dir_all(&frames_dir).map_err(|e| out_err(&frames_dir, e))?;
    let csv_path = dir
        .record("steps.csv")
        .map_err(|e| out_err(dir.path(), e))?;
    let mut csv = StepsCsv::create(
        &csv_path,
        scene.dim,
        stepper.has_moving(),
        stepper.has_contact(),
    )
    .map_err(|e| out_err(&csv_path, e))?;

    let record = |s: &Stepper, rep: Option<&crate::sim::integrator::StepReport>| StepRecord {
        step: s.step,
        time: s.t,
        newton_iterations: rep.map_or(0, |r| r.newton_iterations),
        linear_iterations: rep.map_or(0, |r| r.linear_iterations),
        linear_seconds: rep.map_or(0.0, |r| r.linear_seconds),
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
    };

    let first = record(stepper, None);
    if let Some(what) = non_finite(stepper, &first) {
        // Finite entries whose products overflow (sizes near 1e300, ...): the scene's fault.
        return Err(InputError::new(
            scene.file.clone(),
            "scene",
            format!(
                "the initial state is not finite: {what}; the scene's magnitudes (mesh size, \
                 density, offsets, time step) overflow f64"
            ),
        )
        .into());
    }
    csv.row(&first).map_err(|e| out_err(&csv_path, e))?;
    summary.records.push(first);
    write_frame(scene, dir, stepper, summary)?;

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
        b
    };

    summary.moving_boundary = stepper.has_moving().then(|| MovingSummary {
        settings: scene.moving.clone(),
        moving_nodes: scene.bcs.iter().filter(|b| b.motion.is_some()).count(),
        k_m_start: stepper.k_m,
        k_m_final: stepper.k_m,
        k_m_doublings: 0,
        k_m_history: vec![(0, stepper.k_m)],
        eliminated_at_iteration: Vec::new(),
        first_step_eliminated_at_start: None,
        all_eliminated_every_step: true,
    });
    let mut ccd_limited = 0usize;
    let contact = |stepper: &Stepper, records: &[StepRecord], ccd: usize| {
        stepper.has_contact().then(|| ContactSummary {
            obstacles: scene.obstacles.len(),
            dhat: scene.obstacles.iter().map(|o| o.plane.dhat).collect(),
            kappa: scene.obstacles.iter().map(|o| o.plane.kappa).collect(),
            min_distance: records
                .iter()
                .filter_map(|r| r.min_distance)
                .fold(f64::INFINITY, f64::min),
            ccd_limited_line_searches: ccd,
            final_contact_force: stepper.total_contact().unwrap_or_default(),
        })
    };
    summary.contact = contact(stepper, &summary.records, 0);

    // 4–6. Time loop: step, recover, output.
    for _ in 0..scene.steps {
        let rep = stepper.step().map_err(|cause| RunError::Solve {
            step: stepper.step + 1,
            time: stepper.t + scene.time_step,
            cause: cause.to_string(),
        })?;
        summary.newton_iterations += rep.newton_iterations;
        summary.linear_iterations += rep.linear_iterations;
        summary.linear_seconds += rep.linear_seconds;
        ccd_limited += rep.ccd_limited;
        if let Some(m) = summary.moving_boundary.as_mut() {
            m.k_m_doublings += rep.k_m_doublings;
            if rep.k_m != m.k_m_final {
                m.k_m_history.push((rep.step, rep.k_m));
            }
            m.k_m_final = rep.k_m;
            match rep.eliminated_at_iteration {
                Some(k) => {
                    m.eliminated_at_iteration.push(k);
                    if k == 0 && m.first_step_eliminated_at_start.is_none() {
                        m.first_step_eliminated_at_start = Some(rep.step);
                    }
                }
                None => m.all_eliminated_every_step = false,
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
        csv.row(&r).map_err(|e| out_err(&csv_path, e))?;
        summary.records.push(r);
        summary.steps_completed = stepper.step;
        summary.end_time = stepper.t;
        summary.contact = contact(stepper, &summary.records, ccd_limited);
        if stepper.step % scene.output.every == 0 || stepper.step == scene.steps {
            write_frame(scene, dir, stepper, summary)?;
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
