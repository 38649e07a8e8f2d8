//! `stickslip run`: simulates a scene and writes VTK frames, steps.csv and summary.json.
//!
//! The driver reads as numbered steps, like MFEM's examples:
//! 1. scene (file or built-in name) → mesh, materials, masses;
//! 2. boundary conditions (regions → per-node sticky / plane / line, moving or not);
//! 3. forms: inertia, gravity, elasticity, penalties ([`crate::energy`]);
//! 4. time loop: each step projects, then runs Newton with the eliminated solve
//!    ([`crate::integrator`]);
//! 5. recover: velocities, reaction forces, momentum, center of mass, energy;
//! 6. output: frames every k steps, one steps.csv row per step, summary.json at the end.

use crate::error::InputError;
use crate::integrator::{ContactCounters, InitError, Stepper};
use crate::output::{write_vtk, StepRecord, StepsCsv};
use crate::scene::{self, LinearKind, MovingSpec, Scene};
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

/// What a run did (summary.json holds everything but the per-step records and state).
#[derive(Debug, Clone, serde::Serialize)]
pub struct RunSummary {
    pub scene: String,
    pub file: String,
    pub dimension: usize,
    pub nodes: usize,
    pub elements: usize,
    pub total_mass: f64,
    pub time_step: f64,
    pub gravity: Vec<f64>,
    pub steps: usize,
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

/// Runs a scene to the end. One call: parse, simulate, write.
pub fn run(opts: &RunOptions) -> Result<RunSummary, RunError> {
    let wall = Instant::now();
    // 1–3. Scene, boundary conditions and forms.
    // `--size` is checked (once) by the scene parser, which names `--size`.
    let size = opts.size.unwrap_or(1.0);
    let mut scene = load_scene(opts.scene.as_deref().unwrap_or("default"), size)?;
    if let Some(s) = &opts.solver {
        scene.solver.linear = s
            .parse::<LinearKind>()
            .map_err(|e| InputError::new("--solver", "", e))?;
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
    let out = opts
        .out
        .clone()
        .unwrap_or_else(|| PathBuf::from("out").join(&scene.name));
    let out_err = |path: &Path, e: std::io::Error| RunError::Output {
        path: path.display().to_string(),
        cause: e.to_string(),
    };
    let frames_dir = out.join("frames");
    std::fs::create_dir_all(&frames_dir).map_err(|e| out_err(&frames_dir, e))?;

    let mut stepper = Stepper::new(&scene).map_err(|e| match e {
        InitError::Input { entry, problem } => {
            RunError::Input(InputError::new(scene.file.clone(), entry, problem))
        }
        InitError::Solver(cause) => RunError::Solve {
            step: 0,
            time: 0.0,
            cause,
        },
    })?;
    let csv_path = out.join("steps.csv");
    let mut csv = StepsCsv::create(
        &csv_path,
        scene.dim,
        stepper.has_moving(),
        stepper.has_contact(),
    )
    .map_err(|e| out_err(&csv_path, e))?;

    let record = |s: &Stepper, rep: Option<&crate::integrator::StepReport>| StepRecord {
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
    let mut frames = 0usize;
    let mut write_frame = |s: &Stepper| -> Result<(), RunError> {
        if !scene.output.vtk {
            return Ok(());
        }
        let path = frames_dir.join(format!("{}_{:05}.vtk", scene.name, s.step));
        let title = format!("stickslip {} step {} t = {}", scene.name, s.step, s.t);
        let c = s.has_contact().then_some(&s.contact_forces[..]);
        write_vtk(&path, &scene, &title, &s.x, &s.v, &s.reactions, c)
            .map_err(|e| out_err(&path, e))?;
        frames += 1;
        Ok(())
    };

    let first = record(&stepper, None);
    if let Some(what) = non_finite(&stepper, &first) {
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
    let mut records = vec![first];
    csv.row(&records[0]).map_err(|e| out_err(&csv_path, e))?;
    write_frame(&stepper)?;

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

    // 4–6. Time loop: step, recover, output.
    let mut moving = stepper.has_moving().then(|| MovingSummary {
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
    let (mut newton, mut linear, mut linear_s) = (0usize, 0usize, 0.0f64);
    let mut ccd_limited = 0usize;
    for _ in 0..scene.steps {
        let rep = stepper.step().map_err(|cause| RunError::Solve {
            step: stepper.step + 1,
            time: stepper.t + scene.time_step,
            cause,
        })?;
        newton += rep.newton_iterations;
        linear += rep.linear_iterations;
        linear_s += rep.linear_seconds;
        ccd_limited += rep.ccd_limited;
        if let Some(m) = moving.as_mut() {
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
        let r = record(&stepper, Some(&rep));
        if let Some(what) = non_finite(&stepper, &r) {
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
        records.push(r);
        if stepper.step % scene.output.every == 0 || stepper.step == scene.steps {
            write_frame(&stepper)?;
        }
        bar.set_message(format!(
            "newton {} linear {}",
            rep.newton_iterations, rep.linear_iterations
        ));
        bar.inc(1);
    }
    bar.finish_and_clear();
    csv.finish().map_err(|e| out_err(&csv_path, e))?;

    let contact = stepper.has_contact().then(|| ContactSummary {
        obstacles: scene.obstacles.len(),
        dhat: scene.obstacles.iter().map(|o| o.plane.dhat).collect(),
        kappa: scene.obstacles.iter().map(|o| o.plane.kappa).collect(),
        min_distance: records
            .iter()
            .filter_map(|r| r.min_distance)
            .fold(f64::INFINITY, f64::min),
        ccd_limited_line_searches: ccd_limited,
        final_contact_force: stepper.total_contact().unwrap_or_default(),
    });
    let summary = RunSummary {
        scene: scene.name.clone(),
        file: scene.file.clone(),
        dimension: scene.dim,
        nodes: scene.model.n_nodes,
        elements: scene.cells.iter().map(|b| b.cells.len()).sum(),
        total_mass: scene.model.total_mass(),
        time_step: scene.time_step,
        gravity: scene.gravity.clone(),
        steps: scene.steps,
        end_time: stepper.t,
        wall_seconds: wall.elapsed().as_secs_f64(),
        solver: scene.solver.linear.to_string(),
        adapter: stepper.linear.adapter.clone(),
        characteristic_length: scene.characteristic_length,
        newton_tolerance: stepper.newton_tol,
        newton_iterations: newton,
        linear_iterations: linear,
        linear_seconds: linear_s,
        frames,
        out_dir: out.display().to_string(),
        moving_boundary: moving,
        contact_counters: stepper.contact_counters(),
        contact,
        records,
        final_positions: stepper.x.clone(),
        final_velocities: stepper.v.clone(),
    };
    let json_path = out.join("summary.json");
    let json = serde_json::to_string_pretty(&summary).map_err(|e| RunError::Output {
        path: json_path.display().to_string(),
        cause: e.to_string(),
    })?;
    std::fs::write(&json_path, json).map_err(|e| out_err(&json_path, e))?;
    Ok(summary)
}
