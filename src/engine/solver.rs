//! [`Solver`]: one entry point to the three solvers of the eliminated system (sparse
//! Cholesky, CPU CG, GPU CG), configured by [`SolverConfig`], returning a [`Solution`].
#![deny(missing_docs)]

use crate::core::elimination::{reactions, ConstrainedDiagonal, Eliminated};
pub use crate::core::problem::LayoutKey;
use crate::core::problem::Problem;
use crate::error::{Error, InputError, SolveError};
use crate::gpu::DifferenceForm;
use crate::gpu::{GpuContext, GpuError, GpuOptions, GpuParams, GpuSolveInfo, PcgSolver, Precision};
use crate::solve::cg::{CgInfo, CgParams, Preconditioner, Scaling};
use crate::solve::coarse::CoarseSpace;
use crate::solve::multilevel::reuse::KeptLevels;
use crate::solve::options::MultilevelSetup;
pub use crate::solve::options::SolverKind;
use crate::solve::oracle::{CholeskyOracle, OracleInfo};
use crate::solve::ordering::CholeskyOrdering;
use std::time::Instant;

/// How a [`Solver`] solves. Build it with [`SolverConfig::cholesky`],
/// [`SolverConfig::cg`] or [`SolverConfig::gpu`] and adjust it with the builder methods.
/// Each setting has one place: the settings the solvers share are fields here, and
/// [`CgTuning`] and [`GpuTuning`] hold only what one backend alone has. The solver runs
/// with [`SolverConfig::cg_params`] or [`SolverConfig::gpu_params`], both formed from these.
///
/// | field | default | used by | meaning |
/// |---|---|---|---|
/// | `kind` | the constructor | all | `cholesky()`, `cg()`, `gpu(precision)` |
/// | `precision` | f64 (CPU); the argument of `gpu(..)` | gpu | f32, f64 or mixed; f64 and mixed need SHADER_F64 |
/// | `tol` | 1e-8 | cg, gpu | stop at ‖b̂ − Ĥy‖/‖b̂‖ ≤ tol (true residual, f64); in (0, 1) |
/// | `max_iters` | 10 000 | cg, gpu | iteration limit; ≥ 1 |
/// | `preconditioner` | jacobi | cg, gpu | jacobi, block-jacobi, none, multilevel (cg, and gpu in f64) |
/// | `coarse` | aggregates | cg, gpu | coarse correction (docs/coarse.md) |
/// | `multilevel_setup` | every | cg, gpu f64 | `MultilevelSetup::Every` builds the multilevel levels for every solve; `Reuse` keeps them across the solves of a Newton sequence (as scenes do: `[solver] multilevel_setup`) |
/// | `error_tol` | none | gpu mixed | refine until the estimated relative error ≤ this |
/// | `constrained_diagonal` | identity | all | D on constrained components: identity or diag(VᵀHV) |
/// | `ordering` | auto | cholesky | fill-reducing ordering: auto, amd or nested-dissection (`CholeskyOrdering`; as `solve --ordering`) |
/// | `cg_tuning` | `CgTuning::default()` | cg | what only the CPU CG has: |
/// | `.stagnation_window` | 1 000 | cg | restart from the true residual when the best recurrence residual has not improved for this many iterations |
/// | `.max_restarts` | 3 | cg | restarts allowed |
/// | `.check_every` | 64 | cg | iterations between true-residual checks (0: only at convergence) |
/// | `.scaling` | none | cg | diagonal equilibration (`Scaling::NodeDiagonal`) |
/// | `gpu_tuning` | `GpuTuning::default()` | gpu | what only the GPU CG has: |
/// | `.stagnation_window`, `.max_restarts` | 1 000, 3 | gpu | as for cg |
/// | `.inner_tol` | 1e-2 | gpu mixed | reliable-update factor δ |
/// | `.max_outer` | 200 | gpu mixed | limit on reliable updates |
/// | `.f32_difference` | auto | gpu f32, mixed | difference form of the f32 operator (`DifferenceForm`) |
/// | `.binding_limit`, `.memory_limit` | none | gpu | caps on the binding size and device memory the solver assumes (tests) |
/// | `gpu_context` | none | gpu | a device to share; none opens the default adapter |
#[derive(Clone)]
pub struct SolverConfig {
    /// Which solver runs.
    pub kind: SolverKind,
    /// Arithmetic of the GPU CG (the CPU solvers compute in f64).
    pub precision: Precision,
    /// Relative residual tolerance of the iterative solvers.
    pub tol: f64,
    /// Iteration limit of the iterative solvers.
    pub max_iters: usize,
    /// Point-wise preconditioner of the iterative solvers.
    pub preconditioner: Preconditioner,
    /// Coarse correction of the iterative solvers.
    pub coarse: CoarseSpace,
    /// When the multilevel preconditioner's levels are rebuilt (CPU CG and the device PCG
    /// in f64): for every system, or kept across the systems of a Newton solve.
    pub multilevel_setup: MultilevelSetup,
    /// Mixed precision only: target of the estimated relative error.
    pub error_tol: Option<f64>,
    /// D on constrained components of Ĥ.
    pub constrained_diagonal: ConstrainedDiagonal,
    /// Fill-reducing ordering of the Cholesky analysis.
    pub ordering: CholeskyOrdering,
    /// What only the CPU CG has.
    pub cg_tuning: CgTuning,
    /// What only the GPU CG has.
    pub gpu_tuning: GpuTuning,
    /// The GPU device to use; none: the default adapter.
    pub gpu_context: Option<GpuContext>,
}

