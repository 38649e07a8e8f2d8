//! Steps 1–4 of `stickslip run` ([`crate::sim::driver`]): the scene (a file or a built-in
//! name) read into its mesh, materials, boundary conditions and forms, with the run's
//! overrides, and checked before any output is written.

use crate::error::InputError;
use crate::sim::checkpoint::StartOptions;
use crate::sim::memory::SceneTooLarge;
use crate::sim::run_error::RunError;
use crate::sim::scene::{self, LinearKind, LoadError, Scene};
use std::path::Path;

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

/// 1–4: the scene of `start` with the run's overrides, checked.
pub(crate) fn build_scene(
    start: &StartOptions,
    steps: Option<usize>,
    end_time: Option<f64>,
) -> Result<Scene, RunError> {
    // `--size` is checked (once) by the scene parser, which names `--size`.
    let mut scene = open_scene(&start.scene, start.size).map_err(|e| match e {
        LoadError::Input(e) => RunError::Input(e),
        LoadError::Memory(m) => RunError::Memory(m),
    })?;
    if let Some(s) = start.solver {
        scene.solver.linear = s;
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
    if let Some(p) = start.preconditioner {
        scene.solver.preconditioner_choice = p;
    }
    // "auto" depends on the solver and the Newton loop, which the options may change.
    scene
        .solver
        .resolve_preconditioner(scene.dim, scene.model.n_nodes);
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
        // Name what asked for it: the command line's option or the scene's key.
        let (source, key) = match start.preconditioner {
            Some(_) => ("command line".to_string(), "--preconditioner"),
            None => (scene.file.clone(), "solver.preconditioner"),
        };
        return Err(InputError::new(
            source,
            key,
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
