//! The command line (docs/cli.md): `solve`, `generate`, `info`, `run`, `bench`,
//! `export` and `recover`. `main.rs` only calls [`main`].
//!
//! Exit codes: 0 success; 1 a solve failed (H not positive definite on the free
//! subspace, CG did not converge, GPU failure) or a subcommand is not available; 2 bad
//! input or usage. Every error is exactly one line on stderr.

use crate::app::report::{CgReport, CholeskyReport, Files, Report, Seconds};
use crate::cases::generate::{random_system, ConstraintMix, Stencil, SystemSpec};
use crate::core::constraints::{node_rows, Constraint, Frames};
use crate::core::elimination::{ConstrainedDiagonal, Eliminated};
use crate::error::{Error, InputError, SolveError};
use crate::io::files::{self, Named, OutputDir};
use crate::io::{bcjson, mtx};
use crate::solve::cg::Preconditioner;
use crate::solve::coarse::CoarseSpace;
use crate::{CholeskyOrdering, Precision, Problem, SolveDetails, Solver, SolverConfig, SolverKind};
use clap::{ArgGroup, Args, Parser, Subcommand, ValueEnum};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

#[derive(Debug, Parser)]
#[command(
    name = "stickslip",
    version,
    about = "Newton systems of implicit simulation with Dirichlet boundary conditions eliminated (CPU Cholesky/CG, GPU CG)"
)]
pub struct Cli {
    /// Print nothing on stderr except errors.
    #[arg(long, short, global = true)]
    pub quiet: bool,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Solve one constrained Newton system read from Matrix Market and JSON files.
    Solve(SolveArgs),
    /// Write a seeded random system (H.mtx, g.mtx, bc.json) for tests and benchmarks.
    Generate(GenerateArgs),
    /// List the GPU adapters.
    Info,
    /// Simulate a scene (the built-in default scene when none is given).
    Run(RunArgs),
    /// CPU-versus-GPU benchmark: speed against error over a ladder of sizes.
    Bench(BenchArgs),
    /// Write the eliminated system (Ĥ, b̂ in node frames) for PETSc and Matrix Market readers.
    Export(ExportArgs),
    /// Turn a solution y of an exported system into Δx and the reaction forces.
    Recover(RecoverArgs),
}

#[derive(Debug, Clone, Args)]
pub struct BenchArgs {
    /// CI-sized ladder (1,000–8,000 nodes) and a two-tolerance sweep.
    #[arg(long)]
    pub quick: bool,
    /// Node counts to run (comma-separated) instead of the default ladder; each 4 to
    /// 20,000,000.
    #[arg(long, value_delimiter = ',', value_parser = generated_nodes)]
    pub sizes: Option<Vec<usize>>,
    /// Dimensions to run (comma-separated).
    #[arg(long, value_delimiter = ',', default_values_t = [2usize, 3])]
    pub dims: Vec<usize>,
    /// CPU solvers only.
    #[arg(long)]
    pub no_gpu: bool,
    /// Largest node count for the Cholesky oracle; above it the reference is CPU CG at 1e-12.
    #[arg(long, default_value_t = 300_000)]
    pub oracle_max_nodes: usize,
    /// Write bench.json, bench.csv and SVG plots here.
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Run the hard-case stability suite instead (src/app/hard.rs): writes hard.md/hard.json.
    #[arg(long)]
    pub hard: bool,
    /// With --hard: grid scale of the larger cases timing GPU f64 against mixed (1 to 20;
    /// (6·scale)³ nodes; the two cantilever cases also run at twice the scale with the
    /// first coarse space, where they reach the others' size).
    #[arg(long, default_value_t = 3, value_parser = hard_scale)]
    pub hard_scale: usize,
    /// Coarse correction of every CG, CPU and GPU: aggregates, translations or none
    /// [default: aggregates; with --hard and no --coarse the f64-vs-mixed timing runs
    /// aggregates and translations].
    #[arg(long)]
    pub coarse: Option<CoarseSpace>,
    /// Fill-reducing ordering of the Cholesky oracle (see `solve --ordering`).
    #[arg(long, value_enum, default_value_t = CholeskyOrdering::Auto)]
    pub ordering: CholeskyOrdering,
    /// Worker threads of the CPU solvers, 1 to 1024 [default: RAYON_NUM_THREADS, else
    /// every core]. CPU CG gives the same bits on any count.
    #[arg(long, value_parser = thread_count)]
    pub threads: Option<usize>,
    /// Time one Newton iteration of a 3D neo-Hookean box, phase by phase (assembly,
    /// elimination and preconditioner, CG to 1e-8, line search), CPU against GPU f64, over
    /// a ladder of 2,673 to 1,036,288 nodes (--quick: 425 and 2,673; --sizes: the nearest
    /// grids to those node counts).
    #[arg(long, conflicts_with_all = ["hard", "dims", "oracle_max_nodes", "coarse", "ordering", "seed"])]
    pub newton: bool,
    /// With --newton: timed repetitions of every phase after one warm-up (the median is
    /// reported), at least 1 [default: 5; with --quick 2].
    #[arg(long, requires = "newton", value_parser = positive_usize)]
    pub reps: Option<usize>,
    /// Time every solver and preconditioner (Cholesky; CPU CG with Jacobi and block
    /// Jacobi, each with no coarse space, translations and aggregates; multilevel; the GPU
    /// CG in f64 with Jacobi and aggregates and with multilevel unless --no-gpu) to
    /// relative residual 1e-6 on the Newton systems captured under
    /// DIR (`run --dump-systems`: every folder with H.mtx, g.mtx and bc.json).
    #[arg(long, value_name = "DIR", conflicts_with_all = ["newton", "hard", "quick", "sizes", "dims", "oracle_max_nodes", "coarse", "ordering", "seed"])]
    pub systems: Option<PathBuf>,
}

#[derive(Debug, Clone, Args)]
pub struct ExportArgs {
    #[command(flatten)]
    pub system: SystemArgs,
    /// The diagonal D on constrained components of Ĥ.
    #[arg(long, value_enum, default_value_t = ConstrainedDiagonal::Identity)]
    pub constrained_diagonal: ConstrainedDiagonal,
    /// Skip the Matrix Market copies (hhat.mtx, bhat.mtx); PETSc binary only.
    #[arg(long)]
    pub no_mtx: bool,
    /// Output folder: hhat.petsc(+.info), bhat.petsc, hhat.mtx, bhat.mtx, layout.json.
    #[arg(long, value_name = "DIR")]
    pub out_dir: PathBuf,
    /// Replace files with export's output names that no previous export there wrote.
    #[arg(long)]
    pub overwrite: bool,
}