impl std::fmt::Debug for SolverConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SolverConfig")
            .field("kind", &self.kind)
            .field("precision", &self.precision)
            .field("tol", &self.tol)
            .field("max_iters", &self.max_iters)
            .field("preconditioner", &self.preconditioner)
            .field("coarse", &self.coarse)
            .field("multilevel_setup", &self.multilevel_setup)
            .field("error_tol", &self.error_tol)
            .field("constrained_diagonal", &self.constrained_diagonal)
            .field("ordering", &self.ordering)
            .field("cg_tuning", &self.cg_tuning)
            .field("gpu_tuning", &self.gpu_tuning)
            .field(
                "gpu_context",
                &self
                    .gpu_context
                    .as_ref()
                    .map(|c| c.adapter_name().to_string()),
            )
            .finish()
    }
}

/// Default relative residual tolerance of the iterative solvers.
pub const DEFAULT_TOL: f64 = 1e-8;
/// Default CG iteration limit.
pub const DEFAULT_MAX_ITERS: usize = 10_000;

impl SolverConfig {
    fn with_kind(kind: SolverKind, precision: Precision) -> Self {
        SolverConfig {
            kind,
            precision,
            tol: DEFAULT_TOL,
            max_iters: DEFAULT_MAX_ITERS,
            preconditioner: Preconditioner::Jacobi,
            coarse: CoarseSpace::default(),
            multilevel_setup: MultilevelSetup::default(),
            error_tol: None,
            constrained_diagonal: ConstrainedDiagonal::Identity,
            ordering: CholeskyOrdering::Auto,
            cg_tuning: CgTuning::default(),
            gpu_tuning: GpuTuning::default(),
            gpu_context: None,
        }
    }

    /// Sparse Cholesky of the assembled Ĥ (f64). The symbolic analysis is reused while the
    /// pattern and the constraints stay.
    pub fn cholesky() -> Self {
        Self::with_kind(SolverKind::Cholesky, Precision::F64)
    }

    /// Preconditioned CG on the CPU (f64).
    pub fn cg() -> Self {
        Self::with_kind(SolverKind::Cg, Precision::F64)
    }

    /// Preconditioned CG on the GPU in the given precision.
    pub fn gpu(precision: Precision) -> Self {
        Self::with_kind(SolverKind::Gpu, precision)
    }

    /// Sets the relative residual tolerance.
    pub fn tol(mut self, tol: f64) -> Self {
        self.tol = tol;
        self
    }

    /// Sets the iteration limit.
    pub fn max_iters(mut self, n: usize) -> Self {
        self.max_iters = n;
        self
    }

    /// Sets the point-wise preconditioner.
    pub fn preconditioner(mut self, p: Preconditioner) -> Self {
        self.preconditioner = p;
        self
    }

    /// Sets the coarse correction.
    pub fn coarse(mut self, c: CoarseSpace) -> Self {
        self.coarse = c;
        self
    }

