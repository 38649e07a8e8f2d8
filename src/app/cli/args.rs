//! The command line's definitions, in one place: every subcommand's options (clap), the
//! parsers of their values and the limits they enforce (docs/cli.md).

use crate::app::system_files::SystemFiles;
use crate::core::elimination::ConstrainedDiagonal;
use crate::solve::cg::Preconditioner;
use crate::solve::coarse::CoarseSpace;
use crate::{CholeskyOrdering, Precision, SolverKind};
use clap::{ArgGroup, Args, Parser, Subcommand, ValueEnum};
use std::path::PathBuf;

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
    /// Run the hard-case stability suite instead (src/app/bench/hard.rs): writes hard.md/hard.json.
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
    /// The CG solvers' preconditioner: auto, none, jacobi, block-jacobi or multilevel
    /// (jacobi and block-jacobi add the scene's `[solver] coarse` correction) [default: the
    /// scene's `[solver] preconditioner`, else auto].
    #[arg(long, value_name = "PRECONDITIONER", value_parser = str::parse::<crate::sim::scene::PreconditionerChoice>)]
    pub preconditioner: Option<crate::sim::scene::PreconditionerChoice>,
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
    /// checkpoint; only --steps or --end-time (to go further), --dump-systems (the steps
    /// dumped from the resume on), --threads and --quiet may be given. A run whose steps
    /// are all done is finished (its summary marked complete).
    #[arg(long, value_name = "DIR")]
    pub resume: Option<PathBuf>,
}

impl SystemArgs {
    /// The files named, for [`crate::app::system_files::read_system`].
    pub fn files(&self) -> SystemFiles {
        SystemFiles {
            hessian: self.hessian.clone(),
            gradient: self.gradient.clone(),
            constraints: self.constraints.clone(),
            constraint_matrix: self.constraint_matrix.clone(),
            constraint_values: self.constraint_values.clone(),
            dim: self.dim,
        }
    }
}