#[derive(Debug, Clone, Args)]
pub struct RecoverArgs {
    /// layout.json written by `stickslip export`.
    #[arg(long, value_name = "layout.json")]
    pub layout: String,
    /// The solution y: a PETSc binary Vec (.petsc) or Matrix Market array (.mtx).
    #[arg(long, value_name = "y.petsc")]
    pub solution: String,
    /// The H the system was exported from (for the reactions, and checked against the layout).
    #[arg(long, value_name = "H.mtx")]
    pub hessian: String,
    /// The g the system was exported from.
    #[arg(long, value_name = "g.mtx")]
    pub gradient: String,
    /// Δx: Matrix Market array dn × 1.
    #[arg(long, value_name = "dx.mtx")]
    pub out: String,
    /// Reactions f = −(HΔx + g): Matrix Market array dn × 1.
    #[arg(long, value_name = "f.mtx")]
    pub reactions: Option<String>,
    /// Refuse (exit 1, nothing written) a y whose relative residual ‖b̂ − Ĥy‖/‖b̂‖ in the
    /// exported system exceeds this.
    #[arg(long, default_value = "1e-6", value_parser = relative_tol)]
    pub max_residual: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum StencilArg {
    /// 2D: 8 neighbours; 3D: 14 (tetrahedral-mesh-like).
    Mesh,
    /// 2D: 4 neighbours; 3D: 6.
    Face,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum MixArg {
    /// x = 0 face sticky, x = max face moved, y = 0 face on a tilted plane, a few lines.
    Realistic,
    /// Every kind mixed at random, with combinations and redundant rows.
    Random,
    /// No constraints.
    None,
}

fn positive_f64(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        Ok(_) => Err("must be a positive finite number".into()),
        Err(e) => Err(e.to_string()),
    }
}

/// A relative tolerance: in (0, 1). At 1 or above, y = 0 already meets it.
fn relative_tol(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 && v < 1.0 => Ok(v),
        Ok(_) => Err("must be a relative tolerance in (0, 1)".into()),
        Err(e) => Err(e.to_string()),
    }
}

/// An iteration limit: at least 1.
fn positive_usize(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(0) => Err("must be at least 1".into()),
        Ok(v) => Ok(v),
        Err(e) => Err(e.to_string()),
    }
}

/// Most worker threads `--threads` takes: far past any machine's cores, short of the
/// thousands of threads that only cost start-up time (and memory for their stacks).
pub const MAX_THREADS: usize = 1024;

fn thread_count(s: &str) -> Result<usize, String> {
    let n = positive_usize(s)?;
    if n > MAX_THREADS {
        return Err(format!(
            "{n} is more than the limit of {MAX_THREADS} threads (this machine has {} cores)",
            std::thread::available_parallelism().map_or(1, |c| c.get())
        ));
    }
    Ok(n)
}

/// Largest generated system (`generate --nodes`, `bench --sizes`): about 2 KiB per node
/// for a 3D mesh-stencil H (27 blocks of 9 f64) and its copies, so 20M nodes is ~40 GiB of
/// Hessian before any solver state.
pub const MAX_GENERATED_NODES: usize = 20_000_000;

/// Largest `bench --hard-scale`: the timed cases have (6·scale)³ nodes, 1.7M at 20.
pub const MAX_HARD_SCALE: usize = 20;

fn generated_nodes(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(v) if v > MAX_GENERATED_NODES => Err(format!(
            "{v} is more than the cap of {MAX_GENERATED_NODES} nodes"
        )),
        Ok(v) => Ok(v),
        Err(e) => Err(e.to_string()),
    }
}

fn hard_scale(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(v) if (1..=MAX_HARD_SCALE).contains(&v) => Ok(v),
        Ok(_) => Err(format!("must be in 1..={MAX_HARD_SCALE}")),
        Err(e) => Err(e.to_string()),
    }
}

#[derive(Debug, Clone, Args)]
#[command(group(ArgGroup::new("constraint_input").required(true).args(["constraints", "constraint_matrix"])))]
pub struct SystemArgs {
    /// H: Matrix Market coordinate real (symmetric or general), dn × dn, node-major.
    #[arg(long, value_name = "H.mtx")]
    pub hessian: String,
    /// g: Matrix Market array (or coordinate) real, dn × 1.
    #[arg(long, value_name = "g.mtx")]
    pub gradient: String,
    /// Per-node constraints as JSON (docs/formats.md, "Constraint JSON").
    #[arg(long, value_name = "bc.json")]
    pub constraints: Option<String>,
    /// Global constraints B Δx = p: Matrix Market coordinate, m × dn, each row on one node.
    #[arg(long, value_name = "B.mtx", requires = "dim")]
    pub constraint_matrix: Option<String>,
    /// p for --constraint-matrix: Matrix Market array, m × 1 (zero when absent).
    #[arg(long, value_name = "p.mtx", requires = "constraint_matrix")]
    pub constraint_values: Option<String>,
    /// Spatial dimension (default: bc.json's "dim"; required with --constraint-matrix).
    #[arg(long, value_parser = clap::value_parser!(u8).range(2..=3))]
    pub dim: Option<u8>,
}

#[derive(Debug, Clone, Args)]
pub struct SolveArgs {
    #[command(flatten)]
    pub system: SystemArgs,
    #[arg(long, value_enum, default_value_t = SolverKind::Cholesky)]
    pub solver: SolverKind,
    /// Arithmetic (f32 and mixed need --solver gpu) [default: f64].
    #[arg(long, value_enum)]
    pub precision: Option<Precision>,
    /// Iterative solvers: stop at ‖b̂ − Ĥy‖/‖b̂‖ ≤ tol (the true residual).
    #[arg(long, default_value = "1e-8", value_parser = relative_tol)]
    pub tol: f64,
    /// Iterative solvers: iteration limit, at least 1 [default: 10000].
    #[arg(long, value_parser = positive_usize)]
    pub max_iters: Option<usize>,
    /// --precision mixed: after --tol is met, refine with double-double residuals until the
    /// estimated relative error ‖y − y*‖/‖y*‖ is ≤ this. A small residual bounds the error
    /// only by κ·tol; this targets the error directly.
    #[arg(long, value_parser = relative_tol)]
    pub error_tol: Option<f64>,
    /// Iterative solvers: none, jacobi, block-jacobi or multilevel (the CPU CG and the GPU
    /// in f64; it replaces --coarse).
    #[arg(long, default_value = "jacobi")]
    pub preconditioner: Preconditioner,
    /// Iterative solvers: coarse correction added to the preconditioner: aggregates (the
    /// translations of each aggregate of about 64 nodes, at most 128 aggregates: a body's
    /// smooth modes), translations (the d rigid translations only) or none; see
    /// docs/coarse.md.
    #[arg(long, default_value = "aggregates")]
    pub coarse: CoarseSpace,
    /// The diagonal D on constrained components of Ĥ.
    #[arg(long, value_enum, default_value_t = ConstrainedDiagonal::Identity)]
    pub constrained_diagonal: ConstrainedDiagonal,
    /// Cholesky: fill-reducing ordering. auto: AMD below 2,000 nodes; from there AMD and
    /// nested dissection both, keeping the one whose factor needs fewer flops.
    #[arg(long, value_enum, default_value_t = CholeskyOrdering::Auto)]
    pub ordering: CholeskyOrdering,
    /// Δx: Matrix Market array dn × 1, 17 significant digits.
    #[arg(long, value_name = "dx.mtx")]
    pub out: String,
    /// Reactions f = −(HΔx + g): Matrix Market array dn × 1.
    #[arg(long, value_name = "f.mtx")]
    pub reactions: Option<String>,
    /// Timings, sizes and solver details as JSON.
    #[arg(long, value_name = "report.json")]
    pub report: Option<String>,
    /// Worker threads of the CPU solvers, 1 to 1024 [default: RAYON_NUM_THREADS, else
    /// every core]. CPU CG gives the same bits on any count.
    #[arg(long, value_parser = thread_count)]
    pub threads: Option<usize>,
}