    /// Sets when the multilevel preconditioner's levels are rebuilt.
    pub fn multilevel_setup(mut self, s: MultilevelSetup) -> Self {
        self.multilevel_setup = s;
        self
    }

    /// Mixed precision: refine until the estimated relative error is ≤ `e`.
    pub fn error_tol(mut self, e: f64) -> Self {
        self.error_tol = Some(e);
        self
    }

    /// Sets D on constrained components.
    pub fn constrained_diagonal(mut self, d: ConstrainedDiagonal) -> Self {
        self.constrained_diagonal = d;
        self
    }

    /// Sets the Cholesky analysis' fill-reducing ordering.
    pub fn ordering(mut self, o: CholeskyOrdering) -> Self {
        self.ordering = o;
        self
    }

    /// Sets what only the CPU CG has (the shared settings stay as set).
    pub fn cg_tuning(mut self, t: CgTuning) -> Self {
        self.cg_tuning = t;
        self
    }

    /// Sets what only the GPU CG has (the shared settings stay as set).
    pub fn gpu_tuning(mut self, t: GpuTuning) -> Self {
        self.gpu_tuning = t;
        self
    }

    /// Runs on this device instead of opening the default adapter.
    pub fn gpu_context(mut self, ctx: GpuContext) -> Self {
        self.gpu_context = Some(ctx);
        self
    }

    /// The CPU CG parameters this configuration runs with: the shared settings and
    /// [`CgTuning`].
    pub fn cg_params(&self) -> CgParams {
        // No `..Default`: a new CgParams field has to be given its one place here.
        let CgTuning {
            stagnation_window,
            max_restarts,
            check_every,
            scaling,
        } = self.cg_tuning;
        CgParams {
            tol: self.tol,
            max_iters: self.max_iters,
            preconditioner: self.preconditioner,
            coarse: self.coarse,
            stagnation_window,
            max_restarts,
            check_every,
            scaling,
        }
    }

    /// The GPU parameters this configuration runs with: the shared settings and
    /// [`GpuTuning`].
    pub fn gpu_params(&self) -> GpuParams {
        let GpuTuning {
            stagnation_window,
            max_restarts,
            inner_tol,
            max_outer,
            f32_difference,
            binding_limit,
            memory_limit,
        } = self.gpu_tuning;
        GpuParams {
            precision: self.precision,
            tol: self.tol,
            max_iters: self.max_iters,
            preconditioner: self.preconditioner,
            multilevel_setup: self.multilevel_setup,
            error_tol: self.error_tol,
            coarse: self.coarse,
            stagnation_window,
            max_restarts,
            inner_tol,
            max_outer,
            f32_difference,
            binding_limit,
            memory_limit,
        }
    }

    /// Checks the fields the chosen solver uses.
    fn validate(&self) -> Result<(), Error> {
        let bad = |entry: &str, problem: String| {
            Err(InputError::new("solver config", entry, problem).into())
        };
        if self.kind != SolverKind::Gpu && self.precision != Precision::F64 {
            return bad(
                "precision",
                format!(
                    "{} needs the gpu solver (cholesky and cg compute in f64)",
                    self.precision
                ),
            );
        }
        if self.kind == SolverKind::Cholesky {
            return Ok(());
        }
        if self.kind == SolverKind::Gpu
            && self.preconditioner == Preconditioner::Multilevel
            && self.precision != Precision::F64
        {
            return bad("preconditioner", crate::gpu::MULTILEVEL_ON_CPU.into());
        }
        let (tol, max_iters, error_tol) = (self.tol, self.max_iters, self.error_tol);
        if !(tol > 0.0 && tol < 1.0) {
            return bad("tol", format!("must lie in (0, 1), got {tol}"));
        }
        if max_iters == 0 {
            return bad("max_iters", "must be at least 1".into());
        }
        if let Some(e) = error_tol {
            if self.kind != SolverKind::Gpu || self.precision != Precision::Mixed {
                return bad(
                    "error_tol",
                    "needs the gpu solver in mixed precision".into(),
                );
            }
            if !(e > 0.0 && e < 1.0) {
                return bad("error_tol", format!("must lie in (0, 1), got {e}"));
            }
        }
        Ok(())
    }
}

/// What only the CPU CG has; the settings it shares with the GPU CG are
/// [`SolverConfig`]'s fields. Defaults in [`SolverConfig`]'s table (those of [`CgParams`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CgTuning {
    /// Restart when the best recurrence residual has not improved for this many iterations.
    pub stagnation_window: usize,
    /// Restarts allowed from the true residual.
    pub max_restarts: usize,
    /// Iterations between true-residual checks (0: only at convergence).
    pub check_every: usize,
    /// Diagonal equilibration.
    pub scaling: Scaling,
}

impl Default for CgTuning {
    fn default() -> Self {
        let p = CgParams::default();
        CgTuning {
            stagnation_window: p.stagnation_window,
            max_restarts: p.max_restarts,
            check_every: p.check_every,
            scaling: p.scaling,
        }
    }
}

/// What only the GPU CG has; the settings it shares with the CPU CG are [`SolverConfig`]'s
/// fields. Defaults in [`SolverConfig`]'s table (those of [`GpuParams`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GpuTuning {
    /// Restart when the recurrence residual has not improved for this many iterations.
    pub stagnation_window: usize,
    /// Restarts allowed from the current iterate.
    pub max_restarts: usize,
    /// Mixed: reliable-update factor δ ([`GpuParams::inner_tol`]).
    pub inner_tol: f64,
    /// Mixed: limit on outer steps (reliable updates).
    pub max_outer: usize,
    /// Whether f32 operators use the difference form.
    pub f32_difference: DifferenceForm,
    /// Caps the storage binding size the solver assumes (bytes; tests).
    #[doc(hidden)]
    pub binding_limit: Option<u64>,
    /// Caps the device memory the solver assumes (bytes; tests).
    #[doc(hidden)]
    pub memory_limit: Option<u64>,
}

impl Default for GpuTuning {
    fn default() -> Self {
        let p = GpuParams::default();
        GpuTuning {
            stagnation_window: p.stagnation_window,
            max_restarts: p.max_restarts,
            inner_tol: p.inner_tol,
            max_outer: p.max_outer,
            f32_difference: p.f32_difference,
            binding_limit: p.binding_limit,
            memory_limit: p.memory_limit,
        }
    }
}

/// Wall time of one solve, in seconds.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct SolveSeconds {
    /// Forming b̂ and D, plus the analysis or device upload of a new layout, or the CPU
    /// CG's multilevel clusters and levels.
    pub setup: f64,
    /// The solve proper (factorization and triangular solves, or CG).
    pub solve: f64,
    /// Recovering Δx = Δx_p + V y (and the reactions, for [`Solver::solve`]).
    pub recover: f64,
}

/// What each solver reports of its own.
#[derive(Debug, Clone, PartialEq)]
pub enum SolveDetails {
    /// Sparse Cholesky: timings of its phases, nonzeros of Ĥ and of the factor.
    Cholesky(OracleInfo),
    /// CPU CG: restarts, condition estimate, residual replacements.
    Cg(CgInfo),
    /// GPU CG: adapter, precision path, bytes per iteration, kernel times, fallbacks.
    Gpu(Box<GpuSolveInfo>),
}

/// What a solve did.
#[derive(Debug, Clone, PartialEq)]
pub struct SolveStats {
    /// The solver that ran.
    pub solver: SolverKind,
    /// Its arithmetic (f64 for the CPU solvers).
    pub precision: Precision,
    /// CG iterations (all restarts and inner solves); None for Cholesky.
    pub iterations: Option<usize>,
    /// ‖b̂ − Ĥy‖/‖b̂‖ recomputed in f64 at the end.
    pub relative_residual: f64,
    /// True when the solve reused the analysis or device buffers of an earlier solve.
    pub reused: bool,
    /// The GPU adapter, for the GPU solver.
    pub adapter: Option<String>,
    /// Wall time by stage.
    pub seconds: SolveSeconds,
    /// The solver's own report.
    pub details: SolveDetails,
}

/// The answer of [`Solver::solve`].
#[derive(Debug, Clone, PartialEq)]
pub struct Solution {
    /// The step Δx (length d·n): it meets every constraint to f64 rounding.
    pub dx: Vec<f64>,
    /// The reactions f = −(HΔx + g): the forces the constraints exert (zero on free
    /// components up to the solver's residual).
    pub reactions: Vec<f64>,
    /// What the solve did.
    pub stats: SolveStats,
}