#[derive(Debug, Clone, Args)]
pub struct GenerateArgs {
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u8).range(2..=3))]
    pub dim: u8,
    /// About this many nodes (a square or cubic grid); at most 20,000,000.
    #[arg(long, default_value_t = 1000, value_parser = generated_nodes)]
    pub nodes: usize,
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    #[arg(long, value_enum, default_value_t = StencilArg::Mesh)]
    pub stencil: StencilArg,
    #[arg(long, value_enum, default_value_t = MixArg::Realistic)]
    pub mix: MixArg,
    /// Also write the constraints as B.mtx and p.mtx.
    #[arg(long)]
    pub matrix_form: bool,
    #[arg(long, value_name = "DIR")]
    pub out_dir: PathBuf,
    /// Replace files with generate's output names that no previous generate there wrote.
    #[arg(long)]
    pub overwrite: bool,
}

#[derive(Debug, Clone, Args)]
pub struct RunArgs {
    /// A scene file (TOML) or a built-in scene name (default, hanging, incline, bead,
    /// twist, compress, slip-line, drop, squash, crush); the built-in `default` when absent.
    pub scene: Option<String>,
    /// Output folder for frames (VTK), steps.csv and summary.json [default: out/SCENE].
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Override the scene's linear solver.
    #[arg(long, value_enum)]
    pub solver: Option<SolverKind>,
    /// Mesh resolution multiplier (scales every generated mesh's cell count per axis).
    #[arg(long, value_parser = positive_f64)]
    pub size: Option<f64>,
    /// Override the number of time steps.
    #[arg(long)]
    pub steps: Option<usize>,
    /// Override the scene's Cholesky ordering (auto, amd or nested-dissection).
    #[arg(long, value_enum)]
    pub ordering: Option<CholeskyOrdering>,
    /// Where the Newton loop runs: cpu, or gpu (the whole step on the device in f64)
    /// [default: the scene's `[solver] newton`, else cpu].
    #[arg(long, value_enum)]
    pub newton: Option<crate::sim::scene::NewtonLoop>,
    /// The CG tolerance of the Newton systems: adaptive (inexact Newton) or a relative
    /// residual in (0, 1) for every system [default: the scene's `[solver] cg_tolerance`,
    /// else adaptive].
    #[arg(long, value_name = "adaptive|TOL", value_parser = str::parse::<crate::sim::scene::CgTolerance>)]
    pub cg_tolerance: Option<crate::sim::scene::CgTolerance>,
    /// Write every Newton system of these steps (all, or step numbers from 1: 1,10) under
    /// DIR/systems/step_S/iter_K/: H.mtx, g.mtx, bc.json (the input of `solve` and
    /// `export`), x.mtx (the iterate), dx.mtx (the direction the run used), system.json.
    #[arg(long, value_name = "STEPS", value_parser = str::parse::<crate::sim::integrator::StepSelection>)]
    pub dump_systems: Option<crate::sim::integrator::StepSelection>,
    /// Replace files with run's output names that no previous run there wrote.
    #[arg(long)]
    pub overwrite: bool,
    /// Worker threads of the CPU solvers, 1 to 1024 [default: RAYON_NUM_THREADS, else
    /// every core]. CPU CG gives the same bits on any count.
    #[arg(long, value_parser = thread_count)]
    pub threads: Option<usize>,
    /// Override the number of steps by an end time T (s): round(T / time_step) steps.
    #[arg(long, value_name = "T", conflicts_with = "steps")]
    pub end_time: Option<f64>,
    /// Continue the run in DIR from its last checkpoint (checkpoint.bin): steps.csv rows
    /// and frames after it are removed, then the run goes on, appending, with the same
    /// bits as a run that was never stopped. The scene and its options come from the
    /// checkpoint; only --steps or --end-time (to go further) may be given.
    #[arg(long, value_name = "DIR")]
    pub resume: Option<PathBuf>,
}

/// Why a command failed; decides the exit code.
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    /// Bad input data or options: exit 2.
    #[error("{0}")]
    Input(#[from] InputError),
    /// The system could not be solved as posed: exit 1.
    #[error("{0}")]
    Solve(#[from] SolveError),
    /// Anything else (unwritable output, a feature not in this build): exit 1.
    #[error("{0}")]
    Failed(String),
    /// A run stopped by SIGINT or SIGTERM after a completed step: exit 128 + the signal.
    #[error("{message}")]
    Interrupted { message: String, code: u8 },
}

impl CliError {
    pub fn exit_code(&self) -> u8 {
        match self {
            CliError::Input(_) => 2,
            CliError::Interrupted { code, .. } => *code,
            _ => 1,
        }
    }
}

fn write_failed(path: &str, e: std::io::Error) -> CliError {
    CliError::Failed(format!("cannot write {path}: {e}"))
}

/// Entry point of the binary.
pub fn main() -> ExitCode {
    // A panic is a bug, but the one-line contract holds for it too: no backtrace hint.
    std::panic::set_hook(Box::new(|info| {
        // A panic inside a third-party parser that the reader turns into an input error.
        if crate::io::panic_is_contained() {
            return;
        }
        let msg = info
            .payload()
            .downcast_ref::<&str>()
            .map(|s| s.to_string())
            .or_else(|| info.payload().downcast_ref::<String>().cloned())
            .unwrap_or_default();
        let at = info
            .location()
            .map(|l| format!(" at {}:{}", l.file(), l.line()))
            .unwrap_or_default();
        eprintln!("error: internal error{at}: {}", msg.replace('\n', " "));
    }));
    let cli = match Cli::try_parse() {
        Ok(c) => c,
        Err(e) => {
            use clap::error::ErrorKind;
            match e.kind() {
                // Help and version are not errors: clap prints them as usual.
                ErrorKind::DisplayHelp
                | ErrorKind::DisplayVersion
                | ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => e.exit(),
                _ => {
                    // One line, like every other error: clap's first paragraph (which
                    // lists the missing arguments, if any), without tips and usage.
                    let text = e.to_string();
                    let first: Vec<&str> = text
                        .lines()
                        .take_while(|l| !l.trim().is_empty())
                        .map(str::trim)
                        .collect();
                    let first = first.join(" ");
                    let first = first.strip_prefix("error: ").unwrap_or(&first);
                    let first = if first.is_empty() {
                        "invalid usage"
                    } else {
                        first
                    };
                    eprintln!("error: command line: {first} (see --help)");
                    return ExitCode::from(2);
                }
            }
        }
    };
    match run(&cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            let line = e.to_string().replace('\n', " ");
            eprintln!("error: {}", crate::io::cut_tokens(&line));
            ExitCode::from(e.exit_code())
        }
    }
}