/// The answer of [`Solver::solve_eliminated`]: the eliminated solution and the step.
#[derive(Debug, Clone, PartialEq)]
pub struct Step {
    /// y, the solution of Ĥ y = b̂ in the nodes' frames.
    pub y: Vec<f64>,
    /// Δx = Δx_p + V y.
    pub dx: Vec<f64>,
    /// What the solve did.
    pub stats: SolveStats,
}

/// Layouts whose analysis or device buffers a solver keeps (a simulation alternates
/// between a few constraint sets, for example while moving boundaries are eliminated).
const KEPT_LAYOUTS: usize = 8;

enum Prepared {
    Cholesky(Box<CholeskyOracle>),
    /// The device PCG, in every precision; its multilevel clusters and levels are the
    /// engine's `levels`, shared by every constraint set of the mesh.
    Gpu(Box<PcgSolver>),
}

// A `Solver` moves between threads (the Python package releases the GIL around solves).
const _: fn() = || {
    fn send<T: Send>() {}
    send::<Solver>();
};

/// Solves [`Problem`]s with one configured solver, keeping what can be reused between
/// solves of the same layout (Cholesky analysis, GPU buffers and pipelines).
pub struct Solver {
    config: SolverConfig,
    gpu: Option<GpuContext>,
    /// Most recently used last.
    prepared: Vec<(LayoutKey, Prepared)>,
    /// The multilevel preconditioner's clusters of the last pattern solved, and its
    /// levels when they are kept between systems.
    levels: KeptLevels,
}

impl Solver {
    /// Checks the configuration and, for the GPU solver, opens the device (or takes the
    /// configured one). Fails with [`Error::Input`] for a bad configuration and
    /// [`Error::Gpu`] when no suitable GPU is there.
    pub fn new(config: SolverConfig) -> Result<Self, Error> {
        config.validate()?;
        let gpu = match (config.kind, &config.gpu_context) {
            (SolverKind::Gpu, Some(ctx)) => Some(ctx.clone()),
            (SolverKind::Gpu, None) => Some(
                GpuContext::new(&GpuOptions::default())
                    .map_err(|e| Error::Gpu(e.cannot_start("GPU solver")))?,
            ),
            _ => None,
        };
        if let Some(ctx) = &gpu {
            if config.precision != Precision::F32 && !ctx.has_f64() {
                return Err(GpuError::NoF64 {
                    adapter: ctx.adapter_name().to_string(),
                    precision: config.precision.name(),
                }
                .into());
            }
        }
        Ok(Solver {
            levels: KeptLevels::new(config.multilevel_setup),
            config,
            gpu,
            prepared: Vec::new(),
        })
    }

    /// The configuration.
    pub fn config(&self) -> &SolverConfig {
        &self.config
    }

    /// Sets the relative residual tolerance of the iterative solvers for the next solves
    /// (an inexact Newton loop changes it per system; Cholesky ignores it). Refuses a
    /// value outside (0, 1) and leaves the solver as it was.
    pub fn set_tol(&mut self, tol: f64) -> Result<(), Error> {
        if !(tol > 0.0 && tol < 1.0) {
            return Err(InputError::new(
                "solver config",
                "tol",
                format!("must lie in (0, 1), got {tol}"),
            )
            .into());
        }
        self.config.tol = tol;
        Ok(())
    }

    /// The GPU adapter's name, for the GPU solver.
    pub fn adapter(&self) -> Option<&str> {
        self.gpu.as_ref().map(|c| c.adapter_name())
    }

    /// Bytes moved between host and device by the GPU solver so far (None for the CPU
    /// solvers).
    pub fn gpu_traffic(&self) -> Option<crate::gpu::TrafficCount> {
        self.gpu.as_ref().map(GpuContext::traffic)
    }

    /// Solves the problem: Δx meeting every constraint, and the reactions.
    pub fn solve(&mut self, problem: &Problem) -> Result<Solution, Error> {
        let t = Instant::now();
        let e = Eliminated::new(
            problem.hessian(),
            problem.gradient(),
            problem.frames(),
            self.config.constrained_diagonal,
        );
        let form = t.elapsed().as_secs_f64();
        let Step { dx, mut stats, .. } = self.solve_formed(problem.layout(), &e)?;
        stats.seconds.setup += form;
        let t = Instant::now();
        let f = reactions(problem.hessian(), problem.gradient(), &dx);
        all_finite("the reactions f = −(HΔx + g)", &f)?;
        stats.seconds.recover += t.elapsed().as_secs_f64();
        Ok(Solution {
            dx,
            reactions: f,
            stats,
        })
    }

    /// Solves an eliminated system the caller formed (a simulation that assembles H into
    /// its own [`crate::core::sparse::BlockCsr`]); `layout` identifies its pattern and
    /// constraint set for reuse ([`LayoutKey::fresh`] once per layout).
    pub fn solve_eliminated(&mut self, layout: LayoutKey, e: &Eliminated) -> Result<Step, Error> {
        if e.h.dim != e.frames.dim || e.h.n != e.frames.n_nodes || e.rhs.len() != e.h.ndof() {
            return Err(
                InputError::new("problem", "", "H, the frames and b̂ disagree in size").into(),
            );
        }
        self.solve_formed(layout, e)
    }

    fn solve_formed(&mut self, layout: LayoutKey, e: &Eliminated) -> Result<Step, Error> {
        let t = Instant::now();
        let (y, mut stats) = match self.config.kind {
            SolverKind::Cholesky => self.cholesky(layout, e)?,
            SolverKind::Cg => {
                let (y, info, levels_s) = self.cg(e)?;
                let mut stats = self.stats(
                    Some(info.iterations),
                    info.relative_residual,
                    false,
                    SolveDetails::Cg(info),
                );
                stats.seconds.setup = levels_s;
                (y, stats)
            }
            SolverKind::Gpu => self.gpu(layout, e)?,
        };
        all_finite("the solution y", &y)?;
        let total = t.elapsed().as_secs_f64();
        let t = Instant::now();
        // Δx from the f64 frames in every precision: the constraints then hold to f64
        // rounding whatever arithmetic produced y.
        let dx = e.recover(&y);
        all_finite("Δx", &dx)?;
        stats.seconds.recover = t.elapsed().as_secs_f64();
        stats.seconds.solve = (total - stats.seconds.setup).max(0.0);
        Ok(Step { y, dx, stats })
    }

    fn stats(
        &self,
        iterations: Option<usize>,
        relative_residual: f64,
        reused: bool,
        details: SolveDetails,
    ) -> SolveStats {
        SolveStats {
            solver: self.config.kind,
            precision: self.config.precision,
            iterations,
            relative_residual,
            reused,
            adapter: self.adapter().map(str::to_string),
            seconds: SolveSeconds::default(),
            details,
        }
    }

    /// The prepared state of `layout`, moved to the back (most recent); evicts the oldest.
    fn take_prepared(&mut self, layout: LayoutKey) -> Option<Prepared> {
        let k = self.prepared.iter().position(|(l, _)| *l == layout)?;
        Some(self.prepared.remove(k).1)
    }

    fn keep_prepared(&mut self, layout: LayoutKey, p: Prepared) {
        if self.prepared.len() >= KEPT_LAYOUTS {
            self.prepared.remove(0);
        }
        self.prepared.push((layout, p));
    }

    /// Systems so far whose multilevel levels were built, and systems that kept them (the
    /// CPU CG and the device PCG; both zero for the other solvers and preconditioners).
    pub fn multilevel_levels(&self) -> (usize, usize) {
        self.levels.counts()
    }

    /// The next system begins a new Newton solve (a simulation step): the multilevel
    /// preconditioner's kept levels (`multilevel_setup = "reuse"`) are rebuilt for it, so
    /// that the solve does not depend on the systems before it.
    pub fn new_newton_solve(&mut self) {
        self.levels.new_newton_solve();
    }