/// Runs a parsed command line (on a pool of `--threads` workers where given).
pub fn run(cli: &Cli) -> Result<(), CliError> {
    let threads = match &cli.command {
        Command::Solve(a) => a.threads,
        Command::Run(a) => a.threads,
        Command::Bench(a) => a.threads,
        _ => None,
    };
    match threads {
        None => dispatch(cli),
        Some(t) => {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build()
                .map_err(|e| CliError::Failed(format!("--threads {t}: {e}")))?;
            // faer (the Cholesky) takes its thread count from its own global setting.
            faer::set_global_parallelism(faer::Par::rayon(t));
            pool.install(|| dispatch(cli))
        }
    }
}

fn dispatch(cli: &Cli) -> Result<(), CliError> {
    match &cli.command {
        Command::Solve(a) => {
            let r = solve(a)?;
            if !cli.quiet {
                eprintln!("{}", r.summary());
            }
            Ok(())
        }
        Command::Generate(a) => generate(a, cli.quiet),
        Command::Info => info(),
        Command::Run(a) => run_scene(a, cli.quiet),
        Command::Bench(a) => bench(a, cli.quiet),
        Command::Export(a) => export(a, cli.quiet),
        Command::Recover(a) => recover(a, cli.quiet),
    }
}

/// `stickslip info`: the GPU adapters wgpu can see (`WGPU_BACKEND` narrows them).
fn info() -> Result<(), CliError> {
    println!("stickslip {}", env!("CARGO_PKG_VERSION"));
    let adapters = crate::gpu::list_adapters();
    if adapters.is_empty() {
        return Err(CliError::Failed(crate::gpu::no_adapter_message(
            &crate::gpu::GpuOptions::default(),
        )));
    }
    for (k, a) in adapters.iter().enumerate() {
        println!(
            "adapter {k}: {} ({}, {}; driver {} {}); shader_f64 {}, shader_int64 {}, subgroup {} ({}..{}), timestamp_query {}, max storage binding {} MiB (larger per-block arrays are bound in pieces), max buffer {} MiB, device memory {}",
            a.name,
            a.backend,
            a.device_type,
            a.driver,
            a.driver_info,
            a.shader_f64,
            a.shader_int64,
            a.subgroup,
            a.subgroup_min_size,
            a.subgroup_max_size,
            a.timestamp_query,
            a.max_storage_buffer_binding_size >> 20,
            a.max_buffer_size >> 20,
            a.device_memory
                .map_or("not reported".to_string(), |m| format!("{} MiB", m >> 20))
        );
    }
    Ok(())
}

/// H, g, the constraints and their frames, read and checked.
pub struct LoadedSystem {
    pub dim: usize,
    pub h: crate::core::sparse::BlockCsr,
    pub g: Vec<f64>,
    pub constraints: Vec<Constraint>,
    pub frames: Frames,
    pub read_seconds: f64,
    pub frames_seconds: f64,
}

/// Steps 1–2 shared by `solve` and `export`: read H, g and the constraints (JSON or B/p)
/// with one-line errors, then build the per-node frames.
pub fn read_system(sys: &SystemArgs) -> Result<LoadedSystem, CliError> {
    let t_start = Instant::now();
    // 1. Read. bc.json first: it may fix the dimension that H's blocks need.
    let cli_dim = sys.dim.map(usize::from);
    let bc = match &sys.constraints {
        Some(path) => Some(bcjson::read(path, cli_dim)?),
        None => None,
    };
    let dim = match (cli_dim, bc.as_ref().and_then(|b| b.dim)) {
        (Some(d), _) | (None, Some(d)) => d,
        (None, None) => {
            let file = sys.constraints.as_deref().unwrap_or("command line");
            return Err(InputError::new(
                file,
                "dim",
                "the dimension is not given: add \"dim\": 2 or 3 to the file, or pass --dim",
            )
            .into());
        }
    };
    // B before H: its rows bound the nodes H may leave without entries.
    let b = match (&bc, &sys.constraint_matrix) {
        (None, Some(bpath)) => Some(mtx::read_matrix(bpath, "B")?),
        _ => None,
    };
    // H's size line is checked before any of its entries is stored: no more rows than
    // g declares, and no more nodes than its entries plus the nodes the constraints fix.
    let g_rows = mtx::read_header(&sys.gradient)
        .ok()
        .and_then(|h| h.vector_len());
    let g_what = g_rows.map(|r| format!("the {r} rows of g ({})", sys.gradient));
    let constrained_nodes = match (&bc, &b) {
        (Some(bc), _) => bc.constraints.len(),
        (None, Some(b)) => b.nrows,
        (None, None) => 0,
    };
    let h = mtx::read_hessian_bounded(
        &sys.hessian,
        dim,
        &mtx::HessianBounds {
            max_rows: g_rows.zip(g_what.as_deref()),
            constrained_nodes: Some(constrained_nodes),
        },
    )?;
    let (nd, n) = (h.ndof(), h.n);
    let g = mtx::read_vector(
        &sys.gradient,
        "g",
        Some((nd, &format!("{nd} = {dim} × {n} nodes"))),
    )?;
    let (constraints, cfile): (Vec<Constraint>, &str) = match (&bc, &b) {
        (Some(bc), _) => (
            bc.constraints.clone(),
            sys.constraints.as_deref().unwrap_or_default(),
        ),
        (None, Some(b)) => {
            // B was read above (read_matrix refuses more rows than entries).
            let bpath = sys.constraint_matrix.as_deref().unwrap_or_default();
            let p = match &sys.constraint_values {
                Some(ppath) => Some((
                    ppath.as_str(),
                    mtx::read_vector(
                        ppath,
                        "p",
                        Some((b.nrows, &format!("{} (the rows of B)", b.nrows))),
                    )?,
                )),
                None => None,
            };
            let cs = bcjson::constraints_from_matrix(
                bpath,
                b,
                p.as_ref().map(|(f, v)| (*f, v.as_slice())),
                dim,
                n,
            )?;
            (cs, bpath)
        }
        (None, None) => unreachable!("clap requires one constraint input"),
    };
    let read_seconds = t_start.elapsed().as_secs_f64();

    // 2. Constraints → per-node frames, masks and the lift Δx_p.
    let t = Instant::now();
    // With B and p, a contradiction is in p's values as much as in B: name both files.
    let vfile = match (&bc, &sys.constraint_values) {
        (None, Some(ppath)) => format!(" (values from {ppath})"),
        _ => String::new(),
    };
    let frames = Frames::build(dim, n, &constraints)
        .map_err(|e| InputError::new(cfile, e.label, format!("{}{vfile}", e.problem)))?;
    Ok(LoadedSystem {
        dim,
        h,
        g,
        constraints,
        frames,
        read_seconds,
        frames_seconds: t.elapsed().as_secs_f64(),
    })
}

/// `solve`'s inputs and outputs, for [`files::check_outputs`].
fn solve_files(args: &SolveArgs) -> (Vec<Named<'_>>, Vec<Named<'_>>) {
    (
        system_inputs(&args.system),
        [
            ("--out", Some(&args.out)),
            ("--reactions", args.reactions.as_ref()),
            ("--report", args.report.as_ref()),
        ]
        .into_iter()
        .filter_map(|(o, p)| p.map(|p| Named::new(o, p)))
        .collect(),
    )
}

/// The input files of a system (H, g, the constraints).
fn system_inputs(sys: &SystemArgs) -> Vec<Named<'_>> {
    [
        ("--hessian", Some(&sys.hessian)),
        ("--gradient", Some(&sys.gradient)),
        ("--constraints", sys.constraints.as_ref()),
        ("--constraint-matrix", sys.constraint_matrix.as_ref()),
        ("--constraint-values", sys.constraint_values.as_ref()),
    ]
    .into_iter()
    .filter_map(|(o, p)| p.map(|p| Named::new(o, p)))
    .collect()
}

/// `stickslip solve`: read → constraints → frames → eliminate → solve → recover → write.
pub fn solve(args: &SolveArgs) -> Result<Report, CliError> {
    let t_start = Instant::now();
    // Before any work: no output may destroy an input or another output, and each can be
    // created.
    let (inputs, outputs) = solve_files(args);
    files::check_outputs(&inputs, &outputs)?;
    if args.solver == SolverKind::Gpu {
        check_adapter_name()?;
    }
    let precision = args.precision.unwrap_or(Precision::F64);
    let max_iters = args
        .max_iters
        .unwrap_or(crate::engine::solver::DEFAULT_MAX_ITERS);
    // The configuration is checked before any file is read (f32 on the CPU, --error-tol
    // without mixed): one line naming the option.
    let mut config = match args.solver {
        SolverKind::Cholesky => SolverConfig::cholesky(),
        SolverKind::Cg => SolverConfig::cg(),
        SolverKind::Gpu => SolverConfig::gpu(precision),
    }
    .tol(args.tol)
    .max_iters(max_iters)
    .preconditioner(args.preconditioner)
    .coarse(args.coarse)
    .constrained_diagonal(args.constrained_diagonal)
    .ordering(args.ordering);
    config.precision = precision;
    config.error_tol = args.error_tol;
    if args.solver != SolverKind::Gpu && precision != Precision::F64 {
        return Err(InputError::new(
            "command line",
            "--precision",
            format!("{precision} needs --solver gpu (cholesky and cg compute in f64)"),
        )
        .into());
    }
    if args.error_tol.is_some() && (args.solver != SolverKind::Gpu || precision != Precision::Mixed)
    {
        return Err(InputError::new(
            "command line",
            "--error-tol",
            "needs --solver gpu --precision mixed (extended-precision refinement)",
        )
        .into());
    }

    // 1–2. Read H, g and the constraints; build the per-node frames.
    let LoadedSystem {
        dim,
        h,
        g,
        constraints,
        frames,
        read_seconds: t_read,
        frames_seconds,
    } = read_system(&args.system)?;
    let n = h.n;
    let problem = Problem::from_checked_parts(h, g, constraints, frames);

    // 3–5. Eliminate, solve, recover Δx = Δx_p + V y and f = −(HΔx + g). Every GPU
    // failure (no adapter, no SHADER_F64, a device error) is a solve error: exit 1.
    let t = Instant::now();
    let mut solver = Solver::new(config).map_err(solve_error)?;
    let t_open = t.elapsed().as_secs_f64();
    let sol = solver.solve(&problem).map_err(solve_error)?;
    let st = &sol.stats;
    let (dx, f) = (&sol.dx, &sol.reactions);
    let constraints = problem.constraints();
    let frames = problem.frames();
    let violation = constraint_violation(dim, constraints, dx);
    let mut seconds = Seconds::default();
    let mut chol = None;
    let mut cgr = None;
    let mut gpu = None;
    match &st.details {
        SolveDetails::Cholesky(info) => {
            seconds.symbolic = Some(info.symbolic_seconds);
            seconds.numeric = Some(info.numeric_seconds);
            seconds.triangular = Some(info.solve_seconds);
            chol = Some(CholeskyReport {
                matrix_nnz: info.matrix_nnz,
                factor_nnz: info.factor_nnz,
                reused_symbolic: info.reused_symbolic,
                factor_nnz_exact: info.factor_nnz_exact,
                ordering: info.ordering.name().into(),
                ordering_seconds: info.ordering_seconds,
                scaled_residual: info.scaled_residual,
                refinements: info.refinements,
                condition_estimate: info.condition_estimate,
            });
        }
        SolveDetails::Cg(info) => {
            cgr = Some(CgReport {
                preconditioner: args.preconditioner.name().into(),
                coarse: args.coarse.name().into(),
                tol: args.tol,
                max_iters,
                restarts: info.restarts,
            });
        }
        SolveDetails::Gpu(info) => {
            gpu = Some(serde_json::to_value(info).unwrap_or(serde_json::Value::Null));
        }
    }
    let relative_residual = st.relative_residual;

    // 6. Write.
    let t = Instant::now();
    let solver = args.solver.name();
    let note =
        format!("stickslip solve --solver {solver}: relative residual {relative_residual:.3e}");
    mtx::write_vector(&args.out, dx, &format!("dx: {note}"))
        .map_err(|e| write_failed(&args.out, e))?;
    if let Some(path) = &args.reactions {
        mtx::write_vector(path, f, &format!("reactions f = -(H dx + g): {note}"))
            .map_err(|e| write_failed(path, e))?;
    }
    seconds.read = t_read;
    seconds.setup = frames_seconds + t_open + st.seconds.setup;
    seconds.solve = st.seconds.solve;
    seconds.recover = st.seconds.recover;
    seconds.write = t.elapsed().as_secs_f64();
    seconds.total = t_start.elapsed().as_secs_f64();
    let report = Report {
        threads: rayon::current_num_threads(),
        solver: solver.into(),
        precision: precision.to_string(),
        adapter: st.adapter.clone(),
        iterations: st.iterations,
        relative_residual,
        seconds,
        dim,
        nodes: n,
        free_dofs: frames.free_dofs(),
        constrained_dofs: frames.constrained_dofs(),
        rotated_nodes: frames.rot_nodes.len(),
        constraints: constraints.len(),
        prescribed: !frames.homogeneous,
        constrained_diagonal: match args.constrained_diagonal {
            ConstrainedDiagonal::Identity => "identity",
            ConstrainedDiagonal::Hessian => "hessian",
        }
        .into(),
        constraint_violation: violation,
        cholesky: chol,
        cg: cgr,
        gpu,
        files: Files {
            hessian: args.system.hessian.clone(),
            gradient: args.system.gradient.clone(),
            constraints: args.system.constraints.clone(),
            constraint_matrix: args.system.constraint_matrix.clone(),
            constraint_values: args.system.constraint_values.clone(),
            out: args.out.clone(),
            reactions: args.reactions.clone(),
        },
    };
    if let Some(path) = &args.report {
        let mut text =
            serde_json::to_string_pretty(&report).map_err(|e| CliError::Failed(e.to_string()))?;
        text.push('\n');
        files::write_atomic_bytes(path, text.as_bytes()).map_err(|e| write_failed(path, e))?;
    }
    Ok(report)
}