    /// The CPU CG; the multilevel preconditioner partitions H's pattern once and keeps the
    /// clusters while the pattern stays (and its levels, as the setup says: a solve that
    /// fails on kept levels runs again on fresh ones). Also returns the seconds spent on
    /// the multilevel preconditioner's clusters and levels (0 for the others).
    fn cg(&mut self, e: &Eliminated) -> Result<(Vec<f64>, crate::solve::cg::CgInfo, f64), Error> {
        use crate::solve::cg::BuiltPreconditioner;
        let params = self.config.cg_params();
        if params.preconditioner != Preconditioner::Multilevel || params.scaling != Scaling::None {
            let (y, info) = crate::solve::cg::solve(e, &params)?;
            return Ok((y, info, 0.0));
        }
        crate::solve::cg::check_pinned(e)?;
        let mut levels_s = 0.0;
        loop {
            let t = Instant::now();
            let (levels, _) = self.levels.for_cpu_system(e);
            levels_s += t.elapsed().as_secs_f64();
            let pre = BuiltPreconditioner::with_levels(levels);
            match crate::solve::cg::solve_with(e, &pre, None, &params) {
                Ok((y, info)) => {
                    self.levels.solved(info.iterations, params.tol);
                    return Ok((y, info, levels_s));
                }
                Err(err) => {
                    if !self.levels.failed() {
                        return Err(err.into());
                    }
                }
            }
        }
    }

    fn cholesky(
        &mut self,
        layout: LayoutKey,
        e: &Eliminated,
    ) -> Result<(Vec<f64>, SolveStats), Error> {
        let t = Instant::now();
        let mut oracle = match self.take_prepared(layout) {
            Some(Prepared::Cholesky(o)) => o,
            _ => Box::new(CholeskyOracle::analyze_with(e, self.config.ordering)?),
        };
        let analysed = t.elapsed().as_secs_f64();
        // A layout key reused with another pattern re-analyses inside solve.
        let result = oracle.solve(e);
        self.keep_prepared(layout, Prepared::Cholesky(oracle));
        let (y, info) = result?;
        let mut stats = self.stats(
            None,
            info.relative_residual,
            info.reused_symbolic,
            SolveDetails::Cholesky(info),
        );
        stats.seconds.setup = analysed;
        Ok((y, stats))
    }

    fn gpu(&mut self, layout: LayoutKey, e: &Eliminated) -> Result<(Vec<f64>, SolveStats), Error> {
        let t = Instant::now();
        let prepared = self.take_prepared(layout);
        let ctx = self
            .gpu
            .as_ref()
            .ok_or_else(|| Error::Gpu(GpuError::Internal("the GPU solver has no device".into())))?;
        let params = self.config.gpu_params();
        let (mut solver, reused) = match prepared {
            Some(Prepared::Gpu(mut s)) => {
                match s
                    .update_sharing(e, &mut self.levels)
                    .and_then(|()| s.set_tol(params.tol))
                {
                    Ok(()) => (s, true),
                    // Another pattern under the same key: build afresh.
                    Err(GpuError::Mismatch(_)) => (
                        Box::new(PcgSolver::sharing(ctx, e, &params, &mut self.levels)?),
                        false,
                    ),
                    Err(err) => return Err(err.into()),
                }
            }
            _ => (
                Box::new(PcgSolver::sharing(ctx, e, &params, &mut self.levels)?),
                false,
            ),
        };
        let setup = t.elapsed().as_secs_f64();
        let result = solver.solve_sharing(&mut self.levels);
        self.keep_prepared(layout, Prepared::Gpu(solver));
        let crate::gpu::SolveOutcome { y, info, .. } = result?;
        let mut stats = self.stats(
            Some(info.iterations),
            info.relative_residual,
            reused,
            SolveDetails::Gpu(Box::new(info)),
        );
        stats.seconds.setup = setup;
        Ok((y, stats))
    }
}

/// A solve error when `v` holds a NaN or an infinity: the inputs were finite (checked when
/// the problem was built), so f64 overflowed on the way.
pub(crate) fn all_finite(what: &str, v: &[f64]) -> Result<(), Error> {
    match v.iter().position(|x| !x.is_finite()) {
        None => Ok(()),
        Some(k) => Err(SolveError::NotFinite(format!(
            "{what} has a non-finite entry ({} at index {k}): the data's magnitudes overflow \
             f64 on the way (H·Δx_p, g, or the lift); scale the system",
            v[k]
        ))
        .into()),
    }
}