/// A solve error (exit 1) when `v` holds a NaN or an infinity.
fn all_finite(what: &str, v: &[f64]) -> Result<(), CliError> {
    crate::engine::solver::all_finite(what, v).map_err(solve_error)
}

/// The facade's errors as the command line reports them: bad input exits 2, everything
/// else (unsolvable system, GPU failure) exits 1.
fn solve_error(e: Error) -> CliError {
    match e {
        Error::Input(e) => CliError::Input(e),
        Error::Solve(e) => CliError::Solve(e),
        // A system too large for the device: the input must change, not the device.
        Error::Gpu(e) if e.does_not_fit() => {
            CliError::Input(InputError::new("--solver gpu", "", e.to_string()))
        }
        Error::Gpu(e) => CliError::Solve(SolveError::Gpu(e)),
    }
}

/// max over constraint rows of |aᵀΔx_i − c| / ‖a‖: how well Δx meets B Δx = p.
fn constraint_violation(dim: usize, cs: &[Constraint], dx: &[f64]) -> f64 {
    let mut worst = 0.0f64;
    for c in cs {
        let (rows, vals) = node_rows(dim, c);
        let xi = &dx[c.node * dim..c.node * dim + dim];
        for (r, v) in rows.iter().zip(vals) {
            // Scaled norm: rows near 1e±200 are accepted and must not turn into 0 or ∞.
            let len = crate::core::elimination::norm2(r);
            let s: f64 = r.iter().zip(xi).map(|(a, b)| a * b).sum();
            let miss = (s - v).abs() / len;
            if !miss.is_finite() {
                return f64::NAN;
            }
            worst = worst.max(miss);
        }
    }
    worst
}

/// Every file `generate` may write in its folder.
pub const GENERATE_OUTPUTS: [&str; 5] = ["H.mtx", "g.mtx", "bc.json", "B.mtx", "p.mtx"];

/// `stickslip generate`: a seeded system as H.mtx, g.mtx, bc.json (and B.mtx, p.mtx).
pub fn generate(args: &GenerateArgs, quiet: bool) -> Result<(), CliError> {
    let t = Instant::now();
    if args.nodes == 0 {
        return Err(InputError::new("command line", "--nodes", "must be at least 1").into());
    }
    let mut out = OutputDir::open(
        &args.out_dir,
        "--out-dir",
        "generate",
        &GENERATE_OUTPUTS,
        &[],
        args.overwrite,
    )?;
    let dim = usize::from(args.dim);
    let mut spec = SystemSpec::with_nodes(dim, args.nodes, args.seed);
    spec.stencil = match args.stencil {
        StencilArg::Mesh => Stencil::Mesh,
        StencilArg::Face => Stencil::Face,
    };
    spec.mix = match args.mix {
        MixArg::Realistic => ConstraintMix::Realistic,
        MixArg::Random => ConstraintMix::Random,
        MixArg::None => ConstraintMix::None,
    };
    let s = random_system(&spec);
    let dir = &args.out_dir;
    let shown = dir.display().to_string();
    out.clean().map_err(|e| write_failed(&shown, e))?;
    let comment = format!(
        "stickslip generate --dim {dim} --nodes {} --seed {} --stencil {:?} --mix {:?}: {} nodes on a {}x{}{} grid",
        args.nodes,
        args.seed,
        args.stencil,
        args.mix,
        s.h.n,
        spec.grid[0],
        spec.grid[1],
        if dim == 3 { format!("x{}", spec.grid[2]) } else { String::new() }
    )
    .to_lowercase();
    // Recorded before they exist: a killed run's files are cleared by the next one.
    for name in GENERATE_OUTPUTS {
        if args.matrix_form || !matches!(name, "B.mtx" | "p.mtx") {
            out.record(name).map_err(|e| write_failed(&shown, e))?;
        }
    }
    let path = |name: &str| dir.join(name);
    let shown = |name: &str| path(name).display().to_string();
    mtx::write_hessian(path("H.mtx"), &s.h, &comment)
        .map_err(|e| write_failed(&shown("H.mtx"), e))?;
    mtx::write_vector(path("g.mtx"), &s.g, &comment)
        .map_err(|e| write_failed(&shown("g.mtx"), e))?;
    bcjson::write(path("bc.json"), dim, &s.constraints)
        .map_err(|e| write_failed(&shown("bc.json"), e))?;
    if args.matrix_form {
        let (b, p) = bcjson::constraints_to_matrix(dim, &s.constraints);
        mtx::write_coo(path("B.mtx"), p.len(), s.h.ndof(), &b, &comment)
            .map_err(|e| write_failed(&shown("B.mtx"), e))?;
        mtx::write_vector(path("p.mtx"), &p, &comment)
            .map_err(|e| write_failed(&shown("p.mtx"), e))?;
    }
    if !quiet {
        eprintln!(
            "stickslip: wrote {} nodes (dim {dim}, {} blocks, {} constraints, {} free dofs) to {} in {:.2} s",
            s.h.n,
            s.h.nnz_blocks(),
            s.constraints.len(),
            s.frames.free_dofs(),
            dir.display(),
            t.elapsed().as_secs_f64()
        );
    }
    Ok(())
}

/// `WGPU_ADAPTER_NAME` naming no adapter is a usage error (exit 2, with the adapters
/// listed), found before any work, not a silent run on another adapter.
pub fn check_adapter_name() -> Result<(), InputError> {
    match crate::gpu::adapter_name_mismatch(&crate::gpu::GpuOptions::default()) {
        Some(problem) => Err(InputError::new("WGPU_ADAPTER_NAME", "", problem)),
        None => Ok(()),
    }
}

/// `stickslip bench`: see [`crate::app::bench`].
fn bench(a: &BenchArgs, quiet: bool) -> Result<(), CliError> {
    if !a.no_gpu {
        check_adapter_name()?;
    }
    // Fail before a long run, not after it, when the output folder cannot be written.
    if let Some(out) = &a.out {
        let shown = out.display().to_string();
        if std::fs::metadata(out).is_ok_and(|m| !m.is_dir()) {
            return Err(InputError::new(&shown, "--out", "is a file, not a folder").into());
        }
        std::fs::create_dir_all(out).map_err(|e| write_failed(&shown, e))?;
        let probe = out.join(".stickslip-write-probe");
        std::fs::write(&probe, b"").map_err(|e| write_failed(&shown, e))?;
        let _ = std::fs::remove_file(&probe);
        // records.jsonl holds this run's records (appended as each one finishes): an
        // earlier run's go first.
        match std::fs::remove_file(out.join("records.jsonl")) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(write_failed(&shown, e));
            }
            _ => {}
        }
    }
    if a.newton {
        return bench_newton(a, quiet);
    }
    if let Some(dir) = &a.systems {
        return bench_systems(dir, a, quiet);
    }
    if a.hard {
        let coarse = match a.coarse {
            Some(c) => vec![c],
            None => vec![CoarseSpace::Aggregates, CoarseSpace::Translations],
        };
        let md =
            crate::app::bench::run_hard(a.out.as_deref(), a.no_gpu, a.hard_scale, &coarse, quiet)
                .map_err(|e| CliError::Failed(format!("bench --hard: {e}")))?;
        if !quiet {
            println!("{md}");
        }
        return Ok(());
    }
    if let Some(d) = a.dims.iter().find(|&&d| d != 2 && d != 3) {
        return Err(InputError::new(
            "command line",
            "--dims",
            format!("dimension {d} is not 2 or 3"),
        )
        .into());
    }
    if a.sizes.as_ref().is_some_and(|s| s.iter().any(|&n| n < 4)) {
        return Err(InputError::new(
            "command line",
            "--sizes",
            "every size must be at least 4 nodes",
        )
        .into());
    }
    let opts = crate::app::bench::BenchOptions {
        quick: a.quick,
        sizes: a.sizes.clone(),
        dims: a.dims.clone(),
        no_gpu: a.no_gpu,
        oracle_max_nodes: a.oracle_max_nodes,
        out: a.out.clone(),
        quiet,
        seed: a.seed,
        coarse: a.coarse.unwrap_or_default(),
        ordering: a.ordering,
    };
    let command: Vec<String> = std::env::args().collect();
    let report = crate::app::bench::run(&opts, &command.join(" ")).map_err(|e| match e {
        crate::app::bench::BenchError::Io(m) => CliError::Failed(m),
        crate::app::bench::BenchError::Solve(m) => CliError::Failed(format!("bench: {m}")),
    })?;
    if !quiet {
        println!("{}", crate::app::bench::summary_text(&report));
    }
    Ok(())
}

/// `stickslip bench --systems DIR`: see [`crate::app::bench_systems`].
fn bench_systems(dir: &Path, a: &BenchArgs, quiet: bool) -> Result<(), CliError> {
    use crate::app::bench_systems as bs;
    let shown = dir.display().to_string();
    if !dir.is_dir() {
        return Err(InputError::new(&shown, "--systems", "is not a folder").into());
    }
    let found =
        bs::find_systems(dir).map_err(|e| CliError::Failed(format!("cannot read {shown}: {e}")))?;
    if found.is_empty() {
        return Err(InputError::new(
            &shown,
            "--systems",
            "holds no system (a folder with H.mtx, g.mtx and bc.json; `run --dump-systems` writes them)",
        )
        .into());
    }
    let mut progress = |r: &bs::SystemRecord| {
        if !quiet {
            eprintln!(
                "{} {}: {}",
                r.system,
                r.solver,
                match (&r.error, r.iterations, r.solve_s) {
                    (Some(e), _, _) => format!("failed: {e}"),
                    (None, k, Some(t)) => format!(
                        "{:.4} s setup, {t:.4} s solve, {} iterations",
                        r.setup_s.unwrap_or(0.0),
                        k.map_or("–".into(), |k| k.to_string())
                    ),
                    _ => String::new(),
                }
            );
        }
    };
    let records = bs::run(dir, a.no_gpu, &mut progress).map_err(CliError::Failed)?;
    if let Some(out) = &a.out {
        let json = serde_json::json!({
            "command": std::env::args().collect::<Vec<_>>().join(" "),
            "tolerance": bs::TOL,
            "records": records,
        });
        let path = out.join("bench.json");
        crate::io::files::write_atomic_bytes(&path, json.to_string().as_bytes())
            .map_err(|e| write_failed(&path.display().to_string(), e))?;
    }
    if !quiet {
        print!("{}", bs::table(&records));
    }
    Ok(())
}

/// `stickslip bench --newton`: see [`crate::app::bench_newton`].
fn bench_newton(a: &BenchArgs, quiet: bool) -> Result<(), CliError> {
    let opts = crate::app::bench_newton::NewtonOptions {
        quick: a.quick,
        sizes: a.sizes.clone(),
        no_gpu: a.no_gpu,
        reps: a.reps,
        out: a.out.clone(),
        quiet,
    };
    crate::app::bench_newton::plan(&opts)?;
    let command: Vec<String> = std::env::args().collect();
    let report = crate::app::bench_newton::run(&opts, &command.join(" ")).map_err(|e| match e {
        crate::app::bench_newton::NewtonBenchError::Gpu(m) => CliError::Failed(m),
        crate::app::bench_newton::NewtonBenchError::Io(m) => CliError::Failed(m),
    })?;
    if !quiet {
        print!("{}", crate::app::bench_newton::summary_text(&report));
    }
    Ok(())
}

/// `stickslip export`: read → frames → eliminate → write Ĥ, b̂ and the layout.
fn export(a: &ExportArgs, quiet: bool) -> Result<(), CliError> {
    let inputs = system_inputs(&a.system);
    let names = &crate::app::export::OUTPUT_NAMES;
    OutputDir::check(
        &a.out_dir,
        "--out-dir",
        "export",
        names,
        &inputs,
        a.overwrite,
    )?;
    let sys = read_system(&a.system)?;
    let mut out = OutputDir::open(
        &a.out_dir,
        "--out-dir",
        "export",
        names,
        &inputs,
        a.overwrite,
    )?;
    let diag = a.constrained_diagonal;
    let e = Eliminated::new(&sys.h, &sys.g, &sys.frames, diag);
    all_finite("b̂ = −Vᵀ(g + HΔx_p)", &e.rhs)?;
    let shown = a.out_dir.display().to_string();
    out.clean().map_err(|e| write_failed(&shown, e))?;
    for name in crate::app::export::OUTPUT_NAMES {
        if a.no_mtx && name.ends_with(".mtx") {
            continue;
        }
        out.record(name).map_err(|e| write_failed(&shown, e))?;
    }
    let files = crate::app::export::export(&e, diag, &sys.g, &a.out_dir, !a.no_mtx)
        .map_err(|err| write_failed(&a.out_dir.display().to_string(), err))?;
    if !quiet {
        eprintln!(
            "exported {} nodes ({} free of {} DOFs, block size {}) to {}: {}",
            sys.h.n,
            sys.frames.free_dofs(),
            sys.h.ndof(),
            sys.dim,
            a.out_dir.display(),
            files.layout.display()
        );
    }
    Ok(())
}

/// `stickslip recover`: y → Δx = Δx_p + V y and f = −(HΔx + g), checked against the layout.
fn recover(a: &RecoverArgs, quiet: bool) -> Result<(), CliError> {
    let inputs = [
        Named::new("--layout", &a.layout),
        Named::new("--solution", &a.solution),
        Named::new("--hessian", &a.hessian),
        Named::new("--gradient", &a.gradient),
    ];
    let outputs: Vec<Named> = std::iter::once(Named::new("--out", &a.out))
        .chain(a.reactions.iter().map(|r| Named::new("--reactions", r)))
        .collect();
    files::check_outputs(&inputs, &outputs)?;
    let layout = crate::app::export::read_layout(std::path::Path::new(&a.layout))?;
    let nd_layout = layout.dim * layout.n_nodes;
    let y = if a.solution.ends_with(".mtx") {
        mtx::read_vector(
            &a.solution,
            "y",
            Some((
                nd_layout,
                &format!(
                    "{nd_layout} = {} × {} nodes (the layout's system)",
                    layout.dim, layout.n_nodes
                ),
            )),
        )?
    } else {
        crate::app::export::read_petsc_vec(std::path::Path::new(&a.solution))?
    };
    let what = format!("the {nd_layout} rows of the layout's system ({})", a.layout);
    let h = mtx::read_hessian_bounded(
        &a.hessian,
        layout.dim,
        &mtx::HessianBounds {
            max_rows: Some((nd_layout, &what)),
            // The layout fixes the size; no bound from the entries.
            constrained_nodes: Some(layout.n_nodes),
        },
    )?;
    let nd = h.ndof();
    let g = mtx::read_vector(
        &a.gradient,
        "g",
        Some((nd, &format!("{nd} = {} × {} nodes", layout.dim, h.n))),
    )?;
    let rec = crate::app::export::recover(
        &layout,
        &y,
        &h,
        &g,
        [&a.layout, &a.solution, &a.hessian, &a.gradient],
    )?;
    // A y that does not solve the exported system (another system's, or zero) would give
    // a Δx that looks like a result: refuse it.
    if rec.relative_residual.is_nan() || rec.relative_residual > a.max_residual {
        return Err(SolveError::NotSolved(format!(
            "{}: y does not solve the exported system: relative residual ‖b̂ − Ĥy‖/‖b̂‖ = \
             {:.3e} > --max-residual {:.1e}; nothing written",
            a.solution, rec.relative_residual, a.max_residual
        ))
        .into());
    }
    all_finite("Δx", &rec.dx)?;
    all_finite("the reactions f = −(HΔx + g)", &rec.reactions)?;
    mtx::write_vector(&a.out, &rec.dx, "dx recovered by stickslip recover")
        .map_err(|e| write_failed(&a.out, e))?;
    if let Some(path) = &a.reactions {
        mtx::write_vector(
            path,
            &rec.reactions,
            "reactions f = -(H dx + g), stickslip recover",
        )
        .map_err(|e| write_failed(path, e))?;
    }
    if !quiet {
        eprintln!(
            "recovered {} nodes; relative residual of y in the exported system {:.3e}",
            h.n, rec.relative_residual
        );
    }
    Ok(())
}

/// `stickslip run`: see [`crate::sim::driver`].
fn run_scene(a: &RunArgs, quiet: bool) -> Result<(), CliError> {
    let opts = crate::sim::driver::RunOptions {
        scene: a.scene.clone(),
        out: a.out.clone(),
        solver: a.solver.map(|s| s.name().to_string()),
        size: a.size,
        steps: a.steps,
        quiet,
        overwrite: a.overwrite,
        ordering: a.ordering,
        newton: a.newton,
        cg_tolerance: a.cg_tolerance,
        dump_systems: a.dump_systems.clone(),
        end_time: a.end_time,
        resume: a.resume.clone(),
    };
    stop_after_the_step_on_signals();
    match crate::sim::driver::run(&opts) {
        Ok(summary) => {
            if !quiet {
                eprintln!(
                    "{}: {} steps of {} s on {} nodes with {}{} in {:.2} s ({} Newton, {} linear iterations); output in {}",
                    summary.scene,
                    summary.steps,
                    summary.time_step,
                    summary.nodes,
                    summary.solver,
                    summary
                        .linear_choice
                        .as_ref()
                        .map_or(String::new(), |r| format!(" ({r})")),
                    summary.wall_seconds,
                    summary.newton_iterations,
                    summary.linear_iterations,
                    summary.out_dir
                );
                if let Some(g) = summary.gpu.as_ref().filter(|g| !g.phases.is_empty()) {
                    eprintln!("{}", largest_phases(&g.phases, summary.wall_seconds));
                }
            }
            Ok(())
        }
        Err(crate::sim::driver::RunError::Input(e)) => Err(CliError::Input(e)),
        Err(e @ crate::sim::driver::RunError::Interrupted { .. }) => Err(CliError::Interrupted {
            code: u8::try_from(e.exit_code()).unwrap_or(1),
            message: e.to_string(),
        }),
        Err(e) => Err(CliError::Failed(e.to_string())),
    }
}

/// SIGINT and SIGTERM end a run after the step it is in, with a checkpoint there; a second
/// one ends it at once (the handler restores the default action).
fn stop_after_the_step_on_signals() {
    #[cfg(unix)]
    {
        extern "C" fn on_signal(sig: libc::c_int) {
            crate::sim::driver::request_interrupt(sig);
            // SAFETY: signal(2) is async-signal-safe; it restores the default action.
            unsafe {
                libc::signal(sig, libc::SIG_DFL);
            }
        }
        let handler = on_signal as extern "C" fn(libc::c_int) as libc::sighandler_t;
        // SAFETY: installs a handler that only stores an atomic and calls signal(2).
        unsafe {
            libc::signal(libc::SIGINT, handler);
            libc::signal(libc::SIGTERM, handler);
        }
    }
}

/// The three phases of a device run with the most wall seconds, in one line.
fn largest_phases(phases: &[(crate::gpu::Phase, f64)], wall: f64) -> String {
    let mut v = phases.to_vec();
    v.sort_by(|a, b| b.1.total_cmp(&a.1));
    let parts: Vec<String> = v
        .iter()
        .take(3)
        .map(|(p, s)| {
            let share = if wall > 0.0 { 100.0 * s / wall } else { 0.0 };
            format!("{} {s:.2} s ({share:.0} %)", p.name().replace('_', " "))
        })
        .collect();
    format!("largest phases: {}", parts.join(", "))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A system too large for the device is an input fault (exit 2); other device
    /// failures exit 1.
    #[test]
    fn a_system_too_large_for_the_device_exits_2() {
        let big = Error::Gpu(crate::gpu::GpuError::DoesNotFit {
            need: 9,
            limit: 8,
            adapter: "a".into(),
        });
        assert_eq!(solve_error(big).exit_code(), 2);
        let lost = Error::Gpu(crate::gpu::GpuError::Lost {
            what: "solving".into(),
            cause: "device lost".into(),
        });
        assert_eq!(solve_error(lost).exit_code(), 1);
    }
}
